"""The Python API (placeholder until the API lands)."""
