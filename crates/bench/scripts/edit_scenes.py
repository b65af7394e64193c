#!/usr/bin/env python3
"""Material edits after inversion against the truths of edit_truths.py.

Benchmark only (Mitsuba 3's Python package reads the EXR files). For each
scene of a validation set with edit truths (``edit.json``) and an
inversion by ``matflow-bench invert --validation`` (its work folder's
``SCENE-BUDGET-default-COMPLETE``), it runs a pipeline over the recovered
scene: the completion the inversion used, a ``trace`` of the recovered
maps, the object's albedo set (``paint``) and the object made smooth
metal (``polish``), each rendered three ways: the plain render
(``full``), and the photo with the edit's change as a ratio or a
difference (``render`` with ``photo``, ``composite: ratio`` or
``differential``); ``auto`` is ratio for the albedo edit and
differential for the metal one. Next to them, two baselines: the photo
left unedited, and (albedo only) the 2D recolour photo × new albedo /
predicted albedo inside the mask.

PSNR (sRGB, gamma 2.2, as matflow reports) inside the object's mask and
over the whole image, per scene and per kind; medians and worsts.

    python3 crates/bench/scripts/edit_scenes.py --validation out/kinds \\
        --work out/bench-kinds-inv [--budget 60] [--complete auto]
        [--halves heldback] [--matflow target/release/matflow] [--spp 128]
"""

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import drjit_llvm  # noqa: E402

WAYS = ["full", "ratio", "differential"]


def gamma(x):
    return np.clip(x, 0.0, 1.0) ** (1 / 2.2)


def psnr(a, b, mask=None):
    d = (gamma(a) - gamma(b)) ** 2
    if mask is not None:
        d = d[mask]
    mse = float(np.mean(d))
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def pipeline(inv, mode, mask, edit, work, spp):
    albedo = ", ".join(f"{x:.6f}" for x in edit["albedo_gamma"])
    metal = ", ".join(f"{x ** (1 / 2.2):.6f}" for x in edit["metal"]["albedo"])
    lines = [
        "pipeline: edit-bench",
        "description: an object's albedo set, and the object made smooth metal, after inversion",
        "outputs: [" + ", ".join(f"{e}_{w}" for e in ("albedo", "metal") for w in WAYS) + "]",
        "stages:",
        "  b:", "    kind: bundle", f"    path: {inv}", "    materials: best_results",
        "  mesh:", "    kind: mesh", "    scene: b", f"    complete: {mode}",
        "  base:", "    kind: trace", "    mesh: mesh", "    materials: b", "    envmap: b.envmap",
        f"    spp: {spp}", "    path_spp: 8",
        "  albedo:", "    kind: edit", "    materials: b", f"    mask_png: {mask}", f"    albedo: [{albedo}]",
        "  metal:", "    kind: edit", "    materials: b", f"    mask_png: {mask}", f"    albedo: [{metal}]",
        f"    roughness: {edit['metal']['roughness']}", "    metallic: 1",
    ]
    for e in ("albedo", "metal"):
        for w in WAYS:
            lines += [f"  {e}_{w}:", "    kind: render", "    mesh: mesh", "    paths: base", f"    materials: {e}",
                      f"    output: {os.path.join(work, f'{e}_{w}.exr')}"]
            if w != "full":
                lines += ["    photo: b", f"    composite: {w}"]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--validation", required=True)
    ap.add_argument("--work", required=True, help="the bench invert --validation work folder")
    ap.add_argument("--budget", default="60")
    ap.add_argument("--complete", default="auto", help="the configuration's completion in the work folder")
    ap.add_argument("--halves", nargs="+", default=["heldback"])
    ap.add_argument("--matflow", default="target/release/matflow")
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--llvm")
    a = ap.parse_args()
    drjit_llvm.choose(a.llvm)
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    from PIL import Image

    def read(p):
        return np.array(mi.Bitmap(p), dtype=np.float64)[:, :, :3]

    with open(os.path.join(a.validation, "validation.json")) as fh:
        index = json.load(fh)
    rows = []
    for half in a.halves:
        for name in index[half]:
            d = os.path.join(a.validation, name)
            inv = os.path.abspath(os.path.join(a.work, f"{name}-{a.budget}-default-{a.complete}"))
            if not os.path.exists(os.path.join(d, "edit.json")) or not os.path.exists(os.path.join(inv, "summary.json")):
                continue
            with open(os.path.join(d, "edit.json")) as fh:
                edit = json.load(fh)
            with open(os.path.join(inv, "summary.json")) as fh:
                mode = json.load(fh)["options"]["complete"]
            out = os.path.abspath(os.path.join(a.work, f"{name}-edits"))
            os.makedirs(out, exist_ok=True)
            mask_path = os.path.abspath(os.path.join(d, "edit_mask.png"))
            spec = os.path.join(out, "edit.yaml")
            with open(spec, "w") as fh:
                fh.write(pipeline(inv, mode, mask_path, edit, out, a.spp))
            subprocess.run([a.matflow, "run", spec, "--quiet", "--cache", os.path.join(out, "cache")], check=True)
            mask = np.array(Image.open(mask_path).convert("L")) > 127
            photo = read(os.path.join(d, "gt_image.exr"))
            pred = read(os.path.join(d, "albedoPred.exr"))
            kind = index.get("kinds", {}).get(name, "closed")
            row = {"scene": name, "kind": kind, "complete": mode, "pixels": int(mask.sum())}
            for e in ("albedo", "metal"):
                truth = read(os.path.join(d, "ground_truth", f"edit_{e}.exr"))
                cands = {"unedited": photo}
                if e == "albedo":
                    new = np.asarray(edit["albedo"])[None, None, :]
                    rec = photo.copy()
                    rec[mask] = (photo * new / np.maximum(pred, 1e-3))[mask]
                    cands["recolour"] = rec
                for w in WAYS:
                    cands[w] = read(os.path.join(out, f"{e}_{w}.exr"))
                for c, img in cands.items():
                    row[f"{e} {c}"] = (psnr(img, truth, mask), psnr(img, truth))
            rows.append(row)
            print(name, kind, mode, {k: (round(v[0], 2), round(v[1], 2)) for k, v in row.items() if isinstance(v, tuple)},
                  flush=True)
    cols = [k for k in (rows[0] if rows else {}) if isinstance(rows[0][k], tuple)]
    print()
    print("| kind | scenes | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    kinds = sorted({r["kind"] for r in rows})
    for kind in kinds + ["all"]:
        sel = [r for r in rows if kind == "all" or r["kind"] == kind]
        cells = []
        for c in cols:
            ins = [r[c][0] for r in sel]
            full = [r[c][1] for r in sel]
            cells.append(f"{np.median(ins):.2f} / {min(ins):.2f} (full {np.median(full):.2f} / {min(full):.2f})")
        print(f"| {kind} | {len(sel)} | " + " | ".join(cells) + " |")
    print("\nEach cell: inside the object, median / worst (whole image, median / worst), dB.")


if __name__ == "__main__":
    main()
