//! `matflow run`: the pipeline engine end to end, over the binary.
//!
//! The demo pipeline runs at 64² with small budgets so the suite stays
//! quick; what is checked is what the engine promises: only what changed
//! re-runs, identical bytes whatever the thread count, corruption is a
//! cache miss, and bad input is reported with file, line and column before
//! any work starts.

mod support;
use support::{matflow, repo, s};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;
use support::SMALL;

use serde_json::Value;

struct Run {
    out: Output,
    report: Value,
}

fn run_demo(cache: &Path, work: &Path, extra: &[&str], threads: Option<usize>) -> Run {
    let report = work.join("report.json");
    let demo = repo().join("pipelines/demo.yaml");
    let edited = work.join("edited.exr");
    let relit = work.join("relit.exr");
    let set_e = format!("edited.output={}", s(&edited));
    let set_r = format!("relit.output={}", s(&relit));
    let mut args = vec![
        "run",
        s(&demo),
        "--quiet",
        "--cache",
        s(cache),
        "--report",
        s(&report),
        "--set",
        &set_e,
        "--set",
        &set_r,
    ];
    args.extend_from_slice(SMALL);
    args.extend_from_slice(extra);
    let out = matflow(&args, threads);
    assert!(
        out.status.success(),
        "matflow run failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let report = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    Run { out, report }
}

/// Stage name → one field of its report entry.
fn by_stage(r: &Value, field: &str) -> BTreeMap<String, Value> {
    r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["name"].as_str().unwrap().to_string(), s[field].clone()))
        .collect()
}

fn statuses(r: &Value) -> BTreeMap<String, String> {
    by_stage(r, "status")
        .into_iter()
        .map(|(k, v)| (k, v.as_str().unwrap().to_string()))
        .collect()
}

fn outputs(r: &Value) -> BTreeMap<String, Value> {
    by_stage(r, "outputs")
}

fn with(status: &BTreeMap<String, String>, want: &str) -> Vec<String> {
    status
        .iter()
        .filter(|(_, v)| v.as_str() == want)
        .map(|(k, _)| k.clone())
        .collect()
}

#[test]
fn re_edit_reruns_only_the_edit_and_its_render_then_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let first = run_demo(&cache, dir.path(), &[], None);
    let st = statuses(&first.report);
    assert_eq!(with(&st, "executed").len(), st.len(), "{st:?}");
    for key in ["pipeline", "seconds", "stages"] {
        assert!(first.report.get(key).is_some(), "report lacks {key}");
    }
    let s0 = &first.report["stages"][0];
    for key in ["name", "kind", "status", "seconds", "key", "outputs"] {
        assert!(s0.get(key).is_some(), "stage report lacks {key}");
    }
    assert!(dir.path().join("edited.exr").is_file());
    assert!(dir.path().join("relit.png").is_file());
    // A file written anew is a new inode (written aside, then renamed).
    let inode = |f: &str| {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(dir.path().join(f)).unwrap().ino()
    };
    let relit_before = (inode("relit.exr"), inode("relit.png"));
    let edited_before = inode("edited.exr");

    let second = run_demo(&cache, dir.path(), &["--set", "shiny.roughness=0.4"], None);
    let st = statuses(&second.report);
    assert_eq!(with(&st, "executed"), vec!["edited", "shiny"], "{st:?}");
    assert_eq!(
        with(&st, "cached"),
        vec![
            "base",
            "evening",
            "lighting",
            "mesh",
            "recovered",
            "relit",
            "scene"
        ]
    );
    let (o1, o2) = (outputs(&first.report), outputs(&second.report));
    assert_ne!(o1["edited"], o2["edited"]);
    assert_eq!(o1["relit"], o2["relit"]);

    let third = run_demo(&cache, dir.path(), &["--set", "shiny.roughness=0.4"], None);
    let st = statuses(&third.report);
    assert!(with(&st, "executed").is_empty(), "{st:?}");
    assert_eq!(outputs(&third.report), o2);
    let table = String::from_utf8_lossy(&third.out.stdout);
    assert!(table.contains("0 executed"), "{table}");

    // Files already holding what the stage would write are left alone;
    // the edit's image is written again, and so is a file changed by hand.
    assert_eq!((inode("relit.exr"), inode("relit.png")), relit_before);
    assert_ne!(inode("edited.exr"), edited_before);
    let png = std::fs::read(dir.path().join("relit.png")).unwrap();
    std::fs::write(dir.path().join("relit.png"), b"scribbled over").unwrap();
    run_demo(&cache, dir.path(), &["--set", "shiny.roughness=0.4"], None);
    assert_eq!(std::fs::read(dir.path().join("relit.png")).unwrap(), png);
    assert_eq!(inode("relit.exr"), relit_before.0);
}

#[test]
fn outputs_are_bit_identical_across_runs_and_thread_counts() {
    let dir = tempfile::tempdir().unwrap();
    let a = run_demo(&dir.path().join("c1"), dir.path(), &[], Some(1));
    let b = run_demo(&dir.path().join("c2"), dir.path(), &[], Some(2));
    assert_eq!(outputs(&a.report), outputs(&b.report));
    let keys = |r: &Value| -> Vec<Value> {
        r["stages"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["key"].clone())
            .collect()
    };
    assert_eq!(keys(&a.report), keys(&b.report));
}

fn blob_path(cache: &Path, hex: &str) -> PathBuf {
    cache.join("blobs").join(&hex[..2]).join(&hex[2..])
}

#[test]
fn corrupt_blobs_and_truncated_actions_recompute_to_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let first = run_demo(&cache, dir.path(), &[], None);
    let o1 = outputs(&first.report);
    // Flip one byte of the mesh blob.
    let mesh_hex = o1["mesh"]["mesh"].as_str().unwrap().to_string();
    let p = blob_path(&cache, &mesh_hex);
    let mut bytes = std::fs::read(&p).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x40;
    std::fs::write(&p, bytes).unwrap();
    let second = run_demo(&cache, dir.path(), &[], None);
    let st = statuses(&second.report);
    assert_eq!(st["mesh"], "executed", "{st:?}");
    assert_eq!(st["scene"], "cached");
    assert_eq!(st["recovered"], "cached", "early cutoff: same mesh bytes");
    assert_eq!(outputs(&second.report), o1);
    // Truncate the edit's action entry as a crash mid-write would.
    let key = second.report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "shiny")
        .unwrap()["key"]
        .as_str()
        .unwrap()
        .to_string();
    let action = cache
        .join("actions")
        .join(&key[..2])
        .join(format!("{}.json", &key[2..]));
    let text = std::fs::read(&action).unwrap();
    std::fs::write(&action, &text[..text.len() / 3]).unwrap();
    let third = run_demo(&cache, dir.path(), &[], None);
    let st = statuses(&third.report);
    assert_eq!(st["shiny"], "executed", "{st:?}");
    assert_eq!(st["edited"], "cached", "same edit bytes: early cutoff");
    assert_eq!(outputs(&third.report), o1);
    // verify finds everything intact now.
    let v = matflow(&["cache", "verify", "--cache", s(&cache)], None);
    assert!(v.status.success());
    assert!(String::from_utf8_lossy(&v.stdout).contains(" 0 corrupt"));
}

/// Runs a pipeline text that must be rejected; returns stderr. The cache
/// folder must not be created.
fn rejected(yaml: &str, extra: &[&str]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("p.yaml");
    std::fs::write(&f, yaml).unwrap();
    let cache = dir.path().join("cache");
    let mut args = vec!["run", s(&f), "--quiet", "--cache", s(&cache)];
    args.extend_from_slice(extra);
    let out = matflow(&args, None);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success(), "accepted:\n{yaml}");
    assert!(!cache.exists(), "the cache was touched for a bad pipeline");
    assert!(err.contains("p.yaml"), "the message names the file: {err}");
    err
}

const GOOD: &str = "outputs: [r]\nstages:\n  sc:\n    kind: synthetic_scene\n    size: 32\n  m:\n    kind: mesh\n    scene: sc\n  r:\n    kind: render\n    mesh: m\n    materials: sc\n    envmap: sc\n";

#[test]
fn bad_pipelines_are_rejected_with_their_location_and_no_cache_writes() {
    // (edit of the good pipeline, what the message must contain)
    let cases: &[(&str, &str, &[&str])] = &[
        (
            "    size: 32",
            "    size: 32\n    sise: 3",
            &[":6:5:", "unknown parameter `sise`"],
        ),
        (
            "    size: 32",
            "    size: 32\n    size: 64",
            &[":6:5:", "`size` is given twice"],
        ),
        ("size: 32", "size: big", &[":5:11:", "expected an integer"]),
        ("size: 32", "size: 100000", &["in [16, 4096]"]),
        (
            "scene: sc",
            "scene: nowhere",
            &[":8:12:", "no stage `nowhere`"],
        ),
        ("    mesh: m\n", "", &["missing parameter `mesh`"]),
        ("envmap: sc", "envmap: m", &["no output of type envmap"]),
        (
            "kind: mesh",
            "kind: meshh",
            &[":7:11:", "unknown kind `meshh`"],
        ),
    ];
    for (from, to, want) in cases {
        let e = rejected(&GOOD.replace(from, to), &[]);
        for w in *want {
            assert!(e.contains(w), "{from:?} -> {to:?}: {e}");
        }
    }
    // YAML syntax.
    let e = rejected("outputs: [r\nstages: {}\n", &[]);
    assert!(e.contains("p.yaml:"), "{e}");
    // A bad --set.
    let e = rejected(GOOD, &["--set", "sc.size=abc"]);
    assert!(e.contains("--set sc.size"), "{e}");
    let e = rejected(GOOD, &["--set", "zz.size=3"]);
    assert!(e.contains("no stage `zz`"), "{e}");
}

#[test]
fn cycles_are_named() {
    let cyc = "outputs: [a]\nstages:\n  a:\n    kind: relight\n    source: b\n  b:\n    kind: relight\n    source: a\n";
    let e = rejected(cyc, &[]);
    assert!(
        e.contains("cycle: a -> b -> a") || e.contains("cycle: b -> a -> b"),
        "{e}"
    );
}

#[test]
fn unreadable_and_corrupt_inputs_are_named_before_work_starts() {
    let e = rejected(
        "outputs: [i]\nstages:\n  i:\n    kind: image\n    path: missing.exr\n",
        &[],
    );
    assert!(e.contains("missing.exr"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.exr");
    std::fs::write(&bad, b"not an exr at all").unwrap();
    let e = rejected(
        &format!(
            "outputs: [i]\nstages:\n  i:\n    kind: image\n    path: {}\n",
            s(&bad)
        ),
        &[],
    );
    assert!(e.contains("bad.exr"), "{e}");
}

#[test]
fn only_what_the_outputs_need_runs() {
    // The material optimisation is defined but not needed: relighting the
    // predicted materials does not run it.
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("relight.yaml");
    std::fs::write(
        &f,
        "outputs: [r]\nstages:\n  sc: {kind: synthetic_scene, size: 32, spp: 4}\n  m: {kind: mesh, scene: sc}\n  \
         opt: {kind: material_opt, scene: sc, mesh: m, budget_seconds: 1}\n  \
         sky: {kind: relight, source: sc.truth_envmap, rotation: 90}\n  \
         r: {kind: render, mesh: m, materials: sc, envmap: sky, spp: 4}\n",
    )
    .unwrap();
    let report = dir.path().join("r.json");
    let out = matflow(
        &[
            "run",
            s(&f),
            "--quiet",
            "--cache",
            s(&dir.path().join("c")),
            "--report",
            s(&report),
        ],
        None,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let st = statuses(&r);
    assert_eq!(st["opt"], "skipped");
    assert_eq!(with(&st, "executed"), vec!["m", "r", "sc", "sky"]);
}

/// The reference-scene pipeline, pointed at the stored scenes with
/// `--set` (small budget and sample counts: this checks the wiring, the
/// benchmark the numbers). Vacuous only when ../shared is absent.
#[test]
fn reference_pipeline_runs_on_the_stored_scenes() {
    let data = repo().join("../shared/data/materialist/jinjya");
    if !data.is_dir() {
        eprintln!("skipping: {} not found", data.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let report = dir.path().join("r.json");
    let pipeline = repo().join("pipelines/reference.yaml");
    let cache = dir.path().join("c");
    let sets = [
        format!("bundle.path={}", s(&data)),
        "recovered.budget_seconds=2".to_string(),
        "rerender.spp=2".to_string(),
        "relit.spp=2".to_string(),
        format!("rerender.output={}", s(&dir.path().join("re.exr"))),
        format!("relit.output={}", s(&dir.path().join("relit.exr"))),
    ];
    let mut args = vec![
        "run",
        s(&pipeline),
        "--quiet",
        "--cache",
        s(&cache),
        "--report",
        s(&report),
    ];
    for x in &sets {
        args.push("--set");
        args.push(x);
    }
    let out = matflow(&args, None);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert!(with(&statuses(&r), "executed").len() == 6, "{r}");
    assert!(dir.path().join("relit.png").is_file());
}

#[test]
fn cache_commands_list_count_and_collect() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let f = dir.path().join("p.yaml");
    std::fs::write(&f, GOOD.replace("size: 32", "size: 32\n    spp: 2")).unwrap();
    let run = matflow(&["run", s(&f), "--quiet", "--cache", s(&cache)], None);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let ls = matflow(&["cache", "ls", "--cache", s(&cache)], None);
    let text = String::from_utf8_lossy(&ls.stdout);
    assert_eq!(text.lines().count(), 4, "header + 3 actions:\n{text}");
    assert!(text.contains("synthetic_scene") && text.contains("render"));
    // Keeping the pipeline as it is keeps everything...
    let gc = matflow(
        &["cache", "gc", "--cache", s(&cache), "--keep", s(&f)],
        None,
    );
    assert!(String::from_utf8_lossy(&gc.stdout).contains("removed 0 actions"));
    // ...keeping it with another render drops the old render only.
    std::fs::write(
        &f,
        GOOD.replace("size: 32", "size: 32\n    spp: 2") + "    spp: 3\n",
    )
    .unwrap();
    let gc = matflow(
        &["cache", "gc", "--cache", s(&cache), "--keep", s(&f)],
        None,
    );
    assert!(
        String::from_utf8_lossy(&gc.stdout).contains("removed 1 actions, 1 blobs"),
        "{}",
        String::from_utf8_lossy(&gc.stdout)
    );
    let stats = matflow(&["cache", "stats", "--cache", s(&cache)], None);
    assert!(String::from_utf8_lossy(&stats.stdout).contains("2 actions"));
    let none = matflow(&["cache", "gc", "--cache", s(&cache)], None);
    assert!(!none.status.success(), "gc without a policy must refuse");
}
