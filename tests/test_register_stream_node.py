"""The register node through the in-process LocalBus: queueing before anchors, anchors, fast path, outputs."""

from __future__ import annotations

import hashlib

import numpy as np
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide import camera as cam
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.register.node import SPEC, Config
from schemas import keys
from schemas.messages import AnchorClicks, AnchorPoint, NeedsAnchor, NodeError, Photo, Registration, SparseCloud

W, H = 640, 360
SITE = "t"


def make_photo(data: bytes, camera: str | None, t_s: int) -> Photo:
    return Photo(
        site=SITE,
        photo_id=hashlib.sha256(data).hexdigest()[:16],
        camera_id=camera,
        capture_time_ns=1_800_000_000_000_000_000 + t_s * 1_000_000_000,
        data=data,
        width_px=W,
        height_px=H,
    )


def clicks_msg(photo_id: str, px: np.ndarray, pts: np.ndarray) -> AnchorClicks:
    return AnchorClicks(
        site=SITE,
        photo_id=photo_id,
        points=tuple(
            AnchorPoint(pixel_px=(float(u), float(v)), point_in_world_m=tuple(float(x) for x in p))
            for (u, v), p in zip(px, pts, strict=True)
        ),
    )


def test_node_queues_until_anchor_then_registers_everything() -> None:
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(5)
    frames = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(3)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k) for k, (i, t) in enumerate(frames)]
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        views = bus.collect(keys.pattern(keys.VIEWPOINTS, site=SITE))
        sparse = bus.collect(keys.key(keys.SPARSE, site=SITE))
        errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
        # Frames before any anchor: queued, one NeedsAnchor for the camera, no registration yet.
        for p in photos[1:]:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), p)
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), photos[0])
        ((nkey, need),) = needs.wait(1, timeout=30)
        assert isinstance(need, NeedsAnchor) and need.photo_id == photos[1].photo_id
        assert node.wait_idle(30)
        assert regs.items == []
        # Bad clicks: a NodeError, the node keeps going.
        px, pts = anchor_clicks(intr, T, noise_px=0.2)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px[:3], pts[:3])
        )
        ((_, err),) = errors.wait(1, timeout=30)
        assert isinstance(err, NodeError) and "at least 4" in err.reason
        # Good clicks: the anchor, then every queued frame by the fast path.
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
        )
        items = regs.wait(4, timeout=60)
        by_id = {m.photo_id: (k, m) for k, m in items}
        assert set(by_id) == {p.photo_id for p in photos}
        key0, anchor = by_id[photos[0].photo_id]
        assert isinstance(anchor, Registration) and anchor.status == "anchor"
        assert key0 == f"constructaide/{SITE}/registration/cam-a/{photos[0].photo_id}"
        for p in photos[1:]:
            r = by_id[p.photo_id][1]
            assert r.status == "auto" and r.method == "fastpath" and r.num_inliers > 50, r.message
            assert r.processing_ms > 0 and r.reprojection_rms_px < 1.0
        ((_, cloud),) = sparse.wait(1, timeout=10)
        assert isinstance(cloud, SparseCloud) and cloud.photo_ids == (photos[0].photo_id,)
        assert len(cloud.points_xyz_f32) == 12 * (len(cloud.colors_rgb_u8) // 3)
        assert node.wait_idle(30)
        groups = {m.photo_id: m for _, m in views.items}
        last = groups[photos[-1].photo_id]
        assert {n.photo_id for n in last.neighbours} >= {p.photo_id for p in photos[:-1]}
        # Late clicks on an automatically registered frame correct it (its pixels were kept).
        i2, T2 = frames[2]
        px2, pts2 = anchor_clicks(i2, T2, noise_px=0.2, seed=3)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[2].photo_id), clicks_msg(photos[2].photo_id, px2, pts2)
        )
        fixed = regs.wait(5, timeout=60)[-1][1]
        assert fixed.photo_id == photos[2].photo_id and fixed.status == "anchor" and "replaces" in fixed.message


def test_node_uses_bim_depth_and_bim_updates_do_not_reregister() -> None:
    from constructaide.bimgeom import meshes_to_glb
    from schemas.messages import BimElement, BimModel, BimUpdate

    scene = PlaneScene(0)
    meshes = {}
    for i, pl in enumerate(scene.planes):
        v = np.array(
            [
                pl.origin,
                pl.origin + pl.u * pl.size_a,
                pl.origin + pl.u * pl.size_a + pl.v * pl.size_b,
                pl.origin + pl.v * pl.size_b,
            ]
        )
        meshes[f"el{i}"] = (v, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    model = BimModel(
        site=SITE,
        revision="r1",
        elements=tuple(BimElement(global_id=k, ifc_class="IfcWall", geometry_ref=k) for k in meshes),
        geometry_glb=meshes_to_glb(meshes),
    )
    intr, T = mast_camera(W, H)
    anchor = make_photo(encode_jpeg(scene.render(intr, T)), "cam-b", 0)
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        sparse = bus.collect(keys.key(keys.SPARSE, site=SITE))
        errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model)
        # Anchor clicks before the photo: they wait for it.
        px, pts = anchor_clicks(intr, T, noise_px=0.2)
        bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=anchor.photo_id), clicks_msg(anchor.photo_id, px, pts))
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-b"), anchor)
        ((_, reg),) = regs.wait(1, timeout=60)
        assert reg.status == "anchor"
        ((_, cloud),) = sparse.wait(1, timeout=30)
        xyz = np.frombuffer(cloud.points_xyz_f32, "<f4").reshape(-1, 3)
        assert len(xyz) > 200  # anchor features got 3D points from the BIM depth
        # Points lie on the model: facade (y = 20), ground (z = 0) or the box.
        on_model = (
            (np.abs(xyz[:, 1] - 20) < 0.1)
            | (np.abs(xyz[:, 2]) < 0.1)
            | ((np.abs(xyz[:, 0]) < 2.1) & (xyz[:, 1] > 11.9) & (xyz[:, 1] < 15.1))
        )
        assert on_model.mean() > 0.95
        bus.publish(
            keys.key(keys.BIM_UPDATE, site=SITE),
            BimUpdate(site=SITE, base_revision="r1", revision="r2", removed=("el2",)),
        )
        assert node.wait_idle(30)
        assert len(regs.items) == 1 and errors.items == []


def test_late_clicks_for_a_photo_whose_pixels_are_gone_check_its_registration() -> None:
    """Clicks answering a request after the photo registered on its own, its pixels no longer kept: clicks that
    agree confirm the registration (no error); clicks that disagree give an error and re-anchor the photo when it
    is pushed again."""
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(7)
    frames = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(3)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k) for k, (i, t) in enumerate(frames)]
    topic = keys.key(keys.PHOTO, site=SITE, camera="cam-a")
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE, keep_recent_photos=1), bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
        bus.publish(topic, photos[0])
        px, pts = anchor_clicks(intr, T, noise_px=0.2)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
        )
        for p in photos[1:]:
            bus.publish(topic, p)
        regs.wait(4, timeout=60)
        assert node.wait_idle(30)
        # Photo 1 registered automatically and only the last photo's pixels are kept.
        i1, T1 = frames[1]
        px1, pts1 = anchor_clicks(i1, T1, noise_px=0.5, seed=4)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[1].photo_id), clicks_msg(photos[1].photo_id, px1, pts1)
        )
        assert node.wait_idle(30)
        assert errors.items == [] and len(regs.items) == 4
        # Clicks 30 px away from where photo 1's registration puts their points: an error that says what to do.
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[1].photo_id),
            clicks_msg(photos[1].photo_id, px1 + np.array([30.0, 0.0]), pts1),
        )
        ((_, err),) = errors.wait(1, timeout=30)
        assert isinstance(err, NodeError) and "disagree with its registration" in err.reason
        assert "push the photo again" in err.reason
        # Pushed again, the photo is re-anchored with the kept clicks.
        bus.publish(topic, photos[1])
        fixed = regs.wait(5, timeout=60)[-1][1]
        assert fixed.photo_id == photos[1].photo_id and fixed.status == "anchor" and "replaces" in fixed.message


def test_refused_up_front_clicks_leave_the_photo_waiting_for_new_clicks() -> None:
    """Clicks that arrive before their photo and that the anchor solve refuses (six clicks, one of them a gross
    mis-click: five left are too few) give a NodeError naming the photo; the photo is not lost: it waits and asks
    for clicks, and corrected clicks then register it."""
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    photo = make_photo(encode_jpeg(scene.render(intr, T)), "cam-a", 0)
    px, pts = anchor_clicks(intr, T, noise_px=0.3, seed=4)
    assert len(px) >= 6
    bad = px[:6].copy()
    bad[2] += (45.0, -30.0)  # a neighbouring corner
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        errors = bus.collect(keys.key(keys.ERRORS, site=SITE))
        bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=photo.photo_id), clicks_msg(photo.photo_id, bad, pts[:6]))
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), photo)
        ((_, err),) = errors.wait(1, timeout=30)
        assert isinstance(err, NodeError) and photo.photo_id in err.reason and "refused" in err.reason, err.reason
        ((_, need),) = needs.wait(1, timeout=30)
        assert isinstance(need, NeedsAnchor) and need.photo_id == photo.photo_id
        assert node.wait_idle(30)
        assert regs.items == []
        bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=photo.photo_id), clicks_msg(photo.photo_id, px, pts))
        ((_, reg),) = regs.wait(1, timeout=60)
        assert isinstance(reg, Registration) and reg.photo_id == photo.photo_id and reg.status == "anchor"


def test_frames_before_the_anchor_that_the_map_cannot_place_say_why() -> None:
    """Frames that came before their camera's anchor clicks wait without a Registration (one NeedsAnchor for the
    camera). When the clicks come, the anchor registers and the frames are tried again: the ones that register are
    published, and a frame the map cannot place either (the camera turned away from the building) gets its failed
    Registration and a NeedsAnchor that say why, instead of waiting unseen (arrival order across a node's inputs is
    not guaranteed: a partitioned worker got its photos before the clicks published first, CI 2026-12-05)."""
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(5)
    away = T.copy()
    away[:3, :3] = T[:3, :3] @ cam.rodrigues_to_matrix(np.radians([0.0, 150.0, 0.0]))
    frames = [(intr, T), jitter(T, intr, rng, 0.3, 0.005), (intr, away), jitter(T, intr, rng, 0.3, 0.005)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-a", k) for k, (i, t) in enumerate(frames)]
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), p)
        assert node.wait_idle(30)
        assert regs.items == [] and len(needs.items) == 1
        px, pts = anchor_clicks(intr, T, noise_px=0.2)
        bus.publish(
            keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
        )
        regs.wait(4, timeout=60)
        assert node.wait_idle(30)
        by_id = {m.photo_id: m for _, m in regs.items}
        assert set(by_id) == {p.photo_id for p in photos}
        assert by_id[photos[0].photo_id].status == "anchor"
        assert {by_id[p.photo_id].method for p in (photos[1], photos[3])} == {"fastpath"}
        lost = by_id[photos[2].photo_id]
        assert lost.status == "failed" and "please click anchors" in lost.message, lost.message
        asked = [m for _, m in needs.items if m.photo_id == photos[2].photo_id]
        assert asked and asked[-1].reason in lost.message, (asked, lost.message)
        assert "no registered photos yet" not in asked[-1].reason
