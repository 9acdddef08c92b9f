"""The shared lower layer: image/mask codec, intrinsics scaling, the model view's depth lookups, the element-stands
rule and the recording reader."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest
from render_scenes import box

from constructaide import imagecodec, schedule4d
from constructaide.camera import (
    centered_intrinsics,
    invert_rigid,
    look_at,
    pose_to_tuple,
    project_points,
    registered_camera,
    scaled_intrinsics,
)
from constructaide.modelview import ModelView
from constructaide.sampling import farthest_point_order
from schemas.messages import OcclusionMask, Registration, ScheduleTask

DAY_NS = 86_400 * 10**9


def test_image_and_mask_codec_round_trip_and_errors() -> None:
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    assert np.array_equal(imagecodec.decode_bgr(imagecodec.encode_png(bgr)), bgr)
    assert np.array_equal(imagecodec.decode_rgb(imagecodec.encode_png_rgb(bgr[..., ::-1].copy())), bgr[..., ::-1])
    rgba = np.dstack([bgr, np.full((20, 30), 7, np.uint8)])
    assert imagecodec.decode_unchanged(imagecodec.encode_png_rgb(rgba))[..., 3].max() == 7
    jpeg = imagecodec.encode_jpeg(bgr, 95)
    assert jpeg[:2] == b"\xff\xd8" and imagecodec.decode_bgr(jpeg).shape == bgr.shape
    mask = np.zeros((20, 30), bool)
    mask[5:10, 3:20] = True
    png = imagecodec.encode_mask(mask)
    assert np.array_equal(imagecodec.decode_mask(png), mask)
    big = imagecodec.decode_mask(png, (40, 60))  # nearest-neighbour resize to (H, W)
    assert big.shape == (40, 60) and big.sum() == 4 * mask.sum()
    msg = OcclusionMask(site="s", photo_id="p", kind="static", status="ok", mask_png=png)
    got = imagecodec.mask_of_message(msg, (20, 30))
    assert got is not None and np.array_equal(got, mask)
    not_ok = OcclusionMask(site="s", photo_id="p", kind="static", status="not_enough_views")
    assert imagecodec.mask_of_message(not_ok, (20, 30)) is None and imagecodec.mask_of_message(None, (2, 2)) is None
    with pytest.raises(ValueError, match="photo x: not a decodable"):
        imagecodec.decode_bgr(b"\x89PNG broken", "photo x")
    with pytest.raises(ValueError, match="not a decodable"):
        imagecodec.decode_mask(b"")


def test_scaled_intrinsics_maps_pixel_centres_and_keeps_the_aspect() -> None:
    intr = centered_intrinsics(1280, 800, 960.0, k1=-0.1, fy_over_fx=1.02)
    half = scaled_intrinsics(intr, 640, 400)
    assert half.f_px == pytest.approx(480.0) and half.fy_over_fx == pytest.approx(1.02)
    assert (half.cx_px, half.cy_px) == pytest.approx(((640 - 1) / 2, (400 - 1) / 2)) and half.k1 == intr.k1
    squashed = scaled_intrinsics(intr, 640, 200)  # fy follows the height
    assert squashed.f_px * squashed.fy_over_fx == pytest.approx(intr.f_px * 1.02 / 4)
    with pytest.raises(ValueError, match="positive"):
        scaled_intrinsics(intr, 0, 10)


@pytest.mark.parametrize("k1", [0.0, -0.1])
def test_model_view_depth_lookup(k1: float) -> None:
    """Depth at distorted pixels is the projection's depth on the faces, NaN off the model and on silhouettes;
    ``elements`` leaves meshes out; a ground plane gives the terrain its depth."""
    intr = centered_intrinsics(640, 480, 520.0, k1=k1, k2=0.01 if k1 else 0.0)
    wfc = look_at((0.0, -12.0, 2.0), (0.0, 0.0, 1.5))
    view = ModelView({"A": box((0.0, 0.0, 1.5), (2, 2, 3)), "B": box((0.0, 4.0, 3.0), (8, 1, 6))})
    rng = np.random.default_rng(3)
    front = np.c_[rng.uniform(-0.9, 0.9, 100), np.full(100, -1.0), rng.uniform(0.1, 2.9, 100)]
    px, z = project_points(intr, invert_rigid(wfc), front)
    d = view.depth_at(wfc, intr, px)
    assert np.allclose(d, z, rtol=0.005)
    # points on B's face (y = 3.5) hidden behind A: A's depth with every element, B's with A left out
    hidden = np.c_[rng.uniform(-0.5, 0.5, 50), np.full(50, 3.5), rng.uniform(1.0, 2.5, 50)]
    h_px, h_z = project_points(intr, invert_rigid(wfc), hidden)
    assert np.all(view.depth_at(wfc, intr, h_px) < h_z - 4.0)
    assert np.allclose(view.depth_at(wfc, intr, h_px, elements={"B"}), h_z, rtol=0.005)
    # silhouette of A against B (a 4.5 m jump) and a pixel outside the image: NaN
    edge_px, _ = project_points(intr, invert_rigid(wfc), [(1.0, -1.0, 1.0)])
    sky_px, _ = project_points(intr, invert_rigid(wfc), [(0.0, 0.0, 30.0)])
    assert np.isnan(view.depth_at(wfc, intr, np.vstack([edge_px, [[-5.0, 10.0]], sky_px]))).all()
    # the ground plane at z = 0 in front of the building
    ground = np.array([[0.5, -5.0, 0.0]])
    g_px, g_z = project_points(intr, invert_rigid(wfc), ground)
    assert np.isnan(view.depth_at(wfc, intr, g_px)[0])
    assert view.depth_at(wfc, intr, g_px, ground_z_m=0.0)[0] == pytest.approx(g_z[0], rel=0.01)
    # the surface maps agree with the lookup at the same pixels (working size: half)
    maps = view.maps(intr, wfc, 320, 240)
    small = scaled_intrinsics(intr, 320, 240)
    spx, sz = project_points(small, invert_rigid(wfc), front)
    r, c = np.round(spx[:, 1]).astype(int), np.round(spx[:, 0]).astype(int)
    assert np.allclose(maps.depth_m[r, c], sz, rtol=0.01)
    assert np.all(maps.normal_in_world[r, c, 1] < -0.99)
    view.close()


def test_standing_elements_follows_actual_then_planned_dates() -> None:
    tasks = (
        ScheduleTask(task_id="t1", name="walls", planned_start_ns=0, planned_finish_ns=10 * DAY_NS, element_ids=("w",)),
        ScheduleTask(
            task_id="t2",
            name="roof",
            planned_start_ns=10 * DAY_NS,
            planned_finish_ns=20 * DAY_NS,
            actual_start_ns=12 * DAY_NS,
            actual_finish_ns=25 * DAY_NS,
            element_ids=("r",),
        ),
        ScheduleTask(
            task_id="t3",
            name="scaffold",
            planned_start_ns=0,
            planned_finish_ns=30 * DAY_NS,
            task_type="temporary",
            element_ids=("s",),
        ),
    )
    at = schedule4d.standing_elements(tasks, ["w", "r", "s", "u"])
    assert at(5 * DAY_NS) == {"u"}  # under construction: not standing; unscheduled: standing
    assert at(15 * DAY_NS) == {"w", "u"}
    assert at(22 * DAY_NS) == {"w", "u"}  # the roof finished late (actual 25)
    assert at(26 * DAY_NS) == {"w", "r", "u"}
    assert at(31 * DAY_NS) == {"w", "r", "u"}  # the scaffold was removed at its finish
    assert schedule4d.standing_elements((), ["w"])(0) is None  # no schedule: no filter


def test_a_distortion_that_folds_back_renders_what_it_covers() -> None:
    """An estimated distortion whose undistortion folds outwards (k2 = -0.84, as a poorly constrained batch
    registration can give) renders the covered rays and leaves the rest empty instead of failing."""
    intr = centered_intrinsics(320, 180, 300.0, k1=0.03, k2=-0.84)
    wfc = look_at((0.0, -12.0, 2.0), (0.0, 0.0, 1.5))
    view = ModelView({"A": box((0.0, 0.0, 1.5), (6, 2, 3))})
    ras = view.raster(intr, wfc)
    maps = view.maps(intr, wfc, 320, 180)
    assert ras.ids.shape == (180, 320) and (ras.ids > 0).any()
    assert ras.ids[90, 160] > 0 and np.isfinite(maps.depth_m[90, 160])  # the centre sees the box
    from constructaide.modelview import render_geometry

    outside = render_geometry(intr).outside
    assert outside is not None and outside.any() and not outside[90, 160]
    assert (ras.ids[outside] == 0).all() and not np.isfinite(maps.depth_m[outside]).any()
    view.close()


def test_reduced_decode_halves_the_size() -> None:
    bgr = np.random.default_rng(1).integers(0, 256, (40, 60, 3), dtype=np.uint8)
    jpeg = imagecodec.encode_jpeg(bgr, 95)
    assert imagecodec.decode_bgr(jpeg, reduced=2).shape == (20, 30, 3)
    assert imagecodec.decode_gray(jpeg, reduced=2).shape == (20, 30)


def test_farthest_point_order_spreads_and_never_repeats() -> None:
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [0.0, 10.0]])
    order = farthest_point_order(pts, [0])
    assert sorted(order.tolist()) == list(range(len(pts)))  # every point once, duplicates included
    assert order[1] == 3  # the far corner first
    assert set(order[2:4].tolist()) == {2, 4}  # then the two other corners (4 before its duplicate 5)
    assert order[-1] in (1, 5)
    # an extra reference point (not a candidate) pushes the picks away from it
    t = np.array([[-5.0], [-1.0], [1.0], [6.0]])
    assert farthest_point_order(t, [1, 2], also_from=[[0.0]]).tolist() == [1, 2, 3, 0]
    assert farthest_point_order(pts, [2], n=2).tolist() == [2, 4]


def test_registered_camera_only_of_usable_registrations() -> None:
    intr = centered_intrinsics(64, 48, 50.0)
    pose = look_at([0.0, -5.0, 1.0], [0.0, 0.0, 1.0])
    reg = Registration(site="s", photo_id="p", status="auto", intrinsics=intr, world_from_camera=pose_to_tuple(pose))
    camera = registered_camera(reg)
    assert camera is not None and camera.intrinsics == intr and np.allclose(camera.world_from_camera, pose)
    assert registered_camera(msgspec.structs.replace(reg, status="failed")) is None
    assert registered_camera(msgspec.structs.replace(reg, intrinsics=None)) is None
    assert registered_camera(msgspec.structs.replace(reg, world_from_camera=())) is None
