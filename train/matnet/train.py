#!/usr/bin/env python3
"""Train matflow's own prediction network on its synthetic `rooms` dataset
and export it to ONNX under MatNet's contract (crates/onnx/src/matnet.rs).

The network is a small U-Net. It takes what MatNet takes (the photo,
centre-cropped, /255, raised to 2.2; no mean or std) at 256 x 256 and gives
MatNet's five outputs, named as the official network's dict:

  depth      [N, 1, 256, 256]  camera-space z in scene units (metadata
                               matflow.depth = "z"; MatNet's own depth is
                               disparity-like, and a model without that key
                               is read as disparity)
  albedo     [N, 3, 256, 256]  linear, sigmoid
  roughness  [N, 1, 256, 256]  sigmoid
  metallic   [N, 1, 256, 256]  sigmoid
  normal     [N, 3, 256, 256]  camera space, +z towards the camera; tanh,
                               then L2-normalised per pixel

Data: `matflow dataset train/matnet/rooms.yaml --out out/matnet/train` and
`matflow dataset train/matnet/rooms-heldout.yaml --out out/matnet/heldout`
(WebDataset tar shards; this script reads them with tarfile, the EXR
members with the `OpenEXR` package and the PNGs with Pillow). The decoded
arrays are cached next to the shards (`decoded.npz`).

Usage:
  python3 train/matnet/train.py --train out/matnet/train \
      --heldout out/matnet/heldout --out models/matnet_rooms.onnx

Besides the model it writes <out>.json (steps, time, held-out errors) and a
fixture for matflow's Rust test: a small photo the test pre-processes itself
(tests/data/matnet_photo.png, a held-out render cut to 256 x 192) and the
network's outputs for it as PyTorch computes them, every 4th pixel
(<stem>.fixture_output.npy).
"""

import argparse
import io
import json
import math
import os
import tarfile
import time

import numpy as np
import OpenEXR
import torch
import torch.nn as nn
import torch.nn.functional as F
from PIL import Image

SIZE = 256
NAMES = ["depth", "albedo", "roughness", "metallic", "normal"]
CHANNELS = [1, 3, 1, 1, 3]


def exr(data):
    ch = OpenEXR.File(io.BytesIO(data)).channels()
    if "RGB" in ch:
        return np.asarray(ch["RGB"].pixels, np.float32)
    if "Y" in ch:
        return np.asarray(ch["Y"].pixels, np.float32)
    raise ValueError(f"unexpected EXR channels {list(ch)}")


def load(folder):
    """Every sample of the rooms dataset in `folder`, decoded (cached)."""
    cache = os.path.join(folder, "decoded.npz")
    desc = json.load(open(os.path.join(folder, "dataset.json")))
    if os.path.exists(cache):
        z = np.load(cache)
        if int(z["samples"]) == desc["samples"]:
            return {k: z[k] for k in z.files if k != "samples"}
    out = {k: [] for k in ["photo", "depth", "albedo", "roughness", "metallic", "normal", "valid"]}
    for k in range(desc["shards"]):
        path = os.path.join(folder, f"{desc['name']}-{k:06d}.tar")
        cur = {}

        def flush():
            if not cur:
                return
            out["photo"].append(cur["gt_image.png"])
            out["depth"].append(cur["depth.exr"].astype(np.float32))
            out["albedo"].append(cur["albedo.exr"].astype(np.float16))
            out["roughness"].append(cur["roughness.exr"][..., 0].astype(np.float16))
            out["metallic"].append(cur["metallic.exr"][..., 0].astype(np.float16))
            out["normal"].append(cur["normal.exr"].astype(np.float16))
            out["valid"].append(cur["mesh_mask.png"] <= 127)

        with tarfile.open(path) as t:
            for m in t.getmembers():
                key, member = m.name.split(".", 1)
                if cur and cur["key"] != key:
                    flush()
                    cur = {}
                cur["key"] = key
                data = t.extractfile(m).read()
                if member.endswith(".exr") and member != "gt_image.exr":
                    cur[member] = exr(data)
                elif member.endswith(".png"):
                    a = np.asarray(Image.open(io.BytesIO(data)))
                    cur[member] = a[..., :3] if a.ndim == 3 else a
        flush()
        print(f"  decoded {path}", flush=True)
    arrays = {k: np.stack(v) for k, v in out.items()}
    np.savez(cache, samples=desc["samples"], **arrays)
    return arrays


def linearise(photo_u8):
    """MatNet's input values: /255, then ^2.2."""
    return (photo_u8.astype(np.float32) / 255.0) ** 2.2


def block(cin, cout):
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    def __init__(self, c=16):
        super().__init__()
        w = [c, 2 * c, 4 * c, 8 * c, 8 * c]
        self.enc = nn.ModuleList([block(3, w[0])] + [block(w[i], w[i + 1]) for i in range(4)])
        self.dec = nn.ModuleList([block(w[i + 1] + w[i], w[i]) for i in reversed(range(4))])
        self.head = nn.Conv2d(w[0], sum(CHANNELS), 1)

    def forward(self, x):
        skips = []
        for i, e in enumerate(self.enc):
            x = e(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        for d in self.dec:
            s = skips.pop()
            x = d(torch.cat([F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False), s], 1))
        o = self.head(x)
        depth = torch.exp(torch.clamp(o[:, 0:1], -4.0, 4.0))
        albedo = torch.sigmoid(o[:, 1:4])
        rough = torch.sigmoid(o[:, 4:5])
        metal = torch.sigmoid(o[:, 5:6])
        n = torch.tanh(o[:, 6:9])
        n = n / torch.sqrt((n * n).sum(1, keepdim=True) + 1e-8)
        return depth, albedo, rough, metal, n


def batch_tensors(d, idx, crop, rng, augment, exposure=(0.6, 1.6)):
    """Inputs and targets for samples `idx` (random crops and flips when
    training)."""
    n = len(idx)
    h = w = SIZE
    xs, ys = [], []
    for i in idx:
        y0 = rng.integers(0, h - crop + 1) if crop < h else 0
        x0 = rng.integers(0, w - crop + 1) if crop < w else 0
        sl = (slice(y0, y0 + crop), slice(x0, x0 + crop))
        photo = linearise(d["photo"][i][sl])
        t = {
            "depth": d["depth"][i][sl][..., None].astype(np.float32),
            "albedo": d["albedo"][i][sl].astype(np.float32),
            "roughness": d["roughness"][i][sl][..., None].astype(np.float32),
            "metallic": d["metallic"][i][sl][..., None].astype(np.float32),
            "normal": d["normal"][i][sl].astype(np.float32),
            "valid": d["valid"][i][sl][..., None].astype(np.float32),
        }
        if augment:
            photo = photo * float(rng.uniform(*exposure))
            if rng.random() < 0.5:
                photo = photo[:, ::-1]
                t = {k: v[:, ::-1].copy() for k, v in t.items()}
                t["normal"][..., 0] *= -1.0
        xs.append(np.ascontiguousarray(photo.transpose(2, 0, 1)))
        ys.append({k: np.ascontiguousarray(v.transpose(2, 0, 1)) for k, v in t.items()})
    x = torch.from_numpy(np.stack(xs))
    y = {k: torch.from_numpy(np.stack([s[k] for s in ys])) for k in ys[0]}
    return x, y


def losses(pred, y):
    depth, albedo, rough, metal, normal = pred
    v = y["valid"]
    nv = v.sum().clamp(min=1.0)
    mean = lambda e: (e * v).sum() / nv / e.shape[1]  # noqa: E731
    l_depth = mean((torch.log(depth) - torch.log(y["depth"].clamp(min=1e-3))).abs())
    l_albedo = mean((albedo - y["albedo"]).abs())
    l_rough = mean((rough - y["roughness"]).abs())
    l_metal = mean((metal - y["metallic"]).abs())
    l_normal = ((1.0 - (normal * y["normal"]).sum(1, keepdim=True)) * v).sum() / nv
    return {"depth": l_depth, "albedo": l_albedo, "roughness": l_rough, "metallic": l_metal, "normal": l_normal}


@torch.no_grad()
def evaluate(model, d, bs=8):
    """Held-out errors over the valid pixels, as the model card states them."""
    model.eval()
    acc = {k: 0.0 for k in ["albedo", "roughness", "metallic", "normal_deg", "depth_absrel", "depth_absrel_aligned"]}
    count = 0.0
    rng = np.random.default_rng(0)
    n = len(d["photo"])
    for s in range(0, n, bs):
        idx = list(range(s, min(n, s + bs)))
        x, y = batch_tensors(d, idx, SIZE, rng, False)
        depth, albedo, rough, metal, normal = model(x)
        v = y["valid"].bool()[:, 0]
        for j in range(len(idx)):
            m = v[j]
            k = float(m.sum())
            if k == 0:
                continue
            acc["albedo"] += float((albedo[j] - y["albedo"][j]).abs().mean(0)[m].sum())
            acc["roughness"] += float((rough[j, 0] - y["roughness"][j, 0]).abs()[m].sum())
            acc["metallic"] += float((metal[j, 0] - y["metallic"][j, 0]).abs()[m].sum())
            cos = (normal[j] * y["normal"][j]).sum(0).clamp(-1.0, 1.0)
            acc["normal_deg"] += float(torch.rad2deg(torch.acos(cos))[m].sum())
            zp, zt = depth[j, 0][m], y["depth"][j, 0][m]
            acc["depth_absrel"] += float(((zp - zt).abs() / zt).sum())
            scale = torch.median(zt) / torch.median(zp)
            acc["depth_absrel_aligned"] += float(((zp * scale - zt).abs() / zt).sum())
            count += k
    model.train()
    return {k: v / max(count, 1.0) for k, v in acc.items()}


def torch_preprocess(photo_u8, size):
    """The contract's pre-processing with PyTorch's interpolate."""
    x = torch.from_numpy(photo_u8.astype(np.float32)).permute(2, 0, 1)[None]
    h, w = x.shape[2:]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    x = x[:, :, y0 : y0 + s, x0 : x0 + s]
    x = F.interpolate(x, size=(512, 512), mode="bilinear", align_corners=True)
    x = (x / 255.0).clamp(min=0.0) ** 2.2
    return F.interpolate(x, size=(size, size), mode="bicubic", align_corners=False)


def export(model, path, info, heldout):
    model.eval()
    dummy = torch.zeros(1, 3, SIZE, SIZE)
    torch.onnx.export(
        model,
        dummy,
        path,
        opset_version=17,
        input_names=["image"],
        output_names=NAMES,
        dynamic_axes={"image": {0: "N"}, **{k: {0: "N"} for k in NAMES}},
        dynamo=False,
    )
    import onnx

    m = onnx.load(path)
    meta = {
        "matflow.contract": "matnet",
        "matflow.depth": "z",
        "matflow.trained_on": info["data"],
    }
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(m, path)

    # The fixture: a held-out render cut to 256 x 192 (the Rust test crops
    # and resizes it as the contract says), and PyTorch's outputs for it.
    photo = heldout["photo"][0][32:224, :, :]
    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    Image.fromarray(photo).save(os.path.join(repo, "tests/data/matnet_photo.png"))
    x = torch_preprocess(photo, SIZE)
    with torch.no_grad():
        outs = model(x)
    full = torch.cat(outs, 1)[0].numpy()
    stem = path[: -len(".onnx")] if path.endswith(".onnx") else path
    np.save(stem + ".fixture_output.npy", np.ascontiguousarray(full[:, ::4, ::4]).astype(np.float32))

    import onnxruntime as ort

    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    got = np.concatenate(sess.run(None, {"image": x.numpy()}), 1)[0]
    worst = float(np.abs(got - full).max())
    print(f"onnxruntime vs PyTorch: max |difference| {worst:.3e}")
    return worst


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", required=True)
    ap.add_argument("--heldout", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--full-steps", type=int, default=300, help="final steps on whole 256 x 256 images")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exposure", type=float, nargs=2, default=[0.6, 1.6], help="range of the photo's random exposure scale")
    args = ap.parse_args()

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    t0 = time.time()
    train = load(args.train)
    heldout = load(args.heldout)
    print(f"data: {len(train['photo'])} train, {len(heldout['photo'])} held out ({time.time() - t0:.0f} s)", flush=True)

    model = UNet(args.width)
    params = sum(p.numel() for p in model.parameters())
    print(f"U-Net width {args.width}: {params} parameters", flush=True)
    total = args.steps + args.full_steps
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=args.lr, total_steps=total, pct_start=0.05)
    n = len(train["photo"])
    t_train = time.time()
    run = None
    for step in range(total):
        crop = args.crop if step < args.steps else SIZE
        bs = args.batch if step < args.steps else max(1, args.batch * args.crop * args.crop // (SIZE * SIZE))
        idx = rng.integers(0, n, size=bs)
        x, y = batch_tensors(train, idx, crop, rng, True, tuple(args.exposure))
        parts = losses(model(x), y)
        loss = parts["depth"] + parts["albedo"] + parts["roughness"] + parts["metallic"] + parts["normal"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        cur = {k: float(v.detach()) for k, v in parts.items()}
        run = cur if run is None else {k: 0.98 * run[k] + 0.02 * cur[k] for k in cur}
        if step % 100 == 0 or step == total - 1:
            el = time.time() - t_train
            print(
                f"step {step:5d} {el:6.0f} s  " + " ".join(f"{k} {v:.4f}" for k, v in run.items()),
                flush=True,
            )
    train_s = time.time() - t_train
    errs = evaluate(model, heldout)
    print("held out:", json.dumps(errs), flush=True)
    info = {
        "data": "matflow dataset train/matnet/rooms.yaml (rooms, 2000 samples, seed 1, 256 x 256, 32 spp)",
        "heldout": "train/matnet/rooms-heldout.yaml (100 samples, seed 2)",
        "parameters": params,
        "width": args.width,
        "steps": args.steps,
        "full_steps": args.full_steps,
        "batch": args.batch,
        "crop": args.crop,
        "lr": args.lr,
        "seed": args.seed,
        "exposure": args.exposure,
        "threads": args.threads,
        "train_seconds": round(train_s, 1),
        "heldout_errors": errs,
        "torch": torch.__version__,
    }
    worst = export(model, args.out, info, heldout)
    info["onnxruntime_vs_torch_max_abs"] = worst
    stem = args.out[: -len(".onnx")] if args.out.endswith(".onnx") else args.out
    with open(stem + ".train.json", "w") as f:
        json.dump(info, f, indent=2)
    print(f"wrote {args.out} ({os.path.getsize(args.out)} bytes)")


if __name__ == "__main__":
    main()
