//! Generator `refraction`: the paper's refraction-length dataset
//! (supplement §10) — objects × viewpoints × environment maps.
//!
//! Sample i draws, from (seed, i) alone: an object (the built-in vessels
//! and solids, and any OBJ/PLY files or folders given, each labelled
//! hollow or solid), one of `viewpoints` fixed viewpoints spread evenly
//! (a Fibonacci lattice) over the band of elevations, an environment map
//! (the files given and `procedural_envmaps` procedural skies and rooms)
//! turned at random, the object's material, and a ground plane (plain or
//! checkered) when the camera looks down on the object. Its two stages:
//! `refraction_labels` (mask, depth, normals, eq. 24 length, d1, d2) and
//! `refraction_render` (the photograph and its background).

use std::path::{Path, PathBuf};

use matflow_engine::spec::SpecError;
use matflow_engine::{ParamSpec, ParamType, Value};
use matflow_procgen::envgen::EnvKind;
use matflow_procgen::shapes::REFRACTION_OBJECT_NAMES;

use crate::generator::{json_of, Generator, Plan, Rng, Sample, SampleStage};
use crate::spec::DatasetSpec;

pub struct RefractionGenerator;

const OBJECT_FIELDS: &[ParamSpec] = &[
    ParamSpec {
        name: "builtin",
        ty: ParamType::Choice(REFRACTION_OBJECT_NAMES),
        default: Some("~"),
        unit: "",
        doc: "a built-in object",
    },
    ParamSpec {
        name: "file",
        ty: ParamType::InPath,
        default: Some("~"),
        unit: "",
        doc: "an OBJ or PLY mesh, or a folder of them",
    },
    ParamSpec {
        name: "hollow",
        ty: ParamType::Bool,
        default: Some("false"),
        unit: "",
        doc: "whether the file's objects are hollow (eq. 24)",
    },
];

const ENVMAP_FIELDS: &[ParamSpec] = &[ParamSpec {
    name: "file",
    ty: ParamType::InPath,
    default: None,
    unit: "",
    doc: "an HDR or EXR environment map, or a folder of them",
}];

const PARAMS: &[ParamSpec] = &[
    ParamSpec {
        name: "size",
        ty: ParamType::Int { min: 8, max: 4096 },
        default: Some("128"),
        unit: "px",
        doc: "image side",
    },
    ParamSpec {
        name: "spp",
        ty: ParamType::Int { min: 1, max: 65536 },
        default: Some("32"),
        unit: "samples/px",
        doc: "samples per pixel of the renders",
    },
    ParamSpec {
        name: "objects",
        ty: ParamType::Records {
            fields: OBJECT_FIELDS,
            max: 10_000,
        },
        default: Some("~"),
        unit: "",
        doc: "the objects drawn from (default: every built-in object)",
    },
    ParamSpec {
        name: "envmaps",
        ty: ParamType::Records {
            fields: ENVMAP_FIELDS,
            max: 10_000,
        },
        default: Some("~"),
        unit: "",
        doc: "environment map files drawn from, beside the procedural ones",
    },
    ParamSpec {
        name: "procedural_envmaps",
        ty: ParamType::Int {
            min: 0,
            max: 1_000_000,
        },
        default: Some("32"),
        unit: "",
        doc: "procedural environment maps drawn from (half skies, half rooms)",
    },
    ParamSpec {
        name: "envmap_width",
        ty: ParamType::Int { min: 8, max: 8192 },
        default: Some("256"),
        unit: "px",
        doc: "the procedural maps' width",
    },
    ParamSpec {
        name: "viewpoints",
        ty: ParamType::Int {
            min: 1,
            max: 1_000_000,
        },
        default: Some("200"),
        unit: "",
        doc: "fixed viewpoints around the object (the paper's 200)",
    },
    ParamSpec {
        name: "elevation",
        ty: ParamType::Floats {
            len: 2,
            min: -89.0,
            max: 89.0,
        },
        default: Some("[-10, 60]"),
        unit: "degrees",
        doc: "the band of viewpoint elevations",
    },
    ParamSpec {
        name: "fill",
        ty: ParamType::Floats {
            len: 2,
            min: 0.05,
            max: 1.0,
        },
        default: Some("[0.45, 0.8]"),
        unit: "",
        doc: "the object's bounding sphere spans this share of the field of view",
    },
    ParamSpec {
        name: "ground",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0.75"),
        unit: "",
        doc: "chance of a ground plane when the camera looks down (elevation above 3°)",
    },
    ParamSpec {
        name: "checker",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0.5"),
        unit: "",
        doc: "chance that a ground plane is checkered",
    },
    ParamSpec {
        name: "metallic",
        ty: ParamType::Float { min: 0.0, max: 1.0 },
        default: Some("0.2"),
        unit: "",
        doc: "share of metal objects",
    },
    ParamSpec {
        name: "object_size",
        ty: ParamType::Float {
            min: 1e-3,
            max: 1e4,
        },
        default: Some("1"),
        unit: "scene units",
        doc: "objects' bounding-sphere diameter; the refraction length's normaliser",
    },
];

/// Half the camera's horizontal field of view (35°).
const HALF_FOV_DEG: f64 = 17.5;

/// Where an object comes from.
#[derive(Clone, Debug, PartialEq)]
enum ObjectSource {
    Builtin(&'static str),
    File { path: PathBuf, hollow: bool },
}

#[derive(Clone, Debug, PartialEq)]
enum EnvSource {
    File(PathBuf),
    Procedural(EnvKind, u64),
}

struct RefractionPlan {
    seed: u64,
    size: i64,
    spp: i64,
    envmap_width: i64,
    object_size: f64,
    viewpoints: u64,
    elevation: (f64, f64),
    fill: (f64, f64),
    ground: f64,
    checker: f64,
    metallic: f64,
    objects: Vec<ObjectSource>,
    envmaps: Vec<EnvSource>,
}

fn floats(v: &Value) -> (f64, f64) {
    match v {
        Value::List(xs) if xs.len() == 2 => {
            (xs[0].as_f64().unwrap_or(0.0), xs[1].as_f64().unwrap_or(0.0))
        }
        _ => (0.0, 0.0),
    }
}

fn records(v: &Value) -> Vec<&Vec<(String, matflow_engine::Loc, Value, matflow_engine::Loc)>> {
    match v {
        Value::List(items) => items
            .iter()
            .filter_map(|i| match i {
                Value::Map(m) => Some(m),
                _ => None,
            })
            .collect(),
        _ => Vec::new(),
    }
}

fn field<'a>(
    m: &'a [(String, matflow_engine::Loc, Value, matflow_engine::Loc)],
    k: &str,
) -> &'a Value {
    m.iter().find(|e| e.0 == k).map_or(&Value::Null, |e| &e.2)
}

/// The files in `dir` whose extension is one of `exts` (lower case),
/// sorted by name.
fn files_in(dir: &Path, exts: &[&str]) -> std::io::Result<Vec<PathBuf>> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .is_some_and(|e| exts.contains(&e.to_string_lossy().to_lowercase().as_str()))
        })
        .collect();
    out.sort();
    Ok(out)
}

/// (azimuth, elevation) in degrees of viewpoint `j` of `n`: a Fibonacci
/// lattice, uniform in area over the band of elevations.
pub fn viewpoint(j: u64, n: u64, band: (f64, f64)) -> (f64, f64) {
    let (s0, s1) = (band.0.to_radians().sin(), band.1.to_radians().sin());
    let t = (j as f64 + 0.5) / n.max(1) as f64;
    let el = (s0 + (s1 - s0) * t).clamp(-1.0, 1.0).asin().to_degrees();
    let golden = 180.0 * (3.0 - 5f64.sqrt());
    let az = (j as f64 * golden).rem_euclid(360.0);
    (az, el)
}

fn hsv(h: f64, s: f64, v: f64) -> [f64; 3] {
    let h6 = h.rem_euclid(1.0) * 6.0;
    let c = v * s;
    let x = c * (1.0 - ((h6 % 2.0) - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    [r + v - c, g + v - c, b + v - c]
}

/// A float rounded to 6 decimals: parameters read well in the manifest
/// and sample keys do not hang on the last bits of a draw.
fn f(x: f64) -> Value {
    Value::Float((x * 1e6).round() / 1e6)
}

fn rgb(c: [f64; 3]) -> Value {
    Value::List(c.iter().map(|&x| f(x)).collect())
}

impl Generator for RefractionGenerator {
    fn name(&self) -> &'static str {
        "refraction"
    }
    fn doc(&self) -> &'static str {
        "The refraction-length dataset (the paper's supplement §10): objects × viewpoints × \
         environment maps; per sample the photograph, its background without the object, and the \
         object's mask, depth, normals, eq. 24 length (normalised) and d1, d2."
    }
    fn params(&self) -> &'static [ParamSpec] {
        PARAMS
    }
    fn check(&self, spec: &DatasetSpec) -> Result<(), String> {
        let (e0, e1) = floats(spec.param("elevation"));
        if e0 > e1 {
            return Err(format!(
                "`elevation` [{e0}, {e1}]: the first must not exceed the second"
            ));
        }
        let (f0, f1) = floats(spec.param("fill"));
        if f0 > f1 {
            return Err(format!(
                "`fill` [{f0}, {f1}]: the first must not exceed the second"
            ));
        }
        for (k, o) in records(spec.param("objects")).iter().enumerate() {
            match (field(o, "builtin"), field(o, "file")) {
                (Value::Null, Value::Null) => {
                    return Err(format!("`objects`[{k}]: give `builtin` or `file`"))
                }
                (Value::Str(_), Value::Str(_)) => {
                    return Err(format!(
                        "`objects`[{k}]: give `builtin` or `file`, not both"
                    ))
                }
                _ => {}
            }
        }
        if matches!(spec.param("objects"), Value::List(l) if l.is_empty()) {
            return Err("`objects` is empty".into());
        }
        let files = records(spec.param("envmaps")).len();
        if files == 0 && spec.param("procedural_envmaps") == &Value::Int(0) {
            return Err("no environment maps: give `envmaps` or `procedural_envmaps` > 0".into());
        }
        Ok(())
    }
    fn plan(&self, spec: &DatasetSpec) -> Result<Box<dyn Plan>, SpecError> {
        let err = |message: String| SpecError {
            file: spec.file.clone(),
            loc: Some(spec.loc),
            message,
        };
        let int = |k: &str| match spec.param(k) {
            Value::Int(i) => *i,
            _ => 0,
        };
        let float = |k: &str| spec.param(k).as_f64().unwrap_or(0.0);
        let mut objects = Vec::new();
        match spec.param("objects") {
            Value::Null => objects.extend(
                REFRACTION_OBJECT_NAMES
                    .iter()
                    .map(|n| ObjectSource::Builtin(n)),
            ),
            v => {
                for o in records(v) {
                    if let Value::Str(n) = field(o, "builtin") {
                        let name = REFRACTION_OBJECT_NAMES
                            .iter()
                            .find(|b| **b == n)
                            .expect("checked against the choice");
                        objects.push(ObjectSource::Builtin(name));
                    }
                    if let Value::Str(p) = field(o, "file") {
                        let hollow = field(o, "hollow") == &Value::Bool(true);
                        let path = PathBuf::from(p);
                        let files = if path.is_dir() {
                            let fs = files_in(&path, &["obj", "ply"])
                                .map_err(|e| err(format!("{}: {e}", path.display())))?;
                            if fs.is_empty() {
                                return Err(err(format!(
                                    "{}: the folder holds no .obj or .ply files",
                                    path.display()
                                )));
                            }
                            fs
                        } else {
                            vec![path]
                        };
                        for p in files {
                            // Read once here, so a bad mesh is named now.
                            let parts = matflow_scene::meshfile::read_mesh(&p)
                                .map_err(|e| err(e.to_string()))?;
                            if parts.iter().all(|q| q.indices.is_empty()) {
                                return Err(err(format!(
                                    "{}: the mesh has no triangles",
                                    p.display()
                                )));
                            }
                            objects.push(ObjectSource::File { path: p, hollow });
                        }
                    }
                }
            }
        }
        let mut envmaps = Vec::new();
        for e in records(spec.param("envmaps")) {
            if let Value::Str(p) = field(e, "file") {
                let path = PathBuf::from(p);
                let files = if path.is_dir() {
                    let fs = files_in(&path, &["hdr", "exr"])
                        .map_err(|e| err(format!("{}: {e}", path.display())))?;
                    if fs.is_empty() {
                        return Err(err(format!(
                            "{}: the folder holds no .hdr or .exr files",
                            path.display()
                        )));
                    }
                    fs
                } else {
                    vec![path]
                };
                for p in files {
                    matflow_scene::io::read_envmap(&p).map_err(|e| err(e.to_string()))?;
                    envmaps.push(EnvSource::File(p));
                }
            }
        }
        for j in 0..int("procedural_envmaps") as u64 {
            let kind = if j % 2 == 0 {
                EnvKind::Sky
            } else {
                EnvKind::Room
            };
            let s = Rng::for_sample(spec.seed, j, 0xe7).next_u64() >> 1;
            envmaps.push(EnvSource::Procedural(kind, s));
        }
        Ok(Box::new(RefractionPlan {
            seed: spec.seed,
            size: int("size"),
            spp: int("spp"),
            envmap_width: int("envmap_width"),
            object_size: float("object_size"),
            viewpoints: int("viewpoints") as u64,
            elevation: floats(spec.param("elevation")),
            fill: floats(spec.param("fill")),
            ground: float("ground"),
            checker: float("checker"),
            metallic: float("metallic"),
            objects,
            envmaps,
        }))
    }
}

fn object_name(o: &ObjectSource) -> String {
    match o {
        ObjectSource::Builtin(n) => n.to_string(),
        ObjectSource::File { path, .. } => path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
    }
}

fn hollow_of(o: &ObjectSource) -> bool {
    match o {
        ObjectSource::Builtin(n) => matflow_procgen::shapes::refraction_object_is_hollow(n),
        ObjectSource::File { hollow, .. } => *hollow,
    }
}

fn env_name(e: &EnvSource) -> String {
    match e {
        EnvSource::File(p) => p.display().to_string(),
        EnvSource::Procedural(k, s) => format!("{}:{s}", k.name()),
    }
}

/// The members of a sample: `refraction_labels`' outputs, then
/// `refraction_render`'s.
pub const MEMBERS: &[&str] = &[
    "mask.png",
    "depth.npy",
    "normal.npy",
    "length.npy",
    "d1.npy",
    "d2.npy",
    "image.png",
    "background.png",
    "render.json",
];

impl Plan for RefractionPlan {
    fn sample(&self, i: u64) -> Sample {
        let mut r = Rng::for_sample(self.seed, i, 0x5e7);
        // Every draw is made in this order whatever the outcomes, so one
        // choice never shifts another.
        let obj = &self.objects[r.below(self.objects.len() as u64) as usize];
        let vp = r.below(self.viewpoints);
        let env = &self.envmaps[r.below(self.envmaps.len() as u64) as usize];
        let env_rot = r.range(0.0, 360.0);
        let exposure = r.range(-0.5, 0.5);
        let fill = r.range(self.fill.0, self.fill.1);
        let ground_draw = r.f64();
        let checker_draw = r.f64();
        let contrast = r.range(0.3, 0.9);
        let tile = r.range(0.1, 0.4) * self.object_size;
        let ground_albedo = hsv(r.f64(), r.range(0.0, 0.6), r.range(0.2, 0.9));
        let ground_roughness = r.range(0.3, 1.0);
        let albedo = hsv(r.f64(), r.range(0.0, 0.9), r.range(0.2, 0.95));
        let roughness = r.range(0.05, 0.95);
        let metal = r.f64() < self.metallic;

        let (az, el) = viewpoint(vp, self.viewpoints, self.elevation);
        let radius = 0.5 * self.object_size;
        let half = (fill * HALF_FOV_DEG).to_radians();
        let distance = (radius / half.sin().max(1e-6)).max(radius * 1.1);
        let ground = el > 3.0 && ground_draw < self.ground;
        let contrast = if ground && checker_draw < self.checker {
            contrast
        } else {
            0.0
        };
        let mut common: Vec<(String, Value)> = Vec::new();
        match obj {
            ObjectSource::Builtin(n) => common.push(("object".into(), Value::Str(n.to_string()))),
            ObjectSource::File { path, hollow } => {
                common.push((
                    "object_file".into(),
                    Value::Str(path.to_string_lossy().into_owned()),
                ));
                common.push(("hollow".into(), Value::Bool(*hollow)));
            }
        }
        common.extend([
            ("object_size".into(), f(self.object_size)),
            ("azimuth".into(), f(az)),
            ("elevation".into(), f(el)),
            ("distance".into(), f(distance)),
            ("size".into(), Value::Int(self.size)),
            ("ground".into(), Value::Bool(ground)),
        ]);
        let mut render = common.clone();
        match env {
            EnvSource::File(p) => render.push((
                "envmap".into(),
                Value::Str(p.to_string_lossy().into_owned()),
            )),
            EnvSource::Procedural(k, s) => {
                render.push(("envmap_kind".into(), Value::Str(k.name().into())));
                render.push(("envmap_seed".into(), Value::Int(*s as i64)));
                render.push(("envmap_width".into(), Value::Int(self.envmap_width)));
            }
        }
        render.extend([
            ("envmap_rotation".into(), f(env_rot)),
            ("exposure".into(), f(exposure)),
            ("albedo".into(), rgb(albedo)),
            ("roughness".into(), f(roughness)),
            ("metallic".into(), f(if metal { 1.0 } else { 0.0 })),
            ("ground_albedo".into(), rgb(ground_albedo)),
            ("ground_roughness".into(), f(ground_roughness)),
            ("ground_checker".into(), f(contrast)),
            ("ground_tile".into(), f(tile)),
            ("spp".into(), Value::Int(self.spp)),
        ]);
        let mut meta = serde_json::Map::new();
        meta.insert("object".into(), object_name(obj).into());
        meta.insert("hollow".into(), hollow_of(obj).into());
        meta.insert("viewpoint".into(), vp.into());
        meta.insert("envmap".into(), env_name(env).into());
        for (k, v) in &render {
            if !matches!(
                k.as_str(),
                "object" | "object_file" | "hollow" | "envmap" | "envmap_kind" | "envmap_seed"
            ) {
                meta.insert(k.clone(), json_of(v));
            }
        }
        Sample {
            stages: vec![
                SampleStage {
                    role: "labels",
                    kind: "refraction_labels",
                    params: common,
                },
                SampleStage {
                    role: "render",
                    kind: "refraction_render",
                    params: render,
                },
            ],
            meta,
        }
    }

    fn header(&self) -> serde_json::Value {
        serde_json::json!({
            "normaliser": {
                "length.npy": self.object_size,
                "meaning": "length.npy holds the eq. 24 length divided by the normaliser \
                            (the objects' bounding-sphere diameter), clamped to [0, 1]; \
                            d1.npy, d2.npy and depth.npy are in scene units",
            },
            "objects": self.objects.iter().map(|o| serde_json::json!({
                "name": object_name(o),
                "hollow": hollow_of(o),
                "file": match o { ObjectSource::File { path, .. } => Some(path.display().to_string()), _ => None },
            })).collect::<Vec<_>>(),
            "envmaps": self.envmaps.iter().map(env_name).collect::<Vec<_>>(),
            "viewpoints": (0..self.viewpoints)
                .map(|j| viewpoint(j, self.viewpoints, self.elevation))
                .map(|(a, e)| [(a * 1e4).round() / 1e4, (e * 1e4).round() / 1e4])
                .collect::<Vec<_>>(),
        })
    }

    fn members(&self) -> Vec<String> {
        MEMBERS.iter().map(|m| m.to_string()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viewpoints_cover_the_band_evenly() {
        let n = 200;
        let band = (-10.0, 60.0);
        let v: Vec<_> = (0..n).map(|j| viewpoint(j, n, band)).collect();
        assert!(v
            .iter()
            .all(|&(a, e)| (0.0..360.0).contains(&a) && (-10.0..=60.0).contains(&e)));
        // Every quarter of the azimuths and both ends of the band are used.
        for q in 0..4 {
            let lo = 90.0 * q as f64;
            assert!(
                v.iter()
                    .filter(|(a, _)| (lo..lo + 90.0).contains(a))
                    .count()
                    > 35
            );
        }
        assert!(v.iter().any(|&(_, e)| e < -8.0) && v.iter().any(|&(_, e)| e > 55.0));
        // Uniform in area: as many above the band's middle sine as below.
        let mid = ((-10f64).to_radians().sin() + 60f64.to_radians().sin()) / 2.0;
        let above = v.iter().filter(|(_, e)| e.to_radians().sin() > mid).count();
        assert_eq!(above, 100);
    }
}
