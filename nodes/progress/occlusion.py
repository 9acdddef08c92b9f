"""Which occlusion-mask pixels hide the model's elements from the progress cues of a photo."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from constructaide.imagecodec import mask_of_message
from nodes.progress.evidence import NUM_BINS, normalised_hist
from nodes.progress.modelview import Layers
from schemas.messages import OcclusionMask

BoolA = NDArray[np.bool_]


def union_of(masks: dict[str, OcclusionMask], kinds: tuple[str, ...], shape: tuple[int, int]) -> BoolA:
    """(H, W) bool: the union of a photo's masks of these kinds (``masks`` by kind) at ``shape``."""
    out = np.zeros(shape, bool)
    for kind in kinds:
        m = mask_of_message(masks.get(kind), shape)
        if m is not None:
            out |= m
    return out


def hiding_mask(
    occluded: BoolA,
    not_dynamic: BoolA,
    ids_front: NDArray[np.integer],
    ids_all: NDArray[np.integer],
    seen_appearing: NDArray[np.bool_],
    looks_like: BoolA | None = None,
) -> BoolA:
    """(H, W) bool: the pixels that hide an element from a fixed camera's cues.

    ``occluded``: the photo's combined mask; ``not_dynamic``: its static and user masks; ``ids_front``: the
    candidate layer (elements that may be appearing, 0 elsewhere); ``ids_all``: the front-most element of the built
    and candidate layers; ``seen_appearing`` (n + 1,): elements some photo has seen appearing (and standing since).
    A time-lapse (dynamic) mask is what changed between a camera's frames, and construction is such a change: it
    does not hide a candidate, nor an element believed built that no photo has seen appear (a belief the schedule
    gave). It hides the elements seen appearing (a change over them is something in front), and static and user
    masks hide everything. With ``looks_like`` (:func:`material_like`) only the pixels that look like the element's
    material are read through (a truck in front of an element does not)."""
    see = (ids_front > 0) | ~seen_appearing[ids_all.astype(np.int64)]
    see &= ids_all > 0
    if looks_like is not None:
        see &= looks_like
    return occluded & ~(see & ~not_dynamic)


def material_like(
    bins: NDArray[np.int32],
    ids_all: NDArray[np.integer],
    material_of: list[str],
    looks: dict[str, NDArray[np.float64]],
    background: NDArray[np.bool_],
    min_px: float = 150.0,
) -> BoolA:
    """(H, W) bool: pixels whose colour bin (``bins``, :func:`~nodes.progress.evidence.colour_bins`) is likelier
    under the learnt look of the material of the element they show (``ids_all``, ``material_of[i]``; ``looks``:
    colour counts per material) than under the other materials' looks and this photo's ``background`` pixels
    (no element) together, at least twice as likely. False where the element's material has fewer than ``min_px``
    learnt pixels."""
    out = np.zeros(bins.shape, bool)
    known = {m: h for m, h in looks.items() if h.sum() >= min_px}
    if not known:
        return out
    bg = np.bincount(bins[background].ravel(), minlength=NUM_BINS).astype(np.float64)
    total = sum(known.values(), np.zeros(NUM_BINS)) + bg
    code = {m: k for k, m in enumerate(known)}
    mat_of_id = np.array([code.get(m, -1) for m in material_of], np.int64)
    mat_of_id[0] = -1
    px_mat = mat_of_id[ids_all.astype(np.int64)]
    for m, h in known.items():
        here = px_mat == code[m]
        if not here.any():
            continue
        # pseudo-counts in proportion to each side's mass: a colour neither has seen is not likelier under either;
        # read through where the material's look makes the colour at least twice as likely
        rest = total - h
        ratio = np.log(normalised_hist(h, 0.2 * h.sum())) - np.log(normalised_hist(rest, 0.2 * max(rest.sum(), 1.0)))
        out[here] = ratio[bins[here]] > np.log(2.0)
    return out


def fixed_camera_hiding(
    bins: NDArray[np.int32] | None,
    occluded: BoolA,
    static: BoolA,
    layers: Layers,
    seen_appearing: NDArray[np.bool_],
    material_of: list[str],
    looks: dict[str, NDArray[np.float64]] | None,
) -> BoolA:
    """:func:`hiding_mask` of a fixed camera's photo (``bins`` (H, W): :func:`~nodes.progress.evidence.colour_bins`
    of the photo at working size, ``layers`` its render); with ``looks`` (learnt colour counts per material) only the
    pixels that look like their element's material (:func:`material_like`) are read through the dynamic mask."""
    like = None
    if looks is not None and bins is not None:
        shown_bg = ~occluded & (layers.ids_all == 0)
        like = material_like(bins, layers.ids_all, material_of, looks, shown_bg)
    return hiding_mask(occluded, static, layers.ids_front, layers.ids_all, seen_appearing, like)
