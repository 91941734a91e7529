#!/bin/sh
# Run docs/examples/client.py against a live `rigd --sim` on a temporary socket.
# Usage: tests/python_client.sh [path/to/rigd]   (default: target/debug/rigd, built if missing)
set -eu
cd "$(dirname "$0")/.."
RIGD=${1:-target/debug/rigd}
[ -x "$RIGD" ] || cargo build --bin rigd
DIR=$(mktemp -d)
"$RIGD" --sim --socket "$DIR/rigd.sock" --data-root "$DIR/data" 2>"$DIR/rigd.log" &
PID=$!
cleanup() { kill -TERM "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; rm -rf "$DIR"; }
trap cleanup EXIT
i=0
while [ ! -S "$DIR/rigd.sock" ]; do
    i=$((i + 1))
    if [ "$i" -gt 200 ]; then echo "rigd did not start:"; cat "$DIR/rigd.log"; exit 1; fi
    sleep 0.05
done
python3 docs/examples/client.py "$DIR/rigd.sock"
# Without an argument it takes $RIGD_SOCKET, as rigctl does.
RIGD_SOCKET="$DIR/rigd.sock" python3 docs/examples/client.py >/dev/null
# No daemon: a message naming the socket, not a traceback.
if out=$(python3 docs/examples/client.py "$DIR/missing.sock" 2>&1); then
    echo "client.py succeeded without a daemon"; exit 1
fi
case "$out" in
    *"cannot connect to rigd at $DIR/missing.sock"*) ;;
    *) echo "client.py without a daemon said: $out"; exit 1 ;;
esac
