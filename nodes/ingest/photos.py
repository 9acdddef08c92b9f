"""Re-export of :mod:`constructaide.photos` (photo bytes -> ``Photo``), which moved to the core so the app and the
benches need no node for it; import from ``constructaide.photos``."""

from constructaide.photos import (
    MAX_PIXELS,
    PhotoError,
    exif_capture_time_ns,
    exif_focal,
    photo_from_bytes,
    photo_from_file,
)

__all__ = ["MAX_PIXELS", "PhotoError", "exif_capture_time_ns", "exif_focal", "photo_from_bytes", "photo_from_file"]
