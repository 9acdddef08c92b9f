"""Chunked payloads on real zenoh sessions (loopback hub): a 10 MiB payload in 1 MiB parts arrives whole and once
live, to a late joiner's latched fetch and in a history query; the wire holds bounded parts with a header, small
payloads go unchanged; corrupt or incomplete transfers and previews above chunk_bytes never deliver."""

from __future__ import annotations

import os
import threading

import pytest
import zenoh

from constructaide.runtime import BusConfig, open_bus
from constructaide.runtime.chunks import PartHeader, Transfer

pytestmark = pytest.mark.zenoh
MIB = 2**20
KEY = "constructaide/zc/bim/model"
SMALL = "constructaide/zc/small"


class Wire:
    """Raw zenoh samples (size, attachment) of a session, below the bus's reassembly."""

    def __init__(self, bus, keyexpr: str) -> None:  # noqa: ANN001
        self.items: list[tuple[str, int, bytes | None, bytes]] = []
        self.cond = threading.Condition()
        self.sub = bus.session.declare_subscriber(keyexpr, self._on)

    def _on(self, s) -> None:  # noqa: ANN001
        att = s.attachment.to_bytes() if s.attachment is not None else None
        with self.cond:
            self.items.append((str(s.key_expr), len(s.payload.to_bytes()), att, s.payload.to_bytes()[:64]))
            self.cond.notify_all()

    def wait(self, n: int, timeout: float = 30.0) -> list:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.items) >= n, timeout), f"{len(self.items)} of {n} samples"
            return list(self.items)


def test_big_payload_live_latched_history_and_small_unchanged(hub_port: int) -> None:
    payload = os.urandom(10 * MIB + 123)
    small = os.urandom(1000)
    cfg = BusConfig(hub_port=hub_port, chunk_bytes=MIB)
    with open_bus(cfg) as pub, open_bus(BusConfig(hub_port=hub_port, chunk_bytes=MIB)) as sub:
        wire = Wire(sub, "constructaide/zc/**")
        live = sub.collect("constructaide/zc/**", decode=False)
        token = sub.declare_token("constructaide/zc/@live/sub")
        pub.wait_for_tokens(["constructaide/zc/@live/sub"], timeout=30)
        pub.publish(KEY, payload, latched=True)
        pub.publish(SMALL, small)
        got = live.wait(2, timeout=60)
        assert got == [(KEY, payload), (SMALL, small)]  # whole, once, in order
        samples = wire.wait(12)
        parts = [s for s in samples if s[0] == KEY]
        assert len(parts) == 11 and all(n <= MIB for _, n, _, _ in parts)
        heads = [PartHeader.decode(a) for _, _, a, _ in parts]
        assert all(h is not None and h.count == 11 and h.total == len(payload) for h in heads)
        assert [s[1:] for s in samples if s[0] == SMALL] == [(1000, None, small[:64])]  # no header

        with open_bus(BusConfig(hub_port=hub_port)) as late:  # default chunk settings: reassembles all the same
            joined = late.collect(KEY, decode=False, fetch_latched=True)
            assert joined.items == [(KEY, payload)]
            hist = late.history("constructaide/zc/**")
            assert [(p.key, p.payload) for p in hist] == [(KEY, payload), (SMALL, small)]
            assert hist[0].time_ns <= hist[1].time_ns and hist[0].time_ns > 0
        token.close()
        live.close()
        wire.sub.undeclare()


def test_corrupt_or_incomplete_transfers_never_deliver(hub_port: int) -> None:
    payload = os.urandom(3 * MIB + 5)
    cfg = BusConfig(hub_port=hub_port, chunk_bytes=MIB)
    with open_bus(cfg) as pub, open_bus(cfg) as sub:
        got = sub.collect(KEY, decode=False)
        token = sub.declare_token("constructaide/zc/@live/sub2")
        pub.wait_for_tokens(["constructaide/zc/@live/sub2"], timeout=30)

        def put(parts: list[tuple[bytes | None, bytes]]) -> None:
            for head, part in parts:
                # BLOCK as the bus puts data: the default (drop) loses parts or the marker on a loaded machine
                pub.session.put(KEY, part, attachment=head, congestion_control=zenoh.CongestionControl.BLOCK)

        corrupt = list(Transfer(payload, MIB).parts())
        h, p = corrupt[2]
        corrupt[2] = (h, bytes([p[0] ^ 0xFF]) + p[1:])
        put(corrupt)
        put(list(Transfer(payload, MIB).parts())[1:])  # the first part missing
        pub.publish(KEY, payload, preview=True)  # a preview above chunk_bytes is not sent (never chunked)
        put([(None, b"marker")])  # same session and key: delivered after the parts above
        got.wait(1, timeout=30)
        assert got.items == [(KEY, b"marker")]
        pub.publish(KEY, payload)  # the bus's own publication still arrives whole
        assert got.wait(2, timeout=30)[1] == (KEY, payload)
        token.close()
