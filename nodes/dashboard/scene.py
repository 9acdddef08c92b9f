"""Dashboard scene logic: which entities, arrays and times a stream of bus messages becomes.

Pure (numpy, opencv, trimesh via :mod:`constructaide.bimgeom`): :class:`Scene` turns messages into
:class:`LogOp` records; the node maps each op kind to one rerun archetype. Entity layout
(world frame = BIM model frame, metres, z up):

* ``world`` — view coordinates right-hand z-up (static)
* ``world/bim/<IfcClass>/<GlobalId>`` — element mesh (static geometry); colour per class, and,
  when the model has a schedule, the planned 4D state on the ``capture_time`` timeline
  (not started: faint, under construction: orange, complete: class colour, removed: hidden)
* ``world/cameras/<camera>`` — world_from_camera transform at the photo's capture time
  (``<camera>`` = camera id, or ``phone`` for photos without a fixed camera)
* ``world/cameras/<camera>/image`` — pinhole (OpenCV axes) + the photo
* ``world/cameras/<camera>/image/overlay/<mode>`` — overlay images
* ``world/cameras/<camera>/image/occlusion/<kind>`` — occlusion masks (segmentation, class 1 = occluded)
* ``world/cameras/<camera>/image/annotations/<annotation_id>`` — user polygons (occluders, notes)
* ``world/points`` — the sparse cloud
* ``log/needs_anchor``, ``log/errors``, ``log/registration`` — text logs
* ``status/<camera>`` — one status line per camera (registered / failed / waiting for an anchor, latest
  residual, latest detected progress), a markdown text document
* ``progress/<storey>/planned``, ``progress/<storey>/detected`` — planned vs detected share of a storey's
  elements standing (the S-curve), scalars on the ``capture_time`` timeline

Timelines: ``capture_time`` (timestamp, ns UTC) and ``event`` (sequence: messages handled).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from constructaide import bimgeom, schedule4d
from constructaide.camera import K_matrix
from constructaide.imagecodec import decode_mask
from constructaide.sparsecloud import decode_sparse_cloud
from schemas import keys
from schemas import messages as m

OpKind = Literal[
    "view_coordinates",
    "annotation_context",
    "mesh",
    "mesh_color",
    "transform",
    "pinhole",
    "image",
    "segmentation",
    "points",
    "text",
    "clear",
    "lines2d",
    "text_document",
    "scalars",
    "series_style",
]

EntityPath = tuple[str, ...]
"""Entity path as unescaped parts; the node escapes them for rerun."""

WORLD: EntityPath = ("world",)
BIM: EntityPath = ("world", "bim")
CAMERAS: EntityPath = ("world", "cameras")
POINTS: EntityPath = ("world", "points")
LOG: EntityPath = ("log",)
STATUS: EntityPath = ("status",)
PROGRESS: EntityPath = ("progress",)
PLANNED_RGBA = (150, 150, 150, 255)
DETECTED_RGBA = (40, 200, 60, 255)

OCCLUDED_CLASS = 1
OCCLUDED_RGBA = (255, 0, 255, 150)

_CLASS_RGBA: dict[str, tuple[int, int, int, int]] = {
    "IfcWall": (205, 195, 175, 255),
    "IfcWallStandardCase": (205, 195, 175, 255),
    "IfcCurtainWall": (140, 190, 230, 200),
    "IfcSlab": (160, 160, 165, 255),
    "IfcRoof": (170, 80, 60, 255),
    "IfcColumn": (120, 130, 150, 255),
    "IfcBeam": (110, 120, 160, 255),
    "IfcMember": (130, 140, 170, 255),
    "IfcPlate": (150, 155, 175, 255),
    "IfcFooting": (110, 100, 90, 255),
    "IfcPile": (100, 90, 80, 255),
    "IfcStair": (180, 150, 110, 255),
    "IfcStairFlight": (180, 150, 110, 255),
    "IfcRailing": (90, 90, 90, 255),
    "IfcWindow": (120, 180, 230, 160),
    "IfcDoor": (150, 100, 60, 255),
    "IfcCovering": (200, 200, 190, 255),
    "IfcBuildingElementProxy": (190, 170, 200, 255),
}

_UNDER_CONSTRUCTION_RGBA = (255, 150, 30, 255)
_NOT_STARTED_ALPHA = 40


def class_rgba(ifc_class: str) -> tuple[int, int, int, int]:
    """Display colour of an IFC class (fixed for common classes, a stable hash colour otherwise)."""
    if ifc_class in _CLASS_RGBA:
        return _CLASS_RGBA[ifc_class]
    h = hashlib.sha1(ifc_class.encode()).digest()
    return (80 + h[0] % 150, 80 + h[1] % 150, 80 + h[2] % 150, 255)


def state_rgba(ifc_class: str, state: schedule4d.State) -> tuple[int, int, int, int]:
    """Element colour for a planned 4D state."""
    r, g, b, a = class_rgba(ifc_class)
    if state == "not_started":
        return (r, g, b, _NOT_STARTED_ALPHA)
    if state in ("under_construction", "under_demolition"):
        return _UNDER_CONSTRUCTION_RGBA
    if state == "removed":
        return (r, g, b, 0)
    return (r, g, b, a)


@dataclass(frozen=True)
class LogOp:
    """One thing to log. ``time_ns`` sets the ``capture_time`` timeline (None: only ``event``)."""

    path: EntityPath
    kind: OpKind
    fields: dict[str, Any]
    time_ns: int | None = None
    static: bool = False
    event: int = 0


def camera_label(camera_id: str | None) -> str:
    """Entity name of a camera: its id, or ``phone``."""
    return camera_id or keys.PHONE


def image_path(camera: str) -> EntityPath:
    return (*CAMERAS, camera, "image")


def pose_matrix(world_from_camera: tuple[float, ...]) -> np.ndarray:
    """(4, 4) float64 from the row-major 16-tuple; raises ValueError if not a rigid transform."""
    if len(world_from_camera) != 16:
        raise ValueError(f"world_from_camera needs 16 values, got {len(world_from_camera)}")
    T = np.asarray(world_from_camera, dtype=np.float64).reshape(4, 4)
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise ValueError("world_from_camera is not a finite rigid transform")
    return T


def image_from_camera(intr: m.Intrinsics) -> np.ndarray:
    """3x3 pinhole matrix in rerun's pixel convention (pixel (0,0) spans [0,1]^2: OpenCV + 0.5)."""
    K = K_matrix(intr)
    K[:2, 2] += 0.5
    return K


@dataclass
class _PhotoInfo:
    camera: str
    capture_time_ns: int


@dataclass
class _CameraStatus:
    """What the status line of one camera says."""

    registration: str = "no photo registered yet"
    waiting: int = 0  # photos of this camera waiting for anchor clicks
    progress: str = ""
    photos: int = 0


@dataclass
class Scene:
    """State of the dashboard: caches photos (bounded; photos already shown leave first) to pair them with later
    registrations.

    Each ``on_*`` method returns the ops to log, in order. Raises ValueError on malformed input.
    """

    photo_cache_size: int = 512
    photo_cache_bytes: int = 512 * 2**20
    info_cache_size: int = 10_000
    image_plane_distance_m: float = 1.0
    point_radius_m: float = 0.03
    cameras: list[str] = field(default_factory=list)
    _photos: OrderedDict[str, m.Photo] = field(default_factory=OrderedDict)
    _info: OrderedDict[str, _PhotoInfo] = field(default_factory=OrderedDict)
    _registered: OrderedDict[str, m.Registration] = field(default_factory=OrderedDict)
    _element_paths: dict[str, EntityPath] = field(default_factory=dict)
    _element_class: dict[str, str] = field(default_factory=dict)
    _tasks: tuple[m.ScheduleTask, ...] = ()
    _event: int = 0
    _started: bool = False
    _status: dict[str, _CameraStatus] = field(default_factory=dict)
    _waiting: dict[str, str] = field(default_factory=dict)  # photo_id -> camera, photos waiting for an anchor
    _storeys: set[str] = field(default_factory=set)

    # ------------------------------------------------------------------ helpers
    def _op(self, path: EntityPath, kind: OpKind, time_ns: int | None = None, static: bool = False, **f: Any) -> LogOp:
        return LogOp(path=path, kind=kind, fields=f, time_ns=time_ns, static=static, event=self._event)

    def _begin(self) -> list[LogOp]:
        self._event += 1
        if self._started:
            return []
        self._started = True
        return [
            self._op(WORLD, "view_coordinates", static=True, xyz="RIGHT_HAND_Z_UP"),
            self._op(
                CAMERAS,
                "annotation_context",
                static=True,
                classes=((0, "visible", (0, 0, 0, 0)), (OCCLUDED_CLASS, "occluded", OCCLUDED_RGBA)),
            ),
        ]

    def _remember(self, cache: OrderedDict, key: str, value: Any, limit: int) -> None:
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > limit:
            cache.popitem(last=False)

    def _see_camera(self, camera: str) -> None:
        if camera not in self.cameras:
            self.cameras.append(camera)

    def cached_photo_ids(self) -> list[str]:
        return list(self._photos)

    # ------------------------------------------------------------------ messages
    def on_bim_model(self, model: m.BimModel) -> list[LogOp]:
        """All element meshes (static), replacing any previous model; 4D colours if scheduled."""
        ops = self._begin()
        meshes = bimgeom.load_bim_model_glb(model)
        if self._element_paths:
            ops.append(self._op(BIM, "clear", static=True, recursive=True))
        self._element_paths.clear()
        self._element_class.clear()
        ops += self._element_ops(model.elements, meshes, model.tasks)
        return ops

    def on_bim_update(self, update: m.BimUpdate) -> list[LogOp]:
        """Added/changed meshes, removed elements cleared; a new schedule re-logs 4D colours."""
        ops = self._begin()
        for gid in update.removed:
            path = self._element_paths.pop(gid, None)
            self._element_class.pop(gid, None)
            if path is not None:
                ops.append(self._op(path, "clear", static=True, recursive=False))
        meshes = bimgeom.load_bim_model_glb(update)
        ops += self._element_ops((*update.added, *update.changed), meshes, update.tasks)
        return ops

    def _element_ops(
        self,
        elements: tuple[m.BimElement, ...],
        meshes: dict[str, bimgeom.Mesh],
        tasks: tuple[m.ScheduleTask, ...] | None,
    ) -> list[LogOp]:
        ops: list[LogOp] = []
        if tasks is not None:
            self._tasks = tuple(tasks)
        windows = schedule4d.element_windows(self._tasks)
        for el in elements:
            mesh = meshes.get(el.geometry_ref or el.global_id)
            if mesh is None:
                continue
            vertices, faces = mesh
            path = (*BIM, el.ifc_class or "IfcElement", el.global_id)
            self._element_paths[el.global_id] = path
            self._element_class[el.global_id] = el.ifc_class
            scheduled = el.global_id in windows
            ops.append(
                self._op(
                    path,
                    "mesh",
                    static=True,
                    vertex_positions=np.asarray(vertices, dtype=np.float32),
                    triangle_indices=np.asarray(faces, dtype=np.uint32),
                    albedo_factor=None if scheduled else class_rgba(el.ifc_class),
                )
            )
        # A new schedule changes every element's states; otherwise only the (re)logged elements need theirs.
        ops += self._state_ops(windows, None if tasks is not None else {el.global_id for el in elements})
        return ops

    def _state_ops(self, windows: dict[str, schedule4d.ElementWindow], only: set[str] | None) -> list[LogOp]:
        """Colour of scheduled elements (all, or ``only``) at each planned state change (capture_time).

        Every element also gets its colour just before the schedule's first change.
        """
        ops: list[LogOp] = []
        changes: dict[str, list[int]] = {}
        for gid, w in windows.items():
            times = [
                t for t in (w.build_start_ns, w.build_finish_ns, w.remove_start_ns, w.remove_finish_ns) if t is not None
            ]
            changes[gid] = sorted(set(times))
        all_times = [t for ts in changes.values() for t in ts]
        if not all_times:
            return ops
        t_first = min(all_times) - 1
        for gid, times in changes.items():
            if gid not in self._element_paths or (only is not None and gid not in only):
                continue
            w = windows[gid]
            cls = self._element_class.get(gid, "")
            for t in [t_first, *times]:
                rgba = state_rgba(cls, schedule4d.planned_state(w, t))
                ops.append(self._op(self._element_paths[gid], "mesh_color", time_ns=t, albedo_factor=rgba))
        return ops

    def on_photo(self, photo: m.Photo) -> list[LogOp]:
        """Cache the photo; log it now if its registration came first."""
        ops = self._begin()
        camera = camera_label(photo.camera_id)
        self._photos[photo.photo_id] = photo
        self._photos.move_to_end(photo.photo_id)
        self._evict_photos()
        self._remember(self._info, photo.photo_id, _PhotoInfo(camera, photo.capture_time_ns), self.info_cache_size)
        reg = self._registered.get(photo.photo_id)
        if reg is not None:
            ops.append(self._image_op(image_path(camera_label(reg.camera_id or photo.camera_id)), photo))
        return ops

    def _evict_photos(self) -> None:
        """Keep the photo cache within its count and byte limits (the newest photo always stays): photos already
        logged with their registration go first, oldest first; then the oldest still waiting for one."""
        size = sum(len(p.data) for p in self._photos.values())
        while len(self._photos) > 1 and (len(self._photos) > self.photo_cache_size or size > self.photo_cache_bytes):
            victim = next((pid for pid in self._photos if pid in self._registered), next(iter(self._photos)))
            size -= len(self._photos.pop(victim).data)

    def _image_op(self, path: EntityPath, photo: m.Photo) -> LogOp:
        return self._op(path, "image", time_ns=photo.capture_time_ns, contents=photo.data, media_type=photo.media_type)

    def on_registration(self, reg: m.Registration) -> list[LogOp]:
        """Camera transform + pinhole at capture time, with the cached photo; failures as text."""
        ops = self._begin()
        info = self._info.get(reg.photo_id)
        camera = camera_label(reg.camera_id or (info.camera if info else None))
        time_ns = reg.capture_time_ns or (info.capture_time_ns if info else None)
        if reg.status == "failed":
            text = f"registration of photo {reg.photo_id} ({camera}) failed: {reg.message or 'no reason given'}"
            ops.append(self._op((*LOG, "registration"), "text", time_ns=time_ns, text=text, level="WARN"))
            self._cam(camera).registration = f"latest photo failed to register ({reg.message or 'no reason given'})"
            ops.append(self._status_op(camera, time_ns))
            return ops
        if reg.intrinsics is None:
            raise ValueError(f"registration of photo {reg.photo_id} has status {reg.status} but no intrinsics")
        T = pose_matrix(reg.world_from_camera)
        self._see_camera(camera)
        self._remember(self._registered, reg.photo_id, reg, self.info_cache_size)
        if info is None:
            self._remember(self._info, reg.photo_id, _PhotoInfo(camera, time_ns or 0), self.info_cache_size)
        intr = reg.intrinsics
        ops.append(self._op((*CAMERAS, camera), "transform", time_ns=time_ns, translation=T[:3, 3], mat3x3=T[:3, :3]))
        ops.append(
            self._op(
                image_path(camera),
                "pinhole",
                time_ns=time_ns,
                image_from_camera=image_from_camera(intr),
                resolution=(intr.width_px, intr.height_px),
                image_plane_distance=self.image_plane_distance_m,
            )
        )
        photo = self._photos.get(reg.photo_id)
        if photo is not None:
            ops.append(self._image_op(image_path(camera), photo))
        text = (
            f"photo {reg.photo_id} registered ({reg.status}/{reg.method}): "
            f"{reg.num_inliers} inliers, rms {reg.reprojection_rms_px:.2f} px"
        )
        ops.append(self._op((*LOG, "registration"), "text", time_ns=time_ns, text=text, level="INFO"))
        status = self._cam(camera)
        status.photos += 1
        status.registration = (
            f"registered ({reg.status}/{reg.method or '?'}), latest residual {reg.reprojection_rms_px:.2f} px rms"
        )
        self._waiting.pop(reg.photo_id, None)
        status.waiting = sum(c == camera for c in self._waiting.values())
        ops.append(self._status_op(camera, time_ns))
        return ops

    def _photo_place(self, photo_id: str, camera_id: str | None) -> tuple[str, int | None]:
        info = self._info.get(photo_id)
        camera = camera_label(camera_id or (info.camera if info else None))
        return camera, (info.capture_time_ns if info else None)

    def on_overlay(self, overlay: m.Overlay) -> list[LogOp]:
        """Overlay image on the photo's camera view at the photo's capture time."""
        ops = self._begin()
        if not overlay.image_png:
            raise ValueError(f"overlay {overlay.mode} of photo {overlay.photo_id} has no image")
        camera, time_ns = self._photo_place(overlay.photo_id, overlay.camera_id)
        ops.append(
            self._op(
                (*image_path(camera), "overlay", overlay.mode),
                "image",
                time_ns=time_ns,
                contents=overlay.image_png,
                media_type="image/png",
                opacity=0.7,
                draw_order=10.0,
            )
        )
        return ops

    def on_occlusion(self, mask: m.OcclusionMask) -> list[LogOp]:
        """Occlusion mask as a segmentation image (1 = occluded) on the camera view."""
        ops = self._begin()
        camera, time_ns = self._photo_place(mask.photo_id, None)
        if mask.status != "ok":
            text = f"occlusion ({mask.kind}) of photo {mask.photo_id}: {mask.status} ({mask.num_views} views)"
            ops.append(self._op((*LOG, "occlusion"), "text", time_ns=time_ns, text=text, level="WARN"))
            return ops
        classes = decode_mask_png(mask.mask_png)
        ops.append(
            self._op(
                (*image_path(camera), "occlusion", mask.kind),
                "segmentation",
                time_ns=time_ns,
                image=classes,
                opacity=0.5,
                draw_order=20.0,
            )
        )
        return ops

    def on_sparse(self, cloud: m.SparseCloud) -> list[LogOp]:
        """The sparse cloud (replaces the previous revision from the latest capture time on)."""
        ops = self._begin()
        arrays = decode_sparse_cloud(cloud)
        xyz, colors = arrays.points_m, arrays.colors_rgb
        times = [self._info[p].capture_time_ns for p in cloud.photo_ids if p in self._info]
        ops.append(
            self._op(
                POINTS,
                "points",
                time_ns=max(times) if times else None,
                positions=xyz,
                colors=colors,
                radii=self.point_radius_m,
            )
        )
        return ops

    def on_needs_anchor(self, msg: m.NeedsAnchor) -> list[LogOp]:
        ops = self._begin()
        _, time_ns = self._photo_place(msg.photo_id, None)
        text = f"photo {msg.photo_id} needs anchor clicks: {msg.reason} ({msg.num_matched_tracks} matched tracks)"
        ops.append(self._op((*LOG, "needs_anchor"), "text", time_ns=time_ns, text=text, level="WARN"))
        camera, _ = self._photo_place(msg.photo_id, None)
        self._waiting[msg.photo_id] = camera
        self._cam(camera).waiting = sum(c == camera for c in self._waiting.values())
        ops.append(self._status_op(camera, time_ns))
        return ops

    # ------------------------------------------------------------------ progress
    def _cam(self, camera: str) -> _CameraStatus:
        return self._status.setdefault(camera, _CameraStatus())

    def _status_op(self, camera: str, time_ns: int | None) -> LogOp:
        """The camera's status line as a markdown document."""
        s = self._cam(camera)
        parts = [f"**{camera}**: {s.registration}"]
        if s.waiting:
            parts.append(f"**waiting for an anchor** ({s.waiting} photo{'s' if s.waiting > 1 else ''})")
        if s.progress:
            parts.append(s.progress)
        return self._op((*STATUS, camera), "text_document", time_ns=time_ns, text=" · ".join(parts))

    def on_photo_evidence(self, ev: m.PhotoEvidence) -> list[LogOp]:
        """The latest detected progress in the camera's status line."""
        ops = self._begin()
        camera, time_ns = self._photo_place(ev.photo_id, ev.camera_id)
        counts: dict[str, int] = {}
        for e in ev.elements:
            counts[e.state] = counts.get(e.state, 0) + 1
        seen = ", ".join(
            f"{counts[k]} {k.replace('_', ' ')}" for k in ("built", "not_built", "occluded", "unknown") if counts.get(k)
        )
        self._cam(camera).progress = f"latest progress: {seen or 'no elements in view'} ({len(ev.elements)} in view)"
        ops.append(self._status_op(camera, time_ns or ev.capture_time_ns))
        return ops

    def on_progress(self, update: m.ProgressUpdate) -> list[LogOp]:
        """One planned-vs-detected S-curve point per storey at the update's as-of time."""
        ops = self._begin()
        for sp in update.storeys:
            base = (*PROGRESS, sp.storey or "(no storey)")
            if sp.storey not in self._storeys:
                self._storeys.add(sp.storey)
                for kind, rgba in (("planned", PLANNED_RGBA), ("detected", DETECTED_RGBA)):
                    ops.append(
                        self._op((*base, kind), "series_style", static=True, name=f"{sp.storey} {kind}", color=rgba)
                    )
            ops.append(
                self._op((*base, "planned"), "scalars", time_ns=update.as_of_ns, value=100.0 * sp.planned_fraction)
            )
            ops.append(
                self._op((*base, "detected"), "scalars", time_ns=update.as_of_ns, value=100.0 * sp.detected_fraction)
            )
        return ops

    def on_annotation(self, ann: m.Annotation) -> list[LogOp]:
        """A user polygon on its photo's camera view (closed line strip), or a text note."""
        ops = self._begin()
        label = ann.text or ann.status or ann.kind
        if ann.photo_id is not None and len(ann.polygon_px) >= 2:
            camera, time_ns = self._photo_place(ann.photo_id, ann.camera_id)
            # OpenCV pixel centres -> rerun's pixel-corner convention
            strip = np.asarray([*ann.polygon_px, ann.polygon_px[0]], dtype=np.float32) + 0.5
            color = OCCLUDED_RGBA[:3] + (255,) if ann.kind == "occluder" else (255, 220, 0, 255)
            ops.append(
                self._op(
                    (*image_path(camera), "annotations", ann.annotation_id),
                    "lines2d",
                    time_ns=time_ns,
                    strips=[strip],
                    labels=[f"{ann.kind}: {label}"],
                    colors=[color],
                    draw_order=30.0,
                )
            )
        else:
            elements = f" on {len(ann.element_ids)} elements" if ann.element_ids else ""
            text = f"{ann.kind} annotation {ann.annotation_id}{elements}: {label} ({ann.author or 'anonymous'})"
            ops.append(self._op((*LOG, "annotations"), "text", time_ns=ann.created_ns or None, text=text, level="INFO"))
        return ops

    def on_error(self, err: m.NodeError) -> list[LogOp]:
        ops = self._begin()
        text = f"{err.node}: {err.reason} (topic {err.topic}{', key ' + err.key if err.key else ''})"
        ops.append(self._op((*LOG, "errors"), "text", time_ns=err.time_ns or None, text=text, level="ERROR"))
        return ops


def decode_mask_png(png: bytes) -> np.ndarray:
    """(H, W) uint8 class image from an 8-bit mask PNG: 1 where the mask is > 127, else 0."""
    return decode_mask(png, what="occlusion mask").astype(np.uint8)
