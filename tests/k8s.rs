//! The Kubernetes manifests in `cluster/k8s/`, validated offline by
//! `cluster/k8s/check.py`: rendered with `kubectl kustomize`, checked
//! strictly against the Kubernetes 1.32 API schema (`kubernetes-validate`
//! from PyPI), and cross-checked (Secrets, volumes, Services and ports the
//! pods and matflow's arguments name exist; the Indexed Job's completions
//! are its shards). Each check is also shown to fail on a broken copy.
//!
//! Needs kubectl and `pip install kubernetes-validate`; `.ci/run`
//! installs what is missing. Missing tools fail the test, naming them.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn k8s() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../cluster/k8s")
}

fn check(dir: &Path) -> Output {
    let out = Command::new("python3")
        .arg(k8s().join("check.py"))
        .arg(dir)
        .output()
        .expect("python3");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !err.contains("not found") && !err.contains("No module named"),
        "the manifest check needs kubectl and `pip install kubernetes-validate` \
         (.ci/run installs them): {err}"
    );
    out
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A copy of cluster/k8s with one file edited.
fn broken(file: &str, from: &str, to: &str) -> tempfile::TempDir {
    let t = tempfile::tempdir().unwrap();
    for e in std::fs::read_dir(k8s()).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), t.path().join(e.file_name())).unwrap();
        }
    }
    let p = t.path().join(file);
    let s = std::fs::read_to_string(&p).unwrap();
    assert!(s.contains(from), "{file} no longer contains {from:?}");
    std::fs::write(&p, s.replacen(from, to, 1)).unwrap();
    t
}

#[test]
fn manifests_render_and_validate_strictly() {
    let out = check(&k8s());
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    for kind in [
        "Deployment/matflow-cache",
        "Deployment/matflow-worker",
        "Service/matflow-worker",
        "Job/matflow-turntable-shards",
        "Secret/matflow-token",
    ] {
        assert!(
            said.contains(kind),
            "{kind} missing from the render: {said}"
        );
    }
}

#[test]
fn broken_manifests_are_caught() {
    let cases = [
        // A field the API does not have (strict schema).
        (
            "workers.yaml",
            "readinessProbe:",
            "readinessProbez:",
            "readinessProbez",
        ),
        // Shards and completions disagree.
        (
            "shards-job.yaml",
            "completions: 8",
            "completions: 6",
            "--shards=8 but completions 6",
        ),
        // A Service pointing at a port no pod declares.
        (
            "workers.yaml",
            "targetPort: node",
            "targetPort: nodes",
            "targetPort nodes",
        ),
        // A worker that would listen without its token.
        (
            "workers.yaml",
            "            - --token-file=/var/run/matflow/token\n",
            "",
            "without a token",
        ),
        // The submitter naming a store Service that does not exist.
        (
            "run-job.yaml",
            "--remote-cache=grpc://matflow-cache:9092",
            "--remote-cache=grpc://matflow-store:9092",
            "no Service matflow-store",
        ),
    ];
    for (file, from, to, expect) in cases {
        let t = broken(file, from, to);
        let out = check(t.path());
        let said = text(&out);
        assert!(
            !out.status.success(),
            "{file}: {from:?} → {to:?} passed: {said}"
        );
        assert!(
            said.contains(expect),
            "{file}: expected {expect:?} in: {said}"
        );
    }
}
