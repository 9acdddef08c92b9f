"""BIM meshes -> one flat triangle soup with an element index per vertex (pure, numpy).

Element index ``i`` (1-based) names ``BimScene.global_ids[i - 1]``; index 0 is background. The
soup is unshared (three vertices per triangle) so per-face quantities (normal, shade) travel as
vertex attributes and every triangle can be drawn in one call. Coordinates are site-local metres,
z up, exactly as in ``BimModel.geometry_glb``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from constructaide.bimgeom import glb_to_meshes
from schemas.messages import BimElement, BimModel

MeshDict = Mapping[str, tuple[NDArray[np.float64], NDArray[np.integer]]]
"""``{name: (vertices (N, 3) metres, faces (M, 3) vertex indices)}``."""

# Fixed world light used for the cheap per-face shade of overlay renders (unit, z up).
SHADE_LIGHT_DIR_WORLD = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])

MAX_ELEMENTS = (1 << 24) - 2
GROUND_INDEX = (1 << 24) - 1
"""Index written for the optional ground plane (an occluder, never an element)."""


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
    """:class:`BimScene` of a :class:`BimModel` (decodes ``geometry_glb`` unless ``meshes`` are given)."""
    return build_scene(model.elements, glb_to_meshes(model.geometry_glb) if meshes is None else meshes)


def scene_from_meshes(meshes: MeshDict) -> BimScene:
    """:class:`BimScene` of bare meshes (no BIM attributes): one element per mesh, its GlobalId the mesh name."""
    return build_scene([BimElement(global_id=name, ifc_class="", geometry_ref=name) for name in meshes], meshes)
