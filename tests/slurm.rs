//! The Slurm launchers in `cluster/slurm/`, run on a real single-node
//! Slurm (Debian's slurmctld, slurmd, slurm-client and munge, brought up
//! in a temporary folder by `cluster/slurm/testbed.sh`).
//!
//! What must hold: a job array of shards (`submit-shards.sh`: one task per
//! shard, then a merge job after all of them) writes every output file,
//! byte-identical to a local run, each shard rendering only its own
//! outputs and the merge finding everything in the store; and
//! `workers.sbatch` starts workers with srun on the allocation and runs a
//! pipeline on them with the same bytes. Job states are polled with
//! `squeue` and read with `scontrol` (no accounting database here); the
//! files are checked, not only the exit codes.
//!
//! Needs root (slurmd runs jobs as their users) and the packages: the test
//! fails, naming them, when they are missing; `.ci/run` installs them.

mod support;
use support::{repo, s};

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::Value;

fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_matflow"))
}

/// A single-node Slurm in a folder; stopped on drop.
struct Testbed {
    dir: PathBuf,
    conf: PathBuf,
}

impl Testbed {
    fn start(dir: &Path) -> Testbed {
        let uid = Command::new("id").arg("-u").output().expect("id -u");
        assert_eq!(
            String::from_utf8_lossy(&uid.stdout).trim(),
            "0",
            "the Slurm test brings up slurmd, which needs root"
        );
        for b in [
            "munged",
            "slurmctld",
            "slurmd",
            "sbatch",
            "squeue",
            "scontrol",
        ] {
            let found = Command::new("sh")
                .args(["-c", &format!("command -v {b} || test -x /usr/sbin/{b}")])
                .output()
                .map(|o| o.status.success())
                .unwrap_or(false);
            assert!(
                found,
                "{b} not found: the Slurm test needs `apt-get install slurmctld slurmd \
                 slurm-client munge` (.ci/run installs them)"
            );
        }
        let out = Command::new(repo().join("cluster/slurm/testbed.sh"))
            .args(["start", s(dir)])
            .output()
            .expect("running testbed.sh");
        let tb = Testbed {
            dir: dir.to_path_buf(),
            conf: dir.join("slurm.conf"),
        };
        std::fs::create_dir_all(dir.join("tmp")).unwrap();
        assert!(
            out.status.success(),
            "testbed.sh start failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        tb
    }

    fn cmd(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf)
            .env("MATFLOW_BIN", bin())
            .env("MATFLOW_CASD", support::casd_binary())
            .env("TMPDIR", self.dir.join("tmp"))
            .env_remove("MATFLOW_TOKEN")
            .env_remove("MATFLOW_REMOTE_CACHE")
            .env_remove("MATFLOW_WORKER_CACHE");
        c
    }

    /// Waits until none of these jobs is pending or running, then returns
    /// each job's (or array task's) state and exit code from scontrol.
    fn wait(&self, jobs: &[&str], limit: Duration) -> BTreeMap<String, (String, String)> {
        let t0 = Instant::now();
        loop {
            let out = self
                .cmd("squeue")
                .args(["-h", "-o", "%i %T", "-j", &jobs.join(",")])
                .output()
                .expect("squeue");
            let text = String::from_utf8_lossy(&out.stdout).to_string();
            if out.status.success() && text.trim().is_empty() {
                break;
            }
            assert!(
                t0.elapsed() < limit,
                "jobs {jobs:?} still queued after {limit:?}: {text}{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        let mut states = BTreeMap::new();
        for j in jobs {
            let out = self
                .cmd("scontrol")
                .args(["show", "job", "-o", j])
                .output()
                .expect("scontrol");
            for line in String::from_utf8_lossy(&out.stdout).lines() {
                let field = |name: &str| {
                    line.split_whitespace()
                        .find_map(|w| w.strip_prefix(&format!("{name}=")))
                        .unwrap_or("?")
                        .to_string()
                };
                let id = match field("ArrayTaskId").as_str() {
                    "?" => field("JobId"),
                    t => format!("{}_{t}", field("ArrayJobId")),
                };
                states.insert(id, (field("JobState"), field("ExitCode")));
            }
        }
        states
    }

    fn logs(&self) -> String {
        let mut s = String::new();
        for f in ["log/slurmctld.log", "log/slurmd.log"] {
            if let Ok(t) = std::fs::read_to_string(self.dir.join(f)) {
                let tail: Vec<&str> = t.lines().rev().take(15).collect();
                s += &format!("\n--- {f} (last lines)\n");
                for l in tail.into_iter().rev() {
                    s += l;
                    s.push('\n');
                }
            }
        }
        s
    }
}

impl Drop for Testbed {
    fn drop(&mut self) {
        let _ = Command::new(repo().join("cluster/slurm/testbed.sh"))
            .args(["stop", s(&self.dir)])
            .status();
    }
}

/// A small turntable: one 32² room under its sky turned in `n` steps, each
/// render an output written to `out/rotK.exr` beside the file.
fn turntable(dir: &Path, n: usize) -> PathBuf {
    let mut y = String::from("pipeline: turntable-test\noutputs: [");
    y += &(0..n)
        .map(|k| format!("rot{k}"))
        .collect::<Vec<_>>()
        .join(", ");
    y += "]\nstages:\n  scene: {kind: synthetic_scene, seed: 3, size: 32, spp: 4}\n  mesh: {kind: mesh, scene: scene}\n";
    for k in 0..n {
        y += &format!(
            "  sky{k}: {{kind: relight, source: scene.truth_envmap, rotation: {}}}\n  rot{k}: {{kind: render, mesh: mesh, materials: scene.truth, envmap: sky{k}, spp: 4, output: out/rot{k}.exr}}\n",
            k * 360 / n
        );
    }
    std::fs::create_dir_all(dir).unwrap();
    let p = dir.join("turntable.yaml");
    std::fs::write(&p, y).unwrap();
    p
}

fn report(path: &Path) -> Value {
    let text = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_slice(&text).unwrap()
}

fn executed(r: &Value) -> Vec<String> {
    r["stages"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|s| s["status"] == "executed")
        .map(|s| s["name"].as_str().unwrap().to_string())
        .collect()
}

fn local_reference(work: &Path, n: usize) -> BTreeMap<String, Vec<u8>> {
    let p = turntable(&work.join("local"), n);
    let out = Command::new(bin())
        .args([
            "run",
            s(&p),
            "--quiet",
            "--cache",
            s(&work.join("local-cache")),
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (0..n)
        .map(|k| {
            let f = work.join(format!("local/out/rot{k}.exr"));
            (format!("rot{k}"), std::fs::read(&f).unwrap())
        })
        .collect()
}

#[test]
fn job_array_shards_then_merge_and_workers_under_srun() {
    let work = tempfile::tempdir().unwrap();
    let work = work.path();
    let tb = Testbed::start(&work.join("slurm"));
    let n = 6;
    let reference = local_reference(work, n);

    // --- A job array of 3 shards, then a merge job (afterok), sharing a
    // store folder as they would on a shared filesystem.
    let arr = work.join("array");
    let p = turntable(&arr, n);
    let reports = arr.join("reports");
    let store = arr.join("store");
    let out = tb
        .cmd("bash")
        .arg(repo().join("cluster/slurm/submit-shards.sh"))
        .args([s(&p), "3", "--cache", s(&store)])
        .env("MATFLOW_REPORT_DIR", &reports)
        .current_dir(&arr)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "submit-shards.sh: {said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // "shards: job A (array 0-2); merge: job M (…)"
    let ids: Vec<&str> = said
        .split_whitespace()
        .filter(|w| w.chars().all(|c| c.is_ascii_digit()) && !w.is_empty())
        .collect();
    assert_eq!(ids.len(), 2, "two job ids in: {said}");
    let states = tb.wait(&ids, Duration::from_secs(240));
    for t in 0..3 {
        let st = &states[&format!("{}_{t}", ids[0])];
        assert_eq!(st.0, "COMPLETED", "array task {t}: {st:?}{}", tb.logs());
        assert_eq!(st.1, "0:0");
    }
    assert_eq!(
        states[ids[1]].0,
        "COMPLETED",
        "merge job: {:?}{}",
        states[ids[1]],
        tb.logs()
    );
    // Each shard rendered exactly its own outputs: shard i has rot i, i+3.
    for i in 0..3 {
        let r = report(&reports.join(format!("shard-{i}.json")));
        let renders: Vec<String> = executed(&r)
            .into_iter()
            .filter(|n| n.starts_with("rot"))
            .collect();
        let mine: Vec<String> = (0..n)
            .filter(|k| k % 3 == i)
            .map(|k| format!("rot{k}"))
            .collect();
        assert_eq!(renders, mine, "shard {i} rendered {renders:?}");
    }
    // The merge found every stage in the store and wrote every file.
    let merged = report(&reports.join("merge.json"));
    assert!(
        executed(&merged).is_empty(),
        "the merge had to execute {:?}",
        executed(&merged)
    );
    for (name, bytes) in &reference {
        let f = arr.join(format!("out/{name}.exr"));
        let got = std::fs::read(&f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
        assert!(
            got == *bytes,
            "{name}: the array's file differs from the local run"
        );
    }

    // --- A dataset spec is a pipeline to the same scripts: 3 array tasks
    // each write their tar shards, the merge job checks and indexes them;
    // the bytes are those of one local process.
    let ds = work.join("dataset");
    std::fs::create_dir_all(&ds).unwrap();
    let spec = ds.join("spec.yaml");
    std::fs::write(
        &spec,
        "dataset:\n  name: tiny\n  generator: refraction\n  samples: 6\n  seed: 2\n  \
         shard_size: 2\n  out: out\n  params: {size: 24, spp: 2, procedural_envmaps: 2}\n",
    )
    .unwrap();
    let local = Command::new(bin())
        .args(["dataset", s(&spec), "--quiet", "--out"])
        .arg(ds.join("local"))
        .arg("--cache")
        .arg(ds.join("local-cache"))
        .output()
        .unwrap();
    assert!(
        local.status.success(),
        "{}",
        String::from_utf8_lossy(&local.stderr)
    );
    let ds_reports = ds.join("reports");
    let out = tb
        .cmd("bash")
        .arg(repo().join("cluster/slurm/submit-shards.sh"))
        .args([s(&spec), "3", "--cache", s(&ds.join("store"))])
        .env("MATFLOW_REPORT_DIR", &ds_reports)
        .current_dir(&ds)
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "submit-shards.sh (dataset): {said}");
    let ids: Vec<&str> = said
        .split_whitespace()
        .filter(|w| w.chars().all(|c| c.is_ascii_digit()) && !w.is_empty())
        .collect();
    let states = tb.wait(&ids, Duration::from_secs(240));
    for t in 0..3 {
        let st = &states[&format!("{}_{t}", ids[0])];
        assert_eq!(st.0, "COMPLETED", "dataset task {t}: {st:?}{}", tb.logs());
    }
    assert_eq!(
        states[ids[1]].0,
        "COMPLETED",
        "dataset merge: {}",
        tb.logs()
    );
    let merged = report(&ds_reports.join("merge.json"));
    assert_eq!(merged["stages_executed"], 0, "the merge recomputed samples");
    for f in [
        "dataset.json",
        "manifest.jsonl",
        "index.json",
        "tiny-000000.tar",
        "tiny-000001.tar",
        "tiny-000002.tar",
    ] {
        assert!(
            std::fs::read(ds.join("out").join(f)).ok()
                == std::fs::read(ds.join("local").join(f)).ok(),
            "{f}: the array's dataset differs from one local process"
        );
    }

    // --- workers.sbatch: two workers started by srun, the run against them
    // (buildbox-casd started by the script as the store, a token made for
    // the job).
    let wk = work.join("workers");
    let p = turntable(&wk, n);
    let job_dir = wk.join("job");
    let out = tb
        .cmd("sbatch")
        .args(["--parsable", "--ntasks=2", "--cpus-per-task=1", "-o"])
        .arg(wk.join("slurm-%j.out"))
        .arg(repo().join("cluster/slurm/workers.sbatch"))
        .args([s(&p), "--cache", s(&wk.join("submitter-cache"))])
        .env("MATFLOW_JOB_DIR", &job_dir)
        .current_dir(&wk)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "sbatch workers.sbatch: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let states = tb.wait(&[&id], Duration::from_secs(240));
    let job_out = std::fs::read_to_string(wk.join(format!("slurm-{id}.out"))).unwrap_or_default();
    assert_eq!(
        states[&id].0,
        "COMPLETED",
        "workers.sbatch: {:?}\n{job_out}{}",
        states[&id],
        tb.logs()
    );
    let r = report(&job_dir.join("report.json"));
    let mut ran_on = std::collections::BTreeSet::new();
    for st in r["stages"].as_array().unwrap() {
        if st["status"] == "executed" {
            let w = st["worker"].as_str().unwrap_or("local").to_string();
            assert_ne!(
                w, "local",
                "{} ran in the batch step: {job_out}",
                st["name"]
            );
            ran_on.insert(w);
        }
    }
    assert_eq!(
        ran_on.len(),
        2,
        "stages ran on {ran_on:?}, not on both workers"
    );
    let token = std::fs::metadata(job_dir.join("token")).unwrap();
    use std::os::unix::fs::PermissionsExt;
    assert_eq!(
        token.permissions().mode() & 0o077,
        0,
        "the job token is private"
    );
    for (name, bytes) in &reference {
        let got = std::fs::read(wk.join(format!("out/{name}.exr"))).unwrap();
        assert!(
            got == *bytes,
            "{name}: the workers' file differs from the local run"
        );
    }
}
