"""The water between camera and scene: image formation (eqs. 3–8) and the medium module."""
