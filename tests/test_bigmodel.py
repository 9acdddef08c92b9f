"""The big-model generator through the shipping ingest and render path, small (bench/bigmodel.py runs 50,000)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np

import constructaide  # noqa: F401  (EGL platform)
from constructaide.camera import centered_intrinsics, look_at
from constructaide.synth.bigmodel import elements_per_storey, write_big_ifc
from nodes.ingest.ifc import load_site_model
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
