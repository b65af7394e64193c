//! End-to-end tests over the `matflow` binary on scenes it generates itself.

mod support;
use std::path::{Path, PathBuf};
use std::process::Output;
use support::{matflow, s};

fn ok(o: &Output) -> String {
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "matflow failed: {}\n{}",
        out,
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

fn synth(dir: &Path) -> PathBuf {
    let b = dir.join("room");
    ok(&matflow(
        &[
            "synth",
            "--seed",
            "5",
            "--size",
            "48",
            "--spp",
            "4",
            "--out",
            s(&b),
        ],
        None,
    ));
    b
}

#[test]
fn synth_then_render_writes_exr_png_and_summary() {
    let dir = tempfile::tempdir().unwrap();
    let b = synth(dir.path());
    for f in [
        "gt_image.exr",
        "gt_image.png",
        "depth.exr",
        "albedoPred.exr",
        "roughnessPred.png",
        "metallicPred.png",
        "normalPred.exr",
        "ground_truth/albedo.exr",
        "ground_truth/envmap.hdr",
    ] {
        assert!(b.join(f).is_file(), "missing {f}");
    }
    let out = dir.path().join("r.exr");
    let render = |bundle: &Path, extra: &[&str]| {
        let args = [&["render", "--bundle", s(bundle), "--out", s(&out)], extra].concat();
        ok(&matflow(&args, None))
    };
    let text = render(
        &b,
        &[
            "--materials",
            "ground_truth",
            "--spp",
            "8",
            "--depth",
            "3",
            "--compare",
            s(&b.join("gt_image.exr")),
        ],
    );
    assert!(text.contains("rendered 48x48 at 8 spp, depth 3"), "{text}");
    // A synth scene is its depth mesh: the bundle says so, and renders
    // complete nothing past the frame unless asked.
    assert!(
        text.contains("completion none (the bundle's own geometry, geometry.json)"),
        "{text}"
    );
    // The open depth mesh samples its light by radiance alone.
    assert!(text.contains("light sampled by radiance"), "{text}");
    assert!(text.contains(" M rays"), "{text}");
    assert!(out.is_file() && dir.path().join("r.png").is_file());
    // Same scene, different seed and spp: close to the stored input image.
    let psnr: f64 = text
        .split("PSNR (sRGB, gamma 2.2) against")
        .nth(1)
        .unwrap()
        .split(": ")
        .nth(1)
        .unwrap()
        .trim_end_matches(|c: char| !c.is_ascii_digit())
        .trim()
        .parse()
        .unwrap();
    assert!(psnr > 20.0, "{text}");
    // A PLY mesh export readable back.
    let ply = dir.path().join("m.ply");
    let text = ok(&matflow(
        &["mesh", "--bundle", s(&b), "--out", s(&ply)],
        None,
    ));
    assert!(text.contains("triangles"), "{text}");
    assert!(
        text.contains("completion none (the bundle's own geometry, geometry.json)"),
        "{text}"
    );
    let (pos, faces) =
        matflow_geom::mesh::read_ply_positions_faces(&std::fs::read(&ply).unwrap()).unwrap();
    assert!(!pos.is_empty() && !faces.is_empty());
    // A bundle that says nothing of its geometry (a photo's) has its photo
    // test each completion under its own light and maps: this one was
    // rendered on its depth mesh alone, which the photo supports (and it
    // assumes least); the scores are printed, and a render writes them to
    // its report. A geometry.json that names no mode is an error naming
    // the file.
    let geometry = b.join("geometry.json");
    let declared = std::fs::read(&geometry).unwrap();
    std::fs::remove_file(&geometry).unwrap();
    let text = ok(&matflow(
        &["mesh", "--bundle", s(&b), "--out", s(&ply)],
        None,
    ));
    assert!(text.contains("completion none (auto: "), "{text}");
    for h in ["none", "planes", "room", "closed"] {
        assert!(text.contains(&format!("  {h} ")), "{text}");
    }
    assert!(text.contains("tested under "), "{text}");
    let text = render(&b, &["--materials", "ground_truth", "--spp", "2"]);
    assert!(text.contains("completion none (auto: "), "{text}");
    // It explains its own photo (the sanity check of every render in the
    // photo's light), and says so in its report.
    assert!(text.contains("the render explains the photo at "), "{text}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.with_extension("json")).unwrap()).unwrap();
    assert_eq!(report["completion"]["complete"], "none");
    assert_eq!(
        report["completion"]["evidence"]["scores"]
            .as_array()
            .unwrap()
            .len(),
        4
    );
    assert!(report["photo_psnr"].as_f64().unwrap() > 20.0, "{report}");
    // Forced, it is what was asked.
    let text = render(
        &b,
        &[
            "--materials",
            "ground_truth",
            "--spp",
            "2",
            "--complete",
            "planes",
        ],
    );
    assert!(text.contains("completion planes (as asked)"), "{text}");
    std::fs::write(&geometry, r#"{"complete": "box"}"#).unwrap();
    let o = matflow(&["mesh", "--bundle", s(&b), "--out", s(&ply)], None);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("geometry.json: complete:"), "{e}");
    std::fs::write(&geometry, declared).unwrap();
    // With the room completed past the frame: more triangles in the PLY,
    // and a render that still runs (the added triangles take the materials
    // of the pixels they continue); an inversion with it, whose result
    // renders with it by default.
    let text = ok(&matflow(
        &["mesh", "--bundle", s(&b), "--complete", "--out", s(&ply)],
        None,
    ));
    assert!(text.contains("completion room (as asked)"), "{text}");
    assert!(text.contains("completion: "), "{text}");
    let (_, more) =
        matflow_geom::mesh::read_ply_positions_faces(&std::fs::read(&ply).unwrap()).unwrap();
    assert!(more.len() >= faces.len(), "{text}");
    // The closed room guides its light samples by what its regions see,
    // unless told not to.
    let room = |extra: &[&str]| {
        let mut args = vec![
            "--materials",
            "ground_truth",
            "--spp",
            "2",
            "--complete",
            "room",
        ];
        args.extend_from_slice(extra);
        render(&b, &args)
    };
    let text = room(&[]);
    assert!(text.contains("light guided by visibility in "), "{text}");
    // Its light samples also aim at the windows of its assumed walls
    // (portals), unless told not to.
    let portals = |text: &str| -> usize {
        let end = text.find(" portal(s)").expect("a portal count");
        text[..end].rsplit(' ').next().unwrap().parse().unwrap()
    };
    assert!(portals(&text) > 0, "{text}");
    let off = room(&["--portals", "off"]);
    assert_eq!(portals(&off), 0, "{off}");
    let text = room(&["--light-guide", "off"]);
    assert!(text.contains("light sampled by radiance"), "{text}");
    let inv = dir.path().join("inv-room");
    ok(&matflow(
        &[
            "invert",
            "--bundle",
            s(&b),
            "--out",
            s(&inv),
            "--budget-seconds",
            "3",
            "--complete",
            "room",
            "--rm-search",
            "on",
            "--albedo-level",
            "pred",
            "--lamps",
            "on",
            "--sun",
            "on",
            "--quiet",
        ],
        None,
    ));
    let text = render(&inv, &["--spp", "2"]);
    assert!(
        text.contains("completion room (the one matflow invert recovered these maps with)"),
        "{text}"
    );
    // Lamps were fitted at the closed room's sites, and light its render
    // unless told not to.
    let lamps: serde_json::Value =
        serde_json::from_slice(&std::fs::read(inv.join("best_results/lamps.json")).unwrap())
            .unwrap();
    let points: Vec<serde_json::Value> = lamps["lamps"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|l| l.get("position").is_some())
        .cloned()
        .collect();
    assert_eq!(points.len(), 9, "{lamps}");
    assert!(text.contains(", 9 lamp(s), "), "{text}");
    let text = render(&inv, &["--spp", "2", "--lamps", "off"]);
    assert!(text.contains(", 0 lamp(s), 0 sun(s), "), "{text}");
    // A sun in the lamps file lights the render under the envmap it was
    // fitted with, and not under a new one.
    let mut with_sun = points.clone();
    with_sun.push(serde_json::json!({"direction": [0.0, 1.0, 0.0], "intensity": [2.0, 2.0, 2.0]}));
    let with_sun = serde_json::json!({ "lamps": with_sun });
    std::fs::write(
        inv.join("best_results/lamps.json"),
        serde_json::to_vec(&with_sun).unwrap(),
    )
    .unwrap();
    let text = render(&inv, &["--spp", "2"]);
    assert!(text.contains(", 9 lamp(s), 1 sun(s), "), "{text}");
    let sky = inv.join("best_results/envmap.hdr");
    let text = render(&inv, &["--spp", "2", "--envmap", s(&sky)]);
    assert!(text.contains(", 9 lamp(s), 0 sun(s), "), "{text}");
    // The inversion's frozen paths were guided, and its summary says so.
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(inv.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["options"]["light_guide"], true, "{summary}");
    assert_eq!(summary["light_guided"], true, "{summary}");
    assert_eq!(summary["options"]["portals"], true, "{summary}");
    // The sun was looked for: the summary reports the search.
    assert_eq!(summary["options"]["sun"], true, "{summary}");
    assert!(summary["sun"]["found"].is_boolean(), "{summary}");
    assert!(summary["portals"].as_u64().unwrap() > 0, "{summary}");
    // The albedo's level was held at the prediction's: the summary says
    // so, and what gain the light took.
    assert_eq!(summary["options"]["albedo_level"], "pred", "{summary}");
    let gain = summary["level_gain"].as_array().expect("level_gain");
    assert!(
        gain.len() == 3
            && gain
                .iter()
                .all(|g| g.as_f64().is_some_and(|g| g.is_finite() && g > 0.0)),
        "{summary}"
    );
    // Roughness and metallic were searched per segment first (asked
    // for, R and M not trusted), and the summary counts it.
    assert_eq!(summary["options"]["lamps"], true, "{summary}");
    assert_eq!(summary["lamps"]["sites"], 9, "{summary}");
    assert_eq!(summary["options"]["rm_search"], true, "{summary}");
    assert!(
        summary["rm_search"]["segments"].as_u64().unwrap() > 0,
        "{summary}"
    );
    assert!(
        summary["stages"]
            .as_array()
            .unwrap()
            .iter()
            .any(|st| st["name"] == "R/M per segment"),
        "{summary}"
    );
}

#[test]
fn render_is_bit_identical_across_thread_counts_and_runs() {
    let dir = tempfile::tempdir().unwrap();
    let b = synth(dir.path());
    let mut bytes = Vec::new();
    for (k, t) in [1usize, 2, 2].iter().enumerate() {
        let out = dir.path().join(format!("r{k}.exr"));
        ok(&matflow(
            &[
                "render",
                "--bundle",
                s(&b),
                "--materials",
                "pred",
                "--spp",
                "4",
                "--out",
                s(&out),
            ],
            Some(*t),
        ));
        bytes.push(std::fs::read(&out).unwrap());
    }
    assert_eq!(bytes[0], bytes[1]);
    assert_eq!(bytes[1], bytes[2]);
}

#[test]
fn bad_inputs_fail_with_messages_naming_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    // Missing bundle folder.
    let o = matflow(
        &[
            "render",
            "--bundle",
            "/nonexistent/bundle",
            "--out",
            "/tmp/x.exr",
        ],
        None,
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("/nonexistent/bundle"), "{err}");
    // Values out of range are refused, naming the option and the range.
    for (option, value, range) in [
        ("--rm-margin", "1.5", "a number in [0, 0.999]"),
        ("--albedo-level-band", "0.99", "a number in [0, 0.95]"),
    ] {
        let o = matflow(
            &[
                "invert",
                "--bundle",
                "/nonexistent/bundle",
                "--out",
                "/tmp/x",
                option,
                value,
            ],
            None,
        );
        assert!(!o.status.success());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(option) && err.contains(range), "{err}");
    }
    // NaN inside a prediction file: named, with the pixel count.
    let b = synth(dir.path());
    let mut albedo = matflow_scene::io::read_exr_rgb(&b.join("albedoPred.exr")).unwrap();
    albedo.data[10].x = f32::NAN;
    albedo.data[11].y = f32::INFINITY;
    matflow_scene::io::write_exr_rgb(&b.join("albedoPred.exr"), &albedo).unwrap();
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&b),
            "--materials",
            "pred",
            "--out",
            s(&dir.path().join("x.exr")),
        ],
        None,
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("albedoPred.exr") && err.contains("2 pixel"),
        "{err}"
    );
    // The same file given to `invert`: rejected before any work, nothing
    // written.
    let out = dir.path().join("inv-nan");
    let o = matflow(
        &["invert", "--bundle", s(&b), "--out", s(&out), "--quiet"],
        None,
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("albedoPred.exr") && err.contains("2 pixel"),
        "{err}"
    );
    assert!(!out.exists(), "invert wrote output for a rejected input");
    assert!(!dir.path().join("x.exr").exists());
    // Corrupt envmap file.
    let env = dir.path().join("bad.hdr");
    std::fs::write(&env, b"#?RADIANCE\ngarbage").unwrap();
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&b),
            "--materials",
            "ground_truth",
            "--envmap",
            s(&env),
            "--out",
            s(&dir.path().join("y.exr")),
        ],
        None,
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("bad.hdr"));
    // Unknown material source.
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&b),
            "--materials",
            "nope",
            "--out",
            "/tmp/z.exr",
        ],
        None,
    );
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("'nope'") && e.contains("--materials") && e.contains("ground_truth"),
        "{e}"
    );
}

/// `invert` writes the reference's best_results/ layout and a summary,
/// its image outputs are byte-identical across thread counts, and the
/// output bundle re-renders (and relights) with `render`.
#[test]
fn invert_writes_best_results_deterministically_and_rerenders() {
    let dir = tempfile::tempdir().unwrap();
    let b = synth(dir.path());
    let files = [
        "best_results/albedo.exr",
        "best_results/roughness.exr",
        "best_results/metallic.exr",
        "best_results/normal.exr",
        "best_results/envmap.hdr",
        "best_results/rendered_img.exr",
        "best_results/rendered_raw.exr",
    ];
    let mut runs: Vec<Vec<Vec<u8>>> = Vec::new();
    for (k, t) in [1usize, 2].iter().enumerate() {
        let out = dir.path().join(format!("inv{k}"));
        let text = ok(&matflow(
            &[
                "invert",
                "--bundle",
                s(&b),
                "--out",
                s(&out),
                "--budget-seconds",
                "2",
                "--spp",
                "4",
                "--final-spp",
                "4",
                "--steps",
                "15",
                "--trust-rm",
                "--quiet",
            ],
            Some(*t),
        ));
        assert!(text.contains("rerender PSNR"), "{text}");
        assert!(
            text.contains("completion none (the bundle's own geometry, geometry.json)"),
            "{text}"
        );
        for f in files {
            assert!(out.join(f).is_file(), "missing {f}");
        }
        for f in ["depth.exr", "albedoPred.exr", "gt_image.exr"] {
            assert!(out.join(f).is_file(), "missing {f}");
        }
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
        let psnr = summary["rerender"]["psnr"].as_f64().unwrap();
        assert!(psnr.is_finite() && psnr > 10.0, "{summary}");
        assert!(summary["rerender"]["ssim"].as_f64().unwrap() > 0.0);
        // The re-render is denoised by default; its samples as they came
        // are kept beside it, and differ.
        assert_eq!(summary["options"]["denoise_render"], true);
        assert!(summary["rerender_raw"]["psnr"]
            .as_f64()
            .unwrap()
            .is_finite());
        assert!(text.contains("denoised ("), "{text}");
        assert_ne!(
            std::fs::read(out.join("best_results/rendered_img.exr")).unwrap(),
            std::fs::read(out.join("best_results/rendered_raw.exr")).unwrap()
        );
        let stages = summary["stages"].as_array().unwrap();
        assert!(stages.iter().any(|s| s["name"] == "materials arm 1"));
        // No timings: the files must not depend on the clock (the run's
        // report has the stage's seconds).
        for st in stages {
            assert!(st.get("seconds").is_none(), "{st}");
        }
        assert!(summary.get("seconds").is_none());
        runs.push(
            files
                .iter()
                .map(|f| std::fs::read(out.join(f)).unwrap())
                .collect(),
        );
    }
    for (i, f) in files.iter().enumerate() {
        assert!(
            runs[0][i] == runs[1][i],
            "{f} differs between 1 and 2 threads"
        );
    }
    // Re-render the result (with the filter the inversion fitted with,
    // unless told otherwise), and relight it with the ground-truth envmap.
    let out = dir.path().join("inv0");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["options"]["pixel_filter"], "box");
    assert_eq!(summary["options"]["complete"], "none");
    // The result declares the geometry it was recovered on with its depth.
    let declared: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("geometry.json")).unwrap()).unwrap();
    assert_eq!(declared["complete"], "none");
    assert_eq!(summary["completion"]["complete"], "none");
    let r = dir.path().join("rr.exr");
    let render = |materials: &str, extra: &[&str]| {
        let mut args = vec![
            "render",
            "--bundle",
            s(&out),
            "--materials",
            materials,
            "--spp",
            "4",
            "--out",
            s(&r),
        ];
        args.extend_from_slice(extra);
        ok(&matflow(&args, None))
    };
    let text = render("best_results", &[]);
    assert!(
        text.contains("box filter (the one matflow invert fitted these maps with)"),
        "{text}"
    );
    assert!(
        text.contains("completion none (the one matflow invert recovered these maps with)"),
        "{text}"
    );
    assert!(r.is_file());
    let boxed = std::fs::read(&r).unwrap();
    let text = render("best_results", &["--filter", "gaussian"]);
    assert!(text.contains("gaussian filter (as asked)"), "{text}");
    assert_ne!(std::fs::read(&r).unwrap(), boxed);
    let text = render("best_results", &["--denoise"]);
    assert!(text.contains("4 spp (denoised)"), "{text}");
    assert_ne!(std::fs::read(&r).unwrap(), boxed);
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&out),
            "--spp",
            "1",
            "--denoise",
            "--out",
            s(&r),
        ],
        None,
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("spp 2 or more"));
    // Predictions are not what invert fitted: Mitsuba's Gaussian.
    let text = render("pred", &[]);
    assert!(text.contains("gaussian filter (the default)"), "{text}");
    ok(&matflow(
        &[
            "render",
            "--bundle",
            s(&out),
            "--materials",
            "best_results",
            "--envmap",
            s(&b.join("ground_truth/envmap.hdr")),
            "--spp",
            "4",
            "--out",
            s(&dir.path().join("relit.exr")),
        ],
        None,
    ));
}

/// The inverse routes come from one registry (`matflow_inverse::routes`):
/// every registered route and each of its options appears in the pipeline
/// schema (`matflow kinds`) and in `matflow invert --help`, with no list
/// of routes anywhere else (`matflow-bench invert` reads the same registry:
/// `every_registered_route_is_benchmarked_by_default` in its crate); an
/// option given for a route that is not chosen is refused by name.
#[test]
fn registered_routes_reach_cli_and_schema() {
    use matflow_inverse::routes::{all_options, Side, ENV_ROUTES, MAT_ROUTES};
    let kinds = ok(&matflow(&["kinds"], None));
    let help = ok(&matflow(&["invert", "--help"], None));
    let schema_line = |param: &str| -> Vec<String> {
        kinds
            .lines()
            .filter(|l| l.starts_with(&format!("| `{param}` |")))
            .map(String::from)
            .collect()
    };
    for (side, param, names) in [
        (
            Side::Env,
            "env_route",
            ENV_ROUTES
                .iter()
                .map(|e| (e.name, e.doc))
                .collect::<Vec<_>>(),
        ),
        (
            Side::Mat,
            "mat_route",
            MAT_ROUTES.iter().map(|e| (e.name, e.doc)).collect(),
        ),
    ] {
        let lines = schema_line(param);
        assert!(!lines.is_empty(), "`{param}` missing from matflow kinds");
        for (name, doc) in &names {
            for l in &lines {
                assert!(l.contains(name), "{param} choice {name} missing: {l}");
            }
            // clap aligns the docs: "- mlp:   the paper's …".
            assert!(
                help.lines().any(|l| {
                    let l = l.trim_start();
                    l.starts_with(&format!("- {name}:")) && l.ends_with(doc)
                }),
                "--{} {name} missing from invert --help",
                param.replace('_', "-")
            );
        }
        for (q, route, _) in all_options(side) {
            assert!(
                !schema_line(&q).is_empty(),
                "route {route}'s option {q} missing from matflow kinds"
            );
            let flag = format!("--{}", q.replace('_', "-"));
            assert!(help.contains(&flag), "{flag} missing from invert --help");
        }
    }
    // An option of a route that is not chosen is an error, not ignored.
    let o = matflow(
        &[
            "invert",
            "--bundle",
            "x",
            "--out",
            "y",
            "--mat-route",
            "solve",
            "--mat-mlp-width",
            "8",
        ],
        None,
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--mat-mlp-width applies to --mat-route mlp"),
        "{err}"
    );
}

/// `matflow predict`, `mesh`, `render` and `invert` each run one node kind as a
/// one-stage pipeline: a pipeline stage of that kind given the same
/// parameters is the same action (the same key), served from the cache
/// the command filled, with the same bytes; the command run again is a
/// cache hit; the stage computed afresh makes the same bytes; and how the
/// bundle's path is spelled (on the command line as it is, in the
/// pipeline through a link) is no part of the action.
#[test]
fn a_command_and_its_pipeline_stage_are_one_action() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let b = synth(d);
    std::os::unix::fs::symlink(&b, d.join("alias")).unwrap();
    let cache = d.join("cache");
    let report = |p: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
    };
    // (command flags, the stage as a pipeline writes it, its output, and
    // what it writes; `{}` stands for the run's output stem)
    let photo = support::repo().join("tests/data/matnet_photo.png");
    let photo_line = format!("kind: matnet\n    photo: {}", s(&photo));
    let cases: [(&[&str], &str, &str, &[&str]); 4] = [
        (
            &["predict", s(&photo)],
            &photo_line,
            "{}",
            &["{}/albedoPred.exr", "{}/depth.exr", "{}/prediction.json"],
        ),
        (
            &["mesh", "--bundle", s(&b), "--angle", "8"],
            "kind: bundle_mesh\n    bundle: alias\n    angle: 8",
            "{}.ply",
            &["{}.ply"],
        ),
        (
            &[
                "render",
                "--bundle",
                s(&b),
                "--materials",
                "ground_truth",
                "--spp",
                "2",
                "--complete",
                "auto",
            ],
            "kind: bundle_render\n    bundle: alias\n    materials: ground_truth\n    spp: 2\n    \
             complete: auto",
            "{}.exr",
            &["{}.exr", "{}.png", "{}.json"],
        ),
        (
            &[
                "invert",
                "--bundle",
                s(&b),
                "--budget-seconds",
                "2",
                "--quiet",
            ],
            "kind: bundle_invert\n    bundle: alias\n    budget_seconds: 2",
            "{}",
            &[
                "{}/summary.json",
                "{}/geometry.json",
                "{}/best_results/albedo.exr",
                "{}/best_results/envmap.hdr",
            ],
        ),
    ];
    for (k, (flags, stage, out, files)) in cases.iter().enumerate() {
        let at = |run: &str, t: &str| t.replace("{}", s(&d.join(format!("{run}{k}"))));
        let mut args = flags.to_vec();
        let r1 = d.join(format!("cmd{k}.report.json"));
        let cmd_out = at("cmd", out);
        args.extend(["--out", &cmd_out, "--cache", s(&cache), "--report", s(&r1)]);
        ok(&matflow(&args, None));
        let first = report(&r1)["stages"][0].clone();
        assert_eq!(first["status"], "executed", "{first}");
        let yaml = d.join(format!("p{k}.yaml"));
        let text = format!(
            "pipeline: p{k}\noutputs: [s]\nstages:\n  s:\n    {stage}\n    output: {}\n",
            out.replace("{}", &format!("stage{k}"))
        );
        std::fs::write(&yaml, text).unwrap();
        let r2 = d.join(format!("stage{k}.report.json"));
        ok(&matflow(
            &[
                "run",
                s(&yaml),
                "--quiet",
                "--cache",
                s(&cache),
                "--report",
                s(&r2),
            ],
            None,
        ));
        let second = report(&r2)["stages"][0].clone();
        assert_eq!(second["status"], "cached", "{flags:?}: {second}");
        assert_eq!(second["key"], first["key"], "{flags:?}");
        assert_eq!(second["outputs"], first["outputs"], "{flags:?}");
        for f in *files {
            let (x, y) = (at("cmd", f), at("stage", f));
            assert!(Path::new(&x).is_file(), "{x}");
            assert_eq!(
                std::fs::read(&x).unwrap(),
                std::fs::read(&y).unwrap(),
                "{f}"
            );
        }
        // The command again: served from the cache.
        ok(&matflow(&args, None));
        assert_eq!(report(&r1)["stages"][0]["status"], "cached");
        // The stage computed afresh: the same bytes, every output (notes
        // and reports too: none holds a time or a path as spelled).
        let r3 = d.join(format!("fresh{k}.report.json"));
        let fresh = d.join(format!("cache-fresh{k}"));
        ok(&matflow(
            &[
                "run",
                s(&yaml),
                "--quiet",
                "--cache",
                s(&fresh),
                "--report",
                s(&r3),
            ],
            None,
        ));
        let third = report(&r3)["stages"][0].clone();
        assert_eq!(third["status"], "executed", "{third}");
        assert_eq!(third["outputs"], first["outputs"], "{flags:?}");
    }
}
