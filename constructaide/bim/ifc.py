"""IFC files -> :class:`SiteModel` (IFC2X3, IFC4, IFC4X3) with ifcopenshell.

Geometry comes from ``ifcopenshell.geom.iterator`` in world coordinates (placements applied,
openings subtracted), several threads, converted to metres by ifcopenshell's unit handling.
Elements are the IfcProducts with 3D geometry except spatial structure (site, building,
storey, space), openings, annotations and grids. Several files (architecture + structure +
MEP parts) merge into one model; the first file holding a GlobalId wins and duplicates are
listed in ``SiteModel.warnings``.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import ifcopenshell
import ifcopenshell.geom
import ifcopenshell.ifcopenshell_wrapper
import ifcopenshell.util.element as ue
import ifcopenshell.util.unit as uu
import msgspec
import numpy as np

from constructaide.bim.model import ElementMesh, MapConversion, SiteModel
from constructaide.bim.schedule import load_schedule, resolve_elements, tasks_from_ifc, validate_tasks, zone
from schemas.messages import BimElement, GeoPoint, ScheduleTask

SUPPORTED_SCHEMAS = ("IFC2X3", "IFC4", "IFC4X3")
EXCLUDED_CLASSES = (
    "IfcSpatialStructureElement",  # site, building, storey, space (IFC2X3 + IFC4)
    "IfcSpatialElement",  # IFC4+: also spatial zones, external spatial elements
    "IfcFeatureElementSubtraction",  # openings, voids
    "IfcAnnotation",
    "IfcGrid",
    "IfcVirtualElement",
)
LARGE_COORDINATE_M = 10_000.0
"""Models whose bounding box lies further than this from the origin get an origin offset."""
OFFSET_GRID_M = 1_000.0
"""The automatic origin offset is a multiple of this, so small edits keep the same offset."""


class IfcLoadError(ValueError):
    """An IFC file that cannot become a site model; the message names the file and the reason."""


_SCHEMA_RE = re.compile(rb"FILE_SCHEMA\s*\(\s*\(\s*'([^']*)'", re.IGNORECASE)


def _check_spf(path: Path) -> None:
    """Cheap checks on an IFC-SPF file before parsing: header, schema, end marker (truncation)."""
    size = path.stat().st_size
    if size == 0:
        raise IfcLoadError(f"{path}: empty file")
    with path.open("rb") as fh:
        head = fh.read(8192)
        fh.seek(max(0, size - 4096))
        tail = fh.read()
    if not head.removeprefix(b"\xef\xbb\xbf").lstrip().startswith(b"ISO-10303-21;"):
        raise IfcLoadError(f"{path}: not an IFC-SPF file (no 'ISO-10303-21;' header)")
    m = _SCHEMA_RE.search(head)
    if not m:
        raise IfcLoadError(f"{path}: header names no FILE_SCHEMA")
    schema = m.group(1).decode("ascii", "replace").upper()
    if not any(schema == s or schema.startswith(s + "_") for s in SUPPORTED_SCHEMAS):
        raise IfcLoadError(f"{path}: unknown IFC schema {schema!r} (supported: {', '.join(SUPPORTED_SCHEMAS)})")
    if b"END-ISO-10303-21;" not in tail:
        raise IfcLoadError(f"{path}: truncated IFC file (no 'END-ISO-10303-21;' at the end)")


def open_ifc(path: str | Path) -> tuple[ifcopenshell.file, list[str]]:
    """Open one IFC file with ifcopenshell after sanity checks: (file, warnings).

    Raises IfcLoadError for missing, empty, non-IFC, truncated, unknown-schema or malformed files.
    """
    p = Path(path)
    if not p.is_file():
        raise IfcLoadError(f"{p}: no such IFC file")
    if p.suffix.lower() == ".ifc":
        _check_spf(p)
    log_before = _ifc_log()
    try:
        f = ifcopenshell.open(str(p))
    except Exception as exc:  # ifcopenshell raises several error types for corrupt files
        raise IfcLoadError(f"{p}: cannot parse IFC: {type(exc).__name__}: {exc}") from exc
    # The parser is lenient: it logs malformed entities and carries on with blanks. Refuse those.
    log_after = _ifc_log()
    new_log = log_after[len(log_before) :] if log_after.startswith(log_before) else log_after
    messages = [ln.split("] ", 2)[-1] for ln in new_log.splitlines() if ln.startswith("[error]")]
    # Dangling references are a common exporter quirk (the referring attribute stays empty);
    # anything else means entities were mangled.
    dangling = [m for m in messages if "not found" in m]
    malformed = [m for m in messages if "not found" not in m]
    if malformed:
        raise IfcLoadError(f"{p}: cannot parse IFC: {len(malformed)} malformed entit(ies), first: {malformed[0][:200]}")
    if f.schema not in SUPPORTED_SCHEMAS:
        raise IfcLoadError(f"{p}: unsupported IFC schema {f.schema!r} (supported: {', '.join(SUPPORTED_SCHEMAS)})")
    return f, [f"{p.name}: {len(dangling)} dangling reference(s), e.g. {dangling[0][:160]}"] if dangling else []


def _ifc_log() -> str:
    try:
        return str(ifcopenshell.ifcopenshell_wrapper.get_log())
    except Exception:  # older/newer wrappers without a log accessor
        return ""


def _excluded_instances(f: ifcopenshell.file) -> list[ifcopenshell.entity_instance]:
    out: list[ifcopenshell.entity_instance] = []
    for cls in EXCLUDED_CLASSES:
        try:
            out.extend(f.by_type(cls))
        except RuntimeError:  # class not in this schema
            pass
    return out


RGBA = tuple[int, int, int, int]


def _dominant_rgba(geometry: object) -> RGBA | None:
    """0-255 RGBA of the surface style covering most faces of one iterator shape, if any."""
    try:
        materials = geometry.materials  # type: ignore[attr-defined]
        if not materials:
            return None
        ids = np.asarray(geometry.material_ids, dtype=np.int64)  # type: ignore[attr-defined]
        best = int(np.bincount(ids[ids >= 0]).argmax()) if (ids >= 0).any() else 0
        mat = materials[best]
        r, g, b = (float(c) for c in mat.diffuse.components)
        transparency = float(mat.transparency or 0.0)
    except (AttributeError, IndexError, TypeError, ValueError):  # styles the wrapper cannot express
        return None
    if not all(math.isfinite(c) for c in (r, g, b)):
        return None  # a style without a colour
    alpha = 1.0 - transparency if math.isfinite(transparency) else 1.0
    to8 = [int(round(min(max(c, 0.0), 1.0) * 255)) for c in (r, g, b, alpha)]
    return (to8[0], to8[1], to8[2], to8[3])


def iterate_geometry(
    f: ifcopenshell.file, threads: int | None = None
) -> dict[int, tuple[np.ndarray, np.ndarray, RGBA | None]]:
    """World-coordinate triangle meshes in metres with their main surface colour:
    ``{step id: (vertices (N,3) f64, faces (M,3) i32, rgba or None)}`` in step-id order.

    Elements whose geometry ifcopenshell cannot build are skipped by the iterator.
    """
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    n_threads = max(1, threads if threads is not None else min(os.cpu_count() or 1, 8))
    excluded = _excluded_instances(f)
    if excluded:
        it = ifcopenshell.geom.iterator(settings, f, n_threads, exclude=excluded)
    else:
        it = ifcopenshell.geom.iterator(settings, f, n_threads)
    out: dict[int, tuple[np.ndarray, np.ndarray, RGBA | None]] = {}
    if it.initialize():
        while True:
            shape = it.get()
            verts = np.asarray(shape.geometry.verts, dtype=np.float64).reshape(-1, 3)
            faces = np.asarray(shape.geometry.faces, dtype=np.int32).reshape(-1, 3)
            if len(faces):
                out[shape.id] = (verts, faces, _dominant_rgba(shape.geometry))
            if not it.next():
                break
    return dict(sorted(out.items()))  # the file's order, whatever order the threads finished in


def _body_products(f: ifcopenshell.file) -> set[int]:
    """Step ids of non-excluded products that have a representation named 'Body'."""
    excluded = {e.id() for e in _excluded_instances(f)}
    out = set()
    for p in f.by_type("IfcProduct"):
        if p.id() in excluded or p.Representation is None:
            continue
        if any(r.RepresentationIdentifier == "Body" for r in p.Representation.Representations or ()):
            out.add(p.id())
    return out


def _material_name(element: ifcopenshell.entity_instance) -> str:
    try:
        mat = ue.get_material(element, should_skip_usage=True)
    except Exception:  # malformed material associations: treat as no material
        return ""
    if mat is None:
        return ""
    if mat.is_a("IfcMaterial"):
        return mat.Name or ""
    if mat.is_a("IfcMaterialLayerSet"):
        if getattr(mat, "LayerSetName", None):
            return mat.LayerSetName
        names = [ly.Material.Name for ly in mat.MaterialLayers or () if ly.Material is not None]
    elif mat.is_a("IfcMaterialList"):
        names = [m.Name for m in mat.Materials or ()]
    elif mat.is_a("IfcMaterialProfileSet") or mat.is_a("IfcMaterialConstituentSet"):
        if getattr(mat, "Name", None):
            return mat.Name
        parts = getattr(mat, "MaterialProfiles", None) or getattr(mat, "MaterialConstituents", None) or ()
        names = [p.Material.Name for p in parts if p.Material is not None]
    else:
        names = [getattr(mat, "Name", "") or ""]
    return " / ".join(dict.fromkeys(n for n in names if n))


def _storey_name(element: ifcopenshell.entity_instance) -> str:
    node = ue.get_container(element)
    while node is not None and not node.is_a("IfcBuildingStorey"):
        if node.is_a("IfcBuilding") or node.is_a("IfcSite") or node.is_a("IfcProject"):
            return ""
        node = ue.get_aggregate(node) or ue.get_container(node)
    return (node.Name or node.LongName or node.GlobalId) if node is not None else ""


def _type_name(element: ifcopenshell.entity_instance) -> str:
    t = ue.get_type(element)
    return (t.Name or "") if t is not None else ""


def _dms(value: Sequence[int] | None) -> float | None:
    if not value:
        return None
    parts = list(value) + [0] * (4 - len(value))
    d, m, s, us = (int(x) for x in parts[:4])
    return d + m / 60.0 + s / 3600.0 + us / 3.6e9


def _site_gps(f: ifcopenshell.file, unit_scale: float) -> GeoPoint | None:
    for site in f.by_type("IfcSite"):
        lat, lon = _dms(site.RefLatitude), _dms(site.RefLongitude)
        if lat is None or lon is None or (lat == 0.0 and lon == 0.0):
            continue
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            continue
        alt = float(site.RefElevation) * unit_scale if site.RefElevation is not None else None
        return GeoPoint(lat_deg=lat, lon_deg=lon, alt_m=alt)
    return None


def _map_conversion(f: ifcopenshell.file) -> MapConversion | None:
    if f.schema == "IFC2X3":
        return None
    convs = f.by_type("IfcMapConversion")
    if not convs:
        return None
    c = convs[0]
    crs = c.TargetCRS
    return MapConversion(
        eastings=float(c.Eastings or 0.0),
        northings=float(c.Northings or 0.0),
        orthogonal_height=float(c.OrthogonalHeight or 0.0),
        x_axis=(
            float(c.XAxisAbscissa) if c.XAxisAbscissa is not None else 1.0,
            float(c.XAxisOrdinate) if c.XAxisOrdinate is not None else 0.0,
        ),
        scale=float(c.Scale) if c.Scale is not None else 1.0,
        crs_name=(crs.Name or "") if crs is not None else "",
        crs_description=(getattr(crs, "Description", None) or "") if crs is not None else "",
    )


def _parts(product: ifcopenshell.entity_instance) -> set[ifcopenshell.entity_instance]:
    """What a product stands for in a schedule: itself, its aggregated parts and, for spatial
    structure, the elements it contains, recursively (openings and their fillings excluded:
    a door hosted by a wall belongs to its own storey and task)."""
    out: set[ifcopenshell.entity_instance] = set()
    stack = [product]
    while stack:
        x = stack.pop()
        if x in out:
            continue
        out.add(x)
        for rel in getattr(x, "ContainsElements", None) or ():
            stack.extend(rel.RelatedElements)
        for rel in getattr(x, "IsDecomposedBy", None) or ():
            stack.extend(rel.RelatedObjects)
    return out


def auto_origin_offset(lo: np.ndarray, hi: np.ndarray) -> tuple[float, float, float]:
    """Offset to subtract from world coordinates: zero for models near the origin, else the
    bounding-box centre snapped to a 1 km grid (per axis that is far away)."""
    centre = (lo + hi) / 2.0
    out = []
    for c, a, b in zip(centre, lo, hi, strict=True):
        far = max(abs(a), abs(b)) > LARGE_COORDINATE_M
        out.append(float(math.floor(c / OFFSET_GRID_M) * OFFSET_GRID_M) if far else 0.0)
    return (out[0], out[1], out[2])


def load_site_model(
    paths: Sequence[str | Path],
    tz: str = "UTC",
    schedule_path: str | Path | None = None,
    threads: int | None = None,
    origin_offset_m: tuple[float, float, float] | None = None,
    on_missing: str = "error",
    progress: Callable[[str], None] | None = None,
) -> SiteModel:
    """Load one or several IFC files (plus optionally a schedule file) into one SiteModel.

    ``tz``: IANA zone for schedule dates without offsets. ``origin_offset_m``: subtract this
    instead of the automatic offset (keep a site's offset stable across revisions).
    ``on_missing``: what to do with schedule references to elements not in the model.
    Raises IfcLoadError / ScheduleError with one clear line.
    """
    if not paths:
        raise IfcLoadError("no IFC files given")
    zi = zone(tz)
    elements: dict[str, BimElement] = {}
    world_meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    colors: dict[str, RGBA] = {}
    warnings: list[str] = []
    files: list[tuple[ifcopenshell.file, Path]] = []
    map_conv: MapConversion | None = None
    gps: GeoPoint | None = None
    schemas: list[str] = []
    for path in paths:
        p = Path(path)
        if progress is not None:
            progress(str(p))
        f, open_warnings = open_ifc(p)
        warnings.extend(open_warnings)
        schemas.append(f.schema)
        unit_scale = float(uu.calculate_unit_scale(f))
        meshes = iterate_geometry(f, threads)
        if not meshes:
            raise IfcLoadError(f"{p}: contains no elements with 3D geometry")
        failed = _body_products(f) - set(meshes)
        if failed:
            names = ", ".join(f"{f.by_id(i).is_a()} {f.by_id(i).GlobalId}" for i in sorted(failed)[:3])
            warnings.append(f"{p.name}: {len(failed)} element(s) with a Body representation gave no geometry ({names})")
        for step_id, (verts, faces, rgba) in meshes.items():
            el = f.by_id(step_id)
            gid = el.GlobalId
            if gid in elements:
                warnings.append(f"{p.name}: GlobalId {gid} ({el.is_a()}) already loaded from another file; kept first")
                continue
            elements[gid] = BimElement(
                global_id=gid,
                ifc_class=el.is_a(),
                name=el.Name or "",
                storey=_storey_name(el),
                type_name=_type_name(el),
                material=_material_name(el),
                geometry_ref=gid,
            )
            world_meshes[gid] = (verts, faces)
            if rgba is not None:
                colors[gid] = rgba
        files.append((f, p))
        map_conv = map_conv or _map_conversion(f)
        gps = gps or _site_gps(f, unit_scale)

    lo = np.min([v.min(axis=0) for v, _ in world_meshes.values()], axis=0)
    hi = np.max([v.max(axis=0) for v, _ in world_meshes.values()], axis=0)
    offset = origin_offset_m if origin_offset_m is not None else auto_origin_offset(lo, hi)
    off = np.asarray(offset, dtype=np.float64)
    meshes_local: dict[str, ElementMesh] = {}
    for gid, (verts, faces) in world_meshes.items():
        v = verts - off
        meshes_local[gid] = ElementMesh(vertices_m=v, faces=faces, rgba=colors.get(gid))
        b_lo, b_hi = v.min(axis=0), v.max(axis=0)
        e = elements[gid]
        elements[gid] = msgspec.structs.replace(
            e,
            bbox_min_m=(float(b_lo[0]), float(b_lo[1]), float(b_lo[2])),
            bbox_max_m=(float(b_hi[0]), float(b_hi[1]), float(b_hi[2])),
        )

    # Schedules inside the IFC files.
    all_ids = set(elements)
    tasks: list[ScheduleTask] = []
    for f, p in files:

        def expand(product: ifcopenshell.entity_instance) -> set[str]:
            members = set(ue.get_types(product)) if product.is_a("IfcTypeObject") else _parts(product)
            return {m.GlobalId for m in members | {product} if hasattr(m, "GlobalId")} & all_ids

        tasks.extend(tasks_from_ifc(f, all_ids, zi, source=str(p), expand=expand))
    site = SiteModel(
        elements=elements,
        meshes=meshes_local,
        origin_offset_m=(float(off[0]), float(off[1]), float(off[2])),
        map_conversion=map_conv,
        gps=gps,
        tasks=resolve_elements(validate_tasks(tasks, "IFC schedules"), all_ids, "IFC schedule", on_missing),
        source_files=tuple(str(Path(p)) for p in paths),
        schemas=tuple(schemas),
        warnings=tuple(warnings),
        tz=tz,
    )
    if schedule_path is not None:
        site = site.with_tasks(load_schedule(schedule_path, tz, element_index(site), on_missing))
        validate_tasks(site.tasks, f"{schedule_path} + IFC schedule")
    return site


def element_index(site: SiteModel) -> dict[str, tuple[str, str]]:
    """GlobalId -> (ifc_class, storey), what schedule loaders need to resolve references."""
    return {gid: (e.ifc_class, e.storey) for gid, e in site.elements.items()}
