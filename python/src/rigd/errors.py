"""Exceptions: the daemon's error replies (by wire code), and the client's own failures."""

from __future__ import annotations

from typing import Any


class RigdError(Exception):
    """An error reply from rigd: `code` is the wire's error code, `message` its message.

    A code this package does not know (a newer daemon's) is still a `RigdError`, with the
    code as the daemon spelt it.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


class Malformed(RigdError):
    """`malformed`: the line was not JSON or not an object."""


class BadRequest(RigdError):
    """`bad_request`: unknown kind or field, wrong type, missing field, duplicate key, bad id."""


class VersionMismatch(RigdError):
    """`version`: the request's protocol version is not the daemon's."""


class LineTooLong(RigdError):
    """`line_too_long`: the request line was over 65 536 bytes."""


class Rejected(RigdError):
    """`rejected`: a job the rig cannot run, over a budget, or the rig is in fault."""


class NotFound(RigdError):
    """`not_found`: no such job or session."""


class Unavailable(RigdError):
    """`unavailable`: shutting down, or a limit reached (connections, subscriptions, queue)."""


class Busy(RigdError):
    """`busy`: a rig request while a job or another request runs."""


class Hardware(RigdError):
    """`hardware`: a rig request the controller refused or failed."""


class Internal(RigdError):
    """`internal`: the daemon failed on its side."""


_BY_CODE: dict[str, type[RigdError]] = {
    "malformed": Malformed,
    "bad_request": BadRequest,
    "version": VersionMismatch,
    "line_too_long": LineTooLong,
    "rejected": Rejected,
    "not_found": NotFound,
    "unavailable": Unavailable,
    "busy": Busy,
    "hardware": Hardware,
    "internal": Internal,
}


def error_from_wire(error: Any) -> RigdError:
    """The exception for a reply's `error` object (tolerant of a missing or odd shape)."""
    if not isinstance(error, dict):
        return RigdError("internal", f"error reply without an error object: {error!r}")
    code = str(error.get("code", "unknown"))
    message = str(error.get("message", ""))
    return _BY_CODE.get(code, RigdError)(code, message)


class CannotConnect(ConnectionError):
    """No rigd answers at the socket: `path` is where the client looked."""

    def __init__(self, path: Any, error: OSError) -> None:
        why = error.strerror or str(error)
        super().__init__(
            error.errno,
            f"cannot connect to rigd at {path} (is it running? `rigd --sim` starts one; "
            f"$RIGD_SOCKET names another socket): {why}",
        )
        self.path = path

    def __str__(self) -> str:
        return str(self.args[1])


class ProtocolError(Exception):
    """The daemon sent something this client cannot read (not JSON, a known event without
    a field it requires, ...)."""


class ConnectionClosed(ProtocolError):
    """The daemon closed the connection."""


class JobFailed(Exception):
    """`run()`: the job ended `failed` or `cancelled`; `event` is its last event."""

    def __init__(self, job_id: int, event: Any) -> None:
        reason = getattr(event, "reason", None) or ""
        super().__init__(f"job {job_id} {event.kind}: {reason}".rstrip(": "))
        self.job_id = job_id
        self.event = event
