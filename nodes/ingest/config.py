"""The ingest node's config (TOML table ``[nodes.ingest]``, ``--set name=value``)."""

from __future__ import annotations

import msgspec

from constructaide.photos import MAX_PIXELS


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    site: str = "demo"
    tz: str = ""
    """Site IANA time zone (e.g. "Europe/Amsterdam") for schedule dates and EXIF times without offset."""
    ifc: tuple[str, ...] = ()
    """IFC files forming the site model (architecture, structure, MEP parts)."""
    schedule: str = ""
    """Optional schedule file: MS Project XML, P6 XML/XER, CSV."""
    on_missing: str = "error"
    """Schedule references to elements not in the model: "error" (reject the schedule) or "drop"."""
    watch_dir: str = ""
    """Folder cameras upload into; a first-level sub-folder name is taken as the camera id (``phone/``: phone
    photos), as in a site directory (``constructaide.sitedir.camera_of``)."""
    camera_id: str = ""
    """Camera id for files directly in ``watch_dir`` ("" = phone photos)."""
    poll_secs: float = 2.0
    watch_model_files: bool = True
    """Reload and publish a BimUpdate when the IFC/schedule files change."""
    use_mtime: bool = False
    """Accept photo files without EXIF time, stamped with the file's modification time."""
    use_receive_time: bool = False
    """Accept uploaded photos without EXIF time, stamped with the time they arrived."""
    seen_path: str = ""
    """File persisting the content hashes already published (dedupe across restarts); "" = the
    hidden file ``.constructaide-seen`` in ``watch_dir`` when writable, else memory only."""
    seen_capacity: int = 100_000
    max_pixels: int = MAX_PIXELS
    future_tolerance_s: float = 600.0
    threads: int = 0
    """Geometry threads (0 = all cores, at most 8)."""
    terrain_height_m: float | None = None
    """Site ground level in model metres (z up, after the origin offset), published with the model so the
    occlude node hides elements below it; None = unknown (the occlude node then estimates it)."""
