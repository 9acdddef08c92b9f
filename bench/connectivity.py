"""What the photos of a synthetic site allow: how many anchors a perfect registration would still need.

For every pair of photos, the register node's own pair verification (``nodes.register.matching.verify_pair``,
features as the batch detects them) and, from the site's truth (scoring only), how many of the verified matches
are true (both features back-project through the true cameras and depths to points within 0.3 m of each other).
Photos of one fixed camera share its viewpoint (one group). Groups joined by pairs with at least ``--min-true``
true verified matches form components; each component needs at least one anchor, so their number is a lower bound
on the anchors any image-based registration needs (with requests answered). Also counted: verified pairs with
no true match at all (repeated texture: the site hoarding's print, neighbour facades), which is what makes the
geometry checks refuse many automatic poses; the same counts by kind of pair and by the distance between the two
true camera centres, and the phone photos a fixed camera's frame of their day or before joins (what a streaming
registration meeting photos in capture order can use). Last: the photos in components that hold a photo of the site's
``anchors.json`` (the up-front clicks of the plain demo), an upper bound on what any registration with those
anchors alone can register.

Run: ``python bench/connectivity.py [--size small] [--seed 0] [--min-true 30]``.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _report import table, write_section  # noqa: E402

from constructaide import camera as cam  # noqa: E402
from constructaide.synth import ensure_site  # noqa: E402
from constructaide.synth.truth import load_cameras, load_depth  # noqa: E402
from nodes.register.batch import extract_all, find_images  # noqa: E402
from nodes.register.config import MapperConfig  # noqa: E402
from nodes.register.features import pca_basis, project_pca  # noqa: E402
from nodes.register.matching import verify_pair  # noqa: E402


def true_points(site: Path, rel: str, rec: dict, px: np.ndarray) -> np.ndarray:
    """World points (N, 3) of pixels (N, 2) through the true camera and depth (NaN where the depth is 0)."""
    K = np.asarray(rec["K"], np.float64)
    depth = load_depth(site, rel)
    uv = np.clip(np.round(px).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
    z = depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    xy = cam.undistort_normalized((px - K[:2, 2]) / [K[0, 0], K[1, 1]], rec["k1"], rec["k2"])
    T = np.asarray(rec["world_from_camera"], np.float64)
    out = np.c_[xy * z[:, None], z] @ T[:3, :3].T + T[:3, 3]
    out[z <= 0] = np.nan
    return out


def group(rel: str) -> str:
    return rel.split("/")[0] if not rel.startswith("phone") else rel


def link_table(links: list[tuple[str, str, int, int]], names: list[str], cams: dict, min_true: int) -> str:
    """Which verified pairs join (>= ``min_true`` true matches) and which hold no true match, by kind of pair and by
    the distance between the two true camera centres; and the phone photos a fixed camera's frame taken on or before
    their day joins (what a streaming registration that meets photos in capture order can use), with the share of
    true matches among those pairs' verified matches."""

    def centre(n: str) -> np.ndarray:
        return np.asarray(cams[n]["world_from_camera"], np.float64)[:3, 3]

    def day(n: str) -> int:
        return int(cams[n]["capture_time_utc_ns"]) // (86400 * 10**9)

    def kind(a: str, b: str) -> str:
        pa, pb = a.startswith("phone/"), b.startswith("phone/")
        if pa and pb:
            return "phone - phone, same visit" if day(a) == day(b) else "phone - phone, other visit"
        return "phone - fixed camera" if pa or pb else "fixed camera - fixed camera"

    rows: list[list] = []
    by_kind: dict[str, list[int]] = collections.defaultdict(lambda: [0, 0, 0])
    bands = (0.0, 20.0, 40.0, 80.0, np.inf)
    by_band: dict[int, list[int]] = collections.defaultdict(lambda: [0, 0, 0])
    reached: dict[str, list[float]] = collections.defaultdict(list)
    phones = [n for n in names if n.startswith("phone/")]
    for a, b, n, t in links:
        d = float(np.linalg.norm(centre(a) - centre(b)))
        band = int(np.searchsorted(bands, d, side="right")) - 1
        for acc in (by_kind[kind(a, b)], by_band[band]):
            acc[0] += 1
            acc[1] += t >= min_true
            acc[2] += t == 0
        phone, other = (a, b) if a.startswith("phone/") else (b, a)
        if phone.startswith("phone/") and not other.startswith("phone/") and day(other) <= day(phone) and t >= min_true:
            reached[phone].append(t / n)
    band_rows = [
        (
            f"true centres {bands[k]:.0f}-{bands[k + 1]:.0f} m apart"
            if k + 2 < len(bands)
            else f"true centres >= {bands[k]:.0f} m apart",
            v,
        )
        for k, v in sorted(by_band.items())
    ]
    for label, (n, j, z) in [*sorted(by_kind.items()), *band_rows]:
        rows.append([label, n, j, z])
    shares = [s for v in reached.values() for s in v]
    head = ["verified pairs between groups", "pairs", f">= {min_true} true matches", "no true match"]
    note = f"Phone photos that a fixed camera's frame of their day or before joins: {len(reached)} of {len(phones)}" + (
        f" (by {sum(len(v) for v in reached.values())} pairs; true share of those pairs' verified matches: "
        f"median {np.median(shares):.2f}, {min(shares):.2f}-{max(shares):.2f})."
        if shares
        else "."
    )
    return table(head, rows) + "\n\n" + note + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-true", type=int, default=30, help="true verified matches that join two groups")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    site = ensure_site(args.size, args.seed, ROOT / ".cache" / "synth")
    cams = load_cameras(site)
    named = find_images(site / "photos")
    names = [n for n, _ in named]
    feats = [f for f, _ in extract_all([p for _, p in named], 4000, 3200, 2, False)]
    basis = pca_basis([f.descriptors for f in feats], 64)
    feats_pca = [project_pca(f, basis) for f in feats]
    world = {
        n: true_points(site, n, cams[n], f.keypoints_px.astype(np.float64)) for n, f in zip(names, feats, strict=True)
    }
    cfg = MapperConfig()
    parent = {g: g for g in map(group, names)}

    def find(x: str) -> str:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    verified_pairs = junk_pairs = joined = 0
    links: list[tuple[str, str, int, int]] = []  # (photo, photo, verified matches, true ones) between groups
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if group(names[i]) == group(names[j]):
                continue
            g = verify_pair(feats_pca[i], feats_pca[j], cfg)
            if g is None:
                continue
            verified_pairs += 1
            d = np.linalg.norm(world[names[i]][g.matches[:, 0]] - world[names[j]][g.matches[:, 1]], axis=1)
            n_true = int(np.sum(d < 0.3))
            junk_pairs += n_true == 0
            links.append((names[i], names[j], len(g.matches), n_true))
            if n_true >= args.min_true:
                joined += 1
                parent[find(group(names[i]))] = find(group(names[j]))
        print(f"  {i + 1}/{len(names)} photos paired", file=sys.stderr, flush=True)
    comps = collections.Counter(find(g) for g in map(group, names))
    anchored = {find(group(a["image"])) for a in json.loads((site / "anchors.json").read_text())["anchors"]}
    reachable = sum(find(group(n)) in anchored for n in names)
    sizes = collections.Counter(find(group(n)) for n in names)
    rows = [
        [
            f"{args.size} (seed {args.seed})",
            len(names),
            len(set(map(group, names))),
            verified_pairs,
            junk_pairs,
            joined,
            len(comps),
            ", ".join(str(s) for s in sorted(sizes.values(), reverse=True)),
            f"{reachable} of {len(names)} ({len(anchored)} components anchored)",
        ]
    ]
    head = [
        "site",
        "photos",
        "groups",
        "verified pairs between groups",
        "of them with no true match",
        f"pairs with >= {args.min_true} true matches",
        "components = lower bound on anchors",
        "photos per component",
        "photos reachable from anchors.json",
    ]
    out = table(head, rows)
    out += "\n\n" + link_table(links, names, cams, args.min_true)
    print(out)
    print(f"site {args.size} seed {args.seed}: at least {len(comps)} anchors; {reachable} photos reach anchors.json")
    if not args.no_write:
        body = (
            f"Command: `python bench/connectivity.py --size {args.size} --seed {args.seed} --min-true "
            f"{args.min_true}`. {__doc__.split(chr(10) + chr(10))[1]}\n\n{out}\n"
        )
        write_section(f"connectivity ({args.size}, seed {args.seed})", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
