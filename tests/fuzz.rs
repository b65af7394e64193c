//! Mutation fuzzing of everything matflow reads from outside: pipeline
//! files, EXR / PNG / Radiance HDR images, bundles, and cache entries
//! (artifacts and action records). Each target starts from a corpus of
//! real files — the repository's pipelines, and images, bundles and cache
//! entries matflow writes — and applies random byte-level mutations (bit
//! flips, overwrites, boundary values in what may be length fields,
//! insertions, deletions, truncations, duplicated chunks). Every reader
//! must answer `Ok` or `Err`: never panic, hang or exhaust memory.
//!
//! A fixed number of cases per target keeps CI's time bounded:
//! `MATFLOW_FUZZ_CASES` (default 1000). Longer runs:
//! `MATFLOW_FUZZ_CASES=20000 cargo test --release --test fuzz -- --nocapture`.

mod support;
use std::path::{Path, PathBuf};
use std::time::Instant;
use support::{repo, scratch};

use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};

use matflow_scene::{io, Bundle, Image, MaterialSource};

/// The fuzzer's seed: fixed by default, so CI runs the same cases every
/// time (a failure is reproducible); `MATFLOW_FUZZ_SEED` picks others
/// (`random` for a fresh one each run, printed).
fn seed() -> proptest::test_runner::RngSeed {
    use proptest::test_runner::RngSeed;
    match std::env::var("MATFLOW_FUZZ_SEED").ok().as_deref() {
        None => RngSeed::Fixed(0x006d_6174_666c_6f77),
        Some("random") => {
            let s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(1, |d| d.as_nanos() as u64);
            println!("fuzz seed {s}");
            RngSeed::Fixed(s)
        }
        Some(v) => RngSeed::Fixed(v.parse().expect("MATFLOW_FUZZ_SEED: a number or `random`")),
    }
}

fn cases() -> u32 {
    std::env::var("MATFLOW_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1000)
}

/// Runs `matflow args…` and expects it to succeed (building a corpus).
fn matflow_ok(args: &[&str]) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_matflow"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The bytes of each file.
fn read_all(files: &[PathBuf]) -> Vec<Vec<u8>> {
    files.iter().map(|p| std::fs::read(p).unwrap()).collect()
}

#[derive(Clone, Debug)]
enum Mutation {
    Flip(usize, u8),
    Set(usize, u8),
    /// A boundary value written as a little-endian u32 (length fields).
    Boundary(usize, u32),
    Insert(usize, Vec<u8>),
    Delete(usize, usize),
    Truncate(usize),
    /// Copies `len` bytes from `from` to `to`.
    Duplicate {
        from: usize,
        to: usize,
        len: usize,
    },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let pos = any::<usize>();
    prop_oneof![
        (pos, 0u8..8).prop_map(|(p, b)| Mutation::Flip(p, b)),
        (pos, any::<u8>()).prop_map(|(p, v)| Mutation::Set(p, v)),
        (
            pos,
            prop::sample::select(vec![
                0u32,
                1,
                0x7f,
                0x80,
                0xff,
                0xffff,
                0x7fff_ffff,
                0x8000_0000,
                u32::MAX
            ])
        )
            .prop_map(|(p, v)| Mutation::Boundary(p, v)),
        (pos, prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(p, v)| Mutation::Insert(p, v)),
        (pos, 1usize..64).prop_map(|(p, n)| Mutation::Delete(p, n)),
        pos.prop_map(Mutation::Truncate),
        (pos, pos, 1usize..256).prop_map(|(from, to, len)| Mutation::Duplicate { from, to, len }),
    ]
}

fn apply(seed: &[u8], ms: &[Mutation]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for m in ms {
        let n = b.len().max(1);
        match m {
            Mutation::Flip(p, bit) if !b.is_empty() => b[p % n] ^= 1 << bit,
            Mutation::Set(p, v) if !b.is_empty() => b[p % n] = *v,
            Mutation::Boundary(p, v) => {
                let at = p % n;
                for (i, x) in v.to_le_bytes().iter().enumerate() {
                    if at + i < b.len() {
                        b[at + i] = *x;
                    }
                }
            }
            Mutation::Insert(p, v) => {
                let at = p % (b.len() + 1);
                b.splice(at..at, v.iter().copied());
            }
            Mutation::Delete(p, k) if !b.is_empty() => {
                let at = p % n;
                b.drain(at..(at + k).min(b.len()));
            }
            Mutation::Truncate(p) => b.truncate(p % (b.len() + 1)),
            Mutation::Duplicate { from, to, len } if !b.is_empty() => {
                let f = from % n;
                let chunk: Vec<u8> = b[f..(f + len).min(b.len())].to_vec();
                let t = to % (b.len() + 1);
                b.splice(t..t, chunk);
            }
            _ => {}
        }
    }
    b
}

/// Runs `check(corpus index, mutant)` on `cases()` mutants of the corpus; a panic inside it
/// is a failure (proptest shrinks it to a small mutation list).
fn fuzz(name: &str, corpus: &[Vec<u8>], check: impl Fn(usize, &[u8])) {
    assert!(!corpus.is_empty());
    let t = Instant::now();
    let mut runner = TestRunner::new(Config {
        cases: cases(),
        failure_persistence: None,
        rng_seed: seed(),
        ..Config::default()
    });
    let strategy = (0..corpus.len(), prop::collection::vec(mutation(), 1..6));
    let result = runner.run(&strategy, |(i, ms)| {
        let bytes = apply(&corpus[i], &ms);
        // For a crash that is not a panic (an abort): the last input.
        if let Ok(dump) = std::env::var("MATFLOW_FUZZ_DUMP") {
            std::fs::write(format!("{dump}.{name}"), &bytes).unwrap();
        }
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check(i, &bytes))).map_err(|_| {
            TestCaseError::fail(format!("{name}: panicked on a mutant of corpus file {i}"))
        })
    });
    println!(
        "fuzz {name}: {} cases from {} corpus files in {:.2} s: {}",
        cases(),
        corpus.len(),
        t.elapsed().as_secs_f64(),
        if result.is_ok() {
            "no failure"
        } else {
            "FAILED"
        }
    );
    if let Err(e) = result {
        panic!("{e}");
    }
}

fn image(w: usize, h: usize) -> matflow_scene::RgbImage {
    Image::from_fn(w, h, |x, y| {
        glam::Vec3::new(x as f32 * 0.3, y as f32 * 0.1, 0.5)
    })
}

#[test]
fn pipeline_files() {
    let reg = matflow_nodes::registry();
    let mut corpus: Vec<Vec<u8>> = std::fs::read_dir(repo().join("pipelines"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "yaml"))
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    corpus.push(b"a: &x [1, 2]\nb: *x\nstages: {}\noutputs: []\n".to_vec());
    corpus.push(b"stages:\n  s:\n    kind: render\n    spp: [[[[1]]]]\noutputs: [s]\n".to_vec());
    let at = repo().join("pipelines/fuzzed.yaml");
    fuzz("pipeline", &corpus, |_, b| {
        let _ = matflow_engine::spec::parse(&String::from_utf8_lossy(b), &at, &reg, &[]);
    });
}

#[test]
fn image_readers() {
    let dir = scratch("fuzz", "images");
    let mut exr = Vec::new();
    for (w, h) in [(4, 3), (17, 5)] {
        let p = dir.join("seed.exr");
        io::write_exr_rgb(&p, &image(w, h)).unwrap();
        exr.push(std::fs::read(&p).unwrap());
        io::write_exr_gray(&p, &Image::from_fn(w, h, |x, _| x as f32)).unwrap();
        exr.push(std::fs::read(&p).unwrap());
    }
    let f = dir.join("x.exr");
    fuzz("exr", &exr, |_, b| {
        std::fs::write(&f, b).unwrap();
        let _ = io::read_exr_rgb(&f);
        let _ = io::read_exr_gray(&f);
        let _ = io::read_envmap(&f);
    });
    let mut png = Vec::new();
    for (w, h) in [(4, 3), (9, 9)] {
        let p = dir.join("seed.png");
        io::write_png_gamma(&p, &image(w, h)).unwrap();
        png.push(std::fs::read(&p).unwrap());
        io::write_png_srgb_map(&p, &Image::from_fn(w, h, |x, _| x as f32 / 9.0)).unwrap();
        png.push(std::fs::read(&p).unwrap());
    }
    let f = dir.join("x.png");
    fuzz("png", &png, |_, b| {
        std::fs::write(&f, b).unwrap();
        let _ = io::read_ldr_raw(&f);
        let _ = io::read_mask(&f);
        let _ = io::load_photo(&f, 8);
    });
    let p = dir.join("seed.hdr");
    io::write_hdr(&p, &image(8, 4)).unwrap();
    let hdr = vec![std::fs::read(&p).unwrap()];
    let f = dir.join("x.hdr");
    fuzz("hdr", &hdr, |_, b| {
        std::fs::write(&f, b).unwrap();
        let _ = io::read_hdr(&f);
        let _ = io::read_envmap(&f);
    });
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bundles() {
    let dir = scratch("fuzz", "bundle");
    let seed = dir.join("seed");
    matflow_ok(&[
        "synth",
        "--size",
        "8",
        "--spp",
        "1",
        "--degrade",
        "--out",
        seed.to_str().unwrap(),
    ]);
    let files: Vec<PathBuf> = walk(&seed);
    let corpus = read_all(&files);
    let work = dir.join("b");
    // Each case damages one file of the bundle (chosen by the corpus
    // index) and loads everything a pipeline would.
    fuzz("bundle", &corpus, |i, b| {
        let _ = std::fs::remove_dir_all(&work);
        copy_dir(&seed, &work);
        let rel = files[i].strip_prefix(&seed).unwrap();
        std::fs::write(work.join(rel), b).unwrap();
        if let Ok(bundle) = Bundle::open(&work) {
            let _ = bundle.load_depth();
            let _ = bundle.load_gt_image();
            for src in [MaterialSource::Pred, MaterialSource::GroundTruth] {
                let _ = bundle.load_materials(src);
            }
            if let Some(env) = bundle.envmap_path() {
                let _ = io::read_envmap(&env);
            }
        }
    });
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn cache_entries() {
    use matflow_engine::store::{Digest, Store};
    use matflow_nodes::artifact::Artifact;
    let dir = scratch("fuzz", "cache");
    let file = dir.join("p.yaml");
    std::fs::write(
        &file,
        "stages:\n  scene:\n    kind: synthetic_scene\n    size: 16\n    spp: 1\n  \
         mesh:\n    kind: mesh\n    scene: scene\n  \
         shot:\n    kind: render\n    mesh: mesh\n    materials: scene\n    \
         envmap: scene.truth_envmap\n    spp: 1\noutputs: [shot]\n",
    )
    .unwrap();
    let cache = dir.join("cache");
    matflow_ok(&[
        "run",
        file.to_str().unwrap(),
        "--quiet",
        "--cache",
        cache.to_str().unwrap(),
    ]);
    let blobs = read_all(&walk(&cache.join("blobs")));
    let actions = read_all(&walk(&cache.join("actions")));
    let types = [
        "scene",
        "materials",
        "envmap",
        "mesh",
        "image",
        "paths",
        "mask",
    ];
    fuzz("artifact", &blobs, |_, b| {
        let _ = Artifact::type_of(b);
        for ty in types {
            let _ = Artifact::decode(b, ty);
        }
    });
    let store_dir = dir.join("fuzzed");
    let store = Store::open(&store_dir).unwrap();
    let key = Digest::of(b"key");
    fuzz("action", &actions, |_, b| {
        let p = store.action_path(&key);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(&p, b).unwrap();
        let _ = store.get_action(&key);
        let _ = store.verify();
    });
    let _ = std::fs::remove_dir_all(&dir);
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                todo.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

fn copy_dir(from: &Path, to: &Path) {
    for f in walk(from) {
        let t = to.join(f.strip_prefix(from).unwrap());
        std::fs::create_dir_all(t.parent().unwrap()).unwrap();
        std::fs::copy(&f, &t).unwrap();
    }
}

#[test]
fn mesh_files() {
    // OBJ (with an MTL beside it) and PLY, ASCII and binary, through the
    // readers and object placement.
    let dir = scratch("fuzz", "meshes");
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl g\nKd 0.5 0.5 0.5\nNi 1.4\nd 0.2\nillum 7\n",
    )
    .unwrap();
    let obj = |s: &str| s.as_bytes().to_vec();
    let objs = vec![
        std::fs::read(repo().join("pipelines/meshes/cube.obj")).unwrap(),
        obj("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\nusemtl g\nf 1/1/1 2/2/1 3/3/1 4/4/1\n"),
    ];
    let mut ply_ascii = String::from("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n");
    ply_ascii += "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n";
    let mut ply_bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for v in [[0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.]] {
        for c in v {
            ply_bin.extend(c.to_le_bytes());
        }
    }
    ply_bin.push(3);
    for i in [0i32, 1, 2] {
        ply_bin.extend(i.to_le_bytes());
    }
    let cam = matflow_scene::Camera::new(8, 8);
    let wall = matflow_geom::mesh_from_depth(&Image::new(8, 8, 5.0f32), &cam, &Default::default())
        .unwrap()
        .mesh;
    for (name, corpus) in [
        ("obj", objs),
        ("ply", vec![ply_ascii.into_bytes(), ply_bin]),
    ] {
        let f = dir.join(format!("x.{name}"));
        fuzz(name, &corpus, |_, b| {
            std::fs::write(&f, b).unwrap();
            let _ = matflow_scene::meshfile::read_mesh(&f);
            let spec = matflow_nodes::objects::ObjectSpec {
                mesh: f.clone(),
                translate: Some(glam::Vec3::new(0.0, 0.0, -3.0)),
                anchor: None,
                rotate_deg: glam::Vec3::ZERO,
                scale: glam::Vec3::ONE,
                material: None,
            };
            let _ = matflow_nodes::objects::place(&[spec], &cam, &wall);
        });
    }
    let _ = std::fs::remove_dir_all(&dir);
}
