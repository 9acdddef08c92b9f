"""Per-photo evidence of which elements stand, from image evidence only (pure core: numpy + OpenCV).

Inputs are arrays at one working size (H, W): the photo in CIE Lab (``lab``, float32, L in [0, 100]), its
occlusion mask (``occluded``, bool), the model :class:`~nodes.progress.modelview.Layers` at the photo's registered
pose (built = what the fusion believes stood just before, candidates = elements the schedule window allows), and,
for fixed cameras, the camera's reference plate (the last unoccluded look of every pixel in earlier frames, warped
onto this photo). Four cues, each a log-likelihood ratio (natural log) per element:

* ``change``: the fraction of the element's exclusive pixels (it is the only candidate in front of the believed
  built surface there) whose look changed against the reference plate; evidence that the element *appeared*
  between the plate's time and this photo (a transition, not a state). A pixel counts as much as nothing else
  could have changed it: a candidate behind the element, a built element behind it or an element beside it (blur
  and registration error reach ``neighbour_px``) that appeared since the plate's frame. Elements too thin for a
  2 px interior (a slab seen edge-on, a beam) are read 1 px inside;
* ``points``: sparse-cloud observations of this photo lying on the element's surface (present) or behind it along
  the viewing ray (absent: the camera saw through it);
* ``appearance``: the colours of the element's pixels under a model of its material (learnt from this photo's
  believed-built elements of that material and from confident detections elsewhere) against a model of what would
  show if it were absent (the believed-built surface behind it, or the background);
* ``edge`` (candidates only): the share of a candidate's outline, where the same thing would show on both sides
  were it absent, that has an edge across it stronger than the texture just outside.

Elements whose region is mostly covered by the occlusion mask are ``occluded``; too few pixels, ``unknown``.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from nodes.progress.modelview import Layers

F32 = NDArray[np.float32]
BoolA = NDArray[np.bool_]

AB_BINS = 12  # chroma bins per axis of the colour histograms
L_BINS = 4
AB_RANGE = 60.0  # |a|, |b| beyond this fall in the outer bins


@dataclass(frozen=True)
class EvidenceParams:
    """Thresholds of the cues (working resolution ~640 px wide)."""

    min_pixels: int = 40
    """An element needs this many unoccluded pixels in its region for any evidence."""
    occluded_fraction: float = 0.7
    """... and an element whose region is covered by the mask beyond this fraction is ``occluded``."""
    change_threshold: float = 0.5
    """Per-pixel change score above which a pixel counts as changed."""
    change_hit: float = 0.85
    """Changed fraction of an element's pixels where it appeared."""
    change_noise: float = 0.1
    """Changed fraction where nothing appeared (lighting, unmasked movers, registration error)."""
    change_neutral: float = 0.35
    """Changed fraction at which the change cue is neutral (LLR 0)."""
    change_slope: float = 12.0
    """LLR per unit of changed fraction."""
    interior_px: int = 2
    """The change cue uses pixels at least this far inside an element's region."""
    thin_interior_px: int = 1
    """Interior radius for elements with too few pixels at ``interior_px`` (a slab seen edge-on, a beam; -1: none,
    they get no change cue). Their pixels with a candidate behind are left out and their change score's structure
    window shrinks to ``2 * thin_interior_px + 1``."""
    built_behind: bool = True
    """Discount a candidate's changed pixels where a built element behind it may have appeared since the plate."""
    neighbour_px: int = 3
    """Discount, likewise, pixels this close to another element that may have changed since the plate (the
    registration's error and the change score's blur reach it; -1: none). These two, ``thin_interior_px`` and
    ``EngineParams.unchanged_floor``: BENCHMARKS progress notes, 2026-12-05."""
    hidden_behind_appeared: float = 0.3
    """P(appeared since the plate) taken for a candidate behind an element where it has too few pixels of its own to
    tell (fewer than ``min_pixels``)."""
    change_ring_px: int = 8
    """A change inside an element speaks for its appearance only as much as its surroundings stayed the same: a
    positive change LLR is scaled by ``(1 - f) ** change_ring_power``, f the changed fraction of the ring this wide
    around the element (valid pixels; 0: off). Something beside or behind it going up, a moving shadow or a
    registration shift change the ring too; its own appearance mostly does not."""
    change_ring_power: float = 0.5
    change_full_pixels: int = 60
    """Pixels for the full change LLR (fewer scale it down)."""
    max_llr: float = 5.0
    point_margin_m: float = 0.15
    point_margin_rel: float = 0.02
    """A point within ``margin_m + margin_rel * depth`` of a surface lies on it."""
    point_llr: float = 0.7
    """LLR per (verified) point, saturating at ``max_llr``."""
    edge: bool = True
    edge_gap_px: int = 2
    """The silhouette cue compares pixels this far inside (minus one) and outside a candidate's outline ..."""
    edge_control_px: int = 3
    """... and, as the control, the outside pixel with one this much further out."""
    edge_min_contrast: float = 4.0
    """Colour difference (Lab units) across the outline for an edge."""
    edge_control_ratio: float = 1.5
    """... that also exceeds the control's difference this many times (texture of what shows around it)."""
    edge_slope: float = 5.0
    """LLR per unit of the outline's edge fraction ..."""
    edge_neutral: float = 0.45
    """... neutral at this fraction."""
    edge_full_samples: int = 60
    """Outline samples for the full edge LLR (fewer scale it down)."""
    edge_max_llr: float = 2.0
    edge_negative_scale: float = 0.25
    """Share of a negative edge LLR kept: a standing element that looks like what surrounds it (a slab on a slab of
    the same concrete) shows no edge either."""
    appearance: bool = True
    appearance_scale: float = 1.5
    """LLR per unit of mean per-pixel log ratio."""
    appearance_max_llr: float = 1.0
    appearance_negative_scale: float = 0.3
    """Share of a negative appearance LLR kept: on the synthetic sites a built element looks unlike its material
    (partly hidden by an unmasked occluder or a missing neighbour, odd light) about as often as an absent one does
    (6 % vs 10 % of the visible ones, 26 % of the hidden ones), while a positive look is ~12x likelier when built."""
    appearance_full_pixels: int = 200
    """Visible pixels for the full appearance LLR (fewer scale it down linearly; 0: no scaling)."""
    appearance_min_reference_px: int = 150
    """Pixels a material / absence model needs before it is used."""
    appearance_ring_px: int = 12
    """Background pixels this close to an element's region model what shows where it is absent."""
    appearance_same_behind: bool = True
    """A candidate's pixels in front of a believed-built element of its own material say nothing of it: absent, they
    would show that element's look (the same colours), so they count as neutral in its appearance cue (a concrete
    column before a concrete slab was read standing before it went up; BENCHMARKS progress notes, 2026-12-07)."""
    appearance_novelty_weight: float = 0.5
    """Without a known look of its material (the first frames of a site, before any element of that material is
    seen appearing) an element's colours are tested against a flat model (anything unlike what would show where
    it is absent); this weight stands for the material look's confidence (``alpha``) on the mean log ratio, before
    the ``appearance_max_llr`` clip; 0: no appearance evidence then."""


@dataclass
class ElementCue:
    """One element's evidence in one photo. ``index`` is the 1-based element index."""

    index: int
    region_px: int
    visible_px: int
    occluded_fraction: float
    exclusive_px: int = 0
    changed_fraction: float = float("nan")
    llr_change: float = 0.0
    reference_ns: int = 0
    points_on: float = 0.0
    points_behind: float = 0.0
    llr_points: float = 0.0
    llr_appearance: float = 0.0
    edge_samples: int = 0
    edge_fraction: float = float("nan")
    llr_edge: float = 0.0
    status: str = "seen"  # seen | occluded | unknown


def to_lab(rgb: NDArray[np.uint8]) -> F32:
    """(H, W, 3) float32 CIE Lab of an RGB uint8 image (L 0-100, a/b about -100..100)."""
    return np.asarray(cv2.cvtColor(rgb.astype(np.float32) / 255.0, cv2.COLOR_RGB2LAB), np.float32)


class ChangeParts:
    """Per-pixel change score in [0, 1] between two aligned Lab images (the photo, its plate), robust to a global
    exposure change and to ~1 px of misalignment: the largest of an exposure-corrected lightness ratio, a chroma
    difference and a local structure dissimilarity (1 - NCC of L over ``window_px`` windows, where either side is
    textured). Built once per photo and plate (and window); :meth:`changed` thresholds the score with the exposure
    gain (:meth:`gain`) of the valid pixels."""

    _L1: F32
    _L0: F32
    _chroma: F32

    def __init__(self, lab: F32, ref: F32, window_px: int = 5, like: ChangeParts | None = None) -> None:
        """``like``: parts of the same photo and plate at another window (their lightness and chroma are shared)."""
        if like is None:
            cur = cv2.GaussianBlur(lab, (0, 0), 0.6)
            old = cv2.GaussianBlur(ref, (0, 0), 0.6)
            L1, L0 = cur[..., 0] + 1.0, old[..., 0] + 1.0
            self.ratio = np.log(L1 / L0)
            chroma = np.hypot(cur[..., 1] - old[..., 1], cur[..., 2] - old[..., 2]) / 14.0
        else:
            L1, L0, self.ratio, chroma = like._L1, like._L0, like.ratio, like._chroma
        self._L1, self._L0, self._chroma = L1, L0, chroma
        k = (window_px, window_px)
        m1, m0 = cv2.blur(L1, k), cv2.blur(L0, k)
        v1 = np.maximum(cv2.blur(L1 * L1, k) - m1 * m1, 0.0)
        v0 = np.maximum(cv2.blur(L0 * L0, k) - m0 * m0, 0.0)
        ncc = (cv2.blur(L1 * L0, k) - m1 * m0) / np.sqrt(v1 * v0 + 1e-3)
        textured = np.clip((np.sqrt(np.maximum(v1, v0)) - 1.5) / 2.5, 0.0, 1.0)  # smooth -> 0, > 4 L units -> 1
        structure = textured * np.clip((1.0 - ncc) / 1.2, 0.0, 1.0)
        self.rest = np.maximum(chroma, structure)

    def gain(self, valid: BoolA) -> float:
        """Exposure gain: the median lightness log ratio over ``valid`` (the same for every window)."""
        return float(np.median(self.ratio[valid])) if valid.any() else 0.0

    def changed(self, threshold: float, gain: float, where: BoolA | None = None, light_scale: float = 0.5) -> BoolA:
        """Whether the change score (the largest of ``|ratio - gain| / light_scale`` and the chroma and structure
        parts, clipped to [0, 1]) exceeds ``threshold`` in [0, 1), ``gain`` = :meth:`gain` of the valid pixels;
        (H, W) bool, or (K,) at the pixels ``where`` only."""
        ratio, rest = (self.ratio, self.rest) if where is None else (self.ratio[where], self.rest[where])
        return (np.abs(ratio - gain) / light_scale > threshold) | (rest > threshold)


class PhotoCache:
    """What every reading pass of one photo (same photo, same plate) computes alike: colour bins, the edge cue's
    blur, the change score's parts per window. Pass one per photo to :func:`photo_evidence`."""

    def __init__(self, lab: F32) -> None:
        self.lab = lab
        self._bins: NDArray[np.int32] | None = None
        self._blur: F32 | None = None
        self._change: dict[int, ChangeParts] = {}
        self._ref: F32 | None = None

    def bins(self) -> NDArray[np.int32]:
        if self._bins is None:
            self._bins = colour_bins(self.lab)
        return self._bins

    def edge_blur(self) -> F32:
        if self._blur is None:
            self._blur = np.asarray(cv2.GaussianBlur(self.lab, (0, 0), 0.8), np.float32)
        return self._blur

    def change(self, ref: F32, window_px: int) -> ChangeParts:
        if ref is not self._ref:
            self._change, self._ref = {}, ref
        if window_px not in self._change:
            like = next(iter(self._change.values()), None)
            self._change[window_px] = ChangeParts(self.lab, ref, window_px, like)
        return self._change[window_px]


def interior(ids: NDArray[np.int64], radius_px: int) -> BoolA:
    """(H, W) bool: pixels whose (2r+1)^2 neighbourhood carries the same id."""
    if radius_px <= 0:
        return np.ones(ids.shape, bool)
    f = ids.astype(np.float32)  # exact for ids < 2^24
    k = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return (cv2.erode(f, k) == f) & (cv2.dilate(f, k) == f)


def _neighbours(ids: NDArray[np.int64], radius_px: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Two (H, W) maps of another element id within ``radius_px`` of each pixel: the largest and the smallest
    non-zero one (0: none)."""
    f = ids.astype(np.float32)
    k = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    hi = cv2.dilate(f, k).astype(np.int64)
    lo = cv2.erode(np.where(ids > 0, f, np.float32(2**24)), k).astype(np.int64)
    return np.where(hi != ids, hi, 0), np.where((lo != ids) & (lo < 2**24), lo, 0)


def colour_bins(lab: F32) -> NDArray[np.int32]:
    """(H, W) int32 histogram bin of every pixel: coarse L x fine a/b."""
    lb = np.clip((lab[..., 0] / 100.0 * L_BINS).astype(np.int32), 0, L_BINS - 1)
    ab = np.clip(((lab[..., 1:] + AB_RANGE) / (2 * AB_RANGE) * AB_BINS).astype(np.int32), 0, AB_BINS - 1)
    return (lb * AB_BINS + ab[..., 0]) * AB_BINS + ab[..., 1]


NUM_BINS = L_BINS * AB_BINS * AB_BINS


def normalised_hist(counts: NDArray[np.float64], prior: float = 1.0) -> NDArray[np.float64]:
    """Probability per bin with ``prior`` pseudo-counts spread over all bins (no zero probabilities)."""
    c = counts + prior / len(counts)
    return c / c.sum()


@dataclass
class MaterialModel:
    """Colour histograms per material, accumulated from confidently built element regions (any photo)."""

    counts: dict[str, NDArray[np.float64]] = field(default_factory=dict)

    def add(self, material: str, bins: NDArray[np.int32], weight: float = 1.0) -> None:
        h = self.counts.setdefault(material, np.zeros(NUM_BINS))
        h += weight * np.bincount(bins, minlength=NUM_BINS)

    def total(self, material: str) -> float:
        h = self.counts.get(material)
        return 0.0 if h is None else float(h.sum())


def photo_evidence(
    lab: F32,
    occluded: BoolA,
    layers: Layers,
    material_of: list[str],
    params: EvidenceParams,
    reference: tuple[F32, BoolA, NDArray[np.int64]] | None = None,
    points: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = None,
    materials: MaterialModel | None = None,
    present: NDArray[np.float64] | None = None,
    confirmed: NDArray[np.float64] | None = None,
    stood_at: Callable[[NDArray[np.int64], NDArray[np.int64]], NDArray[np.float64]] | None = None,
    cache: PhotoCache | None = None,
    settled: Collection[int] = (),
) -> list[ElementCue]:
    """Cues for every element with pixels in this photo's candidate or built layers.

    ``material_of[i]`` is the material of element index i (row 0 unused). ``reference`` = (plate Lab, plate valid,
    plate time ns per pixel), warped onto this photo. ``points`` = (pixels (N, 2) at working size, camera depths
    (N,) m, weights (N,)). ``present`` (n,): P(element stands) before this photo; ``confirmed`` (n,): 1 for
    elements seen appearing and standing since, whose pixels show their material's look. ``stood_at(indices,
    times_ns)`` -> P(element stood at that time), each (K,): where a candidate stands in front of a believed-built
    element that may have appeared since the plate was taken, a change may be that element's. Returns one
    :class:`ElementCue` per element, ascending index. ``cache``: the photo's :class:`PhotoCache` (the same plate in
    every pass; computed here when None). ``settled``: indices whose cues the caller already holds from an earlier
    pass of this photo: their status is given, their cues are not computed.
    """
    cache = PhotoCache(lab) if cache is None else cache
    n = len(material_of)
    ids_all = layers.ids_all.astype(np.int64)
    free = ~occluded
    region = np.bincount(ids_all.ravel(), minlength=n)[:n]
    visible = np.bincount(ids_all[free], minlength=n)[:n]
    cues: dict[int, ElementCue] = {}
    for i in np.nonzero(region[1:])[0] + 1:
        occ = 1.0 - visible[i] / region[i]
        status = "seen"
        if visible[i] < params.min_pixels:
            status = "occluded" if occ >= params.occluded_fraction else "unknown"
        cues[int(i)] = ElementCue(int(i), int(region[i]), int(visible[i]), float(occ), status=status)
    skip = set(settled)
    work = {i: c for i, c in cues.items() if i not in skip}
    if reference is not None:
        _change_cue(cache, free, layers, reference, params, work, n, present, stood_at)
    if points is not None and len(points[0]):
        _points_cue(layers, points, params, work, n)
    if params.edge:
        _edge_cue(cache.edge_blur(), free, layers, params, work)
    if params.appearance:
        _appearance_cue(cache.bins(), free, layers, material_of, params, work, materials, confirmed)
    return [cues[i] for i in sorted(cues)]


def _change_cue(
    cache: PhotoCache,
    free: BoolA,
    layers: Layers,
    reference: tuple[F32, BoolA, NDArray[np.int64]],
    p: EvidenceParams,
    cues: dict[int, ElementCue],
    n: int,
    present: NDArray[np.float64] | None,
    stood_at: Callable[[NDArray[np.int64], NDArray[np.int64]], NDArray[np.float64]] | None = None,
) -> None:
    """Transition evidence per element from the changed fraction of its front-most interior pixels against the
    plate: ``change_slope * (fraction - change_neutral)``, clipped, scaled down below ``change_full_pixels``.

    A pixel counts as much as nothing else could have changed it: where a candidate stands behind the element,
    the change may be that candidate appearing while the element was absent; how likely that candidate appeared
    is read from its own exclusive pixels (where nothing else could change it).
    """
    ref_lab, ref_valid, ref_time = reference
    valid = free & ref_valid
    parts = cache.change(ref_lab, 5)
    gain = parts.gain(valid)
    changed = parts.changed(p.change_threshold, gain)
    front = layers.ids_front.astype(np.int64)
    built = layers.ids_built.astype(np.int64)
    second = layers.ids_second.astype(np.int64)
    owner = np.where(front > 0, front, built)
    behind = np.where(front > 0, second, 0)
    # the change score looks at a neighbourhood: pixels near another element's region would see that one change
    sel = valid & (owner > 0) & interior(owner, p.interior_px)
    near: tuple[NDArray[np.int64], ...] = ()  # (H, W) elements beside each pixel whose change may spill onto it
    if 0 <= p.thin_interior_px < p.interior_px:
        # elements too thin for interior pixels (a slab seen edge-on, a beam) are read on a narrower interior
        n_in = np.bincount(owner[sel], minlength=n)[:n]
        thin = n_in < p.min_pixels // 2
        thin[0] = False
        extra = (
            valid
            & ~sel
            & (behind == 0)
            & thin[np.minimum(owner, n - 1)]
            & (owner < n)
            & interior(owner, p.thin_interior_px)
        )
        if extra.any():
            # their structure window must stay inside them too ...
            window = 2 * p.thin_interior_px + 1
            changed[extra] = cache.change(ref_lab, window).changed(p.change_threshold, gain, extra)
            sel |= extra
    if p.neighbour_px > 0:
        near = _neighbours(owner, p.neighbour_px)
    ids, beh, chg, times = owner[sel], behind[sel], changed[sel], ref_time[sel]
    sel_ys, sel_xs = np.nonzero(sel)  # the same (row-major) order as ids
    excl = beh == 0
    n_excl = np.bincount(ids[excl], minlength=n)[:n]
    f_excl = np.bincount(ids[excl], weights=chg[excl], minlength=n)[:n] / np.maximum(n_excl, 1)
    appeared = np.where(
        n_excl >= p.min_pixels,
        np.clip((f_excl - p.change_noise) / (p.change_hit - p.change_noise), 0.02, 0.98),
        p.hidden_behind_appeared,
    )
    stood = np.full(n, 0.5) if present is None else np.clip(np.asarray(present, np.float64), 0.0, 1.0)
    # a pixel speaks for its owner as much as nothing else could have changed it: the candidate behind it may have
    # appeared while the owner was absent
    wx = 1.0 - np.where(beh > 0, appeared[beh] * (1.0 - stood[ids]), 0.0)
    # ... and so may a built element behind it or an element beside it, where that one appeared
    # after the plate's frame: such a pixel would have changed with or without the owner, so the cue's strength
    # drops with their share
    is_cand = np.bincount(front[front < n], minlength=n)[:n] > 0
    is_cand[0] = False

    # candidates: P(appeared) from their exclusive pixels; built elements: from their belief, one lookup for all
    others = [np.where(front[sel] > 0, built[sel], 0)] if p.built_behind else []
    others += [side[sel] for side in near]
    p_other = np.zeros(len(ids))
    if others:
        other = np.stack(others)  # (S, K): element behind / beside each selected pixel, 0: none
        p_all = np.where(is_cand[other], appeared[other], 0.0)
        m = (other > 0) & ~is_cand[other]
        if stood_at is not None and m.any():
            t = np.broadcast_to(times, other.shape)
            times_u, t_idx = np.unique(t[m], return_inverse=True)
            key_u, inv = np.unique(other[m] * len(times_u) + t_idx.reshape(-1), return_inverse=True)
            el_u, tm_u = key_u // len(times_u), times_u[key_u % len(times_u)]
            p_all[m] = np.clip(stood[el_u] - stood_at(el_u, tm_u), 0.0, 1.0)[inv.reshape(-1)]
        p_other = p_all.max(0)
    wb = 1.0 - p_other * (1.0 - stood[ids])
    wx *= wb
    informative = np.bincount(ids, weights=wb, minlength=n)[:n] / np.maximum(np.bincount(ids, minlength=n)[:n], 1)
    tot = np.bincount(ids, weights=wx, minlength=n)[:n]
    s_chg = np.bincount(ids, weights=wx * chg, minlength=n)[:n]
    order = np.argsort(ids, kind="stable")
    ids_sorted, times_sorted = ids[order], times[order]
    starts = np.searchsorted(ids_sorted, np.arange(n))
    ends = np.searchsorted(ids_sorted, np.arange(n), side="right")
    for i, cue in cues.items():
        if cue.status != "seen" or tot[i] < p.min_pixels // 2:
            continue
        f = s_chg[i] / tot[i]
        cue.exclusive_px = int(round(tot[i]))
        cue.changed_fraction = float(f)
        weight = min(1.0, tot[i] / p.change_full_pixels) * informative[i]
        llr = float(np.clip(p.change_slope * (f - p.change_neutral), -p.max_llr, p.max_llr) * weight)
        if llr > 0 and p.change_ring_px > 0:
            mine = order[starts[i] : ends[i]]
            ring = _ring_changed(owner, changed, valid, i, sel_ys[mine], sel_xs[mine], p.change_ring_px, p.min_pixels)
            llr *= (1.0 - ring) ** p.change_ring_power
        cue.llr_change = llr
        cue.reference_ns = int(np.median(times_sorted[starts[i] : ends[i]]))


def _ring_changed(
    owner: NDArray[np.int64],
    changed: BoolA,
    valid: BoolA,
    i: int,
    ys: NDArray[np.intp],
    xs: NDArray[np.intp],
    radius_px: int,
    min_pixels: int,
) -> float:
    """Changed fraction of the valid pixels within ``radius_px`` around element ``i``'s region (``owner`` == i,
    found around its pixels ``ys``, ``xs``); 0 with fewer than ``min_pixels`` such pixels."""
    h, w = owner.shape
    y0, y1 = max(int(ys.min()) - 2 * radius_px, 0), min(int(ys.max()) + 2 * radius_px + 1, h)
    x0, x1 = max(int(xs.min()) - 2 * radius_px, 0), min(int(xs.max()) + 2 * radius_px + 1, w)
    region = owner[y0:y1, x0:x1] == i
    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    ring = (cv2.dilate(region.astype(np.uint8), kernel) > 0) & ~region & valid[y0:y1, x0:x1]
    n = int(ring.sum())
    return float(changed[y0:y1, x0:x1][ring].mean()) if n >= min_pixels else 0.0


def _points_cue(
    layers: Layers,
    points: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    p: EvidenceParams,
    cues: dict[int, ElementCue],
    n: int,
) -> None:
    px, z, w = points
    h, wd = layers.ids_front.shape
    u = np.rint(px[:, 0]).astype(np.int64)
    v = np.rint(px[:, 1]).astype(np.int64)
    ok = (u >= 0) & (u < wd) & (v >= 0) & (v < h) & np.isfinite(z) & (z > 0)
    u, v, z, w = u[ok], v[ok], z[ok], w[ok]
    margin = p.point_margin_m + p.point_margin_rel * z
    on = np.zeros(n)
    behind = np.zeros(n)
    for ids, depth in ((layers.ids_front, layers.depth_front_m), (layers.ids_built, layers.depth_built_m)):
        e = ids[v, u].astype(np.int64)
        d = depth[v, u].astype(np.float64)
        has = e > 0
        on += np.bincount(e[has & (np.abs(z - d) <= margin)], weights=w[has & (np.abs(z - d) <= margin)], minlength=n)[
            :n
        ]
        bh = has & (z > d + margin)
        behind += np.bincount(e[bh], weights=w[bh], minlength=n)[:n]
    for i, cue in cues.items():
        if on[i] == 0 and behind[i] == 0:
            continue
        cue.points_on, cue.points_behind = float(on[i]), float(behind[i])
        cue.llr_points = float(np.clip(p.point_llr * (on[i] - behind[i]), -p.max_llr, p.max_llr))


def _appearance_cue(
    bins: NDArray[np.int32],
    free: BoolA,
    layers: Layers,
    material_of: list[str],
    p: EvidenceParams,
    cues: dict[int, ElementCue],
    materials: MaterialModel | None,
    present: NDArray[np.float64] | None,
) -> None:
    """Colours of each element's front-most pixels: the element's material (as this photo shows it on the other
    elements of that material, weighted by how likely each stands, plus what confident detections taught) against
    what would show if it were absent (half the believed-built surface behind it or the background around it,
    half anything else this photo shows). ``present`` weights each element's pixels in its material's look (the
    confirmed elements). Without a known look of its material an element gets no appearance evidence. ``bins``:
    :func:`colour_bins` of the photo."""
    front = layers.ids_front.astype(np.int64)
    built = layers.ids_built.astype(np.int64)
    ids_all = np.where(front > 0, front, built)
    n = len(material_of)
    mats = sorted(set(material_of[1:]))
    mat_index = {m: k for k, m in enumerate(mats)}
    mat_of_id = np.array([-1] + [mat_index[m] for m in material_of[1:]], np.int64)
    weight = np.ones(n) if present is None else np.clip(np.asarray(present, np.float64), 0.0, 1.0)
    shown = free & (ids_all > 0)
    flat_ids, flat_bins = ids_all[shown], bins[shown]
    per_el = np.zeros((n, NUM_BINS))
    np.add.at(per_el, (flat_ids, flat_bins), 1.0)
    local = np.zeros((len(mats), NUM_BINS))
    np.add.at(local, mat_of_id[1:], per_el[1:] * weight[1:, None])
    background_ok = free & (ids_all == 0)
    background = np.bincount(bins[background_ok], minlength=NUM_BINS).astype(np.float64)
    h, w = ids_all.shape
    r = p.appearance_ring_px
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    # every shown pixel grouped by element once (not one full-image scan per element)
    all_ys, all_xs = np.nonzero(shown)
    order = np.argsort(ids_all[all_ys, all_xs], kind="stable")
    all_ys, all_xs = all_ys[order], all_xs[order]
    sorted_ids = ids_all[all_ys, all_xs]
    first = np.searchsorted(sorted_ids, np.arange(n))
    last = np.searchsorted(sorted_ids, np.arange(n), side="right")
    others_all = local.sum(axis=0)
    for i, cue in cues.items():
        if cue.status != "seen":
            continue
        m = mat_of_id[i]
        counts = local[m] - weight[i] * per_el[i]  # leave the element itself out of its material's look
        if materials is not None:
            counts = counts + 0.2 * materials.counts.get(mats[m], np.zeros(NUM_BINS))
        novelty = counts.sum() < p.appearance_min_reference_px
        if novelty and p.appearance_novelty_weight <= 0.0:
            continue
        ys, xs = all_ys[first[i] : last[i]], all_xs[first[i] : last[i]]
        if len(ys) < p.min_pixels:
            continue
        y0, y1, x0, x1 = max(ys.min() - r, 0), min(ys.max() + r + 1, h), max(xs.min() - r, 0), min(xs.max() + r + 1, w)
        sub = np.zeros((y1 - y0, x1 - x0), bool)
        sub[ys - y0, xs - x0] = True
        ring = (cv2.dilate(sub.astype(np.uint8), kernel) > 0) & ~sub & background_ok[y0:y1, x0:x1]
        near = np.bincount(bins[y0:y1, x0:x1][ring], minlength=NUM_BINS).astype(np.float64)
        bg = normalised_hist(near + 0.25 * background * (near.sum() / max(background.sum(), 1.0)) + 1.0, 20.0)
        b = bins[ys, xs]
        others = normalised_hist(others_all - local[m] + background, 20.0)
        absent = 0.5 * bg[b] + 0.5 * others[b]
        same = np.zeros(len(ys), bool)
        if front[ys[0], xs[0]] == i:  # a candidate: what is believed built behind it shows when it is absent
            behind = mat_of_id[built[ys, xs]]
            for k in np.unique(behind[(behind >= 0) & (behind != m)]):
                use = behind == k
                if local[k].sum() >= p.appearance_min_reference_px:
                    absent[use] = 0.5 * normalised_hist(local[k], 20.0)[b[use]] + 0.5 * others[b[use]]
            if p.appearance_same_behind:
                same = behind == m
        if novelty:  # no look of its material yet: anything unlike what would show where it is absent
            ratio = np.clip(np.log(1.0 / NUM_BINS) - np.log(absent), -4.0, 4.0)
            alpha = p.appearance_novelty_weight
        else:
            ratio = np.clip(np.log(normalised_hist(counts, 20.0)[b]) - np.log(absent), -4.0, 4.0)
            alpha = counts.sum() / (counts.sum() + p.appearance_min_reference_px)
        ratio = np.where(same, 0.0, ratio)
        llr = float(np.clip(alpha * p.appearance_scale * ratio.mean(), -p.appearance_max_llr, p.appearance_max_llr))
        if llr < 0.0:
            llr *= p.appearance_negative_scale
        if p.appearance_full_pixels > 0:
            llr *= min(1.0, len(ys) / p.appearance_full_pixels)
        cue.llr_appearance = llr


def _edge_cue(img: F32, free: BoolA, layers: Layers, p: EvidenceParams, cues: dict[int, ElementCue]) -> None:
    """Silhouette evidence of candidates: along the stretches of a candidate's outline where, were it absent, the
    same thing would show on both sides (what stands behind it inside = what shows outside), an edge across the
    outline (a colour difference above ``edge_min_contrast`` and ``edge_control_ratio`` times the difference
    between two outside pixels the same distance apart) says it stands; its fraction of the outline samples gives
    ``edge_slope * (fraction - edge_neutral)``, clipped, scaled down below ``edge_full_samples``. ``img``: the
    photo's Lab blurred by sigma 0.8 px (:meth:`PhotoCache.edge_blur`)."""
    front = layers.ids_front.astype(np.int64)
    built = layers.ids_built.astype(np.int64)
    second = layers.ids_second.astype(np.int64)
    owner = np.where(front > 0, front, built)
    alt = np.where(second > 0, second, built)  # what shows where the front candidate is absent
    h, w = owner.shape
    g, c = p.edge_gap_px, p.edge_control_px
    ids_l, hit_l = [], []
    ys0, xs0 = np.nonzero(front > 0)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        far = g + c
        ok = (ys0 - (g - 1) * dy >= 0) & (ys0 - (g - 1) * dy < h) & (xs0 - (g - 1) * dx >= 0) & (xs0 - (g - 1) * dx < w)
        ok &= (ys0 + far * dy >= 0) & (ys0 + far * dy < h) & (xs0 + far * dx >= 0) & (xs0 + far * dx < w)
        ys, xs = ys0[ok], xs0[ok]
        i = owner[ys, xs]
        o = owner[ys + dy, xs + dx]
        sel = o != i
        ys, xs, i, o = ys[sel], xs[sel], i[sel], o[sel]
        ya, xa = ys - (g - 1) * dy, xs - (g - 1) * dx
        yb, xb = ys + g * dy, xs + g * dx
        yc, xc = ys + far * dy, xs + far * dx
        sel = (
            (owner[ya, xa] == i)
            & (owner[yb, xb] == o)
            & (owner[yc, xc] == o)
            & (alt[ys, xs] == o)
            & free[ya, xa]
            & free[yb, xb]
            & free[yc, xc]
        )
        i = i[sel]
        va, vb, vc = img[ya[sel], xa[sel]], img[yb[sel], xb[sel]], img[yc[sel], xc[sel]]
        across = np.linalg.norm(va - vb, axis=1)
        control = np.linalg.norm(vb - vc, axis=1)
        ids_l.append(i)
        hit_l.append((across >= p.edge_min_contrast) & (across >= p.edge_control_ratio * control))
    if not ids_l:
        return
    ids = np.concatenate(ids_l)
    hits = np.concatenate(hit_l).astype(np.float64)
    n = max(max(cues, default=0), int(ids.max(initial=0))) + 1
    cnt = np.bincount(ids, minlength=n)
    hit = np.bincount(ids, weights=hits, minlength=n)
    for k, cue in cues.items():
        if cue.status != "seen" or cnt[k] < p.min_pixels // 2:
            continue
        f = hit[k] / cnt[k]
        cue.edge_samples = int(cnt[k])
        cue.edge_fraction = float(f)
        weight = min(1.0, cnt[k] / p.edge_full_samples)
        llr = float(np.clip(p.edge_slope * (f - p.edge_neutral), -p.edge_max_llr, p.edge_max_llr) * weight)
        cue.llr_edge = llr * p.edge_negative_scale if llr < 0.0 else llr
