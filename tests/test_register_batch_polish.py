"""The batch command's model-outline polish (``constructaide register --bim``): the IFC read as the ingest node reads
it, the registered poses polished as the register node polishes what it publishes, written to the COLMAP model.
Scored against the synthetic sites' truth (the test is the scoring code; the register command never reads it)."""

from __future__ import annotations

import copy
import json
import re
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from constructaide import camera as cam
from constructaide.errors import UserError
from nodes.register.batch import find_images, load_bim_lookup, polish_reconstruction, run_batch
from nodes.register.colmap_io import read_text_model
from nodes.register.recon import Reconstruction

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import _datasets as ds  # noqa: E402


def _anchor_file(site: Path, cams: list[ds.GtCamera], path: Path, seed: int) -> None:
    """A careful user's clicks (visible corners, 1 px) on each fixed camera's first frame and on every phone photo:
    the phones are anchored, so the polish holds their clicks."""
    firsts = {c.name.split("/")[0]: c for c in reversed(cams) if not c.name.startswith("phone/")}
    anchors = []
    for c in [*firsts.values(), *(c for c in cams if c.name.startswith("phone/"))]:
        try:
            px, world = ds.simulate_synth_clicks(site, c, seed=seed)
        except ValueError:  # fewer than 4 visible corners: a person would not anchor that photo
            continue
        anchors.append(
            {"image": c.name, "points": [{"pixel": list(p), "world": list(w)} for p, w in zip(px, world, strict=True)]}
        )
    path.write_text(json.dumps({"anchors": anchors}))


def _model_error_pct(c: ds.GtCamera, intr, world_from_camera: np.ndarray, X: np.ndarray) -> float:
    """Mean reprojection of the checkpoints the true camera sees, % of the width."""
    px_true, vis = c.visible(X)
    px, _ = cam.project_points(intr, cam.invert_rigid(world_from_camera), X[vis])
    return 100.0 * float(np.mean(np.linalg.norm(px - px_true[vis], axis=1))) / c.width_px


def _bim(site: Path) -> tuple[tuple[Path, ...], str, float]:
    """The site's IFC files, time zone and terrain height (what ``register --bim --tz --terrain-height-m`` take)."""
    doc = tomllib.loads((site / "site.toml").read_text())
    return (site / doc["paths"]["ifc"],), doc["site"]["tz"], doc["site"]["terrain_height_m"]


def _register(photos: Path, tmp: Path, **kwargs: Any) -> tuple[Reconstruction, dict]:
    """``run_batch`` on the site layout with ``tmp/anchors.json``, no densification, into ``tmp/out``."""
    return run_batch(
        photos,
        tmp / "anchors.json",
        tmp / "out",
        show_progress=False,
        densify_params=None,
        camera_folders=True,
        **kwargs,
    )


@pytest.mark.slow
@pytest.mark.parametrize("site_fixture", ["small_site", "small_site_seed7"])
def test_outline_polish_of_a_batch_reconstruction_lowers_the_model_error(
    request: pytest.FixtureRequest, tmp_path: Path, site_fixture: str
) -> None:
    """The whole small site, registered from a careful user's clicks on each camera's first frame and on every
    phone photo, then polished (:func:`polish_reconstruction`, what ``run_batch`` calls with ``bim_paths``): where
    the polish acts, the model sits closer to where it should on average and no photo gets much worse."""
    site: Path = request.getfixturevalue(site_fixture)
    cams = ds.load_synth(site)
    _anchor_file(site, cams, tmp_path / "anchors.json", seed=1)
    solved, _ = _register(site / "photos", tmp_path, polish_params=None)
    recon = copy.deepcopy(solved)
    lookup = load_bim_lookup(*_bim(site))
    try:
        notes = polish_reconstruction(recon, dict(find_images(site / "photos")), lookup)
    finally:
        lookup.close()
    X = ds.synth_checkpoints(site, cams)
    fixed: dict[str, list] = {"before": [], "after": [], "name": []}
    phones: dict[str, list] = {"before": [], "after": [], "name": []}
    for c in cams:
        a, b = solved.images[solved.index(c.name)], recon.images[recon.index(c.name)]
        if not a.registered:
            assert c.name not in notes
            continue
        assert notes[c.name], c.name  # every registered photo says whether and how it was polished
        if not notes[c.name].startswith("polished by the model outline"):
            assert np.array_equal(a.pose, b.pose) and a.camera == b.camera, c.name
            continue
        assert a.camera_id is not None or a.status == "anchor", notes[c.name]  # phones only with their clicks
        group = fixed if a.camera_id is not None else phones
        group["before"].append(_model_error_pct(c, a.camera, a.pose, X))
        group["after"].append(_model_error_pct(c, b.camera, b.pose, X))
        group["name"].append(f"{c.name}: {notes[c.name]}")
    # Fixed cameras' frames: the polish helps where it acts, none made much worse.
    assert len(fixed["after"]) >= 4, notes
    assert np.mean(fixed["after"]) < 0.7 * np.mean(fixed["before"]), fixed
    assert max(np.subtract(fixed["after"], fixed["before"])) < 0.1, fixed
    assert max(fixed["after"]) < 0.3, fixed
    # Anchored phone photos: polished with their clicks held (their RMS within 4 px, or within their RMS as solved).
    # On close-ups of brick and printed hoarding the outlines can still lock onto texture and pull the overlay off
    # by up to a percent of the width (small seed 7's IMG_0002 in some runs): BENCHMARKS.md 'registration
    # (synthetic small sites 7 / 11 / 13, batch outline polish, 2026-12-06)' counts them; no band is asserted.
    for note in phones["name"]:
        rms0, rms1 = map(float, re.search(r"clicks ([0-9.]+) -> ([0-9.]+) px", note).groups())
        assert rms1 <= max(4.0, rms0) + 0.01, note


@pytest.mark.slow
def test_register_with_bim_writes_the_polished_poses(small_site: Path, tmp_path: Path) -> None:
    """``run_batch`` with ``bim_paths`` (``register --bim``): the report says per photo how it was polished or why
    not, and the COLMAP model holds the polished poses."""
    cams = [c for c in ds.load_synth(small_site) if c.name.startswith(("cam-south/", "phone/20260312/"))]
    for c in cams:
        (tmp_path / "photos" / c.name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "photos" / c.name).symlink_to(c.path)
    _anchor_file(small_site, cams, tmp_path / "anchors.json", seed=1)
    ifc, tz, terrain = _bim(small_site)
    recon, report = _register(tmp_path / "photos", tmp_path, bim_paths=ifc, tz=tz, terrain_height_m=terrain)
    assert report["timings_secs"]["outline_polish"] > 0
    written = {im.name: im for im in read_text_model(tmp_path / "out").images}
    notes = {d["image"]: d.get("polish") for d in report["images"]}
    polished = [n for n, note in notes.items() if note and note.startswith("polished by the model outline")]
    assert polished, notes
    for im in recon.images:
        if im.registered:
            assert notes[im.name], im.name
            assert np.allclose(written[im.name].world_from_camera, im.pose, atol=1e-6)
            assert written[im.name].intrinsics.f_px == pytest.approx(im.camera.f_px)


def test_bad_bim_file_is_a_user_error(tmp_path: Path) -> None:
    bad = tmp_path / "model.ifc"
    bad.write_text("not an IFC file")
    with pytest.raises(UserError, match="--bim"):
        load_bim_lookup((bad,))
