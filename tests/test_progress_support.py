"""What rests on what: the support graph from boxes and schedule, and the fusion's support coupling."""

from __future__ import annotations

import numpy as np
import pytest

from constructaide.schedule4d import ElementWindow
from nodes.progress.fusion import NS_PER_DAY, ElementTrack, FusionParams, Observation, coupled, estimate
from nodes.progress.support import dependants_of, support_graph

D = NS_PER_DAY
SPAN = (0, 20 * D)


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(lo, float), np.array(hi, float)


def w(start_day: float, finish_day: float) -> ElementWindow:
    return ElementWindow(build_start_ns=int(start_day * D), build_finish_ns=int(finish_day * D))


def test_support_graph_from_boxes_and_schedule() -> None:
    boxes = {
        "slab": box((-6, -6, -0.3), (6, 6, 0.0)),
        "col_a": box((-6, -0.2, 0.0), (-5.6, 0.2, 3.0)),
        "col_b": box((5.6, -0.2, 0.0), (6, 0.2, 3.0)),
        "beam": box((-5.6, -0.15, 2.5), (5.6, 0.15, 3.0)),  # framed into the columns' sides at their top
        "wall": box((-5.6, 2.0, 0.0), (5.6, 2.2, 2.4)),  # on the slab, beside nothing else
        "late_wall": box((-5.6, 3.0, 0.0), (5.6, 3.2, 2.4)),  # on the slab but planned before it: no edge
        "far": box((20, 20, 0.0), (21, 21, 3.0)),  # touches nothing
    }
    windows = {
        "slab": w(1, 2),
        "col_a": w(3, 4),
        "col_b": w(3, 4),
        "beam": w(5, 6),
        "wall": w(5, 7),
        "late_wall": w(0, 1),
        "far": w(3, 4),
    }
    g = support_graph(boxes, windows)
    assert set(g["beam"]) == {"col_a", "col_b"}  # not the slab: the beam does not touch it
    assert g["col_a"] == ("slab",) and g["col_b"] == ("slab",) and g["wall"] == ("slab",)
    assert "late_wall" not in g and "far" not in g and "slab" not in g
    assert set(dependants_of(g)["slab"]) == {"col_a", "col_b", "wall"}
    # an element of the same task (same window) as the one under it is not ordered by the plan: no edge
    same = dict(windows, beam=w(3, 4))
    assert "beam" not in support_graph(boxes, same)
    # removed (temporary) elements carry nothing in the graph
    temp = dict(windows, slab=ElementWindow(build_finish_ns=2 * D, remove_start_ns=9 * D, remove_finish_ns=10 * D))
    assert "col_a" not in support_graph(boxes, temp)


def daily(change_day: int, days: range, strength: float) -> list[Observation]:
    return [
        Observation(f"p{d}", d * D, llr_change=strength if d == change_day else -strength, reference_ns=(d - 1) * D)
        for d in days
    ]


def track(window: ElementWindow, obs: list[Observation]) -> ElementTrack:
    tr = ElementTrack("e", window, SPAN)
    for o in obs:
        tr.add(o)
    return tr


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_element_is_not_believed_up_before_what_carries_it(seed: int) -> None:
    """A beam with moderate evidence of appearing early (a change through what stood behind it) is moved after its
    columns, which were seen clearly appearing later; alone it stays early."""
    rng = np.random.default_rng(seed)
    params = FusionParams(fit_slip=False)
    days = range(1, 16)
    early = int(rng.integers(3, 6))
    cols = [track(w(8, 9), daily(int(rng.integers(9, 11)), days, 6.0)) for _ in range(2)]
    # one false change (what stood behind it appeared), then looks that neither prove nor deny it
    beam = track(
        w(9, 11),
        [Observation("c", early * D, llr_change=4.0, reference_ns=(early - 1) * D)]
        + [Observation(f"p{d}", d * D, llr_state=0.2) for d in days if d > early],
    )
    own = beam.posterior(params)
    both = coupled(own, [c.posterior(params) for c in cols], [], 0.05, 0.05)
    t_cols = max(c.posterior(params).median_change(0)[2] for c in cols)
    assert own.median_change(0)[2] <= early * D  # alone: up on the day of the false change
    assert both.median_change(0)[2] >= t_cols - D / 2  # coupled: not before its columns
    assert estimate(beam, both, 15 * D, params).deviation == "on_time"
    # the other way: a slab whose own looks weakly say absent, under columns seen standing, is believed standing
    slab = track(w(1, 2), [Observation(f"q{d}", d * D, llr_state=-0.3) for d in days])
    carried = [track(w(3, 4), [Observation(f"q{d}", d * D, llr_state=3.0) for d in days]) for _ in range(3)]
    alone = slab.posterior(params)
    held = coupled(alone, [], [c.posterior(params) for c in carried], 0.05, 0.05)
    assert alone.present_at(15 * D) < 0.3 and held.present_at(15 * D) > 0.5
    # no neighbours, or a path other than construction: unchanged
    assert coupled(own, [], [], 0.05) is own
    demolished = track(ElementWindow(remove_start_ns=8 * D, remove_finish_ns=9 * D), daily(9, days, 3.0))
    post = demolished.posterior(params)
    assert coupled(post, [cols[0].posterior(params)], [], 0.05) is post


def test_present_curve_is_the_hypotheses_mass_changed_by_each_time() -> None:
    """At the grid's own times no interpolation is involved: P(standing at t) is the mass of the hypotheses whose
    change interval ends by t (construction), or has its appearance and not yet its removal (temporary)."""
    obs = daily(7, range(1, 16), 2.0) + [Observation("s", 9 * D + 1, llr_state=1.0)]
    post = track(w(8, 9), obs).posterior(FusionParams())
    g = np.concatenate([post.grid.astype(float), [np.inf]])
    ends = g[post.changes[:, 0]]
    ts = post.grid.astype(float)
    expected = [post.prob[ends <= t].sum() for t in ts]
    assert post.present_curve(ts) == pytest.approx(expected)
    assert post.present_curve([-np.inf, np.inf]) == pytest.approx([0.0, 1.0])
    assert [post.present_at(int(t)) for t in ts] == pytest.approx(expected)
    temp = track(ElementWindow(build_finish_ns=4 * D, remove_start_ns=14 * D, remove_finish_ns=15 * D), obs)
    tp = temp.posterior(FusionParams())
    up, down = g[tp.changes[:, 0]], g[tp.changes[:, 1]]
    expected = [tp.prob[(up <= t) & (down > t)].sum() for t in ts]
    assert tp.present_curve(ts) == pytest.approx(expected)


def test_engine_overrides_from_the_command_line() -> None:
    """`constructaide progress --set JSON`: experiments such as the support coupling run on the shipping engine."""
    from constructaide.errors import UserError
    from nodes.progress.batch import engine_params_from_json

    p = engine_params_from_json('{"support_floor": 0.05, "fusion": {"built_probability": 0.8}}', working_width_px=320)
    assert (p.support_floor, p.dependant_floor, p.fusion.built_probability, p.working_width_px) == (
        0.05,
        None,
        0.8,
        320,
    )
    assert engine_params_from_json('{"work_hours": [6, 15]}').work_hours == (6, 15)
    for bad, says in (
        ('{"nope": 1}', "unknown parameter nope"),
        ('{"fusion": {"x": 1}}', "unknown parameter fusion.x"),
        ('{"support_floor": "a"}', "support_floor must be a number or null"),
        ('{"unchanged_discount": 1}', "unchanged_discount must be like True"),
        ("[1]", "must be a JSON object"),
        ("{", "not JSON"),
    ):
        with pytest.raises(UserError, match=says):
            engine_params_from_json(bad)


def test_a_visits_looks_count_once() -> None:
    """Five photos of one phone visit that each read an element +1.2 say as much as one photo; grouped, they cannot
    outweigh one clear reading of another day on their own."""
    params = FusionParams(fit_slip=False)
    absent = Observation("fixed", 12 * D, llr_state=-2.0)
    visit = [Observation(f"v{k}", 5 * D + k * 600 * 10**9, llr_state=1.2) for k in range(5)]
    grouped = [Observation(o.photo_id, o.time_ns, llr_state=o.llr_state, group="visit:day5") for o in visit]
    apart = track(w(14, 15), [absent, *visit]).posterior(params)
    once = track(w(14, 15), [absent, *grouped]).posterior(params)
    single = track(w(14, 15), [absent, visit[0]]).posterior(params)
    assert apart.present_at(6 * D) > 0.7  # five independent looks win against the plan and the later reading
    assert once.present_at(6 * D) == pytest.approx(single.present_at(6 * D), rel=0.01)  # grid differs a little
    assert once.present_at(6 * D) < 0.3


def test_the_streaming_node_reads_with_the_engines_defaults() -> None:
    """The progress node (live dashboards) and `constructaide progress` (the bench's figures) read photos with the
    same parameters unless configured otherwise: the node's config defaults come from the engine's. (Until
    2026-12-06 the node kept a schedule weight of 0.5 after the engine's became 0.8.)"""
    import msgspec

    from nodes.progress.engine import EngineParams
    from nodes.progress.node import Config, engine_params

    assert engine_params(Config()) == EngineParams()
    cfg = msgspec.convert({"schedule_weight": 0.6, "working_scale": 0.0}, Config)
    p = engine_params(cfg)
    assert (p.fusion.schedule_weight, p.working_scale, p.fusion.proof_llr) == (
        0.6,
        0.0,
        EngineParams().fusion.proof_llr,
    )


def test_prior_cdf_at_one_time_is_the_vector_one() -> None:
    """The schedule prior's CDF at one time (plain floats, the fusion's hot path) equals the vectorised one."""
    from nodes.progress.fusion import NS_PER_DAY, _prior_cdf

    rng = np.random.default_rng(5)
    lo, hi = 0.0, 200 * NS_PER_DAY
    ts = np.concatenate([rng.uniform(-10, 210, 300) * NS_PER_DAY, [-np.inf, np.inf, lo, hi]])
    for window in (None, (50 * NS_PER_DAY, 50 * NS_PER_DAY), (60 * NS_PER_DAY, 64.5 * NS_PER_DAY)):
        for width in (NS_PER_DAY / 24, 1.5 * NS_PER_DAY):
            vec = _prior_cdf(ts, window, width, lo, hi, 0.8)
            one = np.array([_prior_cdf(np.array([t]), window, width, lo, hi, 0.8)[0] for t in ts])
            assert np.allclose(one, vec, rtol=1e-12, atol=1e-14)
            assert _prior_cdf(np.array(ts[0]), window, width, lo, hi, 0.8).shape == ()
