//! `material_opt`: albedo, roughness and metallic recovered together with
//! the envmap.

use std::collections::BTreeMap;
use std::sync::OnceLock;

use std::path::PathBuf;

use matflow_engine::node::{Bytes, Params};
use matflow_engine::{Node, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, RunContext};
use matflow_inverse::invert::{materials_to_maps, InvertOptions};
use matflow_inverse::routes::Side;
use matflow_scene::io;

use crate::artifact::Artifact;
use crate::data::{encode_image, encode_materials, envmap_from, materials_from, MESH, SCENE};
use crate::err;
use crate::recovery::{
    base_options, mat_route, material_options, prepare, run_invert, summary, with_route_params,
};
use crate::recovery::{
    ALBEDO_LEVEL, ALBEDO_LEVEL_BAND, ALBEDO_STRUCTURE, BUDGET, DELTA, ENV_ROUTE, LOOPS, MAT_ROUTE,
    REPORT, TRUST,
};

pub struct MaterialOptNode;

const PARAMS: &[ParamSpec] = &[
    SCENE,
    MESH,
    ParamSpec {
        name: "envmap",
        ty: ParamType::Ref(&["envmap"]),
        default: Some("~"),
        unit: "",
        doc: "starting envmap (e.g. an envmap_opt stage; for routes that take one)",
    },
    BUDGET,
    ENV_ROUTE,
    MAT_ROUTE,
    TRUST,
    DELTA,
    LOOPS,
    ALBEDO_LEVEL,
    ALBEDO_LEVEL_BAND,
    ALBEDO_STRUCTURE,
    ParamSpec {
        name: "output",
        ty: ParamType::OutPath,
        default: Some("~"),
        unit: "",
        doc: "a folder to write what was recovered to: albedo.exr (and albedo.png, γ-encoded), \
              roughness.exr, metallic.exr (linear) and envmap.hdr",
    },
];

/// The files `output` holds.
const FILES: [&str; 5] = [
    "albedo.exr",
    "albedo.png",
    "roughness.exr",
    "metallic.exr",
    "envmap.hdr",
];

const OUTPUTS: &[OutputSpec] = &[
    OutputSpec {
        name: "materials",
        ty: "materials",
        doc: "recovered albedo, roughness, metallic",
    },
    OutputSpec {
        name: "envmap",
        ty: "envmap",
        doc: "recovered lighting",
    },
    OutputSpec {
        name: "rendered",
        ty: "image",
        doc: "independent re-render of the result (denoised)",
    },
    REPORT,
];

impl Node for MaterialOptNode {
    fn info(&self) -> &'static NodeInfo {
        static INFO: OnceLock<NodeInfo> = OnceLock::new();
        static ALL_PARAMS: OnceLock<Vec<ParamSpec>> = OnceLock::new();
        INFO.get_or_init(|| NodeInfo {
            kind: "material_opt",
            version: 8,
            doc: "Recovers albedo, roughness and metallic together with the envmap: the \
                  reference's alternation of envmap and material stages (paper §3.2), on \
                  frozen paths. The albedo's mean per channel stays near the prediction's \
                  (albedo_level); the light takes the rest.",
            params: with_route_params(&ALL_PARAMS, PARAMS, &[Side::Env, Side::Mat]),
            outputs: OUTPUTS,
        })
    }
    fn estimate_seconds(&self, p: &Params, _film: Option<(usize, usize)>) -> f64 {
        p.f64("budget_seconds")
    }
    /// A bad route option fails validation, before anything runs.
    fn check(&self, p: &Params) -> Result<(), String> {
        crate::recovery::check_routes(p)
    }
    fn output_files(&self, p: &Params) -> Vec<PathBuf> {
        p.path("output")
            .map(|d| FILES.iter().map(|f| d.join(f)).collect())
            .unwrap_or_default()
    }
    fn materialize(
        &self,
        params: &Params,
        outputs: &BTreeMap<String, Bytes>,
    ) -> Result<Vec<PathBuf>, NodeError> {
        let Some(dir) = params.path("output") else {
            return Ok(vec![]);
        };
        let get = |name: &str| {
            outputs
                .get(name)
                .ok_or_else(|| err(format!("the stage made no {name}")))
        };
        let maps = materials_from(&get("materials")?[..])?;
        let env = Artifact::decode(&get("envmap")?[..], "envmap")?.rgb("envmap")?;
        std::fs::create_dir_all(&dir).map_err(|e| err(format!("{}: {e}", dir.display())))?;
        let [albedo_exr, albedo_png, rough, metal, hdr] = FILES.map(|f| dir.join(f));
        let files: [(&PathBuf, Vec<u8>); 5] = [
            (
                &albedo_exr,
                io::encode_exr_rgb(&albedo_exr, &maps.albedo).map_err(err)?,
            ),
            (
                &albedo_png,
                io::encode_png_gamma(&albedo_png, &maps.albedo).map_err(err)?,
            ),
            (
                &rough,
                io::encode_exr_gray(&rough, &maps.roughness).map_err(err)?,
            ),
            (
                &metal,
                io::encode_exr_gray(&metal, &maps.metallic).map_err(err)?,
            ),
            (&hdr, io::encode_hdr(&hdr, &env).map_err(err)?),
        ];
        for (path, bytes) in &files {
            io::write_if_changed(path, bytes).map_err(err)?;
        }
        Ok(files.into_iter().map(|(p, _)| p.clone()).collect())
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let pr = prepare(ctx, None)?;
        let p = ctx.params;
        let init_env = match ctx.opt_input("envmap") {
            Some(b) => Some(envmap_from(b)?),
            None => None,
        };
        let opts = material_options(
            p,
            InvertOptions {
                mat_route: mat_route(p)?,
                init_env,
                ..base_options(p, ctx.seed)?
            },
        );
        let (w, h) = (pr.target.width, pr.target.height);
        let res = run_invert(ctx, pr.scene, &pr.target, &pr.start, &opts)?;
        let maps = materials_to_maps(w, h, &res.materials);
        Ok([
            ("materials".to_string(), encode_materials(&maps)),
            (
                "envmap".to_string(),
                encode_image("envmap", "envmap", &res.envmap),
            ),
            (
                "rendered".to_string(),
                encode_image("image", "image", &res.rendered),
            ),
            (
                "report".to_string(),
                summary(&res.report, &res.rendered, &pr.target),
            ),
        ]
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::artifact::Artifact;
    use crate::data::{encode_mesh, SceneData};
    use crate::testutil::{params_of, small_room};
    use matflow_engine::Value;
    use matflow_render::{render, EnvMap, RenderOptions, RenderScene};
    use std::sync::Arc;

    /// The stage's inputs: the procedural room at 24², photographed at half
    /// its brightness (the fit must trade light for albedo), and its mesh.
    fn inputs() -> [(String, Arc<Vec<u8>>); 2] {
        let n = 24;
        let (s, cam, tri) = small_room(n);
        let env = EnvMap::new(&s.envmap).unwrap();
        let scene = RenderScene::new(cam, tri.clone(), &s.maps, env).unwrap();
        let opts = RenderOptions {
            spp: 4,
            ..Default::default()
        };
        let mut target = render(&scene, &opts, &|_, _| {}).image;
        target.data.iter_mut().for_each(|v| *v *= 0.5);
        let data = SceneData {
            depth: s.depth.clone(),
            target: Some(target),
            pred: s.maps.clone(),
        }
        .encode();
        [
            ("scene".to_string(), Arc::new(data)),
            ("mesh".to_string(), Arc::new(encode_mesh(n, n, &tri))),
        ]
    }

    /// The stage's outputs on `inputs` with `given` parameters (a 30 s
    /// budget: what the tests were sized for at 24²).
    fn run_with(
        inputs: &[(String, Arc<Vec<u8>>); 2],
        given: &[(&str, Value)],
    ) -> BTreeMap<String, Vec<u8>> {
        let mut all = vec![("budget_seconds", Value::Float(30.0))];
        all.extend(given.iter().cloned());
        let p = params_of(MaterialOptNode.info(), &all);
        crate::testutil::run_node(&MaterialOptNode, &p, inputs.iter().cloned().collect(), 1)
            .unwrap()
    }

    /// The report of the stage on `inputs` with `albedo_level` set, or at
    /// its default.
    fn report_with(inputs: &[(String, Arc<Vec<u8>>); 2], level: Option<&str>) -> serde_json::Value {
        let given: Vec<_> = level
            .map(|l| ("albedo_level", Value::Str(l.into())))
            .into_iter()
            .collect();
        let out = run_with(inputs, &given);
        let a = Artifact::decode(&out["report"], "report").unwrap();
        serde_json::from_slice(a.bytes("json").unwrap()).unwrap()
    }

    #[test]
    fn the_albedo_level_is_held_near_the_prediction_unless_freed() {
        // Held by default: the report names the gain the light took.
        let inputs = inputs();
        let held = report_with(&inputs, None);
        let gain = held["invert"]["level_gain"].as_array().expect("a gain");
        assert_eq!(gain.len(), 3);
        assert!(gain.iter().all(|g| g.as_f64().is_some_and(|g| g > 0.0)));
        assert_eq!(report_with(&inputs, Some("pred")), held);
        // The stage's default band is the library's.
        let p = params_of(MaterialOptNode.info(), &[]);
        assert_eq!(
            p.f32("albedo_level_band"),
            matflow_inverse::invert::LEVEL_BAND
        );
        // Free: the fit settles the level alone.
        assert!(report_with(&inputs, Some("free"))["invert"]["level_gain"].is_null());
    }

    /// With `albedo_structure: photo` the recovered albedo is the
    /// prediction's structure times one level per surface (at 24² the
    /// photo's detail is below a pixel): its ratio to the prediction varies
    /// far less than the free solve's (the default), which follows every
    /// pixel's noise and shading error.
    #[test]
    fn the_albedo_takes_its_structure_from_the_prediction_and_photo() {
        let inputs = inputs();
        let pred = SceneData::decode(&inputs[0].1).unwrap().pred.albedo;
        let spread = |structure: &str| {
            let out = run_with(
                &inputs,
                &[("albedo_structure", Value::Str(structure.into()))],
            );
            let a = materials_from(&out["materials"]).unwrap().albedo;
            // The spread of log(albedo / prediction) over the pixels, per
            // channel, about its median (robust to the sky's pixels).
            let mut worst = 0f64;
            for c in 0..3 {
                let mut v: Vec<f64> = a
                    .data
                    .iter()
                    .zip(&pred.data)
                    .map(|(x, p)| (f64::from(x[c].max(1e-4)) / f64::from(p[c].max(1e-4))).ln())
                    .collect();
                v.sort_by(f64::total_cmp);
                let med = v[v.len() / 2];
                let mut dev: Vec<f64> = v.iter().map(|x| (x - med).abs()).collect();
                dev.sort_by(f64::total_cmp);
                worst = worst.max(dev[dev.len() * 3 / 4]);
            }
            worst
        };
        let (photo, free) = (spread("photo"), spread("free"));
        assert!(
            photo < 0.5 * free,
            "upper-quartile deviation of log(albedo / prediction): photo {photo}, free {free}"
        );
        let p = params_of(MaterialOptNode.info(), &[]);
        assert_eq!(p.str("albedo_structure"), "free");
    }
}
