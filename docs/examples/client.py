#!/usr/bin/env python3
"""A minimal rigd client: the JSON-lines protocol of docs/protocol.md, standard library only.

Usage: client.py [SOCKET]   (default: $RIGD_SOCKET, else $XDG_RUNTIME_DIR/rigd.sock, else
/tmp/rigd-UID.sock, as rigd's own default)
Says hello, submits a 5-frame capture job, follows its events to the end, fetches the
result and checks a bad request gets an error reply. Exits non-zero if anything is off.

Like every client it is tolerant of a newer daemon (docs/protocol.md, "Compatibility"): it
skips line types and event kinds it does not know and ignores fields it does not use.
"""
import json
import os
import socket
import sys

# The event kinds this client handles; others (a newer daemon's) are skipped. `hello`'s
# capabilities list what the daemon may send.
KNOWN_EVENTS = {"accepted", "started", "step", "processed", "result", "finished", "failed", "cancelled"}


def default_socket():
    """rigd's default socket: $RIGD_SOCKET, $XDG_RUNTIME_DIR/rigd.sock, /tmp/rigd-UID.sock."""
    if os.environ.get("RIGD_SOCKET"):
        return os.environ["RIGD_SOCKET"]
    if os.environ.get("XDG_RUNTIME_DIR"):
        return os.path.join(os.environ["XDG_RUNTIME_DIR"], "rigd.sock")
    return f"/tmp/rigd-{os.getuid()}.sock"


class Rigd:
    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.sock.connect(path)
        except OSError as e:
            raise SystemExit(f"cannot connect to rigd at {path} (is it running? `rigd --sim` "
                             f"starts one): {e.strerror}")
        self.file = self.sock.makefile("rwb")
        self.next_id = 1
        self.events = []

    def _line(self):
        """The next reply or event of a kind this client knows; anything else is skipped."""
        while True:
            line = self.file.readline()
            if not line:
                raise RuntimeError("rigd closed the connection")
            msg = json.loads(line)
            kind = msg.get("type")
            if kind == "reply" or (kind == "event" and msg.get("event") in KNOWN_EVENTS):
                return msg

    def request(self, kind, **fields):
        """Send a request; return its result, or raise with the daemon's error."""
        rid = self.next_id
        self.next_id += 1
        self.file.write((json.dumps({"v": 1, "id": rid, "kind": kind, **fields}) + "\n").encode())
        self.file.flush()
        while True:
            msg = self._line()
            if msg["type"] == "event":
                self.events.append(msg)  # events may arrive before the reply
            elif msg.get("id") == rid:
                if not msg["ok"]:
                    error = msg.get("error", {})
                    raise RuntimeError("{}: {}".format(error.get("code"), error.get("message")))
                return msg.get("result")

    def event(self):
        if self.events:
            return self.events.pop(0)
        while True:
            msg = self._line()
            if msg["type"] == "event":
                return msg


def main(path):
    rigd = Rigd(path)
    hello = rigd.request("hello")
    print("rigd", hello["rigd"], "protocol", hello["protocol"], "rig", hello["rig"]["mode"])
    serves = hello.get("capabilities", {}).get("requests")  # absent before capabilities
    assert serves is None or "submit" in serves, serves
    rigd.request("subscribe")  # all jobs' events: none of the new job's can be missed
    job = rigd.request("submit", job={"step_um": 50.0, "steps": 5, "settle_ms": 0, "process": False})
    job_id = job["job_id"]
    print("job", job_id, "queued:", job["total_frames"], "frames")
    steps = 0
    while True:
        ev = rigd.event()
        if ev["job_id"] != job_id:
            continue
        if ev["event"] == "step":
            steps += 1
            print("  step {index}: commanded {commanded_um:.1f} µm, axis {axis_um:.1f} µm".format(**ev))
        if ev["event"] in ("finished", "failed", "cancelled"):
            print("job", job_id, ev["event"], ev.get("reason", ""))
            break
    assert ev["event"] == "finished" and steps == 5, ev
    result = rigd.request("result", job_id=job_id)
    print("session", result["session"], "state", result["state"])
    try:
        rigd.request("submit", job={"step_um": 0.0, "steps": 3})
        raise SystemExit("a zero step was accepted")
    except RuntimeError as e:
        print("refused as expected:", e)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else default_socket()))
