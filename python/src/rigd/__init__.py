"""rigd: a client for the rigd metrology-rig daemon and a reader of its session folders.

- `Client` (sync) and `AsyncClient` (asyncio): requests, typed events, `watch`, `run`.
- `Session`: a session folder as numpy / pandas / xarray.
"""

from .aio import AsyncClient
from .client import Client, connect
from .errors import (
    BadRequest,
    Busy,
    CannotConnect,
    ConnectionClosed,
    Hardware,
    Internal,
    JobFailed,
    LineTooLong,
    Malformed,
    NotFound,
    ProtocolError,
    RigdError,
    Rejected,
    Unavailable,
    VersionMismatch,
)
from .events import (
    Accepted,
    Calibrated,
    Calibration,
    Cancelled,
    Event,
    Failed,
    Finished,
    Paused,
    Preview,
    Processed,
    Result,
    Resumed,
    Started,
    Step,
    Timings,
    UnknownEvent,
    parse_event,
)
from .paths import default_socket
from .session import Session

__version__ = "0.1.0"

__all__ = [
    "Accepted", "AsyncClient", "BadRequest", "Busy", "Calibrated", "Calibration", "Cancelled", "CannotConnect", "Client", "ConnectionClosed",
    "Event", "Failed", "Finished", "Hardware", "Internal", "JobFailed", "LineTooLong",
    "Malformed", "NotFound", "Paused", "Preview", "Processed", "ProtocolError", "Rejected",
    "Result", "Resumed", "RigdError", "Session", "Started", "Step", "Timings", "Unavailable",
    "UnknownEvent", "VersionMismatch", "connect", "default_socket", "parse_event",
]  # fmt: skip
