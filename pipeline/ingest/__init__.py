"""The ingest stage: validated, upright images from an uploaded archive or a folder."""
