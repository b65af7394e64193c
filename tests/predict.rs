//! The prediction stage over the binary: `matflow predict` writes a bundle
//! in the reference's layout that the other stages read, its report names
//! the backend and the model's digest, a second run is served from the
//! cache; bad photos and bad models are clear errors that leave no bundle
//! behind; the two backends agree; `pipelines/photo.yaml` runs end to end
//! and an edit downstream of the prediction does not re-run it; the
//! export tool maps official MatNet checkpoints.

use std::path::Path;
use std::process::{Command, Output};

mod support;
use support::{matflow, repo, s, scratch};

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn predict(photo: &Path, out: &Path, cache: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "predict",
        s(photo),
        "--out",
        s(out),
        "--cache",
        s(cache),
        "--quiet",
    ];
    args.extend_from_slice(extra);
    matflow(&args, None)
}

fn digest(path: &Path) -> String {
    blake3::hash(&std::fs::read(path).unwrap())
        .to_hex()
        .to_string()
}

const BUNDLE: &[&str] = &[
    "gt_image.exr",
    "gt_image.png",
    "albedoPred.exr",
    "normalPred.exr",
    "roughnessPred.png",
    "metallicPred.png",
    "depth.exr",
    "prediction.json",
];

#[test]
fn predict_writes_a_bundle_that_renders_and_is_cached() {
    let d = scratch("predict", "bundle");
    let (out, cache) = (d.join("bundle"), d.join("cache"));
    let photo = repo().join("tests/data/matnet_photo.png");
    let o = predict(&photo, &out, &cache, &[]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let model = digest(&repo().join("models/matnet_rooms.onnx"));
    assert!(
        t.contains(&format!("tract backend; model blake3 {model}")),
        "{t}"
    );
    assert!(t.contains("executed"), "{t}");
    for f in BUNDLE {
        assert!(out.join(f).is_file(), "{f} missing: {t}");
    }
    assert!(!out.join("depthPred.exr").exists());
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("prediction.json")).unwrap()).unwrap();
    assert_eq!(rec["photo_size"], serde_json::json!([256, 192]));
    assert_eq!(
        rec["crop"],
        serde_json::json!({"x": 32, "y": 0, "side": 192})
    );
    assert_eq!(rec["model"]["blake3"], model.as_str());
    assert_eq!(rec["backend"], "tract");
    let first: Vec<String> = BUNDLE.iter().map(|f| digest(&out.join(f))).collect();

    // Again: served from the cache, the same bytes, the same note.
    let o = predict(&photo, &out, &cache, &[]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("cached"), "{t}");
    assert!(t.contains(&format!("model blake3 {model}")), "{t}");
    let again: Vec<String> = BUNDLE.iter().map(|f| digest(&out.join(f))).collect();
    assert_eq!(first, again);

    // The bundle is what the other commands read: it renders.
    let o = matflow(
        &[
            "render",
            "--bundle",
            s(&out),
            "--materials",
            "pred",
            "--envmap",
            s(&repo().join("../shared/data/materialist/envmaps/0.hdr")),
            "--out",
            s(&d.join("r.exr")),
            "--spp",
            "1",
        ],
        None,
    );
    assert!(o.status.success(), "{}", text(&o));
}

/// A PNG declaring `w`×`h` RGB pixels, with a few bytes of image data
/// (as the start of a real file that size).
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut b = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    let mut ihdr = b"IHDR".to_vec();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    b.extend_from_slice(&13u32.to_be_bytes());
    b.extend_from_slice(&ihdr);
    let crc = crc32(&ihdr);
    b.extend_from_slice(&crc.to_be_bytes());
    for (kind, data) in [
        (&b"IDAT"[..], &[0x78u8, 0x9c, 0x03, 0x00][..]),
        (b"IEND", &[]),
    ] {
        let mut c = kind.to_vec();
        c.extend_from_slice(data);
        b.extend_from_slice(&(data.len() as u32).to_be_bytes());
        b.extend_from_slice(&c);
        b.extend_from_slice(&crc32(&c).to_be_bytes());
    }
    b
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &x in data {
        c ^= x as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn write_exr_with_nan(path: &Path) {
    // Through matflow's own writer: a 64×64 linear image with one NaN.
    let mut px = vec![0.5f32; 64 * 64 * 3];
    px[(10 * 64 + 7) * 3 + 1] = f32::NAN;
    use exr::prelude::*;
    let img = Image::from_channels(
        (64, 64),
        SpecificChannels::rgb(|p: Vec2<usize>| {
            let i = (p.y() * 64 + p.x()) * 3;
            (px[i], px[i + 1], px[i + 2])
        }),
    );
    img.write().to_file(path).unwrap();
}

#[test]
fn bad_photos_are_clear_errors_or_documented_conversions() {
    let d = scratch("predict", "photos");
    let cache = d.join("cache");
    let fails = |photo: &Path, want: &str| {
        let out = d.join("never");
        let o = predict(photo, &out, &cache, &[]);
        let t = text(&o);
        assert!(!o.status.success(), "{} should fail: {t}", photo.display());
        assert!(
            t.contains(want),
            "{} should say {want:?}: {t}",
            photo.display()
        );
        assert!(!t.contains("panicked"), "{t}");
        assert!(!out.join("albedoPred.exr").exists());
    };
    // 1×1.
    let tiny = d.join("tiny.png");
    image::RgbImage::new(1, 1).save(&tiny).unwrap();
    fails(&tiny, "the photo is 1x1: too small to predict from");
    // A header declaring 256 megapixels is refused before decoding.
    let huge = d.join("huge.png");
    std::fs::write(&huge, png_header_only(16_000, 16_000)).unwrap();
    fails(&huge, "256.0 megapixels, more than the 150 megapixels");
    // Not an image at all; a truncated PNG.
    let junk = d.join("junk.png");
    std::fs::write(&junk, b"not a photo").unwrap();
    fails(&junk, "junk.png");
    let good = std::fs::read(repo().join("tests/data/matnet_photo.png")).unwrap();
    let cut = d.join("cut.png");
    std::fs::write(&cut, &good[..good.len() / 2]).unwrap();
    fails(&cut, "cut.png");
    // An EXR holding NaN names the pixel.
    let nan = d.join("nan.exr");
    write_exr_with_nan(&nan);
    fails(&nan, "pixel x=7, y=10");

    // Grey and 16-bit PNGs are converted, and the record says how.
    let photo = image::open(repo().join("tests/data/matnet_photo.png")).unwrap();
    let cases = [
        (
            "grey.png",
            photo.to_luma8().into(),
            "grey replicated to RGB",
        ),
        (
            "deep.png",
            image::DynamicImage::ImageRgb16(photo.to_rgb16()),
            "16-bit samples scaled",
        ),
        ("alpha.png", photo.to_rgba8().into(), "alpha ignored"),
    ];
    let mut albedo = vec![];
    for (name, img, note) in cases {
        let img: image::DynamicImage = img;
        let p = d.join(name);
        img.save(&p).unwrap();
        let out = d.join(format!("{name}.bundle"));
        let o = predict(&p, &out, &cache, &[]);
        assert!(o.status.success(), "{name}: {}", text(&o));
        let rec = std::fs::read_to_string(out.join("prediction.json")).unwrap();
        assert!(rec.contains(note), "{name}: {rec}");
        albedo.push(digest(&out.join("albedoPred.exr")));
    }
    // 16 bits and alpha change nothing the network sees here (the 16-bit
    // values are the 8-bit ones times 257).
    let out = d.join("plain");
    assert!(predict(
        &repo().join("tests/data/matnet_photo.png"),
        &out,
        &cache,
        &[]
    )
    .status
    .success());
    let plain = digest(&out.join("albedoPred.exr"));
    assert_eq!(albedo[1], plain);
    assert_eq!(albedo[2], plain);
    assert_ne!(albedo[0], plain);
}

#[test]
fn a_100_megapixel_photo_is_read_in_bounded_memory() {
    let d = scratch("predict", "big");
    let p = d.join("big.png");
    // 10000×10000 grey, a gradient (a constant would be refused as a
    // flat depth by no model; this one is a real photo's size).
    let img = image::GrayImage::from_fn(10_000, 10_000, |x, y| {
        image::Luma([((x / 40 + y / 40) % 256) as u8])
    });
    img.save(&p).unwrap();
    drop(img);
    let out = d.join("bundle");
    let o = Command::new("/usr/bin/time")
        .args(["-f", "peak-kb %M", env!("CARGO_BIN_EXE_matflow")])
        .args([
            "predict",
            s(&p),
            "--out",
            s(&out),
            "--cache",
            s(&d.join("cache")),
            "--quiet",
        ])
        .env_remove("MATFLOW_CACHE")
        .output()
        .unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let peak_kb: u64 = t
        .lines()
        .find_map(|l| l.strip_prefix("peak-kb "))
        .and_then(|v| v.trim().parse().ok())
        .expect("peak");
    // The decoded photo is 100 MB of grey samples; nothing copies it
    // whole into floats (that alone would be 1.2 GB).
    eprintln!("peak {} MB", peak_kb / 1024);
    assert!(peak_kb < 700 * 1024, "peak {} MB", peak_kb / 1024);
    assert!(out.join("albedoPred.exr").is_file());
}

#[test]
fn bad_models_are_named_errors() {
    let d = scratch("predict", "models");
    let cache = d.join("cache");
    let photo = repo().join("tests/data/matnet_photo.png");
    let fails = |model: &Path, want: &str| {
        let out = d.join("never");
        let o = predict(&photo, &out, &cache, &["--model", s(model)]);
        let t = text(&o);
        assert!(!o.status.success(), "{} should fail: {t}", model.display());
        assert!(
            t.contains(want),
            "{} should say {want:?}: {t}",
            model.display()
        );
        assert!(!t.contains("panicked"), "{t}");
        assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none());
    };
    let junk = d.join("junk.onnx");
    std::fs::write(&junk, b"\x07 this is not a model at all").unwrap();
    fails(&junk, "junk.onnx: not an ONNX model");
    let shipped = std::fs::read(repo().join("models/matnet_rooms.onnx")).unwrap();
    let cut = d.join("cut.onnx");
    std::fs::write(&cut, &shipped[..shipped.len() / 2]).unwrap();
    fails(&cut, "cut.onnx: not an ONNX model");
    fails(
        &repo().join("tests/data/identity_3x8x8.onnx"),
        "not a MatNet-contract model: expected one input f32 [1 or N, 3, S, S]",
    );
    fails(
        &repo().join("tests/data/matnet_wrong_channels.onnx"),
        "output albedo is albedo f32 [1, 2, 32, 32]",
    );
    let missing = d.join("nowhere.onnx");
    fails(&missing, "nowhere.onnx");
}

#[test]
fn a_dynamic_two_head_model_gets_518_and_its_depth_is_disparity() {
    let d = scratch("predict", "heads");
    let out = d.join("bundle");
    let o = predict(
        &repo().join("tests/data/matnet_photo.png"),
        &out,
        &d.join("cache"),
        &[
            "--model",
            s(&repo().join("tests/data/matnet_heads_dynamic.onnx")),
        ],
    );
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("input 518x518, outputs depth/material, depth disparity"),
        "{t}"
    );
    assert!(out.join("depthPred.exr").is_file());
    assert!(!out.join("depth.exr").exists());
}

/// Both backends, where onnxruntime is installed: the same bundle to
/// within 1e-4 (the maps are values of order 1).
#[test]
fn tract_and_onnxruntime_agree() {
    backends_agree(None, "backends");
}

fn have_onnxruntime() -> bool {
    let have = Command::new("python3")
        .args(["-c", "import onnxruntime"])
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    have || std::env::var_os("ORT_DYLIB_PATH").is_some()
}

/// `matflow predict` on the fixture photo with `model` (default: the
/// bundled one) on both backends: the maps agree within 1e-4.
fn backends_agree(model: Option<&Path>, tag: &str) {
    if !have_onnxruntime() {
        eprintln!("onnxruntime is not installed: only tract is tested");
        return;
    }
    let d = scratch("predict", tag);
    let photo = repo().join("tests/data/matnet_photo.png");
    let mut maps = vec![];
    for b in ["tract", "onnxruntime"] {
        let out = d.join(b);
        let mut extra = vec!["--backend", b];
        if let Some(m) = model {
            extra.extend(["--model", s(m)]);
        }
        let o = predict(&photo, &out, &d.join("cache"), &extra);
        let t = text(&o);
        assert!(o.status.success(), "{b}: {t}");
        assert!(t.contains(&format!("{b} backend")), "{t}");
        let read = |f: &str| {
            let c = exr::prelude::read_all_flat_layers_from_file(out.join(f)).unwrap();
            c.layer_data[0]
                .channel_data
                .list
                .iter()
                .flat_map(|c| c.sample_data.values_as_f32().collect::<Vec<_>>())
                .collect::<Vec<f32>>()
        };
        maps.push([
            read("albedoPred.exr"),
            read("normalPred.exr"),
            read("depth.exr"),
        ]);
    }
    for (k, (a, b)) in maps[0].iter().zip(&maps[1]).enumerate() {
        let worst = a
            .iter()
            .zip(b)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        eprintln!("map {k}: max |tract - onnxruntime| = {worst:e}");
        assert!(worst < 1e-4, "map {k}: {worst}");
    }
}

/// The ensemble tool (`train/matnet/ensemble.py`): its own tests on small
/// models (the combination it documents, against onnxruntime), then the
/// bundled model with its mirrored pass, built by the tool, runs on tract
/// as onnxruntime runs it (the mirror is a Gather, the depth's geometric
/// mean Log and Exp).
#[test]
fn the_ensemble_tool_builds_models_tract_runs() {
    python_tests("train/matnet/test_ensemble.py", 3);
    let d = scratch("predict", "ensemble-model");
    let model = d.join("flip.onnx");
    let o = python(
        "train/matnet/ensemble.py",
        &[
            s(&repo().join("models/matnet_rooms.onnx")),
            "--flip",
            "--out",
            s(&model),
        ],
    );
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("2 passes"), "{t}");
    backends_agree(Some(&model), "ensemble");
}

#[test]
fn the_photo_pipeline_runs_and_an_edit_does_not_rerun_the_prediction() {
    let d = scratch("predict", "pipeline");
    let cache = d.join("cache");
    let outs = d.join("out");
    let set = |k: &str, v: &str| format!("{k}={v}");
    let run = |extra: &[String]| {
        let mut args: Vec<String> = vec![
            "run".into(),
            s(&repo().join("pipelines/photo.yaml")).into(),
            "--cache".into(),
            s(&cache).into(),
            "--quiet".into(),
            "--report".into(),
            s(&d.join("report.json")).into(),
        ];
        // Small budgets for the test; the outputs go to the scratch folder.
        for (k, v) in [
            ("lighting.budget_seconds", "2"),
            ("recovered.budget_seconds", "3"),
            ("base.spp", "4"),
            ("base.path_spp", "1"),
            ("relit.spp", "4"),
            ("rerender.spp", "4"),
            ("predict.output", s(&outs.join("bundle"))),
            ("rerender.output", s(&outs.join("rerender.exr"))),
            ("edited.output", s(&outs.join("edited.exr"))),
            ("relit.output", s(&outs.join("relit.exr"))),
        ] {
            args.push("--set".into());
            args.push(set(k, v));
        }
        for e in extra {
            args.push("--set".into());
            args.push(e.clone());
        }
        let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        let o = matflow(&a, None);
        assert!(o.status.success(), "{}", text(&o));
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("report.json")).unwrap()).unwrap();
        r["stages"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| {
                (
                    s["name"].as_str().unwrap().to_string(),
                    s["status"].as_str().unwrap().to_string(),
                )
            })
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    let first = run(&[]);
    assert!(first.values().all(|s| s == "executed"), "{first:?}");
    // Denoised for viewing, with the samples as rendered beside them.
    for f in [
        "rerender.exr",
        "rerender.png",
        "rerender_raw.exr",
        "edited.exr",
        "relit.exr",
        "relit_raw.exr",
        "bundle/albedoPred.exr",
    ] {
        assert!(outs.join(f).is_file(), "{f}");
    }
    let second = run(&["paint.hue_shift=30".to_string()]);
    assert_eq!(second["predict"], "cached");
    assert_eq!(second["recovered"], "cached");
    assert_eq!(second["paint"], "executed");
    assert_eq!(second["edited"], "executed");
    assert_eq!(second["relit"], "cached");
}

/// The export tool's checkpoint handling (`train/matnet/checkpoint.py`,
/// plain Python): the official 303-entry layout, the released state dict
/// loading as it is, a training checkpoint needing `--rename matnet.=
/// --drop criterion_lpips.` and being told so, bad keys named. The
/// PyTorch half of the path is `train/matnet/test_export_matnet.py`.
#[test]
fn the_export_tool_maps_official_checkpoints() {
    python_tests("train/matnet/test_checkpoint.py", 11);
}

/// Runs a Python script of the repository with `args`.
fn python(script: &str, args: &[&str]) -> Output {
    Command::new("python3")
        .arg(repo().join(script))
        .args(args)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .output()
        .expect("python3")
}

/// Runs a Python unittest file of the repository: it passes, all `tests`.
fn python_tests(script: &str, tests: usize) {
    let o = python(script, &[]);
    let t = text(&o);
    assert!(o.status.success(), "{script}: {t}");
    assert!(t.contains(&format!("Ran {tests} tests")), "{script}: {t}");
}
