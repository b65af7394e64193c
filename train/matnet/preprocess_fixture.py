#!/usr/bin/env python3
"""Writes tests/data/matnet_pre_*.npy: PyTorch's and OpenCV's own answers
for the MatNet pre-processing steps on a small deterministic photo, which a
Rust test in crates/onnx checks matflow's implementation against (CI needs
neither PyTorch nor OpenCV).

Steps (MatNet's contract, ../shared/paper/MATNET.md): centre-crop to a
square; bilinear resize with align_corners=True; /255 then ^2.2; bicubic
resize (align_corners=False, PyTorch's A = -0.75, borders clamped), here
both down and up. The official code does that last resize with OpenCV's
`cv2.resize(..., interpolation=cv2.INTER_CUBIC)` on float32; its answers
are written too (matnet_pre_cv2_*.npy), so the test also holds matflow to
OpenCV's kernel.

  pip install torch opencv-python-headless numpy
  python3 train/matnet/preprocess_fixture.py"""
import os

import cv2
import numpy as np
import torch
import torch.nn.functional as F

here = os.path.dirname(os.path.abspath(__file__))
out = os.path.join(here, "..", "..", "tests", "data")
h, w = 9, 13
img = ((np.arange(h * w * 3).reshape(h, w, 3) * 37 + 11) % 256).astype(np.uint8)
np.save(os.path.join(out, "matnet_pre_photo.npy"), img)
s = min(h, w)
y0, x0 = (h - s) // 2, (w - s) // 2
sq = torch.tensor(img[y0:y0 + s, x0:x0 + s]).permute(2, 0, 1)[None].float()
bil = F.interpolate(sq, size=(12, 12), mode="bilinear", align_corners=True)
lin = (bil / 255.0) ** 2.2
down = F.interpolate(lin, size=(7, 7), mode="bicubic", align_corners=False)
up = F.interpolate(lin, size=(17, 17), mode="bicubic", align_corners=False)
for name, t in [("bilinear", bil), ("linear", lin), ("bicubic_down", down), ("bicubic_up", up)]:
    np.save(os.path.join(out, f"matnet_pre_{name}.npy"), t[0].numpy().astype(np.float32))
hwc = np.ascontiguousarray(lin[0].permute(1, 2, 0).numpy().astype(np.float32))
for name, n in [("down", 7), ("up", 17)]:
    cv = cv2.resize(hwc, (n, n), interpolation=cv2.INTER_CUBIC)
    np.save(os.path.join(out, f"matnet_pre_cv2_{name}.npy"), np.ascontiguousarray(cv.transpose(2, 0, 1)))
print("torch", torch.__version__, "opencv", cv2.__version__)
