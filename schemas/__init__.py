"""ConstructAide message schemas, key expressions and codec."""

from schemas import keys
from schemas.codec import decode, encode, from_json, to_json
from schemas.messages import *  # noqa: F403
from schemas.messages import MESSAGE_TYPES, AnyMessage, Message

__all__ = ["keys", "decode", "encode", "from_json", "to_json", "MESSAGE_TYPES", "AnyMessage", "Message"]
