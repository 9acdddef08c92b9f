"""COLMAP text model writer/reader round trip and conventions."""

from __future__ import annotations

import numpy as np
import pytest

from constructaide import camera as cam
from nodes.register.colmap_io import (
    ColmapImage,
    ColmapModel,
    quaternion_to_rotation,
    read_text_model,
    rotation_to_quaternion,
    write_text_model,
)
from schemas.messages import Intrinsics


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = cam.rodrigues_to_matrix(rng.normal(size=3) * 1.5)
        q = rotation_to_quaternion(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        assert np.allclose(quaternion_to_rotation(q), R, atol=1e-12)
    assert np.allclose(rotation_to_quaternion(np.eye(3)), [1, 0, 0, 0])


def test_text_model_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.uniform(-3, 3, (40, 3))
    images = []
    for k in range(3):
        intr = Intrinsics(width_px=640, height_px=480, f_px=500.0 + k, cx_px=319.5, cy_px=239.5, k1=0.01 * k, k2=-0.002)
        T = cam.look_at([k - 1.0, -10.0, 1.0], [0, 0, 0])
        px, _ = cam.project_points(intr, cam.invert_rigid(T), pts)
        idx = np.r_[np.arange(40), -1]
        uv = np.vstack([px, [[5.0, 6.0]]])
        images.append(ColmapImage(f"sub/img {k}.jpg" if k == 0 else f"img{k}.jpg", intr, T, uv, idx))
    model = ColmapModel(images, pts, rng.integers(0, 255, (40, 3)).astype(np.uint8), np.full(40, 0.25))
    write_text_model(model, tmp_path)
    cams_txt = (tmp_path / "cameras.txt").read_text().splitlines()
    assert cams_txt[2].split()[1] == "RADIAL"
    # COLMAP pixel convention: principal point shifted by +0.5.
    assert float(cams_txt[2].split()[5]) == pytest.approx(320.0)
    back = read_text_model(tmp_path)
    assert len(back.images) == 3
    assert back.images[0].name == "sub/img_0.jpg"  # spaces are not allowed in COLMAP names
    for a, b in zip(images, back.images, strict=True):
        assert b.intrinsics == a.intrinsics
        assert np.allclose(b.world_from_camera, a.world_from_camera, atol=1e-9)
        assert np.allclose(b.points2d_px, a.points2d_px, atol=1e-3)
        assert b.point3d_index.tolist() == a.point3d_index.tolist()
    assert np.allclose(back.points, pts)
    assert np.array_equal(back.colors, model.colors)
    # Each point's track lists the 3 images.
    lines = [ln for ln in (tmp_path / "points3D.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(lines[0].split()) == 8 + 2 * 3
