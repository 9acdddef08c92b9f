"""Pose polish by the model's outlines: the BIM's edges, rendered at a registered pose, pulled onto the photo's
intensity edges (pure: arrays and :class:`~constructaide.modelview.ModelView` renders; no bus).

A registration from features and clicks can sit a few pixels off the building it overlays (anchor clicks in the
middle of a far view trade focal against distance; a frame's lens drifts in the adjustments). The model's own
outlines say where the building is: element silhouettes, depth steps and creases (an element's faces turning,
seen as a change of their flat shades) in an ID / depth render at the current pose, of the elements the schedule
says stand at the photo's date, over the terrain plane. Each edge sample (a world point on the edge and the edge's
normal in the image) looks along that normal for the nearest strong intensity edge of the photo (the moving-edge
search of model-based tracking); a robust (Tukey) Gauss-Newton over the pose (rotation and translation in the
camera frame) and the focal length (log scale), each with a prior around the registration, moves the samples onto
their edges. The search range shrinks round by round and the model is rendered again at the refined pose between
rounds.

The result is kept only when it explains the photo clearly better and stays a polish: the share of samples with a
photo edge within ``support_px`` grows by at least ``min_support_gain`` (and in proportion more for an outline moved
by more than ``free_image_shift_rel`` of the width: a far pull needs clear evidence), the camera turns by at most
``max_rotation_deg``, its centre moves by at most ``max_shift_rel`` of the depth and the outline by at most
``max_image_shift_rel`` of the width. Otherwise the registration stands as solved; :class:`AlignResult` says why.
On close-ups of heavy texture (brick, printed hoarding) the search locks onto texture as often as onto outlines
(BENCHMARKS 'model outline polish'), which is why the register node polishes fixed cameras' frames and, of the phone
photos, only anchored ones, with their clicks.

An anchored photo's accepted clicks can be fitted together with the edges (``clicks``): each click a residual over
``click_sigma_px``, the edge samples capped to ``edge_effective_samples`` independent ones. A dozen clicks in a strip
of a close-up leave the camera free to turn about them (1-3 deg on the synthetic sites' phones); the outlines
elsewhere in the photo pin that turn, while the clicks keep the texture from pulling the pose away from what the
user clicked. The clicks' RMS then bounds the result (``click_gate_px``) instead of the turn and shift limits.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.modelview import GROUND_INDEX, ModelView
from nodes.register.bimdepth import MeshDepthLookup
from schemas.messages import Intrinsics

F64 = NDArray[np.float64]


class AlignParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Parameters of :func:`refine_pose` (pixels at the work resolution unless named otherwise)."""

    work_width_px: int = 960
    """Photo and render are read at this width (aspect kept; smaller photos at their own size)."""
    sample_step_px: float = 4.0
    """One edge sample per cell of this size."""
    max_samples: int = 3000
    min_samples: int = 60
    crease_shade: float = 0.02
    """Neighbouring pixels of one element whose flat face shades differ by more than this lie on a crease (an edge
    where the element's faces turn)."""
    depth_step_rel: float = 0.02
    """A relative depth jump above this between neighbouring pixels is an edge (one element folding behind itself)."""
    search_px: tuple[float, ...] = (20.0, 10.0, 5.0, 3.0)
    """Search half-range of each round (the model is rendered again at the start of each round)."""
    iterations: int = 4
    """Gauss-Newton steps per round (the samples search again after each)."""
    min_gradient: float = 12.0
    """Least intensity gradient (Sobel of the 0-255 grey image, blurred with sigma 1 px) along the normal that counts
    as a photo edge."""
    relative_gradient: float = 0.3
    """... and at least this share of the strongest gradient along the sample's search line."""
    tukey_c: float = 4.685
    min_sigma_px: float = 0.7
    refine_focal: bool = True
    focal_sigma_rel: float = 0.03
    """Prior on the focal length's change (relative standard deviation)."""
    rotation_sigma_deg: float = 0.5
    shift_sigma_rel: float = 0.01
    """Priors on the pose's change (per axis; the translation's as a share of the samples' median depth): a
    registration is close, and along the directions the outlines hardly fix (a narrow view turning and sliding
    together) the pose stays where the features and clicks put it."""
    match: str = "nearest"
    """Which photo edge a sample takes: ``nearest`` peak or ``strongest`` peak on its search line."""
    support_px: float = 1.5
    min_support_gain: float = 0.05
    """The refinement is kept when the supported share grows by at least this (absolute) ..."""
    free_image_shift_rel: float = 0.0025
    """... and, for a larger move of the outline (mean, share of the image width), by that much more in proportion:
    a larger pull needs clearer evidence (texture or clutter mistaken for the outline pulls far on little)."""
    max_rotation_deg: float = 1.5
    max_shift_rel: float = 0.1
    """Largest camera-centre move as a share of the median depth of the samples."""
    max_image_shift_rel: float = 0.01
    """Largest mean move of the samples' projections as a share of the image width: the refinement polishes a
    registration, it does not replace one."""
    click_sigma_px: float = 2.0
    """With anchor clicks (:func:`refine_pose` ``clicks``): a click's standard deviation per axis (full-resolution
    pixels)."""
    edge_effective_samples: float = 100.0
    """With anchor clicks: the edge samples together weigh as this many independent ones (neighbouring samples of
    one outline err together; without this cap a few thousand samples would outvote a dozen clicks)."""
    click_gate_px: float = 4.0
    """With anchor clicks: the refinement is kept only when the clicks' RMS stays within this (full-resolution
    pixels; or within their RMS at the start when that is larger); the turn and shift bounds do not apply."""
    ground_steps: bool = False
    """Depth steps between two ground-plane pixels count as edges. Off: far off, grazing ground steps by more than
    ``depth_step_rel`` between neighbouring pixels, a band of false edges along the horizon (on until 2026-12-07;
    BENCHMARKS 'model outline polish (no ground steps, 2026-12-07)')."""
    same_view_deg: float = 0.1
    same_view_m: float = 0.1
    """Two registrations of one fixed camera within this turn and centre move (and 1 % of focal) are one view: its
    frames share the first frame's polish (:func:`same_view`)."""


@dataclass
class EdgeSamples:
    """Model edge samples seen from one camera: world points (N, 3) m and unit image normals (N, 2)."""

    point_in_world_m: F64
    normal_px: F64


@dataclass
class AlignResult:
    """Outcome of :func:`refine_pose`."""

    world_from_camera: F64
    intrinsics: Intrinsics
    accepted: bool
    reason: str
    samples: int = 0
    support_before: float = 0.0
    support_after: float = 0.0
    rotation_deg: float = 0.0
    shift_m: float = 0.0
    focal_change_rel: float = 0.0
    image_shift_rel: float = 0.0
    """Mean move of the samples' projections (share of the image width)."""
    residual_px: float = float("nan")
    """Robust scale of the final residuals (work pixels)."""
    history: list[tuple[float, float]] = field(default_factory=list)
    """(search range, supported share) after each round."""
    click_rms_px: tuple[float, float] = (float("nan"), float("nan"))
    """With clicks: their RMS (full-resolution px) at the start and at the refined camera."""


def work_size(intr: Intrinsics, work_width_px: int) -> tuple[int, int]:
    w = min(int(intr.width_px), int(work_width_px))
    return w, max(1, int(round(intr.height_px * w / intr.width_px)))


def edge_samples(
    view: ModelView,
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    params: AlignParams,
    rng: np.random.Generator | None = None,
) -> EdgeSamples:
    """Edges of the model as the camera ``intr`` (work resolution, distortion ignored for the render: edges are
    points in the world) at ``world_from_camera`` (4, 4) sees them, one sample per ``sample_step_px`` cell."""
    pin = msgspec.structs.replace(intr, k1=0.0, k2=0.0)
    wfc = np.asarray(world_from_camera, np.float64)
    res = view.rasterizer.render_undistorted(view.scene, pin, wfc, view.visible(elements), ground_z_m)
    ids = res.ids.astype(np.int64)
    depth = np.where(res.depth_m > 0, res.depth_m, np.inf).astype(np.float32)
    shade = res.shade
    h, w = ids.shape
    edge = np.zeros((h, w), bool)
    for axis in (0, 1):
        sa = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        sb = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        za, zb = depth[sa], depth[sb]
        fin = np.isfinite(za) & np.isfinite(zb)
        with np.errstate(invalid="ignore"):
            step = fin & (np.abs(za - zb) > params.depth_step_rel * np.minimum(za, zb))
        if not params.ground_steps:
            step &= (ids[sa] != GROUND_INDEX) | (ids[sb] != GROUND_INDEX)
        # faces turning within one element: their flat shades differ (two-sided Lambert under a fixed light)
        crease = fin & (ids[sa] == ids[sb]) & (np.abs(shade[sa] - shade[sb]) > params.crease_shade)
        # the ground's far rim against the sky is no edge of anything
        rim = ((ids[sa] == GROUND_INDEX) & (ids[sb] == 0)) | ((ids[sa] == 0) & (ids[sb] == GROUND_INDEX))
        e = ((ids[sa] != ids[sb]) & ~rim) | step | crease
        edge[sa] |= e
        edge[sb] |= e
    edge[[0, -1], :] = False
    edge[:, [0, -1]] = False
    # the point on an edge is on its near side: the smallest depth of the 3x3 neighbourhood
    near = cv2.erode(depth, np.ones((3, 3), np.uint8))
    edge &= np.isfinite(near)
    # the edge's normal: the structure tensor of the blurred edge map (its main axis is across the edge)
    em = cv2.GaussianBlur(edge.astype(np.float32), (0, 0), 1.5)
    gx = cv2.Sobel(em, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(em, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), 2.0)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), 2.0)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), 2.0)
    v, u = np.nonzero(edge)
    if len(u) == 0:
        return EdgeSamples(np.zeros((0, 3)), np.zeros((0, 2)))
    # one sample per cell (the first in random order)
    rng = rng or np.random.default_rng(0)
    order = rng.permutation(len(u))
    u, v = u[order], v[order]
    cell = (v // params.sample_step_px).astype(np.int64) * (w + 1) + (u // params.sample_step_px).astype(np.int64)
    _, first = np.unique(cell, return_index=True)
    u, v = u[first], v[first]
    a, b, c = jxx[v, u], jxy[v, u], jyy[v, u]
    theta = 0.5 * np.arctan2(2.0 * b, a - c)  # main axis of [[a, b], [b, c]]
    lam1 = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b**2)
    lam2 = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b**2)
    straight = lam1 > 3.0 * np.maximum(lam2, 1e-12)  # corners and clutter have no single normal
    u, v, theta = u[straight], v[straight], theta[straight]
    if len(u) > params.max_samples:
        keep = rng.choice(len(u), params.max_samples, replace=False)
        u, v, theta = u[keep], v[keep], theta[keep]
    z = near[v, u].astype(np.float64)
    xy = cam.pixels_to_normalized(pin, np.c_[u, v].astype(np.float64))
    p_cam = np.c_[xy, np.ones(len(xy))] * z[:, None]
    p_world = p_cam @ wfc[:3, :3].T + wfc[:3, 3]
    return EdgeSamples(p_world, np.c_[np.cos(theta), np.sin(theta)])


def _gradients(gray: NDArray[np.generic]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    g = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), 1.0)
    gx = np.asarray(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), np.float32) / np.float32(4.0)
    gy = np.asarray(cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3), np.float32) / np.float32(4.0)
    return gx, gy


def search_edges(
    gx: NDArray[np.float32],
    gy: NDArray[np.float32],
    pixels_px: F64,
    normals: F64,
    half_range_px: float,
    params: AlignParams,
) -> F64:
    """Signed offset (N,) along each normal from ``pixels_px`` (N, 2) to the nearest photo edge within
    ``half_range_px`` (NaN where none): a local maximum of |gradient . normal| at least ``min_gradient`` and
    ``relative_gradient`` of the line's strongest."""
    n = len(pixels_px)
    out = np.full(n, np.nan)
    if n == 0:
        return out
    r = int(np.ceil(half_range_px))
    s = np.arange(-r, r + 1, dtype=np.float32)
    px = pixels_px.astype(np.float32)
    nn = normals.astype(np.float32)
    mx = px[:, 0:1] + s[None, :] * nn[:, 0:1]
    my = px[:, 1:2] + s[None, :] * nn[:, 1:2]
    sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    g = np.abs(sx * nn[:, 0:1] + sy * nn[:, 1:2])
    peak = np.zeros_like(g, dtype=bool)
    peak[:, 1:-1] = (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] > g[:, 2:])
    strong = g >= np.maximum(params.min_gradient, params.relative_gradient * g.max(axis=1, keepdims=True))
    ok = peak & strong & (np.abs(s)[None, :] <= half_range_px)
    if params.match == "strongest":
        dist = np.where(ok, -g + 1e-3 * np.abs(s)[None, :], np.inf)
    else:
        dist = np.where(ok, np.abs(s)[None, :], np.inf)
    k = np.argmin(dist, axis=1)
    found = np.isfinite(dist[np.arange(n), k])
    rows = np.nonzero(found)[0]
    kk = k[rows]
    # sub-pixel: the parabola through the peak and its neighbours
    g0, g1, g2 = g[rows, kk - 1], g[rows, kk], g[rows, kk + 1]
    den = g0 - 2.0 * g1 + g2
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(np.abs(den) > 1e-6, 0.5 * (g0 - g2) / den, 0.0)
    out[rows] = s[kk] + np.clip(frac, -0.5, 0.5)
    return out


def _project(intr: Intrinsics, cfw: F64, pts: F64, x: F64) -> F64:
    """Pixels (N, 2) of ``pts`` (N, 3) with the update ``x`` = (rotation vector (3), translation (3), log focal
    scale) applied in the camera frame."""
    R = cam.rodrigues_to_matrix(x[:3])
    p = (pts @ cfw[:3, :3].T + cfw[:3, 3]) @ R.T + x[3:6]
    f = float(np.exp(x[6]))
    i2 = msgspec.structs.replace(intr, f_px=intr.f_px * f)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = p[:, :2] / p[:, 2:3]
    xy[p[:, 2] <= 0] = np.nan
    return cam.normalized_to_pixels(i2, xy)


def _tukey(r: F64, c: float) -> F64:
    return np.where(np.abs(r) < c, (1.0 - (r / c) ** 2) ** 2, 0.0)


def _solve(
    intr: Intrinsics,
    cfw: F64,
    samples: EdgeSamples,
    gx: NDArray[np.float32],
    gy: NDArray[np.float32],
    half: float,
    params: AlignParams,
    x: F64,
    depth_m: float,
    clicks: tuple[F64, F64, float] | None = None,
) -> tuple[F64, float, float]:
    """Gauss-Newton steps from ``x`` (7,) at one search range; returns (x, supported share, residual scale).
    ``clicks``: (pixels (N, 2) at the work resolution, world points (N, 3), sigma px) fitted beside the edges."""
    pts, nrm = samples.point_in_world_m, samples.normal_px
    n_par = 7 if params.refine_focal else 6
    sigma = max(half / 2.0, params.min_sigma_px)
    for _ in range(params.iterations):
        p0 = _project(intr, cfw, pts, x)
        off = search_edges(gx, gy, p0, nrm, half, params)
        ok = np.isfinite(off) & np.isfinite(p0).all(axis=1)
        if ok.sum() < params.min_samples:
            break
        target = p0[ok] + off[ok, None] * nrm[ok]
        mad = 1.4826 * float(np.median(np.abs(off[ok])))
        sigma = max(mad, params.min_sigma_px)
        w = _tukey(off[ok] / sigma, params.tukey_c)
        r0 = -off[ok]  # residual = normal . (projection - target)
        J = np.zeros((int(ok.sum()), n_par))
        eps = 1e-6
        for k in range(n_par):
            dx = np.zeros(7)
            dx[k] = eps
            pk = _project(intr, cfw, pts[ok], x + dx)
            J[:, k] = np.sum((pk - p0[ok]) * nrm[ok], axis=1) / eps
        A = J.T @ (w[:, None] * J)
        g = J.T @ (w * r0)
        prior = [np.radians(params.rotation_sigma_deg)] * 3 + [params.shift_sigma_rel * depth_m] * 3
        prior += [params.focal_sigma_rel] if params.refine_focal else []
        if clicks is not None:
            # normalised units (each residual over its sigma); the edges weigh as edge_effective_samples samples
            scale = min(1.0, params.edge_effective_samples / max(float(np.sum(w)), 1.0)) / sigma**2
            A, g = A * scale, g * scale
            Ac, gc = _click_normal(intr, cfw, clicks, x, n_par)
            A, g = A + Ac, g + gc
        for k, sd in enumerate(prior):
            lam = (sigma / sd) ** 2 if clicks is None else 1.0 / sd**2
            A[k, k] += lam
            g[k] += lam * x[k]
        A += 1e-9 * np.eye(n_par) * max(float(np.trace(A)), 1.0)
        try:
            step = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            break
        x = x.copy()
        x[:n_par] += step
        del target
        if np.max(np.abs(step[:3])) < 1e-6 and np.max(np.abs(step[3:6])) < 1e-5:
            break
    return x, support(intr, cfw, samples, gx, gy, x, params), sigma


def _click_normal(intr: Intrinsics, cfw: F64, clicks: tuple[F64, F64, float], x: F64, n_par: int) -> tuple[F64, F64]:
    """Normal equations (n_par, n_par), (n_par,) of the clicks' reprojection residuals over their sigma."""
    px, pts, sigma_px = clicks
    p0 = _project(intr, cfw, pts, x)
    r = (p0 - px).ravel() / sigma_px
    ok = np.isfinite(r)
    J = np.zeros((len(r), n_par))
    eps = 1e-6
    for k in range(n_par):
        dx = np.zeros(7)
        dx[k] = eps
        J[:, k] = (_project(intr, cfw, pts, x + dx) - p0).ravel() / sigma_px / eps
    J, r = J[ok], r[ok]
    return J.T @ J, J.T @ r


def support(
    intr: Intrinsics,
    cfw: F64,
    samples: EdgeSamples,
    gx: NDArray[np.float32],
    gy: NDArray[np.float32],
    x: F64,
    params: AlignParams,
) -> float:
    """Share of the samples with a photo edge within ``support_px`` of their projection."""
    if len(samples.point_in_world_m) == 0:
        return 0.0
    p = _project(intr, cfw, samples.point_in_world_m, x)
    off = search_edges(gx, gy, p, samples.normal_px, params.support_px, params)
    return float(np.mean(np.isfinite(off)))


def refine_pose(
    view: ModelView,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None = None,
    ground_z_m: float | None = None,
    params: AlignParams | None = None,
    clicks: tuple[F64, F64] | None = None,
) -> AlignResult:
    """Refine ``world_from_camera`` (4, 4) and the focal of ``intr`` (the photo's full-resolution camera) so that the
    model's edges (``elements`` standing; None: all) fall on the intensity edges of ``gray`` (H, W) (the photo,
    any resolution of the same aspect). ``clicks``: an anchored photo's accepted clicks (pixels (N, 2) at full
    resolution, model points (N, 3) m), fitted together with the edges; they then bound the result instead of the
    turn and shift limits (``click_gate_px``)."""
    p = params or AlignParams()
    wfc0 = np.asarray(world_from_camera, np.float64)
    ww, wh = work_size(intr, p.work_width_px)
    wi = cam.scaled_intrinsics(intr, ww, wh)
    img = gray if gray.shape[1] == ww else cv2.resize(gray, (ww, wh), interpolation=cv2.INTER_AREA)
    gx, gy = _gradients(img)
    x = np.zeros(7)
    cfw0 = cam.invert_rigid(wfc0)
    work_clicks = None
    if clicks is not None:
        s = ww / intr.width_px
        cpx, cpts = np.asarray(clicks[0], np.float64), np.asarray(clicks[1], np.float64)
        work_clicks = (s * (cpx + 0.5) - 0.5, cpts, p.click_sigma_px * s)
    samples = edge_samples(view, wi, wfc0, elements, ground_z_m, p)
    result = AlignResult(wfc0, intr, False, "", samples=len(samples.point_in_world_m))
    if len(samples.point_in_world_m) < p.min_samples:
        result.reason = f"only {len(samples.point_in_world_m)} model edge samples in view (< {p.min_samples})"
        return result
    result.support_before = support(wi, cfw0, samples, gx, gy, x, p)
    z = (samples.point_in_world_m @ cfw0[:3, :3].T + cfw0[:3, 3])[:, 2]
    depth_m = float(np.median(z[z > 0])) if np.any(z > 0) else 1.0
    sigma = float("nan")
    sup = result.support_before
    for k, half in enumerate(p.search_px):
        if k:  # render again at the refined pose (visibility, new edges)
            wfc_k = compose_update(cfw0, x)
            samples = edge_samples(view, _focal_scaled(wi, x), wfc_k, elements, ground_z_m, p)
            if len(samples.point_in_world_m) < p.min_samples:
                break
        x, sup, sigma = _solve(wi, cfw0, samples, gx, gy, half, p, x, depth_m, work_clicks)
        result.history.append((half, sup))
    wfc = compose_update(cfw0, x)
    result.rotation_deg = cam.rotation_angle_deg(wfc[:3, :3], wfc0[:3, :3])
    result.shift_m = float(np.linalg.norm(wfc[:3, 3] - wfc0[:3, 3]))
    result.focal_change_rel = float(np.exp(x[6]) - 1.0)
    result.residual_px = sigma
    # compare on the same footing: the final render's samples at the start pose and at the refined one
    before = support(wi, cfw0, samples, gx, gy, np.zeros(7), p) if len(samples.point_in_world_m) else 0.0
    result.support_before = min(result.support_before, before) if before else result.support_before
    result.support_after = sup
    if len(samples.point_in_world_m):
        moved = _project(wi, cfw0, samples.point_in_world_m, x) - _project(
            wi, cfw0, samples.point_in_world_m, np.zeros(7)
        )
        result.image_shift_rel = float(np.nanmean(np.linalg.norm(moved, axis=1))) / ww
    refusal = ""
    note = ""
    if clicks is not None:
        rms0 = cam.rms_click_error_px(intr, wfc0, *clicks)
        rms1 = cam.rms_click_error_px(_focal_scaled(intr, x), wfc, *clicks)
        result.click_rms_px = (rms0, rms1)
        note = f", clicks {rms0:.2f} -> {rms1:.2f} px"
        if not rms1 <= max(p.click_gate_px, rms0):
            refusal = f"clicks {rms0:.2f} -> {rms1:.2f} px (> {max(p.click_gate_px, rms0):.2f})"
    elif result.rotation_deg > p.max_rotation_deg:
        refusal = f"rotated {result.rotation_deg:.2f} deg (> {p.max_rotation_deg})"
    elif result.shift_m > p.max_shift_rel * depth_m:
        refusal = f"moved {result.shift_m:.2f} m (> {p.max_shift_rel:.0%} of the {depth_m:.1f} m depth)"
    elif result.image_shift_rel > p.max_image_shift_rel:
        refusal = (
            f"outline moved {100 * result.image_shift_rel:.2f} % of the width (> {100 * p.max_image_shift_rel:.2f} %)"
        )
    gain = p.min_support_gain  # with clicks they bound the move; without, a larger move needs a larger gain
    if clicks is None:
        gain *= max(1.0, result.image_shift_rel / p.free_image_shift_rel)
    if not refusal and sup < result.support_before + gain:
        refusal = f"edge support {result.support_before:.3f} -> {sup:.3f} (gain < {gain:.3f})"
    if refusal:
        result.reason = refusal
    else:
        result.accepted = True
        result.reason = f"edge support {result.support_before:.3f} -> {sup:.3f}{note}"
        result.world_from_camera = wfc
        result.intrinsics = _focal_scaled(intr, x)
    return result


def compose_update(cfw0: F64, x: F64) -> F64:
    """world_from_camera (4, 4) after the camera-frame update ``x`` (rotation vector, translation m, ...) of the
    camera_from_world ``cfw0``."""
    cfw = np.eye(4)
    R = cam.rodrigues_to_matrix(x[:3])
    cfw[:3, :3] = R @ cfw0[:3, :3]
    cfw[:3, 3] = R @ cfw0[:3, 3] + x[3:6]
    return cam.invert_rigid(cfw)


def _focal_scaled(intr: Intrinsics, x: F64) -> Intrinsics:
    return msgspec.structs.replace(intr, f_px=float(intr.f_px * np.exp(x[6])))


def polish(
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    world_from_camera: F64,
    capture_time_ns: int,
    params: AlignParams | None = None,
    clicks: tuple[F64, F64] | None = None,
) -> AlignResult:
    """:func:`refine_pose` on the register node's BIM view: the elements the schedule says stand at the capture
    time, over the terrain plane."""
    return refine_pose(
        lookup.view,
        gray,
        intr,
        world_from_camera,
        lookup.elements(capture_time_ns),
        lookup.ground_height_m,
        params,
        clicks,
    )


def same_view(
    world_from_camera_a: F64, intr_a: Intrinsics, world_from_camera_b: F64, intr_b: Intrinsics, params: AlignParams
) -> bool:
    """Whether two registrations (4x4 world_from_camera, m) are one fixed camera's one view: within
    ``params.same_view_deg``, ``params.same_view_m`` and 1 % of the focal, with the same image size."""
    if (intr_a.width_px, intr_a.height_px) != (intr_b.width_px, intr_b.height_px):
        return False
    if abs(intr_a.f_px / intr_b.f_px - 1.0) > 0.01:
        return False
    turn_deg = cam.rotation_angle_deg(world_from_camera_a[:3, :3], world_from_camera_b[:3, :3])
    shift_m = float(np.linalg.norm(world_from_camera_a[:3, 3] - world_from_camera_b[:3, 3]))
    return turn_deg <= params.same_view_deg and shift_m <= params.same_view_m


@dataclass(frozen=True)
class ViewPolish:
    """The outline polish of a fixed camera's view: its first frame's solved pose (4x4) and intrinsics, and the
    accepted polish (None: refused)."""

    solved: F64
    solved_intrinsics: Intrinsics
    result: AlignResult | None


class Polished(NamedTuple):
    """What :func:`polish_registration` made of a registration: the polished pose (4x4 world_from_camera, m) and
    intrinsics, or None for both when the polish refused (the registration stands as solved), and a note why."""

    world_from_camera: F64 | None
    intrinsics: Intrinsics | None
    note: str


class PolishPolicy(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Which registrations :func:`polish_registration` polishes (the streaming node's ``stream.model_align*`` and
    the batch command's ``--bim`` share it)."""

    fixed_cameras: bool = True
    phones: bool = False
    anchored_phones: bool = True


def polish_registration(
    lookup: MeshDepthLookup,
    gray: Callable[[], NDArray[np.uint8]],
    intr: Intrinsics,
    world_from_camera: F64,
    capture_time_ns: int,
    camera_id: str | None,
    clicks: tuple[F64, F64] | None,
    views: dict[str, ViewPolish],
    params: AlignParams,
    policy: PolishPolicy | None = None,
) -> Polished | None:
    """One registration (4x4 world_from_camera, m) polished by the model outline (:class:`Polished`, also when the
    polish refuses), or None when the policy leaves it. A fixed camera's (``camera_id``) frames of one
    view share the first frame's polish or refusal, kept in ``views`` (polished one by one they would each move a
    little while the camera stood still, and its time-lapse overlays would jitter). A phone photo with ``clicks``
    (accepted anchor clicks: pixels (N, 2), model points (N, 3) m) is polished with them. ``gray`` gives the photo
    (H, W) uint8 when needed. Raises RuntimeError / ValueError when the model cannot be rendered."""
    policy = policy or PolishPolicy()
    anchored_phone = camera_id is None and clicks is not None and policy.anchored_phones
    if not (policy.fixed_cameras if camera_id is not None else policy.phones or anchored_phone):
        return None
    seen = views.get(camera_id) if camera_id is not None else None
    if seen is not None and same_view(seen.solved, seen.solved_intrinsics, world_from_camera, intr, params):
        if seen.result is None:
            return Polished(None, None, "not polished (this camera view's polish was refused)")
        moved = seen.result.world_from_camera @ cam.invert_rigid(seen.solved) @ world_from_camera
        # same_view: the same image size and focal within 1 %
        note = f"polished by the model outline ({seen.result.reason}; this camera view's polish)"
        return Polished(moved, seen.result.intrinsics, note)
    res = polish(lookup, gray(), intr, world_from_camera, capture_time_ns, params, clicks if anchored_phone else None)
    if camera_id is not None:
        views[camera_id] = ViewPolish(world_from_camera, intr, res if res.accepted else None)
    if not res.accepted:
        return Polished(None, None, f"not polished: {res.reason}")
    return Polished(res.world_from_camera, res.intrinsics, f"polished by the model outline ({res.reason})")
