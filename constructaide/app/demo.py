"""``constructaide demo``: the main job on embedded defaults.

Generates (once, cached) the synthetic construction site, starts every node in its own process on
a loopback zenoh bus, publishes the site's BIM (through the ingest node), the up-front anchor clicks of the
site's ``anchors.json`` (the first usable photo of each fixed camera and phone visit, clicked by the simulated
user of ``constructaide.synth.clicker``; nothing tells the nodes that a camera was knocked) and every photo in
capture order as the cameras would (with ``--answer-anchor-requests`` the same simulated user also answers each
NeedsAnchor request with clicks, as a person at the browser page would), waits until the
nodes have processed them and settled (every registered photo's latest overlay is newer than its latest
combined occlusion mask, and no mask or overlay for a few seconds), stops the nodes cleanly and prints a
summary with the paths of the MCAP recording and the rerun file.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import queue
import sys
import threading
import time
import tomllib
from collections import Counter
from pathlib import Path

from tqdm import tqdm

from constructaide.app.launch import Launcher
from constructaide.errors import UserError
from constructaide.runtime import BusConfig, open_bus
from schemas import codec, keys
from schemas.messages import AnchorClicks, AnchorPoint, NeedsAnchor, OcclusionMask, Overlay, Photo

PROCESSING_NODES = tuple(os.environ.get("CONSTRUCTAIDE_DEMO_NODES", "register,occlude,render,progress").split(","))
SETTLE_QUIET_SECS = 4.0  # no new mask or overlay for this long (and overlays newer than masks): settled
REQUEST_GRACE_SECS = 2.0  # with the simulated user: quiet on NeedsAnchor before registration counts as done
STALL_SECS = 60.0  # no new mask or overlay for this long while overlays are behind their masks: stalled


class _Arrivals:
    """Combined occlusion masks and overlays in one arrival order, to tell when the render node has drawn every
    photo with its latest mask and the occlude node has gone quiet."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._seq = 0
        self._last_secs = time.monotonic()
        self.last_mask: dict[str, int] = {}
        self.last_overlay: dict[str, int] = {}

    def __call__(self, key: str, payload: bytes) -> None:
        msg = codec.decode(payload)
        with self._cond:
            self._seq += 1
            self._last_secs = time.monotonic()
            if isinstance(msg, OcclusionMask) and msg.kind == "combined":
                self.last_mask[msg.photo_id] = self._seq
            elif isinstance(msg, Overlay):
                self.last_overlay[msg.photo_id] = self._seq
            self._cond.notify_all()

    def stale(self, photo_ids: set[str]) -> set[str]:
        """Photos without an overlay drawn after their latest combined mask."""
        with self._cond:
            return {p for p in photo_ids if self.last_overlay.get(p, 0) <= self.last_mask.get(p, 0)}

    def wait_settled(self, photo_ids: set[str], quiet_secs: float, stall_secs: float, deadline: float) -> str:
        """Block until no photo is stale and nothing arrived for ``quiet_secs`` ("settled"), or nothing arrived
        for ``stall_secs`` although photos are stale ("stalled": the pipeline went idle without redrawing them),
        or the deadline passed ("timed out")."""
        with self._cond:
            while True:
                now = time.monotonic()
                quiet = now - self._last_secs
                caught_up = all(self.last_overlay.get(p, 0) > self.last_mask.get(p, 0) for p in photo_ids)
                if caught_up and quiet >= quiet_secs:
                    return "settled"
                if quiet >= stall_secs:
                    return "stalled"
                if now >= deadline:
                    return "timed out"
                wake = quiet_secs - quiet if caught_up else stall_secs - quiet
                self._cond.wait(min(deadline - now, max(0.05, wake)))


def _http_port(requested: int | None) -> int:
    """The workbench's TCP port: ``requested`` when it is free, else one the system picks now (an HTTP server in
    another process; unlike the bus, a port lost to a race in between only makes its start fail loudly)."""
    import socket

    for port in ([requested] if requested else []) + [0]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return int(sock.getsockname()[1])
    raise UserError("no free TCP port for the workbench")


class _SimulatedUser:
    """Answers NeedsAnchor requests on the bus as a person would (:class:`constructaide.synth.clicker.SiteClicker`:
    up to 12 visible element corners, 1.5 px noise, about one gross mis-click in 20; reads the site's truth), once
    per photo, on its own thread (the bus callback only queues); a photo registered meanwhile is not clicked.
    ``requested``, ``answered``, ``few`` (answered with fewer than 6 clickable corners) and ``unanswerable`` (fewer
    than 4) are sets of photo ids; ``mis_clicks`` counts the gross mis-clicks sent."""

    def __init__(self, bus, site: str, site_dir: Path, photos: dict[str, Photo], registrations) -> None:
        from constructaide.synth.clicker import SiteClicker

        self._bus, self._site, self._site_dir = bus, site, site_dir
        self._rel = {p.photo_id: rel for rel, p in photos.items()}
        self._clicker = SiteClicker(site_dir)
        self._regs = registrations
        self._queue: queue.Queue[str | None] = queue.Queue()
        self._lock = threading.Lock()
        self.requested: set[str] = set()
        self.answered: set[str] = set()
        self.unanswerable: set[str] = set()
        self.few: set[str] = set()
        self.mis_clicks = 0
        self._thread = threading.Thread(target=self._run, name="simulated-user", daemon=True)

    def __enter__(self) -> _SimulatedUser:
        self._thread.start()
        self._sub = self._bus.subscribe(keys.pattern(keys.NEEDS_ANCHOR, site=self._site), self._on_request)
        return self

    def __exit__(self, *exc: object) -> None:
        self._sub.close()
        self._queue.put(None)
        self._thread.join(timeout=30)

    def _on_request(self, key: str, payload: bytes) -> None:
        msg = codec.decode(payload)
        if isinstance(msg, NeedsAnchor):
            with self._lock:
                self.requested.add(msg.photo_id)
            self._queue.put(msg.photo_id)

    def _run(self) -> None:
        from constructaide.synth.clicker import TooFewCorners

        while (photo_id := self._queue.get()) is not None:
            rel = self._rel.get(photo_id)
            with self._lock:
                if rel is None or photo_id in self.answered or photo_id in self.unanswerable:
                    continue
            if _latest_status(self._regs.items).get(photo_id, "failed") != "failed":
                continue  # registered meanwhile (a later photo brought enough tracks): nothing to click
            try:
                clicks = self._clicker.clicks(rel)
            except TooFewCorners:
                with self._lock:
                    self.unanswerable.add(photo_id)
                continue
            pts = tuple(
                AnchorPoint(pixel_px=(float(u), float(v)), point_in_world_m=(float(x), float(y), float(z)))
                for (u, v), (x, y, z) in zip(clicks.pixels_px, clicks.points_in_world_m, strict=True)
            )
            with self._lock:
                self.answered.add(photo_id)
                self.mis_clicks += len(clicks.mis_clicked)
                if clicks.few:
                    self.few.add(photo_id)
            msg = AnchorClicks(site=self._site, photo_id=photo_id, image_name=rel, points=pts)
            self._bus.publish(keys.key(keys.ANCHORS, site=self._site, photo=photo_id), msg)

    def settled(self, photo_id: str, latest_status: str) -> bool:
        """Whether a photo whose latest registration has ``latest_status`` needs nothing more from this user:
        registered, never asked for (a failure without a request), or no clicks possible."""
        with self._lock:
            return latest_status != "failed" or photo_id not in self.requested or photo_id in self.unanswerable


def _latest_status(items: list) -> dict[str, str]:
    """photo_id -> status of its latest Registration among collected (key, Registration) items."""
    return {m.photo_id: m.status for _, m in items}


def main(argv: list[str]) -> int:
    from constructaide import sitedir
    from constructaide.app.cli import cache_dir
    from constructaide.synth import ensure_site

    ap = argparse.ArgumentParser(prog="constructaide demo", description=__doc__)
    ap.add_argument("--size", default="default", choices=["small", "default", "large"], help="synthetic site size")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--site", default="demo", help="site id on the bus")
    ap.add_argument("--out", type=Path, default=Path("recordings"), help="folder for .mcap, .rrd and logs")
    ap.add_argument("--max-photos", type=int, default=0, help="push only the first N photos (0: all)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for processing")
    ap.add_argument(
        "--answer-anchor-requests",
        action="store_true",
        help="a simulated user answers every NeedsAnchor request, clicking visible element corners as a person would "
        "(1.5 px noise, about one gross mis-click in 20; simulated from the site's truth)",
    )
    ap.add_argument("--workbench-port", type=int, default=8770, help="port of the browser workbench (0: any free)")
    ap.add_argument(
        "--stay", action="store_true", help="after the summary keep every node (and the workbench) running until Ctrl-C"
    )
    args = ap.parse_args(argv)
    keys.check_chunk(args.site, "site")

    t_start = time.monotonic()
    print(f"[1/5] synthetic site ({args.size}, seed {args.seed})", file=sys.stderr)
    site_dir = ensure_site(args.size, args.seed, cache_dir() / "synth")
    site_doc = tomllib.loads((site_dir / "site.toml").read_text())
    tz = site_doc["site"]["tz"]
    photos = sitedir.site_photos(
        site_dir, args.site, progress=lambda files: tqdm(files, desc="reading photos", unit="photo", file=sys.stderr)
    )
    order = sitedir.in_capture_order(photos)
    if args.max_photos:
        order = order[: args.max_photos]
    anchors = [a for a in sitedir.anchor_messages(args.site, site_dir, photos) if a.image_name in set(order)]

    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    mcap_path = out / f"{args.site}-{stamp}.mcap"
    rrd_path = out / f"{args.site}-{stamp}.rrd"
    log_dir = out / "logs" / f"{args.site}-{stamp}"
    ifc_path = site_dir / site_doc["paths"]["ifc"]

    counts: Counter[str] = Counter()
    # the demo's own session is the hub, on a loopback port the system picks; the nodes join it
    with (
        open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], name="demo")) as bus,
        Launcher(
            site=args.site,
            bus=BusConfig(hub_port=bus.listen_port()),
            log_dir=log_dir,
            state_dir=out / "state" / f"{args.site}-{stamp}",
        ) as launcher,
        contextlib.ExitStack() as stack,
    ):
        print("[2/5] starting nodes", file=sys.stderr)
        regs = bus.collect(keys.pattern(keys.REGISTRATION, site=args.site))
        overlays = bus.collect(keys.pattern(keys.OVERLAY, site=args.site))
        masks = bus.collect(keys.pattern(keys.OCCLUSION, site=args.site))
        arrivals = _Arrivals()
        arrival_subs = [
            bus.subscribe(keys.pattern(keys.OCCLUSION, site=args.site), arrivals),
            bus.subscribe(keys.pattern(keys.OVERLAY, site=args.site), arrivals),
        ]
        errors = bus.collect(keys.key(keys.ERRORS, site=args.site))
        evidence = bus.collect(keys.pattern(keys.PHOTO_EVIDENCE, site=args.site))
        needs = bus.collect(keys.pattern(keys.NEEDS_ANCHOR, site=args.site))
        bim = bus.collect(keys.key(keys.BIM_MODEL, site=args.site), fetch_latched=True)
        launcher.start("recorder", sets=[f"path='{mcap_path}'"])
        launcher.start("dashboard", sets=[f"rerun='save:{rrd_path}'"])
        for name in PROCESSING_NODES:
            launcher.start(name)
        wb_port = _http_port(args.workbench_port)
        launcher.start("workbench", sets=[f"port={wb_port}"])
        workbench_url = f"http://127.0.0.1:{wb_port}/"
        launcher.wait_live(bus, ["recorder", "dashboard", "workbench", *PROCESSING_NODES])
        print(f"      workbench: {workbench_url} (answer anchor requests there while the demo runs)", file=sys.stderr)
        ingest_sets = [f"ifc=['{ifc_path}']", f"tz='{tz}'"]
        if site_doc["site"].get("terrain_height_m") is not None:
            ingest_sets.append(f"terrain_height_m={float(site_doc['site']['terrain_height_m'])}")
        launcher.start("ingest", sets=ingest_sets)
        launcher.wait_live(bus, ["ingest"])
        launcher.supervise(bus)  # a crashed node is restarted (and resumes from its state), reported on errors
        bim.wait(1, timeout=300)

        user = None
        if args.answer_anchor_requests:
            user = stack.enter_context(_SimulatedUser(bus, args.site, site_dir, photos, regs))
        print(f"[3/5] publishing {len(anchors)} up-front anchor click sets and {len(order)} photos", file=sys.stderr)
        for a in anchors:
            bus.publish(keys.key(keys.ANCHORS, site=args.site, photo=a.photo_id), a)
        for rel in tqdm(order, desc="push", unit="photo", file=sys.stderr):
            p = photos[rel]
            bus.publish(keys.key(keys.PHOTO, site=args.site, camera=p.camera_id), p)

        print("[4/5] waiting for registration, occlusion and overlays", file=sys.stderr)
        expected = {photos[r].photo_id for r in order}
        deadline = time.monotonic() + args.timeout
        with tqdm(total=len(expected), desc="registered", unit="photo", file=sys.stderr) as bar:
            last_new = time.monotonic()
            while time.monotonic() < deadline:
                done = _finished(regs.items, expected, user)
                bar.n = len(done)
                bar.refresh()
                if len(done) == len(expected):
                    if user is None:
                        break
                    try:  # a request published just after the last failed registration: keep waiting for it
                        needs.wait(len(needs.items) + 1, timeout=REQUEST_GRACE_SECS)
                        continue
                    except TimeoutError:
                        if len(_finished(regs.items, expected, user)) == len(expected):
                            break
                try:
                    regs.wait(len(regs.items) + 1, timeout=min(10.0, max(0.1, deadline - time.monotonic())))
                    last_new = time.monotonic()
                except TimeoutError:
                    if all(p.proc is not None and p.proc.poll() is not None for p in launcher.procs):
                        break
                    if time.monotonic() - last_new >= STALL_SECS:  # e.g. clicks the register node refused
                        break
        # Overlays follow registrations; give the render and occlude queues the time to drain.
        registered = {m.photo_id for _, m in regs.items if m.status != "failed"}
        _drain(overlays, lambda: {m.photo_id for _, m in overlays.items} >= registered, deadline)
        # Masks keep improving after a photo's first overlay (a later frame, more sparse points): wait until the
        # render node has redrawn every photo with its latest mask and the pipeline has gone quiet (as long as
        # masks or overlays keep arriving, up to --timeout).
        settled = arrivals.wait_settled(registered, SETTLE_QUIET_SECS, STALL_SECS, deadline)
        stale = arrivals.stale(registered)
        if "progress" in PROCESSING_NODES:  # the progress node reads each photo once its combined mask is out
            _drain(evidence, lambda: {m.photo_id for _, m in evidence.items} >= registered, deadline)
        for sub in arrival_subs:
            sub.close()
        if args.stay:
            print(f"demo done; nodes keep running, workbench at {workbench_url}; Ctrl-C to stop", file=sys.stderr)
            with contextlib.suppress(KeyboardInterrupt):
                threading.Event().wait()
        print("[5/5] stopping nodes", file=sys.stderr)
        exit_codes = launcher.stop_all()

    final = {m.photo_id: m for _, m in regs.items}  # the latest registration of each photo counts
    for m in final.values():
        counts[f"registration {m.status}"] += 1
    unanswered = len({photos[r].photo_id for r in order} - final.keys())
    # Back-pressure NodeErrors say a node lagged behind the push (nothing dropped): reported apart from faults.
    pressure = [(k, e) for k, e in errors.items if e.topic == "backpressure"]
    faults = [(k, e) for k, e in errors.items if e.topic != "backpressure"]
    summary = [
        ("photos pushed", len(order)),
        ("up-front anchor click sets", len(anchors)),
        ("registered (anchor)", counts["registration anchor"]),
        ("registered (auto)", counts["registration auto"]),
        ("registration failed", counts["registration failed"]),
        ("no registration yet", unanswered),
        ("needs anchor requests", len(needs.items)),
        ("requests answered (simulated user)", len(user.answered) if user is not None else "off"),
        *(
            [
                ("answered with < 6 corners visible", len(user.few)),
                ("requests not clickable (< 4 corners)", len(user.unanswerable)),
                ("gross mis-clicks sent", user.mis_clicks),
            ]
            if user is not None
            else []
        ),
        ("occlusion masks", len(masks.items)),
        ("overlays", len(overlays.items)),
        ("progress evidence (photos)", len({m.photo_id for _, m in evidence.items})),
        ("overlays behind latest mask", f"{len(stale)}" + ("" if settled == "settled" else f" ({settled})")),
        ("node errors", len(faults)),
        ("back-pressure signals", f"{len(pressure)} (photos pushed faster than a node took them; none dropped)"),
        ("wall time", f"{time.monotonic() - t_start:.0f} s"),
        ("MCAP recording", str(mcap_path)),
        ("rerun file", f"{rrd_path}  (view: rerun {rrd_path})"),
        ("node logs", str(log_dir)),
        ("workbench", f"{workbench_url}  (running while the demo runs; --stay keeps it)"),
    ]
    width = max(len(k) for k, _ in summary)
    for _, e in pressure[:3]:
        print(f"  back-pressure at {e.node}: {e.reason}")
    print("\nConstructAide demo summary")
    for k, v in summary:
        print(f"  {k:<{width}}  {v}")
    for _, e in faults[:5]:
        print(f"  error from {e.node}: {e.reason}")
    bad = {k: v for k, v in exit_codes.items() if v not in (0, None)}
    if bad:
        raise UserError(f"nodes exited with errors: {bad}; see {log_dir}")
    if not mcap_path.exists():
        raise UserError(f"recorder wrote no file at {mcap_path}; see {log_dir}")
    return 0


def _finished(items: list, expected: set[str], user: _SimulatedUser | None) -> set[str]:
    """Photos of ``expected`` whose registration is final: any registration without a simulated user; with one,
    those it has nothing more to answer for."""
    latest = _latest_status(items)
    have = latest.keys() & expected
    if user is None:
        return have
    return {p for p in have if user.settled(p, latest[p])}


def _drain(collector, done, deadline: float) -> None:
    while not done() and time.monotonic() < deadline:
        try:
            collector.wait(len(collector.items) + 1, timeout=min(15.0, max(0.1, deadline - time.monotonic())))
        except TimeoutError:
            return
