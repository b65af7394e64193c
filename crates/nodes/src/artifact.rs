//! The bytes that flow between nodes: a small, canonical container of
//! named arrays (f32 or u32, with width, height and channel counts), tagged
//! with an artifact type. Equal contents encode to equal bytes, so the
//! store's digests can cut off re-execution downstream.
//!
//! Layout (little endian): `MFAR`, format version (u32), type (u64 length +
//! UTF-8), section count (u32), then per section in name order: name (u64
//! length + UTF-8), dtype (u8: 0 = f32, 1 = u32, 2 = bytes), width, height,
//! channels (u32 each), payload length in bytes (u64), payload.

use std::collections::BTreeMap;

use glam::Vec3;
use matflow_engine::NodeError;
use matflow_scene::{GrayImage, Image, MaterialMaps, RgbImage};

const MAGIC: &[u8; 4] = b"MFAR";
const FORMAT: u32 = 1;

#[derive(Clone, Debug, PartialEq)]
pub enum Data {
    F32(Vec<f32>),
    U32(Vec<u32>),
    Bytes(Vec<u8>),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Section {
    pub width: u32,
    pub height: u32,
    pub channels: u32,
    pub data: Data,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Artifact {
    pub ty: String,
    pub sections: BTreeMap<String, Section>,
}

fn bad(ty: &str, msg: impl std::fmt::Display) -> NodeError {
    NodeError::new(format!("{ty} artifact: {msg}"))
}

impl Artifact {
    pub fn new(ty: &str) -> Artifact {
        Artifact {
            ty: ty.to_string(),
            sections: BTreeMap::new(),
        }
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT.to_le_bytes());
        put_str(&mut out, &self.ty);
        out.extend_from_slice(&(self.sections.len() as u32).to_le_bytes());
        for (name, s) in &self.sections {
            put_str(&mut out, name);
            let (tag, payload): (u8, Vec<u8>) = match &s.data {
                Data::F32(v) => (0, v.iter().flat_map(|x| x.to_le_bytes()).collect()),
                Data::U32(v) => (1, v.iter().flat_map(|x| x.to_le_bytes()).collect()),
                Data::Bytes(v) => (2, v.clone()),
            };
            out.push(tag);
            for d in [s.width, s.height, s.channels] {
                out.extend_from_slice(&d.to_le_bytes());
            }
            out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
            out.extend_from_slice(&payload);
        }
        out
    }

    /// The type the bytes declare, read from the header alone; `None`
    /// when they are not an artifact.
    pub fn type_of(bytes: &[u8]) -> Option<String> {
        let mut r = Reader { b: bytes, at: 0 };
        if r.take(4)? != MAGIC || u32::from_le_bytes(r.take(4)?.try_into().ok()?) != FORMAT {
            return None;
        }
        let n = u64::from_le_bytes(r.take(8)?.try_into().ok()?);
        let s = r.take(usize::try_from(n).ok()?)?;
        String::from_utf8(s.to_vec()).ok()
    }

    /// Decodes and checks the type.
    pub fn decode(bytes: &[u8], want: &str) -> Result<Artifact, NodeError> {
        let mut r = Reader { b: bytes, at: 0 };
        let e = |m: &str| bad(want, m);
        if r.take(4).ok_or_else(|| e("truncated"))? != MAGIC {
            return Err(e("not a matflow artifact"));
        }
        let ver = r.u32().ok_or_else(|| e("truncated"))?;
        if ver != FORMAT {
            return Err(e(&format!("format {ver}, expected {FORMAT}")));
        }
        let ty = r.string().ok_or_else(|| e("truncated type"))?;
        if ty != want {
            return Err(e(&format!("got a {ty} artifact")));
        }
        let n = r.u32().ok_or_else(|| e("truncated"))?;
        let mut sections = BTreeMap::new();
        for _ in 0..n {
            let name = r.string().ok_or_else(|| e("truncated section name"))?;
            let tag = r.take(1).ok_or_else(|| e("truncated"))?[0];
            let (width, height, channels) = (
                r.u32().ok_or_else(|| e("truncated"))?,
                r.u32().ok_or_else(|| e("truncated"))?,
                r.u32().ok_or_else(|| e("truncated"))?,
            );
            let len = r.u64().ok_or_else(|| e("truncated"))? as usize;
            let payload = r.take(len).ok_or_else(|| e("truncated payload"))?;
            let data = match tag {
                0 | 1 if !len.is_multiple_of(4) => {
                    return Err(e("payload not a multiple of 4 bytes"))
                }
                0 => Data::F32(
                    payload
                        .chunks_exact(4)
                        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                ),
                1 => Data::U32(
                    payload
                        .chunks_exact(4)
                        .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                ),
                2 => Data::Bytes(payload.to_vec()),
                _ => return Err(e("unknown data type")),
            };
            sections.insert(
                name,
                Section {
                    width,
                    height,
                    channels,
                    data,
                },
            );
        }
        Ok(Artifact { ty, sections })
    }

    fn section(&self, name: &str) -> Result<&Section, NodeError> {
        self.sections
            .get(name)
            .ok_or_else(|| bad(&self.ty, format!("has no `{name}`")))
    }

    pub fn has(&self, name: &str) -> bool {
        self.sections.contains_key(name)
    }

    fn put(&mut self, name: &str, (width, height, channels): (usize, usize, u32), data: Data) {
        self.sections.insert(
            name.into(),
            Section {
                width: width as u32,
                height: height as u32,
                channels,
                data,
            },
        );
    }

    pub fn put_rgb(&mut self, name: &str, img: &RgbImage) {
        let v = img.data.iter().flat_map(|v| [v.x, v.y, v.z]).collect();
        self.put(name, (img.width, img.height, 3), Data::F32(v));
    }

    pub fn put_gray(&mut self, name: &str, img: &GrayImage) {
        self.put(
            name,
            (img.width, img.height, 1),
            Data::F32(img.data.clone()),
        );
    }

    /// A list of `width` items of `channels` numbers each.
    pub fn put_f32(&mut self, name: &str, width: u32, channels: u32, v: Vec<f32>) {
        self.put(name, (width as usize, 1, channels), Data::F32(v));
    }

    pub fn put_u32(&mut self, name: &str, width: u32, channels: u32, v: Vec<u32>) {
        self.put(name, (width as usize, 1, channels), Data::U32(v));
    }

    pub fn put_bytes(&mut self, name: &str, v: Vec<u8>) {
        self.put(name, (v.len(), 1, 1), Data::Bytes(v));
    }

    fn f32s(&self, name: &str, channels: u32) -> Result<(usize, usize, &[f32]), NodeError> {
        let s = self.section(name)?;
        let (w, h) = (s.width as usize, s.height as usize);
        match &s.data {
            Data::F32(v) if s.channels == channels && v.len() == w * h * channels as usize => {
                Ok((w, h, v))
            }
            _ => Err(bad(&self.ty, format!("`{name}` has the wrong shape"))),
        }
    }

    pub fn rgb(&self, name: &str) -> Result<RgbImage, NodeError> {
        let (w, h, v) = self.f32s(name, 3)?;
        Ok(Image::from_vec(
            w,
            h,
            v.chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2]))
                .collect(),
        ))
    }

    pub fn gray(&self, name: &str) -> Result<GrayImage, NodeError> {
        let (w, h, v) = self.f32s(name, 1)?;
        Ok(Image::from_vec(w, h, v.to_vec()))
    }

    pub fn f32_list(&self, name: &str, channels: u32) -> Result<&[f32], NodeError> {
        Ok(self.f32s(name, channels)?.2)
    }

    pub fn u32_list(&self, name: &str, channels: u32) -> Result<&[u32], NodeError> {
        let s = self.section(name)?;
        match &s.data {
            Data::U32(v) if s.channels == channels => Ok(v),
            _ => Err(bad(&self.ty, format!("`{name}` has the wrong shape"))),
        }
    }

    pub fn bytes(&self, name: &str) -> Result<&[u8], NodeError> {
        match &self.section(name)?.data {
            Data::Bytes(v) => Ok(v),
            _ => Err(bad(&self.ty, format!("`{name}` is not bytes"))),
        }
    }

    /// Material maps stored under `prefix`albedo / roughness / metallic.
    pub fn put_materials(&mut self, prefix: &str, m: &MaterialMaps) {
        self.put_rgb(&format!("{prefix}albedo"), &m.albedo);
        self.put_gray(&format!("{prefix}roughness"), &m.roughness);
        self.put_gray(&format!("{prefix}metallic"), &m.metallic);
        if let Some(n) = &m.normal {
            self.put_rgb(&format!("{prefix}normal"), n);
        }
        if let Some(t) = &m.transparency {
            self.put_gray(&format!("{prefix}glass_ior"), &t.ior);
            self.put_gray(&format!("{prefix}glass_transmission"), &t.transmission);
            self.put_gray(&format!("{prefix}glass_roughness"), &t.roughness);
            self.put_rgb(&format!("{prefix}glass_tint"), &t.tint);
            self.put_gray(&format!("{prefix}glass_d1"), &t.d1);
            self.put_gray(&format!("{prefix}glass_d2"), &t.d2);
            self.put_rgb(&format!("{prefix}bg_albedo"), &t.bg_albedo);
            self.put_gray(&format!("{prefix}bg_roughness"), &t.bg_roughness);
            self.put_gray(&format!("{prefix}bg_metallic"), &t.bg_metallic);
        }
    }

    pub fn materials(&self, prefix: &str) -> Result<MaterialMaps, NodeError> {
        let m = MaterialMaps {
            albedo: self.rgb(&format!("{prefix}albedo"))?,
            roughness: self.gray(&format!("{prefix}roughness"))?,
            metallic: self.gray(&format!("{prefix}metallic"))?,
            normal: if self.has(&format!("{prefix}normal")) {
                Some(self.rgb(&format!("{prefix}normal"))?)
            } else {
                None
            },
            transparency: if self.has(&format!("{prefix}glass_ior")) {
                Some(matflow_scene::transparency::Transparency {
                    ior: self.gray(&format!("{prefix}glass_ior"))?,
                    transmission: self.gray(&format!("{prefix}glass_transmission"))?,
                    roughness: self.gray(&format!("{prefix}glass_roughness"))?,
                    tint: self.rgb(&format!("{prefix}glass_tint"))?,
                    d1: self.gray(&format!("{prefix}glass_d1"))?,
                    d2: self.gray(&format!("{prefix}glass_d2"))?,
                    bg_albedo: self.rgb(&format!("{prefix}bg_albedo"))?,
                    bg_roughness: self.gray(&format!("{prefix}bg_roughness"))?,
                    bg_metallic: self.gray(&format!("{prefix}bg_metallic"))?,
                })
            } else {
                None
            },
        };
        if !m.albedo.same_size(&m.roughness) || !m.albedo.same_size(&m.metallic) {
            return Err(bad(&self.ty, "material maps differ in size"));
        }
        if let Some(t) = &m.transparency {
            if !t.has_size(m.albedo.width, m.albedo.height) {
                return Err(bad(&self.ty, "transparency maps differ in size"));
            }
        }
        Ok(m)
    }
}

fn put_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u64).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.at.checked_add(n)?;
        let s = self.b.get(self.at..end)?;
        self.at = end;
        Some(s)
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
    }
    fn string(&mut self) -> Option<String> {
        let n = self.u64()? as usize;
        String::from_utf8(self.take(n)?.to_vec()).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_damage() {
        let mut a = Artifact::new("scene");
        a.put_rgb(
            "target",
            &Image::from_fn(3, 2, |x, y| Vec3::new(x as f32, y as f32, 0.5)),
        );
        a.put_gray("depth", &Image::new(3, 2, 2.0));
        a.put_u32("idx", 2, 3, vec![0, 1, 2, 2, 1, 0]);
        let b = a.encode();
        assert_eq!(b, a.clone().encode(), "encoding is canonical");
        let back = Artifact::decode(&b, "scene").unwrap();
        assert_eq!(back, a);
        assert_eq!(
            back.rgb("target").unwrap().get(2, 1),
            Vec3::new(2.0, 1.0, 0.5)
        );
        assert!(Artifact::decode(&b, "mesh").is_err());
        assert!(Artifact::decode(&b[..b.len() - 3], "scene").is_err());
        assert!(back.rgb("depth").is_err(), "wrong channel count is named");
    }
}
