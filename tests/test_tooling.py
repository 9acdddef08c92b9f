"""ruff (check + format) and mypy are part of the test suite, so CI enforces them."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PATHS = ["schemas", "constructaide", "nodes", "tests", "bench"]


def _tool(name: str) -> list[str]:
    exe = Path(sys.executable).with_name(name)
    if exe.exists():
        return [str(exe)]
    found = shutil.which(name)
    if found is None:
        pytest.skip(f"{name} not installed (pip install -e '.[test]')")
    return [found]


def test_ruff_check() -> None:
    r = subprocess.run([*_tool("ruff"), "check", *PATHS], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_ruff_format() -> None:
    r = subprocess.run([*_tool("ruff"), "format", "--check", *PATHS], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_mypy_on_schemas_and_core() -> None:
    r = subprocess.run([*_tool("mypy")], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def _imported_modules(path: Path) -> set[str]:
    """Every absolute module name a file imports (top-level and inside functions)."""
    import ast

    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
    return out


def test_import_direction() -> None:
    """The core (``constructaide`` outside ``constructaide/app``) and ``schemas`` never import a node; a node never
    imports another node."""
    bad = []
    for path in sorted((ROOT / "constructaide").rglob("*.py")) + sorted((ROOT / "schemas").rglob("*.py")):
        if (ROOT / "constructaide" / "app") in path.parents:
            continue
        bad += [f"{path.relative_to(ROOT)} imports {m}" for m in _imported_modules(path) if m.split(".")[0] == "nodes"]
    for path in sorted((ROOT / "nodes").rglob("*.py")):
        own = path.relative_to(ROOT / "nodes").parts[0]
        for m in _imported_modules(path):
            parts = m.split(".")
            if parts[0] == "nodes" and len(parts) > 1 and parts[1] != own:
                bad.append(f"{path.relative_to(ROOT)} imports {m}")
    assert not bad, "\n".join(bad)
