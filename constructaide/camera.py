"""Shared pure camera model and geometry (numpy only).

Frames: camera frame is OpenCV's (x right, y down, z forward); ``world_from_camera`` is a 4x4
rigid transform (camera coordinates -> world metres). ``camera_from_world`` is its inverse,
``[R | t]`` with ``x_cam = R @ x_world + t``. Pixels: (0, 0) is the centre of the top-left pixel.

Distortion: two-term radial (Brown) on normalised coordinates,
``x_d = x (1 + k1 r^2 + k2 r^4)``, then ``u = fx x_d + cx``, ``v = fy y_d + cy`` with ``fx = f_px`` and
``fy = f_px * fy_over_fx`` (square pixels: ``fy_over_fx = 1``, the default). Build K and map pixels through this
module (:func:`K_matrix`, :func:`focal_xy`, :func:`pixels_to_normalized`, :func:`normalized_to_pixels`) so that
the pixel aspect ratio is honoured everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from schemas.messages import Intrinsics, Registration

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class PinholeCamera:
    """A full camera: intrinsics and pose. ``world_from_camera`` is (4, 4)."""

    intrinsics: Intrinsics
    world_from_camera: F64

    @property
    def camera_from_world(self) -> F64:
        return invert_rigid(self.world_from_camera)

    @property
    def center_in_world_m(self) -> F64:
        return self.world_from_camera[:3, 3].copy()

    @property
    def viewing_direction_in_world(self) -> F64:
        """Unit optical axis (+z of the camera) in world coordinates."""
        return self.world_from_camera[:3, 2].copy()

    def project(self, points_in_world_m: ArrayLike) -> tuple[F64, F64]:
        """Project (N, 3) world points. Returns pixels (N, 2) and camera depths z (N,) in metres."""
        return project_points(self.intrinsics, self.camera_from_world, points_in_world_m)


def focal_xy(intr: Intrinsics) -> tuple[float, float]:
    """Horizontal and vertical focal lengths (fx, fy) in pixels."""
    return float(intr.f_px), float(intr.f_px * intr.fy_over_fx)


def K_matrix(intr: Intrinsics) -> F64:
    """3x3 calibration matrix (distortion not included)."""
    fx, fy = focal_xy(intr)
    return np.array([[fx, 0.0, intr.cx_px], [0.0, fy, intr.cy_px], [0.0, 0.0, 1.0]])


def centered_intrinsics(
    width_px: int, height_px: int, f_px: float, k1: float = 0.0, k2: float = 0.0, fy_over_fx: float = 1.0
) -> Intrinsics:
    """Intrinsics with the principal point at the image centre (OpenCV pixel convention)."""
    return Intrinsics(
        width_px=width_px,
        height_px=height_px,
        f_px=float(f_px),
        cx_px=(width_px - 1) / 2.0,
        cy_px=(height_px - 1) / 2.0,
        k1=float(k1),
        k2=float(k2),
        fy_over_fx=float(fy_over_fx),
    )


def scaled_intrinsics(intr: Intrinsics, width_px: int, height_px: int) -> Intrinsics:
    """Intrinsics of the same camera for its image resized to (width_px, height_px): fx scales with the width, fy
    with the height (a resize that changes the aspect changes ``fy_over_fx``); pixel centres map as
    ``u -> s (u + 0.5) - 0.5``. ValueError for a non-positive size or focal length."""
    if intr.width_px <= 0 or intr.height_px <= 0 or intr.f_px <= 0 or width_px <= 0 or height_px <= 0:
        raise ValueError(
            f"intrinsics need a positive image size and focal length, got {intr} -> {width_px}x{height_px}"
        )
    sx = width_px / intr.width_px
    sy = height_px / intr.height_px
    return Intrinsics(
        width_px=width_px,
        height_px=height_px,
        f_px=intr.f_px * sx,
        cx_px=sx * (intr.cx_px + 0.5) - 0.5,
        cy_px=sy * (intr.cy_px + 0.5) - 0.5,
        k1=intr.k1,
        k2=intr.k2,
        fy_over_fx=intr.fy_over_fx * sy / sx,
    )


def resized_pixels(pixels_px: ArrayLike, from_size: tuple[int, int], to_size: tuple[int, int]) -> F64:
    """Pixels (N, 2) of an image of ``from_size`` (width, height) in the same image resized to ``to_size``
    (pixel centres map as ``u -> s (u + 0.5) - 0.5``)."""
    px = np.asarray(pixels_px, np.float64).reshape(-1, 2)
    if tuple(from_size) == tuple(to_size):
        return px.copy()
    s = np.array([to_size[0] / from_size[0], to_size[1] / from_size[1]])
    return s * (px + 0.5) - 0.5


def focal_from_fov(width_px: int, fov_deg: float = 50.0) -> float:
    """Focal length in pixels for a horizontal field of view."""
    return 0.5 * width_px / np.tan(np.radians(fov_deg) / 2.0)


def focal_px_from_35mm(f35_mm: float, width_px: int, height_px: int) -> float:
    """Focal length in pixels from an EXIF 35 mm-equivalent focal length (FocalLengthIn35mmFilm).

    Uses the diagonal crop factor (36 x 24 mm frame diagonal 43.27 mm), as cameras and exiftool do, so it holds
    for any aspect ratio: ``f_px = f35_mm * hypot(width_px, height_px) / hypot(36, 24)``.
    """
    return float(f35_mm) * float(np.hypot(width_px, height_px)) / float(np.hypot(36.0, 24.0))


def distort_normalized(xy: F64, k1: float, k2: float) -> F64:
    """Apply radial distortion to (N, 2) normalised coordinates."""
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    return xy * (1.0 + k1 * r2 + k2 * r2 * r2)


def undistort_normalized(xy_d: F64, k1: float, k2: float, iterations: int = 20) -> F64:
    """Invert :func:`distort_normalized` by fixed-point iteration on (N, 2) coordinates."""
    if k1 == 0.0 and k2 == 0.0:
        return np.array(xy_d, dtype=np.float64)
    xy = np.array(xy_d, dtype=np.float64)
    for _ in range(iterations):
        r2 = np.sum(xy * xy, axis=-1, keepdims=True)
        xy = xy_d / (1.0 + k1 * r2 + k2 * r2 * r2)
    return xy


def pixels_to_normalized(intr: Intrinsics, pixels_px: ArrayLike, iterations: int = 20) -> F64:
    """Undistorted normalised image coordinates (N, 2) of pixels (N, 2) (``iterations`` of
    :func:`undistort_normalized`)."""
    px = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    xy_d = (px - np.array([intr.cx_px, intr.cy_px])) / np.array(focal_xy(intr))
    return undistort_normalized(xy_d, intr.k1, intr.k2, iterations)


def normalized_to_pixels(intr: Intrinsics, xy: ArrayLike) -> F64:
    """Pixels (N, 2) of undistorted normalised coordinates (N, 2), distortion applied."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    xy_d = distort_normalized(xy, intr.k1, intr.k2)
    return xy_d * np.array(focal_xy(intr)) + np.array([intr.cx_px, intr.cy_px])


def project_points(intr: Intrinsics, camera_from_world: F64, points_in_world_m: ArrayLike) -> tuple[F64, F64]:
    """Project (N, 3) world points through a (4, 4) or (3, 4) ``camera_from_world``.

    Returns pixels (N, 2) with distortion and depths z (N,); points with z <= 0 get NaN pixels.
    """
    pts = np.asarray(points_in_world_m, dtype=np.float64).reshape(-1, 3)
    p_cam = pts @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = p_cam[:, :2] / z[:, None]
    xy[z <= 0] = np.nan
    return normalized_to_pixels(intr, xy), z


def median_click_error_px(
    intr: Intrinsics, world_from_camera: F64, pixels_px: ArrayLike, points_in_world_m: ArrayLike
) -> float:
    """Median distance (px) between clicked pixels (N, 2) and their model points (N, 3) projected through the camera
    (points behind it count as infinitely far); NaN without clicks."""
    px = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    proj, _ = project_points(intr, invert_rigid(np.asarray(world_from_camera, dtype=np.float64)), points_in_world_m)
    e = np.linalg.norm(proj - px, axis=1)
    e[~np.isfinite(e)] = np.inf
    return float(np.median(e)) if len(e) else float("nan")


def rms_click_error_px(
    intr: Intrinsics, world_from_camera: F64, pixels_px: ArrayLike, points_in_world_m: ArrayLike
) -> float:
    """RMS distance (px) between clicked pixels (N, 2) and their model points (N, 3) projected through the camera."""
    px = np.asarray(pixels_px, dtype=np.float64).reshape(-1, 2)
    proj, _ = project_points(intr, invert_rigid(np.asarray(world_from_camera, dtype=np.float64)), points_in_world_m)
    return float(np.sqrt(np.mean(np.sum((proj - px) ** 2, axis=1))))


def invert_rigid(T: F64) -> F64:
    """Inverse of a (4, 4) rigid transform."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def rigid(R: ArrayLike, t: ArrayLike) -> F64:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def look_at(eye_m: ArrayLike, target_m: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> F64:
    """``world_from_camera`` (OpenCV frame) for a camera at ``eye_m`` looking at ``target_m``."""
    eye = np.asarray(eye_m, dtype=np.float64)
    z = np.asarray(target_m, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return rigid(np.stack([x, y, z], axis=1), eye)


def rodrigues_to_matrix(rvec: ArrayLike) -> F64:
    """(3, 3) rotation of an axis-angle vector (radians)."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = np.linalg.norm(r)
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def matrix_to_rodrigues(R: ArrayLike) -> F64:
    """Axis-angle vector (3,) of a rotation matrix."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    if theta < 1e-9:
        return np.zeros(3)
    if np.pi - theta < 1e-6:
        # Near 180 degrees: take the axis from the symmetric part.
        A = (R + np.eye(3)) / 2
        axis = A[:, np.argmax(np.diag(A))]
        axis /= np.linalg.norm(axis)
        return axis * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(theta))
    return w * theta


def pose_to_tuple(world_from_camera: F64) -> tuple[float, ...]:
    """Row-major 16-tuple for ``Registration.world_from_camera``."""
    return tuple(float(v) for v in np.asarray(world_from_camera, dtype=np.float64).reshape(16))


def pose_from_tuple(values: tuple[float, ...] | list[float]) -> F64:
    """(4, 4) array from a row-major 16-tuple."""
    if len(values) != 16:
        raise ValueError(f"world_from_camera needs 16 values, got {len(values)}")
    return np.asarray(values, dtype=np.float64).reshape(4, 4)


def registered_camera(reg: Registration) -> PinholeCamera | None:
    """The camera of a usable registration (not failed, with intrinsics and a 16-value pose), else None."""
    if reg.status == "failed" or reg.intrinsics is None or len(reg.world_from_camera) != 16:
        return None
    return PinholeCamera(reg.intrinsics, pose_from_tuple(reg.world_from_camera))


def rotation_angle_deg(R_a: ArrayLike, R_b: ArrayLike) -> float:
    """Angle of the relative rotation between two (3, 3) rotations, in degrees."""
    R = np.asarray(R_a) @ np.asarray(R_b).T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def viewing_angle_deg(world_from_camera_a: F64, world_from_camera_b: F64) -> float:
    """Angle between two cameras' optical axes in degrees (the paper's rotational error)."""
    a = world_from_camera_a[:3, 2]
    b = world_from_camera_b[:3, 2]
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def umeyama_similarity(src: ArrayLike, dst: ArrayLike) -> tuple[float, F64, F64]:
    """Similarity (s, R, t) minimising ``|dst - (s R src + t)|^2`` over (N, 3) point sets."""
    X = np.asarray(src, dtype=np.float64)
    Y = np.asarray(dst, dtype=np.float64)
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    cov = Yc.T @ Xc / len(X)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_x = (Xc**2).sum() / len(X)
    s = float(np.trace(np.diag(S) @ D) / var_x) if var_x > 0 else 1.0
    t = my - s * R @ mx
    return s, R, t
