#!/usr/bin/env python3
"""A validation set with a model's predictions in place of its own maps.

Benchmark only. The sets `relight_scenes.py` writes carry the true depth
and normals and degraded true materials as their "predictions", so
`matflow-bench invert --validation` measures everything downstream of
the prediction stage. This script copies such a set (or several, joined)
with each scene's predictions replaced by what a model predicts from the
scene's photo, so the same bench measures what a model's geometry costs
in renders:

    python3 crates/bench/scripts/predicted_set.py --sets out/kinds out/kinds-b \
        --out out/predicted-bundled [--model M.onnx | --keep]
    matflow-bench invert --validation out/predicted-bundled --geometry-only --relight-spp 16

For every scene: `matflow predict` on its `gt_image.exr` (the linear
capture; without --model, the bundled model), its depth, albedo,
normals, roughness and metallic area-averaged from the prediction's 512²
to the scene's size (normals renormalised), everything else linked
(`scene.json`, `ground_truth/`, the photo). With several sets, scene
names get the set's index as a prefix (a-scene-00, b-scene-00, ...).
`validation.json` lists the halves from each scene's `scene.json`
(`split`) and its kind. `--keep` joins the sets with their own maps
(the true depth: the baseline the predictions are measured against).

Needs numpy, pillow and OpenEXR, and a release build of matflow.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import OpenEXR
from PIL import Image

EXR_MAPS = ["albedoPred.exr", "depth.exr", "normalPred.exr"]
PNG_MAPS = ["roughnessPred.png", "metallicPred.png"]
# The set's own predictions, replaced (a prediction writes PNGs for
# roughness and metallic where the set may have EXRs).
REPLACED = set(EXR_MAPS + PNG_MAPS + ["roughnessPred.exr", "metallicPred.exr", "depthPred.exr"])


def area_mean(a, n):
    """Mean over k×k blocks, from k·n² to n² (k a whole number)."""
    k = a.shape[0] // n
    if k * n != a.shape[0] or a.shape[0] != a.shape[1]:
        sys.exit(f"a prediction of {a.shape[1]}x{a.shape[0]} does not reduce to {n}x{n}")
    return a.reshape(n, k, n, k, *a.shape[2:]).mean(axis=(1, 3))


def reduce_exr(path, n, normals):
    f = OpenEXR.File(path)
    ch = f.channels()
    name = next(iter(ch))
    a = ch[name].pixels.astype(np.float64)
    if a.shape[0] == n:
        return
    o = area_mean(a, n)
    if normals:
        o = o / np.maximum(np.linalg.norm(o, axis=2, keepdims=True), 1e-6)
    header = {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {name: np.ascontiguousarray(o.astype(np.float32))}).write(path)


def reduce_png(path, n):
    im = Image.open(path)
    a = np.asarray(im)
    if a.shape[0] == n:
        return
    top = np.iinfo(a.dtype).max
    o = np.clip(np.round(area_mean(a.astype(np.float64), n)), 0, top).astype(a.dtype)
    Image.fromarray(o).save(path)


def scene_size(scene):
    ch = OpenEXR.File(os.path.join(scene, "gt_image.exr")).channels()
    return next(iter(ch.values())).pixels.shape[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", nargs="+", required=True, help="validation sets (relight_scenes.py's folders)")
    ap.add_argument("--out", required=True, help="the new set's folder (replaced)")
    ap.add_argument("--model", help="an ONNX model under MatNet's contract (default: the bundled one)")
    ap.add_argument("--matflow", default="target/release/matflow", help="the matflow binary")
    ap.add_argument("--keep", action="store_true", help="keep the sets' own maps (join the sets only: the baseline)")
    args = ap.parse_args()
    if args.keep and args.model:
        sys.exit("--keep and --model exclude each other")

    if not args.keep and not os.path.exists(args.matflow):
        sys.exit(f"{args.matflow} not found: cargo build --release -p matflow-cli")
    if os.path.exists(args.out):
        shutil.rmtree(args.out)
    os.makedirs(args.out)
    model = "the sets' own maps" if args.keep else args.model or "bundled"
    index = {"generator": "crates/bench/scripts/predicted_set.py", "model": model,
             "sets": args.sets, "tuning": [], "heldback": [], "kinds": {}}
    for i, root in enumerate(args.sets):
        names = sorted(d for d in os.listdir(root) if os.path.isfile(os.path.join(root, d, "scene.json")))
        if not names:
            sys.exit(f"{root}: no scenes (folders with scene.json)")
        for name in names:
            src = os.path.realpath(os.path.join(root, name))
            new = f"{chr(ord('a') + i)}-{name}" if len(args.sets) > 1 else name
            dst = os.path.join(args.out, new)
            os.makedirs(dst)
            for f in os.listdir(src):
                if args.keep or f not in REPLACED:
                    os.symlink(os.path.join(src, f), os.path.join(dst, f))
            n = scene_size(src)
            with open(os.path.join(src, "scene.json")) as f:
                meta = json.load(f)
            kind = meta.get("kind", "closed")
            index["heldback" if meta.get("split") == "heldback" else "tuning"].append(new)
            index["kinds"][new] = kind
            print(f"{new}: {kind}, {n}²", flush=True)
            if args.keep:
                continue
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [args.matflow, "predict", os.path.join(src, "gt_image.exr"), "--out", tmp, "--quiet"]
                if args.model:
                    cmd += ["--model", args.model]
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
                for f in EXR_MAPS + PNG_MAPS + ["prediction.json"]:
                    shutil.copy(os.path.join(tmp, f), os.path.join(dst, f))
            for f in EXR_MAPS:
                reduce_exr(os.path.join(dst, f), n, f == "normalPred.exr")
            for f in PNG_MAPS:
                reduce_png(os.path.join(dst, f), n)
    with open(os.path.join(args.out, "validation.json"), "w") as f:
        json.dump(index, f, indent=1)
    print(f"wrote {args.out}: {len(index['kinds'])} scenes")


if __name__ == "__main__":
    main()
