"""Registration by the model alone: the camera at which the BIM's outlines fall on the photo's edges, searched over
the poses the photo's GPS allows (pure: arrays and :class:`~constructaide.modelview.ModelView` renders; no bus).

Where no verified geometry joins a photo to the registered ones (each fixed camera of the synthetic sites is its
own component: `bench/connectivity.py`), feature-based registration needs a person's clicks. The model itself
still joins them: a fixed camera looks at the building from a mast a few metres from where its GPS says, level.

Search (coarse to fine):

1. centres on a grid around the GPS position (``centre_steps`` x ``centre_step_m`` each way) at a few heights
   (GPS altitude is not trusted: a mast, a crane, a phone in a hand); from each, the model (elements the schedule
   says stand, over the terrain plane) rendered once with a wide lens aimed at the model's middle gives its
   visible edges as world points with a tangent (visibility depends on the centre, not on the turn);
2. every turn on a yaw x pitch grid about that aim is scored by an oriented chamfer: each edge point projected
   with the photo's focal prior, its distance to the nearest photo edge of like direction (truncated at
   ``truncate_px``), averaged over all points (a model turned out of the photo scores 0);
3. the best distinct hypotheses are refined on the same oriented chamfer (robust least squares over pose and
   focal, the focal held within ``focal_bound_rel`` of the EXIF prior, the visible edges rendered again between
   rounds), at 480 then 960 px wide;
4. the refined camera's edge support (share of its visible edges with a like photo edge within ``support_px``)
   is compared with its chance level (the same share with the outline slid 12 px aside in eight directions: what
   the photo's texture gives anywhere near); kept when support exceeds chance by ``min_contrast`` and by
   ``min_margin`` more than any rival that lays the model elsewhere in the photo, and its focal stays within
   ``max_focal_change_rel`` of the prior (a far view trades focal against distance: default seed 0's cam-west
   came out 25 % short without the bound, its outline 0.29 % of the width off).

Measured (`bench/modelsearch.py`, BENCHMARKS 'model search'): right cameras reach 0.2-0.42 over chance, cameras
more than 2 % of the width off at most 0.19, and first frames of a site with little built (0.6-0.8 % off) up to
0.29: hence 0.3. Views where the building is small, mostly hidden or barely started are refused, and the camera
is asked for as before.

The answer is a camera, not a verdict: the caller turns it into model-point clicks (:func:`virtual_clicks`) that
the anchor solve and the adjustments use like a person's, so everything downstream (anchor hold, lens hold,
release) is unchanged. Poses: ``world_from_camera`` (4, 4), OpenCV camera frame, model metres, z up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from constructaide import camera as cam
from constructaide.geo import enu_m
from constructaide.modelview import ModelView, element_bounds
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.modelalign import AlignParams, EdgeSamples, compose_update, edge_samples, work_size
from schemas.messages import GeoPoint, Intrinsics

F64 = NDArray[np.float64]


class SearchParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Model search. Angles in degrees, lengths in metres, pixels at ``work_width_px``."""

    work_width_px: int = 480
    centre_step_m: float = 3.0
    centre_steps: int = 1
    """Grid of (2 k + 1)^2 centres around the GPS position."""
    heights_m: tuple[float, ...] = (3.0, 6.0, 9.0, 12.0, 16.0, 20.0)
    """Camera heights above the terrain tried (GPS altitude is not trusted)."""
    yaw_half_deg: float = 30.0
    pitch_half_deg: float = 18.0
    angle_step_deg: float = 3.0
    wide_focal_scale: float = 0.4
    """The edge render's focal, relative to the photo's: wide enough to hold every turn tried."""
    truncate_px: float = 8.0
    orientation_bins: int = 8
    keep: int = 8
    """Distinct coarse hypotheses refined."""
    distinct_deg: float = 5.0
    distinct_m: float = 3.0
    refine_widths_px: tuple[int, ...] = (480, 960)
    refine_rounds: int = 2
    focal_bound_rel: float = 0.08
    """The refinement keeps the focal within this of the prior (EXIF: a few per cent)."""
    max_focal_change_rel: float = 0.06
    """A found camera whose focal moved further from the prior is refused (focal traded against distance)."""
    support_px: float = 1.5
    """At 960 px wide (scaled with the width)."""
    chance_shift_px: float = 12.0
    """The support's chance level: the outline slid this far (at 960 px wide) in eight directions."""
    rival_shift_rel: float = 0.02
    min_contrast: float = 0.3
    """Edge support over its chance level the found camera needs."""
    min_margin: float = 0.08
    """... and over the best rival's."""


@dataclass
class Hypothesis:
    """A camera the search considers: ``world_from_camera`` (4, 4), its pinhole ``intrinsics`` (full resolution)
    and the coarse stage's score, then, refined, its edge support and chance level."""

    world_from_camera: F64
    intrinsics: Intrinsics
    coarse: float
    support: float = 0.0
    """Share of the visible edge samples with a like photo edge within ``support_px``."""
    chance: float = 0.0
    """The same share with the outline slid aside (the photo's texture alone)."""

    @property
    def contrast(self) -> float:
        return self.support - self.chance


@dataclass
class SearchResult:
    """The found camera (None when refused), why, and every refined hypothesis (best first)."""

    world_from_camera: F64 | None
    intrinsics: Intrinsics | None
    reason: str
    hypotheses: list[Hypothesis] = field(default_factory=list)


def _work_image(gray: NDArray[np.uint8], width_px: int, height_px: int) -> NDArray[np.uint8]:
    """The photo (H, W) at the work size (area interpolation; as is when it already has that width)."""
    if gray.shape[1] == width_px:
        return gray
    return np.asarray(cv2.resize(gray, (width_px, height_px), interpolation=cv2.INTER_AREA), np.uint8)


def oriented_distance_maps(gray: NDArray[np.uint8], bins: int, truncate_px: float) -> NDArray[np.float32]:
    """(bins, H, W) distance (px, truncated) to the nearest photo edge whose direction lies within one bin of
    the bin's; edges from Canny on the blurred photo, direction from its gradient (mod 180 deg)."""
    g = cv2.GaussianBlur(gray, (0, 0), 1.0)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    hi = float(np.percentile(mag, 90))
    edges = cv2.Canny(g, 0.4 * hi, hi, L2gradient=True) > 0
    # the edge's own direction is across the gradient; both mod 180 deg
    ang = np.mod(np.arctan2(gy, gx) + 0.5 * np.pi, np.pi)
    b = np.minimum((ang / np.pi * bins).astype(np.int64), bins - 1)
    out = np.empty((bins,) + gray.shape, np.float32)
    for k in range(bins):
        near = edges & ((b == k) | (b == (k - 1) % bins) | (b == (k + 1) % bins))
        src = np.where(near, 0, 255).astype(np.uint8)
        out[k] = np.minimum(cv2.distanceTransform(src, cv2.DIST_L2, 3), truncate_px)
    return out


def _rotations(aim_wfc: F64, yaws_deg: F64, pitches_deg: F64) -> F64:
    """(K, 3, 3) camera_from_world rotations: the aim turned by yaw about the world's up and pitch about the
    camera's x axis."""
    r_aim = aim_wfc[:3, :3]
    out = []
    for yaw in np.radians(yaws_deg):
        cy, sy = np.cos(yaw), np.sin(yaw)
        rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
        for pitch in np.radians(pitches_deg):
            cp, sp = np.cos(pitch), np.sin(pitch)
            rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
            out.append((rz @ r_aim @ rx).T)
    return np.asarray(out)


def _score(
    dmaps: NDArray[np.float32], intr: Intrinsics, centre: F64, rot: F64, p: F64, q: F64, truncate_px: float
) -> F64:
    """(K,) oriented chamfer scores of the edge points ``p`` (N, 3) with tangent points ``q`` (N, 3) under the
    camera_from_world rotations ``rot`` (K, 3, 3) at ``centre``: mean of 1 - d / truncate over all points."""
    bins, h, w = dmaps.shape
    fx, fy = cam.focal_xy(intr)
    pc = np.einsum("kij,nj->kni", rot, p - centre)
    qc = np.einsum("kij,nj->kni", rot, q - centre)
    z, zq = pc[..., 2], qc[..., 2]
    front = (z > 0.1) & (zq > 0.1)
    zs, zqs = np.where(front, z, 1.0), np.where(front, zq, 1.0)
    u = fx * pc[..., 0] / zs + intr.cx_px
    v = fy * pc[..., 1] / zs + intr.cy_px
    du = fx * qc[..., 0] / zqs + intr.cx_px - u
    dv = fy * qc[..., 1] / zqs + intr.cy_px - v
    ui, vi = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    inside = front & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ang = np.mod(np.arctan2(dv, du), np.pi)
    b = np.minimum((ang / np.pi * bins).astype(np.int64), bins - 1)
    flat = (b * h + np.clip(vi, 0, h - 1)) * w + np.clip(ui, 0, w - 1)
    d = dmaps.reshape(-1)[flat]
    gain = np.where(inside, 1.0 - d / truncate_px, 0.0)
    return gain.mean(axis=1)


def _tangent_points(intr: Intrinsics, wfc: F64, pts: F64, normals: F64, step_px: float = 3.0) -> F64:
    """World points ``step_px`` along each edge sample's image tangent at the sample's depth (N, 3)."""
    cfw = cam.invert_rigid(wfc)
    pc = pts @ cfw[:3, :3].T + cfw[:3, 3]
    uv, _ = cam.project_points(intr, cfw, pts)
    tang = np.c_[-normals[:, 1], normals[:, 0]]
    xy = cam.pixels_to_normalized(intr, uv + step_px * tang)
    qc = np.c_[xy, np.ones(len(xy))] * pc[:, 2:3]
    return qc @ wfc[:3, :3].T + wfc[:3, 3]


def _distinct(a: Hypothesis, b: Hypothesis, p: SearchParams) -> bool:
    """Whether two hypotheses are different poses (coarse stage: turn or centre apart)."""
    turn = cam.rotation_angle_deg(a.world_from_camera[:3, :3], b.world_from_camera[:3, :3])
    shift = float(np.linalg.norm(a.world_from_camera[:3, 3] - b.world_from_camera[:3, 3]))
    return turn > p.distinct_deg or shift > p.distinct_m


def _rival(a: Hypothesis, b: Hypothesis, points_m: F64, p: SearchParams) -> bool:
    """Whether ``b`` lays the model elsewhere in the photo than ``a``: its points (N, 3) m moved by more than
    ``rival_shift_rel`` of the width on average (a camera a metre aside and turned to compensate is no rival)."""
    pa, _ = cam.project_points(a.intrinsics, cam.invert_rigid(a.world_from_camera), points_m)
    pb, _ = cam.project_points(b.intrinsics, cam.invert_rigid(b.world_from_camera), points_m)
    return float(np.nanmean(np.linalg.norm(pa - pb, axis=1))) > p.rival_shift_rel * a.intrinsics.width_px


def search_pose(
    view: ModelView,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    centre_xy_m: tuple[float, float],
    target_m: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    params: SearchParams | None = None,
) -> SearchResult:
    """Search the camera of the photo ``gray`` (H, W) whose lens prior is ``intr`` (full resolution; focal from
    EXIF) near the GPS position ``centre_xy_m`` (model metres), aimed roughly at ``target_m`` (3,) (the model's
    middle), on the model ``view`` with ``elements`` standing and the terrain at ``ground_z_m``."""
    p = params or SearchParams()
    ground = 0.0 if ground_z_m is None else float(ground_z_m)
    ww, wh = work_size(intr, p.work_width_px)
    wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
    img = _work_image(gray, ww, wh)
    dmaps = oriented_distance_maps(img, p.orientation_bins, p.truncate_px)
    wide = msgspec.structs.replace(wi, f_px=wi.f_px * p.wide_focal_scale)
    sample_params = AlignParams(sample_step_px=3.0, max_samples=2500, min_samples=30)
    steps = np.arange(-p.centre_steps, p.centre_steps + 1) * p.centre_step_m
    yaws = np.arange(-p.yaw_half_deg, p.yaw_half_deg + 1e-9, p.angle_step_deg)
    pitches = np.arange(-p.pitch_half_deg, p.pitch_half_deg + 1e-9, p.angle_step_deg)
    coarse: list[Hypothesis] = []
    for dx in steps:
        for dy in steps:
            for hgt in p.heights_m:
                centre = np.array([centre_xy_m[0] + dx, centre_xy_m[1] + dy, ground + hgt])
                aim = cam.look_at(centre, target_m)
                s = edge_samples(view, wide, aim, elements, ground_z_m, sample_params)
                if len(s.point_in_world_m) < sample_params.min_samples:
                    continue
                q = _tangent_points(wide, aim, s.point_in_world_m, s.normal_px)
                rots = _rotations(aim, yaws, pitches)
                sc = _score(dmaps, wi, centre, rots, s.point_in_world_m, q, p.truncate_px)
                for k in np.argsort(sc)[::-1][: p.keep]:
                    wfc = np.eye(4)
                    wfc[:3, :3] = rots[k].T
                    wfc[:3, 3] = centre
                    coarse.append(Hypothesis(wfc, intr, float(sc[k])))
    coarse.sort(key=lambda h: -h.coarse)
    chosen: list[Hypothesis] = []
    for h in coarse:
        if all(_distinct(h, c, p) for c in chosen):
            chosen.append(h)
        if len(chosen) >= p.keep:
            break
    refined = [_refine(view, gray, h, elements, ground_z_m, p) for h in chosen]
    refined.sort(key=lambda h: -h.contrast)
    if not refined:
        return SearchResult(None, None, "the model shows no edges from the positions the GPS allows")
    best = refined[0]
    pts = edge_samples(view, wi, best.world_from_camera, elements, ground_z_m, sample_params).point_in_world_m
    rivals = [h.contrast for h in refined[1:] if len(pts) and _rival(best, h, pts, p)]
    second = max(rivals, default=0.0)
    why = f"edge support {best.support:.2f} against {best.chance:.2f} by chance, best rival {second:.2f}"
    if best.contrast < p.min_contrast:
        return SearchResult(None, None, f"{why} (< {p.min_contrast} over chance)", refined)
    if best.contrast - second < p.min_margin:
        return SearchResult(None, None, f"{why} (margin < {p.min_margin})", refined)
    if abs(best.intrinsics.f_px / intr.f_px - 1.0) > p.max_focal_change_rel:
        change = best.intrinsics.f_px / intr.f_px - 1.0
        return SearchResult(None, None, f"{why}, but its focal is {change:+.0%} off the prior", refined)
    return SearchResult(best.world_from_camera, best.intrinsics, why, refined)


def _chamfer(dmaps: NDArray[np.float32], intr: Intrinsics, wfc: F64, p: F64, q: F64, truncate_px: float) -> F64:
    """(N,) oriented distance (px, bilinear, truncated) of each edge point to the photo's edges at a camera."""
    bins, h, w = dmaps.shape
    cfw = cam.invert_rigid(wfc)
    fx, fy = cam.focal_xy(intr)
    pc = p @ cfw[:3, :3].T + cfw[:3, 3]
    qc = q @ cfw[:3, :3].T + cfw[:3, 3]
    z, zq = np.maximum(pc[:, 2], 1e-3), np.maximum(qc[:, 2], 1e-3)
    u, v = fx * pc[:, 0] / z + intr.cx_px, fy * pc[:, 1] / z + intr.cy_px
    du, dv = fx * qc[:, 0] / zq + intr.cx_px - u, fy * qc[:, 1] / zq + intr.cy_px - v
    b = np.minimum((np.mod(np.arctan2(dv, du), np.pi) / np.pi * bins).astype(np.int64), bins - 1)
    inside = (pc[:, 2] > 0.1) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0, v0 = np.clip(np.floor(u), 0, w - 2).astype(np.int64), np.clip(np.floor(v), 0, h - 2).astype(np.int64)
    a, c = np.clip(u - u0, 0, 1), np.clip(v - v0, 0, 1)
    flat = dmaps.reshape(bins, -1)
    i00 = v0 * w + u0
    d = (
        flat[b, i00] * (1 - a) * (1 - c)
        + flat[b, i00 + 1] * a * (1 - c)
        + flat[b, i00 + w] * (1 - a) * c
        + flat[b, i00 + w + 1] * a * c
    )
    return np.where(inside, d, truncate_px).astype(np.float64)


def _residuals(x: F64, dmaps: NDArray[np.float32], wi: Intrinsics, wfc: F64, pts: F64, q: F64, trunc: float) -> F64:
    """Oriented chamfer distances (N,) after the update ``x`` (rotation vector, translation m, log focal)."""
    wi_x = msgspec.structs.replace(wi, f_px=wi.f_px * float(np.exp(x[6])))
    return _chamfer(dmaps, wi_x, compose_update(cam.invert_rigid(wfc), x), pts, q, trunc)


def _refine_maps(
    gray: NDArray[np.uint8], intr: Intrinsics, width_px: int, p: SearchParams
) -> tuple[int, int, float, NDArray[np.float32], AlignParams]:
    """What a refinement round at ``width_px`` works on: the work size (w, h), the distance truncation (px), the
    photo's oriented distance maps there and the edge sampling."""
    ww, wh = work_size(intr, width_px)
    trunc = p.truncate_px * max(1.0, ww / p.work_width_px) ** 0.5
    dmaps = oriented_distance_maps(_work_image(gray, ww, wh), p.orientation_bins, trunc)
    return ww, wh, trunc, dmaps, AlignParams(sample_step_px=2.0 * ww / 480, max_samples=3000, min_samples=30)


def _refine(
    view: ModelView,
    gray: NDArray[np.uint8],
    h: Hypothesis,
    elements: set[str] | None,
    ground_z_m: float | None,
    p: SearchParams,
) -> Hypothesis:
    """A coarse hypothesis refined on the oriented chamfer (pose and focal, robust least squares, the model's
    visible edges rendered again between rounds), coarse to fine; its support: the share of the final edge
    samples within ``support_px`` of a like photo edge at the last width."""
    wfc, intr = h.world_from_camera, h.intrinsics
    f_prior = intr.f_px
    sup = luck = 0.0
    for width in p.refine_widths_px:
        ww, wh, trunc, dmaps, sp = _refine_maps(gray, intr, width, p)
        for _ in range(p.refine_rounds):
            wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
            s = edge_samples(view, wi, wfc, elements, ground_z_m, sp)
            if len(s.point_in_world_m) < sp.min_samples:
                return Hypothesis(wfc, intr, h.coarse, 0.0)
            pts, q = s.point_in_world_m, _tangent_points(wi, wfc, s.point_in_world_m, s.normal_px)
            depth = float(np.median((pts - wfc[:3, 3]) @ wfc[:3, 2]))
            f0 = wi.f_px

            x0 = np.zeros(7)
            scale = np.r_[np.full(3, 2.0 / f0), np.full(3, 2.0 * depth / f0), 2.0 / f0]
            # the focal stays within focal_bound_rel of the prior (far views trade focal against distance)
            lo_f, hi_f = (
                np.log((1 + b) * f_prior * ww / intr.width_px / f0) for b in (-p.focal_bound_rel, p.focal_bound_rel)
            )
            lower, upper = np.r_[np.full(6, -np.inf), min(lo_f, -1e-9)], np.r_[np.full(6, np.inf), max(hi_f, 1e-9)]
            r = least_squares(
                _residuals,
                x0,
                bounds=(lower, upper),
                loss="soft_l1",
                f_scale=1.5,
                x_scale=scale,
                diff_step=1e-3,
                max_nfev=60,
                args=(dmaps, wi, wfc, pts, q, trunc),
            )
            wfc = compose_update(cam.invert_rigid(wfc), r.x)
            intr = msgspec.structs.replace(intr, f_px=intr.f_px * float(np.exp(r.x[6])))
        wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
        s = edge_samples(view, wi, wfc, elements, ground_z_m, sp)
        if len(s.point_in_world_m):
            sup, luck = _support_and_chance(dmaps, wi, wfc, s, trunc, p)
    return Hypothesis(wfc, intr, h.coarse, sup, luck)


def _support_and_chance(
    dmaps: NDArray[np.float32], wi: Intrinsics, wfc: F64, s: EdgeSamples, trunc: float, p: SearchParams
) -> tuple[float, float]:
    """Share of the edge samples ``s`` within ``support_px`` of a like photo edge (``dmaps`` at the work size of
    ``wi``), and the same share with the outline slid ``chance_shift_px`` aside in eight directions (what the
    photo's texture alone gives there)."""
    ww = wi.width_px
    q = _tangent_points(wi, wfc, s.point_in_world_m, s.normal_px)
    tol = p.support_px * ww / 960
    sup = float(np.mean(_chamfer(dmaps, wi, wfc, s.point_in_world_m, q, trunc) <= tol))
    step = p.chance_shift_px * ww / 960
    chance = []
    for ang in np.arange(8) * np.pi / 4:
        shifted = msgspec.structs.replace(wi, cx_px=wi.cx_px + step * np.cos(ang), cy_px=wi.cy_px + step * np.sin(ang))
        chance.append(float(np.mean(_chamfer(dmaps, shifted, wfc, s.point_in_world_m, q, trunc) <= tol)))
    return sup, float(np.mean(chance))


def outline_contrast(
    view: ModelView,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    params: SearchParams | None = None,
) -> tuple[float, float, int]:
    """How well the model's visible outline at a registered camera (``intr`` full resolution, distortion ignored;
    ``world_from_camera`` (4, 4)) lies on the photo ``gray`` (H, W)'s edges, at the refinement's last work width:
    (edge support, its chance level, number of edge samples: 0 when too few to tell); see :class:`Hypothesis`."""
    p = params or SearchParams()
    ww, wh, trunc, dmaps, sp = _refine_maps(gray, intr, p.refine_widths_px[-1], p)
    wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
    s = edge_samples(view, wi, np.asarray(world_from_camera, np.float64), elements, ground_z_m, sp)
    if len(s.point_in_world_m) < sp.min_samples:
        return 0.0, 0.0, 0
    sup, luck = _support_and_chance(dmaps, wi, np.asarray(world_from_camera, np.float64), s, trunc, p)
    return sup, luck, len(s.point_in_world_m)


def virtual_clicks(
    view: ModelView,
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    count: int = 24,
    seed: int = 0,
) -> tuple[F64, F64]:
    """Model points on visible edges at a found camera and their pixels (full resolution, with the lens's
    distortion): (pixels (N, 2), points (N, 3) m), ``count`` of them spread over the outline (farthest first)."""
    s = edge_samples(view, intr, world_from_camera, elements, ground_z_m, AlignParams(sample_step_px=8.0))
    pts = s.point_in_world_m
    if not len(pts):
        return np.zeros((0, 2)), np.zeros((0, 3))
    px, _ = cam.project_points(intr, cam.invert_rigid(world_from_camera), pts)
    ok = np.all(np.isfinite(px), axis=1)
    px, pts = px[ok], pts[ok]
    if not len(px):
        return np.zeros((0, 2)), np.zeros((0, 3))
    # farthest-point sampling: spread over the model's outline in the photo
    keep = [int(np.random.default_rng(seed).integers(len(px)))]
    dist = np.linalg.norm(px - px[keep[0]], axis=1)
    while len(keep) < min(count, len(px)):
        k = int(np.argmax(dist))
        keep.append(k)
        dist = np.minimum(dist, np.linalg.norm(px - px[k], axis=1))
    return px[keep], pts[keep]


def standing_bounds(view: ModelView, elements: set[str] | None) -> tuple[F64, F64] | None:
    """Bounds (lo (3,), hi (3,)) m of the ``elements`` standing (None: all) in the model ``view``; None when none."""
    lo, hi, has = element_bounds(view.scene)
    has = has & view.visible(elements)
    if not has.any():
        return None
    return lo[has].min(axis=0), hi[has].max(axis=0)


def model_target(view: ModelView, elements: set[str] | None) -> F64 | None:
    """Where a site camera aims, roughly (3,) m: the middle of the standing elements' bounds, a third of the way
    up. None when nothing stands."""
    box = standing_bounds(view, elements)
    if box is None:
        return None
    a, b = box
    return np.array([0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1]), a[2] + 0.35 * (b[2] - a[2])])


def gps_in_model(lookup: MeshDepthLookup, gps: GeoPoint | None) -> tuple[tuple[float, float] | None, str]:
    """A photo's GPS position in the model frame (x, y) m, placed by the site reference of ``lookup``; or None
    and why not."""
    if gps is None:
        return None, "the photo has no GPS position"
    if lookup.site_gps is None:
        return None, "the model has no site reference (IfcSite latitude / longitude)"
    e, n = enu_m(gps, lookup.site_gps)
    return (e - lookup.origin_offset_m[0], n - lookup.origin_offset_m[1]), ""


def model_anchor(
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    gps: GeoPoint | None,
    capture_time_ns: int,
    count: int = 24,
    params: SearchParams | None = None,
    details: list[Hypothesis] | None = None,
) -> tuple[tuple[F64, F64] | None, str]:
    """A fixed camera's frame ``gray`` (H, W) found by the model (:func:`search_pose`) and turned into clicks
    (pixels (N, 2) full resolution, model points (N, 3) m) for the anchor solve, or None and why not. ``intr``:
    the photo's lens prior (EXIF focal); ``gps``: the photo's position, placed in the model by the site
    reference of ``lookup``. ``details`` receives the refined hypotheses, best first."""
    xy, why = gps_in_model(lookup, gps)
    if xy is None:
        return None, why
    elements = lookup.elements(capture_time_ns)
    target = model_target(lookup.view, elements)
    if target is None:
        return None, "no model element stands at the photo's date"
    res = search_pose(lookup.view, gray, intr, xy, target, elements, lookup.ground_height_m, params)
    if details is not None:
        details.extend(res.hypotheses)
    if res.world_from_camera is None or res.intrinsics is None:
        return None, f"the model's outlines do not find the camera: {res.reason}"
    px, pts = virtual_clicks(
        lookup.view, res.intrinsics, res.world_from_camera, elements, lookup.ground_height_m, count
    )
    if len(px) < 6:
        return None, f"the model's outlines found the camera ({res.reason}) but show only {len(px)} points"
    return (px, pts), res.reason


class ModelAnchors:
    """When the register node searches a fixed camera by the model before asking for its clicks: only fixed
    cameras' frames (``camera_id``; a phone's close-up shows too little of the model), at most once per camera per
    ``retry_secs`` of capture time (the building grows: a later frame shows more of it)."""

    def __init__(self, count: int = 24, retry_secs: float = 6 * 3600.0, params: SearchParams | None = None) -> None:
        self.count = count
        self.retry_ns = int(retry_secs * 1e9)
        self.params = params
        self.tried: dict[str, int] = {}

    def find(
        self,
        lookup: MeshDepthLookup,
        gray: Callable[[], NDArray[np.uint8]],
        focal_px: float | None,
        gps: GeoPoint | None,
        camera_id: str | None,
        capture_time_ns: int,
    ) -> tuple[tuple[F64, F64] | None, str]:
        """:func:`model_anchor` for a frame (``gray`` gives it (H, W) at full resolution; ``focal_px`` its EXIF
        focal, else a 50 deg view is assumed) when the policy allows, else None and why not."""
        if camera_id is None:
            return None, "a phone photo"
        last = self.tried.get(camera_id)
        if last is not None and abs(capture_time_ns - last) < self.retry_ns:
            return None, "its camera was searched for lately"
        self.tried[camera_id] = capture_time_ns
        img = gray()
        h, w = img.shape[:2]
        intr = cam.centered_intrinsics(w, h, focal_px or cam.focal_from_fov(w, 50.0))
        return model_anchor(lookup, img, intr, gps, capture_time_ns, self.count, self.params)


class OutlineCheck:
    """The model's word on a phone photo's automatic pose (``mapper.PoseCheck``): refused when the standing elements'
    visible outline at that pose lies on the photo's edges hardly better than slid aside (:func:`outline_contrast`
    below ``min_contrast``), as on a pose fitted to a repeated print's matches. Fixed cameras' frames are not
    checked (their poses rest on their own camera's frames), nor a pose at which the model shows too few edges."""

    def __init__(self, lookup: MeshDepthLookup, min_contrast: float, params: SearchParams | None = None) -> None:
        self.lookup = lookup
        self.min_contrast = min_contrast
        self.params = params

    def refusal(
        self,
        gray: Callable[[], NDArray[np.uint8]],
        camera_id: str | None,
        capture_time_ns: int,
        intr: Intrinsics,
        world_from_camera: F64,
    ) -> str:
        """Why the pose is refused ("" when it is not); ``gray`` gives the photo (H, W) at full resolution."""
        if camera_id is not None:
            return ""
        lk = self.lookup
        sup, luck, n = outline_contrast(
            lk.view, gray(), intr, world_from_camera, lk.elements(capture_time_ns), lk.ground_height_m, self.params
        )
        if n == 0 or sup - luck >= self.min_contrast:
            return ""
        return (
            f"the model's outline there lies on the photo's edges no better than slid aside (support {sup:.2f}, "
            f"aside {luck:.2f}; needs {self.min_contrast:+.2f})"
        )

    def for_photo(
        self, gray: Callable[[], NDArray[np.uint8]], camera_id: str | None, capture_time_ns: int
    ) -> Callable[[int, Intrinsics, F64], str]:
        """The check of one photo's candidate poses, as ``mapper.PoseCheck`` (the image index is not used)."""
        return lambda _i, intr, wfc: self.refusal(gray, camera_id, capture_time_ns, intr, wfc)
