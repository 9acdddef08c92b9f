"""Ingest node through the in-process bus: BimModel at start, BimUpdate on reload, Photos from a
watched folder (deduplicated), NodeErrors for bad files while the node keeps going."""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from constructaide.bimgeom import glb_to_meshes, load_bim_model_glb
from constructaide.runtime import start_node
from constructaide.runtime.local import LocalBus
from nodes.ingest.node import SPEC, Config
from schemas import keys
from schemas.messages import BimModel, BimUpdate, NodeError, Photo

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BSI = DATA / "ifc" / "bsi_construction-scheduling-task.ifc"
pytestmark = pytest.mark.skipif(not BSI.is_file(), reason=f"bSI 4D example not present at {BSI}")


def jpeg(seed: int, when: str = "2025:05:01 10:30:00") -> bytes:
    arr = np.random.default_rng(seed).integers(0, 255, (40, 60, 3), dtype=np.uint8)
    ex = Image.Exif()
    ex.get_ifd(0x8769)[0x9003] = when
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="JPEG", exif=ex.tobytes())
    return buf.getvalue()


def test_node_publishes_model_updates_and_photos(tmp_path: Path) -> None:
    model = tmp_path / "model.ifc"
    shutil.copy(BSI, model)
    watch = tmp_path / "inbox"
    (watch / "cam-a").mkdir(parents=True)
    cfg = Config(
        site="t", tz="Europe/Amsterdam", ifc=(str(model),), watch_dir=str(watch), poll_secs=0.05, terrain_height_m=-0.4
    )
    with LocalBus() as bus:
        models = bus.collect(keys.pattern(keys.BIM_MODEL, site="t"))
        updates = bus.collect(keys.pattern(keys.BIM_UPDATE, site="t"))
        photos = bus.collect(keys.pattern(keys.PHOTO, site="t"))
        errors = bus.collect(keys.pattern(keys.ERRORS, site="t"))
        with start_node(SPEC, cfg, bus):
            ((key, bim),) = models.wait(count=1, timeout=60.0)
            assert key == "constructaide/t/bim/model" and isinstance(bim, BimModel)
            assert len(bim.elements) == 5 and len(bim.tasks) == 8 and bim.tz == "Europe/Amsterdam"
            assert bim.terrain_height_m == -0.4  # the configured site ground level travels with the model
            meshes = load_bim_model_glb(bim)
            assert set(meshes) == {e.geometry_ref for e in bim.elements}

            # Photos: one good in a camera folder, the same bytes again (deduplicated), a phone
            # photo at the root and one in the site layout's phone/ folder, a truncated one (NodeError, node keeps
            # going).
            (watch / "cam-a" / "001.jpg").write_bytes(jpeg(1))
            (watch / "cam-a" / "001-copy.jpg").write_bytes(jpeg(1))
            (watch / "phone.jpg").write_bytes(jpeg(2))
            (watch / "phone" / "20260312").mkdir(parents=True)
            (watch / "phone" / "20260312" / "IMG_0001.jpg").write_bytes(jpeg(4))
            (watch / "broken.jpg").write_bytes(jpeg(3)[:300])
            got = photos.wait(count=3, timeout=30.0)
            errs = errors.wait(count=1, timeout=30.0)
            by_key = {k: m for k, m in got}
            assert set(by_key) == {
                "constructaide/t/photo/cam-a",
                "constructaide/t/photo/phone",
            }
            assert isinstance(by_key["constructaide/t/photo/cam-a"], Photo)
            assert by_key["constructaide/t/photo/cam-a"].camera_id == "cam-a"
            assert [m.camera_id for k, m in got if k.endswith("/phone")] == [None, None]
            assert by_key["constructaide/t/photo/cam-a"].source == "watch"
            assert isinstance(errs[0][1], NodeError) and "broken.jpg" in errs[0][1].reason
            assert "truncated" in errs[0][1].reason

            # Raw bytes put by camera software on the upload key: a Photo; a repeat is dropped;
            # non-image bytes become a NodeError from the runtime.
            upload = "constructaide/t/upload/cam-z"
            bus.publish(upload, jpeg(7))
            bus.publish(upload, jpeg(7))
            bus.publish(upload, b"GIF89a not really")
            ((_, up),) = photos.wait(count=4, timeout=30.0)[3:]
            assert up.camera_id == "cam-z" and up.source == "upload"
            errs = errors.wait(count=2, timeout=30.0)
            assert "not an image" in errs[1][1].reason and errs[1][1].key == upload

            # A new revision of the model file: BimUpdate with the changed wall, then the new model.
            text = BSI.read_text().replace("'Wall #2',$,$,#394", "'Wall #2 (rev B)',$,$,#394", 1)
            tmp = tmp_path / "model.ifc.new"
            tmp.write_text(text)
            os.replace(tmp, model)
            ((key_u, upd),) = updates.wait(count=1, timeout=60.0)
            assert isinstance(upd, BimUpdate) and upd.base_revision == bim.revision and upd.revision != bim.revision
            assert [e.name for e in upd.changed] == ["Wall #2 (rev B)"] and upd.added == () and upd.removed == ()
            assert set(glb_to_meshes(upd.geometry_glb)) == {upd.changed[0].geometry_ref}
            second = models.wait(count=2, timeout=60.0)[1][1]
            assert second.revision == upd.revision

            # A broken revision: NodeError, the last good model stays.
            model.write_text(text[: len(text) // 2])
            errs = errors.wait(count=3, timeout=60.0)
            assert "truncated" in errs[2][1].reason and errs[2][1].topic == "bim"
        # Exactly the four good photos were published, never a duplicate.
        assert len(photos.items) == 4


def test_node_reports_bad_model_and_keeps_watching(tmp_path: Path) -> None:
    bad = tmp_path / "bad.ifc"
    bad.write_text("ISO-10303-21;\nHEADER;\nFILE_SCHEMA(('IFC2X3'));\nENDSEC;\nDATA;\n#1=IFCWALL(")
    watch = tmp_path / "inbox"
    watch.mkdir()
    cfg = Config(site="u", tz="UTC", ifc=(str(bad),), watch_dir=str(watch), poll_secs=0.05)
    with LocalBus() as bus:
        photos = bus.collect(keys.pattern(keys.PHOTO, site="u"))
        errors = bus.collect(keys.pattern(keys.ERRORS, site="u"))
        with start_node(SPEC, cfg, bus):
            ((_, err),) = errors.wait(count=1, timeout=30.0)
            assert "truncated" in err.reason and "bad.ifc" in err.reason
            (watch / "a.jpg").write_bytes(jpeg(5))
            ((_, photo),) = photos.wait(count=1, timeout=30.0)
            assert photo.filename == "a.jpg" and photo.width_px == 60


def test_watched_photos_not_republished_after_restart(tmp_path: Path) -> None:
    watch = tmp_path / "inbox"
    watch.mkdir()
    (watch / "a.jpg").write_bytes(jpeg(11))
    cfg = Config(site="r", tz="UTC", watch_dir=str(watch), poll_secs=0.05)
    with LocalBus() as bus:
        photos = bus.collect(keys.pattern(keys.PHOTO, site="r"))
        with start_node(SPEC, cfg, bus):
            photos.wait(count=1, timeout=30.0)
        assert (watch / ".constructaide-seen").is_file()
        (watch / "b.jpg").write_bytes(jpeg(12))
        with start_node(SPEC, cfg, bus):  # restarted: a.jpg is known, only b.jpg is new
            got = photos.wait(count=2, timeout=30.0)
        assert [m.filename for _, m in got] == ["a.jpg", "b.jpg"]
        assert len(photos.items) == 2


def test_model_file_reloaded_only_once_it_stops_changing(tmp_path: Path) -> None:
    """A model file still being written (size or mtime changed since the previous poll) is not read; once its
    signature holds for a poll it is, and an unchanged file never is."""
    from nodes.ingest.watcher import settled_change

    model = tmp_path / "model.ifc"
    text = BSI.read_text()
    model.write_text(text)

    def sig() -> tuple[tuple[int, int], ...]:
        st = model.stat()
        return ((st.st_size, st.st_mtime_ns),)

    loaded = sig()
    assert not settled_change(sig(), loaded, loaded)  # nothing changed
    model.write_text(text[: len(text) // 3])  # a save in progress
    first = sig()
    assert not settled_change(first, loaded, loaded)
    with model.open("a") as f:  # ... still being written at the next poll
        f.write(text[len(text) // 3 :])
    os.utime(model, ns=(first[0][1] + 1_000_000, first[0][1] + 1_000_000))
    second = sig()
    assert second != first and not settled_change(second, loaded, first)
    assert settled_change(sig(), loaded, second)  # the same on two polls: load it
