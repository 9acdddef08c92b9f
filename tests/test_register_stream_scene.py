"""Seeded synthetic scene for the streaming-registration tests and bench: textured planes ray-cast into cameras.

World: z up, metres. A facade plane (y = 20, x in [-16, 16], z in [0, 14]), a ground plane (z = 0) and a
box in front of the facade, each with its own seeded texture. Renders are exact perspective projections
(no distortion) so poses recovered from them can be scored against the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from constructaide import camera as cam
from schemas.messages import Intrinsics

PX_PER_M = 60.0


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    img = np.zeros((h, w), np.float32)
    for sigma, amp in ((1.5, 0.5), (4.0, 0.8), (12.0, 1.0), (40.0, 1.0)):
        n = rng.standard_normal((h, w)).astype(np.float32)
        n = cv2.GaussianBlur(n, (0, 0), sigma)
        img += amp * n / (n.std() + 1e-6)
    for _ in range(h * w // 4000):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        s = int(rng.integers(4, 30))
        cv2.rectangle(img, (x, y), (x + s, y + int(rng.integers(4, 30))), float(rng.normal(0, 3)), -1)
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


@dataclass
class Plane:
    """Rectangle ``origin + a*u + b*v`` for a in [0, size_a], b in [0, size_b] (u, v orthonormal)."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    size_a: float
    size_b: float
    texture: np.ndarray
    tint: tuple[float, float, float]

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)


class PlaneScene:
    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        P = np.array
        self.planes: list[Plane] = []

        def add(origin, u, v, a, b, tint):
            tex = _texture(rng, int(b * PX_PER_M), int(a * PX_PER_M))
            self.planes.append(Plane(P(origin, float), P(u, float), P(v, float), a, b, tex, tint))

        add((-16, 20, 0), (1, 0, 0), (0, 0, 1), 32, 14, (1.0, 0.9, 0.8))  # facade
        add((-30, -10, 0), (1, 0, 0), (0, 1, 0), 60, 30, (0.6, 0.7, 0.6))  # ground up to the facade
        # box 4 x 3 x 3 m at x in [-2, 2], y in [12, 15]
        add((-2, 12, 0), (1, 0, 0), (0, 0, 1), 4, 3, (0.8, 0.6, 0.5))  # front face (y = 12)
        add((-2, 15, 0), (0, -1, 0), (0, 0, 1), 3, 3, (0.7, 0.6, 0.6))  # left face (x = -2)
        add((2, 12, 0), (0, 1, 0), (0, 0, 1), 3, 3, (0.7, 0.7, 0.5))  # right face (x = 2)
        add((-2, 12, 3), (1, 0, 0), (0, 1, 0), 4, 3, (0.9, 0.9, 0.9))  # top (z = 3)

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit per ray: distance t (N,) (inf = none), plane index (N,), plane coords a, b (N,)."""
        n = len(dirs)
        best_t = np.full(n, np.inf)
        best_i = np.full(n, -1)
        best_a = np.zeros(n)
        best_b = np.zeros(n)
        for i, pl in enumerate(self.planes):
            nrm = pl.normal
            denom = dirs @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((pl.origin - origins) @ nrm) / denom
            hit = origins + t[:, None] * dirs
            rel = hit - pl.origin
            a = rel @ pl.u
            b = rel @ pl.v
            ok = (t > 1e-6) & (a >= 0) & (a <= pl.size_a) & (b >= 0) & (b <= pl.size_b) & (t < best_t)
            best_t[ok], best_i[ok], best_a[ok], best_b[ok] = t[ok], i, a[ok], b[ok]
        return best_t, best_i, best_a, best_b

    def render(self, intr: Intrinsics, world_from_camera: np.ndarray, gain: float = 1.0) -> np.ndarray:
        """BGR uint8 (H, W, 3) image of the scene; sky is a smooth gradient."""
        w, h = intr.width_px, intr.height_px
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        px = np.stack([uu.ravel(), vv.ravel()], 1)
        xy = cam.pixels_to_normalized(intr, px)
        d = np.c_[xy, np.ones(len(xy))] @ world_from_camera[:3, :3].T
        o = np.broadcast_to(world_from_camera[:3, 3], d.shape)
        _, idx, a, b = self.raycast(o, d)
        out = np.zeros((h * w, 3), np.float32)
        sky = 200 - 60 * (vv.ravel() / h)
        out[:] = np.stack([sky * 1.0, sky * 0.9, sky * 0.8], 1)
        for i, pl in enumerate(self.planes):
            sel = idx == i
            if not sel.any():
                continue
            th, tw = pl.texture.shape
            m = int(sel.sum())
            cols = 1024
            pad = (-m) % cols
            mx = np.pad((a[sel] * PX_PER_M).astype(np.float32), (0, pad)).reshape(-1, cols)
            my = np.pad(((pl.size_b - b[sel]) * PX_PER_M).astype(np.float32), (0, pad)).reshape(-1, cols)
            val = cv2.remap(pl.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).reshape(-1)[:m]
            out[sel] = val[:, None].astype(np.float32) * np.array(pl.tint[::-1], np.float32)
        img = np.clip(out * gain, 0, 255).astype(np.uint8).reshape(h, w, 3)
        return img

    def depth_lookup(
        self, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray, capture_time_ns: int = 0
    ) -> np.ndarray:
        """Camera z (N,) of the surface each pixel sees (NaN for sky)."""
        xy = cam.pixels_to_normalized(intr, pixels_px)
        d_cam = np.c_[xy, np.ones(len(xy))]
        d = d_cam @ world_from_camera[:3, :3].T
        o = np.broadcast_to(world_from_camera[:3, 3], d.shape)
        t, _, _, _ = self.raycast(o, d)
        return np.where(np.isfinite(t), t, np.nan)  # d_cam has z = 1, so t is the camera z

    def point_at(self, world_from_camera: np.ndarray, intr: Intrinsics, pixels_px: np.ndarray) -> np.ndarray:
        """World points (N, 3) seen at pixels (NaN rows for sky)."""
        z = self.depth_lookup(world_from_camera, intr, pixels_px)
        xy = cam.pixels_to_normalized(intr, pixels_px)
        p_cam = np.c_[xy, np.ones(len(xy))] * z[:, None]
        return p_cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]


def box_corners() -> np.ndarray:
    """Model points a user would click: box and facade corners (world metres)."""
    return np.array(
        [
            [-2, 12, 0],
            [2, 12, 0],
            [2, 12, 3],
            [-2, 12, 3],
            [-2, 15, 3],
            [2, 15, 3],
            [-16, 20, 0],
            [16, 20, 0],
            [-16, 20, 14],
            [16, 20, 14],
            [-8, 20, 7],
            [8, 20, 10],
        ],
        float,
    )


def anchor_clicks(intr: Intrinsics, world_from_camera: np.ndarray, noise_px: float, seed: int = 0):
    """Visible click pixels (N, 2) with Gaussian noise and their model points (N, 3)."""
    pts = box_corners()
    px, z = cam.project_points(intr, cam.invert_rigid(world_from_camera), pts)
    ok = (z > 0) & (px[:, 0] > 5) & (px[:, 1] > 5) & (px[:, 0] < intr.width_px - 6) & (px[:, 1] < intr.height_px - 6)
    rng = np.random.default_rng(seed)
    return px[ok] + rng.normal(0, noise_px, (ok.sum(), 2)), pts[ok]


def mast_camera(width: int = 960, height: int = 540, fov_deg: float = 60.0):
    """A fixed camera on a mast looking at the facade: (intrinsics, world_from_camera)."""
    intr = cam.centered_intrinsics(width, height, cam.focal_from_fov(width, fov_deg))
    return intr, cam.look_at((3.0, -6.0, 6.0), (0.0, 16.0, 4.0))


def jitter(world_from_camera: np.ndarray, intr: Intrinsics, rng: np.random.Generator, rot_deg: float, zoom: float):
    """Pan/tilt/roll jitter about the camera centre (degrees, s.d.) and a relative focal change (s.d.)."""
    R_delta = cam.rodrigues_to_matrix(np.radians(rng.normal(0, rot_deg, 3)))
    T = world_from_camera.copy()
    T[:3, :3] = T[:3, :3] @ R_delta
    f = intr.f_px * (1 + rng.normal(0, zoom))
    return cam.centered_intrinsics(intr.width_px, intr.height_px, f), T


def encode_jpeg(bgr: np.ndarray, quality: int = 92) -> bytes:
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


def test_scene_renders_and_depth_is_consistent() -> None:
    scene = PlaneScene(0)
    intr, T = mast_camera(320, 180)
    img = scene.render(intr, T)
    assert img.shape == (180, 320, 3) and img.std() > 10
    px = np.array([[160.0, 90.0], [40.0, 170.0]])
    pts = scene.point_at(T, intr, px)
    back, _ = cam.project_points(intr, cam.invert_rigid(T), pts)
    np.testing.assert_allclose(back, px, atol=1e-6)
