"""Checks of a decoded message beyond its types: what every node refuses before a handler sees it.

:func:`problems` returns what is wrong (empty when nothing): non-finite numbers anywhere (NaN / inf poses,
intrinsics, clicks), negative or gigantic sizes and counts, a rotation that is not one, schedule tasks that end
before they start or form a predecessor cycle, element boxes inside out, colours outside 0-255, clicks at
negative pixels. Image bytes are not decoded here (see :mod:`constructaide.imagecodec` for the pixel limit).
Pure: msgspec and the standard library only.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any

import msgspec

from schemas.messages import (
    BimModel,
    BimUpdate,
    Intrinsics,
    Registration,
    ScheduleTask,
    SparseCloud,
    ViewpointNeighbour,
)

MAX_SIDE_PX = 32768  # the longest image side any message may declare
MAX_PROBLEMS = 5
MAX_IMAGE_PIXELS = 100_000_000  # an image header declaring more is refused before any decoder allocates it
IMAGE_FIELDS = ("data", "mask_png", "background_jpeg", "image_png")


def problems(msg: Any) -> list[str]:
    """What is wrong with a decoded message (at most :data:`MAX_PROBLEMS` items, each naming the field)."""
    out: list[str] = []
    _walk(msg, type(msg).__name__, out)
    if isinstance(msg, Registration):
        _registration(msg, out)
    if isinstance(msg, (BimModel, BimUpdate)):
        if msg.tasks:
            _schedule(msg.tasks, out)
        if msg.geometry_glb:
            _glb(msg.geometry_glb, f"{type(msg).__name__}.geometry_glb", out)
    if isinstance(msg, SparseCloud):
        _sparse(msg, out)
    for f in IMAGE_FIELDS:
        data = getattr(msg, f, b"")
        if data:
            size = image_size(data)
            if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
                pid = getattr(msg, "photo_id", "")
                of = f" of photo {pid}" if pid else ""
                out.append(
                    f"{type(msg).__name__}.{f}{of} declares {size[0]}x{size[1]} pixels (limit {MAX_IMAGE_PIXELS}; "
                    "decompression bomb guard)"
                )
    return out[:MAX_PROBLEMS]


def _walk(v: Any, path: str, out: list[str]) -> None:
    if len(out) >= MAX_PROBLEMS:
        return
    if isinstance(v, float):
        if not math.isfinite(v):
            out.append(f"{path} is {v}")
    elif isinstance(v, bool) or v is None or isinstance(v, (str, bytes)):
        return
    elif isinstance(v, int):
        name = path.rsplit(".", 1)[-1]
        if (name.endswith("_px") or name.startswith("num_") or name == "revision") and v < 0:
            out.append(f"{path} is negative ({v})")
        elif name in ("width_px", "height_px") and v > MAX_SIDE_PX:
            out.append(f"{path} {v} is larger than {MAX_SIDE_PX}")
    elif isinstance(v, (tuple, list)):
        if path.endswith("rgba") and not all(isinstance(c, int) and 0 <= c <= 255 for c in v):
            out.append(f"{path} {v} is not 0-255")
            return
        for i, x in enumerate(v):
            _walk(x, f"{path}[{i}]", out)
    elif isinstance(v, msgspec.Struct):
        for f in v.__struct_fields__:
            _walk(getattr(v, f), f"{path}.{f}", out)
        _struct(v, path, out)


def _struct(v: msgspec.Struct, path: str, out: list[str]) -> None:
    if isinstance(v, Intrinsics):
        if v.width_px <= 0 or v.height_px <= 0:
            out.append(f"{path}: image size {v.width_px}x{v.height_px} is not positive")
        if not v.f_px > 0 or not v.fy_over_fx > 0:
            out.append(f"{path}: focal length {v.f_px} px (fy/fx {v.fy_over_fx}) is not positive")
    elif isinstance(v, ViewpointNeighbour):
        if len(v.this_from_neighbour) != 9:
            out.append(f"{path}.this_from_neighbour has {len(v.this_from_neighbour)} values, expected 9 (3x3)")
    lo, hi = getattr(v, "bbox_min_m", None), getattr(v, "bbox_max_m", None)
    if lo is not None and hi is not None and any(a > b for a, b in zip(lo, hi, strict=False)):
        out.append(f"{path}: bbox_min_m {lo} exceeds bbox_max_m {hi}")
    px = getattr(v, "pixel_px", None)
    if px is not None and any(c < 0 for c in px if math.isfinite(c)):
        out.append(f"{path}.pixel_px {px} is off the image (negative)")


def _registration(r: Registration, out: list[str]) -> None:
    m = r.world_from_camera
    if len(m) not in (0, 16):
        out.append(f"Registration.world_from_camera has {len(m)} values, not 16 (row-major 4x4)")
        return
    if r.status != "failed" and (not m or r.intrinsics is None):
        out.append(f"Registration status {r.status!r} without a pose and intrinsics")
    if len(m) == 16 and all(math.isfinite(x) for x in m):
        rot = [[m[4 * i + j] for j in range(3)] for i in range(3)]  # row-major 4x4
        for i in range(3):
            for j in range(3):
                dot = sum(rot[k][i] * rot[k][j] for k in range(3))
                if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                    out.append("Registration.world_from_camera rotation is not orthonormal")
                    return
        det = (
            rot[0][0] * (rot[1][1] * rot[2][2] - rot[1][2] * rot[2][1])
            - rot[0][1] * (rot[1][0] * rot[2][2] - rot[1][2] * rot[2][0])
            + rot[0][2] * (rot[1][0] * rot[2][1] - rot[1][1] * rot[2][0])
        )
        if det < 0:
            out.append("Registration.world_from_camera rotation is a reflection (det < 0)")
        if (m[12], m[13], m[14], m[15]) != (0.0, 0.0, 0.0, 1.0):
            out.append(f"Registration.world_from_camera last row {m[12:]} is not (0, 0, 0, 1)")


def _schedule(tasks: tuple[ScheduleTask, ...], out: list[str]) -> None:
    ids = {t.task_id for t in tasks}
    if len(ids) != len(tasks):
        out.append("schedule has duplicate task ids")
    for t in tasks:
        if t.planned_finish_ns < t.planned_start_ns:
            out.append(f"task {t.task_id!r} ends before it starts (planned)")
        if t.actual_start_ns is not None and t.actual_finish_ns is not None and t.actual_finish_ns < t.actual_start_ns:
            out.append(f"task {t.task_id!r} ends before it starts (actual)")
    preds = {t.task_id: [p for p in t.predecessor_ids if p in ids] for t in tasks}
    state: dict[str, int] = {}  # 1 on the path, 2 done

    def cyclic(start: str) -> bool:
        stack = [(start, iter(preds.get(start, ())))]
        state[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                state[node] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return True
            elif nxt not in state:
                state[nxt] = 1
                stack.append((nxt, iter(preds.get(nxt, ()))))
        return False

    for tid in preds:
        if tid not in state and cyclic(tid):
            out.append(f"schedule has a predecessor cycle through task {tid!r}")
            return


def _glb(data: bytes, path: str, out: list[str]) -> None:
    """The GLB container: magic, version 2, declared length, a JSON chunk that parses (meshes are not read)."""
    if len(data) < 20 or data[:4] != b"glTF":
        out.append(f"{path} is not a GLB (no glTF header, {len(data)} bytes)")
        return
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2 or length != len(data):
        out.append(f"{path}: GLB version {version}, declared {length} bytes, has {len(data)}")
        return
    chunk_len, chunk_type = struct.unpack_from("<II", data, 12)
    if chunk_type != 0x4E4F534A or 20 + chunk_len > len(data):
        out.append(f"{path}: GLB without a complete JSON chunk")
        return
    try:
        doc = json.loads(data[20 : 20 + chunk_len])
    except ValueError as e:
        out.append(f"{path}: GLB JSON does not parse ({e})")
        return
    if not isinstance(doc, dict) or "asset" not in doc:
        out.append(f"{path}: GLB JSON has no asset")


def _sparse(s: SparseCloud, out: list[str]) -> None:
    n, rem = divmod(len(s.points_xyz_f32), 12)
    mo, rem2 = divmod(len(s.obs_point_i32), 4)
    if rem or rem2:
        out.append("SparseCloud: points_xyz_f32 / obs_point_i32 lengths are not whole float32 x 3 / int32 arrays")
        return
    if s.colors_rgb_u8 and len(s.colors_rgb_u8) != 3 * n:
        out.append(f"SparseCloud: colors_rgb_u8 has {len(s.colors_rgb_u8)} bytes for {n} points")
    if s.point_flags_u8 and len(s.point_flags_u8) != n:
        out.append(f"SparseCloud: point_flags_u8 has {len(s.point_flags_u8)} bytes for {n} points")
    if len(s.obs_photo_i32) != 4 * mo or len(s.obs_pixel_f32) != 8 * mo:
        out.append("SparseCloud: observation arrays (point, photo, pixel) differ in length")
        return
    xyz = struct.unpack(f"<{3 * n}f", s.points_xyz_f32)
    if not all(math.isfinite(v) for v in xyz):
        out.append("SparseCloud.points_xyz_f32 has non-finite values")
    pts = struct.unpack(f"<{mo}i", s.obs_point_i32)
    photos = struct.unpack(f"<{mo}i", s.obs_photo_i32)
    if any(not 0 <= i < n for i in pts) or any(not 0 <= j < len(s.photo_ids) for j in photos):
        out.append("SparseCloud: an observation refers to a point or photo that does not exist")


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG IHDR or a JPEG frame header without decoding; None when neither is found."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack_from(">II", data, 16)
        return int(w), int(h)
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = struct.unpack_from(">H", data, i + 2)[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h, w = struct.unpack_from(">HH", data, i + 5)
            return int(w), int(h)
        i += 2 + seg
    return None
