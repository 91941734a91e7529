#!/bin/sh
# `rigctl export` read back by the reference Python readers: a fresh venv with zarr, ome-zarr,
# tifffile, numpy and Pillow; a session recorded by a live `rigd --sim` (a capture job of a
# few frames, with the sim's interferometer); both formats exported; tests/export_formats.py
# checks shapes, dtype, pixel size and unit, plane positions and times against steps.csv,
# the pixels against the PNGs, and the PNGs' own pHYs and tEXt chunks. NeXus too, of that
# session and of a grid over the axis and the piezo, read with h5py and silx (installed only
# then) when rigctl was built with the cargo feature `hdf5`; a rigctl without it says
# `SKIPPED: ...` for that part and the rest still runs. Builds nothing: give
# the binaries in $RIGD_BIN and $RIGCTL_BIN (default target/debug/rigd, target/debug/rigctl).
# Usage: RIGD_BIN=target/debug/rigd RIGCTL_BIN=target/debug/rigctl tests/export_formats.sh
set -eu
cd "$(dirname "$0")/.."
RIGD_BIN=$(realpath "${RIGD_BIN:-target/debug/rigd}")
RIGCTL_BIN=$(realpath "${RIGCTL_BIN:-target/debug/rigctl}")
for b in "$RIGD_BIN" "$RIGCTL_BIN"; do
    [ -x "$b" ] || { echo "export_formats: no binary at $b (cargo build --bin rigd --bin rigctl)"; exit 1; }
done
if ! python3 -c 'import ensurepip, venv' 2>/dev/null; then
    echo "export_formats: installing python3-venv"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
fi
DIR=$(mktemp -d)
PID=
cleanup() {
    [ -n "$PID" ] && { kill -TERM "$PID" 2>/dev/null || true; wait "$PID" 2>/dev/null || true; }
    rm -rf "$DIR"
}
trap cleanup EXIT
python3 -m venv "$DIR/venv"
"$DIR/venv/bin/pip" install -q --upgrade pip
"$DIR/venv/bin/pip" install -q zarr ome-zarr tifffile numpy pillow

"$RIGD_BIN" --sim --socket "$DIR/rigd.sock" --data-root "$DIR/data" 2>"$DIR/rigd.log" &
PID=$!
i=0
while [ ! -S "$DIR/rigd.sock" ]; do
    i=$((i + 1))
    if [ "$i" -gt 400 ]; then echo "export_formats: rigd did not start:"; cat "$DIR/rigd.log"; exit 1; fi
    sleep 0.05
done
"$RIGCTL_BIN" submit --socket "$DIR/rigd.sock" --step-um 50 --steps 6 --settle-ms 0 --no-process >"$DIR/submit.log" ||
    { cat "$DIR/submit.log" "$DIR/rigd.log"; exit 1; }
SESSION=$(ls -d "$DIR"/data/*-job1)
echo "export_formats: session $(basename "$SESSION")"
"$RIGCTL_BIN" export "$SESSION" --format ome-tiff --out "$DIR/out.ome.tif"
"$RIGCTL_BIN" export "$SESSION" --format ome-zarr --out "$DIR/out.ome.zarr"

# NeXus: only a rigctl built without the `hdf5` feature may skip it, and only saying so.
NEXUS=
if "$RIGCTL_BIN" export "$SESSION" --format nexus --out "$DIR/out.nxs" 2>"$DIR/nexus.err"; then
    "$RIGCTL_BIN" submit --socket "$DIR/rigd.sock" --grid-inner axis:50:3 --grid-outer piezo:20:2 \
        --settle-ms 0 --no-process >"$DIR/submit2.log" || { cat "$DIR/submit2.log" "$DIR/rigd.log"; exit 1; }
    GRID=$(ls -d "$DIR"/data/*-job2)
    "$RIGCTL_BIN" export "$GRID" --format nexus --out "$DIR/grid.nxs"
    "$DIR/venv/bin/pip" install -q h5py silx
    NEXUS="$SESSION $DIR/out.nxs $GRID $DIR/grid.nxs"
elif grep -q 'built without the cargo feature `hdf5`' "$DIR/nexus.err"; then
    echo "SKIPPED: tests/export_formats.sh NeXus: $RIGCTL_BIN was built without the cargo feature hdf5 (cargo build --features hdf5)"
else
    cat "$DIR/nexus.err"
    exit 1
fi
# shellcheck disable=SC2086 # NEXUS is pairs of paths from mktemp: no spaces
"$DIR/venv/bin/python" tests/export_formats.py "$SESSION" "$DIR/out.ome.tif" "$DIR/out.ome.zarr" $NEXUS
echo "export_formats: 1 passed, 0 failed"
