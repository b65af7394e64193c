#!/usr/bin/env python3
"""Generate matflow's relighting validation set with Mitsuba 3.

Benchmark only: Mitsuba is never a dependency of matflow. The point of the
set is that the renderer that made the truth is not the one being evaluated,
and that the scenes are unlike the ones matflow's routes were tuned on.

Every scene is a furnished room seen from inside, written as a matflow
bundle (camera at the origin looking down -z, +y up, 35 deg horizontal field
of view, 512x512 by default):

* the room: box-shaped, 3.5-7 m wide, 4-8 m deep, 2.5-3.2 m high, so its
  walls, ceiling and furniture continue outside the frame and behind the
  camera; coloured walls, a plank or tiled floor (glossy in some rooms), a
  white-ish ceiling (missing in one room of eight: a courtyard open to the
  sky);
* openings, in turn: one to three windows (the first in the front half of
  the room), or one or two large windows (half to 85 % of a wall), or a
  wall missing altogether (a loggia, an open-plan room) and at most one
  window; the sky lights the room through them and shows through them in
  view;
* furniture and objects: cabinets, tables on legs, spheres, cylinders; at
  least one metal (gold, copper, steel, aluminium or chrome, roughness
  0.05-0.5) and one glossy dielectric (roughness 0.05-0.4) per room, the
  rest diffuse or glossy or metal; some are cut by the image border;
* the capture light: a clear sky with a sun, an overcast sky or a low
  warm sun (in turn), with buildings on the horizon; in some rooms (j = 0,
  4, 8 ... of each half's j-th scene: every sky kind) also bright interior
  lamps (small spherical emitters near the ceiling);
* exposure: the capture image is scaled so that its level (the mean over
  the room's pixels, brightest 1 % clipped) is 0.12-0.35; the true envmap
  is scaled alike (the lamps are not part of it).

Materials are Mitsuba's ``principled`` BSDF (Burley diffuse, GGX specular,
alpha = roughness^2, specular 0.5, i.e. F0 = 0.04 on dielectrics): base
colour, roughness and metallic are the true maps. Light transport is
Mitsuba's ``path`` integrator, max_depth 8 (Russian roulette after 5),
Gaussian pixel filter, ``--spp`` samples (1024 by default) rendered in
passes of ``--pass-spp``.

Each bundle holds:

* ``gt_image.exr``: the capture image (linear RGB, exposure applied);
* ``depth.exr``: true camera-space z (0 where a window shows the sky);
* ``normalPred.exr``: true shading normals (camera space, +z to the camera);
* the degraded predictions, as MatNet's are degraded: ``albedoPred.exr`` is
  the true base colour blurred (Gaussian, sigma 1.5 px), times a per-channel
  gain in [0.75, 1.25], plus uniform noise of standard deviation 0.03,
  clamped to [0, 1]; ``roughnessPred.exr`` and ``metallicPred.exr`` are
  constants (roughness 0.4-0.7, metallic 0-0.15) as a network that cannot
  tell materials apart would predict;
* ``ground_truth/``: ``albedo.exr``, ``roughness.exr``, ``metallic.exr``,
  ``normal.exr`` (pixel-centre values), ``envmap.hdr`` (the capture sky at
  32x16, matflow's layout, exposure applied; ``envmap.exr`` is the same at
  1024x512, the light the capture was rendered with, less the lamps),
  ``lamps.json`` (the capture's lamps as matflow's point lights: camera
  space, intensity pi r^2 times radiance, exposure applied; empty without
  lamps), ``relight_envmap.exr`` and
  ``relight_envmap_2.exr`` (two new skies, 1024x512) with
  ``relit_image.exr`` and ``relit_image_2.exr``: the room under each new sky
  alone (lamps off), the sky scaled so that the image's level is 0.15-0.3;
* ``scene.json``: every parameter drawn, the split, the render settings,
  and ``noise_floor_psnr`` for the capture and the two relit images: the
  PSNR of each truth against its own noise-free limit, estimated from two
  independent halves of its samples (a perfect, noise-free prediction
  would score this against the stored truth).

With ``--kinds``, each half cycles through kinds of scene (``closed`` is
the room above; the others are drawn by ``draw_other_kind``): ``open``
rooms (a floor and one to three walls that continue past the frame,
nothing above or behind), ``stage`` (a raised platform and a back wall
that end near the frame's sides, a lower ground and the sky beyond) and
``outdoor`` (objects on a wide ground under the sky); validation.json
then names each scene's kind (``kinds``). E.g. six of each kind, three in
each half:

    python3 crates/bench/scripts/relight_scenes.py --out out/kinds --scenes 24 \
        --kinds closed open stage outdoor --size 256 --spp 256

Scene k is drawn from a generator seeded with (--seed, k). The first half
of the scenes (k < n/2) is the tuning half, the second half is held back:
no choice is made on it. ``validation.json`` at the top lists both halves.

    python3 crates/bench/scripts/relight_scenes.py --out out/relight-val [--scenes 16]
        [--spp 1024] [--size 512] [--only K ...] [--threads 2]
        [--kinds closed open stage outdoor]

Existing complete bundles are kept unless --force; a bundle is written to a
temporary folder and renamed when complete.
"""

import argparse
import colorsys
import json
import math
import os
import shutil
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import drjit_llvm  # noqa: E402

FOV_X_DEG = 35.0
ENV_W, ENV_H = 1024, 512
TRUTH_ENV_W, TRUTH_ENV_H = 32, 16
MAX_DEPTH = 8
RR_DEPTH = 5
GENERATOR_VERSION = 1


def log(*a):
    print(*a, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------
# Small linear algebra
# ----------------------------------------------------------------------------


def normalize(v):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def frame_matrix(c, u, v, n):
    """4x4 matrix mapping local (x, y, z, 1) to c + x u + y v + z n."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u, v, n, c
    return m


def srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def hsv(h, s, v):
    return srgb_to_linear(colorsys.hsv_to_rgb(h % 1.0, s, v))


# ----------------------------------------------------------------------------
# Materials
# ----------------------------------------------------------------------------

# Normal-incidence reflectance (linear RGB) of common metals.
METALS = {
    "gold": (1.000, 0.766, 0.336),
    "copper": (0.955, 0.638, 0.538),
    "steel": (0.560, 0.570, 0.580),
    "aluminium": (0.913, 0.922, 0.924),
    "chrome": (0.550, 0.556, 0.554),
}


def mat(albedo, roughness, metallic, kind):
    return {
        "albedo": [float(x) for x in np.clip(albedo, 0.0, 1.0)],
        "roughness": float(roughness),
        "metallic": float(metallic),
        "kind": kind,
    }


def draw_object_material(rng, kind):
    if kind == "metal":
        name = list(METALS)[rng.integers(len(METALS))]
        m = mat(METALS[name], rng.uniform(0.05, 0.5), 1.0, "metal")
        m["metal"] = name
        return m
    if kind == "glossy":
        return mat(hsv(rng.uniform(), rng.uniform(0.2, 0.8), rng.uniform(0.3, 0.9)),
                   rng.uniform(0.05, 0.4), 0.0, "glossy")
    return mat(hsv(rng.uniform(), rng.uniform(0.0, 0.7), rng.uniform(0.25, 0.9)),
               rng.uniform(0.6, 1.0), 0.0, "diffuse")


# ----------------------------------------------------------------------------
# Geometry: quads (as PLY meshes), boxes, spheres, cylinders
# ----------------------------------------------------------------------------


class Geometry:
    """Shapes in world space (y up), each with its own constant material."""

    def __init__(self):
        self.shapes = []  # (name, kind, params, material)

    def quads(self, name, quads, material):
        """quads: list of 4 corners each, counter-clockwise seen from the
        side the normal points to."""
        self.shapes.append((name, "mesh", {"quads": [np.asarray(q, float) for q in quads]}, material))

    def box(self, name, centre, half, yaw, material):
        """Axis-aligned box turned by yaw about +y: 12 triangles, outward."""
        c, s = math.cos(yaw), math.sin(yaw)
        ex = np.array([c, 0.0, -s]) * half[0]
        ey = np.array([0.0, 1.0, 0.0]) * half[1]
        ez = np.array([s, 0.0, c]) * half[2]
        centre = np.asarray(centre, float)
        quads = []
        for axis, (a, b) in ((ex, (ey, ez)), (ey, (ez, ex)), (ez, (ex, ey))):
            for sign in (1.0, -1.0):
                f = centre + sign * axis
                u, v = (a, b) if sign > 0 else (b, a)
                quads.append([f - u - v, f + u - v, f + u + v, f - u + v])
        self.quads(name, quads, material)

    def sphere(self, name, centre, radius, material):
        self.shapes.append((name, "sphere", {"centre": np.asarray(centre, float), "radius": radius}, material))

    def cylinder(self, name, base, radius, height, material):
        base = np.asarray(base, float)
        self.shapes.append((name, "cylinder", {"base": base, "radius": radius, "height": height}, material))


def wall_with_holes(origin, u_dir, v_dir, length, height, holes):
    """Quads of a rectangular wall (origin + s u + t v, s in [0, length],
    t in [0, height]) minus rectangular holes (s0, s1, t0, t1), by cutting
    it into a grid along every hole edge."""
    ss = sorted({0.0, length, *[h[0] for h in holes], *[h[1] for h in holes]})
    ts = sorted({0.0, height, *[h[2] for h in holes], *[h[3] for h in holes]})
    quads = []
    for i in range(len(ss) - 1):
        for j in range(len(ts) - 1):
            sm, tm = 0.5 * (ss[i] + ss[i + 1]), 0.5 * (ts[j] + ts[j + 1])
            if any(h[0] < sm < h[1] and h[2] < tm < h[3] for h in holes):
                continue
            p = lambda s, t: origin + s * u_dir + t * v_dir  # noqa: E731
            quads.append([p(ss[i], ts[j]), p(ss[i + 1], ts[j]), p(ss[i + 1], ts[j + 1]), p(ss[i], ts[j + 1])])
    return quads


# ----------------------------------------------------------------------------
# Skies (functions of the world direction, y up)
# ----------------------------------------------------------------------------


def sky_radiance(p, d):
    """Radiance (N x 3) of the sky `p` in world directions d (N x 3)."""
    dy = d[:, 1]
    up = np.clip(dy, 0.0, 1.0)[:, None]
    zen, hor = np.asarray(p["zenith"]), np.asarray(p["horizon"])
    if p["type"] == "overcast":
        # CIE overcast sky: luminance (1 + 2 sin(elevation)) / 3.
        L = hor[None, :] * ((1.0 + 2.0 * up) / 3.0)
    else:
        L = hor[None, :] + (zen - hor)[None, :] * np.sqrt(up)
    # Buildings and trees on the horizon.
    az = np.arctan2(d[:, 0], -d[:, 2])
    el = np.arcsin(np.clip(dy, -1.0, 1.0))
    for b in p["skyline"]:
        da = np.angle(np.exp(1j * (az - b["azimuth"])))
        inside = (np.abs(da) < b["half_width"]) & (el >= 0.0) & (el < b["height"])
        L = np.where(inside[:, None], np.asarray(b["colour"])[None, :], L)
    ground = np.asarray(p["ground"])[None, :] * np.ones_like(L)
    L = np.where((dy < 0.0)[:, None], ground, L)
    if p.get("sun"):
        s = p["sun"]
        sd = np.array(s["direction"])
        cosang = np.clip(d @ sd, -1.0, 1.0)
        ang = np.arccos(cosang)
        disk = (ang < s["radius"]).astype(float)[:, None]
        glow = np.exp(-ang / s["glow_width"])[:, None] * np.asarray(s["glow"])[None, :]
        L = L + disk * np.asarray(s["radiance"])[None, :] + glow * (dy > -0.05)[:, None]
    return L


def draw_sky(rng, kind):
    tint = rng.uniform(-0.08, 0.08)
    if kind == "overcast":
        level = rng.uniform(0.6, 1.4)
        base = np.array([1.0 - tint, 1.0, 1.0 + tint]) * level
        p = {"type": "overcast", "zenith": base.tolist(), "horizon": base.tolist(),
             "ground": (base * rng.uniform(0.1, 0.25) * np.array([0.9, 0.85, 0.7])).tolist()}
    else:
        sunset = kind == "sunset"
        zen = np.array([0.25, 0.45, 1.0]) * rng.uniform(0.5, 1.0)
        hor = (np.array([1.0, 0.6, 0.35]) if sunset else np.array([0.75, 0.85, 1.0])) * rng.uniform(0.6, 1.2)
        elev = math.radians(rng.uniform(3, 12) if sunset else rng.uniform(15, 65))
        azim = rng.uniform(0, 2 * math.pi)
        sd = [math.cos(elev) * math.sin(azim), math.sin(elev), -math.cos(elev) * math.cos(azim)]
        radius = math.radians(1.0)
        omega = 2 * math.pi * (1 - math.cos(radius))
        # Sun irradiance 4-15x pi times the zenith level.
        e_sun = rng.uniform(4, 15) * math.pi * float(np.mean(zen))
        colour = np.array([1.0, 0.55, 0.25]) if sunset else np.array([1.0, 0.95, 0.88])
        p = {"type": kind, "zenith": zen.tolist(), "horizon": hor.tolist(),
             "ground": (np.array([0.35, 0.3, 0.22]) * rng.uniform(0.15, 0.4) * np.mean(hor)).tolist(),
             "sun": {"direction": sd, "radius": radius, "radiance": (colour * e_sun / omega).tolist(),
                     "glow": (colour * rng.uniform(0.5, 2.0)).tolist(), "glow_width": rng.uniform(0.05, 0.15)}}
    p["skyline"] = []
    for _ in range(rng.integers(0, 7)):
        v = rng.uniform(0.05, 0.3) * float(np.mean(p["horizon"]))
        p["skyline"].append({"azimuth": rng.uniform(-math.pi, math.pi), "half_width": rng.uniform(0.05, 0.5),
                             "height": rng.uniform(0.03, 0.25),
                             "colour": (v * np.array(hsv(rng.uniform(), rng.uniform(0, 0.4), 1.0))).tolist()})
    return p


def envmap_directions(w, h):
    """Directions (in the map's own frame) of matflow's lat-long texels:
    column j at u = (j + 0.5) / w, row i at theta = pi i / (h - 1);
    u = atan2(d.x, -d.z) / 2 pi, v = acos(d.y) / pi (Mitsuba's layout)."""
    u = (np.arange(w) + 0.5) / w
    th = math.pi * np.arange(h) / max(h - 1, 1)
    phi = 2 * math.pi * u
    st, ct = np.sin(th)[:, None], np.cos(th)[:, None]
    d = np.stack([st * np.sin(phi)[None, :], ct * np.ones((1, w)), -st * np.cos(phi)[None, :]], axis=-1)
    return d.reshape(-1, 3), th


def sky_image(p, cam_to_world_rot, w, h):
    """The sky as matflow's envmap in the camera frame."""
    d_cam, _ = envmap_directions(w, h)
    d_world = d_cam @ cam_to_world_rot.T
    return sky_radiance(p, d_world).reshape(h, w, 3).astype(np.float32)


def downsample_env(img, w, h):
    """Solid-angle-weighted average of a lat-long map into w x h texels of
    matflow's layout (rows at theta = pi i / (h - 1))."""
    H, W, _ = img.shape
    _, th = envmap_directions(W, H)
    wt = np.maximum(np.sin(th), 1e-4)[:, None] * np.ones((1, W))
    row = np.clip(np.rint(th / math.pi * (h - 1)).astype(int), 0, h - 1)
    col = np.minimum((np.arange(W) * w) // W, w - 1)
    out = np.zeros((h, w, 3))
    acc = np.zeros((h, w))
    for i in range(H):
        np.add.at(out[row[i]], col, img[i] * wt[i][:, None])
        np.add.at(acc[row[i]], col, wt[i])
    return (out / np.maximum(acc, 1e-12)[:, :, None]).astype(np.float32)


# ----------------------------------------------------------------------------
# Scene drawing
# ----------------------------------------------------------------------------

SKY_KINDS = ["sun", "overcast", "sunset"]


def camera(P, cam_p, yaw, pitch):
    """The camera-to-world matrix of a camera at cam_p turned by yaw
    (about +y) and pitch, recorded in P["camera"]."""
    fwd = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), -math.cos(yaw) * math.cos(pitch)])
    right = normalize(np.cross(fwd, [0.0, 1.0, 0.0]))
    up = np.cross(right, fwd)
    P["camera"] = {"position": cam_p.tolist(), "yaw_deg": math.degrees(yaw), "pitch_deg": math.degrees(pitch),
                   "fov_x_deg": FOV_X_DEG}
    return frame_matrix(cam_p, right, up, -fwd)


SCENE_KINDS = ["closed", "open", "stage", "outdoor"]
KIND_STREAM = {"open": 1, "stage": 2, "outdoor": 3}


def draw_objects(rng, geo, cam_p, yaw, bounds, far):
    """Objects on the floor (y = 0) in front of the camera, some cut by the
    frame: their centres inside `bounds` (x0, x1, z0, z1, less the object's
    radius) at 1.6 to `far` from the camera; returns their parameters."""
    x0, x1, z0, z1 = bounds
    kinds = ["metal", "glossy"] + [str(rng.choice(["diffuse", "glossy", "metal"], p=[0.45, 0.3, 0.25]))
                                   for _ in range(rng.integers(2, 6))]
    placed = []  # (x, z, r)
    objects = []
    half_fov = math.radians(FOV_X_DEG / 2)
    for oi, kind in enumerate(kinds):
        m = draw_object_material(rng, kind)
        for _ in range(200):
            dist = rng.uniform(1.6, max(1.7, far))
            lat = rng.uniform(-1.15, 1.15) * math.tan(half_fov) * dist
            hf = np.array([math.sin(yaw), 0.0, -math.cos(yaw)])
            hr = np.array([math.cos(yaw), 0.0, math.sin(yaw)])
            p = cam_p + hf * dist + hr * lat
            shape = str(rng.choice(["box", "sphere", "cylinder", "table"], p=[0.3, 0.3, 0.25, 0.15]))
            r = {"box": 0.6, "sphere": 0.45, "cylinder": 0.3, "table": 0.8}[shape]
            if not (x0 + r < p[0] < x1 - r and z0 + r < p[2] < z1 - r):
                continue
            if any((p[0] - q[0]) ** 2 + (p[2] - q[1]) ** 2 < (r + q[2]) ** 2 for q in placed):
                continue
            placed.append((p[0], p[2], r))
            break
        else:
            continue
        name = f"obj{oi}"
        o = {"name": name, "shape": shape, "material": m, "position": [p[0], p[2]]}
        if shape == "box":
            half = [rng.uniform(0.2, 0.55), rng.uniform(0.2, 0.55), rng.uniform(0.18, 0.3)]
            ang = rng.uniform(-0.6, 0.6)
            geo.box(name, [p[0], half[1], p[2]], half, ang, m)
            o.update(half=half, yaw=ang)
        elif shape == "sphere":
            rad = rng.uniform(0.15, 0.42)
            geo.sphere(name, [p[0], rad, p[2]], rad, m)
            o.update(radius=rad)
        elif shape == "cylinder":
            rad, h = rng.uniform(0.08, 0.28), rng.uniform(0.25, 0.9)
            geo.cylinder(name, [p[0], 0.0, p[2]], rad, h, m)
            o.update(radius=rad, height=h)
        else:
            ht, hw, hd = rng.uniform(0.65, 0.8), rng.uniform(0.4, 0.75), rng.uniform(0.3, 0.5)
            ang = rng.uniform(-0.6, 0.6)
            geo.box(name, [p[0], ht - 0.02, p[2]], [hw, 0.02, hd], ang, m)
            c, s = math.cos(ang), math.sin(ang)
            leg_mat = mat(np.array(m["albedo"]) * 0.6, 0.7, m["metallic"], m["kind"])
            for sx in (-1, 1):
                for sz in (-1, 1):
                    lx, lz = sx * (hw - 0.04), sz * (hd - 0.04)
                    geo.box(f"{name}leg{sx}{sz}", [p[0] + c * lx + s * lz, (ht - 0.04) / 2, p[2] - s * lx + c * lz],
                            [0.025, (ht - 0.04) / 2, 0.025], ang, leg_mat)
            o.update(height=ht, half=[hw, hd], yaw=ang)
        objects.append(o)
    return objects


def draw_lighting(rng, P, jh, lamp_box=None):
    """The capture sky (sun, overcast, sunset in turn by `jh`), lamps under
    the ceiling of `lamp_box` (W, D, H) in some rooms, two new skies, the
    exposure targets and the predictions' degradation, into P."""
    sky_kind = SKY_KINDS[jh % 3]
    sky = draw_sky(rng, sky_kind)
    lamps = []
    if lamp_box is not None and jh % 3 == (jh // 3) % 3:
        W, D, H = lamp_box
        for _ in range(rng.integers(1, 3)):
            lamps.append({"position": [rng.uniform(0.5, W - 0.5), H - rng.uniform(0.3, 0.6), rng.uniform(0.5, D - 0.5)],
                          "radius": rng.uniform(0.06, 0.12),
                          "radiance": (np.array([1.0, 0.85, 0.65]) * rng.uniform(20, 60)
                                       * float(np.mean(sky["horizon"]))).tolist()})
    relights = [draw_sky(rng, SKY_KINDS[(SKY_KINDS.index(sky_kind) + j) % 3]) for j in (1, 2)]
    P["sky"], P["lamps"], P["relight_skies"] = sky, lamps, relights
    P["exposure_target_mean"] = rng.uniform(0.12, 0.35)
    P["relit_target_means"] = [rng.uniform(0.15, 0.3), rng.uniform(0.15, 0.3)]
    P["degrade"] = {"gain": rng.uniform(0.75, 1.25, size=3).tolist(), "blur_sigma_px": 1.5, "noise_std": 0.03,
                    "roughness": rng.uniform(0.4, 0.7), "metallic": rng.uniform(0.0, 0.15),
                    "noise_seed": int(rng.integers(0, 2**31))}


def draw_other_kind(seed, k, n, kind, jh):
    """A scene of a kind other than a closed room (draw_scene's own):

    * open: a floor and one to three walls (the one ahead always) that
      continue past the frame; nothing above (no ceiling) or behind the
      camera, which stands at or past the walls' open end;
    * stage: a raised platform (a box, its top the floor) and a back wall
      of its width, both ending near the frame's sides (within 0.85-1.1 of
      the half-width the view spans there), the wall's top in view; a
      distant lower ground and the sky beyond;
    * outdoor: objects on a wide ground plane under the sky, at times a
      low wall or a building block further off.

    Its own random stream ([seed, k, kind]); no lamps (daylight alone)."""
    if kind not in KIND_STREAM:
        raise ValueError(f"unknown scene kind {kind!r} (one of {SCENE_KINDS})")
    rng = np.random.default_rng([seed, k, KIND_STREAM[kind]])
    P = {"index": k, "seed": seed, "split": "tuning" if k < n // 2 else "heldback",
         "generator_version": GENERATOR_VERSION, "kind": kind}
    geo = Geometry()
    wall_col = hsv(rng.uniform(), rng.uniform(0.05, 0.45), rng.uniform(0.45, 0.85))
    wall_rough = rng.uniform(0.7, 1.0)
    tan_h = math.tan(math.radians(FOV_X_DEG / 2))
    floor_col = hsv(rng.uniform(0.04, 0.12), rng.uniform(0.2, 0.6), rng.uniform(0.3, 0.7)) if rng.uniform() < 0.6 \
        else hsv(rng.uniform(), rng.uniform(0.0, 0.3), rng.uniform(0.25, 0.8))
    floor_rough = rng.uniform(0.3, 0.9)

    def floor_quads(name, x0, x1, z0, z1, col, rough, y=0.0, step=None):
        """A floor in two tones (tiles or strips), so it has texture."""
        step = step or rng.uniform(0.4, 1.0)
        tones = [col, col * rng.uniform(0.7, 0.9)]
        groups = {0: [], 1: []}
        xs = np.arange(x0, x1, step).tolist() + [x1]
        zs = np.arange(z0, z1, step).tolist() + [z1]
        for i in range(len(xs) - 1):
            for j in range(len(zs) - 1):
                a, b, c, d = xs[i], xs[i + 1], zs[j], zs[j + 1]
                groups[(i + j) % 2].append([[a, y, c], [a, y, d], [b, y, d], [b, y, c]])
        for g, qs in groups.items():
            geo.quads(f"{name}{g}", qs, mat(tones[g], rough, 0.0, "floor"))

    if kind == "open":
        W, D, H = rng.uniform(4.0, 8.0), rng.uniform(4.0, 8.0), rng.uniform(2.2, 3.5)
        cam_p = np.array([rng.uniform(0.35, 0.65) * W, rng.uniform(1.1, 1.7), D + rng.uniform(-0.3, 2.0)])
        yaw, pitch = math.radians(rng.uniform(-25, 25)), math.radians(rng.uniform(-22, 0))
        sides = [[], [1], [2], [1, 2]][int(rng.integers(0, 4))]
        P["room"] = {"width": W, "depth": D, "height": H, "ceiling": False, "walls": [0] + sides}
        # Walls: 0 ahead (z = 0), 1 left (x = 0), 2 right (x = W), from
        # z = 0 to z = D; the floor runs on past them and behind the camera.
        geo.quads("wall0", wall_with_holes(np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]),
                                           W, H, []), mat(wall_col, wall_rough, 0.0, "wall"))
        if 1 in sides:
            geo.quads("wall1", wall_with_holes(np.array([0.0, 0, D]), np.array([0.0, 0, -1]),
                                               np.array([0.0, 1, 0]), D, H, []),
                      mat(wall_col, wall_rough, 0.0, "wall"))
        if 2 in sides:
            geo.quads("wall2", wall_with_holes(np.array([W, 0, 0]), np.array([0.0, 0, 1]),
                                               np.array([0.0, 1, 0]), D, H, []),
                      mat(wall_col * rng.uniform(0.8, 1.0), wall_rough, 0.0, "wall"))
        floor_quads("floor", -6.0, W + 6.0, 0.0, D + 8.0, floor_col, floor_rough)
        bounds, far = (0.0, W, 0.0, D), cam_p[2] - 0.8
    elif kind == "stage":
        zc, hc = rng.uniform(4.0, 8.0), rng.uniform(0.3, 1.2)
        yaw, pitch = math.radians(rng.uniform(-8, 8)), math.radians(rng.uniform(-12, 0))
        cam_p = np.array([rng.uniform(-0.3, 0.3), hc, zc])
        half_w = rng.uniform(0.85, 1.1) * tan_h * zc
        Ds = rng.uniform(0.45, 0.8) * zc
        # The wall's top in view: below the top of the frame at the wall.
        top = hc + math.tan(math.radians(FOV_X_DEG / 2) + pitch) * zc
        Hs = max(1.2, rng.uniform(0.55, 0.9) * top)
        drop = rng.uniform(0.6, 1.2)
        P["room"] = {"width": 2 * half_w, "depth": Ds, "height": Hs, "ceiling": False, "stage_height": drop}
        geo.quads("wall0", wall_with_holes(np.array([-half_w, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]),
                                           2 * half_w, Hs, []), mat(wall_col, wall_rough, 0.0, "wall"))
        # The platform: its top the floor, its front and sides down to the
        # ground; the ground far and wide below.
        floor_quads("floor", -half_w, half_w, 0.0, Ds, floor_col, floor_rough)
        side = mat(floor_col * 0.6, 0.8, 0.0, "wall")
        geo.quads("platform", [[[-half_w, -drop, Ds], [half_w, -drop, Ds], [half_w, 0, Ds], [-half_w, 0, Ds]],
                               [[half_w, -drop, Ds], [half_w, -drop, 0], [half_w, 0, 0], [half_w, 0, Ds]],
                               [[-half_w, -drop, 0], [-half_w, -drop, Ds], [-half_w, 0, Ds], [-half_w, 0, 0]]], side)
        ground = hsv(rng.uniform(0.05, 0.35), rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.45))
        geo.quads("ground", [[[-80.0, -drop, -80.0], [-80.0, -drop, 80.0], [80.0, -drop, 80.0],
                              [80.0, -drop, -80.0]]], mat(ground, 0.95, 0.0, "ground"))
        bounds, far = (-half_w, half_w, 0.0, Ds), zc - 0.8
    else:
        cam_p = np.array([0.0, rng.uniform(1.2, 1.8), 0.0])
        yaw, pitch = math.radians(rng.uniform(-30, 30)), math.radians(rng.uniform(-25, -4))
        P["room"] = {"ceiling": False}
        ground = hsv(rng.uniform(0.05, 0.35), rng.uniform(0.1, 0.6), rng.uniform(0.2, 0.6))
        floor_quads("ground", -60.0, 60.0, -60.0, 60.0, ground, rng.uniform(0.6, 1.0), step=rng.uniform(1.0, 3.0))
        if rng.uniform() < 0.5:
            # A building block or a low wall further off.
            d, ang = rng.uniform(10.0, 25.0), yaw + rng.uniform(-0.4, 0.4)
            c = np.array([math.sin(ang) * d, 0.0, -math.cos(ang) * d])
            half = [rng.uniform(2.0, 6.0), rng.uniform(0.5, 5.0), rng.uniform(1.0, 4.0)]
            geo.box("block", [c[0], half[1], c[2]], half, rng.uniform(-0.5, 0.5),
                    mat(hsv(rng.uniform(), rng.uniform(0.0, 0.3), rng.uniform(0.4, 0.8)), 0.9, 0.0, "wall"))
            P["room"]["block"] = {"centre": c.tolist(), "half": half}
        bounds, far = (-12.0, 12.0, -12.0, 12.0), 8.0
    c2w = camera(P, cam_p, yaw, pitch)
    P["windows"] = []
    P["objects"] = draw_objects(rng, geo, cam_p, yaw, bounds, far)
    draw_lighting(rng, P, jh)
    return P, geo, c2w


def draw_scene(seed, k, n, edit_windows=None, kind="closed", jh=None):
    """Scene k of n: its parameters P, its geometry and its camera-to-world
    matrix. `kind` is the kind of scene (SCENE_KINDS; closed rooms are this
    function's own draw, the others draw_other_kind's), `jh` the scene's
    place among its half's scenes of that kind (default: its place in its
    half). `edit_windows`, when given, maps the drawn list of windows to
    another (crates/bench/scripts/relight_twins.py: rooms that differ only where the camera
    cannot see); every other draw is unchanged by it."""
    # The halves get the same mixture of capture skies, lamps and open
    # courtyards: jh is the scene's place in its half.
    if jh is None:
        jh = k % max(1, n // 2)
    if kind != "closed":
        return draw_other_kind(seed, k, n, kind, jh)
    rng = np.random.default_rng([seed, k])
    P = {"index": k, "seed": seed, "split": "tuning" if k < n // 2 else "heldback",
         "generator_version": GENERATOR_VERSION, "kind": "closed"}
    W, D, H = rng.uniform(3.5, 7.0), rng.uniform(4.0, 8.0), rng.uniform(2.5, 3.2)
    has_ceiling = jh % 8 != 5
    P["room"] = {"width": W, "depth": D, "height": H, "ceiling": bool(has_ceiling)}
    # Camera near the back wall (z = D) looking towards the front wall (z = 0).
    cam_p = np.array([rng.uniform(0.35, 0.65) * W, rng.uniform(1.1, 1.7), D - rng.uniform(0.4, 1.2)])
    yaw = math.radians(rng.uniform(-35, 35))
    pitch = math.radians(rng.uniform(-25, -3))
    c2w = camera(P, cam_p, yaw, pitch)

    wall_col = hsv(rng.uniform(), rng.uniform(0.05, 0.45), rng.uniform(0.5, 0.85))
    accent = rng.uniform() < 0.4
    accent_col = hsv(rng.uniform(), rng.uniform(0.2, 0.6), rng.uniform(0.35, 0.75))
    wall_rough = rng.uniform(0.7, 1.0)
    geo = Geometry()

    # Windows: (wall, s0, s1, t0, t1); wall 0 front (z=0), 1 left (x=0),
    # 2 right (x=W), 3 back (z=D, behind the camera).
    lengths = [W, D, D, W]
    windows = []
    # How open the room is, in turn: small windows, large windows, or a
    # wall missing altogether (a loggia, an open-plan room).
    openness = ["small windows", "large windows", "open wall", "small windows", "large windows",
                "large windows", "open wall", "small windows"][jh % 8]
    missing = int(rng.integers(1, 4)) if openness == "open wall" else -1
    n_win = {"small windows": int(rng.integers(1, 4)), "large windows": int(rng.integers(1, 3)),
             "open wall": int(rng.integers(0, 2))}[openness]
    for i in range(n_win):
        wall = int(rng.choice([0, 1, 2])) if i == 0 else int(rng.integers(0, 4))
        if wall == missing or any(w_[0] == wall for w_ in windows):
            continue
        L = lengths[wall]
        if openness == "large windows":
            ww = rng.uniform(0.5, 0.85) * L
            s0 = rng.uniform(0.1, 0.9) * (L - ww)
            t0 = rng.uniform(0.3, 0.8)
            t1 = H - rng.uniform(0.15, 0.4)
            windows.append((wall, s0, s0 + ww, t0, t1))
            continue
        ww = min(rng.uniform(1.0, 2.4), L - 0.6)
        if wall in (1, 2) and i == 0:
            # In the front half of the side wall (near the front wall z=0):
            # side walls run from z=0 (s=0) to z=D (s=D).
            s0 = rng.uniform(0.3, max(0.31, D / 2 - ww))
        else:
            s0 = rng.uniform(0.3, L - 0.3 - ww)
        t0 = rng.uniform(0.4, 0.9)
        t1 = min(t0 + rng.uniform(1.0, 1.8), H - 0.2)
        windows.append((wall, s0, s0 + ww, t0, t1))
    if edit_windows is not None:
        windows = edit_windows(windows, {"width": W, "depth": D, "height": H, "missing_wall": missing})
    P["room"]["openness"] = openness
    P["room"]["missing_wall"] = missing
    P["windows"] = [{"wall": w_[0], "s": [w_[1], w_[2]], "t": [w_[3], w_[4]]} for w_ in windows]

    walls = [
        (np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), W),  # front, normal +z
        (np.array([0.0, 0, D]), np.array([0.0, 0, -1]), D),  # left x=0, normal +x
        (np.array([W, 0, 0]), np.array([0.0, 0, 1]), D),  # right x=W, normal -x
        (np.array([W, 0, D]), np.array([-1.0, 0, 0]), W),  # back, normal -z
    ]
    vdir = np.array([0.0, 1, 0])
    for wi, (o, u, L) in enumerate(walls):
        if wi == missing:
            continue
        holes = []
        for w_ in windows:
            if w_[0] != wi:
                continue
            s0, s1 = w_[1], w_[2]
            if wi == 1:  # left wall runs from z=D to z=0; s measured from z=0
                s0, s1 = L - w_[2], L - w_[1]
            holes.append((s0, s1, w_[3], w_[4]))
        m = mat(accent_col if (accent and wi == 0) else wall_col, wall_rough, 0.0, "wall")
        geo.quads(f"wall{wi}", wall_with_holes(o, u, vdir, L, H, holes), m)
        # Window reveals (the wall's thickness), so the openings read as windows.
        for (s0, s1, t0, t1) in holes:
            n = np.cross(u, vdir)
            t = 0.15
            a, b = o + s0 * u, o + s1 * u
            rev = []
            for (p0, p1) in ((a + t0 * vdir, b + t0 * vdir), (b + t1 * vdir, a + t1 * vdir)):
                rev.append([p0, p1, p1 - n * t, p0 - n * t])
            for (p0, p1) in ((b + t0 * vdir, b + t1 * vdir), (a + t1 * vdir, a + t0 * vdir)):
                rev.append([p0, p1, p1 - n * t, p0 - n * t])
            geo.quads(f"reveal{wi}", rev, m)
    if has_ceiling:
        ceil = mat(hsv(rng.uniform(), rng.uniform(0, 0.1), rng.uniform(0.75, 0.92)), 0.9, 0.0, "ceiling")
        geo.quads("ceiling", [[[0, H, 0], [W, H, 0], [W, H, D], [0, H, D]]], ceil)

    # Floor: planks or tiles, two or three tones.
    floor_rough = rng.uniform(0.2, 0.8)
    base = hsv(rng.uniform(0.04, 0.12), rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7)) if rng.uniform() < 0.6 \
        else hsv(rng.uniform(), rng.uniform(0.0, 0.3), rng.uniform(0.3, 0.9))
    tones = [base * rng.uniform(0.75, 1.25, size=3) ** 0.3 * f for f in (1.0, rng.uniform(0.6, 0.9), rng.uniform(1.05, 1.3))]
    tiles = rng.uniform() < 0.4
    step = rng.uniform(0.4, 0.7) if tiles else rng.uniform(0.15, 0.3)
    P["floor"] = {"kind": "tiles" if tiles else "planks", "step": step, "roughness": floor_rough}
    groups = {0: [], 1: [], 2: []}
    xs = np.arange(0.0, W, step).tolist() + [W]
    zs = np.arange(0.0, D, step if tiles else D / max(1, int(D / 1.8))).tolist() + [D]
    for i in range(len(xs) - 1):
        for j in range(len(zs) - 1):
            g = (i + j) % 2 if tiles else int(rng.integers(0, 3))
            x0, x1, z0, z1 = xs[i], xs[i + 1], zs[j], zs[j + 1]
            groups[g].append([[x0, 0, z0], [x0, 0, z1], [x1, 0, z1], [x1, 0, z0]])
    for g, qs in groups.items():
        if qs:
            geo.quads(f"floor{g}", qs, mat(tones[g], floor_rough, 0.0, "floor"))

    P["objects"] = draw_objects(rng, geo, cam_p, yaw, (0.0, W, 0.0, D), D - 0.8)

    draw_lighting(rng, P, jh, lamp_box=(W, D, H))
    return P, geo, c2w


# ----------------------------------------------------------------------------
# Mitsuba scene
# ----------------------------------------------------------------------------


def write_ply(path, quads, w2c):
    v = np.concatenate([np.asarray(q, float) for q in quads]).reshape(-1, 3)
    v = (np.c_[v, np.ones(len(v))] @ w2c.T)[:, :3].astype("<f4")
    nq = len(quads)
    f = np.empty((2 * nq, 4), dtype="<u4")
    base = 4 * np.arange(nq, dtype=np.uint32)
    f[0::2] = np.stack([np.full(nq, 3), base, base + 1, base + 2], 1)
    f[1::2] = np.stack([np.full(nq, 3), base, base + 2, base + 3], 1)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty float x\n"
              f"property float y\nproperty float z\nelement face {2 * nq}\n"
              "property list uchar uint vertex_indices\nend_header\n").encode()
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(v.tobytes())
        for row in f:
            fh.write(np.uint8(row[0]).tobytes() + row[1:].tobytes())


def principled(m):
    return {"type": "principled", "base_color": {"type": "rgb", "value": m["albedo"]},
            "roughness": m["roughness"], "metallic": m["metallic"], "specular": 0.5}


def mitsuba_shapes(mi, geo, w2c, tmp):
    T = lambda m: mi.ScalarTransform4f(m.tolist())  # noqa: E731
    out, mats = {}, {}
    for (name, kind, prm, m) in geo.shapes:
        key = name
        n = 1
        while key in out:
            key, n = f"{name}_{n}", n + 1
        if kind == "mesh":
            path = os.path.join(tmp, f"{key}.ply")
            write_ply(path, prm["quads"], w2c)
            out[key] = {"type": "ply", "filename": path, "face_normals": True, "bsdf": principled(m)}
        elif kind == "sphere":
            c = (w2c @ np.r_[prm["centre"], 1.0])[:3]
            out[key] = {"type": "sphere", "center": c.tolist(), "radius": prm["radius"], "bsdf": principled(m)}
        else:
            b, r, h = prm["base"], prm["radius"], prm["height"]
            p0 = (w2c @ np.r_[b, 1.0])[:3]
            p1 = (w2c @ np.r_[b + [0, h, 0], 1.0])[:3]
            out[key] = {"type": "cylinder", "p0": p0.tolist(), "p1": p1.tolist(), "radius": r, "bsdf": principled(m)}
            cap = frame_matrix(b + [0, h, 0], np.array([r, 0, 0]), np.array([0, 0, -r]), np.array([0, 1.0, 0]))
            out[key + "_cap"] = {"type": "disk", "to_world": T(w2c @ cap), "bsdf": principled(m)}
            mats[key + "_cap"] = m
        mats[key] = m
    return out, mats


def camera_and_integrator(mi, size, spp, fov=FOV_X_DEG):
    """A scene dict with the set's integrator and camera (matflow's: at the
    origin looking down -z, +y up, `fov` degrees across, size x size),
    shared with mitsuba_rooms.py."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH, "rr_depth": RR_DEPTH, "hide_emitters": False},
        "sensor": {
            "type": "perspective", "fov": fov, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0.0, 0, 0], target=[0.0, 0, -1], up=[0.0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgb",
                     "component_format": "float32", "rfilter": {"type": "gaussian", "stddev": 0.5}},
        },
    }


def build_scene(mi, shapes, env_path, lamps, w2c, size, spp):
    d = camera_and_integrator(mi, size, spp)
    d["sky"] = {"type": "envmap", "filename": env_path, "scale": 1.0}
    d.update(shapes)
    for i, l in enumerate(lamps):
        c = (w2c @ np.r_[l["position"], 1.0])[:3]
        d[f"lamp{i}"] = {"type": "sphere", "center": c.tolist(), "radius": l["radius"],
                         "emitter": {"type": "area", "radiance": {"type": "rgb", "value": l["radiance"]}},
                         "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.8, 0.8]}}}
    # No merging: every shape keeps its id, which names its material.
    return mi.load_dict(d, optimize=False)


def render(mi, scene, spp, pass_spp, seed):
    """The image at `spp` samples, rendered in passes, and the two halves
    (even and odd passes) for the noise estimate."""
    passes = max(2, math.ceil(spp / pass_spp))
    halves = [np.zeros((1,)), np.zeros((1,))]
    counts = [0, 0]
    for k in range(passes):
        n = spp // passes + (1 if k < spp % passes else 0)
        img = np.array(mi.render(scene, spp=n, seed=(seed * 256 + k) % 2**32), dtype=np.float64) * n
        halves[k % 2] = halves[k % 2] + img
        counts[k % 2] += n
    full = (halves[0] + halves[1]) / spp
    return full.astype(np.float32), halves[0] / counts[0], halves[1] / counts[1]


def gamma(x):
    return np.clip(x, 0.0, 1.0) ** (1 / 2.2)


def noise_floor_psnr(a, b, scale):
    """PSNR (sRGB, gamma 2.2, as matflow reports) of the full image against
    its noise-free limit, estimated from its two halves: for independent
    halves of equal weight, E|A - B|^2 = 4 E|full - limit|^2."""
    mse = float(np.mean((gamma(a * scale) - gamma(b * scale)) ** 2)) / 4.0
    return 100.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def pixel_truth(mi, dr, scene, mats, size):
    """Pixel-centre truth: depth, shading normal, material of the first hit
    (matflow's camera: pixel (i, j) looks along ((i - c)/f, -(j - c)/f, -1))."""
    f = size * 0.5 / math.tan(math.radians(FOV_X_DEG / 2))
    c = (size - 1) / 2
    jj, ii = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    d = np.stack([(ii - c) / f, -(jj - c) / f, -np.ones_like(ii, float)], -1).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    df = d.astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(df[:, 0], df[:, 1], df[:, 2]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    t = np.array(si.t, dtype=np.float64)
    n = np.stack([np.array(si.sh_frame.n.x), np.array(si.sh_frame.n.y), np.array(si.sh_frame.n.z)], -1)
    ids = np.array(dr.reinterpret_array(mi.UInt32, si.shape), dtype=np.int64)
    albedo = np.zeros((size * size, 3), np.float32)
    rough = np.zeros(size * size, np.float32)
    metal = np.zeros(size * size, np.float32)
    kind = np.full(size * size, "", dtype=object)
    for sh in scene.shapes():
        sid = int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh)))[0])
        m = mats.get(sh.id())
        sel = valid & (ids == sid)
        if m is None:  # a lamp
            albedo[sel] = 0.8
            rough[sel] = 1.0
            kind[sel] = "lamp"
            continue
        albedo[sel] = m["albedo"]
        rough[sel] = m["roughness"]
        metal[sel] = m["metallic"]
        kind[sel] = m["kind"]
    # Normals face the camera.
    flip = np.sum(n * d, axis=1) > 0
    n[flip] *= -1
    n[~valid] = 0.0
    z = np.where(valid, t * -d[:, 2], 0.0)
    sh = (size, size)
    return {"z": z.reshape(sh).astype(np.float32), "normal": n.reshape(size, size, 3).astype(np.float32),
            "albedo": albedo.reshape(size, size, 3), "roughness": rough.reshape(sh), "metallic": metal.reshape(sh),
            "valid": valid.reshape(sh), "kind": kind.reshape(sh)}


def gaussian_blur(img, sigma):
    r = int(math.ceil(3 * sigma))
    g = np.exp(-np.arange(-r, r + 1) ** 2 / (2 * sigma * sigma))
    out = img.astype(np.float64)
    for axis in (0, 1):
        pad = [(0, 0)] * out.ndim
        pad[axis] = (r, r)
        num = np.zeros_like(out)
        den = np.zeros(out.shape[axis])
        ones = np.pad(np.ones(out.shape[axis]), (r, r))
        padded = np.pad(out, pad)
        for k, gk in enumerate(g):
            sl = [slice(None)] * out.ndim
            sl[axis] = slice(k, k + out.shape[axis])
            num += gk * padded[tuple(sl)]
            den += gk * ones[k:k + out.shape[axis]]
        shape = [1] * out.ndim
        shape[axis] = -1
        out = num / den.reshape(shape)
    return out


def degrade(truth, prm):
    rng = np.random.default_rng(prm["noise_seed"])
    a = gaussian_blur(truth["albedo"], prm["blur_sigma_px"]) * np.asarray(prm["gain"])[None, None, :]
    half = prm["noise_std"] * math.sqrt(3)
    a = a + rng.uniform(-half, half, size=a.shape)
    sh = truth["roughness"].shape
    return (np.clip(a, 0, 1).astype(np.float32), np.full(sh, prm["roughness"], np.float32),
            np.full(sh, prm["metallic"], np.float32))


def level(img, valid):
    """The image's level: the mean over the room's pixels (not the sky seen
    through windows), with the brightest 1 % clipped (a sun patch, a lamp)."""
    v = img[valid].astype(np.float64)
    if v.size == 0:
        v = img.reshape(-1, 3).astype(np.float64)
    return max(float(np.mean(np.minimum(v, np.percentile(v, 99)))), 1e-12)


def write_exr(mi, path, img):
    a = np.ascontiguousarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    mi.Bitmap(a, mi.Bitmap.PixelFormat.RGB).write(path)


def scene_kind(k, n, kinds):
    """The kind of scene k of n and its place among its half's scenes of
    that kind: each half cycles through `kinds`."""
    j = k % max(1, n // 2)
    return kinds[j % len(kinds)], j // len(kinds)


def make_bundle(mi, dr, k, a, out_dir):
    kind, jh = scene_kind(k, a.scenes, a.kinds)
    P, geo, c2w = draw_scene(a.seed, k, a.scenes, kind=kind, jh=None if a.kinds == ["closed"] else jh)
    w2c = np.linalg.inv(c2w)
    rot = c2w[:3, :3]
    tmp = out_dir + ".partial"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(os.path.join(tmp, "ground_truth"))
    os.makedirs(os.path.join(tmp, "mitsuba"))
    t0 = time.perf_counter()
    shapes, mats = mitsuba_shapes(mi, geo, w2c, os.path.join(tmp, "mitsuba"))

    env = sky_image(P["sky"], rot, ENV_W, ENV_H)
    env_path = os.path.join(tmp, "mitsuba", "capture_sky.exr")
    write_exr(mi, env_path, env)
    scene = build_scene(mi, shapes, env_path, P["lamps"], w2c, a.size, a.pass_spp)
    truth = pixel_truth(mi, dr, scene, mats, a.size)
    if not truth["valid"].any() or truth["z"][truth["valid"]].max() <= truth["z"][truth["valid"]].min():
        raise RuntimeError(f"scene {k}: no usable geometry in view")
    img, ha, hb = render(mi, scene, a.spp, a.pass_spp, ((a.seed % 1000) * 1000 + k) * 10)
    exposure = P["exposure_target_mean"] / level(img, truth["valid"])
    P["exposure"] = exposure
    P["noise_floor_psnr"] = [noise_floor_psnr(ha, hb, exposure)]
    write_exr(mi, os.path.join(tmp, "gt_image.exr"), img * exposure)
    mi.Bitmap((downsample_env(env, TRUTH_ENV_W, TRUTH_ENV_H) * exposure).astype(np.float32),
              mi.Bitmap.PixelFormat.RGB).write(os.path.join(tmp, "ground_truth", "envmap.hdr"))

    P["relight_scales"] = []
    for j, sky in enumerate(P["relight_skies"]):
        suffix = "" if j == 0 else f"_{j + 1}"
        renv = sky_image(sky, rot, ENV_W, ENV_H)
        rpath = os.path.join(tmp, "mitsuba", f"relight_sky{suffix}.exr")
        write_exr(mi, rpath, renv)
        rscene = build_scene(mi, shapes, rpath, [], w2c, a.size, a.pass_spp)
        rimg, ha, hb = render(mi, rscene, a.spp, a.pass_spp, ((a.seed % 1000) * 1000 + k) * 10 + j + 1)
        scale = P["relit_target_means"][j] / level(rimg, truth["valid"])
        P["noise_floor_psnr"].append(noise_floor_psnr(ha, hb, scale))
        P["relight_scales"].append(scale)
        write_exr(mi, os.path.join(tmp, "ground_truth", f"relight_envmap{suffix}.exr"), renv * scale)
        write_exr(mi, os.path.join(tmp, "ground_truth", f"relit_image{suffix}.exr"), rimg * scale)
        os.remove(rpath)
    write_exr(mi, os.path.join(tmp, "ground_truth", "envmap.exr"), env * exposure)
    write_lamps(P, w2c, tmp)
    shutil.rmtree(os.path.join(tmp, "mitsuba"))

    write_exr(mi, os.path.join(tmp, "depth.exr"), truth["z"])
    write_exr(mi, os.path.join(tmp, "normalPred.exr"), truth["normal"])
    for name, arr in (("albedo", truth["albedo"]), ("roughness", truth["roughness"]),
                      ("metallic", truth["metallic"]), ("normal", truth["normal"])):
        write_exr(mi, os.path.join(tmp, "ground_truth", f"{name}.exr"), arr)
    alb, rough, metal = degrade(truth, P["degrade"])
    write_exr(mi, os.path.join(tmp, "albedoPred.exr"), alb)
    write_exr(mi, os.path.join(tmp, "roughnessPred.exr"), rough)
    write_exr(mi, os.path.join(tmp, "metallicPred.exr"), metal)
    kinds, counts = np.unique(truth["kind"], return_counts=True)
    P["pixel_kinds"] = {str(kk) if kk else "sky": int(c) for kk, c in zip(kinds, counts)}
    P["render"] = {"renderer": f"mitsuba {mi.__version__} {mi.variant()}", "integrator": "path",
                   "max_depth": MAX_DEPTH, "rr_depth": RR_DEPTH, "spp": a.spp, "size": a.size,
                   "filter": "gaussian 0.5", "seconds": round(time.perf_counter() - t0, 1)}
    with open(os.path.join(tmp, "scene.json"), "w") as fh:
        json.dump(P, fh, indent=1, default=float)
    shutil.rmtree(out_dir, ignore_errors=True)
    os.rename(tmp, out_dir)
    return P


def write_lamps(P, w2c, folder):
    """ground_truth/lamps.json: the capture's lamps as matflow reads them
    (crates/scene/src/lamps.rs): camera-space points whose intensity is a
    sphere's (pi r^2 times its radiance), with the capture's exposure."""
    lamps = []
    for l in P["lamps"]:
        c = (w2c @ np.r_[l["position"], 1.0])[:3]
        lamps.append({"position": c.tolist(),
                      "intensity": [math.pi * l["radius"] ** 2 * v * P["exposure"] for v in l["radiance"]]})
    with open(os.path.join(folder, "ground_truth", "lamps.json"), "w") as fh:
        json.dump({"lamps": lamps}, fh, indent=1)


def camera_w2c(P):
    """The world-to-camera matrix of the camera recorded in P."""
    c = P["camera"]
    c2w = camera({}, np.array(c["position"]), math.radians(c["yaw_deg"]), math.radians(c["pitch_deg"]))
    return np.linalg.inv(c2w)


def add_render_args(ap, size, spp):
    """The set's draw and render options (this script's and
    crates/bench/scripts/relight_twins.py's), with their own default size and spp."""
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--size", type=int, default=size)
    ap.add_argument("--spp", type=int, default=spp)
    ap.add_argument("--pass-spp", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--llvm", help="libLLVM for Dr.Jit (>= 17); see crates/bench/scripts/drjit_llvm.py")
    ap.add_argument("--kinds", nargs="+", default=["closed"], choices=SCENE_KINDS,
                    help="kinds of scene, in turn within each half (default: closed rooms alone, the "
                         "original set)")


def start_mitsuba(a):
    """Mitsuba and Dr.Jit for the parsed options `a` (--llvm, --threads)."""
    drjit_llvm.choose(a.llvm)
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(max(1, a.threads))
    return mi, dr


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for the bundles (scene-00 ...)")
    add_render_args(ap, 512, 1024)
    ap.add_argument("--only", type=int, nargs="+", help="generate only these scene indices")
    ap.add_argument("--force", action="store_true", help="re-render complete bundles")
    a = ap.parse_args()
    if a.scenes < 2:
        sys.exit("relight_scenes: --scenes must be at least 2 (a tuning and a held-back half)")
    mi, dr = start_mitsuba(a)
    os.makedirs(a.out, exist_ok=True)
    index = {"generator": "crates/bench/scripts/relight_scenes.py", "generator_version": GENERATOR_VERSION, "seed": a.seed,
             "size": a.size, "spp": a.spp, "tuning": [], "heldback": [], "kinds": {}}
    for k in range(a.scenes):
        index["tuning" if k < a.scenes // 2 else "heldback"].append(f"scene-{k:02d}")
        index["kinds"][f"scene-{k:02d}"] = scene_kind(k, a.scenes, a.kinds)[0]
    with open(os.path.join(a.out, "validation.json"), "w") as fh:
        json.dump(index, fh, indent=1)
    for k in range(a.scenes):
        name = f"scene-{k:02d}"
        if a.only is not None and k not in a.only:
            continue
        d = os.path.join(a.out, name)
        if os.path.exists(os.path.join(d, "scene.json")) and not a.force:
            lamps = os.path.join(d, "ground_truth", "lamps.json")
            if not os.path.exists(lamps):
                with open(os.path.join(d, "scene.json")) as fh:
                    P = json.load(fh)
                write_lamps(P, camera_w2c(P), d)
                log(f"relight_scenes: {name} exists, kept; its lamps.json written")
            else:
                log(f"relight_scenes: {name} exists, kept")
            continue
        P = make_bundle(mi, dr, k, a, d)
        log(f"relight_scenes: {name} ({P['split']}, {P['kind']}, sky {P['sky']['type']}, {len(P['lamps'])} lamp(s), "
            f"{len(P['windows'])} window(s), {len(P['objects'])} object(s)) in {P['render']['seconds']} s")


if __name__ == "__main__":
    main()
