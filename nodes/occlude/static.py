"""Static occlusions (fence, ground over the basement, scaffolding, neighbours) (paper Sec. 4.1.2).

For each sparse 3D point observed in the photo, compare it with the model surface at its pixel:
it occludes the model when it is more than ``depth_margin_m`` closer to the camera than every
model surface around that pixel, or (within the margin) when its normal, estimated by PCA of its
nearest neighbours in the cloud, differs from the model's normal by more than
``normal_angle_deg`` (normals only where the neighbourhood is flat enough to trust). SLIC
superpixels are flooded where occluding points are at least ``vote_fraction`` of the points judged
in them (paper: any point), then the labels spread to the superpixels without points (sparse clouds
leave most of them empty): by default one harmonic (random-walker) solve over the superpixel graph,
affinity ``exp(-(dLab / harmonic_sigma_lab)^2)`` between adjacent superpixels, seeded by the flooded
(occluded) and judged-clear superpixels and by those mostly below the terrain, so a label runs across
a fence panel and its lettering but stops at a colour edge (``propagation="rounds"``: the greedy
spreading to similar neighbours for a few rounds). Model pixels whose surface lies below the site
terrain are occluded by the ground.

Only points the registration confirmed by epipolar-guided matching should be given (the node keeps the
SparseCloud points flagged ``SPARSE_POINT_VERIFIED``): a blind match of repeated texture triangulates
at a wrong depth and reprojects perfectly in its two views, and a point looked up on the BIM lies on
the model by construction. The mask is smoothed with a cross-bilateral
filter guided by the photo, limited to the projected model (nothing else can be occluded) and
upsampled with a guided filter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from constructaide.modelview import ModelMaps
from nodes.occlude.dynamic import upsample_mask

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class StaticParams:
    """Tuning of :func:`static_mask`. Sizes are in working-resolution pixels unless named otherwise."""

    depth_margin_m: float = 0.3
    normal_angle_deg: float = 30.0
    normal_neighbours: int = 12
    max_flatness: float = 0.05  # smallest PCA eigenvalue / sum: above it the normal is not trusted
    depth_window_px: int = 3  # model depth is the minimum over this window around the point
    slic_region_px: int = 14
    slic_ruler: float = 12.0
    slic_iterations: int = 4
    vote_fraction: float = 0.5  # flood a superpixel when occluding >= this fraction of its judged points
    propagate_rounds: int = 3  # spread labels to point-less superpixels of similar colour (0: paper, no spreading)
    propagate_lab_dist: float = 6.0  # max mean-Lab distance (OpenCV 8-bit Lab units) for spreading
    # "harmonic": one random-walker solve over the superpixel graph (see harmonic_labels); "rounds": greedy
    # spreading for propagate_rounds rounds (0: the paper, no spreading)
    propagation: Literal["harmonic", "rounds"] = "harmonic"
    harmonic_sigma_lab: float = 2.0
    harmonic_ground_seeds: bool = True  # superpixels mostly under the terrain seed the spreading as occluded
    bilateral_diameter_px: int = 9
    bilateral_sigma_color: float = 0.1
    bilateral_sigma_space_px: float = 4.0
    ground_margin_m: float = 0.05
    restrict_to_model: bool = True
    guided_radius_px: int = 8  # full-resolution pixels
    guided_eps: float = 1e-3
    min_points: int = 1


@dataclass
class StaticResult:
    """``mask``: uint8 (H, W) 0/255 at photo resolution; counts of judged and occluding points."""

    status: Literal["ok", "not_enough_views"]
    mask: U8
    num_points: int
    num_occluding: int


def estimate_point_normals(points_world_m: F64, k: int = 12) -> tuple[F32, F32]:
    """PCA normals (N, 3) and flatness (N,) (smallest eigenvalue / eigenvalue sum; 1/3 = isotropic)
    of each point from its ``k`` nearest neighbours. Fewer than 4 points: zero normals, flatness 1."""
    pts = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    if n < 4:
        return np.zeros((n, 3), np.float32), np.ones(n, np.float32)
    k = min(k, n)
    _, idx = cKDTree(pts).query(pts, k=k)
    nb = pts[idx]  # (N, k, 3)
    centred = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    evals, evecs = np.linalg.eigh(cov)  # ascending
    normals = evecs[:, :, 0]
    flatness = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-12)
    return normals.astype(np.float32), flatness.astype(np.float32)


def estimate_terrain_height(
    points_world_m: F64,
    normals: F32,
    flatness: F32,
    bin_m: float = 0.25,
    min_points: int = 30,
    footprint_xy_m: tuple[F64, F64] | None = None,
    footprint_margin_m: float = 1.0,
) -> float | None:
    """Height (world z, metres) of the most populated horizontal surface in the sparse cloud, taken as
    the site terrain; None when fewer than ``min_points`` flat points face up.

    The ground around a building site is the largest horizontal surface in view; its points are
    binned by z and the fullest bin (and its neighbours) gives the median height. With
    ``footprint_xy_m`` ((2,) min, (2,) max of the model in world x, y) points above the building's
    footprint (grown by ``footprint_margin_m``) are left out: floor slabs and roofs are horizontal too.
    """
    pts = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
    horizontal = (np.abs(normals[:, 2]) > 0.95) & (flatness < 0.05)
    if footprint_xy_m is not None:
        lo_xy = np.asarray(footprint_xy_m[0], np.float64) - footprint_margin_m
        hi_xy = np.asarray(footprint_xy_m[1], np.float64) + footprint_margin_m
        inside = np.all((pts[:, :2] >= lo_xy) & (pts[:, :2] <= hi_xy), axis=1)
        horizontal &= ~inside
    z = pts[horizontal, 2]
    if len(z) < min_points:
        return None
    lo = np.floor(z.min() / bin_m)
    idx = np.floor(z / bin_m - lo).astype(np.int64)
    counts = np.bincount(idx)
    best = int(np.argmax(counts))
    near = np.abs(idx - best) <= 1
    return float(np.median(z[near]))


def classify_points(
    points_world_m: F64,
    pixels_small: F64,
    camera_center_m: F64,
    maps: ModelMaps,
    normals: F32,
    flatness: F32,
    params: StaticParams,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Judge points against the model. Returns (judged, occluding), both bool (N,).

    ``pixels_small``: (N, 2) pixel of each point in the working image. A point is judged when its
    pixel shows model surface; occluding per the paper's heuristic (see module docstring).
    """
    h, w = maps.depth_m.shape
    n = len(points_world_m)
    judged = np.zeros(n, bool)
    occluding = np.zeros(n, bool)
    if n == 0:
        return judged, occluding
    ui = np.round(pixels_small[:, 0]).astype(np.int64)
    vi = np.round(pixels_small[:, 1]).astype(np.int64)
    inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    ui, vi = np.clip(ui, 0, w - 1), np.clip(vi, 0, h - 1)
    win = max(1, params.depth_window_px)
    depth_min = cv2.erode(maps.depth_m, np.ones((win, win), np.uint8), borderType=cv2.BORDER_REPLICATE)
    model_pt = maps.point_in_world_m[vi, ui].astype(np.float64)
    model_n = maps.normal_in_world[vi, ui].astype(np.float64)
    has = inside & np.isfinite(maps.depth_m[vi, ui])
    judged[:] = has
    # ranges along the viewing ray: the point's, the model's at the pixel and the nearest model's around it
    ray_p = points_world_m - camera_center_m
    r_p = np.linalg.norm(ray_p, axis=1)
    r_m = np.linalg.norm(model_pt - camera_center_m, axis=1)
    z_m = maps.depth_m[vi, ui].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_min = r_m * depth_min[vi, ui] / z_m
    closer = has & (r_min - r_p > params.depth_margin_m)
    near = has & (np.abs(r_m - r_p) <= params.depth_margin_m)
    cos_ang = np.abs(np.sum(normals.astype(np.float64) * model_n, axis=1))
    trusted = (flatness <= params.max_flatness) & (np.linalg.norm(model_n, axis=1) > 0.5)
    turned = near & trusted & (cos_ang < np.cos(np.radians(params.normal_angle_deg)))
    occluding[:] = closer | turned
    return judged, occluding


def superpixel_flood(
    photo_small: U8,
    pixels_small: F64,
    judged: NDArray[np.bool_],
    occluding: NDArray[np.bool_],
    params: StaticParams,
    seed_occluded: NDArray[np.bool_] | None = None,
) -> U8:
    """SLIC superpixels of the working photo flooded by occluding points, labels then spread to superpixels
    without points (``params.propagation``). ``seed_occluded`` (h, w): pixels known occluded without points (the
    ground rule), seeds for the harmonic spreading. uint8 (h, w) 0/1."""
    h, w = photo_small.shape[:2]
    lab = np.asarray(cv2.cvtColor(photo_small, cv2.COLOR_BGR2LAB), np.uint8)
    slic = cv2.ximgproc.createSuperpixelSLIC(lab, cv2.ximgproc.SLICO, params.slic_region_px, params.slic_ruler)
    slic.iterate(params.slic_iterations)
    labels = np.asarray(slic.getLabels(), np.int32)
    nlab = int(labels.max()) + 1
    ui = np.clip(np.round(pixels_small[:, 0]).astype(np.int64), 0, w - 1)
    vi = np.clip(np.round(pixels_small[:, 1]).astype(np.int64), 0, h - 1)
    lab_of = labels[vi, ui]
    n_occ = np.bincount(lab_of[occluding], minlength=nlab)
    n_judged = np.bincount(lab_of[judged], minlength=nlab)
    flooded = (n_occ >= 1) & (n_occ >= params.vote_fraction * n_judged)
    clear_seeds = bool(np.any(~flooded & (n_judged > 0)))
    if params.propagation == "harmonic" and clear_seeds:
        # (without a single clear superpixel the harmonic solution is "occluded" wherever a seed reaches:
        # the greedy rounds below are the safer spreading then)
        state = np.where(flooded, 1, np.where(n_judged > 0, -1, 0)).astype(np.int8)
        if seed_occluded is not None:  # e.g. the ground rule: superpixels mostly below the terrain
            weights = seed_occluded.ravel().astype(np.float64)
            frac = np.bincount(labels.ravel(), weights=weights, minlength=nlab).astype(np.float64)
            frac = frac / np.maximum(np.bincount(labels.ravel(), minlength=nlab), 1)
            state[(state == 0) & (frac > 0.5)] = 1
        flooded = harmonic_labels(labels, lab, state, params.harmonic_sigma_lab) > 0.5
    elif params.propagate_rounds > 0 and flooded.any():
        state = np.where(flooded, 1, np.where(n_judged > 0, -1, 0)).astype(np.int8)
        state = propagate_labels(labels, lab, state, params.propagate_rounds, params.propagate_lab_dist)
        flooded = state > 0
    return flooded[labels].astype(np.uint8)


def _superpixel_graph(labels: NDArray[np.int32], lab: U8) -> tuple[F64, NDArray[np.int64], F64]:
    """Mean Lab colour (n, 3) per superpixel, adjacent pairs (E, 2) (each once) and their colour distances (E,)."""
    n = int(labels.max()) + 1
    counts = np.maximum(np.bincount(labels.ravel(), minlength=n), 1).astype(np.float64)
    mean = np.stack(
        [
            np.bincount(labels.ravel(), weights=lab[..., c].ravel().astype(np.float64), minlength=n) / counts
            for c in range(3)
        ],
        axis=1,
    )
    pairs = np.concatenate(
        [
            np.stack([labels[:, :-1].ravel(), labels[:, 1:].ravel()], axis=1),
            np.stack([labels[:-1, :].ravel(), labels[1:, :].ravel()], axis=1),
        ]
    )
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    pairs = np.unique(np.sort(pairs, axis=1), axis=0).astype(np.int64)
    dist = np.linalg.norm(mean[pairs[:, 0]] - mean[pairs[:, 1]], axis=1)
    return mean, pairs, dist


def harmonic_labels(labels: NDArray[np.int32], lab: U8, state: NDArray[np.int8], sigma_lab: float) -> F64:
    """Occlusion probability (n,) per superpixel by harmonic label propagation (the random-walker / Gaussian-field
    solution): superpixels with points keep their label (``state`` +1 occluded -> 1, -1 clear -> 0), every other
    one takes the affinity-weighted mean of its neighbours, affinity ``exp(-(dLab / sigma_lab)^2)`` between
    adjacent superpixels. One sparse solve over all of them, so a label crosses a fence panel's lettering when the
    panel colour continues behind it, and stops at a colour edge; superpixels connected to no label get 0."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    n = len(state)
    _, pairs, dist = _superpixel_graph(labels, lab)
    w = np.exp(-((dist / max(sigma_lab, 1e-6)) ** 2)) + 1e-9
    W = sp.coo_matrix((np.r_[w, w], (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])), (n, n)).tocsr()
    f = np.where(state > 0, 1.0, 0.0)
    known = state != 0
    unknown = np.flatnonzero(~known)
    if len(unknown) == 0 or not known.any():
        return f
    L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
    L_uu = L[unknown][:, unknown].tocsc()
    rhs = -(L[unknown][:, np.flatnonzero(known)] @ f[known])
    # a small ridge towards 0 keeps components without any label solvable and at "not occluded"
    f[unknown] = spla.spsolve(L_uu + sp.identity(len(unknown), format="csc") * 1e-6, rhs)
    return np.clip(f, 0.0, 1.0)


def propagate_labels(
    labels: NDArray[np.int32], lab: U8, state: NDArray[np.int8], rounds: int, max_dist: float
) -> NDArray[np.int8]:
    """Give superpixels without points (state 0) the state (+1 occluded, -1 clear) of their most
    similar adjacent labelled superpixel when their mean Lab colours are closer than ``max_dist``;
    repeated ``rounds`` times so labels spread along uniform surfaces (a fence panel, the ground)."""
    _, once, dist_once = _superpixel_graph(labels, lab)
    pairs = np.concatenate([once, once[:, ::-1]])  # (E, 2): (unknown candidate, neighbour), both directions
    dist = np.concatenate([dist_once, dist_once])
    state = state.copy()
    for _ in range(rounds):
        ok = (state[pairs[:, 0]] == 0) & (state[pairs[:, 1]] != 0) & (dist < max_dist)
        if not ok.any():
            break
        cand, nb, d = pairs[ok, 0], pairs[ok, 1], dist[ok]
        order = np.lexsort((d, cand))  # per candidate, nearest neighbour first
        cand, nb = cand[order], nb[order]
        first = np.ones(len(cand), bool)
        first[1:] = cand[1:] != cand[:-1]
        state[cand[first]] = state[nb[first]]
    return state


def below_terrain(maps: ModelMaps, terrain_height_m: float, margin_m: float) -> NDArray[np.bool_]:
    """Model pixels whose visible surface lies below the terrain plane z = terrain_height_m."""
    z = maps.point_in_world_m[..., 2]
    return np.isfinite(z) & (z < terrain_height_m - margin_m)


def static_mask(
    photo_full: U8,
    photo_small: U8,
    maps: ModelMaps,
    camera_center_m: F64,
    points_world_m: F64,
    pixels_full: F64,
    normals: F32,
    flatness: F32,
    terrain_height_m: float | None,
    params: StaticParams | None = None,
) -> StaticResult:
    """Static-occluder mask of one photo.

    ``photo_full``/``photo_small``: uint8 BGR at photo and working size; ``maps``: model maps at the
    working size; ``points_world_m`` (N, 3) the cloud points observed in the photo with their
    observed full-resolution pixels ``pixels_full`` (N, 2) and PCA ``normals``/``flatness`` (N,).
    """
    params = params or StaticParams()
    H, W = photo_full.shape[:2]
    h, w = photo_small.shape[:2]
    if maps.depth_m.shape != (h, w):
        raise ValueError(f"model maps {maps.depth_m.shape} do not match the working photo {(h, w)}")
    sx, sy = w / W, h / H
    pts = np.asarray(points_world_m, dtype=np.float64).reshape(-1, 3)
    px = np.asarray(pixels_full, dtype=np.float64).reshape(-1, 2)
    pixels_small = np.stack([sx * (px[:, 0] + 0.5) - 0.5, sy * (px[:, 1] + 0.5) - 0.5], axis=1)
    judged, occluding = classify_points(
        pts, pixels_small, np.asarray(camera_center_m, np.float64), maps, normals, flatness, params
    )
    ground = (
        below_terrain(maps, terrain_height_m, params.ground_margin_m)
        if terrain_height_m is not None
        else np.zeros((h, w), bool)
    )
    if int(judged.sum()) < params.min_points and not ground.any():
        return StaticResult("not_enough_views", np.zeros((H, W), np.uint8), int(judged.sum()), 0)
    flood = (
        superpixel_flood(
            photo_small,
            pixels_small,
            judged,
            occluding,
            params,
            ground & maps.has_model if params.harmonic_ground_seeds else None,
        )
        if occluding.any() or (params.propagation == "harmonic" and params.harmonic_ground_seeds and ground.any())
        else np.zeros((h, w), np.uint8)
    )
    soft = np.maximum(flood.astype(np.float32), ground.astype(np.float32))
    photo_f = photo_small.astype(np.float32) / 255.0
    soft = np.asarray(
        cv2.ximgproc.jointBilateralFilter(
            photo_f, soft, params.bilateral_diameter_px, params.bilateral_sigma_color, params.bilateral_sigma_space_px
        ),
        np.float32,
    )
    if params.restrict_to_model:
        soft = soft * maps.has_model.astype(np.float32)
    mask = upsample_mask(soft, photo_full, params.guided_radius_px, params.guided_eps)
    return StaticResult("ok", mask, int(judged.sum()), int(occluding.sum()))
