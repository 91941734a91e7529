#!/usr/bin/env python3
"""The paper's job done the usual way with OpenCV + numpy: the baseline rigd is timed against.

    pip install opencv-python-headless numpy
    python3 benches/opencv_baseline.py DIR [--k 10] [--whole-frame]

DIR is a `rigctl process` folder (frames/*.png + steps.csv). Like `rigctl process DIR --k K
--estimator paper`: find the red targets in frame 0, register every frame by the mean shift
of the targets' ring centroids (the paper's), then per target ROI resize x k (INTER_CUBIC),
shift on the fine grid, average, and measure ring and disk centroids on the result. With
--whole-frame the whole green channel is reconstructed too. Prints the offsets and the time
of each stage; time the whole process with `/usr/bin/time -v`.
"""
import argparse
import csv
import glob
import os
import sys
import time

import cv2
import numpy as np


def red_mask(bgr):
    b, g, r = [c.astype(np.float32) for c in cv2.split(bgr)]
    return ((r - np.maximum(g, b)) / np.maximum(r, 1.0) > 0.4) & (r > 20)


def find_targets(bgr):
    """Rings: red components with a hole; ROI = bounding box + margin."""
    mask = red_mask(bgr).astype(np.uint8)
    n, labels, stats, cent = cv2.connectedComponentsWithStats(mask, connectivity=8)
    rois = []
    for i in range(1, n):
        x, y, w, h, area = stats[i]
        if w < 10 or h < 10 or abs(w - h) > 0.2 * max(w, h):
            continue
        if area > 0.6 * w * h:  # a disk, not a ring
            continue
        m = 6
        rois.append((max(x - m, 0), max(y - m, 0), w + 2 * m, h + 2 * m))
    return rois


def centroids(img, scale):
    """Ring and disk centroids of a thresholded grey ROI (ink is dark in green)."""
    lo, hi = np.percentile(img, 5), np.percentile(img, 95)
    ink = (img < (lo + hi) / 2).astype(np.uint8)
    n, labels, stats, cent = cv2.connectedComponentsWithStats(ink, connectivity=8)
    if n < 3:
        return None
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:2] + 1
    # The ring has the larger bounding box.
    ring, disk = sorted(order, key=lambda i: -stats[i, cv2.CC_STAT_WIDTH])
    to_px = lambda c: (c + 0.5) / scale - 0.5
    return to_px(cent[ring]), to_px(cent[disk])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("--k", type=int, default=10)
    ap.add_argument("--whole-frame", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    paths = sorted(glob.glob(os.path.join(a.dir, "frames", "*.png")))
    with open(os.path.join(a.dir, "steps.csv")) as f:
        steps = [float(r["position_um"]) for r in csv.DictReader(f)]
    frames = [cv2.imread(p, cv2.IMREAD_COLOR) for p in paths]
    t_read = time.perf_counter()
    rois = find_targets(frames[0])
    greens = [f[:, :, 1].astype(np.float32) for f in frames]
    ref = []
    for (x, y, w, h) in rois:
        ref.append(centroids(greens[0][y:y + h, x:x + w], 1)[0] + (x, y))
    shifts = []
    for g in greens:
        d = []
        for (x, y, w, h), r0 in zip(rois, ref):
            c = centroids(g[y:y + h, x:x + w], 1)
            if c is not None:
                d.append(c[0] + (x, y) - r0)
        shifts.append(np.mean(d, axis=0))
    t_reg = time.perf_counter()
    k = a.k
    out = []
    for (x, y, w, h) in rois:
        acc = np.zeros((h * k, w * k), np.float32)
        for g, d in zip(greens, shifts):
            up = cv2.resize(g[y:y + h, x:x + w], (w * k, h * k), interpolation=cv2.INTER_CUBIC)
            s = np.round(np.asarray(d) * k).astype(int)
            m = np.float32([[1, 0, -s[0]], [0, 1, -s[1]]])
            acc += cv2.warpAffine(up, m, (w * k, h * k), borderMode=cv2.BORDER_REPLICATE)
        acc /= len(greens)
        c = centroids(acc, k)
        if c is not None:
            out.append(((c[0][0] + x, c[0][1] + y), (c[1] - c[0]) * 774.0))
    t_roi = time.perf_counter()
    if a.whole_frame:
        h, w = greens[0].shape
        acc = np.zeros((h * k, w * k), np.float32)
        for g, d in zip(greens, shifts):
            up = cv2.resize(g, (w * k, h * k), interpolation=cv2.INTER_CUBIC)
            s = np.round(np.asarray(d) * k).astype(int)
            m = np.float32([[1, 0, -s[0]], [0, 1, -s[1]]])
            acc += cv2.warpAffine(up, m, (w * k, h * k), borderMode=cv2.BORDER_REPLICATE)
        acc /= len(greens)
    t_whole = time.perf_counter()
    for centre, off in out:
        print(f"centre ({centre[0]:8.2f}, {centre[1]:8.2f}) px  offset ({off[0]:8.1f}, {off[1]:8.1f}) um")
    print(
        f"{len(frames)} frames, {len(rois)} targets, k={k}: read {t_read - t0:.3f} s, "
        f"register {t_reg - t_read:.3f} s, ROIs {t_roi - t_reg:.3f} s, "
        f"whole frame {t_whole - t_roi:.3f} s, total {t_whole - t0:.3f} s",
        file=sys.stderr,
    )


if __name__ == "__main__":
    main()
