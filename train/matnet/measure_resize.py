#!/usr/bin/env python3
"""How far matflow's 512 -> 518 bicubic resize (PyTorch's kernel) is from
the official MatNet's (OpenCV's INTER_CUBIC on float32), on real photos:
the official preprocessing up to the resize (centre crop; bilinear to 512
with align_corners; /255; ^2.2), then both resizes, and their largest and
mean differences, in the interior and on the 3-pixel border.

  pip install torch opencv-python-headless pillow
  python3 train/matnet/measure_resize.py [PHOTO ...]   # default: ../shared's"""
import os
import sys

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

SHARED = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "shared", "data", "materialist")
DEFAULT = ["examples/indoor1.png", "examples/indoor2.png", "examples/99866.png", "indoor/gt_image.png", "jinjya/gt_image.png"]


def official_512(path):
    """The official inference's input up to its 518 resize: the photo's
    centre square, /255, bilinear to 512² (align_corners), ^2.2; [1, 3,
    512, 512] float32."""
    img = np.asarray(Image.open(path).convert("RGB"))
    h, w, _ = img.shape
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    t = torch.tensor(img[y0 : y0 + s, x0 : x0 + s]).permute(2, 0, 1)[None].float() / 255.0
    return F.interpolate(t, size=(512, 512), mode="bilinear", align_corners=True) ** 2.2


def main():
    photos = sys.argv[1:] or [os.path.join(SHARED, p) for p in DEFAULT]
    print(f"opencv {cv2.__version__}, torch {torch.__version__}")
    print("| photo | max abs | mean abs | interior max | border max | max, in 8-bit steps |")
    print("|---|---|---|---|---|---|")
    worst = 0.0
    for path in photos:
        lin = official_512(path)
        hwc = np.ascontiguousarray(lin[0].permute(1, 2, 0).numpy())
        cv = cv2.resize(hwc, (518, 518), interpolation=cv2.INTER_CUBIC)
        pt = F.interpolate(lin, size=(518, 518), mode="bicubic", align_corners=False)[0].permute(1, 2, 0).numpy()
        d = np.abs(cv - pt)
        border = max(d[:3].max(), d[-3:].max(), d[:, :3].max(), d[:, -3:].max())
        name = os.path.relpath(path, SHARED) if path.startswith(SHARED) else path
        print(
            f"| {name} | {d.max():.2e} | {d.mean():.2e} | {d[3:-3, 3:-3].max():.2e} | {border:.2e} "
            f"| {d.max() * 255:.4f} |"
        )
        worst = max(worst, float(d.max()))
    print(f"largest difference: {worst:.2e} ({worst * 255:.4f} of an 8-bit step)")


if __name__ == "__main__":
    main()
