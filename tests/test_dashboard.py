"""Dashboard: pure scene logic, and a .rrd written by the node read back with rerun's RrdReader."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from constructaide import bimgeom
from constructaide.camera import look_at
from nodes.dashboard.scene import CAMERAS, Scene, class_rgba, decode_mask_png, state_rgba
from schemas import keys
from schemas import messages as m

SITE = "dash"
T0 = 1_700_000_000_000_000_000
DAY = 86_400 * 10**9
WALL = "2O2Fr$t4X7Zf8NOew3FLOH"
SLAB = "1kTvXnbbzCWw8lcMd1dR4o"


def _png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _jpeg(h: int = 48, w: int = 64) -> bytes:
    img = np.zeros((h, w, 3), np.uint8)
    img[:, : w // 2] = (40, 120, 200)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def bim_model() -> m.BimModel:
    wall = trimesh.creation.box(extents=(4.0, 0.2, 3.0))
    wall.apply_translation((0, 0, 1.5))
    slab = trimesh.creation.box(extents=(6.0, 6.0, 0.2))
    glb = bimgeom.meshes_to_glb({WALL: (wall.vertices, wall.faces), SLAB: (slab.vertices, slab.faces)})
    return m.BimModel(
        site=SITE,
        revision="r1",
        elements=(
            m.BimElement(global_id=WALL, ifc_class="IfcWall", geometry_ref=WALL),
            m.BimElement(global_id=SLAB, ifc_class="IfcSlab", geometry_ref=SLAB),
        ),
        tasks=(
            m.ScheduleTask(
                task_id="T1", name="wall", planned_start_ns=T0, planned_finish_ns=T0 + DAY, element_ids=(WALL,)
            ),
        ),
        geometry_glb=glb,
    )


def photo(pid: str = "p0", cam: str | None = "cam-a", t: int = T0 + DAY // 2) -> m.Photo:
    return m.Photo(site=SITE, photo_id=pid, camera_id=cam, capture_time_ns=t, data=_jpeg(), width_px=64, height_px=48)


def registration(pid: str = "p0", cam: str | None = "cam-a", t: int = T0 + DAY // 2) -> m.Registration:
    pose = look_at((8.0, -6.0, 2.0), (0.0, 0.0, 1.0))
    return m.Registration(
        site=SITE,
        photo_id=pid,
        camera_id=cam,
        capture_time_ns=t,
        intrinsics=m.Intrinsics(width_px=64, height_px=48, f_px=60.0, cx_px=31.5, cy_px=23.5),
        world_from_camera=tuple(pose.ravel().tolist()),
        status="anchor",
        method="anchor",
    )


def test_dashboard_scene_pairs_photos_and_registrations_in_any_order() -> None:
    scene = Scene(photo_cache_size=2)
    assert [op.kind for op in scene.on_photo(photo("p0"))] == ["view_coordinates", "annotation_context"]
    ops = scene.on_registration(registration("p0"))
    kinds = {(op.path, op.kind) for op in ops}
    assert ((*CAMERAS, "cam-a"), "transform") in kinds
    assert ((*CAMERAS, "cam-a", "image"), "pinhole") in kinds
    img = [op for op in ops if op.kind == "image"]
    assert len(img) == 1 and img[0].time_ns == T0 + DAY // 2 and img[0].fields["media_type"] == "image/jpeg"
    tf = next(op for op in ops if op.kind == "transform")
    np.testing.assert_allclose(tf.fields["translation"], (8.0, -6.0, 2.0))
    pin = next(op for op in ops if op.kind == "pinhole")
    np.testing.assert_allclose(pin.fields["image_from_camera"][:2, 2], (32.0, 24.0))  # OpenCV centre + 0.5
    assert scene.cameras == ["cam-a"]

    # registration first, photo later: the image is logged when the photo arrives
    assert not [op for op in scene.on_registration(registration("p1", t=T0 + DAY)) if op.kind == "image"]
    late = scene.on_photo(photo("p1", t=T0 + DAY))
    assert [op.kind for op in late] == ["image"] and late[0].path == (*CAMERAS, "cam-a", "image")

    # bounded cache: p0 evicted after two newer photos, a re-registration has no photo to show
    scene.on_photo(photo("p2"))
    scene.on_photo(photo("p3"))
    assert scene.cached_photo_ids() == ["p2", "p3"]
    small = Scene(photo_cache_bytes=len(photo().data) * 2)
    for pid in ("a", "b", "c"):
        small.on_photo(photo(pid))
    assert small.cached_photo_ids() == ["b", "c"]
    assert not [op for op in scene.on_registration(registration("p0")) if op.kind == "image"]
    # a photo still waiting for its registration outlives photos already shown
    waiting = Scene(photo_cache_size=2)
    waiting.on_photo(photo("x"))
    waiting.on_photo(photo("y"))
    waiting.on_registration(registration("y"))
    waiting.on_photo(photo("z"))
    assert waiting.cached_photo_ids() == ["x", "z"]
    assert [op.kind for op in waiting.on_registration(registration("x")) if op.kind == "image"] == ["image"]

    # phone photos share the "phone" camera; failures are text only (a log line and the camera's status line)
    scene.on_photo(photo("q", cam=None))
    assert any(op.path == (*CAMERAS, "phone", "image") for op in scene.on_registration(registration("q", cam=None)))
    failed = scene.on_registration(m.Registration(site=SITE, photo_id="z", status="failed", message="no matches"))
    assert [op.kind for op in failed] == ["text", "text_document"] and "no matches" in failed[0].fields["text"]
    assert "failed to register (no matches)" in failed[1].fields["text"]
    assert scene.cameras == ["cam-a", "phone"]


def test_dashboard_scene_bim_4d_colours_and_bad_input() -> None:
    scene = Scene()
    ops = scene.on_bim_model(bim_model())
    meshes = {op.path: op for op in ops if op.kind == "mesh"}
    assert set(meshes) == {("world", "bim", "IfcWall", WALL), ("world", "bim", "IfcSlab", SLAB)}
    wall = meshes[("world", "bim", "IfcWall", WALL)]
    assert wall.static and wall.fields["vertex_positions"].shape == (8, 3)
    assert wall.fields["triangle_indices"].shape == (12, 3)
    assert wall.fields["albedo_factor"] is None  # scheduled: colour is temporal
    assert meshes[("world", "bim", "IfcSlab", SLAB)].fields["albedo_factor"] == class_rgba("IfcSlab")
    colours = [(op.time_ns, op.fields["albedo_factor"]) for op in ops if op.kind == "mesh_color"]
    assert colours == [
        (T0 - 1, state_rgba("IfcWall", "not_started")),
        (T0, state_rgba("IfcWall", "under_construction")),
        (T0 + DAY, state_rgba("IfcWall", "complete")),
    ]
    assert colours[0][1][3] < 255 and colours[2][1] == class_rgba("IfcWall")
    # a new revision clears the old one first
    assert scene.on_bim_model(bim_model())[0].kind == "clear"
    removed = scene.on_bim_update(m.BimUpdate(site=SITE, base_revision="r1", revision="r2", removed=(SLAB,)))
    assert [(op.kind, op.path) for op in removed] == [("clear", ("world", "bim", "IfcSlab", SLAB))]

    # a changed element keeps its 4D colours from the model's schedule
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    changed = scene.on_bim_update(
        m.BimUpdate(
            site=SITE,
            base_revision="r2",
            revision="r3",
            changed=(m.BimElement(global_id=WALL, ifc_class="IfcWall"),),
            geometry_glb=bimgeom.meshes_to_glb({WALL: (box.vertices, box.faces)}),
        )
    )
    assert [op.kind for op in changed] == ["mesh", "mesh_color", "mesh_color", "mesh_color"]
    assert changed[0].fields["albedo_factor"] is None

    with pytest.raises(ValueError, match="no image"):
        scene.on_overlay(m.Overlay(site=SITE, photo_id="p0", mode="state4d"))
    with pytest.raises(ValueError, match="multiple of 3"):
        scene.on_sparse(m.SparseCloud(site=SITE, points_xyz_f32=np.zeros(4, np.float32).tobytes()))
    with pytest.raises(ValueError, match="rigid"):
        scene.on_registration(
            m.Registration(
                site=SITE,
                photo_id="p0",
                status="auto",
                intrinsics=registration().intrinsics,
                world_from_camera=tuple([2.0] * 16),
            )
        )
    with pytest.raises(ValueError, match="decodable"):
        decode_mask_png(b"\x89PNG nope")
    mask = np.zeros((4, 5), np.uint8)
    mask[1:3, 2:] = 255
    assert decode_mask_png(_png(mask)).tolist() == (mask > 0).astype(int).tolist()


def _rrd_contents(path: Path) -> dict[str, dict[str, object]]:
    """{entity path: {"static": bool, "columns": set of column names, "batches": [RecordBatch]}}."""
    from rerun.chunk import RrdReader

    out: dict[str, dict[str, object]] = {}
    for chunk in RrdReader(path).stream():
        entry = out.setdefault(chunk.entity_path, {"static": False, "columns": set(), "batches": []})
        batch = chunk.to_record_batch()
        entry["static"] = bool(entry["static"]) or chunk.is_static
        entry["columns"].update(batch.schema.names)  # type: ignore[union-attr]
        entry["batches"].append(batch)  # type: ignore[union-attr]
    return out


def test_dashboard_node_writes_rrd_with_expected_entities(tmp_path: Path) -> None:
    from constructaide.runtime import start_node
    from constructaide.runtime.local import LocalBus
    from nodes.dashboard.node import SPEC, Config

    rrd = tmp_path / "dash.rrd"
    mask = np.zeros((48, 64), np.uint8)
    mask[10:30, 20:40] = 255
    overlay_rgba = np.zeros((48, 64, 4), np.uint8)
    overlay_rgba[..., 1] = 255
    overlay_rgba[..., 3] = 128
    pts = np.random.default_rng(0).normal(size=(25, 3)).astype(np.float32)
    with LocalBus() as bus:
        errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
        with start_node(SPEC, Config(site=SITE, rerun=f"save:{rrd}"), bus) as node:
            bus.publish(keys.key(keys.BIM_MODEL, site=SITE), bim_model(), latched=True)
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), photo())
            bus.publish(keys.key(keys.REGISTRATION, site=SITE, camera="cam-a", photo="p0"), registration())
            bus.publish(
                keys.key(keys.OVERLAY, site=SITE, mode="state4d", photo="p0"),
                m.Overlay(site=SITE, photo_id="p0", mode="state4d", image_png=_png(overlay_rgba)),
            )
            bus.publish(
                keys.key(keys.OCCLUSION, site=SITE, kind="dynamic", photo="p0"),
                m.OcclusionMask(site=SITE, photo_id="p0", kind="dynamic", mask_png=_png(mask)),
            )
            bus.publish(
                keys.key(keys.SPARSE, site=SITE),
                m.SparseCloud(site=SITE, photo_ids=("p0",), points_xyz_f32=pts.tobytes()),
            )
            bus.publish(
                keys.key(keys.NEEDS_ANCHOR, site=SITE, photo="p9"),
                m.NeedsAnchor(site=SITE, photo_id="p9", reason="few"),
            )
            bus.publish(
                keys.key(keys.ANNOTATION, site=SITE, annotation="a1"),
                m.Annotation(
                    site=SITE, annotation_id="a1", kind="occluder", photo_id="p0", polygon_px=((1, 1), (20, 1), (20, 9))
                ),
            )
            # a bad overlay: the handler raises, the runtime turns it into a NodeError, the dashboard logs it
            bus.publish(
                keys.key(keys.OVERLAY, site=SITE, mode="xray", photo="p0"),
                m.Overlay(site=SITE, photo_id="p0", mode="xray"),
            )
            errors.wait(count=1, timeout=30)
            assert node.wait_idle(30)
    assert rrd.is_file()
    got = _rrd_contents(rrd)
    wall = "/world/bim/IfcWall/" + WALL.replace("$", "\\$")
    assert got[wall]["static"] and "Mesh3D:vertex_positions" in got[wall]["columns"]
    assert "Mesh3D:albedo_factor" in got[wall]["columns"]  # temporal 4D colours
    assert "Transform3D:translation" in got["/world/cameras/cam-a"]["columns"]
    image = got["/world/cameras/cam-a/image"]
    assert {"Pinhole:image_from_camera", "EncodedImage:blob", "capture_time", "event"} <= image["columns"]  # type: ignore[operator]
    times = {
        int(v.value)
        for b in image["batches"]  # type: ignore[union-attr]
        if "capture_time" in b.schema.names
        for v in b.column("capture_time")
    }
    assert times == {T0 + DAY // 2}
    assert "EncodedImage:blob" in got["/world/cameras/cam-a/image/overlay/state4d"]["columns"]
    assert "SegmentationImage:buffer" in got["/world/cameras/cam-a/image/occlusion/dynamic"]["columns"]
    assert "LineStrips2D:strips" in got["/world/cameras/cam-a/image/annotations/a1"]["columns"]
    points = got["/world/points"]
    n_points = sum(len(b.column("Points3D:positions")[0]) for b in points["batches"])  # type: ignore[union-attr]
    assert n_points == 25
    assert "TextLog:text" in got["/log/needs_anchor"]["columns"]
    assert "TextLog:text" in got["/log/errors"]["columns"]

    from rerun.chunk import RrdReader

    blueprints = RrdReader(rrd).blueprints()
    assert blueprints, "default blueprint stored"
    bp_text = " ".join(
        str(c.to_record_batch().to_pydict()) for bp in blueprints for c in RrdReader(rrd).stream(store=bp)
    )
    assert "/world/cameras/cam-a/image" in bp_text


def test_dashboard_rejects_bad_sink() -> None:
    from constructaide.errors import UserError
    from nodes.dashboard.node import make_blueprint, open_stream

    with pytest.raises(UserError, match="save:PATH"):
        open_stream("file:/tmp/x.rrd", SITE, "t", make_blueprint(()))


DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.mark.skipif(not (DATA / "ifc").is_dir(), reason=f"real IFC data not present at {DATA / 'ifc'}")
@pytest.mark.parametrize("ifc", ["webifc_IfcOpenHouse_IFC4.ifc", "bsi_construction-scheduling-task.ifc"])
def test_dashboard_real_ifc_model_to_rrd(tmp_path: Path, ifc: str) -> None:
    """A real IFC model (ingest core -> BimModel) becomes one static mesh entity per element."""
    import logging

    from constructaide.bim.ifc import load_site_model
    from nodes.dashboard.node import Config, DashboardNode, entity_path
    from nodes.ingest.revisions import to_bim_model

    model = to_bim_model(load_site_model([DATA / "ifc" / ifc], tz="UTC", threads=1), SITE, "r1")
    with_mesh = set(bimgeom.load_bim_model_glb(model))
    expected = {
        entity_path(("world", "bim", e.ifc_class, e.global_id))
        for e in model.elements
        if (e.geometry_ref or e.global_id) in with_mesh
    }
    assert expected, "the model has element meshes"

    class Ctx:
        site = SITE
        node = "dashboard"
        log = logging.getLogger("test-dashboard")

    rrd = tmp_path / "model.rrd"
    dash = DashboardNode(Config(site=SITE, rerun=f"save:{rrd}"), Ctx())  # type: ignore[arg-type]
    dash.on_message(model)
    dash.close()
    got = _rrd_contents(rrd)
    bim = {p for p, v in got.items() if p.startswith("/world/bim/") and "Mesh3D:vertex_positions" in v["columns"]}
    assert bim == expected
    coloured = {p for p in bim if "Mesh3D:albedo_factor" in got[p]["columns"]}
    assert coloured == bim, "every element has a colour (static by class, or temporal by 4D state)"
    temporal = {p for p in bim if "capture_time" in got[p]["columns"]}
    assert bool(temporal) == bool(model.tasks), "scheduled elements (only) get temporal 4D colours"
