"""The register node's durable state: what a restart needs to resume without re-anchoring.

``map``: the :class:`~nodes.register.streaming.StreamingRegistrar` (reconstruction: images, tracks, points,
poses; per-camera fast-path state; viewpoint graph; vocabulary) with the photos waiting for anchors or kept
for late clicks; ``feat/<image>``: each map image's features (written once); ``bim``: the meshes and schedule
the depth lookup is built from (written only when they change).
Blobs are pickles (protocol 5) of the node's own objects, read back only from the node's own state file; the
depth lookup (an EGL view) is not kept, it is rebuilt from ``bim``. Pure: no bus, no SQLite (the runtime's
:class:`~constructaide.runtime.history.Ledger` stores the blobs).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from typing import Any

STATE_VERSION = 1
MAP_FIELDS = ("inbox", "sparse_revision", "_map_changes")
BIM_FIELDS = ("bim",)


def dump_map(node: Any, saved: dict[str, tuple[int, bool]] | None = None) -> dict[str, bytes]:
    """Blobs of the registrar (without its depth lookup) and the node's queues: ``map``, plus ``feat/<image>`` for
    each map image whose features are not in ``saved`` yet (``{image: (id(features), has PCA)}``, updated): the
    features (MBs per image, unchanged once extracted) are written once, not with every snapshot; an image that
    left the map (retired, forgotten) gets an empty ``feat/<image>`` blob, which deletes it from the store."""
    reg = node.registrar
    saved = {} if saved is None else saved
    out: dict[str, bytes] = {}
    images = reg.recon.images
    feats = [im.features for im in images]
    lookup, reg.depth_lookup = reg.depth_lookup, None
    try:
        for im, f in zip(images, feats, strict=True):
            tag = (id(f), getattr(f, "descriptors_pca", None) is not None)
            if saved.get(im.name) != tag:
                out[f"feat/{im.name}"] = pickle.dumps(f, protocol=5)
                saved[im.name] = tag
            im.features = None
        names = {im.name for im in images}
        for name in [n for n in saved if n not in names]:
            out[f"feat/{name}"] = b""
            del saved[name]
        doc = {"version": STATE_VERSION, "registrar": reg, **{f: getattr(node, f) for f in MAP_FIELDS}}
        out["map"] = pickle.dumps(doc, protocol=5)
        return out
    finally:
        reg.depth_lookup = lookup
        for im, f in zip(images, feats, strict=True):
            im.features = f


def saved_features(recon: Any) -> dict[str, tuple[int, bool]]:
    """What :func:`dump_map` needs to skip features already saved: per image its features' identity and whether
    they carry PCA descriptors (as restored)."""
    return {
        im.name: (id(im.features), getattr(im.features, "descriptors_pca", None) is not None) for im in recon.images
    }


def dump_bim(node: Any) -> bytes:
    return pickle.dumps({"version": STATE_VERSION, **{f: getattr(node, f) for f in BIM_FIELDS}}, protocol=5)


def load_into(node: Any, blobs: dict[str, bytes]) -> bool:
    """Set the node's fields from saved blobs; True when the BIM part was restored (rebuild the depth lookup)."""
    if "map" in blobs:
        doc = pickle.loads(blobs["map"])  # noqa: S301 - the node's own state file
        if doc.get("version") != STATE_VERSION:
            raise ValueError(f"register state version {doc.get('version')} (this build reads {STATE_VERSION})")
        node.registrar = doc["registrar"]
        for im in node.registrar.recon.images:
            blob = blobs.get(f"feat/{im.name}")
            if blob is None:
                raise ValueError(f"register state: features of {im.name} missing")
            im.features = pickle.loads(blob)  # noqa: S301
        for f in MAP_FIELDS:
            setattr(node, f, doc[f])
    if "bim" in blobs:
        doc = pickle.loads(blobs["bim"])  # noqa: S301
        if doc.get("version") == STATE_VERSION:
            for f in BIM_FIELDS:
                setattr(node, f, doc[f])
            return True
    return False


def adopt_cameras(node: Any, sources: list[dict[str, bytes]], owns_camera: Callable[[str], bool]) -> list[str]:
    """Hand the node's registrar the cameras it owns from other workers' saved ``map`` blobs (``sources``): per
    camera the freshest fast-path track (latest tracked frame, this node's own included), with its pose records,
    and each owned camera's waiting photos that no source registered. Returns the cameras taken over."""
    mine = node.registrar
    best: dict[str, tuple[int, Any]] = {
        c: (t.capture_time_ns, None) for c, t in mine.fast.tracks.items() if owns_camera(c)
    }
    docs = []
    for blobs in sources:
        if "map" not in blobs:
            continue
        doc = pickle.loads(blobs["map"])  # noqa: S301 - the site's own state files (same state directory)
        if doc.get("version") != STATE_VERSION:
            continue
        docs.append(doc)
        reg = doc["registrar"]
        for c, t in reg.fast.tracks.items():
            if owns_camera(c) and t.capture_time_ns > best.get(c, (-1, None))[0]:
                best[c] = (t.capture_time_ns, reg)
    taken = sorted(c for c, (_, reg) in best.items() if reg is not None)
    for c in taken:
        mine.adopt_camera(c, best[c][1])
    registered = set(mine.poses).union(*(d["registrar"].poses for d in docs)) if docs else set(mine.poses)
    for doc in docs:
        inbox = doc["inbox"]
        for pid, photo in inbox.pending.items():
            if photo.camera_id and owns_camera(photo.camera_id) and pid not in registered:
                node.inbox.pending.setdefault(pid, photo)
        node.inbox.asked_groups |= {g for g in inbox.asked_groups if owns_camera(g)}
    return taken
