"""GPS safeguards of the batch registration (nodes.register.sfm): homography transfer refused between photos whose
GPS positions are far apart, automatic poses refused when they contradict the registered photos' GPS, and automatic
poses checked against clicks given up front. Seeded synthetic cases; the scene frame is east / north / up metres."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_register_batch_sfm import F, H, W, arc_cameras, clicks_for, make_features, scene_points

from constructaide import camera as cam
from constructaide.errors import UserError
from constructaide.geo import gps_distance_residuals_m
from nodes.register import batch, config, gps, mapper, matching, sfm
from nodes.register import recon as rc
from schemas.messages import GeoPoint

LAT0, LON0, R_EARTH = 51.8583, 5.8647, 6_371_008.8


def gps_at(east_m: float, north_m: float) -> GeoPoint:
    """WGS84 point at (east, north) metres from the site origin."""
    lat = LAT0 + math.degrees(north_m / R_EARTH)
    return GeoPoint(lat_deg=lat, lon_deg=LON0 + math.degrees(east_m / (R_EARTH * math.cos(math.radians(LAT0)))))


def model_frame(rng: np.random.Generator):
    """A z-up metric model frame turned and shifted against east/north (the check must not need it)."""
    a = rng.uniform(0, 2 * np.pi)
    Rm = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = rng.uniform(-100, 100, 2)
    return lambda xy: np.asarray(xy, float) @ Rm.T + t


FIXED = {"north": (0.0, 45.0), "east": (46.0, -11.0), "south": (0.0, -45.0), "west": (-46.0, 5.0)}


def site_references(rng, to_model, cameras=("north", "east", "south"), frames=5, phones=8, phone_sigma=3.0):
    """Registered photos of a site: fixed cameras (exact GPS, several frames each, 0.5 m registration error) and
    phones scattered over the site (GPS N(0, phone_sigma) per axis)."""
    refs = []
    for name in cameras:
        p = np.array(FIXED[name])
        for _ in range(frames):
            refs.append((np.r_[to_model(p + rng.normal(0, 0.5, 2)), 9.0], gps_at(*p)))
    for p in rng.uniform(-25, 25, (phones, 2)):
        refs.append((np.r_[to_model(p + rng.normal(0, 0.1, 2)), 1.6], gps_at(*(p + rng.normal(0, phone_sigma, 2)))))
    return refs


def test_gps_residual_accepts_true_poses_and_refuses_displaced_ones():
    """300 seeded sites: a phone registered where it was (GPS 3 m per axis) passes in >= 99 % of them, the same
    phone registered 40 m off (any direction) is refused in >= 97 %; the bound is 15 m."""
    rng = np.random.default_rng(0)
    n, accepted, refused, residuals = 300, 0, 0, []
    for _ in range(n):
        to_model = model_frame(rng)
        refs = site_references(rng, to_model)
        true = rng.uniform(-25, 25, 2)
        g = gps_at(*(true + rng.normal(0, 3.0, 2)))
        why, res = gps.gps_refusal(np.r_[to_model(true + rng.normal(0, 0.3, 2)), 1.6], g, refs, 15.0)
        accepted += why == ""
        residuals.append(res)
        d = rng.normal(size=2)
        why, _ = gps.gps_refusal(np.r_[to_model(true + 40.0 * d / np.linalg.norm(d)), 1.6], g, refs, 15.0)
        refused += why != ""
    assert accepted / n >= 0.99
    assert refused / n >= 0.97
    assert np.median(residuals) < 6.0  # a true pose's residual is GPS noise, far below the bound


def test_mirrored_pose_keeps_distances_but_not_the_heading():
    """A west camera registered at the east camera's place (the site mirrored across its north-south line, as
    repeated hoarding print gives): its distances to photos on that line are unchanged, so the distance test cannot
    see it; the rigid motion fitted to the references' GPS (no reflection) puts it 92 m from its GPS position."""
    rng = np.random.default_rng(3)
    to_model = model_frame(rng)
    refs = [(np.r_[to_model(FIXED[k]), 9.0], gps_at(*FIXED[k])) for k in ("north", "south") for _ in range(4)]
    for north in (-12.0, 12.0):
        refs.append((np.r_[to_model((0.0, north)), 1.6], gps_at(*(np.array([0.0, north]) + rng.normal(0, 1.0, 2)))))
    west, east = np.array(FIXED["west"]), np.array([46.0, 5.0])  # mirror image of west across x = 0
    centre = np.r_[to_model(east), 9.0]
    assert gps.gps_median_residual_m(centre, gps_at(*west), refs) < 2.0
    head, allowance = gps.gps_heading_residual_m(centre, gps_at(*west), refs)
    assert head == pytest.approx(92.0, abs=3.0) and allowance < 20.0
    why, res = gps.gps_refusal(centre, gps_at(*west), refs, 15.0)
    assert "fitted" in why and res > 60.0
    # Registered where it is, it passes both tests.
    why, res = gps.gps_refusal(np.r_[to_model(west), 9.0], gps_at(*west), refs, 15.0)
    assert why == "" and res < 5.0


def test_fixed_camera_frames_count_as_one_position():
    """Twenty frames of one camera at one GPS position do not outvote the other positions: a phone at (0, 10)
    registered at (0, 80) keeps its 35 m to the north camera only."""
    rng = np.random.default_rng(5)
    to_model = model_frame(rng)
    refs = [(np.r_[to_model(FIXED["north"]), 9.0], gps_at(*FIXED["north"])) for _ in range(20)]
    refs += [(np.r_[to_model(FIXED[k]), 9.0], gps_at(*FIXED[k])) for k in ("east", "west")]
    phone, wrong = gps_at(0.0, 10.0), np.r_[to_model((0.0, 80.0)), 1.6]
    centres = np.array([c for c, _ in refs])
    per_photo = np.median(gps_distance_residuals_m(wrong, phone, centres, [g for _, g in refs]))
    assert per_photo < 1.0
    assert gps.gps_median_residual_m(wrong, phone, refs) > 40.0


def _two_view_recon(gps_turned: GeoPoint) -> tuple[rc.Reconstruction, config.MapperConfig, np.ndarray]:
    """An anchor and a view from its centre turned by 4 degrees and zoomed 10 % (one rotation homography)."""
    rng = np.random.default_rng(7)
    pts = scene_points(rng)
    desc = rng.normal(size=(len(pts), 128))
    T0 = arc_cameras(7)[0]
    turned = T0.copy()
    turned[:3, :3] = T0[:3, :3] @ cam.rodrigues_to_matrix([0.0, np.radians(4.0), 0.0])
    recon = rc.Reconstruction()
    for name, T, f, g in (("anchor", T0, F, gps_at(*T0[:2, 3])), ("turned", turned, F * 1.1, gps_turned)):
        rc.add_image(recon, name, make_features(rng, pts, desc, T, f_px=f)[0], gps=g)
    cfg = config.MapperConfig(focal_px=F)
    matching.match_image(recon, 1, [0], cfg)
    mapper.register_anchor(recon, 0, clicks_for(rng, pts, T0), cfg)
    return recon, cfg, turned


def test_homography_transfer_refused_between_far_apart_gps_positions():
    T0 = arc_cameras(7)[0]
    rng = np.random.default_rng(11)
    # Same viewpoint, GPS 3 m sigma per axis: transferred.
    recon, cfg, turned = _two_view_recon(gps_at(*(T0[:2, 3] + rng.normal(0, 3.0, 2))))
    assert mapper.try_homography_transfer(recon, 0, 1, cfg)
    im = recon.images[1]
    assert im.method == "homography" and cam.viewing_angle_deg(im.world_from_camera, turned) < 0.3
    # The same images with GPS 40 m apart (a repeated print seen from elsewhere): refused, nothing registered.
    recon, cfg, _ = _two_view_recon(gps_at(*(T0[:2, 3] + [40.0, 0.0])))
    assert not mapper.try_homography_transfer(recon, 0, 1, cfg)
    assert not recon.images[1].registered and "GPS positions 40 m apart" in recon.images[1].message
    # Off: transferred again.
    off = config.MapperConfig(focal_px=F, gps_max_homography_distance_m=None)
    assert mapper.try_homography_transfer(recon, 0, 1, off)


def _arc_run(gps_offsets: dict[str, np.ndarray], cfg: config.MapperConfig, up_front: dict | None = None):
    """Five views on an arc (20 m from a building corner), GPS = true position + N(0, 1 m) + offsets; anchors: view0
    (up front), view2 (asked for). Returns (reconstruction, true poses, requested names, points)."""
    rng = np.random.default_rng(21)
    pts = scene_points(rng)
    desc = rng.normal(size=(len(pts), 128))
    poses = arc_cameras(5)
    recon = rc.Reconstruction()
    for k, T in enumerate(poses):
        name = f"view{k}"
        g = gps_at(*(T[:2, 3] + rng.normal(0, 1.0, 2) + gps_offsets.get(name, 0.0)))
        rc.add_image(recon, name, make_features(rng, pts, desc, T)[0], gps=g)
    anchors = {"view0": clicks_for(rng, pts, poses[0]), **(up_front or {})}
    answers = {"view2": clicks_for(rng, pts, poses[2])}
    requests: list[tuple[str, str]] = []

    def request(name: str, reason: str, n: int):
        requests.append((name, reason))
        return answers.pop(name, None)

    sfm.reconstruct(recon, anchors, cfg, request_anchor=request)
    return recon, poses, requests, pts


@pytest.fixture(scope="module")
def gps_displaced_run():
    # The arc's random descriptors match across its 80 deg (real ones do not): the relative pose to view0 is tried
    # whatever its parallax, so that the GPS check is what refuses it.
    cfg = config.MapperConfig(focal_px=F, release_anchors=False, bootstrap_max_parallax_deg=180.0)
    return _arc_run({"view4": np.array([0.0, 40.0])}, cfg)


def test_pnp_refused_when_gps_contradicts_it(gps_displaced_run):
    """view4's GPS says 40 m further north than it is: its (correct) PnP pose is refused and it asks for an anchor
    with the GPS reason; the other views register as usual."""
    recon, poses, requests, _ = gps_displaced_run
    im = recon.images[recon.index("view4")]
    assert not im.registered
    assert "GPS" in im.message and im.gps_residual_m > 15.0
    assert any(name == "view4" and "GPS" in reason for name, reason in requests)
    for k in (0, 1, 2, 3):
        o = recon.images[recon.index(f"view{k}")]
        assert o.registered, (o.name, o.message)
        assert cam.viewing_angle_deg(o.world_from_camera, poses[k]) < 0.3
        assert np.isnan(o.gps_residual_m) or o.gps_residual_m < 5.0


def test_pnp_kept_with_the_gps_check_off():
    cfg = config.MapperConfig(focal_px=F, release_anchors=False, gps_max_residual_m=None)
    recon, poses, _, _ = _arc_run({"view4": np.array([0.0, 40.0])}, cfg)
    im = recon.images[recon.index("view4")]
    assert im.registered and im.method in ("pnp", "relative"), im.message
    assert cam.viewing_angle_deg(im.world_from_camera, poses[4]) < 0.3


def test_automatic_pose_checked_against_up_front_clicks():
    """Clicks given up front for view3 (with use_all_anchors off, so that view3 is reached by PnP first) anchor it
    when it is reached: clicks that agree with its automatic pose say so in its message; clicks that contradict it
    by > 2 % of the width (here: clicked as if the camera stood 3 m further along the arc) re-register it from
    them and say that."""
    rng = np.random.default_rng(31)
    pts = scene_points(np.random.default_rng(21))
    poses = arc_cameras(5)
    # Anchor requests in collection order (view1 refused, view2 answered) so that view3 is reached by PnP and its
    # up-front clicks only check it; the default would ask the widest view first and take view3's clicks at once.
    cfg = config.MapperConfig(
        focal_px=F, release_anchors=False, anchor_request_min_shared_matches=0, use_all_anchors=False
    )
    agree = {"view3": clicks_for(rng, pts, poses[3], n=10)}
    recon, _, _, _ = _arc_run({}, cfg, up_front=agree)
    im = recon.images[recon.index("view3")]
    assert im.status == "anchor" and "anchored by its up-front clicks" in im.message, im.message
    assert mapper.click_disagreement_px(im, agree["view3"]) < 0.005 * W
    shifted = poses[3].copy()
    shifted[:3, 3] += [3.0, 0.0, 0.0]
    px, world = clicks_for(rng, pts, shifted, n=10)
    recon, _, _, _ = _arc_run({}, cfg, up_front={"view3": (px, world)})
    im = recon.images[recon.index("view3")]
    assert im.status == "anchor" and "re-registered from its clicks" in im.message, im.message
    assert np.linalg.norm(im.world_from_camera[:3, 3] - shifted[:3, 3]) < 0.5
    # Off: the automatic pose stays.
    off = config.MapperConfig(
        focal_px=F,
        release_anchors=False,
        check_auto_with_clicks=False,
        anchor_request_min_shared_matches=0,
        use_all_anchors=False,
    )
    recon, _, _, _ = _arc_run({}, off, up_front={"view3": (px, world)})
    assert recon.images[recon.index("view3")].status == "auto"


def test_anchor_file_on_request_flag(tmp_path):
    pts = [{"pixel": [float(i), float(i)], "world": [float(i), 0.0, 1.0]} for i in range(5)]
    doc = {"anchors": [{"image": "a.jpg", "points": pts}, {"image": "b.jpg", "points": pts, "on_request": True}]}
    path = tmp_path / "anchors.json"
    path.write_text(json.dumps(doc))
    clicks, focal, held = batch.load_anchor_file(path)
    assert list(clicks) == ["a.jpg", "b.jpg"] and focal is None and held == {"b.jpg"}
    doc["anchors"][0]["on_request"] = True
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="given up front"):
        batch.load_anchor_file(path)
    doc["anchors"][0]["on_request"] = "yes"
    path.write_text(json.dumps(doc))
    with pytest.raises(UserError, match="true or false"):
        batch.load_anchor_file(path)


def test_exif_gps_read_by_the_batch(tmp_path):
    from PIL import Image

    exif = Image.Exif()
    exif.get_ifd(0x8825).update({1: "N", 2: (51.0, 51.0, 29.88), 3: "E", 4: (5.0, 51.0, 52.92)})
    Image.new("RGB", (W // 8, H // 8)).save(tmp_path / "a.jpg", "JPEG", exif=exif.tobytes())
    Image.new("RGB", (8, 8)).save(tmp_path / "b.jpg", "JPEG")
    g = batch.exif_gps_position(tmp_path / "a.jpg")
    assert (
        g is not None and g.lat_deg == pytest.approx(51.8583, abs=1e-6) and g.lon_deg == pytest.approx(5.8647, abs=1e-6)
    )
    assert batch.exif_gps_position(tmp_path / "b.jpg") is None
