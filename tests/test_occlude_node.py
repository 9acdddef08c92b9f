"""The occlude node end to end on the in-process bus: photos, registrations, sparse cloud, model, annotations."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest
from occlude_scenes import iou, static_scene

from constructaide.bimgeom import meshes_to_glb
from constructaide.camera import pose_to_tuple
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.occlude.node import SPEC, Config
from schemas import keys
from schemas.messages import (
    SPARSE_POINT_FROM_MODEL,
    SPARSE_POINT_VERIFIED,
    Annotation,
    BimModel,
    OcclusionMask,
    Photo,
    Registration,
    SparseCloud,
    ViewpointGroup,
    ViewpointNeighbour,
)

SITE = "t"
DAY_NS = 86_400 * 10**9


def _frames(scene, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The scene with a red vehicle at a different place in each frame; returns images and truth masks."""
    h, w = scene.image.shape[:2]
    images, truths = [], []
    for i in range(n):
        img = scene.image.copy()
        truth = np.zeros((h, w), np.uint8)
        x0 = int(w * (0.1 + 0.25 * i))
        cv2.rectangle(truth, (x0, int(h * 0.6)), (x0 + w // 8, int(h * 0.75)), 255, -1)
        img[truth > 0] = (30, 40, 210)
        images.append(img)
        truths.append(truth)
    return images, truths


def _photo(img: np.ndarray, camera: str | None, t_ns: int) -> Photo:
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    pid = hashlib.sha256(data).hexdigest()[:16]
    return Photo(site=SITE, photo_id=pid, camera_id=camera, capture_time_ns=t_ns, data=data)


def _registration(scene, photo_id: str, camera: str | None) -> Registration:
    """The scene's true camera as an automatic registration of ``photo_id``."""
    return Registration(
        site=SITE,
        photo_id=photo_id,
        camera_id=camera,
        intrinsics=scene.intrinsics,
        world_from_camera=pose_to_tuple(scene.world_from_camera),
        status="auto",
    )


def _is(kind: str, photo_id: str, status: str | None = None):
    def where(key: str, msg: OcclusionMask) -> bool:
        return msg.kind == kind and msg.photo_id == photo_id and (status is None or msg.status == status)

    return where


def _mask(msg: OcclusionMask) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(msg.mask_png, np.uint8), cv2.IMREAD_GRAYSCALE)


@pytest.fixture(scope="module")
def scene():
    return static_scene(5)


def test_node_fixed_camera_static_user_combined(scene) -> None:
    images, truths = _frames(scene, 3)
    photos = [_photo(img, "cam-a", (i + 1) * DAY_NS) for i, img in enumerate(images)]
    model = BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    pts = scene.points_m.astype(np.float32)
    n = len(pts)
    cloud = SparseCloud(
        site=SITE,
        revision=1,
        photo_ids=tuple(p.photo_id for p in photos),
        points_xyz_f32=pts.tobytes(),
        colors_rgb_u8=np.zeros((n, 3), np.uint8).tobytes(),
        obs_point_i32=np.tile(np.arange(n, dtype=np.int32), 3).tobytes(),
        obs_photo_i32=np.repeat(np.arange(3, dtype=np.int32), n).tobytes(),
        obs_pixel_f32=np.tile(scene.pixels_px.astype(np.float32), (3, 1)).tobytes(),
    )
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        errors = bus.collect(keys.pattern(keys.ERRORS, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), photos[0])
        first = got.wait(where=_is("dynamic", photos[0].photo_id))[0][1]
        assert first.status == "not_enough_views" and first.mask_png == b""
        for p in photos[1:]:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), p)
        for i, p in enumerate(photos):
            dyn = got.wait(where=_is("dynamic", p.photo_id, "ok"))[0][1]
            assert dyn.background_jpeg and dyn.num_views >= 1
            assert iou(_mask(dyn), truths[i]) > 0.8
        # the first frame was recomputed once the second arrived (it had no stack), the second once the
        # third arrived (it had no later neighbour), the newest only once
        assert node.wait_idle(30.0)
        dyn_msgs = [m for _, m in got.items if m.kind == "dynamic"]
        assert [sum(m.photo_id == p.photo_id for m in dyn_msgs) for p in photos] == [2, 2, 1]
        # two-pass: each frame's own mask is remembered, so the other frames' stacks leave it out
        for i, p in enumerate(photos):
            occ = node.obj.store.frames[p.photo_id].occluder_small
            assert occ is not None
            small_truth = cv2.resize(truths[i], occ.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
            assert np.count_nonzero(occ & small_truth) > 0.8 * np.count_nonzero(small_truth)

        for p in photos:
            reg = _registration(scene, p.photo_id, "cam-a")
            bus.publish(keys.key(keys.REGISTRATION, site=SITE, camera="cam-a", photo=p.photo_id), reg)
        bus.publish(keys.key(keys.SPARSE, site=SITE), cloud)
        for p in photos:
            st = got.wait(
                where=lambda k, m, pid=p.photo_id: m.kind == "static" and m.photo_id == pid and m.num_views > 0
            )
            assert iou(_mask(st[-1][1]), scene.truth) > 0.7
        # with its camera known, each frame's dynamic mask was redone once with the projected model
        assert node.wait_idle(30.0)
        dyn_msgs = [m for _, m in got.items if m.kind == "dynamic"]
        assert [sum(m.photo_id == p.photo_id for m in dyn_msgs) for p in photos] == [3, 3, 2]
        for i, p in enumerate(photos):
            last = [m for m in dyn_msgs if m.photo_id == p.photo_id][-1]
            assert iou(_mask(last), truths[i]) > 0.8

        poly = ((10.0, 10.0), (200.0, 10.0), (200.0, 120.0), (10.0, 120.0))
        ann = Annotation(site=SITE, annotation_id="a1", kind="occluder", photo_id=photos[1].photo_id, polygon_px=poly)
        bus.publish(keys.key(keys.ANNOTATION, site=SITE, annotation="a1"), ann)
        user1 = got.wait(where=_is("user", photos[1].photo_id))[0][1]
        user2 = got.wait(where=_is("user", photos[2].photo_id))[0][1]
        assert node.wait_idle(30.0)
        assert not any(m.kind == "user" and m.photo_id == photos[0].photo_id for _, m in got.items)
        for u in (user1, user2):
            m = _mask(u)
            assert m[60, 100] == 255 and m[300, 500] == 0
            assert abs(np.count_nonzero(m) - 191 * 111) < 400
        comb = [m for _, m in got.items if m.kind == "combined" and m.photo_id == photos[2].photo_id][-1]
        c = _mask(comb)
        assert c[60, 100] == 255  # user
        assert np.count_nonzero(c[scene.truth > 0]) > 0.7 * np.count_nonzero(scene.truth)  # static
        assert np.count_nonzero(c[truths[2] > 0]) > 0.8 * np.count_nonzero(truths[2])  # dynamic
        # the same registration again: the masks are recomputed to the same pixels, and an unchanged combined
        # mask is not republished (the render node would redraw every mode for nothing)
        before = len(got.items)
        reg2 = _registration(scene, photos[2].photo_id, "cam-a")
        bus.publish(keys.key(keys.REGISTRATION, site=SITE, camera="cam-a", photo=photos[2].photo_id), reg2)
        got.wait(
            where=_is("static", photos[2].photo_id),
            count=len([1 for _, m in got.items if m.kind == "static" and m.photo_id == photos[2].photo_id]) + 1,
        )
        assert node.wait_idle(30.0)
        again = [m for _, m in got.items[before:]]
        assert any(m.kind == "static" for m in again) and not any(m.kind == "combined" for m in again)
        assert errors.items == []


def test_node_phone_photos_use_viewpoint_group(scene) -> None:
    images, truths = _frames(scene, 2)
    # the second phone photo is zoomed: neighbour pixels = 1.1 x this photo's pixels about the centre
    h, w = images[1].shape[:2]
    A = cv2.getRotationMatrix2D((w / 2, h / 2), 0.0, 1.1)
    zoomed = cv2.warpAffine(images[1], A, (w, h))
    photos = [_photo(images[0], None, DAY_NS), _photo(zoomed, None, 2 * DAY_NS)]
    this_from_neighbour = np.linalg.inv(np.vstack([A, [0, 0, 1]]))
    group = ViewpointGroup(
        site=SITE,
        photo_id=photos[0].photo_id,
        neighbours=(
            ViewpointNeighbour(
                photo_id=photos[1].photo_id,
                this_from_neighbour=tuple(float(x) for x in this_from_neighbour.ravel()),
                inlier_ratio=0.9,
                num_matches=200,
            ),
        ),
    )
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus):
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        errors = bus.collect(keys.pattern(keys.ERRORS, site=SITE))
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera=None), p)
        got.wait(where=_is("dynamic", photos[1].photo_id, "not_enough_views"))
        bus.publish(keys.key(keys.VIEWPOINTS, site=SITE, photo=photos[0].photo_id), group)
        dyn = got.wait(where=_is("dynamic", photos[0].photo_id, "ok"))[0][1]
        assert iou(_mask(dyn), truths[0]) > 0.75
        # the group also gives photo 1 its neighbour (inverse homography)
        dyn1 = got.wait(where=_is("dynamic", photos[1].photo_id, "ok"))[0][1]
        assert dyn1.num_views == 1
        bad = ViewpointGroup(
            site=SITE,
            photo_id=photos[0].photo_id,
            neighbours=(
                ViewpointNeighbour(photo_id="x", this_from_neighbour=(1.0, 2.0), inlier_ratio=1, num_matches=9),
            ),
        )
        bus.publish(keys.key(keys.VIEWPOINTS, site=SITE, photo=photos[0].photo_id), bad)
        err = errors.wait()[0][1]
        assert "expected 9" in err.reason


def test_node_keeps_at_most_max_stored_photos(scene) -> None:
    images, _ = _frames(scene, 3)
    photos = [_photo(img, "cam-b", (i + 1) * DAY_NS) for i, img in enumerate(images)]
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE, max_stored_photos=2), bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-b"), p)
        got.wait(where=_is("dynamic", photos[2].photo_id))
        assert node.wait_idle(30.0)
        assert list(node.obj.photos) == [photos[1].photo_id, photos[2].photo_id]
        assert photos[0].photo_id not in node.obj.store.frames
        # the newest frame's stack holds only the frame still kept
        last = [m for _, m in got.items if m.kind == "dynamic" and m.photo_id == photos[2].photo_id][-1]
        assert last.status == "ok" and last.num_views == 1


def test_node_fixed_camera_frames_borrow_the_registered_frames_model_region(scene) -> None:
    images, _ = _frames(scene, 3)
    photos = [_photo(img, "cam-b", (i + 1) * DAY_NS) for i, img in enumerate(images)]
    model = BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-b"), p)
        for p in photos:
            got.wait(where=_is("dynamic", p.photo_id, "ok"))
        assert node.wait_idle(30.0)
        assert not any(node.obj.dynamic_used_region.values())
        # only the middle frame is registered: the others use its projected model (same fixed view)
        reg = _registration(scene, photos[1].photo_id, "cam-b")
        bus.publish(keys.key(keys.REGISTRATION, site=SITE, camera="cam-b", photo=photos[1].photo_id), reg)
        assert node.wait_idle(30.0)
        obj = node.obj
        assert set(obj.model_region) == {photos[1].photo_id}
        assert all(obj.dynamic_used_region[p.photo_id] for p in photos)
        own = obj.model_region[photos[1].photo_id]
        assert own.mean() > 0.05
        for p in (photos[0], photos[2]):
            borrowed = obj._region(p.photo_id)
            assert borrowed is not None and borrowed.shape == own.shape
            assert np.count_nonzero(borrowed & own) / np.count_nonzero(borrowed | own) > 0.95


def test_node_fast_path_frames_take_their_cameras_static_mask(scene) -> None:
    """Only the first frame of a fixed camera has sparse observations (a key image); the others, registered by
    the fast path without features, take its static mask. Points flagged as BIM-depth or not verified by
    guided matching are not used."""
    images, _ = _frames(scene, 3)
    photos = [_photo(img, "cam-a", (i + 1) * DAY_NS) for i, img in enumerate(images)]
    model = BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    pts = scene.points_m.astype(np.float32)
    n = len(pts)
    flags = np.full(n, SPARSE_POINT_VERIFIED, np.uint8)
    flags[::3] = SPARSE_POINT_FROM_MODEL | SPARSE_POINT_VERIFIED  # dropped: looked up on the BIM
    flags[1::3] = 0  # dropped: blind matches
    cloud = SparseCloud(
        site=SITE,
        revision=1,
        photo_ids=(photos[0].photo_id,),
        points_xyz_f32=pts.tobytes(),
        colors_rgb_u8=np.zeros((n, 3), np.uint8).tobytes(),
        obs_point_i32=np.arange(n, dtype=np.int32).tobytes(),
        obs_photo_i32=np.zeros(n, np.int32).tobytes(),
        obs_pixel_f32=scene.pixels_px.astype(np.float32).tobytes(),
        point_flags_u8=flags.tobytes(),
    )
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE), bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        bus.publish(keys.key(keys.BIM_MODEL, site=SITE), model, latched=True)
        bus.publish(keys.key(keys.SPARSE, site=SITE), cloud, latched=True)
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), p)
            reg = _registration(scene, p.photo_id, "cam-a")
            bus.publish(keys.key(keys.REGISTRATION, site=SITE, camera="cam-a", photo=p.photo_id), reg)
        assert node.wait_idle(60.0)
        last = {}
        for _, m in got.items:
            if m.kind == "static":
                last[m.photo_id] = m
        judged = last[photos[0].photo_id].num_views
        # only the verified points (a third of the cloud) are judged; a bit over half of them show the model
        assert 0 < judged <= 0.6 * np.count_nonzero(flags == SPARSE_POINT_VERIFIED)
        assert iou(_mask(last[photos[0].photo_id]), scene.truth) > 0.7
        for p in photos[1:]:
            m = last[p.photo_id]
            assert m.status == "ok" and m.num_views == 0  # no points of its own
            assert node.obj.static_borrowed[p.photo_id] == photos[0].photo_id
            assert iou(_mask(m), scene.truth) > 0.7


def _vehicle(img: np.ndarray, x0: int, y0: int, bw: int, bh: int) -> tuple[np.ndarray, np.ndarray]:
    """A copy of ``img`` with the red vehicle of ``_frames`` at (x0, y0), and its truth mask."""
    out = img.copy()
    truth = np.zeros(img.shape[:2], np.uint8)
    cv2.rectangle(truth, (x0, y0), (x0 + bw, y0 + bh), 255, -1)
    out[truth > 0] = (30, 40, 210)
    return out, truth


@pytest.mark.parametrize("appearance", ["all", "off"])
def test_node_labels_photos_without_a_stack_by_colour(scene, appearance: str) -> None:
    h, w = scene.image.shape[:2]
    fixed = [_vehicle(scene.image, int(w * (0.05 + 0.14 * i)), int(h * 0.6), w // 8, h // 7)[0] for i in range(6)]
    # a phone photo from elsewhere (here: the scene mirrored), no viewpoint group: no stack
    phone_img, phone_truth = _vehicle(np.ascontiguousarray(scene.image[:, ::-1]), w // 3, h // 2, w // 6, h // 6)
    phone = _photo(phone_img, None, 3 * DAY_NS)
    photos = [_photo(img, "cam-c", (i + 1) * DAY_NS) for i, img in enumerate(fixed)]
    with LocalBus() as bus, start_node(SPEC, Config(site=SITE, dynamic_appearance=appearance), bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera=None), phone)
        got.wait(where=_is("dynamic", phone.photo_id, "not_enough_views"))  # the colour model knows nothing yet
        for p in photos:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-c"), p)
        for p in photos:
            got.wait(where=_is("dynamic", p.photo_id, "ok"))
        assert node.wait_idle(30.0)
        obj = node.obj
        # every fixed frame's time-lapse mask was learnt but the newest's (provisional until a later frame comes)
        assert obj.colour.num_frames == len(photos) - 1 and photos[-1].photo_id not in obj.colour.per_photo
        last = [m for _, m in got.items if m.kind == "dynamic" and m.photo_id == phone.photo_id][-1]
        if appearance == "off":
            assert last.status == "not_enough_views" and last.mask_png == b""
            return
        # redone once the model had seen enough masks: labelled by colour alone
        assert last.status == "ok" and last.num_views == 0 and last.background_jpeg == b""
        assert iou(_mask(last), phone_truth) > 0.8
        assert phone.photo_id in obj.dynamic_no_stack
        combined = [m for _, m in got.items if m.kind == "combined" and m.photo_id == phone.photo_id][-1]
        assert combined.status == "ok" and iou(_mask(combined), phone_truth) > 0.8


@pytest.mark.parametrize("appearance", ["all", "no_stack"])
def test_node_redoes_fixed_camera_frames_as_the_colour_model_grows(scene, appearance: str) -> None:
    """A vehicle parked in every frame is invisible to the time-lapse; the colour model, ready after five learnt
    masks (a camera's newest frame is learnt only once the next frame refined it), labels it. Frames whose masks
    were made before that are redone from the idle hook, newest first, one per call (the colour step only: same
    clean plate; the newest frame, not learnt, in full), and not again until the model has grown by
    ``appearance_refresh_growth``. With ``"no_stack"`` time-lapse masks are left alone."""
    h, w = scene.image.shape[:2]
    parked_img, parked = _vehicle(scene.image, int(w * 0.7), int(h * 0.12), w // 12, h // 10)
    frames = [_vehicle(parked_img, int(w * (0.04 + 0.12 * i)), int(h * 0.6), w // 9, h // 7) for i in range(7)]
    photos = [_photo(img, "cam-d", (i + 1) * DAY_NS) for i, (img, _) in enumerate(frames)]
    ids = [p.photo_id for p in photos]
    config = Config(site=SITE, dynamic_appearance=appearance, appearance_refresh_per_idle=1)

    def dynamic_since(start: int) -> list[OcclusionMask]:
        return [m for _, m in got.items[start:] if m.kind == "dynamic"]

    def parked_share(msg: OcclusionMask) -> float:
        return float(np.count_nonzero(_mask(msg)[parked > 0])) / np.count_nonzero(parked)

    with LocalBus() as bus, start_node(SPEC, config, bus) as node:
        got = bus.collect(keys.pattern(keys.OCCLUSION, site=SITE))
        for p in photos[:5]:
            bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-d"), p)
        got.wait(where=_is("dynamic", ids[4], "ok"))
        assert node.wait_idle(30.0)
        obj = node.obj
        # not ready yet (the newest frame is not learnt): time-lapse masks only, the parked vehicle missed
        assert obj.colour.num_frames == 4 and ids[4] not in obj.colour.per_photo
        before = {m.photo_id: m for m in dynamic_since(0)}  # the last of each
        assert all(m.status == "ok" and parked_share(m) < 0.1 for m in before.values())
        start = len(got.items)
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-d"), photos[5])
        got.wait(where=_is("dynamic", ids[5], "ok"))
        assert node.wait_idle(30.0)
        assert obj.colour.num_frames == 5 and obj._appearance_due() == []
        after = dynamic_since(start)
        # the handler's own work: the new frame, the previous newest frame refined (and then learnt: ready)
        assert [m.photo_id for m in after[:2]] == [ids[5], ids[4]]
        plates = {**before, ids[4]: after[1], ids[5]: after[0]}
        redone = after[2:]
        if appearance == "no_stack":
            assert redone == [] and all(parked_share(m) < 0.1 for m in after)
            return
        # every frame made before the model was ready, newest first
        assert [m.photo_id for m in redone] == [ids[5], ids[4], ids[3], ids[2], ids[1], ids[0]]
        for m in redone:
            assert m.status == "ok" and parked_share(m) > 0.8
            assert m.num_views == plates[m.photo_id].num_views > 0
            truth = frames[ids.index(m.photo_id)][1] | parked
            assert iou(_mask(m), truth) > 0.7
        # the learnt frames got the colour step alone: the clean plate they had
        assert all(m.background_jpeg == plates[m.photo_id].background_jpeg != b"" for m in redone[1:])
        last = {m.photo_id: m for _, m in got.items if m.kind == "combined"}
        assert all(parked_share(last[pid]) > 0.8 for pid in ids[:6])
        # one more mask (6 < 5 x 1.25): nothing is redone but the frame and its predecessor
        start = len(got.items)
        bus.publish(keys.key(keys.PHOTO, site=SITE, camera="cam-d"), photos[6])
        got.wait(where=_is("dynamic", ids[6], "ok"))
        assert node.wait_idle(30.0)
        assert obj.colour.num_frames == 6
        assert [m.photo_id for m in dynamic_since(start)] == [ids[6], ids[5]]
        assert parked_share(dynamic_since(start)[0]) > 0.8
        # the idle hook does at most appearance_refresh_per_idle redos per call and says when more are due
        for pid in ids:
            obj.dynamic_colour_seen[pid] = 0  # (the worker is idle: no message waits)
        assert len(obj._appearance_due()) == 7
        assert obj.idle() is True and len(obj._appearance_due()) == 6
        calls = 1
        while obj.idle():
            calls += 1
        assert calls == 6 and obj._appearance_due() == []
