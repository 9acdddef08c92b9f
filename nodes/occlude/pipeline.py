"""The occlude node's policy, pure (no bus): which masks to (re)compute when, and what each photo publishes.

:class:`OcclusionPipeline` takes the node's input messages (photos, registrations, viewpoint groups, the sparse
cloud, the BIM model and its updates, annotations) and hands every mask it makes to ``emit`` as an
``OcclusionMask`` (kinds ``dynamic`` with the clean plate, ``static``, ``user`` and ``combined``: the union of
the ``ok`` masks of the other kinds, re-emitted only when it changed) together with the (H, W) uint8 0/255 mask.
The node shell (``node.py``) and ``bench/occlusion.py`` both drive it.

Incremental: a new photo gets its masks from its own stack; older photos are recomputed only when they had no
usable stack yet (``not_enough_views``, or a mask from the colour model alone) or when their inputs changed (their
viewpoint group, a registration, a sparse cloud with markedly more observations of them, a new model). A fixed
camera's previous newest frame is recomputed once when the next frame arrives. Dynamic masks made before the
projected model was known are redone once it is. A fixed-camera frame that judges fewer than
``static_borrow_below_points`` sparse points takes the static mask of its camera's frame that judged the most,
warped by the stack homography; it is redone when that donor's mask changes or a better donor appears. Every
time-lapse mask teaches the colour model except a fixed camera's newest frame's (provisional until the next frame
refines it). As the colour model learns, the dynamic masks it shaped are redone from
:meth:`OcclusionPipeline.idle`, a few per call.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide.bimgeom import glb_to_meshes, load_bim_model_glb
from constructaide.camera import registered_camera, resized_pixels
from constructaide.imagecodec import decode_bgr, decode_mask, encode_jpeg, encode_png
from constructaide.modelview import ModelMaps, ModelView
from constructaide.sparsecloud import decode_sparse_cloud
from nodes.occlude.colour import ColourModel
from nodes.occlude.dynamic import DynamicParams, dynamic_mask, recombine
from nodes.occlude.stacks import TimelapseStore, scale_matrix, working_size
from nodes.occlude.static import StaticParams, estimate_point_normals, estimate_terrain_height, static_mask
from nodes.occlude.user import UserCorrections
from schemas.messages import (
    SPARSE_POINT_FROM_MODEL,
    SPARSE_POINT_VERIFIED,
    Annotation,
    BimModel,
    BimUpdate,
    OcclusionMask,
    Photo,
    Registration,
    SparseCloud,
    ViewpointGroup,
)

U8 = NDArray[np.uint8]
NS_PER_DAY = 86_400 * 10**9


class Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The occlude node's config (TOML table ``[nodes.occlude]``, ``--set name=value``)."""

    site: str = "demo"
    working_width_px: int = 480  # dynamic masks are computed at this width, then upsampled
    static_working_width_px: int = 640  # static masks (model render, SLIC) at this width
    max_views: int = 10  # stack size
    stack_selection: str = "spread"  # "spread": nearest earlier + later, then spread over the time span; "nearest"
    two_pass: bool = True  # stacks leave out the pixels of their neighbours' own dynamic masks (when known)
    refine_previous_frame: bool = True  # recompute a camera's previous newest frame once a later one arrives
    # a photo's viewpoint group that grows recomputes its dynamic mask only while that mask is provisional (no later
    # frame in its stack, or no stack) or its stack is not full (fewer than max_views candidates); True: whenever its
    # candidates change (every new fixed-camera frame then recomputes up to its ~30 registered neighbours' masks)
    regroup_final_masks: bool = False
    max_stored_photos: int = 2000  # photos kept for stacks and republishing; the oldest arrivals are dropped
    # ... and at most this many frames of one fixed camera (its earliest captures go first, but not the frame the
    # others borrow their static mask from, see static_borrow_below_points; 0: no per-camera bound),
    # so a camera's state stays bounded however long it runs: about 1.1 MB per 960x540 frame at the default working
    # width (photo JPEG, working image, SIFT features, projected model and own mask, clean plate, masks), held once
    # more by every state snapshot; the stack takes max_views of them, spread over their time span
    max_photos_per_camera: int = 40
    # registrations and viewpoint groups of photos not stored (sent ahead of their photo, or late: the photo was
    # dropped already) are kept for at most this many such photos, the oldest dropped first
    max_unstored_inputs: int = 64
    max_time_gap_days: float = 0.0  # 0: no limit on the time between a photo and its neighbours
    dynamic_threshold: float = 0.08  # smoothed squared HSV difference, any channel (paper: 0.05 for the median score)
    # the dynamic mask grows from the pixels above the threshold through weaker ones only within this many working
    # pixels of the convex hulls of the strong blobs (None: without bound, as before 2026-12-06)
    dynamic_max_grow_px: int | None = 24
    dynamic_score: str = "vote"  # "vote": must differ from most neighbours; "median": from the median (paper)
    fixed_alignment: str = "homography"  # a fixed camera's frames: "homography" (SIFT) or "shift"
    # colour model learnt from the time-lapse masks (dynamic.ColourModel): "all" labels photos without a stack and
    # adds to / vetoes time-lapse masks, "no_stack" only labels photos without a stack, "off"
    dynamic_appearance: str = "all"
    appearance_veto: float = 0.2  # time-lapse blobs whose mean P(dynamic | colour) is below this are dropped
    appearance_pixel_veto: float = 0.2  # ... and time-lapse pixels whose smoothed P is below this
    # redo a dynamic mask once the colour model has seen this fraction more time-lapse masks than when it was made
    # (photos without a stack: in full; time-lapse masks: the colour step only, with "all")
    appearance_refresh_growth: float = 0.25
    appearance_refresh_per_idle: int = 2  # such redos per idle call (the runtime calls again while nothing waits)
    depth_margin_m: float = 0.3  # static: point closer than the model by more than this occludes
    normal_angle_deg: float = 30.0  # static: normal disagreement that occludes
    terrain_height_m: float | None = None  # site ground level; else BimModel's, else estimated from the cloud
    static_excludes_dynamic: bool = True  # static mask minus the photo's dynamic mask
    sparse_growth: float = 0.2  # recompute a static mask when a photo's observations grew by this fraction
    # a fixed-camera frame judging fewer sparse points than this (a frame registered by the fast path has no
    # features of its own) also takes the static mask of its camera's frame that judged the most, warped by the
    # stack homography: fences, ground and trees stay where they are (0: off)
    static_borrow_below_points: int = 20
    jpeg_quality: int = 90


@dataclass
class _PhotoInfo:
    camera_id: str | None
    capture_time_ns: int
    data: bytes
    width_px: int
    height_px: int


@dataclass
class _Cloud:
    """A decoded sparse cloud: per point, then the terrain it shows, then the observations."""

    points_m: NDArray[np.float64]  # (N, 3)
    normals: NDArray[np.float32]  # (N, 3) PCA normals
    flatness: NDArray[np.float32]  # (N,)
    terrain_height_m: float | None  # dominant horizontal surface, when one stands out
    photo_index: dict[str, int]  # photo id -> index in obs_photo
    obs_point: NDArray[np.int32]  # (M,)
    obs_photo: NDArray[np.int32]  # (M,)
    obs_pixel: NDArray[np.float32]  # (M, 2) registered-image pixels


def decode_sparse(msg: SparseCloud) -> _Cloud:
    """Arrays of a SparseCloud message (see its docstring) with PCA normals per point. With point flags, only the
    points flagged ``SPARSE_POINT_VERIFIED`` and not ``SPARSE_POINT_FROM_MODEL`` are kept (with their
    observations)."""
    arrays = decode_sparse_cloud(msg)
    pts64 = arrays.points_m.astype(np.float64)
    obs_point, obs_photo, obs_pixel = arrays.obs_point, arrays.obs_photo, arrays.obs_pixel_px
    if arrays.point_flags is not None:
        flags = arrays.point_flags
        # only triangulated, guided-matching points judge the model: a BIM-depth point lies on the model by
        # construction, and blind matches of repeated texture land at wrong depths
        usable = ((flags & SPARSE_POINT_VERIFIED) > 0) & ((flags & SPARSE_POINT_FROM_MODEL) == 0)
        keep = usable[obs_point]
        remap = np.cumsum(usable) - 1
        pts64 = pts64[usable]
        obs_point, obs_photo, obs_pixel = remap[obs_point[keep]].astype(np.int32), obs_photo[keep], obs_pixel[keep]
    normals, flatness = estimate_point_normals(pts64)
    terrain = estimate_terrain_height(pts64, normals, flatness)
    index = {p: i for i, p in enumerate(msg.photo_ids)}
    return _Cloud(pts64, normals, flatness, terrain, index, obs_point, obs_photo, obs_pixel)


def _flushing(handler: Callable[..., None]) -> Callable[..., None]:
    """Input wrapper: emit the pending combined masks once the input is handled (even on error)."""

    @functools.wraps(handler)
    def wrapper(self: OcclusionPipeline, *args: object) -> None:
        try:
            handler(self, *args)
        finally:
            self._flush()

    return wrapper


Emit = Callable[[OcclusionMask, U8 | None], None]
"""Receives every mask the pipeline makes: the message and its (H, W) uint8 0/255 mask (None when not ``ok``)."""


class OcclusionPipeline:
    """The occlude node's state and policy (see the module docstring); ``emit`` receives every mask made."""

    def __init__(self, config: Config, emit: Emit, site: str | None = None) -> None:
        self.config = config
        self.emit = emit
        self.site = config.site if site is None else site
        gap = int(config.max_time_gap_days * NS_PER_DAY) if config.max_time_gap_days > 0 else None
        self.store = TimelapseStore(
            working_width_px=config.working_width_px,
            max_views=config.max_views,
            max_time_gap_ns=gap,
            selection=config.stack_selection,
            fixed_alignment=config.fixed_alignment,
        )
        if config.stack_selection not in ("spread", "nearest"):
            raise ValueError(f"stack_selection must be spread or nearest, got {config.stack_selection!r}")
        if config.dynamic_score not in ("vote", "median"):
            raise ValueError(f"dynamic_score must be vote or median, got {config.dynamic_score!r}")
        if config.fixed_alignment not in ("homography", "shift"):
            raise ValueError(f"fixed_alignment must be homography or shift, got {config.fixed_alignment!r}")
        if config.dynamic_appearance not in ("all", "no_stack", "off"):
            raise ValueError(f"dynamic_appearance must be all, no_stack or off, got {config.dynamic_appearance!r}")
        self.dyn_params = DynamicParams(
            threshold=config.dynamic_threshold,
            max_grow_px=config.dynamic_max_grow_px,
            vote_quantile=0.5 if config.dynamic_score == "vote" else None,
            appearance=config.dynamic_appearance,
            appearance_veto=config.appearance_veto,
            appearance_pixel_veto=config.appearance_pixel_veto,
        )
        self.static_params = StaticParams(
            depth_margin_m=config.depth_margin_m, normal_angle_deg=config.normal_angle_deg
        )
        self.photos: dict[str, _PhotoInfo] = {}
        self.registrations: dict[str, Registration] = {}
        self.cloud: _Cloud | None = None
        self.meshes: dict[str, tuple[NDArray[np.float64], NDArray[np.int32]]] = {}
        self.model_revision: str | None = None
        self.renderer: ModelView | None = None
        self.model_terrain_height_m: float | None = None
        self.user = UserCorrections()
        self.masks: dict[tuple[str, str], tuple[str, bytes]] = {}  # (photo, kind) -> (status, png)
        self.dynamic_stack_ids: dict[str, tuple[str, ...]] = {}
        self.static_obs_count: dict[str, int] = {}
        self.static_judged: dict[str, int] = {}  # sparse points judged by a photo's own static mask
        self.static_borrowed: dict[str, str] = {}  # photo -> the camera frame whose static mask it took
        # photo -> (status, PNG of its static occluders, own and borrowed, before the dynamic mask is taken out,
        # points judged)
        self.static_raw: dict[str, tuple[str, bytes, int]] = {}
        self._dirty: set[str] = set()
        self.model_region: dict[str, NDArray[np.bool_]] = {}  # projected model at dynamic working size
        self.dynamic_used_region: dict[str, bool] = {}
        self.dynamic_had_later: dict[str, bool] = {}  # the stack held a later frame when last computed
        self.colour = ColourModel()  # learns from every time-lapse dynamic mask
        self.dynamic_no_stack: set[str] = set()  # photos whose dynamic mask had no stack (colour model alone)
        self.dynamic_colour_seen: dict[str, int] = {}  # photo -> colour-model masks seen when its mask was made
        # photo -> (clean plate JPEG, stack size) last published: kept when only the colour step is redone
        self.dynamic_plate: dict[str, tuple[bytes, int]] = {}
        if config.appearance_refresh_growth < 0 or config.appearance_refresh_per_idle < 1:
            raise ValueError(
                "appearance_refresh_growth must be >= 0 and appearance_refresh_per_idle >= 1, got "
                f"{config.appearance_refresh_growth} and {config.appearance_refresh_per_idle}"
            )

    # ----------------------------------------------------------------- handlers

    @_flushing
    def add_photo(self, msg: Photo) -> None:
        img = decode_bgr(msg.data, f"photo {msg.photo_id}")
        h, w = img.shape[:2]
        self.photos.pop(msg.photo_id, None)  # re-insert: dict order is arrival order
        self.photos[msg.photo_id] = _PhotoInfo(msg.camera_id, msg.capture_time_ns, msg.data, w, h)
        while len(self.photos) > max(1, self.config.max_stored_photos):
            self._forget(next(iter(self.photos)))
        self.store.add_photo(msg.photo_id, msg.camera_id, msg.capture_time_ns, img)
        cap = self.config.max_photos_per_camera
        if msg.camera_id is not None and cap > 0:
            # kept: the camera's frames without points borrow its static mask
            donor = self._static_donor(msg.camera_id) if self.config.static_borrow_below_points > 0 else None
            while len(frames := self.store.by_camera.get(msg.camera_id, [])) > cap:
                others = [p for p in frames if p != msg.photo_id]
                older = [p for p in others if p != donor] or others
                self._forget(min(older, key=lambda p: self.photos[p].capture_time_ns))
        self._dynamic(msg.photo_id, img)
        if msg.camera_id is not None:
            refine: list[str] = []
            for other in self.store.by_camera.get(msg.camera_id, ()):
                if other == msg.photo_id:
                    continue
                status = self.masks.get((other, "dynamic"), ("ok",))[0]
                if other in self.dynamic_no_stack:  # it may have a stack now
                    self._dynamic(other)
                elif (
                    self.config.refine_previous_frame
                    and status == "ok"
                    and not self.dynamic_had_later.get(other, True)
                    and self.photos[other].capture_time_ns < msg.capture_time_ns
                ):
                    refine.append(other)
            if refine:
                # the newest earlier frame was judged without a later neighbour (construction progress and
                # a new occluder look alike then); its stack now has one
                self._dynamic(max(refine, key=lambda p: self.photos[p].capture_time_ns))
        self._static(msg.photo_id, img)
        self._refresh_dynamic_with_region(msg.photo_id, img)
        self._user(msg.photo_id)

    @_flushing
    def set_viewpoints(self, msg: ViewpointGroup) -> None:
        groups = {}
        for n in msg.neighbours:
            if len(n.this_from_neighbour) != 9:
                raise ValueError(
                    f"viewpoint group of {msg.photo_id}: homography of {n.photo_id} "
                    f"has {len(n.this_from_neighbour)} values, expected 9"
                )
            groups[n.photo_id] = np.asarray(n.this_from_neighbour, dtype=np.float64).reshape(3, 3)
        self.store.set_neighbours(msg.photo_id, groups)
        self._bound_unstored()
        touched = [msg.photo_id] + [p for p in groups if p in self.dynamic_no_stack]
        for pid in touched:
            if pid in self.photos and self._stack_ids(pid) != self.dynamic_stack_ids.get(pid) and self._regroup(pid):
                self._dynamic(pid)

    def _regroup(self, photo_id: str) -> bool:
        """Whether a change of ``photo_id``'s candidates recomputes its dynamic mask (``regroup_final_masks``)."""
        if self.config.regroup_final_masks or photo_id not in self.dynamic_stack_ids:
            return True
        provisional = photo_id in self.dynamic_no_stack or not self.dynamic_had_later.get(photo_id, False)
        return provisional or len(self.dynamic_stack_ids[photo_id]) < self.config.max_views

    @_flushing
    def add_registration(self, msg: Registration) -> None:
        if registered_camera(msg) is None or msg.intrinsics is None:
            return
        if msg.intrinsics.f_px <= 0:
            raise ValueError(f"registration of {msg.photo_id}: focal length {msg.intrinsics.f_px} px is not positive")
        if msg.intrinsics.width_px <= 0 or msg.intrinsics.height_px <= 0:
            info = self.photos.get(msg.photo_id)
            if info is None:
                raise ValueError(f"registration of {msg.photo_id}: intrinsics without an image size")
            intr = msgspec.structs.replace(msg.intrinsics, width_px=info.width_px, height_px=info.height_px)
            msg = msgspec.structs.replace(msg, intrinsics=intr)
        self.registrations[msg.photo_id] = msg
        self.static_obs_count.pop(msg.photo_id, None)
        self._static(msg.photo_id)
        self._refresh_dynamic_with_region(msg.photo_id)
        self._bound_unstored()

    @_flushing
    def set_sparse(self, msg: SparseCloud) -> None:
        self.cloud = decode_sparse(msg)
        for pid in list(self.registrations):
            n_obs = self._num_obs(pid)
            last = self.static_obs_count.get(pid)
            if last is None or n_obs > last * (1.0 + self.config.sparse_growth):
                self._static(pid)

    @_flushing
    def set_model(self, msg: BimModel) -> None:
        self.model_terrain_height_m = msg.terrain_height_m  # first: the static masks redone below use it
        self._use_meshes(load_bim_model_glb(msg), msg.revision)

    @_flushing
    def apply_update(self, msg: BimUpdate) -> None:
        if self.model_revision is None or msg.base_revision != self.model_revision:
            raise ValueError(
                f"BIM update {msg.base_revision} -> {msg.revision} does not apply to revision {self.model_revision}"
            )
        meshes = dict(self.meshes)
        for gid in msg.removed:
            meshes.pop(gid, None)
        new = glb_to_meshes(msg.geometry_glb)
        for el in (*msg.added, *msg.changed):
            ref = el.geometry_ref or el.global_id
            meshes.pop(ref, None)
            if ref in new:
                meshes[ref] = new[ref]
        self._use_meshes(meshes, msg.revision)

    @_flushing
    def add_annotation(self, msg: Annotation) -> None:
        if msg.kind != "occluder":
            return
        info = self.photos.get(msg.photo_id) if msg.photo_id else None
        camera_id = msg.camera_id if msg.camera_id is not None else (info.camera_id if info else None)
        self.user.add(
            msg.annotation_id,
            msg.photo_id,
            camera_id,
            msg.polygon_px,
            info.capture_time_ns if info else None,
            (info.width_px, info.height_px) if info else None,
        )
        for pid, p in self.photos.items():
            if pid == msg.photo_id or (camera_id is not None and p.camera_id == camera_id):
                self._user(pid)

    def _forget(self, photo_id: str) -> None:
        """Drop everything kept about a photo (its masks stay published)."""
        self.photos.pop(photo_id, None)
        self.store.forget(photo_id)
        self.registrations.pop(photo_id, None)
        for kind in ("dynamic", "static", "user", "combined"):
            self.masks.pop((photo_id, kind), None)
        for d in (
            self.dynamic_stack_ids,
            self.static_obs_count,
            self.model_region,
            self.dynamic_used_region,
            self.dynamic_had_later,
            self.dynamic_colour_seen,
            self.dynamic_plate,
            self.static_judged,
            self.static_borrowed,
            self.static_raw,
        ):
            d.pop(photo_id, None)
        self.dynamic_no_stack.discard(photo_id)
        self.colour.forget(photo_id)
        for other, donor in list(self.static_borrowed.items()):
            if donor == photo_id:
                del self.static_borrowed[other]
        self._dirty.discard(photo_id)

    def _bound_unstored(self) -> None:
        """Keep the registrations and viewpoint groups of at most ``max_unstored_inputs`` photos that are not
        stored, the oldest dropped first: an early one waits for its photo, a late one (its photo was dropped, e.g.
        the register node lags behind a camera's cap) would otherwise stay for good."""
        cap = max(0, self.config.max_unstored_inputs)
        unstored = [pid for pid in self.registrations if pid not in self.photos]
        for pid in unstored[: max(0, len(unstored) - cap)]:
            del self.registrations[pid]
        self.store.bound_unstored(cap)

    def mask(self, photo_id: str, kind: str) -> tuple[str, bytes] | None:
        """(status, PNG) of the last mask of ``kind`` emitted for a stored photo, else None."""
        return self.masks.get((photo_id, kind))

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    # ----------------------------------------------------------------- work

    def _image(self, photo_id: str) -> U8:
        return decode_bgr(self.photos[photo_id].data, f"photo {photo_id}")

    def _stack_ids(self, photo_id: str) -> tuple[str, ...]:
        cands = self.store.candidate_neighbours(photo_id)
        return tuple(sorted(cands))

    def _publish(self, photo_id: str, kind: str, status: str, mask: U8 | None, started: float, **extra: object) -> None:
        png = encode_png(mask) if mask is not None and status == "ok" else b""
        if kind == "combined" and self.masks.get((photo_id, kind)) == (status, png):
            return  # unchanged: consumers (the render node redraws on every combined mask) have it already
        self.masks[(photo_id, kind)] = (status, png)
        msg = OcclusionMask(
            site=self.site,
            photo_id=photo_id,
            kind=kind,  # type: ignore[arg-type]
            status=status,  # type: ignore[arg-type]
            mask_png=png,
            processing_ms=(time.perf_counter() - started) * 1000.0,
            **extra,  # type: ignore[arg-type]
        )
        self.emit(msg, mask if png else None)
        if kind != "combined":
            self._dirty.add(photo_id)
        if kind == "dynamic" and photo_id in self.static_raw:
            self._publish_static(photo_id, started, only_if_changed=True)

    def _flush(self) -> None:
        """Publish the combined mask of every photo whose component masks changed in this handler."""
        while self._dirty:
            self._combined(self._dirty.pop())

    def _dynamic(self, photo_id: str, img: U8 | None = None) -> None:
        started = time.perf_counter()
        img = self._image(photo_id) if img is None else img
        stack = self.store.aligned_stack(photo_id)
        self.dynamic_stack_ids[photo_id] = self._stack_ids(photo_id)
        region = self._region(photo_id)
        self.dynamic_used_region[photo_id] = region is not None
        self.dynamic_had_later[photo_id] = any(t > stack.photo_time_ns for t in stack.times_ns)
        small = self.store.frames[photo_id].image_small
        self.dynamic_colour_seen[photo_id] = self.colour.num_frames
        res = dynamic_mask(img, small, stack, self.dyn_params, region, self.colour)
        if self.config.two_pass and res.status == "ok":
            self.store.set_occluder_mask(photo_id, res.mask)
        if res.num_views > 0 and res.timelapse_small is not None:
            camera = self.photos[photo_id].camera_id if photo_id in self.photos else None
            if camera is None or self.dynamic_had_later[photo_id]:
                self.colour.add(photo_id, small, res.timelapse_small, camera, self._working_image)
            else:
                # a fixed camera's newest frame: without a later frame construction progress and a new occluder look
                # alike, so its provisional mask teaches the colour model only once the next frame refined it
                self.colour.forget(photo_id)
            self.dynamic_no_stack.discard(photo_id)
        else:
            self.dynamic_no_stack.add(photo_id)
        bg = b"" if res.background is None else encode_jpeg(res.background, self.config.jpeg_quality)
        self.dynamic_plate[photo_id] = (bg, res.num_views)
        self._publish(photo_id, "dynamic", res.status, res.mask, started, background_jpeg=bg, num_views=res.num_views)

    def _working_image(self, photo_id: str) -> U8 | None:
        frame = self.store.frames.get(photo_id)
        return None if frame is None else frame.image_small

    def idle(self) -> bool:
        """Deferred work: redo up to ``appearance_refresh_per_idle`` of the dynamic masks the colour model has
        outgrown (:meth:`_appearance_due`, in that order); True while more are due (the node's runtime calls again
        as long as no message waits, so an input never waits for more than one share)."""
        due = self._appearance_due()
        budget = self.config.appearance_refresh_per_idle
        try:
            for pid in due[:budget]:
                self._refresh_colour(pid)
        finally:
            self._flush()
        return len(due) > budget

    def _appearance_due(self) -> list[str]:
        """Photos whose dynamic mask was made before the colour model was ready (``appearance_min_frames``) or
        before it had seen ``appearance_refresh_growth`` more time-lapse masks than now: with
        ``dynamic_appearance="all"`` every such photo, with ``"no_stack"`` those without a stack. Photos without
        a usable mask first, then newest (capture time) first."""
        mode = self.config.dynamic_appearance
        n, ready = self.colour.num_frames, self.dyn_params.appearance_min_frames
        if mode == "off" or n < ready:
            return []
        growth = 1.0 + self.config.appearance_refresh_growth
        due = [
            pid
            for pid, seen in self.dynamic_colour_seen.items()
            if pid in self.photos
            and n > seen
            and (seen < ready or n >= seen * growth)
            and (mode == "all" or pid in self.dynamic_no_stack)
        ]
        due.sort(key=lambda p: (self.masks.get((p, "dynamic"), ("",))[0] == "ok", -self.photos[p].capture_time_ns))
        return due

    def _refresh_colour(self, photo_id: str) -> None:
        """Redo a dynamic mask for the colour model as it is now: in full for a photo without a stack (it may
        have one by now); else only the colour step on the time-lapse mask the model learnt from it (its stack
        did not change: same time-lapse mask and clean plate). Published only when the mask changed."""
        started = time.perf_counter()
        self.dynamic_colour_seen[photo_id] = self.colour.num_frames  # first: a photo that fails is not retried
        frame = self.store.frames.get(photo_id)
        learnt = self.colour.learnt_mask(photo_id)
        status, png = self.masks.get((photo_id, "dynamic"), ("", b""))
        if (
            photo_id in self.dynamic_no_stack
            or status != "ok"
            or frame is None
            or learnt is None
            or learnt.shape != frame.image_small.shape[:2]
        ):
            self._dynamic(photo_id)
            return
        timelapse = np.where(learnt, 255, 0).astype(np.uint8)
        mask, _ = recombine(timelapse, self._image(photo_id), frame.image_small, self.colour, self.dyn_params)
        if encode_png(mask) == png:
            return
        if self.config.two_pass:
            self.store.set_occluder_mask(photo_id, mask)
        plate, views = self.dynamic_plate.get(photo_id, (b"", 0))
        self._publish(photo_id, "dynamic", "ok", mask, started, background_jpeg=plate, num_views=views)

    def _region(self, photo_id: str) -> NDArray[np.bool_] | None:
        """Projected model (working size) of a photo: its own, else, for a fixed camera, that of the
        camera's registered frame nearest in time, warped by the stack's homography between the two."""
        own = self.model_region.get(photo_id)
        info = self.photos.get(photo_id)
        if own is not None or info is None or info.camera_id is None or photo_id not in self.store.frames:
            return own
        others = [p for p in self.store.by_camera.get(info.camera_id, ()) if p != photo_id and p in self.model_region]
        if not others:
            return None
        src = min(others, key=lambda p: abs(self.photos[p].capture_time_ns - info.capture_time_ns))
        H = self.store.candidate_neighbours(photo_id).get(src)
        if H is None:
            return None
        frame, nf = self.store.frames[photo_id], self.store.frames[src]
        h, w = frame.image_small.shape[:2]
        H_small = scale_matrix(frame.scale) @ H @ np.linalg.inv(scale_matrix(nf.scale))
        warped = cv2.warpPerspective(
            self.model_region[src].astype(np.uint8), H_small, (w, h), flags=cv2.INTER_NEAREST, borderValue=0
        )
        return np.asarray(warped > 0)

    def _refresh_dynamic_with_region(self, photo_id: str, img: U8 | None = None) -> None:
        """Recompute dynamic masks made before the projected model (where construction progress may
        change the scene) was known: the photo's own and, for a fixed camera, those of its frames that
        had no region (they borrow this one)."""
        if photo_id not in self.model_region:
            return
        status = self.masks.get((photo_id, "dynamic"), ("", b""))[0]
        if status == "ok" and not self.dynamic_used_region.get(photo_id, False):
            self._dynamic(photo_id, img)
        info = self.photos.get(photo_id)
        if info is not None and info.camera_id is not None:
            for other in self.store.by_camera.get(info.camera_id, ()):
                if (
                    other != photo_id
                    and self.masks.get((other, "dynamic"), ("", b""))[0] == "ok"
                    and not self.dynamic_used_region.get(other, False)
                ):
                    self._dynamic(other)

    def _terrain_height_m(self) -> float | None:
        """Configured ground level, else the model's, else the cloud's dominant horizontal surface (outside
        the model's footprint once the model is known)."""
        if self.config.terrain_height_m is not None:
            return self.config.terrain_height_m
        if self.model_terrain_height_m is not None:
            return self.model_terrain_height_m
        if self.cloud is None:
            return None
        if not self.meshes:
            return self.cloud.terrain_height_m
        xy = np.concatenate([v[:, :2] for v, _ in self.meshes.values()])
        c = self.cloud
        return estimate_terrain_height(c.points_m, c.normals, c.flatness, footprint_xy_m=(xy.min(0), xy.max(0)))

    def _num_obs(self, photo_id: str) -> int:
        if self.cloud is None or photo_id not in self.cloud.photo_index:
            return 0
        return int(np.count_nonzero(self.cloud.obs_photo == self.cloud.photo_index[photo_id]))

    def _static(self, photo_id: str, img: U8 | None = None) -> None:
        reg = self.registrations.get(photo_id)
        if reg is None or photo_id not in self.photos or self.renderer is None or reg.intrinsics is None:
            return
        started = time.perf_counter()
        img = self._image(photo_id) if img is None else img
        H, W = img.shape[:2]
        w, h, _ = working_size(W, H, self.config.static_working_width_px)
        small = np.asarray(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), np.uint8)
        world_from_camera = np.asarray(reg.world_from_camera, dtype=np.float64).reshape(4, 4)
        maps: ModelMaps = self.renderer.maps(reg.intrinsics, world_from_camera, w, h)
        frame = self.store.frames.get(photo_id)
        if frame is not None:
            dh, dw = frame.image_small.shape[:2]
            region = cv2.resize(maps.has_model.astype(np.uint8), (dw, dh), interpolation=cv2.INTER_NEAREST)
            self.model_region[photo_id] = cv2.dilate(region, np.ones((9, 9), np.uint8)) > 0
        pts = np.zeros((0, 3))
        px = np.zeros((0, 2))
        normals = np.zeros((0, 3), np.float32)
        flat = np.zeros(0, np.float32)
        if self.cloud is not None and photo_id in self.cloud.photo_index:
            sel = self.cloud.obs_photo == self.cloud.photo_index[photo_id]
            idx = self.cloud.obs_point[sel]
            pts, px = self.cloud.points_m[idx], self.cloud.obs_pixel[sel].astype(np.float64)
            normals, flat = self.cloud.normals[idx], self.cloud.flatness[idx]
            # observations are in the registered image's pixels; rescale when the photo differs
            px = resized_pixels(px, (reg.intrinsics.width_px, reg.intrinsics.height_px), (W, H))
        self.static_obs_count[photo_id] = len(pts)
        res = static_mask(
            img,
            small,
            maps,
            world_from_camera[:3, 3],
            pts,
            px,
            normals,
            flat,
            self._terrain_height_m(),
            self.static_params,
        )
        mask, status = res.mask, res.status
        self.static_judged[photo_id] = res.num_points
        self.static_borrowed.pop(photo_id, None)
        info = self.photos[photo_id]
        if info.camera_id is not None and res.num_points < self.config.static_borrow_below_points:
            borrowed = self._borrow_static(photo_id, info.camera_id, maps.has_model, (W, H))
            if borrowed is not None:
                mask, status = mask | borrowed, "ok"
        self.static_raw[photo_id] = (status, encode_png(mask) if status == "ok" else b"", res.num_points)
        self._publish_static(photo_id, started)
        for other, donor in list(self.static_borrowed.items()):
            if donor == photo_id and other != photo_id:  # its mask changed: the frames that took it follow
                self._static(other)
        if info.camera_id is not None and res.num_points >= max(1, self.config.static_borrow_below_points):
            # a (better) donor for the camera's frames that judge too few points of their own
            for other in self.store.by_camera.get(info.camera_id, ()):
                current = self.static_borrowed.get(other)
                if (
                    other != photo_id
                    and other in self.registrations
                    and self.static_judged.get(other, 0) < self.config.static_borrow_below_points
                    and (current is None or self.static_judged.get(current, 0) < res.num_points)
                ):
                    self._static(other)

    def _publish_static(self, photo_id: str, started: float, only_if_changed: bool = False) -> None:
        """Publish a photo's static mask: its own (and borrowed) static occluders, minus its current dynamic mask with
        ``static_excludes_dynamic`` (what moves between views is a dynamic occluder; the combined mask has both).
        Redone whenever the dynamic mask changes; ``only_if_changed``: not published when the result is the same."""
        status, raw, num_points = self.static_raw[photo_id]
        mask = np.where(decode_mask(raw), 255, 0).astype(np.uint8) if raw else None
        dyn_status, dyn_png = self.masks.get((photo_id, "dynamic"), ("", b""))
        if mask is not None and self.config.static_excludes_dynamic and dyn_status == "ok" and dyn_png:
            mask = np.where(decode_mask(dyn_png, mask.shape), 0, mask).astype(np.uint8)
        if only_if_changed:
            png = encode_png(mask) if mask is not None and status == "ok" else b""
            if self.masks.get((photo_id, "static")) == (status, png):
                return
        self._publish(photo_id, "static", status, mask, started, num_views=num_points)

    def _borrow_static(
        self, photo_id: str, camera_id: str, has_model_small: NDArray[np.bool_], size: tuple[int, int]
    ) -> U8 | None:
        """The static mask (H, W) 0/255 of the camera's frame that judged the most points (at least
        ``static_borrow_below_points``), warped into ``photo_id`` by the stack homography and limited to this
        frame's projected model; None when no frame qualifies."""
        q = self._static_donor(camera_id, photo_id)
        if q is None:
            return None
        H_this_from_q = self.store.candidate_neighbours(photo_id).get(q)
        png = self.static_raw[q][1]  # the donor's static occluders before its own dynamic ones are taken out
        if H_this_from_q is None or not png:
            return None
        src = np.where(decode_mask(png), 255, 0).astype(np.uint8)
        warped = cv2.warpPerspective(src, H_this_from_q, size, flags=cv2.INTER_NEAREST, borderValue=0)
        model = cv2.resize(has_model_small.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        self.static_borrowed[photo_id] = q
        return np.where((warped > 0) & (model > 0), 255, 0).astype(np.uint8)

    def _static_donor(self, camera_id: str, exclude: str | None = None) -> str | None:
        """The camera's frame (not ``exclude``) whose own static mask judged the most sparse points, at least
        ``static_borrow_below_points``; None when none does. Its frames that judge fewer borrow its mask, so the
        per-camera cap drops it last (the frames with points are often the earliest: the register node's map)."""
        donors = [
            q
            for q in self.store.by_camera.get(camera_id, ())
            if q != exclude
            and self.static_judged.get(q, 0) >= self.config.static_borrow_below_points
            and self.static_raw.get(q, ("",))[0] == "ok"
        ]
        return max(donors, key=lambda d: self.static_judged[d]) if donors else None

    def _user(self, photo_id: str) -> None:
        info = self.photos.get(photo_id)
        if info is None:
            return
        started = time.perf_counter()
        mask = self.user.mask_for(photo_id, info.camera_id, info.capture_time_ns, info.width_px, info.height_px)
        if mask is not None:
            self._publish(photo_id, "user", "ok", mask, started)

    def _combined(self, photo_id: str) -> None:
        info = self.photos.get(photo_id)
        if info is None:
            return
        started = time.perf_counter()
        out = np.zeros((info.height_px, info.width_px), np.uint8)
        any_ok = False
        for kind in ("dynamic", "static", "user"):
            status, png = self.masks.get((photo_id, kind), ("", b""))
            if status == "ok" and png:
                out[decode_mask(png, out.shape)] = 255
                any_ok = True
        self._publish(photo_id, "combined", "ok" if any_ok else "not_enough_views", out if any_ok else None, started)

    def _use_meshes(self, meshes: dict[str, tuple[NDArray[np.float64], NDArray[np.int32]]], revision: str) -> None:
        self.meshes = meshes
        self.model_revision = revision
        if self.renderer is None:
            self.renderer = ModelView(meshes)
        else:
            self.renderer.set_meshes(meshes)  # keeps the GL context
        self.static_obs_count.clear()
        for pid in list(self.registrations):
            self._static(pid)
