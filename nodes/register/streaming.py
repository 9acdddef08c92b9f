"""Streaming registration: each new photo registered on its own against what is already registered.

One engine with the batch (:mod:`nodes.register.sfm`): every photo that is not a fast-path frame becomes an image
of one :class:`~nodes.register.recon.Reconstruction`, and the same mapper steps register it
(:mod:`nodes.register.mapper`: anchor clicks, homography transfer, PnP on tracks, relative-pose bootstrap), the
same triangulation, bundle adjustment (:func:`nodes.register.adjust.bundle`), densification
(:func:`nodes.register.densify.densify_reconstruction`) and retrieval (:class:`nodes.register.matching.Vocabulary`)
grow the map. What streaming adds:

* the **fast path** (:mod:`nodes.register.fastpath`) for a frame of a fixed camera whose previous frame is
  registered (KLT tracking, rotation about the camera's centre); a bumped camera fails it and takes the full path;
* **model points**: an anchor's features get 3D points from the BIM (:mod:`nodes.register.bimdepth`), which
  serve its own camera at once and other photos once a second view confirms them;
* photos that cannot be registered yet stay in the reconstruction with their matches, so :meth:`retry`
  registers them when the map grows (no second anchor for a camera or a phone visit whose first photo is
  anchored);
* viewpoint groups (paper Sec. 4.1.1) and the sparse map for the occlusion work;
* a fixed camera's frame that would need clicks is first searched for by the model's outlines around its GPS
  position (:mod:`nodes.register.modelsearch`), as the batch does before a request.

Frames and units: ``world_from_camera`` (4, 4) maps OpenCV camera coordinates to world metres; pixels use the
OpenCV convention at the photo's full resolution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import msgspec
import numpy as np

from constructaide import camera as cam
from constructaide.geo import horizontal_distance_m
from nodes.register import mapper
from nodes.register.adjust import bundle
from nodes.register.bimdepth import DepthLookup, MeshDepthLookup, points_from_depth
from nodes.register.densify import DensifyParams, densify_reconstruction
from nodes.register.fastpath import FastPath
from nodes.register.features import extract_features, homography_inlier_ratio
from nodes.register.matching import Vocabulary, match_image
from nodes.register.modelalign import PolishPolicy, ViewPolish, polish_registration
from nodes.register.modelsearch import ModelAnchors, OutlineCheck
from nodes.register.phonesearch import phone_anchor_in
from nodes.register.photo import FrameImage, PhotoInput
from nodes.register.pose import rotation_deviation
from nodes.register.recon import (
    Reconstruction,
    add_image,
    image_tracks,
    link_image_tracks,
    local_window,
    remove_images,
)
from nodes.register.sfm import register_one
from nodes.register.streamconfig import StreamConfig
from nodes.register.triangulation import confirm_model_points, triangulate_tracks
from nodes.register.viewpoints import ViewpointGraph, rotation_homography
from schemas.messages import SPARSE_POINT_FROM_MODEL as POINT_FROM_MODEL
from schemas.messages import SPARSE_POINT_VERIFIED as POINT_VERIFIED
from schemas.messages import GeoPoint, Intrinsics, Registration

__all__ = ["FrameImage", "Outcome", "PhotoInput", "StreamConfig", "StreamingRegistrar"]


@dataclass
class PoseRecord:
    photo_id: str
    camera_id: str | None
    capture_time_ns: int
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    method: str
    gps: GeoPoint | None = None


@dataclass
class Outcome:
    """Result of one registration attempt.

    ``needs_anchor``: reason an anchor is requested (None when registered); ``viewpoint_changed``: photo ids whose
    viewpoint group changed; ``map_changed``: the sparse map grew or moved.
    """

    registration: Registration
    needs_anchor: str | None = None
    num_matched_tracks: int = 0
    viewpoint_changed: list[str] = field(default_factory=list)
    map_changed: bool = False


_ViewPolish = ViewPolish  # the name register-node states saved before 2026-12-06 pickled it under


class StreamingRegistrar:
    """Registers photos one at a time (see the module docstring).

    ``depth_lookup`` (optional) gives anchor features 3D points on the BIM model; it can be replaced at any time
    (BIM updates never trigger re-registration).
    """

    def __init__(self, config: StreamConfig | None = None, depth_lookup: DepthLookup | None = None, site: str = "demo"):
        self.config = config or StreamConfig()
        self.mcfg = self.config.mapper
        self.depth_lookup = depth_lookup
        self.site = site
        self.recon = Reconstruction()
        self.fast = FastPath(self.config.fast)
        self.poses: dict[str, PoseRecord] = {}
        self.by_camera: dict[str, list[str]] = {}
        self.viewpoints = ViewpointGraph(
            min_inlier_ratio=self.mcfg.homography_min_inlier_ratio,
            min_matches=self.mcfg.homography_min_matches,
            max_neighbours=self.config.viewpoint_max_neighbours,
        )
        self.depth_error = ""
        """Why the depth lookup was switched off (empty while it works)."""
        self._vocab: Vocabulary | None = None
        self._vocab_size = 0
        self._bow: dict[int, np.ndarray] = {}
        self._tried: dict[int, set[int]] = {}
        self._last_try: dict[int, tuple[int, int]] = {}
        self._new_since_global = 0
        self._polish_next: PhotoInput | None = None
        """The photo of the latest successful registration, for :meth:`polish_registration`."""

    # -- queries -----------------------------------------------------------

    @property
    def num_registered(self) -> int:
        return len(self.poses)

    def has_registrations(self) -> bool:
        return bool(self.recon.registered_indices())

    def can_track(self, camera_id: str | None) -> bool:
        """Whether the fast path holds a tracked frame of this fixed camera (its next frame needs no map)."""
        return camera_id is not None and camera_id in self.fast.tracks

    def adopt_camera(self, camera_id: str, other: StreamingRegistrar) -> int:
        """Take over fixed camera ``camera_id`` from another worker's registrar (a hand-over when workers are added
        or removed): its fast-path track and its pose records, so its next frame registers by the fast path without
        new clicks. Its map images stay behind (a bumped camera's frame then matches this worker's map only).
        Returns the number of pose records taken."""
        self.fast.tracks[camera_id] = other.fast.tracks[camera_id]
        frames = self.by_camera.setdefault(camera_id, [])
        taken = 0
        for pid in other.by_camera.get(camera_id, []):
            rec = other.poses.get(pid)
            if rec is None or pid in self.poses:
                continue
            self.poses[pid] = rec
            self.viewpoints.add_photo(pid)
            frames.append(pid)
            taken += 1
        frames.sort(key=lambda p: self.poses[p].capture_time_ns if p in self.poses else 0)
        self._bound_camera(frames)
        return taken

    def click_disagreement_px(self, photo_id: str, pixels_px: np.ndarray, points_in_world: np.ndarray) -> float:
        """Median distance (px) between clicked pixels (N, 2) and their model points (N, 3) projected under the
        registered pose of ``photo_id`` (inf for points behind the camera). Raises KeyError when it is not
        registered."""
        rec = self.poses[photo_id]
        return cam.median_click_error_px(rec.intrinsics, rec.world_from_camera, pixels_px, points_in_world)

    def sparse_arrays(self) -> dict[str, np.ndarray | list[str]]:
        """Map arrays: ``points_xyz`` (P, 3) f32, ``colors_rgb`` (P, 3) u8, ``point_flags`` (P,) u8 (bits
        ``POINT_FROM_MODEL``, ``POINT_VERIFIED``, as in SparseCloud), ``obs_point`` / ``obs_photo`` (M,) i32,
        ``obs_pixel`` (M, 2) f32 and ``photo_ids`` (the registered images)."""
        r = self.recon
        pts, cols, op, oi, px = r.sparse_arrays()
        ok = np.nonzero(np.all(np.isfinite(r.points), axis=1))[0]
        model_only = r.point_from_model[ok] & ~r.point_confirmed[ok]
        flags = model_only.astype(np.uint8) * POINT_FROM_MODEL + r.point_verified[ok].astype(np.uint8) * POINT_VERIFIED
        reg = r.registered_indices()
        local = -np.ones(len(r.images), np.int64)
        local[reg] = np.arange(len(reg))
        return {
            "points_xyz": pts.astype(np.float32),
            "colors_rgb": cols.astype(np.uint8),
            "point_flags": flags.astype(np.uint8),
            "obs_point": np.asarray(op, np.int32),
            "obs_photo": local[np.asarray(oi, np.int64)].astype(np.int32),
            "obs_pixel": np.asarray(px, np.float32).reshape(-1, 2),
            "photo_ids": [r.images[i].name for i in reg],
        }

    # -- public entry points -----------------------------------------------

    def register_anchor(
        self,
        photo: PhotoInput,
        pixels_px: np.ndarray,
        points_in_world: np.ndarray,
        focal_px: float | None = None,
        method: str = "anchor",
        note: str = "",
    ) -> Outcome:
        """Register a photo from user clicks (pixels (N, 2) <-> model points (N, 3)); a registered photo is
        corrected in place (re-anchoring). Raises ``DegenerateAnchors`` (a ValueError) for unusable clicks.
        ``method`` "model": the clicks are model points the model search found (``note`` says how)."""
        t0 = time.perf_counter()
        idx = self._ensure_image(photo)
        im = self.recon.images[idx]
        if focal_px is not None:
            im.focal_prior_px = float(focal_px)
        was = photo.photo_id in self.poses
        sol = mapper.register_anchor(
            self.recon, idx, (np.asarray(pixels_px, float), np.asarray(points_in_world, float)), self.mcfg
        )
        self.recon.images[idx].method = method
        flagged = int(np.sum(sol.outlier_mask))
        msg = f"{len(sol.residuals_px)} clicks, RMS {sol.rms_px:.2f} px" + (
            f"; {flagged} click(s) look mis-placed (residual > {sol.outlier_threshold_px:.1f} px)" if flagged else ""
        )
        if was:
            msg += "; replaces the earlier registration"
        if note:
            msg = f"{note}; {msg}"
        self._match(idx)
        link_image_tracks(self.recon, idx)
        changed = self._grow(photo, idx)
        im = self.recon.images[idx]
        reg = self._registration(
            photo,
            "anchor",
            method,
            im.intrinsics,
            im.world_from_camera,
            len(sol.residuals_px),
            sol.rms_px,
            msg,
            t0,
            residuals=tuple(float(r) for r in sol.residuals_px),
        )
        self._retire_camera_images(photo)
        return Outcome(reg, viewpoint_changed=changed, map_changed=True)

    def register(self, photo: PhotoInput) -> Outcome:
        """Register a photo without clicks: fast path for a tracked fixed camera, else the full path."""
        t0 = time.perf_counter()
        if photo.photo_id in self.poses:
            rec = self.poses[photo.photo_id]
            return Outcome(
                self._registration(
                    photo, "auto", rec.method, rec.intrinsics, rec.world_from_camera, 0, 0.0, "already registered", t0
                )
            )
        out, note = self._fast_path(photo, t0)
        if out is not None:
            return out
        if not self.has_registrations():
            reason = "no registered images yet: anchor clicks are needed"
            return self._by_model(photo, Outcome(self._failed(photo, reason, t0), needs_anchor=reason))
        return self._by_model(photo, self._full_path(photo, self._ensure_image(photo), t0, note))

    def register_by_model(self, photo: PhotoInput) -> Outcome | None:
        """A fixed camera's frame anchored by the model's outlines alone (also before any registration), or None."""
        reason = "anchor clicks are needed"
        out = self._by_model(photo, Outcome(self._failed(photo, reason, time.perf_counter()), needs_anchor=reason))
        return None if out.needs_anchor is not None else out

    def _by_model(self, photo: PhotoInput, out: Outcome) -> Outcome:
        """A fixed camera's frame that needs clicks, anchored by the model's outlines when the search finds its
        camera (:class:`~nodes.register.modelsearch.ModelAnchors`); else ``out``."""
        lookup = self.depth_lookup
        if out.needs_anchor is None or not isinstance(lookup, MeshDepthLookup):
            return out
        if photo.camera_id is None:
            return self._phone_by_model(photo, out, lookup)
        if not self.mcfg.model_search:
            return out
        try:
            focal = self.mcfg.focal_px or photo.focal_px
            anchors = self.__dict__.setdefault("model_anchors", ModelAnchors(self.mcfg.model_search_clicks))
            clicks, why = anchors.find(
                lookup, photo.image.gray, focal, photo.gps, photo.camera_id, photo.capture_time_ns
            )
            if clicks is None:
                return out
            px, pts = clicks
            return self.register_anchor(photo, px, pts, method="model", note=f"found by the model's outlines ({why})")
        except (RuntimeError, ValueError) as e:  # no GL context, degenerate clicks: the request stands
            self.depth_error = f"model search of {photo.photo_id} failed: {e}"
            return out

    def _phone_by_model(self, photo: PhotoInput, out: Outcome, lookup: MeshDepthLookup) -> Outcome:
        """A phone photo that needs clicks, anchored by the model when the fixed cameras' latest frames' texture (or its
        matches with registered photos) confirm a camera the outlines suggest
        (:func:`~nodes.register.phonesearch.phone_anchor_in`; once per photo, again only when more fixed cameras
        carry texture to it than at its last search); else ``out``."""
        tried: dict[str, frozenset[str]] = self.__dict__.setdefault("phones_searched", {})
        latest: dict[str, tuple[str, np.ndarray]] = self.__dict__.get("latest_frames", {})
        cameras = frozenset(c for c, (p, _) in latest.items() if p in self.poses)
        last = tried.get(photo.photo_id)
        if not self.mcfg.phone_search or (last is not None and not cameras > last) or photo.photo_id not in self.recon:
            return out
        tried[photo.photo_id] = cameras
        idx = self.recon.index(photo.photo_id)
        w, h = self.recon.images[idx].width_px, self.recon.images[idx].height_px
        intr = cam.centered_intrinsics(w, h, self.mcfg.focal_px or photo.focal_px or cam.focal_from_fov(w, 50.0))
        try:
            frames = [(px, self.poses[p].intrinsics, self.poses[p].world_from_camera, self.poses[p].capture_time_ns)
                      for p, px in latest.values() if p in self.poses]  # fmt: skip
            clicks, why = phone_anchor_in(self.recon, idx, lookup, photo.image.gray(), intr, self.mcfg, frames)
            if clicks is None:
                return out
            return self.register_anchor(photo, *clicks, method="model", note=f"found by the model's outlines ({why})")
        except (RuntimeError, ValueError) as e:  # no GL context, degenerate clicks: the request stands
            self.depth_error = f"model search of {photo.photo_id} failed: {e}"
            return out

    def _fast_path(self, photo: PhotoInput, t0: float) -> tuple[Outcome | None, str]:
        """A tracked fixed camera's frame by the fast path (joining the map as a key frame now and then): its
        Outcome, else None and why the fast path failed ("" when its camera is not tracked)."""
        if photo.camera_id is None or photo.camera_id not in self.fast.tracks:
            return None, ""
        res, note = self.fast.track(photo, self._lookup if self.depth_lookup is not None else None)
        if res is None:
            return None, note
        changed = self._record(
            photo, res.intrinsics, res.world_from_camera, res.method, (res.inlier_ratio, res.num_inliers)
        )
        grew = self._wants_key_frame(photo)
        if grew:  # the site changes: a fixed camera's frame now and then joins the map (other photos match it)
            idx = self._ensure_image(photo)
            im = self.recon.images[idx]
            im.intrinsics, im.world_from_camera = res.intrinsics, res.world_from_camera
            im.status, im.method, im.message, im.num_inliers = "auto", res.method, res.note, res.num_inliers
            self._match(idx)
            link_image_tracks(self.recon, idx)
            changed += [p for p in self._grow(photo, idx, trusted=True) if p not in changed]
            res.note += "; joined the map as a key frame"
        reg = self._registration(
            photo, "auto", res.method, res.intrinsics, res.world_from_camera, res.num_inliers, res.rms_px, res.note, t0
        )
        if grew:
            self._retire_camera_images(photo)
        return Outcome(reg, viewpoint_changed=changed, map_changed=grew), ""

    def retry(self, photo: PhotoInput) -> Outcome | None:
        """Try again a photo that could not be registered (the map has grown since): by the fast path when its
        fixed camera is tracked now, else matched with the registered photos it has not been matched with yet and
        registered by the full path. None when nothing new could change its outcome (no new registered photo to
        match it with)."""
        if photo.photo_id in self.poses:
            return None
        if photo.photo_id not in self.recon:
            return self.register(photo)
        # A frame that waited for its camera's anchor (it came first: arrival order across a node's inputs is not
        # guaranteed) is tracked from it as if it had come after it, not placed by the full path.
        out, _ = self._fast_path(photo, time.perf_counter())
        if out is not None:
            if photo.photo_id in self.recon and not self.recon.images[self.recon.index(photo.photo_id)].registered:
                self._remove_images({self.recon.index(photo.photo_id)})  # the map image it waited as
            return out
        idx = self.recon.index(photo.photo_id)
        n_pairs = sum(1 for j in self.recon.registered_indices() if self.recon.pair(j, idx) is not None)
        self._match(idx)
        link_image_tracks(self.recon, idx)
        now = (
            sum(1 for j in self.recon.registered_indices() if self.recon.pair(j, idx) is not None),
            len(mapper.usable_track_matches(self.recon, idx, self.mcfg)[0]),
        )
        if now[0] == n_pairs and self._last_try.get(idx) == now:
            return None  # nothing new connects it
        self._last_try[idx] = now
        return self._by_model(photo, self._full_path(photo, idx, time.perf_counter(), ""))

    # -- the full path -----------------------------------------------------

    def _ensure_image(self, photo: PhotoInput) -> int:
        if photo.photo_id in self.recon:
            return self.recon.index(photo.photo_id)
        c = self.config
        image = photo.image
        feats = extract_features(image.gray(), c.sift_max_features, c.sift_max_side_px)
        bgr = image.bgr()
        h, w = bgr.shape[:2]
        uv = np.clip(np.round(feats.keypoints_px).astype(int), 0, [w - 1, h - 1])
        colors = bgr[uv[:, 1], uv[:, 0], ::-1].copy()
        return add_image(
            self.recon, photo.photo_id, feats, colors, photo.focal_px, photo.gps, photo.camera_id, photo.capture_time_ns
        )

    def _full_path(self, photo: PhotoInput, idx: int, t0: float, note: str) -> Outcome:
        prefix = (note + "; ") if note else ""
        self._match(idx)
        link_image_tracks(self.recon, idx)
        im = self.recon.images[idx]
        why = self._try_register(idx, photo)
        if why:
            im.status = "unregistered"
            reason = f"{prefix}not registered: {why}; please click anchors"
            return Outcome(
                self._failed(photo, reason, t0), needs_anchor=reason, num_matched_tracks=im.num_matched_tracks
            )
        changed = self._grow(photo, idx)
        im = self.recon.images[idx]
        if not im.registered:  # refused after the adjustment (implausible)
            reason = f"{prefix}not registered: {im.message}; please click anchors"
            return Outcome(self._failed(photo, reason, t0), needs_anchor=reason, map_changed=True)
        msg = f"{prefix}full path: {im.method}: {im.message}"
        reg = self._registration(
            photo, "auto", im.method, im.intrinsics, im.world_from_camera, im.num_inliers, im.rms_px, msg, t0
        )
        self._retire_camera_images(photo)
        return Outcome(reg, num_matched_tracks=im.num_matched_tracks, viewpoint_changed=changed, map_changed=True)

    def _try_register(self, idx: int, photo: PhotoInput) -> str:
        """Register image ``idx`` (``photo``) by the mapper's steps (:func:`nodes.register.sfm.register_one`), a
        phone's automatic pose checked by the model's outlines (:class:`~nodes.register.modelsearch.OutlineCheck`)."""
        lookup, floor, check = self.depth_lookup, self.mcfg.min_outline_contrast, None
        if isinstance(lookup, MeshDepthLookup) and floor is not None:
            check = OutlineCheck(lookup, floor).for_photo(photo.image.gray, photo.camera_id, photo.capture_time_ns)
        return register_one(self.recon, idx, self.mcfg, len(self._tried.get(idx, ())), check)

    def _wants_key_frame(self, photo: PhotoInput) -> bool:
        """Whether a fast-path frame joins the map: its camera has no photo in it from the last
        ``key_frame_every_secs``."""
        every = self.config.key_frame_every_secs
        if every is None or photo.camera_id is None:
            return False
        last = max(
            (im.capture_time_ns for im in self.recon.images if im.registered and im.camera_id == photo.camera_id),
            default=None,
        )
        return last is None or photo.capture_time_ns - last >= every * 1e9

    def _grow(self, photo: PhotoInput, idx: int, trusted: bool = False) -> list[str]:
        """After image ``idx`` registered: model points (anchors, and ``trusted`` poses: a fixed camera's fast-path
        frame), triangulation, adjustment, plausibility, densification, viewpoint edges, fast-path state and pose
        records. Returns photo ids whose viewpoint group changed."""
        r, cfg, c = self.recon, self.mcfg, self.config
        im = r.images[idx]
        if im.status == "anchor" or trusted:
            self._add_model_points(idx)
        mapper.prune_observations(r, idx, cfg)
        tracks = image_tracks(r, [idx])
        triangulate_tracks(r, cfg, only=tracks)
        confirm_model_points(r, tracks, cfg)
        self._new_since_global += 1
        held = self._held_images()
        if c.global_ba_every and self._new_since_global >= c.global_ba_every:
            movable = [i for i in r.registered_indices() if i not in held]
            if movable:
                bundle(r, cfg, window=movable if held else None)
            triangulate_tracks(r, cfg)
            self._new_since_global = 0
        elif c.local_ba:
            window = [i for i in local_window(r, idx, c.local_ba_window) if i not in held]
            if window:
                bundle(r, msgspec.structs.replace(cfg, ba_max_nfev=c.local_ba_iterations), window=window)
                triangulate_tracks(r, cfg, only=image_tracks(r, window))
        why = mapper.implausible(im, cfg)
        if why:
            im.status, im.message = "failed", f"implausible registration ({im.method}): {why}"
            return []
        if c.densify and len(r.registered_indices()) >= 2:
            densify_reconstruction(r, DensifyParams(pairs_per_view=c.densify_pairs), only=idx)
        changed = self._viewpoint_edges(idx)
        self.fast.init_track(photo, im.camera, im.pose)
        changed += self._record(photo, im.camera, im.pose, im.method)
        for j in r.registered_indices():  # adjustments moved other photos too
            rec = self.poses.get(r.images[j].name)
            if rec is not None and j != idx:
                rec.world_from_camera, rec.intrinsics = r.images[j].pose, r.images[j].camera
        return sorted(set(changed), key=changed.index)

    def _retire_camera_images(self, photo: PhotoInput) -> None:
        """After ``photo`` joined the map: retire its fixed camera's oldest registered map images beyond
        ``max_map_images_per_camera`` (not anchors, not this photo, not the centre or lens source of another
        image). Their pose records stay (bounded by ``max_frames_per_camera``). Image indices change."""
        cap, camera_id, keep = self.config.max_map_images_per_camera, photo.camera_id, photo.photo_id
        if camera_id is None:
            return
        r = self.recon
        mine = [i for i, im in enumerate(r.images) if im.camera_id == camera_id and im.registered]
        if cap <= 0 or len(mine) <= cap:
            return
        sources = {s for im in r.images for s in (im.centre_source, im.lens_source) if s is not None}
        movable = sorted(
            (i for i in mine if r.images[i].status != "anchor" and r.images[i].name != keep and i not in sources),
            key=lambda i: r.images[i].capture_time_ns,
        )
        self._remove_images(set(movable[: len(mine) - cap]))

    def forget(self, photo_id: str) -> bool:
        """Take a photo that is not registered (given up on: pushed out of the waiting queue) out of the map.
        Returns whether it was there."""
        if photo_id in self.poses or photo_id not in self.recon:
            return False
        self._remove_images({self.recon.index(photo_id)})
        return True

    def _remove_images(self, drop: set[int]) -> None:
        """Remove map images ``drop`` (:func:`~nodes.register.recon.remove_images`) and renumber what is keyed by
        image index here."""
        if not drop:
            return
        new = remove_images(self.recon, drop)
        self._bow = {int(new[i]): h for i, h in self._bow.items() if new[i] >= 0}
        self._tried = {
            int(new[i]): {int(new[j]) for j in js if new[j] >= 0} for i, js in self._tried.items() if new[i] >= 0
        }
        self._last_try = {int(new[i]): v for i, v in self._last_try.items() if new[i] >= 0}

    def _held_images(self) -> set[int]:
        """Map images the adjustments never move: fixed cameras' fast-path key frames. Their pose was tracked from
        the camera's previous frame and published as such, and the camera's next frames are tracked from it; an
        adjustment over the map's few views (SIFT tracks matched across cameras on repeated texture among them)
        would move it to a pose nobody published and hand that on to every later frame of the camera."""
        r = self.recon
        return {i for i in r.registered_indices() if r.images[i].method.startswith("fastpath")}

    def add_model_points_to_map(self) -> int:
        """Model points (BIM depth) for the map images :meth:`_grow` gives them to — anchors and fixed cameras'
        fast-path key frames — that registered while no depth lookup was set (the BIM model came after them, or
        its depth renderer was still starting): call when a lookup appears. Features with a triangulated track
        keep it. Returns how many points were added."""
        r = self.recon
        return sum(
            self._add_model_points(i)
            for i in r.registered_indices()
            if r.images[i].status == "anchor" or r.images[i].method.startswith("fastpath")
        )

    def _add_model_points(self, idx: int) -> int:
        """BIM-depth model points for registered map image ``idx``'s features without a point (0 without a lookup)."""
        if self.depth_lookup is None:
            return 0
        im = self.recon.images[idx]
        pts = self._lookup(im.pose, im.camera, im.features.keypoints_px, im.capture_time_ns)
        return mapper.add_model_points(self.recon, idx, pts)

    def _lookup(self, world_from_camera: np.ndarray, intr: Intrinsics, px: np.ndarray, t_ns: int) -> np.ndarray:
        if self.depth_lookup is None:
            return np.full((len(px), 3), np.nan)
        try:
            return points_from_depth(self.depth_lookup, world_from_camera, intr, px, t_ns)
        except Exception as e:  # e.g. no EGL/OpenGL on this machine: register without BIM depth
            self.depth_error = f"BIM depth lookup disabled: {type(e).__name__}: {e}"
            self.depth_lookup = None
            return np.full((len(px), 3), np.nan)

    # -- matching ----------------------------------------------------------

    def _match(self, idx: int) -> None:
        """Verify pairs of image ``idx`` with its candidates (:meth:`_candidates`) not tried yet."""
        tried = self._tried.setdefault(idx, set())
        todo = [j for j in self._candidates(idx) if j not in tried]
        match_image(self.recon, idx, todo, self.mcfg)
        tried.update(todo)
        for j in todo:
            self._tried.setdefault(j, set()).add(idx)

    def _candidates(self, idx: int) -> list[int]:
        r, c = self.recon, self.config
        im = r.images[idx]
        reg = [j for j in r.registered_indices() if j != idx]
        unreg = [j for j in range(len(r.images)) if j != idx and not r.images[j].registered]
        chosen: list[int] = []
        if im.camera_id is not None:
            chosen += [j for j in reversed(reg) if r.images[j].camera_id == im.camera_id][
                : max(1, c.max_candidates // 2)
            ]
        near = []
        for j in reg:
            o = r.images[j]
            same_visit = (
                o.camera_id is None
                and im.camera_id is None
                and abs(o.capture_time_ns - im.capture_time_ns) < c.visit_gap_secs * 1e9
            )
            close = im.gps is not None and o.gps is not None and horizontal_distance_m(im.gps, o.gps) < 20.0
            if same_visit or close:
                near.append(j)
        chosen += [j for j in near if j not in chosen][:2]
        ranked = self._rank(idx, [j for j in reg if j not in chosen])
        chosen += ranked[: max(0, c.max_candidates - len(chosen))]
        chosen += self._rank(idx, unreg)[: c.max_unregistered_candidates]
        return chosen

    def _rank(self, idx: int, others: list[int]) -> list[int]:
        """``others`` by bag-of-words similarity to image ``idx`` (most similar first)."""
        if len(others) <= 1:
            return others
        self._ensure_vocab()
        if self._vocab is None:
            return others[::-1]
        q = self._histogram(idx)
        scores = [float(q @ self._histogram(j)) for j in others]
        return [others[k] for k in np.argsort(scores)[::-1]]

    def _ensure_vocab(self) -> None:
        """(Re)build the retrieval vocabulary when the set of images has doubled since the last one."""
        n = len(self.recon.images)
        if n < 4 or (self._vocab is not None and n < 2 * self._vocab_size):
            return
        self._vocab = Vocabulary.build(
            [im.features.descriptors for im in self.recon.images], max_words=self.config.vocabulary_words
        )
        self._vocab_size = n
        self._bow = {}

    def _histogram(self, idx: int) -> np.ndarray:
        if idx not in self._bow:
            assert self._vocab is not None
            self._bow[idx] = self._vocab.histogram(self.recon.images[idx].features.descriptors)
        return self._bow[idx]

    # -- viewpoints and records ----------------------------------------------

    def _viewpoint_edges(self, idx: int) -> list[str]:
        """Same-viewpoint edges (paper Sec. 4.1.1) between image ``idx`` and the registered images it has a pair
        with: a homography explaining most matches that is a rotation (+ zoom)."""
        r, cfg = self.recon, self.mcfg
        im = r.images[idx]
        self.viewpoints.add_photo(im.name)
        changed = [im.name]
        thr = max(1.0, cfg.homography_threshold_frac * im.width_px)
        for j in r.registered_indices():
            p = r.pair(j, idx)
            if j == idx or p is None:
                continue
            o = r.images[j]
            H, ratio = homography_inlier_ratio(o.features.keypoints_px, im.features.keypoints_px, p[0], thr)
            if H is None:
                continue
            _, dev = rotation_deviation(H, o.camera, im.camera.cx_px, im.camera.cy_px)
            if dev <= cfg.homography_max_rotation_deviation and self.viewpoints.add_pair(
                im.name, o.name, H, ratio, len(p[0])
            ):
                changed.append(o.name)
        return changed

    def _record(
        self,
        photo: PhotoInput,
        intr: Intrinsics,
        world_from_camera: np.ndarray,
        method: str,
        fast_ratio: tuple[float, int] | None = None,
    ) -> list[str]:
        """Remember a registered pose; for a fixed camera add same-camera viewpoint edges from the poses."""
        c = self.config
        self.poses[photo.photo_id] = PoseRecord(
            photo.photo_id,
            photo.camera_id,
            photo.capture_time_ns,
            intr,
            np.asarray(world_from_camera).copy(),
            method,
            photo.gps,
        )
        changed: list[str] = []
        self.viewpoints.add_photo(photo.photo_id)
        if photo.camera_id is None:
            return changed
        if self.mcfg.phone_search and self.mcfg.phone_search_texture:  # each fixed camera's latest frame: texture
            self.__dict__.setdefault("latest_frames", {})[photo.camera_id] = (photo.photo_id, photo.image.gray())
        frames = self.by_camera.setdefault(photo.camera_id, [])
        if fast_ratio is not None:
            ratio, n = fast_ratio
            for other in frames[-c.viewpoint_max_neighbours :]:
                rec = self.poses[other]
                if np.linalg.norm(rec.world_from_camera[:3, 3] - world_from_camera[:3, 3]) > 1e-6:
                    continue  # a different centre: only matched features can tell (full path)
                if cam.viewing_angle_deg(rec.world_from_camera, world_from_camera) > c.viewpoint_max_angle_deg:
                    continue
                H = rotation_homography(intr, world_from_camera, rec.intrinsics, rec.world_from_camera)
                if self.viewpoints.add_pair(photo.photo_id, other, H, ratio, n, check=False):
                    changed.append(other)
        if photo.photo_id not in frames:
            frames.append(photo.photo_id)
            self._bound_camera(frames)
        if photo.photo_id not in changed:
            changed.insert(0, photo.photo_id)
        return changed

    def _bound_camera(self, frames: list[str]) -> None:
        """Forget a fixed camera's oldest fast-path frames beyond ``max_frames_per_camera`` (map images stay)."""
        cap = self.config.max_frames_per_camera
        if cap <= 0 or len(frames) <= cap:
            return
        excess = len(frames) - cap
        drop = [p for p in frames[:-1] if p not in self.recon][:excess]
        gone = set(drop)
        for pid in drop:
            self.poses.pop(pid, None)
            self.viewpoints.forget(pid)
        frames[:] = [p for p in frames if p not in gone]

    def _registration(
        self,
        photo: PhotoInput,
        status: Literal["anchor", "auto", "failed"],
        method: str,
        intr: Intrinsics | None,
        world_from_camera: np.ndarray | None,
        num_inliers: int,
        rms: float,
        message: str,
        t0: float,
        residuals: tuple[float, ...] = (),
    ) -> Registration:
        if status != "failed":
            self._polish_next = photo
        return Registration(
            site=self.site,
            photo_id=photo.photo_id,
            camera_id=photo.camera_id,
            capture_time_ns=photo.capture_time_ns,
            intrinsics=intr,
            world_from_camera=cam.pose_to_tuple(world_from_camera) if world_from_camera is not None else (),
            status=status,
            method=method,
            num_inliers=int(num_inliers),
            reprojection_rms_px=float(rms) if np.isfinite(rms) else 0.0,
            anchor_residuals_px=residuals,
            message=message,
            processing_ms=(time.perf_counter() - t0) * 1000.0,
        )

    def polish_registration(self, reg: Registration) -> Registration | None:
        """The latest registration polished by the BIM's outlines (:func:`nodes.register.modelalign.polish`), or None
        when it is not polished (off, a phone photo, no BIM, or the polish refused). Called after the solved
        registration is published: the solved pose goes out at once, the polished one follows as its update. The
        map keeps the solved pose."""
        photo, self._polish_next = getattr(self, "_polish_next", None), None  # (state saved before it existed)
        lookup = self.depth_lookup
        if photo is None or photo.photo_id != reg.photo_id or reg.intrinsics is None or not reg.world_from_camera:
            return None
        im = self.recon.images[self.recon.index(photo.photo_id)] if photo.photo_id in self.recon else None
        clicks = im.accepted_clicks if im is not None and photo.camera_id is None else None
        if not self.config.model_align or not isinstance(lookup, MeshDepthLookup):
            return None
        t0 = time.perf_counter()
        policy = PolishPolicy(
            phones=self.config.model_align_phones, anchored_phones=self.config.model_align_anchored_phones
        )
        views: dict[str, ViewPolish] = self.__dict__.setdefault("_polish_of_view", {})  # (state saved before it)
        try:
            out = polish_registration(
                lookup,
                photo.image.gray,
                reg.intrinsics,
                cam.pose_from_tuple(reg.world_from_camera),
                photo.capture_time_ns,
                photo.camera_id,
                clicks,
                views,
                self.config.align,
                policy,
            )
        except (RuntimeError, ValueError) as e:  # no GL context, a degenerate render: the solved pose stands
            self.depth_error = f"model outline polish of {reg.photo_id} failed: {e}"
            return None
        if out is None or out.world_from_camera is None or out.intrinsics is None:
            return None
        world_from_camera, intrinsics, note = out.world_from_camera, out.intrinsics, out.note
        return msgspec.structs.replace(
            reg,
            intrinsics=intrinsics,
            world_from_camera=cam.pose_to_tuple(world_from_camera),
            method=f"{reg.method}+outline",
            message=f"{reg.message}; {note}" if reg.message else note,
            processing_ms=reg.processing_ms + (time.perf_counter() - t0) * 1000.0,
        )

    def _failed(self, photo: PhotoInput, reason: str, t0: float) -> Registration:
        return self._registration(photo, "failed", "", None, None, 0, 0.0, reason, t0)
