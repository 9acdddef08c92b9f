"""The occlude node's policy without a bus (``nodes.occlude.pipeline.OcclusionPipeline``): config checks, static-mask
borrowing between a fixed camera's frames and the re-runs it triggers, model changes."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest
from occlude_scenes import iou, static_scene

from constructaide.bimgeom import meshes_to_glb
from constructaide.camera import pose_to_tuple
from constructaide.imagecodec import decode_mask
from nodes.occlude.pipeline import Config, OcclusionPipeline
from schemas.messages import BimModel, OcclusionMask, Photo, Registration, SparseCloud

SITE = "t"
DAY_NS = 86_400 * 10**9


class Emitted:
    """Collects what the pipeline emits."""

    def __init__(self) -> None:
        self.items: list[OcclusionMask] = []

    def __call__(self, msg: OcclusionMask, mask: np.ndarray | None) -> None:
        assert (mask is not None) == (msg.status == "ok" and bool(msg.mask_png))
        self.items.append(msg)

    def since(self, start: int, kind: str) -> list[OcclusionMask]:
        return [m for m in self.items[start:] if m.kind == kind]

    def last(self, kind: str, photo_id: str) -> OcclusionMask:
        return [m for m in self.items if m.kind == kind and m.photo_id == photo_id][-1]


@pytest.fixture(scope="module")
def scene():
    return static_scene(5)


def _photo(img: np.ndarray, camera: str | None, t_ns: int) -> Photo:
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    return Photo(
        site=SITE, photo_id=hashlib.sha256(data).hexdigest()[:16], camera_id=camera, capture_time_ns=t_ns, data=data
    )


def _registration(scene, photo_id: str) -> Registration:
    return Registration(
        site=SITE,
        photo_id=photo_id,
        camera_id="cam-a",
        intrinsics=scene.intrinsics,
        world_from_camera=pose_to_tuple(scene.world_from_camera),
        status="auto",
    )


def _cloud(scene, observers: dict[str, slice], revision: int) -> SparseCloud:
    """The scene's points, observed by each photo of ``observers`` on its slice of the points."""
    pts = scene.points_m.astype(np.float32)
    ids = list(observers)
    obs_point = np.concatenate([np.arange(len(pts), dtype=np.int32)[s] for s in observers.values()])
    obs_photo = np.concatenate(
        [np.full(len(range(*s.indices(len(pts)))), i, np.int32) for i, s in enumerate(observers.values())]
    )
    obs_pixel = scene.pixels_px.astype(np.float32)[obs_point]
    return SparseCloud(
        site=SITE,
        revision=revision,
        photo_ids=tuple(ids),
        points_xyz_f32=pts.tobytes(),
        colors_rgb_u8=np.zeros((len(pts), 3), np.uint8).tobytes(),
        obs_point_i32=obs_point.tobytes(),
        obs_photo_i32=obs_photo.tobytes(),
        obs_pixel_f32=obs_pixel.tobytes(),
    )


def _frames(scene, n: int) -> list[Photo]:
    """``n`` frames of one fixed camera: the scene with slightly different noise (a distinct photo each)."""
    rng = np.random.default_rng(1)
    out = []
    for i in range(n):
        img = np.clip(scene.image.astype(np.int16) + rng.integers(-2, 3, scene.image.shape), 0, 255).astype(np.uint8)
        out.append(_photo(img, "cam-a", (i + 1) * DAY_NS))
    return out


def test_config_selects_dynamic_score_and_alignment_and_rejects_unknown_values() -> None:
    vote = OcclusionPipeline(Config(site=SITE), Emitted())
    assert vote.dyn_params.vote_quantile == 0.5 and vote.store.fixed_alignment == "homography"
    assert vote.dyn_params.appearance == "all" and vote.dyn_params.appearance_veto == 0.2
    paper = OcclusionPipeline(
        Config(site=SITE, dynamic_score="median", dynamic_threshold=0.05, fixed_alignment="shift"), Emitted()
    )
    assert paper.dyn_params.vote_quantile is None and paper.dyn_params.threshold == 0.05
    assert paper.store.fixed_alignment == "shift"
    for bad, match in (
        ({"dynamic_score": "mean"}, "dynamic_score"),
        ({"dynamic_appearance": "colour"}, "dynamic_appearance"),
        ({"fixed_alignment": "affine"}, "fixed_alignment"),
        ({"stack_selection": "random"}, "stack_selection"),
        ({"appearance_refresh_per_idle": 0}, "appearance_refresh_per_idle"),
    ):
        with pytest.raises(ValueError, match=match):
            OcclusionPipeline(Config(site=SITE, **bad), Emitted())  # type: ignore[arg-type]


def test_static_borrowing_follows_its_donor_and_moves_to_a_better_one(scene) -> None:
    """Frames without sparse points take the static mask of the camera's frame that judged the most points; they
    are redone when that donor's mask changes, move to a frame that judges more, and stop borrowing once they
    judge enough points of their own."""
    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE, static_borrow_below_points=20), out)
    a, b, c = _frames(scene, 3)
    n = len(scene.points_m)
    pipe.set_model(
        BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    )
    pipe.set_sparse(_cloud(scene, {a.photo_id: slice(0, n // 2)}, 1))  # only a observes points
    for p in (a, b, c):
        pipe.add_photo(p)
        pipe.add_registration(_registration(scene, p.photo_id))
    judged_a = out.last("static", a.photo_id).num_views
    assert judged_a >= 20
    assert pipe.static_borrowed == {b.photo_id: a.photo_id, c.photo_id: a.photo_id}
    for p in (b, c):
        m = out.last("static", p.photo_id)
        assert m.status == "ok" and m.num_views == 0  # none judged by itself
        assert iou(decode_mask(m.mask_png).astype(np.uint8) * 255, scene.truth) > 0.7
        # the combined mask holds the borrowed static one
        assert decode_mask(out.last("combined", p.photo_id).mask_png).sum() >= decode_mask(m.mask_png).sum()

    # the donor is registered again: its static mask is redone, and so are the masks borrowed from it
    start = len(out.items)
    pipe.add_registration(_registration(scene, a.photo_id))
    assert [m.photo_id for m in out.since(start, "static")] == [a.photo_id, b.photo_id, c.photo_id]

    # b comes to observe every point (more than a): it judges for itself, and c moves to it as the better donor
    start = len(out.items)
    pipe.set_sparse(_cloud(scene, {a.photo_id: slice(0, n // 2), b.photo_id: slice(0, n)}, 2))
    redone = [m.photo_id for m in out.since(start, "static")]
    assert b.photo_id in redone and c.photo_id in redone and a.photo_id not in redone  # a's observations held
    assert out.last("static", b.photo_id).num_views > judged_a
    assert pipe.static_borrowed == {c.photo_id: b.photo_id}

    # the donor leaves the store: nothing borrows from a forgotten frame
    pipe._forget(b.photo_id)
    assert pipe.static_borrowed == {}
    pipe.close()


def test_camera_cap_keeps_the_static_donor(scene) -> None:
    """The per-camera cap drops a camera's earliest frames, but not the one its frames without sparse points borrow
    the static mask from (in a stream the frames with points are the register node's earliest, its map)."""
    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE, max_photos_per_camera=3, static_borrow_below_points=20), out)
    frames = _frames(scene, 6)
    pipe.set_model(
        BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    )
    pipe.set_sparse(_cloud(scene, {frames[0].photo_id: slice(0, len(scene.points_m))}, 1))
    for p in frames:
        pipe.add_photo(p)
        pipe.add_registration(_registration(scene, p.photo_id))
    kept = [p.photo_id for p in frames if p.photo_id in pipe.photos]
    assert kept == [frames[0].photo_id, frames[4].photo_id, frames[5].photo_id]
    assert len(pipe.store.by_camera["cam-a"]) == 3
    last = out.last("static", frames[5].photo_id)
    assert last.status == "ok" and last.num_views == 0 and pipe.static_borrowed[frames[5].photo_id] == kept[0]
    pipe.close()


def test_static_borrowing_off_and_phone_photos_never_borrow(scene) -> None:
    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE, static_borrow_below_points=0), out)
    a, b = _frames(scene, 2)
    n = len(scene.points_m)
    pipe.set_model(BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes)))
    pipe.set_sparse(_cloud(scene, {a.photo_id: slice(0, n)}, 1))
    for p in (a, b):
        pipe.add_photo(p)
        pipe.add_registration(_registration(scene, p.photo_id))
    assert pipe.static_borrowed == {}
    pipe.close()

    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE), out)
    phone = _photo(scene.image, None, DAY_NS)
    pipe.set_model(BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes)))
    pipe.add_photo(phone)
    pipe.add_registration(msgspec_replace(_registration(scene, phone.photo_id), camera_id=None))
    assert pipe.static_borrowed == {}
    pipe.close()


def msgspec_replace(msg: Registration, **changes: object) -> Registration:
    import msgspec

    return msgspec.structs.replace(msg, **changes)


def test_a_new_model_redoes_every_registered_static_mask_with_its_terrain(scene) -> None:
    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE), out)
    a, b = _frames(scene, 2)
    for p in (a, b):
        pipe.add_photo(p)
        pipe.add_registration(_registration(scene, p.photo_id))
    assert out.since(0, "static") == []  # no model yet
    glb = meshes_to_glb(scene.model_meshes)
    pipe.set_model(BimModel(site=SITE, revision="r1", geometry_glb=glb, terrain_height_m=0.0))
    first = {m.photo_id: m for m in out.since(0, "static")}
    assert set(first) == {a.photo_id, b.photo_id}
    # no sparse points: the ground rule alone (model surface below the model's terrain) makes the mask
    assert all(m.status == "ok" for m in first.values())
    start = len(out.items)
    pipe.set_model(BimModel(site=SITE, revision="r2", geometry_glb=glb, terrain_height_m=-5.0))
    second = {m.photo_id: m for m in out.since(start, "static")}
    assert set(second) == {a.photo_id, b.photo_id}
    # the terrain 5 m lower leaves the basement above ground: less (here: none) of the model counts as buried

    def area(m: OcclusionMask) -> int:
        return int(decode_mask(m.mask_png).sum()) if m.mask_png else 0

    assert area(first[a.photo_id]) > 0 and area(second[a.photo_id]) < area(first[a.photo_id])
    pipe.close()


def test_static_masks_follow_their_dynamic_masks(scene) -> None:
    """A static mask leaves out the photo's dynamic occluders as they are now: when a dynamic mask is redone (here:
    the first frame gets a stack once the second arrives) the static mask is republished, and a frame that borrows
    takes its donor's static occluders without the donor's own dynamic ones."""
    h, w = scene.image.shape[:2]
    photos, vehicles = [], []
    for i in range(3):
        img = scene.image.copy()
        truth = np.zeros((h, w), np.uint8)
        x0 = int(w * (0.1 + 0.25 * i))
        cv2.rectangle(truth, (x0, int(h * 0.55)), (x0 + w // 6, int(h * 0.8)), 255, -1)
        img[truth > 0] = (30, 40, 210)
        photos.append(_photo(img, "cam-a", (i + 1) * DAY_NS))
        vehicles.append(truth > 0)
    out = Emitted()
    pipe = OcclusionPipeline(Config(site=SITE), out)
    n = len(scene.points_m)
    pipe.set_model(
        BimModel(site=SITE, revision="r1", geometry_glb=meshes_to_glb(scene.model_meshes), terrain_height_m=0.0)
    )
    pipe.set_sparse(_cloud(scene, {photos[0].photo_id: slice(0, n)}, 1))  # frame 0 judges; 1 and 2 borrow
    start = {}
    for p in photos:
        start[p.photo_id] = len(out.items)
        pipe.add_photo(p)
        pipe.add_registration(_registration(scene, p.photo_id))
    first = photos[0].photo_id
    # frame 0 had no stack when its static mask was made; its dynamic mask came with the second frame, and its
    # static mask was published again after that
    kinds = [(m.kind, m.status) for m in out.items if m.photo_id == first and m.kind in ("dynamic", "static")]
    first_dyn_ok = kinds.index(("dynamic", "ok"))
    assert ("static", "ok") in kinds[first_dyn_ok + 1 :]
    assert pipe.static_borrowed == {photos[1].photo_id: first, photos[2].photo_id: first}
    for p, vehicle in zip(photos, vehicles, strict=True):
        static = decode_mask(out.last("static", p.photo_id).mask_png)
        dynamic = decode_mask(out.last("dynamic", p.photo_id).mask_png)
        raw = decode_mask(pipe.static_raw[p.photo_id][1])
        assert dynamic[vehicle].mean() > 0.8  # the vehicle is found
        assert np.array_equal(static, raw & ~dynamic)  # the static mask is the raw one minus the current dynamic
        assert not (static & dynamic).any()
    # the donor's raw static mask is what frame 1 borrowed (warped by an identity-like homography): the donor's
    # vehicle pixels are not cut out of it
    donor_raw = decode_mask(pipe.static_raw[first][1])
    donor_static = decode_mask(out.last("static", first).mask_png)
    cut = donor_raw & ~donor_static  # where the donor's dynamic mask took pixels out
    assert cut.sum() > 100
    borrowed_raw = decode_mask(pipe.static_raw[photos[1].photo_id][1])
    assert borrowed_raw[cut].mean() > 0.5
    pipe.close()
