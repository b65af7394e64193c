#!/usr/bin/env python3
"""The official-checkpoint path of export_matnet.py, end to end, with
PyTorch (not in `cargo test`: it needs PyTorch and writes ~1.3 GB;
test_checkpoint.py covers the name logic there).

Builds the two files a MatNet user has, from a seeded random network of the
official layout: the released kind (a flat state dict, .pth) and the
official Lightning trainer's (.ckpt: `state_dict` with `matnet.` keys plus
the LPIPS network's 20, and the trainer's other entries). Then:

1. the .pth passes `--check` as it is;
2. the .ckpt without flags fails, naming the fix;
3. the .ckpt with `--rename matnet.= --drop criterion_lpips.` exports, and
   the ONNX file (through onnxruntime) gives the source network's outputs;
4. with `--matflow BIN`: `matflow predict --model` on a photo gives the
   official inference's maps (its preprocessing with OpenCV's resize, the
   source network in PyTorch, its bilinear resize back to 512).

  pip install torch onnx onnxruntime opencv-python-headless OpenEXR pillow
  python3 train/matnet/test_export_matnet.py [--keep DIR] \
      [--matflow target/release/matflow [--photo pipelines/photos/room.png]]"""
import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np
import torch

sys.dont_write_bytecode = True
HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import export_matnet  # noqa: E402
from test_checkpoint import LPIPS  # noqa: E402


def run(*args):
    p = subprocess.run([sys.executable, os.path.join(HERE, "export_matnet.py"), *args], capture_output=True, text=True)
    return p.returncode, p.stdout + p.stderr


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--keep", help="write the files here and keep them")
    ap.add_argument("--matflow", help="the matflow binary: also check `matflow predict --model`")
    ap.add_argument("--photo", default=os.path.join(HERE, "..", "..", "pipelines", "photos", "room.png"))
    a = ap.parse_args()
    d = a.keep or tempfile.mkdtemp(prefix="matnet-export-")
    os.makedirs(d, exist_ok=True)
    torch.manual_seed(0)
    model = export_matnet.MatNet()
    export_matnet.randomise(model, 7)
    model.eval()
    sd = model.state_dict()
    pth = os.path.join(d, "matnet_weights.pth")
    torch.save(sd, pth)
    g = torch.Generator().manual_seed(1)
    lp = {k: torch.randn(s, generator=g) for k, s in LPIPS.items()}
    ckpt = os.path.join(d, "matnet-latest.ckpt")
    torch.save(
        {
            "epoch": 3,
            "global_step": 12000,
            "pytorch-lightning_version": "1.9.0",
            "state_dict": {**{"matnet." + k: v for k, v in sd.items()}, **lp},
            "loops": {"fit_loop": {"state_dict": {}, "epoch_progress": {"total": {"completed": 3}}}},
            "callbacks": {"ModelCheckpoint": {"best_model_score": torch.tensor(0.12), "dirpath": d}},
            "optimizer_states": [{"state": {0: {"step": torch.tensor(12000.0)}}, "param_groups": [{"lr": 1e-4}]}],
            "lr_schedulers": [],
        },
        ckpt,
    )

    rc, out = run("--checkpoint", pth, "--check")
    assert rc == 0 and "303 entries match" in out, out
    print("1. the released kind loads as it is:", out.strip().splitlines()[-1])

    rc, out = run("--checkpoint", ckpt, "--check")
    assert rc == 1 and "try: --drop criterion_lpips. --rename matnet.=" in out, out
    print("2. the training checkpoint alone fails:\n   " + "\n   ".join(out.strip().splitlines()[:4]))

    onnx_path = os.path.join(d, "matnet.onnx")
    rc, out = run("--checkpoint", ckpt, "--rename", "matnet.=", "--drop", "criterion_lpips.", "--out", onnx_path)
    assert rc == 0, out
    print("3. exported:\n   " + "\n   ".join(out.strip().splitlines()))
    import onnxruntime as ort

    x = torch.rand(1, 3, 518, 518, generator=torch.Generator().manual_seed(5)) ** 2.2
    with torch.no_grad():
        want = [t.numpy() for t in model(x)]
    got = ort.InferenceSession(onnx_path, providers=["CPUExecutionProvider"]).run(None, {"image": x.numpy()})
    worst = max(float(np.abs(a - b).max()) for a, b in zip(got, want))
    scale = max(float(np.abs(b).max()) for b in want)
    assert worst <= 1e-3 * max(1.0, scale), worst
    print(f"   the export reproduces the source network: max |difference| {worst:.2e} (outputs up to {scale:.3g})")
    if a.matflow:
        through_matflow(a.matflow, a.photo, onnx_path, model, d)
    print(f"files in {d}" if a.keep else "ok")


def official_inference(model, photo):
    """`inverse_img_w_mi.py`'s MatNet steps: centre crop, /255, bilinear
    to 512 (align_corners), ^2.2, cv2 INTER_CUBIC to 518, the network,
    bilinear back to 512 (align_corners). Unclamped, as it writes them."""
    import cv2
    import torch.nn.functional as F
    from measure_resize import official_512

    t = official_512(photo)
    x = cv2.resize(np.ascontiguousarray(t[0].permute(1, 2, 0).numpy()), (518, 518), interpolation=cv2.INTER_CUBIC)
    with torch.no_grad():
        outs = model(torch.from_numpy(x).permute(2, 0, 1)[None])
    back = lambda o: F.interpolate(o, size=(512, 512), mode="bilinear", align_corners=True)[0].numpy()  # noqa: E731
    return dict(zip(export_matnet.NAMES, [back(o) for o in outs]))


def through_matflow(matflow, photo, onnx_path, model, d):
    import OpenEXR

    out = os.path.join(d, "bundle")
    p = subprocess.run(
        [matflow, "predict", photo, "--out", out, "--model", onnx_path, "--cache", os.path.join(d, "cache"), "--quiet"],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    want = official_inference(model, photo)

    def exr(name):
        ch = OpenEXR.File(os.path.join(out, name)).channels()
        a = next(iter(ch.values())).pixels.astype(np.float32)
        return a.transpose(2, 0, 1) if a.ndim == 3 else a[None]

    print("4. matflow predict --model against the official inference (max |difference|, the maps' range):")
    for name, key in [("albedoPred.exr", "albedo"), ("normalPred.exr", "normal"), ("depthPred.exr", "depth")]:
        got, ref = exr(name), want[key]
        if key == "normal":
            # matflow renormalises after the resize back to 512 (the
            # official code does not: its bilinear blend shortens them).
            ref = ref / np.maximum(np.sqrt((ref * ref).sum(0, keepdims=True)), 1e-6)
        worst = float(np.abs(got - ref).max())
        scale = float(np.abs(ref).max())
        print(f"   {key:7s} {worst:.2e} (up to {scale:.3g})")
        assert worst <= 2e-3 * max(1.0, scale), (key, worst)


if __name__ == "__main__":
    main()
