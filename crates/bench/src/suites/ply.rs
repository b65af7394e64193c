//! The triangle meshes the suites hand to Mitsuba 3: binary little-endian
//! PLY with per-vertex normals and texture coordinates when given.

use std::path::Path;

use anyhow::Result;
use glam::{Vec2, Vec3};
use matflow_geom::TriMesh;
use matflow_scene::io;

/// Writes `mesh` to `path`; `normals` and `uvs` are written (as `nx ny nz`
/// and `u v`, as given) when each has one entry per vertex.
pub fn write_ply(path: &Path, mesh: &TriMesh, normals: &[Vec3], uvs: &[Vec2]) -> Result<()> {
    let nv = mesh.positions.len();
    let (with_n, with_uv) = (normals.len() == nv, uvs.len() == nv);
    let mut head = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {nv}\n\
         property float x\nproperty float y\nproperty float z\n"
    );
    if with_n {
        head.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if with_uv {
        head.push_str("property float u\nproperty float v\n");
    }
    head.push_str(&format!(
        "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.indices.len()
    ));
    let mut b = head.into_bytes();
    for (k, p) in mesh.positions.iter().enumerate() {
        let n = if with_n {
            &normals[k].to_array()[..]
        } else {
            &[]
        };
        let uv = if with_uv { &uvs[k].to_array()[..] } else { &[] };
        for c in p.to_array().iter().chain(n).chain(uv) {
            b.extend(c.to_le_bytes());
        }
    }
    for t in &mesh.indices {
        b.push(3);
        for i in t {
            b.extend((*i as i32).to_le_bytes());
        }
    }
    io::write_atomic(path, &b)?;
    Ok(())
}
