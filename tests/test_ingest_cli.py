"""``constructaide bim summary`` (nodes.ingest.cli.bim_summary_main)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from constructaide.errors import UserError
from nodes.ingest.cli import bim_summary_main

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BSI = DATA / "ifc" / "bsi_construction-scheduling-task.ifc"
pytestmark = pytest.mark.skipif(not BSI.is_file(), reason=f"bSI 4D example not present at {BSI}")


def test_bim_summary_json_and_text(capsys: pytest.CaptureFixture[str]) -> None:
    assert bim_summary_main([str(BSI), "--at", "2010-09-22T12:00", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["elements"] == 5 and s["by_class"] == {"IfcSlab": 1, "IfcWall": 4}
    assert s["by_storey"] == {"Ground Level": 5}
    assert len(s["tasks"]) == 8
    assert s["schedule_start"].startswith("2010-09-20T08:00") and s["schedule_finish"].startswith("2010-09-24T16:00")
    assert s["planned_states"] == {"complete": 2, "under_construction": 1, "not_started": 2}
    assert bim_summary_main([str(BSI), "--at", "2010-09-22T12:00"]) == 0
    text = capsys.readouterr().out
    assert "IfcWall" in text and "tasks: 8" in text and "under_construction 1" in text


def test_bim_summary_bad_input_is_one_line_user_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.ifc"
    bad.write_text("not an ifc")
    with pytest.raises(UserError, match="not an IFC-SPF file"):
        bim_summary_main([str(bad)])
    with pytest.raises(UserError, match="bad --at"):
        bim_summary_main([str(BSI), "--at", "next tuesday"])
    with pytest.raises(UserError, match="schedule file not found"):
        bim_summary_main([str(BSI), "--schedule", str(tmp_path / "none.xml")])
