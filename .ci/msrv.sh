#!/usr/bin/env bash
# MSRV check: fails when a package in Cargo.lock declares a `rust-version` newer than the
# workspace's (Cargo.toml [workspace.package] rust-version, inherited by rigd and rigd-sim).
# So the MSRV we state is one the locked dependencies can actually be built with.
#
# This only compares declarations: the machine has one toolchain, so a real
# `cargo +<msrv> build` is not possible here. Where rustup can install it, also run
# `cargo +$(msrv) build --locked --workspace --all-targets`.
# Every locked package counts (dev-dependencies and the optional `v4l` too): the tests and
# the `v4l2` feature must build with the MSRV as well.
set -euo pipefail
cd "$(dirname "$0")/.."
# --offline first: no index update when everything is already downloaded.
meta=$(cargo metadata --format-version 1 --locked --offline 2>/dev/null ||
    cargo metadata --format-version 1 --locked)
python3 -c '
import json, sys

def key(v):
    # "1.88" and "1.88.0" are the same version.
    parts = [int(x) for x in v.split(".")]
    return tuple(parts + [0] * (3 - len(parts)))

meta = json.load(sys.stdin)
members = set(meta["workspace_members"])
msrvs = {p["name"]: p.get("rust_version") for p in meta["packages"] if p["id"] in members}
missing = [n for n, v in msrvs.items() if not v]
if missing:
    sys.exit(f"msrv: workspace members without rust-version: {missing} (add rust-version.workspace = true)")
if len(set(msrvs.values())) != 1:
    sys.exit(f"msrv: workspace members disagree: {msrvs}")
msrv = next(iter(msrvs.values()))
newer = sorted(
    (p["rust_version"], p["name"], p["version"])
    for p in meta["packages"]
    if p["id"] not in members and p.get("rust_version") and key(p["rust_version"]) > key(msrv)
)
for rv, name, version in newer:
    print(f"msrv: {name} {version} needs Rust {rv}, above the workspace rust-version {msrv}")
if newer:
    sys.exit(1)
top = max((p.get("rust_version") or "0" for p in meta["packages"] if p["id"] not in members), key=key)
print(f"msrv: rust-version {msrv}; the newest any locked package asks for is {top}")
' <<<"$meta"
