"""The synthetic site's IFC and GLB: classes, storeys, schedule, geometry in world metres; CLI and determinism."""

from __future__ import annotations

import filecmp
from pathlib import Path

import ifcopenshell
import ifcopenshell.geom
import numpy as np
import pytest

from constructaide.bimgeom import glb_to_meshes
from constructaide.errors import UserError
from constructaide.synth import build_site, ensure_site
from constructaide.synth.cli import main as synth_main
from constructaide.synth.truth import element_states


@pytest.fixture(scope="module")
def ifc(small_site: Path):
    return ifcopenshell.open(str(small_site / "model" / "building.ifc"))


def test_ifc_classes_storeys_materials(ifc) -> None:
    assert ifc.schema == "IFC4"
    for cls in ("IfcFooting", "IfcColumn", "IfcBeam", "IfcSlab", "IfcWall", "IfcWindow", "IfcRoof"):
        assert len(ifc.by_type(cls)) > 0, cls
    storeys = sorted(ifc.by_type("IfcBuildingStorey"), key=lambda s: s.Elevation)
    assert [s.Name for s in storeys] == ["Basement", "Ground floor", "Level 1"]
    assert storeys[0].Elevation < 0
    mats = {m.Name for m in ifc.by_type("IfcMaterial")}
    assert {"Concrete C30/37", "Brick, red clay", "Glass, double glazing", "Steel S355"} <= mats
    assert len(ifc.by_type("IfcColumnType")) >= 1 and len(ifc.by_type("IfcWindowType")) == 1
    site = ifc.by_type("IfcSite")[0]
    lat = site.RefLatitude[0] + site.RefLatitude[1] / 60 + site.RefLatitude[2] / 3600
    assert abs(lat - 51.858) < 0.01


def test_ifc_schedule_assigns_every_element(ifc) -> None:
    tasks = ifc.by_type("IfcTask")
    assert len(tasks) >= 10
    assert all(t.TaskTime is not None and t.TaskTime.ScheduleStart < t.TaskTime.ScheduleFinish for t in tasks)
    assigned = set()
    for rel in ifc.by_type("IfcRelAssignsToProduct"):
        assert rel.RelatedObjects[0].is_a("IfcTask")
        assigned.add(rel.RelatingProduct.GlobalId)
    elements = ifc.by_type("IfcBuildingElement")
    assert {e.GlobalId for e in elements} <= assigned
    # realistic order: footings start before ground-floor columns, which start before the roof
    start = {t.Name: t.TaskTime.ScheduleStart for t in tasks}
    assert start["Pad footings"] < start["Columns ground floor"] < start["Columns level 1"] < start["Gable roof"]


def test_ifc_geometry_matches_glb_and_truth(ifc, small_site: Path) -> None:
    settings = ifcopenshell.geom.settings()
    settings.set("use-world-coords", True)
    it = ifcopenshell.geom.iterator(settings, ifc)
    assert it.initialize()
    glb = glb_to_meshes((small_site / "model" / "building.glb").read_bytes())
    states = element_states(small_site)["elements"]
    seen = 0
    while True:
        shape = it.get()
        v = np.asarray(shape.geometry.verts).reshape(-1, 3)
        gv, _ = glb[shape.guid]
        assert np.allclose(v.min(0), gv.min(0), atol=1e-6) and np.allclose(v.max(0), gv.max(0), atol=1e-6)
        assert shape.guid in states
        seen += 1
        if not it.next():
            break
    assert seen == len(states) == len(glb)
    top = max(m[0][:, 2].max() for m in glb.values())
    assert 8.0 < top < 12.0  # two storeys plus a gable roof, metres


def test_tiny_site_is_deterministic(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    assert synth_main(["--out", str(a), "--size", "tiny", "--seed", "3", "--quiet"]) == 0
    build_site(b, seed=3, size="tiny", progress=False)
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) > 20
    _, mismatch, errors = filecmp.cmpfiles(a, b, [str(p) for p in files_a], shallow=False)
    assert mismatch == [] and errors == []
    c = tmp_path / "c"
    build_site(c, seed=4, size="tiny", progress=False)
    assert (c / "model" / "building.ifc").read_bytes() != (a / "model" / "building.ifc").read_bytes()
    jpg_a = sorted((a / "photos" / "cam-north").glob("*.jpg"))[0].read_bytes()
    jpg_c = sorted((c / "photos" / "cam-north").glob("*.jpg"))[0].read_bytes()
    assert jpg_a != jpg_c


def test_bad_input_is_a_user_error(tmp_path: Path) -> None:
    (tmp_path / "x").write_text("occupied")
    with pytest.raises(UserError, match="not empty"):
        build_site(tmp_path, size="tiny", progress=False)
    with pytest.raises(UserError, match="unknown site size"):
        ensure_site("huge", 0, tmp_path / "cache")


def test_undistortion_maps_match_the_camera_model() -> None:
    from constructaide.camera import centered_intrinsics, normalized_to_pixels
    from constructaide.synth.render import undistortion_maps

    intr = centered_intrinsics(400, 300, 330.0, -0.1, 0.02)
    x, y = undistortion_maps(intr)
    back = normalized_to_pixels(intr, np.stack([x.ravel(), y.ravel()], 1))
    u, v = np.meshgrid(np.arange(400.0), np.arange(300.0))
    err = np.abs(back - np.stack([u.ravel(), v.ravel()], 1))
    assert err.max() < 0.02  # re-distorting the map lands on the pixel it came from


def test_sun_position_agrees_with_pvlib() -> None:
    import datetime as dt

    import pandas as pd
    import pvlib

    from constructaide.synth.sun import sun_azimuth_elevation_deg

    for when in (dt.datetime(2026, 3, 9, 11, 0, tzinfo=dt.UTC), dt.datetime(2026, 4, 20, 14, 30, tzinfo=dt.UTC)):
        az, el = sun_azimuth_elevation_deg(when, 51.8583, 5.8647)
        ref = pvlib.solarposition.get_solarposition(pd.DatetimeIndex([when]), 51.8583, 5.8647)
        assert abs(az - float(ref["azimuth"].iloc[0])) < 1.0
        assert abs(el - float(ref["elevation"].iloc[0])) < 1.0


def test_ensure_site_builds_once_and_reuses(tmp_path: Path) -> None:
    first = ensure_site("tiny", 1, tmp_path)
    stamp = (first / "site.toml").stat().st_mtime_ns
    again = ensure_site("tiny", 1, tmp_path)
    assert again == first and (again / "site.toml").stat().st_mtime_ns == stamp
    assert "tiny" in first.name and "seed1" in first.name
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")] == [first.name]  # no temp dirs left


def test_contact_sheet(small_site: Path, tmp_path: Path) -> None:
    from PIL import Image

    from constructaide.synth.contact_sheet import make_contact_sheet

    out = make_contact_sheet(small_site, tmp_path / "sheet.png", columns=4, thumb_w=160)
    with Image.open(out) as im:
        assert im.size == (4 * 164 + 4, 4 * (90 + 4) + 4)  # 3 fixed cameras + 1 phone row
    assert out.stat().st_size < 1_500_000
