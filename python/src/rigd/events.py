"""Typed events: one frozen dataclass per event kind of docs/protocol.md, `UnknownEvent`
for kinds this package does not know (a newer daemon's). Every event keeps the whole line
in `raw`, so fields this package does not know are not lost; unknown fields are ignored.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Optional

from .errors import ProtocolError

Json = dict[str, Any]


@dataclass(frozen=True, kw_only=True)
class Event:
    """What every event carries: the job it is about (0: none, e.g. a live-view frame),
    its kind (`event` on the wire) and the whole line as received."""

    kind: ClassVar[str] = ""
    #: Whether this event ends its job (`finished`, `failed`, `cancelled`).
    terminal: ClassVar[bool] = False
    job_id: int
    raw: Json = field(repr=False, compare=False)

    @property
    def event(self) -> str:
        """The wire's event kind."""
        return self.kind


@dataclass(frozen=True)
class Timings:
    """A step's durations, ms."""

    move_ms: float
    settle_ms: float
    grab_ms: float


@dataclass(frozen=True, kw_only=True)
class Accepted(Event):
    kind: ClassVar[str] = "accepted"
    queue_position: int
    total_frames: int
    job: Json = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class Started(Event):
    kind: ClassVar[str] = "started"
    session: str
    total_frames: int


@dataclass(frozen=True, kw_only=True)
class Step(Event):
    """A frame is on disk. Positions in µm; `interferometer_um` None without a reading."""

    kind: ClassVar[str] = "step"
    index: int
    run: int
    case: str
    repeat: int
    commanded_um: float
    axis_um: Optional[float] = None
    interferometer_um: Optional[float] = None
    timings: Optional[Timings] = None
    total_frames: int = 0
    #: With a plan that moves the piezo besides the axis.
    piezo_commanded_um: Optional[float] = None
    piezo_um: Optional[float] = None


@dataclass(frozen=True, kw_only=True)
class Processed(Event):
    kind: ClassVar[str] = "processed"
    index: int
    process_ms: float = 0.0
    targets_found: int = 0


@dataclass(frozen=True, kw_only=True)
class Result(Event):
    """A run was processed: `objects` targets measured, or `error`."""

    kind: ClassVar[str] = "result"
    run: int
    case: str
    repeat: int
    objects: Optional[int] = None
    error: Optional[str] = None


@dataclass(frozen=True, kw_only=True)
class Finished(Event):
    kind: ClassVar[str] = "finished"
    terminal: ClassVar[bool] = True
    session: str


@dataclass(frozen=True, kw_only=True)
class Failed(Event):
    kind: ClassVar[str] = "failed"
    terminal: ClassVar[bool] = True
    reason: str
    session: Optional[str] = None
    #: The reason's fields (`kind`, `device`, `stopped`, ...: docs/protocol.md).
    detail: Optional[Json] = None


@dataclass(frozen=True, kw_only=True)
class Cancelled(Event):
    kind: ClassVar[str] = "cancelled"
    terminal: ClassVar[bool] = True
    session: Optional[str] = None
    reason: Optional[str] = None
    detail: Optional[Json] = None


@dataclass(frozen=True, kw_only=True)
class Paused(Event):
    """The job paused (a client's `pause`, or the controller's feed hold)."""

    kind: ClassVar[str] = "paused"
    next_index: int
    at_um: Optional[float] = None
    cause: Optional[str] = None
    reason: Optional[str] = None


@dataclass(frozen=True, kw_only=True)
class Resumed(Event):
    kind: ClassVar[str] = "resumed"
    next_index: int


@dataclass(frozen=True, kw_only=True)
class Preview(Event):
    """A live-view frame (after `preview`): the image is `png_base64` (8-bit RGB PNG)."""

    kind: ClassVar[str] = "preview"
    t_unix_s: float
    sequence: int
    width: int
    height: int
    png_base64: str = field(repr=False)
    index: Optional[int] = None
    stage_um: Json = field(default_factory=dict)
    frame_size: Optional[list[int]] = None
    crop: Optional[list[int]] = None
    scale: Optional[float] = None
    targets: list[Json] = field(default_factory=list)


@dataclass(frozen=True, kw_only=True)
class Calibration(Event):
    """After `started`: the stage calibration the job applies (`applied`), or why none
    (`reason`); `warnings` when it is stale or fitted for another scale, board or frame."""

    kind: ClassVar[str] = "calibration"
    applied: bool
    id: Optional[str] = None
    date: Optional[str] = None
    method: Optional[str] = None
    source: Optional[str] = None
    age_days: Optional[float] = None
    reason: Optional[str] = None
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True, kw_only=True)
class Calibrated(Event):
    """A calibration job fitted its scan and made it the data root's current one."""

    kind: ClassVar[str] = "calibrated"
    id: str
    path: str
    date: Optional[str] = None
    method: Optional[str] = None
    session: Optional[str] = None
    frames: Optional[int] = None
    step_um: Optional[float] = None
    targets: Optional[int] = None
    residual_rms_um: Optional[float] = None
    residual_max_um: Optional[float] = None
    summary: Optional[str] = None


@dataclass(frozen=True, kw_only=True)
class UnknownEvent(Event):
    """An event kind this package does not know: `name` is its kind, `raw` the line."""

    name: str

    @property
    def event(self) -> str:
        return self.name


KNOWN: dict[str, type[Event]] = {
    cls.kind: cls
    for cls in (
        Accepted,
        Started,
        Step,
        Processed,
        Result,
        Finished,
        Failed,
        Cancelled,
        Paused,
        Resumed,
        Preview,
        Calibration,
        Calibrated,
    )
}


def _value(cls: type[Event], name: str, value: Any) -> Any:
    if cls is Step and name == "timings" and isinstance(value, Mapping):
        return Timings(
            move_ms=float(value.get("move_ms", 0.0)),
            settle_ms=float(value.get("settle_ms", 0.0)),
            grab_ms=float(value.get("grab_ms", 0.0)),
        )
    return value


def parse_event(line: Json) -> Event:
    """The typed event of an event line (`{"type": "event", ...}`).

    Unknown kinds give an `UnknownEvent`; unknown fields are ignored (kept in `raw`). A
    known kind that lacks a field it requires raises `ProtocolError`.
    """
    name = line.get("event")
    job_id = line.get("job_id", 0)
    if not isinstance(name, str) or not isinstance(job_id, int):
        raise ProtocolError(f"an event line without a kind or job id: {line!r}")
    cls = KNOWN.get(name)
    if cls is None:
        return UnknownEvent(job_id=job_id, raw=line, name=name)
    args: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name in ("job_id", "raw"):
            continue
        if f.name in line and line[f.name] is not None:
            args[f.name] = _value(cls, f.name, line[f.name])
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            if f.name in line:  # present but null: take it as None
                args[f.name] = None
            else:
                raise ProtocolError(f"`{name}` event without `{f.name}`: {line!r}")
    return cls(job_id=job_id, raw=line, **args)
