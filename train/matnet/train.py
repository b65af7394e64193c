#!/usr/bin/env python3
"""Train matflow's own prediction network on its synthetic `rooms` dataset
(closed and open rooms, stages, outdoor scenes) and export it to ONNX under
MatNet's contract (crates/onnx/src/matnet.rs).

The network is a U-Net of six levels with the image's mean features added
at the bottom (the layout of a scene is a strong cue to its depth and
normals). The pixel's position as an input (`--position`) is off by
default: with it, the network learnt the average layout from where a pixel
is and ignored what the photo shows (the objects vanished). With
`--depth-range` the mean features also set each image's gain and offset
of log z (`UNet`; tests: test_train.py, which needs PyTorch). It takes what
MatNet takes (the photo, centre-cropped, /255, raised to 2.2; no mean or
std) at 256 x 256 and gives MatNet's five outputs, named as the official
network's dict:

  depth      [N, 1, 256, 256]  camera-space z in scene units, e^-4 to e^6
                               (metadata
                               matflow.depth = "z"; MatNet's own depth is
                               disparity-like, and a model without that key
                               is read as disparity)
  albedo     [N, 3, 256, 256]  linear, sigmoid (with --albedo photo: tanh
                               of the photo times a predicted gain; blend:
                               the two mixed per pixel)
  roughness  [N, 1, 256, 256]  sigmoid
  metallic   [N, 1, 256, 256]  sigmoid
  normal     [N, 3, 256, 256]  camera space, +z towards the camera; tanh,
                               then L2-normalised per pixel

Training (losses fit to what a photo cannot tell; augmentation for real
cameras):

  depth      L1 of log z less its mean over the image (scale-invariant;
             --depth-loss berhu: L2 beyond a fifth of the largest
             residual), the same residual's gradients at 3 scales
             (edges), and a small weight on the mean itself (the scale)
  albedo     L1 after the best single gain (gain-invariant), and a small
             weight on plain L1 (the level)
  normals    the angle between prediction and truth
  silhouettes  (--silhouette-weight, off by default) the predicted ln z
             step's size against the true one's where the true depth
             steps (objects against what is behind them), averaged over
             those edges alone, so small objects count
  affine z   (--affine-weight, off by default) 1 - the correlation of the
             predicted and the true z per image: the log loss lets a far
             floor or ground shrink towards the camera (an uncertain far
             depth regresses to the mean in log z), which z itself, the
             mesh's, does not forgive
  depth order  (--order-weight, off by default) pixel pairs 2, 6 and 16
             apart across a true silhouette must have the true order in
             depth, by a margin (a hinge): an object's inside, not just
             its outline, stands in front of what is behind it
  false steps  (--false-step-weight, off by default) a hinge on the
             predicted ln z step beyond the true one's + 0.05 where the
             true depth is smooth (nothing over 0.03 within 2 px), summed
             over the silhouettes' count as that term is averaged: what a
             step the truth lacks costs (the relight sparkles along it)
  depth's own normals  the angle between the normals of the surface the
             predicted depth makes (what the mesh stage shades with) and
             the true depth's, on smooth surfaces; without it a depth
             map can fit z well and still give a mesh of noisy facets
  roughness, metallic  L1
  photos     exposure (x0.5-2), white balance (+-15 % a channel), zoom
             crops (75-100 %), mirror, blur, sensor noise, JPEG
  schedule   most steps at 128 x 128: whole images halved, or (a share,
             --crop-share, 0 by default) full-resolution windows; the rest
             at 256 x 256 (the contract's size)

Data: `matflow dataset train/matnet/kinds.yaml --out out/matnet/train` and
`matflow dataset train/matnet/kinds-heldout.yaml --out out/matnet/heldout`
(WebDataset tar shards; this script reads them with tarfile, the EXR
members with the `OpenEXR` package and the PNGs with Pillow). The decoded
arrays are cached next to the shards (`decoded.npz`).

Usage:
  python3 train/matnet/train.py --train out/matnet/train \
      --heldout out/matnet/heldout --out models/matnet_rooms.onnx \
      --minutes 50

It trains on the GPU when PyTorch sees one (`--device auto`), else on the
CPU (`--threads`); the export, its check and the fixture run on the CPU.

Besides the model it writes <stem>.train.json (steps, time, held-out
errors), <stem>.pt (the PyTorch weights, for --init: fine-tuning; not for
the repository), with --ema the same three for the weights' moving
average (<stem>-ema.onnx; the training run itself is unchanged), and a
fixture for matflow's Rust test: a small photo the test pre-processes itself
(tests/data/matnet_photo.png, a held-out render cut to 256 x 192) and the
network's outputs for it as PyTorch computes them, every 4th pixel
(<stem>.fixture_output.npy).
"""

import argparse
import copy
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
from PIL import Image, ImageFilter

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
    """Every sample of the rooms dataset in `folder`, decoded (cached), with
    each sample's kind of scene. A dataset still being made gives its
    finished shards (those whose index is written)."""
    cache = os.path.join(folder, "decoded.npz")
    desc = json.load(open(os.path.join(folder, "dataset.json")))
    kinds, shards = {}, []
    for k in range(desc["shards"]):
        index = os.path.join(folder, f"{desc['name']}-{k:06d}.jsonl")
        if not os.path.exists(index):
            break
        with open(index) as f:
            for line in f:
                v = json.loads(line)
                kinds[v["key"]] = v.get("params", {}).get("kind", "open")
        shards.append(k)
    if os.path.exists(cache):
        z = np.load(cache)
        if int(z["samples"]) == len(kinds):
            return {k: z[k] for k in z.files if k != "samples"}
    keys = ["photo", "depth", "albedo", "roughness", "metallic", "normal", "valid", "kind"]
    out = {k: [] for k in keys}
    for k in shards:
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
            out["kind"].append(kinds.get(cur["key"], "open"))

        with tarfile.open(path) as t:
            for m in t.getmembers():
                key, member = m.name.split(".", 1)
                if cur and cur["key"] != key:
                    flush()
                    cur = {}
                cur["key"] = key
                if member in ("gt_image.exr", "envmap.hdr", "meta.json"):
                    continue
                data = t.extractfile(m).read()
                if member.endswith(".exr"):
                    cur[member] = exr(data)
                elif member.endswith(".png"):
                    a = np.asarray(Image.open(io.BytesIO(data)))
                    cur[member] = a[..., :3] if a.ndim == 3 else a
        flush()
        print(f"  decoded {path}", flush=True)
    arrays = {k: np.stack(v) for k, v in out.items()}
    np.savez(cache, samples=len(kinds), **arrays)
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
    """Six levels (c, 2c, 4c, 8c, 8c, 8c channels), max-pool down, bilinear
    up; with `position`, the pixel's position (x, y in [-1, 1]) through its
    own 3 x 3 convolution, added to the first convolution's output (the
    same as two more input channels, but a constant once the size is
    fixed, so the export holds no shape arithmetic for tract to run); at
    the bottom, the image's mean features through a 1x1 convolution added
    to every position. With `depth_range`, the same mean features also give
    each image a gain and an offset of the log depth (a linear layer, zero
    at the start: gain 1, offset 0): log z = b + exp(a) * o, so that a
    scene whose depth spans two orders of magnitude (ground out to the
    horizon) is not held to the range of log z that the last features
    span in a room. The albedo (`albedo`):
      free   sigmoid of the network's own three channels;
      photo  the photo corrected for its shading, tanh(photo * exp(g)) with
             g (a gain per pixel and channel) from the network: an albedo
             of the photo's own detail, where a free albedo comes out
             blurred, and the photo as albedo (a constant g) is where
             training starts from;
      blend  m * free + (1 - m) * photo (free from three more channels, m
             the sigmoid of one more):
             the photo's detail where its light carries it, the network's
             own albedo where it does not (deep shadow, clipped light)."""

    LEVELS = 6

    ALBEDO = ("free", "photo", "blend")

    def __init__(self, c=16, position=False, albedo="free", depth_range=False):
        super().__init__()
        if albedo not in self.ALBEDO:
            raise ValueError(f"albedo: {albedo!r} is not one of {self.ALBEDO}")
        self.albedo = albedo
        w = [c, 2 * c, 4 * c, 8 * c, 8 * c, 8 * c][: self.LEVELS]
        self.enc = nn.ModuleList([block(3, w[0])] + [block(w[i], w[i + 1]) for i in range(len(w) - 1)])
        self.position = nn.Conv2d(2, w[0], 3, padding=1, bias=False) if position else None
        self.context = nn.Conv2d(w[-1], w[-1], 1)
        self.depth_range = nn.Linear(w[-1], 2) if depth_range else None
        if self.depth_range is not None:
            nn.init.zeros_(self.depth_range.weight)
            nn.init.zeros_(self.depth_range.bias)
        self.dec = nn.ModuleList([block(w[i + 1] + w[i], w[i]) for i in reversed(range(len(w) - 1))])
        self.head = nn.Conv2d(w[0], sum(CHANNELS) + (4 if albedo == "blend" else 0), 1)
        self.fixed = None  # (h, w) to export at: the position term is then a constant

    def position_term(self, h, w):
        dev = self.position.weight.device
        ys = torch.linspace(-1.0, 1.0, h, device=dev).view(1, 1, h, 1).expand(1, 1, h, w)
        xs = torch.linspace(-1.0, 1.0, w, device=dev).view(1, 1, 1, w).expand(1, 1, h, w)
        return self.position(torch.cat([xs, ys], 1))

    def forward(self, x):
        photo = x
        if self.position is None:
            pos = 0.0
        elif self.fixed is not None:
            with torch.no_grad():
                pos = self.position_term(*self.fixed).detach()
        else:
            pos = self.position_term(x.shape[2], x.shape[3])
        skips = []
        for i, e in enumerate(self.enc):
            if i == 0:
                x = e[1:](e[0](x) + pos)
            else:
                x = e(F.max_pool2d(x, 2))
            skips.append(x)
        x = skips.pop()
        pooled = x.mean((2, 3), keepdim=True)
        span = self.depth_range(pooled.flatten(1))[:, :, None, None] if self.depth_range is not None else None
        x = x + self.context(pooled)
        for d in self.dec:
            s = skips.pop()
            x = d(torch.cat([F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False), s], 1))
        o = self.head(x)
        lz = o[:, 0:1]
        if span is not None:
            # The gain's clamp: a third to 4.5 times the features' range.
            lz = span[:, 1:2] + torch.exp(torch.clamp(span[:, 0:1], -1.1, 1.5)) * lz
        depth = torch.exp(torch.clamp(lz, -4.0, 6.0))
        if self.albedo == "free":
            albedo = torch.sigmoid(o[:, 1:4])
        else:
            # 0.7: exp(0.7) = 2, a photo's mid-grey to a wall's albedo.
            albedo = torch.tanh(photo * torch.exp(torch.clamp(o[:, 1:4] + 0.7, -6.0, 6.0)))
            if self.albedo == "blend":
                m = torch.sigmoid(o[:, 12:13])
                albedo = m * torch.sigmoid(o[:, 9:12]) + (1.0 - m) * albedo
        rough = torch.sigmoid(o[:, 4:5])
        metal = torch.sigmoid(o[:, 5:6])
        n = torch.tanh(o[:, 6:9])
        n = n / torch.sqrt((n * n).sum(1, keepdim=True) + 1e-8)
        return depth, albedo, rough, metal, n


def camera(photo_u8, rng, a):
    """A photo as another camera might have taken it: exposure and white
    balance (on linear values, clipped as a sensor clips), blur, noise
    and JPEG. 8-bit sRGB in and out."""
    lin = linearise(photo_u8)
    gain = 2.0 ** rng.uniform(-a.exposure, a.exposure)
    wb = rng.uniform(1.0 - a.white_balance, 1.0 + a.white_balance, size=3).astype(np.float32)
    wb /= wb.mean()
    lin = np.clip(lin * gain * wb, 0.0, 1.0)
    out = lin ** (1.0 / 2.2)
    img = Image.fromarray((out * 255.0 + 0.5).astype(np.uint8))
    if rng.random() < 0.25:
        img = img.filter(ImageFilter.GaussianBlur(float(rng.uniform(0.3, 1.2))))
    out = np.asarray(img).astype(np.float32) / 255.0
    if rng.random() < 0.6:
        sigma = rng.uniform(0.0, 0.03)
        shot = rng.uniform(0.0, 0.03)
        noise = rng.standard_normal(out.shape).astype(np.float32)
        out = out + noise * (sigma + shot * np.sqrt(out))
    u8 = (np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if rng.random() < 0.4:
        buf = io.BytesIO()
        Image.fromarray(u8).save(buf, format="JPEG", quality=int(rng.integers(35, 96)))
        u8 = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))
    return u8


def batch_tensors(d, idx, size, rng, a):
    """Inputs and targets for samples `idx` at `size` x `size` (whole
    images; halved by averaging 2 x 2 photo pixels and taking one target
    pixel of each 2 x 2). With `a` (training), the photo goes through
    `camera`, and now and then a zoom crop and a mirror; and a share
    (`a.crop_share`) of the halved images is a full-resolution window
    instead."""
    xs, ys, zooms = [], [], []
    for i in idx:
        photo = d["photo"][i]
        zoom = 1.0
        t = {
            "depth": d["depth"][i][..., None].astype(np.float32),
            "albedo": d["albedo"][i].astype(np.float32),
            "roughness": d["roughness"][i][..., None].astype(np.float32),
            "metallic": d["metallic"][i][..., None].astype(np.float32),
            "normal": d["normal"][i].astype(np.float32),
            "valid": d["valid"][i][..., None].astype(np.float32),
        }
        if a is not None:
            if rng.random() < a.zoom_share:
                s = int(SIZE * rng.uniform(0.75, 1.0))
                zoom = SIZE / s
                y0, x0 = rng.integers(0, SIZE - s + 1), rng.integers(0, SIZE - s + 1)
                src = y0 + (np.arange(SIZE) * s) // SIZE, x0 + (np.arange(SIZE) * s) // SIZE
                crop = Image.fromarray(photo[y0 : y0 + s, x0 : x0 + s])
                photo = np.asarray(crop.resize((SIZE, SIZE), Image.BICUBIC))
                t = {k: v[src[0]][:, src[1]] for k, v in t.items()}
            photo = camera(photo, rng, a)
            if rng.random() < 0.5:
                photo = photo[:, ::-1]
                t = {k: v[:, ::-1].copy() for k, v in t.items()}
                t["normal"][..., 0] *= -1.0
        x = linearise(photo)
        if size != SIZE and a is not None and rng.random() < a.crop_share:
            # A window at full resolution: the photo's detail, and no
            # whole layout to lean on. The focal length in the window's
            # widths grows by SIZE / size (the principal point moves off
            # centre; prediction and truth share the same rays).
            y0, x0 = rng.integers(0, SIZE - size + 1), rng.integers(0, SIZE - size + 1)
            x = x[y0 : y0 + size, x0 : x0 + size]
            t = {k: v[y0 : y0 + size, x0 : x0 + size] for k, v in t.items()}
            zoom *= SIZE / size
        elif size != SIZE:
            f = SIZE // size
            x = x.reshape(size, f, size, f, 3).mean((1, 3))
            t = {k: v[::f, ::f] for k, v in t.items()}
        xs.append(np.ascontiguousarray(x.transpose(2, 0, 1)))
        zooms.append(zoom)
        ys.append({k: np.ascontiguousarray(v.transpose(2, 0, 1)) for k, v in t.items()})
    x = torch.from_numpy(np.stack(xs))
    y = {k: torch.from_numpy(np.stack([s[k] for s in ys])) for k in ys[0]}
    y["zoom"] = torch.tensor(zooms, dtype=torch.float32)
    return x, y


def masked_mean(e, v):
    """Mean of `e` [N, C, H, W] over the pixels where `v` [N, 1, H, W] is
    set, per image: [N, C]."""
    return (e * v).sum((2, 3)) / v.sum((2, 3)).clamp(min=1.0)


FOV_X_DEG = 35.0  # matflow's camera (crates/scene/src/camera.rs), the generator's too


def depth_normals(z, zoom):
    """Camera-space normals (+z towards the camera) of the surface that
    depth `z` [N, 1, H, W] makes under matflow's camera (35 deg across,
    centred; the focal length scaled by each image's `zoom` [N]): the
    cross product of the back-projected point's forward differences, so
    [N, 3, H-1, W-1]. This is the normal the mesh stage shades with, and
    it does not change with the depth's scale."""
    n, _, h, w = z.shape
    f = (w * 0.5 / math.tan(math.radians(FOV_X_DEG * 0.5))) * zoom.view(n, 1, 1)
    u = (torch.arange(w, dtype=z.dtype, device=z.device) - (w - 1) * 0.5).view(1, 1, w) / f
    v = -(torch.arange(h, dtype=z.dtype, device=z.device) - (h - 1) * 0.5).view(1, h, 1) / f
    zz = z[:, 0]
    p = torch.stack([u * zz, v * zz, -zz], 1)
    di = p[:, :, :-1, 1:] - p[:, :, :-1, :-1]
    dj = p[:, :, 1:, :-1] - p[:, :, :-1, :-1]
    c = torch.cross(dj, di, dim=1)
    return c / torch.sqrt((c * c).sum(1, keepdim=True) + 1e-12)


def true_facets(y, zoom):
    """The true depth's facets (`depth_normals`) and where they count: all
    three pixels have geometry and the facet is within ~25 deg of the true
    normal map's (a smooth surface, not across an edge); [N, 3, H-1, W-1]
    and [N, 1, H-1, W-1] (0/1)."""
    nt = depth_normals(y["depth"].clamp(min=1e-3), zoom)
    v = y["valid"]
    m = v[:, :, :-1, :-1] * v[:, :, 1:, :-1] * v[:, :, :-1, 1:]
    m = m * ((nt * y["normal"][:, :, :-1, :-1]).sum(1, keepdim=True) > 0.9).float()
    return nt, m


def neighbour_steps(z, valid, span=1):
    """ln z's steps to the pixel `span` to the right and `span` below,
    each with where both pixels are valid: [(step, both)] for x, then y
    (none along an axis shorter than the span)."""
    lz = torch.log(z.clamp(min=1e-3))
    out = []
    for dim in (3, 2):
        n = lz.shape[dim] - span
        if n > 0:
            out.append((lz.narrow(dim, span, n) - lz.narrow(dim, 0, n), valid.narrow(dim, span, n) * valid.narrow(dim, 0, n)))
    return out


def silhouette_loss(depth, y):
    """L1 of the predicted ln z step's size against the true one's across
    the true depth's silhouettes (neighbours whose ln z differs by > 0.1,
    both with geometry), averaged over the silhouettes alone: an object
    counts however few its edge pixels are against the layout's. The
    sign is left to the depth loss: on a signed step, L1 is least at 0
    while the network doubts which side is nearer, and a run with it
    learnt no steps at all."""
    total = 0.0
    pred, true = neighbour_steps(depth, y["valid"]), neighbour_steps(y["depth"], y["valid"])
    for (dp, _), (dt, both) in zip(pred, true):
        on = both * (dt.abs() > 0.1).float()
        total = total + ((dp.abs() - dt.abs()).abs() * on).sum() / on.sum().clamp(min=1.0)
    return total


FALSE_STEP = 0.05  # ln z: a step the truth lacks costs beyond this


def false_step_loss(depth, y):
    """The predicted ln z steps where the true depth is smooth (no step by
    more than 0.03 within 2 pixels, both with geometry): a hinge on the
    predicted step's size beyond the true one's plus FALSE_STEP, summed
    and divided by the number of true silhouette pixels (steps > 0.1), as
    `silhouette_loss` averages. So a false step costs what missing a true
    step by as much costs, however few the silhouettes: with the
    silhouette term alone, a long run learnt steps wherever an edge might
    be (a cube's face split along an arc, the wall's foot), and the
    relight sparkled along them."""
    total = 0.0
    pred, true = neighbour_steps(depth, y["valid"]), neighbour_steps(y["depth"], y["valid"])
    near = F.max_pool2d(depth_steps(y["depth"], y["valid"], 0.03, true), 5, stride=1, padding=2)
    silhouettes = 0.0
    for axis, ((dp, _), (dt, both)) in enumerate(zip(pred, true)):
        # near[..., x] covers the step between x and x+1 along the axis.
        n = near[..., :, :-1] if axis == 0 else near[..., :-1, :]
        smooth = both * (1.0 - n)
        total = total + (F.relu(dp.abs() - dt.abs() - FALSE_STEP) * smooth).sum()
        silhouettes = silhouettes + (both * (dt.abs() > 0.1).float()).sum()
    return total / torch.as_tensor(silhouettes).clamp(min=1.0)


ORDER_SPANS = (2, 6, 16)


def order_loss(depth, y):
    """Depth order across the true silhouettes, at a distance: for pixel
    pairs 2, 6 and 16 apart (across and down) whose true ln z differs by
    more than 0.1, a hinge on the predicted difference, which must have
    the true sign and at least the true size (up to 0.3). A step one
    pixel wide that comes back at the next pixel (an outline) fails the
    wider pairs, so the object's inside must stand in front of what is
    behind it; while the network doubts the side, any answer inside the
    margin costs the same (the loss does not pull the step to 0). Averaged
    over the pairs of each span."""
    total = 0.0
    for s in ORDER_SPANS:
        pred, true = neighbour_steps(depth, y["valid"], s), neighbour_steps(y["depth"], y["valid"], s)
        for (dp, _), (dt, both) in zip(pred, true):
            on = both * (dt.abs() > 0.1).float()
            margin = dt.abs().clamp(max=0.3)
            total = total + (F.relu(margin - torch.sign(dt) * dp) * on).sum() / on.sum().clamp(min=1.0)
    return total / len(ORDER_SPANS)


def affine_loss(depth, y):
    """1 - the Pearson correlation of the predicted and the true z over an
    image's geometry (the R² of the best affine map from one to the other
    is its square). In z itself, as the mesh stage builds the scene: a far
    floor squeezed towards the camera costs what it costs the mesh, where
    the log loss weighs it as it weighs the near wall."""
    v = y["valid"]
    p, t = depth, y["depth"].clamp(min=1e-3)
    dp = (p - masked_mean(p, v)[:, :, None, None]) * v
    dt = (t - masked_mean(t, v)[:, :, None, None]) * v
    cov = (dp * dt).sum((1, 2, 3))
    den = torch.sqrt((dp * dp).sum((1, 2, 3)) * (dt * dt).sum((1, 2, 3)) + 1e-12)
    corr = cov / den
    has = (v.sum((1, 2, 3)) > 1).float()
    return ((1.0 - corr) * has).sum() / has.sum().clamp(min=1.0)


def berhu(r, v):
    """The reverse Huber penalty of residuals `r` [N, 1, H, W] over `v`:
    |r| up to c, (r² + c²) / 2c beyond, c a fifth of the image's largest
    |r| (Laina et al. 2016). Small residuals keep L1's sharpness; large
    ones (a far floor drawn near) pull in proportion to their size."""
    a = r.abs()
    c = (0.2 * (a * v).amax((1, 2, 3), keepdim=True)).detach().clamp(min=1e-3)
    return torch.where(a <= c, a, (a * a + c * c) / (2.0 * c))


def losses(pred, y, w_level, w_dn=1.0, w_sil=0.0, w_affine=0.0, w_order=0.0, depth_loss="l1", w_false=0.0):
    depth, albedo, rough, metal, normal = pred
    v = y["valid"]
    has = (v.sum((1, 2, 3)) > 0).float()
    per_image = lambda e: (e * has).sum() / has.sum().clamp(min=1.0)  # noqa: E731
    # Depth: log residual less its mean, its gradients, and the mean.
    r = torch.log(depth) - torch.log(y["depth"].clamp(min=1e-3))
    shift = masked_mean(r, v)[:, :, None, None]
    ri = r - shift
    pen = berhu(ri, v) if depth_loss == "berhu" else ri.abs()
    l_depth = per_image(masked_mean(pen, v)[:, 0]) + w_level * per_image(shift[:, 0, 0, 0].abs())
    l_grad = 0.0
    rr, vv = ri, v
    for _ in range(3):
        gx = (rr[..., :, 1:] - rr[..., :, :-1]).abs() * vv[..., :, 1:] * vv[..., :, :-1]
        gy = (rr[..., 1:, :] - rr[..., :-1, :]).abs() * vv[..., 1:, :] * vv[..., :-1, :]
        nv = vv.sum().clamp(min=1.0)
        l_grad = l_grad + (gx.sum() + gy.sum()) / nv
        rr, vv = F.avg_pool2d(rr * vv, 2) / F.avg_pool2d(vv, 2).clamp(min=1e-6), (F.avg_pool2d(vv, 2) > 0.99).float()
    # Albedo: after the best single gain per image, and plainly.
    t = y["albedo"].clamp(0.0, 1.0)
    pt = masked_mean(albedo * t, v).sum(1)
    pp = masked_mean(albedo * albedo, v).sum(1).clamp(min=1e-6)
    g = (pt / pp).detach().clamp(0.25, 4.0)[:, None, None, None]
    l_albedo = per_image(masked_mean((albedo * g - t).abs(), v).mean(1))
    l_albedo = l_albedo + w_level * per_image(masked_mean((albedo - t).abs(), v).mean(1))
    l_rough = per_image(masked_mean((rough - y["roughness"]).abs(), v)[:, 0])
    l_metal = per_image(masked_mean((metal - y["metallic"]).abs(), v)[:, 0])
    cos = (normal * y["normal"]).sum(1, keepdim=True).clamp(-0.9999, 0.9999)
    l_normal = per_image(masked_mean(torch.acos(cos), v)[:, 0])
    # The depth's own surface normals against the true depth's on smooth
    # surfaces. The mesh is shaded with these.
    zoom = y.get("zoom", torch.ones(depth.shape[0], device=depth.device))
    nt, vv = true_facets(y, zoom)
    cos_d = (depth_normals(depth, zoom) * nt).sum(1, keepdim=True).clamp(-0.9999, 0.9999)
    l_dn = w_dn * per_image(masked_mean(torch.acos(cos_d), vv)[:, 0])
    l_sil = w_sil * silhouette_loss(depth, y) if w_sil > 0 else torch.zeros((), device=depth.device)
    l_affine = w_affine * affine_loss(depth, y) if w_affine > 0 else torch.zeros((), device=depth.device)
    l_order = w_order * order_loss(depth, y) if w_order > 0 else torch.zeros((), device=depth.device)
    l_false = w_false * false_step_loss(depth, y) if w_false > 0 else torch.zeros((), device=depth.device)
    return {
        "depth": l_depth,
        "depth_grad": l_grad,
        "albedo": l_albedo,
        "roughness": l_rough,
        "metallic": l_metal,
        "normal": l_normal,
        "depth_normal": l_dn,
        "silhouette": l_sil,
        "affine_z": l_affine,
        "order": l_order,
        "false_steps": l_false,
    }


def depth_steps(z, valid, step, steps=None):
    """Where log depth `z` [N, 1, H, W] steps by more than `step` to a
    right or lower neighbour (both valid), [N, 1, H, W] (0/1): the
    silhouettes of objects against what is behind them. `steps`: z's
    `neighbour_steps`, where the caller has them already."""
    (dx, vx), (dy, vy) = steps if steps is not None else neighbour_steps(z, valid)
    e = torch.zeros_like(z)
    e[..., :, :-1] = (dx.abs() > step).float() * vx
    e[..., :-1, :] = torch.maximum(e[..., :-1, :], (dy.abs() > step).float() * vy)
    return e


def silhouette_recall(pred, true, valid):
    """Share of the true depth's steps (log z by > 0.1: silhouettes) where
    the predicted depth also steps (by > 0.03, within 2 pixels). A map of
    the average layout, with no objects, scores near 0."""
    t = depth_steps(true, valid, 0.1)
    p = F.max_pool2d(depth_steps(pred, valid, 0.03), 5, stride=1, padding=2)
    return (t * p).sum((1, 2, 3)) / t.sum((1, 2, 3)).clamp(min=1.0), t.sum((1, 2, 3))


@torch.no_grad()
def evaluate(model, d, bs=8, device="cpu"):
    """Held-out scores per kind of scene (medians over scenes): albedo PSNR
    after the best gain, normal angle, R^2 of an affine fit of z, and the
    angle of the predicted depth's own surface normals (what the mesh
    shades with) to the true depth's, on smooth surfaces, and the share of
    the true silhouettes the predicted depth has (`silhouette_recall`)."""
    model.eval()
    scores = {}
    n = len(d["photo"])
    for s in range(0, n, bs):
        idx = list(range(s, min(n, s + bs)))
        x, y = batch_tensors(d, idx, SIZE, None, None)
        depth, albedo, rough, metal, normal = (o.cpu() for o in model(x.to(device)))
        zoom = torch.ones(len(idx))
        facets, smooth = true_facets(y, zoom)
        cos_f = (depth_normals(depth, zoom) * facets).sum(1).clamp(-1.0, 1.0)
        recall, edges = silhouette_recall(depth, y["depth"], y["valid"])
        for j, i in enumerate(idx):
            m = y["valid"][j, 0].bool()
            if int(m.sum()) < 16:
                continue
            t = y["albedo"][j].clamp(0, 1)[:, m]
            p = albedo[j][:, m]
            g = float((p * t).sum() / (p * p).sum().clamp(min=1e-9))
            psnr = -10.0 * math.log10(max(float(((p * g - t) ** 2).mean()), 1e-12))
            cos = (normal[j] * y["normal"][j]).sum(0).clamp(-1.0, 1.0)[m]
            angle = float(torch.rad2deg(torch.acos(cos)).mean())
            zp, zt = depth[j, 0][m].double(), y["depth"][j, 0][m].double()
            a = torch.stack([zp, torch.ones_like(zp)], 1)
            sol = torch.linalg.lstsq(a, zt[:, None]).solution
            res = ((a @ sol)[:, 0] - zt).pow(2).sum()
            r2 = float(1.0 - res / (zt - zt.mean()).pow(2).sum().clamp(min=1e-12))
            sm = smooth[j, 0].bool()
            cd = cos_f[j][sm]
            mesh = float(torch.rad2deg(torch.acos(cd)).mean()) if int(sm.sum()) > 0 else float("nan")
            sil = float(recall[j]) if float(edges[j]) >= 16 else float("nan")
            scores.setdefault(str(d["kind"][i]), []).append((psnr, angle, r2, mesh, sil))
    model.train()
    out = {}
    for k, v in sorted(scores.items()):
        a = np.array(v)
        out[k] = {
            "scenes": len(v),
            "albedo_psnr": round(float(np.median(a[:, 0])), 2),
            "normal_deg": round(float(np.median(a[:, 1])), 1),
            "depth_r2": round(float(np.median(a[:, 2])), 3),
            "depth_normal_deg": round(float(np.nanmedian(a[:, 3])), 1),
            "silhouette_recall": round(float(np.nanmedian(a[:, 4])), 3),
        }
    return out


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
    model.fixed = (SIZE, SIZE)
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
    ap.add_argument("--train", required=True, action="append",
                    help="a rooms dataset's folder (again for more: their samples are pooled)")
    ap.add_argument("--heldout", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--minutes", type=float, default=50.0, help="training time; the steps follow from it")
    ap.add_argument("--steps", type=int, default=0, help="a fixed number of steps instead of --minutes")
    ap.add_argument("--full-share", type=float, default=0.2, help="share of the time at 256 x 256 (the rest at 128)")
    ap.add_argument("--batch", type=int, default=8, help="images a step at 128 x 128 (a quarter of that at 256)")
    ap.add_argument("--width", type=int, default=16)
    ap.add_argument(
        "--depth-range",
        action="store_true",
        help="a gain and offset of log z per image from the image's mean features (the range a scene's depth spans)",
    )
    ap.add_argument("--position", action="store_true", help="the pixel's position as an input (learns the layout, loses objects)")
    ap.add_argument(
        "--albedo",
        choices=UNet.ALBEDO,
        default="free",
        help="free: the network's own; photo: the photo times a predicted gain per pixel (keeps the "
        "photo's detail); blend: the two mixed per pixel by the network",
    )
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--threads", type=int, default=2, help="CPU threads")
    ap.add_argument("--device", default="auto", help="cpu, cuda, or auto (cuda when PyTorch sees one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--exposure", type=float, default=1.0, help="photo exposure: +- this many stops")
    ap.add_argument("--white-balance", type=float, default=0.15, help="photo white balance: +- this share a channel")
    ap.add_argument("--zoom-share", type=float, default=0.3, help="share of photos zoom-cropped (75-100 %%)")
    ap.add_argument("--level-weight", type=float, default=0.2, help="weight of the depth scale and albedo level")
    ap.add_argument("--depth-normal-weight", type=float, default=1.0, help="weight of the depth's own normals")
    ap.add_argument("--silhouette-weight", type=float, default=0.0, help="weight of the depth's step sizes at true silhouettes")
    ap.add_argument(
        "--affine-weight", type=float, default=0.0, help="weight of 1 - the correlation of predicted and true z (not log z)"
    )
    ap.add_argument(
        "--false-step-weight", type=float, default=0.0, help="weight of the depth's steps where the true depth is smooth"
    )
    ap.add_argument(
        "--order-weight", type=float, default=0.0, help="weight of the depth order across true silhouettes, 2-16 px apart"
    )
    ap.add_argument(
        "--depth-loss",
        choices=("l1", "berhu"),
        default="l1",
        help="penalty of the log-depth residual: l1, or berhu (L2 on the large residuals; tried, worse: the notes)",
    )
    ap.add_argument("--init", default="", help="start from this state dict (a .pt the script wrote) instead of at random")
    ap.add_argument(
        "--ema",
        type=float,
        default=0.0,
        help="also keep an exponential moving average of the weights with this decay (e.g. 0.999) and write it "
        "beside the model as <stem>-ema.onnx (training itself is unchanged)",
    )
    ap.add_argument("--crop-share", type=float, default=0.0, help="share of the 128 x 128 images that are full-resolution windows")
    ap.add_argument("--data", default="matflow dataset train/matnet/kinds.yaml", help="what the data is, for the record")
    args = ap.parse_args()

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    # The outputs' folder now, not after the run: a run must not end in a
    # failed save.
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    t0 = time.time()
    parts = [load(folder) for folder in args.train]
    train = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    del parts
    heldout = load(args.heldout)
    kinds, counts = np.unique(train["kind"], return_counts=True)
    print(f"data: {len(train['photo'])} train ({dict(zip(kinds.tolist(), counts.tolist()))}), "
          f"{len(heldout['photo'])} held out ({time.time() - t0:.0f} s)", flush=True)

    device = ("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device
    model = UNet(args.width, args.position, args.albedo, args.depth_range).to(device, memory_format=torch.channels_last)
    if args.init:
        # A state dict without the depth range's layer starts it at zero
        # (the plain model's output); any other difference is an error.
        missing, unexpected = model.load_state_dict(torch.load(args.init, map_location=device), strict=False)
        if unexpected or any(not k.startswith("depth_range.") for k in missing):
            raise SystemExit(f"train.py: --init {args.init}: does not fit this network (missing {missing}, unexpected {unexpected})")
        print(f"started from {args.init}" + (f" (new: {', '.join(missing)})" if missing else ""), flush=True)
    params = sum(p.numel() for p in model.parameters())
    print(f"U-Net width {args.width}: {params} parameters", flush=True)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    if not 0.0 <= args.ema < 1.0:
        raise SystemExit(f"train.py: --ema {args.ema}: a decay in [0, 1)")
    # The average of the weights (and the batch norms' running statistics)
    # along the run, against the last steps' noise (a batch of 2 at
    # 256 x 256). The state dicts' tensors are the live ones, paired once.
    ema = copy.deepcopy(model) if args.ema > 0 else None
    ema_pairs = list(zip(ema.state_dict().values(), model.state_dict().values())) if ema is not None else []
    budget = args.minutes * 60.0
    n = len(train["photo"])
    t_train = time.time()
    run = None
    step = 0
    # The learning rate follows a one-cycle shape over the time budget
    # (or the steps): warm up over 5 %, then cosine down to 1 %.
    while True:
        el = time.time() - t_train
        frac = step / args.steps if args.steps else el / budget
        if frac >= 1.0:
            break
        lr = args.lr * (frac / 0.05 if frac < 0.05 else 0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * (frac - 0.05) / 0.95)))
        for gr in opt.param_groups:
            gr["lr"] = lr
        full = frac >= 1.0 - args.full_share
        size = SIZE if full else SIZE // 2
        bs = max(1, args.batch // 4) if full else args.batch
        idx = rng.integers(0, n, size=bs)
        x, y = batch_tensors(train, idx, size, rng, args)
        x = x.to(device).contiguous(memory_format=torch.channels_last)
        y = {k: v.to(device) for k, v in y.items()}
        parts = losses(model(x), y, args.level_weight, args.depth_normal_weight, args.silhouette_weight, args.affine_weight,
                       args.order_weight, args.depth_loss, args.false_step_weight)
        loss = sum(parts.values())
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        if ema is not None:
            # Early on the average follows the weights closely (the decay
            # ramps up), so it does not keep the random start.
            d = min(args.ema, (1.0 + step) / (10.0 + step))
            with torch.no_grad():
                for e, w in ema_pairs:
                    if e.dtype.is_floating_point:
                        e.mul_(d).add_(w, alpha=1.0 - d)
                    else:
                        e.copy_(w)
        cur = {k: float(v.detach()) for k, v in parts.items()}
        run = cur if run is None else {k: 0.98 * run[k] + 0.02 * cur[k] for k in cur}
        if step % 100 == 0:
            print(
                f"step {step:5d} {el:6.0f} s {size}px lr {lr:.2e} " + " ".join(f"{k} {v:.4f}" for k, v in run.items()),
                flush=True,
            )
        step += 1
    train_s = time.time() - t_train
    errs = evaluate(model, heldout, device=device)
    print("held out:", json.dumps(errs), flush=True)
    info = {
        "data": f"{args.data} ({n} samples: {dict(zip(kinds.tolist(), counts.tolist()))})",
        "heldout": f"{len(heldout['photo'])} samples",
        "parameters": params,
        "width": args.width,
        "position": args.position,
        "depth_range": args.depth_range,
        "albedo": args.albedo,
        "steps": step,
        "minutes": args.minutes,
        "full_share": args.full_share,
        "batch": args.batch,
        "lr": args.lr,
        "seed": args.seed,
        "exposure_stops": args.exposure,
        "white_balance": args.white_balance,
        "zoom_share": args.zoom_share,
        "level_weight": args.level_weight,
        "depth_normal_weight": args.depth_normal_weight,
        "silhouette_weight": args.silhouette_weight,
        "affine_weight": args.affine_weight,
        "order_weight": args.order_weight,
        "false_step_weight": args.false_step_weight,
        "depth_loss": args.depth_loss,
        "init": args.init or None,
        "crop_share": args.crop_share,
        "ema": args.ema or None,
        "threads": args.threads,
        "device": device,
        "train_seconds": round(train_s, 1),
        "heldout_medians_per_kind": errs,
        "torch": torch.__version__,
    }
    stem = args.out[: -len(".onnx")] if args.out.endswith(".onnx") else args.out
    write_model(model, args.out, info, heldout)
    if ema is not None:
        errs = evaluate(ema, heldout, device=device)
        print("held out, averaged weights:", json.dumps(errs), flush=True)
        weights = f"exponential moving average, decay {args.ema}"
        write_model(ema, stem + "-ema.onnx", dict(info, heldout_medians_per_kind=errs, weights=weights), heldout)


def write_model(model, path, info, heldout):
    """The ONNX export at path (and its fixture), <stem>.pt and <stem>.train.json."""
    stem = path[: -len(".onnx")] if path.endswith(".onnx") else path
    model = model.to("cpu", memory_format=torch.contiguous_format)
    # The weights as PyTorch holds them (the export folds the batch norms
    # into the convolutions), for --init: not a file to commit.
    torch.save(model.state_dict(), stem + ".pt")
    info = dict(info, onnxruntime_vs_torch_max_abs=export(model, path, info, heldout))
    with open(stem + ".train.json", "w") as f:
        json.dump(info, f, indent=2)
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")


if __name__ == "__main__":
    main()
