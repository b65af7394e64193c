//! Bounding volume hierarchy over a triangle mesh and the two ray queries the
//! renderer needs: closest hit and occlusion.
//!
//! The topology comes from `obvhs`' BVH2 builder (PLOC + reinsertion, leaves
//! of at most four triangles); it is then collapsed into an 8-wide BVH whose
//! nodes hold their children's boxes as structure-of-arrays, so one ray is
//! tested against four boxes per SIMD operation, and each leaf holds blocks
//! of four triangles, tested at once (Embree's BVH8 + Triangle4 layout).
//! A traversal is a state stepped node by node (one ray alone, or many
//! in turn as a stream), which prefetches the slot it visits next.
//! Boxes are
//! stored uncompressed in f32: `obvhs`' CWBVH, which quantises child boxes
//! to 8 bits, misses hits on axis-aligned planar geometry (DEPENDENCIES.md),
//! and depth meshes of rooms are full of such planes; zero-thickness boxes
//! are exact here, and the far distance of each slab test is widened by
//! 2γ₃ (pbrt's conservative box test) so rounding never drops a box.
//!
//! The triangle test is Möller–Trumbore with a small barycentric tolerance
//! so rays through shared edges of the grid mesh never slip between
//! triangles. Each lane evaluates exactly the scalar formula of
//! [`intersect_tri`] (same operations in the same order, no fused
//! multiply-add), so the wide test and the brute-force oracle agree bit for
//! bit. Closest hits at equal t go to the lower original triangle index, so
//! the answer does not depend on traversal order — up to one rounding
//! effect: a triangle lying in the face of its box can compute a t an ulp
//! below the box's own rounded entry, so a traversal that already holds a
//! hit at that t may skip it (about 2 camera rays in 100 000 on `indoor`
//! hit the neighbouring triangle of a shared edge instead, at the same
//! point to within an ulp).
//!
//! Camera rays of one pixel share their origin and nearly their direction;
//! [`Bvh::intersect_packet`] takes up to [`PACKET`] of them down the tree
//! at once with one interval box test per node (Wald's packet traversal,
//! with the frustum bound by interval arithmetic instead of planes).

use std::borrow::Cow;
use std::time::Duration;

use glam::{BVec4A, Vec3, Vec4};
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::bvh2::Bvh2;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

use crate::mesh::TriMesh;

/// Barycentric tolerance (relative, so independent of scale).
const BARY_EPS: f32 = 1e-4;

/// 1 + 2γ₃ (pbrt-v4's bound on the rounding of the slab test).
const SLAB_WIDEN: f32 = 1.0 + 2.0 * (3.0 * f32::EPSILON * 0.5) / (1.0 - 3.0 * f32::EPSILON * 0.5);

/// Deepest traversal stack: a 4-wide tree of 2³² triangles is far shallower,
/// but the builder does not bound depth, so the stack grows on the heap past
/// this (never in practice).
const STACK: usize = 128;

/// A closest-hit result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the (not necessarily unit) ray direction.
    pub t: f32,
    /// Index of the triangle in the original mesh.
    pub prim: u32,
    /// Barycentric coordinates of vertices 1 and 2.
    pub u: f32,
    pub v: f32,
}

/// Child slot of a wide node: an inner node index, a leaf (high bit set,
/// index of its triangle block) or empty.
const LEAF: u32 = 1 << 31;
const EMPTY: u32 = u32::MAX;
/// The first-block index in a leaf slot (bits 28–29 hold the count less one).
const BLOCK_INDEX: u32 = 0x0fff_ffff;

/// Children per node. The boxes of a node's children are tested together,
/// four lanes at a time (an 8-wide AVX version of the box test measured no
/// faster: traversal waits on memory, not arithmetic).
const LANES: usize = 8;
const HALVES: usize = LANES / 4;

/// Words per stored node: six bound vectors of `LANES` lanes, then the
/// child slots.
const NODE_WORDS: usize = 6 * LANES + LANES;

/// A hierarchy as flat words ([`Bvh::to_words`]); read back, the arrays
/// may borrow the stored bytes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BvhWords<'a> {
    pub root: u32,
    pub triangle_count: u32,
    pub nodes: Cow<'a, [u32]>,
    /// Per block of four triangles, their indices (`u32::MAX`: unused).
    pub prims: Cow<'a, [u32]>,
}

/// Stored hierarchy words that cannot be a hierarchy of the mesh.
#[derive(Debug, thiserror::Error)]
#[error("stored BVH: {0}")]
pub struct BvhError(&'static str);

/// A node's children's boxes as [min x, min y, min z, max x, max y, max z],
/// each a lane per child. Empty slots have min = +∞, max = −∞ and so are
/// never entered.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node {
    bounds: [[Vec4; HALVES]; 6],
    child: [u32; LANES],
}

impl Node {
    fn empty() -> Node {
        let inf = [Vec4::INFINITY; HALVES];
        let ninf = [Vec4::NEG_INFINITY; HALVES];
        Node {
            bounds: [inf, inf, inf, ninf, ninf, ninf],
            child: [EMPTY; LANES],
        }
    }

    fn set_lane(&mut self, lane: usize, min: [f32; 3], max: [f32; 3], slot: u32) {
        let (h, l) = (lane / 4, lane % 4);
        for a in 0..3 {
            self.bounds[a][h][l] = min[a];
            self.bounds[a + 3][h][l] = max[a];
        }
        self.child[lane] = slot;
    }
}

/// Up to four triangles, lane per triangle: v0, edge 1, edge 2 and the
/// original index. Unused lanes have zero edges (determinant 0: no hit).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Tri4 {
    v0: [Vec4; 3],
    e1: [Vec4; 3],
    e2: [Vec4; 3],
    prim: [u32; 4],
}

impl Tri4 {
    fn empty() -> Tri4 {
        Tri4 {
            v0: [Vec4::ZERO; 3],
            e1: [Vec4::ZERO; 3],
            e2: [Vec4::ZERO; 3],
            prim: [u32::MAX; 4],
        }
    }

    /// Lane `lane` becomes triangle `prim` with vertices `v`: the one place
    /// the edges are computed, so a block rebuilt from a stored hierarchy
    /// ([`Bvh::from_words`]) has the built one's bits.
    fn set_lane(&mut self, lane: usize, v: [glam::Vec3A; 3], prim: u32) {
        let (e1, e2) = (v[1] - v[0], v[2] - v[0]);
        for a in 0..3 {
            self.v0[a][lane] = v[0][a];
            self.e1[a][lane] = e1[a];
            self.e2[a][lane] = e2[a];
        }
        self.prim[lane] = prim;
    }
}

#[derive(Clone)]
pub struct Bvh {
    nodes: Vec<Node>,
    tris: Vec<Tri4>,
    triangle_count: usize,
    /// Root slot: an inner node, a single leaf, or empty.
    root: u32,
    /// Triangles added after the build ([`Bvh::with_added`]), in a
    /// hierarchy of their own; every query asks it after this one.
    added: Option<Box<Bvh>>,
}

/// Möller–Trumbore with the barycentric tolerance, written out
/// component-wise in the order every SIMD lane of the wide test uses.
/// Returns (t, u, v) for t in (tmin, tmax).
#[inline(always)]
fn intersect_tri(
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
    o: Vec3,
    d: Vec3,
    tmin: f32,
    tmax: f32,
) -> Option<(f32, f32, f32)> {
    let px = d.y * e2.z - d.z * e2.y;
    let py = d.z * e2.x - d.x * e2.z;
    let pz = d.x * e2.y - d.y * e2.x;
    let det = e1.x * px + e1.y * py + e1.z * pz;
    let inv = 1.0 / det;
    let sx = o.x - v0.x;
    let sy = o.y - v0.y;
    let sz = o.z - v0.z;
    let u = (sx * px + sy * py + sz * pz) * inv;
    let qx = sy * e1.z - sz * e1.y;
    let qy = sz * e1.x - sx * e1.z;
    let qz = sx * e1.y - sy * e1.x;
    let v = (d.x * qx + d.y * qy + d.z * qz) * inv;
    let t = (e2.x * qx + e2.y * qy + e2.z * qz) * inv;
    let ok = det != 0.0
        && det.is_finite()
        && (-BARY_EPS..=1.0 + BARY_EPS).contains(&u)
        && v >= -BARY_EPS
        && u + v <= 1.0 + BARY_EPS
        && t > tmin
        && t < tmax;
    ok.then_some((t, u, v))
}

/// The ray as the wide tests need it: splatted origin and direction,
/// the safe reciprocal direction and, per axis, which bound is near.
struct WideRay {
    o: [Vec4; 3],
    d: [Vec4; 3],
    inv: [Vec4; 3],
    near: [usize; 3],
    far: [usize; 3],
}

impl WideRay {
    #[inline(always)]
    fn new(o: Vec3, d: Vec3) -> Self {
        let inv = [safe_inv(d.x), safe_inv(d.y), safe_inv(d.z)];
        WideRay {
            o: [Vec4::splat(o.x), Vec4::splat(o.y), Vec4::splat(o.z)],
            d: [Vec4::splat(d.x), Vec4::splat(d.y), Vec4::splat(d.z)],
            inv: inv.map(Vec4::splat),
            near: [0, 1, 2].map(|a| if inv[a] < 0.0 { 3 + a } else { a }),
            far: [0, 1, 2].map(|a| if inv[a] < 0.0 { a } else { 3 + a }),
        }
    }

    /// Entry distances of a node's boxes (lane per child) and the bit mask
    /// of the boxes the segment (tmin, tmax] enters.
    #[inline(always)]
    fn slabs(&self, n: &Node, tmin: f32, tmax: f32) -> ([Vec4; HALVES], u32) {
        let b = &n.bounds;
        let (bnx, bny, bnz) = (&b[self.near[0]], &b[self.near[1]], &b[self.near[2]]);
        let (bfx, bfy, bfz) = (&b[self.far[0]], &b[self.far[1]], &b[self.far[2]]);
        let tmin4 = Vec4::splat(tmin);
        let tmax4 = Vec4::splat(tmax);
        let mut tn = [Vec4::ZERO; HALVES];
        let mut mask = 0u32;
        for h in 0..HALVES {
            let t0x = (bnx[h] - self.o[0]) * self.inv[0];
            let t0y = (bny[h] - self.o[1]) * self.inv[1];
            let t0z = (bnz[h] - self.o[2]) * self.inv[2];
            let t1x = (bfx[h] - self.o[0]) * self.inv[0];
            let t1y = (bfy[h] - self.o[1]) * self.inv[1];
            let t1z = (bfz[h] - self.o[2]) * self.inv[2];
            let near = t0x.max(t0y).max(t0z.max(tmin4));
            let far = t1x.min(t1y).min(t1z.min(tmax4)) * SLAB_WIDEN;
            mask |= near.cmple(far).bitmask() << (4 * h);
            tn[h] = near;
        }
        (tn, mask)
    }
}

/// The four lanes of [`intersect_tri`] for the ray with splatted origin `o`
/// and direction `d`: hit distances and barycentrics, and which lanes hit
/// inside (tmin, tmax).
#[inline(always)]
fn triangles4(
    o: &[Vec4; 3],
    d: &[Vec4; 3],
    t: &Tri4,
    tmin: f32,
    tmax: Vec4,
) -> (Vec4, Vec4, Vec4, BVec4A) {
    let [dx, dy, dz] = *d;
    let [e1x, e1y, e1z] = t.e1;
    let [e2x, e2y, e2z] = t.e2;
    let px = dy * e2z - dz * e2y;
    let py = dz * e2x - dx * e2z;
    let pz = dx * e2y - dy * e2x;
    let det = e1x * px + e1y * py + e1z * pz;
    let inv = Vec4::ONE / det;
    let sx = o[0] - t.v0[0];
    let sy = o[1] - t.v0[1];
    let sz = o[2] - t.v0[2];
    let u = (sx * px + sy * py + sz * pz) * inv;
    let qx = sy * e1z - sz * e1y;
    let qy = sz * e1x - sx * e1z;
    let qz = sx * e1y - sy * e1x;
    let v = (dx * qx + dy * qy + dz * qz) * inv;
    let tt = (e2x * qx + e2y * qy + e2z * qz) * inv;
    let eps = Vec4::splat(BARY_EPS);
    let one = Vec4::splat(1.0 + BARY_EPS);
    let ok = det.cmpne(Vec4::ZERO)
        & det.abs().cmplt(Vec4::INFINITY)
        & u.cmpge(-eps)
        & u.cmple(one)
        & v.cmpge(-eps)
        & (u + v).cmple(one)
        & tt.cmpgt(Vec4::splat(tmin))
        & tt.cmplt(tmax);
    (tt, u, v, ok)
}

/// The reciprocal of a direction component, with a zero component made a
/// tiny one so that (bound − o)·(1/d) is never 0·∞ = NaN but finite or
/// ±∞ with the right sign.
#[inline(always)]
fn safe_inv(x: f32) -> f32 {
    if x.abs() < 1e-30 {
        1e30f32.copysign(x)
    } else {
        1.0 / x
    }
}

/// Most rays one [`Bvh::intersect_packet`] traversal carries; longer
/// slices are traced in packets of this many.
pub const PACKET: usize = 64;

/// One ray's closest hit so far and the bound on further hits: below
/// the ray's tmax, then at or below the best t (ties are resolved by
/// index, so a hit at exactly that t may still win).
#[derive(Clone, Copy)]
struct Closest {
    best: Option<Hit>,
    limit: f32,
    inclusive: bool,
}

impl Closest {
    fn new(tmax: f32) -> Closest {
        Closest {
            best: None,
            limit: tmax,
            inclusive: false,
        }
    }

    /// Tests the ray (splatted origin `o`, direction `d`) against a leaf's
    /// triangle blocks; true when the best hit changed.
    #[inline(always)]
    fn leaf(&mut self, o: &[Vec4; 3], d: &[Vec4; 3], blocks: &[Tri4], tmin: f32) -> bool {
        let mut changed = false;
        for tri in blocks {
            let lim = if self.inclusive {
                self.limit.next_up_f32()
            } else {
                self.limit
            };
            let (t, u, v, ok) = triangles4(o, d, tri, tmin, Vec4::splat(lim));
            let mut bits = ok.bitmask();
            while bits != 0 {
                let lane = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let (t, prim) = (t[lane], tri.prim[lane]);
                let better = match self.best {
                    None => true,
                    Some(b) => t < b.t || (t == b.t && prim < b.prim),
                };
                if better {
                    self.best = Some(Hit {
                        t,
                        prim,
                        u: u[lane],
                        v: v[lane],
                    });
                    self.limit = t;
                    self.inclusive = true;
                    changed = true;
                }
            }
        }
        changed
    }
}

/// Visits the nearest entered child next: pushes the other entered
/// children of `node` (bit mask `bits`, entry distances `tn`) as they
/// come, prefetches the nearest one (with `prefetch_rest`, the pushed ones
/// too) and returns it, or `None` when no child is entered. Finding the
/// nearest costs one pass; sorting the rest pays little, as most
/// incoherent rays end without a hit and visit every entered child.
#[inline(always)]
fn nearest_first(
    bvh: &Bvh,
    node: &Node,
    mut bits: u32,
    tn: &[Vec4; HALVES],
    stack: &mut Stack,
    prefetch_rest: bool,
) -> Option<(u32, f32)> {
    if bits == 0 {
        return None;
    }
    let mut entry = [0f32; LANES];
    for h in 0..HALVES {
        tn[h].write_to_slice(&mut entry[4 * h..4 * h + 4]);
    }
    let mut best = bits.trailing_zeros() as usize;
    let mut rest = bits & (bits - 1);
    while rest != 0 {
        let l = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        best = if entry[l] < entry[best] { l } else { best };
    }
    bits &= !(1 << best);
    while bits != 0 {
        let l = bits.trailing_zeros() as usize;
        bits &= bits - 1;
        if prefetch_rest {
            prefetch(bvh, node.child[l]);
        }
        stack.push((node.child[l], entry[l]));
    }
    prefetch(bvh, node.child[best]);
    Some((node.child[best], entry[best]))
}

impl Bvh {
    /// Builds the hierarchy. Degenerate (zero-area or non-finite) triangles
    /// are kept out of it.
    pub fn build(mesh: &TriMesh) -> Bvh {
        Bvh::build_from(mesh, 0)
    }

    /// This hierarchy with `mesh`'s triangles from index `first` on added
    /// (their hits numbered as in `mesh`), where this one was built over
    /// `mesh`'s first `first` triangles: inserted objects without
    /// rebuilding the scene's hierarchy. The added triangles get a
    /// hierarchy of their own, asked after this one with the nearer hit
    /// bounding it, so every query answers as [`Bvh::build`]`(mesh)`'s
    /// does (the tie rule included: at equal t the lower index, which is
    /// this one's), up to the module's rounding effect.
    pub fn with_added(mut self, mesh: &TriMesh, first: usize) -> Bvh {
        let added = Bvh::build_from(mesh, first);
        self.triangle_count += added.triangle_count;
        self.added = (added.root != EMPTY).then(|| Box::new(added));
        self
    }

    /// The hierarchy of `mesh`'s triangles from index `first` on.
    fn build_from(mesh: &TriMesh, first: usize) -> Bvh {
        let mut tris = Vec::with_capacity(mesh.indices.len().saturating_sub(first));
        let mut orig = Vec::with_capacity(mesh.indices.len().saturating_sub(first));
        for (i, idx) in mesh.indices.iter().enumerate().skip(first) {
            let [a, b, c] = idx.map(|k| glam::Vec3A::from(mesh.positions[k as usize]));
            let area2 = (b - a).cross(c - a).length_squared();
            if !(area2 > 0.0) || !area2.is_finite() {
                continue;
            }
            tris.push(Triangle {
                v0: a,
                v1: b,
                v2: c,
            });
            orig.push(i as u32);
        }
        if tris.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                tris: Vec::new(),
                triangle_count: 0,
                root: EMPTY,
                added: None,
            };
        }
        // Leaves of up to four triangles (one 4-wide test); the builder's
        // other defaults. Measured on indoor: slower builds (pre-splits,
        // more reinsertion) gave no faster traversal, leaves of 1–2 were
        // ~25 % slower, of 8 the same.
        let params = BvhBuildParams {
            max_prims_per_leaf: 4,
            ..BvhBuildParams::medium_build()
        };
        let bvh2 = build_bvh2_from_tris(&tris, params, &mut Duration::default());
        let mut out = Bvh {
            nodes: Vec::with_capacity(bvh2.nodes.len() / 2),
            tris: Vec::with_capacity(tris.len() / 2),
            triangle_count: tris.len(),
            root: EMPTY,
            added: None,
        };
        out.root = out.collapse(&bvh2, 0, &tris, &orig);
        out.nodes = crate::huge::huge(out.nodes);
        out.tris = crate::huge::huge(out.tris);
        out
    }

    /// Emits the BVH2 subtree at `id` as a wide slot (depth first, so a
    /// node's children lie close to it in memory).
    fn collapse(&mut self, b: &Bvh2, id: usize, tris: &[Triangle], orig: &[u32]) -> u32 {
        let node = &b.nodes[id];
        if node.prim_count > 0 {
            let first = node.first_index as usize;
            let prims = &b.primitive_indices[first..first + node.prim_count as usize];
            return self.leaf_of(prims, tris, orig);
        }
        // Open the largest inner child until the node is full.
        let mut kids: Vec<usize> = vec![node.first_index as usize, node.first_index as usize + 1];
        while kids.len() < LANES {
            let best = kids
                .iter()
                .enumerate()
                .filter(|(_, &k)| b.nodes[k].prim_count == 0)
                .max_by(|(_, &x), (_, &y)| {
                    let ax = b.nodes[x].aabb.half_area();
                    let ay = b.nodes[y].aabb.half_area();
                    ax.total_cmp(&ay)
                })
                .map(|(i, _)| i);
            let Some(i) = best else { break };
            let k = kids.remove(i);
            let first = b.nodes[k].first_index as usize;
            kids.insert(i, first + 1);
            kids.insert(i, first);
        }
        let me = self.nodes.len();
        self.nodes.push(Node::empty());
        for (lane, &k) in kids.iter().enumerate() {
            let bb = b.nodes[k].aabb;
            let slot = self.collapse(b, k, tris, orig);
            self.nodes[me].set_lane(lane, bb.min.into(), bb.max.into(), slot);
        }
        me as u32
    }

    /// A slot for these triangles: one leaf of up to four blocks of four,
    /// or (never with the builder's leaf limit, but kept correct) an inner
    /// node over up to four such parts.
    fn leaf_of(&mut self, prims: &[u32], tris: &[Triangle], orig: &[u32]) -> u32 {
        if prims.len() > 16 {
            let me = self.nodes.len();
            self.nodes.push(Node::empty());
            for (lane, part) in prims.chunks(prims.len().div_ceil(LANES)).enumerate() {
                let slot = self.leaf_of(part, tris, orig);
                let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
                for &pi in part {
                    let t = &tris[pi as usize];
                    for v in [t.v0, t.v1, t.v2] {
                        for a in 0..3 {
                            lo[a] = lo[a].min(v[a]);
                            hi[a] = hi[a].max(v[a]);
                        }
                    }
                }
                self.nodes[me].set_lane(lane, lo, hi, slot);
            }
            return me as u32;
        }
        let at = self.tris.len();
        for chunk in prims.chunks(4) {
            let mut t = Tri4::empty();
            for (lane, &pi) in chunk.iter().enumerate() {
                let tri = &tris[pi as usize];
                t.set_lane(lane, [tri.v0, tri.v1, tri.v2], orig[pi as usize]);
            }
            self.tris.push(t);
        }
        // The blocks of a leaf are consecutive; the slot keeps the first
        // block's index and, in bits 28–29, the count less one.
        let blocks = self.tris.len() - at;
        LEAF | ((blocks as u32 - 1) << 28) | at as u32
    }

    /// The hierarchy as words (box bounds as their bits; of each block of
    /// four triangles only their indices, the vertices being the mesh's),
    /// to be stored beside its mesh and read back with
    /// [`Bvh::from_words`] instead of building it again. `None` for one
    /// with added triangles ([`Bvh::with_added`]), which is never stored.
    pub fn to_words(&self) -> Option<BvhWords<'static>> {
        if self.added.is_some() {
            return None;
        }
        let mut nodes = Vec::with_capacity(self.nodes.len() * NODE_WORDS);
        for n in &self.nodes {
            for axis in &n.bounds {
                for half in axis {
                    nodes.extend(half.to_array().map(f32::to_bits));
                }
            }
            nodes.extend_from_slice(&n.child);
        }
        Some(BvhWords {
            root: self.root,
            triangle_count: self.triangle_count as u32,
            nodes: nodes.into(),
            prims: self
                .tris
                .iter()
                .flat_map(|t| t.prim)
                .collect::<Vec<_>>()
                .into(),
        })
    }

    /// The hierarchy [`Bvh::build`]`(mesh)` built, from its
    /// [`Bvh::to_words`]: it answers every query as that one does (its
    /// triangle blocks are made from `mesh` as the build makes them).
    /// Whatever the words, using the result cannot loop or index out of
    /// range: every inner child lies after its parent, every leaf's blocks
    /// exist, every triangle index is the mesh's (or an unused lane).
    pub fn from_words(w: &BvhWords<'_>, mesh: &TriMesh) -> Result<Bvh, BvhError> {
        if !w.nodes.len().is_multiple_of(NODE_WORDS) || !w.prims.len().is_multiple_of(4) {
            return Err(BvhError("the arrays are cut short"));
        }
        let (n_nodes, n_tris) = (w.nodes.len() / NODE_WORDS, w.prims.len() / 4);
        if w.triangle_count as usize > mesh.triangle_count() {
            return Err(BvhError("more triangles than the mesh has"));
        }
        let slot_ok = |slot: u32, parent: Option<usize>| -> bool {
            if slot == EMPTY {
                return true;
            }
            if slot & LEAF != 0 {
                let at = (slot & BLOCK_INDEX) as usize;
                let count = ((slot >> 28) & 3) as usize + 1;
                return slot & !(LEAF | BLOCK_INDEX | 3 << 28) == 0 && at + count <= n_tris;
            }
            (slot as usize) < n_nodes && parent.is_none_or(|p| slot as usize > p)
        };
        if !slot_ok(w.root, None) {
            return Err(BvhError("the root is out of range"));
        }
        let f = |c: &[u32]| Vec4::from_array([c[0], c[1], c[2], c[3]].map(f32::from_bits));
        let mut nodes = Vec::with_capacity(n_nodes);
        for (i, c) in w.nodes.chunks_exact(NODE_WORDS).enumerate() {
            let mut n = Node::empty();
            for (a, axis) in n.bounds.iter_mut().enumerate() {
                for (h, half) in axis.iter_mut().enumerate() {
                    *half = f(&c[(a * HALVES + h) * 4..]);
                }
            }
            n.child.copy_from_slice(&c[6 * HALVES * 4..]);
            if !n.child.iter().all(|&s| slot_ok(s, Some(i))) {
                return Err(BvhError("a node's child is out of range or before it"));
            }
            nodes.push(n);
        }
        let mut tris = Vec::with_capacity(n_tris);
        for prim in w.prims.chunks_exact(4) {
            let mut t = Tri4::empty();
            for (lane, &p) in prim.iter().enumerate() {
                if p == u32::MAX {
                    continue;
                }
                let idx = mesh
                    .indices
                    .get(p as usize)
                    .ok_or(BvhError("a triangle index is out of range"))?;
                let mut v = [glam::Vec3A::ZERO; 3];
                for (k, &i) in idx.iter().enumerate() {
                    v[k] = glam::Vec3A::from(
                        *mesh
                            .positions
                            .get(i as usize)
                            .ok_or(BvhError("a vertex index is out of range"))?,
                    );
                }
                t.set_lane(lane, v, p);
            }
            tris.push(t);
        }
        Ok(Bvh {
            nodes: crate::huge::huge(nodes),
            tris: crate::huge::huge(tris),
            triangle_count: w.triangle_count as usize,
            root: w.root,
            added: None,
        })
    }

    pub fn triangle_count(&self) -> usize {
        self.triangle_count
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Closest hit with t in (tmin, tmax). Ties at equal t go to the lower
    /// original triangle index, so the answer does not depend on the order
    /// in which the hierarchy is traversed.
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        let hit = self.intersect_here(origin, dir, tmin, tmax);
        match &self.added {
            None => hit,
            Some(a) => a.nearer(hit, origin, dir, tmin, tmax),
        }
    }

    /// `hit` (this hierarchy's owner's), or a nearer one of this one's.
    /// The bound is open, so a tie stays with `hit`: its index is lower.
    #[inline]
    fn nearer(
        &self,
        hit: Option<Hit>,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
    ) -> Option<Hit> {
        let bound = hit.map_or(tmax, |h| h.t);
        self.intersect_here(origin, dir, tmin, bound).or(hit)
    }

    #[inline]
    fn intersect_here(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        if self.root == EMPTY {
            return None;
        }
        let mut w = Walk::new(self, origin, dir, tmin, tmax);
        loop {
            if let Some(hit) = w.step_closest(self) {
                return hit;
            }
        }
    }

    /// Closest hits of rays that share one origin (the camera rays of one
    /// pixel): `out[i]` is [`Bvh::intersect`]`(origin, dirs[i], tmin, tmax)`,
    /// computed by the same triangle test, with the same tie rule and the
    /// same rounding exception (module docs). Up to [`PACKET`] rays go down the tree
    /// together: a node's boxes are tested once for the whole packet, with
    /// slab intervals bounded over the rays' reciprocal directions (interval
    /// arithmetic, tight when the rays are close, conservative always), so
    /// each node is fetched once per packet instead of once per ray; only
    /// the triangles of the leaves reached are tested ray by ray. Coherent
    /// rays gain most; divergent ones are still answered exactly.
    pub fn intersect_packet(
        &self,
        origin: Vec3,
        dirs: &[Vec3],
        tmin: f32,
        tmax: f32,
        out: &mut [Option<Hit>],
    ) {
        assert_eq!(dirs.len(), out.len(), "one result per ray");
        for (d, o) in dirs.chunks(PACKET).zip(out.chunks_mut(PACKET)) {
            self.packet(origin, d, tmin, tmax, o);
        }
        if let Some(a) = &self.added {
            for (d, o) in dirs.iter().zip(out.iter_mut()) {
                *o = a.nearer(*o, origin, *d, tmin, tmax);
            }
        }
    }

    fn packet(&self, origin: Vec3, dirs: &[Vec3], tmin: f32, tmax: f32, out: &mut [Option<Hit>]) {
        out.fill(None);
        if self.root == EMPTY || dirs.is_empty() {
            return;
        }
        let mut hits = [Closest::new(tmax); PACKET];
        let hits = &mut hits[..dirs.len()];
        // Bounds of the reciprocal directions per axis over the packet.
        let mut inv_lo = [f32::INFINITY; 3];
        let mut inv_hi = [f32::NEG_INFINITY; 3];
        for d in dirs {
            for a in 0..3 {
                let inv = safe_inv(d[a]);
                inv_lo[a] = inv_lo[a].min(inv);
                inv_hi[a] = inv_hi[a].max(inv);
            }
        }
        let o4 = [origin.x, origin.y, origin.z].map(Vec4::splat);
        let il = inv_lo.map(Vec4::splat);
        let ih = inv_hi.map(Vec4::splat);
        let tmin4 = Vec4::splat(tmin);
        // No ray may hit beyond this: the largest of the rays' limits.
        let mut limit = tmax;
        let mut stack = Stack::new();
        let mut slot = self.root;
        let mut entry = tmin;
        loop {
            if entry <= limit {
                if slot & LEAF == 0 {
                    let node = &self.nodes[slot as usize];
                    let b = &node.bounds;
                    let limit4 = Vec4::splat(limit);
                    let mut tn = [Vec4::ZERO; HALVES];
                    let mut bits = 0u32;
                    for h in 0..HALVES {
                        // Per axis, each ray's entry and exit are the two
                        // products (bound − o)·(1/d); over the packet they
                        // lie between the extremes of the four products
                        // with the interval's ends (the product is monotone
                        // in 1/d for a fixed bound, rounding included).
                        let mut near = tmin4;
                        let mut far = limit4;
                        for a in 0..3 {
                            let lo = b[a][h] - o4[a];
                            let hi = b[a + 3][h] - o4[a];
                            let (p1, p2, p3, p4) = (lo * il[a], lo * ih[a], hi * il[a], hi * ih[a]);
                            near = near.max(p1.min(p2).min(p3.min(p4)));
                            far = far.min(p1.max(p2).max(p3.max(p4)));
                        }
                        bits |= near.cmple(far * SLAB_WIDEN).bitmask() << (4 * h);
                        tn[h] = near;
                    }
                    // Empty slots have infinite bounds, which the interval
                    // test cannot reject.
                    for lane in 0..LANES {
                        if node.child[lane] == EMPTY {
                            bits &= !(1 << lane);
                        }
                    }
                    if let Some(next) = nearest_first(self, node, bits, &tn, &mut stack, true) {
                        (slot, entry) = next;
                        continue;
                    }
                } else {
                    let blocks = self.leaf_blocks(slot);
                    let mut changed = false;
                    for (hit, d) in hits.iter_mut().zip(dirs) {
                        let d4 = [d.x, d.y, d.z].map(Vec4::splat);
                        changed |= hit.leaf(&o4, &d4, blocks, tmin);
                    }
                    if changed {
                        // A ray at its limit still takes ties (inclusive),
                        // so the packet's bound is the largest limit.
                        limit = hits.iter().fold(f32::NEG_INFINITY, |m, h| m.max(h.limit));
                    }
                }
            }
            match stack.pop() {
                Some(e) => (slot, entry) = e,
                None => break,
            }
        }
        for (o, h) in out.iter_mut().zip(hits.iter()) {
            *o = h.best;
        }
    }

    /// The triangle blocks of a leaf slot (consecutive; the slot keeps
    /// the first block's index and, in bits 28–29, the count less one).
    #[inline(always)]
    fn leaf_blocks(&self, slot: u32) -> &[Tri4] {
        let at = (slot & BLOCK_INDEX) as usize;
        let blocks = ((slot >> 28) & 3) as usize + 1;
        &self.tris[at..at + blocks]
    }

    /// True when anything lies on the segment t in (tmin, tmax).
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        self.occluded_here(origin, dir, tmin, tmax)
            || self
                .added
                .as_ref()
                .is_some_and(|a| a.occluded_here(origin, dir, tmin, tmax))
    }

    #[inline]
    fn occluded_here(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        if self.root == EMPTY {
            return false;
        }
        let mut w = Walk::new(self, origin, dir, tmin, tmax);
        loop {
            if let Some(blocked) = w.step_occluded(self) {
                return blocked;
            }
        }
    }
}

/// Asks for the memory of a child slot ahead of its visit: a node's
/// four cache lines, or a leaf's first triangle block.
#[inline(always)]
fn prefetch(bvh: &Bvh, slot: u32) {
    #[cfg(target_arch = "x86_64")]
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p: *const i8 = if slot & LEAF == 0 {
            bvh.nodes.as_ptr().add(slot as usize) as *const i8
        } else {
            bvh.tris.as_ptr().add((slot & BLOCK_INDEX) as usize) as *const i8
        };
        for k in 0..4 {
            _mm_prefetch::<_MM_HINT_T0>(p.add(64 * k));
        }
    }
}

/// How many rays [`Bvh::intersect_stream`] and [`Bvh::occluded_stream`]
/// keep in flight. Traversal of incoherent rays waits on memory (a node or
/// a triangle block missed in cache); stepping several independent rays in
/// turn, each one's next node prefetched while the others step, overlaps
/// those waits (asynchronous memory-access chaining).
pub const IN_FLIGHT: usize = 32;

/// A traversal stack: fixed depth on the stack, spilling to the heap.
struct Stack {
    items: [(u32, f32); STACK],
    sp: usize,
    spill: Vec<(u32, f32)>,
}

impl Stack {
    #[inline(always)]
    fn new() -> Stack {
        Stack {
            items: [(0, 0.0); STACK],
            sp: 0,
            spill: Vec::new(),
        }
    }

    #[inline(always)]
    fn push(&mut self, e: (u32, f32)) {
        if self.sp < STACK {
            self.items[self.sp] = e;
            self.sp += 1;
        } else {
            self.spill.push(e);
        }
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<(u32, f32)> {
        if let Some(e) = self.spill.pop() {
            return Some(e);
        }
        if self.sp == 0 {
            return None;
        }
        self.sp -= 1;
        Some(self.items[self.sp])
    }
}

/// One ray's traversal in progress: the slot to visit next (with its
/// entry distance), the stack of slots still to visit and the closest hit
/// so far.
struct Walk {
    ray: WideRay,
    tmin: f32,
    tmax: f32,
    hit: Closest,
    stack: Stack,
    slot: u32,
    entry: f32,
}

impl Walk {
    #[inline(always)]
    fn new(bvh: &Bvh, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Walk {
        prefetch(bvh, bvh.root);
        Walk {
            ray: WideRay::new(o, d),
            tmin,
            tmax,
            hit: Closest::new(tmax),
            stack: Stack::new(),
            slot: bvh.root,
            entry: tmin,
        }
    }

    #[inline(always)]
    fn restart(&mut self, bvh: &Bvh, o: Vec3, d: Vec3, tmin: f32, tmax: f32) {
        prefetch(bvh, bvh.root);
        self.ray = WideRay::new(o, d);
        self.tmin = tmin;
        self.tmax = tmax;
        self.hit = Closest::new(tmax);
        self.stack.sp = 0;
        self.stack.spill.clear();
        self.slot = bvh.root;
        self.entry = tmin;
    }

    /// Closest hit: visits the current slot (when the ray may still hit
    /// something in it); `Some(answer)` when the traversal is over.
    #[inline(always)]
    fn step_closest(&mut self, bvh: &Bvh) -> Option<Option<Hit>> {
        if self.entry <= self.hit.limit {
            if self.slot & LEAF == 0 {
                let node = &bvh.nodes[self.slot as usize];
                let (tn, bits) = self.ray.slabs(node, self.tmin, self.hit.limit);
                // Only the child visited next is prefetched: prefetching
                // them all floods the fill buffers when many rays are in
                // flight.
                if let Some(next) = nearest_first(bvh, node, bits, &tn, &mut self.stack, false) {
                    (self.slot, self.entry) = next;
                    return None;
                }
            } else {
                self.hit.leaf(
                    &self.ray.o,
                    &self.ray.d,
                    bvh.leaf_blocks(self.slot),
                    self.tmin,
                );
            }
        }
        // Next: the nearest pushed slot the ray may still hit before its
        // best (skipping the others costs no memory).
        while let Some((slot, entry)) = self.stack.pop() {
            if entry <= self.hit.limit {
                (self.slot, self.entry) = (slot, entry);
                prefetch(bvh, slot);
                return None;
            }
        }
        Some(self.hit.best)
    }

    /// Occlusion: visits the current slot; `Some(answer)` when known.
    #[inline(always)]
    fn step_occluded(&mut self, bvh: &Bvh) -> Option<bool> {
        if self.slot & LEAF == 0 {
            let node = &bvh.nodes[self.slot as usize];
            let (_, mut bits) = self.ray.slabs(node, self.tmin, self.tmax);
            if bits != 0 {
                let lane = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                while bits != 0 {
                    let l = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    self.stack.push((node.child[l], 0.0));
                }
                self.slot = node.child[lane];
                prefetch(bvh, self.slot);
                return None;
            }
        } else {
            let tmax4 = Vec4::splat(self.tmax);
            for tri in bvh.leaf_blocks(self.slot) {
                if triangles4(&self.ray.o, &self.ray.d, tri, self.tmin, tmax4)
                    .3
                    .any()
                {
                    return Some(true);
                }
            }
        }
        match self.stack.pop() {
            Some((slot, _)) => {
                self.slot = slot;
                prefetch(bvh, slot);
                None
            }
            None => Some(false),
        }
    }
}

impl Bvh {
    /// Closest hits of many rays (origin, direction) with t in (tmin, tmax):
    /// `out[i]` is exactly [`Bvh::intersect`] of ray i (each ray's traversal
    /// is the single ray's, step for step), but [`IN_FLIGHT`] rays are
    /// traversed in turn so that their memory waits overlap.
    pub fn intersect_stream(
        &self,
        rays: &[(Vec3, Vec3)],
        tmin: f32,
        tmax: f32,
        out: &mut [Option<Hit>],
    ) {
        self.stream(rays, tmin, tmax, out, None, Walk::step_closest);
        if let Some(a) = &self.added {
            for ((o, d), h) in rays.iter().zip(out.iter_mut()) {
                *h = a.nearer(*h, *o, *d, tmin, tmax);
            }
        }
    }

    /// Occlusion of many rays: `out[i]` is [`Bvh::occluded`] of ray i,
    /// with [`IN_FLIGHT`] rays traversed in turn (as
    /// [`Bvh::intersect_stream`]).
    pub fn occluded_stream(&self, rays: &[(Vec3, Vec3)], tmin: f32, tmax: f32, out: &mut [bool]) {
        self.stream(rays, tmin, tmax, out, false, Walk::step_occluded);
        if let Some(a) = &self.added {
            for ((o, d), b) in rays.iter().zip(out.iter_mut()) {
                *b = *b || a.occluded_here(*o, *d, tmin, tmax);
            }
        }
    }

    /// Steps [`IN_FLIGHT`] walks in turn, each with `step` until it has
    /// its answer, then restarts it on the next ray; an empty hierarchy
    /// answers `none` to every ray.
    #[inline(always)]
    fn stream<T: Copy>(
        &self,
        rays: &[(Vec3, Vec3)],
        tmin: f32,
        tmax: f32,
        out: &mut [T],
        none: T,
        step: impl Fn(&mut Walk, &Bvh) -> Option<T>,
    ) {
        assert_eq!(rays.len(), out.len(), "one result per ray");
        if self.root == EMPTY {
            out.fill(none);
            return;
        }
        let mut lanes: Vec<(usize, Walk)> = Vec::with_capacity(IN_FLIGHT);
        let mut next = 0;
        while next < rays.len() && lanes.len() < IN_FLIGHT {
            let (o, d) = rays[next];
            lanes.push((next, Walk::new(self, o, d, tmin, tmax)));
            next += 1;
        }
        while !lanes.is_empty() {
            let mut i = 0;
            while i < lanes.len() {
                let (k, w) = &mut lanes[i];
                if let Some(answer) = step(w, self) {
                    out[*k] = answer;
                    if next < rays.len() {
                        let (o, d) = rays[next];
                        *k = next;
                        w.restart(self, o, d, tmin, tmax);
                        next += 1;
                    } else {
                        lanes.swap_remove(i);
                        continue;
                    }
                }
                i += 1;
            }
        }
    }
}

trait NextUp {
    fn next_up_f32(self) -> f32;
}
impl NextUp for f32 {
    #[inline(always)]
    fn next_up_f32(self) -> f32 {
        if self.is_nan() || self == f32::INFINITY {
            return self;
        }
        let bits = self.to_bits();
        if self == 0.0 {
            return f32::from_bits(1);
        }
        if self > 0.0 {
            f32::from_bits(bits + 1)
        } else {
            f32::from_bits(bits - 1)
        }
    }
}

/// Brute-force closest hit over every triangle (the test oracle).
pub fn brute_force_intersect(
    mesh: &TriMesh,
    origin: Vec3,
    dir: Vec3,
    tmin: f32,
    tmax: f32,
) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    for (i, idx) in mesh.indices.iter().enumerate() {
        let [a, b, c] = idx.map(|k| mesh.positions[k as usize]);
        let (e1, e2) = (b - a, c - a);
        let area2 = glam::Vec3A::from(e1)
            .cross(glam::Vec3A::from(e2))
            .length_squared();
        if !(area2 > 0.0) || !area2.is_finite() {
            continue;
        }
        let limit = best.map(|b| b.t.next_up_f32()).unwrap_or(tmax);
        if let Some((t, u, v)) = intersect_tri(a, e1, e2, origin, dir, tmin, limit) {
            let better = match best {
                None => true,
                Some(b) => t < b.t || (t == b.t && (i as u32) < b.prim),
            };
            if better {
                best = Some(Hit {
                    t,
                    prim: i as u32,
                    u,
                    v,
                });
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::TriMesh;

    use matflow_scene::rng::Rng;

    /// Test rays' directions: uniform in the unit ball's shell past 0.1,
    /// normalised.
    trait Dir {
        fn dir(&mut self) -> Vec3;
    }
    impl Dir for Rng {
        fn dir(&mut self) -> Vec3 {
            loop {
                let v = Vec3::new(self.signed(), self.signed(), self.signed());
                let l = v.length();
                if l > 0.1 && l <= 1.0 {
                    return v / l;
                }
            }
        }
    }

    /// A stored hierarchy reads back to the same words and answers every
    /// query as the one built; words that are not a hierarchy of the mesh
    /// (a child before its parent, a leaf past the blocks, a triangle the
    /// mesh lacks, cut short) are refused.
    #[test]
    fn stored_words_read_back_to_the_same_hierarchy() {
        let mesh = test_mesh();
        let built = Bvh::build(&mesh);
        let w = built.to_words().unwrap();
        let back = Bvh::from_words(&w, &mesh).unwrap();
        assert_eq!(back.to_words().unwrap(), w);
        let mut rng = Rng(0x0b1d_5eed);
        for _ in 0..2000 {
            let o = Vec3::new(rng.signed(), rng.signed(), rng.signed()) * 4.0;
            let d = rng.dir();
            assert_eq!(
                back.intersect(o, d, 1e-4, f32::INFINITY),
                built.intersect(o, d, 1e-4, f32::INFINITY)
            );
            assert_eq!(
                back.occluded(o, d, 1e-4, 3.0),
                built.occluded(o, d, 1e-4, 3.0)
            );
        }
        let refused = |w: &BvhWords<'_>, m: &TriMesh| Bvh::from_words(w, m).is_err();
        let mut fewer = mesh.clone();
        fewer.indices.truncate(mesh.triangle_count() - 1);
        assert!(refused(&w, &fewer), "too few triangles");
        let mut cut = w.clone();
        cut.prims.to_mut().pop();
        assert!(refused(&cut, &mesh));
        let mut back_edge = w.clone();
        assert!(built.node_count() >= 2);
        // Node 1's first child made node 0: a cycle.
        back_edge.nodes.to_mut()[NODE_WORDS + 6 * LANES] = 0;
        assert!(refused(&back_edge, &mesh), "a cycle");
        let mut leaf = w.clone();
        leaf.root = LEAF | (3 << 28) | (w.prims.len() / 4) as u32;
        assert!(refused(&leaf, &mesh), "blocks past the end");
        let mut prim = w.clone();
        prim.prims.to_mut()[0] = mesh.triangle_count() as u32;
        assert!(refused(&prim, &mesh), "a triangle out of range");
        let empty = Bvh::build(&TriMesh::default()).to_words().unwrap();
        assert!(Bvh::from_words(&empty, &TriMesh::default()).is_ok());
    }

    /// An axis-aligned box room (12 triangles, planes on all three axes),
    /// a tessellated floor grid and a sloped quad.
    fn test_mesh() -> TriMesh {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-5.0), Vec3::splat(5.0));
        m.add_box(Vec3::new(-1.0, -5.0, -1.0), Vec3::new(1.0, -3.0, 1.0));
        // 40×40 grid on the plane y = -2 (axis-aligned, many shared edges).
        let n = 40;
        let base = m.positions.len() as u32;
        for j in 0..=n {
            for i in 0..=n {
                m.positions.push(Vec3::new(
                    -4.0 + 8.0 * i as f32 / n as f32,
                    -2.0,
                    -4.0 + 8.0 * j as f32 / n as f32,
                ));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let a = base + (j * (n + 1) + i) as u32;
                let b = a + 1;
                let c = a + (n + 1) as u32;
                let d = c + 1;
                m.indices.push([a, c, b]);
                m.indices.push([b, c, d]);
            }
        }
        m
    }

    #[test]
    fn closest_hit_matches_brute_force_on_axis_aligned_planes() {
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        let mut rng = Rng(0x9e3779b97f4a7c15);
        let mut hits = 0;
        for k in 0..4000 {
            let o = if k % 2 == 0 {
                Vec3::new(
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                )
            } else {
                // Axis-aligned rays straight at the planes.
                Vec3::new(rng.f() * 6.0 - 3.0, 0.5, rng.f() * 6.0 - 3.0)
            };
            let d = if k % 2 == 0 { rng.dir() } else { Vec3::NEG_Y };
            let a = bvh.intersect(o, d, 1e-4, f32::INFINITY);
            let b = brute_force_intersect(&mesh, o, d, 1e-4, f32::INFINITY);
            match (a, b) {
                (Some(a), Some(b)) => {
                    assert_eq!(a.prim, b.prim, "ray {k}: {a:?} vs {b:?}");
                    assert_eq!(a.t, b.t);
                    hits += 1;
                }
                (None, None) => {}
                _ => panic!("ray {k} from {o} dir {d}: bvh {a:?} brute {b:?}"),
            }
            let occl = bvh.occluded(o, d, 1e-4, 3.0);
            let bf = b.map(|h| h.t < 3.0).unwrap_or(false);
            assert_eq!(occl, bf, "occlusion ray {k}");
        }
        // Inside a closed room every ray hits something.
        assert_eq!(hits, 4000);
    }

    #[test]
    fn packets_answer_exactly_as_single_rays() {
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        let mut rng = Rng(0x2545f4914f6cdd1d);
        for k in 0..300 {
            let o = Vec3::new(
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
                rng.f() * 8.0 - 4.0,
            );
            // Cones from a pixel's width to the whole sphere, axis-aligned
            // centres (components straddling zero) and packets longer
            // than one traversal.
            let spread = [1e-3, 0.05, 0.5, 2.0][k % 4];
            let centre = match k % 5 {
                0 => Vec3::NEG_Y,
                1 => Vec3::X,
                _ => rng.dir(),
            };
            let n = [1, 7, 64, 100][k % 4];
            let dirs: Vec<Vec3> = (0..n)
                .map(|_| (centre + rng.dir() * spread * rng.f()).normalize_or(centre))
                .collect();
            let tmax = if k % 3 == 0 { 4.0 } else { f32::INFINITY };
            let mut out = vec![None; n];
            bvh.intersect_packet(o, &dirs, 1e-4, tmax, &mut out);
            for (i, d) in dirs.iter().enumerate() {
                let single = bvh.intersect(o, *d, 1e-4, tmax);
                assert_eq!(out[i], single, "packet {k} ray {i} from {o} dir {d}");
                let brute = brute_force_intersect(&mesh, o, *d, 1e-4, tmax);
                assert_eq!(out[i], brute, "packet {k} ray {i}: brute force");
            }
        }
        let mut out = [None];
        Bvh::build(&TriMesh::default()).intersect_packet(
            Vec3::ZERO,
            &[Vec3::X],
            0.0,
            1.0,
            &mut out,
        );
        assert_eq!(out[0], None);
    }

    /// Streams are many single rays traversed in turn: each answer is the
    /// single ray's, closest hit and occlusion, for streams shorter and
    /// longer than the number in flight, with rays that end early (short
    /// tmax) mixed with ones that cross the whole mesh.
    #[test]
    fn streams_answer_exactly_as_single_rays() {
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        let mut rng = Rng(0x9e3779b97f4a7c15);
        for n in [0usize, 1, 5, IN_FLIGHT, IN_FLIGHT + 1, 300] {
            let rays: Vec<(Vec3, Vec3)> = (0..n)
                .map(|k| {
                    let o = Vec3::new(
                        rng.f() * 8.0 - 4.0,
                        rng.f() * 8.0 - 4.0,
                        rng.f() * 8.0 - 4.0,
                    );
                    let d = match k % 7 {
                        0 => Vec3::NEG_Y,
                        1 => Vec3::Z,
                        _ => rng.dir(),
                    };
                    (o, d)
                })
                .collect();
            for tmax in [0.5, f32::INFINITY] {
                let mut hits = vec![None; n];
                bvh.intersect_stream(&rays, 1e-4, tmax, &mut hits);
                let mut blocked = vec![false; n];
                bvh.occluded_stream(&rays, 1e-4, tmax, &mut blocked);
                for (i, &(o, d)) in rays.iter().enumerate() {
                    let single = bvh.intersect(o, d, 1e-4, tmax);
                    assert_eq!(hits[i], single, "stream of {n}, ray {i} from {o} dir {d}");
                    assert_eq!(
                        hits[i],
                        brute_force_intersect(&mesh, o, d, 1e-4, tmax),
                        "stream of {n}, ray {i}: brute force"
                    );
                    assert_eq!(blocked[i], bvh.occluded(o, d, 1e-4, tmax), "ray {i}");
                    assert_eq!(blocked[i], single.is_some(), "ray {i}: occluded = any hit");
                }
            }
        }
        let empty = Bvh::build(&TriMesh::default());
        let (mut h, mut b) = (
            [Some(Hit {
                t: 1.0,
                prim: 0,
                u: 0.0,
                v: 0.0,
            })],
            [true],
        );
        empty.intersect_stream(&[(Vec3::ZERO, Vec3::X)], 0.0, 1.0, &mut h);
        empty.occluded_stream(&[(Vec3::ZERO, Vec3::X)], 0.0, 1.0, &mut b);
        assert_eq!((h[0], b[0]), (None, false));
    }

    /// Objects added to a built hierarchy ([`Bvh::with_added`]): every
    /// query answers as brute force does — single rays, packets and
    /// streams, nearer and farther hits, a quad coincident with the floor
    /// (whichever face rounds nearer wins; at equal t the lower index) —
    /// and as the one hierarchy over everything does, but for the
    /// module's rounding effect on coincident faces.
    #[test]
    fn added_triangles_answer_as_one_hierarchy_over_everything() {
        let mut mesh = test_mesh();
        let scene = mesh.triangle_count();
        let base = Bvh::build(&mesh);
        // Objects: a box standing on the grid, one floating, and a quad
        // lying exactly in the grid's plane (coincident: ties).
        mesh.add_box(Vec3::new(2.0, -2.0, 2.0), Vec3::new(3.0, -1.0, 3.0));
        mesh.add_box(Vec3::new(-3.0, 1.0, -3.0), Vec3::new(-2.0, 1.5, -2.0));
        let q = mesh.positions.len() as u32;
        mesh.positions.extend([
            Vec3::new(-1.5, -2.0, 1.0),
            Vec3::new(1.5, -2.0, 1.0),
            Vec3::new(1.5, -2.0, 3.0),
            Vec3::new(-1.5, -2.0, 3.0),
        ]);
        let quad_from = mesh.triangle_count();
        mesh.indices.extend([[q, q + 1, q + 2], [q, q + 2, q + 3]]);
        let whole = Bvh::build(&mesh);
        let added = base.clone().with_added(&mesh, scene);
        assert_eq!(added.triangle_count(), whole.triangle_count());
        let mut rng = Rng(0x5eed_0bec);
        let rays: Vec<(Vec3, Vec3)> = (0..3000)
            .map(|k| {
                let o = Vec3::new(
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                    rng.f() * 8.0 - 4.0,
                );
                let d = match k % 5 {
                    0 => Vec3::NEG_Y,
                    _ => rng.dir(),
                };
                (o, d)
            })
            .collect();
        let (mut objects_hit, mut rounded) = (0, 0);
        for tmax in [0.7, f32::INFINITY] {
            let mut hits = vec![None; rays.len()];
            added.intersect_stream(&rays, 1e-4, tmax, &mut hits);
            let mut blocked = vec![false; rays.len()];
            added.occluded_stream(&rays, 1e-4, tmax, &mut blocked);
            for (i, &(o, d)) in rays.iter().enumerate() {
                let h = added.intersect(o, d, 1e-4, tmax);
                assert_eq!(h, brute_force_intersect(&mesh, o, d, 1e-4, tmax), "ray {i}");
                // The one hierarchy may differ by the module's rounding
                // effect alone: on coincident faces, a hit an ulp away.
                let w = whole.intersect(o, d, 1e-4, tmax);
                if w != h {
                    let (a, b) = (w.map(|w| w.t), h.map(|h| h.t));
                    let close = matches!((a, b), (Some(a), Some(b)) if (a - b).abs() <= 1e-6 * a);
                    let quad = [w, h]
                        .iter()
                        .flatten()
                        .any(|x| x.prim as usize >= quad_from);
                    assert!(close && quad, "ray {i} from {o} dir {d}: {w:?} {h:?}");
                    rounded += 1;
                }
                assert_eq!(hits[i], h, "stream, ray {i}");
                assert_eq!(added.occluded(o, d, 1e-4, tmax), h.is_some(), "ray {i}");
                assert_eq!(blocked[i], h.is_some(), "stream, ray {i}");
                objects_hit += h.is_some_and(|h| h.prim as usize >= scene) as usize;
            }
        }
        assert!(objects_hit > 50, "{objects_hit} rays met an object");
        assert!(
            rounded < 30,
            "{rounded} of 6000 rays differ from one hierarchy's"
        );
        // A packet straight down onto the coincident quad.
        let origin = Vec3::new(0.1, 3.0, 2.1);
        let dirs: Vec<Vec3> = (0..100)
            .map(|k| {
                (Vec3::new(0.0, -5.0, 0.0)
                    + Vec3::new(0.01 * (k % 10) as f32, 0.0, 0.01 * (k / 10) as f32))
                .normalize()
            })
            .collect();
        let mut packet = vec![None; dirs.len()];
        added.intersect_packet(origin, &dirs, 1e-4, f32::INFINITY, &mut packet);
        for (d, p) in dirs.iter().zip(&packet) {
            let h = brute_force_intersect(&mesh, origin, *d, 1e-4, f32::INFINITY);
            assert_eq!(*p, h, "dir {d}");
            assert!(h.is_some(), "{d}");
        }
    }

    #[test]
    fn rays_through_shared_grid_edges_never_leak() {
        // Rays aimed exactly at grid vertices and edge midpoints of the floor.
        let mesh = test_mesh();
        let bvh = Bvh::build(&mesh);
        for j in 1..80 {
            for i in 1..80 {
                let x = -4.0 + 0.1 * i as f32;
                let z = -4.0 + 0.1 * j as f32;
                let o = Vec3::new(x * 0.5, 1.0, z * 0.5);
                let target = Vec3::new(x, -2.0, z);
                let d = (target - o).normalize();
                let h = bvh.intersect(o, d, 1e-4, f32::INFINITY).expect("hit");
                let p = o + d * h.t;
                assert!(
                    (p.y + 2.0).abs() < 1e-3,
                    "leaked through the floor at {target}: {p}"
                );
            }
        }
    }

    #[test]
    fn empty_and_degenerate_meshes() {
        let mut m = TriMesh::default();
        let bvh = Bvh::build(&m);
        assert!(bvh.intersect(Vec3::ZERO, Vec3::X, 0.0, 1e9).is_none());
        assert!(!bvh.occluded(Vec3::ZERO, Vec3::X, 0.0, 1e9));
        m.positions = vec![Vec3::ZERO, Vec3::X, Vec3::X * 2.0];
        m.indices = vec![[0, 1, 2]];
        assert_eq!(Bvh::build(&m).triangle_count(), 0);
    }
}
