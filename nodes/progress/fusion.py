"""Fusion of per-photo evidence into each element's state over time (pure core: numpy).

An element's state follows a fixed path over time: ``absent -> present`` for construction, ``present ->
absent`` for demolition, ``absent -> present -> absent`` for a temporary element. The unknowns are the times of
the changes; hypotheses place each change in one interval of the grid made of the element's observation times
(and the reference times of its transition evidence), so the posterior over change intervals is exact:

* a *state* observation (photo at ``t``, log-likelihood ratio ``llr_state`` of present vs absent) adds
  ``+llr/2`` to hypotheses under which the element is present at ``t`` and ``-llr/2`` otherwise;
* a *transition* observation (``llr_change`` over ``(ref, t]``: the element's pixels changed since the reference
  plate) adds ``llr`` to hypotheses with a change inside ``(ref, t]``;
* the prior of a change time is the schedule's (uniform over the planned window, blurred by a logistic slip)
  mixed with a flat prior over the whole project, so the evidence, not the plan, decides once there is any.

Times are int ns UTC. Monotone by construction: no hypothesis removes a constructed element unless a demolition
or temporary task says so.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from itertools import combinations_with_replacement
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from constructaide.schedule4d import ElementWindow

NS_PER_DAY = 86_400 * 10**9
Path = Literal["construction", "demolition", "temporary"]
Deviation = Literal["ahead", "on_time", "behind", "not_built", "unknown"]


@dataclass(frozen=True)
class FusionParams:
    schedule_weight: float = 0.8
    """Share of the prior that follows the schedule (the rest is flat over the project). With 0.5 the flat part
    (months of project for one week of photos) outweighed the plan wherever the photos were silent (an element built
    before a camera's first frame, a late one never seen changing)."""
    schedule_width_days: float = 1.5
    """Logistic scale of the slip around the planned window (the schedule prior is the window, uniform, blurred by
    this slip)."""
    margin_days: float = 30.0
    """The flat prior reaches this far before the first planned start and after the last planned finish."""
    finish_from_median: bool = True
    """The change interval and finish are the posterior median's (else the most probable interval's middle)."""
    finish_at_median: bool = True
    """The finish is the posterior median itself (inside its interval the evidence is flat and the change follows
    the prior: the slip learnt from the photos places it), else the working-time middle of its interval."""
    built_probability: float = 0.7
    """P(present) at or above which an element counts as built (at or below 1 - this: not built)."""
    tolerance_days: float = 0.0
    """Deviation tolerance around the planned window."""
    proof_llr: float = 1.0
    """A deviation also needs one photo that shows it by itself: absent (or seen appearing) after the planned
    finish for ``behind``, standing before the planned start for ``ahead``, with a log-likelihood ratio of at least
    this (0: the posterior alone decides). Many weak looks can outweigh a precise plan (an element-level schedule)
    without any of them showing the deviation; on six synthetic sites this halved the false ``ahead`` flags for a
    few of the true ones (BENCHMARKS 'progress notes')."""
    fit_slip: bool = True
    """Learn the slip scale of this site's schedule from the photos (:func:`fit_slip_days`) once enough elements
    were seen appearing; ``schedule_width_days`` until then."""
    fit_min_elements: int = 8
    """Elements seen appearing (a transition of at least ``fit_min_llr``) needed to learn the slip."""
    fit_min_llr: float = 3.0


@dataclass(frozen=True)
class Observation:
    """One photo's evidence on one element (see the module docstring)."""

    photo_id: str
    time_ns: int
    llr_state: float = 0.0
    llr_change: float = 0.0
    reference_ns: int = 0
    """Start of the transition interval; 0 = no transition evidence."""
    group: str = ""
    """Observations of one group (the photos of one phone visit) are one look: their ``llr_state`` counts divided by
    the group's size (the same light, the same clip, minutes apart: not independent evidence)."""


@dataclass(frozen=True)
class Posterior:
    """Posterior over change-interval hypotheses. ``grid`` (m,) sorted ns; interval ``i`` is
    ``(grid[i-1], grid[i]]`` with ``grid[-1] = -inf`` and ``grid[m] = +inf``. ``changes`` (H, k) interval index of
    each of the path's k changes per hypothesis, ``prob`` (H,)."""

    path: Path
    grid: NDArray[np.int64]
    changes: NDArray[np.int64]
    prob: NDArray[np.float64]
    cdfs: tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]], ...] = ()
    """Prior CDF of each change's time: places a change inside the interval that holds a query time."""

    def _bounds(self, i: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        g = np.concatenate([[-np.inf], self.grid.astype(np.float64), [np.inf]])
        return g[i], g[i + 1]

    @cached_property
    def _interval_cdfs(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(lo, hi, prior CDF at lo, prior CDF at hi), each (H, k): the hypotheses' change intervals (computed once
        per posterior; the queries below only evaluate the CDF at their own times)."""
        lo, hi = self._bounds(self.changes)
        f_lo, f_hi = np.zeros(lo.shape), np.zeros(hi.shape)
        for col, cdf in enumerate(self.cdfs):
            f_lo[:, col], f_hi[:, col] = cdf(lo[:, col]), cdf(hi[:, col])
        return lo, hi, f_lo, f_hi

    def present_at(self, t_ns: int) -> float:
        """P(the element stands at ``t_ns``); a change in the interval holding ``t`` is before ``t`` with its prior
        odds (evidence is the same anywhere inside an interval)."""
        return float(self.present_curve(np.array([float(t_ns)]))[0])

    def present_curve(self, t_ns: ArrayLike) -> NDArray[np.float64]:
        """:meth:`present_at` at each of the times ``t_ns`` (K,) ns (+-inf allowed) -> (K,)."""
        t = np.asarray(t_ns, np.float64).reshape(-1)
        lo, hi, f_los, f_his = self._interval_cdfs
        frac = np.full((*self.changes.shape, len(t)), 0.5)
        for col, cdf in enumerate(self.cdfs):
            f_lo, f_hi, f_t = f_los[:, col, None], f_his[:, col, None], cdf(t)[None, :]
            span = f_hi - f_lo
            frac[:, col] = np.where(span > 1e-12, np.clip((f_t - f_lo) / np.maximum(span, 1e-12), 0.0, 1.0), 0.5)
        done = np.where(hi[:, :, None] <= t, 1.0, np.where(lo[:, :, None] >= t, 0.0, frac))
        if self.path == "temporary":
            present = np.clip(done[:, 0] - done[:, 1], 0.0, 1.0)
        elif self.path == "demolition":
            present = 1.0 - done.sum(axis=1)
        else:
            present = done.sum(axis=1)
        return np.asarray(self.prob @ present, np.float64)

    def change_interval(self, which: int = 0) -> tuple[int | None, int | None, float]:
        """Most probable interval of change ``which``: (after_ns, by_ns, probability); ``None`` = unbounded."""
        idx = self.changes[:, which]
        mass = np.bincount(idx, weights=self.prob, minlength=len(self.grid) + 1)
        i = int(np.argmax(mass))
        lo = int(self.grid[i - 1]) if i > 0 else None
        hi = int(self.grid[i]) if i < len(self.grid) else None
        return lo, hi, float(mass[i])

    def median_change(self, which: int = 0) -> tuple[int | None, int | None, float, float]:
        """Posterior median time of change ``which`` (inside each hypothesis' interval the change follows its prior,
        as the evidence is the same anywhere there) and the grid interval holding it: (after_ns, by_ns, median_ns,
        probability of that interval); ``None`` = unbounded. Unlike the most probable interval it does not favour
        the wide open intervals before the first and after the last observation over the fine ones between."""
        los, his, f_los, f_his = self._interval_cdfs
        lo, hi, f_lo, f_hi = los[:, which], his[:, which], f_los[:, which], f_his[:, which]
        cdf = self.cdfs[which]
        span = np.maximum(f_hi - f_lo, 1e-300)

        def below(x: NDArray[np.float64]) -> NDArray[np.float64]:
            """P(change before each of the times ``x`` (K,))."""
            f_x = cdf(x)[None, :]
            xx = x[None, :]
            frac = np.where(
                hi[:, None] <= xx,
                1.0,
                np.where(lo[:, None] >= xx, 0.0, np.clip((f_x - f_lo[:, None]) / span[:, None], 0.0, 1.0)),
            )
            return np.asarray(self.prob @ frac, np.float64)

        g = self.grid.astype(np.float64)
        a = float(g[0]) - 400 * NS_PER_DAY if len(g) else -400.0 * NS_PER_DAY
        b = float(g[-1]) + 400 * NS_PER_DAY if len(g) else 400.0 * NS_PER_DAY
        while b - a > 1e9:  # bracket the median to a second: 64 sub-intervals per round
            xs = np.linspace(a, b, 65)
            k = int(np.clip(np.searchsorted(below(xs), 0.5, side="left"), 1, 64))
            a, b = float(xs[k - 1]), float(xs[k])
        t = int(0.5 * (a + b))
        i = int(np.searchsorted(self.grid, t, side="left"))  # interval (grid[i-1], grid[i]] holds t
        mass = float(self.prob[self.changes[:, which] == i].sum())
        after = int(self.grid[i - 1]) if i > 0 else None
        by = int(self.grid[i]) if i < len(self.grid) else None
        return after, by, t, mass

    def change_mass(self, which: int, before_ns: float | None = None, after_ns: float | None = None) -> float:
        """Probability that change ``which`` lies in an interval wholly before ``before_ns`` (or wholly after
        ``after_ns``): deviations the evidence proves."""
        lo, hi = self._bounds(self.changes[:, which])
        if before_ns is not None:
            return float(self.prob[hi <= before_ns].sum())
        assert after_ns is not None
        return float(self.prob[lo >= after_ns].sum())


def path_of(window: ElementWindow | None) -> Path:
    if window is not None and window.remove_finish_ns is not None:
        built = window.build_start_ns is not None or window.build_finish_ns is not None
        return "temporary" if built else "demolition"
    return "construction"


def _window_cdf(t: NDArray[np.float64], a: ArrayLike, b: ArrayLike, width_ns: float) -> NDArray[np.float64]:
    """CDF at ``t`` (ns) of a time uniform over the planned window ``[a, b]`` (a task's elements are built one
    after another over its duration) blurred by a logistic slip of scale ``width_ns`` (a zero-length window: the
    plain logistic). Broadcasts over ``t``, ``a``, ``b``."""
    a_, b_ = np.asarray(a, np.float64), np.asarray(b, np.float64)
    x = np.clip((np.asarray(t, np.float64) - a_) / width_ns, -1e6, 1e6)  # t may be +-inf
    span = (b_ - a_) / width_ns
    wide = span >= 1e-6
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        logistic = 1.0 / (1.0 + np.exp(-x))
        uniform = (np.logaddexp(0.0, x) - np.logaddexp(0.0, x - span)) / np.where(wide, span, 1.0)
    return np.clip(np.where(wide, uniform, logistic), 0.0, 1.0)


def _prior_cdf(
    t: NDArray[np.float64], window: tuple[float, float] | None, width_ns: float, lo: float, hi: float, w: float
) -> NDArray[np.float64]:
    """Prior CDF of a change time at ``t`` (ns): with weight ``w`` the planned ``window`` blurred by the slip
    (:func:`_window_cdf`), the rest flat over ``[lo, hi]``."""
    if np.size(t) == 1:  # one time (present_at): the same in plain floats, without numpy's per-call overhead
        return np.array([_prior_cdf_at(float(np.reshape(t, -1)[0]), window, width_ns, lo, hi, w)]).reshape(np.shape(t))
    flat = np.clip((t - lo) / max(hi - lo, 1.0), 0.0, 1.0)
    if window is None:
        return flat
    return w * _window_cdf(t, window[0], window[1], width_ns) + (1.0 - w) * flat


def _softplus(x: float) -> float:
    return math.log1p(math.exp(-abs(x))) + max(x, 0.0)


def _prior_cdf_at(
    t: float, window: tuple[float, float] | None, width_ns: float, lo: float, hi: float, w: float
) -> float:
    """:func:`_prior_cdf` at one time ``t`` (ns, +-inf allowed)."""
    flat = min(max((t - lo) / max(hi - lo, 1.0), 0.0), 1.0)
    if window is None:
        return flat
    a, b = window
    x = min(max((t - a) / width_ns, -1e6), 1e6)
    span = (b - a) / width_ns
    if span >= 1e-6:
        f = (_softplus(x) - _softplus(x - span)) / span
    else:
        f = 1.0 / (1.0 + math.exp(-x)) if x > -700 else 0.0
    return w * min(max(f, 0.0), 1.0) + (1.0 - w) * flat


@dataclass
class ElementTrack:
    """Evidence and schedule of one element; :meth:`posterior` is recomputed from scratch (cheap)."""

    global_id: str
    window: ElementWindow | None
    span_ns: tuple[int, int]
    """(earliest planned start, latest planned finish) of the project: the flat prior's support with margins."""
    observations: dict[str, Observation] = field(default_factory=dict)

    def add(self, obs: Observation) -> None:
        self.observations[obs.photo_id] = obs

    def posterior(self, params: FusionParams) -> Posterior:
        path = path_of(self.window)
        obs = sorted(self.observations.values(), key=lambda o: (o.time_ns, o.photo_id))
        times = {o.time_ns for o in obs} | {o.reference_ns for o in obs if o.reference_ns}
        grid = np.array(sorted(times), np.int64)
        m = len(grid)
        k = 2 if path == "temporary" else 1
        changes = np.array(list(combinations_with_replacement(range(m + 1), k)), np.int64).reshape(-1, k)
        g = np.concatenate([[-np.inf], grid.astype(np.float64), [np.inf]])
        lo_b, hi_b = g[changes], g[changes + 1]
        cdfs = self._prior_cdfs(path, params)
        logp = np.zeros(len(changes))
        sizes: dict[str, int] = {}
        for o in obs:
            if o.group:
                sizes[o.group] = sizes.get(o.group, 0) + 1
        for col, cdf in enumerate(cdfs):
            f = cdf(g)
            logp += np.log(np.maximum(f[changes[:, col] + 1] - f[changes[:, col]], 1e-12))
        for o in obs:
            done = (hi_b <= o.time_ns).sum(axis=1)  # changes completed by the observation
            if path == "construction":
                present = done >= 1
            elif path == "demolition":
                present = done == 0
            else:
                present = done == 1
            share = 1.0 / sizes[o.group] if o.group else 1.0
            logp = logp + np.where(present, 0.5, -0.5) * (o.llr_state * share)
            if o.reference_ns:
                inside = ((lo_b >= o.reference_ns) & (hi_b <= o.time_ns)).any(axis=1)
                logp = logp + np.where(inside, o.llr_change, 0.0)
        logp -= logp.max()
        p = np.exp(logp)
        return Posterior(path=path, grid=grid, changes=changes, prob=p / p.sum(), cdfs=cdfs)

    def _prior_cdfs(
        self, path: Path, params: FusionParams
    ) -> tuple[Callable[[NDArray[np.float64]], NDArray[np.float64]], ...]:
        """Prior CDF of each change of the path (see the module docstring)."""
        w = self.window
        margin = params.margin_days * NS_PER_DAY
        lo, hi = self.span_ns[0] - margin, self.span_ns[1] + margin
        planned: list[tuple[float, float] | None] = []
        for start, finish in (
            ((w.build_start_ns, w.build_finish_ns) if w else (None, None)),
            ((w.remove_start_ns, w.remove_finish_ns) if w else (None, None)),
        ):
            if finish is None:
                planned.append(None)
            else:
                planned.append((float(finish if start is None else min(start, finish)), float(finish)))
        which = {"construction": [0], "demolition": [1], "temporary": [0, 1]}[path]
        weight = params.schedule_weight
        width = params.schedule_width_days * NS_PER_DAY
        return tuple((lambda t, pl=planned[ph]: _prior_cdf(t, pl, width, lo, hi, weight)) for ph in which)


SLIP_GRID_DAYS = np.geomspace(1.0 / 24.0, 3.0, 48)
"""Slip scales :func:`fit_slip_days` chooses from: an hour to three days."""


def fit_slip_days(tracks: list[ElementTrack], params: FusionParams) -> float | None:
    """Slip scale (days) of the site's schedule learnt from the photos (empirical Bayes), or None with too few
    elements seen appearing.

    Every constructed element seen appearing (a transition of at least ``fit_min_llr`` over ``(ref, t]``, the
    narrowest when several) is an interval-censored sample of its change time; the scale maximising the likelihood
    of these intervals under the prior (planned window blurred by the slip, mixed with the flat part, as
    :meth:`ElementTrack.posterior` uses it) is the one the photos show. How far a schedule slips is a property of
    the site and its crews, not of one element; the flat part keeps elements far off their plan from inflating it.
    """
    rows: list[tuple[float, float, float, float, float, float]] = []  # window a, b; seen in (lo, hi]; span
    margin = params.margin_days * NS_PER_DAY
    for tr in tracks:
        w = tr.window
        if path_of(w) != "construction" or w is None or w.build_finish_ns is None:
            continue
        seen = [
            (o.time_ns - o.reference_ns, o.reference_ns, o.time_ns)
            for o in tr.observations.values()
            if o.reference_ns and o.llr_change >= params.fit_min_llr
        ]
        if seen:
            _, ref_ns, t_ns = min(seen)
            finish = float(w.build_finish_ns)
            start = finish if w.build_start_ns is None else float(min(w.build_start_ns, w.build_finish_ns))
            rows.append((start, finish, float(ref_ns), float(t_ns), tr.span_ns[0] - margin, tr.span_ns[1] + margin))
    if len(rows) < params.fit_min_elements:
        return None
    a, b, lo, hi, s0, s1 = (np.array(c) for c in zip(*rows, strict=True))
    t = np.stack([lo, hi], axis=1)  # (N, 2)
    flat = np.clip((t - s0[:, None]) / np.maximum(s1 - s0, 1.0)[:, None], 0.0, 1.0)
    wt = params.schedule_weight
    best, best_ll = None, -np.inf
    for width in SLIP_GRID_DAYS:
        f = wt * _window_cdf(t, a[:, None], b[:, None], float(width) * NS_PER_DAY) + (1.0 - wt) * flat
        ll = float(np.sum(np.log(np.maximum(f[:, 1] - f[:, 0], 1e-12))))
        if ll > best_ll:
            best, best_ll = float(width), ll
    return best


@dataclass(frozen=True)
class ElementEstimate:
    """What the fusion says about one element at ``as_of_ns``."""

    global_id: str
    present_probability: float
    state: Literal["built", "not_built", "unknown"]
    last_absent_ns: int | None
    """Latest time the element was (most probably) still absent: its construction happened after this."""
    first_present_ns: int | None
    finish_ns: int | None
    """Point estimate of the actual finish (middle of the change interval), None when a bound is unknown."""
    finish_probability: float
    deviation: Deviation
    num_observations: int


def estimate(
    track: ElementTrack,
    posterior: Posterior,
    as_of_ns: int,
    params: FusionParams,
    midpoint=None,  # noqa: ANN001 - callable (lo_ns, hi_ns) -> ns; default: plain middle
) -> ElementEstimate:
    """State, change interval, finish estimate and deviation of an element at ``as_of_ns``."""
    n_obs = len(track.observations)
    p = posterior.present_at(as_of_ns) if n_obs else float("nan")
    state: Literal["built", "not_built", "unknown"] = "unknown"
    if n_obs and p >= params.built_probability:
        state = "built"
    elif n_obs and p <= 1.0 - params.built_probability:
        state = "not_built"
    finish = None
    if n_obs and params.finish_from_median and posterior.cdfs:
        lo, hi, t_med, mass = posterior.median_change(0)
        if posterior.path == "demolition":
            lo = hi = None
        elif state != "built" or t_med > as_of_ns:
            hi = None
        elif lo is not None and hi is not None and not params.finish_at_median:
            finish = midpoint(lo, hi) if midpoint is not None else (lo + hi) // 2
        else:
            finish = t_med
    else:
        lo, hi, mass = posterior.change_interval(0) if n_obs else (None, None, 0.0)
        if posterior.path == "demolition":
            lo = hi = None
        if lo is not None and hi is not None:
            finish = midpoint(lo, hi) if midpoint is not None else (lo + hi) // 2
    return ElementEstimate(
        global_id=track.global_id,
        present_probability=p,
        state=state,
        last_absent_ns=lo,
        first_present_ns=hi,
        finish_ns=finish,
        finish_probability=mass,
        deviation=deviation(track, posterior, state, as_of_ns, params) if n_obs else "unknown",
        num_observations=n_obs,
    )


def deviation(track: ElementTrack, posterior: Posterior, state: str, as_of_ns: int, params: FusionParams) -> Deviation:
    """Deviation at ``as_of_ns`` against the element's planned build window (only deviations the evidence
    proves: a change interval wholly before the planned start is ``ahead``, wholly after the planned finish is
    ``behind``; an element still absent after its planned finish is ``not_built``)."""
    w = track.window
    if w is None or w.build_finish_ns is None or posterior.path == "demolition":
        return "unknown" if state == "unknown" else "on_time"
    tol = params.tolerance_days * NS_PER_DAY
    start = w.build_start_ns if w.build_start_ns is not None else w.build_finish_ns
    if state == "built":
        half = 0.5
        if posterior.change_mass(0, after_ns=w.build_finish_ns + tol) > half and _shows(
            track, params.proof_llr, after_ns=w.build_finish_ns + tol
        ):
            return "behind"
        if posterior.change_mass(0, before_ns=start - tol) > half and _shows(
            track, params.proof_llr, before_ns=start - tol
        ):
            return "ahead"
        return "on_time"
    if state == "not_built":
        return "not_built" if as_of_ns > w.build_finish_ns + tol else "on_time"
    return "unknown"


def _shows(track: ElementTrack, llr: float, after_ns: float | None = None, before_ns: float | None = None) -> bool:
    """Whether one photo shows the element absent after ``after_ns`` (or appearing after it, from a reference
    taken after it), or standing before ``before_ns``, by a log-likelihood ratio of at least ``llr``."""
    if llr <= 0.0:
        return True
    for o in track.observations.values():
        if after_ns is not None and (
            (o.time_ns > after_ns and o.llr_state <= -llr) or (o.reference_ns > after_ns and o.llr_change >= llr)
        ):
            return True
        if before_ns is not None and (
            (o.time_ns < before_ns and o.llr_state >= llr)
            or (0 < o.reference_ns and o.time_ns < before_ns and o.llr_change >= llr)
        ):
            return True
    return False


def working_midpoint(lo_ns: int, hi_ns: int, tz: str, hours: tuple[float, float], weekdays: int = 5) -> int:
    """Middle of ``(lo, hi]`` counted in working time (``weekdays`` Mon.. and ``hours`` local); the plain middle
    when the interval holds no working time."""
    import datetime as dt
    from zoneinfo import ZoneInfo

    zone = ZoneInfo(tz)
    a = dt.datetime.fromtimestamp(lo_ns / 1e9, zone)
    b = dt.datetime.fromtimestamp(hi_ns / 1e9, zone)
    spans: list[tuple[dt.datetime, dt.datetime]] = []
    day = a.date()
    while day <= b.date() and len(spans) < 400:
        if day.weekday() < weekdays:
            h0, h1 = (dt.datetime.combine(day, dt.time(0), zone) + dt.timedelta(hours=h) for h in hours)
            s, e = max(a, h0), min(b, h1)
            if e > s:
                spans.append((s, e))
        day += dt.timedelta(days=1)
    total = sum((e - s).total_seconds() for s, e in spans)
    if total <= 0:
        return (lo_ns + hi_ns) // 2
    left = total / 2.0
    for s, e in spans:
        d = (e - s).total_seconds()
        if left <= d:
            return int(math.floor((s.timestamp() + left) * 1e9))
        left -= d
    return hi_ns


def coupled(
    post: Posterior,
    supports: list[Posterior],
    dependants: list[Posterior],
    floor: float | None,
    dependant_floor: float | None = None,
    mean: bool = True,
) -> Posterior:
    """``post`` of a constructed element weighed by what carries it and what it carries (:mod:`support`): a
    hypothesis placing its appearance in ``(lo, hi]`` needs its supports standing at ``hi`` and the elements it
    carries not yet standing at ``lo``. The supports' factor is ``floor + (1 - floor) * p`` with ``p`` the mean
    (``mean``) or product over them of their own posteriors' probability (the graph is read off boxes and the
    neighbours' beliefs may be wrong: a soft constraint), the dependants' likewise with ``dependant_floor``; a
    floor of None leaves that side out. Other paths are returned unchanged."""
    if post.path != "construction" or not len(post.prob):
        return post
    if not (supports and floor is not None) and not (dependants and dependant_floor is not None):
        return post
    lo, hi = post._bounds(post.changes[:, 0])
    weight = np.ones(len(post.prob))
    for side, at, flip, fl in ((supports, hi, False, floor), (dependants, lo, True, dependant_floor)):
        if not side or fl is None:
            continue
        ps = np.array([q.present_curve(at) for q in side])  # (n, H)
        if flip:
            ps = 1.0 - ps
        p = ps.mean(axis=0) if mean else ps.prod(axis=0)
        weight *= fl + (1.0 - fl) * np.clip(p, 0.0, 1.0)
    prob = post.prob * weight
    total = prob.sum()
    if not total > 0:
        return post
    return Posterior(path=post.path, grid=post.grid, changes=post.changes, prob=prob / total, cdfs=post.cdfs)
