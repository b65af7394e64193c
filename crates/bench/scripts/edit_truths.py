#!/usr/bin/env python3
"""Truths of material edits for a validation set made by relight_scenes.py.

Benchmark only (Mitsuba 3, like relight_scenes.py). For each scene of the
set it draws the scene again (the same draw: same parameters, geometry,
camera, capture sky and lamps), takes the object of the scene with the
most pixels in view that is not a metal, and renders the capture twice
more with that object edited, at the capture's exposure:

* ``ground_truth/edit_albedo.exr``: its base colour set to ``new`` (its
  hue turned by 180 degrees, saturation at least 0.5, value 0.3-0.8);
* ``ground_truth/edit_metal.exr``: made a smooth metal (metallic 1,
  roughness 0.05, base colour that of polished aluminium).

It writes the object's mask (``edit_mask.png``, white where a pixel's
centre sees the object) and ``edit.json`` (the object, the new albedo in
linear and gamma-encoded RGB as matflow's ``edit`` stage takes it, the
metal's base colour and roughness, the mask's pixel count, the seconds).

    python3 crates/bench/scripts/edit_truths.py --validation out/kinds [--only K ...]
        [--threads 2] [--spp N]

Scenes whose edit files exist are kept unless --force.
"""

import argparse
import colorsys
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import relight_scenes as rs  # noqa: E402

METAL = {"albedo": [0.913, 0.922, 0.924], "roughness": 0.05}


def kind_order(index):
    """The --kinds list the set was made with, from its first half's scenes
    (each half cycles through it)."""
    kinds = index.get("kinds") or {}
    if not kinds:
        return ["closed"]
    order = []
    for name in index["tuning"]:
        k = kinds[name]
        if k in order:
            break
        order.append(k)
    return order


def open_set(a):
    """The set's index, Mitsuba (a.threads, a.llvm), its scene names in
    order and its kinds' order."""
    with open(os.path.join(a.validation, "validation.json")) as fh:
        index = json.load(fh)
    mi, dr = rs.start_mitsuba(a)
    return index, mi, dr, index["tuning"] + index["heldback"], kind_order(index)


def redraw(index, k, order, d):
    """Scene k of the set drawn again (parameters, geometry, camera), and
    its stored scene.json, which the draw must reproduce."""
    with open(os.path.join(d, "scene.json")) as fh:
        stored = json.load(fh)
    n = len(index["tuning"]) + len(index["heldback"])
    kind, jh = rs.scene_kind(k, n, order)
    P, geo, c2w = rs.draw_scene(index["seed"], k, n, kind=kind, jh=None if order == ["closed"] else jh)
    if P["objects"] != stored["objects"]:
        sys.exit(f"{d}: the draw does not reproduce scene.json (another generator version?)")
    return P, geo, c2w, stored


def object_ids(mi, dr, scene, size):
    """Per pixel centre, the id (Mitsuba shape id string) of the first hit,
    "" for the sky; matflow's camera, as relight_scenes.pixel_truth."""
    f = size * 0.5 / np.tan(np.radians(rs.FOV_X_DEG / 2))
    c = (size - 1) / 2
    jj, ii = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    d = np.stack([(ii - c) / f, -(jj - c) / f, -np.ones_like(ii, float)], -1).reshape(-1, 3)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    ids = np.array(dr.reinterpret_array(mi.UInt32, si.shape), dtype=np.int64)
    out = np.full(size * size, "", dtype=object)
    for sh in scene.shapes():
        sid = int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh)))[0])
        out[valid & (ids == sid)] = sh.id()
    return out.reshape(size, size)


def object_of(shape_id, objects):
    """The object a Mitsuba shape id belongs to (obj3, obj3_cap, obj3leg-1-1)."""
    for o in objects:
        n = o["name"]
        if shape_id == n or shape_id.startswith(n + "_") or shape_id.startswith(n + "leg"):
            return n
    return None


def new_albedo(old):
    """A clearly different colour: the hue turned by half a turn."""
    h, s, v = colorsys.rgb_to_hsv(*[float(x) ** (1 / 2.2) for x in old])
    s = max(s, 0.5)
    v = min(max(v, 0.3), 0.8)
    return rs.srgb_to_linear(colorsys.hsv_to_rgb((h + 0.5) % 1.0, s, v)).tolist()


def edited_geometry(geo, name, material):
    """`geo` with every shape of object `name` given `material`."""
    out = rs.Geometry()
    for (sname, kind, prm, m) in geo.shapes:
        mine = sname == name or sname.startswith(name + "leg")
        out.shapes.append((sname, kind, prm, material if mine else m))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--validation", required=True)
    ap.add_argument("--only", type=int, nargs="+")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp", type=int, help="default: the set's")
    ap.add_argument("--pass-spp", type=int, default=32)
    ap.add_argument("--llvm")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    index, mi, dr, names, order = open_set(a)
    n = len(names)
    spp = a.spp or index["spp"]
    size = index["size"]
    for k in range(n):
        name = f"scene-{k:02d}"
        if a.only is not None and k not in a.only:
            continue
        d = os.path.join(a.validation, name)
        if os.path.exists(os.path.join(d, "edit.json")) and not a.force:
            rs.log(f"edit_truths: {name} exists, kept")
            continue
        t0 = time.perf_counter()
        P, geo, c2w, stored = redraw(index, k, order, d)
        kind = P["kind"]
        w2c = np.linalg.inv(c2w)
        rot = c2w[:3, :3]
        tmp = os.path.join(d, "mitsuba-edit")
        os.makedirs(tmp, exist_ok=True)
        env_path = os.path.join(tmp, "capture_sky.exr")
        rs.write_exr(mi, env_path, rs.sky_image(P["sky"], rot, rs.ENV_W, rs.ENV_H))
        shapes, mats = rs.mitsuba_shapes(mi, geo, w2c, tmp)
        scene = rs.build_scene(mi, shapes, env_path, P["lamps"], w2c, size, a.pass_spp)
        ids = object_ids(mi, dr, scene, size)
        counts = {}
        for o in P["objects"]:
            if o["material"]["kind"] == "metal":
                continue
            counts[o["name"]] = int(sum(object_of(s, [o]) == o["name"] for s in ids.ravel() if s))
        if not counts or max(counts.values()) < 0.01 * size * size:
            rs.log(f"edit_truths: {name}: no non-metal object covers 1 % of the view, skipped")
            continue
        target = max(counts, key=counts.get)
        obj = next(o for o in P["objects"] if o["name"] == target)
        mask = np.vectorize(lambda s: bool(s) and object_of(s, [obj]) == target)(ids)
        exposure = stored["exposure"]
        albedo = new_albedo(obj["material"]["albedo"])
        edits = {
            "albedo": rs.mat(albedo, obj["material"]["roughness"], obj["material"]["metallic"], obj["material"]["kind"]),
            "metal": rs.mat(METAL["albedo"], METAL["roughness"], 1.0, "metal"),
        }
        seed = ((index["seed"] % 1000) * 1000 + k) * 10 + 7
        for tag, m in edits.items():
            g = edited_geometry(geo, target, m)
            sh, _ = rs.mitsuba_shapes(mi, g, w2c, tmp)
            sc = rs.build_scene(mi, sh, env_path, P["lamps"], w2c, size, a.pass_spp)
            img, _, _ = rs.render(mi, sc, spp, a.pass_spp, seed)
            rs.write_exr(mi, os.path.join(d, "ground_truth", f"edit_{tag}.exr"), img * exposure)
        from PIL import Image

        Image.fromarray((mask * 255).astype(np.uint8)).save(os.path.join(d, "edit_mask.png"))
        info = {"object": target, "shape": obj["shape"], "kind": obj["material"]["kind"],
                "old_albedo": obj["material"]["albedo"], "albedo": albedo,
                "albedo_gamma": [float(x) for x in np.clip(np.asarray(albedo), 0, 1) ** (1 / 2.2)],
                "metal": METAL, "mask_pixels": int(mask.sum()), "spp": spp,
                "seconds": round(time.perf_counter() - t0, 1)}
        with open(os.path.join(d, "edit.json"), "w") as fh:
            json.dump(info, fh, indent=1)
        import shutil

        shutil.rmtree(tmp)
        rs.log(f"edit_truths: {name} ({kind}): {target} ({obj['shape']}, {mask.sum()} px) in {info['seconds']} s")


if __name__ == "__main__":
    main()
