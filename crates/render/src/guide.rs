//! Visibility-guided environment sampling: next-event estimation that
//! knows which parts of the sky a region of the scene can see.
//!
//! Importance sampling the envmap alone (∝ radiance × solid angle) wastes
//! its samples wherever geometry blocks most of the sky: inside a closed
//! room, light arrives only through its openings, and almost every envmap
//! sample's shadow ray hits a wall. BSDF sampling rarely finds a small
//! opening either, so such rooms stay noisy at any practical sample count.
//! (The same need is what portal sampling serves; this version needs no
//! portals to be marked, since it measures what each region sees.)
//!
//! [`Visibility`] measures, once per geometry, what each region sees: the
//! scene's bounding box is cut into voxels, a few points on the surfaces
//! inside each occupied voxel (a *cluster*) are chosen, and from each point
//! a shadow ray is traced into every cell of a lat-long grid of directions.
//! `V_c(j)` is the fraction of cluster c's points that see direction cell
//! j (directions below a point's surface count as blocked).
//!
//! Bound to an envmap ([`crate::EnvMap::guided`]), the envmap's sampling
//! cells are grouped (each cell, or for a fine map each direction cell's
//! worth of cells) and a vertex in cluster c samples the defensive mixture
//!
//! ```text
//! p_c(ω) = p_env(ω) · (β + (1 − β) · V_c(g(ω)) / Z_c),   Z_c = Σ_g V_c(g) P_env(g)
//! ```
//!
//! that is, with probability β the plain envmap density and otherwise the
//! envmap density restricted to what the cluster sees. The estimate stays
//! unbiased whatever V is (β > 0 keeps the density positive wherever the
//! envmap's is; a cluster that sees nothing uses the plain density), so V
//! only needs to be good, not exact. The cluster is a function of the
//! shaded point, kept with the path, so light samples and BSDF samples
//! that reach the sky are weighted (MIS) with the same density.
//!
//! Deterministic: the points and ray directions come from hashes of the
//! voxel, point and cell, and clusters are traced in parallel into their
//! own rows.

use std::f32::consts::PI;

use glam::Vec3;
use matflow_geom::Bvh;
#[cfg(test)]
use matflow_geom::TriMesh;
use rayon::prelude::*;

use crate::envmap::{dir_to_uv, locate_cell};
use crate::fmath::ONE_BELOW;
use crate::integrator::offset_origin;
use crate::rng::mix64;

/// [`Visibility::cluster_of`] for a point in no cluster.
pub const NO_CLUSTER: u32 = u32::MAX;

/// How the visibility is measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuideParams {
    /// Voxels along the longest side of the scene's bounding box.
    pub voxels: usize,
    /// Points per occupied voxel.
    pub points: usize,
    /// Walks from the camera that find the points: a grid of this many
    /// primary directions across the image, each bouncing up to
    /// `bounces` times.
    pub walks: usize,
    pub bounces: usize,
    /// Direction cells: columns (azimuth) × rows (polar angle).
    pub dir_width: usize,
    pub dir_height: usize,
    /// β: the share of light samples drawn from the plain envmap density.
    pub defensive: f32,
    /// Scenes whose [`Visibility::open_fraction`] is at least this are
    /// not guided at all: open depth meshes (about 0.35–0.39 measured on
    /// rooms and both reference photos) gain little for the lookups'
    /// cost, closed rooms (0.03–0.06) gain most.
    pub enclosed_below: f64,
    /// Clusters that see more than this share of the envmap's light
    /// (Z_c) sample by radiance alone: guiding gains little there (at
    /// most 1/Z_c in variance) for what its lookups cost.
    pub open_above: f32,
    pub seed: u64,
}

impl Default for GuideParams {
    fn default() -> Self {
        GuideParams {
            voxels: 16,
            points: 4,
            walks: 16384,
            bounces: 3,
            dir_width: 64,
            dir_height: 32,
            defensive: 0.2,
            enclosed_below: 0.2,
            open_above: 0.25,
            seed: 0x006d_6174_666c_6f77,
        }
    }
}

/// What each cluster of the scene sees of the sky.
#[derive(Clone, Debug)]
pub struct Visibility {
    grid: VoxelGrid,
    /// Per voxel (x fastest), its cluster or [`NO_CLUSTER`].
    voxel_cluster: Vec<u32>,
    clusters: usize,
    dir_width: usize,
    dir_height: usize,
    /// Per cluster, per direction cell (row-major), the fraction of its
    /// points that see it.
    vis: Vec<f32>,
    pub defensive: f32,
    pub open_above: f32,
    /// Shadow rays traced to measure it.
    pub rays: u64,
}

/// The voxels the scene's bounding box is cut into.
#[derive(Clone, Copy, Debug)]
struct VoxelGrid {
    origin: Vec3,
    inv_voxel: f32,
    dims: [usize; 3],
}

impl VoxelGrid {
    /// The voxel (x fastest) of point `p`, or `None` outside the grid;
    /// points a rounding error past its far faces belong to the last
    /// voxel.
    #[inline]
    fn index(&self, p: Vec3) -> Option<usize> {
        let g = (p - self.origin) * self.inv_voxel;
        if !(g.min_element() >= 0.0) {
            return None;
        }
        let d = self.dims;
        let slack = |c: usize, n: usize| if c == n { n - 1 } else { c };
        let (x, y, z) = (
            slack(g.x as usize, d[0]),
            slack(g.y as usize, d[1]),
            slack(g.z as usize, d[2]),
        );
        (x < d[0] && y < d[1] && z < d[2]).then_some((z * d[1] + y) * d[0] + x)
    }
}

/// Uniform in [0, 1) from a hash.
#[inline]
fn unit(h: u64) -> f32 {
    (h >> 40) as f32 * (1.0 / 16_777_216.0)
}

impl Visibility {
    /// Measures the visibility of the scene traced through `bvh` (whose
    /// triangle normals are `face_normals`) where paths from the camera
    /// (at the origin, looking along `primary`) go: from each primary
    /// direction a walk of up to [`GuideParams::bounces`] cosine-sampled
    /// bounces, each vertex a candidate point with its normal as the path
    /// tracer shades it. The first `one_sided` triangles (the depth mesh)
    /// keep their normal; the rest (objects, two-sided) face the path that
    /// reached them. A scene no walk hits gives a visibility with no
    /// clusters (plain sampling). A direction counts as much as its ray
    /// carries: through a partly open triangle (`openness`, per triangle,
    /// empty for none) its openness.
    pub fn build(
        face_normals: &[Vec3],
        one_sided: usize,
        bvh: &Bvh,
        openness: &[f32],
        primary: &[Vec3],
        params: &GuideParams,
    ) -> Visibility {
        let dw = params.dir_width.clamp(1, 256);
        let dh = params.dir_height.clamp(1, 256);
        let bounces = params.bounces.clamp(1, 16);
        let walks: Vec<Vec<(u64, Vec3, Vec3)>> = primary
            .par_iter()
            .enumerate()
            .map(|(i, &d0)| {
                let mut out = Vec::with_capacity(bounces);
                let (mut o, mut d) = (Vec3::ZERO, d0);
                for b in 0..bounces {
                    let Some(hit) = bvh.intersect(o, d, 0.0, f32::INFINITY) else {
                        break;
                    };
                    let t = hit.prim as usize;
                    let mut n = face_normals.get(t).copied().unwrap_or(Vec3::ZERO);
                    if n == Vec3::ZERO || !n.is_finite() {
                        break;
                    }
                    if t >= one_sided && n.dot(d) > 0.0 {
                        n = -n;
                    }
                    let p = o + d * hit.t;
                    let h = mix64(params.seed ^ mix64(((i as u64) << 8) ^ b as u64));
                    out.push((h, p, n));
                    let local = crate::warp::square_to_cosine_hemisphere(unit(h), unit(mix64(h)));
                    d = crate::warp::Frame::from_normal(n)
                        .to_world(local)
                        .normalize_or(n);
                    o = offset_origin(p, n, d);
                }
                out
            })
            .collect();
        let points: Vec<(u64, Vec3, Vec3)> = walks
            .into_iter()
            .flatten()
            .filter(|e| e.1.is_finite())
            .collect();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for e in &points {
            lo = lo.min(e.1);
            hi = hi.max(e.1);
        }
        let empty = Visibility {
            grid: VoxelGrid {
                origin: Vec3::ZERO,
                inv_voxel: 0.0,
                dims: [0; 3],
            },
            voxel_cluster: Vec::new(),
            clusters: 0,
            dir_width: dw,
            dir_height: dh,
            vis: Vec::new(),
            defensive: params.defensive.clamp(0.0, 1.0),
            open_above: params.open_above,
            rays: 0,
        };
        let extent = hi - lo;
        let longest = extent.max_element();
        if !(longest > 0.0) || !longest.is_finite() {
            return empty;
        }
        let res = params.voxels.clamp(1, 256);
        let size = longest / res as f32;
        let dims =
            [extent.x, extent.y, extent.z].map(|e| ((e / size).ceil() as usize).clamp(1, res));
        let grid = VoxelGrid {
            origin: lo,
            inv_voxel: 1.0 / size,
            dims,
        };
        let nvox = dims[0] * dims[1] * dims[2];

        // Per voxel the `points` walk vertices with the smallest hashes.
        let k = params.points.clamp(1, 64);
        let mut chosen: Vec<Vec<(u64, Vec3, Vec3)>> = vec![Vec::new(); nvox];
        for &(h, p, n) in &points {
            let Some(v) = grid.index(p) else {
                continue;
            };
            let list = &mut chosen[v];
            if list.len() < k {
                list.push((h, p, n));
            } else if let Some(worst) = list
                .iter_mut()
                .max_by_key(|e| e.0)
                .filter(|worst| worst.0 > h)
            {
                *worst = (h, p, n);
            }
        }
        let mut voxel_cluster = vec![NO_CLUSTER; nvox];
        let mut members = Vec::new();
        for (v, list) in chosen.iter_mut().enumerate() {
            if !list.is_empty() {
                // The hash order, not the insertion order, fixes the rays.
                list.sort_by_key(|e| e.0);
                voxel_cluster[v] = members.len() as u32;
                members.push(v);
            }
        }
        let ncells = dw * dh;
        let traced: Vec<(Vec<f32>, u64)> = members
            .par_iter()
            .map(|&v| {
                let pts = &chosen[v];
                let mut rays = Vec::with_capacity(pts.len() * ncells);
                let mut ray_cell = Vec::with_capacity(pts.len() * ncells);
                for (i, &(_, p, n)) in pts.iter().enumerate() {
                    for cell in 0..ncells {
                        let h = mix64(
                            params.seed
                                ^ mix64(((v as u64) << 32) ^ ((i as u64) << 24) ^ cell as u64),
                        );
                        let d = cell_direction(dw, dh, cell, unit(h), unit(mix64(h)));
                        if n.dot(d) > 0.0 {
                            rays.push((offset_origin(p, n, d), d));
                            ray_cell.push(cell as u32);
                        }
                    }
                }
                let mut row = vec![0f32; ncells];
                if openness.is_empty() {
                    let mut blocked = vec![false; rays.len()];
                    bvh.occluded_stream(&rays, 0.0, f32::INFINITY, &mut blocked);
                    for (&cell, &b) in ray_cell.iter().zip(&blocked) {
                        if !b {
                            row[cell as usize] += 1.0;
                        }
                    }
                } else {
                    let (mut hits, mut through) = (Vec::new(), Vec::new());
                    crate::scene::transmittance_stream(
                        bvh,
                        openness,
                        &rays,
                        &mut hits,
                        &mut through,
                    );
                    for (&cell, &t) in ray_cell.iter().zip(&through) {
                        row[cell as usize] += t;
                    }
                }
                let inv = 1.0 / pts.len() as f32;
                row.iter_mut().for_each(|x| *x *= inv);
                (row, rays.len() as u64)
            })
            .collect();
        let mut vis = Vec::with_capacity(members.len() * ncells);
        let mut rays = 0;
        for (row, r) in traced {
            vis.extend_from_slice(&row);
            rays += r;
        }
        Visibility {
            grid,
            voxel_cluster,
            clusters: members.len(),
            dir_width: dw,
            dir_height: dh,
            vis,
            defensive: params.defensive.clamp(0.0, 1.0),
            open_above: params.open_above,
            rays,
        }
    }

    /// Number of clusters (occupied voxels).
    pub fn clusters(&self) -> usize {
        self.clusters
    }

    /// The share of the sphere of directions the clusters see, in the
    /// mean over clusters (solid-angle weighted): about ½ for surfaces
    /// under an open sky (their lower hemisphere is blocked by
    /// themselves), near 0 inside a closed room.
    pub fn open_fraction(&self) -> f64 {
        if self.clusters == 0 {
            return 1.0;
        }
        let (dw, dh) = (self.dir_width, self.dir_height);
        let omega: Vec<f64> = (0..dh)
            .map(|r| {
                let c0 = (std::f64::consts::PI * r as f64 / dh as f64).cos();
                let c1 = (std::f64::consts::PI * (r + 1) as f64 / dh as f64).cos();
                (c0 - c1) / (2.0 * dw as f64)
            })
            .collect();
        let total: f64 = (0..self.clusters)
            .map(|c| {
                (0..dw * dh)
                    .map(|j| self.seen(c as u32, j) as f64 * omega[j / dw])
                    .sum::<f64>()
            })
            .sum();
        total / self.clusters as f64
    }

    /// Direction cells per cluster: (columns, rows).
    pub fn dir_cells(&self) -> (usize, usize) {
        (self.dir_width, self.dir_height)
    }

    /// The cluster of point `p`, or [`NO_CLUSTER`] outside every occupied
    /// voxel.
    #[inline]
    pub fn cluster_of(&self, p: Vec3) -> u32 {
        if self.clusters == 0 {
            return NO_CLUSTER;
        }
        match self.grid.index(p) {
            Some(v) => self.voxel_cluster[v],
            None => NO_CLUSTER,
        }
    }

    /// The fraction of cluster `c`'s points that see direction cell `cell`.
    #[inline]
    pub fn seen(&self, c: u32, cell: usize) -> f32 {
        self.vis[c as usize * self.dir_width * self.dir_height + cell]
    }

    /// The direction cell (row-major) of direction `d`.
    #[inline]
    pub fn cell_of(&self, d: Vec3) -> usize {
        let (u, v) = dir_to_uv(d);
        self.cell_of_uv(u, v)
    }

    /// The direction cell (row-major) at (u, v) ([`dir_to_uv`]).
    #[inline]
    pub fn cell_of_uv(&self, u: f32, v: f32) -> usize {
        let col = ((u * self.dir_width as f32) as usize).min(self.dir_width - 1);
        let row = ((v * self.dir_height as f32) as usize).min(self.dir_height - 1);
        row * self.dir_width + col
    }
}

/// [`cell_direction`] and the direction's (u, v).
fn cell_direction_uv(dw: usize, dh: usize, cell: usize, a: f32, b: f32) -> (Vec3, f32, f32) {
    let d = cell_direction(dw, dh, cell, a, b);
    let (row, col) = (cell / dw, cell % dw);
    let u = ((col as f32 + a) / dw as f32).min(ONE_BELOW);
    let v = (d.y.clamp(-1.0, 1.0).acos() / PI)
        .clamp(row as f32 / dh as f32, (row + 1) as f32 / dh as f32);
    (d, u, v)
}

/// A direction uniform in solid angle inside direction cell `cell` of a
/// `dw`×`dh` lat-long grid (rows of equal polar angle, row 0 at the top),
/// from (a, b) in [0, 1)².
fn cell_direction(dw: usize, dh: usize, cell: usize, a: f32, b: f32) -> Vec3 {
    let (row, col) = (cell / dw, cell % dw);
    let c0 = (PI * row as f32 / dh as f32).cos();
    let c1 = (PI * (row + 1) as f32 / dh as f32).cos();
    let cos_t = (c0 + (c1 - c0) * b).clamp(-1.0, 1.0);
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * PI * (col as f32 + a) / dw as f32;
    let (sp, cp) = phi.sin_cos();
    Vec3::new(sin_t * sp, cos_t, -sin_t * cp)
}

/// A [`Visibility`] bound to one envmap: per cluster, a distribution over
/// the direction cells ∝ V_c(j) · m_j, where m_j is the envmap's
/// probability of cell j. Inside the chosen direction cell the direction
/// follows the envmap's own density when the envmap is finer than the
/// direction grid (its cells are grouped by the direction cell their
/// centre lies in), or is uniform in solid angle when it is coarser (the
/// envmap is near constant across a direction cell then, and what the
/// cluster sees varies inside one envmap cell).
#[derive(Clone, Debug)]
pub(crate) struct Guide {
    pub(crate) vis: std::sync::Arc<Visibility>,
    layout: Layout,
    ndir: usize,
    /// Per cluster, its row among the guided clusters ([`NO_ROW`] for one
    /// that samples by radiance alone: Z_c = Σ_j V_c(j)·m_j is 0 or above
    /// [`GuideParams::open_above`]).
    row: Vec<u32>,
    /// Per guided cluster × direction cell: V_c(j)/Z_c (fine layout: q_c
    /// is p_env times it) or V_c(j)·m_j/(Z_c·Ω_j) (coarse: q_c itself).
    factor: Vec<f32>,
    /// Per cluster, the direction cells it draws from (V_c(j)·m_j > 0)
    /// as `cell[start[c]..start[c+1]]`, and their CDF in `cdf` (a leading
    /// 0 per guided cluster: from index `start[c] + row[c]`).
    start: Vec<u32>,
    cell: Vec<u16>,
    cdf: Vec<f64>,
    defensive: f32,
}

#[derive(Clone, Debug)]
enum Layout {
    /// Envmap cells grouped by direction cell: group j's are
    /// `members[start[j]..start[j+1]]`, with `member_cdf` their cumulative
    /// probability inside the group (a leading 0 per group: index
    /// `start[j] + j`); `group_of_cell` per envmap cell.
    Fine {
        group_of_cell: Vec<u32>,
        members: Vec<u32>,
        start: Vec<u32>,
        member_cdf: Vec<f64>,
    },
    /// Uniform inside each direction cell, whose solid angles these are.
    Coarse { omega: Vec<f32> },
}

impl Guide {
    /// Binds `vis` to an envmap of `width`×`height` texels whose cells
    /// (row-major, `height − 1` rows spanning θ ∈ [0, π] evenly, columns
    /// centred half a texel on) have probabilities `cell_prob` and the
    /// solid angles `row_solid_angle` per row.
    pub(crate) fn bind(
        vis: std::sync::Arc<Visibility>,
        width: usize,
        height: usize,
        cell_prob: &[f32],
        row_solid_angle: &[f32],
    ) -> Guide {
        let rows = height - 1;
        let ncells = rows * width;
        let (dw, dh) = vis.dir_cells();
        let ndir = dw * dh;
        // m_j per direction cell (they sum to 1).
        let mut mass = vec![0f64; ndir];
        let layout = if ncells > ndir {
            let cell_centre = |k: usize| {
                let (r, c) = (k / width, k % width);
                let theta = PI * (r as f32 + 0.5) / rows as f32;
                let u = (c as f32 + 1.0) / width as f32;
                let (st, ct) = theta.sin_cos();
                let (sp, cp) = (2.0 * PI * u).sin_cos();
                Vec3::new(st * sp, ct, -st * cp)
            };
            let group_of_cell: Vec<u32> = (0..ncells)
                .map(|k| vis.cell_of(cell_centre(k)) as u32)
                .collect();
            let mut members: Vec<u32> = (0..ncells as u32).collect();
            members.sort_by_key(|&k| (group_of_cell[k as usize], k));
            let mut start = vec![0u32; ndir + 1];
            for &g in &group_of_cell {
                start[g as usize + 1] += 1;
            }
            for g in 0..ndir {
                start[g + 1] += start[g];
            }
            let mut member_cdf = Vec::with_capacity(ncells + ndir);
            for g in 0..ndir {
                let m = &members[start[g] as usize..start[g + 1] as usize];
                let total: f64 = m.iter().map(|&k| cell_prob[k as usize] as f64).sum();
                mass[g] = total;
                member_cdf.push(0.0);
                let mut acc = 0.0;
                for (i, &k) in m.iter().enumerate() {
                    acc += cell_prob[k as usize] as f64;
                    member_cdf.push(if total > 0.0 {
                        acc / total
                    } else {
                        (i + 1) as f64 / m.len() as f64
                    });
                }
            }
            Layout::Fine {
                group_of_cell,
                members,
                start,
                member_cdf,
            }
        } else {
            // m_j: the envmap's density at the cell's centre times its
            // solid angle, normalised.
            let mut omega = vec![0f32; ndir];
            for (j, (o, m)) in omega.iter_mut().zip(mass.iter_mut()).enumerate() {
                let row = j / dw;
                let c0 = (PI * row as f32 / dh as f32).cos();
                let c1 = (PI * (row + 1) as f32 / dh as f32).cos();
                *o = 2.0 * PI / dw as f32 * (c0 - c1);
                let (r, c, _, _) = locate_cell(width, height, cell_direction(dw, dh, j, 0.5, 0.5));
                let ra = row_solid_angle[r];
                if ra > 0.0 {
                    *m = cell_prob[r * width + c] as f64 / ra as f64 * *o as f64;
                }
            }
            let total: f64 = mass.iter().sum();
            if total > 0.0 {
                mass.iter_mut().for_each(|m| *m /= total);
            }
            Layout::Coarse { omega }
        };
        let clusters = vis.clusters();
        let open_above = vis.open_above;
        let defensive = vis.defensive;
        // Per cluster: Z_c, then (if the cluster is guided) the factors
        // and the sparse CDF over the cells it draws from.
        // Per cluster its factors and (direction cell, CDF) pairs, empty
        // for one that samples by radiance alone.
        type Rows = (Vec<f32>, Vec<(u32, f64)>);
        let per: Vec<Rows> = (0..clusters)
            .into_par_iter()
            .map(|c| {
                let zc: f64 = (0..ndir)
                    .map(|j| vis.seen(c as u32, j) as f64 * mass[j])
                    .sum();
                if !(zc > 0.0) || zc > open_above as f64 {
                    return (Vec::new(), Vec::new());
                }
                let mut factor = vec![0f32; ndir];
                let mut cells = Vec::new();
                let mut acc = 0f64;
                for j in 0..ndir {
                    let w = vis.seen(c as u32, j) as f64 * mass[j];
                    factor[j] = match &layout {
                        Layout::Fine { .. } => (vis.seen(c as u32, j) as f64 / zc) as f32,
                        Layout::Coarse { omega } if omega[j] > 0.0 => {
                            (w / (zc * omega[j] as f64)) as f32
                        }
                        Layout::Coarse { .. } => 0.0,
                    };
                    if w > 0.0 {
                        acc += w;
                        cells.push((j as u32, acc / zc));
                    }
                }
                (factor, cells)
            })
            .collect();
        let mut row = vec![NO_ROW; clusters];
        let mut factor = Vec::new();
        let mut start = Vec::with_capacity(clusters + 1);
        let mut cell = Vec::new();
        let mut cdf = Vec::new();
        for (c, (f, cells)) in per.into_iter().enumerate() {
            start.push(cell.len() as u32);
            if !cells.is_empty() {
                row[c] = (factor.len() / ndir) as u32;
                factor.extend_from_slice(&f);
                cdf.push(0.0);
                for (j, x) in cells {
                    cell.push(j as u16);
                    cdf.push(x);
                }
                // The last value is 1 up to rounding; make it exactly so.
                if let Some(l) = cdf.last_mut() {
                    *l = 1.0;
                }
            }
        }
        start.push(cell.len() as u32);
        Guide {
            defensive,
            vis,
            layout,
            ndir,
            row,
            factor,
            start,
            cell,
            cdf,
        }
    }

    /// Whether cluster `c` samples by visibility at all: it is a cluster
    /// that sees some of the light, and not most of it.
    #[inline]
    pub(crate) fn active(&self, c: u32) -> bool {
        c != NO_CLUSTER && self.row[c as usize] != NO_ROW
    }

    /// How many clusters sample by visibility.
    pub(crate) fn active_clusters(&self) -> usize {
        self.row.iter().filter(|&&r| r != NO_ROW).count()
    }

    /// β.
    #[inline]
    pub(crate) fn defensive(&self) -> f32 {
        self.defensive
    }

    /// The density cluster `c` (active) draws the direction at (u, v)
    /// with ([`crate::envmap::dir_to_uv`]), given the envmap's density
    /// `p_env` there and the envmap cell `k` it lies in:
    /// β·p_env + (1 − β)·q_c.
    #[inline]
    pub(crate) fn pdf(&self, c: u32, u: f32, v: f32, k: usize, p_env: f32) -> f32 {
        let r = self.row[c as usize] as usize;
        let b = self.defensive;
        let q = match &self.layout {
            Layout::Fine { group_of_cell, .. } => {
                p_env * self.factor[r * self.ndir + group_of_cell[k] as usize]
            }
            Layout::Coarse { .. } => self.factor[r * self.ndir + self.vis.cell_of_uv(u, v)],
        };
        let p = b * p_env + (1.0 - b) * q;
        if p.is_finite() {
            p
        } else {
            b * p_env
        }
    }

    /// The visibility-restricted part for cluster `c` (active) from `u1`
    /// (direction cell) and `u2`; `None` when nothing can be drawn.
    #[inline]
    pub(crate) fn sample(&self, c: u32, u1: f64, u2: f64) -> Option<Draw> {
        let (s, e) = (
            self.start[c as usize] as usize,
            self.start[c as usize + 1] as usize,
        );
        if e == s {
            return None;
        }
        let o = self.row[c as usize] as usize;
        let (i, r1) = crate::envmap::sample_cdf(&self.cdf[s + o..e + o + 1], u1);
        let j = self.cell[s + i] as usize;
        match &self.layout {
            Layout::Fine {
                members,
                start,
                member_cdf,
                ..
            } => {
                let (s, e) = (start[j] as usize, start[j + 1] as usize);
                if e == s {
                    return None;
                }
                let (i, r2) = crate::envmap::sample_cdf(&member_cdf[s + j..e + j + 1], u2);
                Some(Draw::Cell(members[s + i] as usize, r1, r2))
            }
            Layout::Coarse { .. } => {
                let (dw, dh) = self.vis.dir_cells();
                let (d, u, v) = cell_direction_uv(dw, dh, j, r1 as f32, u2 as f32);
                Some(Draw::Direction(d, u, v))
            }
        }
    }
}

/// What [`Guide::sample`] drew.
pub(crate) enum Draw {
    /// An envmap cell, with the positions left in each draw (across its
    /// columns, across its rows).
    Cell(usize, f64, f64),
    /// A direction and its (u, v).
    Direction(Vec3, f32, f32),
}

/// [`Guide::row`] of a cluster that samples by radiance alone.
const NO_ROW: u32 = u32::MAX;

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::envmap::tests::sphere_integral;
    use crate::envmap::EnvMap;
    use crate::rng::Pcg32;
    use matflow_scene::{Image, RgbImage};
    use std::sync::Arc;

    /// A closed box [−2, 2] × [−1, 2] × [−5, 1] (normals inward) with a
    /// 1 × 1 opening in the ceiling above (0, 2, −2).
    pub(crate) fn box_with_window() -> TriMesh {
        let mut m = TriMesh::default();
        let mut quad = |a: Vec3, b: Vec3, c: Vec3, d: Vec3| {
            let base = m.positions.len() as u32;
            m.positions.extend_from_slice(&[a, b, c, d]);
            m.indices.push([base, base + 1, base + 2]);
            m.indices.push([base, base + 2, base + 3]);
        };
        let (x0, x1, y0, y1, z0, z1) = (-2.0, 2.0, -1.0, 2.0, -5.0, 1.0);
        let v = Vec3::new;
        // Floor (normal +y), walls (inward).
        quad(v(x0, y0, z0), v(x0, y0, z1), v(x1, y0, z1), v(x1, y0, z0));
        quad(v(x0, y0, z0), v(x1, y0, z0), v(x1, y1, z0), v(x0, y1, z0));
        quad(v(x0, y0, z1), v(x0, y1, z1), v(x1, y1, z1), v(x1, y0, z1));
        quad(v(x0, y0, z0), v(x0, y1, z0), v(x0, y1, z1), v(x0, y0, z1));
        quad(v(x1, y0, z0), v(x1, y0, z1), v(x1, y1, z1), v(x1, y1, z0));
        // Ceiling (normal −y) around the opening x ∈ [−0.5, 0.5], z ∈ [−2.5, −1.5].
        let ceil = |xa: f32, xb: f32, za: f32, zb: f32| {
            [v(xa, y1, za), v(xb, y1, za), v(xb, y1, zb), v(xa, y1, zb)]
        };
        for [a, b, c, d] in [
            ceil(x0, x1, z0, -2.5),
            ceil(x0, x1, -1.5, z1),
            ceil(x0, -0.5, -2.5, -1.5),
            ceil(0.5, x1, -2.5, -1.5),
        ] {
            quad(a, b, c, d);
        }
        m
    }

    /// Directions from the origin over the lower half of the sphere in
    /// front (−z): where a camera inside the room looks.
    fn primaries(n: usize) -> Vec<Vec3> {
        (0..n * n)
            .map(|i| {
                let (a, b) = ((i % n) as f32 / n as f32, (i / n) as f32 / n as f32);
                Vec3::new(2.0 * a - 1.0, -b, -1.0).normalize()
            })
            .collect()
    }

    fn visibility(mesh: &TriMesh, params: &GuideParams) -> Visibility {
        let normals: Vec<Vec3> = (0..mesh.triangle_count())
            .map(|i| mesh.face_normal(i))
            .collect();
        let bvh = Bvh::build(mesh);
        Visibility::build(
            &normals,
            mesh.triangle_count(),
            &bvh,
            &mesh.openness,
            &primaries(128),
            params,
        )
    }

    pub(crate) fn sky(w: usize, h: usize) -> RgbImage {
        Image::from_fn(w, h, |x, y| {
            let d =
                crate::envmap::uv_to_dir((x as f32 + 0.5) / w as f32, y as f32 / (h - 1) as f32);
            let sun = if d.dot(Vec3::new(0.3, 0.9, -0.3).normalize()) > 0.995 {
                200.0
            } else {
                0.0
            };
            Vec3::new(0.4, 0.6, 1.0) * (0.2 + d.y.max(0.0)) + Vec3::splat(sun)
        })
    }

    #[test]
    fn a_closed_room_sees_the_sky_only_through_its_opening() {
        let mesh = box_with_window();
        let vis = visibility(&mesh, &GuideParams::default());
        assert!(vis.clusters() > 20, "{} clusters", vis.clusters());
        assert!(
            vis.open_fraction() < 0.05,
            "open fraction {}",
            vis.open_fraction()
        );
        // The floor below the opening sees straight up; nothing sees down.
        let c = vis.cluster_of(Vec3::new(0.0, -0.99, -2.0));
        assert_ne!(c, NO_CLUSTER);
        assert!(vis.seen(c, vis.cell_of(Vec3::Y)) > 0.0);
        assert_eq!(vis.seen(c, vis.cell_of(-Vec3::Y)), 0.0);
        // A direction that leaves through the walls is blocked from all of it.
        assert_eq!(
            vis.seen(c, vis.cell_of(Vec3::new(1.0, 0.1, 0.0).normalize())),
            0.0
        );
        assert_eq!(vis.cluster_of(Vec3::new(0.0, 50.0, 0.0)), NO_CLUSTER);
        // Without the ceiling the room is open.
        let mut open = mesh.clone();
        open.indices.truncate(2);
        assert!(visibility(&open, &GuideParams::default()).open_fraction() > 0.2);
        // Measured twice, the same.
        let again = visibility(&mesh, &GuideParams::default());
        assert_eq!(again.vis, vis.vis);
    }

    /// For a guided cluster, with an envmap coarser (8×4: uniform inside
    /// direction cells) and finer (256×128: the envmap's own density
    /// inside them) than the direction grid: the density integrates to 1,
    /// sampling reports it, and f/pdf averages to ∫f.
    #[test]
    fn guided_density_is_normalised_and_unbiased() {
        let mesh = box_with_window();
        let vis = Arc::new(visibility(&mesh, &GuideParams::default()));
        let p = Vec3::new(0.3, -0.99, -2.2);
        for (w, h) in [(8, 4), (256, 128)] {
            let env = EnvMap::new(&sky(w, h)).unwrap().guided(vis.clone());
            let c = env.cluster(p);
            assert!(env.guided_clusters() > 0);
            // The density is sharp where the opening's edge crosses it:
            // a fine quadrature.
            let total = sphere_integral(3000, |d| env.eval_pdf_in(c, d).1 as f64);
            assert!((total - 1.0).abs() < 5e-3, "{w}x{h}: ∫pdf = {total}");
            let f = |d: Vec3| 1.0 + 2.0 * (d.y as f64).max(0.0) + 0.3 * d.x as f64;
            let quad = sphere_integral(1000, f);
            let mut rng = Pcg32::new(5, 6);
            let (mut est, m) = (0.0f64, 400_000);
            for _ in 0..m {
                let Some((d, l, pdf)) = env.sample_in(c, rng.next_f32(), rng.next_f32()) else {
                    continue;
                };
                let (le, q) = env.eval_pdf_in(c, d);
                // At the poles the azimuth a sample was drawn at is lost.
                assert!(
                    (pdf - q).abs() <= 1e-3 * pdf.max(q) || d.y.abs() > 0.9999,
                    "{w}x{h}: {pdf} vs {q}"
                );
                assert!((l - le).abs().max_element() <= 1e-3 * (1.0 + le.max_element()));
                est += f(d) / pdf as f64;
            }
            est /= m as f64;
            assert!((est - quad).abs() / quad < 0.02, "{w}x{h}: {est} vs {quad}");
        }
    }

    /// Most guided light samples of the floor under the opening leave
    /// through it; by radiance alone most hit the room.
    #[test]
    fn guided_samples_find_the_opening() {
        let mesh = box_with_window();
        let normals: Vec<Vec3> = (0..mesh.triangle_count())
            .map(|i| mesh.face_normal(i))
            .collect();
        let bvh = Bvh::build(&mesh);
        let vis = Arc::new(Visibility::build(
            &normals,
            mesh.triangle_count(),
            &bvh,
            &mesh.openness,
            &primaries(128),
            &GuideParams::default(),
        ));
        let p = Vec3::new(-1.0, -0.99, -3.5);
        for (w, h) in [(32, 16), (512, 256)] {
            let plain = EnvMap::new(&sky(w, h)).unwrap();
            let guided = plain.clone().guided(vis.clone());
            let c = guided.cluster(p);
            let through = |env: &EnvMap| {
                let mut rng = Pcg32::new(1, 2);
                (0..4000)
                    .filter(|_| {
                        env.sample_in(c, rng.next_f32(), rng.next_f32())
                            .is_some_and(|(d, _, _)| {
                                d.y > 0.0
                                    && !bvh.occluded(p + Vec3::Y * 1e-3, d, 0.0, f32::INFINITY)
                            })
                    })
                    .count()
            };
            let (a, b) = (through(&plain), through(&guided));
            assert!(
                a < 400 && b > 2000,
                "{w}x{h}: {a} plain, {b} guided of 4000"
            );
        }
    }

    /// The room as a rendered scene: a two-sided diffuse object seen from
    /// inside, the camera looking at the floor under the opening.
    pub(crate) fn room_scene(n: usize, env: RgbImage, mesh: TriMesh) -> crate::RenderScene {
        let cam = matflow_scene::Camera::new(n, n);
        let maps = matflow_scene::MaterialMaps::uniform(n, n, Vec3::splat(0.5), 1.0, 0.0);
        let room = crate::SceneObject {
            mesh,
            normals: Vec::new(),
            surface: crate::Surface::Diffuse(Vec3::splat(0.6)),
            uvs: Vec::new(),
            texture: None,
        };
        crate::RenderScene::with_objects(
            cam,
            TriMesh::default(),
            &maps,
            EnvMap::new(&env).unwrap(),
            &[room],
        )
        .unwrap()
    }

    /// Render options of the closed-room tests: `spp` samples, `seed`,
    /// paths of up to `max_depth` segments.
    pub(crate) fn opts(spp: u32, seed: u64, max_depth: u32) -> crate::RenderOptions {
        crate::RenderOptions {
            spp,
            seed,
            max_depth,
            ..Default::default()
        }
    }

    /// The image of `s` rendered with `o`.
    pub(crate) fn render(s: &crate::RenderScene, o: crate::RenderOptions) -> RgbImage {
        crate::render(s, &o, &|_, _| {}).image
    }

    pub(crate) fn rmse(a: &RgbImage, b: &RgbImage) -> f64 {
        let s: f64 = a
            .data
            .iter()
            .zip(&b.data)
            .map(|(x, y)| (*x - *y).length_squared() as f64)
            .sum();
        (s / a.data.len() as f64).sqrt()
    }

    pub(crate) fn mean(a: &RgbImage) -> f64 {
        a.data.iter().map(|x| x.element_sum() as f64).sum::<f64>() / a.data.len() as f64
    }

    /// Inside a closed room lit through one opening, the guided renderer
    /// converges to the same image as sampling by radiance alone, with
    /// far less noise at equal samples, bit-identically on any number of
    /// threads; an open scene is left unguided.
    #[test]
    fn a_guided_render_of_a_closed_room_is_unbiased_and_less_noisy() {
        let n = 24;
        let guided = room_scene(n, sky(64, 32), box_with_window());
        assert!(guided.light_visibility.is_some(), "a closed room is guided");
        assert!(guided.env.guided_clusters() > 0);
        let mut plain = room_scene(n, sky(64, 32), box_with_window());
        assert!(!plain.set_light_guide(None));
        // Direct light (depth 2), where guiding acts, and all bounces.
        for (depth, gain) in [(2, 0.5), (4, 0.9)] {
            let (rg, rp) = (
                render(&guided, opts(4096, 99, depth)),
                render(&plain, opts(4096, 99, depth)),
            );
            let (mg, mp) = (mean(&rg), mean(&rp));
            assert!(
                (mg - mp).abs() < 0.02 * mp,
                "depth {depth}: converged means {mg} guided vs {mp} plain"
            );
            let eg = rmse(&render(&guided, opts(16, 1, depth)), &rg);
            let ep = rmse(&render(&plain, opts(16, 1, depth)), &rg);
            assert!(
                eg < gain * ep,
                "depth {depth}: 16 spp error {eg} guided vs {ep} plain"
            );
        }
        let noisy = |s: &crate::RenderScene| render(s, opts(16, 1, 4));
        // Thread count does not change a guided render.
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| noisy(&guided));
        assert_eq!(a.data, noisy(&guided).data);
        // The floor alone is open: not guided.
        let mut floor = box_with_window();
        floor.indices.truncate(2);
        assert!(room_scene(n, sky(64, 32), floor).light_visibility.is_none());
    }
}
