"""Render node on the in-process bus, and the `constructaide render` CLI on an MCAP recording."""

from __future__ import annotations

import cv2
import msgspec
import numpy as np
import pytest
from render_scenes import AT, camera, four_box_model

import constructaide  # noqa: F401
from constructaide.camera import pose_to_tuple
from constructaide.errors import UserError
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.render.node import SPEC, Config
from schemas import codec, keys
from schemas.messages import Annotation, OcclusionMask, Overlay, Photo, Registration


def _photo_and_reg(site="t"):
    intr, wfc = camera()
    img = np.full((intr.height_px, intr.width_px, 3), 110, np.uint8)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    photo = Photo(
        site=site,
        photo_id="p0000000000000001",
        camera_id="cam-a",
        capture_time_ns=AT,
        media_type="image/png",
        data=buf.tobytes(),
        width_px=intr.width_px,
        height_px=intr.height_px,
    )
    reg = Registration(
        site=site,
        photo_id=photo.photo_id,
        camera_id="cam-a",
        capture_time_ns=AT,
        intrinsics=intr,
        world_from_camera=pose_to_tuple(wfc),
        status="anchor",
    )
    return photo, reg


def _png(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def test_render_node_publishes_overlays_for_registered_photos():
    model = four_box_model()
    photo, reg = _photo_and_reg()
    cfg = Config(site="t", modes=("state4d", "progress", "edges"))
    with LocalBus() as bus, start_node(SPEC, cfg, bus):
        got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model)
        bus.publish(keys.key(keys.PHOTO, site="t", camera="cam-a"), photo)
        bus.publish(keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=photo.photo_id), reg)
        items = got.wait(count=3, timeout=60.0)
        modes = {}
        for key, msg in items:
            assert isinstance(msg, Overlay) and msg.photo_id == photo.photo_id and msg.at_ns == AT
            assert keys.parse(keys.OVERLAY, key)["mode"] == msg.mode
            modes[msg.mode] = msg
        assert set(modes) == {"state4d", "progress", "edges"}
        img = _png(modes["progress"].image_png)
        assert img.shape[:2] == (reg.intrinsics.height_px, reg.intrinsics.width_px)
        assert (img != 110).any()
        # A status annotation re-renders the progress overlay with the dark-blue "needs review" colour.
        got2 = bus.collect(keys.pattern(keys.OVERLAY, site="t", mode="progress"))
        ann = Annotation(
            site="t",
            annotation_id="a1",
            kind="status",
            element_ids=("A", "B", "C", "D"),
            status="needs_review",
            created_ns=AT - 1,
        )
        bus.publish(keys.key(keys.ANNOTATION, site="t", annotation="a1"), ann)
        ((_, again),) = got2.wait(count=1, timeout=60.0)
        blue = _png(again.image_png)  # BGR
        assert ((blue[..., 0].astype(int) - blue[..., 2]) > 40).mean() > 0.05


def test_render_cache_keeps_unrendered_photos_and_reports_a_dropped_one():
    """A camera backlog: six photos arrive before any registration (cache of four). Rendered photos leave the cache
    first, so once registrations arrive every photo still cached is drawn; a photo that had to go unrendered is
    reported as a NodeError instead of silently getting no overlay."""
    from schemas.messages import NodeError

    model = four_box_model()
    photo, reg = _photo_and_reg()
    ids = [f"p{k:016d}" for k in range(6)]
    cfg = Config(site="t", modes=("state4d",), photo_cache=4)
    with LocalBus() as bus, start_node(SPEC, cfg, bus) as node:
        got = bus.collect(keys.pattern(keys.OVERLAY, site="t"))
        errors = bus.collect(keys.key(keys.ERRORS, site="t"))
        bus.publish(keys.key(keys.BIM_MODEL, site="t"), model)
        # two photos registered and drawn first, then four more arrive: the drawn ones make room
        for pid in ids[:2]:
            bus.publish(keys.key(keys.PHOTO, site="t", camera="cam-a"), msgspec.structs.replace(photo, photo_id=pid))
            bus.publish(
                keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=pid),
                msgspec.structs.replace(reg, photo_id=pid),
            )
        got.wait(count=2, timeout=60.0)
        assert node.wait_idle(30.0)
        for pid in ids[2:]:
            bus.publish(keys.key(keys.PHOTO, site="t", camera="cam-a"), msgspec.structs.replace(photo, photo_id=pid))
        assert node.wait_idle(30.0)
        assert list(node.obj.photos) == ids[2:] and errors.items == []
        # a fifth unrendered photo: the oldest unrendered one has to go, and that is reported
        extra = "p0000000000000099"
        bus.publish(keys.key(keys.PHOTO, site="t", camera="cam-a"), msgspec.structs.replace(photo, photo_id=extra))
        ((_, err),) = errors.wait(count=1, timeout=30.0)
        assert isinstance(err, NodeError) and ids[2] in err.reason and "before it was rendered" in err.reason
        for pid in [*ids[3:], extra]:
            bus.publish(
                keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=pid),
                msgspec.structs.replace(reg, photo_id=pid),
            )
        items = got.wait(count=6, timeout=60.0)
        assert {m.photo_id for _, m in items} == {*ids[:2], *ids[3:], extra}


def test_render_cli_from_recording(tmp_path, capsys):
    from nodes.recorder.mcapio import RecordingWriter
    from nodes.render.cli import main

    model = four_box_model()
    photo, reg = _photo_and_reg()
    mask = np.zeros((reg.intrinsics.height_px, reg.intrinsics.width_px), np.uint8)
    mask[:, :100] = 255
    ok, mpng = cv2.imencode(".png", mask)
    occ = OcclusionMask(site="t", photo_id=photo.photo_id, kind="combined", mask_png=mpng.tobytes())
    rec = tmp_path / "r.mcap"
    with RecordingWriter(rec) as w:
        w.write(keys.key(keys.BIM_MODEL, site="t"), codec.encode(model))
        w.write(keys.key(keys.PHOTO, site="t", camera="cam-a"), codec.encode(photo))
        w.write(keys.key(keys.REGISTRATION, site="t", camera="cam-a", photo=photo.photo_id), codec.encode(reg))
        w.write(keys.key(keys.OCCLUSION, site="t", kind="combined", photo=photo.photo_id), codec.encode(occ))
    out = tmp_path / "o.png"
    assert main(["--photo", "p00000", "--mode", "state4d", "--out", str(out), "--recording", str(rec)]) == 0
    img = _png(out.read_bytes())
    assert (img[:, :100] == 110).all() and (img[:, 100:] != 110).any()  # occluded strip untouched
    out2 = tmp_path / "f.png"
    # Ten days earlier nothing was built yet, later everything incl. the slab E: state differs by date.
    main(
        [
            "--photo",
            "p00000",
            "--mode",
            "state4d",
            "--at",
            "2026-02-01T00:00",
            "--out",
            str(out2),
            "--recording",
            str(rec),
        ]
    )
    assert (_png(out2.read_bytes()) == 110).mean() > (img == 110).mean()
    out3 = tmp_path / "pr.png"
    assert main(["--photo", "p00000", "--mode", "photoreal", "--out", str(out3), "--recording", str(rec)]) == 0
    assert "sun az" in capsys.readouterr().out
    with pytest.raises(UserError, match="no photo"):
        main(["--photo", "zzz", "--mode", "edges", "--out", str(out), "--recording", str(rec)])
    with pytest.raises(UserError, match="ISO 8601"):
        main(["--photo", "p0", "--mode", "edges", "--at", "yesterday", "--out", str(out), "--recording", str(rec)])


def test_render_engine_applies_model_updates():
    import msgspec
    from render_scenes import box

    from constructaide.bimgeom import meshes_to_glb
    from nodes.render.engine import RenderEngine
    from schemas.messages import BimElement, BimUpdate

    model = four_box_model()
    photo, reg = _photo_and_reg()
    eng = RenderEngine()
    try:
        eng.set_model(model)
        before = _png(eng.render(photo, reg, "state4d").image_png)
        upd = BimUpdate(
            site="t",
            base_revision="r1",
            revision="r2",
            removed=("A",),
            added=(BimElement(global_id="G", ifc_class="IfcWall", geometry_ref="G"),),
            geometry_glb=meshes_to_glb({"G": box((-3.0, 0.0, 1.5), (2, 2, 3))}),
        )
        eng.apply_update(upd)
        assert eng.model.revision == "r2" and "A" not in eng.scene.index_of and "G" in eng.scene.index_of
        after = _png(eng.render(photo, reg, "state4d").image_png)
        assert (before != after).any()
        with pytest.raises(ValueError, match="base"):
            eng.apply_update(msgspec.structs.replace(upd, base_revision="zz"))
        with pytest.raises(ValueError, match="registration"):
            eng.render(photo, msgspec.structs.replace(reg, status="failed"), "edges")
    finally:
        eng.close()
