//! Hostile input, over the binary: what a stranger's pipeline file, flags
//! or files can make matflow do. Each case must end in a clear error
//! naming the file and the line and column (or the flag), quickly and in
//! bounded memory — never a crash, a hang, or a false success.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("matflow-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `matflow args…` with its address space capped at `mem_mib` (so a
/// blow-up fails inside the cap instead of taking the machine), and how
/// long it took.
fn matflow_capped(mem_mib: u64, args: &[&str]) -> (Output, Duration) {
    let t = Instant::now();
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {}; exec \"$0\" \"$@\"", mem_mib * 1024))
        .arg(env!("CARGO_BIN_EXE_matflow"))
        .args(args)
        .env_remove("MATFLOW_CACHE")
        .output()
        .expect("run matflow");
    (out, t.elapsed())
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Runs `pipeline` (written to a file) capped at 1 GiB and expects a
/// prompt, clear failure whose message contains `expect`.
fn refused(dir: &Path, name: &str, pipeline: &str, extra: &[&str], expect: &str) -> String {
    let file = dir.join(name);
    std::fs::write(&file, pipeline).unwrap();
    let cache = dir.join("cache");
    let mut args = vec!["run", file.to_str().unwrap(), "--quiet", "--cache"];
    args.push(cache.to_str().unwrap());
    args.extend_from_slice(extra);
    let (out, took) = matflow_capped(1024, &args);
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
    let dir = tmp("yaml");
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
    let ok = "stages:\n  x:\n    kind: synth\noutputs: [x]\n";
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
