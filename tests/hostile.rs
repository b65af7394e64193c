//! Hostile input, over the binary: what a stranger's pipeline file, flags
//! or files can make matflow do. Each case must end in a clear error
//! naming the file and the line and column (or the flag), quickly and in
//! bounded memory — never a crash, a hang, or a false success.

mod support;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};
use support::{s, scratch};

/// `matflow args…` under the shell resource limits `limits` (e.g.
/// `ulimit -v N`), and how long it took.
fn matflow_limited(limits: &str, args: &[&str]) -> (Output, Duration) {
    let t = Instant::now();
    let cache = support::fresh_cache();
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!("{limits}; exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_matflow"))
        .args(args)
        .env("MATFLOW_CACHE", &cache)
        .output()
        .expect("run matflow");
    let _ = std::fs::remove_dir_all(&cache);
    (out, t.elapsed())
}

/// `matflow args…` with its address space capped at `mem_mib` (so a
/// blow-up fails inside the cap instead of taking the machine).
fn matflow_capped(mem_mib: u64, args: &[&str]) -> (Output, Duration) {
    matflow_limited(&format!("ulimit -v {}", mem_mib * 1024), args)
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// `matflow args…` capped at 4 GiB.
fn matflow(args: &[&str]) -> Output {
    matflow_capped(4096, args).0
}

/// The arguments of `matflow run FILE --quiet --cache CACHE extra…`.
fn run_args<'a>(file: &'a Path, cache: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["run", file.to_str().unwrap(), "--quiet", "--cache"];
    args.push(cache.to_str().unwrap());
    args.extend_from_slice(extra);
    args
}

/// `matflow run FILE --quiet --cache CACHE extra…`.
fn run(file: &Path, cache: &Path, extra: &[&str]) -> Output {
    matflow(&run_args(file, cache, extra))
}

/// `matflow render` of bundle `b` with its true materials at `spp`,
/// plus `extra`, to `out`.
fn render_bundle(b: &Path, spp: &str, extra: &[&str], out: &Path) -> Output {
    let mut args = vec!["render", "--bundle", b.to_str().unwrap(), "--spp", spp];
    args.extend_from_slice(&["--materials", "ground_truth"]);
    args.extend_from_slice(extra);
    args.extend_from_slice(&["--out", out.to_str().unwrap()]);
    matflow(&args)
}

/// Runs `pipeline` (written to a file) capped at 1 GiB and expects a
/// prompt, clear failure whose message contains `expect`.
fn refused(dir: &Path, name: &str, pipeline: &str, extra: &[&str], expect: &str) -> String {
    let file = dir.join(name);
    std::fs::write(&file, pipeline).unwrap();
    let cache = dir.join("cache");
    let (out, took) = matflow_capped(1024, &run_args(&file, &cache, extra));
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{name}: {err}");
    assert!(err.contains(expect), "{name}: {err}");
    assert!(took < Duration::from_secs(20), "{name}: took {took:?}");
    assert!(
        err.len() < 2000,
        "{name}: the message echoes the input: {} bytes",
        err.len()
    );
    err
}

#[test]
fn yaml_bombs_end_in_a_located_error_at_once_and_in_bounded_memory() {
    let dir = scratch("hostile", "yaml");
    // Billion laughs: 9^11 lists of nine strings if expanded.
    let mut bomb = String::from("a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n");
    for i in 1..12 {
        let refs = vec![format!("*a{}", i - 1); 9].join(", ");
        bomb += &format!("a{i}: &a{i} [{refs}]\n");
    }
    bomb += "stages:\n  x: *a11\n";
    let e = refused(&dir, "bomb.yaml", &bomb, &[], "aliases");
    assert!(e.contains("bomb.yaml:2:10:"), "{e}");

    // 8,000 levels of block nesting (compact sequences) and of flow
    // nesting.
    let deep = format!(
        "stages:\n  x:\n    kind: render\n    spp:\n      {}1\n",
        "- ".repeat(8000)
    );
    let e = refused(&dir, "deep.yaml", &deep, &[], "nested more than 64 deep");
    assert!(e.contains("deep.yaml:5:"), "{e}");
    let flow = format!(
        "stages:\n  x:\n    kind: render\n    spp: {}1{}\n",
        "[".repeat(8000),
        "]".repeat(8000)
    );
    refused(&dir, "flow.yaml", &flow, &[], "nested more than 64 deep");

    // The same through --set, whose message does not echo the value.
    let ok = "stages:\n  x:\n    kind: synthetic_scene\noutputs: [x]\n";
    let set = format!("x.size={}1{}", "[".repeat(8000), "]".repeat(8000));
    let e = refused(
        &dir,
        "ok.yaml",
        ok,
        &["--set", &set],
        "nested more than 64 deep",
    );
    assert!(e.contains("--set"), "{e}");

    // A huge document and a huge list.
    let huge = format!("description: \"{}\"\n", "x".repeat(17 << 20));
    refused(&dir, "huge.yaml", &huge, &[], "a pipeline may have at most");
    let wide = format!(
        "stages:\n  x:\n    kind: render\n    spp: [{}]\n",
        vec!["1"; 1_000_001].join(",")
    );
    let e = refused(&dir, "wide.yaml", &wide, &[], "more than 1000000 entries");
    assert!(e.contains("wide.yaml:4:"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A pipeline that renders a small procedural scene to `output`.
fn render_pipeline(output: &str, spp: u32) -> String {
    format!(
        "stages:\n  scene:\n    kind: synthetic_scene\n    size: 24\n    spp: 2\n  \
         mesh:\n    kind: mesh\n    scene: scene\n  \
         shot:\n    kind: render\n    mesh: mesh\n    materials: scene\n    \
         envmap: scene.truth_envmap\n    spp: {spp}\n    output: {output}\n\
         outputs: [shot]\n"
    )
}

#[test]
fn outputs_may_not_destroy_inputs_or_each_other() {
    let dir = scratch("hostile", "outputs");
    let bundle = synth_bundle(&dir, "bundle");
    // The PNG written beside `p.exr` would be the pipeline file itself.
    let e = refused(
        &dir,
        "p.png",
        &render_pipeline("p.exr", 1),
        &[],
        "would overwrite the pipeline file",
    );
    assert!(e.contains("p.png:"), "{e}");
    // … or an input image.
    let photo = dir.join("photo.png");
    std::fs::copy(bundle.join("gt_image.png"), &photo).unwrap();
    let before = std::fs::read(&photo).unwrap();
    let reads_photo = render_pipeline("photo.exr", 1).replace("outputs: [shot]\n", "")
        + "  photo:\n    kind: image\n    path: photo.png\noutputs: [shot, photo]\n";
    let e = refused(
        &dir,
        "photo.yaml",
        &reads_photo,
        &[],
        "would overwrite stage `photo`'s `path`",
    );
    assert!(e.contains("photo.yaml:"), "{e}");
    assert_eq!(std::fs::read(&photo).unwrap(), before);
    // Two stages writing one file, spelt differently (`..`, a link).
    std::fs::create_dir_all(dir.join("out")).unwrap();
    std::os::unix::fs::symlink(dir.join("out"), dir.join("link")).unwrap();
    let two = render_pipeline("out/a.exr", 1).replace("outputs: [shot]\n", "")
        + "  again:\n    kind: render\n    mesh: mesh\n    materials: scene\n    \
           envmap: scene.truth_envmap\n    output: link/../link/a.exr\n\
           outputs: [shot, again]\n";
    let e = refused(
        &dir,
        "two.yaml",
        &two,
        &[],
        "is also written by stage `shot`",
    );
    assert!(e.contains("two.yaml:") && e.contains("`again`"), "{e}");
    // An output inside a folder the pipeline reads (a bundle).
    let into_bundle = "stages:\n  b:\n    kind: bundle\n    path: bundle\n  \
        mesh:\n    kind: mesh\n    scene: b\n  \
        shot:\n    kind: render\n    mesh: mesh\n    materials: b\n    envmap: b.envmap\n    \
        output: bundle/gt_image.exr\noutputs: [shot]\n";
    refused(
        &dir,
        "bundle.yaml",
        into_bundle,
        &[],
        "a folder the pipeline reads",
    );
    // An EXR-producing stage asked for a .png.
    refused(
        &dir,
        "png.yaml",
        &render_pipeline("x.png", 1),
        &[],
        "must end in .exr",
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cached_run_leaves_output_files_alone_and_a_change_rewrites_them() {
    use std::os::unix::fs::MetadataExt;
    let dir = scratch("hostile", "rewrite");
    let cache = dir.join("cache");
    let run = |spp: u32| {
        let file = dir.join("p.yaml");
        std::fs::write(&file, render_pipeline("out/shot.exr", spp)).unwrap();
        let out = run(&file, &cache, &[]);
        assert!(out.status.success(), "{}", stderr(&out));
        let exr = std::fs::metadata(dir.join("out/shot.exr")).unwrap();
        let png = std::fs::metadata(dir.join("out/shot.png")).unwrap();
        (
            exr.ino(),
            png.ino(),
            std::fs::read(dir.join("out/shot.exr")).unwrap(),
        )
    };
    let first = run(2);
    // Cached: the same files (same inodes: nothing was renamed over them).
    assert_eq!(run(2), first);
    // Changed: new bytes, written through a fresh file.
    let changed = run(3);
    assert_ne!(changed.2, first.2);
    assert_ne!(changed.0, first.0);
    // No temporary file is left beside the outputs.
    let names: Vec<String> = std::fs::read_dir(dir.join("out"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A small synthetic bundle in `dir/name`.
fn synth_bundle(dir: &Path, name: &str) -> PathBuf {
    let b = dir.join(name);
    let out = matflow(&[
        "synth",
        "--out",
        b.to_str().unwrap(),
        "--size",
        "16",
        "--spp",
        "1",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    b
}

#[test]
fn inputs_are_checked_before_any_stage_runs() {
    use matflow_scene::{io, Image};
    let dir = scratch("hostile", "inputs");
    let cache = dir.join("cache");
    let edit = |mask: &str| {
        format!(
            "stages:\n  scene:\n    kind: synthetic_scene\n    size: 24\n    spp: 2\n  \
             shiny:\n    kind: edit\n    materials: scene\n    {mask}\n    roughness: 0.2\n\
             outputs: [shiny]\n"
        )
    };
    // A corrupt mask file: refused at once, before the scene is made.
    std::fs::write(dir.join("mask.png"), b"\x89PNG\r\n\x1a\n garbage").unwrap();
    let e = refused(
        &dir,
        "corrupt.yaml",
        &edit("mask_png: mask.png"),
        &[],
        "mask.png",
    );
    assert!(e.contains("corrupt.yaml:"), "{e}");
    assert!(
        !cache.join("ac").exists() || std::fs::read_dir(cache.join("ac")).unwrap().count() == 0
    );
    // Pixel positions outside the image, known from the scene's size.
    refused(
        &dir,
        "rect.yaml",
        &edit("mask_rect: [30, 0, 40, 10]"),
        &[],
        "outside the 24x24 image",
    );
    refused(
        &dir,
        "seed.yaml",
        &edit("mask_flood: [5, 24]"),
        &[],
        "outside the 24x24 image",
    );
    refused(
        &dir,
        "empty.yaml",
        &edit("mask_rect: [5, 5, 5, 9]"),
        &[],
        "is empty",
    );
    let e = refused(
        &dir,
        "set.yaml",
        &edit("mask_flood: [5, 5]"),
        &[
            "--set",
            "scene.size=16",
            "--set",
            "shiny.mask_flood=[20, 3]",
        ],
        "outside the 16x16 image",
    );
    assert!(e.contains("stage `shiny`"), "{e}");

    // Depth maps no scene can be built from: all zeros, one huge or tiny
    // constant, any constant.
    let b = synth_bundle(&dir, "bundle");
    let good = io::read_exr_gray(&b.join("depth.exr")).unwrap();
    let pipeline =
        "stages:\n  b:\n    kind: bundle\n    path: bundle\n  mesh:\n    kind: mesh\n    \
                    scene: b\noutputs: [mesh]\n";
    for (z, why) in [
        (0.0, "no pixel has a positive depth"),
        (1e30, "within"),
        (1e-30, "within"),
        (2.5, "no spread"),
    ] {
        io::write_exr_gray(&b.join("depth.exr"), &Image::from_fn(16, 16, |_, _| z)).unwrap();
        let e = refused(&dir, "depth.yaml", pipeline, &[], why);
        assert!(
            e.contains("depth.exr") && e.contains("unusable depth"),
            "{e}"
        );
        let out = render_bundle(&b, "1", &[], &dir.join("r.exr"));
        assert_eq!(out.status.code(), Some(1), "depth {z}: {}", stderr(&out));
        assert!(stderr(&out).contains("unusable depth"), "{}", stderr(&out));
    }
    io::write_exr_gray(&b.join("depth.exr"), &good).unwrap();

    // Environment maps: 1×1, negative radiance; EXR accepted wherever HDR is.
    let relight = |file: &str| {
        format!(
            "stages:\n  sky:\n    kind: relight\n    path: {file}\n    exposure: 1\noutputs: [sky]\n"
        )
    };
    let write_env = |name: &str, w: usize, h: usize, v: f32| {
        let img = Image::from_fn(w, h, |x, _| glam::Vec3::splat(if x == 1 { v } else { 1.0 }));
        io::write_exr_rgb(&dir.join(name), &img).unwrap();
    };
    write_env("tiny.exr", 1, 1, 1.0);
    refused(
        &dir,
        "tiny.yaml",
        &relight("tiny.exr"),
        &[],
        "1x1 is out of range",
    );
    write_env("neg.exr", 8, 4, -1.0);
    let e = refused(
        &dir,
        "neg.yaml",
        &relight("neg.exr"),
        &[],
        "negative radiance",
    );
    assert!(e.contains("x=1, y=0"), "{e}");
    write_env("sky.exr", 8, 4, 2.0);
    for envmap in ["sky.exr", "neg.exr"] {
        let env = dir.join(envmap);
        let out = render_bundle(
            &b,
            "1",
            &["--envmap", env.to_str().unwrap()],
            &dir.join("r.exr"),
        );
        if envmap == "sky.exr" {
            assert!(
                out.status.success(),
                "render --envmap takes EXR: {}",
                stderr(&out)
            );
        } else {
            assert!(
                stderr(&out).contains("negative radiance"),
                "{}",
                stderr(&out)
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn runs_estimated_above_an_hour_are_refused_with_the_estimate() {
    let dir = scratch("hostile", "cost");
    // 4096² at 65,536 spp: days of tracing for the scene alone.
    let e = refused(
        &dir,
        "big.yaml",
        &render_pipeline("out/big.exr", 65536),
        &["--set", "scene.size=4096"],
        "--allow-expensive",
    );
    assert!(e.contains("estimated at") && e.contains("`shot`"), "{e}");
    // The same pipeline at test size runs, with or without the flag.
    for extra in [&[][..], &["--allow-expensive"][..]] {
        let file = dir.join("small.yaml");
        std::fs::write(&file, render_pipeline("out/small.exr", 2)).unwrap();
        let out = run(&file, &dir.join("cache"), extra);
        assert!(out.status.success(), "{}", stderr(&out));
    }
    // `matflow render` checks the same way (at the render kind's most
    // samples and depth, on a 128² bundle: about two hours).
    let b = dir.join("bundle");
    let made = matflow(&["synth", "--out", s(&b), "--size", "128", "--spp", "1"]);
    assert!(made.status.success(), "{}", stderr(&made));
    let out = render_bundle(&b, "65536", &["--depth", "64"], &dir.join("r.exr"));
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("--allow-expensive"),
        "{}",
        stderr(&out)
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Runs `render_pipeline` into `cache`; returns the action entries by
/// stage name (path of each entry file).
fn populate(dir: &Path, cache: &Path) -> std::collections::BTreeMap<String, PathBuf> {
    let file = dir.join("p.yaml");
    std::fs::write(&file, render_pipeline("out/p.exr", 2)).unwrap();
    let out = run(&file, cache, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    entries(cache)
}

fn entries(cache: &Path) -> std::collections::BTreeMap<String, PathBuf> {
    let mut m = std::collections::BTreeMap::new();
    for sub in std::fs::read_dir(cache.join("actions")).unwrap() {
        for e in std::fs::read_dir(sub.unwrap().path()).unwrap() {
            let p = e.unwrap().path();
            if let Ok(v) =
                serde_json::from_slice::<serde_json::Value>(&std::fs::read(&p).unwrap_or_default())
            {
                m.insert(v["stage"].as_str().unwrap().to_string(), p);
            }
        }
    }
    m
}

#[test]
fn gc_keep_never_deletes_intact_entries_below_a_damaged_one() {
    let dir = scratch("hostile", "gc");
    let cache = dir.join("cache");
    let e = populate(&dir, &cache);
    assert_eq!(e.len(), 3, "{e:?}");
    // Truncate the first stage's entry.
    let scene = std::fs::read(&e["scene"]).unwrap();
    std::fs::write(&e["scene"], &scene[..scene.len() / 2]).unwrap();
    let p = dir.join("p.yaml");
    let out = matflow(&[
        "cache",
        "gc",
        "--cache",
        cache.to_str().unwrap(),
        "--keep",
        p.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}{}", text, stderr(&out));
    assert!(text.contains("removed 1 actions"), "{text}");
    assert!(text.contains("kept 2 entries"), "{text}");
    let left = entries(&cache);
    assert!(
        left.contains_key("mesh") && left.contains_key("shot"),
        "{left:?}"
    );
    // The next run recomputes only the damaged stage.
    let report = dir.join("r.json");
    let out = run(&p, &cache, &["--report", report.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("r.json")).unwrap()).unwrap();
    let status: Vec<(String, String)> = r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            (
                s["name"].as_str().unwrap().into(),
                s["status"].as_str().unwrap().into(),
            )
        })
        .collect();
    assert_eq!(
        status,
        [
            ("scene", "executed"),
            ("mesh", "cached"),
            ("shot", "cached")
        ]
        .map(|(a, b)| (a.to_string(), b.to_string()))
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_entry_pointing_at_a_blob_of_the_wrong_type_is_a_miss_and_verify_reports_it() {
    let dir = scratch("hostile", "wrongtype");
    let cache = dir.join("cache");
    let e = populate(&dir, &cache);
    // The mesh entry now names the scene's (intact) blob as its mesh.
    let scene: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&e["scene"]).unwrap()).unwrap();
    let mut mesh: serde_json::Value =
        serde_json::from_slice(&std::fs::read(&e["mesh"]).unwrap()).unwrap();
    mesh["outputs"]["mesh"] = scene["outputs"]["scene"].clone();
    std::fs::write(&e["mesh"], serde_json::to_vec(&mesh).unwrap()).unwrap();
    let forged = std::fs::read(&e["mesh"]).unwrap();
    // A run recovers: the mesh is recomputed, the render re-runs or hits.
    let p = dir.join("p.yaml");
    let out = run(&p, &cache, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_ne!(
        std::fs::read(&e["mesh"]).unwrap(),
        forged,
        "the entry was rewritten"
    );
    assert!(run(&p, &cache, &[]).status.success());
    // verify finds a forged entry and removes it (and only it).
    std::fs::write(&e["mesh"], &forged).unwrap();
    let out = matflow(&["cache", "verify", "--cache", cache.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}{}", stderr(&out));
    assert!(
        text.contains("1 of the wrong type") && text.contains("removed 0 blobs and 1 actions"),
        "{text}"
    );
    assert!(text.contains("not a mesh artifact"), "{text}");
    let out = matflow(&["cache", "verify", "--cache", cache.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("0 of the wrong type; removed 0 blobs and 0 actions"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn cache_tools_count_only_what_they_removed_and_fail_when_they_cannot() {
    let dir = scratch("hostile", "undeletable");
    let cache = dir.join("cache");
    let e = populate(&dir, &cache);
    // An entry and a blob that cannot be removed, even by root: each is
    // a non-empty directory where a file is expected.
    std::fs::remove_file(&e["shot"]).unwrap();
    std::fs::create_dir_all(e["shot"].join("x")).unwrap();
    let blobs = cache.join("blobs/ff");
    std::fs::create_dir_all(blobs.join(format!("{}/x", "f".repeat(62)))).unwrap();
    let out = matflow(&["cache", "verify", "--cache", cache.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}{}", stderr(&out));
    assert!(text.contains("removed 0 blobs and 0 actions"), "{text}");
    assert!(stderr(&out).contains("could not"), "{}", stderr(&out));
    let out = matflow(&[
        "cache",
        "gc",
        "--cache",
        cache.to_str().unwrap(),
        "--older-than",
        "0",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}{}", stderr(&out));
    // The two intact entries and their blobs went; the stuck ones did not count.
    assert!(text.contains("removed 2 actions"), "{text}");
    assert!(stderr(&out).contains("removals failed"), "{}", stderr(&out));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn listing_into_a_closed_pipe_ends_quietly() {
    let dir = scratch("hostile", "pipe");
    let cache = dir.join("cache");
    populate(&dir, &cache);
    for args in [
        &["cache", "ls", "--cache", cache.to_str().unwrap()][..],
        &["kinds"][..],
    ] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_matflow"))
            .args(args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        assert_eq!(out.status.code(), Some(0), "{args:?}: {}", stderr(&out));
        assert!(out.stderr.is_empty(), "{args:?}: {}", stderr(&out));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_write_error_mid_run_fails_cleanly_and_the_next_run_completes() {
    let dir = scratch("hostile", "efbig");
    let cache = dir.join("cache");
    let file = dir.join("p.yaml");
    std::fs::write(&file, render_pipeline("out/p.exr", 2)).unwrap();
    // A real I/O fault: files may not grow past 4 KiB (RLIMIT_FSIZE, the
    // signal ignored so writes fail with EFBIG), as on a full disk. The
    // scene's blob is larger, so the first stage's store write fails.
    let (out, _) = matflow_limited("trap '' XFSZ; ulimit -f 8", &run_args(&file, &cache, &[]));
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("cache") && err.contains("too large"), "{err}");
    // The cache is consistent: nothing damaged, no temporary left.
    let v = matflow(&["cache", "verify", "--cache", cache.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&v.stdout);
    assert!(v.status.success(), "{text}");
    assert!(
        text.contains(" 0 corrupt; 0 actions complete, 0 unreadable, 0 incomplete"),
        "{text}"
    );
    assert_eq!(std::fs::read_dir(cache.join("tmp")).unwrap().count(), 0);
    assert!(!dir.join("out/p.exr").exists());
    // Without the fault the same run completes.
    let out = run(&file, &cache, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(dir.join("out/p.exr").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}
