//! Generator `rooms`: synthetic scenes with ground truth, for training
//! and validating the prediction stage (MatNet's contract). Sample i is a
//! scene drawn from (seed, i): of the kind asked for (`scenes`) (open or closed
//! rooms, stages, outdoor scenes; `all` takes the four in turn), its
//! shape, furniture, materials (matte, glossy, metal), camera and
//! lighting (`matflow_procgen::rooms`, `matflow_procgen::kinds`),
//! path-traced by matflow's renderer; its members are the files of a
//! reference bundle (the photograph, depth, sky mask, true albedo,
//! roughness, metallic, normals and lighting).

use matflow_engine::spec::SpecError;
use matflow_engine::{ParamSpec, ParamType, Value};

use matflow_procgen::rooms::SceneKind;

use crate::generator::{Generator, Plan, Rng, Sample, SampleStage};
use crate::spec::DatasetSpec;

pub struct RoomsGenerator;

/// The kinds a dataset may ask for: one of the scene kinds, or all four
/// in turn (sample i is of kind i mod 4, in [`SceneKind::ALL`]'s order).
const KINDS: &[&str] = &["open", "closed", "stage", "outdoor", "all"];

/// The camera placements a dataset may ask for (`matflow_procgen::framing`),
/// or both in turn.
const FRAMINGS: &[&str] = &["drawn", "near", "mixed"];

const PARAMS: &[ParamSpec] = &[
    ParamSpec {
        name: "scenes",
        ty: ParamType::Choice(KINDS),
        default: Some("open"),
        unit: "",
        doc: "the kind of scene: open (rooms open to the sky), closed, stage, outdoor, or all \
              four in turn",
    },
    ParamSpec {
        name: "framing",
        ty: ParamType::Choice(FRAMINGS),
        default: Some("drawn"),
        unit: "",
        doc: "where the camera stands: drawn (where each kind's layout puts it), near (walked up \
              to one of the scene's objects), or mixed (the four kinds drawn, then the four \
              near, in turn)",
    },
    ParamSpec {
        name: "size",
        ty: ParamType::Int { min: 8, max: 4096 },
        default: Some("256"),
        unit: "px",
        doc: "image side",
    },
    ParamSpec {
        name: "spp",
        ty: ParamType::Int { min: 1, max: 65536 },
        default: Some("64"),
        unit: "samples/px",
        doc: "samples per pixel of the photographs",
    },
    ParamSpec {
        name: "denoise",
        ty: ParamType::Bool,
        default: Some("true"),
        unit: "",
        doc: "denoise the photographs (two halves of their samples, filtered); false keeps the \
              raw path-traced render",
    },
    ParamSpec {
        name: "envmap_width",
        ty: ParamType::Int { min: 8, max: 8192 },
        default: Some("128"),
        unit: "px",
        doc: "the lighting's width",
    },
];

/// The members of a sample (`room_sample`'s outputs).
pub const MEMBERS: &[&str] = &[
    "gt_image.exr",
    "gt_image.png",
    "depth.exr",
    "mesh_mask.png",
    "albedo.exr",
    "roughness.exr",
    "metallic.exr",
    "normal.exr",
    "envmap.hdr",
];

struct RoomsPlan {
    kind: String,
    framing: String,
    denoise: bool,
    seed: u64,
    size: i64,
    spp: i64,
    envmap_width: i64,
}

impl Generator for RoomsGenerator {
    fn name(&self) -> &'static str {
        "rooms"
    }
    fn doc(&self) -> &'static str {
        "Synthetic scenes (open or closed rooms, stages, outdoor scenes; furniture, \
         matte/glossy/metal materials, camera placement, skies, room lighting, windows and \
         lamps) path-traced by matflow, with ground-truth albedo, roughness, metallic, normals \
         and depth as a reference bundle's files."
    }
    fn params(&self) -> &'static [ParamSpec] {
        PARAMS
    }
    fn plan(&self, spec: &DatasetSpec) -> Result<Box<dyn Plan>, SpecError> {
        let int = |k: &str| match spec.param(k) {
            Value::Int(i) => *i,
            _ => 0,
        };
        let kind = match spec.param("scenes") {
            Value::Str(s) => s.clone(),
            _ => "open".to_string(),
        };
        let framing = match spec.param("framing") {
            Value::Str(s) => s.clone(),
            _ => "drawn".to_string(),
        };
        Ok(Box::new(RoomsPlan {
            kind,
            framing,
            denoise: !matches!(spec.param("denoise"), Value::Bool(false)),
            seed: spec.seed,
            size: int("size"),
            spp: int("spp"),
            envmap_width: int("envmap_width"),
        }))
    }
}

impl Plan for RoomsPlan {
    fn sample(&self, i: u64) -> Sample {
        let room_seed = Rng::for_sample(self.seed, i, 0x200).next_u64() >> 1;
        let kind = if self.kind == "all" {
            SceneKind::ALL[(i % 4) as usize].name()
        } else {
            self.kind.as_str()
        };
        let framing = match self.framing.as_str() {
            "mixed" if (i / 4) % 2 == 1 => "near",
            "mixed" => "drawn",
            f => f,
        };
        let mut meta = serde_json::Map::new();
        meta.insert("kind".into(), kind.into());
        meta.insert("framing".into(), framing.into());
        meta.insert("room_seed".into(), room_seed.into());
        meta.insert("size".into(), self.size.into());
        meta.insert("spp".into(), self.spp.into());
        Sample {
            stages: vec![SampleStage {
                role: "room",
                kind: "room_sample",
                params: vec![
                    ("scene".into(), Value::Str(kind.to_string())),
                    ("seed".into(), Value::Int(room_seed as i64)),
                    ("framing".into(), Value::Str(framing.to_string())),
                    ("size".into(), Value::Int(self.size)),
                    ("spp".into(), Value::Int(self.spp)),
                    ("envmap_width".into(), Value::Int(self.envmap_width)),
                    ("denoise".into(), Value::Bool(self.denoise)),
                ],
            }],
            meta,
        }
    }
    fn header(&self) -> serde_json::Value {
        serde_json::json!({
            "layout": "each sample's members are a reference bundle's files: gt_image.exr \
                       (linear photograph) and gt_image.png, depth.exr (camera-space z), \
                       mesh_mask.png (no geometry), and the ground truth albedo.exr, \
                       roughness.exr, metallic.exr, normal.exr (camera space, +z to the \
                       camera) and envmap.hdr (lighting in the camera's frame)",
        })
    }
    fn members(&self) -> Vec<String> {
        MEMBERS.iter().map(|m| m.to_string()).collect()
    }
    fn layout(&self) -> Vec<(&'static str, &'static str)> {
        vec![
            ("albedo.exr", "ground_truth/albedo.exr"),
            ("roughness.exr", "ground_truth/roughness.exr"),
            ("metallic.exr", "ground_truth/metallic.exr"),
            ("normal.exr", "ground_truth/normal.exr"),
            ("envmap.hdr", "ground_truth/envmap.hdr"),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(kind: &str) -> RoomsPlan {
        RoomsPlan {
            kind: kind.to_string(),
            framing: "mixed".to_string(),
            denoise: true,
            seed: 3,
            size: 32,
            spp: 4,
            envmap_width: 16,
        }
    }

    fn scene_of(s: &Sample) -> String {
        s.stages[0]
            .params
            .iter()
            .find(|(k, _)| k == "scene")
            .map(|(_, v)| match v {
                Value::Str(s) => s.clone(),
                _ => String::new(),
            })
            .unwrap_or_default()
    }

    #[test]
    fn all_kinds_come_in_turn_and_one_kind_alone() {
        let all = plan("all");
        let kinds: Vec<String> = (0..8).map(|i| scene_of(&all.sample(i))).collect();
        assert_eq!(
            kinds,
            ["closed", "open", "stage", "outdoor", "closed", "open", "stage", "outdoor"]
        );
        // Each sample records its kind, and its seed does not depend on
        // the kinds asked for.
        let s = all.sample(2);
        assert_eq!(s.meta["kind"], "stage");
        let open = plan("open");
        assert_eq!(
            open.sample(2).meta["room_seed"],
            s.meta["room_seed"],
            "seeds follow the sample, not the kind"
        );
        assert!((0..4).all(|i| scene_of(&open.sample(i)) == "open"));
        // Mixed framing: each kind drawn, then each near, in turn; the
        // node is told which.
        let framings: Vec<String> = (0..12)
            .map(|i| {
                all.sample(i).meta["framing"]
                    .as_str()
                    .unwrap_or("")
                    .to_string()
            })
            .collect();
        assert_eq!(&framings[..4], ["drawn"; 4]);
        assert_eq!(&framings[4..8], ["near"; 4]);
        assert_eq!(&framings[8..], ["drawn"; 4]);
        assert!(all.sample(5).stages[0]
            .params
            .contains(&("framing".into(), Value::Str("near".into()))));
    }
}
