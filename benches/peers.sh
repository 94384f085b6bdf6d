#!/usr/bin/env bash
# Side-by-side throughput (a benchmark, not a test): mrptv's whole pipeline against OpenCV's
# detection stage alone (benches/peers.py: GaussianBlur 5x5, adaptiveThreshold 15 px mean,
# findContours, moments; one thread), on the same `seeded` recordings (640x480, 2.5-6 px
# particles) at several densities, in one run. Both sides time their work only, on images
# already in memory (mrptv: the time inside the pipeline as `process` reports it; OpenCV: the
# fastest of 3 passes; mrptv: the fastest of 3 runs). Prints stereo pairs/s and the ratio.
#
#   bash benches/peers.sh [FRAMES]        (default 60 frames per density)
#
# With MRPTV_PREVIOUS=PATH (another build of mrptv, e.g. the previous release), that build's
# whole pipeline is measured on the same recordings in the same run, two cores, with its ratio:
# how a change moved the speed, apart from the machine's drift between runs. Its runs alternate
# with this build's two-core runs (5 of each, the fastest of each kept), so a slow spell of the
# machine falls on both alike.
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

previous="${MRPTV_PREVIOUS:-}"
[ -z "$previous" ] || [ -x "$previous" ] || { echo "MRPTV_PREVIOUS=$previous is not an executable" >&2; exit 1; }

# The fastest of 3 runs of this build's `process` ($1: RAYON_NUM_THREADS), pairs/s inside
# the pipeline.
mrptv_rate() {
  local best=0 rate
  for _ in 1 2 3; do
    rate="$(one_rate "$1" "$mrptv")"
    best="$(python3 -c "print(max($best, $rate))")"
  done
  echo "$best"
}

# One run of `process` ($1: RAYON_NUM_THREADS; $2: the binary), pairs/s inside the pipeline.
one_rate() {
  local rate
  # The run's summary is on stderr.
  rate="$(RAYON_NUM_THREADS="$1" "$2" process "$rec" --out "$work/t.csv" 2>&1 >/dev/null \
    | sed -n 's/.*; pipeline \([0-9.]*\) frames\/s.*/\1/p')"
  [ -n "$rate" ] || { echo "$2 process $rec failed" >&2; exit 1; }
  echo "$rate"
}

# The fastest of 5 alternating runs each of this build and the previous one, two cores: "ours
# previous" pairs/s.
paired_rates() {
  local best_ours=0 best_prev=0 ours prev
  for _ in 1 2 3 4 5; do
    ours="$(one_rate 2 "$mrptv")"
    prev="$(one_rate 2 "$previous")"
    best_ours="$(python3 -c "print(max($best_ours, $ours))")"
    best_prev="$(python3 -c "print(max($best_prev, $prev))")"
  done
  echo "$best_ours $best_prev"
}

echo "mrptv $("$mrptv" --version | cut -d' ' -f2), OpenCV $("$venv/bin/python" -c 'import cv2; print(cv2.__version__)'), $(nproc) cores, seeded scene 640x480, $frames frames per density"
header=(particles ppp touching "OpenCV det" "mrptv 1 core" "mrptv 2 cores" "ratio 1" "ratio 2")
[ -z "$previous" ] || header+=("previous 2 cores" "ratio 2 prev")
printf "%-9s %-8s %-9s %-14s %-14s %-14s %-10s %-10s" "${header[@]:0:8}"
[ -z "$previous" ] || printf " %-16s %-12s" "${header[@]:8}"
echo
for particles in 50 200 1000 1540 3070; do
  rec="$work/seeded-$particles"
  scene="$("$mrptv" synth seeded "$rec" --frames "$frames" --particles "$particles" | sed -n 1p)"
  ppp="$(sed -n 's/.*; \([0-9.]*\) particles per pixel.*/\1/p' <<<"$scene")"
  touching="$(sed -n 's/.*, \([0-9]*\) % of particle images touching.*/\1/p' <<<"$scene")"
  read -r opencv _ < <("$venv/bin/python" benches/peers.py "$rec" 3)
  one="$(mrptv_rate 1)"
  prev=""
  if [ -z "$previous" ]; then
    two="$(mrptv_rate 2)"
  else
    read -r two prev < <(paired_rates)
  fi
  python3 - "$particles" "$ppp" "$touching" "$opencv" "$one" "$two" "$prev" <<'PY'
import sys
n, ppp, touching, opencv, one, two, prev = sys.argv[1:]
opencv, one, two = float(opencv), float(one), float(two)
line = f"{n:<9} {ppp:<8} {touching + ' %':<9} {opencv:<14.1f} {one:<14.1f} {two:<14.1f} {one / opencv:<10.2f} {two / opencv:<10.2f}"
if prev:
    line += f" {float(prev):<16.1f} {float(prev) / opencv:<12.2f}"
print(line)
PY
done
echo "(pairs/s; ratio = mrptv's whole pipeline / OpenCV's detection alone)"
