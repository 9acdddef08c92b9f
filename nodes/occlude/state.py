"""The occlude node's durable state: its time-lapse stacks, masks, registrations, sparse cloud and colour model.

One pickle (protocol 5) of the pipeline's fields, without what cannot or need not be kept: the emit callback, the
node context and the GL model view (rebuilt from the kept meshes). Read back only from the node's own state file.
Pure: no bus, no SQLite (the runtime's :class:`~constructaide.runtime.history.Ledger` stores the blob).

Hand-over (:func:`adopt_cameras`): a partitioned worker takes, for each camera it owns, that camera's frames (stack
frames, homographies, registrations, masks, per-photo bookkeeping) from the freshest of the other workers' state
files of the site.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

STATE_VERSION = 1
NOT_KEPT = frozenset({"emit", "ctx", "renderer", "config"})


def dump(pipeline: Any) -> bytes:
    fields = {k: v for k, v in vars(pipeline).items() if k not in NOT_KEPT}
    return pickle.dumps({"version": STATE_VERSION, "fields": fields}, protocol=5)


def load_into(pipeline: Any, blob: bytes) -> None:
    doc = pickle.loads(blob)  # noqa: S301 - the node's own state file
    if doc.get("version") != STATE_VERSION:
        raise ValueError(f"occlude state version {doc.get('version')} (this build reads {STATE_VERSION})")
    for k, v in doc["fields"].items():
        if k not in NOT_KEPT:
            setattr(pipeline, k, v)


def _of(key: Any, ids: set[str]) -> bool:
    """Whether a per-photo table's key is one of ``ids`` (a photo id, or a tuple led by one)."""
    if isinstance(key, tuple):
        return bool(key) and isinstance(key[0], str) and key[0] in ids
    return isinstance(key, str) and key in ids


def _latest(photos: dict[str, Any], camera: str) -> int:
    return max((p.capture_time_ns for p in photos.values() if p.camera_id == camera), default=-1)


def adopt_cameras(pipeline: Any, sources: list[bytes], owns_camera: Callable[[str], bool]) -> list[str]:
    """Take over the cameras this worker owns from other workers' ``pipeline`` blobs: per camera, from the source
    holding its latest frame (when later than this worker's own), every per-photo entry of that camera's frames
    (pipeline tables and sets, the time-lapse store's frames, homographies and features, its frame list). Site-wide
    parts (sparse cloud, model, colour model, user corrections) stay this worker's. Returns the cameras taken."""
    best: dict[str, tuple[int, dict[str, Any] | None]] = {}
    for p in pipeline.photos.values():
        if p.camera_id and owns_camera(p.camera_id):
            best[p.camera_id] = (_latest(pipeline.photos, p.camera_id), None)
    for blob in sources:
        doc = pickle.loads(blob)  # noqa: S301 - the site's own state files (same state directory)
        if doc.get("version") != STATE_VERSION:
            continue
        fields = doc["fields"]
        for c in {p.camera_id for p in fields.get("photos", {}).values() if p.camera_id and owns_camera(p.camera_id)}:
            t = _latest(fields["photos"], c)
            if t > best.get(c, (-1, None))[0]:
                best[c] = (t, fields)
    taken = sorted(c for c, (_, f) in best.items() if f is not None)
    for c in taken:
        fields = best[c][1]
        assert fields is not None
        ids = {pid for pid, p in fields["photos"].items() if p.camera_id == c}
        for name, val in fields.items():
            mine = getattr(pipeline, name, None)
            if name == "store":
                store = pipeline.store
                for table in ("frames", "homographies", "_shift_cache", "_features"):
                    getattr(store, table).update({k: v for k, v in getattr(val, table).items() if _of(k, ids)})
                frames = store.by_camera.setdefault(c, [])
                frames += [pid for pid in val.by_camera.get(c, []) if pid not in frames]
                frames.sort(key=lambda pid: store.frames[pid].capture_time_ns if pid in store.frames else 0)
            elif isinstance(val, dict) and isinstance(mine, dict):
                mine.update({k: v for k, v in val.items() if _of(k, ids)})
            elif isinstance(val, set) and isinstance(mine, set):
                mine |= {k for k in val if _of(k, ids)}
    return taken
