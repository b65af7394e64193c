//! Dataset jobs over the binary: the same spec gives byte-identical shards
//! in one process or split over three (on one thread or two), a job killed
//! with SIGKILL resumes without recomputing a finished sample, the shards
//! open with Python's `tarfile` and the `webdataset` loader with the
//! manifest's BLAKE3 digests (Python's own `blake3`), `merge` finds
//! damage, and bad specs get errors with a line and column.

mod support;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};
use support::{matflow, s, scratch};

/// `matflow dataset SPEC --out OUT --cache CACHE --quiet EXTRA…` on
/// `threads` threads.
fn generate(spec: &Path, out: &Path, cache: &Path, extra: &[&str], threads: usize) -> Output {
    let mut args = vec![
        "dataset",
        s(spec),
        "--out",
        s(out),
        "--cache",
        s(cache),
        "--quiet",
    ];
    args.extend_from_slice(extra);
    matflow(&args, Some(threads))
}

fn text(o: &Output) -> String {
    format!(
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A small refraction dataset spec: `samples` at 32², 4 spp.
fn spec(dir: &Path, samples: u64, shard_size: u64, spp: u64) -> PathBuf {
    let f = dir.join("spec.yaml");
    std::fs::write(
        &f,
        format!(
            "dataset:\n  name: tiny\n  generator: refraction\n  samples: {samples}\n  seed: 7\n  \
             shard_size: {shard_size}\n  params:\n    size: 32\n    spp: {spp}\n    \
             procedural_envmaps: 4\n    envmap_width: 64\n"
        ),
    )
    .unwrap();
    f
}

/// Every file of a folder: name → bytes.
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect()
}

fn report(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

#[test]
fn one_process_or_three_on_one_thread_or_two_give_the_same_bytes() {
    let w = scratch("dataset", "split");
    let f = spec(&w, 8, 3, 4);
    // One process, one thread.
    let (out1, cache1) = (w.join("one"), w.join("cache1"));
    let o = generate(&f, &out1, &cache1, &[], 1);
    assert!(o.status.success(), "{}", text(&o));
    // Three processes at once sharing one store, two threads each.
    let (out3, cache3) = (w.join("three"), w.join("cache3"));
    let kids: Vec<_> = (0..3)
        .map(|i| {
            Command::new(env!("CARGO_BIN_EXE_matflow"))
                .args([
                    "dataset",
                    s(&f),
                    "--out",
                    s(&out3),
                    "--cache",
                    s(&cache3),
                    "--quiet",
                    "--shards",
                    "3",
                    "--shard",
                    &i.to_string(),
                ])
                .env("RAYON_NUM_THREADS", "2")
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for k in kids {
        let o = k.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", text(&o));
    }
    // The three processes leave the shards; merging checks and indexes
    // them (one process that wrote every shard merged them already).
    assert!(!out3.join("manifest.jsonl").exists());
    let o = matflow(&["dataset", "merge", s(&out3)], Some(1));
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("8 samples in 3 shards"), "{}", text(&o));
    let (a, b) = (files(&out1), files(&out3));
    let names: Vec<&String> = a.keys().collect();
    assert_eq!(
        names,
        [
            "dataset.json",
            "index.json",
            "manifest.jsonl",
            "tiny-000000.jsonl",
            "tiny-000000.tar",
            "tiny-000001.jsonl",
            "tiny-000001.tar",
            "tiny-000002.jsonl",
            "tiny-000002.tar"
        ]
    );
    for (n, bytes) in &a {
        assert!(
            b.get(n) == Some(bytes),
            "{n} differs between 1 and 3 processes"
        );
    }
    assert_eq!(a.len(), b.len());
    // A second run finds every sample cached and rewrites nothing.
    let rep = w.join("again.json");
    let o = generate(&f, &out1, &cache1, &["--report", s(&rep)], 2);
    assert!(o.status.success(), "{}", text(&o));
    let r = report(&rep);
    assert_eq!(
        (r["stages_executed"].as_u64(), r["stages_cached"].as_u64()),
        (Some(0), Some(16))
    );
    // More samples keep the first ones: only the new samples' stages run.
    let o = generate(
        &f,
        &w.join("more"),
        &cache1,
        &["--set", "dataset.samples=10", "--report", s(&rep)],
        2,
    );
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(report(&rep)["stages_executed"].as_u64(), Some(4));
    assert_eq!(
        files(&w.join("more"))["tiny-000000.tar"],
        a["tiny-000000.tar"],
        "a shard of the first samples changed"
    );
    // A render setting re-runs the renders, not the labels.
    let o = generate(
        &f,
        &w.join("spp"),
        &cache1,
        &["--set", "dataset.params.spp=2", "--report", s(&rep)],
        2,
    );
    assert!(o.status.success(), "{}", text(&o));
    let r = report(&rep);
    let executed: Vec<&str> = r["run"]["stages"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|s| s["status"] == "executed")
        .map(|s| s["kind"].as_str().unwrap())
        .collect();
    assert_eq!(executed.len(), 8);
    assert!(
        executed.iter().all(|k| *k == "refraction_render"),
        "{executed:?}"
    );
    let _ = std::fs::remove_dir_all(&w);
}

#[test]
fn a_killed_job_resumes_with_identical_bytes_and_no_recomputation() {
    let w = scratch("dataset", "kill");
    let f = spec(&w, 24, 4, 48);
    // The answer, from a run never interrupted.
    let want = w.join("want");
    let o = generate(&f, &want, &w.join("c0"), &[], 2);
    assert!(o.status.success(), "{}", text(&o));
    // Kill a run once a few stages are cached.
    let (out, cache) = (w.join("out"), w.join("c1"));
    let mut kid = Command::new(env!("CARGO_BIN_EXE_matflow"))
        .args([
            "dataset",
            s(&f),
            "--out",
            s(&out),
            "--cache",
            s(&cache),
            "--quiet",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let actions = |c: &Path| -> usize {
        walk(&c.join("actions"))
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == "json"))
            .count()
    };
    let t0 = Instant::now();
    while actions(&cache) < 6 && t0.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(5));
    }
    kid.kill().unwrap(); // SIGKILL
    kid.wait().unwrap();
    let finished = actions(&cache);
    assert!(
        (6..48).contains(&finished),
        "{finished} stages finished before the kill: make the job longer"
    );
    // Shards are written as their samples finish, whole or not at all:
    // whatever the killed run left is already the final bytes.
    let want_files = files(&want);
    if out.exists() {
        for (name, bytes) in files(&out) {
            if name.ends_with(".tar") || name.ends_with(".jsonl") {
                assert!(
                    want_files.get(&name) == Some(&bytes),
                    "{name} left half-written"
                );
            }
        }
    }
    let rep = w.join("resume.json");
    let o = generate(&f, &out, &cache, &["--report", s(&rep)], 2);
    assert!(o.status.success(), "{}", text(&o));
    let r = report(&rep);
    assert_eq!(
        (r["stages_cached"].as_u64(), r["stages_executed"].as_u64()),
        (Some(finished as u64), Some(48 - finished as u64)),
        "the resumed run recomputed a finished stage"
    );
    assert_eq!(files(&out), want_files);
    let _ = std::fs::remove_dir_all(&w);
}

fn walk(d: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Ok(rd) = std::fs::read_dir(d) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
    }
    out
}

/// Python's `tarfile`, `webdataset` and `blake3` read the shards: member
/// names, every member's digest against the manifest, the arrays' shapes
/// and ranges.
#[test]
fn python_reads_the_shards_and_the_manifest_digests_match() {
    let w = scratch("dataset", "python");
    let f = spec(&w, 5, 2, 4);
    let out = w.join("out");
    let o = generate(&f, &out, &w.join("c"), &[], 2);
    assert!(o.status.success(), "{}", text(&o));
    let script = r#"
import io, json, sys, tarfile
import blake3, numpy as np, webdataset as wds
out = sys.argv[1]
desc = json.load(open(f"{out}/dataset.json"))
manifest = [json.loads(l) for l in open(f"{out}/manifest.jsonl")]
assert len(manifest) == desc["samples"] == 5, len(manifest)
by_key = {m["key"]: m for m in manifest}
seen = 0
for k in range(desc["shards"]):
    with tarfile.open(f"{out}/tiny-{k:06d}.tar") as t:
        for m in t.getmembers():
            assert m.isfile() and m.mode == 0o644 and m.mtime == 0, m.name
            key, member = m.name.split(".", 1)
            data = t.extractfile(m).read()
            want = by_key[key]["members"][member]
            assert blake3.blake3(data).hexdigest() == want["blake3"], m.name
            assert len(data) == want["bytes"]
            seen += 1
assert seen == 5 * len(desc["members"]), seen
urls = f"{out}/" + desc["shard_pattern"]
n = 0
for s in wds.WebDataset(urls, shardshuffle=False).decode("rgb8"):
    L, d1, mask = s["length.npy"], s["d1.npy"], s["mask.png"]
    assert L.shape == (32, 32) and L.dtype == np.float16, (L.shape, L.dtype)
    assert s["normal.npy"].shape == (32, 32, 3)
    assert 0.0 <= L.min() and L.max() <= 1.0
    inside = mask[..., 0] > 127
    assert inside.any() and (L[~inside] == 0).all() and (d1[~inside] == 0).all()
    assert s["image.png"].shape == (32, 32, 3)
    assert s["render.json"]["spp"] == 4 and "object" in s["meta.json"]
    n += 1
assert n == 5, n
print("ok", seen)
"#;
    let o = Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(&out)
        .output()
        .expect("python3");
    assert!(o.status.success(), "{}", text(&o));
    // Damage one byte of a member: merge names the member and writes nothing.
    std::fs::remove_file(out.join("manifest.jsonl")).unwrap();
    let tar = out.join("tiny-000001.tar");
    let mut b = std::fs::read(&tar).unwrap();
    let at = b.len() - 1024 - 100;
    b[at] ^= 0xff;
    std::fs::write(&tar, &b).unwrap();
    let o = matflow(&["dataset", "merge", s(&out)], Some(1));
    assert!(!o.status.success());
    assert!(
        text(&o).contains("tiny-000001.tar") && text(&o).contains("BLAKE3"),
        "{}",
        text(&o)
    );
    assert!(!out.join("manifest.jsonl").exists());
    // A missing shard is named too.
    std::fs::remove_file(out.join("tiny-000002.tar")).unwrap();
    let o = matflow(&["dataset", "merge", s(&out)], Some(1));
    assert!(text(&o).contains("tiny-000002.tar"), "{}", text(&o));
    let _ = std::fs::remove_dir_all(&w);
}

#[test]
fn bad_specs_are_located_and_nothing_runs() {
    let w = scratch("dataset", "bad");
    let cases: &[(&str, &str)] = &[
        (
            "dataset:\n  generator: refraction\n  samples: 0\n",
            "3:12: dataset `samples`: expected an integer in [1,",
        ),
        (
            "dataset:\n  generator: lenses\n  samples: 3\n",
            "2:14: dataset: unknown generator `lenses` (one of: refraction, rooms)",
        ),
        (
            "dataset:\n  generator: refraction\n  samples: 3\n  params:\n    size: 4\n",
            "5:11: dataset `params`: field `size`: expected an integer in [8, 4096], got 4",
        ),
        (
            "dataset:\n  generator: refraction\n  samples: 3\n  params:\n    objects: [{builtin: teapot}]\n",
            "5:25: dataset `params`.objects[0]: field `builtin`: expected one of cup,",
        ),
        (
            "dataset:\n  generator: refraction\n  samples: 3\n  params:\n    envmaps: [{file: nowhere.hdr}]\n",
            "nowhere.hdr",
        ),
        (
            "dataset:\n  generator: refraction\n  samples: 3\n  seeds: 4\n",
            "4:3: dataset: unknown key `seeds`",
        ),
        (
            "dataset:\n  generator: refraction\n  samples: 3\n  params:\n    elevation: [50, 10]\n",
            "`elevation` [50, 10]",
        ),
    ];
    for (k, (yaml, want)) in cases.iter().enumerate() {
        let f = w.join(format!("bad{k}.yaml"));
        std::fs::write(&f, yaml).unwrap();
        let out = w.join(format!("out{k}"));
        let o = matflow(
            &[
                "dataset",
                s(&f),
                "--out",
                s(&out),
                "--cache",
                s(&w.join("c")),
            ],
            Some(1),
        );
        assert!(!o.status.success(), "case {k} ran");
        assert!(text(&o).contains(want), "case {k}: {}", text(&o));
        assert!(!out.exists(), "case {k} wrote {}", out.display());
    }
    // An output folder that holds the spec is refused.
    let f = spec(&w, 2, 1, 1);
    let o = matflow(
        &["dataset", s(&f), "--out", s(&w), "--cache", s(&w.join("c"))],
        Some(1),
    );
    assert!(text(&o).contains("holds the dataset spec"), "{}", text(&o));
    let _ = std::fs::remove_dir_all(&w);
}

/// A `rooms` sample unpacks into a reference bundle: `matflow render`
/// re-renders it from its depth and true materials, close to the
/// photograph (the depth mesh lacks what the camera does not see, so not
/// equal).
#[test]
fn a_rooms_sample_unpacks_into_a_bundle_that_renders() {
    let w = scratch("dataset", "rooms");
    let f = w.join("rooms.yaml");
    std::fs::write(
        &f,
        "dataset:\n  generator: rooms\n  samples: 2\n  seed: 5\n  params: {size: 32, spp: 16}\n",
    )
    .unwrap();
    let out = w.join("out");
    let o = generate(&f, &out, &w.join("c"), &[], 2);
    assert!(o.status.success(), "{}", text(&o));
    let b = w.join("bundle");
    let o = matflow(
        &["dataset", "unpack", s(&out), "s00000001", "--to", s(&b)],
        Some(1),
    );
    assert!(o.status.success(), "{}", text(&o));
    for f in [
        "gt_image.exr",
        "depth.exr",
        "mesh_mask.png",
        "ground_truth/albedo.exr",
        "ground_truth/roughness.exr",
        "ground_truth/metallic.exr",
        "ground_truth/normal.exr",
        "ground_truth/envmap.hdr",
    ] {
        assert!(b.join(f).is_file(), "{f} missing");
    }
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&b),
            "--materials",
            "ground_truth",
            "--spp",
            "16",
            // The rooms' geometry is whole and mostly open (no ceiling
            // three times in four, missing walls): the depth mesh alone
            // renders it closer than a room closed by assumption.
            "--complete",
            "none",
            "--out",
            s(&w.join("re.exr")),
            "--compare",
            s(&b.join("gt_image.exr")),
        ],
        Some(2),
    );
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    let psnr: f64 = t
        .split("gt_image.exr: ")
        .nth(1)
        .and_then(|r| r.split(" dB").next())
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no PSNR in {t}"));
    assert!(psnr > 12.0, "{psnr} dB");
    // A key that is not there is named.
    let o = matflow(
        &["dataset", "unpack", s(&out), "s00000009", "--to", s(&b)],
        Some(1),
    );
    assert!(text(&o).contains("no sample `s00000009`"), "{}", text(&o));
    let _ = std::fs::remove_dir_all(&w);
}

/// The `refraction_length` node over the binary: the bundled network on
/// the tract backend and on onnxruntime (the Python wheel's library,
/// loaded at run time) gives the same distances to within 1e-4 scene
/// units; a missing, corrupt or wrong-shaped model is an error naming the
/// file and what was expected.
#[test]
fn refraction_length_runs_on_both_backends_and_names_bad_models() {
    let w = scratch("dataset", "onnx");
    let p = w.join("lengths.yaml");
    std::fs::write(
        &p,
        "stages:\n  scene:\n    kind: synthetic_scene\n    size: 64\n    spp: 4\n  \
         lengths:\n    kind: refraction_length\n    scene: scene\n    \
         mask_rect: [20, 20, 44, 44]\noutputs: [lengths]\n",
    )
    .unwrap();
    let cache = w.join("cache");
    let run = |extra: &[&str]| -> (Output, Option<serde_json::Value>) {
        let rep = w.join("report.json");
        let _ = std::fs::remove_file(&rep);
        let mut args = vec![
            "run",
            s(&p),
            "--quiet",
            "--cache",
            s(&cache),
            "--report",
            s(&rep),
        ];
        args.extend_from_slice(extra);
        let o = matflow(&args, Some(2));
        let r = std::fs::read(&rep)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        (o, r)
    };
    let distances = |r: &serde_json::Value| -> Vec<f32> {
        let hex = r["stages"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["name"] == "lengths")
            .unwrap()["outputs"]["distances"]
            .as_str()
            .unwrap()
            .to_string();
        let blob = std::fs::read(cache.join("blobs").join(&hex[..2]).join(&hex[2..])).unwrap();
        let img = matflow_nodes::artifact::Artifact::decode(&blob, "image")
            .unwrap()
            .rgb("image")
            .unwrap();
        img.data.iter().flat_map(|v| v.to_array()).collect()
    };
    let (o, r) = run(&[]);
    assert!(o.status.success(), "{}", text(&o));
    let tract = distances(&r.unwrap());
    assert!(tract.iter().any(|&v| v > 0.0), "the network saw no object");
    let (o, r) = run(&["--set", "lengths.backend=onnxruntime"]);
    assert!(
        o.status.success(),
        "the onnxruntime backend needs `pip install onnxruntime`: {}",
        text(&o)
    );
    let ort = distances(&r.unwrap());
    let worst = tract
        .iter()
        .zip(&ort)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-4, "tract and onnxruntime differ by {worst}");
    // Bad models, named.
    let corrupt = w.join("corrupt.onnx");
    std::fs::write(&corrupt, b"\x08\x07garbage").unwrap();
    let identity =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/identity_3x8x8.onnx");
    let cases = [
        (w.join("missing.onnx"), "missing.onnx".to_string()),
        (
            corrupt.clone(),
            format!(
                "{}: not an ONNX model the tract backend can load",
                corrupt.display()
            ),
        ),
        (
            identity.clone(),
            "expected one input: f32 [N, 8, 64, 64], the model has Float32 [N, 3, 8, 8]".into(),
        ),
    ];
    for (model, want) in cases {
        let set = format!("lengths.model={}", s(&model));
        let (o, _) = run(&["--set", &set]);
        assert!(!o.status.success(), "{} was accepted", model.display());
        assert!(
            text(&o).contains(&want),
            "{}: {}",
            model.display(),
            text(&o)
        );
    }
    let _ = std::fs::remove_dir_all(&w);
}

/// A user's mesh folder and HDR file join the draw: every sample's object
/// is one of the folder's meshes (labelled as the spec says) and its
/// lighting the file; the labels see the mesh.
#[test]
fn user_meshes_and_envmap_files_join_the_draw() {
    let w = scratch("dataset", "user");
    let meshes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pipelines/meshes");
    let hdr = w.join("sky.hdr");
    matflow_scene::io::write_hdr(&hdr, &matflow_procgen::synthetic::procedural_sky(4, 64, 32))
        .unwrap();
    let f = w.join("user.yaml");
    std::fs::write(
        &f,
        format!(
            "dataset:\n  generator: refraction\n  samples: 6\n  seed: 3\n  params:\n    \
             size: 24\n    spp: 2\n    procedural_envmaps: 0\n    \
             objects: [{{file: {}, hollow: true}}]\n    envmaps: [{{file: sky.hdr}}]\n",
            s(&meshes)
        ),
    )
    .unwrap();
    let out = w.join("out");
    let o = generate(&f, &out, &w.join("c"), &[], 2);
    assert!(o.status.success(), "{}", text(&o));
    let manifest = std::fs::read_to_string(out.join("manifest.jsonl")).unwrap();
    let mut seen = std::collections::BTreeSet::new();
    for line in manifest.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        let p = &v["params"];
        assert_eq!(p["hollow"], true);
        assert!(p["envmap"].as_str().unwrap().ends_with("sky.hdr"), "{p}");
        seen.insert(p["object"].as_str().unwrap().to_string());
    }
    let names = ["cube", "jug", "sphere", "torus"];
    assert!(seen.iter().all(|o| names.contains(&o.as_str())), "{seen:?}");
    let desc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("dataset.json")).unwrap()).unwrap();
    assert_eq!(desc["header"]["objects"].as_array().unwrap().len(), 4);
    // A folder without meshes is named before anything runs.
    let empty = w.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let bad = w.join("bad.yaml");
    std::fs::write(
        &bad,
        format!(
            "dataset:\n  generator: refraction\n  samples: 2\n  params:\n    objects: [{{file: {}}}]\n",
            s(&empty)
        ),
    )
    .unwrap();
    let o = matflow(
        &[
            "dataset",
            s(&bad),
            "--out",
            s(&w.join("o2")),
            "--cache",
            s(&w.join("c")),
        ],
        Some(1),
    );
    assert!(
        text(&o).contains("holds no .obj or .ply files"),
        "{}",
        text(&o)
    );
    let _ = std::fs::remove_dir_all(&w);
}

/// A pipeline may carry a `dataset:` section beside its stages: `matflow
/// run` runs both, the stages' outputs and the dataset's samples in one
/// engine run.
#[test]
fn a_pipeline_with_a_dataset_section_runs_both() {
    let w = scratch("dataset", "section");
    let f = w.join("both.yaml");
    std::fs::write(
        &f,
        "stages:\n  scene:\n    kind: synthetic_scene\n    size: 16\n    spp: 1\n\
         outputs: [scene]\n\
         dataset:\n  name: extra\n  generator: refraction\n  samples: 2\n  out: data\n  \
         params: {size: 16, spp: 1, procedural_envmaps: 1}\n",
    )
    .unwrap();
    let rep = w.join("r.json");
    let o = matflow(
        &[
            "run",
            s(&f),
            "--quiet",
            "--cache",
            s(&w.join("c")),
            "--report",
            s(&rep),
        ],
        Some(2),
    );
    assert!(o.status.success(), "{}", text(&o));
    let r = report(&rep);
    let stages: Vec<&str> = r["run"]["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert!(stages.contains(&"scene"), "{stages:?}");
    assert_eq!(stages.len(), 1 + 2 * 2, "{stages:?}");
    assert!(w.join("data/extra-000000.tar").is_file());
    assert!(w.join("data/manifest.jsonl").is_file());
    let _ = std::fs::remove_dir_all(&w);
}
