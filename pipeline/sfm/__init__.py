"""The SfM stage: the pycolmap recipe from photos to posed, undistorted images."""
