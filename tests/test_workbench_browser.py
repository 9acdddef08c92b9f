"""The workbench page in a real headless Chromium (Debian's, driven by Playwright) on the small synthetic site run
through the real register and render nodes: a person answers an anchor request by clicking model points and photo
pixels, selects an element in a photo and annotates it, finds the note on another camera's photo of another day,
moves the time slider and peeks backward. The test reads the site's truth only to decide where to click and to
score what the page shows. Screenshots go to docs/workbench_*.png.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import httpx
import msgspec
import numpy as np
import pytest
from conftest import ROOT
from workbench_site import SITE, running_site

from constructaide import camera as cam
from constructaide.synth import truth
from nodes.workbench.geometry import ModelGeometry
from schemas import keys
from schemas.messages import Intrinsics, Registration

CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary (apt-get install chromium)")
DOCS = ROOT / "docs"
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture(scope="module")
def site(small_site):
    with running_site(small_site, progress=True) as s:
        yield s


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (pip) is not installed")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture()
def page(browser, site):
    pg = browser.new_page(viewport={"width": 1500, "height": 980})
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.goto(site.url)
    pg.wait_for_function("window.wb && window.wb.ready", timeout=30_000)
    yield pg
    pg.close()
    assert errors == [], errors


def _click_px(pg, selector: str, u: float, v: float, width_px: int, height_px: int) -> None:
    """Click photo / canvas pixel (u, v) (OpenCV convention) of an element showing a width_px x height_px image."""
    box = pg.locator(selector).bounding_box()
    pg.mouse.click(box["x"] + (u + 0.5) * box["width"] / width_px, box["y"] + (v + 0.5) * box["height"] / height_px)


def _photo_id(site, rel: str) -> str:
    return site.photos[rel].photo_id


# ------------------------------------------------------------------------------------------------- anchoring


def _visible_corners(site, rel: str, geometry: ModelGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Model corners a person can see in the photo (truth camera and depth: unoccluded, inside the frame)."""
    cams = truth.load_cameras(site.site_dir)
    intr, wfc = truth.true_camera(site.site_dir, rel, cams)
    depth = truth.load_depth(site.site_dir, rel)
    standing = geometry.standing(site.photos[rel].capture_time_ns)
    pts = geometry.corners[standing[geometry.corner_owner]]
    px, z = cam.PinholeCamera(intr, wfc).project(pts)
    ok = np.isfinite(px).all(1) & (z > 0)
    m = 12
    ok &= (px[:, 0] > m) & (px[:, 0] < intr.width_px - m) & (px[:, 1] > m) & (px[:, 1] < intr.height_px - m)
    keep = []
    for i in np.nonzero(ok)[0]:
        u, v = np.round(px[i]).astype(int)
        d = depth[v - 2 : v + 3, u - 2 : u + 3]
        if np.any(np.abs(d - z[i]) < 0.03 * z[i]) and not np.any((d > 0) & (d < 0.9 * z[i])):
            keep.append(i)
    return pts[keep], px[keep]


def _spread(px: np.ndarray, n: int) -> list[int]:
    """n indices of points far apart (greedy farthest point), as a person spreads clicks over the photo."""
    chosen = [int(np.argmin(px[:, 0] + px[:, 1]))]
    while len(chosen) < min(n, len(px)):
        d = np.min(np.linalg.norm(px[:, None] - px[chosen][None], axis=2), axis=1)
        chosen.append(int(np.argmax(d)))
    return chosen


def test_answer_anchor_request_by_clicking_model_and_photo(page, site) -> None:
    geometry = ModelGeometry(site.model)
    queue = page.evaluate("wb.queue")
    assert queue, "the register node left no anchor request"
    # The person picks the request whose photo shows most of the building (decided here from the truth).
    best = max(queue, key=lambda q: len(_visible_corners(site, site.rel_of[q["photo_id"]], geometry)[0]))
    pid = best["photo_id"]
    rel = site.rel_of[pid]
    photo = site.photos[rel]
    page.click(f"#queue li[data-photo='{pid}']")
    page.wait_for_function("wb.anchor && wb.anchor.state === 'picking'")
    # Orbit the model view towards the photo's side of the building, as a person would.
    cams = truth.load_cameras(site.site_dir)
    _, wfc_true = truth.true_camera(site.site_dir, rel, cams)
    centre = (geometry.bbox_min_m + geometry.bbox_max_m) / 2
    want_yaw = float(np.arctan2(*(wfc_true[:3, 3] - centre)[[1, 0]]))
    yaw = page.evaluate("wb.anchor.view.yaw")
    dx = ((yaw - want_yaw + np.pi) % (2 * np.pi) - np.pi) / 0.008
    box = page.locator("#modelview").bounding_box()
    x0, y0 = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x0, y0)
    page.mouse.down()
    for k in range(1, 11):
        page.mouse.move(x0 + dx * k / 10, y0)
    page.mouse.up()
    cam_view = page.evaluate("wb.anchor.view.camera()")
    view = cam.PinholeCamera(
        msgspec.convert(cam_view["intrinsics"], Intrinsics), np.asarray(cam_view["world_from_camera"]).reshape(4, 4)
    )
    pts, px = _visible_corners(site, rel, geometry)
    vw, vh = view.intrinsics.width_px, view.intrinsics.height_px
    # Corners also clickable in the model view: the page's own pick (snapped) returns that corner.
    clickable = []
    with httpx.Client(base_url=site.url) as http:
        mpx, mz = view.project(pts)
        for i in range(len(pts)):
            if not (mz[i] > 0 and 5 < mpx[i, 0] < vw - 5 and 5 < mpx[i, 1] < vh - 5):
                continue
            r = http.post(
                "/api/pick",
                json={**cam_view, "u": mpx[i, 0], "v": mpx[i, 1], "snap_px": 10, "at_ns": photo.capture_time_ns},
            ).json()
            if r["global_id"] and np.linalg.norm(np.subtract(r["point_in_world_m"], pts[i])) < 1e-3:
                clickable.append(i)
    assert len(clickable) >= 9, f"only {len(clickable)} corners clickable in both views"
    order = [clickable[j] for j in _spread(px[clickable], 9)]
    rng = np.random.default_rng(7)

    def add_pair(i: int, offset_px: float = 0.0) -> None:
        _click_px(page, "#modelview", *view.project(pts[i : i + 1])[0][0], vw, vh)
        page.wait_for_function("wb.anchor.pendingWorld !== null")
        u, v = px[i] + rng.normal(0, 0.7, 2) + [offset_px, 0.0]
        n = page.evaluate("wb.anchor.pairs.length")
        _click_px(page, "#adraw", u, v, photo.width_px, photo.height_px)
        page.wait_for_function(f"wb.anchor.pairs.length === {n + 1}")

    for k, i in enumerate(order[:5]):
        add_pair(i)
        if k >= 3:  # from 4 pairs on: solved live, a residual per click, the model drawn over the photo
            page.wait_for_function(f"wb.anchor.solution && wb.anchor.solution.residuals_px.length === {k + 1}")
            assert page.locator("#aover").get_attribute("data-drawn") == "1"
    # (5 clicks: the focal is not solved yet; the phone's field of view is wider than the 50 degree default)
    assert max(page.evaluate("wb.anchor.solution.residuals_px")) < 0.03 * photo.width_px
    # A mis-click (35 px off) on the 6th pair is flagged; the person removes it and goes on.
    add_pair(order[5], offset_px=35.0)
    page.wait_for_function("wb.anchor.solution && wb.anchor.solution.residuals_px.length === 6")
    flags = page.evaluate("wb.anchor.solution.misclick")
    assert flags == [False] * 5 + [True], flags
    assert page.locator("#pairs tr.misclick").count() == 1
    page.locator("#pairs tr.misclick button.remove-pair").click()
    page.wait_for_function("wb.anchor.pairs.length === 5")
    for i in order[6:]:
        add_pair(i)
    page.wait_for_function("wb.anchor.solution && wb.anchor.solution.residuals_px.length === 8")
    assert not any(page.evaluate("wb.anchor.solution.misclick"))
    page.screenshot(path=str(DOCS / "workbench_anchor.png"))
    page.click("#anchor-submit")
    # The register node solves the published clicks; the page hears the registration (server-sent events).
    page.wait_for_function(f"wb.byId['{pid}'] && wb.byId['{pid}'].status === 'anchor'", timeout=60_000)
    page.wait_for_function("wb.anchor.state === 'registered'")
    assert "registered (anchor" in page.inner_text("#solve-info")
    reg = [m for _, m in site.registrations.items if isinstance(m, Registration) and m.photo_id == pid][-1]
    centre_err = np.linalg.norm(np.asarray(reg.world_from_camera).reshape(4, 4)[:3, 3] - wfc_true[:3, 3])
    dist = np.linalg.norm(wfc_true[:3, 3] - centre)
    assert reg.status == "anchor" and centre_err < 0.03 * dist, (centre_err, dist)


# ------------------------------------------------------------------------------------------- select, annotate


def _element_pixels(site, rel: str) -> tuple[np.ndarray, np.ndarray]:
    """Truth element index image and the occluder mask of a photo."""
    ids = truth.load_ids(site.site_dir, rel).astype(np.int64)
    occ = truth.load_mask(site.site_dir, rel, "static") | truth.load_mask(site.site_dir, rel, "dynamic")
    return ids, occ


def _polygon_mask(polys, shape) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    for p in polys:
        cv2.fillPoly(m, [np.round(np.asarray(p)).astype(np.int32)], 1)
    return m.astype(bool)


def test_select_annotate_and_find_it_on_another_camera_and_date(page, site) -> None:
    a_rel = "cam-north/20260316T1126.jpg"
    b_rel = "cam-south/20260313T1258.jpg"
    index = {v: int(k) for k, v in truth.element_index(site.site_dir).items() if v}
    ids_a, occ_a = _element_pixels(site, a_rel)
    ids_b, occ_b = _element_pixels(site, b_rel)

    # The element a person would click in both photos: the one whose visible part is widest in both (the largest
    # distance from its outline), so that a click in its middle hits it whatever the registration's last pixel.
    def depth(ids, occ, i):
        m = ((ids == i) & ~occ).astype(np.uint8)
        return float(cv2.distanceTransform(m, cv2.DIST_L2, 5).max()) if m.any() else 0.0

    gid = max(index, key=lambda g: min(depth(ids_a, occ_a, index[g]), depth(ids_b, occ_b, index[g])))
    mask_a = ((ids_a == index[gid]) & ~occ_a).astype(np.uint8)
    v, u = np.unravel_index(np.argmax(cv2.distanceTransform(mask_a, cv2.DIST_L2, 5)), mask_a.shape)
    a, b = site.photos[a_rel], site.photos[b_rel]
    page.click("#cameras li[data-group='cam-north']")
    page.click(f"#timeline figure[data-photo='{a.photo_id}']")
    page.wait_for_function(f"wb.current === '{a.photo_id}'")
    _click_px(page, "#draw", float(u), float(v), a.width_px, a.height_px)
    page.wait_for_function("wb.selection.element_ids.length === 1")
    assert page.evaluate("wb.selection.element_ids") == [gid]
    assert page.locator(f"#selection li[data-element='{gid}']").is_visible()
    page.select_option("#ann-status", "behind")
    page.fill("#ann-text", "check this element on site")
    page.click("#ann-save")
    page.wait_for_function("wb.annotations.some(a => a.text === 'check this element on site')")
    # Another camera, another day: the annotation is there, drawn over the element's visible part.
    page.click("#cameras li[data-group='cam-south']")
    page.click(f"#timeline figure[data-photo='{b.photo_id}']")
    page.wait_for_function(f"wb.annotationsFor === '{b.photo_id}' && wb.annotations.length > 0")
    ann = page.evaluate("wb.annotations.find(a => a.text === 'check this element on site')")
    assert ann["status"] == "behind" and ann["element_ids"] == [gid] and ann["photo_id"] == a.photo_id
    assert page.locator("#draw polygon.annotation").count() >= 1
    drawn = _polygon_mask(ann["polygons"], ids_b.shape)
    true_b = ids_b == index[gid]
    recall = np.sum(drawn & true_b & ~occ_b) / np.sum(true_b & ~occ_b)
    precision = np.sum(drawn & (true_b | occ_b)) / max(1, np.sum(drawn))
    assert recall > 0.85 and precision > 0.85, (recall, precision)
    page.screenshot(path=str(DOCS / "workbench_annotation.png"))
    # Edit it: a new revision with the history kept.
    page.locator(f"#annotations li[data-annotation='{ann['annotation_id']}'] button.ann-edit").click()
    page.fill("#ann-text", "checked: slab formwork late")
    page.click("#ann-save")
    page.wait_for_function("wb.annotations.some(a => a.text === 'checked: slab formwork late' && a.revision === 1)")
    with httpx.Client(base_url=site.url) as http:
        hist = http.get(f"/api/annotations/{ann['annotation_id']}/history").json()
    assert [h["revision"] for h in hist] == [0, 1]


# ------------------------------------------------------------------------------------------------- progress


def _wrong_reading(site, states: dict, index: dict[str, int]):
    """A fixed camera's photo and an element the progress node read wrong there, as a person looking at the photo
    would see, and that the fused estimate still gets wrong at that time: read ``not_built`` while it stands (at
    least 400 truly visible pixels) with a fused finish not before the photo, or read ``built`` while it is absent
    (at least 300 pixels of its model region read) with a fused finish before the photo. The one a person sees
    best: (photo path, element id, capture time ns, what the person says); None if there is none."""
    wb = site.workbench.workbench
    best = None
    for pid, ev in wb.state.evidence.items():
        rel = site.rel_of[pid]
        if ev.camera_id is None:
            continue
        ids, occ = _element_pixels(site, rel)
        built = set(states["photos"][rel])
        for e in ev.elements:
            fused = wb.state.progress.get(e.global_id)
            finish = None if fused is None else fused.detected_finish_ns
            if e.state == "not_built" and e.global_id in built and (finish is None or finish > ev.capture_time_ns):
                seen, verdict = int(np.sum((ids == index.get(e.global_id, -1)) & ~occ)) - 400, "built"
            elif (
                e.state == "built" and e.global_id not in built and finish is not None and finish <= ev.capture_time_ns
            ):
                seen, verdict = e.visible_px - 300, "not_built"
            else:
                continue
            if seen > 0 and (best is None or seen > best[0]):
                best = (seen, rel, e.global_id, ev.capture_time_ns, verdict)
    return None if best is None else best[1:]


def test_progress_reading_confirmed_and_corrected_in_the_page(page, site) -> None:
    """The progress node's reading of a photo is listed in the page; a person highlights an element, confirms a
    right reading and corrects a wrong one (an element they see standing read as not built, or one they see absent
    read as built). Each review is a status annotation on the bus; the progress node takes the correction, and the
    element's fused finish moves to the right side of the photo's time."""
    states = truth.element_states(site.site_dir)
    index = {v: int(k) for k, v in truth.element_index(site.site_dir).items() if v}
    wrong = _wrong_reading(site, states, index)
    assert wrong is not None, "no wrong reading on this site to correct (the test needs one)"
    rel, gid, t_ns, verdict = wrong
    p = site.photos[rel]
    ev = site.workbench.workbench.state.evidence[p.photo_id]
    ids, occ = _element_pixels(site, rel)
    # A right reading in the same photo to confirm: the built element read built with the most visible pixels.
    right = max(
        (e for e in ev.elements if e.state == "built" and e.global_id in set(states["photos"][rel])),
        key=lambda e: int(np.sum((ids == index.get(e.global_id, -1)) & ~occ)),
    ).global_id
    heard = site.bus.collect(keys.pattern(keys.ANNOTATION, site=SITE))
    # The queue of readings off schedule: its first entry opens that photo with the element outlined.
    with httpx.Client(base_url=site.url) as http:
        queue = http.get("/api/progress/review-queue?limit=30").json()
    assert queue, "readings off schedule expected on this site (late and early elements)"
    page.wait_for_function(f"document.querySelectorAll('#review-queue li').length === {len(queue)}")
    page.locator("#review-queue li").first.click()
    page.wait_for_function(f"wb.current === '{queue[0]['photo_id']}' && wb.highlighted === '{queue[0]['global_id']}'")
    assert page.locator("#draw polygon.detection").count() >= 1
    page.click(f"#cameras li[data-group='{p.camera_id}']")
    page.click(f"#timeline figure[data-photo='{p.photo_id}']")
    page.wait_for_function(f"wb.detections && wb.detections.photo_id === '{p.photo_id}'")
    assert "built" in page.inner_text("#detect-summary")
    row = page.locator(f"#detections li[data-element='{right}']")
    assert row.get_attribute("data-state") == "built"
    row.locator("a.det-name").click()
    page.wait_for_function(f"wb.highlighted === '{right}' && wb.highlight.length > 0")
    drawn = _polygon_mask(page.evaluate("wb.highlight"), ids.shape)
    true_px = (ids == index[right]) & ~occ
    assert np.sum(drawn & true_px) / np.sum(true_px) > 0.8, "the highlight should cover the element's visible part"
    row.locator("button.review-confirm").click()
    page.wait_for_function(
        f"wb.annotations.some(a => a.element_ids[0] === '{right}' && a.status === 'built' && a.author === 'workbench')"
    )
    page.wait_for_function(f"document.querySelector(\"#detections li[data-element='{right}'] .reviewed\") !== null")
    # The wrong reading: the person sees what stands there and says so.
    bad = page.locator(f"#detections li[data-element='{gid}']")
    read = "not_built" if verdict == "built" else "built"
    assert bad.get_attribute("data-state") == read
    bad.locator(f"button.review-{verdict}").click()
    page.wait_for_function(
        f"wb.annotations.some(a => a.element_ids[0] === '{gid}' && a.status === '{verdict}' && "
        f"a.text.startsWith('corrects the detection {read.replace('_', ' ')}'))"
    )
    sent = [m for _k, m in heard.items if gid in m.element_ids]
    assert sent and sent[-1].status == verdict and sent[-1].photo_id == p.photo_id
    # The progress node took it: the element's fused finish is now on the right side of the photo, and the page
    # shows it.
    right_side = f"f !== null && f <= {t_ns}" if verdict == "built" else f"(f === null || f > {t_ns})"
    page.wait_for_function(
        f"(() => {{ const e = wb.detections.elements.find(x => x.global_id === '{gid}'); if (!e || !e.fused || "
        f"!e.review) return false; const f = e.fused.detected_finish_ns; return {right_side}; }})()",
        timeout=60_000,
    )
    finish = site.workbench.workbench.state.progress[gid].detected_finish_ns
    assert (finish is not None and finish <= t_ns) if verdict == "built" else (finish is None or finish > t_ns)
    page.locator("#review-queue").scroll_into_view_if_needed()
    page.screenshot(path=str(DOCS / "workbench_progress.png"))


# ------------------------------------------------------------------------------------------------- time, peek


def _drag_slider(page, target_s: float) -> None:
    sl = page.locator("#time")
    box = sl.bounding_box()
    lo, hi, val = page.eval_on_selector("#time", "e => [Number(e.min), Number(e.max), Number(e.value)]")
    pad = 8.0
    x_of = lambda s: box["x"] + pad + (s - lo) / (hi - lo) * (box["width"] - 2 * pad)  # noqa: E731
    y = box["y"] + box["height"] / 2
    page.mouse.move(x_of(val), y)
    page.mouse.down()
    for k in range(1, 9):
        page.mouse.move(x_of(val + (target_s - val) * k / 8), y)
    page.mouse.up()


def test_time_slider_navigates_and_peeks_backward(page, site) -> None:
    north = sorted((r for r in site.photos if r.startswith("cam-north/")), key=lambda r: site.photos[r].capture_time_ns)
    first, last = site.photos[north[0]], site.photos[north[-1]]
    page.click("#cameras li[data-group='cam-north']")
    page.wait_for_function(f"wb.current === '{last.photo_id}'")
    # The slider moves through time: dragged to the first day it shows that day's frame of this camera.
    _drag_slider(page, first.capture_time_ns / 1e9 + 3600)
    page.wait_for_function(f"wb.current === '{first.photo_id}'")
    page.click(f"#timeline figure[data-photo='{last.photo_id}']")
    page.wait_for_function(f"wb.current === '{last.photo_id}'")
    # A region over the building, then peek back to the first day inside it.
    page.click("#tools [data-tool='rect']")
    box = page.locator("#draw").bounding_box()
    page.mouse.move(box["x"] + 0.3 * box["width"], box["y"] + 0.25 * box["height"])
    page.mouse.down()
    page.mouse.move(box["x"] + 0.5 * box["width"], box["y"] + 0.5 * box["height"])
    page.mouse.move(box["x"] + 0.7 * box["width"], box["y"] + 0.8 * box["height"])
    page.mouse.up()
    page.wait_for_function("wb.region && wb.region.length === 4")
    page.check("#peek-toggle")
    _drag_slider(page, first.capture_time_ns / 1e9 + 3600)
    page.wait_for_function("wb.lastPeek && wb.lastPeek.direction === 'backward'")
    assert page.evaluate("wb.current") == last.photo_id  # the photo stays; only the region looks back
    assert page.evaluate("wb.lastPeek.source_photo_id") == first.photo_id
    page.wait_for_function(
        "document.querySelector('#peekimg').complete && document.querySelector('#peekimg').naturalWidth > 0"
    )
    page.screenshot(path=str(DOCS / "workbench_peek.png"))
    # What the page shows is the first day's pixels inside the region (fixed camera: homography close to identity).
    region = page.evaluate("wb.region")
    with httpx.Client(base_url=site.url) as http:
        r = http.post(
            f"/api/photos/{last.photo_id}/peek", json={"at_ns": first.capture_time_ns + 3600e9, "polygon": region}
        )
    assert r.status_code == 200
    rgba = cv2.cvtColor(cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)
    inside = rgba[..., 3] == 255
    assert inside.sum() > 0.9 * _polygon_mask([region], inside.shape).sum()

    def blurred(rgb: np.ndarray) -> np.ndarray:  # sub-pixel shifts of the warp do not count
        return cv2.GaussianBlur(rgb.astype(np.float32), (0, 0), 2.0)

    def photo_rgb(p) -> np.ndarray:
        return cv2.cvtColor(cv2.imdecode(np.frombuffer(p.data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)

    inner = cv2.erode(inside.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    peeked = blurred(rgba[..., :3])
    err_first = np.abs(peeked - blurred(photo_rgb(first)))[inner].mean()
    err_last = np.abs(peeked - blurred(photo_rgb(last)))[inner].mean()
    assert err_first < 8 and err_first < 0.5 * err_last, (err_first, err_last)
    # Forward from the first day: the model's later state drawn in the region.
    page.click(f"#timeline figure[data-photo='{first.photo_id}']")
    page.wait_for_function(f"wb.current === '{first.photo_id}'")
    _drag_slider(page, last.capture_time_ns / 1e9)
    page.wait_for_function("wb.lastPeek && wb.lastPeek.direction === 'forward'")
    page.click("#cameras li[data-group='cam-north']")  # back to the site view's default for the overview shot
    page.uncheck("#peek-toggle")
    page.click("#overlay-modes button[data-mode='progress']")
    page.wait_for_function("wb.timings.overlayShown === 'progress'")
    page.screenshot(path=str(DOCS / "workbench_site.png"))
