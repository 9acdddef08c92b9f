"""4D state of elements from a schedule: pure functions over ``ScheduleTask`` tuples.

Shared by the ingest node (summaries, CLI) and any node that colours elements by state
(render, dashboard). Times are int ns UTC, like every message.

An element's planned window is the union of the tasks that name it: ``construction`` tasks
build it (start = earliest start, finish = latest finish), ``demolition`` tasks remove it,
``temporary`` tasks do both (built during the task, removed at its finish).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Literal

from schemas.messages import ScheduleTask

State = Literal["unscheduled", "not_started", "under_construction", "complete", "under_demolition", "removed"]
Status = Literal["early", "on_time", "late", "unknown"]

_RANK: dict[str, int] = {
    "not_started": 0,
    "under_construction": 1,
    "complete": 2,
    "under_demolition": 3,
    "removed": 4,
}


@dataclass(frozen=True, slots=True)
class ElementWindow:
    """When one element is built (and removed), planned and actual; ns UTC, ``None`` = not known."""

    build_start_ns: int | None = None
    build_finish_ns: int | None = None
    remove_start_ns: int | None = None
    remove_finish_ns: int | None = None
    actual_build_start_ns: int | None = None
    actual_build_finish_ns: int | None = None
    actual_remove_start_ns: int | None = None
    actual_remove_finish_ns: int | None = None
    has_actuals: bool = False


def earliest(a: int | None, b: int | None) -> int | None:
    """The earlier of two optional times (None = unknown: the other one)."""
    return b if a is None else a if b is None else min(a, b)


def latest(a: int | None, b: int | None) -> int | None:
    """The later of two optional times (None = unknown: the other one)."""
    return b if a is None else a if b is None else max(a, b)


def element_windows(tasks: Iterable[ScheduleTask]) -> dict[str, ElementWindow]:
    """Planned and actual build/removal windows per element GlobalId."""
    out: dict[str, ElementWindow] = {}
    for task in tasks:
        builds = task.task_type in ("construction", "temporary", "other")
        demolition = task.task_type == "demolition"
        removes = demolition or task.task_type == "temporary"
        # A temporary element is removed at its task's finish; a demolished one from the start.
        remove_start = task.planned_start_ns if demolition else task.planned_finish_ns
        actual_remove_start = task.actual_start_ns if demolition else task.actual_finish_ns
        has_actual = task.actual_start_ns is not None or task.actual_finish_ns is not None
        for gid in task.element_ids:
            w = out.get(gid, ElementWindow())
            if builds:
                w = replace(
                    w,
                    build_start_ns=earliest(w.build_start_ns, task.planned_start_ns),
                    build_finish_ns=latest(w.build_finish_ns, task.planned_finish_ns),
                    actual_build_start_ns=earliest(w.actual_build_start_ns, task.actual_start_ns),
                    actual_build_finish_ns=latest(w.actual_build_finish_ns, task.actual_finish_ns),
                )
            if removes:
                w = replace(
                    w,
                    remove_start_ns=earliest(w.remove_start_ns, remove_start),
                    remove_finish_ns=latest(w.remove_finish_ns, task.planned_finish_ns),
                    actual_remove_start_ns=earliest(w.actual_remove_start_ns, actual_remove_start),
                    actual_remove_finish_ns=latest(w.actual_remove_finish_ns, task.actual_finish_ns),
                )
            out[gid] = replace(w, has_actuals=w.has_actuals or has_actual)
    return out


def _state(at_ns: int, bs: int | None, bf: int | None, rs: int | None, rf: int | None, existed_before: bool) -> State:
    if rf is not None and at_ns >= rf:
        return "removed"
    if rs is not None and at_ns >= rs:
        return "under_demolition"
    if bf is not None and at_ns >= bf:
        return "complete"
    if bs is not None and at_ns >= bs:
        return "under_construction"
    if bs is None and bf is None:
        # Only removal known: the element exists until it is demolished.
        return "complete" if existed_before else "unscheduled"
    return "not_started"


def planned_state(window: ElementWindow | None, at_ns: int) -> State:
    """Planned state of an element at ``at_ns`` (``unscheduled`` when no task names it).

    A task is under construction from its start (inclusive) to its finish (exclusive).
    """
    if window is None:
        return "unscheduled"
    w = window
    return _state(at_ns, w.build_start_ns, w.build_finish_ns, w.remove_start_ns, w.remove_finish_ns, True)


def actual_state(window: ElementWindow | None, at_ns: int) -> State | None:
    """Actual state at ``at_ns`` from actual dates, ``None`` when the element has no actuals at all."""
    if window is None or not window.has_actuals:
        return None
    w = window
    return _state(
        at_ns,
        w.actual_build_start_ns,
        w.actual_build_finish_ns,
        w.actual_remove_start_ns,
        w.actual_remove_finish_ns,
        True,
    )


BUILT_STATES: tuple[State, ...] = ("complete", "under_demolition", "unscheduled")
"""States in which an element stands on site (elements no task names always stand)."""


def stands(window: ElementWindow | None, at_ns: int, basis: Literal["actual", "planned"] = "actual") -> bool:
    """Whether an element stands at ``at_ns``: its construction finished and it is not removed. ``basis``:
    "actual" (actual dates where the element has them, else planned) or "planned"."""
    state = actual_state(window, at_ns) if basis == "actual" else None
    return (state if state is not None else planned_state(window, at_ns)) in BUILT_STATES


def schedule_status(window: ElementWindow | None, at_ns: int) -> Status:
    """Early / on time / late at ``at_ns``: actual progress compared with planned progress.

    ``early`` when the actual state is further along than planned, ``late`` when behind,
    ``unknown`` when the element has no actual dates.
    """
    planned = planned_state(window, at_ns)
    actual = actual_state(window, at_ns)
    if actual is None or planned == "unscheduled" or actual == "unscheduled":
        return "unknown"
    diff = _RANK[actual] - _RANK[planned]
    return "early" if diff > 0 else "late" if diff < 0 else "on_time"


def states_at(tasks: Iterable[ScheduleTask], element_ids: Iterable[str], at_ns: int) -> dict[str, State]:
    """Planned state of every element in ``element_ids`` at ``at_ns``."""
    windows = element_windows(tasks)
    return {gid: planned_state(windows.get(gid), at_ns) for gid in element_ids}


def standing_elements(tasks: Iterable[ScheduleTask], element_ids: Iterable[str]) -> Callable[[int], set[str] | None]:
    """``elements_at(t_ns)``: the elements of ``element_ids`` standing at ``t_ns`` by the schedule.

    Actual dates win over planned ones; complete, under-demolition and unscheduled elements stand; elements under
    construction do not (their full geometry would hide what is really visible behind them). With no tasks every
    element stands: ``elements_at`` returns None (no filter).
    """
    windows = element_windows(tasks)
    ids = list(element_ids)
    if not windows:
        return lambda t_ns: None

    def elements_at(t_ns: int) -> set[str] | None:
        return {gid for gid in ids if stands(windows.get(gid), t_ns)}

    return elements_at


def task_ancestors(tasks: Iterable[ScheduleTask]) -> dict[str, tuple[str, ...]]:
    """Per task id, the summary tasks it is nested in (``parent_id``), nearest first."""
    parent = {t.task_id: t.parent_id for t in tasks}
    out: dict[str, tuple[str, ...]] = {}
    for tid in parent:
        chain: list[str] = []
        p = parent.get(tid)
        while p is not None and p in parent and p not in chain and p != tid:
            chain.append(p)
            p = parent.get(p)
        out[tid] = tuple(chain)
    return out


def task_elements(tasks: Iterable[ScheduleTask]) -> dict[str, tuple[str, ...]]:
    """Per task id, the elements it and its nested sub-tasks name (a summary task's progress rolls them up)."""
    tasks = tuple(tasks)
    ancestors = task_ancestors(tasks)
    out: dict[str, dict[str, None]] = {t.task_id: dict.fromkeys(t.element_ids) for t in tasks}
    for t in tasks:
        for a in ancestors[t.task_id]:
            out[a].update(dict.fromkeys(t.element_ids))
    return {k: tuple(v) for k, v in out.items()}
