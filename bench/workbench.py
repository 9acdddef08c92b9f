"""Workbench benchmark: page load, pick, live anchor solve after a click, overlay switch (medians).

The synthetic site (default size: 110 photos; `--size small`: 23) runs through the real register and render
nodes in-process (LocalBus, the site's anchors.json clicks published as a user's), with the workbench node serving
it on loopback; the page runs in headless Debian chromium driven by Playwright.

* page load: a fresh browser context opens the page until the site view is ready (model, photo list, anchor
  queue, the current camera's timeline) and the first photo has loaded;
* pick: ``GET /api/pick`` round trips (HTTP client) on pixels of registered photos; baseline in the same run:
  the element-ID render (960 px) a render-based pick needs for a photo it has not drawn yet;
* live solve after a click: in the page, the work a photo click that completes a pair triggers (``POST .../solve``
  with all pairs, the table, the markers, the model redrawn over the photo), with 6, 9 and 12 pairs simulated from
  the site's truth (visible model corners and their pixels);
* overlay switch: in the page, from a click on an overlay mode button to the overlay image decoded and shown,
  alternating modes and photos; baseline: the same for the photo itself (a JPEG of the same size).

    python bench/workbench.py [--size small] [--runs 7] [--no-write]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from workbench_site import running_site  # noqa: E402

import constructaide  # noqa: E402,F401  (EGL platform)
from bench._report import median, table, write_section  # noqa: E402
from constructaide import camera as cam  # noqa: E402
from constructaide.synth import ensure_site, truth  # noqa: E402
from nodes.workbench.geometry import ModelGeometry  # noqa: E402

ARGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-first-run"]
TARGETS_MS = {"page load": 1000, "pick": 50, "live solve": 100, "overlay switch": 200}


def _clicks(site, rel: str, geometry: ModelGeometry, n: int, rng: np.random.Generator) -> list[dict]:
    """n model corners visible in a photo (truth camera and depth) and their pixels with 0.7 px noise."""
    intr, wfc = truth.true_camera(site.site_dir, rel, truth.load_cameras(site.site_dir))
    depth = truth.load_depth(site.site_dir, rel)
    pts = geometry.corners[geometry.standing(site.photos[rel].capture_time_ns)[geometry.corner_owner]]
    px, z = cam.PinholeCamera(intr, wfc).project(pts)
    good = []
    for i in np.nonzero(np.isfinite(px).all(1) & (z > 0))[0]:
        u, v = np.round(px[i]).astype(int)
        if 10 < u < intr.width_px - 10 and 10 < v < intr.height_px - 10 and abs(depth[v, u] - z[i]) < 0.03 * z[i]:
            good.append(i)
    pick = rng.choice(good, size=min(n, len(good)), replace=False)
    return [{"pixel": (px[i] + rng.normal(0, 0.7, 2)).tolist(), "world": pts[i].tolist()} for i in pick]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="default", choices=["small", "default"])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    chromium = shutil.which("chromium")
    if chromium is None:
        print("needs Debian's chromium (apt-get install chromium)", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    site_dir = ensure_site(args.size, 0, ROOT / ".cache" / "synth")
    t0 = time.perf_counter()
    with (
        running_site(site_dir, timeout=3600) as site,
        sync_playwright() as pw,
        httpx.Client(base_url=site.url, timeout=60) as http,
    ):
        setup_s = time.perf_counter() - t0
        photos = http.get("/api/photos").json()
        registered = [p for p in photos if p["status"] in ("anchor", "auto")]
        print(f"{len(photos)} photos, {len(registered)} registered, pipeline {setup_s:.0f} s", file=sys.stderr)
        browser = pw.chromium.launch(executable_path=chromium, args=ARGS)
        rows: list[list[object]] = []

        # -- page load (fresh context: nothing cached)
        loads = []
        for _ in range(args.runs):
            ctx = browser.new_context(viewport={"width": 1500, "height": 980})
            page = ctx.new_page()
            t = time.perf_counter()
            page.goto(site.url)
            page.wait_for_function("document.body.dataset.ready === '1' && document.querySelector('#photo').complete")
            loads.append((time.perf_counter() - t) * 1000)
            ctx.close()
        rows.append(["page load", len(photos), median(loads), "-", "-", TARGETS_MS["page load"]])

        # -- pick: HTTP round trips on registered photos; baseline: a cold element-ID render of a photo
        rng = np.random.default_rng(0)
        picks, hits = [], 0
        for p in registered[:: max(1, len(registered) // 20)]:
            for _ in range(5):
                u, v = rng.uniform(0, p["width_px"] - 1), rng.uniform(0, p["height_px"] - 1)
                t = time.perf_counter()
                r = http.get("/api/pick", params={"photo_id": p["photo_id"], "u": u, "v": v}).json()
                picks.append((time.perf_counter() - t) * 1000)
                hits += r["global_id"] is not None
        wb = site.workbench.workbench
        renders = []
        for p in registered[: args.runs]:
            wb._renders.clear()
            t = time.perf_counter()
            wb._render(p["photo_id"])
            renders.append((time.perf_counter() - t) * 1000)
        rows.append(
            [
                "pick",
                f"{len(picks)} picks ({hits} on an element)",
                median(picks),
                "ID render (cold)",
                median(renders),
                TARGETS_MS["pick"],
            ]
        )

        # -- live solve after a click, in the page
        geometry = ModelGeometry(site.model)
        page = browser.new_page(viewport={"width": 1500, "height": 980})
        page.goto(site.url)
        page.wait_for_function("window.wb && window.wb.ready")
        target = next(p for p in registered if p["camera_id"])
        rel = site.rel_of[target["photo_id"]]
        page.click(f"#cameras li[data-group='{target['camera_id']}']")
        page.click(f"#timeline figure[data-photo='{target['photo_id']}']")
        page.click("#reanchor")
        page.wait_for_function("wb.anchor && wb.anchor.state === 'picking'")
        for n in (6, 9, 12):
            times = []
            for _ in range(args.runs):
                pairs = _clicks(site, rel, geometry, n, rng)
                times.append(
                    page.evaluate(
                        "async (pairs) => { wb.anchor.pairs = pairs.map(q => ({...q, snapped: 'vertex'}));"
                        " const t = performance.now(); await wb.anchor.update(); return performance.now() - t; }",
                        pairs,
                    )
                )
            assert page.evaluate("wb.anchor.solution !== null"), "the page did not solve"
            rows.append(["live solve", f"{n} pairs", median(times), "-", "-", TARGETS_MS["live solve"]])
        page.close()

        # -- overlay switch, in the page; baseline: the photo's own image
        page = browser.new_page(viewport={"width": 1500, "height": 980})
        page.goto(site.url)
        page.wait_for_function("window.wb && window.wb.ready")
        with_modes = [p for p in registered if len(p["overlays"]) >= 2 and p["camera_id"]]
        switches, photo_loads = [], []
        for k in range(args.runs):
            p = with_modes[(k * 7) % len(with_modes)]
            page.click(f"#cameras li[data-group='{p['camera_id']}']")
            page.click(f"#timeline figure[data-photo='{p['photo_id']}']")
            t = time.perf_counter()
            page.wait_for_function(f"wb.current === '{p['photo_id']}' && document.querySelector('#photo').complete")
            photo_loads.append((time.perf_counter() - t) * 1000)
            for mode in p["overlays"][:3]:
                t = time.perf_counter()
                page.click(f"#overlay-modes button[data-mode='{mode}']")
                page.wait_for_function(f"wb.timings.overlayShown === '{mode}'")
                switches.append((time.perf_counter() - t) * 1000)
                page.click("#overlay-modes button[data-mode='none']")
        rows.append(
            [
                "overlay switch",
                f"{len(switches)} switches",
                median(switches),
                "photo switch",
                median(photo_loads),
                TARGETS_MS["overlay switch"],
            ]
        )
        browser.close()

    headers = ["what", "n", "median ms", "baseline", "baseline median ms", "target ms"]
    print(table(headers, rows))
    body = (
        f"Synthetic `{args.size}` site (seed 0): {len(photos)} photos, {len(registered)} registered by the register "
        f"node in-process (anchors.json clicks), overlays by the render node ({setup_s:.0f} s of setup); the "
        "workbench node serves it on loopback, the page runs in headless Debian chromium (software WebGL, "
        f"SwiftShader) driven by Playwright. Median of {args.runs} runs unless n says otherwise. Page load: fresh "
        "browser context until the site view is ready and the first photo shown. Pick: `GET /api/pick` round trip "
        "(server ray cast; baseline: the cold 960 px element-ID render a render-based pick would need first). Live "
        "solve: the page's work after the click that completes a pair (`POST /solve` with every pair, table, "
        "markers, model drawn over the photo), pairs simulated from the site's truth (visible corners, 0.7 px "
        "noise). Overlay switch: from the click on a mode button to the overlay PNG decoded and shown (Playwright "
        "round trips included); baseline: switching to another photo until its JPEG is shown. The machine is shared "
        "with other jobs; figures vary with its load.\n\n" + table(headers, rows)
    )
    if not args.no_write:
        write_section("workbench", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
