"""Write the building and its schedule as an IFC4 file with ifcopenshell.api (deterministic GlobalIds)."""

from __future__ import annotations

import hashlib
import uuid
from pathlib import Path

import ifcopenshell
import ifcopenshell.api.aggregate
import ifcopenshell.api.context
import ifcopenshell.api.geometry
import ifcopenshell.api.material
import ifcopenshell.api.project
import ifcopenshell.api.root
import ifcopenshell.api.sequence
import ifcopenshell.api.spatial
import ifcopenshell.api.type
import ifcopenshell.api.unit
import ifcopenshell.guid
import numpy as np

from .building import Building
from .config import ALT_M, LAT_DEG, LON_DEG, SITE_NAME
from .schedule import Schedule, hours_to_datetime

MATERIALS: dict[str, tuple[str, str]] = {
    "concrete": ("Concrete C30/37", "concrete"),
    "brick": ("Brick, red clay", "brick"),
    "glass": ("Glass, double glazing", "glass"),
    "steel": ("Steel S355", "steel"),
    "roof": ("Timber with clay tiles", "wood"),
}


def _compound_angle(deg: float) -> list[int]:
    """IfcCompoundPlaneAngleMeasure: degrees, minutes, seconds, millionths of a second (same sign)."""
    sign = -1 if deg < 0 else 1
    micro = int(round(abs(deg) * 3600e6))
    d, rest = divmod(micro, 3600 * 10**6)
    m, rest = divmod(rest, 60 * 10**6)
    s, us = divmod(rest, 10**6)
    return [sign * d, sign * m, sign * s, sign * us]


def _guid(seed: int, name: str) -> str:
    digest = hashlib.sha256(f"constructaide-synth:{seed}:{name}".encode()).digest()[:16]
    return ifcopenshell.guid.compress(uuid.UUID(bytes=digest).hex)


def _local_iso(h: float) -> str:
    """IfcDateTime (local time, no offset) of working hour ``h``."""
    return hours_to_datetime(h).replace(tzinfo=None).isoformat(timespec="seconds")


def write_ifc(building: Building, schedule: Schedule, path: Path, seed: int) -> dict[str, str]:
    """Write ``path`` and return ``{Element.key: GlobalId}``. Placements are absolute: world = site frame, m."""
    f = ifcopenshell.api.project.create_file(version="IFC4")
    project = ifcopenshell.api.root.create_entity(f, ifc_class="IfcProject", name="ConstructAide synthetic site")
    metre = ifcopenshell.api.unit.add_si_unit(f, unit_type="LENGTHUNIT")
    area = ifcopenshell.api.unit.add_si_unit(f, unit_type="AREAUNIT")
    volume = ifcopenshell.api.unit.add_si_unit(f, unit_type="VOLUMEUNIT")
    ifcopenshell.api.unit.assign_unit(f, units=[metre, area, volume])
    model = ifcopenshell.api.context.add_context(f, context_type="Model")
    body = ifcopenshell.api.context.add_context(
        f, context_type="Model", context_identifier="Body", target_view="MODEL_VIEW", parent=model
    )
    site = ifcopenshell.api.root.create_entity(f, ifc_class="IfcSite", name=SITE_NAME)
    site.RefLatitude = _compound_angle(LAT_DEG)
    site.RefLongitude = _compound_angle(LON_DEG)
    site.RefElevation = ALT_M
    bldg = ifcopenshell.api.root.create_entity(f, ifc_class="IfcBuilding", name="Building A")
    ifcopenshell.api.aggregate.assign_object(f, products=[site], relating_object=project)
    ifcopenshell.api.aggregate.assign_object(f, products=[bldg], relating_object=site)
    ifcopenshell.api.geometry.edit_object_placement(f, product=site, matrix=np.eye(4))
    ifcopenshell.api.geometry.edit_object_placement(f, product=bldg, matrix=np.eye(4))
    storeys = {}
    for st in building.storeys:
        ent = ifcopenshell.api.root.create_entity(f, ifc_class="IfcBuildingStorey", name=st.name)
        ent.Elevation = st.elevation_m
        ifcopenshell.api.aggregate.assign_object(f, products=[ent], relating_object=bldg)
        m = np.eye(4)
        m[2, 3] = st.elevation_m
        ifcopenshell.api.geometry.edit_object_placement(f, product=ent, matrix=m)
        storeys[st.index] = ent

    materials = {k: ifcopenshell.api.material.add_material(f, name=n, category=c) for k, (n, c) in MATERIALS.items()}
    types: dict[tuple[str, str], object] = {}
    by_material: dict[str, list] = {k: [] for k in MATERIALS}
    by_type: dict[tuple[str, str], list] = {}
    by_storey: dict[int, list] = {}
    products: dict[str, object] = {}
    for e in building.elements:
        ent = ifcopenshell.api.root.create_entity(
            f, ifc_class=e.ifc_class, predefined_type=e.predefined_type, name=e.key
        )
        ent.Tag = e.key
        by_material[e.material].append(ent)
        by_type.setdefault((e.ifc_class + "Type", e.type_name), []).append(ent)
        by_storey.setdefault(e.storey, []).append(ent)
        products[e.key] = ent
    # Contain before placing: assign_container re-bases existing placements in set order (non-deterministic ids).
    for idx in sorted(by_storey):
        ifcopenshell.api.spatial.assign_container(f, products=by_storey[idx], relating_structure=storeys[idx])
    for e in building.elements:
        ent = products[e.key]
        origin = e.vertices_m.min(0)
        placement = np.eye(4)
        placement[:3, 3] = origin
        ifcopenshell.api.geometry.edit_object_placement(f, product=ent, matrix=placement)
        rep = ifcopenshell.api.geometry.add_mesh_representation(
            f, context=body, vertices=[(e.vertices_m - origin).tolist()], faces=[e.polygons]
        )
        ifcopenshell.api.geometry.assign_representation(f, product=ent, representation=rep)
    for (type_class, type_name), ents in by_type.items():
        predefined = {"IfcFootingType": "PAD_FOOTING", "IfcRoofType": "GABLE_ROOF", "IfcWindowType": "WINDOW"}.get(
            type_class, "NOTDEFINED"
        )
        t = ifcopenshell.api.root.create_entity(f, ifc_class=type_class, name=type_name, predefined_type=predefined)
        types[(type_class, type_name)] = t
        ifcopenshell.api.type.assign_type(f, related_objects=ents, relating_type=t)
    for k, ents in by_material.items():
        if ents:
            ifcopenshell.api.material.assign_material(f, products=ents, type="IfcMaterial", material=materials[k])

    # Schedule: one work schedule, a construction task per building step, a sub-task per element.
    first = min(t.start_h for t in schedule.tasks)
    ws = ifcopenshell.api.sequence.add_work_schedule(f, name="Construction schedule", predefined_type="PLANNED")
    ws.CreationDate = _local_iso(first)
    ws.StartTime = _local_iso(first)
    task_ents = {}
    task_times = {}
    for t in schedule.tasks:
        te = ifcopenshell.api.sequence.add_task(
            f, work_schedule=ws, name=t.name, identification=t.identification, predefined_type="CONSTRUCTION"
        )
        tt = ifcopenshell.api.sequence.add_task_time(f, task=te)
        ifcopenshell.api.sequence.edit_task_time(
            f,
            task_time=tt,
            attributes={"ScheduleStart": _local_iso(t.start_h), "ScheduleFinish": _local_iso(t.finish_h)},
        )
        task_times[t.key] = tt
        task_ents[t.key] = te
    for t in schedule.tasks:
        if t.predecessor is not None:
            ifcopenshell.api.sequence.assign_sequence(
                f, relating_process=task_ents[t.predecessor], related_process=task_ents[t.key]
            )
    # edit_task_time and assign_sequence snap and cascade dates onto 09:00-17:00 working days; the
    # synthetic schedule is exact to the minute, so its times are written last, directly.
    for t in schedule.tasks:
        task_times[t.key].ScheduleStart = _local_iso(t.start_h)
        task_times[t.key].ScheduleFinish = _local_iso(t.finish_h)
    # Each element has its own planned slot inside its task (the plan the truth's deviations are measured
    # against): a sub-task nested in the task (IfcRelNests), the element its output, as 4D tools export an
    # element-level sequence.
    by_task: dict[str, list] = {}
    for e in building.elements:
        by_task.setdefault(e.task, []).append(e)
    for t in schedule.tasks:
        for i, e in enumerate(
            sorted(by_task.get(t.key, ()), key=lambda e: (schedule.windows[e.key].planned_start_h, e.key))
        ):
            w = schedule.windows[e.key]
            sub = ifcopenshell.api.sequence.add_task(
                f,
                parent_task=task_ents[t.key],
                name=f"{t.name}: {e.key}",
                identification=f"{t.identification}.{i + 1:03d}",
                predefined_type="CONSTRUCTION",
            )
            stt = ifcopenshell.api.sequence.add_task_time(f, task=sub)
            stt.ScheduleStart = _local_iso(w.planned_start_h)
            stt.ScheduleFinish = _local_iso(w.planned_finish_h)
            ifcopenshell.api.sequence.assign_product(f, relating_product=products[e.key], related_object=sub)

    # Deterministic GlobalIds (ifcopenshell assigns random ones) in creation order; elements keyed by name.
    for ent in f.by_type("IfcRoot"):
        ent.GlobalId = _guid(seed, f"{ent.is_a()}#{ent.id()}")
    guids = {}
    for key, ent in products.items():
        ent.GlobalId = _guid(seed, f"element:{key}")
        guids[key] = ent.GlobalId
    # ifcopenshell.api fills unordered collections from Python sets; sort them by step id for stable bytes.
    for ent in list(f.by_type("IfcRelationship")) + list(f.by_type("IfcUnitAssignment")):
        for i in range(len(ent)):
            val = ent[i]
            if isinstance(val, tuple) and val and all(isinstance(x, ifcopenshell.entity_instance) for x in val):
                ent[i] = sorted(val, key=lambda x: x.id())
    f.header.file_name.time_stamp = "2026-01-01T00:00:00"
    f.header.file_name.name = path.name
    path.parent.mkdir(parents=True, exist_ok=True)
    f.write(str(path))
    return guids
