#!/usr/bin/env python3
"""A sheet to look at a model's depth and normals on held-out samples:
one row a sample, columns photo | true ln z | predicted ln z | true
normals | predicted normals.

Both depths are drawn on the true depth's scale (its 2nd to 98th
percentile of ln z over the pixels with geometry, black to white), so a
prediction that squeezes the far floor or ground towards the camera
shows as a lighter near and a darker far; pixels without geometry are
dark blue. Normals as 0.5 + 0.5 n (camera frame: x right, y up, z
towards the camera).

    python3 train/matnet/show_predictions.py --heldout out/matnet/heldout \\
        --model models/matnet_rooms.onnx --samples 2,10,0,36 --out sheet.jpg

The photo goes in as train.py's held-out scoring feeds it (onnxruntime).
"""

import argparse
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import train  # noqa: E402

NONE = np.array([20, 30, 90], np.uint8)


def grey(lz, lo, hi, valid):
    g = (np.clip((lz - lo) / max(hi - lo, 1e-6), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    out = np.repeat(g[..., None], 3, -1)
    out[~valid] = NONE
    return out


def colour(n, valid):
    out = (np.clip(n * 0.5 + 0.5, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    out[~valid] = NONE
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heldout", required=True, help="a rooms dataset (matflow dataset …)")
    ap.add_argument("--model", required=True)
    ap.add_argument("--samples", required=True, help="sample numbers, comma-separated")
    ap.add_argument("--size", type=int, default=128, help="side of each tile")
    ap.add_argument("--out", required=True, help=".png or .jpg")
    a = ap.parse_args()
    d = train.load(a.heldout)
    s = ort.InferenceSession(a.model, providers=["CPUExecutionProvider"])
    rows = []
    for k in a.samples.split(","):
        i = int(k)
        if not 0 <= i < len(d["photo"]):
            sys.exit(f"show_predictions.py: --samples: {i} is not one of the {len(d['photo'])} samples")
        photo = d["photo"][i][..., :3]
        x = train.torch_preprocess(photo, train.SIZE).numpy()
        depth, _, _, _, normal = s.run(None, {s.get_inputs()[0].name: x})
        valid = d["valid"][i].astype(bool)
        valid = valid[..., 0] if valid.ndim == 3 else valid
        tz = d["depth"][i].astype(np.float32)
        tz = tz[..., 0] if tz.ndim == 3 else tz
        lt = np.log(np.maximum(tz, 1e-3))
        lo, hi = np.percentile(lt[valid], [2, 98]) if valid.any() else (0.0, 1.0)
        lp = np.log(np.maximum(depth[0, 0], 1e-3))
        tiles = [
            photo,
            grey(lt, lo, hi, valid),
            grey(lp, lo, hi, valid),
            colour(d["normal"][i].astype(np.float32), valid),
            colour(normal[0].transpose(1, 2, 0), valid),
        ]
        tiles = [np.asarray(Image.fromarray(t).resize((a.size, a.size), Image.BILINEAR)) for t in tiles]
        rows.append(np.concatenate(tiles, 1))
        print(
            f"sample {i} ({d['kind'][i]}): true z {np.exp(lo):.1f} to {np.exp(hi):.1f}, "
            f"predicted {np.exp(np.percentile(lp[valid], 2)):.1f} to {np.exp(np.percentile(lp[valid], 98)):.1f}"
        )
    Image.fromarray(np.concatenate(rows, 0)).save(a.out, quality=88)


if __name__ == "__main__":
    main()
