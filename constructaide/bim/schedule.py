"""Construction schedules -> ``ScheduleTask`` tuples: IFC (IfcTask/IfcTaskTime), MS Project XML,
Primavera P6 (XML / XER through ifc4d) and a simple CSV.

Dates without an explicit UTC offset are local times of the site's IANA zone ``tz``. All outputs
are int ns UTC. Every loader ends with :func:`validate_tasks` (unique ids, known predecessors,
no cycles, finish >= start) and, when element ids are known, :func:`resolve_elements`.
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import io
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable, Collection, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import msgspec

from constructaide.schedule4d import earliest, latest
from schemas.messages import ScheduleTask

if TYPE_CHECKING:  # ifcopenshell is imported lazily: CSV / MS Project schedules do not need it
    import ifcopenshell

TaskType = Literal["construction", "demolition", "temporary", "other"]
Tasks = tuple[ScheduleTask, ...]
ElementIndex = Mapping[str, tuple[str, str]]
"""GlobalId -> (ifc_class, storey) of the site model's elements."""


class ScheduleError(ValueError):
    """A schedule that cannot be used; the message says which file/task and why."""


# ---------------------------------------------------------------------------------------------
# time helpers
# ---------------------------------------------------------------------------------------------


def zone(tz: str) -> ZoneInfo:
    """ZoneInfo for an IANA name; raises ScheduleError for unknown zones."""
    try:
        return ZoneInfo(tz)
    except (ZoneInfoNotFoundError, ValueError) as exc:
        raise ScheduleError(f"unknown time zone {tz!r} (use an IANA name like 'Europe/Amsterdam')") from exc


def datetime_to_ns(value: dt.datetime | dt.date, tz: ZoneInfo, *, end_of_day: bool = False) -> int:
    """ns UTC of a datetime (naive = local in ``tz``) or a date (start of day, or end when ``end_of_day``)."""
    if not isinstance(value, dt.datetime):
        day = value + dt.timedelta(days=1) if end_of_day else value
        value = dt.datetime(day.year, day.month, day.day)
    if value.tzinfo is None:
        value = value.replace(tzinfo=tz)
    delta = value - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000


_DMY = re.compile(r"^\s*(\d{1,2})[-/.](\d{1,2})[-/.](\d{4})(?:[ T](\d{1,2}):(\d{2})(?::(\d{2}))?)?\s*$")


def parse_time(text: str, tz: ZoneInfo, *, end_of_day: bool = False, what: str = "date") -> int:
    """ns UTC of an ISO 8601 date/datetime or a day-first ``D-M-YYYY[ HH:MM[:SS]]``.

    A bare date means the start of that local day, or its end with ``end_of_day`` (finish dates).
    """
    s = text.strip()
    if not s:
        raise ScheduleError(f"empty {what}")
    m = _DMY.match(s)
    if m:
        d, mo, y, hh, mm, ss = m.groups()
        try:
            if hh is None:
                return datetime_to_ns(dt.date(int(y), int(mo), int(d)), tz, end_of_day=end_of_day)
            return datetime_to_ns(dt.datetime(int(y), int(mo), int(d), int(hh), int(mm), int(ss or 0)), tz)
        except ValueError as exc:
            raise ScheduleError(f"bad {what} {text!r}: {exc}") from exc
    try:
        if len(s) == 10 and s[4] == "-":
            return datetime_to_ns(dt.date.fromisoformat(s), tz, end_of_day=end_of_day)
        return datetime_to_ns(dt.datetime.fromisoformat(s.replace("Z", "+00:00")), tz)
    except ValueError as exc:
        raise ScheduleError(f"bad {what} {text!r} (expected ISO 8601 or D-M-YYYY)") from exc


_DURATION = re.compile(
    r"^P(?:(?P<y>\d+(?:\.\d+)?)Y)?(?:(?P<mo>\d+(?:\.\d+)?)M)?(?:(?P<w>\d+(?:\.\d+)?)W)?(?:(?P<d>\d+(?:\.\d+)?)D)?"
    r"(?:T(?:(?P<h>\d+(?:\.\d+)?)H)?(?:(?P<mi>\d+(?:\.\d+)?)M)?(?:(?P<s>\d+(?:\.\d+)?)S)?)?$"
)


def duration_ns(text: str) -> int:
    """ns of an ISO 8601 duration (elapsed time; months = 30 days, years = 365 days)."""
    m = _DURATION.match(text.strip())
    if not m:
        raise ScheduleError(f"bad ISO 8601 duration {text!r}")
    g = {k: float(v) if v else 0.0 for k, v in m.groupdict().items()}
    secs = (
        g["y"] * 365 * 86400
        + g["mo"] * 30 * 86400
        + g["w"] * 7 * 86400
        + g["d"] * 86400
        + g["h"] * 3600
        + g["mi"] * 60
        + g["s"]
    )
    return int(round(secs * 1e9))


# ---------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------


def find_cycle(tasks: Iterable[ScheduleTask]) -> list[str] | None:
    """A predecessor cycle as a list of task ids (first == last), or ``None``."""
    preds = {t.task_id: t.predecessor_ids for t in tasks}
    colour: dict[str, int] = {}  # 0/absent white, 1 grey (on stack), 2 black
    for root in preds:
        if colour.get(root):
            continue
        stack: list[tuple[str, int]] = [(root, 0)]
        path: list[str] = [root]
        colour[root] = 1
        while stack:
            node, i = stack[-1]
            nexts = preds.get(node, ())
            if i < len(nexts):
                stack[-1] = (node, i + 1)
                nxt = nexts[i]
                c = colour.get(nxt, 0)
                if c == 1:
                    return path[path.index(nxt) :] + [nxt]
                if c == 0 and nxt in preds:
                    colour[nxt] = 1
                    stack.append((nxt, 0))
                    path.append(nxt)
            else:
                colour[node] = 2
                stack.pop()
                path.pop()
    return None


def validate_tasks(tasks: Iterable[ScheduleTask], source: str = "schedule") -> tuple[ScheduleTask, ...]:
    """Check ids are unique, predecessors exist, no cycles, finish >= start; returns the tasks.

    Raises ScheduleError naming ``source`` and the offending task.
    """
    out = tuple(tasks)
    ids: dict[str, ScheduleTask] = {}
    for t in out:
        if t.task_id in ids:
            raise ScheduleError(f"{source}: duplicate task id {t.task_id!r}")
        ids[t.task_id] = t
        if t.planned_finish_ns < t.planned_start_ns:
            raise ScheduleError(f"{source}: task {t.task_id!r} ({t.name!r}) finishes before it starts")
        if t.actual_start_ns is not None and t.actual_finish_ns is not None and t.actual_finish_ns < t.actual_start_ns:
            raise ScheduleError(f"{source}: task {t.task_id!r} ({t.name!r}) actually finishes before it starts")
    for t in out:
        for p in t.predecessor_ids:
            if p not in ids:
                raise ScheduleError(f"{source}: task {t.task_id!r} ({t.name!r}) has unknown predecessor {p!r}")
        if t.parent_id is not None and t.parent_id not in ids:
            raise ScheduleError(f"{source}: task {t.task_id!r} ({t.name!r}) has unknown parent {t.parent_id!r}")
        seen, p_id = {t.task_id}, t.parent_id
        while p_id is not None:
            if p_id in seen:
                raise ScheduleError(f"{source}: task {t.task_id!r} ({t.name!r}) is nested in itself")
            seen.add(p_id)
            p_id = ids[p_id].parent_id if p_id in ids else None
    cycle = find_cycle(out)
    if cycle:
        names = " -> ".join(f"{c} ({ids[c].name})" for c in cycle)
        raise ScheduleError(f"{source}: cyclic task sequence: {names}")
    return out


def resolve_elements(
    tasks: Iterable[ScheduleTask], element_ids: Collection[str], source: str = "schedule", on_missing: str = "error"
) -> tuple[ScheduleTask, ...]:
    """Check every task's element ids exist in the model.

    ``on_missing="error"`` raises ScheduleError listing the missing ids; ``"drop"`` removes them.
    """
    if on_missing not in ("error", "drop"):
        raise ValueError(f"on_missing must be 'error' or 'drop', not {on_missing!r}")
    out: list[ScheduleTask] = []
    missing: dict[str, list[str]] = {}
    for t in tasks:
        bad = [e for e in t.element_ids if e not in element_ids]
        if bad:
            missing[t.task_id] = bad
            if on_missing == "drop":
                keep = tuple(e for e in t.element_ids if e in element_ids)
                t = msgspec.structs.replace(t, element_ids=keep)
        out.append(t)
    if missing and on_missing == "error":
        n_ids = len({e for v in missing.values() for e in v})
        example_task, example_ids = next(iter(missing.items()))
        raise ScheduleError(
            f"{source}: {len(missing)} task(s) refer to {n_ids} element(s) missing from the model "
            f"(e.g. task {example_task!r} -> {example_ids[:3]})"
        )
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# IFC (IfcWorkSchedule / IfcTask / IfcTaskTime / IfcRelSequence / IfcRelAssignsTo*)
# ---------------------------------------------------------------------------------------------


def _ifc_time(value: Any, tz: ZoneInfo, *, end_of_day: bool = False) -> int | None:
    import ifcopenshell
    import ifcopenshell.util.date

    if value is None or value == "":
        return None
    if isinstance(value, str):
        return parse_time(value, tz, end_of_day=end_of_day, what="IFC date")
    if isinstance(value, ifcopenshell.entity_instance):  # IFC2X3 IfcDateAndTime / IfcCalendarDate
        conv = ifcopenshell.util.date.ifc2datetime(value)
        if isinstance(conv, dt.datetime | dt.date):
            return datetime_to_ns(conv, tz, end_of_day=end_of_day)
    if isinstance(value, int):  # IfcTimeStamp: seconds since epoch, UTC
        return value * 1_000_000_000
    return None


_TASK_TYPES: dict[str, TaskType] = {
    "CONSTRUCTION": "construction",
    "DEMOLITION": "demolition",
    "DISMANTLE": "demolition",
    "REMOVAL": "demolition",
}


def tasks_from_ifc(
    ifc_file: ifcopenshell.file,
    element_ids: Collection[str],
    tz: ZoneInfo,
    source: str = "IFC",
    expand: Callable[[ifcopenshell.entity_instance], set[str]] | None = None,
    id_prefix: str | None = None,
) -> tuple[ScheduleTask, ...]:
    """ScheduleTasks of every IfcTask in an open ifcopenshell file.

    Dates: IfcTaskTime ScheduleStart/ScheduleFinish, else EarlyStart/EarlyFinish, else start +
    ScheduleDuration; ActualStart/ActualFinish when present (IFC2X3: IfcScheduleTimeControl).
    Tasks without any dates take the span of their nested sub-tasks (IfcRelNests).
    Products: IfcRelAssignsToProcess (task -> products) and IfcRelAssignsToProduct
    (product -> tasks). ``expand(product)`` returns the GlobalIds in ``element_ids`` that a
    product stands for (itself, its parts, a storey's contents, a type's occurrences). Elements
    reached through a spatial structure or a type are only given to a task when no task names
    them directly, so a storey-wide summary task does not blur its sub-tasks' dates.
    ``task_id`` is the IfcTask GlobalId, or ``id_prefix`` + Identification when ``id_prefix`` is
    given and identifications are unique (stable ids for schedules converted on the fly).
    """
    f = ifc_file
    tasks = f.by_type("IfcTask")
    if not tasks:
        return ()
    gid_of = {t.id(): t.GlobalId for t in tasks}
    if id_prefix is not None:
        idents = [getattr(t, "Identification", None) for t in tasks]
        if all(idents) and len(set(idents)) == len(idents):
            gid_of = {t.id(): f"{id_prefix}{i}" for t, i in zip(tasks, idents, strict=True)}

    def _expand(product: ifcopenshell.entity_instance) -> set[str]:
        if expand is not None:
            return expand(product)
        return {product.GlobalId} if product.GlobalId in element_ids else set()

    direct: dict[str, set[str]] = {g: set() for g in gid_of.values()}
    indirect: dict[str, set[str]] = {g: set() for g in gid_of.values()}

    def _assign(task: ifcopenshell.entity_instance, product: ifcopenshell.entity_instance) -> None:
        if task.id() not in gid_of or not hasattr(product, "GlobalId"):
            return
        spatial = product.is_a("IfcSpatialStructureElement") or product.is_a("IfcTypeObject")
        if f.schema != "IFC2X3":
            spatial = spatial or product.is_a("IfcSpatialElement")
        (indirect if spatial else direct)[gid_of[task.id()]].update(_expand(product))

    for rel in f.by_type("IfcRelAssignsToProcess"):
        proc = rel.RelatingProcess
        if proc is not None and proc.is_a("IfcTask"):
            for obj in rel.RelatedObjects or ():
                if obj.is_a("IfcProduct") or obj.is_a("IfcTypeObject"):
                    _assign(proc, obj)
    for rel in f.by_type("IfcRelAssignsToProduct"):
        prod = rel.RelatingProduct
        for obj in rel.RelatedObjects or ():
            if obj.is_a("IfcTask") and prod is not None:
                _assign(obj, prod)
    directly_named = set().union(*direct.values()) if direct else set()

    # nesting (summary tasks)
    children: dict[int, list[int]] = {}
    for rel in f.by_type("IfcRelNests"):
        parent = rel.RelatingObject
        if parent is not None and parent.is_a("IfcTask"):
            children.setdefault(parent.id(), []).extend(o.id() for o in rel.RelatedObjects or () if o.is_a("IfcTask"))

    parent_of = {c: p for p, cs in children.items() for c in cs}

    # predecessors
    preds: dict[int, list[str]] = {}
    for rel in f.by_type("IfcRelSequence"):
        a, b = rel.RelatingProcess, rel.RelatedProcess
        if a is not None and b is not None and a.id() in gid_of and b.id() in gid_of:
            preds.setdefault(b.id(), []).append(gid_of[a.id()])

    # IFC2X3 keeps dates in IfcScheduleTimeControl assigned through IfcRelAssignsTasks
    control_2x3: dict[int, ifcopenshell.entity_instance] = {}
    if f.schema == "IFC2X3":
        for rel in f.by_type("IfcRelAssignsTasks"):
            if rel.TimeForTask is not None:
                for obj in rel.RelatedObjects or ():
                    if obj.is_a("IfcTask"):
                        control_2x3[obj.id()] = rel.TimeForTask

    times: dict[int, tuple[int | None, int | None, int | None, int | None]] = {}
    for t in tasks:
        tt = control_2x3.get(t.id()) if f.schema == "IFC2X3" else getattr(t, "TaskTime", None)
        start = finish = a_start = a_finish = None
        if tt is not None:
            start = _ifc_time(tt.ScheduleStart, tz) or _ifc_time(getattr(tt, "EarlyStart", None), tz)
            finish = _ifc_time(tt.ScheduleFinish, tz, end_of_day=True) or _ifc_time(
                getattr(tt, "EarlyFinish", None), tz, end_of_day=True
            )
            dur = getattr(tt, "ScheduleDuration", None)
            if start is not None and finish is None and isinstance(dur, str) and dur:
                finish = start + duration_ns(dur)
            a_start = _ifc_time(getattr(tt, "ActualStart", None), tz)
            a_finish = _ifc_time(getattr(tt, "ActualFinish", None), tz, end_of_day=True)
        times[t.id()] = (start, finish, a_start, a_finish)

    def _span(tid: int, seen: frozenset[int] = frozenset()) -> tuple[int | None, int | None]:
        s, e, _, _ = times[tid]
        if s is not None and e is not None:
            return s, e
        starts, ends = [s] if s is not None else [], [e] if e is not None else []
        for c in children.get(tid, ()):
            if c in times and c not in seen:
                cs, ce = _span(c, seen | {tid})
                starts += [cs] if cs is not None else []
                ends += [ce] if ce is not None else []
        return (min(starts) if starts else None, max(ends) if ends else None)

    out: list[ScheduleTask] = []
    for t in tasks:
        start, finish = _span(t.id())
        if start is None or finish is None:
            raise ScheduleError(f"{source}: IfcTask {t.GlobalId} ({t.Name!r}) has no usable start/finish dates")
        _, _, a_start, a_finish = times[t.id()]
        gid = gid_of[t.id()]
        elements = direct[gid] | (indirect[gid] - directly_named)
        predefined = str(getattr(t, "PredefinedType", None) or "")
        out.append(
            ScheduleTask(
                task_id=gid,
                name=t.Name or getattr(t, "Identification", None) or "",
                planned_start_ns=start,
                planned_finish_ns=finish,
                actual_start_ns=a_start,
                actual_finish_ns=a_finish,
                element_ids=tuple(sorted(elements)),
                predecessor_ids=tuple(preds.get(t.id(), ())),
                task_type=_TASK_TYPES.get(predefined, "construction"),
                parent_id=gid_of.get(parent_of.get(t.id(), -1)),
            )
        )
    return validate_tasks(out, source)


# ---------------------------------------------------------------------------------------------
# MS Project XML
# ---------------------------------------------------------------------------------------------

_MSP_NS = "{http://schemas.microsoft.com/project}"


def tasks_from_msproject_xml(path: str | Path, tz: ZoneInfo) -> tuple[ScheduleTask, ...]:
    """Tasks of an MS Project XML export (``<Project><Tasks><Task>``), parsed directly.

    Every ``<Task>`` with a UID other than 0 (the project summary) and ``IsNull`` 0 becomes one
    task: ``task_id`` = "msp-<UID>", dates Start/Finish (ActualStart/ActualFinish when present),
    predecessors from ``<PredecessorLink><PredecessorUID>``. Elements are not named by MS Project,
    so ``element_ids`` stays empty; link them by a CSV.
    """
    p = Path(path)
    try:
        root = ET.parse(p).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ScheduleError(f"{p}: not a readable MS Project XML file: {exc}") from exc
    ns = _MSP_NS if root.tag.startswith(_MSP_NS) else ""
    if root.tag != f"{ns}Project":
        raise ScheduleError(f"{p}: root element is {root.tag!r}, expected MS Project <Project>")
    out: list[ScheduleTask] = []
    for task in root.iterfind(f"{ns}Tasks/{ns}Task"):
        uid = (task.findtext(f"{ns}UID") or "").strip()
        if not uid or uid == "0" or (task.findtext(f"{ns}IsNull") or "0").strip() == "1":
            continue
        name = (task.findtext(f"{ns}Name") or "").strip()
        start_s, finish_s = task.findtext(f"{ns}Start"), task.findtext(f"{ns}Finish")
        if not start_s or not finish_s:
            raise ScheduleError(f"{p}: task UID {uid} ({name!r}) has no Start/Finish")
        a_start_s, a_finish_s = task.findtext(f"{ns}ActualStart"), task.findtext(f"{ns}ActualFinish")
        preds = tuple(
            f"msp-{(link.findtext(f'{ns}PredecessorUID') or '').strip()}"
            for link in task.iterfind(f"{ns}PredecessorLink")
            if (link.findtext(f"{ns}PredecessorUID") or "").strip() not in ("", "0")
        )
        out.append(
            ScheduleTask(
                task_id=f"msp-{uid}",
                name=name,
                planned_start_ns=parse_time(start_s, tz, what=f"Start of task UID {uid}"),
                planned_finish_ns=parse_time(finish_s, tz, what=f"Finish of task UID {uid}"),
                actual_start_ns=parse_time(a_start_s, tz) if a_start_s else None,
                actual_finish_ns=parse_time(a_finish_s, tz) if a_finish_s else None,
                predecessor_ids=preds,
            )
        )
    if not out:
        raise ScheduleError(f"{p}: MS Project XML has no tasks")
    return validate_tasks(out, str(p))


# ---------------------------------------------------------------------------------------------
# Primavera P6 (XML, XER) through ifc4d
# ---------------------------------------------------------------------------------------------


def tasks_from_p6(path: str | Path, tz: ZoneInfo) -> tuple[ScheduleTask, ...]:
    """Tasks of a Primavera P6 XML (``.xml``) or XER (``.xer``) export, converted with ifc4d to an
    in-memory IFC4 work schedule and read by :func:`tasks_from_ifc`."""
    from ifc4d.common import ScheduleIfcGenerator

    p = Path(path)
    if p.suffix.lower() == ".xer":
        try:
            from ifc4d.p6xer2ifc import P6XER2Ifc
        except ImportError as exc:
            raise ScheduleError(f"{p}: P6 XER import needs the 'xerparser' package; export P6 XML instead") from exc

        conv: Any = P6XER2Ifc()
        conv.xer = str(p)
    else:
        from ifc4d.p62ifc import P62Ifc

        conv = P62Ifc()
        conv.xml = str(p)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            if hasattr(conv, "parse_xml"):
                conv.parse_xml()
            else:
                conv.parse_xer()
            settings = {
                "work_plan": getattr(conv, "work_plan", None),
                "project": conv.project,
                "calendars": conv.calendars,
                "wbs": conv.wbs,
                "root_activities": conv.root_activites,
                "activities": conv.activities,
                "relationships": conv.relationships,
                "resources": getattr(conv, "resources", {}),
            }
            gen = ScheduleIfcGenerator(None, None, settings)
            gen.create_ifc()
    except Exception as exc:  # ifc4d raises whatever its parser meets
        raise ScheduleError(f"{p}: cannot read P6 schedule: {type(exc).__name__}: {exc}") from exc
    # WBS nodes come out as IfcTasks without times; tasks_from_ifc rolls them up from children.
    return tasks_from_ifc(gen.file, (), tz, source=str(p), id_prefix="p6-")


# ---------------------------------------------------------------------------------------------
# CSV
# ---------------------------------------------------------------------------------------------

_CSV_COLUMNS: Mapping[str, tuple[str, ...]] = {
    "global_id": ("global_id", "globalid", "guid", "element", "element_id"),
    "ifc_class": ("ifc_class", "ifcclass", "class"),
    "storey": ("storey", "level", "floor"),
    "task_id": ("task_id", "taskid", "task"),
    "task_name": ("task_name", "taskname", "name"),
    "start": ("start", "planned_start", "taskstart", "start_date"),
    "finish": ("finish", "planned_finish", "taskfinish", "finish_date", "end"),
    "actual_start": ("actual_start", "actualstart"),
    "actual_finish": ("actual_finish", "actualfinish"),
    "task_type": ("task_type", "tasktype"),
}


_KINDS = ("construction", "demolition", "temporary", "other")


def tasks_from_csv(
    path: str | Path, tz: ZoneInfo, elements: ElementIndex | None = None, on_missing: str = "error"
) -> Tasks:
    """Tasks from a CSV with a header row (names case-insensitive; ``,`` or ``;`` separated).

    Columns: ``global_id`` *or* ``ifc_class`` + ``storey`` (all elements of that class on that
    storey), ``start``, ``finish`` (ISO 8601 or D-M-YYYY; a bare finish date means the end of that
    day), optional ``task_id`` (rows sharing it form one task; default one task per row),
    ``task_name``, ``actual_start``, ``actual_finish``, ``task_type``. ``elements`` maps GlobalId ->
    (ifc_class, storey) of the model, needed for class/storey rows and to check GlobalIds
    (``on_missing``: "error" or "drop").
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScheduleError(f"{p}: cannot read CSV: {exc}") from exc
    first = text.splitlines()[0] if text else ""
    delimiter = ";" if first.count(";") > first.count(",") else ","
    reader = csv.DictReader(io.StringIO(text), delimiter=delimiter)
    header = {(h or "").strip().lower().replace(" ", "_"): h for h in reader.fieldnames or ()}
    col: dict[str, str] = {}
    for canon, aliases in _CSV_COLUMNS.items():
        for a in aliases:
            if a in header:
                col[canon] = header[a]
                break
    if "start" not in col or "finish" not in col:
        raise ScheduleError(f"{p}: CSV needs 'start' and 'finish' columns (found {list(header)})")
    if "global_id" not in col and not ("ifc_class" in col and "storey" in col):
        raise ScheduleError(f"{p}: CSV needs a 'global_id' column or 'ifc_class' + 'storey' columns")

    by_class_storey: dict[tuple[str, str], list[str]] = {}
    for gid, (cls, storey) in (elements or {}).items():
        by_class_storey.setdefault((cls.lower(), storey), []).append(gid)

    groups: dict[str, ScheduleTask] = {}
    for lineno, row in enumerate(reader, start=2):
        if not any((v or "").strip() for v in row.values() if isinstance(v, str)):
            continue  # blank line (spreadsheet exports pad with empty rows)

        def get(name: str, row: dict[str, str] = row) -> str:
            return (row.get(col[name]) or "").strip() if name in col else ""

        where = f"{p}:{lineno}"
        start = parse_time(get("start"), tz, what=f"start at {where}")
        finish = parse_time(get("finish"), tz, end_of_day=True, what=f"finish at {where}")
        a_start = parse_time(get("actual_start"), tz, what=f"actual_start at {where}") if get("actual_start") else None
        a_finish = None
        if get("actual_finish"):
            a_finish = parse_time(get("actual_finish"), tz, end_of_day=True, what=f"actual_finish at {where}")
        gids: list[str] = []
        if get("global_id"):
            gids = [get("global_id")]
        elif get("ifc_class"):
            if elements is None:
                raise ScheduleError(f"{where}: class/storey rows need the model's elements")
            gids = by_class_storey.get((get("ifc_class").lower(), get("storey")), [])
            if not gids and on_missing == "error":
                raise ScheduleError(f"{where}: no {get('ifc_class')} on storey {get('storey')!r} in the model")
        task_id = get("task_id") or f"csv-{lineno}"
        g = groups.get(task_id)
        if g is None:
            kind = get("task_type").lower()
            task_type = cast(TaskType, kind) if kind in _KINDS else "construction"
            g = ScheduleTask(
                task_id=task_id,
                name=get("task_name"),
                planned_start_ns=start,
                planned_finish_ns=finish,
                task_type=task_type,
            )
        groups[task_id] = msgspec.structs.replace(
            g,
            planned_start_ns=min(g.planned_start_ns, start),
            planned_finish_ns=max(g.planned_finish_ns, finish),
            actual_start_ns=earliest(g.actual_start_ns, a_start),
            actual_finish_ns=latest(g.actual_finish_ns, a_finish),
            element_ids=tuple(dict.fromkeys((*g.element_ids, *gids))),
        )
    if not groups:
        raise ScheduleError(f"{p}: CSV has no rows")
    tasks = list(groups.values())
    out = validate_tasks(tasks, str(p))
    if elements is not None:
        out = resolve_elements(out, elements.keys(), str(p), on_missing)
    return out


def load_schedule(path: str | Path, tz: str, elements: ElementIndex | None = None, on_missing: str = "error") -> Tasks:
    """Load a schedule file by its extension: ``.xml`` (MS Project, or P6 when the root is
    ``APIBusinessObjects``), ``.xer`` (P6), ``.csv``, ``.ifc`` (IfcTasks only).

    ``elements``: GlobalId -> (ifc_class, storey) of the site model, used to resolve/check
    element references.
    """
    p = Path(path)
    if not p.is_file():
        raise ScheduleError(f"{p}: schedule file not found")
    zi = zone(tz)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return tasks_from_csv(p, zi, elements, on_missing)
    if suffix == ".xer":
        tasks = tasks_from_p6(p, zi)
    elif suffix == ".xml":
        with p.open("rb") as fh:
            head = fh.read(4096)
        tasks = tasks_from_p6(p, zi) if b"APIBusinessObjects" in head else tasks_from_msproject_xml(p, zi)
    elif suffix == ".ifc":
        import ifcopenshell

        try:
            f = ifcopenshell.open(str(p))
        except Exception as exc:
            raise ScheduleError(f"{p}: cannot open IFC schedule: {exc}") from exc
        known = set(elements or ())
        tasks = tasks_from_ifc(f, known, zi, source=str(p), expand=lambda prod: {prod.GlobalId} & known)
    else:
        raise ScheduleError(f"{p}: unknown schedule format {suffix!r} (use .xml, .xer, .csv or .ifc)")
    if elements is not None:
        tasks = resolve_elements(tasks, elements.keys(), str(p), on_missing)
    return tasks
