"""Node contract and runner.

A node declares its inputs (key template, message type, handler method), outputs and config
(a msgspec Struct with ``forbid_unknown_fields``). The runner subscribes, decodes payloads into
Structs, and calls handlers sequentially on one worker thread fed by an inbox (:class:`Inbox`): while it holds
``queue_size`` messages a delivery waits (back-pressure: with congestion control BLOCK the publishers slow down),
but never longer than ``MAX_BLOCK_SECS``; then the message is taken beyond the bound. zenoh delivers on its link
threads: while one waits the whole link stalls, and a publisher blocked long enough takes the transport down
(``wait_before_close``, raised in :meth:`BusConfig.zenoh_config`), losing every later message; short waits keep
the links flowing. Nothing accepted is dropped; a sender pushing faster than the node takes gets one NodeError
(topic ``backpressure``, naming its camera and the queue) per episode, until the inbox runs dry. A node object may
define ``on_idle()``: it runs after a message when the queue is empty (and at least every ``IDLE_EVERY``
messages), so handlers can mark work dirty and coalesce it. An ``on_idle`` that does a bounded share of its work
returns True while more is pending: it is called again as long as no message waits. A payload that fails to
decode, or a handler that raises, becomes a :class:`~schemas.messages.NodeError` on
``constructaide/{site}/errors``; the node keeps running. So does a message :func:`schemas.validate.problems` refuses
(NaN / infinite numbers, negative sizes, a rotation that is not one, a schedule with a cycle, ...).
Readiness: after restoring its state and subscribing, the node declares the liveliness token
``constructaide/{site}/@live/{node}/{instance}``, before it catches up on what it missed while down.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import faulthandler
import logging
import os
import signal
import sys
import threading
import time
import tomllib
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from constructaide.errors import UserError
from constructaide.partition import PARK, SKIP, Partition, Router
from constructaide.photos import photo_problem
from constructaide.runtime.bus import Bus, BusConfig, add_bus_args, open_bus, payload_of
from constructaide.runtime.history import Ledger, Retention, digest, read_state
from schemas import codec, keys, validate
from schemas.messages import Message, NodeError, Photo


@dataclass(frozen=True)
class Input:
    """One subscription: ``key`` is a template from :mod:`schemas.keys` (unfilled fields become ``*``).

    ``handler`` names a method ``(msg, key) -> None`` of the node object (``(msg) -> None`` with
    ``with_key=False``); with ``raw=True`` it receives the payload bytes instead of a decoded Struct.
    ``latched=True`` also fetches the last value published as latched (e.g. the BIM model) when the node starts.
    ``durable=True`` (default): a node started with a state directory also gets, at start, what was published on
    the input while it was down (:mod:`constructaide.runtime.history`), each message handled once.
    ``check_images=True`` (default): a Photo whose ``data`` is not a decodable JPEG/PNG of its declared size is
    refused with a NodeError before the handler (:func:`constructaide.photos.photo_problem`); False only for test
    and bench nodes that carry opaque bytes.
    """

    key: str
    type: type[Message]
    handler: str
    raw: bool = False
    latched: bool = False
    fields: dict[str, str] = field(default_factory=dict)
    with_key: bool = True
    durable: bool = True
    check_images: bool = True


@dataclass(frozen=True)
class Output:
    """A topic the node publishes (declared for documentation, wiring checks and ``describe``)."""

    key: str
    type: type[Message]
    latched: bool = False


@dataclass(frozen=True)
class NodeSpec:
    name: str
    description: str
    config_type: type[Any]
    factory: Callable[[Any, NodeContext], Any]
    inputs: tuple[Input, ...] = ()
    outputs: tuple[Output, ...] = ()

    def describe(self) -> str:
        lines = [f"{self.name}: {self.description}", "inputs:"]
        lines += [f"  {i.key}  {i.type.__name__}  -> {i.handler}" for i in self.inputs]
        lines += ["outputs:"] + [f"  {o.key}  {o.type.__name__}" for o in self.outputs]
        return "\n".join(lines)


class NodeContext:
    """What a node object gets: its site, name, logger and a publish function."""

    def __init__(self, bus: Bus, site: str, node: str, latched_keys: tuple[str, ...] = ()) -> None:
        self.bus = bus
        self.site = site
        self.node = node
        self.log = logging.getLogger(f"constructaide.{node}")
        self._latched_templates = latched_keys
        self.outbox: list[tuple[str, bytes, bool]] | None = None
        """Set by the runtime while a handler of a node that holds its outputs runs: publications wait here."""

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False) -> None:
        if self.outbox is not None:
            self.outbox.append((key, bytes(payload_of(msg)), preview))
            return
        latched = any(keys.parse(t, key) is not None for t in self._latched_templates)
        self.bus.publish(key, msg, preview=preview, latched=latched)

    def error(self, topic: str, reason: str, key: str = "") -> None:
        """Publish a NodeError (for problems found outside a handler, e.g. a folder watcher)."""
        self.log.warning("%s: %s (%s)", topic, reason, key)
        err = NodeError(site=self.site, node=self.node, topic=topic, reason=reason, key=key, time_ns=time.time_ns())
        self.bus.publish(keys.key(keys.ERRORS, site=self.site), err)


_STOP = object()
IDLE_EVERY = 16


MAX_BLOCK_SECS = 0.5  # longest a zenoh delivery thread waits for room (its link stalls meanwhile)


class Inbox:
    """FIFO of a node's pending messages with a soft bound: :meth:`put` waits while ``maxsize`` items are held,
    at most ``max_block_secs``, then appends anyway (``overflows`` counts those). Order is kept."""

    def __init__(self, maxsize: int, max_block_secs: float = MAX_BLOCK_SECS) -> None:
        self.maxsize = max(1, maxsize)
        self.max_block_secs = max_block_secs
        self._items: collections.deque[Any] = collections.deque()
        self._cond = threading.Condition()
        self.overflows = 0
        self.peak = 0

    def put(self, item: Any, stop: threading.Event | None = None) -> bool:
        """Append ``item``, waiting for room up to ``max_block_secs``; False (not appended) when ``stop`` is set
        while waiting."""
        return self.put_checked(item, stop)[0]

    def put_checked(self, item: Any, stop: threading.Event | None = None) -> tuple[bool, bool]:
        """:meth:`put`, also telling whether the item went beyond the bound (it waited ``max_block_secs`` in
        vain): ``(appended, overflowed)``."""
        deadline = time.monotonic() + self.max_block_secs
        over = False
        with self._cond:
            while len(self._items) >= self.maxsize:
                if stop is not None and stop.is_set():
                    return False, False
                left = deadline - time.monotonic()
                if left <= 0:
                    self.overflows += 1
                    over = True
                    break
                self._cond.wait(min(left, 0.2))
            self._items.append(item)
            self.peak = max(self.peak, len(self._items))
            self._cond.notify_all()
            return True, over

    def put_last(self, item: Any) -> None:
        """Append without waiting (the stop marker: after everything already accepted)."""
        with self._cond:
            self._items.append(item)
            self._cond.notify_all()

    def get(self) -> Any:
        """Oldest item, waiting for one."""
        with self._cond:
            while not self._items:
                self._cond.wait()
            item = self._items.popleft()
            self._cond.notify_all()
            return item

    def empty(self) -> bool:
        with self._cond:
            return not self._items


class RunningNode:
    """A started node: subscriptions, worker thread, liveliness token. Use :func:`start_node`.

    With ``state_dir`` the node keeps ``<state_dir>/<site>-<node>.sqlite`` (:class:`Ledger`): what it handled and,
    when the node object has ``state_snapshot() -> dict[str, bytes] | None`` and ``restore_state(dict)``, its state
    (saved with each handled message, in one transaction); at start it restores that state and replays the
    durable inputs' history, skipping what it handled. Values fetched as latched at start are always handled.
    A node object with ``state_every_secs > 0`` (a large state) is snapshotted at most that often: the messages
    handled in between are marked handled with the next snapshot, so a crash re-handles them (at least once).
    With ``hold_outputs = True`` too, what its handlers publish is held and committed with that snapshot (an
    outbox), then sent; a snapshot is also taken whenever the inbox runs dry. A crash then neither loses nor
    repeats an output (the outbox left by a crash between commit and send is sent at the next start).
    A node object with ``adopt_state(sources, owns_camera)`` is handed, after its own restore, the state blobs of
    the other state files of its kind in ``state_dir`` (other worker counts, removed workers, the single instance)
    and a predicate of the cameras it owns: a worker that gains a camera takes over that camera's state.
    """

    def __init__(
        self,
        spec: NodeSpec,
        config: Any,
        bus: Bus,
        queue_size: int = 64,
        state_dir: str | Path | None = None,
        partition: Partition | None = None,
        retention: Retention | None = None,
    ) -> None:
        self.spec = spec
        self.config = config
        self.bus = bus
        site = getattr(config, "site", None)
        if not site:
            raise UserError(f"node {spec.name}: config needs a site")
        self.site: str = site
        self.ctx = NodeContext(bus, self.site, spec.name, tuple(o.key for o in spec.outputs if o.latched))
        self.obj = spec.factory(config, self.ctx)
        worker = f"-w{partition.spec().replace('/', 'of')}" if partition is not None else ""
        path = Path(state_dir or ".") / f"{self.site}-{spec.name}{worker}.sqlite"
        self.ledger = Ledger(path, retention) if state_dir else None
        self._caught_up = False  # the start's history is queued: the ledger may be pruned (Retention)
        self.replayed = 0
        self.duplicates = 0
        self._inflight: set[str] = set()
        self._uncommitted: list[tuple[str, str]] = []
        self._hold = self.ledger is not None and bool(getattr(self.obj, "hold_outputs", False))
        self._held_out: list[tuple[str, bytes, bool]] = []
        self._last_snapshot = time.monotonic()
        self._held: list[tuple[Input, str, bytes]] | None = None
        self._guard = threading.Lock()
        self._fetching = threading.local()
        restore = getattr(self.obj, "restore_state", None)
        if self.ledger is not None and callable(restore):
            saved = self.ledger.load_state()
            if saved:
                restore(saved)
                self.ctx.log.info("state restored from %s", self.ledger.path)
        adopt = getattr(self.obj, "adopt_state", None)
        if self.ledger is not None and callable(adopt):
            # Hand-over: the state files of the node kind's other workers (another worker count, a removed worker,
            # the single instance) lie beside this one's; the node takes its cameras' state from them (the freshest
            # per camera; a single instance owns every camera).
            folder = self.ledger.path.parent
            others = [folder / f"{self.site}-{spec.name}.sqlite"]
            others += sorted(folder.glob(f"{self.site}-{spec.name}-w*of*.sqlite"))
            sources = [read_state(p) for p in others if p != self.ledger.path and p.exists()]
            sources = [b for b in sources if b]
            if sources:
                adopt(sources, partition.owns_camera if partition is not None else lambda _camera: True)
        self._queue = Inbox(queue_size, MAX_BLOCK_SECS)
        self._pressure: dict[str, int] = {}  # camera / topic -> messages beyond the bound in this episode
        self._subs: list[Any] = []
        self._topics: dict[str, str] = {}
        self._token: Any = None
        self.processed = 0
        self.dropped_after_close = 0
        self._closed = threading.Event()
        self.errors = 0
        self.handled: collections.Counter[str] = collections.Counter()  # messages handled per handler
        self.idle = threading.Event()
        self.idle.set()
        self._worker = threading.Thread(target=self._run, name=f"node-{spec.name}", daemon=True)
        # Partitioned worker (constructaide.partition): only its cameras' and phone photos' messages are handled.
        self.partition = partition
        self.router = Router(partition) if partition is not None else None

    def start(self) -> RunningNode:
        self._worker.start()
        if self.ledger is not None:
            self._held = []  # live messages wait until the history is queued (publication order)
        for inp in self.spec.inputs:
            fields = {"site": self.site, **inp.fields}
            ke = keys.pattern(inp.key, **fields) if "{" in inp.key else inp.key
            if inp.key.endswith("/**"):
                ke = keys.site_pattern(self.site)
            self._topics[inp.handler] = ke
            kes = [ke]
            if self.partition is not None and "{camera}" in inp.key and "camera" not in inp.fields:
                kes = self.partition.camera_keyexprs(inp.key, **fields)  # this worker's cameras and the phone pool
            for k in kes:
                self._fetching.latched = True  # latched values arrive on this thread inside subscribe()
                try:
                    self._subs.append(self.bus.subscribe(k, self._callback(inp), fetch_latched=inp.latched))
                finally:
                    self._fetching.latched = False
        # Live once subscribed and restored: the catch-up below (what was published while the node was down) can
        # take as long as handling it, and the live messages that come meanwhile are held and handled after it in
        # publication order; a supervisor or a dashboard sees the node back at once, not after its backlog.
        instance = uuid.uuid4().hex[:8]
        if self.partition is not None:
            instance = f"w{self.partition.spec().replace('/', 'of')}-{instance}"
        self._token = self.bus.declare_token(
            keys.key(keys.LIVELINESS, site=self.site, node=self.spec.name, instance=instance)
        )
        if self.ledger is not None:
            self._send_outbox(self.ledger.outbox())
            self._replay()
        return self

    def _callback(self, inp: Input) -> Callable[[str, bytes], None]:
        def on_message(key: str, payload: bytes) -> None:
            self._enqueue(inp, key, payload)

        return on_message

    def _replay(self) -> None:
        """Queue what the durable inputs missed since the ledger began (oldest first), then the held live ones."""
        assert self.ledger is not None
        found = []
        for inp in self.spec.inputs:
            if inp.durable:
                ke = self._topics[inp.handler]
                found += [(p.time_ns, i, inp, p) for i, p in enumerate(self.bus.history(ke, self.ledger.since_ns))]
        found.sort(key=lambda t: (t[0], t[1]))
        for _, _, inp, pub in found:
            if self._enqueue(inp, pub.key, pub.payload, held_ok=False):
                self.replayed += 1
        with self._guard:
            held, self._held = self._held or [], None
        for inp, key, payload in held:
            self._enqueue(inp, key, payload, held_ok=False)
        self._caught_up = True
        if self.replayed:
            self.ctx.log.info("replayed %d messages published while the node was down", self.replayed)

    def _enqueue(self, inp: Input, key: str, payload: bytes, held_ok: bool = True) -> bool:
        """Queue one message; False when it is skipped (handled already, or queued already)."""
        item: tuple[Input, str, bytes, str | None] = (inp, key, payload, None)
        if self.ledger is not None:
            dig = digest(key, payload)
            latched_fetch = getattr(self._fetching, "latched", False)
            with self._guard:
                if held_ok and self._held is not None and not latched_fetch:
                    self._held.append((inp, key, payload))
                    return True
                if dig in self._inflight or (not latched_fetch and self.ledger.is_done(dig)):
                    self.duplicates += 1
                    return False
                self._inflight.add(dig)
            item = (inp, key, payload, dig)
        self.idle.clear()
        # Waits while the inbox is full (back-pressure), at most MAX_BLOCK_SECS, and never past close(): a zenoh
        # callback thread stuck here would keep the process from exiting.
        ok, over = self._queue.put_checked(item, self._closed)
        if not ok:
            self.dropped_after_close += 1
            return False
        if over:
            self._overloaded(inp, key)
        return True

    def _overloaded(self, inp: Input, key: str) -> None:
        """A message went beyond the full inbox: its sender pushes faster than this node takes. One NodeError per
        camera (or topic) and episode (until the inbox runs dry), naming the camera and the queue; nothing is
        dropped (the message is queued beyond the bound, so latency grows)."""
        fields = keys.parse(inp.key, key) or {}
        source = fields.get("camera") or self._topics.get(inp.handler, inp.key)
        with self._guard:
            if source in self._pressure:
                self._pressure[source] += 1
                return
            self._pressure[source] = 1
        worker = f" worker {self.partition.spec()}" if self.partition is not None else ""
        what = f"camera {source}" if fields.get("camera") else f"topic {source}"
        self.ctx.error(
            "backpressure",
            f"{what} pushes faster than node {self.spec.name}{worker} takes: its inbox ({inp.handler}, "
            f"{self._queue.maxsize} messages) stayed full for {self._queue.max_block_secs:g} s; messages are queued "
            "beyond the bound (none dropped, latency grows) until it drains",
            key,
        )

    def _run(self) -> None:
        on_idle = getattr(self.obj, "on_idle", None)
        since_idle = 0
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            inp, key, payload, dig = item
            try:
                if self._hold:
                    self.ctx.outbox = self._held_out
                try:
                    self._handle(inp, key, payload)
                finally:
                    self.ctx.outbox = None
                if dig is not None:
                    self._mark_done(dig, key)
                since_idle += 1
                # Coalescing hook: work deferred by handlers runs when the queue is drained (or every
                # IDLE_EVERY messages under a continuous stream, so it never starves).
                if callable(on_idle) and (self._queue.empty() or since_idle >= IDLE_EVERY):
                    since_idle = 0
                    # more pending (True): go on while nothing waits, else the next message comes first
                    while self._call_idle(on_idle) and self._queue.empty():
                        pass
            finally:
                if self._queue.empty():
                    if self._pressure:
                        with self._guard:
                            done, self._pressure = self._pressure, {}
                        self.ctx.log.info(
                            "back-pressure episode over: %s",
                            ", ".join(f"{k} ({n} beyond the bound)" for k, n in done.items()),
                        )
                    self.idle.set()

    def _mark_done(self, dig: str, key: str, final: bool = False) -> None:
        assert self.ledger is not None
        if dig:
            self._uncommitted.append((dig, key))
        every = float(getattr(self.obj, "state_every_secs", 0.0) or 0.0)
        due = time.monotonic() - self._last_snapshot >= every or (self._hold and self._queue.empty())
        if not final and every > 0 and not due:
            return  # stays in _inflight (handled in this run) until the next snapshot commits it
        self._last_snapshot = time.monotonic()
        snap = getattr(self.obj, "state_snapshot", None)
        try:
            state = snap() if callable(snap) else None
        except Exception as e:
            self.errors += 1
            self.ctx.log.debug("state_snapshot failed", exc_info=True)
            self.ctx.error("state", f"cannot snapshot the node state: {type(e).__name__}: {e}", key)
            state = None
        handled, self._uncommitted = self._uncommitted, []
        out, self._held_out = self._held_out, []
        seqs = self.ledger.done_many(handled, state, out)
        with self._guard:
            self._inflight.difference_update(d for d, _ in handled)
        if self._caught_up and self.ledger.maybe_prune():
            self.ctx.log.info("ledger pruned: %d rows kept, history since %d", self.ledger.handled_count(),
                              self.ledger.since_ns)  # fmt: skip
        self._send_outbox(list(zip(seqs, out, strict=True)))

    def _send_outbox(self, out: list[tuple[int, tuple[str, bytes, bool]]]) -> None:
        assert self.ledger is not None
        for seq, (key, payload, preview) in out:
            latched = any(keys.parse(t, key) is not None for t in self.ctx._latched_templates)
            self.bus.publish(key, payload, preview=preview, latched=latched)
            self.ledger.sent(seq)

    def _call_idle(self, on_idle: Callable[[], object]) -> bool:
        """Run the hook; True when it says more work is pending (False after a failure: no retry loop)."""
        try:
            return on_idle() is True
        except Exception as e:
            self.errors += 1
            self.ctx.log.debug("on_idle failed", exc_info=True)
            self.ctx.error("on_idle", f"{type(e).__name__}: {e}")
            return False

    def _handle(self, inp: Input, key: str, payload: bytes) -> None:
        router = self.router
        if router is None:
            self._handle_now(inp, key, payload)
            return
        verdict = router.route(inp.key, key, lambda: _ids_of(payload).photo_id)
        if verdict == SKIP:
            return
        if verdict == PARK:
            router.park(router.photo_of_key(inp.key, key) or "", (inp, key, payload))
            return
        if "photo_ids" in getattr(inp.type, "__struct_fields__", ()):
            ids = _ids_of(payload).photo_ids  # e.g. the SparseCloud of another register worker's cameras
            if ids and not router.owns_any(ids):
                router.skipped += 1
                return
        # Messages parked for a photo now owned were published before it (anchor clicks sent ahead of the photo):
        # they are handled first, in their publication order, as an unpartitioned node would (the register node
        # then registers the photo from its clicks instead of trying it without them first).
        for item in router.release():
            self._handle_now(*item)
        self._handle_now(inp, key, payload)

    def _handle_now(self, inp: Input, key: str, payload: bytes) -> None:
        try:
            if inp.raw:
                msg: Any = payload
            else:
                msg = codec.decode(payload, None if inp.type is Message else inp.type)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            self.errors += 1
            self.ctx.error(self._topics.get(inp.handler, inp.key), f"cannot decode {inp.type.__name__}: {e}", key)
            return
        bad = [] if inp.raw else validate.problems(msg)  # NaN poses, negative sizes, schedule cycles, ...
        if not bad and inp.check_images and isinstance(msg, Photo):
            bad = [p for p in (photo_problem(msg),) if p]  # garbage / truncated / bomb bodies, wrong size
        if bad:
            self.errors += 1
            self.ctx.error(
                self._topics.get(inp.handler, inp.key), f"invalid {type(msg).__name__}: {'; '.join(bad)}", key
            )
            return
        try:
            handler = getattr(self.obj, inp.handler)
            if inp.with_key:
                handler(msg, key)
            else:
                handler(msg)
            self.processed += 1
            self.handled[inp.handler] += 1
        except Exception as e:  # the node survives any handler failure
            self.errors += 1
            self.ctx.log.debug("handler failed", exc_info=True)
            self.ctx.error(self._topics.get(inp.handler, inp.key), f"{type(e).__name__}: {e}", key)

    def wait_idle(self, timeout: float = 30.0) -> bool:
        """Wait until the queue is drained and the last message handled."""
        return self.idle.wait(timeout)

    def close(self) -> None:
        if self._token is not None:
            self._token.close()
            self._token = None
        for s in self._subs:
            s.close()
        self._subs.clear()
        if self._worker.is_alive():
            self._queue.put_last(_STOP)  # after everything already queued: nothing accepted is dropped
            self._worker.join(timeout=60)
        self._closed.set()
        if self.router is not None and self.partition is not None:
            self.ctx.log.info(
                "worker %s: handled %s; skipped %d messages of other workers, %d parked ones dropped",
                self.partition.spec(),
                " ".join(f"{h}={n}" for h, n in sorted(self.handled.items())) or "nothing",
                self.router.skipped,
                self.router.parked_dropped,
            )
        if self.ledger is not None and self._uncommitted:
            self._mark_done("", "", final=True)  # the last snapshot: a clean stop re-handles nothing
        closer = getattr(self.obj, "close", None)
        if callable(closer):
            closer()
        if self.ledger is not None:
            self.ledger.close()

    def __enter__(self) -> RunningNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _Ids(msgspec.Struct):
    """The photo id(s) of any message, read without decoding the rest (image bytes are skipped)."""

    photo_id: str | None = None
    photo_ids: tuple[str, ...] = ()


_ids_decoder = msgspec.msgpack.Decoder(_Ids)


def _ids_of(payload: bytes) -> _Ids:
    try:
        return _ids_decoder.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return _Ids()  # the handler reports the bad payload


@contextlib.contextmanager
def start_node(
    spec: NodeSpec,
    config: Any,
    bus: Bus,
    queue_size: int = 64,
    state_dir: str | Path | None = None,
    partition: Partition | None = None,
    retention: Retention | None = None,
) -> Iterator[RunningNode]:
    """Start a node on a bus; stops it (drains its worker, drops its token) on exit. With ``partition`` it is one
    worker of several of its kind (:mod:`constructaide.partition`); ``retention``: how long the ledger keeps
    handled rows (default :class:`Retention`)."""
    node = RunningNode(
        spec, config, bus, queue_size=queue_size, state_dir=state_dir, partition=partition, retention=retention
    )
    try:
        node.start()
        yield node
    finally:
        node.close()


# ---------------------------------------------------------------------- config


def parse_override(text: str) -> tuple[list[str], Any]:
    """``a.b=value`` -> (['a', 'b'], value) with the value parsed as TOML when it is valid TOML."""
    if "=" not in text:
        raise UserError(f"--set takes name=value, got {text!r}")
    name, raw = text.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return name.strip().split("."), value


def load_config(
    config_type: type[Any],
    path: str | Path | None = None,
    section: str | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    **direct: Any,
) -> Any:
    """Build a node config from a TOML file (optionally one ``[section]``), ``--set`` overrides and keywords."""
    data: dict[str, Any] = {}
    if path:
        try:
            doc = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise UserError(f"config file not found: {path}") from None
        except tomllib.TOMLDecodeError as e:
            raise UserError(f"config file {path} is not valid TOML: {e}") from None
        if section:
            for part in section.split("."):
                doc = doc.get(part, {})
        data.update(doc)
    for item in overrides:
        names, value = parse_override(item)
        cur = data
        for n in names[:-1]:
            cur = cur.setdefault(n, {})
        cur[names[-1]] = value
    data.update({k: v for k, v in direct.items() if v is not None})
    try:
        return msgspec.convert(data, config_type, strict=False)
    except msgspec.ValidationError as e:
        raise UserError(f"bad config for {config_type.__module__}: {e}") from None


def add_node_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--site", help="site id (overrides the config)")
    parser.add_argument("--config", help="TOML config file")
    parser.add_argument("--section", help="table of the TOML file holding this node's config (e.g. nodes.register)")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override one config field")
    parser.add_argument("--describe", action="store_true", help="print the node's inputs/outputs and exit")
    parser.add_argument(
        "--state-dir",
        default=os.environ.get("CONSTRUCTAIDE_STATE_DIR") or None,
        help="folder of the node's SQLite ledger/state: resume after a crash, get what was missed "
        "(default $CONSTRUCTAIDE_STATE_DIR; none: start empty)",
    )
    parser.add_argument(
        "--ledger-keep-days",
        type=float,
        default=Retention().keep_days,
        help="days the ledger keeps handled-message ids (0: no age limit; default %(default)s)",
    )
    parser.add_argument(
        "--ledger-max-rows",
        type=int,
        default=Retention().max_rows,
        help="about this many handled-message ids kept at most (0: no limit; default %(default)s)",
    )
    parser.add_argument("-v", "--verbose", action="store_true")
    parser.add_argument(
        "--partition", metavar="I/N", help="run as worker I of N of this node kind (cameras by rendezvous hashing)"
    )
    parser.add_argument(
        "--cameras", default="", help="the site's fixed camera ids, comma-separated (a worker subscribes to its own)"
    )
    add_bus_args(parser)


BUS_CLOSE_SECS = 15.0
"""How long a stopping node waits for its bus session to close before it exits anyway (run_node_cli)."""


def run_node_cli(spec: NodeSpec, argv: list[str] | None = None, *, prog: str | None = None) -> int:
    """Console entry for a node: parse args, open the bus, run until Ctrl-C / SIGTERM."""
    parser = argparse.ArgumentParser(prog=prog or f"constructaide-{spec.name}", description=spec.description)
    add_node_args(parser)
    args = parser.parse_args(argv)
    if args.describe:
        print(spec.describe())
        return 0
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format=f"%(asctime)s {spec.name} %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    try:
        config = load_config(spec.config_type, args.config, args.section, args.set, site=args.site)
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        if hasattr(signal, "SIGUSR1"):  # `kill -USR1 PID`: every thread's stack to stderr (a node that will not stop)
            faulthandler.register(signal.SIGUSR1, all_threads=True)
        try:
            partition = Partition.parse(args.partition, args.cameras.split(",")) if args.partition else None
        except ValueError as e:
            raise UserError(str(e)) from None
        if args.ledger_keep_days < 0 or args.ledger_max_rows < 0:
            raise UserError("--ledger-keep-days and --ledger-max-rows must be >= 0")
        retention = Retention(keep_days=args.ledger_keep_days, max_rows=args.ledger_max_rows)
        try:
            bus_config = BusConfig.from_args(args, role=spec.name)
            if args.partition:  # workers of one kind apart in Bus.mesh_gaps, named as the launcher names them
                bus_config.name = f"{spec.name}-{args.partition.replace('/', 'of')}"
            with open_bus(bus_config) as bus:
                try:
                    with start_node(
                        spec, config, bus, state_dir=args.state_dir, partition=partition, retention=retention
                    ):
                        logging.getLogger("constructaide").info(
                            "node %s live on site %s (pid %d); bus: %s",
                            spec.name,
                            config.site,
                            os.getpid(),
                            bus.topology(),
                        )
                        stop.wait()
                finally:
                    # The node has drained its queue and saved its state: a zenoh session that does not close (a
                    # wedged link) must not keep the process; its threads' stacks go to stderr, then it exits (1).
                    faulthandler.dump_traceback_later(BUS_CLOSE_SECS, exit=True)
        finally:
            faulthandler.cancel_dump_traceback_later()
        return 0
    except UserError as e:
        print(f"constructaide-{spec.name}: error: {e}", file=sys.stderr)
        return 2
