#!/usr/bin/env bash
# Side-by-side throughput (a benchmark, not a test): mrptv's whole pipeline against OpenCV's
# detection stage alone (benches/peers.py: GaussianBlur 5x5, adaptiveThreshold 15 px mean,
# findContours, moments; one thread), on the same `seeded` recordings (640x480, 2.5-6 px
# particles) at several densities, in one run. Both sides time their work only, on images
# already in memory (mrptv: the time inside the pipeline as `process` reports it; OpenCV: the
# fastest of 3 passes; mrptv: the fastest of 3 runs). Prints stereo pairs/s and the ratio.
#
#   bash benches/peers.sh [FRAMES]        (default 60 frames per density)
set -euo pipefail
cd "$(dirname "$0")/.."
frames="${1:-60}"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$HOME/.cache/mrptv-target}"
cargo build --release --quiet
mrptv="$CARGO_TARGET_DIR/release/mrptv"

# OpenCV in its own virtual environment, installed once from PyPI.
venv="$HOME/.cache/mrptv-peers/venv"
if ! "$venv/bin/python" -c "import cv2" 2>/dev/null; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet "opencv-python-headless>=4.9,<5"
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

# The fastest of 3 runs of `process` ($1: RAYON_NUM_THREADS), pairs/s inside the pipeline.
mrptv_rate() {
  local best=0 rate
  for _ in 1 2 3; do
    # The run's summary is on stderr.
    rate="$(RAYON_NUM_THREADS="$1" "$mrptv" process "$rec" --out "$work/t.csv" 2>&1 >/dev/null \
      | sed -n 's/.*; pipeline \([0-9.]*\) frames\/s.*/\1/p')"
    [ -n "$rate" ] || { echo "mrptv process $rec failed" >&2; exit 1; }
    best="$(python3 -c "print(max($best, $rate))")"
  done
  echo "$best"
}

echo "mrptv $("$mrptv" --version | cut -d' ' -f2), OpenCV $("$venv/bin/python" -c 'import cv2; print(cv2.__version__)'), $(nproc) cores, seeded scene 640x480, $frames frames per density"
printf "%-9s %-8s %-9s %-14s %-14s %-14s %-10s %-10s\n" particles ppp touching "OpenCV det" "mrptv 1 core" "mrptv 2 cores" "ratio 1" "ratio 2"
for particles in 50 200 1000 1540 3070; do
  rec="$work/seeded-$particles"
  scene="$("$mrptv" synth seeded "$rec" --frames "$frames" --particles "$particles" | head -1)"
  ppp="$(sed -n 's/.*; \([0-9.]*\) particles per pixel.*/\1/p' <<<"$scene")"
  touching="$(sed -n 's/.*, \([0-9]*\) % of particle images touching.*/\1/p' <<<"$scene")"
  read -r opencv _ < <("$venv/bin/python" benches/peers.py "$rec" 3)
  one="$(mrptv_rate 1)"
  two="$(mrptv_rate 2)"
  python3 - "$particles" "$ppp" "$touching" "$opencv" "$one" "$two" <<'PY'
import sys
n, ppp, touching, opencv, one, two = sys.argv[1:]
opencv, one, two = float(opencv), float(one), float(two)
print(f"{n:<9} {ppp:<8} {touching + ' %':<9} {opencv:<14.1f} {one:<14.1f} {two:<14.1f} {one / opencv:<10.2f} {two / opencv:<10.2f}")
PY
done
echo "(pairs/s; ratio = mrptv's whole pipeline / OpenCV's detection alone)"
