"""Multi-view triangulation of tracks (midpoint of rays) with angle, reprojection and cheirality checks."""

from __future__ import annotations

import numpy as np

from constructaide import camera as cam
from nodes.register.config import MapperConfig
from nodes.register.recon import Reconstruction, flat_obs, obs_pixels, obs_threshold_per_image


def pixel_rays(recon: Reconstruction, img_idx: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (M, 3) and unit world ray directions (M, 3) of pixels (M, 2) in images ``img_idx``."""
    centers = np.zeros((len(img_idx), 3))
    dirs = np.zeros((len(img_idx), 3))
    for i in np.unique(img_idx):
        sel = img_idx == i
        im = recon.images[i]
        xy = cam.pixels_to_normalized(im.intrinsics, px[sel])
        d = np.c_[xy, np.ones(len(xy))] @ im.world_from_camera[:3, :3].T
        dirs[sel] = d / np.linalg.norm(d, axis=1, keepdims=True)
        centers[sel] = im.world_from_camera[:3, 3]
    return centers, dirs


def _midpoints(
    recon: Reconstruction, candidates: np.ndarray, cfg: MapperConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint triangulation of ``candidates`` (tracks) from their observations in registered images: (tracks
    with >= 2 such views (n,), points (n, 3), accepted (n,): rays spanning >= ``min_triangulation_angle_deg``,
    reprojecting within threshold in front of every camera)."""
    reg = np.array([im.registered for im in recon.images], dtype=bool)
    empty = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, bool))
    tids_a, iids_a, fids_a = flat_obs(recon, candidates)
    keep = reg[iids_a] if len(iids_a) else np.zeros(0, bool)
    tids_a, iids_a, fids_a = tids_a[keep], iids_a[keep], fids_a[keep]
    if len(tids_a) == 0:
        return empty
    uniq, inv, cnt = np.unique(tids_a, return_inverse=True, return_counts=True)
    two = cnt[inv] >= 2
    tids_a, iids_a, fids_a = tids_a[two], iids_a[two], fids_a[two]
    if len(tids_a) == 0:
        return empty
    px = obs_pixels(recon, iids_a, fids_a)
    C, D = pixel_rays(recon, iids_a, px)
    uniq, inv = np.unique(tids_a, return_inverse=True)
    n = len(uniq)
    M = np.eye(3)[None] - D[:, :, None] * D[:, None, :]
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(A, inv, M)
    np.add.at(b, inv, np.einsum("nij,nj->ni", M, C))
    det = np.linalg.det(A)
    good = np.abs(det) > 1e-12
    X = np.full((n, 3), np.nan)
    X[good] = np.linalg.solve(A[good], b[good][:, :, None])[:, :, 0]
    # Ray span: max angle between any ray and the track's first ray, as a bound.
    first = np.zeros(n, int)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    cosang = np.sum(D * D[first][inv], axis=1)
    min_cos = np.ones(n)
    np.minimum.at(min_cos, inv, cosang)
    wide = min_cos < np.cos(np.radians(cfg.min_triangulation_angle_deg))
    # Reprojection and cheirality per observation.
    bad = np.zeros(n, bool)
    thr = obs_threshold_per_image(recon, cfg)
    for i in np.unique(iids_a):
        sel = np.nonzero(iids_a == i)[0]
        im = recon.images[i]
        proj, z = cam.project_points(im.intrinsics, cam.invert_rigid(im.world_from_camera), X[inv[sel]])
        e = np.linalg.norm(proj - px[sel], axis=1)
        fail = ~(np.isfinite(e) & (e < thr[i]) & (z > 0))
        np.logical_or.at(bad, inv[sel], fail)
    return uniq, X, good & wide & ~bad


def triangulate_tracks(
    recon: Reconstruction, cfg: MapperConfig, retriangulate: bool = False, only: list[int] | None = None
) -> int:
    """Triangulate untriangulated tracks seen by >= 2 registered images (midpoint of rays, all at once), keeping
    those whose rays span >= ``min_triangulation_angle_deg`` and that reproject within threshold in front of
    every camera. ``retriangulate`` redoes triangulated ones too (never model points); ``only`` restricts to these
    tracks. Returns the number of points (re)made."""
    candidates = np.arange(len(recon.track_obs)) if only is None else np.asarray(only, dtype=np.int64)
    if len(candidates) == 0 or not recon.registered_indices():
        return 0
    if retriangulate:
        candidates = candidates[~recon.point_from_model[candidates]]
    else:
        candidates = candidates[~np.all(np.isfinite(recon.points[candidates]), axis=1)]
    uniq, X, accept = _midpoints(recon, candidates, cfg)
    if len(uniq) == 0:
        return 0
    if retriangulate:
        recon.points[uniq[~accept]] = np.nan
    acc_t = uniq[accept]
    new = len(acc_t) if retriangulate else int(np.sum(~np.all(np.isfinite(recon.points[acc_t]), axis=1)))
    recon.points[acc_t] = X[accept]
    # Colour from each track's first observation (in dict order).
    first_obs = np.array([next(iter(recon.track_obs[t].items())) for t in acc_t.tolist()], np.int64).reshape(-1, 2)
    for i in np.unique(first_obs[:, 0]):
        cols = recon.images[i].colors_rgb_u8
        if cols is not None:
            sel = first_obs[:, 0] == i
            recon.colors[acc_t[sel]] = cols[first_obs[sel, 1]]
    return new


def confirm_model_points(recon: Reconstruction, tracks: list[int] | np.ndarray, cfg: MapperConfig) -> int:
    """Confirm the model points (BIM depth) among ``tracks`` that a triangulation from their registered views
    reproduces within ``cfg.model_point_tolerance`` of their distance to the nearest observing camera (something
    unmodelled in front of the model gives a feature the wrong depth; such a point stays unconfirmed). Returns how
    many were confirmed."""
    t = np.asarray(tracks, np.int64).ravel()
    t = t[recon.point_from_model[t] & ~recon.point_confirmed[t]] if len(t) else t
    uniq, X, accept = _midpoints(recon, t, cfg)
    if not accept.any():
        return 0
    uniq, X = uniq[accept], X[accept]
    P = recon.points[uniq]
    rng = np.full(len(uniq), np.inf)
    for k, tr in enumerate(uniq.tolist()):
        for i in recon.track_obs[tr]:
            im = recon.images[i]
            if im.registered:
                rng[k] = min(rng[k], float(np.linalg.norm(P[k] - im.world_from_camera[:3, 3])))
    ok = np.linalg.norm(X - P, axis=1) < cfg.model_point_tolerance * rng
    recon.point_confirmed[uniq[ok]] = True
    return int(ok.sum())


def drop_runaway_points(recon: Reconstruction, tracks: np.ndarray, factor: float = 1e3) -> int:
    """Untriangulate (NaN) those of ``tracks`` whose point is not finite or lies more than ``factor`` times the
    median point-to-camera distance of ``tracks`` from every registered camera that observes it. A point carried on
    an anchor's ray whose other views hardly constrain its depth can run off towards infinity, where it still
    reprojects (its rays are then nearly parallel) and a trust-region step no longer moves it; seen on the default
    synthetic site (a depth of 1e141). Its track stays and can be triangulated again. Returns the number dropped."""
    tracks = np.asarray(tracks, np.int64)
    if len(tracks) == 0:
        return 0
    reg = np.array([im.registered for im in recon.images], dtype=bool)
    t_ids, i_ids, _ = flat_obs(recon, tracks)
    on = reg[i_ids] if len(i_ids) else np.zeros(0, bool)
    t_ids, i_ids = t_ids[on], i_ids[on]
    centres = np.array([im.pose[:3, 3] if im.registered else np.zeros(3) for im in recon.images])
    with np.errstate(over="ignore", invalid="ignore"):
        dist_m = np.linalg.norm(recon.points[t_ids] - centres[i_ids], axis=1)
    dist_m = np.where(np.isfinite(dist_m), dist_m, np.inf)
    nearest_m = np.full(len(recon.points), np.inf)
    np.minimum.at(nearest_m, t_ids, dist_m)
    nearest_m = nearest_m[tracks]
    finite = np.isfinite(nearest_m)
    if not np.any(finite):
        return 0
    scale_m = float(np.median(nearest_m[finite]))
    observed = np.isin(tracks, t_ids)
    bad = tracks[observed & ~(nearest_m <= factor * scale_m)]
    recon.points[bad] = np.nan
    return len(bad)
