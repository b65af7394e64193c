#!/usr/bin/env python3
"""Render matflow's exported scene with Mitsuba 3, for side-by-side timing.

Benchmark only: Mitsuba is never a runtime dependency of matflow. This script
re-creates, in Mitsuba 3 (variant ``llvm_ad_rgb``), exactly the scene that
matflow's path tracer renders, the way the paper's original reference
implementation (Python + Mitsuba 3) rendered it:

* ``mesh.ply``: the camera-space triangle mesh (camera at the origin looking
  down -z, +y up), shaded with its face normals (matflow does the same).
* ``envmap.exr``: the lat-long environment map, loaded with Mitsuba's
  ``envmap`` emitter at scale 1 (matflow's orientation matches Mitsuba's).
* ``albedo.f32`` / ``roughness.f32`` / ``metallic.f32``: per-pixel material
  maps (little-endian float32, row-major, row 0 at the top; already
  sanitised by matflow). They are looked up in SCREEN SPACE: every shading
  point, at every bounce, is projected into the image and takes the material
  of the (nearest) pixel it lands in. This is done inside a custom Python
  BSDF (``ScreenSpaceDisney`` below) with ``dr.gather``.
* ``scene.json``: resolution, focal length and principal point in pixels and
  the horizontal field of view.

The BSDF is the paper's simplified Disney model, transcribed from matflow's
``crates/render/src/bsdf.rs`` (same formulas, clamps and 1e-6 guards, same
one-sample mixture of cosine and GGX half-vector sampling). The integrator is
Mitsuba's ``path`` with ``max_depth`` = ray segments (4 = camera ray + 3
bounces, matflow's convention), Russian roulette disabled and emitters
visible; the film is ``hdrfilm`` with Mitsuba's default Gaussian
reconstruction filter (stddev 0.5, radius 2), as in matflow.

The folder is written by::

    matflow-bench render --bundle BUNDLE --export DIR

and ``matflow-bench render`` then runs this script as::

    python3 crates/bench/scripts/mitsuba_render.py DIR --spp 64 --depth 4 --runs 3 --threads 2

Options: ``--seed S`` (seed of the first render; timed run k uses S + k),
``--crop X Y W H`` (render only that film window, through hdrfilm's
crop_offset/crop_size), ``--out image.exr`` (write the last render as float
RGB EXR), ``--llvm LIB`` (see below).

LLVM: Mitsuba 3.9.1 / Dr.Jit 1.5 need libLLVM >= 17 on x86 (older versions
abort inside the first kernel with "LLVM ERROR: Cannot select: ...
fminimum"). Dr.Jit takes the library from ``DRJIT_LIBLLVM_PATH`` or its own
search (LLVM 15 on Debian 12); without either, the newest
``/usr/lib/x86_64-linux-gnu/libLLVM-NN.so`` with NN >= 17 is used (Debian:
``apt-get install libllvm19``); ``--llvm /path/to/libLLVM.so.19.1`` overrides
it. The script refuses to run on an older LLVM rather than crash.

Timing: one first render is reported as ``first_s``: it includes tracing
the integrator and the Python BSDF and the LLVM JIT compilation (or, when
Dr.Jit's on-disk kernel cache ~/.drjit already holds the kernel, only
loading it). Then ``--runs`` further renders, each with its own seed, are
timed (``mi.render`` -- which re-traces the Python code every call, as any
Mitsuba user pays -- plus forcing evaluation of the image) and reported as
``times_s`` and their median ``median_s``. ``load_s`` is the scene loading
time (reading the maps, ``mi.load_dict``: PLY parsing, acceleration
structure, envmap sampling tables). Progress goes to stderr; stdout gets
exactly one JSON line.

Only the standard library, Dr.Jit and Mitsuba are used (no numpy).
"""

import argparse
import array
import json
import os
import statistics
import sys
import time

# Dr.Jit needs libLLVM >= 17 on x86; choose it before mitsuba is imported
# (see drjit_llvm.py beside this script).
from drjit_llvm import MIN_LLVM_MAJOR, choose as choose_llvm  # noqa: E402


def _preparse_llvm():
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--llvm")
    known, _ = pre.parse_known_args()
    choose_llvm(known.llvm)


_preparse_llvm()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

# The variant must be set before mi.BSDF (variant-specific) is subclassed.
mi.set_variant("llvm_ad_rgb")

MIN_ROUGHNESS = 0.07  # matflow's bsdf::MIN_ROUGHNESS


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def read_f32(path, expected_len):
    """Raw little-endian float32 file -> mi.Float (flat)."""
    buf = array.array("f")
    with open(path, "rb") as f:
        buf.frombytes(f.read())
    if sys.byteorder != "little":
        buf.byteswap()
    if len(buf) != expected_len:
        raise ValueError(f"{path}: {len(buf)} floats, expected {expected_len}")
    return mi.Float(buf)


def pow5(x):
    x2 = x * x
    return x2 * x2 * x


class ScreenSpaceDisney(mi.BSDF):
    """The simplified Disney BRDF with screen-space material lookup.

    All directions are in Mitsuba's local shading frame (normal = +z), which
    with face normals is the geometric normal of the hit triangle, so
    n.x = x.z. The model is one-sided: nothing is flipped towards the viewer,
    light arriving from below the surface contributes nothing, and a viewer
    below the surface is simply clamped (n.v = 0), exactly as matflow does.
    """

    def __init__(self, props, maps):
        mi.BSDF.__init__(self, props)
        self.width = maps["width"]
        self.height = maps["height"]
        self.focal = maps["focal"]
        self.cx = maps["cx"]
        self.cy = maps["cy"]
        self.albedo = maps["albedo"]  # H*W*3
        self.roughness = maps["roughness"]  # H*W
        self.metallic = maps["metallic"]  # H*W
        glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        self.m_components = [glossy, diffuse]
        self.m_flags = glossy | diffuse

    # -- material lookup ---------------------------------------------------

    def material(self, p, active):
        """Material of the pixel the camera-space point p projects into.

        Mirrors RenderScene::material_index/material_at: nearest pixel,
        clamped to the image; points at or behind the camera plane get a
        black material (albedo 0, roughness 1, metallic 0).
        """
        depth = -p.z
        fx = self.focal * p.x / depth + self.cx + 0.5
        fy = -self.focal * p.y / depth + self.cy + 0.5
        valid = active & (depth > 1e-8)
        # Non-finite projections fall back to pixel 0 (matflow's saturating cast).
        fx = dr.select(dr.isfinite(fx), fx, 0.0)
        fy = dr.select(dr.isfinite(fy), fy, 0.0)
        x = mi.UInt32(dr.clip(dr.floor(fx), 0.0, self.width - 1.0))
        y = mi.UInt32(dr.clip(dr.floor(fy), 0.0, self.height - 1.0))
        idx = y * self.width + x
        albedo = dr.gather(mi.Color3f, self.albedo, idx, valid)  # 0 if invalid
        metallic = dr.gather(mi.Float, self.metallic, idx, valid)  # 0 if invalid
        rough = dr.select(valid, dr.gather(mi.Float, self.roughness, idx, valid), 1.0)
        rough = dr.clip(rough, MIN_ROUGHNESS, 1.0)
        return albedo, rough, metallic

    # -- the model (bsdf.rs: ggx_d, eval, pdf) -------------------------------

    @staticmethod
    def half_vector(wi, wo):
        """normalize_or_zero(wi + wo) plus the clamped n.h and v.h."""
        h = wi + wo
        length = dr.norm(h)
        h = dr.select(length > 0.0, h / length, mi.Vector3f(0.0))
        noh = dr.maximum(h.z, 0.0)
        voh = dr.maximum(dr.dot(wi, h), 0.0)
        return noh, voh

    @staticmethod
    def ggx_d(noh, alpha2):
        t = noh * noh * (alpha2 - 1.0) + 1.0 + 1e-6
        return alpha2 / (dr.pi * t * t)

    def eval_model(self, mat, wi, wo):
        """f * cos (RGB); zero for wo below the surface."""
        albedo, r, m = mat
        nol = dr.maximum(wo.z, 0.0)
        nov = dr.maximum(wi.z, 0.0)
        noh, voh = self.half_vector(wi, wo)
        alpha = r * r
        d = self.ggx_d(noh, alpha * alpha)
        k = (r + 1.0) * (r + 1.0) / 8.0
        vis = 1.0 / ((nov * (1.0 - k) + k + 1e-6) * (nol * (1.0 - k) + k + 1e-6))
        f0 = 0.04 * (1.0 - m) + albedo * m
        fresnel = f0 + (1.0 - f0) * pow5(1.0 - voh)
        fd90 = 0.5 + 2.0 * r * voh * voh
        fd_v = 1.0 + (fd90 - 1.0) * pow5(1.0 - nov)
        fd_l = 1.0 + (fd90 - 1.0) * pow5(1.0 - nol)
        diffuse = albedo * ((1.0 - m) / dr.pi * fd_v * fd_l * nol)
        specular = fresnel * (d * vis / 4.0 * nol)
        return dr.select(nol > 0.0, diffuse + specular, mi.Color3f(0.0))

    def pdf_model(self, mat, wi, wo):
        """Solid-angle pdf of the mixture: 1/2 GGX reflection + 1/2 cosine."""
        _, r, _ = mat
        nol = dr.maximum(wo.z, 0.0)
        noh, voh = self.half_vector(wi, wo)
        alpha = r * r
        d = self.ggx_d(noh, alpha * alpha)
        return 0.5 * d * noh / (4.0 * dr.maximum(voh, 1e-6)) + 0.5 * nol / dr.pi

    # -- mi.BSDF interface ---------------------------------------------------

    def sample(self, ctx, si, sample1, sample2, active=True):
        mat = self.material(si.p, active)
        wi = si.wi
        _, r, _ = mat
        # Lobe choice as in bsdf::sample: u_lobe > 1/2 -> diffuse.
        diffuse = sample1 > 0.5
        wo_diffuse = mi.warp.square_to_cosine_hemisphere(sample2)
        # GGX half vector with density D(h) cos(theta_h), reflected about wi.
        a2 = r * r * r * r
        u1, u2 = sample2.x, sample2.y
        cos_t = dr.sqrt(dr.clip((1.0 - u1) / (u1 * (a2 - 1.0) + 1.0), 0.0, 1.0))
        sin_t = dr.sqrt(dr.maximum(1.0 - cos_t * cos_t, 0.0))
        sin_p, cos_p = dr.sincos(2.0 * dr.pi * u2)
        h = mi.Vector3f(sin_t * cos_p, sin_t * sin_p, cos_t)
        wo_glossy = 2.0 * dr.dot(wi, h) * h - wi
        wo = dr.select(diffuse, wo_diffuse, wo_glossy)
        length = dr.norm(wo)
        ok = active & (length > 0.0)
        wo = dr.select(ok, wo / length, mi.Vector3f(0.0, 0.0, 1.0))

        pdf = self.pdf_model(mat, wi, wo)
        f = self.eval_model(mat, wi, wo)
        ok &= (pdf > 1e-6) & dr.isfinite(pdf)
        # matflow's sample weight is f / (pdf + 1e-6); the MIS pdf is pdf.
        weight = f / (pdf + 1e-6)
        ok &= dr.all(dr.isfinite(weight))

        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = wo
        bs.pdf = dr.select(ok, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_type = dr.select(
            diffuse,
            mi.UInt32(int(mi.BSDFFlags.DiffuseReflection)),
            mi.UInt32(int(mi.BSDFFlags.GlossyReflection)),
        )
        bs.sampled_component = dr.select(diffuse, mi.UInt32(1), mi.UInt32(0))
        return bs, dr.select(ok, weight, mi.Color3f(0.0))

    def eval(self, ctx, si, wo, active=True):
        mat = self.material(si.p, active)
        f = self.eval_model(mat, si.wi, wo)
        return dr.select(active, f, mi.Color3f(0.0))

    def pdf(self, ctx, si, wo, active=True):
        mat = self.material(si.p, active)
        return dr.select(active, self.pdf_model(mat, si.wi, wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        mat = self.material(si.p, active)
        f = self.eval_model(mat, si.wi, wo)
        pdf = self.pdf_model(mat, si.wi, wo)
        return dr.select(active, f, mi.Color3f(0.0)), dr.select(active, pdf, 0.0)

    def traverse(self, callback):
        pass

    def to_string(self):
        return f"ScreenSpaceDisney[{self.width}x{self.height}]"


def load_scene(folder, depth, crop):
    """Reads the exported folder and builds the Mitsuba scene."""
    with open(os.path.join(folder, "scene.json")) as f:
        cam = json.load(f)
    w, h = int(cam["width"]), int(cam["height"])
    # Mitsuba's perspective camera is centred on the film (principal point
    # (W-1)/2 in matflow's pixel-centre convention), which is what matflow
    # exports; anything else would need principal_point_offset.
    if abs(cam["cx"] - (w - 1) / 2) > 1e-3 or abs(cam["cy"] - (h - 1) / 2) > 1e-3:
        raise ValueError("off-centre principal point is not supported")
    maps = {
        "width": w,
        "height": h,
        "focal": float(cam["focal"]),
        "cx": float(cam["cx"]),
        "cy": float(cam["cy"]),
        "albedo": read_f32(os.path.join(folder, "albedo.f32"), w * h * 3),
        "roughness": read_f32(os.path.join(folder, "roughness.f32"), w * h),
        "metallic": read_f32(os.path.join(folder, "metallic.f32"), w * h),
    }
    mi.register_bsdf("matflow_screen_disney", lambda props: ScreenSpaceDisney(props, maps))

    film = {
        "type": "hdrfilm",
        "width": w,
        "height": h,
        "pixel_format": "rgb",
        "component_format": "float32",
        # Default rfilter: gaussian, stddev 0.5 (radius 4 * stddev = 2).
        "rfilter": {"type": "gaussian", "stddev": 0.5},
    }
    if crop is not None:
        cx, cy, cw, ch = crop
        if cw <= 0 or ch <= 0 or cx < 0 or cy < 0 or cx + cw > w or cy + ch > h:
            raise ValueError(f"crop {crop} outside the {w}x{h} film")
        film.update(crop_offset_x=cx, crop_offset_y=cy, crop_width=cw, crop_height=ch)

    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {
                "type": "path",
                "max_depth": depth,
                "rr_depth": 1000,  # never any Russian roulette
                "hide_emitters": False,
            },
            "sensor": {
                "type": "perspective",
                "fov": float(cam["fov_x_deg"]),
                "fov_axis": "x",
                # Camera space is world space: origin, looking down -z, +y up.
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0.0, 0.0, 0.0], target=[0.0, 0.0, -1.0], up=[0.0, 1.0, 0.0]
                ),
                "sampler": {"type": "independent", "sample_count": 1},
                "film": film,
            },
            "emitter": {
                "type": "envmap",
                "filename": os.path.join(folder, "envmap.exr"),
                "scale": 1.0,
            },
            "mesh": {
                "type": "ply",
                "filename": os.path.join(folder, "mesh.ply"),
                "face_normals": True,  # matflow shades with face normals
                "bsdf": {"type": "matflow_screen_disney"},
            },
        }
    )
    return scene


def render_once(scene, spp, seed):
    """One timed render: mi.render plus forcing the kernel to finish.

    Returns the image, the wall time and the process CPU time (all threads;
    on a shared machine, CPU time well below threads x wall time means the
    render was waiting for cores).
    """
    c0, t0 = time.process_time(), time.perf_counter()
    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return img, time.perf_counter() - t0, time.process_time() - c0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="folder written by `matflow-bench render --export`")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--depth", type=int, default=4, help="max ray segments (Mitsuba max_depth)")
    ap.add_argument("--runs", type=int, default=3, help="timed renders after the first one")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--crop", type=int, nargs=4, metavar=("X", "Y", "W", "H"))
    ap.add_argument("--out", help="write the last render here (float RGB EXR)")
    ap.add_argument(
        "--llvm",
        help=f"libLLVM shared library for Dr.Jit (version >= {MIN_LLVM_MAJOR}); "
        "default: $DRJIT_LIBLLVM_PATH or Dr.Jit's own search",
    )
    a = ap.parse_args()

    llvm = dr.detail.llvm_version()
    if llvm is None or llvm[0] < MIN_LLVM_MAJOR:
        found = ".".join(map(str, llvm)) if llvm else "none"
        sys.exit(
            f"mitsuba_render: Dr.Jit loaded LLVM {found}, but Mitsuba "
            f"{mi.__version__}'s kernels need LLVM >= {MIN_LLVM_MAJOR} on x86 "
            "(older versions abort on llvm.minimum); pass --llvm "
            "/path/to/libLLVM.so.NN or set DRJIT_LIBLLVM_PATH"
        )
    log(f"mitsuba_render: LLVM {'.'.join(map(str, llvm))}")

    dr.set_thread_count(max(1, a.threads))

    t0 = time.perf_counter()
    scene = load_scene(a.dir, a.depth, a.crop)
    load_s = time.perf_counter() - t0
    log(f"mitsuba_render: loaded {a.dir} in {load_s:.3f} s")

    # The first render pays for tracing the Python BSDF and JIT compilation.
    img, first_s, cpu = render_once(scene, a.spp, a.seed)
    log(f"mitsuba_render: first render {first_s:.3f} s (cpu {cpu:.3f} s)")
    times = []
    for k in range(max(0, a.runs)):
        img, t, cpu = render_once(scene, a.spp, a.seed + 1 + k)
        times.append(t)
        log(f"mitsuba_render: run {k + 1}/{a.runs} {t:.3f} s (cpu {cpu:.3f} s)")

    if a.out:
        mi.Bitmap(img).write(a.out)
        log(f"mitsuba_render: wrote {a.out}")

    result = {
        "renderer": f"mitsuba3 {mi.__version__} {mi.variant()}",
        "threads": dr.thread_count(),
        "spp": a.spp,
        "depth": a.depth,
        "first_s": round(first_s, 4),
        "times_s": [round(t, 4) for t in times],
        "median_s": round(statistics.median(times), 4) if times else round(first_s, 4),
        "load_s": round(load_s, 4),
    }
    if a.crop is not None:
        result["crop"] = list(a.crop)
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
