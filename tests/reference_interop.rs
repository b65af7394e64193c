//! Interoperability with the reference implementation's stored outputs in
//! `../shared/data/materialist/` (present beside the checkout in CI; the
//! tests say so and pass vacuously only when that folder is absent).

use std::path::PathBuf;
use std::process::Command;

fn data(scene: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data/materialist")
        .join(scene);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found", p.display());
        None
    }
}

fn run(args: &[&str]) -> String {
    let o = Command::new(env!("CARGO_BIN_EXE_matflow"))
        .args(args)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{out}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

#[test]
fn meshes_match_the_reference_algorithm_counts() {
    // Counts of the reference's depth_file_to_mesh on the same inputs.
    for (scene, verts, tris, copies) in [
        ("indoor", 268_318, 522_183, 6_174),
        ("jinjya", 264_494, 368_289, 2_350),
    ] {
        let Some(b) = data(scene) else { return };
        let dir = tempfile::tempdir().unwrap();
        // The reference meshes the depth alone: no completion.
        let out = run(&[
            "mesh",
            "--bundle",
            b.to_str().unwrap(),
            "--complete",
            "none",
            "--silhouettes",
            "reference",
            "--out",
            dir.path().join("m.ply").to_str().unwrap(),
        ]);
        assert!(out.contains("completion none (as asked)"), "{scene}: {out}");
        assert!(
            out.contains(&format!("{verts} vertices, {tris} triangles")),
            "{scene}: {out}"
        );
        assert!(out.contains(&format!("{copies} copies")), "{scene}: {out}");
    }
}

fn psnr_of(out: &str) -> f64 {
    out.split("PSNR (sRGB, gamma 2.2) against")
        .nth(1)
        .unwrap()
        .split(": ")
        .nth(1)
        .unwrap()
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

#[test]
fn indoor_best_results_reproduce_the_stored_render() {
    let Some(b) = data("indoor") else { return };
    let dir = tempfile::tempdir().unwrap();
    let stored = b.join("best_results/rendered_img.exr");
    // 16 spp keeps CI fast; 64 spp gives 32.2 dB (see docs/results/rendering.md).
    let out = run(&[
        "render",
        "--bundle",
        b.to_str().unwrap(),
        "--materials",
        "best_results",
        "--spp",
        "16",
        "--reference-compat",
        "--compare",
        stored.to_str().unwrap(),
        "--out",
        dir.path().join("r.exr").to_str().unwrap(),
    ]);
    // The reference renders its depth mesh alone, and so does
    // --reference-compat unless told otherwise.
    assert!(
        out.contains("completion none (the reference's, --reference-compat)"),
        "{out}"
    );
    let psnr = psnr_of(&out);
    assert!(
        psnr > 29.0,
        "reference-compatible render at 16 spp: {psnr} dB\n{out}"
    );
}
