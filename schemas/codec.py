"""Encoding of bus messages: msgpack on the wire and in MCAP, JSON for humans and JSON Schema."""

from __future__ import annotations

import json
from functools import cache
from typing import Any, TypeVar

import msgspec

from schemas.messages import MESSAGE_TYPES, AnyMessage, Message

T = TypeVar("T", bound=Message)

_enc = msgspec.msgpack.Encoder()
_any_dec: msgspec.msgpack.Decoder[Any] = msgspec.msgpack.Decoder(AnyMessage)
_json_any_dec: msgspec.json.Decoder[Any] = msgspec.json.Decoder(AnyMessage)


def encode(msg: Message) -> bytes:
    """msgpack bytes of a message (tag included)."""
    return _enc.encode(msg)


def decode(data: bytes, type_: type[T] | None = None) -> T | Any:
    """Decode msgpack bytes into the given type, or into any message by its tag.

    Raises ``msgspec.DecodeError`` / ``msgspec.ValidationError`` on bad input.
    """
    if type_ is None:
        return _any_dec.decode(data)
    return _decoder(type_).decode(data)


@cache
def _decoder(type_: type[T]) -> msgspec.msgpack.Decoder[T]:
    return msgspec.msgpack.Decoder(type_)


def to_json(msg: Message) -> bytes:
    """JSON bytes of a message (bytes fields base64)."""
    return msgspec.json.encode(msg)


def from_json(data: bytes | str, type_: type[T] | None = None) -> T | Any:
    if type_ is None:
        return _json_any_dec.decode(data)
    return msgspec.json.decode(data, type=type_)


def type_name(msg_or_type: Message | type[Message]) -> str:
    t = msg_or_type if isinstance(msg_or_type, type) else type(msg_or_type)
    return f"constructaide.{t.__name__}"


TYPES_BY_NAME: dict[str, type[Message]] = {type_name(t): t for t in MESSAGE_TYPES}


@cache
def json_schema(type_: type[Message]) -> bytes:
    """JSON Schema (draft 2020-12) of one message type, for MCAP schema records."""
    return json.dumps(msgspec.json.schema(type_), sort_keys=True).encode()
