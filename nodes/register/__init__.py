"""The register node."""
