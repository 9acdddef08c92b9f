"""What the workbench knows about a site: the latest of every message, annotation histories, a live event feed.

Pure (no bus, no HTTP): :meth:`SiteState.apply` takes any bus message and returns the events it causes;
:class:`EventHub` fans events out to listeners (the HTTP layer's server-sent event streams) on any thread.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from constructaide.bimgeom import glb_to_meshes, meshes_to_glb
from schemas.messages import (
    Annotation,
    BimModel,
    BimUpdate,
    ElementProgress,
    Message,
    NeedsAnchor,
    OcclusionMask,
    Overlay,
    Photo,
    PhotoEvidence,
    ProgressUpdate,
    Registration,
    ViewpointGroup,
)

STATUSES = ("anchor", "auto", "failed", "needs_anchor", "pending")


def photo_status(reg: Registration | None, needs_anchor: bool) -> str:
    """One of :data:`STATUSES`: a usable registration's own status; else ``needs_anchor`` when the register node
    asked for clicks; else ``failed`` after a failed registration; else ``pending`` (nothing yet)."""
    if reg is not None and reg.status != "failed":
        return reg.status
    if needs_anchor:
        return "needs_anchor"
    return "failed" if reg is not None else "pending"


@dataclass
class SiteState:
    """Latest messages by photo (and mode / kind), every annotation revision, the model and what came with it."""

    photos: dict[str, Photo] = field(default_factory=dict)
    registrations: dict[str, Registration] = field(default_factory=dict)
    needs_anchor: dict[str, NeedsAnchor] = field(default_factory=dict)
    overlays: dict[tuple[str, str], Overlay] = field(default_factory=dict)
    masks: dict[tuple[str, str], OcclusionMask] = field(default_factory=dict)
    viewpoints: dict[str, ViewpointGroup] = field(default_factory=dict)
    annotations: dict[str, list[Annotation]] = field(default_factory=dict)
    model: BimModel | None = None
    updates: list[BimUpdate] = field(default_factory=list)
    evidence: dict[str, PhotoEvidence] = field(default_factory=dict)
    """The progress node's latest reading of each photo."""
    progress: dict[str, ElementProgress] = field(default_factory=dict)
    """The latest fused progress of each element (merged from the ProgressUpdates)."""
    progress_as_of_ns: int = 0
    progress_tz: str = "UTC"
    errors: int = 0
    max_photos: int = 5000
    """Photos kept (with their registrations, overlays, masks, viewpoint groups): beyond it the earliest arrivals
    are forgotten in batches of a tenth, so a site that runs for months keeps a bounded state."""

    def apply(self, msg: Message) -> list[dict[str, Any]]:
        """Take a message; returns the events (JSON-able dicts with ``kind``) a page should hear about."""
        events = self._apply(msg)
        self._bound()
        return events

    def _bound(self) -> None:
        cap = max(1, self.max_photos)
        slack = max(1, cap // 10)
        per_photo = (self.registrations, self.needs_anchor, self.viewpoints, self.evidence)
        per_key = (self.overlays, self.masks)
        over = (
            len(self.photos) > cap + slack
            or any(len(d) > 2 * (cap + slack) for d in per_photo)
            or any(len(t) > 12 * (cap + slack) for t in per_key)
        )
        if not over:
            return
        for pid in list(self.photos)[: max(0, len(self.photos) - cap)]:
            del self.photos[pid]
        keep = self.photos.keys()
        for d in per_photo:
            if len(d) > cap:
                for pid in [p for p in d if p not in keep]:
                    del d[pid]  # type: ignore[attr-defined]
        for t in per_key:
            for k in [k for k in t if k[0] not in keep]:
                del t[k]  # type: ignore[attr-defined]

    def _apply(self, msg: Message) -> list[dict[str, Any]]:
        if isinstance(msg, Photo):
            self.photos[msg.photo_id] = msg
            return [{"kind": "photo", "photo_id": msg.photo_id}]
        if isinstance(msg, Registration):
            self.registrations[msg.photo_id] = msg
            if msg.status != "failed":
                self.needs_anchor.pop(msg.photo_id, None)
            return [{"kind": "registration", "photo_id": msg.photo_id, "status": self.status(msg.photo_id)}]
        if isinstance(msg, NeedsAnchor):
            reg = self.registrations.get(msg.photo_id)
            if reg is not None and reg.status != "failed":
                return []  # registered meanwhile
            self.needs_anchor[msg.photo_id] = msg
            return [{"kind": "needs_anchor", "photo_id": msg.photo_id, "reason": msg.reason}]
        if isinstance(msg, Overlay):
            self.overlays[(msg.photo_id, msg.mode)] = msg
            return [{"kind": "overlay", "photo_id": msg.photo_id, "mode": msg.mode}]
        if isinstance(msg, OcclusionMask):
            self.masks[(msg.photo_id, msg.kind)] = msg
            return [{"kind": "occlusion", "photo_id": msg.photo_id, "mask": msg.kind}]
        if isinstance(msg, ViewpointGroup):
            self.viewpoints[msg.photo_id] = msg
            return [{"kind": "viewpoints", "photo_id": msg.photo_id}]
        if isinstance(msg, Annotation):
            revs = self.annotations.setdefault(msg.annotation_id, [])
            if any(r.revision == msg.revision for r in revs):
                return []  # our own publication heard back, or a duplicate
            revs.append(msg)
            revs.sort(key=lambda a: a.revision)
            return [{"kind": "annotation", "annotation_id": msg.annotation_id, "revision": msg.revision}]
        if isinstance(msg, PhotoEvidence):
            self.evidence[msg.photo_id] = msg
            return [{"kind": "evidence", "photo_id": msg.photo_id}]
        if isinstance(msg, ProgressUpdate):
            for e in msg.elements:
                self.progress[e.global_id] = e
            self.progress_as_of_ns, self.progress_tz = max(self.progress_as_of_ns, msg.as_of_ns), msg.tz
            return [{"kind": "progress", "photo_id": msg.photo_id, "elements": len(msg.elements)}]
        if isinstance(msg, BimModel):
            self.model, self.updates = msg, []
            return [{"kind": "model", "revision": msg.revision}]
        if isinstance(msg, BimUpdate):
            self.updates.append(msg)
            return [{"kind": "model", "revision": msg.revision}]
        return []

    def status(self, photo_id: str) -> str:
        return photo_status(self.registrations.get(photo_id), photo_id in self.needs_anchor)

    def current_annotations(self) -> list[Annotation]:
        """The latest revision of every annotation not deleted."""
        return [revs[-1] for revs in self.annotations.values() if revs and not revs[-1].deleted]

    def photo_entry(self, p: Photo) -> dict[str, Any]:
        """The ``GET /api/photos`` entry of a photo (the fixed fields first)."""
        reg = self.registrations.get(p.photo_id)
        need = self.needs_anchor.get(p.photo_id)
        return {
            "photo_id": p.photo_id,
            "filename": p.filename,
            "camera_id": p.camera_id,
            "capture_time": p.capture_time_ns,
            "status": self.status(p.photo_id),
            "tz": p.tz,
            "width_px": p.width_px,
            "height_px": p.height_px,
            "method": reg.method if reg is not None else "",
            "num_inliers": reg.num_inliers if reg is not None else 0,
            "reprojection_rms_px": reg.reprojection_rms_px if reg is not None else None,
            "anchor_residuals_px": list(reg.anchor_residuals_px) if reg is not None else [],
            "message": reg.message if reg is not None else "",
            "needs_anchor_reason": need.reason if need is not None else "",
            "overlays": sorted(m for (pid, m) in self.overlays if pid == p.photo_id),
            "masks": sorted(k for (pid, k), v in self.masks.items() if pid == p.photo_id and v.status == "ok"),
        }

    def photo_list(self) -> list[dict[str, Any]]:
        """Every photo in capture order (then photo_id)."""
        return [
            self.photo_entry(p) for p in sorted(self.photos.values(), key=lambda q: (q.capture_time_ns, q.photo_id))
        ]


class EventHub:
    """Numbered events to listeners. ``subscribe(fn)`` gets ``fn(event)`` for every later event (on the publishing
    thread: listeners only hand events on); ``recent`` keeps the last few for a reconnecting page."""

    def __init__(self, keep: int = 256) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[int, Callable[[dict[str, Any]], None]] = {}
        self._ids = itertools.count(1)
        self._seq = 0
        self._keep = keep
        self.recent: list[dict[str, Any]] = []

    def publish(self, events: list[dict[str, Any]]) -> None:
        with self._lock:
            out = []
            for ev in events:
                self._seq += 1
                out.append({**ev, "seq": self._seq})
            self.recent = (self.recent + out)[-self._keep :]
            listeners = list(self._listeners.values())
        for fn in listeners:
            for ev in out:
                fn(ev)

    def subscribe(self, fn: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        with self._lock:
            lid = next(self._ids)
            self._listeners[lid] = fn

        def unsubscribe() -> None:
            with self._lock:
                self._listeners.pop(lid, None)

        return unsubscribe

    @property
    def seq(self) -> int:
        with self._lock:
            return self._seq


def merged_model(model: BimModel, updates: list[Any]) -> BimModel:
    """The model after its BimUpdates (elements by GlobalId, meshes by geometry_ref)."""
    if not updates:
        return model
    meshes = glb_to_meshes(model.geometry_glb)
    elements = {e.global_id: e for e in model.elements}
    tasks = model.tasks
    revision = model.revision
    for up in updates:
        for gid in up.removed:
            elements.pop(gid, None)
        for e in (*up.changed, *up.added):
            elements[e.global_id] = e
        meshes.update(glb_to_meshes(up.geometry_glb))
        tasks = tasks if up.tasks is None else up.tasks
        revision = up.revision
    return msgspec.structs.replace(
        model, revision=revision, elements=tuple(elements.values()), tasks=tasks, geometry_glb=meshes_to_glb(meshes)
    )
