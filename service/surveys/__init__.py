"""Survey folders: a folder an ROV keeps filling, registered under an allowed root, scanned on a schedule;
every new image set becomes exactly one job.

- :mod:`.registry`: the surveys (API-registered and from the surveys file), their owners, folders and scan state;
- :mod:`.sets`: listing a survey folder's images and grouping them into sets, the sets' content hashes;
- :mod:`.exif`: the capture time from an image's EXIF header;
- :mod:`.scan`: one scan of one survey, submitting every new, settled set as a job.

The rules are in docs/SERVICE.md ("Survey folders") and in each module's docstring.
"""
