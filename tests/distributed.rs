//! Distributed execution, end to end over real processes: `matflow
//! worker`s on loopback ports, a real Remote Execution API cache server
//! (buildbox-casd) as the shared store, and `matflow run --workers`.
//!
//! What must hold: a run on workers computes byte-identical outputs under
//! the same action keys as a local run; a worker killed or hung mid-stage
//! loses the stage to another and the retry is in the report; a wrong
//! token is refused before anything runs; a blob the store serves
//! corrupt is detected and recomputed; two fresh local caches share one
//! remote; a submitter killed mid-run and restarted finishes from what the
//! store holds.

mod support;
use support::s;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use serde_json::Value;
use support::{Casd, Worker, SMALL};

fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_matflow"))
}

fn demo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pipelines/demo.yaml")
}

/// `matflow run` of the demo; returns the process output and the report.
fn run(work: &Path, tag: &str, extra: &[&str], env: &[(&str, &str)]) -> (Output, Option<Value>) {
    let report = work.join(format!("{tag}.json"));
    let set_e = format!(
        "edited.output={}",
        s(&work.join(format!("{tag}-edited.exr")))
    );
    let set_r = format!("relit.output={}", s(&work.join(format!("{tag}-relit.exr"))));
    let mut c = Command::new(bin());
    c.args(["run", s(&demo()), "--quiet", "--report", s(&report)])
        .args(["--set", &set_e, "--set", &set_r])
        .args(SMALL)
        .args(extra)
        .env_remove("MATFLOW_TOKEN")
        .env_remove("MATFLOW_CACHE");
    for (k, v) in env {
        c.env(k, v);
    }
    let out = c.output().expect("run matflow");
    let rep = std::fs::read(&report)
        .ok()
        .map(|b| serde_json::from_slice(&b).unwrap());
    (out, rep)
}

fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "matflow run failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn field(r: &Value, f: &str) -> BTreeMap<String, Value> {
    r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|st| (st["name"].as_str().unwrap().to_string(), st[f].clone()))
        .collect()
}

fn stage<'a>(r: &'a Value, name: &str) -> &'a Value {
    r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|st| st["name"] == name)
        .unwrap()
}

fn workers_arg(ws: &[&Worker]) -> String {
    ws.iter()
        .map(|w| w.addr.clone())
        .collect::<Vec<_>>()
        .join(",")
}

#[test]
fn the_demo_on_two_workers_matches_a_local_run_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let casd = Casd::start(&d.join("casd"));
    let w1 = Worker::start(&bin(), &d.join("w1"), &[], &[]);
    let w2 = Worker::start(&bin(), &d.join("w2"), &[], &[]);
    let (out, local) = run(d, "local", &["--cache", s(&d.join("c0"))], &[]);
    ok(&out);
    let local = local.unwrap();
    let ws = workers_arg(&[&w1, &w2]);
    let remote_args = ["--workers", &ws, "--remote-cache", &casd.endpoint];
    let c1 = d.join("c1");
    let mut args = vec!["--cache", s(&c1)];
    args.extend_from_slice(&remote_args);
    let (out, dist) = run(d, "dist", &args, &[]);
    ok(&out);
    let dist = dist.unwrap();
    assert_eq!(field(&local, "outputs"), field(&dist, "outputs"));
    assert_eq!(field(&local, "key"), field(&dist, "key"));
    for f in ["edited.exr", "edited.png", "relit.exr", "relit.png"] {
        assert_eq!(
            std::fs::read(d.join(format!("local-{f}"))).unwrap(),
            std::fs::read(d.join(format!("dist-{f}"))).unwrap(),
            "{f} differs"
        );
    }
    for (name, w) in field(&dist, "worker") {
        let w = w.as_str().unwrap_or("").to_string();
        assert!(w == w1.addr || w == w2.addr, "{name} ran on {w}");
    }
    for (name, st) in field(&dist, "status") {
        assert_eq!(st, "executed", "{name}");
    }
    assert!(dist["executor"].as_str().unwrap().contains(&w1.addr));
    assert!(
        w1.said("start ") && w2.said("start "),
        "both workers got stages"
    );
    // A second submitter with a fresh local cache: everything is served
    // from the shared remote, without running anything.
    let c2 = d.join("c2");
    let mut args = vec!["--cache", s(&c2)];
    args.extend_from_slice(&remote_args);
    let (out, again) = run(d, "again", &args, &[]);
    ok(&out);
    let again = again.unwrap();
    for (name, st) in field(&again, "status") {
        assert_eq!(st, "cached", "{name}");
    }
    assert_eq!(field(&again, "outputs"), field(&local, "outputs"));
    assert!(
        again["bytes_downloaded"].as_u64().unwrap() > 0,
        "render outputs were fetched"
    );
}

/// The run goes on in the background while `act` does something to the
/// worker that took `recovered` (the longest stage).
fn disrupt(d: &Path, extra: &[&str], act: impl Fn(&Worker)) -> (Value, Value) {
    let casd = Casd::start(&d.join("casd"));
    let w1 = Worker::start(&bin(), &d.join("w1"), &[], &[]);
    let w2 = Worker::start(&bin(), &d.join("w2"), &[], &[]);
    let long = ["--set", "recovered.budget_seconds=8"];
    let c0 = d.join("c0");
    let mut la = vec!["--cache", s(&c0)];
    la.extend_from_slice(&long);
    let (out, local) = run(d, "local", &la, &[]);
    ok(&out);
    let ws = workers_arg(&[&w1, &w2]);
    let cache = d.join("c1");
    let report = d.join("dist.json");
    let mut c = Command::new(bin());
    c.args(["run", s(&demo()), "--quiet", "--report", s(&report)])
        .args([
            "--cache",
            s(&cache),
            "--workers",
            &ws,
            "--remote-cache",
            &casd.endpoint,
        ])
        .args(SMALL)
        .args(long)
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let child = c.spawn().unwrap();
    let t0 = std::time::Instant::now();
    let victim = loop {
        if w1.said("start recovered") {
            break &w1;
        }
        if w2.said("start recovered") {
            break &w2;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "no worker started `recovered`"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    // Let it get going, then strike.
    std::thread::sleep(Duration::from_millis(300));
    act(victim);
    let out = child.wait_with_output().unwrap();
    ok(&out);
    let dist: Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let other = if std::ptr::eq(victim, &w1) { &w2 } else { &w1 };
    let rec = stage(&dist, "recovered");
    assert_eq!(rec["worker"], other.addr.as_str(), "{rec}");
    (local.unwrap(), dist)
}

#[test]
fn a_worker_killed_mid_stage_loses_it_to_the_other_with_identical_results() {
    let dir = tempfile::tempdir().unwrap();
    let (local, dist) = disrupt(dir.path(), &[], |w| w.signal("-KILL"));
    let rec = stage(&dist, "recovered");
    assert!(rec["attempts"].as_u64().unwrap() >= 2, "{rec}");
    let retries = rec["retries"].as_array().unwrap();
    assert!(!retries.is_empty(), "{rec}");
    assert_eq!(field(&local, "outputs"), field(&dist, "outputs"));
    assert_eq!(field(&local, "key"), field(&dist, "key"));
}

#[test]
fn a_hung_worker_misses_its_heartbeats_and_the_stage_moves() {
    let dir = tempfile::tempdir().unwrap();
    let (local, dist) = disrupt(dir.path(), &["--heartbeat-timeout", "1.5"], |w| {
        w.signal("-STOP")
    });
    let rec = stage(&dist, "recovered");
    let retries = rec["retries"].as_array().unwrap();
    assert!(
        retries
            .iter()
            .any(|r| r.as_str().unwrap().contains("silent")),
        "{rec}"
    );
    assert_eq!(field(&local, "outputs"), field(&dist, "outputs"));
}

#[test]
fn a_wrong_or_missing_token_is_refused_before_anything_runs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let casd = Casd::start(&d.join("casd"));
    let tok = d.join("token");
    std::fs::write(&tok, "right-token-0123456789\n").unwrap();
    let w = Worker::start(&bin(), &d.join("w"), &["--token-file", s(&tok)], &[]);
    let ws = w.addr.clone();
    let c = d.join("c");
    let args = [
        "--cache",
        s(&c),
        "--workers",
        &ws,
        "--remote-cache",
        &casd.endpoint,
    ];
    for env in [vec![("MATFLOW_TOKEN", "wrong-token-0123456789")], vec![]] {
        let (out, rep) = run(d, "bad", &args, &env);
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("refused this run's token"), "{err}");
        assert!(rep.is_none(), "nothing ran, no report");
    }
    assert!(!w.said("start "), "the worker executed nothing");
    // The right token, from the environment: it runs.
    let (out, _) = run(
        d,
        "good",
        &args,
        &[("MATFLOW_TOKEN", "right-token-0123456789")],
    );
    ok(&out);
    assert!(w.said("start "));
    // A token never appears on a command line: there is no flag for it,
    // and a worker on a non-loopback address refuses to start without one.
    let o = Command::new(bin())
        .args([
            "worker",
            "--listen",
            "0.0.0.0:0",
            "--cache",
            s(&d.join("w2")),
        ])
        .env_remove("MATFLOW_TOKEN")
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--insecure"));
}

fn sha256_hex(b: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(b)
        .iter()
        .map(|x| format!("{x:02x}"))
        .collect()
}

#[test]
fn a_corrupt_blob_served_by_the_remote_store_is_detected_and_recomputed() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let casd = Casd::start(&d.join("casd"));
    let c1 = d.join("c1");
    let (out, first) = run(
        d,
        "first",
        &["--cache", s(&c1), "--remote-cache", &casd.endpoint],
        &[],
    );
    ok(&out);
    let first = first.unwrap();
    // Flip a byte of the mesh in the server's own storage.
    let mesh = field(&first, "outputs")["mesh"]["mesh"]
        .as_str()
        .unwrap()
        .to_string();
    let local_blob = c1.join("blobs").join(&mesh[..2]).join(&mesh[2..]);
    let bytes = std::fs::read(&local_blob).unwrap();
    let obj = casd.object_path(&sha256_hex(&bytes));
    let mut bad = std::fs::read(&obj).expect("casd holds the mesh");
    let mid = bad.len() / 2;
    bad[mid] ^= 0x20;
    let mut perm = std::fs::metadata(&obj).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    perm.set_readonly(false);
    std::fs::set_permissions(&obj, perm).unwrap();
    std::fs::write(&obj, &bad).unwrap();
    // A fresh submitter re-edits: the edit's render needs the mesh bytes.
    let (out, second) = run(
        d,
        "second",
        &[
            "--cache",
            s(&d.join("c2")),
            "--remote-cache",
            &casd.endpoint,
            "--set",
            "shiny.roughness=0.4",
        ],
        &[],
    );
    ok(&out);
    let second = second.unwrap();
    let m = stage(&second, "mesh");
    assert_eq!(m["status"], "executed", "{m}");
    assert!(
        m["retries"].as_array().is_some_and(|r| !r.is_empty()),
        "{second}"
    );
    assert_eq!(
        m["outputs"],
        stage(&first, "mesh")["outputs"],
        "the same bytes again"
    );
    assert_eq!(stage(&second, "edited")["status"], "executed");
    assert_eq!(
        stage(&second, "relit")["outputs"],
        stage(&first, "relit")["outputs"]
    );
}

#[test]
fn a_submitter_killed_mid_run_and_restarted_finishes_from_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let casd = Casd::start(&d.join("casd"));
    let w = Worker::start(&bin(), &d.join("w"), &[], &[]);
    let (out, local) = run(d, "local", &["--cache", s(&d.join("c0"))], &[]);
    ok(&out);
    let local = local.unwrap();
    let cache = d.join("c1");
    let remote = [
        "--cache",
        s(&cache),
        "--workers",
        &w.addr,
        "--remote-cache",
        &casd.endpoint,
    ];
    // The first submitter dies (SIGKILL) once the worker is on the
    // material recovery, with scene, mesh and lighting done.
    let set_e = format!("edited.output={}", s(&d.join("killed-edited.exr")));
    let set_r = format!("relit.output={}", s(&d.join("killed-relit.exr")));
    let mut first = Command::new(bin())
        .args([
            "run",
            s(&demo()),
            "--quiet",
            "--set",
            &set_e,
            "--set",
            &set_r,
        ])
        .args(SMALL)
        .args(remote)
        .env_remove("MATFLOW_TOKEN")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    assert!(
        w.wait_for("start recovered", Duration::from_secs(120)),
        "the worker never started `recovered`"
    );
    first.kill().unwrap();
    first.wait().unwrap();
    // The restarted run finds what the store holds and finishes.
    let (out, again) = run(d, "again", &remote, &[]);
    ok(&out);
    let again = again.unwrap();
    let status = field(&again, "status");
    for st in ["scene", "mesh", "lighting"] {
        assert_eq!(status[st], "cached", "{st} was redone after the restart");
    }
    assert_eq!(field(&local, "outputs"), field(&again, "outputs"));
    for f in ["edited.exr", "relit.exr"] {
        assert_eq!(
            std::fs::read(d.join(format!("local-{f}"))).unwrap(),
            std::fs::read(d.join(format!("again-{f}"))).unwrap(),
            "{f} differs"
        );
    }
}
