#!/usr/bin/env python3
"""Photograph `matflow-bench export-rooms` scenes with Mitsuba 3.

Benchmark only: Mitsuba is never a dependency of matflow. The same scenes
of matflow's `rooms` generator, photographed by another renderer, tell how
much of the prediction network's gap on other renderers' scenes (the
`relight_scenes.py` set) is the renderer's look and how much is the
scenes' content:

    matflow-bench export-rooms --dataset out/matnet/heldout --out out/rooms-mf
    python3 crates/bench/scripts/mitsuba_rooms.py out/rooms-mf --out out/rooms-mi
    matflow-bench matnet --accuracy-only --scenes out/rooms-mf --heldout none
    matflow-bench matnet --accuracy-only --scenes out/rooms-mi --heldout none

`out/rooms-mi/KEY` is `out/rooms-mf/KEY` (the dataset's bundle: its depth
and true maps) with `gt_image.exr` replaced by Mitsuba's photograph of
the scene in `KEY/mitsuba/`:

* the camera at the origin looking down -z, +y up, the export's field of
  view (35 deg horizontal), Mitsuba's Gaussian pixel filter;
* Mitsuba's ``path`` integrator, max_depth 8, Russian roulette after 5
  (``relight_scenes.py``'s integrator and camera);
* materials: Mitsuba's ``principled`` BSDF (specular 0.5, i.e. F0 = 0.04 on
  dielectrics; alpha = roughness^2, as matflow's), two-sided (matflow's
  surfaces are); a texture times the albedo as ``base_color`` where the
  object has one; ``diffuse`` and ``dielectric`` / ``roughdielectric`` for
  matflow's Lambertian and glass surfaces;
* the sky as an ``envmap`` emitter (matflow's lat-long layout is
  Mitsuba's), lamps as ``point`` emitters, the sun-like distant lamps as
  ``directional`` ones;
* the exposure as the dataset's: the render times 0.18 over its
  log-average luminance, times 2^EV of the scene (``exposure_ev``).

``--zoom F`` (below 1) photographs the central F of the view instead (a
longer lens: tan of the half field of view times F, at full resolution),
and crops the bundle's depth and true maps alike (nearest pixel, so the
truth is the dataset's, magnified): the same scenes framed tighter, their
objects larger in the frame.
"""

import argparse
import json
import math
import os
import shutil
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import drjit_llvm  # noqa: E402
from relight_scenes import camera_and_integrator  # noqa: E402

# The bundle's per-pixel truth (besides depth.exr), cropped with --zoom.
TRUTH_MAPS = ("albedo.exr", "roughness.exr", "metallic.exr", "normal.exr")


def bsdf(mi, surface, texture):
    t = surface["type"]
    if t == "glass":
        ior = float(surface["eta"])
        trans = [float(surface["transmission"]) * c for c in surface["tint"]]
        a = float(surface["roughness"]) ** 2
        d = {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0,
             "specular_transmittance": {"type": "rgb", "value": trans}}
        if a > 1e-4:
            d.update({"type": "roughdielectric", "distribution": "ggx", "alpha": a})
        return d
    if texture:
        colour = {"type": "bitmap", "filename": texture, "filter_type": "bilinear", "wrap_mode": "repeat"}
    else:
        colour = {"type": "rgb", "value": surface["albedo"]}
    if t == "diffuse":
        inner = {"type": "diffuse", "reflectance": colour}
    else:
        inner = {"type": "principled", "base_color": colour, "roughness": float(surface["roughness"]),
                 "metallic": float(surface["metallic"]), "specular": 0.5}
    return {"type": "twosided", "bsdf": inner}


def build(mi, folder, spp, zoom):
    desc = json.load(open(os.path.join(folder, "scene.json")))
    n = int(desc["size"])
    fov = math.degrees(2.0 * math.atan(zoom * math.tan(math.radians(float(desc["fov_x_deg"]) / 2.0))))
    d = camera_and_integrator(mi, n, spp, fov)
    d["sky"] = {"type": "envmap", "filename": os.path.join(folder, desc["envmap"]), "scale": 1.0}
    for k, o in enumerate(desc["objects"]):
        tex = os.path.join(folder, o["texture"]) if o.get("texture") else None
        d[f"obj{k:03d}"] = {"type": "ply", "filename": os.path.join(folder, o["ply"]),
                            "face_normals": not o["vertex_normals"], "bsdf": bsdf(mi, o["surface"], tex)}
    for k, l in enumerate(desc["lamps"]):
        if "point" in l:
            d[f"lamp{k}"] = {"type": "point", "position": l["point"],
                             "intensity": {"type": "rgb", "value": l["intensity"]}}
        else:
            # matflow's direction points towards the light; Mitsuba's is
            # the light's travel.
            d[f"lamp{k}"] = {"type": "directional", "direction": [-x for x in l["distant"]],
                             "irradiance": {"type": "rgb", "value": l["irradiance"]}}
    return desc, mi.load_dict(d, optimize=False)


def magnify(mi, path, zoom):
    """The central `zoom` of the EXR at `path`, back at its size (nearest
    pixel), written over it."""
    bm = mi.Bitmap(path)
    a = np.array(bm)
    n = a.shape[0]
    idx = (n - n * zoom) / 2.0 + (np.arange(n) + 0.5) * zoom
    idx = np.clip(idx.astype(np.int64), 0, n - 1)
    out = np.ascontiguousarray(a[idx][:, idx])
    mi.Bitmap(out, bm.pixel_format()).write(path)


def exposed(img, ev):
    lum = np.maximum(img @ np.array([0.2126, 0.7152, 0.0722]), 0.0)
    log_avg = float(np.exp(np.mean(np.log(lum.astype(np.float64) + 1e-4))))
    k = min(max(0.18 / max(log_avg, 1e-6), 1e-4), 1e4) * 2.0 ** float(ev)
    return (img * k).astype(np.float32)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", help="an export-rooms folder")
    ap.add_argument("--out", required=True, help="where the bundles with Mitsuba's photographs go")
    ap.add_argument("--spp", type=int, default=128)
    ap.add_argument("--pass-spp", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--zoom", type=float, default=1.0, help="photograph the central share of the view (0 < F <= 1)")
    ap.add_argument("--llvm", help="libLLVM for Dr.Jit (>= 17); see drjit_llvm.py")
    args = ap.parse_args()
    if not 0.0 < args.zoom <= 1.0:
        ap.error(f"--zoom {args.zoom}: a share of the view, in (0, 1]")
    drjit_llvm.choose(args.llvm)
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(args.threads)
    index = json.load(open(os.path.join(args.scenes, "validation.json")))
    os.makedirs(args.out, exist_ok=True)
    for key in sorted(index["kinds"]):
        src, dst = os.path.join(args.scenes, key), os.path.join(args.out, key)
        t0 = time.time()
        desc, scene = build(mi, os.path.join(src, "mitsuba"), args.pass_spp, args.zoom)
        passes = max(1, -(-args.spp // args.pass_spp))
        acc = None
        for p in range(passes):
            img = np.array(mi.render(scene, spp=args.pass_spp, seed=p), dtype=np.float64)
            acc = img if acc is None else acc + img
        img = np.nan_to_num(acc / passes, nan=0.0, posinf=0.0, neginf=0.0)
        img = exposed(np.maximum(img, 0.0), desc["exposure_ev"])
        tmp = dst + ".partial"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(src, tmp, ignore=shutil.ignore_patterns("mitsuba", "gt_image.exr", "gt_image.png"))
        if args.zoom < 1.0:
            truth = [os.path.join(tmp, "ground_truth", f) for f in TRUTH_MAPS]
            own = [os.path.join(tmp, f) for f in ("depth.exr", "mesh_mask.png")]
            for path in own + truth:
                if os.path.exists(path):
                    magnify(mi, path, args.zoom)
        mi.Bitmap(img, mi.Bitmap.PixelFormat.RGB).write(os.path.join(tmp, "gt_image.exr"))
        shutil.rmtree(dst, ignore_errors=True)
        os.rename(tmp, dst)
        print(f"mitsuba_rooms: {key} ({desc['kind']}, {len(desc['objects'])} objects, "
              f"{len(desc['lamps'])} lamps) in {time.time() - t0:.1f} s", flush=True)
    index["renderer"] = f"Mitsuba 3 (mitsuba_rooms.py, {args.spp} spp, zoom {args.zoom})"
    with open(os.path.join(args.out, "validation.json"), "w") as f:
        json.dump(index, f, indent=1)


if __name__ == "__main__":
    main()
