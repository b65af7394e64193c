//! Triangle meshes from files: Wavefront OBJ (with its MTL materials,
//! through `tobj`) and PLY (ASCII and binary, read here). Sizes are bounded
//! before anything large is allocated, and every index and coordinate is
//! checked, so a damaged or hostile file is an error naming the file.

use std::path::{Path, PathBuf};

use glam::{Vec2, Vec3};

use crate::error::{Result, SceneError};

/// Files larger than this are refused before being read.
pub const MAX_MESH_FILE_BYTES: u64 = 1 << 30;
/// At most this many vertices or triangles.
pub const MAX_MESH_ELEMENTS: usize = 20_000_000;

/// What an OBJ's MTL says about a part's surface (the fields matflow maps
/// to its materials; see `nodes`' object placement).
#[derive(Clone, Debug, PartialEq)]
pub struct FileMaterial {
    pub name: String,
    /// `Kd`.
    pub diffuse: Option<Vec3>,
    /// `Ks`.
    pub specular: Option<Vec3>,
    /// `Ns` (Phong exponent).
    pub shininess: Option<f32>,
    /// `Ni`.
    pub ior: Option<f32>,
    /// `d` (1 opaque), or 1 − `Tr`.
    pub dissolve: Option<f32>,
    /// `Tf`.
    pub transmission_filter: Option<Vec3>,
    /// `illum` model number.
    pub illum: Option<u8>,
    /// PBR extension: `Pr`, `Pm`.
    pub roughness: Option<f32>,
    pub metallic: Option<f32>,
    /// `map_Kd`, resolved against the MTL's folder.
    pub diffuse_texture: Option<PathBuf>,
}

/// A part of a mesh file: triangles sharing one material.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshPart {
    pub positions: Vec<Vec3>,
    pub indices: Vec<[u32; 3]>,
    /// Per-vertex normals, or empty.
    pub normals: Vec<Vec3>,
    /// Per-vertex texture coordinates, or empty.
    pub uvs: Vec<Vec2>,
    pub material: Option<FileMaterial>,
}

/// Reads an `.obj` or `.ply` file (by extension) into parts. Degenerate
/// triangles are kept (the caller decides); non-finite coordinates and
/// out-of-range indices are errors.
pub fn read_mesh(path: &Path) -> Result<Vec<MeshPart>> {
    let meta = std::fs::metadata(path).map_err(|e| SceneError::io(path, e))?;
    if !meta.is_file() {
        return Err(SceneError::invalid(path, "is not a file"));
    }
    if meta.len() > MAX_MESH_FILE_BYTES {
        return Err(SceneError::invalid(
            path,
            format!(
                "{} bytes: mesh files of at most {} bytes are read",
                meta.len(),
                MAX_MESH_FILE_BYTES
            ),
        ));
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    let parts = match ext.as_str() {
        "obj" => read_obj(path)?,
        "ply" => vec![read_ply(path)?],
        _ => {
            return Err(SceneError::invalid(
                path,
                "unknown mesh type (use .obj or .ply)",
            ))
        }
    };
    for part in &parts {
        check_part(path, part)?;
    }
    Ok(parts)
}

fn check_part(path: &Path, p: &MeshPart) -> Result<()> {
    if let Some(k) = p.positions.iter().position(|v| !v.is_finite()) {
        return Err(SceneError::invalid(
            path,
            format!(
                "vertex {k} has a non-finite coordinate ({})",
                p.positions[k]
            ),
        ));
    }
    let n = p.positions.len();
    if let Some(t) = p
        .indices
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(SceneError::invalid(
            path,
            format!(
                "triangle {t} refers to vertex {:?}, but there are {n} vertices",
                p.indices[t]
            ),
        ));
    }
    if (!p.normals.is_empty() && p.normals.len() != n) || (!p.uvs.is_empty() && p.uvs.len() != n) {
        return Err(SceneError::invalid(
            path,
            "normals or texture coordinates do not match the vertices",
        ));
    }
    Ok(())
}

fn read_obj(path: &Path) -> Result<Vec<MeshPart>> {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, mats) = tobj::load_obj(path, &opts).map_err(|e| SceneError::Decode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    // A missing or broken MTL leaves the parts without file materials
    // (they take the object's `material` or a neutral one).
    let mats = mats.unwrap_or_default();
    let base = path.parent().unwrap_or(Path::new("."));
    let mut parts: Vec<MeshPart> = Vec::new();
    let mut total = 0usize;
    for m in models {
        let mesh = m.mesh;
        total += mesh.positions.len() / 3 + mesh.indices.len() / 3;
        if total > MAX_MESH_ELEMENTS {
            return Err(SceneError::invalid(
                path,
                format!("more than {MAX_MESH_ELEMENTS} vertices and triangles"),
            ));
        }
        let positions: Vec<Vec3> = mesh
            .positions
            .chunks_exact(3)
            .map(|c| Vec3::new(c[0], c[1], c[2]))
            .collect();
        let nv = positions.len();
        let normals: Vec<Vec3> = if mesh.normals.len() == 3 * nv {
            mesh.normals
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect()
        } else {
            Vec::new()
        };
        let uvs: Vec<Vec2> = if mesh.texcoords.len() == 2 * nv {
            mesh.texcoords
                .chunks_exact(2)
                .map(|c| Vec2::new(c[0], c[1]))
                .collect()
        } else {
            Vec::new()
        };
        let indices: Vec<[u32; 3]> = mesh
            .indices
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let material = mesh.material_id.and_then(|i| mats.get(i)).map(|mt| {
            let v3 = |a: Option<[f32; 3]>| a.map(Vec3::from_array);
            let num = |k: &str| {
                mt.unknown_param
                    .get(k)
                    .and_then(|s| s.split_whitespace().next()?.parse::<f32>().ok())
            };
            let tf = mt.unknown_param.get("Tf").and_then(|s| {
                let v: Vec<f32> = s
                    .split_whitespace()
                    .filter_map(|x| x.parse().ok())
                    .collect();
                match v[..] {
                    [a] => Some(Vec3::splat(a)),
                    [a, b, c] => Some(Vec3::new(a, b, c)),
                    _ => None,
                }
            });
            FileMaterial {
                name: mt.name.clone(),
                diffuse: v3(mt.diffuse),
                specular: v3(mt.specular),
                shininess: mt.shininess,
                ior: mt.optical_density,
                dissolve: mt.dissolve.or_else(|| num("Tr").map(|t| 1.0 - t)),
                transmission_filter: tf,
                illum: mt.illumination_model,
                roughness: num("Pr"),
                metallic: num("Pm"),
                diffuse_texture: mt.diffuse_texture.as_ref().map(|t| base.join(t)),
            }
        });
        // Parts with the same material are merged.
        match parts.iter_mut().find(|p| p.material == material) {
            Some(p)
                if p.normals.is_empty() == normals.is_empty()
                    && p.uvs.is_empty() == uvs.is_empty() =>
            {
                let off = p.positions.len() as u32;
                p.positions.extend(positions);
                p.normals.extend(normals);
                p.uvs.extend(uvs);
                p.indices
                    .extend(indices.iter().map(|t| t.map(|i| i.saturating_add(off))));
            }
            _ => parts.push(MeshPart {
                positions,
                indices,
                normals,
                uvs,
                material,
            }),
        }
    }
    Ok(parts)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Clone, Debug)]
enum Prop {
    One(String, Scalar),
    List(String, Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Prop>,
}

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Le,
    Be,
}

/// Reads values of a PLY body, ASCII or binary.
struct Body<'a> {
    data: &'a [u8],
    pos: usize,
    format: Format,
}

impl Body<'_> {
    fn next(&mut self, t: Scalar) -> Option<f64> {
        if self.format == Format::Ascii {
            while self.pos < self.data.len() && self.data[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            let start = self.pos;
            while self.pos < self.data.len() && !self.data[self.pos].is_ascii_whitespace() {
                self.pos += 1;
            }
            return std::str::from_utf8(&self.data[start..self.pos])
                .ok()?
                .parse()
                .ok();
        }
        let n = t.size();
        let b = self.data.get(self.pos..self.pos + n)?;
        self.pos += n;
        let mut a = [0u8; 8];
        a[..n].copy_from_slice(b);
        if self.format == Format::Be {
            a[..n].reverse();
        }
        Some(match t {
            Scalar::I8 => a[0] as i8 as f64,
            Scalar::U8 => a[0] as f64,
            Scalar::I16 => i16::from_le_bytes([a[0], a[1]]) as f64,
            Scalar::U16 => u16::from_le_bytes([a[0], a[1]]) as f64,
            Scalar::I32 => i32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Scalar::U32 => u32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Scalar::F32 => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            Scalar::F64 => f64::from_le_bytes(a),
        })
    }
}

fn read_ply(path: &Path) -> Result<MeshPart> {
    let data = std::fs::read(path).map_err(|e| SceneError::io(path, e))?;
    let bad = |m: String| decode_error(path, m);
    let (format, elements, body_start) = ply_header(path, &data)?;
    let mut body = Body {
        data: &data[body_start..],
        pos: 0,
        format,
    };
    let mut part = MeshPart::default();
    let short = || bad("the file ends before its elements do".into());
    for el in &elements {
        match el.name.as_str() {
            "vertex" => ply_vertices(path, el, &mut body, &mut part)?,
            "face" => ply_faces(path, el, &mut body, &mut part)?,
            _ => {
                // Other elements are skipped, value by value.
                for _ in 0..el.count {
                    for p in &el.props {
                        match p {
                            Prop::One(_, t) => {
                                body.next(*t).ok_or_else(short)?;
                            }
                            Prop::List(_, c, t) => {
                                let n = body.next(*c).ok_or_else(short)? as usize;
                                for _ in 0..n {
                                    body.next(*t).ok_or_else(short)?;
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(part)
}

fn decode_error(path: &Path, message: String) -> SceneError {
    SceneError::Decode {
        path: path.to_path_buf(),
        message,
    }
}

/// A PLY header: the body's format, its elements with their properties,
/// and where the body starts.
fn ply_header(path: &Path, data: &[u8]) -> Result<(Format, Vec<Element>, usize)> {
    let bad = |m: String| decode_error(path, m);
    let end = data
        .windows(10)
        .position(|w| w == b"end_header")
        .ok_or_else(|| bad("no `end_header` line".into()))?;
    let header =
        std::str::from_utf8(&data[..end]).map_err(|_| bad("the header is not text".into()))?;
    let mut body_start = end + 10;
    // The line break after end_header (\n or \r\n).
    if data.get(body_start) == Some(&b'\r') {
        body_start += 1;
    }
    if data.get(body_start) == Some(&b'\n') {
        body_start += 1;
    }
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err(bad("does not start with `ply`".into()));
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for (no, line) in lines.enumerate() {
        let w: Vec<&str> = line.split_whitespace().collect();
        let at = |m: &str| bad(format!("header line {}: {m}", no + 2));
        match w.first().copied() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                format = Some(match w.get(1).copied() {
                    Some("ascii") => Format::Ascii,
                    Some("binary_little_endian") => Format::Le,
                    Some("binary_big_endian") => Format::Be,
                    _ => return Err(at("unknown format")),
                })
            }
            Some("element") => {
                let (Some(name), Some(count)) = (w.get(1), w.get(2).and_then(|c| c.parse().ok()))
                else {
                    return Err(at("expected `element NAME COUNT`"));
                };
                if count > MAX_MESH_ELEMENTS {
                    return Err(at(&format!(
                        "{count} elements (at most {MAX_MESH_ELEMENTS})"
                    )));
                }
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            Some("property") => {
                let el = elements
                    .last_mut()
                    .ok_or_else(|| at("a property before any element"))?;
                let prop = if w.get(1) == Some(&"list") {
                    match (
                        w.get(2).and_then(|s| Scalar::parse(s)),
                        w.get(3).and_then(|s| Scalar::parse(s)),
                        w.get(4),
                    ) {
                        (Some(c), Some(t), Some(n)) => Prop::List(n.to_string(), c, t),
                        _ => return Err(at("expected `property list COUNT_TYPE TYPE NAME`")),
                    }
                } else {
                    match (w.get(1).and_then(|s| Scalar::parse(s)), w.get(2)) {
                        (Some(t), Some(n)) => Prop::One(n.to_string(), t),
                        _ => return Err(at("expected `property TYPE NAME`")),
                    }
                };
                el.props.push(prop);
            }
            Some(other) => return Err(at(&format!("unknown keyword `{other}`"))),
        }
    }
    let format = format.ok_or_else(|| bad("no `format` line".into()))?;
    Ok((format, elements, body_start))
}

/// The `vertex` element: positions, and normals and texture coordinates
/// where it has them.
fn ply_vertices(path: &Path, el: &Element, body: &mut Body, part: &mut MeshPart) -> Result<()> {
    let bad = |m: String| decode_error(path, m);
    let short = || bad("the file ends before its elements do".into());
    let format = body.format;
    let find = |n: &str| {
        el.props
            .iter()
            .position(|p| matches!(p, Prop::One(name, _) if name == n))
    };
    let (x, y, z) = match (find("x"), find("y"), find("z")) {
        (Some(x), Some(y), Some(z)) => (x, y, z),
        _ => return Err(bad("vertices have no x, y, z".into())),
    };
    let normals = match (find("nx"), find("ny"), find("nz")) {
        (Some(a), Some(b), Some(c)) => Some((a, b, c)),
        _ => None,
    };
    let uv = match (find("u").or(find("s")), find("v").or(find("t"))) {
        (Some(a), Some(b)) => Some((a, b)),
        _ => None,
    };
    // Values of bounded-size binary input cannot outnumber its bytes.
    if format != Format::Ascii && el.count > body.data.len() {
        return Err(short());
    }
    part.positions.reserve(el.count.min(body.data.len()));
    let mut vals = vec![0f64; el.props.len()];
    for _ in 0..el.count {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::One(_, t) => vals[k] = body.next(*t).ok_or_else(short)?,
                Prop::List(_, c, t) => {
                    let n = body.next(*c).ok_or_else(short)? as usize;
                    for _ in 0..n {
                        body.next(*t).ok_or_else(short)?;
                    }
                }
            }
        }
        let v = |i: usize| vals[i] as f32;
        part.positions.push(Vec3::new(v(x), v(y), v(z)));
        if let Some((a, b, c)) = normals {
            part.normals.push(Vec3::new(v(a), v(b), v(c)));
        }
        if let Some((a, b)) = uv {
            part.uvs.push(Vec2::new(v(a), v(b)));
        }
    }
    Ok(())
}

/// The `face` element: each polygon as a fan of triangles.
fn ply_faces(path: &Path, el: &Element, body: &mut Body, part: &mut MeshPart) -> Result<()> {
    let bad = |m: String| decode_error(path, m);
    let short = || bad("the file ends before its elements do".into());
    let format = body.format;
    let list = el
        .props
        .iter()
        .position(
            |p| matches!(p, Prop::List(n, ..) if n == "vertex_indices" || n == "vertex_index"),
        )
        .ok_or_else(|| bad("faces have no vertex_indices list".into()))?;
    if format != Format::Ascii && el.count > body.data.len() {
        return Err(short());
    }
    for _ in 0..el.count {
        let mut poly: Vec<u32> = Vec::new();
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::One(_, t) => {
                    body.next(*t).ok_or_else(short)?;
                }
                Prop::List(_, c, t) => {
                    let n = body.next(*c).ok_or_else(short)?;
                    if !(0.0..=1024.0).contains(&n) {
                        return Err(bad(format!("a face with {n} vertices")));
                    }
                    for _ in 0..n as usize {
                        let i = body.next(*t).ok_or_else(short)?;
                        if k == list {
                            if !(0.0..=u32::MAX as f64).contains(&i) {
                                return Err(bad(format!("vertex index {i}")));
                            }
                            poly.push(i as u32);
                        }
                    }
                }
            }
        }
        // A fan over the polygon.
        for j in 1..poly.len().saturating_sub(1) {
            part.indices.push([poly[0], poly[j], poly[j + 1]]);
        }
        if part.indices.len() > MAX_MESH_ELEMENTS {
            return Err(bad(format!("more than {MAX_MESH_ELEMENTS} triangles")));
        }
    }
    Ok(())
}

/// Writes `part` as Wavefront OBJ text (positions, normals and faces),
/// the format matflow's shipped meshes use; coordinates to 5 decimals.
pub fn obj_text(part: &MeshPart, comment: &str) -> String {
    // Fixed decimals, trailing zeros dropped, no negative zero.
    let num = |x: f32| {
        let t = format!("{x:.5}");
        let t = t.trim_end_matches('0').trim_end_matches('.');
        if t == "-0" || t.is_empty() {
            "0".to_string()
        } else {
            t.to_string()
        }
    };
    let mut s = String::new();
    for line in comment.lines() {
        s.push_str(&format!("# {line}\n"));
    }
    for p in &part.positions {
        s.push_str(&format!("v {} {} {}\n", num(p.x), num(p.y), num(p.z)));
    }
    for n in &part.normals {
        s.push_str(&format!("vn {} {} {}\n", num(n.x), num(n.y), num(n.z)));
    }
    let with_n = part.normals.len() == part.positions.len() && !part.normals.is_empty();
    for t in &part.indices {
        let [a, b, c] = t.map(|i| i + 1);
        if with_n {
            s.push_str(&format!("f {a}//{a} {b}//{b} {c}//{c}\n"));
        } else {
            s.push_str(&format!("f {a} {b} {c}\n"));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("matflow-meshfile-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn tetra() -> MeshPart {
        MeshPart {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
            indices: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            normals: vec![],
            uvs: vec![],
            material: None,
        }
    }

    #[test]
    fn obj_round_trips_and_reads_its_mtl() {
        let d = tmp("obj");
        let f = d.join("t.obj");
        std::fs::write(&f, obj_text(&tetra(), "a tetrahedron")).unwrap();
        let parts = read_mesh(&f).unwrap();
        assert_eq!(parts.len(), 1);
        // tobj numbers vertices in order of first use: compare triangles.
        let tris = |p: &MeshPart| -> Vec<[Vec3; 3]> {
            p.indices
                .iter()
                .map(|t| t.map(|i| p.positions[i as usize]))
                .collect()
        };
        assert_eq!(tris(&parts[0]), tris(&tetra()));
        // Quads are triangulated; the MTL's glass is read.
        std::fs::write(
            d.join("g.mtl"),
            "newmtl glass\nKd 0.1 0.2 0.3\nNi 1.45\nd 0.1\nTf 0.9 1 0.8\nillum 7\nPr 0.2\n",
        )
        .unwrap();
        std::fs::write(
            d.join("q.obj"),
            "mtllib g.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nusemtl glass\nf 1 2 3 4\n",
        )
        .unwrap();
        let parts = read_mesh(&d.join("q.obj")).unwrap();
        assert_eq!(parts[0].indices.len(), 2);
        let m = parts[0].material.as_ref().unwrap();
        assert_eq!(m.ior, Some(1.45));
        assert_eq!(m.dissolve, Some(0.1));
        assert_eq!(m.illum, Some(7));
        assert_eq!(m.transmission_filter, Some(Vec3::new(0.9, 1.0, 0.8)));
        assert_eq!(m.roughness, Some(0.2));
        let _ = std::fs::remove_dir_all(&d);
    }

    fn ply_binary(part: &MeshPart, extra_element: bool) -> Vec<u8> {
        let mut h = String::from("ply\nformat binary_little_endian 1.0\ncomment test\n");
        h += &format!("element vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\n", part.positions.len());
        if extra_element {
            h += "element junk 2\nproperty list uchar short stuff\n";
        }
        h += &format!(
            "element face {}\nproperty list uchar int vertex_indices\nend_header\n",
            part.indices.len()
        );
        let mut b = h.into_bytes();
        for p in &part.positions {
            for c in p.to_array() {
                b.extend(c.to_le_bytes());
            }
            b.push(7);
        }
        if extra_element {
            b.extend([2u8, 1, 0, 2, 0, 1u8, 5, 0]);
        }
        for t in &part.indices {
            b.push(3);
            for i in t {
                b.extend((*i as i32).to_le_bytes());
            }
        }
        b
    }

    #[test]
    fn ply_ascii_and_binary_are_read() {
        let d = tmp("ply");
        let t = tetra();
        let f = d.join("b.ply");
        std::fs::write(&f, ply_binary(&t, true)).unwrap();
        let p = read_mesh(&f).unwrap().remove(0);
        assert_eq!(
            (p.positions, p.indices),
            (t.positions.clone(), t.indices.clone())
        );
        let mut a = String::from("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n");
        for v in &t.positions {
            a += &format!("{} {} {} 0 0 1\n", v.x, v.y, v.z);
        }
        a += "4 0 1 2 3\n";
        std::fs::write(d.join("a.ply"), a).unwrap();
        let p = read_mesh(&d.join("a.ply")).unwrap().remove(0);
        assert_eq!(p.indices, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(p.normals.len(), 4);
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn damaged_files_are_errors_naming_the_file() {
        let d = tmp("bad");
        let t = tetra();
        let good = ply_binary(&t, false);
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            ("cut.ply", good[..good.len() - 5].to_vec(), "ends before"),
            ("nohdr.ply", b"ply\nformat ascii 1.0\n".to_vec(), "end_header"),
            (
                "huge.ply",
                b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nend_header\n".to_vec(),
                "elements",
            ),
            (
                "idx.obj",
                b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n".to_vec(),
                "",
            ),
            (
                "nan.obj",
                b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
                "",
            ),
            ("x.stl", b"solid".to_vec(), "unknown mesh type"),
        ];
        for (name, bytes, want) in cases {
            let f = d.join(name);
            std::fs::write(&f, bytes).unwrap();
            let e = read_mesh(&f).expect_err(name).to_string();
            assert!(e.contains(name) && e.contains(want), "{name}: {e}");
        }
        let e = read_mesh(&d.join("absent.obj")).unwrap_err().to_string();
        assert!(e.contains("absent.obj"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
