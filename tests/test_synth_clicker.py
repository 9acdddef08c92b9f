"""The simulated user who answers anchor requests: clicks on BIM pixels that reproject through the true camera
within the click noise, and the demo's answering loop on an in-process bus."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from constructaide import camera as cam
from constructaide.app.demo import _finished, _SimulatedUser
from constructaide.runtime.local import LocalBus
from constructaide.synth.clicker import simulated_clicks
from constructaide.synth.truth import load_ids, true_camera
from nodes.ingest.photos import photo_from_file
from schemas import codec, keys
from schemas.messages import AnchorClicks, NeedsAnchor, Registration


def test_clicks_lie_on_the_model_and_reproject_within_the_noise(small_site: Path) -> None:
    rel = next(str(p.relative_to(small_site / "photos")) for p in sorted((small_site / "photos").rglob("*.jpg")))
    px, world = simulated_clicks(small_site, rel)
    assert px.shape == (12, 2) and world.shape == (12, 3)
    intr, world_from_camera = true_camera(small_site, rel)
    proj, z = cam.project_points(intr, cam.invert_rigid(world_from_camera), world)
    err_px = np.linalg.norm(proj - px, axis=1)
    assert np.all(z > 0)
    assert 0.4 < float(np.mean(err_px)) < 2.5 and float(np.max(err_px)) < 5.0  # 1 px Gaussian noise per axis
    ids = load_ids(small_site, rel)
    uv = np.round(proj).astype(int)
    assert np.all(ids[uv[:, 1], uv[:, 0]] > 0)  # every click shows a BIM element
    vv, uu = np.nonzero(ids > 0)
    model_extent_px = np.array([np.ptp(uu), np.ptp(vv)])
    assert np.all(np.ptp(px, axis=0) > 0.6 * model_extent_px)  # spread over the model's part of the image
    again_px, again_world = simulated_clicks(small_site, rel)
    assert np.array_equal(again_px, px) and np.array_equal(again_world, world)  # same seed, same clicks


def test_simulated_user_answers_each_request_once(small_site: Path) -> None:
    files = sorted((small_site / "photos" / "phone").rglob("*.jpg"))[:2]
    photos = {str(f.relative_to(small_site / "photos")): photo_from_file(f, None, "s", "UTC") for f in files}
    (rel_a, pa), (_, pb) = photos.items()
    with LocalBus() as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site="s"))
        clicks = bus.collect(keys.pattern(keys.ANCHORS, site="s"))
        failed = Registration(site="s", photo_id=pa.photo_id, status="failed", message="too few tracks")
        bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pa.photo_id), failed)
        with _SimulatedUser(bus, "s", small_site, photos, regs) as user:
            # Never asked for: a failed registration alone is final.
            assert _finished(regs.items, {pa.photo_id}, user) == {pa.photo_id}
            ask = NeedsAnchor(site="s", photo_id=pa.photo_id, reason="too few tracks")
            for _ in range(2):
                bus.publish(keys.key(keys.NEEDS_ANCHOR, site="s", photo=pa.photo_id), ask)
            clicks.wait(1, timeout=30)
            # Asked and answered: not final until a registration that did not fail arrives.
            assert _finished(regs.items, {pa.photo_id, pb.photo_id}, user) == set()
            done = Registration(site="s", photo_id=pa.photo_id, status="anchor")
            bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pa.photo_id), done)
            assert _finished(regs.items, {pa.photo_id, pb.photo_id}, user) == {pa.photo_id}
            # A request for a photo registered meanwhile is not clicked.
            ok_b = Registration(site="s", photo_id=pb.photo_id, status="auto")
            bus.publish(keys.key(keys.REGISTRATION, site="s", camera="phone", photo=pb.photo_id), ok_b)
            ask_b = NeedsAnchor(site="s", photo_id=pb.photo_id, reason="too few tracks")
            bus.publish(keys.key(keys.NEEDS_ANCHOR, site="s", photo=pb.photo_id), ask_b)
        assert user.answered == {pa.photo_id} and user.requested == {pa.photo_id, pb.photo_id}
    assert len(clicks.items) == 1  # the repeated request is not answered twice
    msg = clicks.items[0][1]
    assert isinstance(msg, AnchorClicks) and msg.image_name == rel_a and len(msg.points) == 12
    assert codec.decode(codec.encode(msg)) == msg
