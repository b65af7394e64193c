//! `trace`: a full render of the unedited scene that also keeps its light
//! paths, so that renders of material edits cost an evaluation, not a
//! path trace.
//!
//! Geometry and lighting do not change under a material edit, and every
//! (pixel, sample) of the render has its own random stream, so a pixel's
//! value changes only if one of its paths meets a changed material. The
//! kept paths (`inverse::cache`, a separate set of `path_spp` paths per
//! pixel) show which pixels' light passes through which material texels:
//! an edit re-traces exactly the pixels that see a changed texel directly
//! or along a kept path, with the base render's own sample streams — so
//! those pixels are bit-identical to a full re-render — and keeps the base
//! value elsewhere. What this misses is light the kept paths never carried
//! from the edited region to a pixel (a rare indirect path); the benchmark
//! measures it against full renders.

use std::collections::BTreeMap;

use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::brdf::Geo;
use matflow_inverse::paths::{
    CacheOptions, CacheStats, PathCache, Record, RowPaths, Vertex, NO_MATERIAL,
};
use matflow_render::integrator::render_pixels;
use matflow_render::{render, PixelFilter, RenderOptions};
use matflow_scene::{MaterialMaps, RgbImage};
use rayon::prelude::*;

use crate::artifact::Artifact;
use crate::err;
use crate::inputs::{envmap_from, materials_from, render_scene, MESH};

/// What a `paths` artifact holds.
pub struct Kept {
    pub cache: PathCache,
    /// Samples per pixel and seed of the base render (box filter, the
    /// cache's max_depth).
    pub spp: u32,
    pub seed: u64,
    pub materials: MaterialMaps,
    pub envmap: RgbImage,
    pub image: RgbImage,
}

pub fn encode_paths(k: &Kept) -> Vec<u8> {
    let c = &k.cache;
    let mut a = Artifact::new("paths");
    a.put_u32(
        "meta",
        9,
        1,
        vec![
            c.width as u32,
            c.height as u32,
            c.spp,
            c.max_depth,
            c.env_width as u32,
            c.env_height as u32,
            k.spp,
            k.seed as u32,
            (k.seed >> 32) as u32,
        ],
    );
    let mut vs = Vec::new();
    let mut rs = Vec::new();
    let mut counts = Vec::new();
    let mut verts = Vec::new();
    let mut recs = Vec::new();
    for row in &c.rows {
        vs.extend_from_slice(&row.vert_start);
        rs.extend_from_slice(&row.rec_start);
        counts.push(row.vertices.len() as u32);
        counts.push(row.records.len() as u32);
        for v in &row.vertices {
            verts.push(v.q);
            verts.push(v.n_env as u32 | (v.flags as u32) << 16);
        }
        for r in &row.records {
            recs.push(r.geo.q[0] as u32 | (r.geo.q[1] as u32) << 16);
            recs.push(r.geo.q[2] as u32 | (r.geo.q[3] as u32) << 16);
            recs.push(r.w.to_bits());
            recs.push(r.cell as u32 | (r.fx as u32) << 16);
            recs.push(r.fy as u32 | (r._pad as u32) << 16);
        }
    }
    a.put_u32("vert_start", vs.len() as u32, 1, vs);
    a.put_u32("rec_start", rs.len() as u32, 1, rs);
    a.put_u32("row_counts", c.rows.len() as u32, 2, counts);
    a.put_u32("vertices", (verts.len() / 2) as u32, 2, verts);
    a.put_u32("records", (recs.len() / 5) as u32, 5, recs);
    a.put_materials("base_", &k.materials);
    a.put_rgb("envmap", &k.envmap);
    a.put_rgb("image", &k.image);
    a.encode()
}

pub fn decode_paths(b: &[u8]) -> Result<Kept, NodeError> {
    let a = Artifact::decode(b, "paths")?;
    let bad = || err("paths artifact: inconsistent layout");
    let meta = a.u32_list("meta", 1)?;
    if meta.len() != 9 {
        return Err(bad());
    }
    let (w, h) = (meta[0] as usize, meta[1] as usize);
    let vs = a.u32_list("vert_start", 1)?;
    let rs = a.u32_list("rec_start", 1)?;
    let counts = a.u32_list("row_counts", 2)?;
    let verts = a.u32_list("vertices", 2)?;
    let recs = a.u32_list("records", 5)?;
    if vs.len() != h * (w + 1) || rs.len() != h * (w + 1) || counts.len() != 2 * h {
        return Err(bad());
    }
    let mut rows = Vec::with_capacity(h);
    let (mut vo, mut ro) = (0usize, 0usize);
    for y in 0..h {
        let (nv, nr) = (counts[2 * y] as usize, counts[2 * y + 1] as usize);
        let vrange = vo..vo + nv;
        let rrange = ro..ro + nr;
        if 2 * vrange.end > verts.len() || 5 * rrange.end > recs.len() {
            return Err(bad());
        }
        let vertices: Vec<Vertex> = verts[2 * vo..2 * (vo + nv)]
            .chunks_exact(2)
            .map(|c| Vertex {
                q: c[0],
                n_env: (c[1] & 0xffff) as u16,
                flags: (c[1] >> 16) as u16,
            })
            .collect();
        let records: Vec<Record> = recs[5 * ro..5 * (ro + nr)]
            .chunks_exact(5)
            .map(|c| Record {
                geo: Geo {
                    q: [
                        (c[0] & 0xffff) as u16,
                        (c[0] >> 16) as u16,
                        (c[1] & 0xffff) as u16,
                        (c[1] >> 16) as u16,
                    ],
                },
                w: f32::from_bits(c[2]),
                cell: (c[3] & 0xffff) as u16,
                fx: (c[3] >> 16) as u16,
                fy: (c[4] & 0xffff) as u16,
                _pad: (c[4] >> 16) as u16,
            })
            .collect();
        let vst = vs[y * (w + 1)..(y + 1) * (w + 1)].to_vec();
        let rst = rs[y * (w + 1)..(y + 1) * (w + 1)].to_vec();
        if vst.last().copied() != Some(nv as u32) || rst.last().copied() != Some(nr as u32) {
            return Err(bad());
        }
        rows.push(RowPaths {
            vert_start: vst,
            rec_start: rst,
            vertices,
            records,
        });
        vo += nv;
        ro += nr;
    }
    Ok(Kept {
        spp: meta[6],
        seed: meta[7] as u64 | (meta[8] as u64) << 32,
        cache: PathCache {
            width: w,
            height: h,
            spp: meta[2],
            max_depth: meta[3],
            env_width: meta[4] as usize,
            env_height: meta[5] as usize,
            rows,
            stats: CacheStats::default(),
        },
        materials: a.materials("base_")?,
        envmap: a.rgb("envmap")?,
        image: a.rgb("image")?,
    })
}

/// Options of the base render (re-used for re-traced pixels).
fn base_options(k: &Kept) -> RenderOptions {
    RenderOptions {
        spp: k.spp,
        max_depth: k.cache.max_depth,
        seed: k.seed,
        filter: PixelFilter::Box,
        ..Default::default()
    }
}

/// Pixels whose value an edit from the base materials to `edited` can
/// change: those whose own texel changed or whose kept paths meet a
/// changed texel.
pub fn affected_pixels(k: &Kept, edited: &MaterialMaps) -> Vec<u32> {
    let base = &k.materials;
    let changed: Vec<bool> = (0..base.albedo.data.len())
        .map(|i| {
            base.albedo.data[i] != edited.albedo.data[i]
                || base.roughness.data[i] != edited.roughness.data[i]
                || base.metallic.data[i] != edited.metallic.data[i]
        })
        .collect();
    let (w, h) = (k.cache.width, k.cache.height);
    let rows: Vec<Vec<u32>> =
        (0..h)
            .into_par_iter()
            .map(|y| {
                (0..w)
                    .filter(|&x| {
                        changed[y * w + x]
                            || k.cache.pixel(x, y).0.iter().any(|v| {
                                v.q != NO_MATERIAL && changed.get(v.q as usize) == Some(&true)
                            })
                    })
                    .map(|x| (y * w + x) as u32)
                    .collect()
            })
            .collect();
    rows.concat()
}

/// The edited image: the base render with the affected pixels re-traced.
pub fn edited_image(k: &Kept, mesh: &[u8], edited: &MaterialMaps) -> Result<RgbImage, NodeError> {
    if edited.width() != k.cache.width || edited.height() != k.cache.height {
        return Err(err(format!(
            "the materials are {}x{} but the kept paths are {}x{}",
            edited.width(),
            edited.height(),
            k.cache.width,
            k.cache.height
        )));
    }
    let px = affected_pixels(k, edited);
    let mut img = k.image.clone();
    if !px.is_empty() {
        let scene = render_scene(mesh, edited, &k.envmap)?;
        let vals = render_pixels(&scene, &base_options(k), &px);
        for (p, v) in px.iter().zip(vals) {
            img.data[*p as usize] = v;
        }
    }
    Ok(img)
}

pub struct TraceNode;

const TRACE_INFO: NodeInfo = NodeInfo {
    kind: "trace",
    version: 1,
    doc: "A full render of the unedited scene (box pixel filter) that also keeps a set of its \
         light paths: a `render` given these `paths` re-traces only the pixels whose own \
         material changed or whose kept paths meet a changed material, with the base \
         render's sample streams (bit-identical there to a full re-render), and keeps the \
         base elsewhere.",
    params: &[
            MESH,
            ParamSpec {
                name: "materials",
                ty: ParamType::Ref(&["materials", "scene"]),
                default: None,
                unit: "",
                doc: "the unedited materials (they also guide path sampling)",
            },
            ParamSpec {
                name: "envmap",
                ty: ParamType::Ref(&["envmap"]),
                default: None,
                unit: "",
                doc: "lighting (fixed for every edit rendered from these paths)",
            },
            ParamSpec {
                name: "spp",
                ty: ParamType::Int {
                    min: 1,
                    max: 65536,
                },
                default: Some("64"),
                unit: "samples/px",
                doc: "samples per pixel of the full render",
            },
            ParamSpec {
                name: "path_spp",
                ty: ParamType::Int { min: 1, max: 1024 },
                default: Some("8"),
                unit: "paths/px",
                doc: "paths kept per pixel to find which pixels an edit reaches (~11 MB per path/px at 512²)",
            },
            ParamSpec {
                name: "depth",
                ty: ParamType::Int { min: 2, max: 8 },
                default: Some("4"),
                unit: "segments",
                doc: "maximum path length (Mitsuba's max_depth)",
            },
        ],
    outputs: &[
            OutputSpec {
                name: "paths",
                ty: "paths",
                doc: "kept paths, the unedited materials, envmap and image",
            },
            OutputSpec {
                name: "image",
                ty: "image",
                doc: "the unedited render",
            },
        ],
};

impl Node for TraceNode {
    fn info(&self) -> &'static NodeInfo {
        &TRACE_INFO
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let p = ctx.params;
        let maps = materials_from(ctx.input("materials")?)?;
        let env = envmap_from(ctx.input("envmap")?)?;
        let scene = render_scene(ctx.input("mesh")?, &maps, &env)?;
        let depth = p.i64("depth") as u32;
        let spp = p.i64("spp") as u32;
        let image = render(
            &scene,
            &RenderOptions {
                spp,
                max_depth: depth,
                seed: ctx.seed,
                filter: PixelFilter::Box,
                ..Default::default()
            },
            &|d, t| (ctx.progress)(d as u64, 2 * t as u64),
        )
        .image;
        let cache = PathCache::build(
            &scene,
            &CacheOptions {
                spp: p.i64("path_spp") as u32,
                max_depth: depth,
                seed: ctx.seed ^ 0x7a7a,
                env_width: env.width,
                env_height: env.height,
            },
            &|d, t| (ctx.progress)((t + d) as u64, 2 * t as u64),
        )
        .map_err(err)?;
        let kept = Kept {
            spp,
            seed: ctx.seed,
            cache,
            materials: maps,
            envmap: env,
            image,
        };
        let img = crate::inputs::encode_image("image", "image", &kept.image);
        Ok([
            ("paths".to_string(), encode_paths(&kept)),
            ("image".to_string(), img),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inputs::encode_mesh;
    use glam::Vec3;
    use matflow_scene::Camera;

    /// An edit re-traces exactly the pixels it can reach: there the result
    /// equals a full re-render bit for bit, elsewhere the base; and the
    /// kept paths round-trip through their bytes.
    #[test]
    fn edits_retrace_what_they_reach_bit_identically() {
        let n = 24;
        let s = matflow_scene::synthetic::generate(3, n, n);
        let cam = Camera::new(n, n);
        let tri = matflow_geom::mesh_from_depth(&s.depth, &cam, &Default::default())
            .unwrap()
            .mesh;
        let mesh = encode_mesh(n, n, &tri);
        let scene = render_scene(&mesh, &s.maps, &s.envmap).unwrap();
        let opts = RenderOptions {
            spp: 6,
            max_depth: 4,
            seed: 11,
            filter: PixelFilter::Box,
            ..Default::default()
        };
        let image = render(&scene, &opts, &|_, _| {}).image;
        let cache = PathCache::build(
            &scene,
            &CacheOptions {
                spp: 4,
                max_depth: 4,
                seed: 5,
                env_width: 32,
                env_height: 16,
            },
            &|_, _| {},
        )
        .unwrap();
        let kept = Kept {
            cache,
            spp: 6,
            seed: 11,
            materials: s.maps.clone(),
            envmap: s.envmap.clone(),
            image,
        };
        let kept = decode_paths(&encode_paths(&kept)).unwrap();
        let mut edited = s.maps.clone();
        for y in 14..20 {
            for x in 4..10 {
                edited.albedo.set(x, y, Vec3::new(0.9, 0.1, 0.1));
                edited.roughness.set(x, y, 0.1);
                edited.metallic.set(x, y, 1.0);
            }
        }
        let got = edited_image(&kept, &mesh, &edited).unwrap();
        let full = render(
            &render_scene(&mesh, &edited, &s.envmap).unwrap(),
            &opts,
            &|_, _| {},
        )
        .image;
        let hit: std::collections::BTreeSet<u32> =
            affected_pixels(&kept, &edited).into_iter().collect();
        assert!(hit.len() >= 36 && hit.len() < n * n, "{} pixels", hit.len());
        let mut differ = 0;
        for p in 0..n * n {
            if hit.contains(&(p as u32)) {
                assert_eq!(got.data[p], full.data[p], "re-traced pixel {p}");
            } else {
                assert_eq!(got.data[p], kept.image.data[p], "kept pixel {p}");
                differ += (full.data[p] != kept.image.data[p]) as usize;
            }
        }
        // What the kept paths miss is rare indirect light.
        assert!(differ * 4 < n * n, "{differ} pixels missed");
        assert!(affected_pixels(&kept, &s.maps).is_empty());
    }
}
