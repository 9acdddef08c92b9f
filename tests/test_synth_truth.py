"""Ground-truth self-consistency of the cached `small` synthetic site (built once per session)."""

from __future__ import annotations

import datetime as dt
import tomllib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from constructaide.camera import invert_rigid, pixels_to_normalized, project_points
from constructaide.synth.building import design_building
from constructaide.synth.config import SIZES
from constructaide.synth.scene import make_layout
from constructaide.synth.truth import (
    element_index,
    element_states,
    load_cameras,
    load_depth,
    load_ids,
    load_mask,
    true_camera,
)


@pytest.fixture(scope="module")
def site(small_site: Path) -> Path:
    return small_site


@pytest.fixture(scope="module")
def building():
    return design_building(SIZES["small"])


@pytest.fixture(scope="module")
def guid_of_key(site: Path) -> dict[str, str]:
    states = element_states(site)["elements"]
    return {rec["name"]: guid for guid, rec in states.items()}


def _boxes(element) -> list[np.ndarray]:
    """(2, 3) min/max of each box of an element (the roof prism counts as its bounding box)."""
    v = element.vertices_m
    if len(v) % 8 or len(element.polygons) != 6 * (len(v) // 8):
        return [element.bounds_m]
    return [np.stack([v[i : i + 8].min(0), v[i : i + 8].max(0)]) for i in range(0, len(v), 8)]


@pytest.fixture(scope="module")
def all_boxes(building) -> list[tuple[str, np.ndarray]]:
    return [(e.key, b) for e in building.elements for b in _boxes(e)]


def _touches_other(point: np.ndarray, key: str, all_boxes) -> bool:
    """True if ``point`` lies on or in a box of another element (contact faces are ambiguous in any render)."""
    return any(k != key and np.all(point >= b[0] - 1e-3) and np.all(point <= b[1] + 1e-3) for k, b in all_boxes)


def _face_samples(element, rng: np.random.Generator, per_face: int, all_boxes) -> np.ndarray:
    """Random points strictly inside the element's polygons that are not in contact with another element."""
    out = []
    for poly in element.polygons:
        v = element.vertices_m[poly]
        if _touches_other(v.mean(0), element.key, all_boxes):
            continue
        for _ in range(per_face):
            out.append(rng.dirichlet(np.ones(len(v)) * 3.0) @ v)
    return np.asarray(out).reshape(-1, 3)


def _photos(site: Path) -> list[str]:
    return sorted(load_cameras(site))


def test_site_layout_and_toml(site: Path) -> None:
    meta = tomllib.loads((site / "site.toml").read_text())
    assert meta["site"]["tz"] == "Europe/Amsterdam"
    assert 51.0 < meta["site"]["lat_deg"] < 52.5 and 5.0 < meta["site"]["lon_deg"] < 6.5
    for key in ("ifc", "glb", "photos", "anchors"):
        assert (site / meta["paths"][key]).exists(), key
    photos = _photos(site)
    fixed = [p for p in photos if not p.startswith("phone/")]
    phone = [p for p in photos if p.startswith("phone/")]
    assert len(fixed) == 3 * 6 and len(phone) == 5
    for p in photos:
        assert (site / "photos" / p).is_file()
        ids = load_ids(site, p)
        rec = load_cameras(site)[p]
        assert ids.shape == (rec["height"], rec["width"]) and ids.dtype == np.uint16
        assert load_depth(site, p).shape == ids.shape
        assert load_mask(site, p, "static").shape == ids.shape


def test_backprojected_id_pixels_lie_on_their_element(site: Path, building, guid_of_key) -> None:
    """ID + depth + true camera (with distortion) put every interior element pixel on that element's box."""
    index = element_index(site)
    bounds = {guid_of_key[e.key]: e.bounds_m for e in building.elements}
    cams = load_cameras(site)
    rng = np.random.default_rng(0)
    errors = []
    for p in _photos(site)[::2]:
        intr, wfc = true_camera(site, p, cams)
        ids = load_ids(site, p).astype(np.int64)
        depth = load_depth(site, p)
        # interior pixels: the 3x3 neighbourhood has one id
        core = ids[1:-1, 1:-1]
        same = np.ones_like(core, dtype=bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                same &= ids[1 + dy : ids.shape[0] - 1 + dy, 1 + dx : ids.shape[1] - 1 + dx] == core
        vs, us = np.nonzero(same & (core > 0))
        assert len(vs) > 500, p
        pick = rng.choice(len(vs), size=min(800, len(vs)), replace=False)
        v, u = vs[pick] + 1, us[pick] + 1
        xy = pixels_to_normalized(intr, np.stack([u, v], 1).astype(np.float64))
        z = depth[v, u].astype(np.float64)
        pts_cam = np.concatenate([xy * z[:, None], z[:, None]], 1)
        pts = pts_cam @ wfc[:3, :3].T + wfc[:3, 3]
        for pt, idx in zip(pts, ids[v, u], strict=True):
            lo, hi = bounds[index[int(idx)]]
            errors.append(float(np.linalg.norm(np.maximum(lo - pt, 0) + np.maximum(pt - hi, 0))))
    errors = np.asarray(errors)
    assert np.median(errors) < 0.005
    assert np.percentile(errors, 95) < 0.03


def test_projected_surface_points_land_on_their_element(site: Path, building, guid_of_key, all_boxes) -> None:
    """A visible model point projected with the true camera lands on its element's pixels (within 1 px)."""
    index = {g: i for i, g in element_index(site).items()}
    states = element_states(site)
    cams = load_cameras(site)
    rng = np.random.default_rng(1)
    hits = total = 0
    for p in _photos(site)[1::2]:
        intr, wfc = true_camera(site, p, cams)
        ids, depth = load_ids(site, p), load_depth(site, p)
        H, W = ids.shape
        built = set(states["photos"][p])
        for e in building.elements:
            g = guid_of_key[e.key]
            if g not in built:
                continue
            corners = [c for c in e.vertices_m if not _touches_other(c, e.key, all_boxes)]
            pts = np.vstack([_face_samples(e, rng, 3, all_boxes), np.reshape(corners, (-1, 3))])
            px, z = project_points(intr, invert_rigid(wfc), pts)
            for (uu, vv), zz in zip(px, z, strict=True):
                if not np.isfinite(uu) or zz <= 0:
                    continue
                u, v = int(round(uu)), int(round(vv))
                if not (1 <= u < W - 1 and 1 <= v < H - 1):
                    continue
                # visible: the rendered depth in the 3x3 window reaches the point's depth
                if np.min(np.abs(depth[v - 1 : v + 2, u - 1 : u + 2] - zz)) > 0.01 * zz + 0.02:
                    continue
                total += 1
                hits += bool(np.any(ids[v - 1 : v + 2, u - 1 : u + 2] == index[g]))
    assert total > 2000
    assert hits / total > 0.98


def test_occluded_model_points_are_masked(site: Path, building, guid_of_key, all_boxes) -> None:
    """Where a built element projects, the photo shows an element or a static/dynamic occluder is masked."""
    states = element_states(site)
    cams = load_cameras(site)
    rng = np.random.default_rng(2)
    covered = total = 0
    static_seen = dynamic_seen = 0
    for p in _photos(site):
        intr, wfc = true_camera(site, p, cams)
        ids = load_ids(site, p)
        st, dy = load_mask(site, p, "static"), load_mask(site, p, "dynamic")
        assert not np.any(st & dy), "static and dynamic masks overlap"
        assert not np.any(ids[st | dy]), "masked pixels carry element ids"
        static_seen += st.any()
        dynamic_seen += dy.any()
        H, W = ids.shape
        built = set(states["photos"][p])
        pts = np.vstack([_face_samples(e, rng, 2, all_boxes) for e in building.elements if guid_of_key[e.key] in built])
        px, z = project_points(intr, invert_rigid(wfc), pts)
        ok = np.isfinite(px).all(1) & (z > 0)
        px = px[ok]
        u, v = np.round(px[:, 0]).astype(int), np.round(px[:, 1]).astype(int)
        inside = (u >= 1) & (u < W - 1) & (v >= 1) & (v < H - 1)
        u, v = u[inside], v[inside]
        union = (ids > 0) | st | dy
        # allow one pixel of resampling slack
        ok_px = np.zeros(len(u), bool)
        for dyy in (-1, 0, 1):
            for dxx in (-1, 0, 1):
                ok_px |= union[v + dyy, u + dxx]
        covered += int(ok_px.sum())
        total += len(u)
    assert total > 5000
    assert covered / total > 0.995
    assert static_seen == len(_photos(site))  # the ground always hides the basement
    assert dynamic_seen >= len(_photos(site)) // 2


def test_dynamic_mask_covers_the_crane_mast(site: Path, building) -> None:
    layout = make_layout(building)
    cams = load_cameras(site)
    mast = np.array([[layout.crane_xy[0], layout.crane_xy[1], z] for z in np.linspace(1.0, building.top_m, 40)])
    hits = total = 0
    for p in _photos(site):
        intr, wfc = true_camera(site, p, cams)
        depth, dy = load_depth(site, p), load_mask(site, p, "dynamic")
        H, W = dy.shape
        px, z = project_points(intr, invert_rigid(wfc), mast)
        for (uu, vv), zz in zip(px, z, strict=True):
            if not np.isfinite(uu) or zz <= 0:
                continue
            u, v = int(round(uu)), int(round(vv))
            if 0 <= u < W and 0 <= v < H and abs(depth[v, u] - zz) < 1.2:  # the mast surface is what we see
                total += 1
                hits += bool(dy[v, u])
    assert total > 50
    assert hits / total > 0.97


def test_schedule_states_match_rendered_geometry(site: Path) -> None:
    states = element_states(site)
    index = element_index(site)
    cams = load_cameras(site)
    never = [g for g, r in states["elements"].items() if r["never_built"]]
    assert len(never) == 1
    kinds = {r["deviation"] for r in states["elements"].values()}
    assert {"late", "early", "on_time", "never_built"} <= kinds
    counts = []
    for p in _photos(site):
        built = set(states["photos"][p])
        shown = {index[int(i)] for i in np.unique(load_ids(site, p)) if i > 0}
        assert shown <= built, f"{p} shows elements not built yet"
        assert never[0] not in built
        t = dt.datetime.fromtimestamp(cams[p]["capture_time_utc_ns"] / 1e9, dt.UTC)
        for g, r in states["elements"].items():
            fin = r["actual_finish"]
            assert (g in built) == (fin is not None and dt.datetime.fromisoformat(fin) <= t)
        if p.startswith("cam-north/"):
            counts.append(len(shown))
    assert counts[-1] > counts[0], "the building grows over time"


def test_exif(site: Path) -> None:
    cams = load_cameras(site)
    for p in _photos(site)[::3]:
        with Image.open(site / "photos" / p) as im:
            exif = im.getexif()
        sub, gps = exif.get_ifd(0x8769), exif.get_ifd(0x8825)
        local = dt.datetime.strptime(sub[0x9003], "%Y:%m:%d %H:%M:%S")
        sign = 1 if sub[0x9011][0] == "+" else -1
        hh, mm = sub[0x9011][1:].split(":")
        offset = dt.timedelta(hours=int(hh), minutes=int(mm)) * sign
        utc = (local - offset).replace(tzinfo=dt.UTC)
        assert int(utc.timestamp()) * 10**9 == cams[p]["capture_time_utc_ns"]
        diag_px = np.hypot(cams[p]["width"], cams[p]["height"])
        f35 = cams[p]["K"][0][0] * np.hypot(36.0, 24.0) / diag_px  # diagonal crop factor
        assert abs(sub[0xA405] - f35) <= 0.5
        assert float(sub[0x920A]) > 0
        lat = sum(float(x) / 60**i for i, x in enumerate(gps[0x0002]))
        lon = sum(float(x) / 60**i for i, x in enumerate(gps[0x0004]))
        assert gps[0x0001] == "N" and abs(lat - 51.8583) < 0.002 and abs(lon - 5.8647) < 0.003
