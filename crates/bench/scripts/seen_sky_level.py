#!/usr/bin/env python3
"""Does the sky seen through a window pin the level of the recovered light?

Reads the outputs of ``matflow-bench invert --validation VAL --work WORK``
(benchmark only; needs Mitsuba 3's Python package for EXR reading and
numpy). For each room whose photo shows the sky (pixels with no depth)
unsaturated (every channel below ``--saturated``) over at least
``--min-pixels`` pixels:

* ``g``: the photo's sky over the recovered scene's re-render of it
  (``best_results/rendered_img.exr``), as sums of luminance over those
  pixels: how far the fitted envmap misses the light the camera sees
  directly;
* the relighting PSNR (sRGB, gamma 2.2, as the bench) of the recovered
  scene under each new sky, as it comes and with the room's pixels divided
  by ``g`` (the one correction the seen sky could make: the envmap brought
  to the seen sky's level, the albedo taking the inverse gain; first order
  in the bounces).

If the fit's level error were one the seen sky could see, ``g`` would be
far from 1 where relighting is off, and dividing by it would help.

    python3 crates/bench/scripts/seen_sky_level.py --validation out/relight-val \\
        --work out/bench-camera [more work folders] --complete room
"""

import argparse
import os
import sys

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--validation", required=True, help="the validation set")
    ap.add_argument(
        "--work", required=True, nargs="+", help="the bench's --work folders (the first holding a room wins)"
    )
    ap.add_argument("--complete", default="room", help="the bench's --complete mode")
    ap.add_argument("--budget", default="60", help="the bench's budget")
    ap.add_argument("--config", default="default", help="the bench's configuration")
    ap.add_argument("--saturated", type=float, default=0.95)
    ap.add_argument("--min-pixels", type=int, default=500)
    a = ap.parse_args()

    import mitsuba as mi

    mi.set_variant("scalar_rgb")

    def rd(p):
        return np.array(
            mi.Bitmap(p).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
        )

    def psnr(x, y):
        x = np.clip(x, 0, 1) ** (1 / 2.2)
        y = np.clip(y, 0, 1) ** (1 / 2.2)
        return -10 * np.log10(max(float(np.mean((x - y) ** 2)), 1e-20))

    base, corr = [], []
    print("| room | sky pixels | unsaturated | g | relight 1 / 2 | divided by g |")
    print("|---|---|---|---|---|---|")
    for s in sorted(os.listdir(a.validation)):
        v = os.path.join(a.validation, s)
        runs = [os.path.join(w, f"{s}-{a.budget}-{a.config}-{a.complete}") for w in a.work]
        runs = [r for r in runs if os.path.exists(os.path.join(r, f"relit1-complete-{a.complete}.exr"))]
        if not os.path.isdir(v) or not runs:
            continue
        r = runs[0]
        relit = [os.path.join(r, f"relit{i}-complete-{a.complete}.exr") for i in (0, 1)]
        img = rd(os.path.join(v, "gt_image.exr"))
        sky = rd(os.path.join(v, "depth.exr"))[..., 0] <= 0
        uns = sky & (img.max(axis=2) < a.saturated)
        truths = [rd(os.path.join(v, "ground_truth", n)) for n in ("relit_image.exr", "relit_image_2.exr")]
        ours = [rd(p) for p in relit]
        b = [psnr(o, t) for o, t in zip(ours, truths)]
        if uns.sum() < a.min_pixels:
            print(f"| {s} | {sky.sum()} | {uns.sum()} | | {b[0]:.2f} / {b[1]:.2f} | |")
            continue
        rend = rd(os.path.join(r, "best_results", "rendered_img.exr"))
        g = float((img[uns] @ LUMA).sum() / max((rend[uns] @ LUMA).sum(), 1e-12))
        c = []
        for o, t in zip(ours, truths):
            o = o.copy()
            o[~sky] /= g
            c.append(psnr(o, t))
        base += b
        corr += c
        print(f"| {s} | {sky.sum()} | {uns.sum()} | {g:.2f} | {b[0]:.2f} / {b[1]:.2f} | {c[0]:.2f} / {c[1]:.2f} |")
    if base:
        print(
            f"rooms with seen sky: relight median {np.median(base):.2f} / worst {min(base):.2f} dB; "
            f"divided by g: {np.median(corr):.2f} / {min(corr):.2f} dB"
        )
    else:
        print("no room shows enough unsaturated sky", file=sys.stderr)


if __name__ == "__main__":
    main()
