#!/usr/bin/env python3
"""Export a MatNet-architecture PyTorch checkpoint to ONNX for matflow's
`matnet` stage (and `matflow predict --model`).

The architecture is the official MatNet's (github.com/lez-s/Materialist,
`Material_net/dpt.py` `MaterialNet`, read and re-written here, not
copied): a DINOv2 ViT-B/14 encoder (patch 14, 768 channels, 12 blocks,
features taken after blocks 2, 5, 8 and 11 and layer-normed) and two DPT
heads on it (features 128, out_channels 96/192/384/768): a depth head (1
channel, ReLU) and a material head (8 channels: albedo 0-2, roughness 3,
metallic 4 with ReLU; normal 5-7 with tanh, then L2-normalised per pixel).
Its state dict has the official 303 names and shapes in the official
order (`checkpoint.official_layout()`, checked on every run).

Checkpoints: the released weights (a flat state dict) load as they are. A
training checkpoint of the official Lightning trainer needs
`--rename matnet.= --drop criterion_lpips.` (its network keys carry a
`matnet.` prefix, and it holds the LPIPS loss network's 20 keys too).
Drops apply first, to the names as stored; then renames (prefixes). The
load is strict: every missing, unexpected or mis-shaped key is listed,
with the flags likely to fix it. `--check` stops after that check.

The export is at the fixed 518 x 518 input (dynamic spatial axes break the
position-embedding interpolation), opset 17, TorchScript-based exporter,
with outputs named depth, albedo, roughness, metallic, normal (the official
network's dict keys), each [1, C, 518, 518]. The depth stays MatNet's
disparity-like output (no matflow.depth metadata). The script checks the
export against PyTorch with onnxruntime on a random input and prints the
file's BLAKE3.

  # the released weights, or a training checkpoint
  python3 train/matnet/export_matnet.py --checkpoint matnet_weights.pth --out matnet.onnx
  python3 train/matnet/export_matnet.py --checkpoint run-latest.ckpt \
      --rename matnet.= --drop criterion_lpips. --out matnet.onnx
  # a randomly initialised network of the same architecture (what
  # matflow's benchmarks and documented test use; never commit either)
  python3 train/matnet/export_matnet.py --random --seed 0 --out /tmp/matnet_random.onnx

The official weights are not redistributable: never commit a checkpoint
or an export of one.
"""

import argparse
import hashlib
import os
import sys
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import checkpoint  # noqa: E402

PATCH = 14
SIDE = 518  # 37 patches
DIM = 768
DEPTH_BLOCKS = 12
HEADS = 12
TAKE = [2, 5, 8, 11]
FEATURES = 128
OUT_CHANNELS = [96, 192, 384, 768]
NAMES = ["depth", "albedo", "roughness", "metallic", "normal"]


# ---- the encoder: DINOv2 ViT-B/14 -------------------------------------------


class PatchEmbed(nn.Module):
    def __init__(self):
        super().__init__()
        self.proj = nn.Conv2d(3, DIM, PATCH, stride=PATCH)

    def forward(self, x):
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    def __init__(self):
        super().__init__()
        self.qkv = nn.Linear(DIM, 3 * DIM)
        self.proj = nn.Linear(DIM, DIM)

    def forward(self, x):
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, HEADS, c // HEADS).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        a = (q * (c // HEADS) ** -0.5) @ k.transpose(-2, -1)
        y = (a.softmax(-1) @ v).transpose(1, 2).reshape(b, n, c)
        return self.proj(y)


class LayerScale(nn.Module):
    def __init__(self):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((DIM,), 1.0))  # the official init_values

    def forward(self, x):
        return x * self.gamma


class Mlp(nn.Module):
    def __init__(self):
        super().__init__()
        self.fc1 = nn.Linear(DIM, 4 * DIM)
        self.fc2 = nn.Linear(4 * DIM, DIM)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    def __init__(self):
        super().__init__()
        self.norm1 = nn.LayerNorm(DIM, eps=1e-6)
        self.attn = Attention()
        self.ls1 = LayerScale()
        self.norm2 = nn.LayerNorm(DIM, eps=1e-6)
        self.mlp = Mlp()
        self.ls2 = LayerScale()

    def forward(self, x):
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class ViT(nn.Module):
    def __init__(self):
        super().__init__()
        n = (SIDE // PATCH) ** 2
        self.patch_embed = PatchEmbed()
        self.cls_token = nn.Parameter(torch.zeros(1, 1, DIM))
        self.pos_embed = nn.Parameter(torch.zeros(1, n + 1, DIM))
        self.mask_token = nn.Parameter(torch.zeros(1, DIM))  # in checkpoints; unused
        self.blocks = nn.ModuleList([Block() for _ in range(DEPTH_BLOCKS)])
        self.norm = nn.LayerNorm(DIM, eps=1e-6)

    def features(self, x):
        """Layer-normed patch tokens after blocks TAKE (the input is
        SIDE x SIDE, so the position embedding is used as stored)."""
        t = self.patch_embed(x)
        t = torch.cat([self.cls_token.expand(t.shape[0], -1, -1), t], 1) + self.pos_embed
        out = []
        for i, blk in enumerate(self.blocks):
            t = blk(t)
            if i in TAKE:
                out.append(self.norm(t)[:, 1:])
        return out


# ---- the decoders: DPT heads -------------------------------------------------


class ResidualConvUnit(nn.Module):
    def __init__(self, f):
        super().__init__()
        self.conv1 = nn.Conv2d(f, f, 3, padding=1)
        self.conv2 = nn.Conv2d(f, f, 3, padding=1)

    def forward(self, x):
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    def __init__(self, f):
        super().__init__()
        # Registered in the official order (out_conv first), so that code
        # walking the parameters in order sees the official sequence.
        self.out_conv = nn.Conv2d(f, f, 1)
        self.resConfUnit1 = ResidualConvUnit(f)
        self.resConfUnit2 = ResidualConvUnit(f)

    def forward(self, x, skip=None, size=None):
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class Scratch(nn.Module):
    def __init__(self, out_ch, final_relu):
        super().__init__()
        for i, c in enumerate(OUT_CHANNELS):
            setattr(self, f"layer{i + 1}_rn", nn.Conv2d(c, FEATURES, 3, padding=1, bias=False))
        for i in range(4):
            setattr(self, f"refinenet{i + 1}", FusionBlock(FEATURES))
        self.output_conv1 = nn.Conv2d(FEATURES, FEATURES // 2, 3, padding=1)
        layers = [
            nn.Conv2d(FEATURES // 2, 32, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, out_ch, 1),
        ]
        if final_relu:
            layers.append(nn.ReLU())
        self.output_conv2 = nn.Sequential(*layers)


class DPTHead(nn.Module):
    def __init__(self, out_ch, final_relu):
        super().__init__()
        self.projects = nn.ModuleList([nn.Conv2d(DIM, c, 1) for c in OUT_CHANNELS])
        c = OUT_CHANNELS
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(c[0], c[0], 4, stride=4),
                nn.ConvTranspose2d(c[1], c[1], 2, stride=2),
                nn.Identity(),
                nn.Conv2d(c[3], c[3], 3, stride=2, padding=1),
            ]
        )
        self.scratch = Scratch(out_ch, final_relu)

    def forward(self, feats, ph, pw):
        s = self.scratch
        maps = []
        for i, t in enumerate(feats):
            x = t.permute(0, 2, 1).reshape(t.shape[0], t.shape[2], ph, pw)
            maps.append(self.resize_layers[i](self.projects[i](x)))
        l1, l2, l3, l4 = s.layer1_rn(maps[0]), s.layer2_rn(maps[1]), s.layer3_rn(maps[2]), s.layer4_rn(maps[3])
        p4 = s.refinenet4(l4, size=l3.shape[2:])
        p3 = s.refinenet3(p4, l3, size=l2.shape[2:])
        p2 = s.refinenet2(p3, l2, size=l1.shape[2:])
        p1 = s.refinenet1(p2, l1)
        out = s.output_conv1(p1)
        out = F.interpolate(out, size=(ph * PATCH, pw * PATCH), mode="bilinear", align_corners=True)
        return s.output_conv2(out)


class MatNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.pretrained = ViT()
        self.depth_head = DPTHead(1, True)
        self.material_head = DPTHead(8, False)

    def forward(self, x):
        ph, pw = x.shape[2] // PATCH, x.shape[3] // PATCH
        feats = self.pretrained.features(x)
        depth = F.relu(self.depth_head(feats, ph, pw))
        m = self.material_head(feats, ph, pw)
        albedo = F.relu(m[:, 0:3])
        rough = F.relu(m[:, 3:4])
        metal = F.relu(m[:, 4:5])
        n = torch.tanh(m[:, 5:8])
        n = n / torch.sqrt((n * n).sum(1, keepdim=True)).clamp(min=1e-6)
        return depth, albedo, rough, metal, n


def randomise(model, seed):
    """A random network of the architecture whose outputs vary like a
    trained one's (the default init leaves ReLU heads mostly at zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("gamma"):
                p.fill_(0.1)
            elif p.dim() > 1:
                fan_in = p[0].numel()
                p.copy_(torch.randn(p.shape, generator=g) * (1.0 / fan_in) ** 0.5)
            elif "norm" in name and name.endswith("weight"):
                p.fill_(1.0)
            else:
                p.copy_(torch.randn(p.shape, generator=g) * 0.02)
        # A positive bias on the final convolutions keeps the ReLU outputs
        # (depth, albedo, roughness, metallic) mostly above zero.
        model.depth_head.scratch.output_conv2[2].bias.fill_(1.0)
        model.material_head.scratch.output_conv2[2].bias[:5].fill_(0.5)


def blake3_hex(path):
    try:
        import blake3
    except ImportError:
        return None
    h = blake3.blake3()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_checkpoint(path, renames, drops, trust):
    """The checkpoint's state dict, mapped onto the architecture's names
    (drops, then renames) and checked by name and shape; exits with every
    problem listed (and the flags likely to fix them) when it does not
    fit. A Lightning checkpoint's `state_dict` is unwrapped."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=not trust)
    except FileNotFoundError:
        sys.exit(f"{path}: no such file")
    except Exception as e:  # noqa: BLE001 (pickle errors have many types)
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        hint = "" if trust else " (if you trust the file, --trust-checkpoint loads it with full unpickling)"
        sys.exit(f"{path}: not a loadable PyTorch checkpoint: {msg}{hint}")
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        print(f"{path}: a training checkpoint; using its state_dict ({len(state['state_dict'])} entries)")
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        sys.exit(f"{path}: expected a state dict (names to tensors), found {type(state).__name__}")
    try:
        renames = [checkpoint.parse_rename(r) for r in renames]
    except ValueError as e:
        sys.exit(str(e))
    names, errors = checkpoint.map_names(list(state), renames, drops)
    shapes = {}
    for new, old in names.items():
        v = state[old]
        if not torch.is_tensor(v):
            errors.append(f"{old}: not a tensor ({type(v).__name__})")
            continue
        shapes[new] = tuple(v.shape)
    problems = errors + checkpoint.compare(checkpoint.official_layout(), shapes)
    if problems:
        hints = [p for p in problems if p.startswith("try: ")]
        problems = [p for p in problems if not p.startswith("try: ")]
        counts = {w: sum(p.startswith(w) for p in problems) for w in ("missing", "unexpected", "shape")}
        print(
            f"{path}: does not match the architecture ({len(state)} entries; it has 303): "
            f"{counts['missing']} missing, {counts['unexpected']} unexpected, {counts['shape']} of another shape",
            file=sys.stderr,
        )
        for h in hints:
            print(h, file=sys.stderr)
        for p in problems[:40]:
            print(f"  {p}", file=sys.stderr)
        if len(problems) > 40:
            print(f"  ... and {len(problems) - 40} more", file=sys.stderr)
        sys.exit(1)
    dropped = len(state) - len(names)
    print(f"{path}: 303 entries match by name and shape" + (f" ({dropped} dropped)" if dropped else ""))
    return {new: state[old].float() for new, old in names.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="a state dict (.pth) or a Lightning training checkpoint (.ckpt)")
    src.add_argument("--random", action="store_true", help="a randomly initialised network")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--rename", action="append", default=[], metavar="OLD=NEW", help="rename a key prefix (after the drops)"
    )
    ap.add_argument("--drop", action="append", default=[], metavar="PREFIX", help="drop the keys with this prefix")
    ap.add_argument(
        "--trust-checkpoint", action="store_true", help="unpickle the whole file (only for files you trust)"
    )
    ap.add_argument("--check", action="store_true", help="check the checkpoint's names and shapes; do not export")
    ap.add_argument("--out", help="the ONNX file to write")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    if not args.check and not args.out:
        ap.error("--out is required (or --check)")
    torch.set_num_threads(args.threads)

    model = MatNet()
    have = [(k, tuple(v.shape)) for k, v in model.state_dict().items()]
    assert have == checkpoint.official_layout(), "the module tree drifted from checkpoint.official_layout()"
    if args.random:
        randomise(model, args.seed)
    else:
        state = load_checkpoint(args.checkpoint, args.rename, args.drop, args.trust_checkpoint)
        model.load_state_dict(state, strict=True)
        if args.check:
            return
    model.eval()
    params = sum(p.numel() for p in model.parameters())
    print(f"parameters: {params / 1e6:.1f} M")

    x = torch.rand(1, 3, SIDE, SIDE, generator=torch.Generator().manual_seed(args.seed + 1))
    x = x ** 2.2  # a linearised photo's range
    t0 = time.time()
    torch.onnx.export(
        model,
        torch.zeros(1, 3, SIDE, SIDE),
        args.out,
        opset_version=17,
        input_names=["image"],
        output_names=NAMES,
        dynamo=False,
    )
    print(f"exported {args.out} ({os.path.getsize(args.out) / 1e6:.1f} MB) in {time.time() - t0:.0f} s")

    with torch.no_grad():
        want = [t.numpy() for t in model(x)]
    import onnxruntime as ort

    sess = ort.InferenceSession(args.out, providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": x.numpy()})
    worst = max(float(np.abs(a - b).max()) for a, b in zip(got, want))
    scale = max(float(np.abs(b).max()) for b in want)
    print(f"onnxruntime vs PyTorch on a random input: max |difference| {worst:.3e} (outputs up to {scale:.3g})")
    for name, a in zip(NAMES, want):
        print(f"  {name:9s} {list(a.shape)}  range {a.min():.3g} .. {a.max():.3g}")
    b3 = blake3_hex(args.out)
    sha = hashlib.sha256(open(args.out, "rb").read()).hexdigest()
    print(f"blake3 {b3}" if b3 else "blake3: (pip install blake3 to print it)")
    print(f"sha256 {sha}")
    if worst > 1e-3 * max(1.0, scale):
        print("the export does not match PyTorch", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
