"""SparseCloud messages <-> arrays (pure numpy; the layout is in :class:`schemas.messages.SparseCloud`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.messages import SparseCloud


@dataclass(frozen=True)
class SparseArrays:
    """A decoded SparseCloud: ``points_m`` float32 (N, 3) world metres; ``colors_rgb`` uint8 (N, 3) or None (absent
    or not one per point); ``obs_point``, ``obs_photo`` int32 (M,) indices into the points and ``photo_ids``;
    ``obs_pixel_px`` float32 (M, 2); ``point_flags`` uint8 (N,) or None (not given)."""

    photo_ids: tuple[str, ...]
    points_m: NDArray[np.float32]
    colors_rgb: NDArray[np.uint8] | None
    obs_point: NDArray[np.int32]
    obs_photo: NDArray[np.int32]
    obs_pixel_px: NDArray[np.float32]
    point_flags: NDArray[np.uint8] | None


def decode_sparse_cloud(msg: SparseCloud) -> SparseArrays:
    """Arrays of a SparseCloud (read-only views of its bytes); ValueError when they do not fit together."""
    pts = np.frombuffer(msg.points_xyz_f32, "<f4")
    if pts.size % 3:
        raise ValueError(f"sparse cloud: points_xyz_f32 has {pts.size} floats, not a multiple of 3")
    pts = pts.reshape(-1, 3)
    obs_point = np.frombuffer(msg.obs_point_i32, "<i4")
    obs_photo = np.frombuffer(msg.obs_photo_i32, "<i4")
    obs_pixel = np.frombuffer(msg.obs_pixel_f32, "<f4")
    if obs_pixel.size % 2:
        raise ValueError(f"sparse cloud: obs_pixel_f32 has {obs_pixel.size} floats, not a multiple of 2")
    obs_pixel = obs_pixel.reshape(-1, 2)
    if not (len(obs_point) == len(obs_photo) == len(obs_pixel)):
        raise ValueError(
            f"sparse cloud: observation arrays differ in length ({len(obs_point)}, {len(obs_photo)}, {len(obs_pixel)})"
        )
    if len(obs_point) and (obs_point.max() >= len(pts) or obs_point.min() < 0):
        raise ValueError("sparse cloud: obs_point_i32 indexes outside the points")
    if len(obs_photo) and (obs_photo.max() >= len(msg.photo_ids) or obs_photo.min() < 0):
        raise ValueError("sparse cloud: obs_photo_i32 indexes outside photo_ids")
    flags = None
    if msg.point_flags_u8:
        flags = np.frombuffer(msg.point_flags_u8, np.uint8)
        if len(flags) != len(pts):
            raise ValueError(f"sparse cloud: {len(flags)} point flags for {len(pts)} points")
    rgb = np.frombuffer(msg.colors_rgb_u8, np.uint8)
    colors = rgb.reshape(-1, 3) if rgb.size and rgb.size == pts.size else None
    return SparseArrays(tuple(msg.photo_ids), pts, colors, obs_point, obs_photo, obs_pixel, flags)


def encode_sparse_cloud(
    site: str, revision: int, arr: Mapping[str, NDArray[np.generic] | Sequence[str]]
) -> SparseCloud:
    """SparseCloud of arrays named as the registrar's ``sparse_arrays()`` gives them: ``photo_ids``, ``points_xyz``
    (N, 3), ``colors_rgb`` (N, 3), ``obs_point``, ``obs_photo`` (M,), ``obs_pixel`` (M, 2), ``point_flags`` (N,)."""
    return SparseCloud(
        site=site,
        revision=revision,
        photo_ids=tuple(str(p) for p in arr["photo_ids"]),
        points_xyz_f32=np.ascontiguousarray(arr["points_xyz"], "<f4").tobytes(),
        colors_rgb_u8=np.ascontiguousarray(arr["colors_rgb"], np.uint8).tobytes(),
        obs_point_i32=np.ascontiguousarray(arr["obs_point"], "<i4").tobytes(),
        obs_photo_i32=np.ascontiguousarray(arr["obs_photo"], "<i4").tobytes(),
        obs_pixel_f32=np.ascontiguousarray(arr["obs_pixel"], "<f4").tobytes(),
        point_flags_u8=np.ascontiguousarray(arr["point_flags"], np.uint8).tobytes(),
    )
