"""Which occlusion-mask pixels hide the model's elements from the progress cues of a photo."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from constructaide.imagecodec import mask_of_message
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
) -> BoolA:
    """(H, W) bool: the pixels that hide an element from a fixed camera's cues.

    ``occluded``: the photo's combined mask; ``not_dynamic``: its static and user masks; ``ids_front``: the
    candidate layer (elements that may be appearing, 0 elsewhere); ``ids_all``: the front-most element of the built
    and candidate layers; ``seen_appearing`` (n + 1,): elements some photo has seen appearing (and standing since).
    A time-lapse (dynamic) mask is what changed between a camera's frames, and construction is such a change: it
    does not hide a candidate, nor an element believed built that no photo has seen appear (a belief the schedule
    gave). It hides the elements seen appearing (a change over them is something in front), and static and user
    masks hide everything."""
    see = (ids_front > 0) | ~seen_appearing[ids_all.astype(np.int64)]
    see &= ids_all > 0
    return occluded & ~(see & ~not_dynamic)
