#!/usr/bin/env python3
"""Train the refraction-length network on matflow's refraction dataset and
export it to ONNX.

The network sees a square crop around an object (its bounding box, padded
by CROP_PAD, resampled to CROP x CROP by nearest neighbour) with 8 input
channels and predicts 3 output channels per crop pixel:

  inputs   0-2  the photograph, sRGB in [0, 1]
           3    the object's mask (0 or 1)
           4    depth relative to the object: (z - z_mean) / s, clipped to
                [-2, 2] (0 outside the mask)
           5-7  camera-space normals (0 outside the mask)
  outputs  0    the eq. 24 refraction length / s
           1    d1 (entry to final exit) / s
           2    d2 (exit to the surface behind) / s

where s = (longest side of the mask's bounding box, in pixels) * z_mean / f
is the object's extent in scene units as the camera sees it (f: the focal
length in pixels, W / 2 / tan(17.5 deg)) and z_mean the mean depth over
the mask. Lengths come back as output * s, so the same network serves any
image size and scene scale. matflow's `refraction_length` node does exactly
this preprocessing in Rust (crates/onnx/src/refraction.rs).

Usage (after generating the data, see data.yaml / heldout.yaml):
  python3 train/refraction/train.py --train out/refraction/train \
      --heldout out/refraction/heldout --out models/refraction_length.onnx
"""

import argparse
import io
import json
import math
import os
import sys
import tarfile
import time

import numpy as np
from PIL import Image

CROP = 64
CROP_PAD = 1.2
IN_CH = 8
HALF_FOV = math.radians(17.5)
D2_CLIP = 4.0


def load_shards(folder):
    """Every sample of the dataset in `folder`: dict of decoded members."""
    desc = json.load(open(os.path.join(folder, "dataset.json")))
    norm = desc["header"]["normaliser"]["length.npy"]
    samples = []
    for k in range(desc["shards"]):
        path = os.path.join(folder, f"{desc['name']}-{k:06d}.tar")
        cur = {}
        with tarfile.open(path) as t:
            for m in t.getmembers():
                key, member = m.name.split(".", 1)
                data = t.extractfile(m).read()
                if cur and cur["key"] != key:
                    samples.append(cur)
                    cur = {}
                cur["key"] = key
                if member.endswith(".npy"):
                    cur[member[:-4]] = np.load(io.BytesIO(data)).astype(np.float32)
                elif member.endswith(".png"):
                    cur[member[:-4]] = np.asarray(Image.open(io.BytesIO(data)))
                elif member.endswith(".json"):
                    cur[member[:-5]] = json.loads(data)
        if cur:
            samples.append(cur)
    for s in samples:
        s["length"] = s["length"] * norm
    return samples


def crop_window(mask):
    """(x0, y0, side) of the square crop around the mask's bounding box."""
    ys, xs = np.nonzero(mask)
    bx0, bx1, by0, by1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    side = max(bx1 - bx0, by1 - by0) * CROP_PAD
    cx, cy = (bx0 + bx1) / 2.0, (by0 + by1) / 2.0
    return cx - side / 2.0, cy - side / 2.0, side, max(bx1 - bx0, by1 - by0)


def crop_indices(h, w, x0, y0, side):
    """Source pixel (row, col) of each crop pixel (nearest) and validity."""
    t = (np.arange(CROP) + 0.5) * side / CROP
    cols = np.floor(x0 + t).astype(np.int64)
    rows = np.floor(y0 + t).astype(np.int64)
    r = np.repeat(rows[:, None], CROP, 1)
    c = np.repeat(cols[None, :], CROP, 0)
    ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    return np.clip(r, 0, h - 1), np.clip(c, 0, w - 1), ok


def prepare(s):
    """(inputs [8, C, C], targets [3, C, C], loss weights [3, C, C], s)."""
    mask = s["mask"] > 127
    if mask.ndim == 3:
        mask = mask[..., 0]
    h, w = mask.shape
    f = (w / 2.0) / math.tan(HALF_FOV)
    z = s["depth"]
    z_mean = float(z[mask].mean())
    x0, y0, side, extent = crop_window(mask)
    scale = extent * z_mean / f
    r, c, ok = crop_indices(h, w, x0, y0, side)
    m = (mask[r, c] & ok).astype(np.float32)
    img = s["image"][..., :3].astype(np.float32) / 255.0
    x = np.zeros((IN_CH, CROP, CROP), np.float32)
    x[0:3] = np.transpose(img[r, c], (2, 0, 1)) * ok[None]
    x[3] = m
    x[4] = np.clip((z[r, c] - z_mean) / scale, -2.0, 2.0) * m
    x[5:8] = np.transpose(s["normal"][r, c], (2, 0, 1)) * m[None]
    y = np.zeros((3, CROP, CROP), np.float32)
    y[0] = s["length"][r, c] / scale * m
    y[1] = s["d1"][r, c] / scale * m
    y[2] = np.minimum(s["d2"][r, c] / scale, D2_CLIP) * m
    wgt = np.zeros((3, CROP, CROP), np.float32)
    wgt[0] = m
    wgt[1] = m
    wgt[2] = m * (s["d2"][r, c] > 0)
    return x, y, wgt, scale


def build_model(torch):
    nn = torch.nn

    def block(i, o):
        return nn.Sequential(
            nn.Conv2d(i, o, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(o, o, 3, padding=1), nn.ReLU(inplace=True))

    class UNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.e1, self.e2, self.e3 = block(IN_CH, 16), block(16, 32), block(32, 64)
            self.mid = block(64, 64)
            self.d3, self.d2, self.d1 = block(128, 32), block(64, 16), block(32, 16)
            self.pool = nn.MaxPool2d(2)
            self.up = nn.Upsample(scale_factor=2, mode="nearest")
            self.head = nn.Conv2d(16, 3, 1)

        def forward(self, x):
            a = self.e1(x)
            b = self.e2(self.pool(a))
            c = self.e3(self.pool(b))
            m = self.mid(self.pool(c))
            u = self.d3(torch.cat([self.up(m), c], 1))
            u = self.d2(torch.cat([self.up(u), b], 1))
            u = self.d1(torch.cat([self.up(u), a], 1))
            # Lengths are not negative; only the object's pixels count.
            return nn.functional.softplus(self.head(u)) * x[:, 3:4]

    return UNet()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train", required=True)
    ap.add_argument("--heldout", required=True)
    ap.add_argument("--out", required=True, help="the ONNX file to write")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()

    import torch
    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(a.seed)
    t0 = time.time()
    train = [prepare(s) for s in load_shards(a.train) if (s["mask"] > 127).any()]
    held = [prepare(s) for s in load_shards(a.heldout) if (s["mask"] > 127).any()]
    X = torch.tensor(np.stack([t[0] for t in train]))
    Y = torch.tensor(np.stack([t[1] for t in train]))
    W = torch.tensor(np.stack([t[2] for t in train]))
    Xh = torch.tensor(np.stack([t[0] for t in held]))
    Yh = torch.tensor(np.stack([t[1] for t in held]))
    Wh = torch.tensor(np.stack([t[2] for t in held]))
    print(f"{len(train)} training, {len(held)} held-out samples "
          f"(loaded in {time.time() - t0:.1f} s)", flush=True)

    # The constant baseline: each output's mean over the training pixels
    # that count.
    const = [(Y[:, c] * W[:, c]).sum().item() / max(W[:, c].sum().item(), 1.0)
             for c in range(3)]

    model = build_model(torch)
    opt = torch.optim.Adam(model.parameters(), lr=a.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, a.steps)

    def masked_l1(pred, y, w):
        return ((pred - y).abs() * w).sum((0, 2, 3)) / w.sum((0, 2, 3)).clamp(min=1.0)

    t_train = time.time()
    for step in range(a.steps):
        idx = torch.tensor(rng.integers(0, len(X), a.batch))
        x, y, w = X[idx], Y[idx], W[idx]
        if rng.random() < 0.5:
            # A mirror image: flip columns and the normals' x.
            x, y, w = x.flip(3).clone(), y.flip(3), w.flip(3)
            x[:, 5] = -x[:, 5]
        loss = masked_l1(model(x), y, w).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 250 == 0 or step == a.steps - 1:
            print(f"step {step:5d}  loss {loss.item():.4f}  "
                  f"{time.time() - t_train:.0f} s", flush=True)
    train_s = time.time() - t_train

    model.eval()
    with torch.no_grad():
        ph = torch.cat([model(Xh[i:i + 64]) for i in range(0, len(Xh), 64)])
        err = masked_l1(ph, Yh, Wh).tolist()
        cst = masked_l1(torch.tensor(const)[None, :, None, None] * Xh[:, 3:4], Yh, Wh).tolist()
    names = ["length", "d1", "d2"]
    for n, e, c in zip(names, err, cst):
        print(f"held-out MAE (units of s) {n}: network {e:.4f}, constant {c:.4f}")

    # Export, then check onnxruntime against torch on a held-out crop.
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    dummy = Xh[:1]
    torch.onnx.export(model, (dummy,), a.out, input_names=["input"], output_names=["lengths"],
                      dynamic_axes={"input": {0: "batch"}, "lengths": {0: "batch"}},
                      opset_version=17, dynamo=False)
    import onnxruntime as ort
    sess = ort.InferenceSession(a.out, providers=["CPUExecutionProvider"])
    fx = Xh[:1].numpy()
    with torch.no_grad():
        ft = model(Xh[:1]).numpy()
    fo = sess.run(None, {"input": fx})[0]
    diff = float(np.abs(ft - fo).max())
    print(f"onnxruntime vs torch on a held-out crop: max |diff| {diff:.2e}")
    assert diff < 1e-4, diff
    base = os.path.splitext(a.out)[0]
    np.save(base + ".fixture_input.npy", fx)
    np.save(base + ".fixture_output.npy", ft)
    summary = {
        "train_samples": len(train),
        "heldout_samples": len(held),
        "steps": a.steps,
        "batch": a.batch,
        "lr": a.lr,
        "seed": a.seed,
        "threads": a.threads,
        "train_seconds": round(train_s, 1),
        "heldout_mae": dict(zip(names, [round(e, 4) for e in err])),
        "constant_mae": dict(zip(names, [round(c, 4) for c in cst])),
        "constant": dict(zip(names, [round(c, 4) for c in const])),
        "onnx_vs_torch_max_abs": diff,
        "parameters": sum(p.numel() for p in model.parameters()),
        "torch": torch.__version__,
        "onnxruntime": ort.__version__,
    }
    json.dump(summary, open(base + ".train.json", "w"), indent=2)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    sys.exit(main())
