"""GPS safeguards of the streaming registrar: homography transfer refused between photos whose GPS positions are
far apart, PnP poses refused when they contradict the registered photos' GPS. Seeded synthetic plane scene
(tests/test_register_stream_scene.py; its frame is east / north / up metres)."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, mast_camera

from constructaide import camera as cam
from nodes.register.streaming import FrameImage, PhotoInput, StreamConfig, StreamingRegistrar
from schemas.messages import GeoPoint

W, H = 640, 360
LAT0, LON0, R_EARTH = 51.8583, 5.8647, 6_371_008.8


def gps_at(east_m: float, north_m: float) -> GeoPoint:
    lat = LAT0 + math.degrees(north_m / R_EARTH)
    return GeoPoint(lat_deg=lat, lon_deg=LON0 + math.degrees(east_m / (R_EARTH * math.cos(math.radians(LAT0)))))


@pytest.fixture(scope="module")
def scene() -> PlaneScene:
    return PlaneScene(0)


def photo(scene, pid, intr, T, gps, camera_id=None) -> PhotoInput:
    return PhotoInput(pid, FrameImage(encode_jpeg(scene.render(intr, T))), camera_id=camera_id, gps=gps)


def _reaimed(scene, gps_offset_m, cfg=None):
    """An anchor, then a phone photo from the same centre turned by 8 degrees (a rotation homography)."""
    intr, T = mast_camera(W, H)
    reg = StreamingRegistrar(cfg or StreamConfig(), site="t")
    px, pts = anchor_clicks(intr, T, noise_px=0.0)
    reg.register_anchor(photo(scene, "a0", intr, T, gps_at(*T[:2, 3])), px, pts)
    Tb = T.copy()
    Tb[:3, :3] = T[:3, :3] @ cam.rodrigues_to_matrix(np.radians([2.0, 8.0, 1.0]))
    return reg.register(photo(scene, "b1", intr, Tb, gps_at(*(T[:2, 3] + gps_offset_m)))), Tb


def test_homography_transfer_refused_between_far_apart_gps_positions(scene) -> None:
    out, Tb = _reaimed(scene, np.array([2.0, -2.0]))  # same viewpoint, GPS ~3 m off
    assert out.registration.method == "homography", out.registration.message
    assert cam.viewing_angle_deg(cam.pose_from_tuple(out.registration.world_from_camera), Tb) < 0.5
    out, _ = _reaimed(scene, np.array([0.0, 40.0]))
    assert out.registration.status == "failed" and out.needs_anchor
    assert "GPS positions 40 m apart" in out.registration.message
    no_gps = msgspec.structs.replace(StreamConfig().mapper, gps_max_homography_distance_m=None)
    out, _ = _reaimed(scene, np.array([0.0, 40.0]), StreamConfig(mapper=no_gps))
    assert out.registration.method == "homography"


def _two_anchors_then_pnp(scene, gps_offset_m, cfg=None):
    reg = StreamingRegistrar(cfg or StreamConfig(), site="t")
    ip = cam.centered_intrinsics(W, H, cam.focal_from_fov(W, 55.0))
    rng = np.random.default_rng(4)
    for i, eye in enumerate([(-5.0, -3.0, 2.0), (5.0, -3.0, 2.5)]):
        Ta = cam.look_at(eye, (0.0, 16.0, 3.0))
        px, pts = anchor_clicks(ip, Ta, noise_px=0.3, seed=i)
        g = gps_at(*(np.array(eye[:2]) + rng.normal(0, 2.0, 2)))
        reg.register_anchor(photo(scene, f"a{i}", ip, Ta, g), px, pts)
    Tq = cam.look_at((0.0, -4.0, 1.6), (0.0, 16.0, 3.0))
    g = gps_at(*(np.array([0.0, -4.0]) + rng.normal(0, 2.0, 2) + gps_offset_m))
    return reg.register(photo(scene, "q", ip, Tq, g)), Tq


def test_pnp_refused_when_gps_contradicts_it(scene) -> None:
    out, Tq = _two_anchors_then_pnp(scene, np.zeros(2))
    assert out.registration.method == "pnp", out.registration.message
    assert np.linalg.norm(cam.pose_from_tuple(out.registration.world_from_camera)[:3, 3] - Tq[:3, 3]) < 0.4
    # The photo's GPS says 40 m further south: its PnP pose is refused, an anchor is asked for with the reason.
    out, _ = _two_anchors_then_pnp(scene, np.array([0.0, -40.0]))
    assert out.registration.status == "failed" and out.needs_anchor
    assert "PnP pose" in out.registration.message and "refused" in out.registration.message
    assert "GPS" in out.registration.message
    no_gps = msgspec.structs.replace(StreamConfig().mapper, gps_max_residual_m=None)
    out, _ = _two_anchors_then_pnp(scene, np.array([0.0, -40.0]), StreamConfig(mapper=no_gps))
    assert out.registration.method == "pnp"


def test_register_node_hands_the_photo_gps_to_the_registrar() -> None:
    from nodes.register.inbox import photo_input as _photo_input
    from schemas.messages import Photo

    g = gps_at(10.0, -5.0)
    msg = Photo(site="t", photo_id="p", capture_time_ns=1, data=encode_jpeg(np.zeros((8, 8, 3), np.uint8)), gps=g)
    assert _photo_input(msg).gps == g
    assert _photo_input(Photo(site="t", photo_id="p", capture_time_ns=1, data=msg.data)).gps is None
