"""One registration engine: one anchor bootstraps a collection (batch and streaming), a knocked fixed camera is
re-registered without clicks, batch and streaming agree on the same photos. Seeded synthetic scenes with tolerance
bands (several seeds)."""

from __future__ import annotations

import numpy as np
import pytest
from test_register_batch_sfm import arc_cameras, arc_reconstruction, clicks_for, make_features, scene_points
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide import camera as cam
from nodes.register import config, mapper, sfm
from nodes.register import recon as rc
from nodes.register.features import extract_features
from nodes.register.photo import FrameImage, PhotoInput
from nodes.register.streaming import StreamConfig, StreamingRegistrar

F = 900.0


@pytest.mark.parametrize("seed", [3, 5, 9])
def test_one_anchor_registers_the_arc_and_fixes_its_scale(seed: int) -> None:
    """Seven views of a building corner on an arc, clicks for the first only and no answer to any request: the
    relative-pose bootstrap places a second view (its baseline's length from the anchor's clicks), the others
    follow by PnP; every view within 1 % of the camera distance and 0.3 deg, so the scale is right."""
    rng = np.random.default_rng(seed)
    recon, pts, poses = arc_reconstruction(rng)
    asked: list[str] = []

    def request(name: str, reason: str, n: int):
        asked.append(reason)
        return None

    sfm.reconstruct(recon, {"view0": clicks_for(rng, pts, poses[0])}, config.MapperConfig(focal_px=F), request)
    methods = [im.method for im in recon.images]
    assert all(im.registered for im in recon.images), [(im.name, im.message) for im in recon.images]
    assert "relative" in methods and methods.count("anchor") == 1, methods
    for k, T in enumerate(poses):
        im = recon.images[k]
        dist = np.linalg.norm(T[:3, 3] - np.array([1.0, -2.0, 2.5]))
        assert np.linalg.norm(im.pose[:3, 3] - T[:3, 3]) < 0.01 * dist, (im.name, im.method)
        assert cam.viewing_angle_deg(im.pose, T) < 0.3, (im.name, im.method)
    # Only a second anchor was asked for: once when the bootstrap was needed (the widest view), once at the end for
    # accuracy (the frame rests on one photo's clicks); nothing else.
    assert len(asked) == 2 and asked[1].startswith("accuracy"), asked


def test_relative_pose_refuses_a_rotation_and_a_disagreeing_scale() -> None:
    """A view from the anchor's own centre has no baseline to measure (one rotation explains the matches), nor has
    one turned and moved 0.57 m at 20 m (a rotation explains the matches to a pixel or so: lens errors would pick
    the motion); clicks whose model points contradict the two views' geometry (a scale that differs from click to
    click) are refused."""
    rng = np.random.default_rng(2)
    pts = scene_points(rng)
    desc = rng.normal(size=(len(pts), 128))
    T0 = arc_cameras(3)[0]
    turned = T0.copy()
    turned[:3, :3] = T0[:3, :3] @ cam.rodrigues_to_matrix([0.0, np.radians(6.0), 0.0])
    moved = arc_cameras(3)[1]
    knocked = turned.copy()  # turned by 6 deg and moved 0.57 m, 20 m from the scene: a knocked mast camera
    knocked[:3, 3] += knocked[:3, :3] @ np.array([0.5, 0.2, 0.2])
    cfg = config.MapperConfig(focal_px=F)
    cases = ((turned, "one rotation explains"), (knocked, "too short a baseline"), (moved, "disagree (only"))
    for other, expect in cases:
        recon = rc.Reconstruction()
        for name, T in (("a", T0), ("b", other)):
            rc.add_image(recon, name, make_features(rng, pts, desc, T)[0])
        from nodes.register.matching import match_image

        match_image(recon, 1, [0], cfg)
        px, world = clicks_for(rng, pts, T0, n=10)
        if expect.startswith("disagree"):  # model points stretched away from the camera by 1.0 ... 1.6 (not one scale)
            c = T0[:3, 3]
            world = c + (world - c) * np.linspace(1.0, 1.6, len(world))[:, None]
        mapper.register_anchor(recon, 0, (px, world), cfg)
        assert not mapper.try_relative_pose(recon, 0, 1, cfg)
        assert expect in recon.images[1].message, recon.images[1].message


def test_relative_pose_bounds_its_parallax_and_defers_to_the_check() -> None:
    """The arc's second view is placed from the anchored first (seeds 3 / 5 / 9 above); a median parallax above
    ``bootstrap_max_parallax_deg`` is refused (no descriptor matches across such a change: a motion of wrong
    matches), and so is a pose the ``check`` (the model's outlines in the nodes) refuses, its reason named."""
    from nodes.register.matching import match_image

    for seed in (3, 5):
        rng = np.random.default_rng(seed)
        results = {}
        for case in ("plain", "narrow", "checked", "check passes"):
            recon, pts, poses = arc_reconstruction(np.random.default_rng(seed), n_views=4)
            cfg = config.MapperConfig(focal_px=F, bootstrap_max_parallax_deg=2.5 if case == "narrow" else 60.0)
            match_image(recon, 1, [0], cfg)
            mapper.register_anchor(recon, 0, clicks_for(rng, pts, poses[0]), cfg)
            seen: list[int] = []

            def check(i: int, intr, wfc: np.ndarray, case: str = case, seen: list = seen) -> str:  # noqa: ANN001
                seen.append(i)
                return "the outline says no" if case == "checked" else ""

            ok = mapper.try_relative_pose(recon, 0, 1, cfg, check if case.startswith("check") else None)
            results[case] = (ok, recon.images[1].message, list(seen))
        assert results["plain"][0], results["plain"][1]
        assert not results["narrow"][0] and "too wide to match" in results["narrow"][1], results["narrow"][1]
        assert not results["checked"][0] and results["checked"][1].endswith("refused: the outline says no")
        assert results["checked"][2] == [1]
        assert results["check passes"][0] and results["check passes"][2] == [1]


def test_a_fixed_camera_frame_is_placed_relative_to_its_own_camera_only() -> None:
    """A knocked frame of fixed camera A, with A's anchored frame registered, is not placed by a relative motion to
    another camera's frame (B; CI saw such a motion put a knocked camera 2.7 deg and 3 m off), while a frame of
    a camera with no registered frame of its own, and a phone photo, still are tried from B. The same when the knock
    left the frame no verified pair with A's frame."""
    rng = np.random.default_rng(6)
    pts = scene_points(rng)
    desc = rng.normal(size=(len(pts), 128))
    T_a, T_b, T_c = arc_cameras(3)
    knocked = T_a.copy()
    knocked[:3, :3] = T_a[:3, :3] @ cam.rodrigues_to_matrix(np.radians([1.0, 6.0, 0.5]))
    knocked[:3, 3] += knocked[:3, :3] @ np.array([0.4, 0.2, 0.1])
    cfg = config.MapperConfig(focal_px=F)
    from nodes.register.matching import match_image

    views = (("a0", T_a, "cam-a"), ("b0", T_b, "cam-b"), ("k", knocked, "cam-a"), ("c0", T_c, "cam-c"))
    recon = rc.Reconstruction()
    for name, T, cam_id in views:
        rc.add_image(recon, name, make_features(rng, pts, desc, T)[0], camera_id=cam_id)
    for i in range(1, len(views)):
        match_image(recon, i, list(range(i)), cfg)
    mapper.register_anchor(recon, 0, clicks_for(rng, pts, T_a, n=10), cfg)
    mapper.register_anchor(recon, 1, clicks_for(rng, pts, T_b, n=10), cfg)
    assert not mapper.try_relative_pose(recon, 1, 2, cfg)
    assert "another camera" in recon.images[2].message, recon.images[2].message
    recon.pairs = {k: v for k, v in recon.pairs.items() if set(k) != {0, 2}}  # the knock broke its pair with a0
    assert recon.pair(0, 2) is None
    assert not mapper.try_relative_pose(recon, 1, 2, cfg)
    assert "another camera" in recon.images[2].message, recon.images[2].message
    for cam_id in (None, "cam-c"):  # a phone photo, then a camera without registered frames: tried from B
        recon.images[3].camera_id = cam_id
        mapper.try_relative_pose(recon, 1, 3, cfg)
        assert "another camera" not in recon.images[3].message


W, H = 640, 360


@pytest.fixture(scope="module")
def scene() -> PlaneScene:
    return PlaneScene(4)


def photo(scene: PlaneScene, pid: str, intr, T, t_ns: int, camera_id: str | None = "cam-a") -> PhotoInput:
    return PhotoInput(pid, FrameImage(encode_jpeg(scene.render(intr, T))), camera_id=camera_id, capture_time_ns=t_ns)


def model_offset_px(scene: PlaneScene, intr, world_from_camera: np.ndarray, reg) -> float:
    """Median distance (px) between a grid of the scene's points as the true camera (``intr``, ``world_from_camera``)
    sees them and where the registration ``reg`` projects them: how far off the model would be drawn."""
    grid = np.stack(np.meshgrid(np.linspace(40, W - 40, 12), np.linspace(30, H - 30, 7)), -1).reshape(-1, 2)
    z = scene.depth_lookup(world_from_camera, intr, grid)
    ok = np.isfinite(z)
    xy = cam.pixels_to_normalized(intr, grid[ok])
    X = np.c_[xy * z[ok, None], z[ok]] @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    est, _ = cam.project_points(reg.intrinsics, cam.invert_rigid(cam.pose_from_tuple(reg.world_from_camera)), X)
    return float(np.median(np.linalg.norm(est - grid[ok], axis=1)))


def test_knocked_fixed_camera_is_reregistered_without_clicks(scene) -> None:
    """A mast camera anchored once, tracked for three frames, then knocked (0.6 m, 7 deg): the fast path fails and
    the full path registers it again without new clicks (on this facade-dominated scene one homography may still
    explain the view: then a rotation about the old centre; else PnP on its own camera's model points), with the
    model where it should be in the photo (facade points within 0.5 % of the width), and tracking resumes."""
    intr, T = mast_camera(W, H)
    reg = StreamingRegistrar(StreamConfig(), depth_lookup=scene.depth_lookup, site="t")
    px, pts = anchor_clicks(intr, T, noise_px=0.5, seed=2)
    reg.register_anchor(photo(scene, "a0", intr, T, 0), px, pts)
    rng = np.random.default_rng(5)
    for i in range(3):
        ij, Tj = jitter(T, intr, rng, rot_deg=0.2, zoom=0.005)
        assert reg.register(photo(scene, f"f{i}", ij, Tj, (i + 1) * 10**9)).registration.method == "fastpath"
    knocked = T.copy()
    knocked[:3, :3] = T[:3, :3] @ cam.rodrigues_to_matrix(np.radians([3.0, 7.0, 1.5]))
    knocked[:3, 3] += [0.5, 0.3, -0.1]
    out = reg.register(photo(scene, "k0", intr, knocked, 5 * 10**9))
    r = out.registration
    assert r.status == "auto" and r.method in ("homography", "pnp", "relative"), r.message
    assert "bumped" in r.message or "re-aimed" in r.message or "moved" in r.message
    assert model_offset_px(scene, intr, knocked, r) < 0.005 * W
    ij, Tj = jitter(knocked, intr, rng, rot_deg=0.2, zoom=0.005)
    assert reg.register(photo(scene, "k1", ij, Tj, 6 * 10**9)).registration.method == "fastpath"


def test_bim_depth_arriving_after_the_anchor_still_serves_it(scene) -> None:
    """The BIM model reaches the register node after the camera's anchor registered (its depth renderer still
    starting): once the lookup is set, the anchor gets its model points (``add_model_points_to_map``), once. (A
    CI run of the demo asked for clicks for a knocked camera's frames with "only 12 matches to triangulated
    tracks" and "no known depth in <anchor>", where other runs registered them by PnP on 586: the anchors had
    registered before the lookup.) On this facade scene the knocked frame registers either way (homography); it
    still does, with the model within 0.5 % of the width."""
    intr, T = mast_camera(W, H)
    reg = StreamingRegistrar(StreamConfig(), depth_lookup=None, site="t")
    px, pts = anchor_clicks(intr, T, noise_px=0.5, seed=2)
    reg.register_anchor(photo(scene, "a0", intr, T, 0), px, pts)
    assert reg.add_model_points_to_map() == 0  # no lookup yet
    reg.depth_lookup = scene.depth_lookup
    added = reg.add_model_points_to_map()
    a0 = reg.recon.images[reg.recon.index("a0")]
    ft = reg.recon.feature_track[reg.recon.index("a0")]
    assert added > 100 and reg.recon.point_from_model[ft[ft >= 0]].sum() >= added
    assert reg.add_model_points_to_map() == 0, "a second call adds nothing: features with a point keep it"
    knocked = T.copy()
    knocked[:3, :3] = T[:3, :3] @ cam.rodrigues_to_matrix(np.radians([3.0, 7.0, 1.5]))
    knocked[:3, 3] += [0.5, 0.3, -0.1]
    r = reg.register(photo(scene, "k0", intr, knocked, 5 * 10**9)).registration
    assert r.status == "auto", r.message
    assert model_offset_px(scene, intr, knocked, r) < 0.005 * W
    assert a0.status == "anchor"


@pytest.mark.parametrize("seed", [3, 7, 8])
def test_knocked_fixed_camera_without_bim_depth_is_never_published_off(scene, seed: int) -> None:
    """Without BIM depth nothing tells a knocked mast camera's moved centre (0.4-0.7 m, 5-8 deg) from a turn about
    its old one: a frame that a rotation about the old centre fits worse than a mount's jitter (half the fast
    path's RMS limit) is not published from that fit, but registered by the full path (model within 0.5 % of the
    width) or asked for clicks. The old fast path published seed 8's frame with the model 0.58 % of the width
    off."""
    rng = np.random.default_rng(seed)
    intr, T = mast_camera(W, H)
    reg = StreamingRegistrar(StreamConfig(), site="t")
    px, pts = anchor_clicks(intr, T, noise_px=1.0, seed=seed)
    reg.register_anchor(photo(scene, "a0", intr, T, 0), px, pts)
    ij, Tj = jitter(T, intr, rng, rot_deg=0.2, zoom=0.0)
    assert reg.register(photo(scene, "f0", ij, Tj, 10**9)).registration.method == "fastpath"
    knocked = T.copy()
    knocked[:3, :3] = T[:3, :3] @ cam.rodrigues_to_matrix(np.radians(rng.uniform(-1, 1, 3) * [2.0, 8.0, 1.5]))
    knocked[:3, 3] += knocked[:3, :3] @ (rng.uniform(0.4, 0.7) * np.r_[rng.normal(size=2), 0.2] / np.sqrt(2))
    out = reg.register(photo(scene, "k0", intr, knocked, 5 * 10**9))
    r = out.registration
    if r.status == "failed":
        assert out.needs_anchor, r.message
        return
    assert model_offset_px(scene, intr, knocked, r) < 0.005 * W, (r.method, r.message)


def test_batch_and_streaming_agree_on_the_same_photos(scene) -> None:
    """Four photos of the plane scene from four places, one anchored: the batch (sfm.reconstruct on the same
    features) and the streaming registrar give the same poses within 0.3 deg and 1 % of the camera distance."""
    ip = cam.centered_intrinsics(W, H, cam.focal_from_fov(W, 55.0))
    eyes = [(-6.0, -2.0, 1.7), (-2.0, -3.0, 1.8), (2.0, -3.0, 1.6), (6.0, -2.0, 1.7)]
    poses = [cam.look_at(e, (0.0, 16.0, 3.0)) for e in eyes]
    photos = [photo(scene, f"p{k}", ip, T, k * 10**9, camera_id=None) for k, T in enumerate(poses)]
    px, pts = anchor_clicks(ip, poses[0], noise_px=0.3, seed=1)
    stream = StreamingRegistrar(StreamConfig(), site="t")
    stream.register_anchor(photos[0], px, pts)
    for p in photos[1:]:
        out = stream.register(p)
        assert out.registration.status == "auto", out.registration.message
    recon = rc.Reconstruction()
    for p in photos:
        feats = extract_features(p.image.gray(), 4000, 1600)
        rc.add_image(recon, p.photo_id, feats, focal_prior_px=None)
    cfg = config.MapperConfig(min_anchors=0, release_anchors=False)
    sfm.reconstruct(recon, {"p0": (px, pts)}, cfg)
    dist = np.linalg.norm(poses[0][:3, 3] - np.array([0.0, 16.0, 3.0]))
    for k, p in enumerate(photos):
        im = recon.images[recon.index(p.photo_id)]
        assert im.registered, im.message
        s = stream.poses[p.photo_id].world_from_camera
        assert np.linalg.norm(im.pose[:3, 3] - s[:3, 3]) < 0.01 * dist, (p.photo_id, im.method)
        assert cam.viewing_angle_deg(im.pose, s) < 0.3, (p.photo_id, im.method)
        assert cam.viewing_angle_deg(im.pose, poses[k]) < 0.5


@pytest.mark.parametrize("camera_folders", [True, False])
def test_batch_reads_fixed_cameras_from_the_site_layout(scene, tmp_path, camera_folders: bool) -> None:
    """``register --camera-folders`` on a site's photos folder (``<camera>/`` per fixed camera, ``phone/``): the
    batch gives a camera's frames the camera id the streaming node gets, so the same rules hold. A frame of the
    mast camera moved 1.5 m (2.6 deg of parallax to its first frame) is refused a relative pose to its own frame,
    as in streaming (``test_bumped_camera_takes_full_path_and_a_moved_one_registers_without_clicks``); without the
    layout the two frames are two unrelated photos and it is placed by that relative pose (right here, on a clean
    scene; a knocked camera's came out 2.9 deg off that way)."""
    import json

    from nodes.register.batch import looks_like_site_layout, run_batch

    intr, T = mast_camera(W, H)
    moved = cam.look_at((4.0, -5.0, 6.5), (0.5, 16.0, 4.0))
    elsewhere = cam.look_at((-3.0, -6.0, 6.0), (0.5, 16.0, 4.0))
    poses = {"cam-a/0000.jpg": T, "cam-a/0001.jpg": moved, "phone/IMG_0001.jpg": elsewhere}
    for rel, pose in poses.items():
        (tmp_path / "photos" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "photos" / rel).write_bytes(encode_jpeg(scene.render(intr, pose)))
    px, pts = anchor_clicks(intr, T, noise_px=0.3, seed=1)
    points = [{"pixel": list(p), "world": list(w)} for p, w in zip(px, pts, strict=True)]
    doc = {"focal_px": intr.f_px, "anchors": [{"image": "cam-a/0000.jpg", "points": points}]}
    (tmp_path / "anchors.json").write_text(json.dumps(doc))
    cfg = config.MapperConfig(min_anchors=0, release_anchors=False)
    assert looks_like_site_layout(tmp_path / "photos")  # a phone/ folder: `register` suggests --camera-folders
    assert not looks_like_site_layout(tmp_path / "photos" / "cam-a")
    recon, report = run_batch(
        tmp_path / "photos",
        tmp_path / "anchors.json",
        tmp_path / "out",
        cfg=cfg,
        show_progress=False,
        densify_params=None,
        camera_folders=camera_folders,
    )
    images = {d["image"]: d for d in report["images"]}
    assert report["camera_folders"] is camera_folders
    moved_frame = images["cam-a/0001.jpg"]
    if camera_folders:
        assert images["cam-a/0000.jpg"]["camera_id"] == "cam-a" == moved_frame["camera_id"]
        assert "camera_id" not in images["phone/IMG_0001.jpg"]
        assert moved_frame["method"] != "relative", moved_frame["message"]
        # a phone photo is no frame of the camera: placed relative to the anchor (6 m away), the moved frame then
        # from what the two triangulate
        assert images["phone/IMG_0001.jpg"]["method"] == "relative", images["phone/IMG_0001.jpg"]["message"]
    else:
        assert all("camera_id" not in d for d in images.values())
        assert moved_frame["method"] == "relative", moved_frame["message"]
    for rel, pose in poses.items():
        got = recon.images[recon.index(rel)]
        assert got.registered, (rel, got.message)
        dist = np.linalg.norm(pose[:3, 3] - np.array([0.0, 16.0, 4.0]))
        assert np.linalg.norm(got.pose[:3, 3] - pose[:3, 3]) < 0.01 * dist, (rel, got.method)
        assert cam.viewing_angle_deg(got.pose, pose) < 0.3, (rel, got.method)
