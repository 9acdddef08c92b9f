"""Shared helpers for bench scripts: machine description and BENCHMARKS.md section writing."""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg()  # timings depend on it: the machine is shared with other jobs
    return (
        f"{os.cpu_count()} cores, {cpu}, Python {platform.python_version()}, {platform.system()} {platform.release()}"
        f"; load average {load[0]:.1f} / {load[2]:.1f} (1 / 15 min) when the section was written"
    )


def code_version() -> str:
    """``git <short commit>`` of the checkout the bench runs from, ``+ uncommitted changes`` when dirty (BENCHMARKS.md
    itself, which an earlier bench run of the same session rewrote, does not count)."""
    import subprocess

    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
        dirty = subprocess.run(  # the benches write BENCHMARKS.md: a changed .md file is not a code change
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":!*.md"], cwd=ROOT, capture_output=True
        )
    except OSError:
        return "git commit unknown"
    if rev.returncode != 0:
        return "git commit unknown"
    return f"git {rev.stdout.strip()}" + (" + uncommitted changes" if dirty.stdout.strip() else "")


def median(values: list[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


def table(headers: list[str], rows: list[list[object]]) -> str:
    def fmt(v: object) -> str:
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def write_section(name: str, body: str, command: str | None = None) -> None:
    """Replace (or append) the ``## name`` section of BENCHMARKS.md."""
    command = command or "python " + " ".join(sys.argv)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    section = f"## {name}\n\n- date: {stamp}\n- machine: {machine()}\n- command: `{command}`\n\n{body.strip()}\n"
    text = BENCHMARKS.read_text() if BENCHMARKS.exists() else "# Benchmarks\n\nFigures measured by `bench/` scripts.\n"
    pattern = re.compile(rf"^## {re.escape(name)}\n.*?(?=^## |\Z)", re.S | re.M)
    text = pattern.sub(section + "\n", text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    BENCHMARKS.write_text(text)
