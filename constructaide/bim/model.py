"""The in-memory site model: elements, meshes, geo-reference, schedule, grouping and 4D queries.

Pure data (numpy + schemas); built by :mod:`constructaide.bim.ifc`, turned into bus messages by
:mod:`nodes.ingest.revisions`. Frames: vertices in site-local metres, z up, i.e. the IFC world
frame minus ``origin_offset_m``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import numpy.typing as npt

from constructaide.schedule4d import (
    ElementWindow,
    State,
    Status,
    actual_state,
    element_windows,
    planned_state,
    schedule_status,
)
from schemas.messages import BimElement, GeoPoint, ScheduleTask


@dataclass(frozen=True, slots=True)
class ElementMesh:
    """Triangle mesh of one element: ``vertices_m`` (N, 3) float64 site-local metres, ``faces`` (M, 3) int32,
    ``rgba`` the main IFC surface style colour (0-255) when the model has one."""

    vertices_m: npt.NDArray[np.float64]
    faces: npt.NDArray[np.int32]
    rgba: tuple[int, int, int, int] | None = None

    def geometry_hash(self) -> str:
        """sha256 (hex, 16 chars) of the vertices rounded to 0.1 mm and the faces."""
        h = hashlib.sha256()
        h.update(np.round(self.vertices_m * 1e4).astype(np.int64).tobytes())
        h.update(self.faces.astype(np.int32).tobytes())
        return h.hexdigest()[:16]


@dataclass(frozen=True, slots=True)
class MapConversion:
    """IfcMapConversion (IFC4+) with its target IfcProjectedCRS: model -> map coordinates.

    ``eastings``/``northings``/``orthogonal_height`` are in map units; the x axis of the model
    maps to the direction ``x_axis`` = (XAxisAbscissa, XAxisOrdinate) in the map.
    """

    eastings: float
    northings: float
    orthogonal_height: float
    x_axis: tuple[float, float] = (1.0, 0.0)
    scale: float = 1.0
    crs_name: str = ""
    crs_description: str = ""


def _grouped(attr: str, doc: str) -> cached_property[dict[str, tuple[str, ...]]]:
    """A cached property of :class:`SiteModel`: its elements' GlobalIds grouped by the element attribute ``attr``."""

    def group(self: SiteModel) -> dict[str, tuple[str, ...]]:
        return self._group(attr)

    group.__doc__ = doc
    return cached_property(group)


@dataclass(frozen=True)
class SiteModel:
    """One site: elements from one or several IFC files plus the schedule.

    ``elements`` and ``meshes`` are keyed by GlobalId (``meshes`` keys are the elements'
    ``geometry_ref``, which is the GlobalId). ``origin_offset_m`` was subtracted from the IFC
    world coordinates. ``warnings`` lists non-fatal findings (duplicate GlobalIds across files...).
    """

    elements: dict[str, BimElement]
    meshes: dict[str, ElementMesh]
    origin_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    map_conversion: MapConversion | None = None
    gps: GeoPoint | None = None
    tasks: tuple[ScheduleTask, ...] = ()
    source_files: tuple[str, ...] = ()
    schemas: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    tz: str = "UTC"

    # -- grouping ---------------------------------------------------------------------------

    def _group(self, attr: str) -> dict[str, tuple[str, ...]]:
        out: dict[str, list[str]] = {}
        for gid, el in self.elements.items():
            out.setdefault(getattr(el, attr), []).append(gid)
        return {k: tuple(v) for k, v in sorted(out.items())}

    by_class = _grouped("ifc_class", "GlobalIds per IFC class.")
    by_type = _grouped("type_name", 'GlobalIds per type object name ("" = untyped).')
    by_material = _grouped("material", 'GlobalIds per material name ("" = none).')
    by_storey = _grouped("storey", 'GlobalIds per storey name ("" = not in a storey).')

    def bbox_m(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(min (3,), max (3,)) over all elements, site-local metres."""
        lo = np.array([el.bbox_min_m for el in self.elements.values()], dtype=np.float64)
        hi = np.array([el.bbox_max_m for el in self.elements.values()], dtype=np.float64)
        return lo.min(axis=0), hi.max(axis=0)

    # -- schedule ---------------------------------------------------------------------------

    @cached_property
    def windows(self) -> dict[str, ElementWindow]:
        """Planned/actual build windows per GlobalId."""
        return element_windows(self.tasks)

    def with_tasks(self, tasks: tuple[ScheduleTask, ...]) -> SiteModel:
        """A copy with ``tasks`` appended to the schedule (cached indices dropped)."""
        return replace(self, tasks=self.tasks + tuple(tasks))

    def planned_state(self, global_id: str, at_ns: int) -> State:
        """Planned state of one element at ``at_ns`` (ns UTC)."""
        self._check(global_id)
        return planned_state(self.windows.get(global_id), at_ns)

    def actual_state(self, global_id: str, at_ns: int) -> State | None:
        """Actual state from actual dates, ``None`` when the element has none."""
        self._check(global_id)
        return actual_state(self.windows.get(global_id), at_ns)

    def schedule_status(self, global_id: str, at_ns: int) -> Status:
        """``early`` / ``on_time`` / ``late`` (actual vs planned progress at ``at_ns``) or ``unknown``."""
        self._check(global_id)
        return schedule_status(self.windows.get(global_id), at_ns)

    def planned_states(self, at_ns: int) -> dict[str, State]:
        """Planned state of every element at ``at_ns``."""
        windows = self.windows
        return {gid: planned_state(windows.get(gid), at_ns) for gid in self.elements}

    def _check(self, global_id: str) -> None:
        if global_id not in self.elements:
            raise KeyError(f"no element with GlobalId {global_id!r} in the site model")
