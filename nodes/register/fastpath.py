"""Fast path for fixed cameras: a new frame registered by tracking the camera's previous frame (no SIFT).

The previous frame's corners (at ``track_scale`` of full resolution) are followed by pyramidal KLT with a
forward-backward check; a homography RANSAC rejects outliers; rotation and focal are refined about the camera's
centre (a mounted camera pans, tilts and zooms about its centre, so only each corner's viewing ray matters, not
its depth). With ``model="auto"``, a residual above half the limit fetches BIM depth for the corners and refines
the full 6-DOF pose + focal (a swayed mast). Too few tracked inliers, a high residual or a large rotation since
the previous frame means a bumped / re-aimed camera: the caller takes the full path.

Frames: ``world_from_camera`` (4, 4) OpenCV camera to world metres; pixels at full resolution, OpenCV convention.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import msgspec
import numpy as np

from constructaide import camera as cam
from nodes.register.photo import PhotoInput
from nodes.register.pose import (
    fit_rotation_about_centre,
    rays_from_pixels,
    refine_pose_focal,
    rotation_from_homography,
)
from schemas.messages import Intrinsics


class FastPathConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Options of the fast path (pixels are full-resolution pixels unless named ``_small``)."""

    track_scale: float = 0.5
    track_max_corners: int = 500
    track_min_distance_small_px: float = 10.0
    klt_window_small_px: int = 21
    klt_levels: int = 3
    klt_fb_max_px: float = 1.0
    track_normalize: bool = True
    ransac_px: float = 3.0
    min_inliers: int = 40
    min_tracked_fraction: float = 0.35
    max_rms_px: float = 2.0
    max_rotation_deg: float = 5.0
    solve_focal: bool = True
    model: Literal["rotation", "auto"] = "auto"
    """``auto``: when the rotation fit leaves more than half of ``max_rms_px``, corners with BIM-depth points
    refine the full 6-DOF pose + focal (a mast that swayed or a camera nudged along); ``rotation``: never."""
    replenish_fraction: float = 0.7


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
class FastResult:
    """A frame registered by the fast path: its camera, the fit (inliers, RMS px), the fraction of tracked corners
    the homography explained and a note for the registration message."""

    intrinsics: Intrinsics
    world_from_camera: np.ndarray
    method: str
    num_inliers: int
    rms_px: float
    inlier_ratio: float
    note: str


PointLookup = Callable[[np.ndarray, Intrinsics, np.ndarray, int], np.ndarray]
"""``lookup(world_from_camera, intrinsics, pixels_px (N, 2), capture_time_ns) -> points_in_world (N, 3)`` (NaN rows
where the model is not hit), or None when there is no model."""


class FastPath:
    """Per fixed camera, the latest frame's tracked corners (:class:`TrackState`)."""

    def __init__(self, config: FastPathConfig | None = None) -> None:
        self.config = config or FastPathConfig()
        self.tracks: dict[str, TrackState] = {}

    def _track_image(self, photo: PhotoInput) -> np.ndarray:
        """Grey image at tracking scale, contrast-normalised (CLAHE) when ``track_normalize`` (day-to-day light)."""
        small = photo.image.gray_small(self.config.track_scale)
        if self.config.track_normalize:
            small = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(small)
        return small

    def init_track(self, photo: PhotoInput, intr: Intrinsics, world_from_camera: np.ndarray) -> None:
        """Start (or restart) tracking camera ``photo.camera_id`` from this registered frame."""
        if photo.camera_id is None:
            return
        c = self.config
        small = self._track_image(photo)
        w, h = intr.width_px, intr.height_px
        scale_xy = (small.shape[1] / w, small.shape[0] / h)
        corners = cv2.goodFeaturesToTrack(small, c.track_max_corners, 0.01, c.track_min_distance_small_px, blockSize=7)
        px_small = corners.reshape(-1, 2).astype(np.float64) if corners is not None else np.zeros((0, 2))
        px = (px_small + 0.5) / np.array(scale_xy) - 0.5
        self.tracks[photo.camera_id] = TrackState(
            photo_id=photo.photo_id,
            gray_small=small,
            scale_xy=scale_xy,
            width_px=w,
            height_px=h,
            intrinsics=intr,
            world_from_camera=np.asarray(world_from_camera, np.float64).copy(),
            center_in_world=np.asarray(world_from_camera, np.float64)[:3, 3].copy(),
            pixels_px=px,
            rays_in_world=rays_from_pixels(intr, world_from_camera, px),
            points_in_world=np.full((len(px), 3), np.nan),  # looked up lazily, only when the 6-DOF fit needs them
            num_initial=max(len(px), 1),
            capture_time_ns=photo.capture_time_ns,
        )

    def track(self, photo: PhotoInput, lookup: PointLookup | None = None) -> tuple[FastResult | None, str]:
        """Track the camera's previous frame into this one. Returns (result or None, why it was not used)."""
        c = self.config
        st = self.tracks.get(photo.camera_id or "")
        if st is None:
            return None, "no tracked frame of this camera"
        small = self._track_image(photo)
        if small.shape != st.gray_small.shape:
            return None, f"frame size changed ({small.shape[::-1]} at tracking scale vs {st.gray_small.shape[::-1]})"
        sx, sy = st.scale_xy
        to_small = np.array([sx, sy])
        p0 = ((st.pixels_px + 0.5) * to_small - 0.5).astype(np.float32).reshape(-1, 1, 2)
        if len(p0) < c.min_inliers:
            return None, f"only {len(p0)} corners to track"
        win = (c.klt_window_small_px, c.klt_window_small_px)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            st.gray_small, small, p0, None, winSize=win, maxLevel=c.klt_levels, criteria=crit
        )
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
            small, st.gray_small, p1, None, winSize=win, maxLevel=c.klt_levels, criteria=crit
        )
        fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) / sx
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < c.klt_fb_max_px)
        px1 = (p1.reshape(-1, 2).astype(np.float64) + 0.5) / to_small - 0.5
        inside = (px1[:, 0] >= 0) & (px1[:, 1] >= 0) & (px1[:, 0] <= st.width_px - 1) & (px1[:, 1] <= st.height_px - 1)
        ok &= inside
        n_ok = int(ok.sum())
        if n_ok < max(c.min_inliers, c.min_tracked_fraction * len(p0)):
            return None, f"camera bumped or view changed: only {n_ok} of {len(p0)} corners tracked"
        idx = np.nonzero(ok)[0]
        H, inl = cv2.findHomography(st.pixels_px[idx], px1[idx], cv2.RANSAC, c.ransac_px, maxIters=2000)
        if H is None or inl is None or int(inl.sum()) < c.min_inliers:
            return None, f"camera bumped or view changed: no consistent motion among {n_ok} tracked corners"
        h_inl = idx[inl.ravel().astype(bool)]
        R0 = rotation_from_homography(H, st.intrinsics, st.intrinsics, cam.invert_rigid(st.world_from_camera))
        R, intr, _ = fit_rotation_about_centre(st.rays_in_world[h_inl], px1[h_inl], st.intrinsics, R0, c.solve_focal)
        # Re-score all tracked corners under the fitted model, refit on the inliers.
        Tcw = cam.rigid(R, -R @ st.center_in_world)
        proj, _ = cam.project_points(intr, Tcw, st.center_in_world + st.rays_in_world[idx])
        res_all = np.linalg.norm(proj - px1[idx], axis=1)
        inl2 = idx[res_all < c.ransac_px]
        if len(inl2) >= c.min_inliers:
            R, intr, res = fit_rotation_about_centre(st.rays_in_world[inl2], px1[inl2], intr, R, c.solve_focal)
        else:
            res = res_all[res_all < c.ransac_px]
        world_from_camera = cam.rigid(R.T, st.center_in_world)
        rms = float(np.sqrt(np.mean(res**2))) if len(res) else float("inf")
        method = "fastpath"
        if c.model == "auto" and rms > 0.5 * c.max_rms_px and lookup is not None:
            # 3D points of the previous frame's corners (BIM depth seen from that frame), fetched only now.
            missing = inl2[~np.all(np.isfinite(st.points_in_world[inl2]), axis=1)]
            if len(missing):
                st.points_in_world[missing] = lookup(
                    st.world_from_camera, st.intrinsics, st.pixels_px[missing], st.capture_time_ns
                )
            has3d = inl2[np.all(np.isfinite(st.points_in_world[inl2]), axis=1)]
            if len(has3d) >= c.min_inliers:
                T6, intr6, res6 = refine_pose_focal(
                    st.points_in_world[has3d], px1[has3d], intr, world_from_camera, c.solve_focal
                )
                rms6 = float(np.sqrt(np.mean(res6**2)))
                if rms6 < 0.7 * rms:
                    world_from_camera, intr, res, rms, inl2 = T6, intr6, res6, rms6, has3d
                    method = "fastpath-6dof"
        if c.model == "auto" and method == "fastpath" and rms > 0.5 * c.max_rms_px and lookup is None:
            # A rotation leaves more than a mount's jitter and no BIM depth can tell a moved centre: the full path
            # (its own anchor's clicks carried into the frame fix all six degrees of freedom).
            return None, f"camera centre may have moved: a rotation fits the tracked corners to {rms:.2f} px only"
        if len(inl2) < c.min_inliers or rms > c.max_rms_px:
            return None, (
                f"camera bumped or moved: fast-path fit has {len(inl2)} inliers at RMS {rms:.2f} px "
                f"(limit {c.max_rms_px} px)"
            )
        turned = cam.rotation_angle_deg(world_from_camera[:3, :3], st.world_from_camera[:3, :3])
        if turned > c.max_rotation_deg:
            return None, f"camera re-aimed by {turned:.1f} deg since its previous frame"
        note = f"tracked {n_ok}/{len(p0)} corners from {st.photo_id}"
        if method == "fastpath-6dof":
            moved = float(np.linalg.norm(world_from_camera[:3, 3] - st.center_in_world))
            note += f"; camera centre moved {moved:.2f} m"
            self.init_track(photo, intr, world_from_camera)  # new centre: rays must start from it
        else:
            if rms > 0.5 * c.max_rms_px:
                note += "; residual suggests the camera centre moved (BIM depth could not tell)"
            # Keep the inliers at their predicted positions, replenish when thin.
            keep_px, _ = cam.project_points(
                intr, cam.invert_rigid(world_from_camera), st.center_in_world + st.rays_in_world[inl2]
            )
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
            if len(inl2) < c.replenish_fraction * st.num_initial:
                self._replenish(new_state)
            self.tracks[photo.camera_id] = new_state  # type: ignore[index]
        ratio = len(h_inl) / max(n_ok, 1)
        return FastResult(intr, world_from_camera, method, len(inl2), rms, ratio, note), ""

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
