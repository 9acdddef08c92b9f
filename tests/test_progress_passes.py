"""Reading a photo in passes: unlikely candidates (planned later) are read after the likelier ones."""

from __future__ import annotations

import numpy as np
import pytest

from nodes.progress.evidence import ElementCue
from nodes.progress.passes import covering, settle_deferred


def cue(i: int, llr: float, status: str = "seen") -> ElementCue:
    return ElementCue(i, region_px=100, visible_px=100, occluded_fraction=0.0, llr_appearance=llr, status=status)


def test_covering_names_what_a_later_layer_draws_over_each_element() -> None:
    first = np.zeros((4, 6), np.uint32)
    first[:, :3] = 1  # a beam due today
    first[:, 3:] = 2  # a column
    later = first.copy()
    later[1:3, 1:5] = 3  # a wall planned next week, nearer, over both
    later[0, 5] = 0  # a pixel nothing covers in the later pass: not a cover
    assert covering(first, later) == {1: {3}, 2: {3}}
    assert covering(first, first) == {}


@pytest.mark.parametrize("wall_stands", [False, True])
def test_an_element_keeps_its_first_reading_unless_a_standing_deferred_one_covered_it(wall_stands: bool) -> None:
    """The beam (1) was read without the wall (3); the column (2) is not covered. When the photo shows the wall
    absent the beam's first reading stands; when the wall stands the beam's pixels were the wall's, so its reading
    with the wall drawn counts (here: too few pixels left, ``unknown``)."""
    first = [cue(1, +0.8), cue(2, -0.5)]
    later = [cue(1, 0.0, "unknown"), cue(2, -0.4), cue(3, +0.9 if wall_stands else -0.9)]
    cover = {1: {3}}
    got = settle_deferred(first, later, {3}, cover, lambda i: wall_stands)
    by = {c.index: c for c in got}
    assert set(by) == {1, 2}  # the deferred wall's own cue is the caller's
    assert by[2].llr_appearance == -0.5  # uncovered: first reading
    if wall_stands:
        assert by[1].status == "unknown"
    else:
        assert by[1].status == "seen" and by[1].llr_appearance == pytest.approx(0.8)


def test_an_element_only_the_later_pass_shows_is_kept() -> None:
    """An element hidden in the first pass behind a likelier candidate and shown in the second (the geometry of
    the passes differs only by the deferred candidates, so this is rare) keeps its later reading."""
    got = settle_deferred([cue(1, 0.3)], [cue(1, 0.3), cue(4, 0.6)], {3}, {}, lambda i: False)
    assert sorted(c.index for c in got) == [1, 4]


D = 86_400_000_000_000


@pytest.mark.parametrize("seed", [0, 1])
def test_a_wall_planned_next_week_does_not_hide_the_beam_due_today(seed: int) -> None:
    """A beam due today stands behind where a wall planned for next week would be. Read with every candidate at
    once (no peel pass after it), the wall (nearer) owns the beam's pixels and the beam gets no reading; with the
    unlikely wall deferred the beam is read, with all its pixels, and so is the wall."""
    from test_progress_fusion_evidence import box, textured

    from constructaide.bimgeom import meshes_to_glb
    from constructaide.camera import look_at, pose_to_tuple
    from constructaide.imagecodec import encode_jpeg
    from nodes.progress.engine import EngineParams, ProgressEngine
    from nodes.progress.modelview import LayerRenderer
    from schemas.messages import BimElement, BimModel, Intrinsics, Photo, Registration, ScheduleTask

    meshes = {"beam": box((-1.5, 1.0, 0.8), (1.5, 1.3, 1.6)), "wall": box((-2.0, -1.2, 0.0), (2.0, -1.0, 2.4))}
    intr = Intrinsics(width_px=640, height_px=480, f_px=520.0, cx_px=320.0, cy_px=240.0)
    T = look_at((0.0, -8.0, 1.2), (0.0, 0.0, 1.0))
    r = LayerRenderer()
    r.set_model(["beam", "wall"], meshes)
    beam = r.render(intr, T, np.array([False, True, False]), np.zeros(3, bool)).ids_built == 1
    rng = np.random.default_rng(seed)
    rgb = textured(rng, (480, 640), (70, 120, 60), 12.0)  # green hoarding behind
    rgb[beam] = textured(rng, (480, 640), (150, 150, 145), 18.0)[beam]  # the concrete beam, standing
    tasks = (
        ScheduleTask(task_id="t-beam", name="beam", planned_start_ns=D, planned_finish_ns=3 * D, element_ids=("beam",)),
        ScheduleTask(
            task_id="t-wall", name="wall", planned_start_ns=9 * D, planned_finish_ns=10 * D, element_ids=("wall",)
        ),
    )
    model = BimModel(
        site="t",
        revision="r1",
        elements=(
            BimElement(global_id="beam", ifc_class="IfcBeam", material="concrete"),
            BimElement(global_id="wall", ifc_class="IfcWall", material="brick"),
        ),
        tasks=tasks,
        geometry_glb=meshes_to_glb(meshes),
    )
    photo = Photo(site="t", photo_id="p", capture_time_ns=2 * D + D // 2, data=encode_jpeg(rgb[:, :, ::-1].copy(), 95))
    reg = Registration(
        site="t", photo_id="p", intrinsics=intr, world_from_camera=pose_to_tuple(T), status="auto", method="pnp"
    )

    def read(params: EngineParams) -> dict[int, tuple[str, int, float]]:
        eng = ProgressEngine(params)
        eng.set_model(model)
        eng.add_photo(photo)
        eng.add_registration(reg)
        eng.process("p")
        return eng.records["p"].cues

    at_once = read(EngineParams(peel_passes=0, defer_probability=0.0))
    deferred = read(EngineParams(peel_passes=0, defer_probability=0.25))
    assert 1 not in at_once or at_once[1][0] != "seen"
    assert deferred[1][0] == "seen" and deferred[1][1] >= 0.9 * int(beam.sum())
    assert 2 in deferred  # the wall is read too
