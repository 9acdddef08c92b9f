"""Pixel aspect ratio (fy / fx): camera model, final-release refinement under a Wald test, COLMAP round trip."""

from __future__ import annotations

import numpy as np
import pytest
from test_register_batch_sfm import F, H, W, arc_cameras, clicks_for, make_features, scene_points

from constructaide import camera as cam
from nodes.register import config, sfm
from nodes.register import recon as rc
from nodes.register.colmap_io import ColmapImage, ColmapModel, read_text_model, write_text_model
from schemas.messages import Intrinsics


def test_camera_model_honours_the_aspect():
    intr = Intrinsics(width_px=640, height_px=480, f_px=500.0, cx_px=310.0, cy_px=245.0, k1=-0.05, fy_over_fx=1.02)
    assert cam.focal_xy(intr) == (500.0, pytest.approx(510.0))
    assert np.allclose(cam.K_matrix(intr), [[500.0, 0, 310.0], [0, 510.0, 245.0], [0, 0, 1]])
    xy = np.array([[0.1, -0.2], [-0.3, 0.25]])
    px = cam.normalized_to_pixels(intr, xy)
    r2 = np.sum(xy**2, axis=1)
    assert np.allclose(px[:, 1], 510.0 * xy[:, 1] * (1 - 0.05 * r2) + 245.0)
    assert np.allclose(cam.pixels_to_normalized(intr, px), xy, atol=1e-10)
    # Messages without the field mean square pixels.
    assert Intrinsics(width_px=640, height_px=480, f_px=500.0, cx_px=319.5, cy_px=239.5).fy_over_fx == 1.0


def run_stretched(
    aspect: float, cfg: config.MapperConfig, seed: int = 17
) -> tuple[rc.Reconstruction, list[np.ndarray]]:
    """Six arc views and two anchors (12 clicks each) of a camera with pixel aspect ``aspect``: the square-pixel
    projections are scaled about the image centre so that fx = 2 F / (1 + aspect), fy = aspect fx (mean focal F,
    the focal prior given)."""
    rng = np.random.default_rng(seed)
    pts = scene_points(rng)
    desc = rng.normal(size=(len(pts), 128))
    poses = arc_cameras(6)
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    scale = np.array([2 / (1 + aspect), 2 * aspect / (1 + aspect)])

    def stretch(px: np.ndarray) -> np.ndarray:
        return c + (np.asarray(px, np.float64) - c) * scale

    recon = rc.Reconstruction()
    for k, T in enumerate(poses):
        feats, _ = make_features(rng, pts, desc, T)
        feats.keypoints_px = stretch(feats.keypoints_px).astype(np.float32)
        rc.add_image(recon, f"view{k}", feats)
    px0, X0 = clicks_for(rng, pts, poses[0], n=12)
    px3, X3 = clicks_for(rng, pts, poses[3], n=12)
    sfm.reconstruct(recon, {"view0": (stretch(px0), X0), "view3": (stretch(px3), X3)}, cfg)
    assert all(im.registered for im in recon.images)
    return recon, poses


def centre_errors(recon: rc.Reconstruction, poses: list[np.ndarray]) -> np.ndarray:
    return np.array([np.linalg.norm(recon.images[k].world_from_camera[:3, 3] - T[:3, 3]) for k, T in enumerate(poses)])


def test_non_square_pixels_found_in_the_release():
    """fy / fx = 1.01: the release keeps one shared aspect (significant) near the truth, and the camera centres
    improve over the square-pixel model (seed 17: 1.0091, mean error 1.7 cm vs 6.1 cm)."""
    recon, poses = run_stretched(1.01, config.MapperConfig(focal_px=F))
    assert recon.anchors_released and recon.aspect_wald > 9.0
    aspects = {recon.images[i].intrinsics.fy_over_fx for i in recon.registered_indices()}
    assert len(aspects) == 1  # one camera group, one aspect
    assert aspects.pop() == pytest.approx(1.01, abs=0.003)
    square, _ = run_stretched(1.01, config.MapperConfig(focal_px=F, release_aspect=False))
    assert all(square.images[i].intrinsics.fy_over_fx == 1.0 for i in square.registered_indices())
    assert np.isnan(square.aspect_wald)
    assert np.mean(centre_errors(recon, poses)) < 0.5 * np.mean(centre_errors(square, poses))
    assert np.max(centre_errors(recon, poses)) < 0.03


def test_square_pixels_stay_square():
    recon, poses = run_stretched(1.0, config.MapperConfig(focal_px=F))
    assert recon.anchors_released and np.isfinite(recon.aspect_wald)
    assert recon.aspect_wald < 9.0  # one camera group, 1 parameter: not significant
    assert all(recon.images[i].intrinsics.fy_over_fx == 1.0 for i in recon.registered_indices())
    assert np.max(centre_errors(recon, poses)) < 0.04


def test_colmap_round_trip_with_non_square_pixels(tmp_path):
    rng = np.random.default_rng(3)
    pts = rng.uniform(-3, 3, (30, 3))
    images = []
    for k, aspect in enumerate([1.0, 1.0017]):
        intr = Intrinsics(
            width_px=640, height_px=480, f_px=500.0, cx_px=312.25, cy_px=241.5, k1=0.01, k2=-0.002, fy_over_fx=aspect
        )
        T = cam.look_at([k - 0.5, -10.0, 1.0], [0, 0, 0])
        px, _ = cam.project_points(intr, cam.invert_rigid(T), pts)
        images.append(ColmapImage(f"img{k}.jpg", intr, T, px, np.arange(30)))
    write_text_model(ColmapModel(images, pts, np.zeros((30, 3), np.uint8), np.zeros(30)), tmp_path)
    rows = [ln.split() for ln in (tmp_path / "cameras.txt").read_text().splitlines() if not ln.startswith("#")]
    assert [r[1] for r in rows] == ["RADIAL", "OPENCV"]
    # OPENCV: fx fy cx cy k1 k2 p1 p2, principal point in COLMAP's corner convention (+0.5 px).
    assert [float(v) for v in rows[1][4:]] == pytest.approx([500.0, 500.0 * 1.0017, 312.75, 242.0, 0.01, -0.002, 0, 0])
    back = read_text_model(tmp_path)
    for a, b in zip(images, back.images, strict=True):
        assert b.intrinsics.fy_over_fx == pytest.approx(a.intrinsics.fy_over_fx, abs=1e-15)
        assert b.intrinsics.f_px == a.intrinsics.f_px and b.intrinsics.cy_px == a.intrinsics.cy_px
        # The model read back projects the points where the written one did.
        px, _ = cam.project_points(b.intrinsics, cam.invert_rigid(b.world_from_camera), pts)
        assert np.allclose(px, a.points2d_px, atol=1e-6)


def test_colmap_reader_rejects_tangential_distortion(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 OPENCV 640 480 500 501 320 240 0.01 0 0.001 0\n")
    (tmp_path / "images.txt").write_text("")
    (tmp_path / "points3D.txt").write_text("")
    with pytest.raises(ValueError, match="tangential"):
        read_text_model(tmp_path)
