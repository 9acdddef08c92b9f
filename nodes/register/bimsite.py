"""The BIM as the register node's depth lookup needs it (pure): meshes by geometry_ref, the GlobalId of each, the
schedule and the terrain height, kept current through model updates."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from constructaide.bim.model import SiteModel
from constructaide.bimgeom import glb_to_meshes
from constructaide.schedule4d import standing_elements
from nodes.register.bimdepth import MeshDepthLookup
from schemas.messages import BimModel, BimUpdate, GeoPoint, ScheduleTask


class BimMeshes:
    """Meshes (site-local metres) keyed by geometry_ref, with the model's schedule and terrain height."""

    def __init__(self) -> None:
        self.meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self.ref_of: dict[str, str] = {}
        self.tasks: tuple[ScheduleTask, ...] = ()
        self.terrain_height_m: float | None = None
        self.gps: GeoPoint | None = None
        self.origin_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """The model origin's geographic position (the site reference), when the model has one."""

    def set_model(self, msg: BimModel) -> None:
        self.meshes = dict(glb_to_meshes(msg.geometry_glb))
        self.ref_of = {e.global_id: (e.geometry_ref or e.global_id) for e in msg.elements}
        self.tasks = msg.tasks
        self.terrain_height_m = msg.terrain_height_m
        self.gps = msg.gps
        self.origin_offset_m = msg.origin_offset_m

    @classmethod
    def from_site_model(cls, site_model: SiteModel, terrain_height_m: float | None = None) -> BimMeshes:
        """The model as read from its files (the batch command's ``--bim``), as :meth:`set_model` would hold it."""
        out = cls()
        out.ref_of = {e.global_id: (e.geometry_ref or e.global_id) for e in site_model.elements.values()}
        # in the model's element order, as the GLB the ingest node publishes holds them (the draw order)
        refs = dict.fromkeys(out.ref_of.values())
        out.meshes = {ref: (m.vertices_m, m.faces) for ref in refs if (m := site_model.meshes.get(ref)) is not None}
        out.tasks = site_model.tasks
        out.terrain_height_m = terrain_height_m
        out.gps = site_model.gps
        out.origin_offset_m = site_model.origin_offset_m
        return out

    def apply_update(self, msg: BimUpdate) -> None:
        for gid in msg.removed:
            self.meshes.pop(self.ref_of.pop(gid, gid), None)
        for e in (*msg.added, *msg.changed):
            self.ref_of[e.global_id] = e.geometry_ref or e.global_id
        self.meshes.update(glb_to_meshes(msg.geometry_glb))
        if msg.tasks is not None:
            self.tasks = msg.tasks

    def depth_lookup(self) -> MeshDepthLookup:
        """The register node's BIM view of this model (the schedule's standing elements, the terrain plane, the site
        reference). Raises ValueError for a model without triangles."""
        return MeshDepthLookup(
            self.meshes,
            elements_at=self.refs_at(),
            ground_height_m=self.terrain_height_m,
            site_gps=self.gps,
            origin_offset_m=self.origin_offset_m,
        )

    def refs_at(self) -> Callable[[int], set[str] | None]:
        """``refs_at(t_ns)``: the mesh refs of the elements standing at ``t_ns`` by the schedule (None: all; meshes
        no element names stand by their own name)."""
        gid_of = {ref: gid for gid, ref in self.ref_of.items()}
        by_gid = standing_elements(self.tasks, set(gid_of.values()) | {r for r in self.meshes if r not in gid_of})
        refs = list(self.meshes)

        def refs_at(t_ns: int) -> set[str] | None:
            gids = by_gid(t_ns)
            if gids is None:
                return None
            return {ref for ref in refs if gid_of.get(ref, ref) in gids}

        return refs_at
