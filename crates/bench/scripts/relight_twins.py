#!/usr/bin/env python3
"""How much of relighting does one photo determine? Twin rooms rendered by
Mitsuba 3 (benchmark only, like crates/bench/scripts/relight_scenes.py).

For each room of the validation set (the same draw as relight_scenes.py:
--seed, --scenes, the same index k) three variants differ only in the wall
behind the camera, which no view of the set can show (every camera ray
points away from it; the script checks that the views are identical):

* ``closed``: the room's windows in that wall removed (for all but three
  rooms of the set, scene-03, -07 and -12, this is the room as generated);
* ``end A`` / ``end B``: ``closed`` with one window of 1.4 m x 1.4 m (narrower
  in a narrow room) at one end of that wall or at the other.

Every other draw is the room's own: size, furniture, materials, the capture
sky and lamps, the two new skies. With ``--behind dark`` the capture sky is
black in every direction from which light could come in through that wall
(world directions with z > 0: a building right behind the room, or a
photo taken where nothing lights that side); the new skies are the room's.
Then no capture light enters through the back window, and the variants'
photos differ only by the light the window lets out of the room.

Each variant is rendered as the set is: the capture image scaled to the
room's exposure target by its own level (what a method is given), and each
new sky at the scale that brings the ``closed`` variant's relit image to
the room's target (the same sky for every variant: a method is given the
sky, not the image). All variants use the same sample streams, so little
of their differences is noise (paths part only where the variants do).

The point is a bound. For two rooms A and B and any prediction R of a
relit image, the triangle inequality on the root-mean-square error of the
gamma-encoded images gives max(RMSE(R, A), RMSE(R, B)) >= RMSE(A, B) / 2,
i.e. the worse of the two PSNRs is at most PSNR(A, B) + 6.02 dB. Twins
whose photos are alike (and whose predictions are the same, their views
being identical) get the same answer from any method, so none can relight
both better than that bound.

The script checks that the variants' views are identical (depth and
materials at every pixel centre, and normals but at ties on edges: the
change is unseen) and writes
``twins.json`` (per room: the PSNR between the variants' photos, between
their relit images, the bound, and each image's noise floor) and the
images (``scene-KK/VARIANT_{photo,relit,relit_2}.exr``) under --out.

The bound printed by ``--table`` is conservative: before it is taken, the
two relit images' own Monte Carlo error (their noise floors, from two
halves of the samples) is taken out of their difference as if it were
independent, which it is not (the variants share sample streams), so the
difference left is smaller than the rooms' true one and the bound higher.

    python3 crates/bench/scripts/relight_twins.py --table out/relight-twins [out/relight-twins-dark]
    python3 crates/bench/scripts/relight_twins.py --figure out/relight-twins-dark scene-11 2 docs/figures/twins-scene-11.jpg
    python3 crates/bench/scripts/relight_twins.py --out out/relight-twins [--only 8 9 ...]
        [--size 256] [--spp 128] [--seed 2026] [--scenes 16] [--behind sky|dark]
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
import relight_scenes as rs  # noqa: E402

BACK = 3  # relight_scenes' wall index of the wall behind the camera (z = D)
VARIANTS = ["closed", "end A", "end B"]


def back_windows(variant):
    """An edit_windows for relight_scenes.draw_scene: the room's windows
    without those in the back wall, plus the variant's window there."""

    def edit(windows, room):
        kept = [w for w in windows if w[0] != BACK]
        if variant == "closed":
            return kept
        length = room["width"]  # the back wall runs along x
        ww = min(1.4, (length - 0.9) / 2)
        t0 = 0.8
        t1 = min(t0 + 1.4, room["height"] - 0.2)
        s0 = 0.3 if variant == "end A" else length - 0.3 - ww
        return kept + [(BACK, s0, s0 + ww, t0, t1)]

    return edit


# The worse of two rooms' PSNRs exceeds theirs by at most this (see the top).
TRIANGLE_DB = 20.0 * math.log10(2.0)


def psnr_of(mse):
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def psnr(a, b):
    """PSNR as matflow reports it: clipped to [0, 1], gamma 2.2."""
    return psnr_of(float(np.mean((rs.gamma(a) - rs.gamma(b)) ** 2)))


def render_variant(mi, dr, a, k, variant):
    P, geo, c2w = rs.draw_scene(a.seed, k, a.scenes, edit_windows=back_windows(variant))
    w2c = np.linalg.inv(c2w)
    rot = c2w[:3, :3]
    tmp = os.path.join(a.out, f"scene-{k:02d}", "mitsuba-" + variant.replace(" ", "-"))
    os.makedirs(tmp, exist_ok=True)
    shapes, mats = rs.mitsuba_shapes(mi, geo, w2c, tmp)
    env_path = os.path.join(tmp, "capture_sky.exr")
    env = rs.sky_image(P["sky"], rot, rs.ENV_W, rs.ENV_H)
    if a.behind == "dark":
        d_cam, _ = rs.envmap_directions(rs.ENV_W, rs.ENV_H)
        behind = (d_cam @ rot.T)[:, 2] > 0.0
        env = np.where(behind.reshape(rs.ENV_H, rs.ENV_W, 1), 0.0, env).astype(np.float32)
    rs.write_exr(mi, env_path, env)
    scene = rs.build_scene(mi, shapes, env_path, P["lamps"], w2c, a.size, a.pass_spp)
    truth = rs.pixel_truth(mi, dr, scene, mats, a.size)
    seed = ((a.seed % 1000) * 1000 + k) * 10
    img, ha, hb = rs.render(mi, scene, a.spp, a.pass_spp, seed)
    exposure = P["exposure_target_mean"] / rs.level(img, truth["valid"])
    out = {"P": P, "truth": truth, "photo": img * exposure, "floor": [rs.noise_floor_psnr(ha, hb, exposure)],
           "relit_raw": []}
    for j, sky in enumerate(P["relight_skies"]):
        rpath = os.path.join(tmp, f"relight_sky_{j}.exr")
        rs.write_exr(mi, rpath, rs.sky_image(sky, rot, rs.ENV_W, rs.ENV_H))
        rscene = rs.build_scene(mi, shapes, rpath, [], w2c, a.size, a.pass_spp)
        rimg, ha, hb = rs.render(mi, rscene, a.spp, a.pass_spp, seed + j + 1)
        out["relit_raw"].append((rimg, ha, hb))
    return out


def same_view(t0, t1):
    """Identical depth and materials at every pixel centre. Shading normals
    may differ where a ray meets an edge exactly (Mitsuba's BVH, built over
    other triangles, breaks the tie another way): at most 0.05 % of pixels."""
    if not all(np.array_equal(t0[key], t1[key]) for key in ("z", "albedo", "roughness", "metallic")):
        return False
    differ = np.any(t0["normal"] != t1["normal"], axis=-1)
    return int(differ.sum()) <= max(1, differ.size // 2000)


def mse_of(p):
    return 10.0 ** (-p / 10.0)


def conservative_bound(room, pair, j):
    """The worse twin's best possible relight PSNR under sky j, with both
    relit images' noise taken out of their difference (see the top)."""
    n1, n2 = pair.split("|")
    floors = room["noise_floor"]
    mse = mse_of(room["pairs"][pair]["relit"][j]) - mse_of(floors[n1][j + 1]) - mse_of(floors[n2][j + 1])
    return psnr_of(max(mse, 0.0)) + TRIANGLE_DB


def table(folders):
    """Markdown: per room and new sky the tightest conservative bound over
    the three pairs, with how far apart that pair's photos are ("—" where
    the variants' relit images differ by less than their own noise); then
    per half."""
    for folder in folders:
        r = json.load(open(os.path.join(folder, "twins.json")))
        print(f"\n{folder}: capture sky behind the room {r.get('behind', 'sky')}, {r['size']}², {r['spp']} spp\n")
        print("| room | half | capture sky | new skies | photo noise floor | new sky 1: bound (photos apart) | "
              "new sky 2: bound (photos apart) |")
        print("|---|---|---|---|---|---|---|")
        halves = {}
        for name in sorted(r["rooms"]):
            room = r["rooms"][name]
            floor = min(f[0] for f in room["noise_floor"].values())
            cells, bounds = [], []
            for j in range(2):
                pair = min(room["pairs"], key=lambda pa: conservative_bound(room, pa, j))
                b = conservative_bound(room, pair, j)
                bounds.append(b)
                cells.append(f"{b:.2f} dB ({room['pairs'][pair]['photo']:.2f} dB)" if b < 100 else "—")
            halves.setdefault(room["split"], []).append(bounds)
            print(f"| {name} | {room['split']} | {room['sky']} | {' / '.join(room['relight_skies'])} | "
                  f"{floor:.2f} dB | {cells[0]} | {cells[1]} |")
        for half, bs in sorted(halves.items()):
            flat = [b for pair in bs for b in pair]
            print(f"\n{half}: {len(bs)} rooms; bound over (room, sky) median {float(np.median(flat)):.2f} dB, "
                  f"worst {min(flat):.2f} dB; under 25 dB: {sum(b < 25 for b in flat)} of {len(flat)}, "
                  f"under 30 dB: {sum(b < 30 for b in flat)}")


def figure(folder, room, sky, out):
    """The three variants' photos over their images under new sky `sky`
    (1 or 2), sRGB gamma 2.2, as one JPEG."""
    drjit_llvm.choose(None)
    import mitsuba as mi
    from PIL import Image

    mi.set_variant("scalar_rgb")
    kinds = ["photo", "relit" if sky == "1" else f"relit_{sky}"]
    rows = [np.concatenate([np.array(mi.Bitmap(os.path.join(folder, room, f"{v.replace(' ', '-')}_{kind}.exr")))
                            for v in VARIANTS], 1) for kind in kinds]
    img = (rs.gamma(np.concatenate(rows, 0)) * 255.0 + 0.5).astype(np.uint8)
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    Image.fromarray(img).save(out, quality=88)


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--table":
        table(sys.argv[2:])
        return
    if len(sys.argv) == 6 and sys.argv[1] == "--figure":
        figure(*sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    rs.add_render_args(ap, 256, 128)
    ap.add_argument("--behind", choices=["sky", "dark"], default="sky",
                    help="the capture sky behind the room: the room's own, or black (see above)")
    ap.add_argument("--only", type=int, nargs="+", help="these room indices (default: the held-back half)")
    a = ap.parse_args()
    mi, dr = rs.start_mitsuba(a)
    rooms = a.only if a.only is not None else list(range(a.scenes // 2, a.scenes))
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "twins.json")
    report = json.load(open(path)) if os.path.exists(path) else {}
    report.update({"generator": "crates/bench/scripts/relight_twins.py", "seed": a.seed, "scenes": a.scenes, "size": a.size,
                   "spp": a.spp, "behind": a.behind, "pairs": ["closed|end A", "closed|end B", "end A|end B"]})
    report.setdefault("rooms", {})
    for k in rooms:
        t_start = time.perf_counter()
        P0, _, _ = rs.draw_scene(a.seed, k, a.scenes)
        if P0["room"]["missing_wall"] == BACK:
            rs.log(f"relight_twins: scene-{k:02d} has no wall behind the camera, skipped")
            continue
        v = {name: render_variant(mi, dr, a, k, name) for name in VARIANTS}
        for name in VARIANTS[1:]:
            if not same_view(v["closed"]["truth"], v[name]["truth"]):
                sys.exit(f"relight_twins: scene-{k:02d}: variant {name!r} changes the view")
        # One scale per new sky, the closed room's, for every variant.
        scales = [P0["relit_target_means"][j] / rs.level(v["closed"]["relit_raw"][j][0], v["closed"]["truth"]["valid"])
                  for j in range(len(P0["relight_skies"]))]
        d = os.path.join(a.out, f"scene-{k:02d}")
        for name in VARIANTS:
            x = v[name]
            x["relit"] = [r[0] * s for r, s in zip(x["relit_raw"], scales)]
            x["floor"] += [rs.noise_floor_psnr(r[1], r[2], s) for r, s in zip(x["relit_raw"], scales)]
            tag = name.replace(" ", "-")
            rs.write_exr(mi, os.path.join(d, f"{tag}_photo.exr"), x["photo"])
            for j, r in enumerate(x["relit"]):
                rs.write_exr(mi, os.path.join(d, f"{tag}_relit{'' if j == 0 else f'_{j + 1}'}.exr"), r)
        pairs = {}
        for pa in report["pairs"]:
            n1, n2 = pa.split("|")
            ph = psnr(v[n1]["photo"], v[n2]["photo"])
            rl = [psnr(r1, r2) for r1, r2 in zip(v[n1]["relit"], v[n2]["relit"])]
            pairs[pa] = {"photo": ph, "relit": rl, "bound": [x + TRIANGLE_DB for x in rl]}
        report["rooms"][f"scene-{k:02d}"] = {
            "split": P0["split"], "sky": P0["sky"]["type"], "relight_skies": [s["type"] for s in P0["relight_skies"]],
            "lamps": len(P0["lamps"]), "back_windows_generated": sum(1 for w in P0["windows"] if w["wall"] == BACK),
            "noise_floor": {name: v[name]["floor"] for name in VARIANTS}, "pairs": pairs,
            "seconds": round(time.perf_counter() - t_start, 1)}
        with open(path, "w") as fh:
            json.dump(report, fh, indent=1)
        worst = min(pairs.values(), key=lambda p: min(p["relit"]))
        rs.log(f"relight_twins: scene-{k:02d} photos {min(p['photo'] for p in pairs.values()):.2f}-"
               f"{max(p['photo'] for p in pairs.values()):.2f} dB apart, relit down to "
               f"{min(worst['relit']):.2f} dB (bound {min(worst['bound']):.2f} dB) "
               f"in {report['rooms'][f'scene-{k:02d}']['seconds']} s")
        for name in VARIANTS:
            shutil.rmtree(os.path.join(d, "mitsuba-" + name.replace(" ", "-")), ignore_errors=True)


if __name__ == "__main__":
    main()
