"""Element selection of a :class:`constructaide.modelscene.BimScene` by an ``ElementFilter`` (render policy)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from constructaide.modelscene import BimScene
from schemas.messages import ElementFilter


def filter_mask(scene: BimScene, flt: ElementFilter, task_elements: dict[str, tuple[str, ...]]) -> NDArray[np.bool_]:
    """(num_elements + 1,) bool: elements selected by ``flt`` (row 0, background, is False).

    ``task_elements`` maps task_id -> element GlobalIds (for ``flt.task_ids``). Empty filter
    fields do not restrict.
    """
    sel = np.ones(scene.num_elements + 1, bool)
    sel[0] = False
    els = scene.elements
    if flt.ifc_classes:
        want = {c.lower() for c in flt.ifc_classes}
        sel[1:] &= np.array([e.ifc_class.lower() in want for e in els], bool)
    if flt.storeys:
        want = set(flt.storeys)
        sel[1:] &= np.array([e.storey in want for e in els], bool)
    if flt.materials:
        want = {m.lower() for m in flt.materials}
        sel[1:] &= np.array([e.material.lower() in want for e in els], bool)
    if flt.task_ids:
        unknown = [t for t in flt.task_ids if t not in task_elements]
        if unknown:
            raise ValueError(f"filter names unknown task ids: {unknown[:5]}")
        ids = {g for t in flt.task_ids for g in task_elements[t]}
        sel[1:] &= np.array([e.global_id in ids for e in els], bool)
    if flt.element_ids:
        ids = set(flt.element_ids)
        sel[1:] &= np.array([e.global_id in ids for e in els], bool)
    return sel
