"""Streaming registration: each new photo registered on its own against what is already registered.

Pure core (numpy / OpenCV / scipy / trimesh). Frames and units: ``world_from_camera`` (4, 4) maps OpenCV camera
coordinates (x right, y down, z forward) to world metres; pixels use the OpenCV convention ((0, 0) = centre of
the top-left pixel) at the photo's full resolution.

Paths, tried in this order for a photo:

* **anchor** (:meth:`StreamingRegistrar.register_anchor`): pose (and focal with >= 6 non-coplanar clicks) from
  user clicks by ``anchors.solve_anchor``; SIFT features extracted, 3D points from the optional depth lookup
  (BIM mesh) and from triangulation against other registered images.
* **fast path** for a frame of a fixed camera that already has a registered frame: the previous frame's corners
  (tracked at ``track_scale`` of full resolution) are followed by pyramidal KLT with a forward-backward check;
  a homography RANSAC rejects outliers; rotation and focal are refined by Levenberg-Marquardt with the camera
  centre held at the camera's centre (a mounted camera pans, tilts and zooms about its centre, so only each
  corner's viewing ray matters, not its depth). With ``fast_model="auto"`` (default), a residual above half the
  limit fetches BIM depth for the corners and refines the full 6-DOF pose + focal (a swayed mast). Too few
  tracked inliers, a high residual or a large rotation relative to the previous frame is reported as a bumped /
  re-aimed camera and the full path is taken.
* **full path**: SIFT matched against the best-matching registered key images (same camera first, then a bag of
  visual words shortlist), PnP with RANSAC (inliers within 1 % of the width) on matched 3D points, LM
  refinement of pose and focal, new tracks triangulated (rays >= 2 degrees apart) so the map grows, then a
  local bundle adjustment of the new image, its matched neighbours (anchor poses held) and their points.
  BIM-depth points serve other viewpoints only once a two-view triangulation confirms them (a fence or crane
  in front of the model gives features the wrong depth), unless ``trust_bim_depth``; solutions that explain
  too few tracks, change a known focal by > 30 % or are tilted > 60 degrees from upright are refused.
* **homography transfer** when there are not enough 3D points: against a key image whose matches are >= 80 %
  inliers of one homography, rotation and focal are fitted about that image's centre (many rays instead of a
  few clicks); if that does not fit, the key image's anchor clicks are warped by the homography and the pose
  re-solved from them (paper Sec. 6).
* otherwise the photo is ``failed`` and an anchor is requested (``Outcome.needs_anchor``).

GPS (``PhotoInput.gps``, EXIF) guards the full path's automatic registrations like the batch
(:func:`nodes.register.sfm.gps_refusal`): a homography transfer from a key image whose GPS position is more than
``gps_max_homography_distance_m`` away is not tried (same viewpoint premise), and a PnP or homography pose whose
distances to the registered photos with GPS contradict theirs (or that lies off its GPS position in the frame
fitted to them) is refused. The fast path keeps a fixed camera's centre, so it is not checked.

Anchor clicks for an already registered photo correct it in place (re-anchoring).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import cv2
import msgspec
import numpy as np
from scipy.optimize import least_squares

from constructaide import anchorsolve as anchors
from constructaide import camera as cam
from constructaide.geo import horizontal_distance_m
from constructaide.gl import offscreen_renderer
from nodes.register import bundle, features
from nodes.register.densify import DensifyParams, View, densify
from nodes.register.sfm import gps_refusal
from nodes.register.viewpoints import ViewpointGraph, rotation_deviation, rotation_homography
from schemas.messages import SPARSE_POINT_FROM_MODEL as POINT_FROM_MODEL
from schemas.messages import SPARSE_POINT_VERIFIED as POINT_VERIFIED
from schemas.messages import GeoPoint, Intrinsics, Registration

DepthLookup = Callable[[np.ndarray, Intrinsics, np.ndarray, int], np.ndarray]
"""``depth_lookup(world_from_camera (4, 4), intrinsics, pixels_px (N, 2), capture_time_ns) -> depth_m (N,)``:
camera z of the model surface each pixel sees at that time (NaN where nothing is hit)."""


class StreamConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Options of the streaming registrar (pixels are full-resolution pixels unless named ``_small``)."""

    # fast path (fixed cameras)
    track_scale: float = 0.5
    track_max_corners: int = 500
    track_min_distance_small_px: float = 10.0
    klt_window_small_px: int = 21
    klt_levels: int = 3
    klt_fb_max_px: float = 1.0
    track_normalize: bool = True
    fast_ransac_px: float = 3.0
    fast_min_inliers: int = 40
    fast_min_tracked_fraction: float = 0.35
    fast_max_rms_px: float = 2.0
    fast_max_rotation_deg: float = 5.0
    fast_solve_focal: bool = True
    fast_model: Literal["rotation", "auto"] = "auto"
    """``auto``: when the rotation fit leaves more than half of ``fast_max_rms_px``, corners with BIM-depth points
    refine the full 6-DOF pose + focal (a mast that swayed or a camera nudged along); ``rotation``: never."""
    replenish_fraction: float = 0.7
    # full path
    sift_max_features: int = 4000
    sift_max_side_px: int | None = 1600
    match_ratio: float = 0.8
    fundamental_px: float = 3.0
    max_candidates: int = 4
    min_matches: int = 30
    min_pnp_inliers: int = 30
    min_pnp_inlier_fraction: float = 0.3
    max_focal_change: float = 0.3
    max_tilt_from_upright_deg: float | None = 60.0
    """Reject automatic solutions whose image-up direction is further than this from world +z (None: off)."""
    pnp_inlier_fraction_of_width: float = 0.01
    min_triangulation_angle_deg: float = 2.0
    max_triangulation_error_px: float = 4.0
    confirm_tolerance: float = 0.02
    min_pose_pair_agreement: float = 0.7
    """Refuse automatic PnP poses under which fewer than this fraction of the matches to key images lie within
    2 % of the width of their epipolar lines (repeated texture, e.g. hoarding lettering, gives such poses)."""
    trust_bim_depth: bool = False
    """Use BIM-depth points for other viewpoints before a second view confirms them (only where nothing
    unmodelled stands in front of the model)."""
    """A BIM-depth point is confirmed when a two-view triangulation lands within this fraction of its range."""
    homography_px: float = 4.0
    homography_min_inlier_ratio: float = 0.8
    homography_max_rms_px: float = 3.0
    homography_max_rotation_deviation: float = 0.02
    local_ba: bool = True
    local_ba_iterations: int = 15
    vocabulary_size: int = 128
    # viewpoints
    viewpoint_max_neighbours: int = 30
    viewpoint_max_angle_deg: float = 20.0
    # densification (nodes.register.densify): epipolar-guided matching of each new key image with the registered
    # ones, for the points the static-occlusion test needs
    densify: bool = True
    densify_pairs: int = 3
    # GPS safeguards (as SfmConfig's): no homography transfer between photos whose GPS positions are further apart
    # than this (m; None = off) ...
    gps_max_homography_distance_m: float | None = 15.0
    # ... and no automatic pose whose GPS residual against >= gps_min_references registered photos with GPS exceeds
    # this (m; None = off); see nodes.register.sfm.gps_refusal.
    gps_max_residual_m: float | None = 15.0
    gps_min_references: int = 2
    gps_same_position_m: float = 1.0
    gps_min_fit_span_m: float = 30.0
    gps_sigma_m: float = 3.0


# ---------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------


class FrameImage:
    """A photo's pixels, decoded lazily: a reduced grey decode for tracking, a full decode only when needed."""

    def __init__(self, data: bytes | None = None, image: np.ndarray | None = None) -> None:
        if data is None and image is None:
            raise ValueError("FrameImage needs encoded bytes or a decoded image")
        self._data = data
        self._bgr: np.ndarray | None = None
        self._gray: np.ndarray | None = None
        self._small: dict[float, np.ndarray] = {}
        if image is not None:
            img = np.asarray(image)
            if img.dtype != np.uint8 or img.ndim not in (2, 3):
                raise ValueError(f"expected a uint8 grey or BGR image, got {img.dtype} {img.shape}")
            self._bgr = img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)

    def _decode(self, flag: int) -> np.ndarray:
        assert self._data is not None
        img = cv2.imdecode(np.frombuffer(self._data, np.uint8), flag)
        if img is None:
            raise ValueError("photo bytes are not a decodable image")
        return img

    def bgr(self) -> np.ndarray:
        """Full-resolution BGR uint8 (H, W, 3)."""
        if self._bgr is None:
            self._bgr = self._decode(cv2.IMREAD_COLOR)
        return self._bgr

    def gray(self) -> np.ndarray:
        """Full-resolution grey uint8 (H, W)."""
        if self._gray is None:
            self._gray = cv2.cvtColor(self.bgr(), cv2.COLOR_BGR2GRAY)
        return self._gray

    def gray_small(self, scale: float) -> np.ndarray:
        """Grey image at ``scale`` of full resolution; 0.5 decodes JPEG directly at half size (fast)."""
        if scale not in self._small:
            if scale == 0.5 and self._data is not None and self._bgr is None:
                self._small[scale] = self._decode(cv2.IMREAD_REDUCED_GRAYSCALE_2)
            elif scale == 1.0:
                self._small[scale] = self.gray()
            else:
                g = self.gray()
                size = (round(g.shape[1] * scale), round(g.shape[0] * scale))
                self._small[scale] = cv2.resize(g, size, interpolation=cv2.INTER_AREA)
        return self._small[scale]


@dataclass
class PhotoInput:
    """One photo handed to the registrar. ``focal_px`` is an EXIF prior (full-resolution pixels) or None; ``gps``
    its EXIF position or None."""

    photo_id: str
    image: FrameImage
    camera_id: str | None = None
    capture_time_ns: int = 0
    focal_px: float | None = None
    width_px: int = 0
    height_px: int = 0
    gps: GeoPoint | None = None


# ---------------------------------------------------------------------------
# State
# ---------------------------------------------------------------------------


@dataclass
class KeyImage:
    """A registered image with SIFT features. ``point_ids`` (N,) int: map point of each keypoint or -1."""

    photo_id: str
    camera_id: str | None
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    feats: features.Features
    point_ids: np.ndarray
    is_anchor: bool
    clicks_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    clicks_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    bow: np.ndarray | None = None
    capture_time_ns: int = 0


@dataclass
class TrackState:
    """Fast-path state of one fixed camera: the latest registered frame and its tracked corners.

    ``pixels_px`` (K, 2) full-resolution pixels in that frame; ``rays_in_world`` (K, 3) unit rays from
    ``center_in_world``; ``points_in_world`` (K, 3) BIM-depth points, looked up lazily for the 6-DOF refinement
    (NaN rows where unknown).
    """

    photo_id: str
    gray_small: np.ndarray
    scale_xy: tuple[float, float]
    width_px: int
    height_px: int
    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    center_in_world: np.ndarray
    pixels_px: np.ndarray
    rays_in_world: np.ndarray
    points_in_world: np.ndarray
    num_initial: int
    capture_time_ns: int = 0


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


class PointMap:
    """Sparse 3D points (world metres) with colours and observations (key-image index, keypoint index)."""

    def __init__(self) -> None:
        self.xyz = np.zeros((0, 3))
        self.rgb = np.zeros((0, 3), np.uint8)
        self.fixed_flags = np.zeros(0, bool)
        self.confirmed_flags = np.zeros(0, bool)
        self.verified_flags = np.zeros(0, bool)
        self.obs: list[list[tuple[int, int]]] = []
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def fixed(self) -> np.ndarray:
        """(P,) bool: points taken from the BIM model (held fixed in bundle adjustment)."""
        return self.fixed_flags[: self._n]

    @property
    def confirmed(self) -> np.ndarray:
        """(P,) bool: points seen consistently from two viewpoints (BIM-depth points start unconfirmed)."""
        return self.confirmed_flags[: self._n]

    @property
    def verified(self) -> np.ndarray:
        """(P,) bool: points from epipolar-guided matching (densification), free of repeated-texture mismatches."""
        return self.verified_flags[: self._n]

    def add(
        self,
        xyz: np.ndarray,
        rgb: np.ndarray,
        obs: list[list[tuple[int, int]]],
        fixed: bool = False,
        confirmed: bool = True,
        verified: bool = False,
    ) -> np.ndarray:
        """Append points (P, 3) with colours (P, 3) and observations; returns their ids (P,)."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        n = len(xyz)
        if self._n + n > len(self.xyz):
            cap = max(2 * len(self.xyz), self._n + n, 256)
            grown = np.zeros((cap, 3))
            grown[: self._n] = self.xyz[: self._n]
            rgb_grown = np.zeros((cap, 3), np.uint8)
            rgb_grown[: self._n] = self.rgb[: self._n]
            fixed_grown = np.zeros(cap, bool)
            fixed_grown[: self._n] = self.fixed_flags[: self._n]
            conf_grown = np.zeros(cap, bool)
            conf_grown[: self._n] = self.confirmed_flags[: self._n]
            ver_grown = np.zeros(cap, bool)
            ver_grown[: self._n] = self.verified_flags[: self._n]
            self.xyz, self.rgb, self.fixed_flags, self.confirmed_flags = grown, rgb_grown, fixed_grown, conf_grown
            self.verified_flags = ver_grown
        ids = np.arange(self._n, self._n + n)
        self.xyz[ids] = xyz
        self.rgb[ids] = np.asarray(rgb, np.uint8).reshape(-1, 3)
        self.fixed_flags[ids] = fixed
        self.confirmed_flags[ids] = confirmed
        self.verified_flags[ids] = verified
        self.obs.extend(obs)
        self._n += n
        return ids

    def points(self) -> np.ndarray:
        return self.xyz[: self._n]

    def colors(self) -> np.ndarray:
        return self.rgb[: self._n]


# ---------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------


def _project(intr: Intrinsics, camera_from_world: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return cam.project_points(intr, camera_from_world, pts)


def _with_focal(intr: Intrinsics, f_px: float) -> Intrinsics:
    return Intrinsics(
        width_px=intr.width_px,
        height_px=intr.height_px,
        f_px=float(f_px),
        cx_px=intr.cx_px,
        cy_px=intr.cy_px,
        k1=intr.k1,
        k2=intr.k2,
        fy_over_fx=intr.fy_over_fx,
    )


def rays_from_pixels(intr: Intrinsics, world_from_camera: np.ndarray, pixels_px: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N, 3) in world coordinates of pixels (N, 2)."""
    xy = cam.pixels_to_normalized(intr, pixels_px)
    d = np.c_[xy, np.ones(len(xy))]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d @ np.asarray(world_from_camera)[:3, :3].T


def _rot_residuals(params: np.ndarray, rays_cam0: np.ndarray, px: np.ndarray, intr: Intrinsics, solve_f: bool):
    R = cam.rodrigues_to_matrix(params[:3])
    f = float(np.exp(params[3])) if solve_f else intr.f_px
    d = rays_cam0 @ R.T
    z = np.where(d[:, 2] > 1e-6, d[:, 2], 1e-6)
    xy = cam.distort_normalized(d[:, :2] / z[:, None], intr.k1, intr.k2)
    return (xy * f + np.array([intr.cx_px, intr.cy_px]) - px).ravel()


def fit_rotation_focal(
    rays_in_world: np.ndarray,
    pixels_px: np.ndarray,
    intr: Intrinsics,
    camera_from_world_rotation0: np.ndarray,
    solve_focal: bool = True,
) -> tuple[np.ndarray, Intrinsics, np.ndarray]:
    """Camera rotation and focal about a known centre from rays (N, 3, world) seen at pixels (N, 2).

    Levenberg-Marquardt from ``camera_from_world_rotation0`` (3, 3) and ``intr.f_px``. Returns the rotation
    ``camera_from_world`` (3, 3), the intrinsics with the new focal and per-point residuals (N,) in pixels.
    """
    R0 = np.asarray(camera_from_world_rotation0, np.float64)
    rays_cam0 = rays_in_world @ R0.T
    x0 = np.zeros(4 if solve_focal else 3)
    if solve_focal:
        x0[3] = np.log(intr.f_px)
    sol = least_squares(_rot_residuals, x0, method="lm", args=(rays_cam0, pixels_px, intr, solve_focal), x_scale="jac")
    R = cam.rodrigues_to_matrix(sol.x[:3]) @ R0
    f = float(np.exp(sol.x[3])) if solve_focal else intr.f_px
    res = _rot_residuals(sol.x, rays_cam0, pixels_px, intr, solve_focal).reshape(-1, 2)
    return R, _with_focal(intr, f), np.linalg.norm(res, axis=1)


def _pose_residuals(params: np.ndarray, pts: np.ndarray, px: np.ndarray, intr: Intrinsics, solve_f: bool):
    R = cam.rodrigues_to_matrix(params[:3])
    f = float(np.exp(params[6])) if solve_f else intr.f_px
    p = pts @ R.T + params[3:6]
    z = np.where(p[:, 2] > 1e-6, p[:, 2], 1e-6)
    xy = cam.distort_normalized(p[:, :2] / z[:, None], intr.k1, intr.k2)
    return (xy * f + np.array([intr.cx_px, intr.cy_px]) - px).ravel()


def refine_pose_focal(
    points_in_world: np.ndarray,
    pixels_px: np.ndarray,
    intr: Intrinsics,
    world_from_camera: np.ndarray,
    solve_focal: bool = True,
    robust_px: float | None = 2.0,
) -> tuple[np.ndarray, Intrinsics, np.ndarray]:
    """LM refinement of a 6-DOF pose (and focal) on 2D-3D correspondences (N, 3) <-> (N, 2).

    ``robust_px`` sets a soft-L1 loss scale (None: plain least squares). Returns ``world_from_camera`` (4, 4),
    intrinsics and per-point residuals (N,) in pixels.
    """
    T = cam.invert_rigid(np.asarray(world_from_camera, np.float64))
    x0 = np.concatenate([cam.matrix_to_rodrigues(T[:3, :3]), T[:3, 3]] + ([[np.log(intr.f_px)]] if solve_focal else []))
    args = (points_in_world, pixels_px, intr, solve_focal)
    if robust_px is None:
        sol = least_squares(_pose_residuals, x0, method="lm", args=args, x_scale="jac")
    else:
        sol = least_squares(
            _pose_residuals, x0, method="trf", loss="soft_l1", f_scale=robust_px, args=args, x_scale="jac", max_nfev=50
        )
    R = cam.rodrigues_to_matrix(sol.x[:3])
    f = float(np.exp(sol.x[6])) if solve_focal else intr.f_px
    res = _pose_residuals(sol.x, points_in_world, pixels_px, intr, solve_focal).reshape(-1, 2)
    return cam.invert_rigid(cam.rigid(R, sol.x[3:6])), _with_focal(intr, f), np.linalg.norm(res, axis=1)


def triangulate_pairs(
    intr_a: Intrinsics,
    world_from_a: np.ndarray,
    px_a: np.ndarray,
    intr_b: Intrinsics,
    world_from_b: np.ndarray,
    px_b: np.ndarray,
    min_angle_deg: float,
    max_error_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint-free linear (DLT) triangulation of matched pixels (N, 2) seen by two cameras.

    Returns points (N, 3) in world metres and a validity mask (N,): rays at least ``min_angle_deg`` apart,
    in front of both cameras, reprojection error below ``max_error_px`` in both.
    """
    n = len(px_a)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    Ta = cam.invert_rigid(world_from_a)[:3]
    Tb = cam.invert_rigid(world_from_b)[:3]
    xa = cam.pixels_to_normalized(intr_a, px_a)
    xb = cam.pixels_to_normalized(intr_b, px_b)
    X = cv2.triangulatePoints(Ta, Tb, xa.T.astype(np.float64), xb.T.astype(np.float64))
    w = X[3]
    ok = np.abs(w) > 1e-12
    pts = np.full((n, 3), np.nan)
    pts[ok] = (X[:3, ok] / w[ok]).T
    ray_a = pts - world_from_a[:3, 3]
    ray_b = pts - world_from_b[:3, 3]
    na, nb = np.linalg.norm(ray_a, axis=1), np.linalg.norm(ray_b, axis=1)
    baseline = np.linalg.norm(world_from_a[:3, 3] - world_from_b[:3, 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosang = np.sum(ray_a * ray_b, axis=1) / (na * nb)
    angle_ok = (
        (baseline > 1e-9)
        & (na > 1e-6 * baseline)
        & (nb > 1e-6 * baseline)
        & (cosang < np.cos(np.radians(min_angle_deg)))
    )
    pa, za = _project(intr_a, Ta, pts)
    pb, zb = _project(intr_b, Tb, pts)
    with np.errstate(invalid="ignore"):
        err = np.maximum(np.linalg.norm(pa - px_a, axis=1), np.linalg.norm(pb - px_b, axis=1))
        valid = ok & angle_ok & (za > 0) & (zb > 0) & (err < max_error_px) & np.all(np.isfinite(pts), axis=1)
    return pts, valid


def standing_elements(tasks, element_ids) -> Callable[[int], set[str] | None]:
    """``elements_at(t_ns)`` for :class:`MeshDepthLookup`: elements standing at a time by the schedule.

    Actual dates win over planned ones; complete, under-demolition and unscheduled elements stand. Elements
    under construction are left out (their full geometry would hide what is really visible behind them).
    With no tasks every element stands (returns None).
    """
    from constructaide import schedule4d

    windows = schedule4d.element_windows(tasks)
    ids = list(element_ids)
    if not windows:
        return lambda t_ns: None

    def elements_at(t_ns: int) -> set[str]:
        out = set()
        for gid in ids:
            w = windows.get(gid)
            state = schedule4d.actual_state(w, t_ns) or schedule4d.planned_state(w, t_ns)
            if state in ("complete", "under_demolition", "unscheduled"):
                out.add(gid)
        return out

    return elements_at


class MeshDepthLookup:
    """Depth of a triangle mesh (world metres) at pixels: an OpenGL depth render (pyrender, headless EGL).

    Implements :data:`DepthLookup`. ``meshes``: ``{name: (vertices (N, 3), faces (M, 3))}``; ``elements_at(t_ns)``
    names the meshes standing at a time (None: all); ``ground_height_m`` adds the terrain as a horizontal plane
    (z up), which hides buried footings and gives ground features their depth. Pixels are
    undistorted before the lookup; pixels on depth discontinuities (3x3 neighbourhood spread above
    ``max_relative_spread`` of the depth) get NaN, so silhouette features do not take the background's depth.
    The renderer is created lazily and must be used from one thread (the node's worker thread).
    """

    def __init__(
        self,
        meshes: dict[str, tuple[np.ndarray, np.ndarray]],
        elements_at: Callable[[int], set[str] | None] | None = None,
        max_relative_spread: float = 0.03,
        ground_height_m: float | None = None,
        ground_extent_m: float = 300.0,
    ) -> None:
        self.meshes = {
            name: (np.asarray(v, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3))
            for name, (v, f) in meshes.items()
            if len(v) and len(f)
        }
        if not self.meshes:
            raise ValueError("the BIM model has no triangles to look depth up in")
        self.elements_at = elements_at
        self.max_relative_spread = max_relative_spread
        self.ground: tuple[np.ndarray, np.ndarray] | None = None
        if ground_height_m is not None:
            all_v = np.vstack([v for v, _ in self.meshes.values()])
            cx, cy = (all_v[:, 0].min() + all_v[:, 0].max()) / 2, (all_v[:, 1].min() + all_v[:, 1].max()) / 2
            e = ground_extent_m
            gv = np.array([[cx - e, cy - e], [cx + e, cy - e], [cx + e, cy + e], [cx - e, cy + e]])
            self.ground = (np.c_[gv, np.full(4, ground_height_m)], np.array([[0, 1, 2], [0, 2, 3]]))
        self._scene = None
        self._scene_key: frozenset[str] | None = None
        self._renderer = None
        self._size = (0, 0)

    def _scene_for(self, names: frozenset[str]):
        import pyrender
        import trimesh

        if self._scene is None or self._scene_key != names:
            verts, faces, off = [], [], 0
            parts = [self.meshes[n] for n in sorted(names)] + ([self.ground] if self.ground is not None else [])
            for v, f in parts:
                verts.append(v)
                faces.append(f + off)
                off += len(v)
            self._scene = pyrender.Scene()
            if verts:
                mesh = trimesh.Trimesh(vertices=np.vstack(verts), faces=np.vstack(faces), process=False)
                self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
            self._scene_key = names
        return self._scene

    def depth_map(self, world_from_camera: np.ndarray, intr: Intrinsics, capture_time_ns: int = 0) -> np.ndarray:
        """(H, W) float32 camera-z depth in metres of an undistorted pinhole render (0 where nothing is hit).

        Only the elements standing at ``capture_time_ns`` (``elements_at``; all when it is None) are drawn.
        """
        import pyrender

        present = self.elements_at(capture_time_ns) if self.elements_at is not None else None
        names = frozenset(self.meshes) if present is None else frozenset(n for n in self.meshes if n in present)
        if not names:
            return np.zeros((intr.height_px, intr.width_px), np.float32)
        scene = self._scene_for(names)
        size = (intr.width_px, intr.height_px)
        if self._renderer is None or self._size != size:
            if self._renderer is not None:
                self._renderer.delete()
            self._renderer = offscreen_renderer(*size)
            self._size = size
        parts = [self.meshes[n][0] for n in names] + ([self.ground[0]] if self.ground is not None else [])
        far = max(float(np.max(np.linalg.norm(v - world_from_camera[:3, 3], axis=1))) for v in parts) * 1.1 + 1.0
        camera = pyrender.IntrinsicsCamera(
            fx=intr.f_px, fy=cam.focal_xy(intr)[1], cx=intr.cx_px + 0.5, cy=intr.cy_px + 0.5, znear=0.05, zfar=far
        )
        gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
        node = scene.add(camera, pose=np.asarray(world_from_camera, np.float64) @ gl_from_cv)
        try:
            depth = self._renderer.render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
        finally:
            scene.remove_node(node)
        return np.asarray(depth, np.float32)

    def __call__(
        self, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray, capture_time_ns: int = 0
    ) -> np.ndarray:
        px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
        out = np.full(len(px), np.nan)
        if len(px) == 0:
            return out
        pinhole = Intrinsics(
            width_px=intr.width_px,
            height_px=intr.height_px,
            f_px=intr.f_px,
            cx_px=intr.cx_px,
            cy_px=intr.cy_px,
            fy_over_fx=intr.fy_over_fx,
        )
        depth = self.depth_map(world_from_camera, pinhole, capture_time_ns)
        lo = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32), np.ones((3, 3), np.uint8))
        hi = cv2.dilate(depth, np.ones((3, 3), np.uint8))
        undist = cam.normalized_to_pixels(pinhole, cam.pixels_to_normalized(intr, px))
        uv = np.round(undist).astype(int)
        h, w = depth.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        u, v = uv[inside, 0], uv[inside, 1]
        d, d_lo, d_hi = depth[v, u], lo[v, u], hi[v, u]
        ok = (d > 0) & np.isfinite(d_lo) & (d_hi - d_lo <= self.max_relative_spread * d)
        vals = np.where(ok, d, np.nan)
        out[np.nonzero(inside)[0]] = vals
        return out

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None


# ---------------------------------------------------------------------------
# The registrar
# ---------------------------------------------------------------------------


class StreamingRegistrar:
    """Registers photos one at a time (see the module docstring for the paths).

    ``depth_lookup`` (optional) gives 3D points to features lying on the BIM model; it can be replaced at any
    time (BIM updates never trigger re-registration).
    """

    def __init__(self, config: StreamConfig | None = None, depth_lookup: DepthLookup | None = None, site: str = "demo"):
        self.config = config or StreamConfig()
        self.depth_lookup = depth_lookup
        self.site = site
        self.keys: list[KeyImage] = []
        self.key_index: dict[str, int] = {}
        self.map = PointMap()
        self.tracks: dict[str, TrackState] = {}
        self.poses: dict[str, PoseRecord] = {}
        self.by_camera: dict[str, list[str]] = {}
        self.viewpoints = ViewpointGraph(
            min_inlier_ratio=self.config.homography_min_inlier_ratio,
            min_matches=self.config.min_matches,
            max_neighbours=self.config.viewpoint_max_neighbours,
        )
        self.depth_error = ""
        """Why the depth lookup was switched off (empty while it works)."""
        self._vocab: np.ndarray | None = None
        self._vocab_built_at = 0

    # -- queries -----------------------------------------------------------

    @property
    def num_registered(self) -> int:
        return len(self.poses)

    def has_registrations(self) -> bool:
        return bool(self.keys)

    def click_disagreement_px(self, photo_id: str, pixels_px: np.ndarray, points_in_world: np.ndarray) -> float:
        """Median distance (px) between clicked pixels (N, 2) and their model points (N, 3) projected under the
        registered pose of ``photo_id`` (inf for points behind the camera). Raises KeyError when it is not
        registered."""
        rec = self.poses[photo_id]
        return cam.median_click_error_px(rec.intrinsics, rec.world_from_camera, pixels_px, points_in_world)

    def sparse_arrays(self) -> dict[str, np.ndarray | list[str]]:
        """Map arrays: ``points_xyz`` (P, 3) f32, ``colors_rgb`` (P, 3) u8, ``point_flags`` (P,) u8 (bits
        ``POINT_FROM_MODEL``, ``POINT_VERIFIED``, as in SparseCloud), ``obs_point`` / ``obs_photo`` (M,) i32,
        ``obs_pixel`` (M, 2) f32 and ``photo_ids`` (key images)."""
        obs_p, obs_i, obs_px = [], [], []
        for pid, obs in enumerate(self.map.obs):
            for ki, kp in obs:
                obs_p.append(pid)
                obs_i.append(ki)
                obs_px.append(self.keys[ki].feats.keypoints_px[kp])
        model_only = self.map.fixed & ~self.map.confirmed  # a BIM-depth point no second view has reproduced
        flags = model_only.astype(np.uint8) * POINT_FROM_MODEL + self.map.verified.astype(np.uint8) * POINT_VERIFIED
        return {
            "points_xyz": self.map.points().astype(np.float32),
            "colors_rgb": self.map.colors().astype(np.uint8),
            "point_flags": flags.astype(np.uint8),
            "obs_point": np.asarray(obs_p, np.int32),
            "obs_photo": np.asarray(obs_i, np.int32),
            "obs_pixel": np.asarray(obs_px, np.float32).reshape(-1, 2),
            "photo_ids": [k.photo_id for k in self.keys],
        }

    # -- public entry points -----------------------------------------------

    def register_anchor(
        self, photo: PhotoInput, pixels_px: np.ndarray, points_in_world: np.ndarray, focal_px: float | None = None
    ) -> Outcome:
        """Register a photo from user clicks (pixels (N, 2) <-> model points (N, 3)).

        Raises ``anchors.DegenerateAnchors`` (a ValueError) for unusable clicks.
        """
        t0 = time.perf_counter()
        gray = photo.image.gray()
        h, w = gray.shape
        sol = anchors.solve_anchor(pixels_px, points_in_world, w, h, focal_px=focal_px or photo.focal_px)
        flagged = int(np.sum(sol.outlier_mask)) if len(sol.outlier_mask) else 0
        msg = f"{len(sol.residuals_px)} clicks, RMS {sol.rms_px:.2f} px" + (
            f"; {flagged} click(s) look mis-placed (residual > {sol.outlier_threshold_px:.1f} px)" if flagged else ""
        )
        clicks = (np.asarray(pixels_px, float), np.asarray(points_in_world, float))
        if photo.photo_id in self.key_index:  # re-anchoring a key image: correct it in place
            key = self.keys[self.key_index[photo.photo_id]]
            key.intrinsics, key.world_from_camera = sol.intrinsics, sol.world_from_camera.copy()
            key.is_anchor, (key.clicks_px, key.clicks_world) = True, clicks
            msg += "; replaces the earlier registration"
        else:
            if photo.photo_id in self.poses:
                msg += "; replaces the earlier registration"
            key = self._add_key_image(
                photo, photo.image, sol.intrinsics, sol.world_from_camera, is_anchor=True, clicks=clicks
            )
        changed = self._link_key_image(key, photo.image)
        self._densify_key(self.key_index[photo.photo_id], photo.image)
        if photo.camera_id is not None:
            self._init_track(photo, sol.intrinsics, sol.world_from_camera)
        self._record(photo, sol.intrinsics, sol.world_from_camera, "anchor")
        reg = self._registration(
            photo,
            "anchor",
            "anchor",
            sol.intrinsics,
            sol.world_from_camera,
            len(sol.residuals_px),
            sol.rms_px,
            msg,
            t0,
            residuals=tuple(float(r) for r in sol.residuals_px),
        )
        return Outcome(reg, viewpoint_changed=changed, map_changed=True)

    def register(self, photo: PhotoInput) -> Outcome:
        """Register a photo without clicks: fast path for known fixed cameras, else the full path."""
        t0 = time.perf_counter()
        if photo.photo_id in self.poses:
            rec = self.poses[photo.photo_id]
            return Outcome(
                self._registration(
                    photo, "auto", rec.method, rec.intrinsics, rec.world_from_camera, 0, 0.0, "already registered", t0
                )
            )
        note = ""
        if photo.camera_id is not None and photo.camera_id in self.tracks:
            out, note = self._fast_path(photo, t0)
            if out is not None:
                return out
        if not self.keys:
            reason = "no registered images yet: anchor clicks are needed"
            return Outcome(self._failed(photo, reason, t0), needs_anchor=reason)
        return self._full_path(photo, t0, note)

    # -- fast path ---------------------------------------------------------

    def _init_track(self, photo: PhotoInput, intr: Intrinsics, world_from_camera: np.ndarray) -> None:
        c = self.config
        small = self._track_image(photo)
        w, h = intr.width_px, intr.height_px
        scale_xy = (small.shape[1] / w, small.shape[0] / h)
        corners = cv2.goodFeaturesToTrack(small, c.track_max_corners, 0.01, c.track_min_distance_small_px, blockSize=7)
        px_small = corners.reshape(-1, 2).astype(np.float64) if corners is not None else np.zeros((0, 2))
        px = (px_small + 0.5) / np.array(scale_xy) - 0.5
        rays = rays_from_pixels(intr, world_from_camera, px)
        pts = np.full((len(px), 3), np.nan)  # looked up lazily, only when the 6-DOF refinement needs them
        self.tracks[photo.camera_id] = TrackState(  # type: ignore[index]
            photo_id=photo.photo_id,
            gray_small=small,
            scale_xy=scale_xy,
            width_px=w,
            height_px=h,
            intrinsics=intr,
            world_from_camera=world_from_camera.copy(),
            center_in_world=world_from_camera[:3, 3].copy(),
            pixels_px=px,
            rays_in_world=rays,
            points_in_world=pts,
            num_initial=max(len(px), 1),
            capture_time_ns=photo.capture_time_ns,
        )

    def _track_image(self, photo: PhotoInput) -> np.ndarray:
        """Grey image at tracking scale, contrast-normalised (CLAHE) when ``track_normalize`` (day-to-day light)."""
        small = photo.image.gray_small(self.config.track_scale)
        if self.config.track_normalize:
            small = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(small)
        return small

    def _lookup_points(
        self, world_from_camera: np.ndarray, intr: Intrinsics, px: np.ndarray, capture_time_ns: int
    ) -> np.ndarray:
        pts = np.full((len(px), 3), np.nan)
        if self.depth_lookup is None or len(px) == 0:
            return pts
        try:
            depth = np.asarray(self.depth_lookup(world_from_camera, intr, px, capture_time_ns), np.float64).reshape(-1)
        except Exception as e:  # e.g. no EGL/OpenGL on this machine: register without BIM depth
            self.depth_error = f"BIM depth lookup disabled: {type(e).__name__}: {e}"
            self.depth_lookup = None
            return pts
        ok = np.isfinite(depth) & (depth > 0)
        xy = cam.pixels_to_normalized(intr, px[ok])
        p_cam = np.c_[xy, np.ones(len(xy))] * depth[ok, None]
        pts[ok] = p_cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
        return pts

    def _fast_path(self, photo: PhotoInput, t0: float) -> tuple[Outcome | None, str]:
        """Track the camera's previous frame into this one. Returns (outcome or None, why it was not used)."""
        c = self.config
        st = self.tracks[photo.camera_id]  # type: ignore[index]
        small = self._track_image(photo)
        if small.shape != st.gray_small.shape:
            return None, f"frame size changed ({small.shape[::-1]} at tracking scale vs {st.gray_small.shape[::-1]})"
        sx, sy = st.scale_xy
        to_small = np.array([sx, sy])
        p0 = ((st.pixels_px + 0.5) * to_small - 0.5).astype(np.float32).reshape(-1, 1, 2)
        if len(p0) < c.fast_min_inliers:
            return None, f"only {len(p0)} corners to track"
        lk = {
            "winSize": (c.klt_window_small_px, c.klt_window_small_px),
            "maxLevel": c.klt_levels,
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        }
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(st.gray_small, small, p0, None, **lk)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(small, st.gray_small, p1, None, **lk)
        fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) / sx
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < c.klt_fb_max_px)
        px1 = (p1.reshape(-1, 2).astype(np.float64) + 0.5) / to_small - 0.5
        inside = (px1[:, 0] >= 0) & (px1[:, 1] >= 0) & (px1[:, 0] <= st.width_px - 1) & (px1[:, 1] <= st.height_px - 1)
        ok &= inside
        n_ok = int(ok.sum())
        if n_ok < max(c.fast_min_inliers, c.fast_min_tracked_fraction * len(p0)):
            return None, f"camera bumped or view changed: only {n_ok} of {len(p0)} corners tracked"
        idx = np.nonzero(ok)[0]
        H, inl = cv2.findHomography(st.pixels_px[idx], px1[idx], cv2.RANSAC, c.fast_ransac_px, maxIters=2000)
        if H is None or inl is None or int(inl.sum()) < c.fast_min_inliers:
            return None, f"camera bumped or view changed: no consistent motion among {n_ok} tracked corners"
        h_inl = idx[inl.ravel().astype(bool)]
        # Initial rotation from the homography: H ~ K R_rel K^-1 for a rotating camera.
        K = cam.K_matrix(st.intrinsics)
        M = np.linalg.inv(K) @ H @ K
        U, _, Vt = np.linalg.svd(M / np.cbrt(np.linalg.det(M)))
        R_rel = U @ Vt
        if np.linalg.det(R_rel) < 0:
            R_rel = -R_rel
        R_prev = st.world_from_camera[:3, :3].T
        R0 = R_rel @ R_prev
        R, intr, _ = fit_rotation_focal(st.rays_in_world[h_inl], px1[h_inl], st.intrinsics, R0, c.fast_solve_focal)
        # Re-score all tracked corners under the fitted model, refit on the inliers.
        res_all = np.linalg.norm(
            _rot_residuals(np.zeros(3), st.rays_in_world[idx] @ R.T, px1[idx], intr, False).reshape(-1, 2), axis=1
        )
        inl2 = idx[res_all < c.fast_ransac_px]
        if len(inl2) >= c.fast_min_inliers:
            R, intr, res = fit_rotation_focal(st.rays_in_world[inl2], px1[inl2], intr, R, c.fast_solve_focal)
        else:
            res = res_all[res_all < c.fast_ransac_px]
        world_from_camera = cam.rigid(R.T, st.center_in_world)
        rms = float(np.sqrt(np.mean(res**2))) if len(res) else float("inf")
        method = "fastpath"
        if c.fast_model == "auto" and rms > 0.5 * c.fast_max_rms_px and self.depth_lookup is not None:
            # 3D points of the previous frame's corners (BIM depth seen from that frame), fetched only now.
            missing = inl2[~np.all(np.isfinite(st.points_in_world[inl2]), axis=1)]
            if len(missing):
                st.points_in_world[missing] = self._lookup_points(
                    st.world_from_camera, st.intrinsics, st.pixels_px[missing], st.capture_time_ns
                )
            has3d = inl2[np.all(np.isfinite(st.points_in_world[inl2]), axis=1)]
            if len(has3d) >= c.fast_min_inliers:
                T6, intr6, res6 = refine_pose_focal(
                    st.points_in_world[has3d], px1[has3d], intr, world_from_camera, c.fast_solve_focal
                )
                rms6 = float(np.sqrt(np.mean(res6**2)))
                if rms6 < 0.7 * rms:
                    world_from_camera, intr, res, rms, inl2 = T6, intr6, res6, rms6, has3d
                    method = "fastpath-6dof"
        if len(inl2) < c.fast_min_inliers or rms > c.fast_max_rms_px:
            return None, (
                f"camera bumped or moved: fast-path fit has {len(inl2)} inliers at RMS {rms:.2f} px "
                f"(limit {c.fast_max_rms_px} px)"
            )
        turned = cam.rotation_angle_deg(world_from_camera[:3, :3], st.world_from_camera[:3, :3])
        if turned > c.fast_max_rotation_deg:
            return None, f"camera re-aimed by {turned:.1f} deg since its previous frame"
        # Update the track: keep inliers at their predicted positions, replenish when thin.
        Tcw = cam.invert_rigid(world_from_camera)
        keep_px, _ = _project(intr, Tcw, st.center_in_world + st.rays_in_world[inl2])
        new_state = TrackState(
            photo_id=photo.photo_id,
            gray_small=small,
            scale_xy=st.scale_xy,
            width_px=st.width_px,
            height_px=st.height_px,
            intrinsics=intr,
            world_from_camera=world_from_camera,
            center_in_world=st.center_in_world,
            pixels_px=keep_px,
            rays_in_world=st.rays_in_world[inl2],
            points_in_world=st.points_in_world[inl2],
            num_initial=st.num_initial,
            capture_time_ns=photo.capture_time_ns,
        )
        if method == "fastpath-6dof":
            self._init_track(photo, intr, world_from_camera)  # new centre: rays must start from it
        else:
            if len(inl2) < c.replenish_fraction * st.num_initial:
                self._replenish(new_state)
            self.tracks[photo.camera_id] = new_state  # type: ignore[index]
        inlier_ratio = len(h_inl) / max(n_ok, 1)
        changed = self._record(photo, intr, world_from_camera, method, fast_ratio=(inlier_ratio, len(inl2)))
        note = f"tracked {n_ok}/{len(p0)} corners from {st.photo_id}"
        if method == "fastpath-6dof":
            moved = float(np.linalg.norm(world_from_camera[:3, 3] - st.center_in_world))
            note += f"; camera centre moved {moved:.2f} m"
        elif rms > 0.5 * c.fast_max_rms_px:
            note += "; residual suggests the camera centre moved (no BIM depth to check)"
        reg = self._registration(photo, "auto", method, intr, world_from_camera, len(inl2), rms, note, t0)
        return Outcome(reg, viewpoint_changed=changed), ""

    def _replenish(self, st: TrackState) -> None:
        c = self.config
        mask = np.full(st.gray_small.shape, 255, np.uint8)
        sx, sy = st.scale_xy
        for u, v in (st.pixels_px + 0.5) * np.array([sx, sy]) - 0.5:
            cv2.circle(mask, (int(round(u)), int(round(v))), int(c.track_min_distance_small_px), 0, -1)
        want = c.track_max_corners - len(st.pixels_px)
        if want <= 0:
            return
        corners = cv2.goodFeaturesToTrack(
            st.gray_small, want, 0.01, c.track_min_distance_small_px, mask=mask, blockSize=7
        )
        if corners is None:
            return
        px = (corners.reshape(-1, 2).astype(np.float64) + 0.5) / np.array([sx, sy]) - 0.5
        st.pixels_px = np.vstack([st.pixels_px, px])
        st.rays_in_world = np.vstack([st.rays_in_world, rays_from_pixels(st.intrinsics, st.world_from_camera, px)])
        st.points_in_world = np.vstack([st.points_in_world, np.full((len(px), 3), np.nan)])
        st.num_initial = max(st.num_initial, len(st.pixels_px))

    # -- full path ---------------------------------------------------------

    def _bow(self, feats: features.Features) -> np.ndarray | None:
        if self._vocab is None or len(feats) == 0:
            return None
        d = feats.descriptors
        # nearest word by dot product on unit RootSIFT descriptors
        words = np.argmax(d @ self._vocab.T, axis=1)
        hist = np.bincount(words, minlength=len(self._vocab)).astype(np.float64)
        hist = np.sqrt(hist)
        return hist / max(np.linalg.norm(hist), 1e-12)

    def _ensure_vocab(self) -> None:
        c = self.config
        if len(self.keys) <= c.max_candidates:
            return
        if self._vocab is not None and len(self.keys) < 2 * self._vocab_built_at:
            return
        rng = np.random.default_rng(0)
        sample = np.vstack([k.feats.descriptors[rng.permutation(len(k.feats))[:500]] for k in self.keys])
        k = min(c.vocabulary_size, len(sample) // 4)
        if k < 8:
            return
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-3)
        _, _, centers = cv2.kmeans(sample.astype(np.float32), k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
        self._vocab = centers / np.maximum(np.linalg.norm(centers, axis=1, keepdims=True), 1e-12)
        self._vocab_built_at = len(self.keys)
        for key in self.keys:
            key.bow = self._bow(key.feats)

    def _candidates(self, camera_id: str | None, feats: features.Features) -> list[int]:
        c = self.config
        same = [
            i
            for i in range(len(self.keys) - 1, -1, -1)
            if camera_id is not None and self.keys[i].camera_id == camera_id
        ]
        chosen = same[: max(1, c.max_candidates // 2)]
        rest = [i for i in range(len(self.keys)) if i not in chosen]
        if len(rest) > c.max_candidates - len(chosen):
            self._ensure_vocab()
            q = self._bow(feats)
            if q is not None:
                scores = [float(q @ self.keys[i].bow) if self.keys[i].bow is not None else 0.0 for i in rest]
                rest = [rest[j] for j in np.argsort(scores)[::-1]]
            else:
                rest = rest[::-1]
        return chosen + rest[: c.max_candidates - len(chosen)]

    def _full_path(self, photo: PhotoInput, t0: float, note: str) -> Outcome:
        c = self.config
        image = photo.image
        gray = image.gray()
        h, w = gray.shape
        feats = features.extract_features(gray, c.sift_max_features, c.sift_max_side_px)
        f0 = (
            photo.focal_px
            or self._camera_focal(photo.camera_id)
            or float(cam.focal_from_fov(w, anchors.DEFAULT_FOV_DEG))
        )
        intr0 = cam.centered_intrinsics(w, h, f0)
        known = self.tracks[photo.camera_id].intrinsics if photo.camera_id in self.tracks else None
        if known is not None and (known.width_px, known.height_px) == (w, h) and not photo.focal_px:
            intr0 = known  # a fixed camera's lens (focal, k1, k2) as last solved
        matches: dict[int, np.ndarray] = {}
        homographies: dict[int, tuple[np.ndarray | None, float, int]] = {}
        for ki in self._candidates(photo.camera_id, feats):
            key = self.keys[ki]
            m = features.match_features(feats, key.feats, c.match_ratio)
            if len(m) < c.min_matches:
                continue
            _, mask = features.filter_matches_fundamental(
                feats.keypoints_px, key.feats.keypoints_px, m, c.fundamental_px
            )
            # Homography on all ratio-test matches: a pure rotation leaves F undetermined.
            H_new_from_key, ratio = features.homography_inlier_ratio(
                key.feats.keypoints_px, feats.keypoints_px, m[:, ::-1], c.homography_px
            )
            homographies[ki] = (H_new_from_key, ratio, len(m))
            keep = m[mask] if mask.sum() >= c.min_matches and ratio < c.homography_min_inlier_ratio else m
            matches[ki] = keep
        prefix = (note + "; ") if note else ""
        # 2D-3D correspondences through the candidates' map points.
        kp_to_point: dict[int, int] = {}
        confirmed = self.map.confirmed
        for ki, m in matches.items():
            # Unconfirmed BIM-depth points only serve the camera that produced them (same centre: depth is moot).
            same_camera = photo.camera_id is not None and self.keys[ki].camera_id == photo.camera_id
            pids = self.keys[ki].point_ids[m[:, 1]]
            for kp, pid in zip(m[:, 0], pids, strict=True):
                if pid >= 0 and kp not in kp_to_point and (same_camera or confirmed[pid] or c.trust_bim_depth):
                    kp_to_point[int(kp)] = int(pid)
        num_tracks = len(kp_to_point)
        result = None
        rejected = ""
        method = "pnp"
        if num_tracks >= c.min_pnp_inliers:
            result = self._pnp(feats, kp_to_point, intr0, photo.focal_px is None)
            result, why = self._check_pnp(result, feats, matches)
            rejected += why
            if result is not None:
                why = self._gps_refusal(photo, result[1])
                if why:
                    result, rejected = None, rejected + f"; a PnP solution was rejected: {why}"
        if result is None:
            result, why = self._homography_transfer(feats, homographies, intr0, photo)
            rejected += why
            method = "homography"
        if result is None:
            reason = (
                f"{prefix}not registered: {num_tracks} matched 3D tracks (need {c.min_pnp_inliers}) and no registered "
                f"photo from the same viewpoint{rejected}; please click anchors"
            )
            return Outcome(self._failed(photo, reason, t0), needs_anchor=reason, num_matched_tracks=num_tracks)
        intr, world_from_camera, num_inliers, rms, inlier_kp = result
        key = self._add_key_image(photo, image, intr, world_from_camera, is_anchor=False, feats=feats)
        kidx = self.key_index[photo.photo_id]
        for kp in inlier_kp:
            pid = kp_to_point[int(kp)]
            key.point_ids[kp] = pid
            self.map.obs[pid].append((kidx, int(kp)))
        changed = self._link_key_image(key, image, matches, homographies)
        if c.local_ba and method == "pnp":
            self._local_ba(kidx, list(matches))
            intr, world_from_camera = key.intrinsics, key.world_from_camera
            rms = self._key_rms(kidx)
        self._densify_key(kidx, image)
        if photo.camera_id is not None:
            self._init_track(photo, intr, world_from_camera)
        changed += self._record(photo, intr, world_from_camera, method)
        msg = f"{prefix}full path: {method} with {num_inliers} inliers from {len(matches)} matched image(s)"
        reg = self._registration(photo, "auto", method, intr, world_from_camera, num_inliers, rms, msg, t0)
        return Outcome(reg, num_matched_tracks=num_tracks, viewpoint_changed=sorted(set(changed)), map_changed=True)

    def _check_pnp(self, result, feats: features.Features, matches: dict[int, np.ndarray]):
        """Refuse a PnP solution tilted too far from upright or explaining too few of the verified matches
        (``min_pose_pair_agreement``; a pose fitted to repeated texture disagrees with the other matches).
        Returns (result or None, why it was refused or "")."""
        if result is None:
            return None, ""
        if not self._upright(result[1]):
            return None, f"; a PnP solution tilted {self._tilt_deg(result[1]):.0f} deg from upright was rejected"
        agree = self._pose_pair_agreement(result[0], result[1], feats, matches)
        if agree < self.config.min_pose_pair_agreement:
            return None, f"; a PnP solution agreeing with only {agree:.0%} of the verified matches was rejected"
        return result, ""

    def _pose_pair_agreement(
        self, intr: Intrinsics, world_from_camera: np.ndarray, feats: features.Features, matches: dict[int, np.ndarray]
    ) -> float:
        """Fraction of the matches (new keypoint, key keypoint) to key images whose epipolar distance (px, in the
        new image) under the candidate pose is within 2 % of the width (1.0 without matches)."""
        thr_px = 2 * self.config.pnp_inlier_fraction_of_width * intr.width_px
        n_ok, n_all = 0, 0
        for ki, m in matches.items():
            o = self.keys[ki]
            xj = cam.pixels_to_normalized(o.intrinsics, o.feats.keypoints_px[m[:, 1]].astype(np.float64))
            xi = cam.pixels_to_normalized(intr, feats.keypoints_px[m[:, 0]].astype(np.float64))
            T = cam.invert_rigid(world_from_camera) @ o.world_from_camera  # new camera from key camera
            t = T[:3, 3]
            if np.linalg.norm(t) < 1e-9:
                continue  # same centre: no epipolar geometry
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            ln = np.c_[xj, np.ones(len(xj))] @ (tx @ T[:3, :3]).T
            d = np.abs(np.sum(ln[:, :2] * xi, axis=1) + ln[:, 2]) / np.maximum(np.linalg.norm(ln[:, :2], axis=1), 1e-12)
            n_ok += int(np.sum(d * intr.f_px < thr_px))
            n_all += len(m)
        return n_ok / n_all if n_all else 1.0

    @staticmethod
    def _tilt_deg(world_from_camera: np.ndarray) -> float:
        """Angle between the image's up direction (camera -y) and world up (+z), degrees."""
        up = -np.asarray(world_from_camera)[:3, 1]
        return float(np.degrees(np.arccos(np.clip(up[2] / np.linalg.norm(up), -1.0, 1.0))))

    def _upright(self, world_from_camera: np.ndarray) -> bool:
        limit = self.config.max_tilt_from_upright_deg
        return limit is None or self._tilt_deg(world_from_camera) <= limit

    def _camera_focal(self, camera_id: str | None) -> float | None:
        if camera_id is None or camera_id not in self.tracks:
            return None
        return self.tracks[camera_id].intrinsics.f_px

    def _pnp(self, feats: features.Features, kp_to_point: dict[int, int], intr0: Intrinsics, try_focals: bool):
        c = self.config
        kps = np.fromiter(kp_to_point.keys(), int)
        pts = self.map.points()[np.fromiter(kp_to_point.values(), int)]
        px = feats.keypoints_px[kps].astype(np.float64)
        thr = c.pnp_inlier_fraction_of_width * intr0.width_px
        best = None
        for scale in (1.0, 0.7, 1.4) if try_focals else (1.0,):
            intr = _with_focal(intr0, intr0.f_px * scale)
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                pts,
                px,
                cam.K_matrix(intr),
                np.array([intr.k1, intr.k2, 0.0, 0.0]),  # OpenCV's k1, k2 = the project's radial model
                iterationsCount=1000,
                reprojectionError=thr,
                confidence=0.999,
                flags=cv2.SOLVEPNP_SQPNP,
            )
            if ok and inl is not None and (best is None or len(inl) > len(best[2])):
                best = (intr, cam.invert_rigid(cam.rigid(cam.rodrigues_to_matrix(rvec), tvec)), inl.ravel())
            if best is not None and scale == 1.0 and len(best[2]) > 0.5 * len(kps):
                break
        if best is None or len(best[2]) < c.min_pnp_inliers:
            return None
        intr, world_from_camera, inl = best
        solve_f = len(inl) >= 30
        world_from_camera, intr, _ = refine_pose_focal(pts[inl], px[inl], intr, world_from_camera, solve_f)
        _, res_all = None, np.linalg.norm(_project(intr, cam.invert_rigid(world_from_camera), pts)[0] - px, axis=1)
        inl = np.nonzero(res_all < thr)[0]
        if len(inl) < c.min_pnp_inliers:
            return None
        world_from_camera, intr, res = refine_pose_focal(pts[inl], px[inl], intr, world_from_camera, solve_f)
        rms = float(np.sqrt(np.mean(res**2)))
        # Sanity: a real solution explains a fair share of the tracks and keeps the focal near a known prior.
        if len(inl) < c.min_pnp_inlier_fraction * len(kps):
            return None
        if not try_focals and abs(intr.f_px / intr0.f_px - 1) > c.max_focal_change:
            return None
        return intr, world_from_camera, len(inl), rms, kps[inl]

    def _homography_transfer(
        self,
        feats: features.Features,
        homographies: dict[int, tuple[np.ndarray | None, float, int]],
        intr0: Intrinsics,
        photo: PhotoInput | None = None,
    ):
        """First acceptable transfer over the key images ranked by homography support: (result or None, why
        transfers were refused by GPS or "")."""
        c = self.config
        ranked = sorted(homographies.items(), key=lambda kv: -kv[1][1] * kv[1][2])
        refused = ""
        for ki, (H, ratio, n) in ranked:
            if H is None or ratio < c.homography_min_inlier_ratio or n < c.min_matches:
                continue
            key = self.keys[ki]
            apart = self._gps_apart_m(photo, key.photo_id)
            if c.gps_max_homography_distance_m is not None and apart > c.gps_max_homography_distance_m:
                refused += f"; homography from {key.photo_id} refused: GPS positions {apart:.0f} m apart"
                continue
            result = self._homography_from_key(feats, key, H, intr0)
            if result is None:
                continue
            why = self._gps_refusal(photo, result[1])
            if why:
                refused += f"; homography from {key.photo_id} refused: {why}"
                continue
            return result, refused
        return None, refused

    def _gps_apart_m(self, photo: PhotoInput | None, other_id: str) -> float:
        """Horizontal distance (m) between a photo's GPS position and a registered photo's, NaN when unknown."""
        rec = self.poses.get(other_id)
        if photo is None or photo.gps is None or rec is None or rec.gps is None:
            return float("nan")
        return horizontal_distance_m(photo.gps, rec.gps)

    def _gps_refusal(self, photo: PhotoInput | None, world_from_camera: np.ndarray) -> str:
        """Why an automatic pose contradicts GPS ("" when it does not or cannot be told; sfm.gps_refusal against
        the registered photos with GPS)."""
        c = self.config
        if photo is None or photo.gps is None or c.gps_max_residual_m is None:
            return ""
        refs = [
            (rec.world_from_camera[:3, 3], rec.gps)
            for pid, rec in self.poses.items()
            if pid != photo.photo_id and rec.gps is not None
        ]
        if len(refs) < max(1, c.gps_min_references):
            return ""
        why, _ = gps_refusal(
            np.asarray(world_from_camera)[:3, 3],
            photo.gps,
            refs,
            c.gps_max_residual_m,
            c.gps_same_position_m,
            c.gps_min_fit_span_m,
            c.gps_sigma_m,
        )
        return why

    def _homography_from_key(self, feats: features.Features, key: KeyImage, H: np.ndarray, intr0: Intrinsics):
        """Transfer from one key image whose matches fit one homography ``H`` (key -> new): rotation + focal about
        the key's centre, else the key's warped anchor clicks; None when neither fits."""
        c = self.config
        _, dev = rotation_deviation(H, key.intrinsics, intr0.cx_px, intr0.cy_px)
        if dev > c.homography_max_rotation_deviation:
            return None  # a plane seen from another centre, not the same viewpoint
        # Rotation + focal about the key image's centre, from the key's keypoint rays and H-consistent matches.
        m = features.match_features(feats, key.feats, c.match_ratio)
        pk = key.feats.keypoints_px[m[:, 1]].astype(np.float64)
        pn = feats.keypoints_px[m[:, 0]].astype(np.float64)
        proj = cv2.perspectiveTransform(pk.reshape(-1, 1, 2), H).reshape(-1, 2)
        good = np.linalg.norm(proj - pn, axis=1) < c.homography_px
        if good.sum() >= c.min_matches:
            rays = rays_from_pixels(key.intrinsics, key.world_from_camera, pk[good])
            K_key = cam.K_matrix(key.intrinsics)
            intr_init = _with_focal(intr0, key.intrinsics.f_px * intr0.width_px / key.intrinsics.width_px)
            M = np.linalg.inv(cam.K_matrix(intr_init)) @ H @ K_key
            U, _, Vt = np.linalg.svd(M / np.cbrt(np.linalg.det(M)))
            R_rel = U @ Vt
            if np.linalg.det(R_rel) < 0:
                R_rel = -R_rel
            R0 = R_rel @ key.world_from_camera[:3, :3].T
            R, intr, res = fit_rotation_focal(rays, pn[good], intr_init, R0, True)
            inl = res < c.homography_px
            if inl.sum() >= c.min_matches:
                R, intr, res = fit_rotation_focal(rays[inl], pn[good][inl], intr, R, True)
                rms = float(np.sqrt(np.mean(res**2)))
                if rms <= c.homography_max_rms_px:
                    return intr, cam.rigid(R.T, key.world_from_camera[:3, 3]), int(inl.sum()), rms, np.zeros(0, int)
        # Paper's transfer: warp the anchor clicks by H and solve from them.
        if key.is_anchor and len(key.clicks_px) >= anchors.MIN_CLICKS:
            warped = cv2.perspectiveTransform(key.clicks_px.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
            inside = (
                (warped[:, 0] >= 0)
                & (warped[:, 1] >= 0)
                & (warped[:, 0] <= intr0.width_px - 1)
                & (warped[:, 1] <= intr0.height_px - 1)
            )
            if inside.sum() >= anchors.MIN_CLICKS:
                try:
                    sol = anchors.solve_anchor(
                        warped[inside],
                        key.clicks_world[inside],
                        intr0.width_px,
                        intr0.height_px,
                        focal_px=intr0.f_px,
                    )
                except anchors.DegenerateAnchors:
                    return None
                return sol.intrinsics, sol.world_from_camera, int(inside.sum()), sol.rms_px, np.zeros(0, int)
        return None

    # -- map maintenance -----------------------------------------------------

    def _add_key_image(
        self,
        photo: PhotoInput,
        image: FrameImage,
        intr: Intrinsics,
        world_from_camera: np.ndarray,
        is_anchor: bool,
        feats: features.Features | None = None,
        clicks: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> KeyImage:
        c = self.config
        if feats is None:
            feats = features.extract_features(image.gray(), c.sift_max_features, c.sift_max_side_px)
        key = KeyImage(
            photo_id=photo.photo_id,
            camera_id=photo.camera_id,
            intrinsics=intr,
            world_from_camera=np.asarray(world_from_camera, float).copy(),
            feats=feats,
            point_ids=np.full(len(feats), -1, np.int64),
            is_anchor=is_anchor,
            capture_time_ns=photo.capture_time_ns,
        )
        if clicks is not None:
            key.clicks_px, key.clicks_world = clicks
        key.bow = self._bow(feats)
        self.key_index[photo.photo_id] = len(self.keys)
        self.keys.append(key)
        return key

    def _colors_at(self, image: FrameImage, px: np.ndarray) -> np.ndarray:
        bgr = image.bgr()
        h, w = bgr.shape[:2]
        uv = np.clip(np.round(px).astype(int), 0, [w - 1, h - 1])
        return bgr[uv[:, 1], uv[:, 0], ::-1]

    def _link_key_image(
        self,
        key: KeyImage,
        image: FrameImage,
        matches: dict[int, np.ndarray] | None = None,
        homographies: dict[int, tuple[np.ndarray | None, float, int]] | None = None,
    ) -> list[str]:
        """Give a new key image 3D points (depth lookup, triangulation) and viewpoint edges. Returns changed ids."""
        c = self.config
        kidx = self.key_index[key.photo_id]
        changed = [key.photo_id]
        self.viewpoints.add_photo(key.photo_id)
        kp = key.feats.keypoints_px.astype(np.float64)
        if matches is None:
            matches, homographies = {}, {}
            for ki in self._candidates(key.camera_id, key.feats):
                if ki == kidx:
                    continue
                other = self.keys[ki]
                m = features.match_features(key.feats, other.feats, c.match_ratio)
                if len(m) < c.min_matches:
                    continue
                _, mask = features.filter_matches_fundamental(kp, other.feats.keypoints_px, m, c.fundamental_px)
                H, ratio = features.homography_inlier_ratio(other.feats.keypoints_px, kp, m[:, ::-1], c.homography_px)
                homographies[ki] = (H, ratio, len(m))
                matches[ki] = m[mask] if mask.sum() >= c.min_matches else m
        assert homographies is not None
        for ki, (H, ratio, n) in homographies.items():
            if H is None:
                continue
            _, dev = rotation_deviation(H, self.keys[ki].intrinsics, key.intrinsics.cx_px, key.intrinsics.cy_px)
            if dev > c.homography_max_rotation_deviation:
                continue
            if self.viewpoints.add_pair(key.photo_id, self.keys[ki].photo_id, H, ratio, n):
                changed.append(self.keys[ki].photo_id)
        # Existing points seen by this image through matches (anchors: attach as observations).
        for ki, m in matches.items():
            other = self.keys[ki]
            pids = other.point_ids[m[:, 1]]
            attach = (pids >= 0) & (key.point_ids[m[:, 0]] < 0)
            if key.is_anchor and attach.any():
                # Keep only observations consistent with the anchor pose.
                pts = self.map.points()[pids[attach]]
                proj, z = _project(key.intrinsics, cam.invert_rigid(key.world_from_camera), pts)
                err = np.linalg.norm(proj - kp[m[attach, 0]], axis=1)
                good = np.nonzero(attach)[0][(z > 0) & (err < c.max_triangulation_error_px * 2)]
                for j in good:
                    key.point_ids[m[j, 0]] = pids[j]
                    self.map.obs[pids[j]].append((kidx, int(m[j, 0])))
        # Depth lookup on the BIM for still-unassigned keypoints of anchors.
        if key.is_anchor and self.depth_lookup is not None:
            free = np.nonzero(key.point_ids < 0)[0]
            pts = self._lookup_points(key.world_from_camera, key.intrinsics, kp[free], key.capture_time_ns)
            ok = np.all(np.isfinite(pts), axis=1)
            if ok.any():
                ids = self.map.add(
                    pts[ok],
                    self._colors_at(image, kp[free[ok]]),
                    [[(kidx, int(i))] for i in free[ok]],
                    fixed=True,
                    confirmed=False,
                )
                key.point_ids[free[ok]] = ids
        # Triangulate new tracks with each matched key image.
        for ki, m in matches.items():
            other = self.keys[ki]
            free = (key.point_ids[m[:, 0]] < 0) & (other.point_ids[m[:, 1]] < 0)
            if free.sum() == 0:
                continue
            mf = m[free]
            pts, valid = self._triangulate(key, other, mf)
            if not valid.any():
                continue
            mv = mf[valid]
            obs = [[(kidx, int(a)), (ki, int(b))] for a, b in mv]
            ids = self.map.add(pts[valid], self._colors_at(image, kp[mv[:, 0]]), obs)
            key.point_ids[mv[:, 0]] = ids
            other.point_ids[mv[:, 1]] = ids
        self._confirm_points(key, matches)
        return changed

    def _densify_key(self, kidx: int, image: FrameImage) -> int:
        """Epipolar-guided matching of key image ``kidx`` with up to ``densify_pairs`` registered key images
        (nodes.register.densify; features already holding a point are left out); the new points enter the map as
        verified, with their observations extended to the other key images, and the map points ``kidx`` observes
        are verified (the flag is set when guided matching reproduces one of their matches). Returns how many
        points were added."""
        c = self.config
        if not c.densify or len(self.keys) < 2:
            return 0
        views = [
            View(
                k.intrinsics,
                k.world_from_camera,
                k.feats.keypoints_px.astype(np.float64),
                k.feats.descriptors,
                k.feats.scales,
                k.capture_time_ns,
            )
            for k in self.keys
        ]
        known_obs = [list(o) for o in self.map.obs]
        dense = densify(
            views, DensifyParams(pairs_per_view=c.densify_pairs), self.map.points(), known_obs, only_view=kidx
        )
        self.map.verified_flags[: len(self.map)] |= dense.known_verified  # blind tracks that guided matching confirms
        if dense.num_points == 0:
            return 0
        obs: list[list[tuple[int, int]]] = [[] for _ in range(dense.num_points)]
        for p, v, f in zip(dense.obs_point, dense.obs_view, dense.obs_feature, strict=True):
            if self.keys[int(v)].point_ids[int(f)] < 0:
                obs[int(p)].append((int(v), int(f)))
        keep = [i for i, o in enumerate(obs) if len(o) >= 2]
        if not keep:
            return 0
        rgb = []
        for i in keep:  # every new point comes from a pair of kidx's, so kidx observes it
            kp = next(f for v, f in obs[i] if v == kidx) if any(v == kidx for v, _ in obs[i]) else None
            px = self.keys[kidx].feats.keypoints_px[kp : kp + 1] if kp is not None else None
            rgb.append(self._colors_at(image, px.astype(np.float64))[0] if px is not None else np.full(3, 128))
        ids = self.map.add(dense.points_m[keep], np.array(rgb, np.uint8), [obs[i] for i in keep], verified=True)
        for pid, i in zip(ids, keep, strict=True):
            for v, f in obs[i]:
                self.keys[v].point_ids[f] = pid
        return len(keep)

    def _triangulate(self, key: KeyImage, other: KeyImage, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Two-view triangulation of matches ``m`` (M, 2) between two key images: points (M, 3) m, valid (M,)."""
        c = self.config
        return triangulate_pairs(
            key.intrinsics,
            key.world_from_camera,
            key.feats.keypoints_px[m[:, 0]].astype(np.float64),
            other.intrinsics,
            other.world_from_camera,
            other.feats.keypoints_px[m[:, 1]].astype(np.float64),
            c.min_triangulation_angle_deg,
            c.max_triangulation_error_px,
        )

    def _confirm_points(self, key: KeyImage, matches: dict[int, np.ndarray]) -> None:
        """Confirm BIM-depth points that a two-view triangulation reproduces (within ``confirm_tolerance``).

        A depth looked up on the model is wrong wherever something unmodelled (a fence, a crane, scaffolding)
        stands in front; such points must not register other viewpoints until a second view agrees.
        """
        c = self.config
        for ki, m in matches.items():
            other = self.keys[ki]
            ids_a, ids_b = key.point_ids[m[:, 0]], other.point_ids[m[:, 1]]
            has = (ids_a >= 0) | (ids_b >= 0)
            if not has.any():
                continue
            mh = m[has]
            tri, valid = self._triangulate(key, other, mh)
            rng = np.linalg.norm(tri - key.world_from_camera[:3, 3], axis=1)
            for ids in (ids_a[has], ids_b[has]):
                sel = valid & (ids >= 0)
                if not sel.any():
                    continue
                dist = np.linalg.norm(self.map.points()[ids[sel]] - tri[sel], axis=1)
                agree = dist < c.confirm_tolerance * rng[sel]
                self.map.confirmed_flags[ids[sel][agree]] = True

    def _key_rms(self, kidx: int) -> float:
        key = self.keys[kidx]
        has = np.nonzero(key.point_ids >= 0)[0]
        if len(has) == 0:
            return 0.0
        proj, _ = _project(
            key.intrinsics, cam.invert_rigid(key.world_from_camera), self.map.points()[key.point_ids[has]]
        )
        err = np.linalg.norm(proj - key.feats.keypoints_px[has], axis=1)
        err = err[np.isfinite(err)]
        err = err[err < self.config.pnp_inlier_fraction_of_width * key.intrinsics.width_px]
        return float(np.sqrt(np.mean(err**2))) if len(err) else 0.0

    def _local_ba(self, kidx: int, neighbour_idx: list[int]) -> None:
        """Local bundle adjustment (``bundle.bundle_adjust``) around a new key image.

        Unknowns: the new image's pose and focal, the poses of non-anchor neighbours when at least two anchors
        fix the gauge, and the points the new image sees (points seen by an anchor as depths along its ray).
        BIM-derived points stay fixed. Without enough gauge-fixing points (BIM points or points seen by two fixed
        cameras) the points stay fixed too, since a single fixed camera leaves the scale free.
        """
        c = self.config
        key = self.keys[kidx]
        pids = np.unique(key.point_ids[key.point_ids >= 0])
        if len(pids) < 10:
            return
        cams = [kidx] + [i for i in dict.fromkeys(neighbour_idx) if i != kidx]
        n_anchor = sum(self.keys[i].is_anchor for i in cams)
        pose_fixed = np.array([i != kidx and (self.keys[i].is_anchor or n_anchor < 2) for i in cams])
        cam_pos = {ki: j for j, ki in enumerate(cams)}
        o_cam, o_pt, o_px = [], [], []
        for j, p in enumerate(pids):
            for ki, kpi in self.map.obs[p]:
                if ki in cam_pos:
                    o_cam.append(cam_pos[ki])
                    o_pt.append(j)
                    o_px.append(self.keys[ki].feats.keypoints_px[kpi])
        o_cam_a, o_pt_a = np.asarray(o_cam, int), np.asarray(o_pt, int)
        model_fixed = self.map.fixed[pids]
        n_fixed_views = np.bincount(o_pt_a[pose_fixed[o_cam_a]], minlength=len(pids))
        anchored = model_fixed | (n_fixed_views >= 2)
        point_fixed = model_fixed.copy()
        if anchored.sum() < 10:
            point_fixed[:] = True
        ref_cam = np.full(len(pids), -1)
        ref_px = np.zeros((len(pids), 2))
        for j, p in enumerate(pids):
            if point_fixed[j]:
                continue
            for ki, kpi in self.map.obs[p]:
                if ki in cam_pos and self.keys[ki].is_anchor:
                    ref_cam[j] = cam_pos[ki]
                    ref_px[j] = self.keys[ki].feats.keypoints_px[kpi]
                    break
        intrs = [self.keys[i].intrinsics for i in cams]
        prob = bundle.BundleProblem(
            camera_from_world=np.stack([cam.invert_rigid(self.keys[i].world_from_camera) for i in cams]),
            f_px=np.array([k.f_px for k in intrs]),
            cx_px=np.array([k.cx_px for k in intrs]),
            cy_px=np.array([k.cy_px for k in intrs]),
            k1=np.array([k.k1 for k in intrs]),
            k2=np.array([k.k2 for k in intrs]),
            pose_fixed=pose_fixed,
            intrinsics_fixed=np.array([i != kidx or key.is_anchor for i in cams]),
            points_in_world=self.map.points()[pids].copy(),
            point_fixed=point_fixed,
            point_ref_cam=ref_cam,
            point_ref_px=ref_px,
            obs_cam=o_cam_a,
            obs_point=o_pt_a,
            obs_px=np.asarray(o_px, np.float64).reshape(-1, 2),
        )
        res = bundle.bundle_adjust(
            prob, bundle.BundleOptions(refine_distortion=False, max_nfev=c.local_ba_iterations, loss_scale_px=2.0)
        )
        if not np.isfinite(res.final_rms_px) or res.final_rms_px > res.initial_rms_px:
            return
        for j, ki in enumerate(cams):
            if pose_fixed[j]:
                continue
            self.keys[ki].world_from_camera = cam.invert_rigid(res.camera_from_world[j])
            rec = self.poses.get(self.keys[ki].photo_id)
            if rec is not None:
                rec.world_from_camera = self.keys[ki].world_from_camera
        key.intrinsics = _with_focal(key.intrinsics, float(res.f_px[0]))
        self.map.xyz[pids] = res.points_in_world

    # -- records and messages ------------------------------------------------

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
        if photo.photo_id not in changed:
            changed.insert(0, photo.photo_id)
        return changed

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
            reprojection_rms_px=float(rms),
            anchor_residuals_px=residuals,
            message=message,
            processing_ms=(time.perf_counter() - t0) * 1000.0,
        )

    def _failed(self, photo: PhotoInput, reason: str, t0: float) -> Registration:
        return self._registration(photo, "failed", "", None, None, 0, 0.0, reason, t0)
