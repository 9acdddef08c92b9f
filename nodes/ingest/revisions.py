"""Site model -> bus messages: a whole revision (``BimModel``) or the difference between two
revisions (``BimUpdate``), elements matched by GlobalId."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

from constructaide.bim.model import SiteModel
from constructaide.bimgeom import meshes_to_glb
from schemas.messages import BimModel, BimUpdate


def revision_id(paths: Iterable[str | Path]) -> str:
    """Content hash (sha256 hex, 12 chars) of the given files in order: the same inputs give the
    same revision."""
    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).name.encode())
        h.update(b"\0")
        with Path(p).open("rb") as fh:
            while chunk := fh.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()[:12]


def _colors(site_model: SiteModel, refs: Iterable[str]) -> dict[str, tuple[int, int, int, int]]:
    return {r: m.rgba for r in refs if (m := site_model.meshes.get(r)) is not None and m.rgba is not None}


def to_bim_model(site_model: SiteModel, site: str, revision: str, terrain_height_m: float | None = None) -> BimModel:
    """The whole site model as a ``BimModel``: elements, tasks and a GLB with one node per
    element named by its geometry_ref (site-local metres, z up); ``terrain_height_m`` is the site's
    ground level in the same frame when configured."""
    meshes = {
        e.geometry_ref: (m.vertices_m, m.faces)
        for e in site_model.elements.values()
        if (m := site_model.meshes.get(e.geometry_ref)) is not None
    }
    mc = site_model.map_conversion
    return BimModel(
        site=site,
        revision=revision,
        elements=tuple(site_model.elements.values()),
        tasks=site_model.tasks,
        geometry_glb=meshes_to_glb(meshes, _colors(site_model, meshes)),
        origin_offset_m=site_model.origin_offset_m,
        crs_name=mc.crs_name if mc is not None else "",
        gps=site_model.gps,
        tz=site_model.tz,
        source_files=tuple(Path(p).name for p in site_model.source_files),
        terrain_height_m=terrain_height_m,
    )


def diff_models(old: SiteModel, new: SiteModel, *, site: str, base_revision: str, revision: str) -> BimUpdate:
    """Elements added, removed and changed (attributes or geometry hash differ) from ``old`` to
    ``new``; ``geometry_glb`` carries the meshes of added and changed elements, ``tasks`` is the
    new schedule when it differs, else ``None``."""
    added = [e for gid, e in new.elements.items() if gid not in old.elements]
    removed = tuple(gid for gid in old.elements if gid not in new.elements)
    changed = []
    for gid, e in new.elements.items():
        o = old.elements.get(gid)
        if o is None:
            continue
        if o != e:
            changed.append(e)
            continue
        om, nm = old.meshes.get(o.geometry_ref), new.meshes.get(e.geometry_ref)
        if om is None or nm is None:
            if (om is None) != (nm is None):
                changed.append(e)
        elif om.geometry_hash() != nm.geometry_hash():
            changed.append(e)
    meshes = {
        e.geometry_ref: (m.vertices_m, m.faces)
        for e in (*added, *changed)
        if (m := new.meshes.get(e.geometry_ref)) is not None
    }
    return BimUpdate(
        site=site,
        base_revision=base_revision,
        revision=revision,
        added=tuple(added),
        removed=removed,
        changed=tuple(changed),
        geometry_glb=meshes_to_glb(meshes, _colors(new, meshes)) if meshes else b"",
        tasks=new.tasks if new.tasks != old.tasks else None,
    )
