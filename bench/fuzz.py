"""Longer fuzz run than the suite's: every node with message inputs fed bad payloads (tests/fuzz_payloads.py).

Prints inputs tried per message type and kind, NodeErrors returned, inputs that must be refused but were not,
crashes (a worker that died or did not finish); then the workbench's HTTP API fed bad requests on every endpoint
(tests/fuzz_http.py): answers by status class, 5xx and not-JSON errors, and whether the server still answered a
good request after each; appends the figures to BENCHMARKS.md.

    python bench/fuzz.py [--examples N] [--http-examples N] [--seed S]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "bench"), str(ROOT / "tests")]

from _report import code_version, table, write_section  # noqa: E402
from fuzz_payloads import SITE, good_photo  # noqa: E402
from hypothesis import HealthCheck, given, seed, settings  # noqa: E402
from test_fuzz_nodes import NODES, Harness, case_strategy, start  # noqa: E402

from schemas import codec, keys  # noqa: E402


def make_feed(h: Harness, spec, examples: int, seed_: int, missed: list[str], counts: dict[str, int]):
    @seed(seed_)
    @settings(max_examples=examples, deadline=None, database=None,
              suppress_health_check=list(HealthCheck), phases=["generate"])  # fmt: skip
    @given(case_strategy(spec))
    def feed(pair) -> None:
        inp, case = pair
        try:
            h.bad(inp, case)
            h.good()
        except AssertionError as e:
            if "died" in str(e) or "did not finish" in str(e):
                counts["crashes"] += 1
            else:
                missed.append(f"{h.name}: {str(e).splitlines()[0][:160]}")

    return feed


def fuzz_http(examples: int, seed_: int) -> tuple[list[list], dict[str, int]]:
    """Rows [endpoint, tried, 2xx, 4xx, 5xx] and counts (bad answers, server down after a request)."""
    from fuzz_http import bad_request, check, send, workbench_server

    per: dict[str, list[int]] = {}
    counts = {"bad": 0, "down": 0}
    bad_lines: list[str] = []
    with workbench_server() as (http, bodies, ann_ids):

        @seed(seed_)
        @settings(max_examples=examples, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck), phases=["generate"])  # fmt: skip
        @given(bad_request(bodies, ann_ids))
        def feed(req: tuple) -> None:
            row = per.setdefault(req[0].split(" / ")[0], [0, 0, 0, 0])
            resp = send(http, req)
            row[0] += 1
            row[{2: 1, 4: 2}.get(resp.status_code // 100, 3)] += 1
            try:
                check(resp, req[0])
            except (AssertionError, ValueError) as e:
                counts["bad"] += 1
                bad_lines.append(str(e).splitlines()[0][:160])
            if http.get("/api/site").status_code != 200:
                counts["down"] += 1

        feed()
    for line in bad_lines[:10]:
        print("HTTP", line)
    return [[k, *v] for k, v in sorted(per.items())], counts


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--examples", type=int, default=300, help="bad payloads per node")
    ap.add_argument("--http-examples", type=int, default=1000, help="bad requests to the workbench HTTP API")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    per_type: dict[str, list[int]] = {}
    missed: list[str] = []
    counts = {"crashes": 0}
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory() as tmp:
        for name in NODES:
            spec, bus, errors, ctx = start(name, Path(tmp) / name)
            with bus, ctx as node:
                h = Harness(name, node, bus, errors)
                h.good()
                if name != "ingest":  # the photo the clicks and masks refer to (as in the test)
                    h.send(keys.key(keys.PHOTO, site=SITE, camera="cam-a"), codec.encode(good_photo("p0")))

                make_feed(h, spec, args.examples, args.seed, missed, counts)()
                for kind, n in h.tried.items():
                    row = per_type.setdefault(kind.split("/")[0], [0, 0])
                    row[0] += n
                    row[1] += h.refused.get(kind, 0)
                print(f"{name}: {sum(h.tried.values())} tried, {sum(h.refused.values())} NodeErrors", flush=True)
    rows = [[t, n, e] for t, (n, e) in sorted(per_type.items())]
    tried = sum(r[1] for r in rows)
    refused = sum(r[2] for r in rows)
    body = table(["message type", "inputs tried", "NodeErrors returned"], rows)
    body += (
        f"\n\nNodes: {', '.join(NODES)} (in-process bus), {args.examples} bad payloads each (seed {args.seed}), "
        "every one "
        f"followed by a good Photo that must be handled without an error. Total: {tried} tried, {refused} NodeErrors, "
        f"must-refuse inputs not refused {len(missed)}, crashes {counts['crashes']}; {time.monotonic() - t0:.0f} s "
        f"({code_version()}). Not refused by the recorder by design: it records whatever is on the bus; bit flips "
        "that still decode to a valid message are handled as messages."
    )
    t1 = time.monotonic()
    http_rows, http = fuzz_http(args.http_examples, args.seed)
    n_http = sum(r[1] for r in http_rows)
    body += "\n\nWorkbench HTTP API (the node's real server on an in-process bus; tests/fuzz_http.py):\n\n"
    body += table(["endpoint", "requests", "2xx", "4xx", "5xx"], http_rows)
    body += (
        f"\n\n{n_http} bad or mutated requests (seed {args.seed}): path ids unknown / traversals / huge, query "
        "numbers NaN / infinite / beyond int64, bodies not JSON, wrong shapes, one value replaced, oversized, deeply "
        f"nested; 5xx {sum(r[4] for r in http_rows)}, answers that are not a JSON error {http['bad']}, server not "
        f"answering the good request after one {http['down']}; {time.monotonic() - t1:.0f} s."
    )
    for line in missed[:10]:
        print("MISSED", line)
    print(body)
    print(f"tried {tried}, NodeErrors {refused}, missed {len(missed)}, crashes {counts['crashes']}")
    print(f"http: {n_http} requests, bad answers {http['bad']}, down {http['down']}")
    write_section("fuzz (bad input)", body)
    return 0 if counts["crashes"] == 0 and http["bad"] == 0 and http["down"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
