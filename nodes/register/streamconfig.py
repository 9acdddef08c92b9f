"""Options of the streaming registrar (:class:`nodes.register.streaming.StreamingRegistrar`)."""

from __future__ import annotations

import msgspec

from nodes.register.config import MapperConfig
from nodes.register.fastpath import FastPathConfig
from nodes.register.modelalign import AlignParams

__all__ = ["STREAM_MAPPER", "StreamConfig"]

STREAM_MAPPER = MapperConfig(max_tilt_from_upright_deg=60.0)
"""The mapper's thresholds while streaming: the batch's, with the upright check of a z-up (BIM) frame."""


class StreamConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Options of the streaming registrar; ``mapper`` holds the thresholds it shares with the batch."""

    fast: FastPathConfig = FastPathConfig()
    sift_max_features: int = 4000
    sift_max_side_px: int | None = 1600
    max_candidates: int = 8
    """Registered photos a new photo is matched with: its camera's latest, then the most similar by retrieval
    (bag of words), the nearest by GPS and the same visit (phones within ``visit_gap_secs``)."""
    max_unregistered_candidates: int = 3
    """Photos still waiting for registration it is matched with too (most similar first), so that a chain of
    them registers once one of them does."""
    visit_gap_secs: float = 1800.0
    vocabulary_words: int = 512
    local_ba: bool = True
    local_ba_window: int = 6
    local_ba_iterations: int = 8
    global_ba_every: int = 10
    """A bundle adjustment of the whole map after this many new registered images (0: never)."""
    key_frame_every_secs: float | None = 2 * 86400.0
    """A fixed camera's fast-path frame joins the map (SIFT, matches, model points) when the camera has no photo in
    it from this long before: the site changes, and later photos (phones above all) match what it looks like now
    (None: never)."""
    """A bundle adjustment of the whole map after this many new registered images (0: never)."""
    viewpoint_max_neighbours: int = 30
    max_frames_per_camera: int = 500
    """Pose records (and viewpoint-graph entries) kept per fixed camera: beyond it the oldest frames that are not
    in the map (fast-path frames, not key frames or anchors) are forgotten, so a camera's state stays bounded
    however long it runs (0: keep all)."""
    max_map_images_per_camera: int = 8
    """Map images (SIFT features, matches, tracks) kept per fixed camera: beyond it the oldest that are not anchors
    are retired from the map (key frames above all: a camera running for months adds one every
    ``key_frame_every_secs``), so the map, and the time to match and adjust it, stays bounded (0: keep all)."""
    viewpoint_max_angle_deg: float = 20.0
    densify: bool = True
    densify_pairs: int = 3
    mapper: MapperConfig = STREAM_MAPPER
    model_align: bool = True
    """Polish each published pose of a fixed camera's frame by the BIM's outlines (:mod:`nodes.register.modelalign`;
    needs the BIM depth lookup). The map keeps the pose the features and clicks gave; only the published
    registration moves."""
    model_align_phones: bool = False
    """... phone photos too (off: on close-ups of brick and printed hoarding the outlines lock onto texture as often
    as they help; see BENCHMARKS 'model outline polish')."""
    model_align_anchored_phones: bool = True
    """... anchored phone photos, the outlines fitted together with the photo's accepted clicks, which hold the
    polish where the user clicked (:func:`nodes.register.modelalign.refine_pose` ``clicks``): a dozen clicks in a
    strip of a close-up leave the camera free to turn about them, the outlines elsewhere in the photo pin it."""
    align: AlignParams = AlignParams()
