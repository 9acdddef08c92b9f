"""Streaming registration through real zenoh sessions: the register node in its own process."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from test_register_stream_node import SITE, H, W, clicks_msg, make_photo
from test_register_stream_scene import PlaneScene, anchor_clicks, encode_jpeg, jitter, mast_camera

from constructaide import camera as cam
from constructaide.runtime import BusConfig, open_bus
from schemas import keys

pytestmark = pytest.mark.zenoh


def test_register_node_process_streams_registrations(hub_port: int) -> None:
    scene = PlaneScene(0)
    intr, T = mast_camera(W, H)
    rng = np.random.default_rng(11)
    frames = [(intr, T)] + [jitter(T, intr, rng, 0.3, 0.005) for _ in range(3)]
    photos = [make_photo(encode_jpeg(scene.render(i, t)), "cam-z", k) for k, (i, t) in enumerate(frames)]
    px, pts = anchor_clicks(intr, T, noise_px=0.2)
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        proc = subprocess.Popen(
            [sys.executable, "-m", "nodes.register.node", "--site", SITE, "--hub-port", str(hub_port)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            bus.wait_for_tokens([keys.pattern(keys.LIVELINESS, site=SITE, node="register")], timeout=60)
            photo_key = keys.key(keys.PHOTO, site=SITE, camera="cam-z")
            bus.publish(photo_key, photos[0])
            bus.publish(
                keys.key(keys.ANCHORS, site=SITE, photo=photos[0].photo_id), clicks_msg(photos[0].photo_id, px, pts)
            )
            ((_, anchor),) = regs.wait(1, timeout=60)
            assert anchor.status == "anchor" and anchor.photo_id == photos[0].photo_id
            for p in photos[1:]:
                bus.publish(photo_key, p)
            got = regs.wait(4, timeout=60)
            T_anchor = cam.pose_from_tuple(anchor.world_from_camera)
            for (_, reg), p, (_ij, Tj) in zip(got[1:], photos[1:], frames[1:], strict=True):
                assert reg.photo_id == p.photo_id and reg.method == "fastpath", reg.message
                rel_est = cam.pose_from_tuple(reg.world_from_camera)[:3, :3].T @ T_anchor[:3, :3]
                rel_true = Tj[:3, :3].T @ T[:3, :3]
                assert cam.rotation_angle_deg(rel_est, rel_true) < 0.05
            assert proc.poll() is None
        finally:
            if proc.poll() is None:
                proc.terminate()
                proc.wait(20)
