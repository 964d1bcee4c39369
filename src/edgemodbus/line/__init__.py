"""The line layer: endpoints and their timing (endpoint.py)."""
