"""An adjustment may not bend an anchor's lens away from its clicks: tracks that disagree with the clicked camera (on
the synthetic sites: matches on repeated texture) get the anchor's lens held at its click solve's, and the clicks
stay where the user put them. Seeded arc scenes (several seeds)."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest
from test_register_batch_sfm import arc_reconstruction, clicks_for

from constructaide import camera as cam
from nodes.register import adjust, config, sfm
from nodes.register import recon as rc

F = 900.0


def anchored_arc(seed: int) -> tuple[rc.Reconstruction, config.MapperConfig]:
    """Seven views of a building corner, the first and the fourth anchored (10 clicks, 0.5 px), every view
    registered. The tracks hang on the first anchor's rays, so the fourth's observations are residuals of its lens
    like any camera's."""
    rng = np.random.default_rng(seed)
    recon, pts, poses = arc_reconstruction(rng)
    cfg = config.MapperConfig(focal_px=F)
    clicks = {"view0": clicks_for(rng, pts, poses[0]), "view3": clicks_for(rng, pts, poses[3])}
    sfm.reconstruct(recon, clicks, cfg, lambda *_: None)
    assert all(im.registered for im in recon.images), [(im.name, im.message) for im in recon.images]
    return recon, cfg


def bend_features(im: rc.ImageState, k1: float) -> None:
    """Move an image's keypoints as a lens with radial ``k1`` would show them (the tracks then pull its lens)."""
    intr = im.camera
    kp = im.features.keypoints_px.astype(np.float64)
    xy = (kp - [intr.cx_px, intr.cy_px]) / intr.f_px
    r2 = np.sum(xy**2, axis=1, keepdims=True)
    im.features.keypoints_px[:] = (xy * (1 + k1 * r2) * intr.f_px + [intr.cx_px, intr.cy_px]).astype(np.float32)


def click_rms(im: rc.ImageState) -> float:
    clicks = im.accepted_clicks
    assert clicks is not None
    proj, _ = cam.project_points(im.camera, cam.invert_rigid(im.pose), clicks[1])
    return float(np.sqrt(np.mean(np.sum((proj - clicks[0]) ** 2, axis=1))))


@pytest.mark.parametrize("seed", [1, 4, 8])
def test_tracks_that_bend_an_anchors_lens_are_outvoted_by_its_clicks(seed: int) -> None:
    recon, cfg = anchored_arc(seed)
    anchor = recon.images[3]
    assert anchor.status == "anchor" and anchor.anchor is not None
    solve_rms = anchor.anchor.rms_px
    bound = solve_rms + cfg.max_anchor_click_drift_px  # the final release may move an anchor a little
    assert click_rms(anchor) < bound
    bend_features(anchor, -0.2)

    # Without the rule the tracks win: the lens bends and the clicks are pulled off (what the rule guards against).
    off = msgspec.structs.replace(cfg, max_anchor_click_drift_px=None)
    snap = rc.snapshot(recon)
    adjust.bundle(recon, off)
    assert anchor.camera.k1 < -0.15, anchor.camera
    assert click_rms(anchor) > bound
    assert not anchor.lens_held
    rc.restore(recon, snap)

    adjust.bundle(recon, cfg)
    assert anchor.lens_held
    assert anchor.camera == anchor.anchor.intrinsics
    assert click_rms(anchor) < bound
    assert "lens held" in anchor.message


def test_an_anchor_whose_tracks_agree_keeps_a_free_lens() -> None:
    recon, cfg = anchored_arc(2)
    adjust.bundle(recon, cfg)
    assert not any(im.lens_held for im in recon.images)
    assert adjust.drifted_anchors(recon, cfg) == []
