"""EXIF GPS safeguards against automatic poses that contradict the photos' GPS positions."""

from __future__ import annotations

import numpy as np

from constructaide.geo import enu_m, gps_distance_residuals_m, horizontal_distance_m
from nodes.register.config import MapperConfig
from nodes.register.recon import Reconstruction
from schemas.messages import GeoPoint


def _gps_positions(references: list[tuple[np.ndarray, GeoPoint]], same_position_m: float) -> list[list[int]]:
    """Indices of ``references`` grouped by GPS position (greedy: within ``same_position_m`` of a group's first)."""
    groups: list[list[int]] = []
    for k, (_, g) in enumerate(references):
        for members in groups:
            if horizontal_distance_m(references[members[0]][1], g) <= same_position_m:
                members.append(k)
                break
        else:
            groups.append([k])
    return groups


def _enu_m(g: GeoPoint, origin: GeoPoint) -> np.ndarray:
    """East / north metres (2,) of ``g`` from ``origin`` (:func:`constructaide.geo.enu_m`)."""
    return np.array(enu_m(g, origin))


def gps_median_residual_m(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    same_position_m: float = 1.0,
) -> float:
    """Median GPS distance residual (m) of a camera at ``centre_in_world_m`` (3,) with ``gps`` against
    ``references`` (camera centre (3,) world m, GPS): |horizontal distance between the centres - distance between
    the GPS positions| (:func:`constructaide.geo.gps_distance_residuals_m`, needs no georeference of the model).

    References whose GPS positions lie within ``same_position_m`` of each other (the frames of one fixed camera)
    count once, with the median of their residuals; the result is the median over those positions (20 frames of
    one camera would otherwise outvote every other direction). NaN without references."""
    if not references:
        return float("nan")
    centres = np.array([np.asarray(c, np.float64)[:3] for c, _ in references])
    res = gps_distance_residuals_m(np.asarray(centre_in_world_m, np.float64), gps, centres, [g for _, g in references])
    return float(np.median([np.median(res[m]) for m in _gps_positions(references, same_position_m)]))


def gps_heading_residual_m(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    same_position_m: float = 1.0,
    inlier_m: float = 15.0,
    min_span_m: float = 30.0,
    sigma_m: float = 3.0,
) -> tuple[float, float]:
    """Orientation-aware GPS check of a camera at ``centre_in_world_m`` (3,) with ``gps``: (horizontal distance (m)
    between its GPS position and its centre carried into east/north metres by the rigid motion (rotation about z,
    translation) fitted to ``references``, that fit's own uncertainty at the candidate (3 sigma, m)).

    Distances alone (:func:`gps_median_residual_m`) cannot tell a model from its mirror image: a camera mirrored
    across the line through two references keeps its distances to both (synthetic site: a west camera placed by PnP
    on repeated hoarding print 64 m off, at the east camera's place, keeps its distances to the north and south
    cameras). The z-up model frame is right-handed like east/north/up, so a rigid motion without reflection relates
    them; it is fitted (least median of squares over pairs of positions, then least squares on the positions within
    ``inlier_m``) to the reference positions (grouped as in gps_median_residual_m, model centre = median of the
    group's). Its uncertainty at the candidate is 3 ``sigma_m`` (GPS error) times (1 / sqrt(n) + distance from the
    positions' centroid / their spread (root sum of squares)). (NaN, NaN) when the inlier positions span less than
    ``min_span_m`` (the heading is then too uncertain)."""
    nan = (float("nan"), float("nan"))
    groups = _gps_positions(references, same_position_m)
    if len(groups) < 2:
        return nan
    origin = references[0][1]
    enu = np.array([_enu_m(references[m[0]][1], origin) for m in groups])
    xy = np.array([np.median([np.asarray(references[k][0], np.float64)[:2] for k in m], axis=0) for m in groups])
    n = len(groups)
    ii, jj = np.triu_indices(n, 1)
    sep = np.linalg.norm(enu[jj] - enu[ii], axis=1)
    keep = sep >= 0.5 * min_span_m
    ii, jj = ii[keep], jj[keep]
    if len(ii) == 0:
        return nan
    if len(ii) > 2000:
        pick = np.random.default_rng(0).choice(len(ii), 2000, replace=False)
        ii, jj = ii[pick], jj[pick]
    de, dm = enu[jj] - enu[ii], xy[jj] - xy[ii]
    theta = np.arctan2(de[:, 1], de[:, 0]) - np.arctan2(dm[:, 1], dm[:, 0])
    c, s = np.cos(theta), np.sin(theta)
    mid_m, mid_e = 0.5 * (xy[ii] + xy[jj]), 0.5 * (enu[ii] + enu[jj])
    t = mid_e - np.c_[c * mid_m[:, 0] - s * mid_m[:, 1], s * mid_m[:, 0] + c * mid_m[:, 1]]
    px = c[:, None] * xy[None, :, 0] - s[:, None] * xy[None, :, 1] + t[:, :1]
    py = s[:, None] * xy[None, :, 0] + c[:, None] * xy[None, :, 1] + t[:, 1:]
    err = np.hypot(px - enu[None, :, 0], py - enu[None, :, 1])
    best = int(np.argmin(np.median(err, axis=1)))
    inl = err[best] <= inlier_m
    if inl.sum() < 2:
        return nan
    span = np.max(np.linalg.norm(enu[inl][:, None] - enu[inl][None], axis=2))
    if span < min_span_m:
        return nan
    # Least squares rotation + translation (2D Kabsch) on the inlier positions.
    a, b = xy[inl], enu[inl]
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((b - mb).T @ (a - ma))
    R = u @ np.diag([1.0, np.linalg.det(u @ vt)]) @ vt
    tt = mb - R @ ma
    pred = R @ np.asarray(centre_in_world_m, np.float64)[:2] + tt
    resid = float(np.linalg.norm(pred - _enu_m(gps, origin)))
    spread = float(np.sqrt(np.sum((a - ma) ** 2)))
    dist = float(np.linalg.norm(np.asarray(centre_in_world_m, np.float64)[:2] - ma))
    allowance = 3.0 * sigma_m * (1.0 / np.sqrt(len(a)) + dist / max(spread, 1e-9))
    return resid, float(allowance)


def gps_refusal(
    centre_in_world_m: np.ndarray,
    gps: GeoPoint,
    references: list[tuple[np.ndarray, GeoPoint]],
    max_residual_m: float,
    same_position_m: float = 1.0,
    min_fit_span_m: float = 30.0,
    sigma_m: float = 3.0,
) -> tuple[str, float]:
    """GPS test of a candidate automatic registration (camera centre (3,) world m, its GPS) against registered
    ``references`` (centre, GPS): (why it is refused, "" when it is not; its residual, m). Two tests, each refusing
    above ``max_residual_m``: the median distance residual over the references' positions
    (:func:`gps_median_residual_m`), and, when those positions span enough to fix the heading, the distance after
    the fitted rigid motion less that fit's uncertainty (:func:`gps_heading_residual_m`; it also sees mirror
    images). The residual is the larger of the two."""
    med = gps_median_residual_m(centre_in_world_m, gps, references, same_position_m)
    head, allow = gps_heading_residual_m(
        centre_in_world_m, gps, references, same_position_m, max_residual_m, min_fit_span_m, sigma_m
    )
    excess = head - allow if np.isfinite(head) else float("nan")
    residual = float(np.nanmax([med, excess])) if np.isfinite([med, excess]).any() else float("nan")
    if med > max_residual_m:
        why = (
            f"its distances to {len(references)} registered photos differ from their GPS distances by {med:.1f} m "
            f"(median over GPS positions > {max_residual_m:g} m)"
        )
        return why, residual
    if excess > max_residual_m:
        why = (
            f"its centre lies {head:.1f} m from its GPS position in the frame fitted to {len(references)} registered "
            f"photos' GPS (> {max_residual_m:g} m + {allow:.1f} m fit uncertainty)"
        )
        return why, residual
    return "", residual


def gps_check(
    recon: Reconstruction, idx: int, world_from_camera: np.ndarray, cfg: MapperConfig, min_references: int | None = None
) -> str:
    """Why a candidate automatic pose of image ``idx`` contradicts GPS (:func:`gps_refusal` against the registered
    images with GPS; "" when it does not, or cannot be told: no GPS, fewer than ``cfg.gps_min_references``
    registered photos with GPS (``min_references`` overrides that), or the check is off). Records the residual in
    ``gps_residual_m``."""
    im = recon.images[idx]
    if cfg.gps_max_residual_m is None or im.gps is None:
        return ""
    refs = [
        (o.world_from_camera[:3, 3], o.gps)
        for j, o in enumerate(recon.images)
        if j != idx and o.registered and o.gps is not None and o.world_from_camera is not None
    ]
    if len(refs) < max(1, cfg.gps_min_references if min_references is None else min_references):
        return ""
    why, im.gps_residual_m = gps_refusal(
        world_from_camera[:3, 3],
        im.gps,
        refs,
        cfg.gps_max_residual_m,
        cfg.gps_same_position_m,
        cfg.gps_min_fit_span_m,
        cfg.gps_sigma_m,
    )
    return why
