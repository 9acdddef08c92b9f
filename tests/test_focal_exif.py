"""One EXIF 35 mm-equivalent focal convention (diagonal crop factor) in ingest and batch registration."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from constructaide import camera as cam
from constructaide.photos import exif_focal
from nodes.register.batch import exif_focal_px


def _jpeg_with_f35(path: Path, w: int, h: int, f35_mm: int) -> None:
    img = Image.fromarray(np.zeros((h, w, 3), np.uint8))
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0xA405] = f35_mm
    img.save(path, exif=exif)


def test_focal_px_from_35mm_uses_the_diagonal():
    # A 36 x 24 mm frame's own 35 mm equivalent is its focal: 50 mm on 3600 x 2400 px (0.01 mm pixels) = 5000 px.
    assert cam.focal_px_from_35mm(50.0, 3600, 2400) == pytest.approx(5000.0)
    # 16:9 frames: the width-based rule (f35 / 36 * W) would be 3.7 % long for 31 mm on 960 x 540.
    f = cam.focal_px_from_35mm(31.0, 960, 540)
    assert f == pytest.approx(31.0 * math.hypot(960, 540) / math.hypot(36, 24))
    assert f < 31.0 / 36.0 * 960 * 0.97


def test_ingest_and_batch_agree(tmp_path: Path):
    path = tmp_path / "a.jpg"
    _jpeg_with_f35(path, 960, 540, 31)
    with Image.open(path) as img:
        f_ingest, f35 = exif_focal(img.getexif(), 960, 540)
    assert f35 == 31
    assert exif_focal_px(path, 960) == pytest.approx(f_ingest)
    assert exif_focal_px(path, 480) == pytest.approx(f_ingest / 2)  # features on a half-size copy
    plain = tmp_path / "b.jpg"
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(plain)
    assert exif_focal_px(plain, 10) is None
