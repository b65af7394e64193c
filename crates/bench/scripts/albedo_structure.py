#!/usr/bin/env python3
"""Does the recovered albedo hold structure the scene's albedo lacks?

Runs `pipelines/photo.yaml` (the README's photo example, at its own
budgets) on scenes of the `rooms` generator, whose true albedo is known,
once per shading-normal setting of its mesh stage, and compares the
recovered albedo (material_opt's `output`) with the truth, per kind:

- fine energy: the albedo less its Gaussian blur (sigma 1 px), squared;
- coarse energy: that blur less a sigma 8 px blur, squared (the band of
  the swirls a wavy depth map leaves in the albedo);

each over the scene's pixels, relative to the albedo's mean square (so a
gain does not count), and as a ratio to the true albedo's (1: as much
structure as the scene has); and the albedo's gain-fitted PSNR against
the truth. The predicted albedo is scored the same way for reference.

  matflow dataset crates/bench/scripts/albedo-rooms.yaml --out out/albedo-rooms
  python3 crates/bench/scripts/albedo_structure.py [--normals mesh predicted]

Needs numpy, pillow and OpenEXR."""
import argparse
import glob
import json
import os
import subprocess
import sys

import numpy as np
import OpenEXR
from PIL import Image

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def exr(path):
    ch = OpenEXR.File(path).channels()
    a = next(iter(ch.values())).pixels.astype(np.float64)
    return a if a.ndim == 3 else a[..., None]


def blur(a, m, sigma):
    """Gaussian blur of `a` [H, W, C] over the pixels `m` [H, W]
    (normalised convolution: pixels outside `m` do not bleed in)."""
    r = int(3 * sigma + 0.5)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()

    def sep(x):
        x = np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 0, x)
        return np.apply_along_axis(lambda v: np.convolve(v, k, mode="same"), 1, x)

    w = sep(m.astype(np.float64))
    out = np.stack([sep(a[..., c] * m) for c in range(a.shape[2])], -1)
    return out / np.maximum(w, 1e-9)[..., None]


def bands(a, m):
    """(fine, coarse) energy of `a` over `m`, relative to its mean square."""
    g1, g8 = blur(a, m, 1.0), blur(a, m, 8.0)
    ms = max(float((a[m] ** 2).mean()), 1e-12)
    return float(((a - g1)[m] ** 2).mean()) / ms, float(((g1 - g8)[m] ** 2).mean()) / ms


def psnr_gain(a, t, m):
    g = float((a[m] * t[m]).sum() / max(float((a[m] ** 2).sum()), 1e-12))
    e = float(((np.clip(a * g, 0, 1) - t)[m] ** 2).mean())
    return 10 * np.log10(1.0 / max(e, 1e-12))


def half(a):
    """512² -> 256² by 2 x 2 means (the pipeline works at 512²)."""
    h, w, c = a.shape
    return a.reshape(h // 2, 2, w // 2, 2, c).mean((1, 3))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="out/albedo-rooms")
    ap.add_argument("--work", default="out/albedo-structure")
    ap.add_argument("--matflow", default="target/release/matflow")
    ap.add_argument("--normals", nargs="+", default=["mesh"])
    ap.add_argument("--structure", nargs="+", default=["photo", "free"], help="material_opt's albedo_structure")
    a = ap.parse_args()
    os.chdir(REPO)
    keys = []
    for f in sorted(glob.glob(os.path.join(a.data, "*-[0-9][0-9][0-9][0-9][0-9][0-9].jsonl"))):
        for line in open(f):
            v = json.loads(line)
            keys.append((v["key"], v.get("params", {}).get("kind", "?")))
    if not keys:
        sys.exit(f"{a.data}: no samples (make them with the command in this script's header)")
    rows = []
    for key, kind in keys:
        scene = os.path.join(a.work, key)
        if not os.path.exists(os.path.join(scene, "gt_image.png")):
            subprocess.run([a.matflow, "dataset", "unpack", a.data, key, "--to", scene], check=True, capture_output=True)
        truth = exr(os.path.join(scene, "ground_truth", "albedo.exr"))
        m = np.asarray(Image.open(os.path.join(scene, "mesh_mask.png")).convert("L")) <= 127
        row = {"key": key, "kind": kind, "truth": bands(truth, m)}
        for normals, structure in [(n, s) for n in a.normals for s in a.structure]:
            col = f"{normals}-{structure}"
            out = os.path.join(a.work, f"{key}-{col}")
            sets = {
                "predict.photo": os.path.abspath(os.path.join(scene, "gt_image.png")),
                "predict.output": os.path.abspath(os.path.join(out, "bundle")),
                "mesh.normals": normals,
                "recovered.albedo_structure": structure,
                "recovered.output": os.path.abspath(os.path.join(out, "recovered")),
                # The views are not measured here: as few samples as run.
                "base.spp": "2",
                "base.path_spp": "1",
                "rerender.spp": "2",
                "relit.spp": "2",
                "rerender.output": os.path.abspath(os.path.join(out, "rerender.exr")),
                "edited.output": os.path.abspath(os.path.join(out, "edited.exr")),
                "relit.output": os.path.abspath(os.path.join(out, "relit.exr")),
            }
            cmd = [a.matflow, "run", "pipelines/photo.yaml", "--quiet", "--cache", os.path.join(a.work, "cache")]
            for k, v in sets.items():
                cmd += ["--set", f"{k}={v}"]
            p = subprocess.run(cmd, capture_output=True, text=True)
            if p.returncode != 0:
                sys.exit(f"{key} ({normals}): {p.stderr.strip()}")
            rec = half(exr(os.path.join(out, "recovered", "albedo.exr")))
            row[col] = bands(rec, m) + (psnr_gain(rec, truth, m),)
            if "pred" not in row:
                pred = half(exr(os.path.join(out, "bundle", "albedoPred.exr")))
                row["pred"] = bands(pred, m) + (psnr_gain(pred, truth, m),)
        rows.append(row)
        print(json.dumps(row), flush=True)

    def med(v):
        return float(np.median(v))

    cols = ["pred"] + [f"{n}-{s}" for n in a.normals for s in a.structure]
    print("\nrecovered albedo against the true albedo (medians per kind; energy as a ratio to the truth's)")
    print("| kind | scenes | " + " | ".join(f"{c}: fine / coarse / PSNR" for c in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    kinds = sorted({r["kind"] for r in rows})
    for kind in kinds + ["all"]:
        rs = [r for r in rows if kind in ("all", r["kind"])]
        cells = []
        for c in cols:
            fine = med([r[c][0] / max(r["truth"][0], 1e-12) for r in rs])
            coarse = med([r[c][1] / max(r["truth"][1], 1e-12) for r in rs])
            ps = med([r[c][2] for r in rs])
            cells.append(f"{fine:.2f} / {coarse:.2f} / {ps:.2f} dB")
        print(f"| {kind} | {len(rs)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
