"""The model's geometry for picking: element triangles, 4D visibility, ray casts snapped to corners and edges.

Pure (numpy). Frames: world = site-local metres, z up (as ``BimModel.geometry_glb``); cameras are
:class:`constructaide.camera.PinholeCamera` (OpenCV frame, pixels with (0, 0) at the centre of the top-left pixel).
Element indices here are 0-based positions in ``BimModel.elements``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from constructaide import camera as cam
from constructaide.bimgeom import load_bim_model_glb
from constructaide.modelscene import build_scene
from constructaide.schedule4d import ElementWindow, element_windows, planned_state, stands
from schemas.messages import BimElement, BimModel

FEATURE_EDGE_DEG = 20.0  # edges between faces bent by more than this (or open edges) are snap targets
SNAP_PX = 8.0
GROW_BY = ("ifc_class", "type_name", "material", "storey", "task")

Snap = Literal["vertex", "edge", "surface"]


@dataclass(frozen=True)
class Pick:
    """What lies under a pixel: the element (None: nothing), the 3D point (world metres) and how it was snapped."""

    global_id: str | None
    ifc_class: str = ""
    point_in_world_m: tuple[float, float, float] | None = None
    snapped: Snap | None = None
    depth_m: float = 0.0

    def as_json(self) -> dict[str, object]:
        if self.global_id is None:
            return {"global_id": None}
        return {
            "global_id": self.global_id,
            "ifc_class": self.ifc_class,
            "point_in_world_m": list(self.point_in_world_m or ()),
            "snapped": self.snapped,
            "depth_m": self.depth_m,
        }


def pixel_ray(camera: cam.PinholeCamera, u: float, v: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Origin (3,) and unit direction (3,) in world of the ray through pixel (u, v) (distortion undone)."""
    xy = cam.pixels_to_normalized(camera.intrinsics, [[u, v]])[0]
    d = camera.world_from_camera[:3, :3] @ np.array([xy[0], xy[1], 1.0])
    return camera.center_in_world_m, d / np.linalg.norm(d)


class ModelGeometry:
    """Triangle soup of a :class:`BimModel` with per-triangle owners, feature edges and corners per element."""

    def __init__(self, model: BimModel) -> None:
        self.revision = model.revision
        self.elements: list[BimElement] = list(model.elements)
        self.index_of = {e.global_id: i for i, e in enumerate(self.elements)}
        meshes = load_bim_model_glb(model)
        self.scene = build_scene(self.elements, meshes)
        """The same elements as one soup for the GL rasterizer (index i + 1 = ``elements[i]``)."""
        tris: list[NDArray[np.float64]] = []
        owner: list[NDArray[np.int32]] = []
        for i, e in enumerate(self.elements):
            mesh = meshes.get(e.geometry_ref or e.global_id) or meshes.get(e.global_id)
            if mesh is None or len(mesh[1]) == 0:
                continue
            v, f = mesh
            tris.append(np.asarray(v, np.float64)[np.asarray(f, np.int64)])
            owner.append(np.full(len(f), i, np.int32))
        self.tri = np.concatenate(tris) if tris else np.zeros((0, 3, 3))
        self.tri_owner = np.concatenate(owner) if owner else np.zeros(0, np.int32)
        self._e1 = self.tri[:, 1] - self.tri[:, 0]
        self._e2 = self.tri[:, 2] - self.tri[:, 0]
        self.edges, self.edge_owner = _feature_edges(self.tri, self.tri_owner)
        corners = self.edges.reshape(-1, 3)
        corner_owner = np.repeat(self.edge_owner, 2)
        key = np.c_[corner_owner, np.round(corners * 1e4)]
        _, first = np.unique(key, axis=0, return_index=True)
        self.corners, self.corner_owner = corners[first], corner_owner[first]
        windows = element_windows(model.tasks)
        self.windows: list[ElementWindow | None] = [windows.get(e.global_id) for e in self.elements]
        self.tasks_of: dict[str, list[tuple[str, str]]] = {}
        for t in model.tasks:
            for gid in t.element_ids:
                self.tasks_of.setdefault(gid, []).append((t.task_id, t.name))
        self.tri_elements = np.unique(self.tri_owner)
        self.bbox_min_m = self.tri.reshape(-1, 3).min(0) if len(self.tri) else np.zeros(3)
        self.bbox_max_m = self.tri.reshape(-1, 3).max(0) if len(self.tri) else np.zeros(3)

    # -- 4D ---------------------------------------------------------------------------------------------------

    def standing(self, at_ns: int) -> NDArray[np.bool_]:
        """(E,) bool: element stands at ``at_ns`` (actual dates where known, else planned)."""
        return np.array([stands(w, at_ns) for w in self.windows], bool)

    # -- rays -------------------------------------------------------------------------------------------------

    def ray_cast(
        self, origin: NDArray[np.float64], direction: NDArray[np.float64], visible: NDArray[np.bool_] | None = None
    ) -> tuple[float, int] | None:
        """Nearest hit ``(distance along the unit direction in m, triangle index)`` among triangles of visible
        elements (``visible`` (E,) bool, None = all), or None."""
        if len(self.tri) == 0:
            return None
        d = np.asarray(direction, np.float64)
        p = np.cross(d, self._e2)
        det = np.einsum("ij,ij->i", self._e1, p)
        ok = np.abs(det) > 1e-12
        if visible is not None:
            ok &= visible[self.tri_owner]
        inv = np.divide(1.0, det, out=np.zeros_like(det), where=ok)
        s = np.asarray(origin, np.float64) - self.tri[:, 0]
        uu = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, self._e1)
        vv = (q @ d) * inv
        t = np.einsum("ij,ij->i", self._e2, q) * inv
        hit = ok & (uu >= -1e-9) & (vv >= -1e-9) & (uu + vv <= 1 + 1e-9) & (t > 1e-6)
        if not hit.any():
            return None
        idx = np.nonzero(hit)[0]
        k = idx[np.argmin(t[idx])]
        return float(t[k]), int(k)

    def _sees(self, origin: NDArray[np.float64], point: NDArray[np.float64], visible: NDArray[np.bool_]) -> bool:
        """Whether ``point`` is not hidden from ``origin`` by another surface (2 cm / 0.5 % tolerance)."""
        d = point - origin
        dist = float(np.linalg.norm(d))
        hit = self.ray_cast(origin, d / dist, visible)
        return hit is None or hit[0] >= dist - max(0.02, 0.005 * dist)

    def pick(
        self,
        camera: cam.PinholeCamera,
        u: float,
        v: float,
        visible: NDArray[np.bool_] | None = None,
        snap_px: float = SNAP_PX,
    ) -> Pick:
        """Element and 3D point under pixel (u, v). With ``snap_px`` > 0 the point snaps to the nearest corner, else
        edge, of a visible element that shows within ``snap_px`` pixels (not hidden by another surface), so a click
        just beside a silhouette corner still finds it."""
        origin, d = pixel_ray(camera, u, v)
        vis = np.ones(len(self.elements), bool) if visible is None else visible
        hit = self.ray_cast(origin, d, vis)
        found = self._snap(camera, np.array([u, v]), origin, d, vis, snap_px) if snap_px > 0 else None
        if found is not None:
            point, owner, snapped = found
        elif hit is not None:
            point, owner, snapped = origin + hit[0] * d, int(self.tri_owner[hit[1]]), "surface"
        else:
            return Pick(global_id=None)
        el = self.elements[owner]
        depth = float((camera.camera_from_world[:3, :3] @ point + camera.camera_from_world[:3, 3])[2])
        return Pick(
            global_id=el.global_id,
            ifc_class=el.ifc_class,
            point_in_world_m=(float(point[0]), float(point[1]), float(point[2])),
            snapped=snapped,  # type: ignore[arg-type]
            depth_m=depth,
        )

    def _snap(
        self,
        camera: cam.PinholeCamera,
        px: NDArray[np.float64],
        origin: NDArray[np.float64],
        d: NDArray[np.float64],
        visible: NDArray[np.bool_],
        snap_px: float,
    ) -> tuple[NDArray[np.float64], int, Snap] | None:
        """(point, owner, kind) of the nearest unhidden corner, else edge point, within ``snap_px`` of ``px``."""
        keep = visible[self.corner_owner]
        corners, owners = self.corners[keep], self.corner_owner[keep]
        if len(corners):
            proj, z = camera.project(corners)
            dist = np.linalg.norm(proj - px, axis=1)
            dist[~(z > 0) | ~np.isfinite(dist)] = np.inf
            for i in np.argsort(dist)[:16]:
                if dist[i] > snap_px:
                    break
                if self._sees(origin, corners[i], visible):
                    return corners[i].copy(), int(owners[i]), "vertex"
        keep = visible[self.edge_owner]
        edges, owners = self.edges[keep], self.edge_owner[keep]
        if len(edges):
            a, za = camera.project(edges[:, 0])
            b, zb = camera.project(edges[:, 1])
            ab = b - a
            tt = np.clip(np.einsum("ij,ij->i", px - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
            dist = np.linalg.norm(a + tt[:, None] * ab - px, axis=1)
            dist[~((za > 0) & (zb > 0)) | ~np.isfinite(dist)] = np.inf
            for i in np.argsort(dist)[:16]:
                if dist[i] > snap_px:
                    break
                p = _closest_on_segment_to_ray(edges[i, 0], edges[i, 1], origin, d)
                if self._sees(origin, p, visible):
                    return p, int(owners[i]), "edge"
        return None

    def mesh_bytes(self) -> bytes:
        """The triangles and feature edges for a browser's WebGL view, little-endian: uint32 T, uint32 K, float32
        (T, 3, 3) triangle corners, uint32 (T,) owners, float32 (K, 2, 3) edge ends, uint32 (K,) owners."""
        head = np.array([len(self.tri), len(self.edges)], "<u4").tobytes()
        return b"".join(
            [
                head,
                self.tri.astype("<f4").tobytes(),
                self.tri_owner.astype("<u4").tobytes(),
                self.edges.astype("<f4").tobytes(),
                self.edge_owner.astype("<u4").tobytes(),
            ]
        )

    # -- attributes -------------------------------------------------------------------------------------------

    def grow(self, element_ids: list[str], by: str) -> list[str]:
        """Every element sharing ``by`` (one of :data:`GROW_BY`) with one of ``element_ids``."""
        if by not in GROW_BY:
            raise ValueError(f"grow by must be one of {', '.join(GROW_BY)}, got {by!r}")
        seeds = [self.elements[self.index_of[g]] for g in element_ids if g in self.index_of]
        if by == "task":
            tasks = {t for e in seeds for t, _ in self.tasks_of.get(e.global_id, [])}
            return [e.global_id for e in self.elements if {t for t, _ in self.tasks_of.get(e.global_id, [])} & tasks]
        values = {getattr(e, by) for e in seeds}
        values.discard("")
        return [e.global_id for e in self.elements if getattr(e, by) in values]

    def element_info(self, global_id: str, at_ns: int | None = None) -> dict[str, object]:
        """IFC attributes, tasks and (with ``at_ns``) the planned state and whether it stands then."""
        i = self.index_of.get(global_id)
        if i is None:
            raise KeyError(global_id)
        e = self.elements[i]
        out: dict[str, object] = {
            "global_id": e.global_id,
            "ifc_class": e.ifc_class,
            "name": e.name,
            "storey": e.storey,
            "type_name": e.type_name,
            "material": e.material,
            "tasks": [{"task_id": t, "name": n} for t, n in self.tasks_of.get(e.global_id, [])],
        }
        if at_ns is not None:
            out["planned_state"] = planned_state(self.windows[i], at_ns)
            out["stands"] = stands(self.windows[i], at_ns)
        return out


def _closest_on_segment_to_ray(
    a: NDArray[np.float64], b: NDArray[np.float64], origin: NDArray[np.float64], d: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Point of segment ab closest to the ray origin + s d (d unit)."""
    u = b - a
    w = a - origin
    uu, ud, uw, dw = u @ u, u @ d, u @ w, d @ w
    den = uu - ud * ud
    s = (ud * dw - uw) / den if den > 1e-12 else 0.0
    return a + float(np.clip(s, 0.0, 1.0)) * u


def _feature_edges(tri: NDArray[np.float64], owner: NDArray[np.int32]) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """(K, 2, 3) edges of each element's mesh that are open or between faces bent by more than
    :data:`FEATURE_EDGE_DEG` (the diagonals splitting flat quads are not), and their owners (K,)."""
    if len(tri) == 0:
        return np.zeros((0, 2, 3)), np.zeros(0, np.int32)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-15)
    verts = tri.reshape(-1, 3)
    key = np.c_[np.repeat(owner, 3), np.round(verts * 1e4)]
    _, vid = np.unique(key, axis=0, return_inverse=True)
    vid = vid.reshape(-1, 3)
    pairs = np.concatenate([vid[:, [0, 1]], vid[:, [1, 2]], vid[:, [2, 0]]])
    faces = np.tile(np.arange(len(tri)), 3)
    ends = np.concatenate([[0, 1], [1, 2], [2, 0]])
    pairs = np.sort(pairs, axis=1)
    uniq, inv, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    feature = counts != 2
    two = np.nonzero(counts == 2)[0]
    if len(two):
        starts = np.searchsorted(inv[order], two)
        f0, f1 = faces[order[starts]], faces[order[starts + 1]]
        feature[two] = np.einsum("ij,ij->i", n[f0], n[f1]) < np.cos(np.radians(FEATURE_EDGE_DEG))
    first = order[np.searchsorted(inv[order], np.nonzero(feature)[0])]
    f = faces[first]
    corner = np.repeat(np.arange(3), len(tri))[first]
    a_idx = ends.reshape(3, 2)[corner]
    edges = np.stack([tri[f, a_idx[:, 0]], tri[f, a_idx[:, 1]]], axis=1)
    return edges, owner[f]
