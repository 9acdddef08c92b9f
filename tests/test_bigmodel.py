"""The big-model generator through the shipping ingest and render path, small (bench/bigmodel.py runs 50,000)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np

import constructaide  # noqa: F401  (EGL platform)
from constructaide.bim.ifc import load_site_model
from constructaide.camera import centered_intrinsics, look_at
from constructaide.synth.bigmodel import elements_per_storey, write_big_ifc
from nodes.ingest.revisions import to_bim_model
from nodes.render.engine import RenderEngine
from schemas import codec
from schemas.messages import BimModel, Photo, Registration


def test_generated_model_round_trips_through_ingest_and_render(tmp_path: Path) -> None:
    n = elements_per_storey() + 179  # one full storey and part of a second
    path = tmp_path / "big.ifc"
    counts = write_big_ifc(path, n, seed=3)
    assert counts["elements"] == n and counts["storeys"] == 2 and counts["tasks"] == 2
    site = load_site_model([path])
    assert len(site.elements) == n
    assert not site.warnings
    assert all(len(m.faces) == 12 for m in site.meshes.values())  # every element is one box
    classes = Counter(e.ifc_class for e in site.elements.values())
    assert set(classes) == {"IfcColumn", "IfcBeam", "IfcSlab", "IfcWall", "IfcWindow"}
    assert {len(t.element_ids) for t in site.tasks} == {elements_per_storey(), 179}
    assert {e.storey for e in site.elements.values()} == {"T1 L00", "T1 L01"}

    model = codec.decode(codec.encode(to_bim_model(site, "s", "r1")), BimModel)
    assert len(model.elements) == n
    engine = RenderEngine()
    try:
        engine.set_model(model)
        assert engine.scene is not None and engine.scene.num_elements == n
        assert engine.scene.num_triangles == 12 * n
        lo, hi = engine.scene.bbox_min_m, engine.scene.bbox_max_m
        c = 0.5 * (lo + hi)
        intr = centered_intrinsics(640, 360, 500.0)
        wfc = look_at(c + np.array([0.4, -1.0, 0.5]) * float(np.linalg.norm(hi - lo)), c)
        ids = engine.rasterizer.render(engine.scene, intr, wfc, np.ones(n + 1, bool)).ids
        seen = set(np.unique(ids).tolist()) - {0}
        assert len(seen) > 50 and max(seen) <= n
        at = max(t.planned_finish_ns for t in model.tasks) + 1
        jpeg = bytes(cv2.imencode(".jpg", np.full((360, 640, 3), 120, np.uint8))[1])
        photo = Photo(site="s", photo_id="p", capture_time_ns=at, data=jpeg, width_px=640, height_px=360)
        reg = Registration(
            site="s",
            photo_id="p",
            intrinsics=intr,
            world_from_camera=tuple(float(x) for x in wfc.ravel()),
            status="anchor",
        )
        overlay = engine.render(photo, reg, "state4d")
        img = cv2.imdecode(np.frombuffer(overlay.image_png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (360, 640)
        assert (img.reshape(-1, img.shape[2]) != img.reshape(-1, img.shape[2])[0]).any(axis=1).mean() > 0.05
    finally:
        engine.close()


def test_generator_is_deterministic(tmp_path: Path) -> None:
    a, b = tmp_path / "a" / "m.ifc", tmp_path / "b" / "m.ifc"
    write_big_ifc(a, 120, seed=5)
    write_big_ifc(b, 120, seed=5)
    assert a.read_bytes() == b.read_bytes()


def _box_grid(n: int = 20) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    import trimesh

    box = trimesh.creation.box((1.0, 1.0, 2.0))
    return {f"b{i:02d}{j:02d}": (box.vertices + (3.0 * i, 3.0 * j, 1.0), box.faces) for i in range(n) for j in range(n)}


def test_draw_ranges_merge_consecutive_drawn_elements() -> None:
    from constructaide.modelview import draw_ranges

    tri_range = np.array([[0, 0], [0, 2], [2, 2], [2, 5], [5, 6], [6, 9]])  # element 2 has no triangles
    first, count = draw_ranges(tri_range, np.array([True, True, True, True, False, True]))
    assert first.tolist() == [0, 18] and count.tolist() == [15, 9]
    first, count = draw_ranges(tri_range, np.zeros(6, bool))
    assert len(first) == 0 and len(count) == 0


def test_frustum_culling_draws_less_and_changes_no_pixel(monkeypatch) -> None:  # noqa: ANN001
    import constructaide.modelview as mv
    from constructaide.modelscene import scene_from_meshes

    scene = scene_from_meshes(_box_grid())
    intr = centered_intrinsics(320, 240, 700.0, -0.05, 0.01)
    wfc = look_at((-8.0, -8.0, 3.0), (3.0, 3.0, 1.0))  # sees the corner of the grid
    vis = np.ones(scene.num_elements + 1, bool)
    vis[5::7] = False  # some hidden elements
    ras = mv.GLRasterizer()
    try:
        culled = ras.render(scene, intr, wfc, vis)
        drawn = ras.last_drawn_vertices
        monkeypatch.setattr(mv, "frustum_mask", lambda lo, hi, clip: np.ones(len(lo), bool))
        full = ras.render(scene, intr, wfc, vis)
        drawn_full = ras.last_drawn_vertices
    finally:
        ras.close()
    assert drawn_full == 3 * 12 * int(vis[1:].sum())
    assert 0 < drawn < drawn_full / 2
    assert len(np.unique(culled.ids)) > 10
    np.testing.assert_array_equal(culled.ids, full.ids)
    np.testing.assert_array_equal(culled.depth_m, full.depth_m)
