"""EXIF tag ids of a survey frame's records (CIPA DC-008 2.32), for the generator that writes them
(:mod:`pipeline.synth.exif_records`) and the survey stage that reads them (:mod:`pipeline.survey.records`)."""

IFD_EXIF, IFD_GPS = 0x8769, 0x8825
TAG_DATETIME = 0x0132
TAG_DATETIME_ORIGINAL, TAG_DATETIME_DIGITIZED = 0x9003, 0x9004
TAG_OFFSET_TIME_ORIGINAL, TAG_SUBSEC_TIME_ORIGINAL = 0x9011, 0x9291
TAG_SUBJECT_DISTANCE = 0x9206  # the altimeter's camera-to-bottom distance in survey frames (AIMS ReefScan)
GPS_VERSION, GPS_LAT_REF, GPS_LAT, GPS_LON_REF, GPS_LON = 0x00, 0x01, 0x02, 0x03, 0x04
GPS_ALT_REF, GPS_ALT, GPS_TIME, GPS_DATE = 0x05, 0x06, 0x07, 0x1D
