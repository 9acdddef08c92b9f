"""The site directory layout: which photos are a fixed camera's frames."""

from __future__ import annotations

from constructaide.sitedir import camera_of


def test_camera_of_follows_the_site_layout() -> None:
    assert camera_of("cam-east/20260309T1215.jpg") == "cam-east"
    assert camera_of("cam-east/2026/03/09/1215.jpg") == "cam-east"
    assert camera_of("phone/20260312/IMG_0003.jpg") is None
    assert camera_of("phone/IMG_0003.jpg") is None
    assert camera_of("IMG_0003.jpg") is None
