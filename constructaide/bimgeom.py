"""Element meshes <-> binary glTF (GLB), the geometry carried by ``BimModel`` / ``BimUpdate``.

Convention: one glTF node per element, named by ``BimElement.geometry_ref``; vertices in
site-local metres, **z up** (the model frame itself; no y-up rotation is applied, unlike
glTF's default convention). Pure: numpy + trimesh only.
"""

from __future__ import annotations

import io
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt
import trimesh

from schemas.messages import BimModel, BimUpdate

F64 = npt.NDArray[np.float64]
I32 = npt.NDArray[np.int32]
Mesh = tuple[F64, I32]
"""(vertices (N, 3) float64 metres, faces (M, 3) int32 vertex indices)."""


def meshes_to_glb(
    meshes: Mapping[str, Mesh], colors_rgba: Mapping[str, tuple[int, int, int, int]] | None = None
) -> bytes:
    """GLB bytes with one node per entry of ``meshes`` (node name = key); empty meshes are skipped.

    ``colors_rgba`` optionally gives a uniform 0-255 RGBA colour per node.
    """
    scene = trimesh.Scene()
    for ref, (vertices_m, faces) in meshes.items():
        v = np.asarray(vertices_m, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if len(v) == 0 or len(f) == 0:
            continue
        visual = None
        if colors_rgba is not None and ref in colors_rgba:
            rgba = np.tile(np.asarray(colors_rgba[ref], dtype=np.uint8), (len(f), 1))
            visual = trimesh.visual.ColorVisuals(face_colors=rgba)
        mesh = trimesh.Trimesh(vertices=v, faces=f, process=False, visual=visual)
        scene.add_geometry(mesh, node_name=ref, geom_name=ref)
    if not scene.geometry:
        return b""
    return bytes(scene.export(file_type="glb"))


def glb_to_meshes(glb: bytes) -> dict[str, Mesh]:
    """Decode GLB bytes into ``{node name: (vertices (N,3) float64 m, faces (M,3) int32)}``.

    Node transforms are applied. Raises ValueError on bytes that are not a GLB.
    """
    if not glb:
        return {}
    if glb[:4] != b"glTF":
        raise ValueError("geometry is not a binary glTF (GLB magic missing)")
    try:
        loaded = trimesh.load(io.BytesIO(glb), file_type="glb", process=False, force="scene")
    except Exception as exc:  # trimesh raises many types on corrupt input
        raise ValueError(f"cannot decode GLB: {exc}") from exc
    if not isinstance(loaded, trimesh.Scene):
        raise ValueError(f"GLB decoded to {type(loaded).__name__}, expected a scene")
    scene = loaded
    out: dict[str, Mesh] = {}
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        v = np.asarray(geom.vertices, dtype=np.float64)
        if not np.allclose(transform, np.eye(4)):
            v = v @ transform[:3, :3].T + transform[:3, 3]
        out[str(node)] = (v, np.asarray(geom.faces, dtype=np.int32))
    return out


def load_bim_model_glb(model: BimModel | BimUpdate) -> dict[str, Mesh]:
    """Meshes of a ``BimModel`` (or the added/changed meshes of a ``BimUpdate``) by geometry_ref."""
    return glb_to_meshes(model.geometry_glb)
