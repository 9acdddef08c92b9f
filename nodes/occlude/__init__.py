"""The occlude node."""
