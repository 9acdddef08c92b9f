"""Construction schedule (planned, per task) and the as-built truth (per element, with deviations).

Time is modelled in *working hours*: hour ``h`` falls on working day ``floor(h / 9)`` (Mon-Fri, day 0 = the
first photo day) at local time ``07:00 + (h mod 9) h``. Negative hours are before the first photo day.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from zoneinfo import ZoneInfo

import numpy as np

from .building import Building
from .config import FIRST_PHOTO_DAY, TZ

WORK_START_HOUR = 7
HOURS_PER_DAY = 9


@dataclass(frozen=True)
class Task:
    key: str
    name: str
    identification: str
    start_h: float
    finish_h: float
    predecessor: str | None  # finish-start predecessor on the same crew track


@dataclass(frozen=True)
class ElementWindow:
    planned_start_h: float
    planned_finish_h: float
    actual_start_h: float | None  # None when never built
    actual_finish_h: float | None
    never_built: bool
    deviation: str  # "on_time" | "late" | "early" | "never_built"


@dataclass
class Schedule:
    tasks: list[Task]
    windows: dict[str, ElementWindow]  # by Element.key


def working_day_date(day: int) -> dt.date:
    """Calendar date of working day ``day`` (0 = first photo day; negative = earlier)."""
    start = np.datetime64(dt.date(*FIRST_PHOTO_DAY))
    d = np.busday_offset(start, int(day), roll="forward")
    return d.astype(dt.date)


def local_datetime(day: int, hour: int, minute: int = 0) -> dt.datetime:
    """Time-zone aware local datetime on working day ``day``."""
    d = working_day_date(day)
    return dt.datetime(d.year, d.month, d.day, hour, minute, tzinfo=ZoneInfo(TZ))


def hours_to_datetime(h: float) -> dt.datetime:
    """Aware local datetime of working hour ``h`` (rounded to the minute)."""
    minutes = int(round(h * 60))
    day, rest = divmod(minutes, HOURS_PER_DAY * 60)
    return local_datetime(day, WORK_START_HOUR) + dt.timedelta(minutes=rest)


def _task_name(key: str, n_storeys: int) -> str:
    fixed = {
        "foundations": "Pad footings",
        "basement_slab": "Basement base slab",
        "basement_walls": "Basement retaining walls",
        "roof": "Gable roof",
        f"slab_{n_storeys}": "Roof slab",
        "slab_0": "Ground floor slab",
    }
    if key in fixed:
        return fixed[key]
    kind, _, level = key.rpartition("_")
    lvl = "ground floor" if level == "0" else f"level {level}"
    return {"columns": "Columns", "beams": "Beams", "slab": "Floor slab", "walls": "Brick walls", "windows": "Windows"}[
        kind
    ] + f" {lvl}"


def make_schedule(building: Building, n_days: int, rng: np.random.Generator) -> Schedule:
    """Plan tasks (foundations -> frame per storey -> envelope -> roof), fit them to ``n_days`` photo days and
    draw per-element deviations (about 15 % late, 10 % early, exactly one element never built)."""
    n = max(e.storey for e in building.elements) + 1
    durations: dict[str, float] = {"foundations": 3.0, "basement_slab": 1.5, "basement_walls": 2.5, "slab_0": 1.5}
    frame = ["foundations", "basement_slab", "basement_walls", "slab_0"]
    for s in range(n):
        frame += [f"columns_{s}", f"beams_{s}", f"slab_{s + 1}"]
        durations.update({f"columns_{s}": 1.5, f"beams_{s}": 1.5, f"slab_{s + 1}": 1.5})
    durations["roof"] = 2.0
    # Abstract times (days): frame crew sequential; envelope crew follows one storey behind.
    start: dict[str, float] = {}
    finish: dict[str, float] = {}
    pred: dict[str, str | None] = {}
    t = 0.0
    prev: str | None = None
    for k in frame:
        start[k], finish[k], pred[k] = t, t + durations[k], prev
        t, prev = finish[k], k
    env_t, env_prev = 0.0, None
    for s in range(n):
        for k, d in ((f"walls_{s}", 2.5), (f"windows_{s}", 1.5)):
            s0 = max(env_t, finish[f"slab_{s + 1}"]) if k.startswith("walls") else env_t
            start[k], finish[k], pred[k] = s0, s0 + d, env_prev if k.startswith("windows") else f"slab_{s + 1}"
            env_t, env_prev = finish[k], k
    start["roof"], finish["roof"], pred["roof"] = finish[f"slab_{n}"], finish[f"slab_{n}"] + 2.0, f"slab_{n}"
    # Map abstract time to working hours: columns of the ground floor done by day 0 09:00, everything by the
    # morning of the last photo day.
    a0, a1 = finish["columns_0"], max(finish.values())
    h0, h1 = 2.0, (n_days - 1) * HOURS_PER_DAY + 1.0
    scale = (h1 - h0) / (a1 - a0)

    def to_h(a: float) -> float:
        return h0 + (a - a0) * scale

    order = sorted(start, key=lambda k: (start[k], k))
    tasks = [
        Task(k, _task_name(k, n), f"T{10 * (i + 1):03d}", to_h(start[k]), to_h(finish[k]), pred[k])
        for i, k in enumerate(order)
    ]
    by_task: dict[str, list] = {k: [] for k in start}
    for e in building.elements:
        by_task[e.task].append(e)
    never_key = "L1-WALL-S2" if n >= 2 else "L0-WALL-S1"
    windows: dict[str, ElementWindow] = {}
    for task in tasks:
        els = sorted(by_task[task.key], key=lambda e: (round(e.bounds_m[0, 0], 3), round(e.bounds_m[0, 1], 3), e.key))
        slot = (task.finish_h - task.start_h) / max(len(els), 1)
        dur = task.finish_h - task.start_h
        for i, e in enumerate(els):
            ps, pf = task.start_h + i * slot, task.start_h + (i + 1) * slot
            u = rng.random()
            if e.key == never_key:
                windows[e.key] = ElementWindow(ps, pf, None, None, True, "never_built")
                continue
            if u < 0.15:
                delta, kind = dur * rng.uniform(0.6, 1.5), "late"
            elif u < 0.25:
                delta, kind = -dur * rng.uniform(0.3, 0.6), "early"
            else:
                delta, kind = slot * rng.uniform(-0.2, 0.2), "on_time"
            windows[e.key] = ElementWindow(ps, pf, ps + delta, pf + delta, False, kind)
    return Schedule(tasks, windows)
