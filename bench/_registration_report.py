"""The registration bench's BENCHMARKS.md section: the table and the notes under it (bench/registration.py)."""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYCOLMAP_GT = "pycolmap, GT similarity"
PYCOLMAP_ANCHOR = "pycolmap, anchor similarity"


def machine() -> str:
    cpu = "unknown"
    try:
        m = re.search(r"model name\s*:\s*(.*)", Path("/proc/cpuinfo").read_text())
        cpu = m.group(1).strip() if m else cpu
    except OSError:
        pass
    return f"nproc {os.cpu_count()}, {cpu}, {platform.python_implementation()} {platform.python_version()}"


def write_section(rows: list[dict], notes: list[str], command: str, runs: int, title: str = "registration") -> None:
    lines = [
        f"## {title}",
        "",
        f"Date: {dt.datetime.now(dt.UTC).strftime('%Y-%m-%d %H:%M UTC')}. Machine: {machine()}. Command: `{command}`. "
        f"Each of the {runs} run(s) uses its own click-noise draw (seed = draw number); errors are means over the "
        "draws ('centre dist min-max': the range of the per-draw mean over draws). Wall time = median over the "
        "runs (pycolmap: its first min(runs, 3) runs; it takes no clicks), interleaved (each run: every variant "
        "of ours, then pycolmap), "
        "end to end (features + matching + registration, run_batch(densify_params=None); pycolmap: extraction + "
        "exhaustive matching + incremental mapping, CPU). 'densify s': the densification run_batch adds by default "
        "(epipolar-guided matching for the occlusion work), timed on the default variant's reconstruction in the "
        "same run, not included in 'time s'.",
        "",
        "Errors are means over registered images: viewing-direction angle (deg), camera-centre distance "
        "(model units and % of camera-to-scene distance), reprojection of ground-truth 3D checkpoints (% of width; "
        "mean over checkpoints, and the median per image ('reproj median %'), both averaged over images). "
        "Anchor clicks simulated from ground truth (12 clicks per image, 1 px noise, available for every image; the "
        "algorithm starts from one anchor and asks for more only when no image has enough matched tracks: "
        f"'anchors used'; see `bench/_datasets.py`). pycolmap is aligned two ways: '{PYCOLMAP_GT}' by the "
        "similarity on all camera centres that fits ground truth best (as the paper aligned VSfM), "
        f"'{PYCOLMAP_ANCHOR}' by the similarity mapping its cameras of the anchor file's first two images onto the "
        "poses our anchor solve gets from their clicks (the gauge from the same user input as ours; 'anchors used' = "
        "those 2). 'centre dist after sim.' applies the ground-truth similarity to ours too (shape accuracy without "
        "the gauge given by the clicks). 'predicted centre sigma': the mean over images of the camera-centre "
        "standard deviation our final adjustment reports (report.json centre_sigma: square root of the trace of "
        "the centre's covariance, from the features and clicks, with their noise estimated from their residuals; "
        "'-' when the anchors were not released), and 'error / sigma (RMS)' the RMS over those images of the "
        "actual centre distance over it (1 = the prediction is right on average; above 1 = errors the noise model "
        "misses).",
        "",
        "| set | method | registered | anchors used | angle deg | centre dist | centre dist min-max | centre % "
        "| centre dist after sim. "
        "| predicted centre sigma | error / sigma (RMS) | reproj % width | reproj median % | reproj worst image % "
        "| implausible | time s | time ratio | densify s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    base = {r["set"]: r["secs"] for r in rows if r["method"] == PYCOLMAP_GT}
    for r in rows:
        ratio = r["secs"] / base[r["set"]] if base.get(r["set"]) else float("nan")
        dens = r.get("densify_secs", float("nan"))
        sig, zr = r.get("centre_sigma", float("nan")), r.get("centre_z_rms", float("nan"))
        lines.append(
            f"| {r['set']} | {r['method']} | {r['registered']}/{r['total']} | {r['anchors_used']}{_by_model(r)} | "
            f"{r['angle_deg']:.3f} | "
            f"{r['centre_dist']:.4f} | {r['centre_dist_min']:.4f}-{r['centre_dist_max']:.4f} | "
            f"{r['centre_dist_pct']:.3f} | {r['centre_dist_after_similarity']:.4f} | "
            f"{'-' if sig != sig else f'{sig:.4f}'} | {'-' if zr != zr else f'{zr:.2f}'} | "
            f"{r['reproj_pct_width']:.3f} | {r['reproj_median_pct_width']:.3f} | "
            f"{r.get('reproj_max_pct_width', float('nan')):.3f} | {r.get('implausible', 0):.0f} | {r['secs']:.1f} | "
            f"{ratio:.2f} | {'-' if dens != dens else f'{dens:.1f}'} |"
        )
    lines += ["", "Paper Table 2 (temple small, ours): 2.34 deg, 0.05 units, 2.01 % width.", ""]
    lines += [f"- {n}" for n in notes]
    section = "\n".join(lines) + "\n"
    path = ROOT / "BENCHMARKS.md"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    pattern = re.compile(rf"^## {re.escape(title)}\n.*?(?=^## |\Z)", re.S | re.M)
    text = pattern.sub(lambda _: section + "\n", text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    path.write_text(text)


def base_notes() -> list[str]:
    """Explanations printed under the table."""
    return [
        "Variants: 'default' (MapperConfig()) holds anchor poses fixed while the reconstruction grows (the paper), "
        "then one final adjustment over every triangulated point releases the anchors that observe >= 300 "
        "triangulated points (held by their clicks like the other cameras by their tracks) and refines one principal "
        "point and one pixel aspect ratio fy/fx per camera (images with the same size and focal prior; priors: "
        "principal point sigma 1 % of the width, aspect sigma 0.01 around 1; with an aspect the focal prior holds "
        "the mean focal (fx + fy) / 2), solved with exact Schur-complement steps. The principal points and the "
        "aspects each stay refined only when their offsets are significant (Wald statistic > 9 per parameter; else "
        "the release is redone without them), and the release is kept only when significant (drop in squared error "
        "> 9 noise variances per added parameter); otherwise the fixed-anchor solution stays (the synthetic site: "
        "no anchor observes 300 points). 'release: square pixels' is the default with the aspect held at 1 "
        "(release_aspect=False). 'paper: anchors fixed, anchor k1 = 0' keeps anchors fixed to the end and solves "
        "anchors without distortion (release_anchors=False, anchor_distortion=False). 'pp refined' refines the "
        "shared principal points in every adjustment (--refine-principal-point); 'anchors free' lets anchor poses "
        "move in every adjustment (--free-anchors).",
        "fountain-P11 centre distance, cause: the ground-truth camera has its principal point (-15, -17) px off "
        "centre and non-square pixels (fy/fx = 1.0017). Under a centred, square-pixel model an anchor's pose solved "
        "from 12 clicks absorbs both as a pose error of centimetres that a fixed anchor hands on to every image "
        "registered from it. The final release finds the shared principal point at (-15, -19) px (Wald ~650 for 2 "
        "parameters) and fy/fx = 1.0027 (Wald ~90 for 1; temple: (-14, 4) px for a true (-17, 7), fy/fx = 1.0030 "
        "for a true 1.0036). Diagnosis (not in the table, same code): with noise-free clicks the default gives "
        "3.9 mm (0.041 %; 3.4 mm after the ground-truth similarity), square pixels 12.8 mm, so the camera model now "
        "fits and what remains is the noise of the 24 clicks (1 px) that carry the gauge and, with it, the aspect "
        "(the cameras turn about one axis, so the features hardly constrain fy/fx). Figures in this note and in "
        "the 'Tried' note were measured before the current click seeding and second-anchor rule (second anchor "
        "0001.jpg; six draws, seed offsets 0, 1, 2, 100, 200, 300 of the earlier per-image seeding): the default "
        "gave 10.1, 9.0, 8.3, 7.0, 6.2, 6.3 mm (mean 7.8), square pixels mean 11.4 mm. pycolmap's figures are "
        "after a similarity fitted to the ground-truth centres, ours are in the frame the clicks give ('after "
        "sim.' applies that similarity to ours too). With ground-truth poses and intrinsics, the similarity that "
        "best fits the 24 clicks alone is "
        "already 4.3 mm off (the floor this gauge allows); with the ground-truth poses but our intrinsics it is "
        "8.2 mm, with our principal point and the true focal 5.8 mm, with the true principal point and our focal "
        "(0.1 % below the truth) 9.7 mm: the focal, which the narrow ring of views hardly fixes, carries most of "
        "what is left. One shared focal and k1, k2 per camera in the release (release_shared_intrinsics, "
        "likelihood-ratio test) was tried: mean over the six draws 7.98 mm vs 7.81 mm per image, so it is off "
        "(pycolmap's own focals spread 2750-2777 px over the 11 images; its ground-truth similarity absorbs that). "
        "The final adjustment uses every triangulated point (the incremental ones the 400 longest tracks "
        "per image): mean over the six draws 8.8 -> 7.8 mm, ~1 s more on fountain, nothing on temple (fewer "
        "points than the cap).",
        "Synthetic site centre distance, cause: 15 of 23 photos come from three fixed cameras ~40 m from the "
        "building; their anchors' 9-12 clicks lie in the central ~40 % of the frame, so focal and distance trade "
        "off (EXIF focal 1.4 % below the truth) and the anchor poses are 0.4-0.8 m off along the view; their "
        "tracks are too few (0-250 triangulated points per anchor) to correct them, so they are not released, "
        "and the homography-registered photos of each fixed camera inherit their anchor's error. Tying those "
        "photos to their anchor's centre (MapperConfig.homography_shares_centre) is off by default: the east camera "
        "moved 0.56 m and turned 7 deg on 2026-03-12 and still passes the rotation-homography test.",
        "Speed (temple): matching's mutual check by column maxima instead of a column argmax, RANSAC iterations "
        "bounded by what the minimum inlier count needs (non-overlapping pairs: ~100 instead of 10000), candidate "
        "search on 64 principal components of RootSIFT with the ratio test on exact similarities (99.6 % of the "
        "exact verified matches on temple and fountain, 97 % on the synthetic site), vectorised bundle-problem "
        "assembly and triangulation (after a PnP only the new image's and the window's tracks), local "
        "adjustments of 5 images x 5 evaluations, EXIF read without decoding PNG pixels. The final release costs "
        "~0.3 s on temple (one Schur-complement adjustment over all points). The PCA basis comes from the "
        "eigenvectors of the (128, 128) Gram matrix of a 20000-descriptor sample (0.25 s -> ~0.01 s). Exact "
        "Schur-complement steps for the incremental adjustments too (MapperConfig.ba_solver='schur') were tried: "
        "temple 4.0 vs 4.6 s with the same errors, but on the default synthetic site the west camera's photos "
        "drifted 5 deg (mean 1.05 vs 0.24 deg), so the incremental adjustments keep the trust-region solver. "
        "Temple over 5 interleaved runs (--quick --runs 5): ours 3.96 s vs pycolmap 4.73 s (0.84).",
        "Tried on fountain-P11, not adopted: (1) carrying each anchor click into the other registered photos (local "
        "affine fit to the matches around it, then ECC patch alignment) so the clicked points are triangulated from a"
        " wide baseline: temple improves (centre 0.39 -> 0.33 %, angle 0.294 -> 0.276 deg), the synthetic site is "
        "unchanged (its anchors are not released), fountain gets worse (mean over the six draws 7.8 -> 8.2 mm, the "
        "table's draw 10.1 -> 14.0 mm): on the sculpted fountain the carried pixels are 2-5 px off at wide baselines,"
        " above the clicks' 1 px. With carried pixels taken from the truth instead (a diagnosis only: true projection"
        " + N(0, 1 px)), the mean would be 4.6 mm. (2) OpenCV SIFT without precise upscaling puts every keypoint "
        "+0.25 px (detection pixels) off in both axes (measured: a point-mirrored image's keypoints disagree by 0.5 "
        "px; 0.00 px with enable_precise_upscale); removing that bias changed fountain to angle 0.061 -> 0.055 deg "
        "and reprojection 0.044 -> 0.039 % (six-draw means) but centre 7.8 -> 8.6 mm, temple 0.39 -> 0.45 %, the "
        "synthetic site 1.17 -> 1.54 %: within the click noise or worse, so the default detector stays. (3) Down-"
        "weighting clicks against features (0.5, 0.25, 0.05): centre mean 7.5, 7.4, 7.35 mm but the angle doubles "
        "(0.17 deg at 0.05). The maximum-likelihood weight (the features' noise over the clicks': 0.58 px / 1 px) "
        "gives centre 7.56 mm, angle 0.061 -> 0.090 deg, reprojection 0.044 -> 0.047 % (six-draw means): the "
        "features carry errors beyond their noise that the clicks' weight keeps in check.",
        "Second anchor (MapperConfig.anchor_request_min_shared_matches): at the start every image ties at zero matched "
        "tracks, and the paper's rule (the fewest) does not say which to ask; the collection order gave "
        "fountain-P11's 0001.jpg, 9 deg from the first anchor. Now the image with the most verified matches x sin^2 "
        "of the relative rotation to a registered image is asked (0005.jpg, 47 deg; temple and the synthetic site "
        "get the same anchors as before). fountain-P11 over 18 click-noise draws (draws 0-17, features at 1600 px; "
        "`python bench/registration.py --sets fountain --runs 18 --variants 'default,collection order'` at commit "
        "c4fc556): this rule 6.81 mm (0.073 %, draws 4.2-11.8 mm), 0.059 deg, reprojection 0.019 % against the "
        "collection order's 8.26 mm (0.085 %), 0.062 deg, 0.058 % and pycolmap's 7.16 mm (0.076 %), 0.388 deg, "
        "0.372 %; predicted centre sigma 5.5 vs 9.2 mm. (At 1600 px the standard error of the 18-draw mean, 0.46 "
        "mm, exceeded the gap to pycolmap; see 'Detection size' for the figures at full resolution.) Second anchor "
        "fixed by hand (earlier seeding, six draws each): 0002 6.4 mm, 0003 5.4, 0004 6.7, 0005 6.4, 0006 5.8, 0007 "
        "6.6 mm. Breaking later ties (templeSparseRing's third request) the same way cost 0.2 mm over 18 temple "
        "draws, so they keep collection order.",
        "What the clicks allow (the predicted-sigma columns): the final adjustment's camera-centre covariance "
        "(sandwich estimate, the features' and the clicks' noise each estimated from their own residuals; on a "
        "seeded synthetic scene its mean |error|^2 / trace over 150 noise draws is 1.01) says how well 24 clicks "
        "of 1 px and the features fix each centre: fountain-P11 5.6 mm mean over the six draws against an actual "
        "6.1 mm (error / sigma RMS 1.17; 7.4 mm and 1.42 with features detected at 1600 px), temple 1.8 vs 2.5 mm "
        "(1.49). The excess is input noise the covariance "
        "does not model: it takes the clicked model points as exact, while the simulated ones are triangulated "
        "from the ground-truth cameras over the nearest view (fountain: 1.6 m baseline at ~9 m, 0.5 px matches: "
        "~9 mm median depth error per point, 6-18 mm for 80 % of them); with ground-truth poses and intrinsics the "
        "24 clicks alone already put the frame 4.3 mm off. So the fountain centre figure is what this input "
        "allows, not a defect of the solve; pycolmap's 7.0 mm has no such term (its similarity is fitted to the 11 "
        "ground-truth centres it is scored on), and under that same similarity ours is 2.6 mm. A BIM's points "
        "are exact in the model, but real sites differ from their model by centimetres, so real clicks carry "
        "such errors too.",
        "'accuracy target 5 mm' (MapperConfig(target_centre_sigma=0.005), batch --target-centre-sigma): after the "
        "release, while some centre's predicted sigma exceeds 5 mm the least certain image without clicks is "
        "clicked too (here from the anchor file, as a user answering the request would; at most 4) and the final "
        "adjustment redone. fountain-P11: 2-4 more photos clicked over the six draws (4-6 anchors), centre 5.4 mm "
        "(0.056 %), angle 0.039 deg, reprojection 0.015 % against pycolmap's 7.0 mm, 0.38 deg, 0.37 %. Temple "
        "(sigma 1.8 mm) and the synthetic site (anchors not released) are unchanged.",
        "Detection size: both methods detect SIFT on fountain-P11 at full resolution (3072 px; our default --max-side "
        "3200 = pycolmap's default max_image_size); ours keeps the 4000 strongest features per image (SIFT contrast "
        "threshold 0.01), pycolmap its default 8192. Until 2026-12-02 both detected at 1600 px (then our default): "
        "over click draws 0-5 our centre error went 7.40 -> 6.13 mm with full resolution (after the ground-truth "
        "similarity 3.14 -> 2.6 mm), while pycolmap stays at 7.0-7.1 mm (one run each way: 7.1 mm at 1600 px, 7.03 mm "
        "at full resolution); ours takes ~2x the time (~19 s). Over 36 draws at full resolution (draws 0-35; section "
        "'registration (selected draws, sets or variants)' below, `python bench/registration.py --sets fountain "
        "--runs 36 --variants default`): ours 5.81 mm (0.062 %, standard error 0.28 mm, draws 3.5-9.7 mm, median 5.5 "
        "mm, below pycolmap in 26 of 36; draws 0-17 alone 6.29 mm), 0.050 deg, reprojection 0.018 % against "
        "pycolmap's 6.99 mm (0.074 %), 0.38 deg, 0.37 %. Keeping 8000 features at full resolution: 6.48 mm, ~28 s, so "
        "4000 stay. One shared focal and k1, k2 per camera in the release (release_shared_intrinsics) at full "
        "resolution, draws 0-5: 6.01 mm, 0.049 deg (2.25 mm after the similarity): within the noise of the default's "
        "6.13 mm, so it stays off. The figures of the 'fountain-P11 centre distance', 'Tried' and 'Second anchor' "
        "notes were measured at 1600 px.",
    ]


def _by_model(r: dict) -> str:
    """' (+N by the model)' when fixed cameras were anchored by the model search, else ''."""
    n = r.get("model_anchors", "0")
    return "" if n in ("0", 0, None) else f" (+{n} by the model)"
