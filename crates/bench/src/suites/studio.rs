//! `matflow-bench studio`: the studio's latencies over its API, as the
//! page sees them. A `matflow studio` child opens the procedural room at
//! `--size`² (recovery at a small budget: not what is timed here), one
//! click selects the red box, and `--edits` material changes follow, each
//! different (nothing is served from the cache): the time from the change
//! to its first preview and to its converged result (the studio's own
//! clock, and the client's, polling every 5 ms), the first change after
//! opening apart. Then a sphere is inserted and moved `--edits` times,
//! timed alike, and `--edits` + 1 times moved again half a second into
//! the result of the move before (which the newer move stops). Then: the
//! studio's memory, its CPU time over an idle
//! `--idle` seconds, and whether the exported session, run by `matflow
//! run` on an empty cache, writes the studio's EXR byte for byte.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use serde_json::{json, Value};

use crate::harness::{matflow_exe, median, path_arg};

#[derive(Args)]
pub struct BenchStudioArgs {
    /// Image side in pixels.
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Material changes timed (after the first).
    #[arg(long, default_value_t = 7)]
    pub edits: usize,
    /// Seconds the idle studio is watched for CPU use.
    #[arg(long, default_value_t = 5.0)]
    pub idle: f64,
    /// Working folder (input, cache, session, export).
    #[arg(long, default_value = "/tmp/matflow-bench-studio")]
    pub work: PathBuf,
}

struct Studio {
    child: Child,
    addr: String,
}

impl Drop for Studio {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `METHOD path` (a JSON body) on `addr`: status and body.
fn http(addr: &str, method: &str, path: &str, body: Option<Value>) -> Result<(u16, Vec<u8>)> {
    let mut t = TcpStream::connect(addr).with_context(|| addr.to_string())?;
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    write!(
        t,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\
         Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )?;
    let mut buf = Vec::new();
    t.read_to_end(&mut buf)?;
    let split = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .context("not an HTTP answer")?;
    let head = String::from_utf8_lossy(&buf[..split]).to_lowercase();
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .context("no status")?;
    let mut body = buf[split + 4..].to_vec();
    if head.contains("transfer-encoding: chunked") {
        body = unchunk(&body);
    }
    Ok((code, body))
}

fn unchunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    while let Some(eol) = b.windows(2).position(|w| w == b"\r\n") {
        let n = usize::from_str_radix(String::from_utf8_lossy(&b[..eol]).trim(), 16).unwrap_or(0);
        if n == 0 || b.len() < eol + 2 + n {
            break;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + n]);
        b = &b[(eol + 4 + n).min(b.len())..];
    }
    out
}

fn status(addr: &str) -> Result<Value> {
    let (code, body) = http(addr, "GET", "/api/session", None)?;
    if code != 200 {
        bail!("/api/session: {code}");
    }
    Ok(serde_json::from_slice(&body)?)
}

/// Polls until `done(status)`; the status and the client's seconds.
fn until(
    addr: &str,
    t0: Instant,
    limit: f64,
    done: impl Fn(&Value) -> bool,
) -> Result<(Value, f64)> {
    loop {
        let v = status(addr)?;
        if v["state"] == "failed" {
            bail!("the studio failed: {}", v["message"]);
        }
        if done(&v) {
            return Ok((v, t0.elapsed().as_secs_f64()));
        }
        if t0.elapsed().as_secs_f64() > limit {
            bail!("waited {limit} s: {v}");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Waits for generation `generation`'s preview and result: their
/// seconds by the studio's clock, then by the client's from `t0`.
fn timed(addr: &str, t0: Instant, generation: u64) -> Result<(f64, f64, f64, f64)> {
    let (_, preview) = until(addr, t0, 300.0, |v| v["shown"] == generation)?;
    let (v, result) = until(addr, t0, 300.0, |v| {
        v["shown"] == generation && v["image"] == "result"
    })?;
    Ok((
        v["preview_seconds"].as_f64().unwrap_or(f64::NAN),
        v["result_seconds"].as_f64().unwrap_or(f64::NAN),
        preview,
        result,
    ))
}

/// The room pipeline the studio opens (the procedural room of
/// `pipelines/demo.yaml`, its recovery at 2 + 4 s budgets).
fn room(dir: &Path, size: usize) -> Result<PathBuf> {
    let f = dir.join("room.yaml");
    std::fs::write(
        &f,
        format!(
            "pipeline: room\noutputs: [recovered]\nstages:\n  scene:\n    kind: synthetic_scene\n    \
             seed: 1\n    size: {size}\n    spp: 32\n  mesh:\n    kind: mesh\n    scene: scene\n    \
             complete: none\n  lighting:\n    kind: envmap_opt\n    scene: scene\n    mesh: mesh\n    \
             budget_seconds: 2\n    trust_rm: true\n  recovered:\n    kind: material_opt\n    \
             scene: scene\n    mesh: mesh\n    envmap: lighting\n    budget_seconds: 4\n    \
             trust_rm: true\n"
        ),
    )?;
    Ok(f)
}

/// CPU seconds (user + system) of process `pid` so far.
fn cpu_seconds(pid: u32) -> Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    let after = stat.rsplit_once(')').map(|x| x.1).unwrap_or_default();
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = f[11].parse::<f64>()? + f[12].parse::<f64>()?;
    Ok(ticks / 100.0)
}

/// Resident and peak memory of `pid`, MiB.
fn memory_mib(pid: u32) -> Result<(f64, f64)> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let kb = |key: &str| -> f64 {
        s.lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
            / 1024.0
    };
    Ok((kb("VmRSS:"), kb("VmHWM:")))
}

/// A table of timings (preview and result, by the studio's clock and the
/// client's), one row per `rows` entry named by `what`, and the medians
/// of all rows but the first (which is printed apart).
fn table(head: &str, rows: &[(f64, f64, f64, f64)], what: impl Fn(usize) -> String) {
    outln!("| {head} | preview (studio) | result, 64 spp (studio) | preview (client) | result (client) |");
    outln!("|---|---|---|---|---|");
    for (i, r) in rows.iter().enumerate() {
        outln!(
            "| {} | {:.3} s | {:.3} s | {:.3} s | {:.3} s |",
            what(i),
            r.0,
            r.1,
            r.2,
            r.3
        );
    }
    let col = |f: fn(&(f64, f64, f64, f64)) -> f64| median(rows[1..].iter().map(f).collect());
    outln!(
        "| **median of {}** | **{:.3} s** | **{:.3} s** | **{:.3} s** | **{:.3} s** |",
        rows.len() - 1,
        col(|r| r.0),
        col(|r| r.1),
        col(|r| r.2),
        col(|r| r.3)
    );
    outln!();
}

pub fn bench_studio(a: BenchStudioArgs) -> Result<()> {
    let exe = matflow_exe()?;
    let _ = std::fs::remove_dir_all(&a.work);
    std::fs::create_dir_all(&a.work)?;
    let input = room(&a.work, a.size)?;
    let addr_file = a.work.join("address");
    let t_open = Instant::now();
    let child = Command::new(&exe)
        .args(["studio", &path_arg(&input), "--listen", "127.0.0.1:0"])
        .args(["--cache", &path_arg(&a.work.join("cache"))])
        .args(["--session", &path_arg(&a.work.join("session"))])
        .args(["--address-file", &path_arg(&addr_file)])
        .stdout(Stdio::null())
        .spawn()
        .context("starting matflow studio")?;
    let pid = child.id();
    while !addr_file.is_file() {
        if t_open.elapsed() > Duration::from_secs(30) {
            bail!("the studio did not start");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let st = Studio {
        child,
        addr: std::fs::read_to_string(&addr_file)?,
    };
    let (_, opened) = until(&st.addr, t_open, 600.0, |v| {
        v["state"] == "ready" && v["image"] == "result"
    })?;
    let scale = a.size as f64 / 256.0;
    let (code, body) = http(
        &st.addr,
        "POST",
        "/api/select",
        Some(json!({"x": 205.0 * scale, "y": 185.0 * scale})),
    )?;
    if code != 200 {
        bail!("select: {}", String::from_utf8_lossy(&body));
    }
    let selected = serde_json::from_slice::<Value>(&body)?["selected"].clone();
    // Each change different from every other (hue steps, a colour, a
    // roughness), so that every one is rendered.
    let change = |i: usize| match i % 3 {
        0 => json!({"hue_shift": 20.0 + 7.0 * i as f64}),
        1 => json!({"albedo": [0.1 + 0.02 * i as f64, 0.5, 0.8]}),
        _ => json!({"roughness": 0.05 + 0.03 * i as f64}),
    };
    let mut rows = Vec::new();
    for i in 0..=a.edits {
        let t0 = Instant::now();
        let (code, body) = http(&st.addr, "POST", "/api/edit", Some(change(i)))?;
        if code != 204 {
            bail!("edit: {}", String::from_utf8_lossy(&body));
        }
        let generation = i as u64 + 1;
        rows.push(timed(&st.addr, t0, generation)?);
    }
    // An object: a sphere stood on the floor, then moved `--edits` times
    // (each to a new place: nothing from the cache).
    let generation0 = a.edits as u64 + 1;
    let mut moves = Vec::new();
    for i in 0..=a.edits {
        let x = (40.0 + 6.0 * i as f64) * scale;
        let body = json!({"objects": [{"mesh": "sphere", "anchor": [x, 236.0 * scale],
            "scale": 0.6, "material": {"type": "principled", "albedo": [0.8, 0.3, 0.2],
            "roughness": 0.3, "metallic": 0.0}}]});
        let t0 = Instant::now();
        let (code, answer) = http(&st.addr, "POST", "/api/insert", Some(body))?;
        if code != 204 {
            bail!("insert: {}", String::from_utf8_lossy(&answer));
        }
        let generation = generation0 + i as u64 + 1;
        moves.push(timed(&st.addr, t0, generation)?);
    }
    // Moves made while the move before renders its result: each stops
    // that render (between tiles) and the newer move's preview follows.
    // (Before the stages could be stopped, the preview waited for the
    // superseded result to finish.)
    let mut interrupted = Vec::new();
    let stopped0 = status(&st.addr)?["stopped"].as_u64().unwrap_or(0);
    let sphere_at = |x: f64| {
        json!({"objects": [{"mesh": "sphere", "anchor": [x * scale, 236.0 * scale],
            "scale": 0.6, "material": {"type": "principled", "albedo": [0.8, 0.3, 0.2],
            "roughness": 0.3, "metallic": 0.0}}]})
    };
    for i in 0..=a.edits {
        let t0 = Instant::now();
        let first = sphere_at(110.0 + 6.0 * i as f64);
        let (code, answer) = http(&st.addr, "POST", "/api/insert", Some(first))?;
        if code != 204 {
            bail!("insert: {}", String::from_utf8_lossy(&answer));
        }
        let generation = status(&st.addr)?["generation"].as_u64().unwrap_or(0);
        until(&st.addr, t0, 300.0, |v| {
            v["shown"] == generation && v["stage"] == "result"
        })?;
        // Half a second into its result, the next move.
        std::thread::sleep(Duration::from_millis(500));
        let t1 = Instant::now();
        let second = sphere_at(113.0 + 6.0 * i as f64);
        let (code, answer) = http(&st.addr, "POST", "/api/insert", Some(second))?;
        if code != 204 {
            bail!("insert: {}", String::from_utf8_lossy(&answer));
        }
        interrupted.push(timed(&st.addr, t1, generation + 1)?);
    }
    let stopped = status(&st.addr)?["stopped"].as_u64().unwrap_or(0) - stopped0;
    let (rss, hwm) = memory_mib(pid)?;
    let cpu0 = cpu_seconds(pid)?;
    std::thread::sleep(Duration::from_secs_f64(a.idle));
    let idle_cpu = cpu_seconds(pid)? - cpu0;
    // The export, on an empty cache.
    let (_, exr) = http(&st.addr, "GET", "/api/images/result.exr", None)?;
    let (_, tar) = http(&st.addr, "GET", "/api/export.tar", None)?;
    let out = a.work.join("export");
    std::fs::create_dir_all(&out)?;
    std::fs::write(out.join("session.tar"), &tar)?;
    let untar = Command::new("tar")
        .args(["-xf", "session.tar"])
        .current_dir(&out)
        .status()?;
    if !untar.success() {
        bail!("tar -xf failed");
    }
    let t_run = Instant::now();
    let run = Command::new(&exe)
        .args(["run", "session.yaml", "--quiet", "--cache"])
        .arg(a.work.join("export-cache"))
        .current_dir(&out)
        .output()?;
    if !run.status.success() {
        bail!("matflow run: {}", String::from_utf8_lossy(&run.stderr));
    }
    let run_seconds = t_run.elapsed().as_secs_f64();
    let identical = std::fs::read(out.join("result.exr"))? == exr;
    drop(st);

    let machine = crate::harness::machine();
    outln!("matflow studio, the procedural room at {0}x{0}: one click selected {selected} px (the red box)", a.size);
    outln!("machine: {machine}");
    outln!("opened (predict… recover, first preview and result): {opened:.1} s");
    outln!();
    table("change", &rows, |i| {
        if i == 0 {
            "first after opening".into()
        } else {
            format!("{i}")
        }
    });
    table("object", &moves, |i| {
        if i == 0 {
            "inserted".into()
        } else {
            format!("moved {i}")
        }
    });
    table(
        "object moved again 0.5 s into its result",
        &interrupted,
        |i| format!("{}", i + 1),
    );
    outln!(
        "renders stopped by a newer move: {stopped} of {}",
        interrupted.len()
    );
    outln!("memory of the open session: {rss:.0} MiB resident, {hwm:.0} MiB peak");
    outln!("idle: {idle_cpu:.2} CPU-seconds in {:.0} s", a.idle);
    outln!(
        "export: `matflow run session.yaml` on an empty cache, {run_seconds:.1} s: result.exr {}",
        if identical {
            "byte-identical to the studio's"
        } else {
            "DIFFERS from the studio's"
        }
    );
    outln!();
    outln!(
        "command: matflow-bench studio --size {} --edits {} --idle {}",
        a.size,
        a.edits,
        a.idle
    );
    if !identical {
        bail!("the export does not reproduce the studio's image");
    }
    Ok(())
}
