"""Ingest schedules: MS Project XML (Schependomlaan), CSV, validation errors, 4D state logic."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
from collections import Counter
from pathlib import Path
from zoneinfo import ZoneInfo

import pytest

from constructaide.bim.ifc import element_index, load_site_model
from constructaide.bim.schedule import ScheduleError, load_schedule, tasks_from_msproject_xml, validate_tasks
from constructaide.schedule4d import element_windows, planned_state, schedule_status, task_ancestors, task_elements
from schemas.messages import ScheduleTask

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MSP = DATA / "schependomlaan" / "schedule-msproject.xml"
EVENTLOG = DATA / "schependomlaan" / "eventlog-planned-and-asbuilt.csv"
BSI = DATA / "ifc" / "bsi_construction-scheduling-task.ifc"
AMS = ZoneInfo("Europe/Amsterdam")


def local(ns: int, tz: ZoneInfo = AMS) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).astimezone(tz).replace(tzinfo=None).isoformat()


def ns(*args: int, tz: ZoneInfo = dt.UTC) -> int:  # type: ignore[assignment]
    return int(dt.datetime(*args, tzinfo=tz).timestamp() * 1e9)


@pytest.mark.skipif(not MSP.is_file(), reason=f"Schependomlaan schedule not present at {MSP}")
def test_schependomlaan_msproject_all_tasks_and_dates(tmp_path: Path) -> None:
    import ifc4d.msp2ifc
    import ifcopenshell

    tasks = tasks_from_msproject_xml(MSP, AMS)
    assert len(tasks) == 157
    # Independent reference: ifc4d's own MS Project -> IFC conversion of the same file.
    conv = ifc4d.msp2ifc.MSP2Ifc()
    conv.xml = str(MSP)
    conv.output = str(tmp_path / "msp.ifc")
    with contextlib.redirect_stdout(io.StringIO()):
        conv.execute()
    ref = ifcopenshell.open(conv.output)
    ref_rows = Counter(
        ((t.Name or "").strip(), t.TaskTime.ScheduleStart[:16], t.TaskTime.ScheduleFinish[:16])
        for t in ref.by_type("IfcTask")
        if t.TaskTime is not None
    )
    ours = Counter((t.name, local(t.planned_start_ns)[:16], local(t.planned_finish_ns)[:16]) for t in tasks)
    assert sum(ref_rows.values()) == 157
    assert ours == ref_rows
    assert local(min(t.planned_start_ns for t in tasks)) == "2015-02-19T08:00:00"
    assert local(max(t.planned_finish_ns for t in tasks)) == "2015-12-17T16:00:00"
    assert sum(len(t.predecessor_ids) for t in tasks) == len(ref.by_type("IfcRelSequence")) == 48
    opleveren = next(t for t in tasks if t.name == "Opleveren")
    # 2015-12-11 08:00 CET = 07:00 UTC
    assert opleveren.planned_start_ns == ns(2015, 12, 11, 7)


def _msp(tasks_xml: str) -> str:
    return f'<?xml version="1.0"?><Project xmlns="http://schemas.microsoft.com/project"><Tasks>{tasks_xml}</Tasks></Project>'


def _msp_task(uid: int, preds: tuple[int, ...] = ()) -> str:
    links = "".join(f"<PredecessorLink><PredecessorUID>{p}</PredecessorUID></PredecessorLink>" for p in preds)
    return (
        f"<Task><UID>{uid}</UID><Name>T{uid}</Name><Start>2025-03-0{uid}T08:00:00</Start>"
        f"<Finish>2025-03-0{uid}T16:00:00</Finish>{links}</Task>"
    )


def test_msproject_errors(tmp_path: Path) -> None:
    cyc = tmp_path / "cyclic.xml"
    cyc.write_text(_msp(_msp_task(1, (3,)) + _msp_task(2, (1,)) + _msp_task(3, (2,))))
    with pytest.raises(ScheduleError, match="cyclic task sequence"):
        load_schedule(cyc, "UTC")
    dangling = tmp_path / "dangling.xml"
    dangling.write_text(_msp(_msp_task(1, (7,))))
    with pytest.raises(ScheduleError, match="unknown predecessor"):
        load_schedule(dangling, "UTC")
    ok = tmp_path / "ok.xml"
    ok.write_text(_msp(_msp_task(1) + _msp_task(2, (1,))))
    tasks = load_schedule(ok, "UTC")
    assert [t.predecessor_ids for t in tasks] == [(), ("msp-1",)]
    assert tasks[1].planned_start_ns == ns(2025, 3, 2, 8)
    bad = tmp_path / "bad.xml"
    bad.write_text("<Project><Tasks><Task>")
    with pytest.raises(ScheduleError, match="not a readable MS Project XML"):
        load_schedule(bad, "UTC")
    with pytest.raises(ScheduleError, match="unknown time zone"):
        load_schedule(ok, "Mars/Olympus")
    with pytest.raises(ScheduleError, match="not found"):
        load_schedule(tmp_path / "nope.xml", "UTC")
    garbage = tmp_path / "p6.xml"
    garbage.write_text("<APIBusinessObjects><Project><Activity><Id>broken")
    with pytest.raises(ScheduleError, match="cannot read P6 schedule"):
        load_schedule(garbage, "UTC")


@pytest.fixture(scope="module")
def bsi_site():  # type: ignore[no-untyped-def]
    if not BSI.is_file():
        pytest.skip(f"bSI 4D example not present at {BSI}")
    return load_site_model([BSI], tz="UTC")


def test_csv_by_guid_and_class_storey_with_actuals(tmp_path: Path, bsi_site) -> None:  # type: ignore[no-untyped-def]
    gid = {e.name: g for g, e in bsi_site.elements.items()}
    csv_path = tmp_path / "plan.csv"
    csv_path.write_text(
        "task_id;task_name;GlobalId;ifc_class;storey;start;finish;actual_start;actual_finish\n"
        f"S;slab;{gid['Slab #1']};;;2025-03-03;2025-03-04;2025-03-03;2025-03-03\n"
        "W;walls;;IfcWall;Ground Level;5-3-2025;7-3-2025;2025-03-06;\n"
    )
    site = bsi_site.with_tasks(load_schedule(csv_path, "UTC", element_index(bsi_site)))
    assert len(site.tasks) == 8 + 2
    walls = next(t for t in site.tasks if t.task_id == "W")
    assert sorted(walls.element_ids) == sorted(gid[f"Wall #{i}"] for i in range(1, 5))
    assert walls.planned_finish_ns == ns(2025, 3, 8)  # a bare finish date is the end of that day
    t = ns(2025, 3, 4, 12)
    # Slab: planned until end of 4 March, actually finished end of 3 March -> early on the 4th.
    assert site.planned_state(gid["Slab #1"], t) == "under_construction"
    assert site.actual_state(gid["Slab #1"], t) == "complete"
    assert site.schedule_status(gid["Slab #1"], t) == "early"
    # Walls: planned from 5 March, actually started 6 March -> late on the 5th.
    t5 = ns(2025, 3, 5, 12)
    assert site.planned_state(gid["Wall #2"], t5) == "under_construction"
    assert site.actual_state(gid["Wall #2"], t5) == "not_started"
    assert site.schedule_status(gid["Wall #2"], t5) == "late"
    assert site.schedule_status(gid["Wall #2"], ns(2025, 3, 6, 12)) == "on_time"


def test_csv_missing_elements(tmp_path: Path, bsi_site) -> None:  # type: ignore[no-untyped-def]
    csv_path = tmp_path / "plan.csv"
    csv_path.write_text("GlobalId,start,finish\n0000000000000000000000,2025-03-03,2025-03-04\n")
    with pytest.raises(ScheduleError, match="missing from the model"):
        load_schedule(csv_path, "UTC", element_index(bsi_site))
    kept = load_schedule(csv_path, "UTC", element_index(bsi_site), on_missing="drop")
    assert len(kept) == 1 and kept[0].element_ids == ()
    no_cols = tmp_path / "nocols.csv"
    no_cols.write_text("a,b\n1,2\n")
    with pytest.raises(ScheduleError, match="'start' and 'finish'"):
        load_schedule(no_cols, "UTC")
    bad_date = tmp_path / "baddate.csv"
    bad_date.write_text("GlobalId,start,finish\nx,soon,later\n")
    with pytest.raises(ScheduleError, match="bad start"):
        load_schedule(bad_date, "UTC")
    backwards = tmp_path / "backwards.csv"
    backwards.write_text("GlobalId,start,finish\nx,2025-03-05,2025-03-01\n")
    with pytest.raises(ScheduleError, match="finishes before it starts"):
        load_schedule(backwards, "UTC")


@pytest.mark.skipif(not EVENTLOG.is_file(), reason="Schependomlaan event log not present")
def test_schependomlaan_eventlog_csv_refers_to_missing_model() -> None:
    tasks = load_schedule(EVENTLOG, "Europe/Amsterdam")
    assert len(tasks) == 72
    assert len({g for t in tasks for g in t.element_ids}) > 2000
    first = next(t for t in tasks if t.task_id == "ST00060")
    assert first.name == "Stellen bruggetjes"
    assert first.planned_start_ns == ns(2015, 2, 26, tz=AMS)
    # The event log's GUIDs belong to the full design model, not to the design parts here.
    with pytest.raises(ScheduleError, match=r"72 task\(s\) refer to \d+ element\(s\) missing"):
        load_schedule(EVENTLOG, "Europe/Amsterdam", {"2sMqdqIU5BOBeQp_S3Hjru": ("IfcBuildingElementProxy", "")})


def test_state_logic_demolition_and_temporary() -> None:
    def task(tid: str, s: int, f: int, kind: str, el: str) -> ScheduleTask:
        return ScheduleTask(
            task_id=tid,
            name=tid,
            planned_start_ns=s,
            planned_finish_ns=f,
            element_ids=(el,),
            task_type=kind,  # type: ignore[arg-type]
        )

    tasks = [
        task("a", 10, 20, "construction", "wall"),
        task("b", 50, 60, "demolition", "wall"),
        task("c", 30, 40, "temporary", "scaffold"),
    ]
    w = element_windows(tasks)
    assert [planned_state(w["wall"], t) for t in (5, 10, 25, 55, 60)] == [
        "not_started",
        "under_construction",
        "complete",
        "under_demolition",
        "removed",
    ]
    assert [planned_state(w["scaffold"], t) for t in (29, 35, 40)] == ["not_started", "under_construction", "removed"]
    assert planned_state(w.get("other"), 0) == "unscheduled"
    assert schedule_status(w["wall"], 15) == "unknown"


def test_nested_tasks_roll_up_and_bad_nesting_is_refused() -> None:
    def task(tid: str, s: int, f: int, parent: str | None = None, els: tuple[str, ...] = ()) -> ScheduleTask:
        return ScheduleTask(
            task_id=tid, name=tid, planned_start_ns=s, planned_finish_ns=f, element_ids=els, parent_id=parent
        )

    tasks = [
        task("frame", 0, 100),
        task("columns", 0, 50, "frame"),
        task("c1", 0, 20, "columns", ("col1",)),
        task("c2", 20, 50, "columns", ("col2",)),
        task("slab", 50, 100, "frame", ("slab",)),
    ]
    validate_tasks(tasks)
    assert task_ancestors(tasks)["c2"] == ("columns", "frame") and task_ancestors(tasks)["frame"] == ()
    roll = task_elements(tasks)
    assert set(roll["frame"]) == {"col1", "col2", "slab"} and set(roll["columns"]) == {"col1", "col2"}
    assert roll["c1"] == ("col1",)
    # each element keeps its own sub-task's window: a summary names no element, so it does not blur them
    w = element_windows(tasks)
    assert (w["col2"].build_start_ns, w["col2"].build_finish_ns) == (20, 50)
    with pytest.raises(ScheduleError, match="unknown parent 'nowhere'"):
        validate_tasks([*tasks, task("x", 0, 1, "nowhere")])
    with pytest.raises(ScheduleError, match="nested in itself"):
        validate_tasks([task("a", 0, 1, "b"), task("b", 0, 1, "a")])


P6_XML = """<?xml version="1.0" encoding="UTF-8"?>
<APIBusinessObjects xmlns="http://xmlns.oracle.com/Primavera/P6/V8.3/API/BusinessObjects">
 <Calendar><ObjectId>1</ObjectId><Name>Std</Name><Type>Global</Type><HoursPerDay>8</HoursPerDay>
  <StandardWorkWeek><StandardWorkHours><DayOfWeek>Monday</DayOfWeek>
   <WorkTime><Start>08:00:00</Start><Finish>16:00:00</Finish></WorkTime></StandardWorkHours></StandardWorkWeek>
 </Calendar>
 <Project><Name>Demo</Name><ActivityDefaultCalendarObjectId>1</ActivityDefaultCalendarObjectId>
  <WBS><ObjectId>10</ObjectId><Name>Shell</Name><Code>S</Code><ParentObjectId></ParentObjectId></WBS>
  <Activity><Type>Task Dependent</Type><ObjectId>100</ObjectId><WBSObjectId>10</WBSObjectId><Name>Foundations</Name>
   <Id>A100</Id><StartDate>2025-03-03T08:00:00</StartDate><FinishDate>2025-03-04T16:00:00</FinishDate>
   <PlannedDuration>16</PlannedDuration><Status>Completed</Status>
   <ActualStartDate>2025-03-03T08:00:00</ActualStartDate><ActualFinishDate>2025-03-04T12:00:00</ActualFinishDate>
  </Activity>
  <Activity><Type>Task Dependent</Type><ObjectId>101</ObjectId><WBSObjectId>10</WBSObjectId><Name>Walls</Name>
   <Id>A101</Id><StartDate>2025-03-05T08:00:00</StartDate><FinishDate>2025-03-07T16:00:00</FinishDate>
   <PlannedDuration>24</PlannedDuration><Status>Not Started</Status></Activity>
  <Relationship><ObjectId>1000</ObjectId><PredecessorActivityObjectId>100</PredecessorActivityObjectId>
   <SuccessorActivityObjectId>101</SuccessorActivityObjectId><Type>Finish to Start</Type><Lag>0</Lag></Relationship>
 </Project>
</APIBusinessObjects>
"""


def test_primavera_p6_xml_through_ifc4d(tmp_path: Path) -> None:
    path = tmp_path / "p6.xml"
    path.write_text(P6_XML)
    tasks = {t.task_id: t for t in load_schedule(path, "Europe/Amsterdam")}
    assert set(tasks) == {"p6-S", "p6-A100", "p6-A101"}  # WBS node + 2 activities, stable ids
    found, walls, shell = tasks["p6-A100"], tasks["p6-A101"], tasks["p6-S"]
    assert found.name == "Foundations" and walls.name == "Walls" and shell.name == "Shell"
    assert found.planned_start_ns == ns(2025, 3, 3, 7) and found.planned_finish_ns == ns(2025, 3, 4, 15)  # CET
    assert found.actual_finish_ns == ns(2025, 3, 4, 11) and walls.actual_start_ns is None
    assert walls.predecessor_ids == ("p6-A100",)
    # The WBS summary spans its activities.
    assert (shell.planned_start_ns, shell.planned_finish_ns) == (found.planned_start_ns, walls.planned_finish_ns)
