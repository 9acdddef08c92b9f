"""Small seeded box scenes for the render tests (not a test module)."""

from __future__ import annotations

import numpy as np
import trimesh

from constructaide.bimgeom import meshes_to_glb
from constructaide.camera import centered_intrinsics, look_at
from schemas.messages import BimElement, BimModel, GeoPoint, ScheduleTask

DAY = 86_400 * 10**9
T0 = 1_773_050_400 * 10**9  # 2026-03-09 10:00 UTC
AT = T0 + 10 * DAY


def box(center, extents):
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(center)
    return np.asarray(b.vertices), np.asarray(b.faces)


def four_box_model() -> BimModel:
    """Four 2x2x3 m boxes in a row along x (standing on z = 0), one per progress status at ``AT``.

    A: ahead (actual finish 5 days before planned), B: on time, C: behind (due, not finished),
    D: finished on time but annotated ``needs_review`` in the tests. E: a future box (planned after AT)
    behind the row, F: a basement box fully below the ground at x = 0, y = 0.
    """
    meshes = {
        "A": box((0.0, 0.0, 1.5), (2, 2, 3)),
        "B": box((3.0, 0.0, 1.5), (2, 2, 3)),
        "C": box((6.0, 0.0, 1.5), (2, 2, 3)),
        "D": box((9.0, 0.0, 1.5), (2, 2, 3)),
        "E": box((4.5, 0.0, 4.5), (10, 2, 3)),
        "F": box((4.5, 0.0, -1.5), (10, 2, 2.8)),
    }
    classes = {"A": "IfcWall", "B": "IfcWall", "C": "IfcColumn", "D": "IfcColumn", "E": "IfcSlab", "F": "IfcFooting"}
    materials = {"A": "Brick red", "B": "Brick", "C": "Concrete C30/37", "D": "Concrete", "E": "Concrete", "F": "x"}
    elements = tuple(
        BimElement(global_id=g, ifc_class=classes[g], material=materials[g], storey="L0", geometry_ref=g, name=g)
        for g in meshes
    )

    def task(tid, gid, pf, af, a_start=True):
        return ScheduleTask(
            task_id=tid,
            name=tid,
            planned_start_ns=pf - 2 * DAY,
            planned_finish_ns=pf,
            actual_start_ns=min(pf - 2 * DAY, af if af is not None else pf) if a_start else None,  # never after af
            actual_finish_ns=af,
            element_ids=(gid,),
        )

    tasks = (
        task("tF", "F", T0, T0),
        task("tA", "A", AT - 1 * DAY, AT - 6 * DAY),
        task("tB", "B", AT - 2 * DAY, AT - 2 * DAY),
        task("tC", "C", AT - 3 * DAY, None),
        task("tD", "D", AT - 2 * DAY, AT - 2 * DAY),
        ScheduleTask(
            task_id="tE", name="tE", planned_start_ns=AT + DAY, planned_finish_ns=AT + 3 * DAY, element_ids=("E",)
        ),
    )
    return BimModel(
        site="t",
        revision="r1",
        elements=elements,
        tasks=tasks,
        geometry_glb=meshes_to_glb(meshes),
        gps=GeoPoint(lat_deg=51.8583, lon_deg=5.8647),
        terrain_height_m=0.0,
    )


def camera(width=480, height=320, k1=-0.08, k2=0.015):
    """Intrinsics with distortion and a camera south of the row looking north, slightly down."""
    intr = centered_intrinsics(width, height, 0.75 * width, k1, k2)
    return intr, look_at((4.5, -16.0, 3.0), (4.5, 0.0, 1.0))
