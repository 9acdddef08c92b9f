"""Model-assisted structure from motion (paper Sec. 6, Algorithm 1), pure core.

The state is a :class:`Reconstruction`: images (features, camera, status), pairwise verified matches, tracks
(``track_obs[t]`` maps image index -> feature index) and their triangulated points in the model frame. Images can
be added one at a time (:func:`add_image`, :func:`match_image`, :func:`link_image_tracks`,
:func:`register_image_pnp`, :func:`triangulate_tracks`, :func:`bundle`), which is what the streaming node
does; :func:`reconstruct` runs the whole batch algorithm:

1. the first anchor image is solved from its clicks (:mod:`nodes.register.anchors`);
2. features are matched over the collection (exhaustive, or a bag-of-words shortlist for large sets) and
   pruned by a fundamental matrix (RANSAC); matches are chained into tracks;
3. images whose matches to an anchor are >= 80 % inliers of one homography receive the warped clicks and are
   solved by PnP;
4. constrained bundle adjustment (:mod:`nodes.register.bundle`) after each addition: anchor poses fixed,
   points seen by an anchor parameterised by depth along its ray, rays closer than 2 degrees not triangulated;
5. next image: among unregistered images with >= 60 matches to triangulated tracks, the one with the fewest,
   solved by PnP-RANSAC (inliers within 1 % of the width) refined with the paper's epipolar term;
6. when none qualifies, the image with the fewest matched tracks needs anchor clicks (``request_anchor``);
7. finally, the anchors that observe enough triangulated points are released (held by their clicks) and one
   principal point and one pixel aspect ratio per camera are refined, each kept only when significant
   (:func:`release_anchors_if_significant`); that adjustment also gives each camera centre's standard
   deviation, and with an accuracy target the least certain images are clicked too
   (:func:`add_clicks_for_accuracy`).

Pixels: OpenCV convention. Poses: ``world_from_camera`` (4, 4), OpenCV camera frame, model units.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import msgspec

from constructaide.anchorsolve import DegenerateAnchors
from nodes.register.adjust import (
    ANCHOR_RELEASE_THRESHOLD,
    add_clicks_for_accuracy,
    bundle,
    release_anchors_if_significant,
)
from nodes.register.config import MapperConfig
from nodes.register.features import (
    pca_basis,
    project_pca,
)
from nodes.register.mapper import (
    PoseCheck,
    anchor_request_order,
    bootstrap_next,
    click_disagreement_px,
    frame_anchor_order,
    implausible,
    prune_observations,
    register_anchor,
    register_image_pnp,
    try_homography_transfer,
    try_relative_pose,
)
from nodes.register.matching import select_pairs, verify_pair
from nodes.register.recon import (
    Clicks,
    PairGeometry,
    Reconstruction,
    build_tracks,
    image_tracks,
    local_window,
    matched_track_count,
)
from nodes.register.schur import single_thread_blas
from nodes.register.triangulation import triangulate_tracks


def reconstruct(
    recon: Reconstruction,
    anchors: dict[str, Clicks],
    cfg: MapperConfig,
    request_anchor: Callable[[str, str, int], Clicks | None] | None = None,
    progress: Callable[[str, int], None] | None = None,
    match_progress: Callable[[], None] | None = None,
    by_model: Callable[[int], tuple[Clicks | None, str]] | None = None,
    check: PoseCheck | None = None,
    by_phone: Callable[[int], tuple[Clicks | None, str]] | None = None,
) -> Reconstruction:
    """Run Algorithm 1 on a reconstruction whose images were added with :func:`add_image`.

    ``anchors``: clicks by image name; the first one (or all with ``cfg.use_all_anchors``) starts the
    reconstruction, the others are used when an image needs an anchor. ``request_anchor(name, reason,
    num_tracks)`` may supply clicks for other images (None: the image stays unregistered for now); every request
    is also recorded in ``recon.needs_anchor``. ``progress(stage, registered_count)`` is called after each step.
    ``by_model(index)``: model-point clicks for a fixed camera's frame found by the model's outlines (or None and
    why not); before a request for one of a fixed camera's frames, its latest unregistered frame is searched once.
    ``check``: the last word on each automatic PnP or relative pose (``mapper.PoseCheck``). ``by_phone(index)``:
    the same for a phone photo (:func:`nodes.register.phonesearch.phone_anchor`, confirmed by its matches with the
    registered photos as they stand), searched once before its first request.
    """
    t_start = time.perf_counter()
    names = [im.name for im in recon.images]
    unknown = [n for n in anchors if n not in names]
    if unknown:
        raise ValueError(f"anchor clicks for images not in the collection: {', '.join(unknown[:5])}")
    if not anchors:
        raise ValueError("at least one anchor image with clicks is needed")
    pending = dict(anchors)

    # Matching.
    t0 = time.perf_counter()
    if not recon.pairs:
        feats = [im.features for im in recon.images]
        pairs = select_pairs(feats, cfg)
        if cfg.match_pca_dims and cfg.match_pca_dims < 128:
            basis = pca_basis([f.descriptors for f in feats], cfg.match_pca_dims)
            feats = [project_pca(f, basis) for f in feats]

        def job(ij: tuple[int, int]) -> tuple[tuple[int, int], PairGeometry | None]:
            return ij, verify_pair(feats[ij[0]], feats[ij[1]], cfg)

        # Pairs run in parallel threads, each product on one BLAS thread (no oversubscription).
        with single_thread_blas(), ThreadPoolExecutor(max(1, cfg.workers)) as pool:
            for ij, g in pool.map(job, pairs):
                if g is not None:
                    recon.pairs[ij] = g
                if match_progress is not None:
                    match_progress()
    build_tracks(recon)
    recon.timings_secs["matching"] = time.perf_counter() - t0

    def note(stage: str) -> None:
        if progress is not None:
            progress(stage, len(recon.registered_indices()))

    def clicks_for(i: int, reason: str, num_tracks: int) -> Clicks | None:
        """Clicks for image ``i``: given up front (the anchor file's), else asked for (None: none to be had)."""
        name = recon.images[i].name
        clicks = pending.pop(name, None)
        if clicks is None and request_anchor is not None:
            clicks = request_anchor(name, reason, num_tracks)
        return clicks

    def recheck_with_clicks(u: int) -> bool:
        """Image ``u`` was just registered automatically: when clicks for it are at hand (given up front, not
        answers to requests) and the pose puts them further than ``click_check_max_frac`` of the width (median)
        from where they were clicked, re-register it from them (an anchor). Returns True when it was."""
        im = recon.images[u]
        if not cfg.check_auto_with_clicks or im.name not in pending:
            return False
        err = click_disagreement_px(im, pending[im.name])
        disagrees = err > cfg.click_check_max_frac * im.width_px
        was = f"{im.method} pose ({im.message}) put its clicks {err:.0f} px off (median)"
        clicks = pending.pop(im.name)
        kept = (im.status, im.method, im.world_from_camera, im.intrinsics, im.clicks, im.click_inliers, im.message)
        im.centre_source = None
        try:
            register_anchor(recon, u, clicks, cfg)
        except DegenerateAnchors as e:
            if disagrees:
                im.status, im.method, im.world_from_camera = "failed", "", None
                im.message = f"{was}; its anchor clicks were rejected: {e}"
            else:  # the automatic pose stands
                im.status, im.method, im.world_from_camera, im.intrinsics, im.clicks, im.click_inliers = kept[:6]
                im.message = f"{kept[6]}; its up-front clicks were rejected: {e}"
            return True
        if disagrees:
            im.message += f"; re-registered from its clicks: the automatic {was}"
            note(f"anchor {im.name} (automatic pose disagreed with its clicks)")
        else:
            im.message += f"; anchored by its up-front clicks (the automatic {was})"
            note(f"anchor {im.name} (up-front clicks)")
        return True

    # Initial anchors.
    first = list(pending)[: (len(pending) if cfg.use_all_anchors else 1)]
    for name in first:
        given = pending.pop(name)
        idx = recon.index(name)
        try:
            register_anchor(recon, idx, given, cfg)
        except DegenerateAnchors as e:
            recon.images[idx].status, recon.images[idx].message = "failed", f"anchor clicks rejected: {e}"
        note(f"anchor {name}")
    t_reg = time.perf_counter()
    checked_h: set[tuple[int, int]] = set()
    failed_pnp: set[int] = set()
    dirty = True  # something was added since the last full bundle adjustment
    pruned: set[int] = set()  # registered images detached from the tracks their camera does not explain
    since_full = 0

    searched: set[str] = set()  # fixed cameras searched by the model
    phone_searched: dict[str, frozenset[str | None]] = {}  # phone photo -> the fixed cameras registered then
    not_found: dict[int, str] = {}  # why the model did not find an image's camera

    def model_anchor(u: int) -> bool:
        """Anchor the latest unregistered frame of ``u``'s fixed camera by the model, once per camera; a phone
        photo ``u`` itself, again only when more fixed cameras are registered than at its last search."""
        nonlocal dirty
        cid = recon.images[u].camera_id
        if cid is None:  # a phone photo: itself, again only once more fixed cameras carry texture to it
            fixed = frozenset(recon.images[j].camera_id for j in recon.registered_indices()) - {None}
            name = recon.images[u].name
            last = phone_searched.get(name)
            if by_phone is None or not cfg.phone_search or (last is not None and not fixed > last):
                return False
            phone_searched[name] = fixed
            v = u
            clicks, why = by_phone(v)
        else:
            if by_model is None or not cfg.model_search or cid in searched:
                return False
            searched.add(cid)
            frames = [i for i, im in enumerate(recon.images) if im.camera_id == cid and im.status == "unregistered"]
            v = max(frames, key=lambda i: (recon.images[i].capture_time_ns, recon.images[i].name))
            clicks, why = by_model(v)
        if clicks is None:
            not_found[v] = why
            return False
        try:
            register_anchor(recon, v, clicks, cfg)
        except DegenerateAnchors:
            return False
        im = recon.images[v]
        im.method, im.message = "model", f"found by the model's outlines ({why}); {im.message}"
        failed_pnp.clear()
        dirty = True
        note(f"model {im.name}")
        return True

    def ask_anchor(candidates: list[int]) -> bool:
        """Ask for clicks on ``candidates`` in turn (each request recorded); True once one is anchored. First the
        model searches them (:func:`model_anchor`): every fixed camera's frame, then the phone photos (found on the
        texture the fixed cameras registered by then carry), and only then is a person asked."""
        nonlocal dirty
        for u in sorted(candidates, key=lambda i: recon.images[i].camera_id is None):  # stable: fixed cameras first
            if model_anchor(u):
                return True
        for u in candidates:
            name = recon.images[u].name
            reason = f"only {counts[u]} matches to triangulated tracks (< {cfg.min_track_matches})"
            if u in failed_pnp and recon.images[u].message:
                reason = recon.images[u].message.removeprefix("needs anchor clicks: ")
            if u in not_found and "the model:" not in reason:
                reason += f"; not found by the model: {not_found[u]}"
            recon.needs_anchor = [r for r in recon.needs_anchor if r[0] != name] + [(name, reason, counts[u])]
            clicks = clicks_for(u, reason, counts[u])
            if clicks is None:
                recon.images[u].message = f"needs anchor clicks: {reason}"
                continue
            try:
                register_anchor(recon, u, clicks, cfg)
            except DegenerateAnchors as e:
                recon.images[u].status, recon.images[u].message = "failed", f"anchor clicks rejected: {e}"
                continue
            failed_pnp.clear()
            dirty = True
            note(f"anchor {name}")
            return True
        return False

    while True:
        # Homography transfer from every clicked image to unregistered images.
        added = True
        while added:
            added = False
            sources = sorted(recon.registered_indices(), key=lambda i: recon.images[i].status != "anchor")
            for a in sources:
                for u in [i for i, im in enumerate(recon.images) if im.status == "unregistered"]:
                    if (a, u) in checked_h:
                        continue
                    checked_h.add((a, u))
                    if try_homography_transfer(recon, a, u, cfg):
                        added = dirty = True
                        if not recheck_with_clicks(u):
                            note(f"homography {recon.images[u].name}")
        if dirty:
            for i in recon.registered_indices():
                if i not in pruned:
                    prune_observations(recon, i, cfg)
                    pruned.add(i)
            triangulate_tracks(recon, cfg)
            bundle(recon, cfg)
            triangulate_tracks(recon, cfg)
            dirty, since_full = False, 0
        unreg = [i for i, im in enumerate(recon.images) if im.status == "unregistered"]
        if not unreg:
            break
        counts = {i: matched_track_count(recon, i) for i in unreg}
        for i, c in counts.items():
            recon.images[i].num_matched_tracks = c
        candidates = [i for i in unreg if i not in failed_pnp]
        qualified = [i for i in candidates if counts[i] >= cfg.min_track_matches]
        if qualified:
            # The paper's rule: the qualifying image with the fewest matched tracks (wide baseline).
            u = min(qualified, key=lambda i: counts[i])
        else:
            # Before asking for clicks, try the best-connected image above a lower bar (PnP still has to succeed).
            weak = [i for i in candidates if counts[i] >= cfg.fallback_min_track_matches]
            u = max(weak, key=lambda i: counts[i]) if weak else -1
        if u >= 0:
            if register_image_pnp(recon, u, cfg, check):
                failed_pnp.clear()
                if recheck_with_clicks(u):
                    dirty = True
                    continue
                # Only tracks through the new image can have become triangulable.
                triangulate_tracks(recon, cfg, only=image_tracks(recon, [u]))
                since_full += 1
                if since_full >= cfg.full_ba_every:
                    bundle(recon, cfg)
                    since_full = 0
                    triangulate_tracks(recon, cfg)
                else:
                    local_cfg = msgspec.structs.replace(cfg, ba_max_nfev=cfg.local_ba_max_nfev)
                    window = local_window(recon, u, cfg.local_ba_window)
                    bundle(recon, local_cfg, window=window)
                    triangulate_tracks(recon, cfg, only=image_tracks(recon, window))
                note(f"pnp {recon.images[u].name}")
            else:
                failed_pnp.add(u)
            continue
        # No image has enough tracks. While the frame rests on fewer than min_anchors photos' clicks, the widest
        # view is asked for clicks first (a second anchor fixes the frame better than any bootstrap); otherwise,
        # or unanswered, the relative-pose bootstrap; then anchors are asked for, fewest matched tracks first.
        order = anchor_request_order(recon, unreg, counts, cfg)
        n_anchors = sum(1 for im in recon.images if im.status == "anchor")
        widest = order[:1] if n_anchors < cfg.min_anchors and request_anchor is not None else []
        got = ask_anchor(widest)
        if not got and cfg.bootstrap:
            b = bootstrap_next(recon, unreg, cfg, check)
            if b >= 0:
                failed_pnp.clear()
                dirty = True
                if not recheck_with_clicks(b):
                    note(f"relative pose {recon.images[b].name}")
                continue
        got = got or ask_anchor([u for u in order if u not in widest])
        if not got:
            break
    if since_full:
        bundle(recon, cfg)
    # A model frame resting on fewer than min_anchors photos' clicks: one more is asked for, where it fixes the frame
    # best (unanswered, nothing changes: the one-anchor registration stands).
    anchored = [i for i in recon.registered_indices() if recon.images[i].status == "anchor"]
    if anchored and len(anchored) < cfg.min_anchors:
        for i in frame_anchor_order(recon, anchored)[:1]:
            reason = f"accuracy: the model frame rests on {len(anchored)} photo's clicks; clicks here fix it better"
            recon.needs_anchor = [r for r in recon.needs_anchor if r[0] != recon.images[i].name]
            recon.needs_anchor.append((recon.images[i].name, reason, matched_track_count(recon, i)))
            extra = clicks_for(i, reason, matched_track_count(recon, i))
            if extra is None:
                continue
            im = recon.images[i]
            kept = (im.status, im.method, im.world_from_camera, im.intrinsics, im.clicks, im.click_inliers, im.message)
            try:
                register_anchor(recon, i, extra, cfg)
            except DegenerateAnchors as e:
                im.status, im.method, im.world_from_camera, im.intrinsics, im.clicks, im.click_inliers = kept[:6]
                im.message = f"{kept[6]}; its accuracy clicks were rejected: {e}"
                continue
            im.message += "; clicked for accuracy (second anchor)"
            note(f"anchor {im.name} (accuracy)")
            prune_observations(recon, i, cfg)
            bundle(recon, cfg)
            triangulate_tracks(recon, cfg)
    if cfg.fix_anchor_poses and cfg.release_anchors:
        recon.anchor_release_score = release_anchors_if_significant(recon, cfg)
        recon.anchors_released = bool(recon.anchor_release_score > ANCHOR_RELEASE_THRESHOLD)
        recon.accuracy_anchors, unmet = add_clicks_for_accuracy(
            recon, cfg, lambda i, reason: clicks_for(i, reason, matched_track_count(recon, i))
        )
        for name in recon.accuracy_anchors:
            note(f"anchor {name} (accuracy)")
        if unmet is not None:
            name = recon.images[unmet[0]].name
            n = matched_track_count(recon, unmet[0])
            recon.needs_anchor = [r for r in recon.needs_anchor if r[0] != name] + [(name, unmet[1], n)]
    for im in recon.images:  # a camera the adjustments could not make plausible is not reported as registered
        why = implausible(im, cfg) if im.registered else ""
        if why:
            im.status, im.message = "failed", f"implausible registration ({im.method}): {why}"
    for i, im in enumerate(recon.images):
        if im.status == "unregistered" and i in failed_pnp and not im.message.startswith("needs"):
            im.message = "PnP failed: " + im.message
    recon.timings_secs["registration"] = time.perf_counter() - t_reg
    recon.timings_secs["total"] = time.perf_counter() - t_start
    return recon


def register_one(
    recon: Reconstruction, idx: int, cfg: MapperConfig, matched_with: int = 0, check: PoseCheck | None = None
) -> str:
    """Register image ``idx`` of a growing map (the streaming path) by the mapper's steps against its verified
    partners, most matches first: homography transfer, PnP on tracks, relative pose to the best four. Returns ""
    on success, else why not (``matched_with``: how many registered photos it was matched with, for the message;
    ``check``: the last word on a PnP or relative pose).
    """
    r = recon
    partners = sorted(
        (j for j in r.registered_indices() if j != idx and r.pair(j, idx) is not None),
        key=lambda j: -len(r.pair(j, idx)[0]),  # type: ignore[index]
    )
    if not partners:
        return (
            f"no verified geometry connects it to the {len(r.registered_indices())} registered photos "
            f"(matched with {matched_with})"
        )
    notes: list[str] = []
    im = r.images[idx]
    for j in partners:
        im.message = ""
        if try_homography_transfer(r, j, idx, cfg):
            return ""
        if "refused" in im.message and im.message not in notes:
            notes.append(im.message)
    if register_image_pnp(r, idx, cfg, check):
        return ""
    notes.append(r.images[idx].message)
    for j in partners[:4]:
        if try_relative_pose(r, j, idx, cfg, check):
            return ""
        if r.images[idx].message and r.images[idx].message not in notes:
            notes.append(r.images[idx].message)
    names = ", ".join(r.images[j].name for j in partners[:3])
    return f"matched {len(partners)} registered photo(s) ({names}) but {'; '.join(n for n in notes if n)}"
