"""A fixed camera's reference plate: the last unoccluded look of every pixel in its earlier frames (pure core).

The plate lives in the geometry of the first frame of a pose *segment* (a camera that moves by more than
``max_move_m`` or turns by more than ``max_turn_deg`` starts a new segment with an empty plate). Frames are mapped
onto it and back by the rotation between their registered poses (the centre moves by millimetres between the
frames of a mast camera, so parallax is negligible) through the shared radial lens model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from constructaide.camera import normalized_to_pixels, pixels_to_normalized, rotation_angle_deg
from schemas.messages import Intrinsics

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


def pixel_map(
    src: Intrinsics, src_world_from_camera: F64, dst: Intrinsics, dst_world_from_camera: F64, step_px: int = 8
) -> F32:
    """(H_dst, W_dst, 2) float32 pixel of ``src`` seen along each pixel ray of ``dst`` (rotation only), for
    ``cv2.remap`` of a ``src`` image onto ``dst``. Exact every ``step_px`` pixels, bilinear in between (the map is
    smooth; ``step_px`` 1: exact everywhere)."""
    w, h = dst.width_px, dst.height_px
    gu = np.arange(0, w - 1 + step_px, step_px, dtype=np.float64)
    gv = np.arange(0, h - 1 + step_px, step_px, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    xy = pixels_to_normalized(dst, np.stack([uu.ravel(), vv.ravel()], axis=1))
    rays_dst = np.column_stack([xy, np.ones(len(xy))])
    R = src_world_from_camera[:3, :3].T @ dst_world_from_camera[:3, :3]  # src_from_dst rotation
    rays = rays_dst @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        xy_src = rays[:, :2] / rays[:, 2:3]
    behind = rays[:, 2] <= 1e-6
    xy_src[behind] = 0.0
    uv = normalized_to_pixels(src, xy_src)
    uv[behind] = 1e6
    grid = uv.reshape(len(gv), len(gu), 2).astype(np.float32)
    if step_px == 1:
        return np.ascontiguousarray(grid[:h, :w])
    mu, mv = np.meshgrid(np.arange(w, dtype=np.float32) / step_px, np.arange(h, dtype=np.float32) / step_px)
    out = [cv2.remap(np.ascontiguousarray(grid[..., c]), mu, mv, cv2.INTER_LINEAR) for c in range(2)]
    return np.stack(out, axis=-1)


def same_segment(a: F64, b: F64, max_move_m: float = 1.0, max_turn_deg: float = 5.0) -> bool:
    """Whether two poses (4, 4) of a fixed camera are close enough to share a plate."""
    move = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    return move <= max_move_m and rotation_angle_deg(a[:3, :3], b[:3, :3]) <= max_turn_deg


@dataclass
class ReferencePlate:
    """Canonical plate of one camera segment: ``lab`` (H, W, 3) float32, ``valid`` (H, W) bool, ``time_ns`` (H, W)
    int64 (capture time of the frame each pixel was taken from)."""

    intrinsics: Intrinsics
    world_from_camera: F64
    lab: F32
    valid: NDArray[np.bool_]
    time_ns: NDArray[np.int64]

    @classmethod
    def empty(cls, intr: Intrinsics, world_from_camera: F64) -> ReferencePlate:
        h, w = intr.height_px, intr.width_px
        return cls(
            intr, world_from_camera, np.zeros((h, w, 3), np.float32), np.zeros((h, w), bool), np.zeros((h, w), np.int64)
        )

    def same_segment(self, world_from_camera: F64) -> bool:
        return same_segment(self.world_from_camera, world_from_camera)

    def warp_to(self, intr: Intrinsics, world_from_camera: F64) -> tuple[F32, NDArray[np.bool_], NDArray[np.int64]]:
        """The plate seen by a frame: (Lab, valid, time ns), each at ``intr``'s size."""
        m = pixel_map(self.intrinsics, self.world_from_camera, intr, world_from_camera)
        lab = cv2.remap(self.lab, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        valid_u8 = cv2.remap(
            self.valid.astype(np.uint8), m[..., 0], m[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
        )
        # a pixel is valid only away from invalid plate pixels (bilinear colour must not mix in empty ones)
        valid = np.asarray(cv2.erode(valid_u8, np.ones((3, 3), np.uint8)) > 0)
        t = self._remap_time(m)
        return np.asarray(lab, np.float32), valid, t

    def _remap_time(self, m: F32) -> NDArray[np.int64]:
        base = int(self.time_ns[self.valid].min()) if self.valid.any() else 0
        rel = ((self.time_ns - base) / 1e9).astype(np.float32)  # seconds: float32 keeps them exact enough
        out = cv2.remap(rel, m[..., 0], m[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        return (out.astype(np.float64) * 1e9).astype(np.int64) + base

    def update(self, lab: F32, keep: NDArray[np.bool_], time_ns: int, intr: Intrinsics, world_from_camera: F64) -> None:
        """Write a frame's pixels where ``keep`` (unoccluded) into the plate."""
        m = pixel_map(intr, world_from_camera, self.intrinsics, self.world_from_camera)
        warped = cv2.remap(lab, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        ok_u8 = cv2.remap(
            keep.astype(np.uint8), m[..., 0], m[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
        )
        ok = np.asarray(cv2.erode(ok_u8, np.ones((3, 3), np.uint8)) > 0)
        self.lab[ok] = warped[ok]
        self.valid |= ok
        self.time_ns[ok] = time_ns
