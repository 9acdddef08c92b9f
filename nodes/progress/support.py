"""What rests on what: a precedence graph from the BIM's geometry and schedule (pure core: numpy).

An element cannot stand before the elements that carry it (a beam before its columns, a column before the slab
under it), and once something stands on an element that element stands. :func:`support_graph` reads "S carries B"
off the elements' axis-aligned bounding boxes (z up, metres), kept only where the schedule agrees (S planned to
finish by B's planned start), so a box contact the plan does not order (two walls side by side, elements of one
task) is no edge. The fusion uses it as a soft constraint (:func:`nodes.progress.fusion.coupled`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from constructaide.schedule4d import ElementWindow

Box = tuple[NDArray[np.float64], NDArray[np.float64]]
"""(min (3,), max (3,)) corners in the model frame, metres, z up."""


def mesh_boxes(meshes: Mapping[str, tuple[NDArray[np.float64], NDArray[Any]]]) -> dict[str, Box]:
    """Bounding box of each element's vertices (N, 3); elements without vertices are left out."""
    return {g: (v.min(axis=0), v.max(axis=0)) for g, (v, _f) in meshes.items() if len(v)}


def support_graph(
    boxes: dict[str, Box], windows: dict[str, ElementWindow], contact_m: float = 0.05
) -> dict[str, tuple[str, ...]]:
    """``{B: (S, ...)}``: the elements S that carry B. S carries B when their boxes, grown by ``contact_m``, meet,
    S reaches lower than B (its bottom more than ``contact_m`` below B's: it bears B from below or holds it at its
    side), and both are constructed (planned finish, nothing removed) with S planned to finish by B's planned start.
    """
    gids = [
        g
        for g in boxes
        if (w := windows.get(g)) is not None
        and w.build_finish_ns is not None
        and w.remove_start_ns is None
        and w.remove_finish_ns is None
    ]
    if not gids:
        return {}
    lo = np.array([boxes[g][0] for g in gids], np.float64)  # (n, 3)
    hi = np.array([boxes[g][1] for g in gids], np.float64)
    finish = np.array([float(windows[g].build_finish_ns) for g in gids])  # type: ignore[arg-type]
    start = np.array([float(earliest_start(windows[g])) for g in gids])
    out: dict[str, tuple[str, ...]] = {}
    for a in range(0, len(gids), 512):  # rows b in chunks: (512, n) at a time, not (n, n)
        b = slice(a, a + 512)
        meet = np.all(
            (lo[b, None, :] - contact_m <= hi[None, :, :]) & (lo[None, :, :] - contact_m <= hi[b, None, :]), 2
        )
        lower = lo[None, :, 2] < lo[b, None, 2] - contact_m  # [b, s]: s reaches lower than b
        planned = finish[None, :] <= start[b, None]  # [b, s]: s planned to finish by b's start
        carry = meet & lower & planned
        for k, row in enumerate(carry, start=a):
            row[k] = False
            if row.any():
                out[gids[k]] = tuple(gids[s] for s in np.flatnonzero(row))
    return out


def earliest_start(w: ElementWindow) -> int:
    """Planned start of a window with a planned finish (the finish when no start is given)."""
    assert w.build_finish_ns is not None
    return w.build_finish_ns if w.build_start_ns is None else min(w.build_start_ns, w.build_finish_ns)


def dependants_of(supports: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """The inverse graph: ``{S: (B, ...)}``, the elements each one carries."""
    out: dict[str, list[str]] = {}
    for b, ss in supports.items():
        for s in ss:
            out.setdefault(s, []).append(b)
    return {s: tuple(bs) for s, bs in out.items()}
