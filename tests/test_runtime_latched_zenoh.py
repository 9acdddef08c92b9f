"""A late joiner's latched fetch on real zenoh sessions (loopback hub): for a concrete key it ends at the first
complete payload, not when every holder has answered (a holder that never answers does not hold it up); with a
wildcard it still gathers every holder's keys."""

from __future__ import annotations

import os
import threading

import pytest

from constructaide.runtime import BusConfig, open_bus

pytestmark = pytest.mark.zenoh
MIB = 2**20
KEY = "constructaide/zl/bim/model"
HUGE_FETCH_SECS = 3600.0  # far beyond the test's own bounds: only an early end of the fetch passes


@pytest.mark.parametrize("size", [1000, 3 * MIB + 7], ids=["one-payload", "parts"])
def test_fetch_of_a_key_returns_at_the_first_complete_payload(hub_port: int, size: int) -> None:
    payload = os.urandom(size)
    cfg = BusConfig(hub_port=hub_port, chunk_bytes=MIB)
    queried, release = threading.Event(), threading.Event()

    def never_answers(query: object) -> None:  # a second holder of the key, frozen: no reply, no final
        queried.set()
        release.wait(120)

    with open_bus(cfg) as holder, open_bus(cfg) as frozen:
        holder.publish(KEY, payload, latched=True)
        queryable = frozen.session.declare_queryable(KEY, never_answers)
        token = frozen.declare_token("constructaide/zl/@live/frozen")  # declared after the queryable: same link
        try:
            with open_bus(BusConfig(hub_port=hub_port, chunk_bytes=MIB, latched_fetch_secs=HUGE_FETCH_SECS)) as late:
                late.wait_for_tokens(["constructaide/zl/@live/frozen"], timeout=30)  # late knows the frozen holder
                done, out = threading.Event(), {}

                def join() -> None:
                    out["got"] = late.collect(KEY, decode=False, fetch_latched=True)
                    out["frozen_still_blocked"] = not release.is_set()
                    done.set()

                threading.Thread(target=join, daemon=True).start()
                assert done.wait(60), "the latched fetch waited for the holder that never answers"
                assert queried.wait(30), "the frozen holder was not asked: the test shows nothing"
                assert out["frozen_still_blocked"]  # returned while the frozen holder had not answered
                assert out["got"].items == [(KEY, payload)]  # whole, once
                out["got"].close()
        finally:
            release.set()
            token.close()
            queryable.undeclare()


def test_wildcard_fetch_gathers_every_holders_keys(hub_port: int) -> None:
    big, small = os.urandom(2 * MIB + 3), os.urandom(500)
    cfg = BusConfig(hub_port=hub_port, chunk_bytes=MIB)
    with open_bus(cfg) as a, open_bus(cfg) as b:
        a.publish(KEY, big, latched=True)
        b.publish("constructaide/zl/anchors/p1", small, latched=True)
        tokens = [a.declare_token("constructaide/zl/@live/a"), b.declare_token("constructaide/zl/@live/b")]
        with open_bus(BusConfig(hub_port=hub_port, chunk_bytes=MIB)) as late:
            late.wait_for_tokens(["constructaide/zl/@live/a", "constructaide/zl/@live/b"], timeout=30)
            got = late.collect("constructaide/zl/**", decode=False, fetch_latched=True)
            assert sorted(got.items) == sorted([(KEY, big), ("constructaide/zl/anchors/p1", small)])
            got.close()
        for t in tokens:
            t.close()


def test_a_session_that_just_joined_finds_the_latched_value(hub_port: int) -> None:
    """A late joiner asks right after it opened: a peer joining the hub reaches every peer the hub knows before
    ``open_bus`` returns, so the fetch reaches the holder instead of the hub alone (it came back empty in 2 of 10
    such joins before)."""
    payload = os.urandom(1000)
    with open_bus(BusConfig(hub_port=hub_port)) as holder:
        holder.publish(KEY, payload, latched=True)
        for _ in range(10):
            with open_bus(BusConfig(hub_port=hub_port)) as late:
                assert late.collect(KEY, decode=False, fetch_latched=True).items == [(KEY, payload)]


def test_a_session_that_just_joined_gets_the_other_peers_history(hub_port: int) -> None:
    """The same for a history query (a restarted node's catch-up): another peer's publication is in the answer
    of a session asking right after it opened (7 of 20 such joins missed it before)."""
    with open_bus(BusConfig(hub_port=hub_port)), open_bus(BusConfig(hub_port=hub_port)) as pub:
        pub.publish("constructaide/zl/photo/cam-a", b"frame")
        for _ in range(10):
            with open_bus(BusConfig(hub_port=hub_port)) as late:
                got = late.history("constructaide/zl/**", 0, timeout=10)
                assert [(p.key, p.payload) for p in got] == [("constructaide/zl/photo/cam-a", b"frame")]
