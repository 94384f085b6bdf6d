#!/usr/bin/env bash
# Loopback benchmark of the live path (a benchmark, not a test): `mrptv replay` against a local
# `mrptv serve` on the flume scenario. Reports frames/s and the latency from "frame handed to the
# socket" to "its causal vectors received", for: one headset as fast as the server answers, one
# headset at 30 Hz (raw8 and PNG), and 4 concurrent headsets at 30 Hz; then one headset at 30 Hz
# on the `seeded` scene (dense seeding: 0.005 particles per pixel, 640x480).
#
#   bash benches/loopback.sh [FRAMES]        (default 300 frames = 10 s at 30 Hz)
set -euo pipefail
cd "$(dirname "$0")/.."
frames="${1:-300}"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/mrptv-target}"
cargo build --release --quiet
mrptv="$CARGO_TARGET_DIR/release/mrptv"
work="$(mktemp -d)"
trap 'kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true; rm -rf "$work"' EXIT

"$mrptv" synth flume "$work/flume" --frames "$frames" >/dev/null
"$mrptv" synth seeded "$work/seeded" --frames "$frames" >/dev/null
"$mrptv" serve --bind 127.0.0.1:0 >"$work/server.out" 2>"$work/server.log" &
server=$!
for _ in $(seq 100); do
  grep -q "listening on" "$work/server.out" 2>/dev/null && break
  sleep 0.1
done
addr="$(sed -n 's|.*listening on http://||p' "$work/server.out")"
[ -n "$addr" ] || { echo "server did not start:"; cat "$work/server.log"; exit 1; }
url="ws://$addr/v1/ingest"
echo "mrptv $("$mrptv" --version | cut -d' ' -f2), $(nproc) cores, flume scenario, $frames frames of 640x480 per headset"

run() {
  echo
  echo "== $1"
  shift
  "$mrptv" replay "$work/${scene:-flume}" --url "$url" "$@"
}
run "1 headset, --rate max (2 frames in flight), raw8" --rate max
run "1 headset, 30 Hz, raw8" --rate recorded
run "1 headset, 30 Hz, png" --rate recorded --encoding png
run "4 headsets, 30 Hz each, raw8" --rate recorded --headsets 4
scene=seeded run "1 headset, 30 Hz, raw8, seeded (0.005 particles per pixel)" --rate recorded
