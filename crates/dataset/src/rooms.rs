//! Generator `rooms`: synthetic interiors with ground truth, for training
//! and validating the prediction stage (MatNet's contract). Sample i is a
//! room drawn from (seed, i): its shape, furniture, materials (matte,
//! glossy, metal), camera and lighting (`matflow_procgen::rooms`),
//! path-traced by matflow's renderer; its members are the files of a
//! reference bundle (the photograph, depth, sky mask, true albedo,
//! roughness, metallic, normals and lighting).

use matflow_engine::spec::SpecError;
use matflow_engine::{ParamSpec, ParamType, Value};

use crate::generator::{Generator, Plan, Rng, Sample, SampleStage};
use crate::spec::DatasetSpec;

pub struct RoomsGenerator;

const PARAMS: &[ParamSpec] = &[
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
        "Synthetic interiors (room shapes, furniture, matte/glossy/metal materials, camera \
         placement, sky or room lighting) path-traced by matflow, with ground-truth albedo, \
         roughness, metallic, normals and depth as a reference bundle's files."
    }
    fn params(&self) -> &'static [ParamSpec] {
        PARAMS
    }
    fn plan(&self, spec: &DatasetSpec) -> Result<Box<dyn Plan>, SpecError> {
        let int = |k: &str| match spec.param(k) {
            Value::Int(i) => *i,
            _ => 0,
        };
        Ok(Box::new(RoomsPlan {
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
        let mut meta = serde_json::Map::new();
        meta.insert("room_seed".into(), room_seed.into());
        meta.insert("size".into(), self.size.into());
        meta.insert("spp".into(), self.spp.into());
        Sample {
            stages: vec![SampleStage {
                role: "room",
                kind: "room_sample",
                params: vec![
                    ("seed".into(), Value::Int(room_seed as i64)),
                    ("size".into(), Value::Int(self.size)),
                    ("spp".into(), Value::Int(self.spp)),
                    ("envmap_width".into(), Value::Int(self.envmap_width)),
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
