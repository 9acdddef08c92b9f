"""A large synthetic IFC4 model for scale tests: towers of a multi-storey frame (columns, beams, slabs, walls,
windows) as extruded rectangles, one construction task per storey, any element count.

Written with plain ``ifcopenshell`` entity creation (``ifcopenshell.api``, which the site generator in
:mod:`constructaide.synth.ifcwrite` uses, costs milliseconds per element: minutes for 50,000). Deterministic for a
seed: GlobalIds, sizes and dates. Site frame, metres, z up; every element is an axis-aligned box.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import uuid
from dataclasses import dataclass
from pathlib import Path

import ifcopenshell
import ifcopenshell.guid
import numpy as np

BAYS = 10
"""Bays per side of a storey's grid."""
BAY_M = 6.0
STOREYS_PER_TOWER = 24
TOWER_GAP_M = 30.0
MATERIALS = {
    "IfcColumn": "Concrete C30/37",
    "IfcBeam": "Concrete C30/37",
    "IfcSlab": "Concrete C30/37",
    "IfcWall": "Brick, red clay",
    "IfcWindow": "Glass, double glazing",
}


@dataclass(frozen=True)
class Box:
    """One element: ``ifc_class``, centre of its base ``(x, y, z)`` m and size ``(dx, dy, dz)`` m."""

    ifc_class: str
    base_m: tuple[float, float, float]
    size_m: tuple[float, float, float]


def storey_boxes(height_m: float) -> list[Box]:
    """The elements of one storey at z = 0: a BAYS x BAYS frame, slab, perimeter walls with one window each."""
    n, b = BAYS, BAY_M
    out: list[Box] = []
    for i in range(n + 1):
        for j in range(n + 1):
            out.append(Box("IfcColumn", (i * b, j * b, 0.0), (0.4, 0.4, height_m - 0.5)))
    for j in range(n + 1):
        for i in range(n):
            out.append(Box("IfcBeam", ((i + 0.5) * b, j * b, height_m - 0.5), (b - 0.4, 0.3, 0.5)))
    for i in range(n + 1):
        for j in range(n):
            out.append(Box("IfcBeam", (i * b, (j + 0.5) * b, height_m - 0.5), (0.3, b - 0.4, 0.5)))
    for i in range(n):
        for j in range(n):
            out.append(Box("IfcSlab", ((i + 0.5) * b, (j + 0.5) * b, height_m - 0.25), (b, b, 0.25)))
    edge = n * b
    for k in range(n):
        c = (k + 0.5) * b
        for x, y, horizontal in ((c, 0.0, True), (c, edge, True), (0.0, c, False), (edge, c, False)):
            wall = (b - 0.4, 0.2, height_m - 0.5) if horizontal else (0.2, b - 0.4, height_m - 0.5)
            win = (1.5, 0.3, 1.5) if horizontal else (0.3, 1.5, 1.5)
            out.append(Box("IfcWall", (x, y, 0.0), wall))
            out.append(Box("IfcWindow", (x, y, 0.9), win))
    return out


def elements_per_storey() -> int:
    return len(storey_boxes(3.0))


def _guid(seed: int, name: str) -> str:
    digest = hashlib.sha256(f"constructaide-bigmodel:{seed}:{name}".encode()).digest()[:16]
    return str(ifcopenshell.guid.compress(uuid.UUID(bytes=digest).hex))


def write_big_ifc(path: Path, elements: int = 50_000, seed: int = 0) -> dict[str, int]:
    """Write an IFC4 file of exactly ``elements`` products (storeys filled in order, towers of
    :data:`STOREYS_PER_TOWER` storeys side by side in x) with a work schedule of one task per storey.

    Returns counts: ``elements``, ``storeys``, ``towers``, ``tasks``.
    """
    if elements < 1:
        raise ValueError("elements must be >= 1")
    rng = np.random.default_rng(seed)
    per = elements_per_storey()
    n_storeys = -(-elements // per)
    n_towers = -(-n_storeys // STOREYS_PER_TOWER)
    f = ifcopenshell.file(schema="IFC4")

    def g(name: str) -> str:
        return _guid(seed, name)

    def point(x: float, y: float, z: float):  # noqa: ANN202
        return f.createIfcCartesianPoint((float(x), float(y), float(z)))

    origin = point(0, 0, 0)
    z_axis = f.createIfcDirection((0.0, 0.0, 1.0))
    x_axis = f.createIfcDirection((1.0, 0.0, 0.0))
    world = f.createIfcAxis2Placement3D(origin, z_axis, x_axis)
    ctx = f.createIfcGeometricRepresentationContext(None, "Model", 3, 1e-5, world, None)
    body = f.createIfcGeometricRepresentationSubContext(
        "Body", "Model", None, None, None, None, ctx, None, "MODEL_VIEW", None
    )
    units = f.createIfcUnitAssignment(
        [
            f.createIfcSIUnit(None, "LENGTHUNIT", None, "METRE"),
            f.createIfcSIUnit(None, "AREAUNIT", None, "SQUARE_METRE"),
            f.createIfcSIUnit(None, "VOLUMEUNIT", None, "CUBIC_METRE"),
        ]
    )
    project = f.create_entity(
        "IfcProject",
        GlobalId=g("project"),
        Name="ConstructAide big model",
        RepresentationContexts=[ctx],
        UnitsInContext=units,
    )
    site_pl = f.createIfcLocalPlacement(None, world)
    site = f.create_entity("IfcSite", GlobalId=g("site"), Name="Big site", ObjectPlacement=site_pl)
    site.RefLatitude = (51, 51, 36, 0)
    site.RefLongitude = (5, 51, 36, 0)
    site.RefElevation = 12.0
    f.create_entity("IfcRelAggregates", GlobalId=g("agg:project"), RelatingObject=project, RelatedObjects=[site])
    buildings = []
    for t in range(n_towers):
        loc = f.createIfcAxis2Placement3D(point(t * (BAYS * BAY_M + TOWER_GAP_M), 0, 0), None, None)
        pl = f.createIfcLocalPlacement(site_pl, loc)
        buildings.append(
            f.create_entity("IfcBuilding", GlobalId=g(f"bldg:{t}"), Name=f"Tower {t + 1}", ObjectPlacement=pl)
        )
    f.create_entity("IfcRelAggregates", GlobalId=g("agg:site"), RelatingObject=site, RelatedObjects=buildings)

    materials = {c: f.createIfcMaterial(m, None, None) for c, m in MATERIALS.items()}
    by_class: dict[str, list] = {c: [] for c in MATERIALS}
    profiles: dict[tuple[float, float], object] = {}
    ws = f.create_entity(
        "IfcWorkSchedule",
        GlobalId=g("ws"),
        Name="Construction schedule",
        CreationDate="2026-01-05T08:00:00",
        StartTime="2026-01-05T08:00:00",
        PredefinedType="PLANNED",
    )
    start = dt.datetime(2026, 1, 5, 8, 0)
    tasks = []
    remaining = elements
    storeys_of: dict[int, list] = {}
    count = 0
    for s in range(n_storeys):
        tower, level = divmod(s, STOREYS_PER_TOWER)
        height = 3.2 + 0.4 * float(rng.random())
        elevation = level * 3.6
        st_pl = f.createIfcLocalPlacement(
            buildings[tower].ObjectPlacement, f.createIfcAxis2Placement3D(point(0, 0, elevation), None, None)
        )
        storey = f.create_entity(
            "IfcBuildingStorey",
            GlobalId=g(f"storey:{s}"),
            Name=f"T{tower + 1} L{level:02d}",
            ObjectPlacement=st_pl,
            Elevation=elevation,
        )
        storeys_of.setdefault(tower, []).append(storey)
        products = []
        for k, box in enumerate(storey_boxes(height)[: min(per, remaining)]):
            key = (round(box.size_m[0], 3), round(box.size_m[1], 3))
            prof = profiles.get(key)
            if prof is None:
                prof = profiles[key] = f.createIfcRectangleProfileDef("AREA", None, None, key[0], key[1])
            pl = f.createIfcLocalPlacement(st_pl, f.createIfcAxis2Placement3D(point(*box.base_m), None, None))
            solid = f.createIfcExtrudedAreaSolid(prof, None, z_axis, float(box.size_m[2]))
            rep = f.createIfcShapeRepresentation(body, "Body", "SweptSolid", [solid])
            shape = f.createIfcProductDefinitionShape(None, None, [rep])
            el = f.create_entity(
                box.ifc_class,
                GlobalId=g(f"element:{s}:{k}"),
                Name=f"{box.ifc_class[3:]} {s}.{k}",
                ObjectPlacement=pl,
                Representation=shape,
            )
            products.append(el)
            by_class[box.ifc_class].append(el)
            count += 1
        remaining -= len(products)
        f.create_entity(
            "IfcRelContainedInSpatialStructure",
            GlobalId=g(f"contain:{s}"),
            RelatedElements=products,
            RelatingStructure=storey,
        )
        t0 = start + dt.timedelta(days=7 * s)
        tt = f.create_entity(
            "IfcTaskTime", ScheduleStart=t0.isoformat(), ScheduleFinish=(t0 + dt.timedelta(days=5, hours=9)).isoformat()
        )
        task = f.create_entity(
            "IfcTask",
            GlobalId=g(f"task:{s}"),
            Name=f"Build {storey.Name}",
            Identification=f"S{s:04d}",
            IsMilestone=False,
            TaskTime=tt,
            PredefinedType="CONSTRUCTION",
        )
        tasks.append(task)
        f.create_entity(
            "IfcRelAssignsToProcess", GlobalId=g(f"assign:{s}"), RelatedObjects=products, RelatingProcess=task
        )
    for tower, sts in storeys_of.items():
        f.create_entity(
            "IfcRelAggregates", GlobalId=g(f"agg:bldg:{tower}"), RelatingObject=buildings[tower], RelatedObjects=sts
        )
    f.create_entity("IfcRelAssignsToControl", GlobalId=g("control"), RelatedObjects=tasks, RelatingControl=ws)
    for c, ents in by_class.items():
        if ents:
            f.create_entity(
                "IfcRelAssociatesMaterial", GlobalId=g(f"mat:{c}"), RelatedObjects=ents, RelatingMaterial=materials[c]
            )
    f.header.file_name.time_stamp = "2026-01-01T00:00:00"
    f.header.file_name.name = path.name
    path.parent.mkdir(parents=True, exist_ok=True)
    f.write(str(path))
    return {"elements": count, "storeys": n_storeys, "towers": n_towers, "tasks": len(tasks)}
