"""BIM meshes -> one flat triangle soup with an element index per vertex (pure core).

Element index ``i`` (1-based) names ``BimScene.global_ids[i - 1]``; index 0 is background. The
soup is unshared (three vertices per triangle) so per-face quantities (normal, shade) travel as
vertex attributes and every triangle can be drawn in one call. Coordinates are site-local metres,
z up, exactly as in ``BimModel.geometry_glb``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.messages import BimElement, BimModel, ElementFilter

MeshDict = dict[str, tuple[NDArray[np.float64], NDArray[np.int64]]]

# Fixed world light used for the cheap per-face shade of overlay renders (unit, z up).
SHADE_LIGHT_DIR_WORLD = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])

MAX_ELEMENTS = (1 << 24) - 2
GROUND_INDEX = (1 << 24) - 1
"""Index written for the optional ground plane (an occluder, never an element)."""


def load_glb_meshes(glb: bytes) -> MeshDict:
    """Meshes of a binary glTF: ``{node name: (vertices (N, 3) metres, faces (M, 3) int)}``.

    Node transforms are applied; coordinates are used as stored (site-local, z up).
    """
    if not glb:
        return {}
    import trimesh

    try:
        loaded = trimesh.load(file_obj=io.BytesIO(glb), file_type="glb", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise ValueError(f"geometry_glb is not a readable binary glTF: {exc}") from exc
    out: MeshDict = {}
    if isinstance(loaded, trimesh.Trimesh):
        out["mesh"] = (np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64))
        return out
    for node_name in loaded.graph.nodes_geometry:
        world_from_node, geom_name = loaded.graph[node_name]
        geom = loaded.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        v = np.asarray(geom.vertices, np.float64) @ world_from_node[:3, :3].T + world_from_node[:3, 3]
        f = np.asarray(geom.faces, np.int64)
        if node_name in out:  # several primitives under one node name: concatenate
            v0, f0 = out[node_name]
            out[node_name] = (np.vstack([v0, v]), np.vstack([f0, f + len(v0)]))
        else:
            out[node_name] = (v, f)
    return out


@dataclass
class BimScene:
    """All element meshes as one unshared triangle soup.

    ``positions_m`` (3T, 3) float32; ``element_index`` (3T,) uint32, 1-based; ``normals``
    (3T, 3) float32 unit face normals; ``shade`` (3T,) float32 in [0, 1] (two-sided Lambert
    under :data:`SHADE_LIGHT_DIR_WORLD` plus ambient). ``tri_range[i]`` = (first, end) triangle
    of element index ``i`` (row 0 unused).
    """

    global_ids: list[str]
    elements: list[BimElement]
    positions_m: NDArray[np.float32]
    element_index: NDArray[np.uint32]
    normals: NDArray[np.float32]
    shade: NDArray[np.float32]
    tri_range: NDArray[np.int64]
    bbox_min_m: NDArray[np.float64]
    bbox_max_m: NDArray[np.float64]
    index_of: dict[str, int] = field(default_factory=dict)

    @property
    def num_elements(self) -> int:
        return len(self.global_ids)

    @property
    def num_triangles(self) -> int:
        return len(self.element_index) // 3

    def element_vertices(self, index: int) -> NDArray[np.float32]:
        """(3k, 3) unshared vertices of one element (1-based index)."""
        a, b = self.tri_range[index]
        return self.positions_m[3 * a : 3 * b]


def build_scene(elements: tuple[BimElement, ...] | list[BimElement], meshes: MeshDict) -> BimScene:
    """Flatten element meshes into a :class:`BimScene`; element order = index order.

    Elements whose ``geometry_ref`` (or GlobalId) has no mesh keep an index but no triangles.
    """
    if len(elements) > MAX_ELEMENTS:
        raise ValueError(f"too many elements for 24-bit ids: {len(elements)}")
    pos_parts: list[NDArray[np.float64]] = []
    idx_parts: list[NDArray[np.uint32]] = []
    tri_range = np.zeros((len(elements) + 1, 2), np.int64)
    tri_count = 0
    for i, el in enumerate(elements, start=1):
        mesh = meshes.get(el.geometry_ref or el.global_id)
        if mesh is None and el.geometry_ref:
            mesh = meshes.get(el.global_id)
        tri_range[i, 0] = tri_count
        if mesh is not None:
            v, f = mesh
            f = np.asarray(f, np.int64)
            if f.size and (f.min() < 0 or f.max() >= len(v)):
                raise ValueError(f"element {el.global_id}: face index out of range")
            tris = np.asarray(v, np.float64)[f].reshape(-1, 3)
            pos_parts.append(tris)
            idx_parts.append(np.full(len(tris), i, np.uint32))
            tri_count += len(f)
        tri_range[i, 1] = tri_count
    positions = np.vstack(pos_parts) if pos_parts else np.zeros((0, 3))
    index = np.concatenate(idx_parts) if idx_parts else np.zeros(0, np.uint32)
    tri = positions.reshape(-1, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)
    shade_face = 0.35 + 0.65 * np.abs(n @ SHADE_LIGHT_DIR_WORLD)
    if len(positions):
        bmin, bmax = positions.min(0), positions.max(0)
    else:
        bmin, bmax = np.zeros(3), np.zeros(3)
    gids = [el.global_id for el in elements]
    return BimScene(
        global_ids=gids,
        elements=list(elements),
        positions_m=positions.astype(np.float32),
        element_index=index,
        normals=np.repeat(n, 3, axis=0).astype(np.float32),
        shade=np.repeat(shade_face, 3).astype(np.float32),
        tri_range=tri_range,
        bbox_min_m=bmin,
        bbox_max_m=bmax,
        index_of={g: i for i, g in enumerate(gids, start=1)},
    )


def scene_from_model(model: BimModel, meshes: MeshDict | None = None) -> BimScene:
    """:class:`BimScene` of a :class:`BimModel` (decodes ``geometry_glb`` unless ``meshes`` given).

    Uses the shared ``constructaide.bimgeom.load_bim_model_glb`` when it exists.
    """
    if meshes is None:
        try:
            from constructaide.bimgeom import load_bim_model_glb
        except ImportError:
            meshes = load_glb_meshes(model.geometry_glb)
        else:
            meshes = load_bim_model_glb(model)
    return build_scene(model.elements, meshes)


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
