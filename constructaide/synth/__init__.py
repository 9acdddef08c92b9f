"""Synthetic construction site with exact ground truth (see README.md here for the folder contract).

``build_site`` renders a site folder; ``ensure_site`` returns a cached one. System code must never read a
site's ``truth/`` folder; only tests and benchmarks may (``constructaide.synth.truth`` loads it).
"""

from .site import GENERATOR_VERSION, build_site, ensure_site
from .truth import truth_rel

__all__ = ["GENERATOR_VERSION", "build_site", "ensure_site", "truth_rel"]
