"""The render node."""
