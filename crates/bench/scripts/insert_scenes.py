#!/usr/bin/env python3
"""Object insertion per kind of scene against Mitsuba's render with the objects.

Benchmark only (Mitsuba 3, like relight_scenes.py). For each scene of a
validation set made by relight_scenes.py it draws the scene again, stands
three balls on its floor in front of the camera where nothing else
stands (matflow's shipped sphere, pipelines/meshes/sphere.obj, radius
0.25: a diffuse one, smooth glass and rough glass, roughness 0.3, η 1.5),
renders the capture with them at the capture's exposure
(``ground_truth/insert.exr``), and writes the objects file
``render --insert`` reads (``insert.yaml``, camera frame) and each ball's
pixel mask. Then, for each completion asked, it runs

    matflow render --bundle SCENE --materials ground_truth
        --envmap ground_truth/envmap.exr --insert insert.yaml
        --composite differential --complete MODE --spp N

(the true maps and light: only the geometry past the frame and the
insertion can be wrong) and prints the PSNR (sRGB, gamma 2.2) over the
whole image and inside each ball, per scene and per kind.

    python3 crates/bench/scripts/insert_scenes.py --validation out/kinds --work out/insert \\
        [--complete auto room] [--halves heldback] [--spp 64]
"""

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import edit_truths as et  # noqa: E402
import relight_scenes as rs  # noqa: E402

SPHERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "pipelines", "meshes", "sphere.obj")
SCALE = 0.5  # the shipped sphere is 1 across, standing on its origin
BALLS = [
    ("diffuse", {"type": "diffuse", "albedo": [0.7, 0.55, 0.35]},
     {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.55, 0.35]}}),
    ("smooth glass", {"type": "glass", "ior": 1.5, "roughness": 0.0},
     {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}),
    ("rough glass", {"type": "glass", "ior": 1.5, "roughness": 0.3},
     {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.09, "int_ior": 1.5, "ext_ior": 1.0}),
]


def floor_bounds(P):
    """Where the scene's floor (y = 0) is, as (x0, x1, z0, z1)."""
    r = P["room"]
    if P["kind"] == "stage":
        return (-r["width"] / 2, r["width"] / 2, 0.0, r["depth"])
    if P["kind"] == "outdoor":
        return (-50.0, 50.0, -50.0, 50.0)
    return (0.0, r["width"], 0.0, r["depth"])


def in_view(c2w, centre, radius, margin=0.05):
    """Whether a ball of `radius` at world `centre` lies wholly in the
    frame (with `margin` of the half-width to spare)."""
    p = (np.linalg.inv(c2w) @ np.r_[centre, 1.0])[:3]
    if p[2] > -0.5:
        return False
    t = math.tan(math.radians(rs.FOV_X_DEG / 2))
    u, v = p[0] / (-p[2] * t), p[1] / (-p[2] * t)
    r = radius / (-p[2] * t)
    return abs(u) + r < 1 - margin and abs(v) + r < 1 - margin


def spots(P, c2w):
    """Three free places on the floor, wholly in view, 0.65 apart, or
    None."""
    cam = np.asarray(P["camera"]["position"])
    yaw = math.radians(P["camera"]["yaw_deg"])
    fwd = np.array([math.sin(yaw), 0.0, -math.cos(yaw)])
    right = np.array([math.cos(yaw), 0.0, math.sin(yaw)])
    x0, x1, z0, z1 = floor_bounds(P)
    taken = [(o["position"][0], o["position"][1]) for o in P["objects"]]
    radius = 0.5 * SCALE
    for dist in np.arange(1.5, 7.0, 0.25):
        for shift in np.arange(-0.6, 0.61, 0.15):
            ps = [cam + fwd * dist + right * (shift + 0.65 * i) for i in (-1, 0, 1)]
            ps = [np.array([p[0], 0.0, p[2]]) for p in ps]
            if all(x0 + 0.3 < p[0] < x1 - 0.3 and z0 + 0.3 < p[2] < z1 - 0.3 for p in ps) and all(
                    math.hypot(p[0] - tx, p[2] - tz) > 1.1 for p in ps for tx, tz in taken) and all(
                    in_view(c2w, p + np.array([0.0, radius, 0.0]), radius) for p in ps):
                return ps
    return None


def make_truth(mi, dr, index, k, order, d, spp, pass_spp):
    P, geo, c2w, stored = et.redraw(index, k, order, d)
    places = spots(P, c2w)
    if places is None:
        return None
    w2c = np.linalg.inv(c2w)
    tmp = os.path.join(d, "mitsuba-insert")
    os.makedirs(tmp, exist_ok=True)
    env_path = os.path.join(tmp, "capture_sky.exr")
    rs.write_exr(mi, env_path, rs.sky_image(P["sky"], c2w[:3, :3], rs.ENV_W, rs.ENV_H))
    shapes, _ = rs.mitsuba_shapes(mi, geo, w2c, tmp)
    entries = []
    for i, ((name, mat, bsdf), p) in enumerate(zip(BALLS, places)):
        t = (w2c @ np.r_[p, 1.0])[:3]
        # The ball stands on the floor: its origin (bottom) there, its
        # axis the world's up, which for a sphere needs no rotation but
        # the centre's place: world centre p + up * 0.25.
        centre = (w2c @ np.r_[p + np.array([0.0, 0.5 * SCALE, 0.0]), 1.0])[:3]
        origin = centre - np.array([0.0, 0.5 * SCALE, 0.0])
        m = np.eye(4)
        m[:3, :3] *= SCALE
        m[:3, 3] = origin
        shapes[f"ball{i}"] = {"type": "obj", "filename": os.path.abspath(SPHERE), "to_world": mi.ScalarTransform4f(m.tolist()),
                              "bsdf": bsdf, "face_normals": False}
        entries.append({"name": name, "translate": origin.tolist(), "material": mat, "floor_point": t.tolist()})
    scene = rs.build_scene(mi, shapes, env_path, P["lamps"], w2c, index["size"], pass_spp)
    ids = et.object_ids(mi, dr, scene, index["size"])
    img, _, _ = rs.render(mi, scene, spp, pass_spp, ((index["seed"] % 1000) * 1000 + k) * 10 + 8)
    rs.write_exr(mi, os.path.join(d, "ground_truth", "insert.exr"), img * stored["exposure"])
    masks = np.stack([ids == f"ball{i}" for i in range(len(entries))])
    np.save(os.path.join(d, "insert_masks.npy"), masks)
    lines = []
    for e in entries:
        mat = ", ".join(f"{k}: {json.dumps(v)}" for k, v in e["material"].items())
        lines += [f"- mesh: {os.path.abspath(SPHERE)}", f"  translate: {json.dumps([round(x, 6) for x in e['translate']])}",
                  f"  scale: {SCALE}", f"  material: {{{mat}}}"]
    with open(os.path.join(d, "insert.yaml"), "w") as fh:
        fh.write("# three balls (crates/bench/scripts/insert_scenes.py): " + ", ".join(e["name"] for e in entries) + "\n")
        fh.write("\n".join(lines) + "\n")
    import shutil

    shutil.rmtree(tmp)
    return entries


def psnr(a, b, mask=None):
    d = (rs.gamma(a) - rs.gamma(b)) ** 2
    if mask is not None:
        d = d[mask]
    mse = float(np.mean(d))
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--validation", required=True)
    ap.add_argument("--work", required=True)
    ap.add_argument("--complete", nargs="+", default=["auto", "room"])
    ap.add_argument("--halves", nargs="+", default=["heldback"])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--truth-spp", type=int, help="default: the set's")
    ap.add_argument("--pass-spp", type=int, default=32)
    ap.add_argument("--matflow", default="target/release/matflow")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--llvm")
    a = ap.parse_args()
    index, mi, dr, names, order = et.open_set(a)
    os.makedirs(a.work, exist_ok=True)
    rows = []
    for half in a.halves:
        for name in index[half]:
            k = names.index(name)
            d = os.path.join(a.validation, name)
            if not os.path.exists(os.path.join(d, "insert.yaml")):
                if make_truth(mi, dr, index, k, order, d, a.truth_spp or index["spp"], a.pass_spp) is None:
                    rs.log(f"insert_scenes: {name}: no free floor for three balls, skipped")
                    continue
            truth = np.array(mi.Bitmap(os.path.join(d, "ground_truth", "insert.exr")), dtype=np.float64)[:, :, :3]
            masks = np.load(os.path.join(d, "insert_masks.npy"))
            kind = index.get("kinds", {}).get(name, "closed")
            for mode in a.complete:
                out = os.path.join(a.work, f"{name}-{mode}.exr")
                r = subprocess.run([a.matflow, "render", "--bundle", d, "--materials", "ground_truth", "--envmap",
                                    os.path.join(d, "ground_truth", "envmap.exr"), "--insert", os.path.join(d, "insert.yaml"),
                                    "--composite", "differential", "--complete", mode, "--spp", str(a.spp),
                                    "--filter", "gaussian", "--out", out], capture_output=True, text=True)
                if r.returncode != 0:
                    sys.exit(f"insert_scenes: {name}: matflow render failed:\n{r.stderr}")
                with open(out[:-4] + ".json") as fh:
                    taken = json.load(fh)["completion"]["complete"]
                img = np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3]
                row = {"scene": name, "kind": kind, "mode": mode, "taken": taken, "full": psnr(img, truth)}
                for (bname, _, _), m in zip(BALLS, masks):
                    row[bname] = psnr(img, truth, m) if m.any() else float("nan")
                rows.append(row)
                print(json.dumps({k: (round(v, 2) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    print()
    print("| kind | completion | scenes | taken | full image median / worst | " + " | ".join(b[0] for b in BALLS) + " |")
    print("|---|---|---|---|---|" + "---|" * len(BALLS))
    for mode in a.complete:
        for kind in sorted({r["kind"] for r in rows}) + ["all"]:
            sel = [r for r in rows if r["mode"] == mode and (kind == "all" or r["kind"] == kind)]
            if not sel:
                continue
            taken = {}
            for r in sel:
                taken[r["taken"]] = taken.get(r["taken"], 0) + 1
            cells = []
            for b in BALLS:
                v = [r[b[0]] for r in sel if not math.isnan(r[b[0]])]
                cells.append(f"{np.median(v):.2f} / {min(v):.2f}" if v else "—")
            full = [r["full"] for r in sel]
            print(f"| {kind} | {mode} | {len(sel)} | " + ", ".join(f"{t} {c}" for t, c in taken.items())
                  + f" | {np.median(full):.2f} / {min(full):.2f} | " + " | ".join(cells) + " |")
    print("\nPSNR (sRGB, gamma 2.2) against Mitsuba's render with the balls, dB; a ball's cell is inside its pixels.")


if __name__ == "__main__":
    main()
