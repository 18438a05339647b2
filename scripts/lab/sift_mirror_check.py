"""Lab (2026-12-07): where ``camera_map.sift`` puts its keypoints, checked on any image without knowing where its
features are. A feature at column ``x`` of an image is at ``W - 1 - x`` of its mirror image; an unbiased detector's
keypoints in the two images sum to ``W - 1``. Half the median excess of keypoint pairs (nearest within 0.8 px after
mirroring back) is the detector's bias along that axis (OpenCV's SIFT alone: +0.25 px, opencv/opencv#23123).

Usage: .venv/bin/python scripts/lab/sift_mirror_check.py IMAGE [IMAGE ...]
"""
import sys

import cv2
import numpy as np
from scipy.spatial import cKDTree

from moisst_ns.stages.camera.camera_map import sift

for path in sys.argv[1:]:
    image = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    keys, _ = sift(image, 4000)
    line = [f"{path}: {image.shape[1]}x{image.shape[0]}"]
    for axis, size, c in ((1, image.shape[1], 0), (0, image.shape[0], 1)):
        mirrored, _ = sift(np.ascontiguousarray(np.flip(image, axis)), 4000)
        mirrored[:, c] = (size - 1) - mirrored[:, c]  # x - b for a keypoint at x + b
        dist, j = cKDTree(mirrored).query(keys)
        ok = dist < 0.8
        excess = (keys[ok, c] - mirrored[j[ok], c]) / 2
        line.append(f"{'xy'[c]}: {ok.sum()} pairs, bias median {np.median(excess):+.3f} px, mean {np.mean(excess):+.3f} px")
    print("; ".join(line))
