"""Site context (ground, neighbours, trees, fence), dynamic objects and their per-photo placement.

All geometry is in the site frame (x east, y north, z up, metres). Objects are plain polyhedra
(``Solid``) with a texture key; ``render.py`` turns them into pyrender meshes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .building import Building, Element

F64 = NDArray[np.float64]

FENCE_OFFSET_M = 5.0
FENCE_HEIGHT_M = 2.2
JIB_M = 30.0  # crane jib length beyond the mast


@dataclass
class Solid:
    """A textured polyhedron. ``category`` is "static" or "dynamic"; vertices in the object's frame."""

    name: str
    texture: str
    category: str
    vertices_m: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    polygons: list[list[int]] = field(default_factory=list)
    uv_mode: str = "planar"  # "planar" (world-planar, tiled) or "site" (one non-repeating site texture)
    radius_m: float = 0.0  # footprint radius (dynamic objects: clearance from cameras)

    def add_box(self, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> None:
        tmp = Element("tmp", "", "", "", 0, "", "", self.vertices_m, self.polygons)
        tmp.add_box(lo, hi)
        self.vertices_m, self.polygons = tmp.vertices_m, tmp.polygons

    def add_mesh(self, vertices: F64, triangles: NDArray[np.int64]) -> None:
        base = len(self.vertices_m)
        self.vertices_m = np.vstack([self.vertices_m, vertices])
        self.polygons.extend([[base + int(i) for i in t] for t in triangles])


@dataclass(frozen=True)
class SiteLayout:
    """Where things are, derived from the building size."""

    hx: float
    hy: float
    fence_x: float
    fence_y: float
    site_extent_m: float  # side of the non-repeating gravel area
    paths: list[tuple[float, float, float, float]]
    pads: list[tuple[float, float, float, float]]
    trees: list[tuple[float, float, float]]  # (x, y, crown radius)
    neighbours: list[tuple[float, float, float, float, float, str]]  # (x0, y0, x1, y1, height, texture)
    crane_xy: tuple[float, float]
    truck_slots: list[tuple[float, float, float]]  # (x, y, yaw_deg)
    cabin_slots: list[tuple[float, float, float]]


def make_layout(building: Building) -> SiteLayout:
    hx, hy = building.half_extent_m
    fx, fy = hx + FENCE_OFFSET_M, hy + FENCE_OFFSET_M
    road_y = -fy - 6.0
    ext = 2 * (max(fx, fy) + 45.0)
    paths = [(-ext / 2, road_y, ext / 2, road_y), (fx + 7.0, -ext / 2, fx + 7.0, ext / 2), (0.0, road_y, 0.0, -fy)]
    pads = [(-hx - 1.5, fy - 3.0, -hx + 9.0, fy - 0.5), (hx - 2.0, -fy + 0.5, hx + 3.5, -fy + 2.8)]
    r = max(fx, fy)
    trees = [
        (-fx - 4.0, -fy - 2.5, 2.6),
        (-fx - 9.0, fy + 3.0, 3.0),
        (fx + 3.5, fy + 6.0, 2.8),
        (fx + 11.0, -fy + 4.0, 2.4),
        (-8.0, fy + 9.0, 2.2),
        (7.0, road_y - 5.0, 2.8),
        (-fx - 14.0, 2.0, 3.2),
        (fx + 16.0, fy + 10.0, 3.0),
        (-3.0 - r, road_y - 8.0, 2.5),
        (12.0, fy + 14.0, 2.6),
    ]
    neighbours = [
        (-fx - 32.0, fy + 6.0, -fx - 14.0, fy + 20.0, 12.5, "facade_a"),
        (fx + 20.0, fy + 12.0, fx + 36.0, fy + 26.0, 9.5, "facade_b"),
        (fx + 22.0, -fy - 30.0, fx + 40.0, -fy - 14.0, 15.5, "facade_c"),
        (-fx - 34.0, -fy - 28.0, -fx - 18.0, -fy - 12.0, 9.0, "facade_b"),
        (-12.0, fy + 34.0, 14.0, fy + 46.0, 18.0, "facade_c"),
        (-14.0, road_y - 40.0, 10.0, road_y - 28.0, 12.0, "facade_a"),
        (-fx - 48.0, -8.0, -fx - 36.0, 12.0, 21.0, "facade_a"),
        (fx + 38.0, -10.0, fx + 50.0, 8.0, 13.0, "facade_c"),
    ]
    trucks = [
        (-fx + 6.0, road_y, 0.0),
        (fx - 3.0, road_y, 180.0),
        (-2.0, -fy + 3.0, 0.0),
        (fx - 1.5, hy - 1.0, 90.0),
        (-fx + 3.0, hy, 90.0),
        (fx + 7.0, 6.0, 90.0),
        (-hx + 2.0, -fy + 2.5, 0.0),
        (fx + 7.0, -12.0, 270.0),
    ]
    cabins = [
        (-fx + 4.0, fy - 1.6, 0.0),
        (fx - 1.6, -fy + 5.0, 90.0),
        (-fx + 1.6, -fy + 5.0, 90.0),
        (hx + 1.5, fy - 1.6, 0.0),
        (-fx + 11.0, fy - 1.6, 0.0),
    ]
    return SiteLayout(hx, hy, fx, fy, ext, paths, pads, trees, neighbours, (hx * 0.45, fy - 2.0), trucks, cabins)


def _box_solid(name: str, texture: str, category: str, lo, hi) -> Solid:
    s = Solid(name, texture, category)
    s.add_box(lo, hi)
    return s


def _icosphere(radius: float, center: F64, subdivisions: int = 2) -> tuple[F64, NDArray[np.int64]]:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(m.vertices) * np.array([1.0, 1.0, 1.15]) + center
    return v, np.asarray(m.faces, dtype=np.int64)


def clear_trees(layout: SiteLayout, building: Building, eyes_m: list[F64]) -> SiteLayout:
    """Drop trees whose crown would hide the central part of the building from a fixed camera at ``eyes_m``."""
    centre = np.array([0.0, 0.0, 0.4 * building.top_m])
    keep = []
    for x, y, r in layout.trees:
        crown = np.array([x, y, 2.4 + r])
        ok = True
        for eye in eyes_m:
            to_c, to_t = centre - eye, crown - eye
            if np.linalg.norm(to_t) > np.linalg.norm(to_c):
                continue
            ang = math.acos(np.clip(to_c @ to_t / (np.linalg.norm(to_c) * np.linalg.norm(to_t)), -1, 1))
            half_bldg = math.atan(0.5 * max(layout.hx, layout.hy) / np.linalg.norm(to_c))
            if ang < math.atan(1.15 * r / np.linalg.norm(to_t)) + half_bldg:
                ok = False
        if ok:
            keep.append((x, y, r))
    return dataclasses.replace(layout, trees=keep)


def static_solids(layout: SiteLayout) -> list[Solid]:
    """Ground (grass everywhere, gravel site area), neighbours, trees and the site fence (with a south gate)."""
    out: list[Solid] = []
    g = Solid("ground-outer", "grass", "static")
    big = 600.0
    g.vertices_m = np.array([[-big, -big, 0.0], [big, -big, 0.0], [big, big, 0.0], [-big, big, 0.0]])
    g.polygons = [[0, 1, 2, 3]]
    out.append(g)
    e = layout.site_extent_m / 2
    s = Solid("ground-site", "site_ground", "static", uv_mode="site")
    s.vertices_m = np.array([[-e, -e, 0.02], [e, -e, 0.02], [e, e, 0.02], [-e, e, 0.02]])
    s.polygons = [[0, 1, 2, 3]]
    out.append(s)
    for i, (x0, y0, x1, y1, h, tex) in enumerate(layout.neighbours):
        out.append(_box_solid(f"neighbour-{i}", tex, "static", (x0, y0, 0.0), (x1, y1, h)))
    for i, (x, y, r) in enumerate(layout.trees):
        out.append(_box_solid(f"trunk-{i}", "bark", "static", (x - 0.18, y - 0.18, 0.0), (x + 0.18, y + 0.18, 2.6)))
        crown = Solid(f"crown-{i}", "foliage", "static")
        crown.add_mesh(*_icosphere(r, np.array([x, y, 2.4 + r])))
        out.append(crown)
    fx, fy, t, h = layout.fence_x, layout.fence_y, 0.06, FENCE_HEIGHT_M
    fence = Solid("fence", "hoarding", "static")
    gate = 3.5
    fence.add_box((-fx, -fy - t, 0.0), (-gate / 2, -fy, h))  # south, west of the gate
    fence.add_box((gate / 2, -fy - t, 0.0), (fx, -fy, h))  # south, east of the gate
    fence.add_box((-fx, fy, 0.0), (fx, fy + t, h))
    fence.add_box((-fx - t, -fy - t, 0.0), (-fx, fy + t, h))
    fence.add_box((fx, -fy - t, 0.0), (fx + t, fy + t, h))
    out.append(fence)
    return out


def dynamic_solids(layout: SiteLayout, top_m: float) -> list[Solid]:
    """Crane (in its own frame, mast at the origin), two trucks and two cabins (frames at footprint centre)."""
    out: list[Solid] = []
    crane = Solid("crane", "crane", "dynamic", radius_m=1.5)
    hook_z = top_m + 2.0
    crane.add_box((-0.8, -0.8, 0.0), (0.8, 0.8, hook_z))
    crane.add_box((-10.0, -0.6, hook_z), (JIB_M, 0.6, hook_z + 1.4))
    crane.add_box((-9.5, -1.2, hook_z - 2.0), (-6.5, 1.2, hook_z))  # counterweight
    crane.add_box((-1.0, -1.0, hook_z + 1.4), (1.0, 1.0, hook_z + 5.0))  # apex
    out.append(crane)
    for i in range(2):
        truck = Solid(f"truck-{i}", "truck", "dynamic", radius_m=4.0)
        truck.add_box((-3.5, -1.25, 0.5), (2.0, 1.25, 3.6))  # box body
        truck.add_box((2.0, -1.2, 0.5), (3.6, 1.2, 2.9))  # cab
        truck.add_box((-3.2, -1.1, 0.0), (3.2, 1.1, 0.5))  # chassis
        out.append(truck)
    for i in range(2):
        cabin = Solid(f"cabin-{i}", "cabin", "dynamic", radius_m=3.5)
        cabin.add_box((-3.0, -1.2, 0.0), (3.0, 1.2, 2.6))
        out.append(cabin)
    return out


def _pose(x: float, y: float, yaw_deg: float) -> F64:
    a = math.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:2, 3] = x, y
    return T


def dynamic_poses(
    layout: SiteLayout, rng: np.random.Generator, day: int, camera_xy: F64 | None = None
) -> dict[str, F64 | None]:
    """World pose per dynamic solid (None = absent) for one photo. Cabins move weekly, trucks and the crane
    jib per photo. The jib never points within 25 degrees of a camera it could reach; vehicles closer than
    their radius + 2 m to ``camera_xy`` are dropped."""
    crane_xy = np.asarray(layout.crane_xy)
    yaw = float(rng.uniform(0, 360))
    if camera_xy is not None:
        to_cam = np.asarray(camera_xy) - crane_xy
        cam_deg = math.degrees(math.atan2(to_cam[1], to_cam[0]))
        if np.hypot(*to_cam) < JIB_M + 8.0:
            for _ in range(50):
                off = abs((yaw - cam_deg + 180.0) % 360.0 - 180.0)  # jib to camera
                if 25.0 < off < 155.0:  # clear of the jib and the counter-jib
                    break
                yaw = float(rng.uniform(0, 360))
    poses: dict[str, F64 | None] = {"crane": _pose(*layout.crane_xy, yaw)}
    slots = rng.permutation(len(layout.truck_slots))
    for i in range(2):
        x, y, yaw_t = layout.truck_slots[int(slots[i])]
        poses[f"truck-{i}"] = _pose(x, y, yaw_t) if rng.random() < 0.75 else None
    week_rng = np.random.default_rng(10_000 + day // 5)
    cslots = week_rng.permutation(len(layout.cabin_slots))
    for i in range(2):
        x, y, yaw_c = layout.cabin_slots[int(cslots[i])]
        poses[f"cabin-{i}"] = _pose(x, y, yaw_c)
    if camera_xy is not None:
        radius = {"crane": 1.5, "truck-0": 4.0, "truck-1": 4.0, "cabin-0": 3.5, "cabin-1": 3.5}
        for k, T in poses.items():
            if T is not None and np.hypot(*(T[:2, 3] - camera_xy)) < radius[k] + 2.0:
                poses[k] = None
    return poses


def camera_position_ok(layout: SiteLayout, building: Building, xy: F64) -> bool:
    """True if a handheld camera at ``xy`` stands clear of the fence, building, trees and neighbours."""
    x, y = float(xy[0]), float(xy[1])
    if abs(x) < layout.hx + 2.0 and abs(y) < layout.hy + 2.0:
        return False
    inside = abs(x) < layout.fence_x and abs(y) < layout.fence_y
    d_fence = (
        min(abs(abs(x) - layout.fence_x), abs(abs(y) - layout.fence_y))
        if inside
        else max(abs(x) - layout.fence_x, abs(y) - layout.fence_y)
    )
    if d_fence < 1.5:
        return False
    if np.hypot(x - layout.crane_xy[0], y - layout.crane_xy[1]) < 4.0:
        return False
    for tx, ty, r in layout.trees:
        if np.hypot(x - tx, y - ty) < r + 1.0:
            return False
    for x0, y0, x1, y1, _, _ in layout.neighbours:
        if x0 - 2 < x < x1 + 2 and y0 - 2 < y < y1 + 2:
            return False
    return True
