"""The render node's durable state: cached photos, registrations, masks, what is drawn and what waits to be.

One pickle (protocol 5) of those fields; the engine (GL) is rebuilt from the latched BIM model, and a restart
does not redraw what was drawn with the same model revision. Annotations and detected progress are not kept (a
restart draws the progress mode without them until they come again). Read back only from the node's own file.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

STATE_VERSION = 1
FIELDS = ("photos", "registrations", "masks", "dirty", "rendered", "_photo_bytes", "drawn_revision")


def dump(node: Any) -> bytes:
    return pickle.dumps({"version": STATE_VERSION, **{f: getattr(node, f) for f in FIELDS}}, protocol=5)


def load_into(node: Any, blob: bytes) -> None:
    doc = pickle.loads(blob)  # noqa: S301 - the node's own state file
    if doc.get("version") != STATE_VERSION:
        raise ValueError(f"render state version {doc.get('version')} (this build reads {STATE_VERSION})")
    for f in FIELDS:
        setattr(node, f, doc[f])


def adopt_cameras(node: Any, sources: list[bytes], owns_camera: Callable[[str], bool]) -> list[str]:
    """Take over the cameras this worker owns from other workers' ``render`` blobs: each cached photo of an owned
    camera that this worker does not hold, with its registration, mask and whether it is drawn or waits to be
    (so a later mask redraws it and a photo the other worker had not drawn yet is drawn here); a photo drawn with
    another model revision than this worker's is drawn again. The cache bounds apply afterwards. Returns the
    cameras taken."""
    taken: set[str] = set()
    for blob in sources:
        doc = pickle.loads(blob)  # noqa: S301 - the site's own state files (same state directory)
        if doc.get("version") != STATE_VERSION:
            continue
        drawn_with = doc.get("drawn_revision")
        if node.drawn_revision is None:
            # A fresh worker takes the revision its adopted overlays were drawn with: the same model arriving
            # next is then no reason to redraw them all.
            node.drawn_revision = drawn_with
        for pid, photo in doc["photos"].items():
            camera = photo.camera_id
            if not camera or not owns_camera(camera) or pid in node.photos:
                continue
            node.photos[pid] = photo
            node._photo_bytes += len(photo.data)
            for table in ("registrations", "masks", "dirty"):
                if pid in doc[table]:
                    getattr(node, table)[pid] = doc[table][pid]
            if pid in doc["rendered"]:
                node.rendered.add(pid)
                if drawn_with != node.drawn_revision and pid in node.registrations:
                    node._mark(pid)  # drawn with another model revision than this worker's: drawn again
            taken.add(camera)
    return sorted(taken)
