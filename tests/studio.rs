//! `matflow studio` over HTTP: the page and its script come from the
//! binary; the session's pipeline runs on the engine and its maps are
//! served by fixed names; nothing else on disk is reachable; a token is
//! required off loopback and, when set, of every request.

mod support;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use support::{s, scratch};

/// A studio process, killed when dropped.
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

fn start(dir: &Path, input: &Path, extra: &[&str], env: &[(&str, &str)]) -> Studio {
    let addr_file = dir.join("address");
    let _ = std::fs::remove_file(&addr_file);
    let mut c = Command::new(env!("CARGO_BIN_EXE_matflow"));
    c.args(["studio", s(input), "--listen", "127.0.0.1:0"])
        .args([
            "--cache",
            s(&dir.join("cache")),
            "--session",
            s(&dir.join("session")),
        ])
        .args(["--address-file", s(&addr_file)])
        .args(extra)
        .env_remove("MATFLOW_TOKEN")
        .stdout(Stdio::null());
    for (k, v) in env {
        c.env(k, v);
    }
    // Started in `dir`, so that an input given relative to it is taken
    // from there (not from the session's folder).
    c.current_dir(dir);
    let child = c.spawn().expect("start matflow studio");
    let t0 = Instant::now();
    while !addr_file.is_file() {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "the studio did not start"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let addr = std::fs::read_to_string(&addr_file).unwrap();
    Studio { child, addr }
}

/// `GET path` (with `headers`): the status code and the body.
fn get(addr: &str, path: &str, headers: &[&str]) -> (u16, Vec<u8>) {
    let mut t = TcpStream::connect(addr).unwrap();
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for h in headers {
        req += &format!("{h}\r\n");
    }
    req += "\r\n";
    t.write_all(req.as_bytes()).unwrap();
    let mut buf = Vec::new();
    t.read_to_end(&mut buf).unwrap();
    let split = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("an HTTP answer");
    let head = String::from_utf8_lossy(&buf[..split]).to_string();
    let code: u16 = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    let mut body = buf[split + 4..].to_vec();
    if head.to_lowercase().contains("transfer-encoding: chunked") {
        body = unchunk(&body);
    }
    (code, body)
}

fn unchunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let Some(eol) = b.windows(2).position(|w| w == b"\r\n") else {
            return out;
        };
        let n = usize::from_str_radix(String::from_utf8_lossy(&b[..eol]).trim(), 16).unwrap_or(0);
        if n == 0 {
            return out;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + n]);
        b = &b[eol + 2 + n + 2..];
    }
}

fn session_json(addr: &str, headers: &[&str]) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let (code, body) = get(addr, "/api/session", headers);
        assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        if v["state"] != "running" {
            return v;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "still running: {v}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn synth_bundle(dir: &Path) -> std::path::PathBuf {
    let b = dir.join("room");
    let o = support::matflow(
        &[
            "synth",
            "--seed",
            "4",
            "--size",
            "32",
            "--spp",
            "2",
            "--out",
            s(&b),
        ],
        None,
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    b
}

#[test]
fn the_studio_serves_its_page_and_the_sessions_maps_and_nothing_else() {
    let dir = scratch("studio", "serve");
    synth_bundle(&dir);
    let st = start(&dir, Path::new("room"), &[], &[]);
    let (code, page) = get(&st.addr, "/", &[]);
    assert_eq!(code, 200);
    let page = String::from_utf8_lossy(&page);
    assert!(page.contains("<title>matflow studio</title>"), "{page}");
    assert_eq!(get(&st.addr, "/studio.js", &[]).0, 200);
    // The session's pipeline runs on the engine; its maps are PNGs of the
    // bundle's size.
    let v = session_json(&st.addr, &[]);
    assert_eq!(v["state"], "ready", "{v}");
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(32), Some(32))
    );
    let names: Vec<&str> = v["maps"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|m| m.as_str())
        .collect();
    for want in ["photo", "albedo", "roughness", "metallic", "depth"] {
        assert!(names.contains(&want), "{names:?}");
        let (code, png) = get(&st.addr, &format!("/api/maps/{want}.png"), &[]);
        assert_eq!(code, 200, "{want}");
        let img = image::load_from_memory(&png).unwrap();
        assert_eq!((img.width(), img.height()), (32, 32), "{want}");
    }
    // The session is a pipeline: exported, it runs as `matflow run`, from
    // the cache the studio filled.
    let (code, yaml) = get(&st.addr, "/api/pipeline.yaml", &[]);
    assert_eq!(code, 200);
    let exported = dir.join("exported.yaml");
    std::fs::write(&exported, &yaml).unwrap();
    let o = support::matflow(
        &[
            "run",
            s(&exported),
            "--quiet",
            "--cache",
            s(&dir.join("cache")),
        ],
        None,
    );
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success() && out.contains("1 cached"), "{out}");
    // Nothing outside its own names: not by path, not by escape.
    for bad in [
        "/api/maps/../../etc/passwd",
        "/api/maps/..%2f..%2fetc%2fpasswd",
        "/api/maps/albedo.exr",
        "/api/maps/secret.png",
        "/session/session.yaml",
        "/etc/passwd",
    ] {
        let (code, body) = get(&st.addr, bad, &[]);
        assert_eq!(code, 404, "{bad}: {}", String::from_utf8_lossy(&body));
        assert!(!String::from_utf8_lossy(&body).contains("root:"), "{bad}");
    }
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn off_loopback_a_token_is_required_and_then_asked_of_every_request() {
    let dir = scratch("studio", "token");
    let b = synth_bundle(&dir);
    // Any address but loopback, without a token: refused at the start.
    let o = Command::new(env!("CARGO_BIN_EXE_matflow"))
        .args(["studio", s(&b), "--listen", "0.0.0.0:0"])
        .args([
            "--cache",
            s(&dir.join("cache")),
            "--session",
            s(&dir.join("session")),
        ])
        .env_remove("MATFLOW_TOKEN")
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("reachable from other machines") && e.contains("token"),
        "{e}"
    );
    // With a token, every request presents it.
    let secret = "0123456789abcdef-studio";
    let st = start(&dir, &b, &[], &[("MATFLOW_TOKEN", secret)]);
    assert_eq!(get(&st.addr, "/", &[]).0, 401);
    assert_eq!(
        get(
            &st.addr,
            "/api/session",
            &["Authorization: Bearer wrong-token-000000"]
        )
        .0,
        401
    );
    let bearer = format!("Authorization: Bearer {secret}");
    assert_eq!(get(&st.addr, "/api/session", &[&bearer]).0, 200);
    assert_eq!(get(&st.addr, &format!("/?token={secret}"), &[]).0, 200);
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The page in headless Chromium (Debian's `chromium`), as a user opens
/// it: its script polls the session until the pipeline has run and shows
/// every map; the page after its script ran has them all, and its
/// screenshot is kept under the target folder for a person to look at.
#[test]
fn chromium_shows_the_sessions_maps() {
    let chromium = ["chromium", "chromium-browser"]
        .into_iter()
        .find(|c| {
            Command::new(c)
                .arg("--version")
                .output()
                .is_ok_and(|o| o.status.success())
        })
        .expect("no chromium: install Debian's chromium (`.ci/run` does)");
    let dir = scratch("studio", "chromium");
    synth_bundle(&dir);
    let st = start(&dir, Path::new("room"), &[], &[]);
    assert_eq!(session_json(&st.addr, &[])["state"], "ready");
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("studio");
    std::fs::create_dir_all(&shots).unwrap();
    let shot = shots.join("bundle.png");
    let _ = std::fs::remove_file(&shot);
    let browse = |what: &str| {
        let o = Command::new(chromium)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--window-size=1400,500",
                "--virtual-time-budget=10000",
            ])
            .arg(format!(
                "--user-data-dir={}",
                s(&dir.join(format!("profile-{}", what.len())))
            ))
            .arg(what)
            .arg(format!("http://{}/", st.addr))
            .output()
            .expect("run chromium");
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let dom = browse("--dump-dom");
    assert!(dom.contains("status ready"), "{dom}");
    for name in ["photo", "albedo", "roughness", "metallic", "depth"] {
        assert!(
            dom.contains(&format!("src=\"api/maps/{name}.png\"")),
            "{name} missing from the page:\n{dom}"
        );
    }
    browse(&format!("--screenshot={}", s(&shot)));
    let img = image::open(&shot).expect("a screenshot");
    assert_eq!((img.width(), img.height()), (1400, 500));
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}
