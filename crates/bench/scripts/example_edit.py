#!/usr/bin/env python3
"""Does the README's photo example still edit the object it points at?

`pipelines/photo.yaml` recolours the cylinder of `pipelines/photos/room.png`
from one seed pixel (`mask_object: [80, 400]`), grown over the predicted
albedo, depth and normals. A prediction model that loses the objects (a
depth of the average layout, an albedo without the cylinder) lets the mask
flood the room. This runs the example with a model and compares what the
edit changed with the true cylinder:

- changed: the pixels whose edited render differs from the re-render by
  more than 15 % in some channel (relative; the hue shift changes the
  object's pixels by far more, its bounce light on the floor by less);
- the true object: the photo's own ground truth, pixels connected to the
  seed whose true albedo is the seed's (within 0.02) at a depth within
  0.3 in ln z of the seed's;
- their intersection over union (1: the edit is the cylinder).

It also counts what makes the images a user looks at unclean: in the
re-render and the relight, sparkles (pixels brighter than twice their
5 x 5 median + 0.05, the frame's 2 px left out) and the frame's
brightness against the interior's (1: no bright or dark line round the
image).

  matflow dataset pipelines/photos/rooms.yaml --out out/photos
  matflow dataset unpack out/photos s00000000 --to out/photos/s0
  python3 crates/bench/scripts/example_edit.py [--model M.onnx] [--work DIR] [--set mesh.silhouettes=reference]

Without --model, the bundled one. Needs numpy, scipy and OpenEXR; the
matflow binary from `cargo build --release -p matflow-cli`."""
import argparse
import os
import subprocess
import sys

import numpy as np
import OpenEXR
from scipy import ndimage

SEED = (80, 400)  # x, y: pipelines/photo.yaml's mask_object


def read(path):
    ch = OpenEXR.File(path).channels()
    key = "RGB" if "RGB" in ch else next(iter(ch))
    return np.asarray(ch[key].pixels, np.float64)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="an ONNX model under MatNet's contract (default: the bundled one)")
    ap.add_argument("--truth", default="out/photos/s0", help="the unpacked sample 0 of pipelines/photos/rooms.yaml")
    ap.add_argument("--work", default="target/bench-example-edit")
    ap.add_argument("--matflow", default="target/release/matflow")
    ap.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="passed on to `matflow run` (again for more)")
    a = ap.parse_args()
    for f in ("ground_truth/albedo.exr", "depth.exr"):
        if not os.path.exists(os.path.join(a.truth, f)):
            sys.exit(f"{a.truth}/{f} is missing: make it with the two commands in this script's help")
    os.makedirs(a.work, exist_ok=True)
    w = os.path.abspath(a.work)
    cmd = [a.matflow, "run", "pipelines/photo.yaml", "--quiet", "--cache", os.path.join(w, "cache")]
    for k, v in [("predict.output", "bundle"), ("rerender.output", "rerender.exr"),
                 ("edited.output", "edited.exr"), ("relit.output", "relit.exr")]:
        cmd += ["--set", f"{k}={os.path.join(w, v)}"]
    for kv in a.set:
        cmd += ["--set", kv]
    if a.model:
        cmd += ["--set", f"predict.model={os.path.abspath(a.model)}"]
    subprocess.run(cmd, check=True)
    edited, rerender = read(os.path.join(w, "edited.exr")), read(os.path.join(w, "rerender.exr"))
    changed = (np.abs(edited - rerender) / (np.abs(rerender) + 0.02)).max(-1) > 0.15
    albedo = read(os.path.join(a.truth, "ground_truth/albedo.exr"))
    z = read(os.path.join(a.truth, "depth.exr"))
    z = z[..., 0] if z.ndim == 3 else z
    if changed.shape != z.shape:
        sys.exit(f"the edit is {changed.shape} but the truth is {z.shape}")
    x, y = SEED
    lz = np.log(np.maximum(z, 1e-3))
    same = (np.abs(albedo - albedo[y, x]).max(-1) < 0.02) & (np.abs(lz - lz[y, x]) < 0.3)
    labels, _ = ndimage.label(same)
    obj = labels == labels[y, x]
    iou = (changed & obj).sum() / max((changed | obj).sum(), 1)
    print(f"edited {100 * changed.mean():.1f} % of the image; the true object is {100 * obj.mean():.1f} %; "
          f"IoU {iou:.3f} ({a.model or 'the bundled model'}; renders in {w})")
    for name in ("rerender", "relit"):
        sparkles, frame = cleanliness(read(os.path.join(w, name + ".exr")))
        print(f"{name}: {sparkles} sparkles, frame / interior {frame:.2f}")


def cleanliness(img):
    """Isolated bright pixels (over twice their 5 x 5 median + 0.05, the
    frame's 2 px left out) and the mean of the 1-px frame over the mean of
    the interior (3 px in)."""
    y = img.mean(-1) if img.ndim == 3 else img
    sparkles = int((y > 2.0 * ndimage.median_filter(y, 5) + 0.05)[2:-2, 2:-2].sum())
    frame = np.concatenate([y[0], y[-1], y[:, 0], y[:, -1]]).mean()
    return sparkles, float(frame / max(y[3:-3, 3:-3].mean(), 1e-12))


if __name__ == "__main__":
    main()
