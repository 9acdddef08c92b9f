"""Option (off by default): a fixed camera's repeated missing outline of an element without a change cue counts once."""

from __future__ import annotations

import pytest

from constructaide.schedule4d import ElementWindow
from nodes.progress.engine import EngineParams, ProgressEngine
from nodes.progress.evidence import ElementCue
from nodes.progress.fusion import NS_PER_DAY, ElementTrack

D = NS_PER_DAY


def _engine(once: bool) -> ProgressEngine:
    eng = ProgressEngine(EngineParams(repeated_no_edge_once=once))
    eng.global_ids, eng.index_of = ["a"], {"a": 1}
    eng.tracks = {"a": ElementTrack("a", ElementWindow(build_start_ns=2 * D, build_finish_ns=3 * D), (0, 30 * D))}
    return eng


def _thin_cue(edge: float, appearance: float) -> ElementCue:
    """A thin element's cue: no interior pixels, so no change cue (no changed fraction, no reference time)."""
    cue = ElementCue(1, 60, 60, 0.0)
    cue.llr_edge, cue.llr_appearance = edge, appearance
    return cue


def test_a_repeated_missing_outline_of_a_thin_element_counts_once() -> None:
    """A thin element planned (and built) on days 2-3, seen by one fixed camera daily from day 5 on without an
    outline (it looks like what stands behind it): the first frame (no plate yet) counts its weak negative outline
    LLR, the nine repeats (with a plate) do not, so the element is not read 'not built'; counting every repeat, the
    missing outline adds up to 'not built' against the plan and a standing element."""
    est = {}
    for once in (True, False):
        eng = _engine(once)
        for d in range(5, 15):
            eng._observe(f"p{d}", d * D, [_thin_cue(-0.35, -0.05)], has_plate=d > 5)
        obs = sorted(eng.tracks["a"].observations.values(), key=lambda o: o.time_ns)
        assert obs[0].llr_state == pytest.approx(-0.40)
        assert all(o.llr_state == pytest.approx(-0.05 if once else -0.40) for o in obs[1:])
        est[once] = eng.estimate("a", 14 * D)
    assert est[True].state != "not_built" and est[True].deviation != "not_built"
    assert est[False].state == "not_built"


def test_a_found_outline_and_a_changed_look_still_count() -> None:
    """With a plate, a thin element's found outline counts in full (when it appears, the only state evidence it
    has), and an element with a change cue keeps its missing outline (the unchanged-look discount handles it)."""
    eng = _engine(True)
    eng._observe("p6", 6 * D, [_thin_cue(1.2, 0.1)], has_plate=True)
    assert eng.tracks["a"].observations["p6"].llr_state == pytest.approx(1.3)
    cue = ElementCue(1, 400, 400, 0.0, changed_fraction=0.9, reference_ns=5 * D)
    cue.llr_edge, cue.llr_appearance, cue.llr_change = -0.4, -0.1, 4.0
    eng._observe("p7", 7 * D, [cue], has_plate=True)
    assert eng.tracks["a"].observations["p7"].llr_state == pytest.approx(-0.5)
