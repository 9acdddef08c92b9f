"""Entry points (CLI, demo, launcher, push): the only part of ``constructaide`` that may import ``nodes``."""
