//! A small W3C WebDriver client over HTTP/1.1, driving Debian's
//! `chromedriver` and headless `chromium` (both installed by `.ci/run`):
//! the tests start the real browser and click, type and read the page as
//! a user's browser does. A missing browser fails the test with what to
//! install; these tests never skip.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{json, Value};

/// The W3C name of an element reference in JSON.
const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// `METHOD path` with a JSON body on `addr`: the status and the body.
pub fn http(addr: &str, method: &str, path: &str, body: Option<&Value>) -> (u16, Vec<u8>) {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    http_raw(
        addr,
        method,
        path,
        &["Content-Type: application/json"],
        body.as_bytes(),
    )
}

/// `METHOD path` with `headers` and `body` on `addr`: the status and the
/// body.
pub fn http_raw(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[&str],
    body: &[u8],
) -> (u16, Vec<u8>) {
    let mut t = TcpStream::connect(addr).unwrap_or_else(|e| panic!("{addr}: {e}"));
    t.set_read_timeout(Some(Duration::from_secs(120))).unwrap();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for h in headers {
        req += &format!("{h}\r\n");
    }
    req += &format!("Content-Length: {}\r\n\r\n", body.len());
    let mut bytes = req.into_bytes();
    bytes.extend_from_slice(body);
    t.write_all(&bytes).unwrap();
    // Read by the answer's own length: a server may keep the connection
    // open whatever the request asked (chromedriver does).
    let mut buf = Vec::new();
    let mut chunk = [0u8; 65536];
    let (head, body_at, length, chunked) = loop {
        let n = t.read(&mut chunk).unwrap();
        assert!(
            n > 0 || !buf.is_empty(),
            "{addr}: no answer to {method} {path}"
        );
        buf.extend_from_slice(&chunk[..n]);
        if let Some(split) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&buf[..split]).to_lowercase();
            let length = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok());
            let chunked = head.contains("transfer-encoding: chunked");
            break (head, split + 4, length, chunked);
        }
        if n == 0 {
            panic!("{addr}: a truncated answer to {method} {path}");
        }
    };
    let done = |b: &[u8]| match (length, chunked) {
        (Some(l), _) => b.len() >= l,
        (None, true) => b.ends_with(b"0\r\n\r\n"),
        (None, false) => false,
    };
    while !done(&buf[body_at..]) {
        let n = t.read(&mut chunk).unwrap();
        if n == 0 {
            break;
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    let code: u16 = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    let mut body = buf[body_at..].to_vec();
    if let Some(l) = length {
        body.truncate(l);
    } else if chunked {
        body = unchunk(&body);
    }
    (code, body)
}

pub fn unchunk(mut b: &[u8]) -> Vec<u8> {
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

fn found(names: &[&str]) -> Option<String> {
    names.iter().find_map(|c| {
        Command::new(c)
            .arg("--version")
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|_| c.to_string())
    })
}

/// A chromedriver process and one browser session on it; both ended on
/// drop.
pub struct Browser {
    driver: Child,
    addr: String,
    session: String,
}

impl Browser {
    /// Headless Chromium at `width`×`height`, its profile in `profile`.
    pub fn start(profile: &Path, width: u32, height: u32) -> Browser {
        let driver_bin = found(&["chromedriver"])
            .expect("no chromedriver: install Debian's chromium-driver (`.ci/run` does)");
        let chromium = ["/usr/bin/chromium", "/usr/bin/chromium-browser"]
            .into_iter()
            .find(|p| Path::new(p).is_file())
            .expect("no chromium: install Debian's chromium (`.ci/run` does)");
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            l.local_addr().unwrap().port()
        };
        let driver = Command::new(driver_bin)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start chromedriver");
        let addr = format!("127.0.0.1:{port}");
        let t0 = Instant::now();
        loop {
            if TcpStream::connect(&addr).is_ok() {
                let (code, body) = http(&addr, "GET", "/status", None);
                let v: Value = serde_json::from_slice(&body).unwrap_or_default();
                if code == 200 && v["value"]["ready"] == true {
                    break;
                }
            }
            assert!(
                t0.elapsed() < Duration::from_secs(30),
                "chromedriver did not start"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": chromium,
                "args": [
                    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                    "--no-first-run", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--hide-scrollbars",
                    format!("--window-size={width},{height}"),
                    format!("--user-data-dir={}", profile.display()),
                ],
            },
        }}});
        let mut b = Browser {
            driver,
            addr,
            session: String::new(),
        };
        let v = b.call("POST", "/session", Some(&caps));
        b.session = v["sessionId"].as_str().expect("a session id").to_string();
        b
    }

    /// A WebDriver command; its `value`, or a panic with the driver's
    /// error.
    pub fn call(&self, method: &str, path: &str, body: Option<&Value>) -> Value {
        let (code, body) = http(&self.addr, method, path, body);
        let v: Value = serde_json::from_slice(&body)
            .unwrap_or_else(|_| panic!("{path}: {}", String::from_utf8_lossy(&body)));
        assert_eq!(code, 200, "{method} {path}: {v}");
        v["value"].clone()
    }

    fn at(&self, cmd: &str) -> String {
        format!("/session/{}/{cmd}", self.session)
    }

    pub fn open(&self, url: &str) {
        self.call("POST", &self.at("url"), Some(&json!({ "url": url })));
    }

    /// Runs `script` (a function body; `arguments` are `args`) in the page.
    pub fn eval(&self, script: &str, args: Value) -> Value {
        self.call(
            "POST",
            &self.at("execute/sync"),
            Some(&json!({ "script": script, "args": args })),
        )
    }

    /// Waits until `script` returns something truthy; returns it.
    pub fn wait_for(&self, what: &str, script: &str, limit: Duration) -> Value {
        let t0 = Instant::now();
        loop {
            let v = self.eval(script, json!([]));
            if !(v.is_null() || v == false || v == "") {
                return v;
            }
            assert!(t0.elapsed() < limit, "waited {limit:?} for {what}");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The element `css` selects (its JSON reference).
    pub fn element(&self, css: &str) -> Value {
        let v = self.call(
            "POST",
            &self.at("element"),
            Some(&json!({"using": "css selector", "value": css})),
        );
        assert!(v[ELEMENT].is_string(), "{css}: {v}");
        v
    }

    pub fn click(&self, css: &str) {
        let e = self.element(css);
        let id = e[ELEMENT].as_str().unwrap();
        self.call(
            "POST",
            &self.at(&format!("element/{id}/click")),
            Some(&json!({})),
        );
    }

    /// The element `css` scrolled whole into view, and how a point given
    /// in CSS pixels from its top left is offset from its centre, as
    /// WebDriver's actions take it (from the centre of the element's
    /// visible part).
    fn in_view(&self, css: &str) -> (Value, impl Fn((f64, f64)) -> (i64, i64)) {
        let e = self.element(css);
        let rect = self.eval(
            "arguments[0].scrollIntoView({block: 'center', inline: 'center'}); \
             const r = arguments[0].getBoundingClientRect(); return [r.width, r.height];",
            json!([e]),
        );
        let (w, h) = (rect[0].as_f64().unwrap(), rect[1].as_f64().unwrap());
        let at =
            move |(x, y): (f64, f64)| ((x - w / 2.0).round() as i64, (y - h / 2.0).round() as i64);
        (e, at)
    }

    /// A mouse click at (`x`, `y`) CSS pixels from the top left of the
    /// element `css`.
    pub fn click_at(&self, css: &str, x: f64, y: f64) {
        let (e, at) = self.in_view(css);
        let (dx, dy) = at((x, y));
        let actions = json!({"actions": [{
            "type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"},
            "actions": [
                {"type": "pointerMove", "origin": e, "x": dx, "y": dy},
                {"type": "pointerDown", "button": 0},
                {"type": "pointerUp", "button": 0},
            ],
        }]});
        self.call("POST", &self.at("actions"), Some(&actions));
        self.call("DELETE", &self.at("actions"), None);
    }

    /// A mouse drag from `from` to `to` (CSS pixels from the top left of
    /// the element `css`), in steps as a hand moves.
    pub fn drag(&self, css: &str, from: (f64, f64), to: (f64, f64)) {
        self.drag_holding(css, from, to, None)
    }

    /// [`Browser::drag`] holding `key` (a WebDriver key code, e.g. shift
    /// `\u{E008}`) throughout.
    pub fn drag_holding(&self, css: &str, from: (f64, f64), to: (f64, f64), key: Option<&str>) {
        let (e, at) = self.in_view(css);
        let (x0, y0) = at(from);
        let mut steps = vec![
            json!({"type": "pointerMove", "origin": e, "x": x0, "y": y0}),
            json!({"type": "pointerDown", "button": 0}),
        ];
        for k in 1..=5 {
            let t = k as f64 / 5.0;
            let (x, y) = at((from.0 + t * (to.0 - from.0), from.1 + t * (to.1 - from.1)));
            steps.push(json!({"type": "pointerMove", "origin": e, "x": x, "y": y, "duration": 20}));
        }
        steps.push(json!({"type": "pointerUp", "button": 0}));
        let mut sources = vec![json!({
            "type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"},
            "actions": steps,
        })];
        if let Some(k) = key {
            // Down before the pointer moves, up after it is released.
            let mut keys = vec![json!({"type": "keyDown", "value": k})];
            keys.extend((0..steps.len() - 1).map(|_| json!({"type": "pause", "duration": 0})));
            keys.push(json!({"type": "keyUp", "value": k}));
            sources.insert(0, json!({"type": "key", "id": "keys", "actions": keys}));
            sources[1]["actions"]
                .as_array_mut()
                .unwrap()
                .insert(0, json!({"type": "pause", "duration": 0}));
        }
        let actions = json!({ "actions": sources });
        self.call("POST", &self.at("actions"), Some(&actions));
        self.call("DELETE", &self.at("actions"), None);
    }

    /// One notch of the mouse wheel (`dy` > 0: towards the user, as
    /// browsers scroll down) at (`x`, `y`) CSS pixels from the top left
    /// of the element `css`.
    pub fn wheel(&self, css: &str, x: f64, y: f64, dy: i64) {
        let (e, at) = self.in_view(css);
        let actions = json!({"actions": [{
            "type": "wheel", "id": "wheel",
            "actions": [{"type": "scroll", "origin": e, "x": at((x, y)).0, "y": at((x, y)).1,
                         "deltaX": 0, "deltaY": dy}],
        }]});
        self.call("POST", &self.at("actions"), Some(&actions));
        self.call("DELETE", &self.at("actions"), None);
    }

    /// Chooses `file` in the file input `css`, as a user picking it does.
    pub fn choose_file(&self, css: &str, file: &Path) {
        let e = self.element(css);
        let id = e[ELEMENT].as_str().unwrap();
        self.call(
            "POST",
            &self.at(&format!("element/{id}/value")),
            Some(&json!({ "text": file.display().to_string() })),
        );
    }

    /// A screenshot of the window, written to `path` (PNG).
    pub fn screenshot(&self, path: &Path) {
        let v = self.call("GET", &self.at("screenshot"), None);
        let png = base64::engine::general_purpose::STANDARD
            .decode(v.as_str().expect("base64"))
            .expect("a base64 screenshot");
        std::fs::write(path, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        if !self.session.is_empty() {
            let _ = http(
                &self.addr,
                "DELETE",
                &format!("/session/{}", self.session),
                None,
            );
        }
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}
