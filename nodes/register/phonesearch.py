"""A phone photo's camera from the model's outlines: the rotation from its straight lines, the position by sliding
the model's outline over the photo around its GPS position (pure: arrays and
:class:`~constructaide.modelview.ModelView` renders; no bus).

A phone photo is taken by a person standing outside the building, at hand height, within a few metres of the
photo's GPS position, looking at the building from close up (2-25 m). The fixed-camera search of
:mod:`nodes.register.modelsearch` (a 3 m grid of centres, turns about an aim) is too coarse for such views: at 5 m a
metre aside moves the outline by a third of the image. So:

1. the rotation from vanishing directions (:func:`nodes.register.vanishing.vanishing_rotations`, within a degree
   on most photos), each solution as its four quarter turns; turns that do not face the model are dropped;
2. for each turn, cameras at hand height on a grid of offsets along and across the view around the GPS position;
   from each the standing elements' visible edges are rendered once, and their oriented chamfer gain against the
   photo's edges is computed for every image shift at once (``cv2.matchTemplate`` per orientation bin): a shift of
   the outline is a camera moved across the view; the score of a shift is its gain less the mean gain of the
   shifts ``chance_shift_px`` around it (the model search's chance level, so the photo's texture alone scores 0);
3. the best distinct cameras (outside the standing elements' footprint, the model's edges at least
   ``min_depth_m`` away) are refined and scored as in the model search (:func:`nodes.register.modelsearch._refine`:
   pose and focal on the oriented chamfer, edge support against its chance level).

The result is a ranked list, not a verdict: on the default synthetic site the best-scored camera is right for a
third of the phone photos and wrong ones score as high on outlines alone (a wall of brick matches many views). So
:func:`phone_anchor_by_texture` refines the coarse cameras on the fixed cameras' texture carried through the model
(:mod:`nodes.register.texture`) and keeps the best only when it is plausible and unique; the older
:func:`phone_anchor` keeps a camera when the photo's own feature matches with a registered fixed frame agree.
Poses: ``world_from_camera`` (4, 4), OpenCV camera frame, model metres, z up.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from constructaide import camera as cam
from constructaide.modelview import ModelView
from nodes.register.bimdepth import MeshDepthLookup
from nodes.register.config import MapperConfig
from nodes.register.modelalign import AlignParams, compose_update, edge_samples, work_size
from nodes.register.modelsearch import (
    Hypothesis,
    SearchParams,
    _distinct,
    _refine,
    _refine_maps,
    _residuals,
    _support_and_chance,
    _tangent_points,
    _work_image,
    gps_in_model,
    model_target,
    oriented_distance_maps,
    standing_bounds,
    virtual_clicks,
)
from nodes.register.pose import best_pair_agreement, epipolar_distances, fixed_partners
from nodes.register.recon import Reconstruction
from nodes.register.texture import (
    TextureParams,
    TextureSource,
    refine_by_texture,
    texture_score,
    texture_source,
    work_gray,
)
from nodes.register.vanishing import VanishingParams, model_axes_yaw_deg, vanishing_rotations
from schemas.messages import GeoPoint, Intrinsics

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


class PhoneSearchParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Phone search. Lengths in metres, pixels at ``work_width_px``."""

    work_width_px: int = 480
    hand_height_m: float = 1.6
    forward_offsets_m: tuple[float, ...] = (-6.0, -4.5, -3.0, -1.5, 0.0, 1.5, 3.0, 4.5, 6.0)
    lateral_offsets_m: tuple[float, ...] = (-3.0, 0.0, 3.0)
    shift_range_rel: float = 0.35
    """Image shifts tried, as a share of the work width each way."""
    peaks_per_render: int = 3
    peak_spacing_px: int = 9
    facing_deg: float = 75.0
    """A turn whose view points further than this from the model's middle is not tried."""
    min_depth_m: float = 2.0
    """Renders whose edges lie nearer than this (median) are a camera inside something: skipped."""
    keep: int = 6
    """Distinct cameras refined."""
    distinct_m: float = 1.0
    distinct_deg: float = 3.0
    agree_rel: float = 0.0025
    """A found camera is confirmed by matches within this share of the width of their epipolar lines
    (:func:`phone_anchor`)."""
    coarse_agree_rel: float = 0.015
    """... and a coarse camera is refined only when as many agree within this (it is a metre and a degree off)."""
    texture_hypotheses: int = 30
    """Distinct coarse cameras refined on the registered photos' texture (:func:`phone_anchor_by_texture`)."""
    min_texture_ncc: float = 0.15
    """A camera found by the texture needs at least this mean local correlation with the carried texture ..."""
    texture_margin: float = 0.03
    """... this much more than any other refined camera that draws the model elsewhere in the photo (by more than
    ``distinct_image_rel`` of the width) ..."""
    distinct_image_rel: float = 0.01
    stand_height_m: tuple[float, float] = (1.0, 2.3)
    """... its centre this high above the terrain (a person's hand) ..."""
    max_from_gps_m: float = 9.0
    """... this near the GPS position (horizontally) ..."""
    max_turn_deg: float = 8.0
    """... turned at most this far by the refinement from the rotation the photo's lines gave (within a degree
    on most photos) ..."""
    ambiguity_shifts_rel: tuple[float, ...] = (0.05, 0.12)
    """... and unique: started again with the model moved this share of the width left, right, up and down in the
    photo, no refinement that lands elsewhere (``distinct_image_rel``) scores within ``texture_margin`` of it (a
    wall of bricks filling the view lines up one brick aside as well) ..."""
    ambiguity_steps_m: tuple[float, ...] = (1.5, 3.0, 4.5, 6.0)
    """... nor started again this far aside (horizontally, across the view, both ways): a close-up of one bay of a
    facade of like bays lines up a bay aside too, and the GPS cannot tell which."""
    ambiguity_model_axes: bool = True
    """... nor along either of the model's horizontal axes (when more than 20 deg from across the view): a photo of a
    facade of like bays taken obliquely, its camera a bay along the facade, lines up as well."""
    ambiguity_take_better: bool = True
    """Where one of those moves lines up better by ``texture_margin``, that camera is taken instead and tested
    again (once)."""
    bay_scan_steps_m: tuple[float, float] = (0.5, 8.0)
    """Before those tests the found camera is also tried moved along each of the model's horizontal axes by
    multiples of the first (m) up to the second, unrefined, scored by the large structures
    (:func:`~nodes.register.texture.texture_score` ``structures``): the fine texture of a facade of like bays
    lines up a bay aside nearly as well as in the right one, the columns, beams and windows around it do not ..."""
    bay_scan_gain: float = 0.1
    """... and where a move scores this much better than the found camera, the camera refined from there is taken
    instead when its structures line up better too."""


def model_axes_yaw(view: ModelView) -> float:
    """Heading (deg, [0, 90)) of the model's first horizontal axis (:func:`model_axes_yaw_deg` of its faces)."""
    scene = view.scene
    tri = scene.positions_m.reshape(-1, 3, 3).astype(np.float64)
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return model_axes_yaw_deg(scene.normals.reshape(-1, 3, 3)[:, 0].astype(np.float64), areas)


def model_axes(view: ModelView) -> tuple[F64, F64]:
    """The model's two horizontal axes (unit (3,) world vectors) at :func:`model_axes_yaw`."""
    yaw = math.radians(model_axes_yaw(view))
    return np.array([math.cos(yaw), math.sin(yaw), 0.0]), np.array([-math.sin(yaw), math.cos(yaw), 0.0])


def outside(footprint: tuple[F64, F64], centre_m: F64) -> bool:
    """Whether a camera centre (3,) lies outside the standing elements' horizontal bounds."""
    lo, hi = footprint
    return not bool(np.all(centre_m[:2] > lo[:2]) and np.all(centre_m[:2] < hi[:2]))


def shift_contrast(
    gain: NDArray[np.float32], uv_px: NDArray[np.int64], bins: NDArray[np.int64], pad: int, chance_px: float
) -> NDArray[np.float32]:
    """(2 pad + 1, 2 pad + 1) score of the outline points ``uv_px`` (N, 2) (orientation ``bins`` (N,)) shifted by
    (dv, du) - pad: the mean gain (``gain`` (B, H, W), 1 on a like photo edge, 0 beyond the truncation) less the
    mean of the same score at the eight shifts ``chance_px`` around."""
    n_bins, h, w = gain.shape
    total = np.zeros((2 * pad + 1, 2 * pad + 1), np.float32)
    for b in range(n_bins):
        sel = bins == b
        if not sel.any():
            continue
        tmpl = np.zeros((h, w), np.float32)
        np.add.at(tmpl, (uv_px[sel, 1], uv_px[sel, 0]), 1.0)
        padded = cv2.copyMakeBorder(gain[b], pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
        total += cv2.matchTemplate(padded, tmpl, cv2.TM_CCORR)
    total /= max(len(uv_px), 1)
    k = max(1, int(round(chance_px)))
    ext = cv2.copyMakeBorder(total, k, k, k, k, cv2.BORDER_REPLICATE)
    around = np.zeros_like(total)
    for ang in np.arange(8) * np.pi / 4:
        dx, dy = int(round(k * math.cos(ang))), int(round(k * math.sin(ang)))
        around += ext[k + dy : k + dy + total.shape[0], k + dx : k + dx + total.shape[1]]
    return total - around / 8.0


def search_phone(
    view: ModelView,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    centre_xy_m: tuple[float, float],
    elements: set[str] | None,
    ground_z_m: float | None,
    params: PhoneSearchParams | None = None,
    search: SearchParams | None = None,
    vanishing: VanishingParams | None = None,
    worth_refining: Callable[[Hypothesis], bool] | None = None,
    refine: bool = True,
) -> list[Hypothesis]:
    """Cameras of the phone photo ``gray`` (H, W) (lens prior ``intr``, full resolution, EXIF focal) near its GPS
    position ``centre_xy_m`` (model metres) on the model ``view`` with ``elements`` standing and the terrain at
    ``ground_z_m``: refined hypotheses outside the model's footprint, best edge contrast first (empty when the
    photo shows no straight lines or the model no edges). ``worth_refining``: a cheap test of a coarse camera
    before its refinement (the refinements are most of the cost). ``refine`` False: the distinct coarse cameras,
    best coarse score first, unrefined."""
    p = params or PhoneSearchParams()
    sp = search or SearchParams()
    box = standing_bounds(view, elements)
    target = model_target(view, elements)
    if box is None or target is None:
        return []
    rotations = vanishing_rotations(gray, intr, model_axes_yaw(view), vanishing)
    ground = 0.0 if ground_z_m is None else float(ground_z_m)
    ww, wh = work_size(intr, p.work_width_px)
    wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
    trunc = sp.truncate_px * ww / 480
    dmaps = oriented_distance_maps(_work_image(gray, ww, wh), sp.orientation_bins, trunc)
    gain = (1.0 - dmaps / trunc).astype(np.float32)
    pad = int(p.shift_range_rel * ww)
    chance_px = sp.chance_shift_px * ww / 960
    samples = AlignParams(sample_step_px=3.0 * ww / 480, max_samples=3000, min_samples=30)
    gps = np.array([centre_xy_m[0], centre_xy_m[1], ground + p.hand_height_m])
    coarse: list[Hypothesis] = []
    for rot, _share in rotations:
        fwd = rot[2]
        to_model = (target - gps) / max(float(np.linalg.norm(target - gps)), 1e-9)
        if float(to_model @ fwd) < math.cos(math.radians(p.facing_deg)):
            continue
        ahead = np.array([fwd[0], fwd[1], 0.0]) / max(math.hypot(fwd[0], fwd[1]), 1e-9)
        across = np.array([-ahead[1], ahead[0], 0.0])
        for a in p.forward_offsets_m:
            for b in p.lateral_offsets_m:
                wfc = np.eye(4)
                wfc[:3, :3] = rot.T
                wfc[:3, 3] = gps + a * ahead + b * across
                s = edge_samples(view, wi, wfc, elements, ground_z_m, samples)
                pts = s.point_in_world_m
                if len(pts) < samples.min_samples:
                    continue
                cfw = cam.invert_rigid(wfc)
                uv, z = cam.project_points(wi, cfw, pts)
                uq, _ = cam.project_points(wi, cfw, _tangent_points(wi, wfc, pts, s.normal_px))
                ij = np.rint(uv).astype(np.int64)
                ok = (ij[:, 0] >= 0) & (ij[:, 0] < ww) & (ij[:, 1] >= 0) & (ij[:, 1] < wh) & (z > 0)
                if ok.sum() < samples.min_samples:
                    continue
                depth = float(np.median(z[ok]))
                if depth < p.min_depth_m:
                    continue
                ang = np.mod(np.arctan2(uq[:, 1] - uv[:, 1], uq[:, 0] - uv[:, 0]), np.pi)
                bins = np.minimum((ang / np.pi * sp.orientation_bins).astype(np.int64), sp.orientation_bins - 1)
                score = shift_contrast(gain, ij[ok], bins[ok], pad, chance_px)
                top = cv2.dilate(score, np.ones((p.peak_spacing_px,) * 2, np.uint8))
                peaks = np.argwhere((score >= top) & (score > 0))
                values = score[peaks[:, 0], peaks[:, 1]]
                for k in np.argsort(-values)[: p.peaks_per_render]:
                    dv, du = peaks[k] - pad
                    # the outline moved by (du, dv) px: the camera moved the other way across the view at its depth
                    moved = wfc.copy()
                    moved[:3, 3] = wfc[:3, 3] + rot.T @ np.array([-du * depth / wi.f_px, -dv * depth / wi.f_px, 0.0])
                    if outside(box, moved[:3, 3]):
                        coarse.append(Hypothesis(moved, intr, float(values[k])))
    coarse.sort(key=lambda h: -h.coarse)
    apart = msgspec.structs.replace(sp, distinct_m=p.distinct_m, distinct_deg=p.distinct_deg)
    chosen: list[Hypothesis] = []
    for h in coarse:
        if all(_distinct(h, c, apart) for c in chosen) and (worth_refining is None or worth_refining(h)):
            chosen.append(h)
        if len(chosen) >= p.keep:
            break
    if not refine:
        return chosen
    refined = [_refine(view, gray, h, elements, ground_z_m, sp) for h in chosen]
    refined = [h for h in refined if outside(box, h.world_from_camera[:3, 3])]
    refined.sort(key=lambda h: -h.contrast)
    return refined


def epipolar_distances_px(x_other: F64, other_wfc: F64, px_this: F64, intr: Intrinsics, world_from_camera: F64) -> F64:
    """(M,) distance (px, this image, pinhole) of each matched pixel ``px_this`` (M, 2) to the epipolar line of its
    match in another registered camera (normalised points ``x_other`` (M, 2), pose ``other_wfc`` (4, 4)) when this
    camera is at ``world_from_camera``."""
    this_from_other = cam.invert_rigid(world_from_camera) @ other_wfc
    d = epipolar_distances(x_other, cam.pixels_to_normalized(intr, px_this), this_from_other)
    return d * intr.f_px


def refine_on_matches(
    view: ModelView,
    gray: NDArray[np.uint8],
    h: Hypothesis,
    elements: set[str] | None,
    ground_z_m: float | None,
    matches: list[tuple[F64, F64, F64]],
    near_rel: float = 0.01,
    search: SearchParams | None = None,
) -> Hypothesis:
    """A found camera refined on the model's outline and the photo's matches together (pose; the focal held): the
    epipolar test leaves a camera free along the baseline, the outline alone drifts on texture. ``matches``: per
    registered photo (its normalised points (M, 2), its world_from_camera (4, 4), this photo's pixels (M, 2)); only
    matches within ``near_rel`` of the width of their epipolar lines at ``h`` take part. Support and chance level
    recomputed at the end."""
    sp = search or SearchParams()
    intr = h.intrinsics
    ww, wh, trunc, dmaps, samp = _refine_maps(gray, intr, sp.refine_widths_px[-1], sp)
    wi = msgspec.structs.replace(cam.scaled_intrinsics(intr, ww, wh), k1=0.0, k2=0.0)
    pin = msgspec.structs.replace(intr, k1=0.0, k2=0.0)
    wfc = h.world_from_camera
    s = edge_samples(view, wi, wfc, elements, ground_z_m, samp)
    pts = s.point_in_world_m
    if len(pts) < samp.min_samples:
        return h
    q = _tangent_points(wi, wfc, pts, s.normal_px)
    kept = []
    for xo, ow, px in matches:
        near = epipolar_distances_px(xo, ow, px, pin, wfc) < near_rel * intr.width_px
        if near.any():
            kept.append((xo[near], ow, px[near]))
    n_match = sum(len(k[0]) for k in kept)
    if not n_match:
        return h
    weight = math.sqrt(len(pts) / n_match) * ww / intr.width_px  # matches as a whole weigh as much as the outline
    cfw = cam.invert_rigid(wfc)
    depth = float(np.median((pts - wfc[:3, 3]) @ wfc[:3, 2]))

    def res(x6: F64) -> F64:
        x = np.r_[x6, 0.0]
        moved = compose_update(cfw, x)
        epi = [epipolar_distances_px(xo, ow, px, pin, moved) for xo, ow, px in kept]
        return np.r_[_residuals(x, dmaps, wi, wfc, pts, q, trunc), weight * np.concatenate(epi)]

    scale = np.r_[np.full(3, 2.0 / wi.f_px), np.full(3, 2.0 * depth / wi.f_px)]
    r = least_squares(res, np.zeros(6), loss="cauchy", f_scale=1.5, x_scale=scale, diff_step=1e-3, max_nfev=80)
    moved = compose_update(cfw, np.r_[r.x, 0.0])
    s2 = edge_samples(view, wi, moved, elements, ground_z_m, samp)
    if len(s2.point_in_world_m) < samp.min_samples:
        return h
    sup, luck = _support_and_chance(dmaps, wi, moved, s2, trunc, sp)
    return Hypothesis(moved, intr, h.coarse, sup, luck)


def phone_anchor(
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    gps: GeoPoint | None,
    capture_time_ns: int,
    agree: Callable[[Intrinsics, F64, float], tuple[int, str]],
    min_agreeing: int,
    min_contrast: float,
    count: int = 24,
    params: PhoneSearchParams | None = None,
    polish: Callable[[Hypothesis], Hypothesis] | None = None,
    min_contrast_polished: float = 0.0,
) -> tuple[tuple[F64, F64] | None, str]:
    """A phone photo ``gray`` (H, W) found by the model (:func:`search_phone`, lens prior ``intr``, GPS ``gps``)
    and confirmed by its own matches, turned into model-point clicks (pixels (N, 2) full resolution, points (N, 3)
    m) for the anchor solve; or None and why not. ``agree(intrinsics, world_from_camera, tolerance_rel)`` gives the
    most verified matches one registered photo shares with it that lie within ``tolerance_rel`` of the width of
    their epipolar lines under a camera, and that photo's name. A coarse camera is refined only when
    ``min_agreeing`` of them agree within ``coarse_agree_rel``; the first refined camera (best outline contrast
    first, at least ``min_contrast``) with ``min_agreeing`` within ``agree_rel`` is taken, after ``polish`` (a
    refinement on the matches) when given, which it must pass again (its contrast then at least
    ``min_contrast_polished``)."""
    xy, why = gps_in_model(lookup, gps)
    if xy is None:
        return None, why
    elements = lookup.elements(capture_time_ns)
    p = params or PhoneSearchParams()
    loose: list[int] = [0]

    def worth(h: Hypothesis) -> bool:
        n = agree(h.intrinsics, h.world_from_camera, p.coarse_agree_rel)[0]
        loose[0] = max(loose[0], n)
        return n >= min_agreeing

    found = search_phone(lookup.view, gray, intr, xy, elements, lookup.ground_height_m, p, worth_refining=worth)
    best_agree = 0
    for h in found:
        if h.contrast < min_contrast:
            break
        agreeing, partner = agree(h.intrinsics, h.world_from_camera, p.agree_rel)
        best_agree = max(best_agree, agreeing)
        if agreeing < min_agreeing:
            continue
        if polish is not None:  # refined on the matches and the outline, then tested again
            h = polish(h)
            agreeing, partner = agree(h.intrinsics, h.world_from_camera, p.agree_rel)
            if agreeing < min_agreeing or h.contrast < max(min_contrast, min_contrast_polished):
                continue
        ground = lookup.ground_height_m
        px, pts = virtual_clicks(lookup.view, h.intrinsics, h.world_from_camera, elements, ground, count)
        if len(px) < 6:
            continue
        why = f"edge support {h.support:.2f} against {h.chance:.2f} by chance; {agreeing} matches with {partner} agree"
        return (px, pts), why
    if not found:
        return None, (
            f"the model's outlines do not find the camera: at most {loose[0]} of the photo's matches agree roughly "
            f"with any camera they suggest (< {min_agreeing})"
        )
    top = found[0]
    return None, (
        f"the model's outlines do not find the camera: best edge support {top.support:.2f} against {top.chance:.2f} "
        f"by chance, at most {best_agree} of the photo's matches agree (< {min_agreeing})"
    )


def phone_anchor_by_texture(
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    gps: GeoPoint | None,
    capture_time_ns: int,
    sources: list[TextureSource],
    count: int = 24,
    params: PhoneSearchParams | None = None,
    texture: TextureParams | None = None,
) -> tuple[tuple[F64, F64] | None, str]:
    """A phone photo ``gray`` (H, W) found by the model (:func:`search_phone`'s coarse cameras, lens prior ``intr``,
    GPS ``gps``), each refined on the texture of registered photos carried through the model
    (:func:`~nodes.register.texture.refine_by_texture`, ``sources``) and scored by its correlation with it
    (:func:`~nodes.register.texture.texture_score`), the best also tried a bay aside (:func:`bay_scan`); it is
    taken when it stands where a person can (height, near the GPS, outside the building), correlates by at least
    ``min_texture_ncc`` and beats every camera that draws the model elsewhere by ``texture_margin``, also those
    refined from it moved (the ambiguity test: the model shifted in the photo, the camera a bay aside or along the
    model's axes; one that lines up better by the margin is taken instead and tested again). Returns
    model-point clicks (pixels (N, 2) full resolution, points (N, 3) m) for the anchor solve, or None, and why."""
    xy, why = gps_in_model(lookup, gps)
    if xy is None:
        return None, why
    if not sources:
        return None, "no registered fixed camera's frame to carry texture from"
    p = params or PhoneSearchParams()
    tp = texture or TextureParams()
    elements = lookup.elements(capture_time_ns)
    view, ground = lookup.view, lookup.ground_height_m
    coarse = search_phone(
        view, gray, intr, xy, elements, ground, msgspec.structs.replace(p, keep=p.texture_hypotheses), refine=False
    )
    if not coarse:
        return None, "the model's outlines suggest no camera (no straight lines, or no model edges in view)"
    widths = {*tp.levels_px, tp.score_width_px}
    photo = {w: work_gray(gray, w) for w in widths}
    box = standing_bounds(view, elements)
    lo, hi = p.stand_height_m
    terrain = 0.0 if ground is None else float(ground)

    def refined(start: F64) -> tuple[float, F64] | None:
        """A camera refined on the texture from ``start`` and scored; None where no person stands or it turned."""
        wfc = refine_by_texture(view, photo, intr, start, elements, ground, sources, tp)
        if wfc is None or cam.rotation_angle_deg(wfc[:3, :3], start[:3, :3]) > p.max_turn_deg:
            return None
        c = wfc[:3, 3]
        if not lo <= c[2] - terrain <= hi or math.hypot(c[0] - xy[0], c[1] - xy[1]) > p.max_from_gps_m:
            return None
        if box is not None and not outside(box, c):
            return None
        return texture_score(view, photo[tp.score_width_px], intr, wfc, elements, ground, sources, tp)[0], wfc

    found = [f for f in (refined(h.world_from_camera) for h in coarse) if f is not None]
    if not found:
        return None, f"none of {len(coarse)} cameras the outlines suggest lines up with the fixed cameras' texture"
    found.sort(key=lambda f: -f[0])
    best, wfc = found[0]
    work = photo[tp.score_width_px]
    moved, structure = bay_scan(view, work, intr, wfc, elements, ground, sources, xy, p, tp)
    if moved is not None:
        again = refined(moved)
        if again is not None:
            theirs = texture_score(view, work, intr, again[1], elements, ground, sources, tp, structures=True)[0]
            if theirs > structure + p.bay_scan_gain:
                found.append((best, wfc))
                (best, wfc), structure = again, theirs
    px, pts = virtual_clicks(view, intr, wfc, elements, ground, count)
    if len(px) < 6:
        return None, "the camera the texture finds sees too little of the model to click"
    rival = max(
        (s for s, other in found if other is not wfc and _image_shift_rel(intr, other, pts, px) > p.distinct_image_rel),
        default=-1.0,
    )
    why = (
        f"texture correlation {best:.2f} (large structures {structure:.2f}), next camera that draws the model "
        f"elsewhere {max(rival, 0.0):.2f}"
    )
    if best < p.min_texture_ncc or best - rival < p.texture_margin:
        return None, f"the fixed cameras' texture does not single out a camera: {why}"
    axes = model_axes(view)
    for turn in range(2):
        depth = float(np.median((pts - wfc[:3, 3]) @ wfc[:3, 2]))
        across = np.array([wfc[0, 0], wfc[1, 0], 0.0]) / max(math.hypot(wfc[0, 0], wfc[1, 0]), 1e-9)
        aside = [(across, "aside")]
        if p.ambiguity_model_axes:  # a bay along the facade the photo looks at obliquely: along the model's axes too
            aside += [(a, "along a model axis") for a in axes if abs(float(a @ across)) < math.cos(math.radians(20))]
        moves = [
            (sign * q * intr.width_px * depth / intr.f_px * wfc[:3, axis], f"the model moved {q:.0%} of the width")
            for q in p.ambiguity_shifts_rel
            for axis in (0, 1)
            for sign in (1.0, -1.0)
        ] + [
            (sign * m * d, f"the camera {m:g} m {how}")
            for d, how in aside
            for m in p.ambiguity_steps_m
            for sign in (1, -1)
        ]
        better = None
        for move, how in moves:
            start = wfc.copy()
            start[:3, 3] += move
            again = refined(start)
            if again is None or _image_shift_rel(intr, again[1], pts, px) <= p.distinct_image_rel:
                continue
            if p.ambiguity_take_better and turn == 0 and again[0] > best + p.texture_margin:
                better = again, how
                break
            if again[0] > best - p.texture_margin:
                return None, (
                    f"the fixed cameras' texture lines up as well elsewhere: {again[0]:.2f} against {best:.2f} with "
                    f"{how} (repeated texture)"
                )
        if better is None:
            return (px, pts), why
        (best, wfc), how = better  # lines up clearly better a bay away: taken, and tested again from there
        px, pts = virtual_clicks(view, intr, wfc, elements, ground, count)
        if len(px) < 6:
            return None, "the camera the texture finds sees too little of the model to click"
        why = f"texture correlation {best:.2f} with {how} from the first found, which scored {why}"
    raise AssertionError("not reached: the second turn takes no better camera")


def bay_scan(
    view: ModelView,
    photo_work: F32,
    intr: Intrinsics,
    wfc: F64,
    elements: set[str] | None,
    ground: float | None,
    sources: list[TextureSource],
    gps_xy: tuple[float, float],
    p: PhoneSearchParams,
    tp: TextureParams,
) -> tuple[F64 | None, float]:
    """The camera ``wfc`` (world_from_camera (4, 4)) moved along one of the model's horizontal axes (steps
    ``bay_scan_steps_m``, within ``max_from_gps_m`` of the GPS) whose large structures line up best with the photo,
    when by ``bay_scan_gain`` better than ``wfc``'s own, else None; and ``wfc``'s own structure score."""
    own = texture_score(view, photo_work, intr, wfc, elements, ground, sources, tp, structures=True)[0]
    step, reach = p.bay_scan_steps_m
    best, best_score = None, own + p.bay_scan_gain
    for axis in model_axes(view):
        for k in range(-int(reach / step), int(reach / step) + 1):
            if k == 0:
                continue
            start = wfc.copy()
            start[:3, 3] += k * step * axis
            if math.hypot(start[0, 3] - gps_xy[0], start[1, 3] - gps_xy[1]) > p.max_from_gps_m:
                continue
            score = texture_score(view, photo_work, intr, start, elements, ground, sources, tp, structures=True)[0]
            if score > best_score:
                best, best_score = start, score
    return best, own


TextureFrame = tuple[NDArray[np.uint8], Intrinsics, F64, int]
"""A registered fixed camera's frame as a texture source: grey pixels (H, W), lens, world_from_camera (4, 4),
capture time (ns)."""


def texture_sources(lookup: MeshDepthLookup, frames: list[TextureFrame]) -> list[TextureSource]:
    """Registered fixed frames as texture sources, each with the model standing at its capture time."""
    ground = lookup.ground_height_m
    return [texture_source(lookup.view, px, i, wfc, lookup.elements(t), ground) for px, i, wfc, t in frames]


def retexture(
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    world_from_camera: F64,
    capture_time_ns: int,
    frames: list[TextureFrame],
    count: int = 24,
    params: PhoneSearchParams | None = None,
    texture: TextureParams | None = None,
) -> tuple[F64, F64] | None:
    """A phone camera found by the texture (``world_from_camera`` (4, 4), lens ``intr``) refined again on the
    texture of ``frames`` at their final poses (the fixed frames it was found on moved in the adjustments since,
    and their errors of then stay in it), at the finest working width; its model-point clicks (pixels (N, 2),
    points (N, 3) m) or None when the refinement fails, turns the camera by more than ``max_turn_deg`` or does not
    line up better with the texture (:func:`~nodes.register.texture.texture_score`) than the camera it started from."""
    if not frames:
        return None
    p, tp = params or PhoneSearchParams(), texture or TextureParams()
    view, ground = lookup.view, lookup.ground_height_m
    sources = texture_sources(lookup, frames)
    elements = lookup.elements(capture_time_ns)
    fine = max(tp.levels_px)
    again = refine_by_texture(
        view,
        {fine: work_gray(gray, fine)},
        intr,
        world_from_camera,
        elements,
        ground,
        sources,
        msgspec.structs.replace(tp, levels_px=tuple(w for w in tp.levels_px if w == fine)),
    )
    if again is None or cam.rotation_angle_deg(again[:3, :3], world_from_camera[:3, :3]) > p.max_turn_deg:
        return None
    work = work_gray(gray, tp.score_width_px)
    if (
        texture_score(view, work, intr, again, elements, ground, sources, tp)[0]
        <= texture_score(view, work, intr, world_from_camera, elements, ground, sources, tp)[0]
    ):
        return None  # the texture at the final poses lines up no better there
    px, pts = virtual_clicks(view, intr, again, elements, ground, count)
    return (px, pts) if len(px) >= 6 else None


def nearest_fixed_frames(recon: Reconstruction, capture_time_ns: int) -> list[int]:
    """Per fixed camera, its registered frame nearest in time to ``capture_time_ns`` (image indices)."""
    best: dict[str, int] = {}
    for j in recon.registered_indices():
        o = recon.images[j]
        if o.camera_id is None:
            continue
        k = best.get(o.camera_id)
        dt = abs(o.capture_time_ns - capture_time_ns)
        if k is None or dt < abs(recon.images[k].capture_time_ns - capture_time_ns):
            best[o.camera_id] = j
    return [best[c] for c in sorted(best)]


def _image_shift_rel(intr: Intrinsics, world_from_camera: F64, pts: F64, px: F64) -> float:
    """Median distance (share of the width) between pixels ``px`` (N, 2) and where a camera draws their model
    points ``pts`` (N, 3)."""
    uv, z = cam.project_points(intr, cam.invert_rigid(world_from_camera), pts)
    d = np.linalg.norm(uv - px, axis=1)
    d[~np.isfinite(d) | (z <= 0)] = np.inf
    return float(np.median(d)) / intr.width_px


def phone_anchor_in(
    recon: Reconstruction,
    idx: int,
    lookup: MeshDepthLookup,
    gray: NDArray[np.uint8],
    intr: Intrinsics,
    cfg: MapperConfig,
    frames: list[TextureFrame] | None = None,
) -> tuple[tuple[F64, F64] | None, str]:
    """A camera for image ``idx`` of a reconstruction found by the model. With ``cfg.phone_search_texture`` and
    ``frames`` (registered fixed cameras' frames, e.g. :func:`nearest_fixed_frames`): :func:`phone_anchor_by_texture`.
    Else :func:`phone_anchor`: its matches with one registered fixed camera's frame confirm
    (``cfg.phone_search_min_agreeing`` within ``PhoneSearchParams.agree_rel`` of the width; not searched when no such
    frame shares that many matches), its outline contrast reaches ``cfg.min_outline_contrast`` (0 when off)."""
    im = recon.images[idx]
    if cfg.phone_search_texture and frames is not None:
        sources = texture_sources(lookup, frames)
        return phone_anchor_by_texture(lookup, gray, intr, im.gps, im.capture_time_ns, sources, cfg.model_search_clicks)
    partners = fixed_partners(recon, idx, cfg.phone_search_min_agreeing)
    if not partners:
        n = cfg.phone_search_min_agreeing
        return None, f"no registered fixed camera's frame shares {n} matches to confirm a camera"

    def agree(i: Intrinsics, wfc: F64, tolerance_rel: float) -> tuple[int, str]:
        return best_pair_agreement(recon, idx, i, wfc, tolerance_rel * im.width_px)

    matches = []
    for j in partners:
        pair = recon.pair(j, idx)
        assert pair is not None  # a partner has a pair
        o = recon.images[j]
        x_other = cam.pixels_to_normalized(o.camera, o.features.keypoints_px[pair[0][:, 0]].astype(np.float64))
        matches.append((x_other, o.pose, im.features.keypoints_px[pair[0][:, 1]].astype(np.float64)))
    elements = lookup.elements(im.capture_time_ns)

    def polish(h: Hypothesis) -> Hypothesis:
        return refine_on_matches(lookup.view, gray, h, elements, lookup.ground_height_m, matches)

    return phone_anchor(
        lookup,
        gray,
        intr,
        im.gps,
        im.capture_time_ns,
        agree,
        cfg.phone_search_min_agreeing,
        cfg.min_outline_contrast or 0.0,
        cfg.model_search_clicks,
        polish=polish,
        min_contrast_polished=cfg.phone_search_min_contrast,
    )
