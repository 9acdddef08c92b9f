"""Node contract and runner.

A node declares its inputs (key template, message type, handler method), outputs and config
(a msgspec Struct with ``forbid_unknown_fields``). The runner subscribes, decodes payloads into
Structs, and calls handlers sequentially on one worker thread fed by an inbox (:class:`Inbox`): while it holds
``queue_size`` messages a delivery waits (back-pressure: with congestion control BLOCK the publishers slow down),
but never longer than ``MAX_BLOCK_SECS``; then the message is taken beyond the bound. zenoh delivers on its link
threads: while one waits the whole link stalls, and a publisher blocked long enough takes the transport down
(``wait_before_close``, raised in :meth:`BusConfig.zenoh_config`), losing every later message; short waits keep
the links flowing. Nothing accepted is dropped. A node object may
define ``on_idle()``: it runs after a message when the queue is empty (and at least every ``IDLE_EVERY``
messages), so handlers can mark work dirty and coalesce it. An ``on_idle`` that does a bounded share of its work
returns True while more is pending: it is called again as long as no message waits. A payload that fails to
decode, or a handler that raises, becomes a :class:`~schemas.messages.NodeError` on
``constructaide/{site}/errors``; the node keeps running. So does a message :func:`schemas.validate.problems` refuses
(NaN / infinite numbers, negative sizes, a rotation that is not one, a schedule with a cycle, ...).
Readiness: after subscribing, the node declares the liveliness token
``constructaide/{site}/@live/{node}/{instance}``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
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
from constructaide.runtime.bus import Bus, BusConfig, add_bus_args, open_bus
from schemas import codec, keys, validate
from schemas.messages import Message, NodeError


@dataclass(frozen=True)
class Input:
    """One subscription: ``key`` is a template from :mod:`schemas.keys` (unfilled fields become ``*``).

    ``handler`` names a method ``(msg, key) -> None`` of the node object (``(msg) -> None`` with
    ``with_key=False``); with ``raw=True`` it receives the payload bytes instead of a decoded Struct.
    ``latched=True`` also fetches the last value published as latched (e.g. the BIM model) when the node starts.
    """

    key: str
    type: type[Message]
    handler: str
    raw: bool = False
    latched: bool = False
    fields: dict[str, str] = field(default_factory=dict)
    with_key: bool = True


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

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False) -> None:
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
        deadline = time.monotonic() + self.max_block_secs
        with self._cond:
            while len(self._items) >= self.maxsize:
                if stop is not None and stop.is_set():
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    self.overflows += 1
                    break
                self._cond.wait(min(left, 0.2))
            self._items.append(item)
            self.peak = max(self.peak, len(self._items))
            self._cond.notify_all()
            return True

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
    """A started node: subscriptions, worker thread, liveliness token. Use :func:`start_node`."""

    def __init__(self, spec: NodeSpec, config: Any, bus: Bus, queue_size: int = 64) -> None:
        self.spec = spec
        self.config = config
        self.bus = bus
        site = getattr(config, "site", None)
        if not site:
            raise UserError(f"node {spec.name}: config needs a site")
        self.site: str = site
        self.ctx = NodeContext(bus, self.site, spec.name, tuple(o.key for o in spec.outputs if o.latched))
        self.obj = spec.factory(config, self.ctx)
        self._queue = Inbox(queue_size, MAX_BLOCK_SECS)
        self._subs: list[Any] = []
        self._topics: dict[str, str] = {}
        self._token: Any = None
        self.processed = 0
        self.dropped_after_close = 0
        self._closed = threading.Event()
        self.errors = 0
        self.idle = threading.Event()
        self.idle.set()
        self._worker = threading.Thread(target=self._run, name=f"node-{spec.name}", daemon=True)

    def start(self) -> RunningNode:
        self._worker.start()
        for inp in self.spec.inputs:
            fields = {"site": self.site, **inp.fields}
            ke = keys.pattern(inp.key, **fields) if "{" in inp.key else inp.key
            if inp.key.endswith("/**"):
                ke = keys.site_pattern(self.site)
            self._topics[inp.handler] = ke
            self._subs.append(self.bus.subscribe(ke, self._callback(inp), fetch_latched=inp.latched))
        instance = uuid.uuid4().hex[:8]
        self._token = self.bus.declare_token(
            keys.key(keys.LIVELINESS, site=self.site, node=self.spec.name, instance=instance)
        )
        return self

    def _callback(self, inp: Input) -> Callable[[str, bytes], None]:
        return lambda key, payload: self._enqueue(inp, key, payload)

    def _enqueue(self, inp: Input, key: str, payload: bytes) -> None:
        self.idle.clear()
        # Waits while the inbox is full (back-pressure), at most MAX_BLOCK_SECS, and never past close(): a zenoh
        # callback thread stuck here would keep the process from exiting.
        if not self._queue.put((inp, key, payload), self._closed):
            self.dropped_after_close += 1

    def _run(self) -> None:
        on_idle = getattr(self.obj, "on_idle", None)
        since_idle = 0
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            inp, key, payload = item
            try:
                self._handle(inp, key, payload)
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
                    self.idle.set()

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
        closer = getattr(self.obj, "close", None)
        if callable(closer):
            closer()

    def __enter__(self) -> RunningNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def start_node(spec: NodeSpec, config: Any, bus: Bus, queue_size: int = 64) -> Iterator[RunningNode]:
    """Start a node on a bus; stops it (drains its worker, drops its token) on exit."""
    node = RunningNode(spec, config, bus, queue_size=queue_size)
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
    parser.add_argument("-v", "--verbose", action="store_true")
    add_bus_args(parser)


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
        with open_bus(BusConfig.from_args(args, role=spec.name)) as bus, start_node(spec, config, bus):
            logging.getLogger("constructaide").info(
                "node %s live on site %s (pid %d)", spec.name, config.site, os.getpid()
            )
            stop.wait()
        return 0
    except UserError as e:
        print(f"constructaide-{spec.name}: error: {e}", file=sys.stderr)
        return 2
