"""Render core: ID/depth rasters with distortion, overlay modes, photoreal composite."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest
from render_scenes import AT, camera, four_box_model

import constructaide  # noqa: F401  (EGL platform)
from constructaide.camera import invert_rigid, project_points
from constructaide.modelscene import GROUND_INDEX, scene_from_model
from constructaide.modelview import GLRasterizer
from nodes.render.overlays import (
    AHEAD_RGBA,
    BEHIND_RGBA,
    ON_TIME_RGBA,
    REVIEW_RGBA,
    ScheduleView,
    composite,
    render_overlay,
)
from nodes.render.photoreal import MaterialLibrary, PhotorealRenderer
from nodes.render.scene import filter_mask
from nodes.render.sun import sun_direction_in_site, sun_position
from schemas.messages import Annotation, BimElement, ElementFilter


@pytest.fixture(scope="module")
def ras():
    r = GLRasterizer()
    yield r
    r.close()


@pytest.fixture(scope="module")
def world():
    model = four_box_model()
    scene = scene_from_model(model)
    return model, scene, ScheduleView.from_model(model, scene)


def _px(intr, wfc, point):
    uv, z = project_points(intr, invert_rigid(wfc), [point])
    return int(round(uv[0, 1])), int(round(uv[0, 0])), float(z[0])


def test_render_ids_and_depth_match_projection_with_distortion(ras, world):
    _, scene, _ = world
    intr, wfc = camera()
    vis = np.ones(scene.num_elements + 1, bool)
    res = ras.render(scene, intr, wfc, vis)
    assert res.ids.shape == (intr.height_px, intr.width_px)
    for name, x in (("A", 0.0), ("B", 3.0), ("C", 6.0), ("D", 9.0)):
        # Centre of the box's front face (y = -1), projected with the shared distortion model.
        r, c, z = _px(intr, wfc, (x, -1.0, 1.0))
        assert scene.global_ids[res.ids[r, c] - 1] == name
        assert abs(res.depth_m[r, c] - z) < 0.02
    assert res.ids[2, 2] == 0 and res.depth_m[2, 2] == 0.0  # sky corner
    # Undistorted rendering would put the corner of box A elsewhere: distortion is really applied.
    r, c, _ = _px(intr, wfc, (-0.95, -1.0, 2.95))
    assert scene.global_ids[res.ids[r + 1, c + 1] - 1] == "A"


def test_render_visibility_mask_and_ground_plane(ras, world):
    _, scene, _ = world
    intr, wfc = camera(k1=0.0, k2=0.0)
    vis = np.ones(scene.num_elements + 1, bool)
    vis[scene.index_of["B"]] = False
    res = ras.render(scene, intr, wfc, vis, ground_z_m=0.0)
    r, c, _ = _px(intr, wfc, (3.0, -1.0, 1.0))
    assert res.ids[r, c] in (scene.index_of["E"], scene.index_of["F"], GROUND_INDEX)
    r, c, _ = _px(intr, wfc, (4.5, -1.0, -1.0))  # basement box F is below the ground plane
    assert res.ids[r, c] == GROUND_INDEX
    res2 = ras.render(scene, intr, wfc, vis)
    assert res2.ids[r, c] == scene.index_of["F"]


def test_render_ids_match_synthetic_truth(ras, small_site):
    """Element-ID render vs the synthetic site's truth with TRUE cameras, distortion included (>= 99.5 %)."""
    from constructaide.bimgeom import glb_to_meshes
    from constructaide.modelscene import build_scene
    from constructaide.synth import truth

    idx = truth.element_index(small_site)
    meshes = glb_to_meshes((small_site / "model" / "building.glb").read_bytes())
    scene = build_scene([BimElement(global_id=idx[i], ifc_class="x") for i in sorted(idx)], meshes)
    cams = truth.load_cameras(small_site)
    built = truth.element_states(small_site)["photos"]
    rels = sorted(cams)
    picks = [next(r for r in rels if r.startswith(p)) for p in ("cam-north", "cam-east", "cam-south", "phone")]
    picks.append(rels[-1])
    for rel in picks:
        intr, wfc = truth.true_camera(small_site, rel, cams)
        assert intr.k1 != 0.0
        vis = np.zeros(scene.num_elements + 1, bool)
        vis[[scene.index_of[g] for g in built[rel]]] = True
        ids = ras.render(scene, intr, wfc, vis).ids.astype(np.int64)
        true_ids = truth.load_ids(small_site, rel).astype(np.int64)
        # Occluders (ground over the basement, fence, trees, vehicles) are not BIM: compare elsewhere.
        keep = ~(truth.load_mask(small_site, rel, "static") | truth.load_mask(small_site, rel, "dynamic"))
        agree = float((ids == true_ids)[keep].mean())
        assert agree >= 0.995, f"{rel}: {agree:.4%}"
        assert (true_ids[keep] > 0).mean() > 0.02  # the building is in view


def _dominant(layer, mask):
    return np.median(layer[mask][:, :3].astype(float), axis=0)


def test_render_progress_colours_follow_schedule_and_annotations(ras, world):
    model, scene, _ = world
    sched = ScheduleView.from_model(model, scene)
    sched.apply_annotation(
        Annotation(
            site="t", annotation_id="a1", kind="status", element_ids=("D",), status="needs_review", created_ns=AT - 10
        )
    )
    intr, wfc = camera()
    res = render_overlay(ras, scene, sched, intr, wfc, "progress", AT)
    expect = {"A": AHEAD_RGBA, "B": ON_TIME_RGBA, "C": BEHIND_RGBA, "D": REVIEW_RGBA}
    for name, rgba in expect.items():
        m = res.raster.ids == scene.index_of[name]
        assert m.sum() > 200
        got = _dominant(res.layer_rgba, m)
        base = np.asarray(rgba[:3], float)
        # Colours are shaded by face orientation (x 0.55..1): compare the direction of the colour.
        cos = got @ base / (np.linalg.norm(got) * np.linalg.norm(base) + 1e-9)
        assert cos > 0.98, (name, got, base)
        assert np.median(res.layer_rgba[m][:, 3]) >= rgba[3]
    assert {e.label for e in res.legend} >= {"ahead of schedule", "on time", "behind schedule"}
    # A user's judgement (workbench status) overrides; deleting it (a later revision) restores the schedule's.
    judged = Annotation(
        site="t", annotation_id="a2", kind="status", element_ids=("B",), status="behind", created_ns=AT - 10
    )
    sched.apply_annotation(judged)
    assert sched.progress(AT, scene.global_ids)[scene.index_of["B"]] == 2
    sched.apply_annotation(msgspec.structs.replace(judged, revision=1, deleted=True))
    assert sched.progress(AT, scene.global_ids)[scene.index_of["B"]] == 1
    # Before anything was due nothing is coloured.
    early = render_overlay(ras, scene, sched, intr, wfc, "progress", AT - 30 * 86_400 * 10**9)
    assert early.layer_rgba[..., 3].max() == 0


def test_render_state4d_future_xray_edges(ras, world):
    model, scene, sched = world
    intr, wfc = camera()
    photo = np.full((intr.height_px, intr.width_px, 3), 90, np.uint8)
    st = render_overlay(ras, scene, sched, intr, wfc, "state4d", AT)
    assert scene.index_of["E"] not in np.unique(st.raster.ids)  # not yet built per plan
    assert {e.label for e in st.legend} >= {"IfcWall", "IfcColumn"}
    fut = render_overlay(ras, scene, sched, intr, wfc, "future", AT)
    e_px = fut.raster.ids == scene.index_of["E"]
    assert e_px.sum() > 500 and (fut.layer_rgba[e_px][:, 3] > 0).all()
    assert (fut.layer_rgba[fut.raster.ids == scene.index_of["A"]][:, 3] == 0).all()
    # X-ray of the basement footing: hidden by the ground, so it is ghosted where the ground is.
    xr = render_overlay(ras, scene, sched, intr, wfc, "xray", AT, ElementFilter(ifc_classes=("IfcFooting",)))
    f_px = xr.raster.ids == scene.index_of["F"]
    assert f_px.sum() > 500 and (xr.layer_rgba[f_px][:, 3] > 0).mean() > 0.95
    ed = render_overlay(ras, scene, sched, intr, wfc, "edges", AT)
    edge_frac = (ed.layer_rgba[..., 3] > 0).mean()
    assert 0.002 < edge_frac < 0.08
    out = composite(photo, st.layer_rgba)
    assert out.shape == photo.shape and (out != photo).any()
    # Occlusion: nothing is drawn on occluded pixels.
    occ = np.zeros(photo.shape[:2], bool)
    occ[:, : intr.width_px // 2] = True
    st2 = render_overlay(ras, scene, sched, intr, wfc, "state4d", AT, occlusion=occ)
    assert st2.layer_rgba[occ][:, 3].max() == 0 and st2.layer_rgba[~occ][:, 3].max() > 0
    with pytest.raises(ValueError, match="unknown overlay mode"):
        render_overlay(ras, scene, sched, intr, wfc, "sparkles", AT)


def test_render_filters(world):
    model, scene, sched = world
    m = filter_mask(scene, ElementFilter(ifc_classes=("IfcColumn",)), sched.task_elements)
    assert [scene.global_ids[i - 1] for i in np.nonzero(m)[0]] == ["C", "D"]
    m = filter_mask(scene, ElementFilter(task_ids=("tA", "tE")), sched.task_elements)
    assert [scene.global_ids[i - 1] for i in np.nonzero(m)[0]] == ["A", "E"]
    m = filter_mask(scene, ElementFilter(materials=("brick",), element_ids=("B", "C")), sched.task_elements)
    assert [scene.global_ids[i - 1] for i in np.nonzero(m)[0]] == ["B"]
    with pytest.raises(ValueError, match="unknown task"):
        filter_mask(scene, ElementFilter(task_ids=("nope",)), sched.task_elements)


def test_render_material_presets_and_toml(tmp_path):
    lib = MaterialLibrary()
    assert lib.preset_for(BimElement(global_id="a", ifc_class="IfcWall", material="Concrete C30/37")).name == "concrete"
    assert lib.preset_for(BimElement(global_id="a", ifc_class="IfcWall", material="Masonry, sand-lime")).name == "brick"
    assert lib.preset_for(BimElement(global_id="a", ifc_class="IfcWindow", material="")).name == "glass"
    assert lib.preset_for(BimElement(global_id="a", ifc_class="IfcBuildingElementProxy")).name == "concrete"
    f = tmp_path / "p.toml"
    f.write_text(
        "[presets.brick]\nbase_rgb = [0.1, 0.2, 0.9]\n[presets.gold]\nbase_rgb = [1, 0.8, 0.2]\n"
        'metallic = 1.0\nkeywords = ["gold"]\n[lighting]\nsun_intensity = 2.0\n'
    )
    lib2 = MaterialLibrary.from_toml(f)
    assert lib2.presets["brick"].base_rgb == (0.1, 0.2, 0.9)
    assert lib2.preset_for(BimElement(global_id="a", ifc_class="IfcBeam", material="Gold leaf")).name == "gold"
    assert lib2.lighting.sun_intensity == 2.0
    f.write_text("[presets.brick]\nbase_rgb = 3\n")
    with pytest.raises(ValueError, match="brick"):
        MaterialLibrary.from_toml(f)


def test_render_photoreal_differential_composite(ras, world):
    model, scene, sched = world
    intr, wfc = camera()
    rng = np.random.default_rng(0)
    photo = np.clip(rng.normal(120, 6, (intr.height_px, intr.width_px, 3)), 0, 255).astype(np.uint8)
    vis = sched.built(AT, basis="planned")
    sun = sun_position(51.8583, 5.8647, AT + 3 * 3600 * 10**9)  # early afternoon, sun to the south-west
    sun_dir = sun_direction_in_site(sun)
    assert sun_dir[2] > 0.2
    pr = PhotorealRenderer(ras)
    out = pr.render(scene, vis, intr, wfc, photo, sun_dir)
    ids = ras.render(scene, intr, wfc, vis).ids
    obj = ids > 0
    assert obj.mean() > 0.05
    assert np.abs(out[obj].astype(int) - photo[obj]).mean() > 10  # the model is drawn
    ground = ~obj
    ground[: intr.height_px // 2] = False
    diff = out[ground].astype(int).mean(1) - photo[ground].astype(int).mean(1)
    # Outside the object the photo only changes where rendered shadows fall: darker, never much brighter.
    assert (diff < -10).mean() > 0.005 and (diff > 8).mean() < 0.01
    occ = np.zeros(ids.shape, bool)
    occ[:, : intr.width_px // 3] = True
    out2 = pr.render(scene, vis, intr, wfc, photo, sun_dir, occlusion=occ)
    assert (out2[occ] == photo[occ]).all()
