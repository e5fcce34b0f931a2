"""Survey products: metric scale, georeference, orthomosaic and elevation model in metres."""
