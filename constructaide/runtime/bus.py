"""The bus a node talks to: zenoh in production, an in-process twin for tests.

Both implement :class:`Bus`. Payloads are msgpack bytes of :mod:`schemas` messages. Data topics
use reliable delivery with congestion control BLOCK (a slow subscriber slows the publisher
instead of losing data); ``preview=True`` publishes with DROP for ring-buffer style previews.
``latched=True`` keeps the last payload of a key and serves it to late joiners through a
queryable (e.g. the BIM model): a subscriber that asks with ``fetch_latched=True`` gets it.
Every session also keeps its recent data publications (:class:`~constructaide.runtime.history.PublicationCache`)
and answers :meth:`Bus.history` queries over them, so a restarted node gets what was published while it was down.

Large payloads (above ``BusConfig.chunk_bytes``, 4 MiB by default) travel in parts of at most ``chunk_bytes``, each
with a part header as zenoh attachment (:mod:`constructaide.runtime.chunks`), on every path: live puts (BLOCK),
latched replies (the last transfer of a key, served part by part) and history replies. Every subscription, latched
fetch and history query reassembles them: callbacks and :meth:`Bus.history` only ever see whole payloads, once
per transfer, and only when the sha256 matches. Payloads up to ``chunk_bytes`` go unchanged, with no attachment.
Previews are never chunked: a preview above ``chunk_bytes`` is not sent (a warning), since parts sent with DROP
could arrive incomplete and a ring-buffer preview is lossy by contract anyway.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from constructaide.runtime.chunks import Reassembler, Receiver, Transfer, unpack
from constructaide.runtime.history import HISTORY_ROOT, Publication, PublicationCache
from schemas import codec
from schemas.messages import Message

if TYPE_CHECKING:
    from constructaide.runtime.security import BusSecurity

log = logging.getLogger("constructaide.bus")

DEFAULT_HUB_PORT = 7447
BLOCK_WAIT_BEFORE_CLOSE_US = 120_000_000  # 2 min: see BusConfig.zenoh_config
DEFAULT_HISTORY_MB = 128.0  # publication cache of a session ($CONSTRUCTAIDE_HISTORY_MB)
DEFAULT_CHUNK_MIB = 4.0  # largest payload sent whole; larger ones go in parts of this size ($CONSTRUCTAIDE_CHUNK_MIB)
DEFAULT_CHUNK_BUFFER_MIB = 512.0  # incomplete transfers a subscription holds ($CONSTRUCTAIDE_CHUNK_BUFFER_MIB)
Callback = Callable[[str, bytes], None]


class Closeable(Protocol):
    def close(self) -> None: ...


def default_chunk_bytes() -> int:
    return int(float(os.environ.get("CONSTRUCTAIDE_CHUNK_MIB", DEFAULT_CHUNK_MIB)) * 2**20)


def default_chunk_buffer_bytes() -> int:
    return int(float(os.environ.get("CONSTRUCTAIDE_CHUNK_BUFFER_MIB", DEFAULT_CHUNK_BUFFER_MIB)) * 2**20)


def warn_large_preview(key: str, size: int, chunk_bytes: int) -> None:
    log.warning("preview on %s not sent: %d bytes exceed chunk_bytes (%d); previews are never chunked", key, size,
                chunk_bytes)  # fmt: skip


def payload_of(msg: Message | bytes) -> bytes:
    return msg if isinstance(msg, (bytes, bytearray, memoryview)) else codec.encode(msg)  # type: ignore[return-value]


class Collector:
    """Collects (key, message) pairs from a subscription; ``wait`` blocks on a condition, not a sleep."""

    def __init__(self, decode: bool = True) -> None:
        self._decode = decode
        self._items: list[tuple[str, Any]] = []
        self._cond = threading.Condition()
        self.sub: Closeable | None = None

    def __call__(self, key: str, payload: bytes) -> None:
        item = codec.decode(payload) if self._decode else payload
        with self._cond:
            self._items.append((key, item))
            self._cond.notify_all()

    @property
    def items(self) -> list[tuple[str, Any]]:
        with self._cond:
            return list(self._items)

    def wait(self, count: int = 1, timeout: float = 30.0, where: Callable[[str, Any], bool] | None = None) -> list:
        """Block until ``count`` items (matching ``where``) arrived; returns them. Raises TimeoutError."""
        deadline = time.monotonic() + timeout

        def matching() -> list:
            return [kv for kv in self._items if where is None or where(*kv)]

        with self._cond:
            while len(found := matching()) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"got {len(found)} of {count} expected messages within {timeout:.1f} s")
                self._cond.wait(remaining)
            return found

    def close(self) -> None:
        if self.sub is not None:
            self.sub.close()


class Bus:
    """Publish/subscribe on key expressions plus liveliness; see module docstring."""

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False, latched: bool = False) -> None:
        raise NotImplementedError

    def subscribe(self, keyexpr: str, callback: Callback, *, fetch_latched: bool = False) -> Closeable:
        raise NotImplementedError

    def declare_token(self, key: str) -> Closeable:
        raise NotImplementedError

    def live_tokens(self, keyexpr: str, timeout: float = 2.0) -> list[str]:
        raise NotImplementedError

    def watch_tokens(self, keyexpr: str, callback: Callable[[str, bool], None]) -> Closeable:
        """Call ``callback(key, alive)`` for every current and future token under ``keyexpr``."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def topology(self) -> str:
        """This session's place on the bus, for logs."""
        return type(self).__name__

    def mesh_gaps(self) -> list[tuple[str, str]]:
        """Pairs of sessions on the bus with no transport between them (each named by its ``BusConfig.name``, else
        its zenoh id's first 8 digits): in a peer mesh neither gets the other's publications. Empty when every
        session reaches every other (always for the in-process bus)."""
        return []

    def history(self, keyexpr: str, since_ns: int = 0, timeout: float = 10.0) -> list[Publication]:
        """Publications under ``keyexpr`` since ``since_ns`` still cached by any session, oldest first."""
        return []

    # ------------------------------------------------------------------ helpers
    def collect(self, keyexpr: str, *, decode: bool = True, fetch_latched: bool = False) -> Collector:
        c = Collector(decode=decode)
        c.sub = self.subscribe(keyexpr, c, fetch_latched=fetch_latched)
        return c

    def wait_for_tokens(self, keyexprs: list[str], timeout: float = 30.0) -> None:
        """Block until a liveliness token matching each key expression is alive."""
        cond = threading.Condition()
        alive: set[str] = set()

        def on_token(key: str, is_alive: bool) -> None:
            with cond:
                (alive.add if is_alive else alive.discard)(key)
                cond.notify_all()

        watchers = [self.watch_tokens(k, on_token) for k in keyexprs]
        try:
            deadline = time.monotonic() + timeout
            with cond:
                while not all(any(_ke_match(k, a) for a in alive) for k in keyexprs):
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        missing = [k for k in keyexprs if not any(_ke_match(k, a) for a in alive)]
                        raise TimeoutError(f"nodes not live within {timeout:.0f} s: {missing}")
                    cond.wait(remaining)
        finally:
            for w in watchers:
                w.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _ke_match(keyexpr: str, key: str) -> bool:
    """Whether a concrete key matches a key expression with ``*`` and ``**`` (zenoh rules, no '$*')."""
    ke = keyexpr.split("/")
    k = key.split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(ke):
            return j == len(k)
        if ke[i] == "**":
            return any(rec(i + 1, jj) for jj in range(j, len(k) + 1) if all(not c.startswith("@") for c in k[j:jj]))
        if j == len(k):
            return False
        if ke[i] == "*":
            return not k[j].startswith("@") and rec(i + 1, j + 1)
        return ke[i] == k[j] and rec(i + 1, j + 1)

    return rec(0, 0)


ke_match = _ke_match


# ---------------------------------------------------------------------- zenoh


@dataclass
class BusConfig:
    """How to join the bus. Defaults: peer on loopback, multicast scouting off, a hub port.

    With no ``listen``/``connect`` given (:attr:`embedded`), the session tries to listen on
    ``tcp/127.0.0.1:<hub_port>`` (it becomes the hub); when that port is taken it listens on a port the system
    picks and connects to the hub instead, so processes on one machine meet without a daemon. A session that
    listens on port 0 can read the port it got back with :meth:`ZenohBus.listen_port`.
    """

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    hub_port: int = DEFAULT_HUB_PORT
    extra_json5: dict[str, Any] = field(default_factory=dict)
    client_connect_timeout_ms: int = 15000
    history_bytes: int = field(
        default_factory=lambda: int(float(os.environ.get("CONSTRUCTAIDE_HISTORY_MB", DEFAULT_HISTORY_MB)) * 1e6)
    )
    """Payload bytes of recent data publications kept to answer history queries (0: none)."""
    chunk_bytes: int = field(default_factory=default_chunk_bytes)
    """Payloads above this go in parts of at most this many bytes (0: never split)."""
    chunk_buffer_bytes: int = field(default_factory=default_chunk_buffer_bytes)
    """Bytes of incomplete transfers a subscription holds (the oldest are dropped beyond); larger payloads are
    refused."""
    latched_fetch_secs: float = 15.0
    """How long a ``fetch_latched`` subscription waits for the latched values at most (a big model comes in parts,
    and a loaded machine is slow to send them). It ends earlier: for a concrete key as soon as one complete payload
    arrived, for a key expression with wildcards as soon as every holder has answered."""
    mesh_join_secs: float = 3.0
    """How long a peer joining the embedded hub waits at open to reach the other peers the hub knows."""
    security: BusSecurity | None = None  # TLS / mTLS / ACL from the site TOML (constructaide.runtime.security)
    name: str = ""
    """This session's name on the bus (zenoh ``metadata/name``; a node's name), shown by :meth:`Bus.mesh_gaps`."""

    @classmethod
    def from_args(cls, args: argparse.Namespace, role: str = "admin") -> BusConfig:
        """``role``: the certificate name when the site TOML given with ``--bus-security`` turns TLS on (a node
        passes its name; ``--role`` overrides)."""
        from constructaide.runtime.security import load_security

        sec_toml = getattr(args, "bus_security", None)
        security = load_security(sec_toml, getattr(args, "role", None) or role) if sec_toml else None
        return cls(
            mode=getattr(args, "mode", None) or "peer",
            listen=list(getattr(args, "listen", None) or []),
            connect=list(getattr(args, "connect", None) or []),
            hub_port=int(
                getattr(args, "hub_port", None) or os.environ.get("CONSTRUCTAIDE_HUB_PORT") or DEFAULT_HUB_PORT
            ),
            security=security,
            name=role,
        )

    @property
    def embedded(self) -> bool:
        """True when neither ``listen`` nor ``connect`` is given: the loopback hub scheme."""
        return not self.listen and not self.connect

    def zenoh_config(self, as_hub: bool = True) -> Any:
        """The zenoh config; for :attr:`embedded` sessions ``as_hub`` says whether to listen on the hub port (else on
        port 0, connecting to the hub)."""
        import zenoh

        from constructaide.runtime.security import check_endpoints

        listen, connect = list(self.listen), list(self.connect)
        proto = "tls" if self.security is not None else "tcp"
        if self.embedded:
            hub = f"{proto}/127.0.0.1:{self.hub_port}"
            listen, connect = ([hub], []) if as_hub else ([f"{proto}/127.0.0.1:0"], [hub])
        check_endpoints(listen + connect, self.security)
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        c.insert_json5("scouting/multicast/enabled", "false")
        # With congestion control BLOCK zenoh takes the whole transport to a peer down when a message waits longer
        # than this for room (default 5 s) - and every later message to that peer is lost. A node busy for a while
        # (a bundle adjustment, a burst of masks) must slow its publishers, not cut them off.
        c.insert_json5(
            "transport/link/tx/queue/congestion_control/block/wait_before_close", json.dumps(BLOCK_WAIT_BEFORE_CLOSE_US)
        )
        if self.security is not None and not listen and self.mode == "peer":
            # zenoh's default listener is plain tcp/[::]:0 (never with TLS on); and under the ACL a peer without a
            # listener is not heard through a router (zenoh 1.10): listen on loopback. Across machines: mode client.
            listen = ["tls/127.0.0.1:0"]
        if listen or self.security is not None:
            c.insert_json5("listen/endpoints", json.dumps(listen))
        if connect:
            c.insert_json5("connect/endpoints", json.dumps(connect))
        if self.mode == "client":
            # Wait for a router that is still starting instead of failing at once.
            c.insert_json5("connect/timeout_ms", json.dumps(self.client_connect_timeout_ms))
        if any(_port_of(e) == 0 for e in listen) or (self.embedded and as_hub):
            # Read back: the port the system picked; the hub's peers, for a joining peer to reach them all.
            c.insert_json5("adminspace/enabled", "true")
        if self.name:
            c.insert_json5("metadata", json.dumps({"name": self.name}))
        for k, v in (self.security.json5() if self.security else {}).items():
            c.insert_json5(k, json.dumps(v))
        for k, v in self.extra_json5.items():
            c.insert_json5(k, json.dumps(v))
        return c


def add_bus_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("bus")
    g.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to, e.g. tcp/10.0.0.5:7447"
    )
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on")
    g.add_argument(
        "--mode", choices=["peer", "client", "router"], default=None, help="zenoh session mode (default peer)"
    )
    g.add_argument(
        "--hub-port",
        type=int,
        default=None,
        help=f"loopback hub port (default {DEFAULT_HUB_PORT} or $CONSTRUCTAIDE_HUB_PORT)",
    )
    g.add_argument(
        "--bus-security", metavar="SITE.toml", help="site TOML whose [bus.tls] / [bus.acl] secure this session"
    )
    g.add_argument("--role", help="certificate / ACL role of this session (default: the node's name)")


def _port_of(endpoint: str) -> int | None:
    """The port of a ``proto/host:port`` endpoint (None when it has none)."""
    tail = endpoint.split("#", 1)[0].rsplit(":", 1)
    return int(tail[1]) if len(tail) == 2 and tail[1].isdigit() else None


class _Closer:
    def __init__(self, fn: Callable[[], None]) -> None:
        self._fn: Callable[[], None] | None = fn

    def close(self) -> None:
        fn, self._fn = self._fn, None
        if fn is not None:
            fn()


class ZenohBus(Bus):
    """A zenoh session. Thread-safe; callbacks run on zenoh's threads."""

    def __init__(self, config: BusConfig | None = None) -> None:
        import zenoh

        zenoh.init_log_from_env_or("error")
        self._z = zenoh
        self.config = config or BusConfig()
        self.is_hub = self.config.embedded
        try:
            self.session = zenoh.open(self.config.zenoh_config())
        except zenoh.ZError as e:
            if not (self.config.embedded and "listener" in str(e)):
                from constructaide.errors import UserError

                raise UserError(f"cannot open the zenoh session ({self.config.mode}): {e}") from None
            self.session = zenoh.open(self.config.zenoh_config(as_hub=False))  # the hub port is taken: join it
            self.is_hub = False
        if self.config.embedded and not self.is_hub:
            self._join_mesh(self.config.mesh_join_secs)
        self._latched: dict[str, Transfer] = {}
        self._latched_lock = threading.Lock()
        self._queryables: dict[str, Any] = {}
        self.cache = PublicationCache(self.config.history_bytes)
        if self.cache.max_bytes > 0:
            self._queryables[HISTORY_ROOT] = self.session.declare_queryable(f"{HISTORY_ROOT}/**", self._serve_history)

    def _join_mesh(self, secs: float) -> bool:
        """Wait up to ``secs`` until this peer has reached every peer the hub knows (True when it has). A peer opens
        connected to the hub alone and finds the others through it a moment later; a query sent before (a restarted
        node's catch-up on the history, a latched fetch) reached the hub alone and missed the other peers'
        publications (7 of 20 such joins, 2026-12-04). The hub's admin space (``@/<hub>/peer``) lists them."""
        own = str(self.session.info.zid())
        want: set[str] = set()
        try:
            for reply in self.session.get("@/*/peer", timeout=min(secs, 1.0)):
                if reply.ok is not None:
                    doc = json.loads(reply.ok.payload.to_bytes())
                    want |= {str(x.get("peer")) for x in doc.get("sessions", []) if x.get("peer")}
        except Exception:  # an admin space this zenoh does not serve: nothing to wait for
            return True
        want.discard(own)
        deadline = time.monotonic() + secs
        while True:
            missing = want - {str(z) for z in self.session.info.peers_zid()}
            if not missing or time.monotonic() >= deadline:
                if missing:
                    log.warning("%d peer(s) the hub knows not reached in %.1f s", len(missing), secs)
                return not missing
            time.sleep(0.01)  # zenoh has no event for a new transport in its Python API

    def publish(self, key: str, msg: Message | bytes, *, preview: bool = False, latched: bool = False) -> None:
        z = self._z
        transfer = Transfer(bytes(payload_of(msg)), self.config.chunk_bytes)
        if preview and transfer.chunked:
            warn_large_preview(key, len(transfer.payload), self.config.chunk_bytes)
            return
        if latched:
            with self._latched_lock:
                self._latched[key] = transfer
                if key not in self._queryables:
                    self._queryables[key] = self.session.declare_queryable(key, self._serve_latched)
        if self.config.security is not None and self.config.security.acl:
            self.config.security.check_publish(key)  # zenoh would drop it silently: say so
        if not preview:
            self.cache.add(key, transfer.payload)
        for head, part in transfer.parts():
            self.session.put(
                key,
                part,
                congestion_control=z.CongestionControl.DROP if preview else z.CongestionControl.BLOCK,
                priority=z.Priority.DATA_LOW if preview else z.Priority.DATA,
                attachment=head,
            )

    def _serve_history(self, query: Any) -> None:
        ke = str(query.key_expr)[len(HISTORY_ROOT) + 1 :]
        since = int(query.parameters.get("since_ns") or 0)
        with query:  # the final goes on exit, not when Python gets to free the query
            for pub in self.cache.since(lambda k: _ke_match(ke, k), since):
                # attachment: the publication time, then ";" and the part header when chunked
                for head, part in Transfer(pub.payload, self.config.chunk_bytes).parts():
                    stamp = str(pub.time_ns).encode()
                    query.reply(
                        f"{HISTORY_ROOT}/{pub.key}", part, attachment=stamp if head is None else stamp + b";" + head
                    )

    def history(self, keyexpr: str, since_ns: int = 0, timeout: float = 10.0) -> list[Publication]:
        z = self._z
        out = []
        parts = Reassembler(self.config.chunk_buffer_bytes, f"history {keyexpr}")
        replies = self.session.get(
            f"{HISTORY_ROOT}/{keyexpr}?since_ns={since_ns}",
            timeout=timeout,
            consolidation=z.ConsolidationMode.NONE,
        )
        for reply in replies:
            s = reply.ok
            if s is None:
                continue
            stamp, _, head = (s.attachment.to_bytes() if s.attachment is not None else b"0").partition(b";")
            key, payload = str(s.key_expr)[len(HISTORY_ROOT) + 1 :], s.payload.to_bytes()
            whole = unpack(parts, key, payload, head or None)
            if whole is not None:
                out.append(Publication(key, whole, int(stamp or 0)))
        out.sort(key=lambda p: p.time_ns)
        return out

    def _serve_latched(self, query: Any) -> None:
        ke = str(query.key_expr)
        with self._latched_lock:
            items = [(k, v) for k, v in self._latched.items() if _ke_match(ke, k) or k == ke]
        with query:  # the final goes on exit, not when Python gets to free the query
            for k, transfer in items:
                for head, part in transfer.parts():
                    query.reply(k, part, attachment=head)

    def subscribe(self, keyexpr: str, callback: Callback, *, fetch_latched: bool = False) -> Closeable:
        def deliver(key: str, payload: bytes) -> None:
            try:
                callback(key, payload)
            except Exception:  # a callback must never kill zenoh's thread
                log.exception("subscriber callback failed for %s", key)

        receiver = Receiver(deliver, self.config.chunk_buffer_bytes, f"subscription {keyexpr}")

        def on_sample(sample: Any) -> None:
            att = sample.attachment
            receiver(str(sample.key_expr), sample.payload.to_bytes(), att.to_bytes() if att is not None else None)

        sub = self.session.declare_subscriber(keyexpr, on_sample)
        if fetch_latched:
            for k, whole in self._fetch_latched(keyexpr, receiver).items():
                deliver(k, whole)
        return _Closer(sub.undeclare)

    def _fetch_latched(self, keyexpr: str, receiver: Receiver) -> dict[str, bytes]:
        """The latched payloads under ``keyexpr``, one per key: ``{key: whole payload}``.

        zenoh ends a query when every matching queryable (every session holding a matching latched key) has sent
        its final, or at ``latched_fetch_secs``. For a concrete key the fetch ends as soon as one complete payload
        arrived (the first holder's): a second holder that is slow, frozen or gone without closing does not hold
        a late joiner up. A key expression with wildcards waits for every holder (which keys exist is not known
        before), keeping the last completed payload per key.
        """
        z = self._z
        concrete = "*" not in keyexpr  # '*', '**', '$*'
        token = z.CancellationToken() if concrete and hasattr(z, "CancellationToken") else None  # zenoh >= 1.7
        kwargs: dict[str, Any] = {} if token is None else {"cancellation_token": token}
        # no consolidation (it would keep one part per key)
        replies = self.session.get(
            keyexpr, timeout=self.config.latched_fetch_secs, consolidation=z.ConsolidationMode.NONE, **kwargs
        )
        latest: dict[str, bytes] = {}
        for reply in replies:
            if (s := reply.ok) is not None:
                att = s.attachment.to_bytes() if s.attachment is not None else None
                if (whole := receiver.unpack(str(s.key_expr), s.payload.to_bytes(), att)) is not None:
                    latest[str(s.key_expr)] = whole
                    if concrete:
                        break
        if token is not None:
            token.cancel()  # the other holders' replies are dropped by zenoh
        del replies  # without a token (zenoh < 1.7): later replies find the channel closed
        return latest

    def declare_token(self, key: str) -> Closeable:
        token = self.session.liveliness().declare_token(key)
        return _Closer(token.undeclare)

    def live_tokens(self, keyexpr: str, timeout: float = 2.0) -> list[str]:
        out = []
        for reply in self.session.liveliness().get(keyexpr, timeout=timeout):
            if reply.ok is not None:
                out.append(str(reply.ok.key_expr))
        return sorted(set(out))

    def watch_tokens(self, keyexpr: str, callback: Callable[[str, bool], None]) -> Closeable:
        z = self._z

        def on_sample(sample: Any) -> None:
            callback(str(sample.key_expr), sample.kind == z.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(keyexpr, on_sample, history=True)
        return _Closer(sub.undeclare)

    def locators(self) -> list[str]:
        """The endpoints this session listens on, as bound (a port 0 endpoint shows the port the system picked)."""
        if self.is_hub:
            return [f"{'tls' if self.config.security else 'tcp'}/127.0.0.1:{self.config.hub_port}"]
        listen = list(self.config.listen)
        if listen and all(_port_of(e) != 0 for e in listen):
            return listen
        key = f"@/{self.session.info.zid()}/{self.config.mode}"  # the admin space (enabled for port 0 endpoints)
        for reply in self.session.get(key, timeout=5.0):
            if reply.ok is not None:
                return [str(x) for x in json.loads(reply.ok.payload.to_bytes()).get("locators", [])]
        return listen

    def listen_port(self) -> int:
        """The TCP port of this session's first TCP listening endpoint (e.g. the hub port for other processes)."""
        for loc in self.locators():
            port = _port_of(loc)
            if loc.startswith(("tcp/", "tls/")) and port:
                return port
        raise RuntimeError(f"the zenoh session listens on no TCP port ({self.locators()})")

    def topology(self) -> str:
        """This session's place on the bus, for logs: its zenoh id, hub or not, and the peers and routers it has a
        transport to (a peer another session has no transport to gets none of its publications)."""
        info = self.session.info
        peers = sorted(str(z)[:8] for z in info.peers_zid())
        routers = sorted(str(z)[:8] for z in info.routers_zid())
        role = "hub" if self.is_hub else self.config.mode
        return f"zid {str(info.zid())[:8]} ({role}), peers {peers}, routers {routers}"

    def mesh_gaps(self) -> list[tuple[str, str]]:
        """See :meth:`Bus.mesh_gaps`; read from the admin space of every session this one reaches that serves one
        (the embedded hub and the peers that joined it: ``@/<zid>/peer`` lists each one's transports). A session
        this one does not reach is known from the others' lists (named by its id then): ask the hub, which reaches
        every session, for names throughout. A pair neither of which answered (an ACL that hides the admin space)
        is not judged."""
        adj: dict[str, set[str]] = {}
        names: dict[str, str] = {}
        try:
            for reply in self.session.get("@/*/peer", timeout=1.0):
                if reply.ok is None:
                    continue
                doc = json.loads(reply.ok.payload.to_bytes())
                zid = str(doc.get("zid") or str(reply.ok.key_expr).split("/")[1])
                names[zid] = str((doc.get("metadata") or {}).get("name") or zid[:8])
                for other in (str(x.get("peer")) for x in doc.get("sessions", []) if x.get("peer")):
                    adj.setdefault(zid, set()).add(other)
                    adj.setdefault(other, set()).add(zid)
        except Exception:  # an admin space this zenoh does not serve: nothing known to be missing
            return []
        zids = sorted(adj)
        return [
            (names.get(a, a[:8]), names.get(b, b[:8]))
            for i, a in enumerate(zids)
            for b in zids[i + 1 :]
            if b not in adj[a] and (a in names or b in names)  # known from an answer, not only from lists
        ]

    def close(self) -> None:
        for q in self._queryables.values():
            q.undeclare()
        self._queryables.clear()
        self.session.close()


def open_bus(config: BusConfig | None = None) -> ZenohBus:
    """Open a zenoh session with the embedded defaults (see :class:`BusConfig`); use as a context manager."""
    return ZenohBus(config)
