//! A studio session: a pipeline in a folder of its own (`session.yaml`,
//! with the masks its edits use beside it), whose stages are the session.
//!
//! ```text
//! scene      the input: a photo predicted (`matnet`), a bundle, or a
//!            pipeline file's own stages
//! mesh       the geometry (and what is chosen past the frame)
//! lighting   envmap recovery;  recovered: envmap + materials
//! base       the re-render, keeping its light paths for edits
//! edit1..N   the history: material edits (`edit`, each on the one
//!            before) and new lighting (`relight`)
//! result     the last edit rendered from the kept paths into the photo;
//!            under new lighting, the whole scene rendered under it
//! quick,     the same at a few samples per pixel: the first look at an
//! preview    edit (not among the outputs: `matflow run` skips them)
//! ```
//!
//! Undo and redo move the last edit stage between the pipeline and a redo
//! list. The file is the whole session: `matflow run session.yaml`
//! computes the studio's result byte for byte, and the studio opening it
//! takes its edits back.

use std::path::{Path, PathBuf};

use matflow_engine::spec::Pipeline;
use matflow_engine::value::{parse_yaml, Value};
use matflow_engine::{ParamType, Registry};
use matflow_scene::Image;

/// What went wrong opening, changing or running a session.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("{0}: not a photo (.png, .jpg, .jpeg, .exr), a bundle folder or a pipeline (.yaml)")]
    Input(PathBuf),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{0}")]
    Pipeline(String),
    /// A request the session cannot take (a 4xx).
    #[error("{0}")]
    Request(String),
    /// A request the session cannot take as it stands (nothing to undo).
    #[error("{0}")]
    Conflict(String),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> SessionError + '_ {
    move |source| SessionError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One stage as the file spells it: its name and its fields, each value
/// YAML flow text (`kind` first).
#[derive(Clone, Debug, PartialEq)]
pub struct Stage {
    pub name: String,
    pub fields: Vec<(String, String)>,
    /// Stages this one needs that come and go with it in the history
    /// (`editN_lengths`, the refraction lengths of a transparency),
    /// written before it.
    pub helpers: Vec<Stage>,
}

impl Stage {
    fn new(name: &str, fields: &[(&str, String)]) -> Stage {
        Stage {
            name: name.into(),
            fields: fields
                .iter()
                .map(|(k, v)| (k.to_string(), v.clone()))
                .collect(),
            helpers: vec![],
        }
    }
    pub fn get(&self, key: &str) -> Option<&str> {
        self.fields
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }
    fn set(&mut self, key: &str, value: String) {
        match self.fields.iter_mut().find(|(k, _)| k == key) {
            Some(f) => f.1 = value,
            None => self.fields.push((key.into(), value)),
        }
    }
    /// What the edit does, for the history list: its kind and fields.
    pub fn describe(&self) -> String {
        let fields: Vec<String> = self
            .fields
            .iter()
            .filter(|(k, _)| k != "kind" && k != "materials")
            .map(|(k, v)| format!("{k} {v}"))
            .collect();
        format!(
            "{} ({}): {}",
            self.name,
            self.get("kind").unwrap_or_default(),
            fields.join(", ")
        )
    }
}

/// A string as YAML: bare where YAML reads it back as this string (a
/// name, a file name), else double-quoted (JSON's quoting is YAML's).
fn quoted(s: &str) -> String {
    let plain = s.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
        && !matches!(
            s.to_ascii_lowercase().as_str(),
            "true" | "false" | "null" | "yes" | "no" | "on" | "off" | "y" | "n" | "inf" | "nan"
        );
    if plain {
        s.into()
    } else {
        serde_json::to_string(s).unwrap_or_default()
    }
}

/// [`quoted`]'s text back as the string.
fn unquoted(v: &str) -> String {
    serde_json::from_str(v).unwrap_or_else(|_| v.to_string())
}

/// A number as YAML that reads back as the same f64 (and as a number
/// where an integer is asked, when it is whole).
fn number(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        format!("{}", x as i64)
    } else {
        format!("{x:?}")
    }
}

/// A parsed value back as YAML flow text.
fn flow(v: &Value) -> String {
    match v {
        Value::Null => "~".into(),
        Value::Bool(b) => b.to_string(),
        Value::Int(i) => i.to_string(),
        Value::Float(f) => format!("{f:?}"),
        Value::Str(s) => quoted(s),
        Value::List(l) => format!("[{}]", l.iter().map(flow).collect::<Vec<_>>().join(", ")),
        Value::Map(m) => format!(
            "{{{}}}",
            m.iter()
                .map(|(k, _, v, _)| format!("{}: {}", quoted(k), flow(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// The stage names the studio writes itself.
const GENERATED: [&str; 3] = ["quick", "preview", "result"];

/// Samples per pixel of the first look at an edit.
pub const PREVIEW_SPP: i64 = 4;

/// A material change, as the page sends it: each field optional, the
/// albedo γ-encoded (as a colour picker shows it).
#[derive(Clone, Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Change {
    pub albedo: Option<[f64; 3]>,
    pub hue_shift: Option<f64>,
    pub saturation_scale: Option<f64>,
    pub value_scale: Option<f64>,
    pub roughness: Option<f64>,
    pub metallic: Option<f64>,
}

/// New lighting, as the page sends it: the recovered envmap or one the
/// session holds (`envmap`, a file name from [`Session::envmaps`]),
/// rotated about the vertical axis (degrees) and exposed (stops).
#[derive(Clone, Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Light {
    pub envmap: Option<String>,
    #[serde(default)]
    pub rotation: f64,
    #[serde(default)]
    pub exposure: f64,
}

/// The history's stage kinds: a material edit, new lighting.
const HISTORY_KINDS: [&str; 4] = ["edit", "relight", "insert", "transparency"];

/// A region made glass, as the page sends it (on the selection).
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Glass {
    #[serde(default = "ior")]
    pub ior: f64,
    #[serde(default = "one")]
    pub transmission: f64,
    pub roughness: Option<f64>,
}

fn ior() -> f64 {
    1.5
}

/// The meshes the studio offers by name (`matflow_procgen::shapes::shipped`,
/// written into the session as `mesh-NAME.obj` when first used).
pub const SHIPPED_MESHES: [&str; 4] = ["jug", "torus", "sphere", "cube"];

/// An object to insert, as the page sends it: a shipped mesh by name or
/// one uploaded to the session (`mesh-….obj`/`.ply`), the pixel it stands
/// on, its size and turn about its up axis, and its material.
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Object {
    pub mesh: String,
    pub anchor: [f64; 2],
    #[serde(default = "one")]
    pub scale: f64,
    /// Degrees about the object's up axis.
    #[serde(default)]
    pub rotate: f64,
    pub material: ObjectMaterial,
}

fn one() -> f64 {
    1.0
}

/// An inserted object's material: `diffuse`, `principled` or `glass`;
/// the albedo γ-encoded (as a colour picker shows it).
#[derive(Clone, Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectMaterial {
    #[serde(rename = "type")]
    pub kind: String,
    pub albedo: Option<[f64; 3]>,
    pub roughness: Option<f64>,
    pub metallic: Option<f64>,
    pub ior: Option<f64>,
}

/// The session's own files named in `text` (masks, envmaps, meshes: the
/// names the studio gives them).
fn session_files(text: &str) -> Vec<String> {
    let mut v: Vec<String> = text
        .split(|c: char| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_')))
        .filter(|w| {
            ["mask-", "envmap-", "mesh-", "photo-"]
                .iter()
                .any(|p| w.starts_with(p))
                && [".png", ".hdr", ".exr", ".obj", ".ply", ".jpg"]
                    .iter()
                    .any(|e| w.ends_with(e))
        })
        .map(str::to_string)
        .collect();
    v.sort();
    v.dedup();
    v
}

/// A session: its folder and its stages.
pub struct Session {
    pub dir: PathBuf,
    base: Vec<Stage>,
    edits: Vec<Stage>,
    undone: Vec<Stage>,
}

impl Session {
    /// A session on `input` (a photo, a bundle folder or a pipeline file,
    /// absolute) kept in `dir`: its `session.yaml` is written.
    pub fn open(input: &Path, dir: &Path, reg: &Registry) -> Result<Session, SessionError> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        let ext = input
            .extension()
            .map(|e| e.to_string_lossy().to_lowercase())
            .unwrap_or_default();
        // A file in the session's own folder (an uploaded photo) is named
        // relative to it, so that it travels with the session.
        let path = match input.strip_prefix(dir) {
            Ok(rel) if rel.components().count() == 1 => quoted(&rel.display().to_string()),
            _ => quoted(&input.display().to_string()),
        };
        let (mut base, edits) = if input.is_dir() {
            let scene = Stage::new(
                "scene",
                &[
                    ("kind", "bundle".into()),
                    ("path", path),
                    ("materials", "pred".into()),
                ],
            );
            (vec![scene], vec![])
        } else {
            match ext.as_str() {
                "png" | "jpg" | "jpeg" | "exr" => (
                    vec![Stage::new(
                        "scene",
                        &[("kind", "matnet".into()), ("photo", path)],
                    )],
                    vec![],
                ),
                "yaml" | "yml" => stages_of_file(input, dir, reg)?,
                _ => return Err(SessionError::Input(input.to_path_buf())),
            }
        };
        complete_base(&mut base)?;
        let s = Session {
            dir: dir.to_path_buf(),
            base,
            edits,
            undone: vec![],
        };
        s.pipeline(reg)?;
        s.save()?;
        Ok(s)
    }

    /// The stage the renders take their materials from: the last edit.
    fn last(&self) -> &str {
        self.edits
            .iter()
            .rev()
            .find(|e| matches!(e.get("kind"), Some("edit" | "transparency")))
            .map_or("recovered", |e| e.name.as_str())
    }

    /// The objects in the scene: the last `insert` of the history's.
    fn objects(&self) -> Option<&str> {
        self.edits
            .iter()
            .rev()
            .find(|e| e.get("kind") == Some("insert"))
            .and_then(|e| e.get("objects"))
    }

    /// The objects in the scene as the page sends them (shipped meshes by
    /// name, the albedo γ-encoded), read back from the last `insert`.
    pub fn objects_json(&self) -> serde_json::Value {
        let Some(text) = self.objects() else {
            return serde_json::json!([]);
        };
        let Ok((Value::List(items), _)) = parse_yaml(text) else {
            return serde_json::json!([]);
        };
        let field = |m: &[(
            String,
            matflow_engine::value::Loc,
            Value,
            matflow_engine::value::Loc,
        )],
                     k: &str| {
            m.iter()
                .find(|(n, ..)| n == k)
                .map(|(_, _, v, _)| v.clone())
        };
        let num = |v: Option<Value>| v.and_then(|v| v.as_f64());
        let list = |v: Option<Value>| match v {
            Some(Value::List(l)) => l.iter().filter_map(|x| x.as_f64()).collect(),
            _ => vec![],
        };
        let objs: Vec<serde_json::Value> = items
            .iter()
            .filter_map(|it| match it {
                Value::Map(m) => Some(m),
                _ => None,
            })
            .map(|m| {
                let mesh = match field(m, "mesh") {
                    Some(Value::Str(f)) => f,
                    _ => String::new(),
                };
                let shipped = SHIPPED_MESHES.iter().find(|s| mesh == format!("mesh-{s}.obj"));
                let mat = match field(m, "material") {
                    Some(Value::Map(mm)) => mm,
                    _ => vec![],
                };
                let albedo: Vec<f64> = list(field(&mat, "albedo"))
                    .iter()
                    .map(|c| (matflow_scene::color::linear_to_gamma(*c as f32) as f64 * 1e3).round() / 1e3)
                    .collect();
                serde_json::json!({
                    "mesh": shipped.map_or(mesh.clone(), |s| s.to_string()),
                    "anchor": list(field(m, "anchor")),
                    "scale": num(field(m, "scale")).unwrap_or(1.0),
                    "rotate": list(field(m, "rotate")).get(1).copied().unwrap_or(0.0),
                    "material": {
                        "type": match field(&mat, "type") { Some(Value::Str(t)) => t, _ => "diffuse".into() },
                        "albedo": (albedo.len() == 3).then_some(albedo),
                        "roughness": num(field(&mat, "roughness")),
                        "metallic": num(field(&mat, "metallic")),
                        "ior": num(field(&mat, "ior")),
                    },
                })
            })
            .collect();
        serde_json::Value::Array(objs)
    }

    /// The lighting stage in force: the last `relight` of the history.
    fn light_stage(&self) -> Option<&str> {
        self.edits
            .iter()
            .rev()
            .find(|e| e.get("kind") == Some("relight"))
            .map(|e| e.name.as_str())
    }

    /// The session as pipeline text.
    pub fn yaml(&self) -> String {
        let base = self
            .stage("base")
            .cloned()
            .unwrap_or_else(|| Stage::new("base", &[]));
        let mut quick = base.clone();
        quick.name = "quick".into();
        quick.set("spp", PREVIEW_SPP.to_string());
        quick.set("path_spp", "1".into());
        let render = |name: &str, paths: &str| {
            Stage::new(
                name,
                &[
                    ("kind", "render".into()),
                    ("mesh", "mesh".into()),
                    ("paths", paths.into()),
                    ("materials", self.last().into()),
                    ("photo", "scene".into()),
                ],
            )
        };
        let spp = base.get("spp").unwrap_or("64").to_string();
        let light = self.light_stage();
        let (preview, mut result) = if let Some(objects) = self.objects() {
            // Objects: rendered with full geometry and composited into the
            // photo (photo + with − without); under new light, the whole
            // render.
            let insert = |name: &str, spp: String| {
                let mut st = Stage::new(
                    name,
                    &[
                        ("kind", "insert".into()),
                        ("mesh", "mesh".into()),
                        ("materials", self.last().into()),
                        ("envmap", light.unwrap_or("recovered.envmap").into()),
                        ("objects", objects.into()),
                        ("spp", spp),
                    ],
                );
                match light {
                    None => st.set("photo", "scene".into()),
                    Some(_) => st.set("composite", "full".into()),
                }
                st
            };
            (
                insert("preview", PREVIEW_SPP.to_string()),
                insert("result", spp),
            )
        } else if let Some(light) = light {
            // New light: the whole scene rendered under it (the kept paths
            // and the photo belong to the old one).
            let relit = |name: &str, spp: String| {
                Stage::new(
                    name,
                    &[
                        ("kind", "render".into()),
                        ("mesh", "mesh".into()),
                        ("materials", self.last().into()),
                        ("envmap", light.into()),
                        ("spp", spp),
                    ],
                )
            };
            (
                relit("preview", PREVIEW_SPP.to_string()),
                relit("result", spp),
            )
        } else {
            (render("preview", "quick"), render("result", "base"))
        };
        result.set("output", quoted("result.exr"));
        let mut out = String::from(
            "# A matflow studio session: `matflow run session.yaml` renders its\n\
             # result (result.exr); `matflow studio session.yaml` opens it again.\n\
             pipeline: studio\noutputs: [result]\nstages:\n",
        );
        let history = self
            .edits
            .iter()
            .flat_map(|e| e.helpers.iter().chain(std::iter::once(e)));
        let all = self.base.iter().chain(history);
        for st in all.chain([&quick, &preview, &result]) {
            out += &format!("  {}:\n", st.name);
            for (k, v) in &st.fields {
                out += &format!("    {k}: {v}\n");
            }
        }
        out
    }

    fn stage(&self, name: &str) -> Option<&Stage> {
        self.base.iter().chain(&self.edits).find(|s| s.name == name)
    }

    /// The session's pipeline, validated.
    pub fn pipeline(&self, reg: &Registry) -> Result<Pipeline, SessionError> {
        matflow_engine::spec::parse(&self.yaml(), &self.dir.join("session.yaml"), reg, &[])
            .map_err(|e| SessionError::Pipeline(e.to_string()))
    }

    /// Writes `session.yaml` (when it changed).
    pub fn save(&self) -> Result<(), SessionError> {
        let f = self.dir.join("session.yaml");
        matflow_scene::io::write_if_changed(&f, self.yaml().as_bytes())
            .map_err(|e| SessionError::Pipeline(e.to_string()))?;
        Ok(())
    }

    /// Adds an edit of `mask` by `change` (its mask written beside the
    /// pipeline, named by its contents); the redo list is dropped. Checked
    /// as the engine checks any pipeline before it is taken.
    pub fn edit(
        &mut self,
        mask: &Image<bool>,
        change: &Change,
        reg: &Registry,
    ) -> Result<(), SessionError> {
        let name = self.write_mask(mask)?;
        let mut st = Stage::new(
            &format!("edit{}", self.edits.len() + 1),
            &[
                ("kind", "edit".into()),
                ("materials", self.last().into()),
                ("mask_png", quoted(&name)),
            ],
        );
        if let Some(a) = change.albedo {
            st.set("albedo", format!("[{}]", a.map(number).join(", ")));
        }
        for (k, v) in [
            ("hue_shift", change.hue_shift),
            ("saturation_scale", change.saturation_scale),
            ("value_scale", change.value_scale),
            ("roughness", change.roughness),
            ("metallic", change.metallic),
        ] {
            if let Some(v) = v {
                st.set(k, number(v));
            }
        }
        if st.fields.len() == 3 {
            return Err(SessionError::Request(
                "the change changes nothing: give albedo, hue_shift, saturation_scale, \
                 value_scale, roughness or metallic"
                    .into(),
            ));
        }
        self.push(st, reg)
    }

    /// Adds new lighting (a `relight` stage of the recovered envmap or of
    /// one of the session's files); the redo list is dropped.
    pub fn light(&mut self, light: &Light, reg: &Registry) -> Result<(), SessionError> {
        let mut st = Stage::new(
            &format!("edit{}", self.edits.len() + 1),
            &[("kind", "relight".into())],
        );
        match &light.envmap {
            None => st.set("source", "recovered.envmap".into()),
            Some(name) => {
                if !self.envmaps().contains(name) {
                    return Err(SessionError::Request(format!(
                        "no envmap {name:?} in the session: upload it first"
                    )));
                }
                st.set("path", quoted(name));
            }
        }
        st.set("rotation", number(light.rotation));
        st.set("exposure", number(light.exposure));
        self.push(st, reg)
    }

    /// The mask as a PNG beside the pipeline, named by its contents; an
    /// empty one is refused (nothing selected).
    fn write_mask(&self, mask: &Image<bool>) -> Result<String, SessionError> {
        if !mask.data.iter().any(|&b| b) {
            return Err(SessionError::Request("select something first".into()));
        }
        let png = matflow_scene::io::png_mask_bytes(mask)
            .map_err(|e| SessionError::Pipeline(e.to_string()))?;
        let hex = matflow_engine::store::Digest::of(&png).hex();
        let name = format!("mask-{}.png", &hex[..16]);
        let file = self.dir.join(&name);
        matflow_scene::io::write_if_changed(&file, &png)
            .map_err(|e| SessionError::Pipeline(e.to_string()))?;
        Ok(name)
    }

    /// Makes `mask` glass (the paper's single-view transparency): a
    /// `transparency` stage, its refraction lengths from matflow's network
    /// (`refraction_length` on the same mask, its helper `editN_lengths`).
    pub fn glass(
        &mut self,
        mask: &Image<bool>,
        glass: &Glass,
        reg: &Registry,
    ) -> Result<(), SessionError> {
        let name = self.write_mask(mask)?;
        let n = self.edits.len() + 1;
        let lengths = Stage::new(
            &format!("edit{n}_lengths"),
            &[
                ("kind", "refraction_length".into()),
                ("scene", "scene".into()),
                ("mask_png", quoted(&name)),
            ],
        );
        let mut st = Stage::new(
            &format!("edit{n}"),
            &[
                ("kind", "transparency".into()),
                ("materials", self.last().into()),
                ("mesh", "mesh".into()),
                ("mask_png", quoted(&name)),
                ("refraction", lengths.name.clone()),
                ("ior", number(glass.ior)),
                ("transmission", number(glass.transmission)),
            ],
        );
        if let Some(r) = glass.roughness {
            st.set("roughness", number(r));
        }
        st.helpers.push(lengths);
        self.push(st, reg)
    }

    /// Places `objects` (all of them: adding, moving and removing one are
    /// each a new placement) as an `insert` stage of the history.
    pub fn insert(&mut self, objects: &[Object], reg: &Registry) -> Result<(), SessionError> {
        if objects.is_empty() {
            return Err(SessionError::Request(
                "no objects: to take the last one out, undo its insertion".into(),
            ));
        }
        let meshes = self.meshes();
        let mut items = Vec::new();
        for (i, o) in objects.iter().enumerate() {
            let file = if SHIPPED_MESHES.contains(&o.mesh.as_str()) {
                self.shipped_mesh(&o.mesh)?
            } else if meshes.contains(&o.mesh) {
                o.mesh.clone()
            } else {
                return Err(SessionError::Request(format!(
                    "objects[{i}]: no mesh {:?}: one of {} or an uploaded one",
                    o.mesh,
                    SHIPPED_MESHES.join(", ")
                )));
            };
            let nums = |v: &[f64]| v.iter().map(|x| number(*x)).collect::<Vec<_>>().join(", ");
            let m = &o.material;
            let mut mat = vec![format!("type: {}", quoted(&m.kind))];
            if let Some(a) = m.albedo {
                // Linear, rounded: the file reads as the picker's colour.
                let lin = a.map(|c| {
                    let l = matflow_scene::color::gamma_to_linear(c.clamp(0.0, 1.0) as f32);
                    (l as f64 * 1e4).round() / 1e4
                });
                mat.push(format!("albedo: [{}]", nums(&lin)));
            }
            for (k, v) in [
                ("roughness", m.roughness),
                ("metallic", m.metallic),
                ("ior", m.ior),
            ] {
                if let Some(v) = v {
                    mat.push(format!("{k}: {}", number(v)));
                }
            }
            items.push(format!(
                "{{mesh: {}, anchor: [{}], scale: {}, rotate: [0, {}, 0], material: {{{}}}}}",
                quoted(&file),
                nums(&o.anchor),
                number(o.scale),
                number(o.rotate),
                mat.join(", ")
            ));
        }
        let mut st = Stage::new(
            &format!("edit{}", self.edits.len() + 1),
            &[
                ("kind", "insert".into()),
                ("mesh", "mesh".into()),
                ("materials", self.last().into()),
                (
                    "envmap",
                    self.light_stage().unwrap_or("recovered.envmap").into(),
                ),
            ],
        );
        st.set("objects", format!("[{}]", items.join(", ")));
        st.set("photo", "scene".into());
        self.push(st, reg)
    }

    /// A shipped mesh written into the session (once), by its file name.
    fn shipped_mesh(&self, name: &str) -> Result<String, SessionError> {
        let file = format!("mesh-{name}.obj");
        let path = self.dir.join(&file);
        if !path.is_file() {
            let (_, shape) = matflow_procgen::shapes::shipped()
                .into_iter()
                .find(|(n, _)| *n == name)
                .ok_or_else(|| SessionError::Request(format!("no shipped mesh {name:?}")))?;
            let part = matflow_scene::meshfile::MeshPart {
                positions: shape.mesh.positions.clone(),
                indices: shape.mesh.indices.clone(),
                normals: shape.normals.clone(),
                ..Default::default()
            };
            let text = matflow_scene::meshfile::obj_text(
                &part,
                &format!("{name}: generated by matflow (matflow_procgen::shapes::shipped)"),
            );
            matflow_scene::io::write_atomic(&path, text.as_bytes())
                .map_err(|e| SessionError::Pipeline(e.to_string()))?;
        }
        Ok(file)
    }

    /// An uploaded mesh (PLY, told by its first bytes, else OBJ) kept in
    /// the session's folder `dir`, named by its contents; read as
    /// `insert` reads it, within its limits. Returns its name.
    pub fn add_mesh(dir: &Path, bytes: &[u8]) -> Result<String, SessionError> {
        let ext = if bytes.starts_with(b"ply") {
            "ply"
        } else {
            "obj"
        };
        keep_upload(dir, bytes, "mesh", ext, |f| {
            matflow_scene::meshfile::read_mesh(f)
                .map(|_| ())
                .map_err(|e| e.to_string())
        })
    }

    /// The session on another photo: its scene stage a `matnet` of
    /// `photo` (in the session's folder), its other settings (mesh,
    /// recovery, trace) kept, its history empty.
    pub fn on_photo(&self, photo: &Path, reg: &Registry) -> Result<Session, SessionError> {
        let name = photo
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let scene = Stage::new(
            "scene",
            &[("kind", "matnet".into()), ("photo", quoted(&name))],
        );
        let base = self
            .base
            .iter()
            .map(|s| {
                if s.name == "scene" {
                    scene.clone()
                } else {
                    s.clone()
                }
            })
            .collect();
        let s = Session {
            dir: self.dir.clone(),
            base,
            edits: vec![],
            undone: vec![],
        };
        s.pipeline(reg)?;
        s.save()?;
        Ok(s)
    }

    /// An uploaded photo (PNG, JPEG or OpenEXR, told by its first bytes)
    /// kept in `dir`, named by its contents, once its size (read from its
    /// header) is one matflow predicts from. Returns its path.
    pub fn add_photo(dir: &Path, bytes: &[u8]) -> Result<PathBuf, SessionError> {
        let ext = if bytes.starts_with(b"\x89PNG") {
            "png"
        } else if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
            "jpg"
        } else if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
            "exr"
        } else {
            return Err(SessionError::Request(
                "not a photo: give a PNG, a JPEG or a linear OpenEXR".into(),
            ));
        };
        let name = keep_upload(dir, bytes, "photo", ext, |f| {
            let (w, h) = if ext == "exr" {
                matflow_scene::io::exr_size(f).map_err(|e| e.to_string())?
            } else {
                let r = image::ImageReader::open(f)
                    .and_then(|r| r.with_guessed_format())
                    .map_err(|e| e.to_string())?;
                let (w, h) = r.into_dimensions().map_err(|e| e.to_string())?;
                (w as usize, h as usize)
            };
            let side = matflow_nodes::MIN_PHOTO_SIDE;
            if w.min(h) < side || w.max(h) > 16384 {
                return Err(format!(
                    "the photo is {w}x{h}: its sides must be {side} to 16384 pixels"
                ));
            }
            Ok(())
        })?;
        Ok(dir.join(name))
    }

    /// The meshes uploaded to the session, by name.
    pub fn meshes(&self) -> Vec<String> {
        self.files("mesh-", &[".obj", ".ply"])
            .into_iter()
            .filter(|n| !SHIPPED_MESHES.iter().any(|s| *n == format!("mesh-{s}.obj")))
            .collect()
    }

    /// The session's files named `PREFIX…` ending in one of `exts`.
    fn files(&self, prefix: &str, exts: &[&str]) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(&self.dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(prefix) && exts.iter().any(|e| n.ends_with(e)))
            .collect();
        v.sort();
        v
    }

    /// An uploaded environment map (Radiance HDR or OpenEXR, told by its
    /// first bytes) kept in the session's folder `dir`, named by its
    /// contents; checked as `relight` reads it. Returns its name.
    pub fn add_envmap(dir: &Path, bytes: &[u8]) -> Result<String, SessionError> {
        let ext = if bytes.starts_with(b"#?") {
            "hdr"
        } else if bytes.starts_with(&[0x76, 0x2f, 0x31, 0x01]) {
            "exr"
        } else {
            return Err(SessionError::Request(
                "not an environment map: give a Radiance .hdr or an OpenEXR .exr".into(),
            ));
        };
        keep_upload(dir, bytes, "envmap", ext, |f| {
            matflow_scene::io::read_envmap(f)
                .map(|_| ())
                .map_err(|e| e.to_string())
        })
    }

    /// The environment maps the session holds (uploaded), by name.
    pub fn envmaps(&self) -> Vec<String> {
        self.files("envmap-", &[".hdr", ".exr"])
    }

    /// Appends a history stage, checked as the engine checks any pipeline.
    fn push(&mut self, st: Stage, reg: &Registry) -> Result<(), SessionError> {
        self.edits.push(st);
        if let Err(e) = self.pipeline(reg) {
            self.edits.pop();
            return Err(SessionError::Request(e.to_string()));
        }
        self.undone.clear();
        self.save()
    }

    /// The geometry past the frame the `mesh` stage is asked for (its
    /// `complete`; `auto` when the file leaves it out).
    pub fn geometry(&self) -> String {
        self.stage("mesh")
            .and_then(|m| m.get("complete"))
            .map(unquoted)
            .unwrap_or_else(|| "auto".into())
    }

    /// Asks the `mesh` stage for other geometry past the frame (not a step
    /// of the history: the recovery and every render after it run again).
    pub fn set_geometry(&mut self, mode: &str, reg: &Registry) -> Result<(), SessionError> {
        let Some(i) = self.base.iter().position(|s| s.name == "mesh") else {
            return Err(SessionError::Request(
                "the session has no `mesh` stage".into(),
            ));
        };
        let before = self.base[i].clone();
        self.base[i].set("complete", quoted(mode));
        if let Err(e) = self.pipeline(reg) {
            self.base[i] = before;
            return Err(SessionError::Request(e.to_string()));
        }
        self.save()
    }

    /// Takes the last edit back (kept for redo); false when there is none.
    pub fn undo(&mut self) -> Result<bool, SessionError> {
        let Some(e) = self.edits.pop() else {
            return Ok(false);
        };
        self.undone.push(e);
        self.save()?;
        Ok(true)
    }

    /// Puts the last edit taken back in again; false when there is none.
    pub fn redo(&mut self) -> Result<bool, SessionError> {
        let Some(e) = self.undone.pop() else {
            return Ok(false);
        };
        self.edits.push(e);
        self.save()?;
        Ok(true)
    }

    /// The edit history (oldest first) and how many edits redo can bring
    /// back.
    pub fn history(&self) -> (Vec<String>, usize) {
        (
            self.edits.iter().map(Stage::describe).collect(),
            self.undone.len(),
        )
    }

    /// The session as a tar archive: `session.yaml` and the masks its
    /// edits name, flat beside it; unpacked anywhere, `matflow run
    /// session.yaml` renders the result.
    pub fn export(&self) -> Result<Vec<u8>, SessionError> {
        let mut tar = matflow_dataset::tar::Writer::new();
        let bad = |e: matflow_dataset::tar::TarError| SessionError::Pipeline(e.to_string());
        tar.add("session.yaml", self.yaml().as_bytes())
            .map_err(bad)?;
        for m in session_files(&self.yaml()) {
            let f = self.dir.join(&m);
            let bytes = std::fs::read(&f).map_err(io_err(&f))?;
            tar.add(&m, &bytes).map_err(bad)?;
        }
        Ok(tar.finish())
    }
}

/// Keeps `bytes` as `PREFIX-HASH.EXT` in the session's folder `dir` once
/// `check` accepts the file (its errors name "the uploaded PREFIX").
fn keep_upload(
    dir: &Path,
    bytes: &[u8],
    prefix: &str,
    ext: &str,
    check: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<String, SessionError> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    let hex = matflow_engine::store::Digest::of(bytes).hex();
    let name = format!("{prefix}-{}.{ext}", &hex[..16]);
    let file = dir.join(&name);
    let tmp = dir.join(format!("upload-{}.{ext}", &hex[..16]));
    std::fs::write(&tmp, bytes).map_err(io_err(&tmp))?;
    match check(&tmp) {
        Ok(()) => std::fs::rename(&tmp, &file).map_err(io_err(&file))?,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(SessionError::Request(e.replace(
                &tmp.display().to_string(),
                &format!("the uploaded {prefix}"),
            )));
        }
    }
    Ok(name)
}

/// The studio's stages after the scene, where the input does not have
/// them: the mesh, the recovery and the kept-path render.
fn complete_base(base: &mut Vec<Stage>) -> Result<(), SessionError> {
    if !base.iter().any(|s| s.name == "scene") {
        return Err(SessionError::Request(
            "the pipeline has no `scene` stage (a matnet, bundle or synthetic_scene stage \
             named `scene`)"
                .into(),
        ));
    }
    let defaults = [
        Stage::new(
            "mesh",
            &[("kind", "mesh".into()), ("scene", "scene".into())],
        ),
        Stage::new(
            "lighting",
            &[
                ("kind", "envmap_opt".into()),
                ("scene", "scene".into()),
                ("mesh", "mesh".into()),
                ("budget_seconds", "10".into()),
            ],
        ),
        Stage::new(
            "recovered",
            &[
                ("kind", "material_opt".into()),
                ("scene", "scene".into()),
                ("mesh", "mesh".into()),
                ("envmap", "lighting".into()),
                ("budget_seconds", "30".into()),
            ],
        ),
        Stage::new(
            "base",
            &[
                ("kind", "trace".into()),
                ("mesh", "mesh".into()),
                ("materials", "recovered".into()),
                ("envmap", "recovered.envmap".into()),
                ("spp", "64".into()),
                ("path_spp", "8".into()),
            ],
        ),
    ];
    for d in defaults {
        if !base.iter().any(|s| s.name == d.name) {
            base.push(d);
        }
    }
    Ok(())
}

/// A pipeline file's stages: the history (`editN`, in order: `edit` and
/// `relight` stages) and the rest; the stages the studio writes itself
/// are dropped. Its relative input paths are made absolute, except the
/// history's files (masks, envmaps), which are copied into the session's
/// folder (they travel with it).
fn stages_of_file(
    file: &Path,
    dir: &Path,
    reg: &Registry,
) -> Result<(Vec<Stage>, Vec<Stage>), SessionError> {
    let text = std::fs::read_to_string(file).map_err(io_err(file))?;
    let bad = |m: String| SessionError::Pipeline(format!("{}: {m}", file.display()));
    let (root, _) = parse_yaml(&text).map_err(|e| bad(format!("{}: {}", e.loc, e.message)))?;
    let Value::Map(top) = root else {
        return Err(bad("not a pipeline (a mapping with `stages:`)".into()));
    };
    let Some((_, _, Value::Map(stages), _)) = top.iter().find(|(k, ..)| k == "stages") else {
        return Err(bad("no `stages:` mapping".into()));
    };
    let folder = file.parent().unwrap_or(Path::new("."));
    let (mut base, mut edits, mut helpers) = (vec![], vec![], vec![]);
    for (name, _, v, loc) in stages {
        let Value::Map(fields) = v else {
            return Err(bad(format!("{loc}: stage `{name}` is not a mapping")));
        };
        if GENERATED.contains(&name.as_str()) {
            continue;
        }
        let kind = fields
            .iter()
            .find(|(k, ..)| k == "kind")
            .and_then(|(_, _, v, _)| match v {
                Value::Str(s) => Some(s.as_str()),
                _ => None,
            })
            .unwrap_or_default();
        let is_edit = HISTORY_KINDS.contains(&kind) && name == &format!("edit{}", edits.len() + 1);
        let is_helper = name.starts_with(&format!("edit{}_", edits.len() + 1));
        let specs = reg.get(kind).map(|n| n.params()).unwrap_or(&[]);
        let mut st = Stage {
            name: name.clone(),
            fields: vec![],
            helpers: vec![],
        };
        for (k, _, v, _) in fields {
            let in_path = specs
                .iter()
                .any(|p| p.name == k && matches!(p.ty, ParamType::InPath));
            let text = match v {
                Value::Str(s) if in_path && Path::new(s).is_relative() => {
                    let from = folder.join(s);
                    if is_edit || is_helper {
                        let to = dir.join(Path::new(s).file_name().unwrap_or_default());
                        if from != to {
                            std::fs::copy(&from, &to).map_err(io_err(&from))?;
                        }
                        quoted(&to.file_name().unwrap_or_default().to_string_lossy())
                    } else {
                        quoted(
                            &std::path::absolute(&from)
                                .unwrap_or(from)
                                .display()
                                .to_string(),
                        )
                    }
                }
                _ => flow(v),
            };
            st.fields.push((k.clone(), text));
        }
        if is_edit || is_helper {
            let text: Vec<&str> = st.fields.iter().map(|(_, v)| v.as_str()).collect();
            for f in session_files(&text.join(" ")) {
                let (from, to) = (folder.join(&f), dir.join(&f));
                if from != to && from.is_file() {
                    std::fs::copy(&from, &to).map_err(io_err(&from))?;
                }
            }
            if is_helper {
                helpers.push(st);
                continue;
            }
            st.helpers = std::mem::take(&mut helpers);
            edits.push(st);
        } else {
            base.push(st);
        }
    }
    Ok((base, edits))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(what: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("matflow-studio-{what}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn inputs_become_pipelines_by_what_they_are() {
        let reg = matflow_nodes::registry();
        let d = scratch("in");
        let photo = d.join("x \"odd\": name.PNG");
        image::RgbImage::new(32, 32)
            .save_with_format(&photo, image::ImageFormat::Png)
            .unwrap();
        let s = Session::open(&photo, &d.join("s1"), &reg).unwrap();
        let y = s.yaml();
        assert!(y.contains("kind: matnet"), "{y}");
        // A path with quotes or a colon stays one YAML string.
        assert!(y.contains(r#"x \"odd\": name.PNG""#), "{y}");
        for stage in [
            "mesh:",
            "lighting:",
            "recovered:",
            "base:",
            "quick:",
            "preview:",
        ] {
            assert!(y.contains(stage), "{stage} in {y}");
        }
        assert!(matches!(
            Session::open(&d.join("notes.txt"), &d.join("s2"), &reg),
            Err(SessionError::Input(_))
        ));
        let _ = std::fs::remove_dir_all(&d);
    }

    /// Edits are stages; undo and redo move the last; the file, opened
    /// elsewhere, is the same session (its masks copied with it).
    #[test]
    fn edits_undo_redo_and_a_session_reopened_from_its_file() {
        let reg = matflow_nodes::registry();
        let d = scratch("edits");
        // A pipeline of its own scene and a cheaper recovery.
        let input = d.join("in.yaml");
        std::fs::write(
            &input,
            "pipeline: mine\noutputs: [lighting]\nstages:\n  scene:\n    kind: synthetic_scene\n    \
             size: 16\n  lighting:\n    kind: envmap_opt\n    scene: scene\n    mesh: mesh\n    \
             budget_seconds: 1\n  mesh:\n    kind: mesh\n    scene: scene\n    complete: none\n",
        )
        .unwrap();
        let mut s = Session::open(&input, &d.join("a"), &reg).unwrap();
        let y = s.yaml();
        assert!(
            y.contains("budget_seconds: 1\n") && y.contains("complete: none"),
            "{y}"
        );
        let mask = Image::from_fn(16, 16, |x, _| x < 4);
        let none = Image::new(16, 16, false);
        let red = Change {
            albedo: Some([0.9, 0.1, 0.1]),
            ..Default::default()
        };
        assert!(matches!(
            s.edit(&none, &red, &reg),
            Err(SessionError::Request(_))
        ));
        assert!(matches!(
            s.edit(&mask, &Change::default(), &reg),
            Err(SessionError::Request(_))
        ));
        // Out of the edit kind's range: refused with the engine's words.
        let e = s
            .edit(
                &mask,
                &Change {
                    roughness: Some(7.0),
                    ..Default::default()
                },
                &reg,
            )
            .unwrap_err();
        assert!(e.to_string().contains("roughness"), "{e}");
        s.edit(&mask, &red, &reg).unwrap();
        let shiny = Change {
            roughness: Some(0.1),
            metallic: Some(1.0),
            ..Default::default()
        };
        s.edit(&mask, &shiny, &reg).unwrap();
        let y = s.yaml();
        assert!(
            y.contains("edit2:\n    kind: edit\n    materials: edit1\n"),
            "{y}"
        );
        assert!(
            y.contains("materials: edit2\n    photo: scene\n    output: result.exr"),
            "{y}"
        );
        assert!(s.undo().unwrap());
        assert!(s
            .yaml()
            .contains("materials: edit1\n    photo: scene\n    output"));
        assert_eq!(s.history().1, 1);
        assert!(s.redo().unwrap());
        assert!(!s.redo().unwrap());
        assert_eq!(s.yaml(), y);
        // Opened from its own file in another folder: the same stages.
        let t = Session::open(&d.join("a/session.yaml"), &d.join("b"), &reg).unwrap();
        assert_eq!(t.yaml(), y);
        let mask_file = unquoted(t.edits[0].get("mask_png").unwrap());
        assert!(d.join("b").join(mask_file).is_file());
        // New light: a relight of the recovered envmap; the renders are
        // of the whole scene under it, the materials still the last edit's.
        s.light(
            &Light {
                envmap: None,
                rotation: 45.0,
                exposure: -0.5,
            },
            &reg,
        )
        .unwrap();
        let y = s.yaml();
        assert!(y.contains("edit3:\n    kind: relight\n    source: recovered.envmap\n    rotation: 45\n    exposure: -0.5\n"), "{y}");
        assert!(y.contains("  preview:\n    kind: render\n    mesh: mesh\n    materials: edit2\n    envmap: edit3\n    spp: 4\n"), "{y}");
        let no_file = Light {
            envmap: Some("envmap-none.hdr".into()),
            ..Default::default()
        };
        assert!(matches!(
            s.light(&no_file, &reg),
            Err(SessionError::Request(_))
        ));
        assert!(matches!(
            Session::add_envmap(&s.dir, b"GIF89a"),
            Err(SessionError::Request(_))
        ));
        s.undo().unwrap();
        // A new edit after an undo drops what redo would have brought.
        s.undo().unwrap();
        s.edit(&mask, &shiny, &reg).unwrap();
        assert_eq!(s.history().1, 0);
        let _ = std::fs::remove_dir_all(&d);
    }
}
