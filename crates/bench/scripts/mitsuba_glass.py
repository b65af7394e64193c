#!/usr/bin/env python3
"""Render matflow's glass-interop scene with Mitsuba 3 (benchmark only).

``matflow-bench glass`` writes a folder with:

* ``scene.json``: resolution and horizontal field of view of matflow's
  camera (at the origin, looking down -z, +y up; principal point centred),
  and the list of objects, each ``{"ply": FILE, "bsdf": {...}}`` where the
  BSDF is one of ``{"type": "diffuse", "albedo": [r, g, b]}``,
  ``{"type": "dielectric", "ior": n, "transmittance": [r, g, b]}`` and
  ``{"type": "roughdielectric", "ior": n, "alpha": a, "transmittance": [...]}``;
* the PLY meshes (camera space, with per-vertex normals where matflow
  shades with them);
* ``envmap.exr``: the lat-long envmap texels (Mitsuba's ``envmap``
  orientation, which is matflow's).

This script builds the same scene from Mitsuba's own plugins: ``diffuse``,
``dielectric`` and ``roughdielectric`` (GGX, visible-normal sampling), the
``path`` integrator with a large ``max_depth`` and no Russian roulette, a
box reconstruction filter; it renders ``--spp`` samples with ``--seed`` and
writes ``--out`` (float RGB EXR). stdout gets one JSON line with timings.

    python3 crates/bench/scripts/mitsuba_glass.py DIR --spp 256 --depth 64 --seed 0 --out m.exr
"""

import argparse
import json
import os
import sys
import time

# Dr.Jit needs libLLVM >= 17 on x86 (see drjit_llvm.py beside this script).
from drjit_llvm import choose as choose_llvm  # noqa: E402

choose_llvm()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")


def bsdf_dict(b):
    t = b["type"]
    if t == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": b["albedo"]}}
    if t == "dielectric":
        return {
            "type": "dielectric",
            "int_ior": float(b["ior"]),
            "ext_ior": 1.0,
            "specular_transmittance": {"type": "rgb", "value": b["transmittance"]},
        }
    if t == "roughdielectric":
        return {
            "type": "roughdielectric",
            "distribution": "ggx",
            "alpha": float(b["alpha"]),
            "sample_visible": True,
            "int_ior": float(b["ior"]),
            "ext_ior": 1.0,
            "specular_transmittance": {"type": "rgb", "value": b["transmittance"]},
        }
    raise ValueError(f"unknown bsdf {t}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--depth", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    dr.set_thread_count(max(1, a.threads))
    with open(os.path.join(a.dir, "scene.json")) as f:
        cam = json.load(f)
    shapes = {}
    for k, o in enumerate(cam["objects"]):
        shapes[f"object{k}"] = {
            "type": "ply",
            "filename": os.path.join(a.dir, o["ply"]),
            "face_normals": not o.get("vertex_normals", False),
            "bsdf": bsdf_dict(o["bsdf"]),
        }
    t0 = time.perf_counter()
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {
                "type": "path",
                "max_depth": a.depth,
                "rr_depth": 100000,
                "hide_emitters": False,
            },
            "sensor": {
                "type": "perspective",
                "fov": float(cam["fov_x_deg"]),
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0.0, 0.0, 0.0], target=[0.0, 0.0, -1.0], up=[0.0, 1.0, 0.0]
                ),
                "sampler": {"type": "independent", "sample_count": 1},
                "film": {
                    "type": "hdrfilm",
                    "width": int(cam["width"]),
                    "height": int(cam["height"]),
                    "pixel_format": "rgb",
                    "component_format": "float32",
                    "rfilter": {"type": "box"},
                },
            },
            "emitter": {
                "type": "envmap",
                "filename": os.path.join(a.dir, "envmap.exr"),
                "scale": 1.0,
            },
            **shapes,
        }
    )
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    img = mi.render(scene, spp=a.spp, seed=a.seed)
    dr.eval(img)
    dr.sync_thread()
    render_s = time.perf_counter() - t0
    mi.util.write_bitmap(a.out, img)
    print(
        json.dumps(
            {
                "renderer": f"mitsuba {mi.__version__} llvm_ad_rgb",
                "load_s": load_s,
                "render_s": render_s,
            }
        )
    )


if __name__ == "__main__":
    sys.exit(main())
