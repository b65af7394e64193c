//! An indexed triangle mesh in camera space, and binary PLY export.

use std::io::Write;

use glam::{Vec2, Vec3};

/// Corner `k` (bits: x, y, z at the high end) of the box `lo`..`hi`.
pub fn box_corner(lo: Vec3, hi: Vec3, k: u32) -> Vec3 {
    Vec3::new(
        if k & 1 != 0 { hi.x } else { lo.x },
        if k & 2 != 0 { hi.y } else { lo.y },
        if k & 4 != 0 { hi.z } else { lo.z },
    )
}

/// A box's faces as quads of [`box_corner`]s, counter-clockwise from
/// outside: −x, +x, −y, +y, −z, +z.
pub const BOX_QUADS: [[u32; 4]; 6] = [
    [0, 4, 6, 2],
    [1, 3, 7, 5],
    [0, 1, 5, 4],
    [2, 6, 7, 3],
    [0, 2, 3, 1],
    [4, 5, 7, 6],
];

#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<Vec3>,
    /// Counter-clockwise seen from the camera (normals face the viewer).
    pub indices: Vec<[u32; 3]>,
    /// Per-vertex film position (pixel units, pixel i spans [i, i+1)) of the
    /// image point the vertex was made from; empty for meshes not made from
    /// an image.
    pub film: Vec<Vec2>,
    /// Per triangle, the pixel whose (screen-space) material it takes, or
    /// [`PROJECTED`] for the pixel its points project into (the depth
    /// mesh's own triangles); empty when every triangle is projected.
    /// Geometry completed past the frame names a pixel of the surface it
    /// continues (see `complete`).
    pub material_pixel: Vec<u32>,
    /// Per triangle, the share of light that passes through it, in
    /// [0, 1]: 0 for a solid surface. Assumed walls and ceilings of a
    /// completed room are partly open (their unseen windows, skylights and
    /// lamps spread over them); light passing one reaches the sky, since
    /// they bound the scene. Empty when every triangle is solid.
    pub openness: Vec<f32>,
    /// Openings light is known to come in through (a completed room's
    /// assumed windows): renderers may sample them as lights. They add no
    /// geometry (the opening is a hole in the triangles); a portal larger
    /// than its hole only wastes samples. Empty for most meshes.
    pub portals: Vec<Portal>,
    /// Per-vertex shading normals (unit, camera space, facing the viewer)
    /// for the first `normals.len()` vertices, e.g. a predicted normal map
    /// laid on the depth mesh; the other vertices' (all, when empty) are
    /// the triangles' own, averaged.
    pub normals: Vec<Vec3>,
}

/// A rectangular opening of a mesh that the scene's light comes in
/// through ([`TriMesh::portals`]): corner `corner`, perpendicular edges
/// `u` and `v`, with `u × v` pointing into the scene (only points on that
/// side see light through it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Portal {
    pub corner: Vec3,
    pub u: Vec3,
    pub v: Vec3,
}

impl Portal {
    /// The inward unit normal (zero for a degenerate portal).
    pub fn normal(&self) -> Vec3 {
        self.u.cross(self.v).normalize_or_zero()
    }

    /// Finite, with edges of positive length meeting at a right angle
    /// (within 1e-3 of the product of their lengths).
    pub fn is_valid(&self) -> bool {
        let (lu, lv) = (self.u.length(), self.v.length());
        self.corner.is_finite()
            && self.u.is_finite()
            && self.v.is_finite()
            && lu > 0.0
            && lv > 0.0
            && (lu * lv).is_finite()
            && self.u.dot(self.v).abs() <= 1e-3 * lu * lv
    }
}

/// A triangle whose points take the material of the pixel they project
/// into (see [`TriMesh::material_pixel`]).
pub const PROJECTED: u32 = u32::MAX;

impl TriMesh {
    /// The pixel triangle `prim` takes its material from, when it names
    /// one rather than projecting.
    #[inline]
    pub fn material_pixel_of(&self, prim: usize) -> Option<u32> {
        self.material_pixel
            .get(prim)
            .copied()
            .filter(|&q| q != PROJECTED)
    }

    /// The share of light that passes through triangle `prim` (0: solid).
    #[inline]
    pub fn openness_of(&self, prim: usize) -> f32 {
        self.openness.get(prim).copied().unwrap_or(0.0)
    }

    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// Unit geometric normal of triangle `i` (zero for degenerate ones).
    #[inline]
    pub fn face_normal(&self, i: usize) -> Vec3 {
        let [a, b, c] = self.indices[i].map(|k| self.positions[k as usize]);
        (b - a).cross(c - a).normalize_or_zero()
    }

    /// Adds an axis-aligned box with outward-facing triangles.
    pub fn add_box(&mut self, lo: Vec3, hi: Vec3) {
        let base = self.positions.len() as u32;
        for k in 0..8u32 {
            self.positions.push(box_corner(lo, hi, k));
        }
        for q in BOX_QUADS {
            self.indices.push([base + q[0], base + q[1], base + q[2]]);
            self.indices.push([base + q[0], base + q[2], base + q[3]]);
        }
        if !self.film.is_empty() {
            self.film.resize(self.positions.len(), Vec2::ZERO);
        }
        if !self.material_pixel.is_empty() {
            self.material_pixel.resize(self.indices.len(), PROJECTED);
        }
        if !self.openness.is_empty() {
            self.openness.resize(self.indices.len(), 0.0);
        }
    }

    /// Binary little-endian PLY (x, y, z as float; faces as uchar count +
    /// int indices), readable by Blender and MeshLab. Film positions are
    /// written as texture coordinates `s, t` in [0, 1] when present.
    pub fn write_ply(
        &self,
        w: &mut impl Write,
        width: usize,
        height: usize,
    ) -> std::io::Result<()> {
        let has_uv = self.film.len() == self.positions.len() && !self.film.is_empty();
        let mut header = String::new();
        header.push_str("ply\nformat binary_little_endian 1.0\ncomment made by matflow\n");
        header.push_str(&format!("element vertex {}\n", self.positions.len()));
        header.push_str("property float x\nproperty float y\nproperty float z\n");
        if has_uv {
            header.push_str("property float s\nproperty float t\n");
        }
        header.push_str(&format!("element face {}\n", self.indices.len()));
        header.push_str("property list uchar int vertex_indices\nend_header\n");
        let mut buf =
            Vec::with_capacity(header.len() + self.positions.len() * 20 + self.indices.len() * 13);
        buf.extend_from_slice(header.as_bytes());
        for (i, p) in self.positions.iter().enumerate() {
            for c in p.to_array() {
                buf.extend_from_slice(&c.to_le_bytes());
            }
            if has_uv {
                let f = self.film[i];
                buf.extend_from_slice(&(f.x / width.max(1) as f32).to_le_bytes());
                buf.extend_from_slice(&(1.0 - f.y / height.max(1) as f32).to_le_bytes());
            }
        }
        for t in &self.indices {
            buf.push(3u8);
            for &k in t {
                buf.extend_from_slice(&(k as i32).to_le_bytes());
            }
        }
        w.write_all(&buf)
    }
}

/// Parses a binary PLY written by [`TriMesh::write_ply`] (positions and
/// faces only). Used by tests and tools to check exports.
pub fn read_ply_positions_faces(bytes: &[u8]) -> Result<(Vec<Vec3>, Vec<[u32; 3]>), String> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or("no end_header")?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|e| e.to_string())?;
    let mut nv = 0usize;
    let mut nf = 0usize;
    let mut vprops = 0usize;
    let mut in_vertex = false;
    for line in header.lines() {
        let parts: Vec<&str> = line.split_whitespace().collect();
        match parts.as_slice() {
            ["element", "vertex", n] => {
                nv = n.parse().map_err(|_| "bad vertex count")?;
                in_vertex = true;
            }
            ["element", "face", n] => {
                nf = n.parse().map_err(|_| "bad face count")?;
                in_vertex = false;
            }
            ["property", "float", _] if in_vertex => vprops += 1,
            _ => {}
        }
    }
    let mut off = end + 11;
    let rd = |off: &mut usize| -> Result<[u8; 4], String> {
        let s = bytes.get(*off..*off + 4).ok_or("truncated")?;
        *off += 4;
        Ok([s[0], s[1], s[2], s[3]])
    };
    let mut pos = Vec::with_capacity(nv);
    for _ in 0..nv {
        let mut v = [0f32; 3];
        for p in 0..vprops {
            let x = f32::from_le_bytes(rd(&mut off)?);
            if p < 3 {
                v[p] = x;
            }
        }
        pos.push(Vec3::from_array(v));
    }
    let mut faces = Vec::with_capacity(nf);
    for _ in 0..nf {
        let n = *bytes.get(off).ok_or("truncated")?;
        off += 1;
        if n != 3 {
            return Err("non-triangle face".into());
        }
        let mut f = [0u32; 3];
        for k in &mut f {
            *k = i32::from_le_bytes(rd(&mut off)?) as u32;
        }
        faces.push(f);
    }
    Ok((pos, faces))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_normals_point_outwards() {
        let mut m = TriMesh::default();
        m.add_box(Vec3::splat(-1.0), Vec3::splat(1.0));
        for i in 0..m.triangle_count() {
            let [a, b, c] = m.indices[i].map(|k| m.positions[k as usize]);
            let centre = (a + b + c) / 3.0;
            assert!(m.face_normal(i).dot(centre) > 0.0, "face {i}");
        }
    }

    #[test]
    fn ply_round_trip() {
        let mut m = TriMesh::default();
        m.add_box(Vec3::new(-1.0, -2.0, -3.0), Vec3::new(1.0, 2.0, 3.0));
        m.film = vec![Vec2::new(1.0, 2.0); m.positions.len()];
        let mut buf = Vec::new();
        m.write_ply(&mut buf, 4, 4).unwrap();
        let (p, f) = read_ply_positions_faces(&buf).unwrap();
        assert_eq!(p, m.positions);
        assert_eq!(f, m.indices);
    }
}
