"""Where the daemon's socket is, as rigd and rigctl resolve it."""

from __future__ import annotations

import os
from pathlib import Path


def default_socket() -> Path:
    """`$RIGD_SOCKET`, else `$XDG_RUNTIME_DIR/rigd.sock`, else `/tmp/rigd-UID.sock`."""
    explicit = os.environ.get("RIGD_SOCKET")
    if explicit:
        return Path(explicit)
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        return Path(runtime) / "rigd.sock"
    return Path(f"/tmp/rigd-{os.getuid()}.sock")


def resolve_socket(path: str | os.PathLike[str] | None) -> Path:
    """`path` if given, else `default_socket()`."""
    return Path(path) if path is not None else default_socket()
