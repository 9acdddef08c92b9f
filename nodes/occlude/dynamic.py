"""Dynamic occlusions (moving equipment, workers) from an aligned time-lapse stack (paper Sec. 4.1.2).

Steps, all at working resolution except the last:
1. exposure normalisation: every stack image gets a per-channel gain/offset fitted to the photo on
   robust pixels (iteratively trimmed least squares), so day-to-day lighting changes cancel;
2. background = per-pixel median of the normalised stack (the photo itself excluded; the clean plate);
3. squared HSV difference (hue circular, weighted by saturation because hue is noise on grey pixels),
   max over channels, smoothed by a cross-bilateral filter guided by the photo (so "any channel above
   threshold" becomes "score above threshold"). Paper (``vote_quantile=None``): difference to the
   median background, threshold 0.05. Default (``vote_quantile=0.5``): difference to every
   neighbour separately, and the score is a low order statistic over the neighbours that see the
   pixel, i.e. the photo must differ from more than half of them (from both of two): an occluder
   in one neighbour then leaves no ghost, which the median of a short stack does; threshold 0.08;
5. temporal guard (beyond the paper): the photo must also differ from its nearest earlier and
   nearest later neighbour, inside the projected model when it is known, so construction progress
   between days is not taken for an occluder (a neighbour's own mask does not take it out of the
   guard, see :func:`vote_score`); changes between sky-like pixels (clouds) are ignored
   and pixels of the photo's open sky (sky-like, connected to the top border) are never occluders;
6. the mask grows by hysteresis through pixels above a weaker threshold, but only within ``max_grow_px`` of the
   convex hulls of the strong blobs (beyond the paper: unbounded, an occluder in front of a saturated surface
   whose colour shifts a little from day to day, the green hoarding, flooded its whole length), enclosed holes
   are filled (an occluder's colour may match the background in places), and blobs whose outline is a
   contrast edge of the background rather than of the photo are ghosts of a neighbour's occluder
   and dropped (see :func:`remove_ghosts`);
7. colour model (beyond the paper, ``appearance``; :class:`nodes.occlude.colour.ColourModel`): HSV histograms of every
   photo's time-lapse mask against the rest of the photo, summed over the site, give
   P(dynamic | colour). With ``appearance="all"`` (default) blobs of the time-lapse mask whose mean
   P is below ``appearance_veto`` and pixels whose smoothed P is below ``appearance_pixel_veto`` are
   dropped (they have the colours of the static scene: new construction, a truck's shadow,
   misalignment), but only when the model recognises its own training masks (``recall`` at that
   level >= ``appearance_min_recall``; where equipment shares the scene's colours the time-lapse
   mask stays as it is); pixels whose smoothed P exceeds ``appearance_threshold`` (in blobs of at
   least ``appearance_min_component_frac`` of the image) are added (occluders that do not move while
   the stack is taken, e.g. a site cabin that stands for a week); a photo without a stack (a phone
   photo) gets those pixels as its mask (status ok, ``num_views`` 0, no clean plate). ``"no_stack"``
   only labels photos without a stack; ``"off"`` is the time-lapse alone.
   The model is used once it has seen ``appearance_min_frames`` masks; a fixed camera's background
   counts leave out the places where any of its frames saw something move. It relies on equipment
   having colours the static scene lacks (true of the synthetic site; a grey truck before a grey
   facade stays unlabelled, and static things of an equipment colour are labelled);
8. the soft mask is upsampled to full resolution with a guided filter driven by the photo, only
   inside the mask's bounding box.

The clean background plate is the photo outside the mask and the (upsampled) median inside. Variants measured
and not kept are in BENCHMARKS.md (``occlusion notes``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from nodes.occlude.colour import ColourModel
from nodes.occlude.stacks import AlignedStack

U8 = NDArray[np.uint8]
F32 = NDArray[np.float32]


@dataclass(frozen=True)
class DynamicParams:
    """Tuning of :func:`dynamic_mask`. Filter sizes are in working-resolution pixels."""

    threshold: float = 0.08  # the paper's 0.05 is for the median score (vote_quantile=None)
    weak_ratio: float = 0.25  # hysteresis: grow from strong pixels through pixels above threshold * weak_ratio ...
    max_grow_px: int | None = 24  # ... within this distance of the strong blobs' convex hulls (None: anywhere)
    fill_holes: bool = True
    ghost_ratio: float = 1.0  # 0 disables ghost removal (see remove_ghosts)
    temporal_guard: bool = True  # the photo must also differ from its nearest earlier and later neighbours
    exclude_neighbour_occluders: bool = True  # two-pass: neighbours' known masks are left out of the median
    ignore_sky: bool = True  # changes between sky-like pixels (clouds) are not occluders
    hue_saturation_weighted: bool = True
    bilateral_diameter_px: int = 9
    bilateral_sigma_color: float = 0.1
    bilateral_sigma_space_px: float = 4.0
    min_views: int = 1
    min_component_frac: float = 2e-4  # drop blobs smaller than this fraction of the image
    guided_radius_px: int = 8  # full-resolution pixels
    guided_eps: float = 1e-3
    exposure_iterations: int = 3
    # None: score against the median background (paper). A number q in [0, 1]: score = the
    # floor(q * (n - 1))-th smallest of the per-neighbour scores over the n neighbours that see the
    # pixel without their own occluder (q = 0.5: the photo must differ from more than half of them;
    # with two neighbours from both), so one neighbour's occluder cannot leave a ghost
    vote_quantile: float | None = 0.5
    guard_views: int = 1  # vote mode: neighbours per side (earlier / later) in the temporal guard
    # appearance model (see ColourModel): "off"; "no_stack": label photos without a stack (phone photos) by the
    # colours of the time-lapse masks of the site's other photos; "all": and add such pixels to time-lapse masks
    # too (occluders that do not move while the stack is taken, e.g. a site cabin for a week)
    appearance: str = "all"
    appearance_threshold: float = 0.5  # posterior P(dynamic | colour) above which a pixel is labelled
    appearance_prior_count: float = 20.0  # pseudo-count of other pixels per colour bin: rare colours stay background
    appearance_sigma_px: float = 2.0  # Gaussian smoothing of the posterior map
    appearance_min_frames: int = 5  # time-lapse masks the model must have seen before it is used
    appearance_veto: float = 0.2  # "all": time-lapse blobs whose mean posterior is below this are dropped
    appearance_pixel_veto: float = 0.2  # "all": time-lapse pixels whose smoothed posterior is below this are dropped
    appearance_min_recall: float = 0.7  # vetoes only when this much of the learnt masks has P >= the veto level
    appearance_min_component_frac: float = 2e-3  # colour-only blobs smaller than this fraction of the image are dropped


@dataclass
class DynamicResult:
    """``mask``: uint8 (H, W) 0/255 at photo resolution (all zero unless status is ok);
    ``background``: uint8 BGR (H, W, 3) clean plate or None; ``num_views``: stack size used."""

    status: Literal["ok", "not_enough_views"]
    mask: U8
    background: U8 | None
    num_views: int
    # working-size 0/255 time-lapse mask (before any appearance pixels): what ColourModel.add learns from
    timelapse_small: U8 | None = None
    appearance_px: int = 0  # working-size pixels labelled by the appearance model only


def smoothed_posterior(photo_small: U8, model: ColourModel, params: DynamicParams) -> F32:
    """:meth:`ColourModel.posterior` (h, w) smoothed by a Gaussian of ``params.appearance_sigma_px``."""
    post = model.posterior(photo_small, params.appearance_prior_count)
    if params.appearance_sigma_px > 0:
        post = np.asarray(cv2.GaussianBlur(post, (0, 0), params.appearance_sigma_px), np.float32)
    return post


def appearance_small_mask(photo_small: U8, posterior: F32, params: DynamicParams) -> U8:
    """Working-size 0/255 mask of the pixels whose (smoothed) posterior (h, w) exceeds
    ``params.appearance_threshold`` (blobs below ``appearance_min_component_frac`` of the image
    dropped, enclosed holes filled); open sky never."""
    small = np.where(posterior > params.appearance_threshold, 255, 0).astype(np.uint8)
    if params.ignore_sky:
        small[open_sky(photo_small.astype(np.float32) * np.float32(1.0 / 255.0))] = 0
    small = remove_small_components(small, int(params.appearance_min_component_frac * small.size))
    return fill_holes(small) if params.fill_holes else small


def veto_by_colour(mask_small: U8, posterior: F32, min_mean: float) -> U8:
    """Drop the 8-connected blobs of a 0/255 mask whose mean posterior is below ``min_mean``: they have
    the colours of the static scene (construction progress, shadows, misalignment), not of anything
    that was seen to move."""
    n, labels = cv2.connectedComponents((mask_small > 0).astype(np.uint8), connectivity=8)
    if n <= 1 or min_mean <= 0:
        return mask_small
    sums = np.bincount(labels.ravel(), weights=posterior.ravel().astype(np.float64), minlength=n)
    area = np.bincount(labels.ravel(), minlength=n)
    keep = sums >= min_mean * area
    keep[0] = False
    return np.where(keep[labels], 255, 0).astype(np.uint8)


def fit_exposure(src: F32, dst: F32, valid: NDArray[np.bool_], iterations: int = 3, max_samples: int = 20000) -> F32:
    """Per-channel gain/offset (2, C) mapping ``src`` onto ``dst`` (both float (h, w, C)) on robust pixels.

    Each iteration keeps the pixels whose residual is below the median residual, so occluders and
    local changes (a few tens of percent of the image) do not bias the fit.
    """
    idx = np.flatnonzero(valid.ravel())
    if idx.size < 16:
        return np.stack([np.ones(src.shape[2], np.float32), np.zeros(src.shape[2], np.float32)])
    if idx.size > max_samples:
        idx = idx[:: idx.size // max_samples + 1]
    x = src.reshape(-1, src.shape[2])[idx].astype(np.float64)
    y = dst.reshape(-1, dst.shape[2])[idx].astype(np.float64)
    keep = np.ones(len(idx), bool)
    coef = np.zeros((2, src.shape[2]))
    for _ in range(max(1, iterations)):
        for c in range(src.shape[2]):
            xc, yc = x[keep, c], y[keep, c]
            var = xc.var()
            gain = ((xc - xc.mean()) * (yc - yc.mean())).mean() / var if var > 1e-8 else 1.0
            gain = float(np.clip(gain, 0.2, 5.0))
            coef[0, c], coef[1, c] = gain, yc.mean() - gain * xc.mean()
        resid = np.abs(x * coef[0] + coef[1] - y).sum(axis=1)
        keep = resid <= np.median(resid)
    return coef.astype(np.float32)


def masked_median(images: F32, valid: NDArray[np.bool_]) -> tuple[F32, NDArray[np.int32]]:
    """Per-pixel median over N of ``images`` (N, h, w, C) where ``valid`` (N, h, w).

    Returns the median (h, w, C) (zero where nothing is valid) and the count (h, w).
    """
    n, h, w, c = images.shape
    count = valid.sum(axis=0).astype(np.int32)
    if n == 1:
        return np.where(valid[0][..., None], images[0], 0.0).astype(np.float32), count
    # (h, w, C, N) contiguous so the sort runs along memory
    data = np.ascontiguousarray(np.moveaxis(images, 0, -1))
    data[~np.broadcast_to(np.moveaxis(valid, 0, -1)[:, :, None, :], data.shape)] = np.inf
    data.sort(axis=-1)
    lo = np.clip((count - 1) // 2, 0, n - 1)[..., None, None]
    hi = np.clip(count // 2, 0, n - 1)[..., None, None]
    lo = np.broadcast_to(lo, (h, w, c, 1))
    hi = np.broadcast_to(hi, (h, w, c, 1))
    med = 0.5 * (np.take_along_axis(data, lo, axis=-1)[..., 0] + np.take_along_axis(data, hi, axis=-1)[..., 0])
    med[count == 0] = 0.0
    return med.astype(np.float32), count


def to_hsv(bgr: F32) -> F32:
    """HSV (h, w, 3) of a float BGR image in [0, 1]: H in degrees [0, 360), S and V in [0, 1]."""
    return np.asarray(cv2.cvtColor(np.clip(bgr, 0.0, 1.0), cv2.COLOR_BGR2HSV), np.float32)


def hsv_channel_differences(ha: F32, hb: F32, saturation_weighted: bool = True) -> tuple[F32, F32, F32]:
    """Squared hue, saturation and value differences (each (h, w)) of two HSV images (:func:`to_hsv`).

    Hue difference is circular in [0, 0.5] (H scaled to [0, 1)); with ``saturation_weighted`` it is
    multiplied by the smaller saturation of the two pixels.
    """
    dh = np.abs(ha[..., 0] - hb[..., 0]) / 360.0
    dh = np.minimum(dh, 1.0 - dh)
    if saturation_weighted:
        dh = dh * np.minimum(ha[..., 1], hb[..., 1])
    ds = ha[..., 1] - hb[..., 1]
    dv = ha[..., 2] - hb[..., 2]
    return dh * dh, ds * ds, dv * dv


def hsv_squared_difference(a_bgr: F32, b_bgr: F32, saturation_weighted: bool = True) -> F32:
    """Squared per-channel HSV difference (h, w, 3) of two float BGR images in [0, 1] (see
    :func:`hsv_channel_differences`)."""
    d = hsv_channel_differences(to_hsv(a_bgr), to_hsv(b_bgr), saturation_weighted)
    return np.stack(d, axis=-1).astype(np.float32)


def sky_like(bgr: F32, max_std: float = 0.08) -> NDArray[np.bool_]:
    """Bright, smooth (5x5 grey std < ``max_std``), grey or blue pixels (h, w) of a float BGR image in
    [0, 1]: sky and clouds (cloud outlines included at the default ``max_std``)."""
    hsv = cv2.cvtColor(np.clip(bgr, 0.0, 1.0), cv2.COLOR_BGR2HSV)
    g = cv2.cvtColor(np.clip(bgr, 0.0, 1.0), cv2.COLOR_BGR2GRAY)
    mean = cv2.blur(g, (5, 5))
    std = np.sqrt(np.maximum(cv2.blur(g * g, (5, 5)) - mean * mean, 0.0))
    blue = (hsv[..., 0] > 180.0) & (hsv[..., 0] < 250.0)
    return (hsv[..., 2] > 0.55) & ((hsv[..., 1] < 0.25) | blue) & (std < max_std)


def open_sky(photo_bgr: F32) -> NDArray[np.bool_]:
    """Sky-like pixels (h, w) of the photo connected to the top image border: open sky. A pixel of the
    photo that shows open sky cannot show an occluder (a white vehicle on the ground is sky-like in
    colour but not connected to the top through sky)."""
    core = sky_like(photo_bgr, max_std=0.03).astype(np.uint8)  # strict: does not leak over bright ground
    n, labels = cv2.connectedComponents(core, connectivity=4)
    top = np.unique(labels[0][core[0] > 0])
    keep = np.zeros(n, bool)
    keep[top] = True
    keep[0] = False
    sky = keep[labels].astype(np.uint8)
    # cloud outlines are not smooth: take relaxed sky-like pixels within a few pixels of the open sky
    return (cv2.dilate(sky, np.ones((9, 9), np.uint8)) > 0) & sky_like(photo_bgr)


def raw_score(photo: F32, other: F32, params: DynamicParams, photo_hsv: F32 | None = None) -> F32:
    """Per-pixel max over channels of the squared HSV difference (h, w), before smoothing.
    ``photo_hsv``: :func:`to_hsv` of ``photo`` when already computed."""
    hp = to_hsv(photo) if photo_hsv is None else photo_hsv
    dh, ds, dv = hsv_channel_differences(hp, to_hsv(other), params.hue_saturation_weighted)
    return np.maximum(np.maximum(dh, ds), dv).astype(np.float32)


def order_statistic(scores: F32, valid: NDArray[np.bool_], q: float) -> F32:
    """Per-pixel floor(q * (n - 1))-th smallest of ``scores`` (N, h, w) over the n entries ``valid``
    (N, h, w) at the pixel; inf where none is valid."""
    data = np.where(valid, scores, np.inf).astype(np.float32)
    data.sort(axis=0)
    n = valid.sum(axis=0)
    rank = np.clip(np.floor(q * (n - 1)).astype(np.int64), 0, data.shape[0] - 1)
    return np.take_along_axis(data, rank[None], axis=0)[0]


def _sides(stack: AlignedStack, per_side: int) -> list[NDArray[np.intp]]:
    """Indices of the up to ``per_side`` nearest-in-time neighbours before and at-or-after the photo
    (sides without neighbours omitted; when all are on one side, that side only)."""
    dt = np.asarray(stack.times_ns, dtype=np.float64) - float(stack.photo_time_ns)
    out = []
    for idx in (np.flatnonzero(dt < 0), np.flatnonzero(dt >= 0)):
        if len(idx):
            out.append(idx[np.argsort(np.abs(dt[idx]), kind="stable")[:per_side]])
    return out


def vote_score(
    photo: F32,
    norm: F32,
    valid: NDArray[np.bool_],
    stack: AlignedStack,
    params: DynamicParams,
    progress_region: NDArray[np.bool_] | None,
) -> F32:
    """Order-statistic score (h, w): every neighbour's (N, h, w, 3) max-channel squared HSV difference
    to the photo is smoothed by the cross-bilateral filter; the score is the floor(q * (n - 1))-th
    smallest over the n neighbours valid at the pixel (q = ``params.vote_quantile``). With
    ``temporal_guard`` it is capped, inside ``progress_region`` (everywhere when None), by the
    smaller of the two per-side scores (median-rank of the ``guard_views`` nearest earlier, resp.
    later, neighbours): construction progress agrees with one side, a transient occluder with none.
    The guard counts every neighbour that sees the pixel (``stack.valid``), also where its own mask
    says occluder: a provisional mask that took the progress for an occluder (streaming: computed
    before the registration, or without a later frame) would otherwise switch the guard off there and
    pass the error on to every frame whose stack holds it.
    """
    q = 0.5 if params.vote_quantile is None else float(params.vote_quantile)
    hp = to_hsv(photo)
    raw = [raw_score(photo, norm[i], params, hp) for i in range(norm.shape[0])]
    scores = np.stack(smooth_scores(photo, raw, params))
    score = order_statistic(scores, valid, q)
    if params.temporal_guard and stack.num_views >= 2 and len(stack.times_ns) == stack.num_views:
        guard = np.full(score.shape, np.inf, np.float32)
        for idx in _sides(stack, params.guard_views):
            guard = np.minimum(guard, order_statistic(scores[idx], stack.valid[idx], 0.5))
        capped = np.minimum(score, guard)
        score = capped if progress_region is None else np.where(progress_region, capped, score)
    score[~np.isfinite(score)] = 0.0
    return score


def median_score(
    photo: F32,
    background: F32,
    norm: F32,
    stack: AlignedStack,
    params: DynamicParams,
    progress_region: NDArray[np.bool_] | None,
) -> F32:
    """Paper score (h, w): smoothed max-channel squared HSV difference to the median ``background``;
    with ``temporal_guard`` capped (inside ``progress_region``, everywhere when None) by the score
    against the nearest earlier and the nearest later neighbour."""
    raw = [raw_score(photo, background, params)]
    guard_valid: list[NDArray[np.bool_]] = []
    if params.temporal_guard and stack.num_views >= 2 and len(stack.times_ns) == stack.num_views:
        dt = np.asarray(stack.times_ns, dtype=np.float64) - float(stack.photo_time_ns)
        sides = [np.flatnonzero(dt < 0), np.flatnonzero(dt >= 0)]
        nearest = [int(idx[np.argmin(np.abs(dt[idx]))]) for idx in sides if len(idx)]
        if len(nearest) == 1:  # all neighbours on one side: the two nearest
            nearest = [int(i) for i in np.argsort(np.abs(dt))[:2]]
        raw += [raw_score(photo, norm[i], params) for i in nearest]
        guard_valid += [stack.valid[i] for i in nearest]
    smoothed = smooth_scores(photo, raw, params)
    score = smoothed[0]
    if guard_valid:
        guard = np.full(score.shape, np.inf, np.float32)
        for v_i, s_i in zip(guard_valid, smoothed[1:], strict=True):
            guard = np.minimum(guard, np.where(v_i, s_i, np.inf))
        capped = np.minimum(score, guard)
        score = capped if progress_region is None else np.where(progress_region, capped, score)
    return score


def smooth_scores(photo: F32, scores: list[F32], params: DynamicParams) -> list[F32]:
    """Cross-bilateral smoothing (guided by the photo) of up to three score maps in one filter call."""
    out: list[F32] = []
    for k in range(0, len(scores), 3):
        chunk = scores[k : k + 3]
        stacked = np.stack(chunk + [chunk[0]] * (3 - len(chunk)), axis=-1)
        smoothed = cv2.ximgproc.jointBilateralFilter(
            photo, stacked, params.bilateral_diameter_px, params.bilateral_sigma_color, params.bilateral_sigma_space_px
        )
        out += [np.asarray(smoothed[..., c], np.float32) for c in range(len(chunk))]
    return out


def background_and_difference(
    photo_small: U8, stack: AlignedStack, params: DynamicParams, progress_region: NDArray[np.bool_] | None = None
) -> tuple[F32, F32, NDArray[np.int32]]:
    """Exposure-normalised median background (h, w, 3) float BGR, difference score (h, w) (occluded
    where > ``params.threshold``) and per-pixel view count (h, w).

    The score is the cross-bilateral-smoothed max-channel squared HSV difference between photo and
    median. With ``temporal_guard`` it is also capped by the score against the nearest earlier and
    the nearest later neighbour (the photo must differ from both): construction progress between
    days changes the scene for good, so a photo agrees with the neighbours on its side of the
    change, while a transient occluder differs from both. ``progress_region`` (h, w) limits the
    guard to where the building can change (the projected model); None applies it everywhere.
    """
    photo = photo_small.astype(np.float32) * np.float32(1.0 / 255.0)
    norm = np.empty(stack.images.shape, np.float32)
    for i in range(stack.num_views):
        img = stack.images[i].astype(np.float32) * np.float32(1.0 / 255.0)
        coef = fit_exposure(img, photo, stack.valid[i], params.exposure_iterations)
        np.multiply(img, coef[0], out=norm[i])
        norm[i] += coef[1]
    valid_bg: NDArray[np.bool_] = stack.valid
    if params.exclude_neighbour_occluders and stack.occluded is not None:
        # leave the neighbours' own occluders out of the median where another view still covers the pixel
        clean: NDArray[np.bool_] = np.logical_and(stack.valid, np.logical_not(stack.occluded))
        valid_bg = np.where(np.any(clean, axis=0, keepdims=True), clean, stack.valid).astype(np.bool_)
    background, count = masked_median(norm, valid_bg)
    if params.vote_quantile is not None:
        score = vote_score(photo, norm, valid_bg, stack, params, progress_region)
    else:
        score = median_score(photo, background, norm, stack, params, progress_region)
    if params.ignore_sky:
        score[sky_like(photo) & sky_like(background)] = 0.0
    score[count == 0] = 0.0
    return np.clip(background, 0.0, 1.0), score, count


def hysteresis_mask(score: F32, strong: float, weak: float, max_grow_px: int | None = None) -> U8:
    """0/255 mask of pixels with ``score`` (h, w) above ``weak`` that are 8-connected to a pixel above ``strong``;
    with ``max_grow_px``, only through weak pixels within that distance of the convex hull of a blob of strong
    pixels. An occluder's inside may match the background in places and is filled (it lies in its outline's hull),
    but the growth does not run off along the scene: a slight day-to-day change of a saturated surface (the
    hoarding's green under another sky) passes the weak threshold along its whole length, and an occluder standing
    in front of it would flood it."""
    strong_px = score > strong
    if weak >= strong:
        return strong_px.astype(np.uint8) * 255
    weak_px = (score > weak) | strong_px
    if max_grow_px is not None:
        hull = np.zeros(score.shape, np.uint8)
        contours, _ = cv2.findContours(strong_px.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        for c in contours:
            cv2.fillConvexPoly(hull, cv2.convexHull(c), 1)
        near = hull
        if max_grow_px > 0:
            near = np.asarray(cv2.dilate(hull, np.ones((2 * max_grow_px + 1, 2 * max_grow_px + 1), np.uint8)))
        weak_px &= near > 0
    n, labels = cv2.connectedComponents(weak_px.astype(np.uint8), connectivity=8)
    seeded = np.zeros(n, bool)
    seeded[np.unique(labels[strong_px])] = True
    seeded[0] = False
    return np.where(seeded[labels], 255, 0).astype(np.uint8)


def remove_ghosts(mask: U8, photo: U8, background: U8, ratio: float, window_px: int = 7) -> U8:
    """Drop blobs whose outline separates regions of the background rather than of the photo.

    With few views the background can still show a neighbour's occluder ("ghost"); its difference
    blob then has the occluder's colour inside *in the background* and the scene in the photo. Across
    a real occluder's outline the photo changes (occluder | scene) while the background is continuous
    scene; across a ghost's it is the other way round. A blob is kept when the photo's mean colour
    contrast across its outline (local means inside vs outside, ``window_px`` box) is at least
    ``ratio`` x the background's.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask
    out = mask.copy()
    H, W = mask.shape
    pad = window_px + 2
    kernel = np.ones((3, 3), np.uint8)
    box = (window_px, window_px)
    for i in range(1, n):
        x, y, w, h = stats[i, :4]
        x0, y0, x1, y1 = max(0, x - pad), max(0, y - pad), min(W, x + w + pad), min(H, y + h + pad)
        comp = (labels[y0:y1, x0:x1] == i).astype(np.float32)
        outline = (cv2.dilate(comp, kernel) - comp) > 0
        w_in = cv2.boxFilter(comp, -1, box, normalize=False)
        w_out = cv2.boxFilter(1.0 - comp, -1, box, normalize=False)
        ok = outline & (w_in > 0) & (w_out > 0)
        if not ok.any():
            continue
        contrast = []
        for img in (photo, background):
            crop = img[y0:y1, x0:x1].astype(np.float32)
            m_in = cv2.boxFilter(crop * comp[..., None], -1, box, normalize=False) / np.maximum(w_in, 1e-6)[..., None]
            m_out = (
                cv2.boxFilter(crop * (1.0 - comp[..., None]), -1, box, normalize=False)
                / np.maximum(w_out, 1e-6)[..., None]
            )
            contrast.append(float(np.linalg.norm((m_in - m_out)[ok], axis=1).mean()))
        if contrast[0] < ratio * contrast[1]:
            out[y0:y1, x0:x1][comp > 0] = 0
    return out


def fill_holes(mask: U8) -> U8:
    """Fill background regions of a 0/255 mask that do not touch the image border."""
    inv = (mask == 0).astype(np.uint8)
    n, labels = cv2.connectedComponents(inv, connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    hole = np.ones(n, bool)
    hole[border] = False
    hole[0] = False  # label 0 is the mask itself
    return np.where(hole[labels] | (mask > 0), 255, 0).astype(np.uint8)


def remove_small_components(mask: U8, min_area_px: int) -> U8:
    """Drop 8-connected blobs of ``mask`` (0/255) smaller than ``min_area_px``."""
    if min_area_px <= 1:
        return mask
    n, labels, stats, _ = cv2.connectedComponentsWithStats((mask > 0).astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area_px
    keep[0] = False
    return np.where(keep[labels], 255, 0).astype(np.uint8)


def small_bbox(mask_small: NDArray[np.generic], pad_px: int) -> tuple[int, int, int, int] | None:
    """Bounding box (x0, y0, x1, y1) of the non-zero pixels of a working-size mask, padded; None if empty."""
    ys, xs = np.nonzero(mask_small)
    if len(xs) == 0:
        return None
    h, w = mask_small.shape[:2]
    return (
        max(0, xs.min() - pad_px),
        max(0, ys.min() - pad_px),
        min(w, xs.max() + 1 + pad_px),
        min(h, ys.max() + 1 + pad_px),
    )


def _full_box(
    box: tuple[int, int, int, int], small_size: tuple[int, int], full_size: tuple[int, int]
) -> tuple[int, ...]:
    (x0, y0, x1, y1), (w, h), (W, H) = box, small_size, full_size
    return round(x0 * W / w), round(y0 * H / h), round(x1 * W / w), round(y1 * H / h)


def upsample_mask(soft_small: F32, photo_full: U8, radius_px: int, eps: float) -> U8:
    """Upsample a soft mask in [0, 1] to the photo's size, edges snapped by a guided filter. 0/255.

    Full-resolution work is confined to the bounding box of the mask (plus the filter's reach).
    """
    H, W = photo_full.shape[:2]
    h, w = soft_small.shape[:2]
    out = np.zeros((H, W), np.uint8)
    box = small_bbox(soft_small > 0.02, 2 + (4 * radius_px * w) // W)
    if box is None:
        return out
    X0, Y0, X1, Y1 = _full_box(box, (w, h), (W, H))
    x0, y0, x1, y1 = box
    soft = cv2.resize(soft_small[y0:y1, x0:x1], (X1 - X0, Y1 - Y0), interpolation=cv2.INTER_LINEAR)
    if radius_px > 0:
        guide = cv2.cvtColor(np.ascontiguousarray(photo_full[Y0:Y1, X0:X1]), cv2.COLOR_BGR2GRAY)
        soft = cv2.ximgproc.guidedFilter(guide, soft, radius_px, eps * 255.0 * 255.0)
    out[Y0:Y1, X0:X1] = np.where(soft > 0.5, 255, 0).astype(np.uint8)
    return out


def clean_plate(photo_full: U8, mask_small: U8, mask: U8, background_small: F32, count: NDArray[np.int32]) -> U8:
    """The photo with the masked pixels replaced by the (upsampled) median background, feathered."""
    H, W = photo_full.shape[:2]
    h, w = mask_small.shape[:2]
    plate = photo_full.copy()
    box = small_bbox(mask_small, 3)
    if box is None:
        return plate
    X0, Y0, X1, Y1 = _full_box(box, (w, h), (W, H))
    x0, y0, x1, y1 = box
    size = (X1 - X0, Y1 - Y0)
    bg = cv2.resize((background_small[y0:y1, x0:x1] * 255.0).astype(np.uint8), size, interpolation=cv2.INTER_LINEAR)
    covered = cv2.resize((count[y0:y1, x0:x1] > 0).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    dilated = np.asarray(cv2.dilate(mask[Y0:Y1, X0:X1], np.ones((5, 5), np.uint8)), np.uint8)
    m = dilated & (np.asarray(covered, np.uint8) * np.uint8(255))
    alpha = cv2.GaussianBlur(m, (0, 0), 2.0).astype(np.float32) * np.float32(1.0 / 255.0)
    plate[Y0:Y1, X0:X1] = cv2.blendLinear(bg, np.ascontiguousarray(photo_full[Y0:Y1, X0:X1]), alpha, 1.0 - alpha)
    return plate


def dynamic_mask(
    photo_full: U8,
    photo_small: U8,
    stack: AlignedStack,
    params: DynamicParams | None = None,
    progress_region: NDArray[np.bool_] | None = None,
    appearance: ColourModel | None = None,
) -> DynamicResult:
    """Dynamic-occluder mask and clean plate of a photo (uint8 BGR, full and working size).

    ``progress_region``: bool (h, w) at working size, where the building may change between views
    (the projected BIM); see :func:`background_and_difference`. ``appearance``: the site's colour
    model, used as ``params.appearance`` says once it has seen ``appearance_min_frames`` masks (see
    :func:`appearance_combine`). ``timelapse_small`` of the result is the mask before that step.
    """
    params = params or DynamicParams()
    h, w = photo_full.shape[:2]
    if stack.num_views < max(1, params.min_views):
        res = DynamicResult("not_enough_views", np.zeros((h, w), np.uint8), None, stack.num_views)
        return with_appearance(res, photo_full, photo_small, appearance, params)
    background, score, count = background_and_difference(photo_small, stack, params, progress_region)
    small = hysteresis_mask(score, params.threshold, params.threshold * params.weak_ratio, params.max_grow_px)
    if params.ignore_sky:
        small[open_sky(photo_small.astype(np.float32) * np.float32(1.0 / 255.0))] = 0
    small = remove_small_components(small, int(params.min_component_frac * small.size))
    if params.ghost_ratio > 0:
        small = remove_ghosts(small, photo_small, (background * 255.0).astype(np.uint8), params.ghost_ratio)
    if params.fill_holes:
        small = fill_holes(small)
    combined, added = appearance_combine(small, photo_small, appearance, params)
    mask, plate = _finish(photo_full, combined, background, count, params)
    return DynamicResult("ok", mask, plate, stack.num_views, small, added)


def _finish(
    photo_full: U8, small: U8, background: F32 | None, count: NDArray[np.int32] | None, params: DynamicParams
) -> tuple[U8, U8 | None]:
    """Full-resolution mask of a working-size 0/255 mask and the clean plate (None without a background)."""
    soft = np.asarray(cv2.GaussianBlur(small.astype(np.float32) / 255.0, (3, 3), 0), np.float32)
    mask = upsample_mask(soft, photo_full, params.guided_radius_px, params.guided_eps)
    if background is None or count is None:
        return mask, None
    return mask, clean_plate(photo_full, small, mask, background, count)


def _appearance_ready(model: ColourModel | None, params: DynamicParams) -> bool:
    if params.appearance not in ("off", "no_stack", "all"):
        raise ValueError(f"unknown appearance mode {params.appearance!r} (off, no_stack or all)")
    return model is not None and params.appearance != "off" and model.num_frames >= max(1, params.appearance_min_frames)


def appearance_combine(
    timelapse_small: U8, photo_small: U8, model: ColourModel | None, params: DynamicParams
) -> tuple[U8, int]:
    """With ``params.appearance == "all"`` and a ready model: a time-lapse working-size mask without its
    blobs (:func:`veto_by_colour`, ``appearance_veto``) and pixels (``appearance_pixel_veto``) of
    static-scene colour, and with the appearance pixels (:func:`appearance_small_mask`) added.
    The vetoes apply only when the model recognises its own training masks
    (:meth:`ColourModel.recall` at the veto level >= ``appearance_min_recall``): where equipment
    shares the static scene's colours the time-lapse mask is kept as it is. Returns the mask and
    the number of added pixels; the mask itself otherwise."""
    if params.appearance != "all" or not _appearance_ready(model, params):
        return timelapse_small, 0
    assert model is not None
    post = smoothed_posterior(photo_small, model, params)
    kept = timelapse_small
    veto_level = max(params.appearance_veto, params.appearance_pixel_veto)
    if veto_level > 0 and model.recall(veto_level, params.appearance_prior_count) >= params.appearance_min_recall:
        kept = veto_by_colour(kept, post, params.appearance_veto)
        if params.appearance_pixel_veto > 0:
            kept = remove_small_components(
                np.where(post >= params.appearance_pixel_veto, kept, 0).astype(np.uint8),
                int(params.min_component_frac * kept.size),
            )
    added = (appearance_small_mask(photo_small, post, params) > 0) & (kept == 0)
    small = np.where(added, 255, kept).astype(np.uint8)
    return (fill_holes(small) if params.fill_holes else small), int(np.count_nonzero(added))


def recombine(
    timelapse_small: U8, photo_full: U8, photo_small: U8, model: ColourModel | None, params: DynamicParams
) -> tuple[U8, int]:
    """The full-resolution mask (H, W) 0/255 of a time-lapse working mask redone with the colour model as it is
    now (:func:`appearance_combine`, then upsampled as :func:`dynamic_mask` does) and the number of pixels the
    model added: what a photo's dynamic mask becomes when only the colour model changed since (its stack, and
    so its time-lapse mask and clean plate, did not)."""
    small, added = appearance_combine(timelapse_small, photo_small, model, params)
    mask, _ = _finish(photo_full, small, None, None, params)
    return mask, added


def with_appearance(
    res: DynamicResult,
    photo_full: U8,
    photo_small: U8,
    model: ColourModel | None,
    params: DynamicParams,
) -> DynamicResult:
    """Apply the appearance model to a finished result: a photo without a stack gets
    :func:`appearance_small_mask` as its mask (status ok, ``num_views`` 0, no clean plate) with
    ``params.appearance`` "no_stack" or "all"; with "all" a time-lapse result is redone by
    :func:`appearance_combine` (its clean plate kept). Unchanged when the model is None or not ready."""
    if not _appearance_ready(model, params):
        return res
    assert model is not None
    if res.status != "ok":
        extra = appearance_small_mask(photo_small, smoothed_posterior(photo_small, model, params), params)
        mask, _ = _finish(photo_full, extra, None, None, params)
        return DynamicResult("ok", mask, None, 0, None, int(np.count_nonzero(extra)))
    if res.timelapse_small is None:
        return res
    small, added = appearance_combine(res.timelapse_small, photo_small, model, params)
    if np.array_equal(small, res.timelapse_small):
        return res
    mask, _ = _finish(photo_full, small, None, None, params)
    return DynamicResult("ok", mask, res.background, res.num_views, res.timelapse_small, added)
