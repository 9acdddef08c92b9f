"""Chaos: nodes SIGKILLed at random moments while fixed cameras stream; nothing lost, nothing registered twice.

    nice -n 10 python bench/chaos.py [--frames 1000] [--seed 0] [--kills-per-node 2] [--no-write]

Loopback only. The small synthetic site's fixed-camera frames are repeated (new photo ids, capture times a
repeat's span later) up to ``--frames`` and pushed as fast as the register node takes them (at most ``--window``
photos ahead of its registrations). The real shipping nodes run as processes under the supervisor
(:mod:`constructaide.app.supervise`) with a state directory (ledger + durable state): ingest (the BIM), register,
occlude, render and a rotating recorder. At frame indices drawn from ``--seed`` the bench SIGKILLs register,
occlude, render and the recorder, each ``--kills-per-node`` times, one at a time (the next kill waits until the
previous node is live again). After the stream it waits for every photo's registration and overlay, stops the
nodes and checks the rotated recording (read through its index): every photo's registration, combined mask and
overlay present. Time to recover = SIGKILL to the node's liveliness token back (back-off + start + state restore);
first output again = SIGKILL to the first registration / mask / overlay the restarted node publishes.
The last line reads ``frames N, kills K, photos lost L, duplicated D`` (lost: photos without a registration in
the recording; duplicated: photos registered successfully more than once).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import tempfile
import threading
import time
import tomllib
from collections import Counter, defaultdict
from pathlib import Path

import msgspec
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import code_version, median, table, write_section  # noqa: E402

from constructaide import sitedir  # noqa: E402
from constructaide.app.launch import Launcher  # noqa: E402
from constructaide.app.supervise import RestartPolicy  # noqa: E402
from constructaide.recording import decoded_messages, index_path, read_index  # noqa: E402
from constructaide.runtime import BusConfig, open_bus  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from schemas import codec, keys  # noqa: E402
from schemas.messages import OcclusionMask, Overlay, Photo, Registration  # noqa: E402

SITE = "chaos"
VICTIMS = ("register", "occlude", "render", "recorder")
DAY_NS = 86_400 * 10**9


def frames(site_dir: Path, n: int) -> tuple[list[Photo], dict[str, Photo]]:
    """``n`` fixed-camera frames in capture order (the site's, then repeats with new ids and later times) and the
    site's own photos by relative path (for the up-front anchors)."""
    by_rel = sitedir.site_photos(site_dir, SITE, cameras=lambda camera: camera != keys.PHONE)
    base = sorted(by_rel.values(), key=lambda p: (p.capture_time_ns, p.photo_id))
    span = base[-1].capture_time_ns - base[0].capture_time_ns + DAY_NS
    out = []
    for i in range(n):
        r, p = divmod(i, len(base))
        src = base[p]
        if r == 0:
            out.append(src)
        else:
            out.append(
                msgspec.structs.replace(
                    src, photo_id=f"{src.photo_id}r{r}", capture_time_ns=src.capture_time_ns + r * span
                )
            )
    return out, by_rel


class Watch:
    """Live view of the bus: registrations, overlays, liveliness (for flow control and recovery times)."""

    def __init__(self, bus) -> None:
        self.cond = threading.Condition()
        self.regs: dict[str, list[str]] = defaultdict(list)
        self.overlays: set[str] = set()
        self.live: dict[str, int] = Counter()
        self.back_at: dict[str, list[float]] = defaultdict(list)
        self.out_at: dict[str, list[float]] = defaultdict(list)  # when each node kind published an output
        self.subs = [
            bus.subscribe(keys.pattern(keys.OCCLUSION, site=SITE), self.on_mask),
            bus.subscribe(keys.pattern(keys.REGISTRATION, site=SITE), self.on_reg),
            bus.subscribe(keys.pattern(keys.OVERLAY, site=SITE), self.on_overlay),
            bus.watch_tokens(keys.pattern(keys.LIVELINESS, site=SITE), self.on_token),
        ]

    def on_reg(self, key: str, payload: bytes) -> None:
        msg = codec.decode(payload, Registration)
        with self.cond:
            self.regs[msg.photo_id].append(msg.status)
            self.out_at["register"].append(time.monotonic())
            self.cond.notify_all()

    def on_mask(self, key: str, payload: bytes) -> None:
        with self.cond:
            self.out_at["occlude"].append(time.monotonic())

    def on_overlay(self, key: str, payload: bytes) -> None:
        with self.cond:
            self.overlays.add(key.rsplit("/", 1)[1])
            self.out_at["render"].append(time.monotonic())
            self.cond.notify_all()

    def on_token(self, key: str, alive: bool) -> None:
        node = key.split("/")[3]
        with self.cond:
            self.live[node] += 1 if alive else -1
            if alive:
                self.back_at[node].append(time.monotonic())
            self.cond.notify_all()

    def wait(self, pred, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(pred, timeout)

    def close(self) -> None:
        for s in self.subs:
            s.close()


def resume_secs(killed_at: list[tuple[str, float]], watch: Watch) -> dict[str, list[float]]:
    """Per node kind: seconds from each SIGKILL to the first output the node published after its token was back
    (its restart, state restore and the start of its catch-up); nodes without outputs (recorder) are left out."""
    out: dict[str, list[float]] = defaultdict(list)
    for node, t_kill in killed_at:
        back = [t for t in watch.back_at[node] if t > t_kill]
        after = [t for t in watch.out_at.get(node, []) if back and t > back[0]]
        if after:
            out[node].append(min(after) - t_kill)
    return dict(out)


def rss_mib(pid: int) -> float:
    """Resident memory (MiB) of a process, NaN when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def kill_plan(
    rng: np.random.Generator, n: int, per_node: int, victims: tuple[str, ...] = VICTIMS
) -> list[tuple[int, str]]:
    plan = [(int(rng.integers(int(n * 0.05), int(n * 0.85))), node) for node in victims for _ in range(per_node)]
    return sorted(plan)


def run(args: argparse.Namespace, out: Path) -> dict:
    site_dir = ensure_site("small", 0, ROOT / ".cache" / "synth")
    doc = tomllib.loads((site_dir / "site.toml").read_text())
    stream, by_rel = frames(site_dir, args.frames)
    anchors = sitedir.anchor_messages(SITE, site_dir, by_rel)
    plan = kill_plan(np.random.default_rng(args.seed), args.frames, args.kills_per_node, tuple(args.victims))
    rec_dir = out / "recordings"
    os.environ["CONSTRUCTAIDE_HISTORY_MB"] = str(args.history_mb)
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    t0 = time.monotonic()
    recover: dict[str, list[float]] = defaultdict(list)
    killed_at: list[tuple[str, float]] = []  # node, time of the SIGKILL
    kills: list[tuple[int, str, int]] = []
    rss: list[dict] = []  # resident memory of every node process every 100 frames
    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"], history_bytes=int(args.history_mb * 1e6))) as bus:
        watch = Watch(bus)
        launcher = Launcher(
            site=SITE, bus=BusConfig(hub_port=bus.listen_port()), log_dir=out / "logs", state_dir=out / "state"
        )
        with launcher:
            launcher.start(
                "recorder",
                sets=[f"directory='{rec_dir}'", f"max_file_mb={args.max_file_mb}", "max_file_secs=60"],
            )
            launcher.start("register")
            launcher.start("occlude")
            launcher.start("render", sets=[f"modes={list(args.modes)!r}".replace("'", '"')])
            launcher.wait_live(bus, ["recorder", "register", "occlude", "render"])
            ifc = site_dir / doc["paths"]["ifc"]
            launcher.start("ingest", sets=[f"ifc=['{ifc}']", f"tz='{doc['site']['tz']}'"])
            bim = bus.collect(keys.key(keys.BIM_MODEL, site=SITE), fetch_latched=True)
            launcher.wait_live(bus, ["ingest"])
            bim.wait(1, timeout=300)
            sup = launcher.supervise(bus, RestartPolicy(backoff_initial_secs=0.2, max_crashes=1000, window_secs=60))
            for a in anchors:
                bus.publish(keys.key(keys.ANCHORS, site=SITE, photo=a.photo_id), a)
            t_stream = time.monotonic()
            pending_kill: tuple[str, float, int] | None = None  # node, time, live count before
            next_kill = 0
            for i, photo in enumerate(stream):
                watch.wait(lambda i=i: len(watch.regs) >= i - args.window, timeout=args.timeout)
                if pending_kill is not None:
                    node, t_kill, seen = pending_kill
                    if len(watch.back_at[node]) > seen:
                        recover[node].append(watch.back_at[node][seen] - t_kill)
                        pending_kill = None
                if pending_kill is None and next_kill < len(plan) and i >= plan[next_kill][0]:
                    node = plan[next_kill][1]
                    proc = next(p for p in launcher.procs if p.name == node)
                    assert proc.proc is not None
                    with watch.cond:
                        seen = len(watch.back_at[node])
                    os.kill(proc.proc.pid, signal.SIGKILL)
                    pending_kill = (node, time.monotonic(), seen)
                    killed_at.append((node, pending_kill[1]))
                    kills.append((i, node, proc.proc.pid))
                    next_kill += 1
                bus.publish(keys.key(keys.PHOTO, site=SITE, camera=photo.camera_id), photo)
                if (i + 1) % 100 == 0:
                    mem = {p.name: rss_mib(p.proc.pid) for p in launcher.procs if p.proc and p.proc.poll() is None}
                    rss.append({"frames": i + 1, **mem})
                    print(
                        f"  {i + 1} frames pushed, {len(watch.regs)} registered, {len(kills)} kills; RSS MiB "
                        + ", ".join(f"{k} {v:.0f}" for k, v in mem.items()),
                        file=sys.stderr,
                        flush=True,
                    )
            if pending_kill is not None:
                node, t_kill, seen = pending_kill
                watch.wait(lambda: len(watch.back_at[node]) > seen, timeout=120)
                if len(watch.back_at[node]) > seen:
                    recover[node].append(watch.back_at[node][seen] - t_kill)
            t_pushed = time.monotonic()
            ids = {p.photo_id for p in stream}
            watch.wait(lambda: ids <= watch.regs.keys(), timeout=args.timeout)
            t_registered = time.monotonic()

            def drawn() -> bool:
                ok = {pid for pid, st in watch.regs.items() if any(s != "failed" for s in st)}
                return ok <= watch.overlays

            watch.wait(drawn, timeout=args.timeout)
            t_drawn = time.monotonic()
            quiet_until = time.monotonic() + 5.0
            while time.monotonic() < quiet_until:  # let the last masks/overlays reach the recorder
                n_before = len(watch.overlays)
                watch.wait(lambda n=n_before: len(watch.overlays) > n, timeout=max(0.1, quiet_until - time.monotonic()))
            restarts = [e for e in sup.events if e.kind == "restart"]
            gave_up = [e for e in sup.events if e.kind == "give_up"]
            watch.close()
        t_end = time.monotonic()
    # -- the recording, through its index
    index = index_path(rec_dir, SITE)
    entries = read_index(index)
    reg_ok: dict[str, int] = Counter()
    reg_any: set[str] = set()
    combined: set[str] = set()
    overlays: set[str] = set()
    photos_rec: set[str] = set()
    for _, msg in decoded_messages(index, (Photo, Registration, OcclusionMask, Overlay), allow_truncated=True):
        if isinstance(msg, Photo):
            photos_rec.add(msg.photo_id)
        elif isinstance(msg, Registration):
            reg_any.add(msg.photo_id)
            if msg.status != "failed":
                reg_ok[msg.photo_id] += 1
        elif isinstance(msg, OcclusionMask) and msg.kind == "combined":
            combined.add(msg.photo_id)
        elif isinstance(msg, Overlay):
            overlays.add(msg.photo_id)
    ids = {p.photo_id for p in stream}
    registered = {p for p in ids if reg_ok.get(p, 0) > 0}
    live_dups = sum(1 for p in ids if sum(s != "failed" for s in watch.regs.get(p, [])) > 1)
    return {
        "frames": len(stream),
        "kills": len(kills),
        "kills_by_node": Counter(n for _, n, _ in kills),
        "restarts": len(restarts),
        "gave_up": len(gave_up),
        "lost": len(ids - reg_any),
        "lost_live": len(ids - watch.regs.keys()),
        "duplicated": sum(1 for p in ids if reg_ok.get(p, 0) > 1),
        "duplicated_live": live_dups,
        "registered": len(registered),
        "failed_only": len((ids & reg_any) - registered),
        "photos_not_recorded": len(ids - photos_rec),
        "no_combined_mask": len(ids - combined),
        "registered_without_overlay": len(registered - overlays),
        "files": len(entries),
        "repaired_files": sum(e.state == "repaired" for e in entries),
        "open_files": sum(e.state == "open" for e in entries),
        "recover_secs": {n: v for n, v in recover.items()},
        "resume_secs": resume_secs(killed_at, watch),
        "stream_secs": t_pushed - t_stream,
        "registered_secs": t_registered - t_stream,
        "drawn_secs": t_drawn - t_stream,
        "total_secs": t_end - t0,
        "rss": rss,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kills-per-node", type=int, default=2)
    ap.add_argument("--victims", nargs="+", default=list(VICTIMS), choices=VICTIMS, help="nodes to kill")
    ap.add_argument("--window", type=int, default=32, help="photos pushed ahead of the registrations")
    ap.add_argument("--modes", nargs="+", default=["state4d"], help="render modes")
    ap.add_argument("--max-file-mb", type=float, default=20.0, help="recorder rotation size")
    ap.add_argument("--history-mb", type=float, default=1024.0, help="publication cache of each session")
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--out", type=Path, help="keep recordings, state and logs here (default: a temporary folder)")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args()
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        r = run(args, args.out)
    else:
        with tempfile.TemporaryDirectory(prefix="chaos-") as tmp:
            r = run(args, Path(tmp))
    rec = r["recover_secs"]
    res = r["resume_secs"]
    rows = [
        [
            n,
            r["kills_by_node"].get(n, 0),
            len(rec.get(n, [])),
            median(rec.get(n, [])),
            max(rec.get(n, [0.0])),
            median(res[n]) if res.get(n) else "-",
            max(res[n]) if res.get(n) else "-",
        ]
        for n in VICTIMS
    ]
    head = ["node", "SIGKILLs", "recovered", "median recover s", "max recover s"]
    t1 = table(head + ["median first output again s", "max first output again s"], rows)
    t2 = table(
        ["figure", "value"],
        [
            ["frames pushed", r["frames"]],
            ["kills / supervisor restarts / given up", f"{r['kills']} / {r['restarts']} / {r['gave_up']}"],
            ["photos without a registration (recording / live)", f"{r['lost']} / {r['lost_live']}"],
            ["photos registered twice (recording / live)", f"{r['duplicated']} / {r['duplicated_live']}"],
            ["registered / failed only", f"{r['registered']} / {r['failed_only']}"],
            ["photos missing in the recording", r["photos_not_recorded"]],
            ["photos without a combined mask", r["no_combined_mask"]],
            ["registered photos without an overlay", r["registered_without_overlay"]],
            [
                "recording files (repaired after a kill / open)",
                f"{r['files']} ({r['repaired_files']} / {r['open_files']})",
            ],
            [
                "push time s / all registered s / all drawn s",
                f"{r['stream_secs']:.0f} / {r['registered_secs']:.0f} / {r['drawn_secs']:.0f}",
            ],
            ["frames per second (to all drawn)", f"{r['frames'] / max(r['drawn_secs'], 1e-9):.2f}"],
        ],
    )
    names = [n for n in ("ingest", *VICTIMS) if any(n in row for row in r["rss"])]
    t3 = table(
        ["frames pushed", *[f"{n} RSS MiB" for n in names]],
        [[row["frames"], *[f"{row.get(n, float('nan')):.0f}" for n in names]] for row in r["rss"]],
    )
    last = f"frames {r['frames']}, kills {r['kills']}, photos lost {r['lost']}, duplicated {r['duplicated']}"
    print(t1)
    print()
    print(t2)
    print()
    print(t3)
    if not args.no_write:
        body = (
            f"Code: {code_version()}. Seed {args.seed}; render modes {', '.join(args.modes)}; recorder rotation at "
            f"{args.max_file_mb:g} MB / 60 s. Recover = SIGKILL to the node's liveliness token back (supervisor "
            "back-off 0.2 s doubling per crash within 60 s, process start, state restore); first output again = "
            "SIGKILL to the first registration / mask / overlay the restarted node publishes (the recorder has no "
            "output).\n\n"
            f"{t1}\n\n{t2}\n\nResident memory of the node processes (a killed node's restarted process from its "
            f"restart on):\n\n{t3}\n\n`{last}`\n"
        )
        write_section(
            f"Chaos ({r['frames']} frames)",
            body,
            command="python " + " ".join(sys.argv),
        )
    print(last)


if __name__ == "__main__":
    main()
