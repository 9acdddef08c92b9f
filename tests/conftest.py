"""Shared fixtures: data paths, the cached synthetic site, a private zenoh hub port per test."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"
CACHE = Path(os.environ.get("CONSTRUCTAIDE_CACHE", ROOT / ".cache"))


def require_data(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with the reason."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not present: {p}")
    return p


@pytest.fixture(scope="session")
def shared_data() -> Path:
    return require_data()


@pytest.fixture(scope="session")
def small_site() -> Path:
    """The `small` synthetic site (seed 0), generated once and cached under .cache/synth."""
    from constructaide.synth import ensure_site

    return ensure_site("small", 0, CACHE / "synth")


@pytest.fixture(scope="session")
def small_site_seed7() -> Path:
    """The `small` synthetic site generated with seed 7 (no threshold is tuned on it), cached like seed 0."""
    from constructaide.synth import ensure_site

    return ensure_site("small", 7, CACHE / "synth")


@pytest.fixture()
def hub_port() -> Iterator[int]:
    """The port of a loopback hub session opened for the test (bound to a port the system picked, read back): the
    test's sessions and node processes given ``hub_port`` find it taken and join it."""
    from constructaide.runtime import BusConfig, open_bus

    with open_bus(BusConfig(listen=["tcp/127.0.0.1:0"])) as hub:
        yield hub.listen_port()
