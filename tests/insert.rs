//! Object insertion over the binary: `pipelines/insert.yaml` at test size
//! (composited and full renders, an incremental re-edit of an inserted
//! object's material), `render --insert`, the shipped meshes, and clear
//! errors for bad objects files.

mod support;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Output;
use support::{matflow, repo, s, scratch};

use matflow_scene::io;
use serde_json::Value;

fn text(o: &Output) -> String {
    format!(
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// The insert pipeline's objects at 64², meshes by absolute path.
fn objects(jug: &str) -> String {
    let m = repo().join("pipelines/meshes");
    format!(
        "[{{mesh: {}, anchor: [50, 59], scale: 0.9, rotate: [0, 20, 0], material: {jug}}}, \
         {{mesh: {}, anchor: [10, 59], scale: 0.7, material: {{type: diffuse, albedo: [0.2, 0.4, 0.8]}}}}]",
        s(&m.join("jug.obj")),
        s(&m.join("torus.obj"))
    )
}

/// `matflow run FILE --quiet --cache CACHE --report WORK/report.json`
/// with `--set` for each of `sets`, then `extra`: the output and the
/// report (null when the run failed).
fn run_pipeline(
    file: &Path,
    cache: &Path,
    work: &Path,
    sets: &[String],
    extra: &[&str],
) -> (Output, Value) {
    let report = work.join("report.json");
    let mut args = vec![
        "run",
        s(file),
        "--quiet",
        "--cache",
        s(cache),
        "--report",
        s(&report),
    ];
    for set in sets {
        args.push("--set");
        args.push(set);
    }
    args.extend_from_slice(extra);
    let out = matflow(&args, None);
    if !out.status.success() {
        return (out, Value::Null);
    }
    let r = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    (out, r)
}

/// Stage → status, from a report.
fn statuses(r: &Value) -> BTreeMap<String, String> {
    r["stages"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|s| {
                    (
                        s["name"].as_str().unwrap().to_string(),
                        s["status"].as_str().unwrap().to_string(),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The stages that executed (sorted: a report's map is).
fn executed(st: &BTreeMap<String, String>) -> Vec<&str> {
    st.iter()
        .filter(|(_, v)| *v == "executed")
        .map(|(k, _)| k.as_str())
        .collect()
}

/// How many pixels of two images of one size differ.
fn pixels_differing(a: &matflow_scene::RgbImage, b: &matflow_scene::RgbImage) -> usize {
    a.data.iter().zip(&b.data).filter(|(x, y)| x != y).count()
}

/// Runs pipelines/insert.yaml at 64²; returns the report's stage statuses.
fn run_insert(cache: &Path, work: &Path, extra: &[String]) -> (Output, BTreeMap<String, String>) {
    let sets = [
        "scene.size=64".to_string(),
        "scene.spp=8".into(),
        "lighting.budget_seconds=1".into(),
        "recovered.budget_seconds=2".into(),
        "base.spp=8".into(),
        "base.path_spp=4".into(),
        format!("base.objects={}", objects("{type: glass, ior: 1.5}")),
        format!("inserted.output={}", s(&work.join("inserted.exr"))),
        format!("full.output={}", s(&work.join("full.exr"))),
    ];
    let extra: Vec<&str> = extra.iter().map(|a| a.as_str()).collect();
    let (out, r) = run_pipeline(
        &repo().join("pipelines/insert.yaml"),
        cache,
        work,
        &sets,
        &extra,
    );
    (out, statuses(&r))
}

#[test]
fn the_insert_pipeline_composites_and_re_edits_an_object_from_kept_paths() {
    let work = scratch("insert", "pipeline");
    let cache = work.join("cache");
    let (out, st) = run_insert(&cache, &work, &[]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(st.values().all(|s| s == "executed"), "{st:?}");
    let inserted = io::read_exr_rgb(&work.join("inserted.exr")).unwrap();
    let full = io::read_exr_rgb(&work.join("full.exr")).unwrap();
    assert!(work.join("inserted.png").is_file() && work.join("full.png").is_file());
    assert_eq!((inserted.width, inserted.height), (64, 64));
    // Composited and full differ (the photo's own detail is kept outside
    // the objects), and both are finite.
    assert!(inserted
        .data
        .iter()
        .chain(&full.data)
        .all(|v| v.is_finite()));
    let differ = pixels_differing(&inserted, &full);
    assert!(differ > 64 * 64 / 2, "{differ}");

    // Tinting the jug re-runs only the composited stage, from kept paths.
    let tinted = format!(
        "inserted.objects={}",
        objects("{type: glass, ior: 1.5, tint: [1, 0.5, 0.2]}")
    );
    let (out, st) = run_insert(&cache, &work, &["--set".into(), tinted]);
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(executed(&st), ["inserted"], "{st:?}");
    let again = io::read_exr_rgb(&work.join("inserted.exr")).unwrap();
    let changed = pixels_differing(&again, &inserted);
    assert!(
        changed > 0 && changed < 64 * 64 / 2,
        "{changed} pixels changed"
    );

    // Moving an object cannot be served from the kept paths.
    let moved = format!(
        "inserted.objects={}",
        objects("{type: glass, ior: 1.5}").replace("[50, 59]", "[40, 59]")
    );
    let (out, _) = run_insert(&cache, &work, &["--set".into(), moved]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("not placed as in the `paths` stage"),
        "{}",
        text(&out)
    );
    let _ = std::fs::remove_dir_all(&work);
}

#[test]
fn render_insert_reads_an_objects_file_and_reports_its_mistakes() {
    let work = scratch("insert", "cli");
    let bundle = work.join("room");
    let o = matflow(
        &["synth", "--size", "48", "--spp", "8", "--out", s(&bundle)],
        None,
    );
    assert!(o.status.success(), "{}", text(&o));
    std::fs::create_dir_all(work.join("meshes")).unwrap();
    let o = matflow(&["shapes", "--out", s(&work.join("meshes"))], None);
    assert!(o.status.success(), "{}", text(&o));
    let file = work.join("objects.yaml");
    std::fs::write(
        &file,
        "- mesh: meshes/sphere.obj\n  anchor: [24, 44]\n  scale: 0.5\n  material: {type: glass, roughness: 0.2}\n",
    )
    .unwrap();
    // `render` of the bundle's true maps at `spp` with the objects file,
    // `extra` flags, to `out`.
    let insert = |spp: &str, extra: &[&str], out: &Path| {
        let mut args = vec![
            "render",
            "--bundle",
            s(&bundle),
            "--materials",
            "ground_truth",
            "--spp",
            spp,
            "--insert",
            s(&file),
        ];
        args.extend_from_slice(extra);
        args.extend(["--out", s(out)]);
        matflow(&args, None)
    };
    for composite in ["differential", "full"] {
        let out = work.join(format!("{composite}.exr"));
        let o = insert("4", &["--composite", composite], &out);
        assert!(o.status.success(), "{}", text(&o));
        assert!(text(&o).contains("inserted 1 object(s)"), "{}", text(&o));
        assert!(out.is_file());
    }
    // Mistakes, each located in the objects file or naming the mesh.
    let cases = [
        (
            "- mesh: meshes/sphere.obj\n  anchor: [24, 44]\n  colour: red\n",
            "objects.yaml:3:3",
            "unknown field `colour`",
        ),
        (
            "- mesh: meshes/none.obj\n  anchor: [24, 44]\n",
            "objects.yaml:1:9",
            "none.obj",
        ),
        (
            "- mesh: meshes/sphere.obj\n",
            "objects.yaml",
            "give `translate",
        ),
        (
            "- mesh: meshes/sphere.obj\n  anchor: [24, 44]\n  scale: 0\n",
            "objects.yaml:3:10",
            "field `scale`",
        ),
        (
            "- mesh: meshes/sphere.obj\n  translate: [0, 0, 5]\n",
            "objects.yaml",
            "behind the camera",
        ),
        (
            "- mesh: meshes/sphere.obj\n  anchor: [24, 44]\n  material: {type: glass, ior: 0.5}\n",
            "objects.yaml:3:32",
            "field `ior`",
        ),
        (
            "- mesh: meshes/sphere.obj\n  anchor: [99, 44]\n",
            "objects.yaml",
            "outside the 48x48 image",
        ),
    ];
    for (yaml, at, want) in cases {
        std::fs::write(&file, yaml).unwrap();
        let o = insert("1", &[], &work.join("bad.exr"));
        let t = text(&o);
        assert!(!o.status.success(), "accepted:\n{yaml}");
        assert!(t.contains(at) && t.contains(want), "{yaml}\n{t}");
        assert!(!t.contains("panicked"), "{t}");
    }
    let _ = std::fs::remove_dir_all(&work);
}

#[test]
fn the_shipped_meshes_are_what_matflow_shapes_writes() {
    let work = scratch("insert", "shapes");
    let o = matflow(&["shapes", "--out", s(&work)], None);
    assert!(o.status.success(), "{}", text(&o));
    for name in ["jug", "torus", "sphere", "cube"] {
        let shipped = std::fs::read(repo().join(format!("pipelines/meshes/{name}.obj"))).unwrap();
        let made = std::fs::read(work.join(format!("{name}.obj"))).unwrap();
        assert!(
            shipped == made,
            "pipelines/meshes/{name}.obj differs from `matflow shapes`"
        );
    }
    let _ = std::fs::remove_dir_all(&work);
}

#[test]
fn the_glass_pipeline_makes_a_region_transparent_and_re_edits_t_from_kept_paths() {
    let work = scratch("insert", "glass");
    let cache = work.join("cache");
    let glass_yaml = repo().join("pipelines/glass.yaml");
    let sets: Vec<String> = [
        "scene.size=64",
        "scene.spp=8",
        "lighting.budget_seconds=1",
        "recovered.budget_seconds=2",
        "base.spp=8",
        "base.path_spp=4",
        "glassy.mask_flood=~",
        "glassy.mask_rect=[44, 38, 58, 52]",
        "lengths.mask_flood=~",
        "lengths.mask_rect=[44, 38, 58, 52]",
    ]
    .iter()
    .map(|x| x.to_string())
    .chain([format!("glass.output={}", s(&work.join("glass.exr")))])
    .collect();
    let run_file = |file: &Path, extra: &[&str]| run_pipeline(file, &cache, &work, &sets, extra);
    let run = |extra: &[&str]| {
        let (out, r) = run_file(&glass_yaml, extra);
        (out, statuses(&r))
    };
    let (out, st) = run(&[]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(st.values().all(|s| s == "executed"), "{st:?}");
    let first = io::read_exr_rgb(&work.join("glass.exr")).unwrap();
    assert!(first.data.iter().all(|v| v.is_finite()));
    // Less transmission: the transparency and its render re-run, from the
    // kept paths; pixels far from the region keep their values.
    let (out, st) = run(&["--set", "glassy.transmission=0.3"]);
    assert!(out.status.success(), "{}", text(&out));
    assert_eq!(executed(&st), ["glass", "glassy"], "{st:?}");
    let second = io::read_exr_rgb(&work.join("glass.exr")).unwrap();
    let changed = pixels_differing(&second, &first);
    assert!(
        (14 * 14 / 2..64 * 64 / 2).contains(&changed),
        "{changed} pixels changed"
    );
    // Distances from a refraction map (the refraction-length network's
    // output) are used as given: a map of zeros makes the same materials
    // as a zero thickness and gap.
    let digest_of = |file: &Path, extra: &[&str]| {
        let (out, r) = run_file(file, extra);
        assert!(out.status.success(), "{}", text(&out));
        r["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == "glassy")
            .unwrap()["outputs"]["materials"]
            .clone()
    };
    let digest = |extra: &[&str]| digest_of(&glass_yaml, extra);
    let zeros = work.join("zeros.exr");
    io::write_exr_rgb(
        &zeros,
        &matflow_scene::RgbImage::new(64, 64, glam::Vec3::ZERO),
    )
    .unwrap();
    let set = format!("glassy.refraction_map={}", s(&zeros));
    let no_net = ["--set", "glassy.refraction=~"];
    let from_map = digest(&[&no_net[..], &["--set", &set]].concat());
    let from_rule = digest(
        &[
            &no_net[..],
            &["--set", "glassy.thickness=0", "--set", "glassy.gap=0"],
        ]
        .concat(),
    );
    let from_network = digest(&[]);
    assert_eq!(from_map, from_rule);
    // The same map from a stage (where a refraction-length network's
    // output comes in): an `image` stage reading the file.
    let with_stage = work.join("glass-with-map.yaml");
    let yaml = std::fs::read_to_string(&glass_yaml).unwrap()
        + "  dists:\n    kind: image\n    path: zeros.exr\n";
    std::fs::write(&with_stage, yaml).unwrap();
    let from_stage = digest_of(&with_stage, &["--set", "glassy.refraction=dists"]);
    assert_eq!(from_stage, from_map);
    assert_ne!(
        from_map, from_network,
        "the network gives the region thickness"
    );
    // A refraction map must match the image.
    let bad = work.join("small.exr");
    io::write_exr_rgb(&bad, &matflow_scene::RgbImage::new(8, 8, glam::Vec3::ZERO)).unwrap();
    let set = format!("glassy.refraction_map={}", s(&bad));
    let (out, _) = run(&["--set", &set, "--set", "glassy.refraction=~"]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("refraction map is 8x8"),
        "{}",
        text(&out)
    );
    let _ = std::fs::remove_dir_all(&work);
}
