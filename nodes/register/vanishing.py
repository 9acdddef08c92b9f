"""A photo's rotation from its straight lines: the building's axes as vanishing directions (pure: arrays; no bus).

A building is laid out along two horizontal axes at right angles and the vertical (a Manhattan frame): its walls,
columns, window frames, brick courses and the site hoarding's panels give the photo straight edges along those three
directions. An image line segment is the image of a world line along axis ``d`` when the plane through the camera
centre and the segment (its interpretation plane, unit normal ``n`` in the camera frame) contains ``d``:
``n . (camera_from_world d) = 0``. The camera's rotation is the one under which the most segment length lies on
such planes, searched on a grid of heading (modulo 90 deg: the axes look alike), pitch and roll, then on a finer
grid with a tighter tolerance. Each solution stands for four cameras, one per quarter turn; the photo's position
and the model's outlines tell them apart (:mod:`nodes.register.phonesearch`).

The model's horizontal axes come from its vertical faces (:func:`model_axes_yaw_deg`). Lens distortion is ignored
(phones' lenses bend a line by a pixel or two). Frames: ``camera_from_world`` (3, 3), OpenCV camera (x right, y down,
z forward), model z up. Measured on the phone photos of default seeds 0 / 7 / 3 and small seeds 0 / 7
(BENCHMARKS 'phones found by the model (notes, 2026-12-07)'): median 0.31-0.59 deg from the true rotation, 26 / 28 /
27 of 30 and 5 / 4 of 5 within 2 deg; close-ups filled with brick fail (one wall's courses give one direction).
"""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from schemas.messages import Intrinsics

F64 = NDArray[np.float64]


class VanishingParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Line detection and the rotation grid. Angles in degrees; lengths in pixels at ``work_width_px``."""

    work_width_px: int = 960
    min_length_px: float = 25.0
    pitch_range_deg: tuple[float, float] = (-20.0, 50.0)
    """Upward tilt of the view tried (a person photographs a building from the ground, looking up at it)."""
    roll_half_deg: float = 10.0
    coarse_step_deg: float = 2.0
    coarse_tolerance_deg: float = 1.5
    fine_step_deg: float = 0.25
    fine_tolerance_deg: float = 0.5
    keep: int = 2
    """Distinct solutions returned (each as its four quarter turns)."""
    distinct_deg: float = 6.0


def model_axes_yaw_deg(normals: F64, areas: F64) -> float:
    """Heading (deg, [0, 90)) of the model's first horizontal axis: the area-weighted mean direction, modulo 90 deg,
    of its vertical faces' normals (``normals`` (T, 3) unit, world; ``areas`` (T,) m^2). 0 without vertical faces."""
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    a = np.asarray(areas, np.float64).reshape(-1)
    vertical = np.abs(n[:, 2]) < 0.1
    if not vertical.any():
        return 0.0
    ang = np.arctan2(n[vertical, 1], n[vertical, 0])
    z = np.sum(a[vertical] * np.exp(4j * ang))
    if abs(z) < 1e-12:
        return 0.0
    return float(np.degrees(np.angle(z) / 4.0) % 90.0)


def camera_from_world(heading: F64, pitch: F64, roll: F64) -> F64:
    """(..., 3, 3) rotations of cameras looking along ``heading`` (rad, from +x towards +y), tilted up by ``pitch``
    (rad) and turned by ``roll`` (rad) about their optical axis."""
    h, p, r = np.broadcast_arrays(np.asarray(heading, float), np.asarray(pitch, float), np.asarray(roll, float))
    fwd = np.stack([np.cos(p) * np.cos(h), np.cos(p) * np.sin(h), np.sin(p)], -1)
    right = np.stack([np.sin(h), -np.cos(h), np.zeros_like(h)], -1)
    down = np.cross(fwd, right)
    wfc = np.stack([right, down, fwd], -1)
    c, s = np.cos(r), np.sin(r)
    turn = np.zeros(r.shape + (3, 3))
    turn[..., 0, 0], turn[..., 0, 1], turn[..., 1, 0], turn[..., 1, 1], turn[..., 2, 2] = c, -s, s, c, 1.0
    return np.swapaxes(wfc @ turn, -1, -2)


def line_segments(gray: NDArray[np.uint8], params: VanishingParams) -> F64:
    """(N, 4) segments (x0, y0, x1, y1) full-resolution px of the photo ``gray`` (H, W), detected (LSD) at the work
    width, at least ``min_length_px`` long there."""
    s = min(1.0, params.work_width_px / gray.shape[1])
    size = (round(gray.shape[1] * s), round(gray.shape[0] * s))
    g = gray if s == 1.0 else cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    found = cv2.createLineSegmentDetector().detect(g)[0]
    if found is None:
        return np.zeros((0, 4))
    seg = np.asarray(found, np.float64).reshape(-1, 4)
    keep = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]) >= params.min_length_px
    return seg[keep] / s


def interpretation_planes(intr: Intrinsics, segments_px: F64) -> tuple[F64, F64]:
    """Unit normals (N, 3) (camera frame) of the planes through the camera centre and each segment (N, 4), and the
    segments' lengths (N,) px (pinhole: distortion ignored)."""
    fx, fy = cam.focal_xy(intr)
    one = np.ones(len(segments_px))
    a = np.c_[(segments_px[:, 0] - intr.cx_px) / fx, (segments_px[:, 1] - intr.cy_px) / fy, one]
    b = np.c_[(segments_px[:, 2] - intr.cx_px) / fx, (segments_px[:, 3] - intr.cy_px) / fy, one]
    n = np.cross(a, b)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n, np.hypot(segments_px[:, 2] - segments_px[:, 0], segments_px[:, 3] - segments_px[:, 1])


def explained_length(rot: F64, axes: F64, normals: F64, lengths: F64, tolerance_deg: float) -> F64:
    """(K,) segment length whose interpretation plane holds one of the ``axes`` (3, 3) (rows: world directions)
    within ``tolerance_deg`` under each camera_from_world rotation of ``rot`` (K, 3, 3)."""
    s = math.sin(math.radians(tolerance_deg))
    hit = np.zeros((len(rot), len(normals)), bool)
    for d in axes:
        hit |= np.abs((rot @ d) @ normals.T) < s
    return hit.astype(np.float64) @ lengths


def _grid(params: VanishingParams, centre: tuple[float, float, float] | None) -> tuple[F64, F64, F64]:
    if centre is None:
        step = params.coarse_step_deg
        h = np.arange(0.0, 90.0, step)
        p = np.arange(params.pitch_range_deg[0], params.pitch_range_deg[1] + 1e-9, step)
        r = np.arange(-params.roll_half_deg, params.roll_half_deg + 1e-9, step)
    else:
        step, half = params.fine_step_deg, params.coarse_step_deg
        h = centre[0] + np.arange(-half, half + 1e-9, step)
        p = centre[1] + np.arange(-half, half + 1e-9, step)
        r = centre[2] + np.arange(-half, half + 1e-9, 2.0 * step)
    hh, pp, rr = np.meshgrid(h, p, r, indexing="ij")
    return hh.ravel(), pp.ravel(), rr.ravel()


def vanishing_rotations(
    gray: NDArray[np.uint8], intr: Intrinsics, axes_yaw_deg: float, params: VanishingParams | None = None
) -> list[tuple[F64, float]]:
    """Camera rotations (camera_from_world (3, 3)) under which the photo ``gray`` (H, W)'s straight lines follow the
    model's axes (first horizontal axis at heading ``axes_yaw_deg``), best first, each with the share of the
    segments' length it explains; every solution comes as its four quarter turns. Empty without lines."""
    p = params or VanishingParams()
    normals, lengths = interpretation_planes(intr, line_segments(gray, p))
    if len(normals) < 3:
        return []
    a = math.radians(axes_yaw_deg)
    axes = np.array([[math.cos(a), math.sin(a), 0.0], [-math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    h, pt, r = _grid(p, None)
    rot = camera_from_world(np.radians(h + axes_yaw_deg), np.radians(pt), np.radians(r))
    tol = p.coarse_tolerance_deg
    score = np.concatenate(
        [explained_length(rot[i : i + 4000], axes, normals, lengths, tol) for i in range(0, len(rot), 4000)]
    )
    picked: list[tuple[float, float, float]] = []
    for k in np.argsort(-score):
        cand = (float(h[k]), float(pt[k]), float(r[k]))
        turn = [abs((cand[0] - q[0] + 45.0) % 90.0 - 45.0) for q in picked]
        if any(t < p.distinct_deg and abs(cand[1] - q[1]) < p.distinct_deg for t, q in zip(turn, picked, strict=True)):
            continue
        picked.append(cand)
        if len(picked) >= p.keep:
            break
    out: list[tuple[F64, float]] = []
    total = float(lengths.sum())
    for centre in picked:
        fh, fp, fr = _grid(p, centre)
        fine = camera_from_world(np.radians(fh + axes_yaw_deg), np.radians(fp), np.radians(fr))
        sc = explained_length(fine, axes, normals, lengths, p.fine_tolerance_deg)
        k = int(np.argmax(sc))
        for quarter in range(4):
            rot_k = camera_from_world(
                np.radians(fh[k] + axes_yaw_deg + 90.0 * quarter), np.radians(fp[k]), np.radians(fr[k])
            )
            out.append((rot_k, float(sc[k]) / total))
    return out
