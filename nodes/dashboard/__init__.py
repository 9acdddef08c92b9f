"""The dashboard node."""
