"""File formats: ..."""
