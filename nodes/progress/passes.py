"""Reading a photo in passes: candidates the belief finds unlikely are read after the likelier ones.

Pure helpers of :meth:`nodes.progress.engine.ProgressEngine.process`: which elements a later pass drew in front of
what an earlier pass read, and which of the two readings of each element stands.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import NDArray

from nodes.progress.evidence import ElementCue
from nodes.progress.modelview import Layers


def covering(first_ids: NDArray[np.integer], later_ids: NDArray[np.integer]) -> dict[int, set[int]]:
    """For two (H, W) element-id layers of one photo (0: none), the elements that the later layer shows over each
    element of the first: ``{first id: {later ids}}`` where they differ (pixels the later layer leaves empty do
    not count)."""
    a, b = np.asarray(first_ids, np.int64).ravel(), np.asarray(later_ids, np.int64).ravel()
    m = (a > 0) & (a != b) & (b > 0)
    out: dict[int, set[int]] = {}
    if not m.any():
        return out
    pairs = np.unique(np.stack([a[m], b[m]]), axis=1)
    for i, j in pairs.T:
        out.setdefault(int(i), set()).add(int(j))
    return out


def settle_deferred(
    first: Iterable[ElementCue],
    later: Iterable[ElementCue],
    deferred: set[int],
    cover: dict[int, set[int]],
    stands: Callable[[int], bool],
) -> list[ElementCue]:
    """The cues that stand after a deferred pass, for every element but the deferred ones.

    ``first``: the cues read without the deferred candidates; ``later``: with them drawn (in front where they are
    nearer); ``cover``: :func:`covering` of the two passes' layers; ``stands(i)``: whether deferred element ``i``
    most probably stands, with this photo's evidence. An element keeps its first reading unless a deferred
    element that stands covers it (then its pixels showed that one: the later reading counts)."""
    by_later = {c.index: c for c in later if c.index not in deferred}
    out: list[ElementCue] = []
    for c in first:
        if c.index in deferred:
            continue
        covered = any(j in deferred and stands(j) for j in cover.get(c.index, ()))
        if not covered:
            out.append(c)
        elif c.index in by_later:
            out.append(by_later.pop(c.index))
        by_later.pop(c.index, None)
    return out + list(by_later.values())


def behind_candidates(layers: Layers, occluded: NDArray[np.bool_]) -> dict[tuple[int, int], tuple[int, int]]:
    """(candidate index, believed-built element index behind it) -> (pixels, unoccluded pixels) where a candidate
    hid a believed-built element in ``layers`` (the last evidence pass); ``occluded``: (H, W) mask."""
    front = layers.ids_front.astype(np.int64)
    built = layers.ids_built.astype(np.int64)
    sel = (front > 0) & (built > 0)
    if not sel.any():
        return {}
    key = front[sel] * (int(built.max()) + 1) + built[sel]
    keys, counts = np.unique(key, return_counts=True)
    free = np.unique(key[~occluded[sel]], return_counts=True)
    vis = dict(zip(free[0].tolist(), free[1].tolist(), strict=True))
    m = int(built.max()) + 1
    return {(k // m, k % m): (int(c), int(vis.get(k, 0))) for k, c in zip(keys.tolist(), counts.tolist(), strict=True)}
