"""Partitioned register workers in real processes (``constructaide run`` with ``[workers] register = 2``) on the
small synthetic site (fixed cameras): every photo is handled by exactly one worker; every frame two workers register
one worker registers too, as accurately; no pose either run publishes as good is wrong; a frame left failed (a
knocked camera's, which a worker cannot register reliably) has asked for an anchor."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from constructaide import camera as cam
from constructaide.partition import Partition
from constructaide.runtime import BusConfig, open_bus
from constructaide.synth.truth import load_cameras
from schemas import keys
from schemas.messages import AnchorClicks, Photo

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

SITE = "partsite"
ROOT = Path(__file__).resolve().parents[1]


def site_photos(site_dir: Path, site: str = SITE) -> tuple[list[Photo], list[AnchorClicks], dict[str, str]]:
    """The site's photos in capture order, the up-front anchor clicks of its anchors.json, and each photo id's
    path relative to photos/."""
    from constructaide import sitedir

    by_rel = sitedir.site_photos(site_dir, site)
    anchors = sitedir.anchor_messages(site, site_dir, by_rel)
    rel_of = {p.photo_id: rel for rel, p in by_rel.items()}
    return sorted(by_rel.values(), key=lambda p: (p.capture_time_ns, p.photo_id)), anchors, rel_of


def wait_tokens(bus: object, keyexpr: str, count: int, timeout: float) -> None:
    """Block until ``count`` distinct liveliness tokens under ``keyexpr`` are alive."""
    cond = threading.Condition()
    alive: set[str] = set()

    def on_token(key: str, is_alive: bool) -> None:
        with cond:
            (alive.add if is_alive else alive.discard)(key)
            cond.notify_all()

    watcher = bus.watch_tokens(keyexpr, on_token)  # type: ignore[attr-defined]
    try:
        with cond:
            assert cond.wait_for(lambda: len(alive) >= count, timeout), f"live: {sorted(alive)}"
    finally:
        watcher.close()


def run_register(
    tmp: Path, hub_port: int, workers: int, photos: list[Photo], anchors: list[AnchorClicks]
) -> tuple[list, set[str]]:
    cameras = sorted({p.camera_id for p in photos if p.camera_id})
    cfg = tmp / f"site-{workers}.toml"
    cfg.write_text(
        f'[site]\nname = "{SITE}"\ncameras = {json.dumps(cameras)}\n\n'
        "[nodes.register]\nuse_bim_depth = false\n\n"
        f"[workers]\nregister = {workers}\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYOPENGL_PLATFORM": "egl"}
    with open_bus(BusConfig(hub_port=hub_port)) as bus:
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=SITE))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=SITE))
        run = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "constructaide.app.cli",
                "run",
                str(cfg),
                "--log-dir",
                str(tmp / f"logs{workers}"),
                "--state-dir",  # each run starts empty (else the second takes the first's map over)
                str(tmp / f"state{workers}"),
                "--hub-port",
                str(hub_port),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            live_ke = keys.pattern(keys.LIVELINESS, site=SITE, node="register")
            wait_tokens(bus, live_ke, workers, timeout=90)
            print(f"{workers} worker(s): the test's bus at publishing: {bus.topology()}")
            for a in anchors:
                bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=a.photo_id), a)
            for p in photos:
                bus.publish(keys.key(keys.PHOTO, site=SITE, camera=p.camera_id), p)
            ids = {p.photo_id for p in photos}
            # every photo's first registration (counting messages would stop early: a photo may fail, then register)
            deadline = time.monotonic() + 240
            while not ids <= {r.photo_id for _k, r in regs.items}:
                try:
                    regs.wait(len(regs.items) + 1, timeout=max(deadline - time.monotonic(), 0.1))
                except TimeoutError:
                    missing = sorted(
                        f"{p.camera_id}@{p.capture_time_ns}"
                        for p in photos
                        if p.photo_id not in {r.photo_id for _k, r in regs.items}
                    )
                    raise TimeoutError(f"{workers} worker(s): no registration of {missing}") from None
        finally:
            run.send_signal(signal.SIGINT)
            run.wait(120)
        assert run.returncode == 0
        return regs.items, {m.photo_id for _k, m in needs.items}


def test_two_register_workers_register_each_photo_once_as_one_worker_does(
    small_site: Path, tmp_path: Path, hub_port: int
) -> None:
    photos, anchors, rel_of = site_photos(small_site)
    fixed = [p for p in photos if p.camera_id]  # phones register against the map of their worker's cameras only
    fixed_anchors = [a for a in anchors if any(p.photo_id == a.photo_id for p in fixed)]
    cameras = sorted({p.camera_id for p in fixed if p.camera_id})
    shares = [Partition.parse(f"{i}/2", cameras).my_cameras() for i in range(2)]
    assert all(shares), f"both workers must own a camera for the test to mean anything: {shares}"
    one, asked1 = run_register(tmp_path, hub_port, 1, fixed, fixed_anchors)
    two, asked2 = run_register(tmp_path, hub_port, 2, fixed, fixed_anchors)
    # each photo handled by exactly one worker: the workers' own counts (logged when they stop) add up
    handled = []
    for log in sorted((tmp_path / "logs2").glob("register-*of2.log")):
        m = re.search(r"worker \d/2: handled .*\bon_photo=(\d+)", log.read_text())
        assert m, f"no handled count in {log.name}"
        handled.append(int(m.group(1)))
    assert len(handled) == 2 and sum(handled) == len(fixed) and min(handled) > 0, handled
    # same results: every photo's last registration (a photo may fail first and register on a retry)
    last1 = {r.photo_id: r for _k, r in one}
    last2 = {r.photo_id: r for _k, r in two}
    assert set(last1) == set(last2) == {p.photo_id for p in fixed}
    registered1 = {p for p, r in last1.items() if r.status != "failed"}
    registered2 = {p for p, r in last2.items() if r.status != "failed"}
    assert len(registered1) >= len(fixed) // 2, f"only {len(registered1)} of {len(fixed)} registered"
    # Frames taken after their camera was knocked (scoring from the site's truth: its pose differs from the
    # camera's first frame's): without BIM depth (this test) nothing registers them reliably; they ask for clicks,
    # and no pose of theirs may be published off (a relative pose to another camera's frame once placed them 2.7 deg
    # and 3 m off in CI; a fixed camera's frame is now placed relative to its own camera's frames only).
    truth = load_cameras(small_site)
    first = {}
    for p in fixed:
        first.setdefault(p.camera_id, np.array(truth[rel_of[p.photo_id]]["world_from_camera"]))
    knocked = {
        p.photo_id
        for p in fixed
        if np.linalg.norm(np.array(truth[rel_of[p.photo_id]]["world_from_camera"])[:3, 3] - first[p.camera_id][:3, 3])
        > 0.2
    }
    assert 0 < len(knocked) <= len(fixed) // 4, sorted(rel_of[p] for p in knocked)  # the east camera's last frames
    assert (registered2 - knocked) <= registered1
    # None is lost silently: a photo left failed asked for an anchor, in both runs. What differs with two workers:
    # frames a worker cannot register from its own cameras' map, all of them frames of a camera alone on its worker.
    assert {p for p in last1 if p not in registered1} <= asked1, "a frame failed without asking for an anchor"
    assert {p for p in last2 if p not in registered2} <= asked2, "a frame failed without asking for an anchor"
    missing = registered1 - registered2
    camera_of = {p.photo_id: p.camera_id for p in fixed}
    alone = [share[0] for share in shares if share is not None and len(share) == 1]
    assert all(camera_of[p] in alone for p in missing), {camera_of[p] for p in missing}
    # Poses, scored against the site's truth (tests only): every pose either run published as good, not only each
    # photo's last one (a consumer uses whatever arrives), within the band, and the same with two workers as with one.

    def errors(regs: list) -> dict[str, list[tuple[float, float]]]:
        out: dict[str, list[tuple[float, float]]] = {}
        for _k, r in regs:
            if r.status == "failed":
                continue
            t = np.array(truth[rel_of[r.photo_id]]["world_from_camera"])
            est = cam.pose_from_tuple(r.world_from_camera)
            err = (cam.rotation_angle_deg(est[:3, :3], t[:3, :3]), float(np.linalg.norm(est[:3, 3] - t[:3, 3])))
            out.setdefault(r.photo_id, []).append(err)
        return out

    errs1, errs2 = errors(one), errors(two)
    methods = [{r.photo_id: r.method or "failed" for _k, r in regs} for regs in (one, two)]
    report = {
        rel_of[p]: [
            f"{round(max(e[0] for e in errs[p]), 2)} {how.get(p)}" if p in errs else "failed"
            for errs, how in zip((errs1, errs2), methods, strict=True)
        ]
        for p in last1
    }
    print("worst published rotation error (deg) and last method per photo, 1 vs 2 workers:", json.dumps(report))
    bad = [
        (rel_of[p], n + 1, round(rot, 2), round(pos, 2))
        for n, errs in enumerate((errs1, errs2))
        for p, es in errs.items()
        for rot, pos in es
        if not (rot < 1.5 and pos < 1.5)
    ]
    assert not bad, f"wrong poses published as good (photo, workers, deg, m): {bad}"
    # The same computation gives the same pose: photos both runs registered by the same method agree within 0.25 deg.
    # Arrival order between the workers can send a frame down another path (the full path's homography instead of
    # the fast path, 0.48 vs 0.92 deg in one clean-clone run); such a pose is held to the band above only.
    same = {p for p in (registered1 & registered2) - knocked if methods[0].get(p) == methods[1].get(p)}
    assert len(same) >= 0.8 * len((registered1 & registered2) - knocked), report
    for p in same:
        assert abs(errs2[p][-1][0] - errs1[p][-1][0]) < 0.25, (rel_of[p], report[rel_of[p]], errs1[p], errs2[p])
