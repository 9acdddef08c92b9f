"""A camera scored and refined against registered photos' texture carried through the model (pure: arrays and
:class:`~constructaide.modelview.ModelView` renders; no bus).

Where the model stands, a registered photo (a fixed camera's frame) shows what its surfaces look like. A camera
hypothesised for another photo (a phone photo) sees those surfaces at the pixels its render of the model gives, so
each such pixel takes the grey value a registered photo shows at the same model point (where that photo sees it:
its own depth render agrees) - the *carried texture*, an image of what the photo should show there. Then:

* :func:`texture_score`: the local normalised cross-correlation (windows of ``window_px``) between the photo and the
  carried texture, averaged over the pixels where both have texture. A camera a brick period aside still lines up
  bricks, but not the windows, joints and edges around them (the repeats that mislead feature matches do not
  mislead a comparison of whole neighbourhoods at known places);
* :func:`refine_by_texture`: dense optical flow (DIS) from the carried texture to the photo pairs model points with
  photo pixels; a PnP (RANSAC, from the current pose) on those pairs moves the camera; coarse to fine.

Grey images are (H, W); poses ``world_from_camera`` (4, 4), OpenCV camera frame, model metres, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.modelview import ModelView
from schemas.messages import Intrinsics

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


class TextureParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Sizes and thresholds of the texture comparison (pixel values at the working widths named)."""

    source_width_px: int = 960
    """Width of a source photo's depth render (its visibility test)."""
    visible_rel: float = 0.03
    """A model point counts as seen by a source when the source's depth there is within this share of its
    distance ..."""
    visible_m: float = 0.1
    """... plus this."""
    levels_px: tuple[int, ...] = (240, 480, 480)
    """Working widths of the refinement's steps (flow + PnP each)."""
    grid_step_px: int = 3
    """Carried pixels taken for the PnP: every this many in both directions."""
    pnp_error_px: float = 2.0
    pnp_iterations: int = 200
    min_inliers: int = 50
    min_carried_px: int = 500
    """A step needs this many carried pixels (else the camera sees too little of what the sources saw)."""
    score_width_px: int = 480
    window_px: int = 9
    """Side of the correlation windows."""
    min_texture: float = 4.0
    """A window counts only where both images vary by at least this grey-level variance."""
    min_scored_px: int = 200
    structure_sigma_px: float = 3.0
    """Blur (Gaussian sigma, at ``score_width_px``) before the structure correlation (:func:`texture_score`
    ``structures``): a brick course or a joint is gone, a column, a beam or a window stays."""
    structure_window_px: int = 31
    """Side of the structure correlation's windows."""


@dataclass(frozen=True)
class TextureSource:
    """A registered photo whose texture is carried: ``gray`` (H, W) float32 at full resolution, its lens and pose,
    and its model depth render (``depth_m`` (h, w), camera z, 0 where nothing; pinhole ``depth_intrinsics``)."""

    gray: F32
    intrinsics: Intrinsics
    world_from_camera: F64
    depth_intrinsics: Intrinsics
    depth_m: F32


@dataclass(frozen=True)
class Carried:
    """The carried texture of one camera at one working size: ``image`` (H, W) grey, ``valid`` (H, W) where some
    source sees the model point, ``point_in_world_m`` (H, W, 3) the model point of every rendered pixel."""

    image: F32
    valid: NDArray[np.bool_]
    point_in_world_m: F64


def texture_source(
    view: ModelView,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    params: TextureParams | None = None,
) -> TextureSource:
    """A registered photo (``gray`` (H, W), its solved ``intr`` and pose) as a source, with the model standing at its
    date (``elements``) rendered from its pose for the visibility test."""
    p = params or TextureParams()
    h, w = gray.shape
    dw = min(p.source_width_px, w)
    di = msgspec.structs.replace(cam.scaled_intrinsics(intr, dw, int(round(h * dw / w))), k1=0.0, k2=0.0)
    depth = view.depth_map(world_from_camera, di, elements, ground_z_m)
    return TextureSource(np.asarray(gray, np.float32), intr, np.asarray(world_from_camera, np.float64), di, depth)


def work_gray(gray: NDArray[np.uint8], width_px: int) -> F32:
    """``gray`` (H, W) blurred and resized to ``width_px`` wide (float32)."""
    h, w = gray.shape
    small = cv2.GaussianBlur(gray, (0, 0), max(0.5 * w / width_px, 0.5))
    return cv2.resize(small, (width_px, int(round(h * width_px / w))), interpolation=cv2.INTER_AREA).astype(np.float32)


def carry(
    view: ModelView,
    work_intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    sources: list[TextureSource],
    params: TextureParams | None = None,
) -> Carried:
    """The sources' texture at the pixels of a pinhole camera (``work_intr``, the working size) at a pose; each
    model point takes the nearest source that sees it (the finest texture)."""
    p = params or TextureParams()
    depth = view.depth_map(world_from_camera, work_intr, elements, ground_z_m)
    hh, ww = depth.shape
    vv, uu = np.nonzero(depth > 0)
    z = depth[vv, uu].astype(np.float64)
    xy = cam.pixels_to_normalized(work_intr, np.c_[uu, vv].astype(np.float64))
    points = np.c_[xy * z[:, None], z] @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    nearest = np.full(len(points), np.inf, np.float32)
    chosen = np.full(len(points), -1)
    pts32 = points.astype(np.float32)
    for k, s in enumerate(sources):  # which source sees each point nearest (its depth render agrees)
        cfw = cam.invert_rigid(s.world_from_camera)
        p_cam = pts32 @ cfw[:3, :3].T.astype(np.float32) + cfw[:3, 3].astype(np.float32)  # pinhole render: no lens
        zs = p_cam[:, 2]
        (fx, fy), di = cam.focal_xy(s.depth_intrinsics), s.depth_intrinsics
        with np.errstate(divide="ignore", invalid="ignore"):
            col = np.rint(fx * p_cam[:, 0] / zs + di.cx_px)
            row = np.rint(fy * p_cam[:, 1] / zs + di.cy_px)
        dh, dw = s.depth_m.shape
        at = np.flatnonzero((zs > 0.1) & (col >= 0) & (col < dw) & (row >= 0) & (row < dh))  # NaN compares False
        seen = s.depth_m[row[at].astype(np.int64), col[at].astype(np.int64)]
        zt = zs[at]
        at = at[(np.abs(seen - zt) < p.visible_rel * zt + p.visible_m) & (zt < nearest[at])]
        nearest[at] = zs[at]
        chosen[at] = k
    image = np.zeros((hh, ww), np.float32)
    valid = np.zeros((hh, ww), bool)
    for k, s in enumerate(sources):
        at = np.flatnonzero(chosen == k)
        if len(at) == 0:
            continue
        uv_full, _ = cam.project_points(s.intrinsics, cam.invert_rigid(s.world_from_camera), points[at])  # lens on
        rows = -(-len(at) // 256)  # remap wants a 2-D map under 32767 a side: rows of 256
        maps = np.full((rows * 256, 2), -10.0, np.float32)
        maps[: len(at)] = uv_full
        sampled = cv2.remap(s.gray, maps.reshape(rows, 256, 2), None, cv2.INTER_LINEAR, borderValue=0)
        image[vv[at], uu[at]] = sampled.ravel()[: len(at)]
        valid[vv[at], uu[at]] = True
    grid = np.zeros((hh, ww, 3))
    grid[vv, uu] = points
    return Carried(image, valid, grid)


def local_ncc(a: F32, b: F32, valid: NDArray[np.bool_], window_px: int, min_texture: float) -> tuple[F32, NDArray]:
    """Normalised cross-correlation of ``a`` and ``b`` (H, W) in ``window_px`` windows over ``valid`` pixels, and
    where it is defined (windows mostly valid, both images varying by at least ``min_texture`` grey levels^2)."""
    v = valid.astype(np.float64)  # float64: the variance as a difference of box sums cancels
    a, b = a.astype(np.float64), b.astype(np.float64)
    k = (window_px, window_px)

    def box(x: F64) -> F64:
        return np.asarray(cv2.boxFilter(x, -1, k, normalize=False), np.float64)

    n = box(v)
    sa, sb = box(a * v), box(b * v)
    nn = np.maximum(n, 1.0)
    var_a = box(a * a * v) - sa * sa / nn
    var_b = box(b * b * v) - sb * sb / nn
    cov = box(a * b * v) - sa * sb / nn
    ok = valid & (n >= 0.8 * window_px * window_px) & (var_a > min_texture * nn) & (var_b > min_texture * nn)
    return (cov / np.sqrt(np.maximum(var_a * var_b, 1e-6))).astype(np.float32), ok


def texture_score(
    view: ModelView,
    photo_work: F32,
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    sources: list[TextureSource],
    params: TextureParams | None = None,
    structures: bool = False,
) -> tuple[float, int]:
    """Mean local NCC between the photo (``photo_work``, :func:`work_gray` at ``score_width_px``) and the texture
    carried to the camera (``intr`` full resolution, pose), and the pixels it averages (-1 below
    ``min_scored_px``).

    ``structures``: of both images blurred (``structure_sigma_px``, windows ``structure_window_px``; the carried
    one over its valid pixels only, a normalised convolution): how well the photo's large structures (columns,
    beams, windows, slab edges) line up with the carried ones, blind to a repeated fine texture (bricks, joints)
    that lines up as well a course or a bay aside."""
    p = params or TextureParams()
    hh, ww = photo_work.shape
    wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, hh), k1=0.0, k2=0.0)
    c = carry(view, wi, world_from_camera, elements, ground_z_m, sources, p)
    if structures:
        s = p.structure_sigma_px
        photo = np.asarray(cv2.GaussianBlur(photo_work.astype(np.float32), (0, 0), s), np.float32)
        weight = cv2.GaussianBlur(c.valid.astype(np.float32), (0, 0), s)
        blurred = cv2.GaussianBlur(np.where(c.valid, c.image, 0.0).astype(np.float32), (0, 0), s)
        carried = (blurred / np.maximum(weight, 1e-3)).astype(np.float32)
        ncc, ok = local_ncc(photo, carried, c.valid & (weight > 0.7), p.structure_window_px, 1.0)
    else:
        ncc, ok = local_ncc(photo_work, c.image, c.valid, p.window_px, p.min_texture)
    n = int(ok.sum())
    return (float(ncc[ok].mean()) if n >= p.min_scored_px else -1.0), n


def refine_by_texture(
    view: ModelView,
    photo_by_width: dict[int, F32],
    intr: Intrinsics,
    world_from_camera: F64,
    elements: set[str] | None,
    ground_z_m: float | None,
    sources: list[TextureSource],
    params: TextureParams | None = None,
) -> F64 | None:
    """The camera (``intr`` full resolution, focal held) moved to where the carried texture meets the photo: per
    working width of ``levels_px`` (``photo_by_width[width]``: :func:`work_gray`), DIS optical flow from the carried
    texture to the photo, then a PnP RANSAC from the current pose on (model point, flowed pixel) pairs. None when a
    step has too few carried pixels or inliers."""
    p = params or TextureParams()
    wfc = np.asarray(world_from_camera, np.float64)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]  # per call
    for width in p.levels_px:
        photo = photo_by_width[width]
        hh, ww = photo.shape
        wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, hh), k1=0.0, k2=0.0)
        c = carry(view, wi, wfc, elements, ground_z_m, sources, p)
        if int(c.valid.sum()) < p.min_carried_px:
            return None
        target = np.clip(photo, 0, 255).astype(np.uint8)
        carried = np.clip(c.image, 0, 255).astype(np.uint8)
        carried[~c.valid] = target[~c.valid]  # no texture there: the photo itself, which flows nowhere
        flow = dis.calc(carried, target, None)
        vv, uu = np.mgrid[0 : hh : p.grid_step_px, 0 : ww : p.grid_step_px]
        keep = c.valid[vv, uu]
        vv, uu = vv[keep], uu[keep]
        obj = c.point_in_world_m[vv, uu].astype(np.float64)
        img = np.c_[uu + flow[vv, uu, 0], vv + flow[vv, uu, 1]].astype(np.float64)
        cfw = cam.invert_rigid(wfc)
        rvec, _ = cv2.Rodrigues(cfw[:3, :3])
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj,
            img,
            cam.K_matrix(wi),
            None,
            rvec.copy(),
            cfw[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True,
            iterationsCount=p.pnp_iterations,
            reprojectionError=p.pnp_error_px,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        if not ok or inliers is None or len(inliers) < p.min_inliers:
            return None
        R, _ = cv2.Rodrigues(rvec)
        wfc = cam.invert_rigid(cam.rigid(R, tvec.ravel()))
    return wfc
