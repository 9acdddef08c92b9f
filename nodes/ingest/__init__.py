"""The ingest node."""
