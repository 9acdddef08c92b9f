"""Procedural building design: elements as closed polyhedra in the world frame (x east, y north, z up, m).

Geometry is made of axis-aligned boxes (and one gable prism for the roof). Adjacent elements touch only with
opposite-facing faces, never with coplanar same-facing faces, so ID renders have no z-fighting.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .config import BASEMENT_DEPTH_M, BAY_M, GROUND_FLOOR_TOP_M, STOREY_HEIGHT_M, SizeConfig

F64 = NDArray[np.float64]

COLUMN_M = 0.4
BEAM_W_M = 0.3
BEAM_D_M = 0.5
SLAB_T_M = 0.3
SLAB_OVERHANG_M = 0.3  # slab edge beyond the grid line
WALL_T_M = 0.25
ROOF_RISE_M = 2.2

# Box faces as quads (outward winding, counter-clockwise seen from outside) over corners indexed by
# bit pattern (x, y, z) -> x + 2 y + 4 z.
_BOX_QUADS = [
    [0, 2, 3, 1],  # z-
    [4, 5, 7, 6],  # z+
    [0, 1, 5, 4],  # y-
    [2, 6, 7, 3],  # y+
    [0, 4, 6, 2],  # x-
    [1, 3, 7, 5],  # x+
]


@dataclass
class Element:
    """One BIM element. ``vertices_m`` (N, 3) world metres; ``polygons`` index lists (outward CCW)."""

    key: str  # stable human-readable id, e.g. "L1-COL-B2"
    ifc_class: str
    predefined_type: str
    type_name: str  # element type (IfcXxxType name)
    storey: int  # -1 = basement, 0 = ground floor, ...
    material: str  # key into MATERIALS
    task: str  # key of the construction task that builds it
    vertices_m: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    polygons: list[list[int]] = field(default_factory=list)

    def add_box(self, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> None:
        """Append an axis-aligned box with corners ``lo`` < ``hi`` (m)."""
        lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
        if np.any(hi_a <= lo_a):
            raise ValueError(f"degenerate box {lo} {hi} in {self.key}")
        corners = np.array([[(hi_a if (i >> a) & 1 else lo_a)[a] for a in range(3)] for i in range(8)])
        base = len(self.vertices_m)
        self.vertices_m = np.vstack([self.vertices_m, corners])
        self.polygons.extend([[base + i for i in q] for q in _BOX_QUADS])

    def triangles(self) -> NDArray[np.int64]:
        """(M, 3) triangle fan of every polygon."""
        tris = [[p[0], p[i], p[i + 1]] for p in self.polygons for i in range(1, len(p) - 1)]
        return np.asarray(tris, dtype=np.int64)

    @property
    def bounds_m(self) -> F64:
        """(2, 3) min and max corner."""
        return np.stack([self.vertices_m.min(0), self.vertices_m.max(0)])


@dataclass(frozen=True)
class Storey:
    index: int
    name: str
    elevation_m: float  # top of the floor slab


@dataclass
class Building:
    elements: list[Element]
    storeys: list[Storey]
    half_extent_m: tuple[float, float]  # grid half-size along x and y
    top_m: float  # highest point (roof ridge)


def _grid(n_bays: int) -> list[float]:
    half = n_bays * BAY_M / 2
    return [-half + i * BAY_M for i in range(n_bays + 1)]


def _label(ix: int, iy: int) -> str:
    return f"{chr(ord('A') + ix)}{iy + 1}"


def _boxed(key: str, kind: tuple[str, str, str, int, str, str], lo: tuple, hi: tuple) -> Element:
    """An element ``key`` of ``kind`` = (ifc_class, predefined_type, type_name, storey, material, task): a box from
    corner ``lo`` to ``hi`` (metres)."""
    e = Element(key, *kind)
    e.add_box(lo, hi)
    return e


def design_building(size: SizeConfig) -> Building:
    """The building for a size: basement, ``size.storeys`` storeys, gable roof."""
    xs, ys = _grid(size.bays_x), _grid(size.bays_y)
    hx, hy = xs[-1], ys[-1]
    n = size.storeys
    elevations = [GROUND_FLOOR_TOP_M + i * STOREY_HEIGHT_M for i in range(n + 1)]  # level n = roof slab top
    storeys = [Storey(-1, "Basement", -BASEMENT_DEPTH_M)] + [
        Storey(i, "Ground floor" if i == 0 else f"Level {i}", elevations[i]) for i in range(n)
    ]
    els: list[Element] = []
    c = COLUMN_M / 2
    so = SLAB_OVERHANG_M

    # Foundations and basement.
    z_b = -BASEMENT_DEPTH_M
    footing = ("IfcFooting", "PAD_FOOTING", "Pad footing 1400x1400", -1, "concrete", "foundations")
    for iy, y in enumerate(ys):
        for ix, x in enumerate(xs):
            lo, hi = (x - 0.7, y - 0.7, z_b - SLAB_T_M - 0.6), (x + 0.7, y + 0.7, z_b - SLAB_T_M)
            els.append(_boxed(f"B-FTG-{_label(ix, iy)}", footing, lo, hi))
    e = Element("B-SLAB", "IfcSlab", "BASESLAB", "Base slab 300", -1, "concrete", "basement_slab")
    e.add_box((-hx - so, -hy - so, z_b - SLAB_T_M), (hx + so, hy + so, z_b))
    els.append(e)
    for side, (lo, hi) in {
        "S": ((-hx - 0.2, -hy - 0.2, z_b), (hx + 0.2, -hy + 0.1, -SLAB_T_M + GROUND_FLOOR_TOP_M)),
        "N": ((-hx - 0.2, hy - 0.1, z_b), (hx + 0.2, hy + 0.2, -SLAB_T_M + GROUND_FLOOR_TOP_M)),
        "W": ((-hx - 0.2, -hy + 0.1, z_b), (-hx + 0.1, hy - 0.1, -SLAB_T_M + GROUND_FLOOR_TOP_M)),
        "E": ((hx - 0.1, -hy + 0.1, z_b), (hx + 0.2, hy - 0.1, -SLAB_T_M + GROUND_FLOOR_TOP_M)),
    }.items():
        e = Element(f"B-WALL-{side}", "IfcWall", "SOLIDWALL", "Retaining wall 300", -1, "concrete", "basement_walls")
        e.add_box(lo, hi)
        els.append(e)
    e = Element("L0-SLAB", "IfcSlab", "FLOOR", "Floor slab 300", 0, "concrete", "slab_0")
    e.add_box((-hx - so, -hy - so, GROUND_FLOOR_TOP_M - SLAB_T_M), (hx + so, hy + so, GROUND_FLOOR_TOP_M))
    els.append(e)

    for s in range(n):
        z0, z1 = elevations[s], elevations[s + 1]
        z_beam_top = z1 - SLAB_T_M
        z_beam_bot = z_beam_top - BEAM_D_M
        steel = s == n - 1 and n > 1  # top-storey frame in steel
        frame_mat = "steel" if steel else "concrete"
        column = ("IfcColumn", "COLUMN", "Steel column HEB 400" if steel else "Column 400x400", s, frame_mat)
        beam = ("IfcBeam", "BEAM", "Steel beam IPE 500" if steel else "Beam 300x500", s, frame_mat, f"beams_{s}")
        for iy, y in enumerate(ys):
            for ix, x in enumerate(xs):
                lo, hi = (x - c, y - c, z0), (x + c, y + c, z_beam_top)
                els.append(_boxed(f"L{s}-COL-{_label(ix, iy)}", (*column, f"columns_{s}"), lo, hi))
        bw = BEAM_W_M / 2
        for iy, y in enumerate(ys):
            for ix in range(len(xs) - 1):
                lo, hi = (xs[ix] + c, y - bw, z_beam_bot), (xs[ix + 1] - c, y + bw, z_beam_top)
                els.append(_boxed(f"L{s}-BM-{_label(ix, iy)}x", beam, lo, hi))
        for ix, x in enumerate(xs):
            for iy in range(len(ys) - 1):
                lo, hi = (x - bw, ys[iy] + c, z_beam_bot), (x + bw, ys[iy + 1] - c, z_beam_top)
                els.append(_boxed(f"L{s}-BM-{_label(ix, iy)}y", beam, lo, hi))
        # Slab above this storey (the roof slab for the top storey).
        top = s == n - 1
        e = Element(
            f"L{s + 1}-SLAB" if not top else "RF-SLAB",
            "IfcSlab",
            "ROOF" if top else "FLOOR",
            "Roof slab 300" if top else "Floor slab 300",
            s,
            "concrete",
            f"slab_{s + 1}",
        )
        e.add_box((-hx - so, -hy - so, z1 - SLAB_T_M), (hx + so, hy + so, z1))
        els.append(e)
        # Envelope: brick infill panel per perimeter bay, with a window opening; windows as separate elements.
        wt = WALL_T_M / 2
        win_lo, win_hi = z0 + 0.9, min(z0 + 2.3, z_beam_bot - 0.15)
        bays: list[tuple[str, str, float, float, float]] = []  # (label, axis, along_lo, along_hi, across)
        for ix in range(len(xs) - 1):
            bays.append((f"S{ix + 1}", "x", xs[ix] + c, xs[ix + 1] - c, ys[0]))
            bays.append((f"N{ix + 1}", "x", xs[ix] + c, xs[ix + 1] - c, ys[-1]))
        for iy in range(len(ys) - 1):
            bays.append((f"W{iy + 1}", "y", ys[iy] + c, ys[iy + 1] - c, xs[0]))
            bays.append((f"E{iy + 1}", "y", ys[iy] + c, ys[iy + 1] - c, xs[-1]))
        for label, axis, a0, a1, across in bays:
            mid = (a0 + a1) / 2
            w0, w1 = mid - 0.9, mid + 0.9

            def box(
                along0: float,
                along1: float,
                za: float,
                zb: float,
                t: float = wt,
                axis: str = axis,
                across: float = across,
            ) -> tuple[tuple[float, float, float], ...]:
                if axis == "x":
                    return (along0, across - t, za), (along1, across + t, zb)
                return (across - t, along0, za), (across + t, along1, zb)

            e = Element(f"L{s}-WALL-{label}", "IfcWall", "SOLIDWALL", "Brick cavity wall 250", s, "brick", f"walls_{s}")
            e.add_box(*box(a0, w0, z0, z_beam_bot))
            e.add_box(*box(w1, a1, z0, z_beam_bot))
            e.add_box(*box(w0, w1, z0, win_lo))
            e.add_box(*box(w0, w1, win_hi, z_beam_bot))
            els.append(e)
            e = Element(f"L{s}-WIN-{label}", "IfcWindow", "WINDOW", "Window 1800x1400", s, "glass", f"windows_{s}")
            e.add_box(*box(w0, w1, win_lo, win_hi, t=0.04))
            els.append(e)

    # Gable roof over the roof slab, ridge along x.
    z_top = elevations[n]
    e = Element("RF-ROOF", "IfcRoof", "GABLE_ROOF", "Timber gable roof", n - 1, "roof", "roof")
    x0, x1, y0, y1 = -hx - so - 0.2, hx + so + 0.2, -hy - so - 0.2, hy + so + 0.2
    r = ROOF_RISE_M
    e.vertices_m = np.array(
        [[x0, y0, z_top], [x1, y0, z_top], [x1, y1, z_top], [x0, y1, z_top], [x0, 0.0, z_top + r], [x1, 0.0, z_top + r]]
    )
    e.polygons = [[0, 3, 2, 1], [0, 1, 5, 4], [3, 4, 5, 2], [0, 4, 3], [1, 2, 5]]
    els.append(e)
    return Building(els, storeys, (hx, hy), z_top + r)
