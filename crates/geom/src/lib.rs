//! Geometry for matflow: the mesh rebuilt from a depth map (paper §3.1),
//! PLY export, and the BVH with closest-hit and occlusion queries.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

pub mod bvh;
pub mod complete;
pub mod depth_mesh;
pub mod huge;
pub mod mesh;
pub mod planes;

pub use bvh::{Bvh, BvhError, BvhWords, Hit, PACKET};
pub use complete::{
    assumed_planes, complete_beyond_frame, extensions, window_slots, AssumedPlane, CompleteParams,
    Completion, Extension, Extensions, WindowSlot, COMPLETE_MODES, HIGH_WALLS, MAX_WINDOW_PLANES,
    RAISE_SEEN_WALLS, RAISE_WALLS_HIGH,
};
pub use depth_mesh::{
    mesh_for_view, mesh_from_depth, vertex_normals, DepthMesh, MeshError, MeshParams, MeshStats,
    Silhouettes,
};
pub use mesh::{Portal, TriMesh, PROJECTED};
pub use planes::{fit_planes, view_up, Plane, PlaneFit, PlaneKind, PlaneParams};
