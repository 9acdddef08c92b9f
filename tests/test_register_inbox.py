"""The register node's holding areas and BIM bookkeeping (pure parts of the shell)."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from constructaide.bimgeom import meshes_to_glb
from constructaide.sparsecloud import decode_sparse_cloud, encode_sparse_cloud
from nodes.register.bimsite import BimMeshes
from nodes.register.inbox import Inbox, click_arrays, dropped_registration, photo_input
from schemas.messages import AnchorClicks, AnchorPoint, BimElement, BimModel, BimUpdate, Photo, ScheduleTask

DAY = 86_400 * 10**9


def _photo(pid: str, t: int, camera: str | None = None) -> Photo:
    return Photo(site="s", photo_id=pid, camera_id=camera, capture_time_ns=t, data=b"x", width_px=4, height_px=3)


def _clicks(pid: str, n: int = 4) -> AnchorClicks:
    pts = tuple(AnchorPoint(pixel_px=(float(i), 2.0 * i), point_in_world_m=(i, 0.0, 1.0)) for i in range(n))
    return AnchorClicks(site="s", photo_id=pid, points=pts)


def test_queues_push_out_the_oldest_and_ask_once_per_camera() -> None:
    inbox = Inbox(max_pending=2, max_pending_anchors=1, max_recent=2)
    assert inbox.enqueue(_photo("a", 30)) == [] and inbox.enqueue(_photo("b", 10)) == []
    assert [p.photo_id for p in inbox.enqueue(_photo("c", 20))] == ["a"]
    assert [p.photo_id for p in inbox.waiting_by_time()] == ["b", "c"]
    inbox.keep_anchors(_clicks("x"))
    inbox.keep_anchors(_clicks("y"))
    assert list(inbox.pending_anchors) == ["y"]
    for pid in ("r1", "r2", "r1", "r3"):
        inbox.remember(_photo(pid, 0))
    assert list(inbox.recent) == ["r1", "r3"]  # r1 refreshed, r2 the oldest
    assert inbox.photo_for_clicks("b") is not None and "b" not in inbox.pending  # taken out of the queue
    assert inbox.photo_for_clicks("r3") is not None and "r3" in inbox.recent  # recent ones stay
    assert inbox.photo_for_clicks("nope") is None
    assert inbox.first_ask(_photo("p1", 0, "mast")) and not inbox.first_ask(_photo("p2", 0, "mast"))
    assert inbox.first_ask(_photo("p3", 0)) and inbox.first_ask(_photo("p4", 0))  # phones: each its own
    none_kept = Inbox(1, 1, 0)
    none_kept.remember(_photo("a", 0))
    assert not none_kept.recent
    with pytest.raises(ValueError, match="max_pending"):
        Inbox(0, 1, 1)


def test_message_conversions() -> None:
    px, pts = click_arrays(_clicks("a", 5))
    assert px.shape == (5, 2) and pts.shape == (5, 3) and px[3, 1] == 6.0 and pts[4, 0] == 4.0
    reg = dropped_registration("s", _photo("a", 7, "mast"), 3)
    assert (reg.status, reg.photo_id, reg.camera_id, reg.capture_time_ns) == ("failed", "a", "mast", 7)
    assert "3 photos" in reg.message
    inp = photo_input(_photo("a", 7, "mast"))
    assert (inp.photo_id, inp.camera_id, inp.capture_time_ns, inp.width_px) == ("a", "mast", 7, 4)
    with pytest.raises(ValueError, match="no image data"):
        photo_input(Photo(site="s", photo_id="e", capture_time_ns=0, data=b""))
    arr = {
        "photo_ids": ["a", "b"],
        "points_xyz": np.arange(6, dtype=np.float64).reshape(2, 3),
        "colors_rgb": np.zeros((2, 3), np.uint8),
        "obs_point": np.array([0, 1]),
        "obs_photo": np.array([1, 0]),
        "obs_pixel": np.ones((2, 2)),
        "point_flags": np.array([1, 0]),
    }
    cloud = encode_sparse_cloud("s", 4, arr)
    assert cloud.revision == 4 and cloud.photo_ids == ("a", "b")
    back = decode_sparse_cloud(cloud)
    assert back.points_m.tolist() == [[0, 1, 2], [3, 4, 5]] and back.colors_rgb is not None
    assert back.obs_photo.tolist() == [1, 0] and back.obs_pixel_px.shape == (2, 2)
    assert back.point_flags is not None and back.point_flags.tolist() == [1, 0]
    bad = [
        ({"obs_photo_i32": np.array([0], "<i4").tobytes()}, "differ in length"),
        ({"obs_point_i32": np.array([0, 2], "<i4").tobytes()}, "outside the points"),
        ({"obs_photo_i32": np.array([0, 2], "<i4").tobytes()}, "outside photo_ids"),
        ({"point_flags_u8": b"\x01"}, "point flags for"),
        ({"points_xyz_f32": b"\x00" * 16}, "multiple of 3"),
    ]
    for change, message in bad:
        with pytest.raises(ValueError, match=message):
            decode_sparse_cloud(msgspec.structs.replace(cloud, **change))
    assert decode_sparse_cloud(msgspec.structs.replace(cloud, colors_rgb_u8=b"", point_flags_u8=b"")).colors_rgb is None


def _box(x: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, 0, 0], [x + 1, 0, 0], [x, 1, 0], [x, 0, 1]], float)
    return v, np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.int32)


def test_bim_meshes_follow_updates_and_the_schedule() -> None:
    bim = BimMeshes()
    elements = (BimElement(global_id="wall", ifc_class="IfcWall", geometry_ref="m-wall"),)
    task = ScheduleTask(
        task_id="t", name="wall", planned_start_ns=DAY, planned_finish_ns=2 * DAY, element_ids=("wall",)
    )
    glb = meshes_to_glb({"m-wall": _box(0.0), "fence": _box(5.0)})
    bim.set_model(
        BimModel(site="s", revision="r1", elements=elements, tasks=(task,), geometry_glb=glb, terrain_height_m=0.5)
    )
    assert set(bim.meshes) == {"m-wall", "fence"} and bim.terrain_height_m == 0.5
    refs_at = bim.refs_at()
    assert refs_at(0) == {"fence"}  # the wall is not built yet; a mesh no element names stands
    assert refs_at(3 * DAY) == {"m-wall", "fence"}
    col = BimElement(global_id="col", ifc_class="IfcColumn")
    bim.apply_update(
        BimUpdate(
            site="s",
            base_revision="r1",
            revision="r2",
            added=(col,),
            removed=("wall",),
            geometry_glb=meshes_to_glb({"col": _box(9.0)}),
            tasks=(),
        )
    )
    assert set(bim.meshes) == {"fence", "col"} and bim.ref_of == {"col": "col"}
    assert bim.refs_at()(0) is None  # no tasks: no filter


def test_inbox_saved_before_the_unreported_field_loads_with_it_empty() -> None:
    import pickle

    box = Inbox(4, 4, 2)
    del box.__dict__["unreported"]  # as pickled by a build before the field existed
    restored = pickle.loads(pickle.dumps(box))
    assert restored.unreported == set() and restored.max_pending == 4
