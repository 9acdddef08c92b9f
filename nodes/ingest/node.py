"""Ingest node: publishes the site's BIM (``BimModel``, then ``BimUpdate`` per changed revision)
and photos found in a watched folder (``Photo``).

One background thread loads the configured IFC files and schedule, publishes the model
(latched, so late joiners get it), then polls the watched folder and the model files every
``poll_secs``; a changed model file is loaded once its size and mtime were the same on two consecutive polls
(a save or copy in progress is not read half-written). Problems found there become ``NodeError`` messages; the
node keeps the last good model and keeps watching. Photo files are never moved or deleted.

Cameras with their own software either publish ``Photo`` messages on ``keys.PHOTO`` or put the
raw JPEG/PNG bytes on :data:`UPLOAD` (``constructaide/{site}/upload/{camera}``); the node turns
those into ``Photo`` messages (same checks and de-duplication as for files).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from constructaide.bim.ifc import load_site_model
from constructaide.bim.model import SiteModel
from constructaide.photos import PhotoError, photo_from_bytes
from constructaide.runtime import Input, NodeContext, NodeSpec, Output, run_node_cli
from constructaide.sitedir import camera_of
from nodes.ingest.config import Config
from nodes.ingest.revisions import diff_models, revision_id, to_bim_model
from nodes.ingest.watcher import FolderWatcher, SeenHashes, Signature, content_hash, file_signature, settled_change
from schemas import keys
from schemas.messages import BimModel, BimUpdate, Photo
from schemas.messages import NodeError as NodeErrorMsg

UPLOAD = keys.UPLOAD
"""Raw image bytes put by camera software; ``camera`` = camera id or ``phone``."""


class IngestNode:
    """Owns the current site model revision and the folder watcher."""

    def __init__(self, config: Config, ctx: NodeContext) -> None:
        self.config = config
        self.ctx = ctx
        self.site_model: SiteModel | None = None
        self.revision = ""
        self._model_sig: Signature | None = None
        self._changing_sig: Signature | None = None  # the model files' signature on the previous poll
        self._lock = threading.Lock()
        self.watcher = FolderWatcher(config.watch_dir) if config.watch_dir else None
        self.seen = SeenHashes(config.seen_capacity, self._seen_path())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="ingest-poll", daemon=True)
        self._thread.start()

    def _seen_path(self) -> Path | None:
        if self.config.seen_path:
            return Path(self.config.seen_path)
        if not self.config.watch_dir:
            return None
        path = Path(self.config.watch_dir) / ".constructaide-seen"
        try:
            with path.open("a", encoding="ascii"):
                pass
        except OSError as exc:
            self.ctx.log.warning("cannot persist seen photo hashes in %s (%s); memory only", path, exc)
            return None
        return path

    # -- model -------------------------------------------------------------------------------

    def _model_paths(self) -> list[Path]:
        return [Path(p) for p in self.config.ifc] + ([Path(self.config.schedule)] if self.config.schedule else [])

    def _signature(self) -> Signature:
        return file_signature(self._model_paths())

    def _load(self) -> SiteModel:
        c = self.config
        offset = self.site_model.origin_offset_m if self.site_model is not None else None
        return load_site_model(
            c.ifc,
            tz=c.tz or "UTC",
            schedule_path=c.schedule or None,
            threads=c.threads or None,
            origin_offset_m=offset,
            on_missing=c.on_missing,
        )

    def reload(self) -> BimUpdate | None:
        """Load the configured files; publish the first revision as ``BimModel``, later changed
        revisions as ``BimUpdate`` (and the new ``BimModel``, latched). Returns the update or
        ``None`` (first load or no change). Raises on bad input; the previous model stays."""
        if not self.config.ifc:
            return None
        with self._lock:
            sig = self._signature()
            missing = [str(p) for p in self._model_paths() if not p.is_file()]
            if missing:
                raise ValueError(f"model file(s) not found: {', '.join(missing)}")
            rev = revision_id(self._model_paths())
            if self.site_model is not None and rev == self.revision:
                self._model_sig = sig  # touched, same content
                return None
            site_model = self._load()
            self._model_sig = sig
            if site_model.tasks and not self.config.tz:
                self.ctx.log.warning("no site tz configured: schedule dates without offset are taken as UTC")
            old, old_rev = self.site_model, self.revision
            self.site_model, self.revision = site_model, rev
            for w in site_model.warnings:
                self.ctx.log.warning("%s", w)
            update = None
            if old is not None:
                update = diff_models(old, site_model, site=self.ctx.site, base_revision=old_rev, revision=rev)
                self.ctx.publish(keys.key(keys.BIM_UPDATE, site=self.ctx.site), update)
            model = to_bim_model(site_model, self.ctx.site, rev, self.config.terrain_height_m)
            self.ctx.publish(keys.key(keys.BIM_MODEL, site=self.ctx.site), model)
            self.ctx.log.info(
                "published BIM revision %s: %d elements, %d tasks", rev, len(site_model.elements), len(site_model.tasks)
            )
            return update

    def _try_reload(self) -> None:
        try:
            self.reload()
        except Exception as exc:  # any bad input: report, keep the last good model
            self._model_sig = self._signature()  # do not retry the same broken files every poll
            self.ctx.error("bim", f"{type(exc).__name__}: {exc}", ",".join(self.config.ifc))

    # -- photos ------------------------------------------------------------------------------

    def _camera_for(self, path: Path) -> str | None:
        assert self.watcher is not None
        rel = path.relative_to(self.watcher.root).as_posix()
        if "/" in rel:
            return camera_of(rel)  # the site layout: <camera>/..., phone/... for phones
        return self.config.camera_id or None

    def poll_photos(self) -> list[Photo]:
        """Publish every new complete photo file of ``watch_dir`` once; returns what was published."""
        if self.watcher is None:
            return []
        out = []
        for path in self.watcher.poll():
            topic = f"watch:{self.config.watch_dir}"
            try:
                data = path.read_bytes()
                raw_hash = content_hash(data)
                if raw_hash in self.seen:
                    self.ctx.log.info("%s: already published (same content), skipped", path.name)
                    continue
                camera = self._camera_for(path)
                if camera is not None:
                    keys.check_chunk(camera, "camera")
                photo = photo_from_bytes(
                    data,
                    site=self.ctx.site,
                    camera_id=camera,
                    tz=self.config.tz or None,
                    filename=path.name,
                    source="watch",
                    fallback_time_ns=path.stat().st_mtime_ns if self.config.use_mtime else None,
                    max_pixels=self.config.max_pixels,
                    future_tolerance_s=self.config.future_tolerance_s,
                )
            except (PhotoError, ValueError, OSError) as exc:
                self.ctx.error(topic, f"{path.name}: {exc}", str(path))
                continue
            self.ctx.publish(keys.key(keys.PHOTO, site=self.ctx.site, camera=photo.camera_id), photo)
            self.seen.add(raw_hash)
            out.append(photo)
        return out

    def on_upload(self, payload: bytes, key: str) -> None:
        """Raw JPEG/PNG bytes from camera software -> ``Photo`` on ``keys.PHOTO`` (duplicates dropped).

        Raises PhotoError for bad images (the runtime publishes it as a NodeError)."""
        fields = keys.parse(UPLOAD, key) or {}
        camera = fields.get("camera")
        camera_id = None if camera in (None, keys.PHONE) else camera
        raw_hash = content_hash(payload)
        if raw_hash in self.seen:
            self.ctx.log.info("upload on %s: already published (same content), skipped", key)
            return
        photo = photo_from_bytes(
            payload,
            site=self.ctx.site,
            camera_id=camera_id,
            tz=self.config.tz or None,
            source="upload",
            fallback_time_ns=time.time_ns() if self.config.use_receive_time else None,
            max_pixels=self.config.max_pixels,
            future_tolerance_s=self.config.future_tolerance_s,
        )
        self.ctx.publish(keys.key(keys.PHOTO, site=self.ctx.site, camera=photo.camera_id), photo)
        self.seen.add(raw_hash)

    # -- loop --------------------------------------------------------------------------------

    def _loop(self) -> None:
        self._try_reload()
        while not self._stop.wait(self.config.poll_secs):
            if self.config.ifc and self.config.watch_model_files:
                sig = self._signature()
                if settled_change(sig, self._model_sig, self._changing_sig):
                    self._try_reload()
                self._changing_sig = sig
            try:
                self.poll_photos()
            except Exception as exc:  # never let the watcher thread die
                self.ctx.error(f"watch:{self.config.watch_dir}", f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=60)


SPEC = NodeSpec(
    name="ingest",
    description="Loads IFC models + schedules (BimModel/BimUpdate) and photos from a watched folder or raw uploads.",
    config_type=Config,
    factory=IngestNode,
    inputs=(Input(UPLOAD, Photo, "on_upload", raw=True),),
    outputs=(
        Output(keys.BIM_MODEL, BimModel, latched=True),
        Output(keys.BIM_UPDATE, BimUpdate),
        Output(keys.PHOTO, Photo),
        Output(keys.ERRORS, NodeErrorMsg),
    ),
)


def main(argv: list[str] | None = None) -> int:
    return run_node_cli(SPEC, argv)


if __name__ == "__main__":
    raise SystemExit(main())
