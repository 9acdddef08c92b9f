"""Ingest BIM core: IFC loading on real models, 4D schedule from IFC, bad IFC input, revisions, GLB."""

from __future__ import annotations

import datetime as dt
import glob
import io
from pathlib import Path

import numpy as np
import pytest
import trimesh

from constructaide.bim.ifc import IfcLoadError, load_site_model
from constructaide.bimgeom import glb_to_meshes, load_bim_model_glb
from nodes.ingest.revisions import diff_models, to_bim_model

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
IFC_DIR = DATA / "ifc"
PARTS = sorted(glob.glob(str(DATA / "schependomlaan" / "design-parts" / "*.ifc")))
BSI = IFC_DIR / "bsi_construction-scheduling-task.ifc"
needs_data = pytest.mark.skipif(not IFC_DIR.is_dir(), reason=f"real IFC data not present at {IFC_DIR}")

EXCLUDED = (
    "IfcSpatialStructureElement",
    "IfcFeatureElementSubtraction",
    "IfcAnnotation",
    "IfcGrid",
    "IfcVirtualElement",
)
NON_BODY_TYPES = ("Curve2D", "GeometricCurveSet", "Annotation2D", "BoundingBox")


def independent_geometry_products(path: Path) -> set[str]:
    """GlobalIds of physical products with a body representation, counted straight from the
    IFC entities (no geometry iterator): what the loader must deliver."""
    import ifcopenshell

    f = ifcopenshell.open(str(path))
    out = set()
    for p in f.by_type("IfcProduct"):
        if any(p.is_a(c) for c in EXCLUDED) or (f.schema != "IFC2X3" and p.is_a("IfcSpatialElement")):
            continue
        if p.Representation is None:
            continue
        for r in p.Representation.Representations:
            if (r.RepresentationIdentifier or "") in ("Body", "Facetation", "") and (
                r.RepresentationType or ""
            ) not in NON_BODY_TYPES:
                out.add(p.GlobalId)
                break
    return out


def utc_ns(*args: int) -> int:
    return int(dt.datetime(*args, tzinfo=dt.UTC).timestamp() * 1e9)


@pytest.fixture(scope="module")
def models() -> dict[str, object]:
    """Each real model loaded once for the whole module."""
    if not IFC_DIR.is_dir():
        pytest.skip(f"real IFC data not present at {IFC_DIR}")
    return {p.name: load_site_model([p], tz="UTC") for p in sorted(IFC_DIR.glob("*.ifc"))}


@needs_data
def test_element_counts_match_ifcopenshell(models: dict) -> None:
    assert len(models) >= 5
    for name, site in models.items():
        expected = independent_geometry_products(IFC_DIR / name)
        assert set(site.elements) == expected, name
        assert len(site.meshes) == len(site.elements)
        for gid, mesh in site.meshes.items():
            assert mesh.vertices_m.dtype == np.float64 and mesh.vertices_m.shape[1] == 3
            assert mesh.faces.shape[1] == 3 and mesh.faces.max() < len(mesh.vertices_m), (name, gid)


@needs_data
def test_metadata_units_and_grouping(models: dict) -> None:
    haus = models["AC20-FZK-Haus.ifc"]
    lo, hi = haus.bbox_m()
    size = hi - lo
    # The FZK-Haus is a 2-storey house of about 13 x 11 m footprint (metres, not mm).
    assert 10.0 < size[0] < 20.0 and 8.0 < size[1] < 20.0 and 5.0 < size[2] < 10.0
    assert set(haus.by_storey) == {"Erdgeschoss", "Dachgeschoss"}
    assert haus.by_class["IfcWindow"] and haus.by_class["IfcWallStandardCase"]
    assert sum(len(v) for v in haus.by_material.values()) == len(haus.elements)
    assert any(m for m in haus.by_material if m)
    assert any(t for t in haus.by_type if t)
    assert haus.warnings == ()
    # IFC surface styles become mesh colours in the GLB (the FZK-Haus styles every element).
    assert all(m.rgba is not None for m in haus.meshes.values())
    assert len({m.rgba for m in haus.meshes.values()}) >= 5
    glb = to_bim_model(haus, "t", "r").geometry_glb
    scene = trimesh.load(io.BytesIO(glb), file_type="glb", force="scene")
    assert all(g.visual.kind is not None for g in scene.geometry.values())
    # webifc_example.ifc has dangling references: tolerated, reported.
    assert any("dangling reference" in w for w in models["webifc_example.ifc"].warnings)
    assert haus.gps is not None and abs(haus.gps.lat_deg - 49.1) < 0.01 and abs(haus.gps.lon_deg - 8.44) < 0.01
    # IfcOpenHouse is in millimetres: converted it is a house of a few metres.
    house = models["webifc_IfcOpenHouse_IFC4.ifc"]
    lo, hi = house.bbox_m()
    assert 5.0 < (hi - lo)[0] < 20.0
    for el in haus.elements.values():
        assert el.geometry_ref == el.global_id
        assert all(a <= b for a, b in zip(el.bbox_min_m, el.bbox_max_m, strict=True))


@needs_data
def test_bsi_4d_example_tasks_and_states(models: dict) -> None:
    site = models["bsi_construction-scheduling-task.ifc"]
    assert len(site.tasks) == 8
    by_name = {t.name: t for t in site.tasks}
    expected = {
        "Ground Level": ((2010, 9, 20, 8), (2010, 9, 24, 16)),
        "Slab #1": ((2010, 9, 20, 8), (2010, 9, 20, 16)),
        "Wall #1": ((2010, 9, 21, 8), (2010, 9, 21, 16)),
        "Wall #2": ((2010, 9, 22, 8), (2010, 9, 22, 16)),
        "Wall #3": ((2010, 9, 23, 8), (2010, 9, 23, 16)),
        "Wall #4": ((2010, 9, 24, 8), (2010, 9, 24, 16)),
        "Wall (Standard)": ((2010, 9, 21, 8), (2010, 9, 24, 16)),
        "Slab (Standard)": ((2010, 9, 20, 8), (2010, 9, 20, 16)),
    }
    assert set(by_name) == set(expected)
    for name, (start, finish) in expected.items():
        assert by_name[name].planned_start_ns == utc_ns(*start), name
        assert by_name[name].planned_finish_ns == utc_ns(*finish), name
    # Each leaf task builds the element of the same name (assigned by IfcRelAssignsToProduct).
    names = {gid: e.name for gid, e in site.elements.items()}
    for leaf in ("Slab #1", "Wall #1", "Wall #2", "Wall #3", "Wall #4"):
        assert [names[g] for g in by_name[leaf].element_ids] == [leaf]
    # IfcRelSequence: walls follow the slab and each other.
    assert by_name["Slab #1"].task_id in by_name["Wall #1"].predecessor_ids
    assert by_name["Wall #3"].task_id in by_name["Wall #4"].predecessor_ids
    sum_seq = sum(len(t.predecessor_ids) for t in site.tasks)
    assert sum_seq == 7
    gid = {e.name: g for g, e in site.elements.items()}
    t = utc_ns(2010, 9, 22, 12)
    assert site.planned_state(gid["Slab #1"], t) == "complete"
    assert site.planned_state(gid["Wall #1"], t) == "complete"
    assert site.planned_state(gid["Wall #2"], t) == "under_construction"
    assert site.planned_state(gid["Wall #3"], t) == "not_started"
    assert site.planned_state(gid["Wall #4"], t) == "not_started"
    assert set(site.planned_states(utc_ns(2010, 9, 19)).values()) == {"not_started"}
    assert set(site.planned_states(utc_ns(2010, 9, 25)).values()) == {"complete"}
    assert site.actual_state(gid["Wall #2"], t) is None
    assert site.schedule_status(gid["Wall #2"], t) == "unknown"


@needs_data
@pytest.mark.skipif(not PARTS, reason="Schependomlaan design parts not present")
def test_schependomlaan_parts_make_one_site_model() -> None:
    site = load_site_model(PARTS, tz="Europe/Amsterdam")
    expected: set[str] = set()
    for p in PARTS:
        expected |= independent_geometry_products(Path(p))
    assert set(site.elements) == expected
    assert len(site.source_files) == len(PARTS) == 7
    # The parts share one storey structure and one reference proxy (reported, kept once).
    assert {"00 begane grond", "01 eerste verdieping", "04 dak"} <= set(site.by_storey)
    assert any("already loaded" in w for w in site.warnings)
    assert {"IfcSlab", "IfcBeam", "IfcWallStandardCase", "IfcColumn", "IfcStair"} <= set(site.by_class)
    lo, hi = site.bbox_m()
    assert np.all(hi - lo < 100.0) and np.all(hi - lo > 5.0)


# ---------------------------------------------------------------------------- synthetic IFC


def build_ifc(path: Path, walls: list[tuple[str, tuple[float, float], float]], map_conv: bool = True) -> list[str]:
    """An IFC4 file in millimetres with walls placed at map coordinates (metres given)."""
    import ifcopenshell
    import ifcopenshell.api.aggregate
    import ifcopenshell.api.context
    import ifcopenshell.api.geometry
    import ifcopenshell.api.root
    import ifcopenshell.api.spatial
    import ifcopenshell.api.unit

    api = ifcopenshell.api
    f = ifcopenshell.file(schema="IFC4")
    proj = api.root.create_entity(f, ifc_class="IfcProject", name="synthetic")
    api.unit.assign_unit(f, length={"is_metric": True, "raw": "MILLIMETERS"})
    model = api.context.add_context(f, context_type="Model")
    body = api.context.add_context(
        f, context_type="Model", context_identifier="Body", target_view="MODEL_VIEW", parent=model
    )
    site = api.root.create_entity(f, ifc_class="IfcSite", name="Site")
    bldg = api.root.create_entity(f, ifc_class="IfcBuilding", name="B")
    storey = api.root.create_entity(f, ifc_class="IfcBuildingStorey", name="Level 0")
    api.aggregate.assign_object(f, products=[site], relating_object=proj)
    api.aggregate.assign_object(f, products=[bldg], relating_object=site)
    api.aggregate.assign_object(f, products=[storey], relating_object=bldg)
    if map_conv:
        crs = f.createIfcProjectedCRS(Name="EPSG:28992", Description="Amersfoort / RD New")
        f.createIfcMapConversion(
            SourceCRS=model, TargetCRS=crs, Eastings=155000.0, Northings=463000.0, OrthogonalHeight=10.0,
            XAxisAbscissa=1.0, XAxisOrdinate=0.0, Scale=1.0,
        )  # fmt: skip
    out = []
    for name, (x, y), length in walls:
        w = api.root.create_entity(f, ifc_class="IfcWall", name=name)
        rep = api.geometry.add_wall_representation(f, context=body, length=length, height=3.0, thickness=0.2)
        api.geometry.assign_representation(f, product=w, representation=rep)
        m = np.eye(4)
        m[0, 3], m[1, 3] = x, y
        api.geometry.edit_object_placement(f, product=w, matrix=m)
        api.spatial.assign_container(f, products=[w], relating_structure=storey)
        out.append(w.GlobalId)
    f.write(str(path))
    return out


def test_map_coordinates_offset_and_crs(tmp_path: Path) -> None:
    path = tmp_path / "map.ifc"
    gids = build_ifc(path, [("W1", (155010.0, 463020.0), 5.0), ("W2", (155020.5, 463020.0), 4.0)])
    site = load_site_model([path])
    assert site.origin_offset_m == (155000.0, 463000.0, 0.0)
    assert site.map_conversion is not None and site.map_conversion.crs_name == "EPSG:28992"
    assert site.map_conversion.eastings == 155000.0
    w1, w2 = site.elements[gids[0]], site.elements[gids[1]]
    assert np.allclose(w1.bbox_min_m, (10.0, 20.0, 0.0), atol=1e-6)
    assert np.allclose(w1.bbox_max_m, (15.0, 20.2, 3.0), atol=1e-6)  # mm -> m
    assert np.allclose(w2.bbox_min_m, (20.5, 20.0, 0.0), atol=1e-6)
    assert w1.storey == "Level 0"
    bim = to_bim_model(site, "t", "r1")
    assert bim.crs_name == "EPSG:28992" and bim.origin_offset_m == site.origin_offset_m
    meshes = load_bim_model_glb(bim)
    assert set(meshes) == set(gids)
    v, f = meshes[gids[0]]
    assert np.allclose(v.min(axis=0), (10.0, 20.0, 0.0), atol=1e-4)  # z up, site-local
    assert f.shape[1] == 3 and len(f) == len(site.meshes[gids[0]].faces)


# ---------------------------------------------------------------------------- bad input


@needs_data
def test_bad_ifc_inputs_give_clear_errors(tmp_path: Path) -> None:
    text = BSI.read_text()
    truncated = tmp_path / "truncated.ifc"
    truncated.write_text(text[: len(text) // 2])
    with pytest.raises(IfcLoadError, match="truncated"):
        load_site_model([truncated])

    corrupt = tmp_path / "corrupt.ifc"
    corrupt.write_bytes(b"\x00\x01garbage" * 100)
    with pytest.raises(IfcLoadError, match="not an IFC"):
        load_site_model([corrupt])

    broken_body = tmp_path / "broken.ifc"
    broken_body.write_text(text.replace("#356= IFCWALL(", "#356= IFCWALL(((((", 1))
    with pytest.raises(IfcLoadError, match="cannot parse"):
        load_site_model([broken_body])

    unknown = tmp_path / "unknown.ifc"
    unknown.write_text(text.replace("FILE_SCHEMA(('IFC4X3_ADD2'))", "FILE_SCHEMA(('IFC9X9'))"))
    with pytest.raises(IfcLoadError, match="unknown IFC schema 'IFC9X9'"):
        load_site_model([unknown])

    # Only spatial structure, no element with geometry.
    import ifcopenshell
    import ifcopenshell.api.root

    f = ifcopenshell.file(schema="IFC4")
    ifcopenshell.api.root.create_entity(f, ifc_class="IfcProject", name="empty")
    ifcopenshell.api.root.create_entity(f, ifc_class="IfcWall", name="no geometry")
    empty = tmp_path / "empty.ifc"
    f.write(str(empty))
    with pytest.raises(IfcLoadError, match="no elements with 3D geometry"):
        load_site_model([empty])

    with pytest.raises(IfcLoadError, match="no such IFC file"):
        load_site_model([tmp_path / "missing.ifc"])


@needs_data
def test_ifc_cyclic_sequence_rejected(tmp_path: Path) -> None:
    from constructaide.bim.schedule import ScheduleError

    text = BSI.read_text()
    # Add Wall #4 -> Slab #1, closing the loop Slab #1 -> Wall #1 -> ... -> Wall #4 -> Slab #1.
    anchor = "#797= IFCRELASSIGNSTOCONTROL("
    extra = "#9999= IFCRELSEQUENCE('1cYcLeCyCLe0000000000a',#201,$,$,#690,#621,$,.FINISH_START.,$);\n"
    cyclic = text.replace(anchor, extra + anchor)
    assert cyclic != text
    path = tmp_path / "cyclic.ifc"
    path.write_text(cyclic)
    with pytest.raises(ScheduleError, match="cyclic task sequence"):
        load_site_model([path])


# ---------------------------------------------------------------------------- revisions


@needs_data
def test_revision_diff_added_removed_changed(tmp_path: Path) -> None:
    text = BSI.read_text()
    edited = text.replace("'Wall #2',$,$,#394", "'Wall #2 (moved)',$,$,#394", 1)  # attribute change
    edited = edited.replace(
        "#544= IFCEXTRUDEDAREASOLID(#543,#546,#547,120.);", "#544= IFCEXTRUDEDAREASOLID(#543,#546,#547,150.);"
    )  # noqa: E501
    assert edited.count("Wall #2 (moved)") == 1 and "#547,150.)" in edited
    v2 = tmp_path / "bsi_v2.ifc"
    v2.write_text(edited)
    house = IFC_DIR / "webifc_IfcOpenHouse_IFC4.ifc"
    old = load_site_model([BSI, house])
    new = load_site_model([v2])
    upd = diff_models(old, new, site="t", base_revision="a", revision="b")
    names = {e.name for e in upd.changed}
    assert names == {"Wall #1", "Wall #2 (moved)"}  # geometry (taller wall #1) and attribute
    assert len(upd.removed) == len(load_site_model([house]).elements) == 34
    assert upd.added == ()
    assert set(glb_to_meshes(upd.geometry_glb)) == {e.geometry_ref for e in upd.changed}
    assert upd.tasks is None  # same schedule
    back = diff_models(new, old, site="t", base_revision="b", revision="a")
    assert len(back.added) == 34 and back.removed == ()
    assert set(glb_to_meshes(back.geometry_glb)) == {e.geometry_ref for e in (*back.added, *back.changed)}
    same = diff_models(old, old, site="t", base_revision="a", revision="a")
    assert same.added == same.changed == same.removed == () and same.geometry_glb == b""


# ---------------------------------------------------------------------------- synthetic site IFC


def test_synthetic_site_ifc_elements_and_schedule(tmp_path: Path) -> None:
    try:
        from constructaide.synth.building import design_building
        from constructaide.synth.config import SIZES, TZ
        from constructaide.synth.ifcwrite import _local_iso, write_ifc
        from constructaide.synth.schedule import make_schedule
    except ImportError as exc:  # the synthetic site generator is optional for this test
        pytest.skip(f"synthetic site generator not available: {exc}")
    cfg = SIZES["tiny"]
    building = design_building(cfg)
    schedule = make_schedule(building, cfg.days, np.random.default_rng([0, 1]))
    guids = write_ifc(building, schedule, tmp_path / "building.ifc", 0)
    site = load_site_model([tmp_path / "building.ifc"], tz=TZ)
    assert set(site.elements) == set(guids.values())
    # A summary task per building step, a sub-task per element nested in it (the element's planned slot).
    assert len(site.tasks) == len(schedule.tasks) + len(building.elements)
    by_id = {t.task_id: t for t in site.tasks}
    summaries = [t for t in site.tasks if t.parent_id is None]
    assert len(summaries) == len(schedule.tasks) and all(not t.element_ids for t in summaries)
    # Dates as the IFC file states them (IfcTaskTime, local time of the site zone), read directly.
    from zoneinfo import ZoneInfo

    import ifcopenshell

    f = ifcopenshell.open(str(tmp_path / "building.ifc"))
    zi = ZoneInfo(TZ)

    def ns_of(text: str) -> int:
        return int(dt.datetime.fromisoformat(text).replace(tzinfo=zi).timestamp()) * 10**9

    ifc_window = {}
    for rel in f.by_type("IfcRelAssignsToProduct"):
        for task in rel.RelatedObjects:
            if task.is_a("IfcTask"):
                tt = task.TaskTime
                ifc_window[rel.RelatingProduct.GlobalId] = (ns_of(tt.ScheduleStart), ns_of(tt.ScheduleFinish))
    task_names = {t.key: t.name for t in schedule.tasks}
    for e in building.elements:
        gid = guids[e.key]
        el = site.elements[gid]
        assert el.ifc_class == e.ifc_class and el.name == e.key
        lo, hi = e.vertices_m.min(axis=0), e.vertices_m.max(axis=0)
        assert np.allclose(el.bbox_min_m, lo, atol=1e-4) and np.allclose(el.bbox_max_m, hi, atol=1e-4)
        (task,) = [t for t in site.tasks if gid in t.element_ids]
        assert task.element_ids == (gid,) and task.parent_id is not None
        assert by_id[task.parent_id].name == task_names[e.task]
        start_ns, finish_ns = ifc_window[gid]
        slot = schedule.windows[e.key]
        assert (start_ns, finish_ns) == (
            ns_of(_local_iso(slot.planned_start_h)),
            ns_of(_local_iso(slot.planned_finish_h)),
        )
        win = site.windows[gid]
        assert (win.build_start_ns, win.build_finish_ns) == (start_ns, finish_ns), e.key
        assert site.planned_state(gid, start_ns - 1) == "not_started"
        assert site.planned_state(gid, (start_ns + finish_ns) // 2) == "under_construction"
        assert site.planned_state(gid, finish_ns) == "complete"


@needs_data
def test_ifc2x3_schedule_time_control(tmp_path: Path) -> None:
    """IFC2X3 keeps task dates in IfcScheduleTimeControl (IfcRelAssignsTasks); products by
    IfcRelAssignsToProcess (task -> products) and a storey through IfcRelAssignsToProduct."""
    import ifcopenshell
    import ifcopenshell.guid

    src = IFC_DIR / "webifc_duplex.ifc"
    f = ifcopenshell.open(str(src))
    oh = f.by_type("IfcOwnerHistory")[0]

    def when(y: int, mo: int, d: int, h: int) -> object:
        return f.create_entity(
            "IfcDateAndTime",
            DateComponent=f.create_entity("IfcCalendarDate", DayComponent=d, MonthComponent=mo, YearComponent=y),
            TimeComponent=f.create_entity("IfcLocalTime", HourComponent=h, MinuteComponent=0, SecondComponent=0.0),
        )

    def task(name: str, start: object, finish: object, actual_finish: object | None = None) -> object:
        t = f.create_entity("IfcTask", GlobalId=ifcopenshell.guid.new(), OwnerHistory=oh, Name=name, TaskId=name)
        stc = f.create_entity(
            "IfcScheduleTimeControl",
            GlobalId=ifcopenshell.guid.new(),
            OwnerHistory=oh,
            ScheduleStart=start,
            ScheduleFinish=finish,
            ActualFinish=actual_finish,
        )
        ws = f.create_entity(
            "IfcWorkSchedule", GlobalId=ifcopenshell.guid.new(), OwnerHistory=oh, Name="Plan", CreationDate=start,
            StartTime=start,
        )  # fmt: skip
        f.create_entity(
            "IfcRelAssignsTasks", GlobalId=ifcopenshell.guid.new(), OwnerHistory=oh, RelatedObjects=[t],
            RelatingControl=ws, TimeForTask=stc,
        )  # fmt: skip
        return t

    walls = sorted(f.by_type("IfcWallStandardCase"), key=lambda w: w.GlobalId)[:2]
    t_walls = task("walls", when(2024, 5, 2, 8), when(2024, 5, 3, 17), when(2024, 5, 6, 12))
    f.create_entity(
        "IfcRelAssignsToProcess", GlobalId=ifcopenshell.guid.new(), OwnerHistory=oh, RelatedObjects=walls,
        RelatingProcess=t_walls,
    )  # fmt: skip
    storey = f.by_type("IfcBuildingStorey")[0]
    t_storey = task("storey", when(2024, 4, 1, 8), when(2024, 6, 1, 17))
    f.create_entity(
        "IfcRelAssignsToProduct", GlobalId=ifcopenshell.guid.new(), OwnerHistory=oh, RelatedObjects=[t_storey],
        RelatingProduct=storey,
    )  # fmt: skip
    path = tmp_path / "duplex_4d.ifc"
    f.write(str(path))

    site = load_site_model([path], tz="America/New_York")
    by_name = {t.name: t for t in site.tasks}
    assert set(by_name) == {"walls", "storey"}
    tw = by_name["walls"]
    assert sorted(tw.element_ids) == sorted(w.GlobalId for w in walls)
    assert tw.planned_start_ns == utc_ns(2024, 5, 2, 12)  # 08:00 EDT
    assert tw.planned_finish_ns == utc_ns(2024, 5, 3, 21)
    assert tw.actual_finish_ns == utc_ns(2024, 5, 6, 16)
    on_storey = {g for g, e in site.elements.items() if e.storey == (storey.Name or storey.GlobalId)}
    # The storey task gets the storey's elements except the two walls the wall task names.
    assert set(by_name["storey"].element_ids) == on_storey - {w.GlobalId for w in walls}
    assert len(on_storey) > 10
    w0 = walls[0].GlobalId
    assert site.planned_state(w0, utc_ns(2024, 5, 3, 12)) == "under_construction"
    assert site.actual_state(w0, utc_ns(2024, 5, 4, 12)) is not None
    assert site.schedule_status(w0, utc_ns(2024, 5, 4, 12)) == "late"  # planned done, not actually finished
