//! Geometry for matflow: the mesh rebuilt from a depth map (paper §3.1),
//! PLY export, and the BVH with closest-hit and occlusion queries.

pub mod bvh;
pub mod depth_mesh;
pub mod mesh;

pub use bvh::{Bvh, Hit};
pub use depth_mesh::{mesh_from_depth, vertex_normals, DepthMesh, MeshError, MeshParams, MeshStats};
pub use mesh::TriMesh;
