"""The JSON-lines framing both clients share: encoding requests, reading server lines."""

from __future__ import annotations

import json
from typing import Any

from .errors import ProtocolError

Json = dict[str, Any]

PROTOCOL_VERSION = 1
#: Event kinds that end a job.
TERMINAL = ("finished", "failed", "cancelled")
#: Job states after which nothing more happens.
ENDED_STATES = ("finished", "failed", "cancelled")
#: Codes of an id-less error reply that answers this client's own last line (the daemon
#: could not read its id); any other id-less reply is a notice (events lost).
OWN_IDLESS_CODES = ("malformed", "line_too_long", "bad_request", "version")


def encode_request(rid: int, kind: str, fields: dict[str, Any]) -> bytes:
    """One request line; fields given as None are left out (the daemon's default)."""
    body = {k: v for k, v in fields.items() if v is not None}
    return (json.dumps({"v": PROTOCOL_VERSION, "id": rid, "kind": kind, **body}) + "\n").encode()


def decode_line(line: bytes) -> Json:
    """A server line as a dict; not JSON or not an object is a `ProtocolError`."""
    try:
        msg = json.loads(line)
    except ValueError as e:
        raise ProtocolError(f"rigd sent a line that is not JSON ({e}): {line[:200]!r}") from e
    if not isinstance(msg, dict):
        raise ProtocolError(f"rigd sent a line that is not an object: {line[:200]!r}")
    return msg


def notice_of(msg: Json) -> str:
    """The message of an id-less reply (a notice such as lost events)."""
    err = msg.get("error")
    return str(err.get("message", "")) if isinstance(err, dict) else str(msg)
