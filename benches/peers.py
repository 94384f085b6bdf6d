"""OpenCV's detection stage on a recording's images, one thread: the peer mrptv is compared with.

GaussianBlur 5x5, adaptiveThreshold (15 px box mean, 6 grey levels above it), findContours,
moments: the published method's detection, as its authors ran it. Images are read first; only
detection is timed. Prints one line: stereo pairs per second and detections per image.

    python3 benches/peers.py RECORDING [REPEATS]
"""

import sys
import time
from pathlib import Path

import cv2


def detect(image):
    blurred = cv2.GaussianBlur(image, (5, 5), 0)
    mask = cv2.adaptiveThreshold(
        blurred, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, 15, -6
    )
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    centroids = []
    for contour in contours:
        m = cv2.moments(contour)
        if m["m00"] > 0:
            centroids.append((m["m10"] / m["m00"], m["m01"] / m["m00"]))
    return centroids


def main():
    recording = Path(sys.argv[1])
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    cv2.setNumThreads(1)
    pairs = []
    for left in sorted((recording / "left").glob("*.png")):
        right = recording / "right" / left.name
        pairs.append(
            (
                cv2.imread(str(left), cv2.IMREAD_GRAYSCALE),
                cv2.imread(str(right), cv2.IMREAD_GRAYSCALE),
            )
        )
    if not pairs:
        sys.exit(f"no left/*.png in {recording}")
    best = float("inf")
    found = 0
    # The fastest of a few passes: this VM's neighbours only ever slow a pass down.
    for _ in range(repeats):
        start = time.perf_counter()
        found = sum(len(detect(left)) + len(detect(right)) for left, right in pairs)
        best = min(best, time.perf_counter() - start)
    print(f"{len(pairs) / best:.1f} {found / (2 * len(pairs)):.1f}")


if __name__ == "__main__":
    main()
