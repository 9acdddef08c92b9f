"""Large payloads in parts (constructaide.runtime.chunks) and through the in-process bus: whole and once to
subscribers, late joiners and history queries; corrupt or missing parts never deliver; small payloads unchanged;
a BimModel above chunk_bytes from the ingest node reaches the register node and the recorder whole."""

from __future__ import annotations

import hashlib
import logging
import os
import random
from pathlib import Path

import pytest

from constructaide.runtime import start_node
from constructaide.runtime.chunks import HEADER_BYTES, PartHeader, Reassembler, Receiver, Transfer
from constructaide.runtime.local import LocalBus

MIB = 2**20
KEY = "constructaide/t/bim/model"


def big(n: int = 10 * MIB + 123) -> bytes:
    return os.urandom(n)


def test_transfer_parts_are_bounded_and_carry_the_header() -> None:
    payload = big(5 * MIB + 7)
    t = Transfer(payload, MIB)
    parts = list(t.parts())
    assert len(parts) == 6 and all(len(p) <= MIB for _, p in parts)
    assert b"".join(p for _, p in parts) == payload
    heads = [PartHeader.decode(h) for h, _ in parts]
    assert all(h is not None for h in heads)
    assert [h.index for h in heads if h] == list(range(6))
    assert {(h.transfer_id, h.digest, h.count, h.total) for h in heads if h} == {
        (t.transfer_id, hashlib.sha256(payload).digest(), 6, len(payload))
    }
    assert all(len(h or b"") == HEADER_BYTES for h, _ in parts)
    small = Transfer(b"x" * MIB, MIB)  # exactly chunk_bytes: whole, no header
    assert list(small.parts()) == [(None, b"x" * MIB)]
    assert list(Transfer(payload, 0).parts()) == [(None, payload)]  # 0: never split


def test_reassembly_in_any_order_once_and_only_with_the_right_digest(caplog: pytest.LogCaptureFixture) -> None:
    payload = big(3 * MIB + 5)
    parts = list(Transfer(payload, MIB).parts())
    got: list[tuple[str, bytes]] = []
    rx = Receiver(lambda k, p: got.append((k, p)), max_bytes=64 * MIB)
    shuffled = parts[:]
    random.Random(0).shuffle(shuffled)
    for h, p in shuffled + parts:  # every part twice (live + latched fetch of the same transfer)
        rx(KEY, p, h)
    assert got == [(KEY, payload)]
    assert rx.reassembler.nbytes == 0 and len(rx.reassembler) == 0

    # A corrupted part: never delivered, reported.
    bad = list(Transfer(payload, MIB).parts())
    h1, p1 = bad[1]
    bad[1] = (h1, p1[:-1] + bytes([p1[-1] ^ 1]))
    with caplog.at_level(logging.WARNING, "constructaide.bus"):
        for h, p in bad:
            rx(KEY, p, h)
    assert len(got) == 1 and "sha256 does not match" in caplog.text
    # A missing part: never delivered, held until evicted.
    for h, p in list(Transfer(payload, MIB).parts())[:-1]:
        rx(KEY, p, h)
    assert len(got) == 1 and len(rx.reassembler) == 1
    # A part claiming another transfer's size: refused. Not a part header: passed through unchanged.
    tid = os.urandom(16)
    rx(KEY, b"abc", PartHeader(tid, b"\0" * 32, 0, 2, 2).encode())  # 3 bytes of a 2-byte payload
    assert len(got) == 1
    rx(KEY, b"plain", b"another attachment")
    assert got[-1] == (KEY, b"plain")


def test_incomplete_transfers_are_bounded_oldest_first(caplog: pytest.LogCaptureFixture) -> None:
    asm = Reassembler(max_bytes=3 * MIB)
    transfers = [list(Transfer(big(2 * MIB + 1), MIB).parts()) for _ in range(3)]
    with caplog.at_level(logging.WARNING, "constructaide.bus"):
        for parts in transfers:  # the first two parts of each (2 MiB held per transfer)
            for h, p in parts[:2]:
                assert h is not None and asm.add(KEY, PartHeader.decode(h), p) is None  # type: ignore[arg-type]
            assert asm.nbytes <= 3 * MIB
        assert len(asm) == 1 and asm.dropped == 2 and "reassembly buffer is full" in caplog.text
        # the newest completes; an evicted one cannot come back with its last part
        h, p = transfers[2][2]
        assert asm.add(KEY, PartHeader.decode(h), p) is not None  # type: ignore[arg-type]
        h, p = transfers[0][2]
        assert asm.add(KEY, PartHeader.decode(h), p) is None  # type: ignore[arg-type]
        too_big = list(Transfer(big(4 * MIB), MIB).parts())
        assert asm.add(KEY, PartHeader.decode(too_big[0][0]), too_big[0][1]) is None  # type: ignore[arg-type]
        assert "exceed the reassembly buffer" in caplog.text and asm.nbytes <= 3 * MIB


def test_local_bus_live_latched_history_and_small_payloads(caplog: pytest.LogCaptureFixture) -> None:
    payload = big()
    with LocalBus(chunk_bytes=MIB) as bus:
        live = bus.collect("constructaide/t/**", decode=False)
        bus.publish(KEY, payload, latched=True)
        assert live.items == [(KEY, payload)]
        parts = [w for w in bus.wire if w[0] == KEY]
        assert len(parts) == 11 and all(n <= MIB and head for _, n, head in parts)
        bus.publish("constructaide/t/small", b"\x01" * MIB)
        assert bus.wire[-1] == ("constructaide/t/small", MIB, False)  # unchanged, no header
        late = bus.collect(KEY, decode=False, fetch_latched=True)
        assert late.items == [(KEY, payload)]
        hist = bus.history("constructaide/t/**")
        assert [(p.key, p.payload) for p in hist] == [(KEY, payload), ("constructaide/t/small", b"\x01" * MIB)]
        with caplog.at_level(logging.WARNING, "constructaide.bus"):
            bus.publish("constructaide/t/preview", payload, preview=True)
        assert "previews are never chunked" in caplog.text
        assert all(k != "constructaide/t/preview" for k, _ in live.items)
        bus.publish("constructaide/t/preview", b"p", preview=True)  # small previews go as before
        assert live.items[-1] == ("constructaide/t/preview", b"p")


def test_a_big_bim_model_reaches_the_nodes_whole(tmp_path: Path) -> None:
    """Ingest publishes a BimModel of a synthetic 400-element IFC above chunk_bytes (latched); a running register
    node, one started later (latched fetch) and the recorder (one MCAP message) get it whole."""
    from constructaide.synth.bigmodel import write_big_ifc
    from nodes.ingest.node import SPEC as INGEST
    from nodes.ingest.node import Config as IngestConfig
    from nodes.recorder import mcapio
    from nodes.recorder.node import SPEC as RECORDER
    from nodes.recorder.node import Config as RecorderConfig
    from nodes.register.node import SPEC as REGISTER
    from nodes.register.node import Config as RegisterConfig
    from schemas import codec, keys
    from schemas.messages import BimModel

    ifc = tmp_path / "big.ifc"
    write_big_ifc(ifc, 400)
    chunk = 64 * 1024
    key = keys.key(keys.BIM_MODEL, site="t")
    with (
        LocalBus(chunk_bytes=chunk) as bus,
        start_node(REGISTER, RegisterConfig(site="t"), bus) as early,
        start_node(RECORDER, RecorderConfig(site="t", path=str(tmp_path / "r.mcap")), bus) as rec,
    ):
        # subscribed after the nodes: delivered after them (LocalBus delivers in order, on the publisher's thread)
        models = bus.collect(key, decode=False)
        with start_node(INGEST, IngestConfig(site="t", ifc=(str(ifc),), watch_model_files=False), bus):
            ((_, payload),) = models.wait(1, timeout=120)
            model = codec.decode(payload, BimModel)
            assert len(payload) > 4 * chunk and len(model.elements) == 400
            assert sum(1 for k, _, head in bus.wire if k == key and head) == -(-len(payload) // chunk)
            with start_node(REGISTER, RegisterConfig(site="t"), bus) as late:
                for node in (early, late):
                    assert node.wait_idle(60)
                    assert node.errors == 0
                    assert set(node.obj.bim.meshes) == {e.geometry_ref for e in model.elements}
        assert rec.wait_idle(30)
    rows = [r for r in mcapio.iter_recording(tmp_path / "r.mcap") if r[0] == key]
    assert len(rows) == 1 and rows[0][2] == payload
