"""A site directory as the synthetic generator (and a user's export) lays it out: ``site.toml``, ``photos/<camera>/``
(``photos/phone/`` for phones) and ``anchors.json`` (clicks made up front).

One reader for the demo, the benches and the tests: photos become :class:`schemas.messages.Photo` messages (the
camera id from the first folder, None for phones; capture time from EXIF in the site's time zone).
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable, Iterable
from pathlib import Path

from constructaide.photos import photo_from_file
from schemas import keys
from schemas.messages import AnchorClicks, AnchorPoint, Photo

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


def camera_of(rel_path: str) -> str | None:
    """The fixed camera a photo at ``rel_path`` (posix, relative to the photos folder) belongs to in the site
    layout: its first folder; None for the ``phone`` folder and for a photo directly in the photos folder."""
    parts = rel_path.split("/")
    return None if len(parts) < 2 or parts[0] == keys.PHONE else parts[0]


def site_doc(site_dir: Path) -> dict:
    """The parsed ``site.toml``."""
    return tomllib.loads((Path(site_dir) / "site.toml").read_text())


def site_photos(
    site_dir: Path,
    site: str,
    cameras: Callable[[str], bool] | None = None,
    progress: Callable[[Iterable[Path]], Iterable[Path]] | None = None,
) -> dict[str, Photo]:
    """Photos of the site by path relative to its photos folder (sorted by path); ``cameras(camera_folder)``
    selects folders (None: all); ``progress`` wraps the file iteration (e.g. tqdm)."""
    doc = site_doc(site_dir)
    photos_dir = Path(site_dir) / doc["paths"]["photos"]
    tz = doc["site"]["tz"]
    files = sorted(p for p in photos_dir.rglob("*") if p.suffix.lower() in PHOTO_SUFFIXES)
    out: dict[str, Photo] = {}
    for f in progress(files) if progress is not None else files:
        rel = f.relative_to(photos_dir).as_posix()
        if cameras is not None and not cameras(rel.split("/")[0]):
            continue
        out[rel] = photo_from_file(f, camera_id=camera_of(rel), site=site, tz=tz)
    return out


def in_capture_order(photos: dict[str, Photo]) -> list[str]:
    """Relative paths of ``photos`` by capture time (then path)."""
    return sorted(photos, key=lambda r: (photos[r].capture_time_ns, r))


def anchor_messages(site: str, site_dir: Path, photos: dict[str, Photo]) -> list[AnchorClicks]:
    """AnchorClicks for every anchor in the site's ``anchors.json`` whose photo is in ``photos`` (by relative
    path): what the user clicked up front."""
    doc = json.loads((Path(site_dir) / "anchors.json").read_text())
    out = []
    for a in doc.get("anchors", []):
        photo = photos.get(a["image"])
        if photo is None:
            continue
        pts = tuple(AnchorPoint(pixel_px=tuple(p["pixel"]), point_in_world_m=tuple(p["world"])) for p in a["points"])
        out.append(
            AnchorClicks(
                site=site, photo_id=photo.photo_id, image_name=a["image"], points=pts, focal_px=doc.get("focal_px")
            )
        )
    return out
