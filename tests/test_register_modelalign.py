"""Pose polish by the model's outlines (nodes/register/modelalign.py) on seeded synthetic scenes: boxes rendered
into a noisy, textured photo at a true camera, the refinement started from a perturbed registration."""

from __future__ import annotations

import cv2
import msgspec
import numpy as np
import pytest
import trimesh

from constructaide import camera as cam
from constructaide.modelscene import GROUND_INDEX
from constructaide.modelview import ModelView
from nodes.register.modelalign import AlignParams, refine_pose
from schemas.messages import Intrinsics

INTR = Intrinsics(width_px=960, height_px=540, f_px=800.0, cx_px=479.5, cy_px=269.5, k1=-0.05, k2=0.01)


def _scene(seed: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A building of a few boxes (site metres, z up) on the ground."""
    rng = np.random.default_rng(seed)
    meshes = {}
    boxes = [((12.0, 8.0, 9.0), (0.0, 0.0, 4.5))]
    for _ in range(4):
        size = tuple(rng.uniform(1.5, 4.0, 3))
        centre = (rng.uniform(-7, 7), rng.uniform(-5, -3.5), size[2] / 2 + rng.uniform(0, 5))
        boxes.append((size, centre))
    for k, (size, centre) in enumerate(boxes):
        b = trimesh.creation.box(extents=size)
        b.apply_translation(centre)
        meshes[f"e{k}"] = (np.asarray(b.vertices, np.float64), np.asarray(b.faces, np.int64))
    return meshes


def _true_camera(seed: int) -> np.ndarray:
    rng = np.random.default_rng(100 + seed)
    az = rng.uniform(-0.6, 0.6) - np.pi / 2
    eye = np.array([30.0 * np.cos(az), 30.0 * np.sin(az), rng.uniform(4.0, 9.0)])
    return cam.look_at(eye, (0.0, 0.0, 4.0))


def _photo(view: ModelView, wfc: np.ndarray, seed: int) -> np.ndarray:
    """Grey photo (540, 960): shaded elements, a sky / ground background, texture strokes and sensor noise."""
    rng = np.random.default_rng(200 + seed)
    res = view.raster(INTR, wfc, ground_z_m=0.0)
    tone = np.r_[0.0, rng.uniform(-20.0, 20.0, len(view.scene.global_ids))]
    ids = np.minimum(res.ids, len(tone) - 1)
    img = 130.0 + 80.0 * res.shade + tone[ids]  # each element its own material
    img[res.ids == 0] = 215.0
    img[res.ids == GROUND_INDEX] = 90.0
    img = img.astype(np.float32)
    for _ in range(60):  # texture: short strokes anywhere (not model outlines)
        p = rng.uniform((0, 0), (960, 540))
        q = p + rng.normal(0, 25, 2)
        cv2.line(img, tuple(int(v) for v in p), tuple(int(v) for v in q), float(rng.uniform(60, 200)), 1)
    img += rng.normal(0, 3.0, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def _corner_error_px(view_meshes, intr_a, wfc_a, intr_b, wfc_b) -> float:  # noqa: ANN001
    pts = np.concatenate([v for v, _ in view_meshes.values()])
    pa, _ = cam.project_points(intr_a, cam.invert_rigid(wfc_a), pts)
    pb, _ = cam.project_points(intr_b, cam.invert_rigid(wfc_b), pts)
    return float(np.mean(np.linalg.norm(pa - pb, axis=1)))


def _perturbed(wfc: np.ndarray, seed: int, rot_deg: float, shift_m: float) -> np.ndarray:
    rng = np.random.default_rng(300 + seed)
    axis = rng.normal(size=3)
    out = wfc.copy()
    out[:3, :3] = wfc[:3, :3] @ cam.rodrigues_to_matrix(axis / np.linalg.norm(axis) * np.radians(rot_deg))
    d = rng.normal(size=3)
    out[:3, 3] += d / np.linalg.norm(d) * shift_m
    return out


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_outline_pulls_an_offset_registration_onto_the_building(seed: int) -> None:
    meshes = _scene(seed)
    view = ModelView(meshes)
    try:
        wfc = _true_camera(seed)
        photo = _photo(view, wfc, seed)
        start = _perturbed(wfc, seed, rot_deg=0.08, shift_m=0.1)
        start_intr = msgspec.structs.replace(INTR, f_px=INTR.f_px * 1.006)
        before = _corner_error_px(meshes, INTR, wfc, start_intr, start)
        res = refine_pose(view, photo, start_intr, start, None, 0.0)
        after = _corner_error_px(meshes, INTR, wfc, res.intrinsics, res.world_from_camera)
    finally:
        view.close()
    assert 1.5 < before < 0.5 * 0.01 * 960, before  # a few pixels off: what a registration hands over
    assert res.accepted, res.reason
    assert res.support_after > res.support_before
    assert after < 0.5 * before and after < 1.0, (before, after)


@pytest.mark.parametrize("seed", [0, 1])
def test_true_pose_stays_put(seed: int) -> None:
    meshes = _scene(seed)
    view = ModelView(meshes)
    try:
        wfc = _true_camera(seed)
        res = refine_pose(view, _photo(view, wfc, seed), INTR, wfc, None, 0.0)
    finally:
        view.close()
    assert _corner_error_px(meshes, INTR, wfc, res.intrinsics, res.world_from_camera) < 0.5


@pytest.mark.parametrize("seed", [0, 1])
def test_a_pull_beyond_the_polish_bound_is_refused(seed: int) -> None:
    """A registration ~2 % of the width off is not the polish's to move: the input comes back, with the reason."""
    meshes = _scene(seed)
    view = ModelView(meshes)
    try:
        wfc = _true_camera(seed)
        start = _perturbed(wfc, seed, rot_deg=1.2, shift_m=0.3)
        res = refine_pose(view, _photo(view, wfc, seed), INTR, start, None, 0.0, AlignParams())
    finally:
        view.close()
    assert _corner_error_px(meshes, INTR, wfc, INTR, start) > 0.015 * 960
    assert not res.accepted
    assert np.array_equal(res.world_from_camera, start) and res.intrinsics == INTR
    assert res.reason


def test_too_few_outline_samples_is_said() -> None:
    meshes = _scene(0)
    view = ModelView(meshes)
    try:
        away = cam.look_at((0.0, 60.0, 5.0), (0.0, 200.0, 5.0))  # looking away from the building
        res = refine_pose(view, np.full((540, 960), 128, np.uint8), INTR, away, None, None)
    finally:
        view.close()
    assert not res.accepted and "samples" in res.reason


def _clicks(meshes, intr: Intrinsics, wfc: np.ndarray, seed: int, noise_px: float = 1.0):  # noqa: ANN001
    """A person's clicks: up to 8 box corners in view (pixels (N, 2) with ``noise_px`` noise, model points (N, 3))."""
    rng = np.random.default_rng(400 + seed)
    pts = np.unique(np.concatenate([v for v, _ in meshes.values()]), axis=0)
    px, z = cam.project_points(intr, cam.invert_rigid(wfc), pts)
    inside = (z > 0) & (px[:, 0] > 20) & (px[:, 0] < intr.width_px - 20) & (px[:, 1] > 20) & (px[:, 1] < 520)
    pick = rng.choice(np.nonzero(inside)[0], size=min(8, int(inside.sum())), replace=False)
    return px[pick] + rng.normal(0.0, noise_px, (len(pick), 2)), pts[pick]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_an_anchors_clicks_replace_the_turn_bound(seed: int) -> None:
    """An anchor off by more than the polish bound (a camera turned about its clicks): with its clicks fitted beside
    the outlines the refinement is kept and lands on the building; without them it is refused."""
    meshes = _scene(seed)
    view = ModelView(meshes)
    try:
        wfc = _true_camera(seed)
        photo = _photo(view, wfc, seed)
        clicks = _clicks(meshes, INTR, wfc, seed)
        start = _perturbed(wfc, seed, rot_deg=2.0, shift_m=0.3)
        alone = refine_pose(view, photo, INTR, start, None, 0.0)
        joint = refine_pose(view, photo, INTR, start, None, 0.0, clicks=clicks)
    finally:
        view.close()
    before = _corner_error_px(meshes, INTR, wfc, INTR, start)
    after = _corner_error_px(meshes, INTR, wfc, joint.intrinsics, joint.world_from_camera)
    assert before > 0.005 * 960
    assert not alone.accepted
    assert joint.accepted, joint.reason
    assert after < 1.5, (before, after)
    assert joint.click_rms_px[1] < 3.0 and joint.click_rms_px[1] < joint.click_rms_px[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_pull_off_the_clicks_is_refused(seed: int) -> None:
    """The photo shows the building from a camera 2 m and 1 deg away from the one the clicks fit: the joint fit
    trades click RMS for outline support, and where the clicks would leave ``click_gate_px`` the start stands, with
    the reason; a looser gate takes the compromise."""
    meshes = _scene(seed)
    view = ModelView(meshes)
    try:
        wfc = _true_camera(seed)
        elsewhere = _perturbed(wfc, seed, rot_deg=1.0, shift_m=2.0)
        clicks = _clicks(meshes, INTR, wfc, seed, noise_px=0.5)
        photo = _photo(view, elsewhere, seed)
        # this scene's ground meets a flat sky: the band of ground steps near the horizon lies on a true edge here,
        # and the compromise between clicks and outline needs its support (off by default: real horizons are trees)
        tight = refine_pose(
            view, photo, INTR, wfc, None, 0.0, AlignParams(click_gate_px=1.0, ground_steps=True), clicks
        )
        loose = refine_pose(
            view, photo, INTR, wfc, None, 0.0, AlignParams(click_gate_px=6.0, ground_steps=True), clicks
        )
    finally:
        view.close()
    assert not tight.accepted
    assert "clicks" in tight.reason, tight.reason
    assert np.array_equal(tight.world_from_camera, wfc)
    assert loose.accepted, loose.reason
    assert 1.0 < loose.click_rms_px[1] < 6.0
