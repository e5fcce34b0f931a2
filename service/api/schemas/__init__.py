"""Request models (what clients send) and response models (what the API returns), kept apart."""
