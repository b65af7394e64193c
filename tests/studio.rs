//! `matflow studio` over HTTP and in a real browser: the page and its
//! script come from the binary; the session is a pipeline run on the
//! engine; a click selects an object, a change re-renders it (a preview,
//! then the result), undo and redo move along the history; the exported
//! session is a pipeline that `matflow run` turns into the studio's image
//! byte for byte. Nothing outside the studio's own names is reachable, a
//! token is required off loopback, a change must come from the page's own
//! origin, and bad requests get a 4xx with a message.

mod support;
mod webdriver;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use support::{s, scratch};
use webdriver::{http, http_raw, Browser};

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

/// The room matflow generates (64², the red box at about (51, 46)), with
/// a recovery of a few seconds: the studio's input in these tests.
fn room_pipeline(dir: &Path) -> PathBuf {
    room_pipeline_at(dir, 16)
}

/// The room, its renders (the kept trace and the results) at `spp`.
fn room_pipeline_at(dir: &Path, spp: u32) -> PathBuf {
    let f = dir.join("room.yaml");
    std::fs::write(
        &f,
        format!("pipeline: room\noutputs: [recovered]\nstages:\n  scene:\n    kind: synthetic_scene\n    \
         seed: 1\n    size: 64\n    spp: 16\n  mesh:\n    kind: mesh\n    scene: scene\n    \
         complete: none\n  lighting:\n    kind: envmap_opt\n    scene: scene\n    mesh: mesh\n    \
         budget_seconds: 1\n    trust_rm: true\n  recovered:\n    kind: material_opt\n    \
         scene: scene\n    mesh: mesh\n    envmap: lighting\n    budget_seconds: 2\n    \
         trust_rm: true\n  base:\n    kind: trace\n    mesh: mesh\n    materials: recovered\n    \
         envmap: recovered.envmap\n    spp: {spp}\n    path_spp: 4\n"),
    )
    .unwrap();
    f
}

/// A pixel on the room's red box.
const BOX: (f64, f64) = (51.0, 46.0);

fn start(dir: &Path, input: &Path, session: &str, env: &[(&str, &str)]) -> Studio {
    start_with(dir, input, session, env, &[])
}

/// [`start`] with more flags, and a cache of the session's own (so that
/// two studios in one test share nothing but what the flags give).
fn start_with(
    dir: &Path,
    input: &Path,
    session: &str,
    env: &[(&str, &str)],
    extra: &[&str],
) -> Studio {
    let addr_file = dir.join(format!("address-{session}"));
    let _ = std::fs::remove_file(&addr_file);
    let mut c = Command::new(env!("CARGO_BIN_EXE_matflow"));
    c.args(["studio", s(input), "--listen", "127.0.0.1:0"])
        .args([
            "--cache",
            s(&dir.join(if extra.is_empty() {
                "cache".into()
            } else {
                format!("cache-{session}")
            })),
            "--session",
            s(&dir.join(session)),
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

fn get(addr: &str, path: &str) -> (u16, Vec<u8>) {
    http_raw(addr, "GET", path, &[], b"")
}

fn post(addr: &str, path: &str, body: Value) -> (u16, String) {
    let (code, b) = http(addr, "POST", path, Some(&body));
    (code, String::from_utf8_lossy(&b).into_owned())
}

fn status(addr: &str) -> Value {
    let (code, body) = get(addr, "/api/session");
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    serde_json::from_slice(&body).unwrap()
}

/// Waits until the session's result of generation `generation` is shown.
fn result_of(addr: &str, generation: u64) -> Value {
    let t0 = Instant::now();
    loop {
        let v = status(addr);
        assert_ne!(v["state"], "failed", "{v}");
        if v["shown"] == generation && v["image"] == "result" && v["state"] == "ready" {
            return v;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "no result of generation {generation}: {v}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn rgb(png: &[u8]) -> image::RgbImage {
    image::load_from_memory(png).unwrap().to_rgb8()
}

/// The selection's overlay as a mask.
fn selection(addr: &str) -> Vec<bool> {
    let (code, png) = get(addr, "/api/images/selection.png");
    assert_eq!(code, 200);
    let img = image::load_from_memory(&png).unwrap().to_rgba8();
    img.pixels().map(|p| p[3] > 0).collect()
}

/// Mean absolute change (0..255) of two images inside and outside `mask`.
fn change_in_and_out(a: &image::RgbImage, b: &image::RgbImage, mask: &[bool]) -> (f64, f64) {
    let (mut sum, mut n) = ([0.0f64; 2], [0usize; 2]);
    for ((p, q), &m) in a.pixels().zip(b.pixels()).zip(mask) {
        let d: f64 = (0..3)
            .map(|c| (p[c] as f64 - q[c] as f64).abs())
            .sum::<f64>()
            / 3.0;
        sum[m as usize] += d;
        n[m as usize] += 1;
    }
    (sum[1] / n[1].max(1) as f64, sum[0] / n[0].max(1) as f64)
}

/// Unpacks an exported session into `dir`.
fn unpack(tar: &[u8], dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    let f = dir.join("session.tar");
    std::fs::write(&f, tar).unwrap();
    let o = Command::new("tar")
        .args(["-xf", s(&f), "-C", s(dir)])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// The whole edit loop over the API: select, change, preview then
/// result, undo and redo; the export runs as `matflow run` to the
/// studio's image byte for byte; opened again, it is the same session.
#[test]
fn a_session_is_edited_undone_redone_and_exported_as_its_pipeline() {
    let dir = scratch("studio", "edit");
    let input = room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    let v = result_of(&st.addr, 0);
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(64), Some(64))
    );
    // The recovery's loss, step by step, for the page's curve.
    assert_eq!(v["loss_stage"], "recovered", "{v}");
    let loss = v["loss"].as_array().unwrap();
    assert!(
        loss.len() > 3 && loss.iter().all(|l| l.as_f64().is_some_and(|l| l >= 0.0)),
        "{v}"
    );
    for want in ["photo", "albedo", "roughness", "metallic", "depth"] {
        assert!(v["maps"].as_array().unwrap().contains(&json!(want)), "{v}");
        let (code, png) = get(&st.addr, &format!("/api/maps/{want}.png"));
        assert_eq!(code, 200, "{want}");
        assert_eq!(rgb(&png).dimensions(), (64, 64), "{want}");
    }
    let (_, before) = get(&st.addr, "/api/images/result.png");
    // One click takes the box.
    let (code, body) = post(&st.addr, "/api/select", json!({"x": BOX.0, "y": BOX.1}));
    assert_eq!(code, 200, "{body}");
    let mask = selection(&st.addr);
    let count = mask.iter().filter(|&&m| m).count();
    assert!((100..400).contains(&count), "the box is ~170 px: {count}");
    // Its colour changed: a preview comes first, then the result.
    let (code, body) = post(
        &st.addr,
        "/api/edit",
        json!({"albedo": [0.1, 0.3, 0.9], "roughness": 0.3}),
    );
    assert_eq!(code, 204, "{body}");
    let v = result_of(&st.addr, 1);
    assert!(v["preview_seconds"].as_f64().unwrap() <= v["result_seconds"].as_f64().unwrap());
    assert_eq!(v["history"].as_array().unwrap().len(), 1, "{v}");
    let (_, after) = get(&st.addr, "/api/images/result.png");
    let (inside, outside) = change_in_and_out(&rgb(&before), &rgb(&after), &mask);
    assert!(
        inside > 20.0 && outside < inside / 20.0,
        "changed {inside:.1} inside the box and {outside:.2} outside"
    );
    let (_, exr) = get(&st.addr, "/api/images/result.exr");
    assert!(
        exr.starts_with(&[0x76, 0x2f, 0x31, 0x01]),
        "an OpenEXR file"
    );
    // Undo: the unedited result again (from the cache, the same bytes);
    // redo: the edit again.
    assert_eq!(post(&st.addr, "/api/undo", json!({})).0, 204);
    let v = result_of(&st.addr, 2);
    assert_eq!(v["redo"], 1);
    assert_eq!(get(&st.addr, "/api/images/result.png").1, before);
    assert_eq!(post(&st.addr, "/api/redo", json!({})).0, 204);
    result_of(&st.addr, 3);
    assert_eq!(get(&st.addr, "/api/images/result.exr").1, exr);
    // New light: an uploaded envmap (a warm sky, HDR), turned and
    // darker; the whole scene is rendered under it. Undone, the edit's
    // result again.
    let (code, body) = http_raw(
        &st.addr,
        "POST",
        "/api/light/envmap",
        &["Content-Type: application/octet-stream"],
        &sky_hdr(),
    );
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let name = serde_json::from_slice::<Value>(&body).unwrap()["envmap"].clone();
    assert!(status(&st.addr)["envmaps"]
        .as_array()
        .unwrap()
        .contains(&name));
    let (code, body) = post(
        &st.addr,
        "/api/light",
        json!({"envmap": name, "rotation": 90, "exposure": -1}),
    );
    assert_eq!(code, 204, "{body}");
    let v = result_of(&st.addr, 4);
    assert!(v["history"][1].as_str().unwrap().contains("relight"), "{v}");
    let relit = rgb(&get(&st.addr, "/api/images/result.png").1);
    let everywhere = vec![false; 64 * 64];
    let (_, changed) = change_in_and_out(&rgb(&after), &relit, &everywhere);
    assert!(
        changed > 5.0,
        "the new light changed the image by {changed:.1}"
    );
    assert_eq!(post(&st.addr, "/api/undo", json!({})).0, 204);
    result_of(&st.addr, 5);
    assert_eq!(get(&st.addr, "/api/images/result.exr").1, exr);
    assert_eq!(post(&st.addr, "/api/redo", json!({})).0, 204);
    let v = result_of(&st.addr, 6);
    let relit = rgb(&get(&st.addr, "/api/images/result.png").1);
    // An object: a shipped sphere on the floor, then an uploaded
    // tetrahedron beside it; moved; undone to where it was.
    let sphere = json!({"mesh": "sphere", "anchor": [20, 58], "scale": 0.5,
                        "material": {"type": "principled", "albedo": [0.9, 0.2, 0.2],
                                     "roughness": 0.3, "metallic": 0.0}});
    let (code, body) = post(&st.addr, "/api/insert", json!({"objects": [sphere]}));
    assert_eq!(code, 204, "{body}");
    let v7 = result_of(&st.addr, v["generation"].as_u64().unwrap() + 1);
    let with_sphere = rgb(&get(&st.addr, "/api/images/result.png").1);
    let near = |cx: u32, cy: u32| -> Vec<bool> {
        (0..64 * 64u32)
            .map(|i| (i % 64).abs_diff(cx) <= 6 && (i / 64).abs_diff(cy) <= 8)
            .collect()
    };
    let (inside, outside) = change_in_and_out(&relit, &with_sphere, &near(20, 54));
    assert!(
        inside > 10.0 && outside < inside / 4.0,
        "the sphere: {inside:.1} near, {outside:.1} elsewhere"
    );
    let (code, body) = http_raw(
        &st.addr,
        "POST",
        "/api/insert/mesh",
        &["Content-Type: application/octet-stream"],
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
    );
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let tetra = serde_json::from_slice::<Value>(&body).unwrap()["mesh"].clone();
    assert_eq!(status(&st.addr)["meshes"], json!([tetra]));
    let objects = |x: f64| {
        json!({"objects": [sphere, {"mesh": tetra, "anchor": [x, 60], "scale": 0.4,
                                     "material": {"type": "diffuse", "albedo": [0.2, 0.8, 0.3]}}]})
    };
    assert_eq!(post(&st.addr, "/api/insert", objects(44.0)).0, 204);
    let v8 = result_of(&st.addr, v7["generation"].as_u64().unwrap() + 1);
    assert_eq!(v8["objects"].as_array().unwrap().len(), 2, "{v8}");
    assert_eq!(v8["objects"][0]["mesh"], "sphere");
    let (_, placed) = get(&st.addr, "/api/images/result.exr");
    assert_eq!(post(&st.addr, "/api/insert", objects(36.0)).0, 204);
    let v9 = result_of(&st.addr, v8["generation"].as_u64().unwrap() + 1);
    assert_ne!(get(&st.addr, "/api/images/result.exr").1, placed, "moved");
    assert_eq!(post(&st.addr, "/api/undo", json!({})).0, 204);
    result_of(&st.addr, v9["generation"].as_u64().unwrap() + 1);
    assert_eq!(get(&st.addr, "/api/images/result.exr").1, placed, "undone");
    // The box made glass (its refraction lengths from the network): the
    // box changes; the history has one entry more, undo takes it back.
    assert_eq!(
        post(&st.addr, "/api/select", json!({"x": BOX.0, "y": BOX.1})).0,
        200
    );
    let g = status(&st.addr)["generation"].as_u64().unwrap();
    let (code, body) = post(
        &st.addr,
        "/api/glass",
        json!({"ior": 1.5, "transmission": 1}),
    );
    assert_eq!(code, 204, "{body}");
    let vg = result_of(&st.addr, g + 1);
    assert!(
        vg["history"][4].as_str().unwrap().contains("transparency"),
        "{vg}"
    );
    assert_ne!(get(&st.addr, "/api/images/result.exr").1, placed, "glass");
    let (_, yaml) = get(&st.addr, "/api/pipeline.yaml");
    assert!(String::from_utf8_lossy(&yaml).contains("edit5_lengths:\n    kind: refraction_length"));
    let (_, exr) = get(&st.addr, "/api/images/result.exr");
    // Exported and unpacked elsewhere, `matflow run` (its own, empty
    // cache) writes the studio's EXR byte for byte.
    let (code, tar) = get(&st.addr, "/api/export.tar");
    assert_eq!(code, 200);
    let out = dir.join("exported");
    unpack(&tar, &out);
    let o = support::matflow(&["run", s(&out.join("session.yaml")), "--quiet"], None);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        std::fs::read(out.join("result.exr")).unwrap() == exr,
        "`matflow run` of the export differs from the studio's result.exr"
    );
    drop(st);
    // The export, opened in the studio, is the same session.
    let again = start(&dir, &out.join("session.yaml"), "reopened", &[]);
    let v = result_of(&again.addr, 0);
    assert_eq!(v["history"].as_array().unwrap().len(), 5, "{v}");
    assert_eq!(v["objects"].as_array().unwrap().len(), 2, "{v}");
    assert_eq!(get(&again.addr, "/api/images/result.exr").1, exr);
    drop(again);
    let _ = std::fs::remove_file(input);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A request and what it must get: method, path, headers, body, status,
/// a word of the message.
type Case = (
    &'static str,
    &'static str,
    Vec<&'static str>,
    Vec<u8>,
    u16,
    &'static str,
);

/// Every endpoint with bad input answers 4xx with a message, and the
/// studio goes on serving; nothing outside its own names is reachable.
#[test]
fn bad_requests_get_a_4xx_with_a_message_and_nothing_else_is_reachable() {
    let dir = scratch("studio", "bad");
    room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    result_of(&st.addr, 0);
    let json = "Content-Type: application/json";
    let cases: Vec<Case> = vec![
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": 64, "y": 1}"#.to_vec(),
            422,
            "outside",
        ),
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": -1, "y": 1}"#.to_vec(),
            422,
            "outside",
        ),
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": 1, "y": 1, "tolerance": 9}"#.to_vec(),
            422,
            "tolerance",
        ),
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": 1, "y": 1, "mode": "xor"}"#.to_vec(),
            422,
            "mode",
        ),
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": 1, "y": 1, "extra": 1}"#.to_vec(),
            422,
            "extra",
        ),
        (
            "POST",
            "/api/select",
            vec![json],
            br#"{"x": 1,"#.to_vec(),
            400,
            "JSON",
        ),
        (
            "POST",
            "/api/select",
            vec!["Content-Type: text/plain"],
            br#"{"x": 1, "y": 1}"#.to_vec(),
            415,
            "Content-Type",
        ),
        (
            "POST",
            "/api/select/rect",
            vec![json],
            br#"{"x0": 1, "y0": 1, "x1": 2}"#.to_vec(),
            422,
            "y1",
        ),
        (
            "POST",
            "/api/select/brush",
            vec![json],
            br#"{"points": [[1, 1]], "radius": 0}"#.to_vec(),
            422,
            "radius",
        ),
        (
            "POST",
            "/api/select/brush",
            vec![json],
            br#"{"points": [], "radius": 3}"#.to_vec(),
            422,
            "points",
        ),
        (
            "POST",
            "/api/select/mask",
            vec!["Content-Type: image/png"],
            b"not a png".to_vec(),
            422,
            "decode",
        ),
        (
            "POST",
            "/api/select/mask",
            vec!["Content-Type: image/png"],
            png(8, 8),
            422,
            "64x64",
        ),
        // A header claiming a 100000² image: refused before decoding.
        (
            "POST",
            "/api/select/mask",
            vec!["Content-Type: image/png"],
            huge_png_header(),
            422,
            "size",
        ),
        (
            "POST",
            "/api/edit",
            vec![json],
            br#"{"roughness": 0.5}"#.to_vec(),
            422,
            "select",
        ),
        (
            "POST",
            "/api/edit",
            vec![json],
            br#"{"colour": 1}"#.to_vec(),
            422,
            "colour",
        ),
        (
            "POST",
            "/api/light",
            vec![json],
            br#"{"envmap": "../../etc/passwd"}"#.to_vec(),
            422,
            "no envmap",
        ),
        (
            "POST",
            "/api/light",
            vec![json],
            br#"{"rotation": 720}"#.to_vec(),
            422,
            "rotation",
        ),
        (
            "POST",
            "/api/light/envmap",
            vec!["Content-Type: application/octet-stream"],
            b"P6 not a map".to_vec(),
            422,
            "not an environment map",
        ),
        (
            "POST",
            "/api/light/envmap",
            vec!["Content-Type: application/octet-stream"],
            b"#?RADIANCE\nbroken".to_vec(),
            422,
            "uploaded envmap",
        ),
        (
            "POST",
            "/api/insert",
            vec![json],
            br#"{"objects": [{"mesh": "teapot", "anchor": [5, 5], "material": {"type": "diffuse"}}]}"#.to_vec(),
            422,
            "no mesh",
        ),
        (
            "POST",
            "/api/insert",
            vec![json],
            br#"{"objects": [{"mesh": "cube", "anchor": [5, 5], "scale": 0, "material": {"type": "diffuse"}}]}"#.to_vec(),
            422,
            "scale",
        ),
        (
            "POST",
            "/api/insert",
            vec![json],
            br#"{"objects": [{"mesh": "cube", "anchor": [5, 5], "material": {"type": "chrome"}}]}"#.to_vec(),
            422,
            "type",
        ),
        (
            "POST",
            "/api/insert",
            vec![json],
            br#"{"objects": [{"mesh": "cube", "anchor": [500, 5], "material": {"type": "diffuse"}}]}"#.to_vec(),
            422,
            "anchor",
        ),
        (
            "POST",
            "/api/insert",
            vec![json],
            br#"{"objects": []}"#.to_vec(),
            422,
            "undo",
        ),
        (
            "POST",
            "/api/insert/mesh",
            vec!["Content-Type: application/octet-stream"],
            b"v 0 0 0\nf 1 2 3\n".to_vec(),
            422,
            "uploaded mesh",
        ),
        (
            "POST",
            "/api/undo",
            vec![json],
            b"{}".to_vec(),
            409,
            "nothing to undo",
        ),
        (
            "POST",
            "/api/redo",
            vec![json],
            b"{}".to_vec(),
            409,
            "nothing to redo",
        ),
        // A change from another page is refused.
        (
            "POST",
            "/api/select/clear",
            vec!["Origin: http://evil.example"],
            vec![],
            403,
            "origin",
        ),
        ("GET", "/api/maps/secret.png", vec![], vec![], 404, "no map"),
        (
            "GET",
            "/api/images/session.yaml",
            vec![],
            vec![],
            404,
            "images are",
        ),
        ("GET", "/api/maps/../../etc/passwd", vec![], vec![], 404, ""),
        (
            "GET",
            "/api/maps/..%2f..%2fetc%2fpasswd",
            vec![],
            vec![],
            404,
            "",
        ),
        ("GET", "/session/session.yaml", vec![], vec![], 404, ""),
        ("GET", "/etc/passwd", vec![], vec![], 404, ""),
    ];
    for (method, path, headers, body, want, says) in &cases {
        let (code, answer) = http_raw(&st.addr, method, path, headers, body);
        let answer = String::from_utf8_lossy(&answer);
        assert_eq!(code, *want, "{method} {path}: {answer}");
        assert!(
            answer.to_lowercase().contains(&says.to_lowercase()),
            "{method} {path}: {answer:?} should say {says:?}"
        );
        assert!(!answer.contains("root:"), "{path}");
    }
    // Selected, an out-of-range change is the engine's message.
    assert_eq!(
        post(&st.addr, "/api/select", json!({"x": 5, "y": 5})).0,
        200
    );
    let (code, body) = post(&st.addr, "/api/edit", json!({"metallic": 3}));
    assert_eq!(code, 422, "{body}");
    assert!(body.contains("metallic"), "{body}");
    // A brush, a rectangle and a mask of the right size select.
    let (code, body) = post(
        &st.addr,
        "/api/select/brush",
        json!({"points": [[10, 10], [12, 10]], "radius": 2, "mode": "set"}),
    );
    assert_eq!((code, body.trim()), (200, r#"{"selected":20}"#));
    let (code, body) = post(
        &st.addr,
        "/api/select/rect",
        json!({"x0": 0, "y0": 0, "x1": 4, "y1": 2, "mode": "add"}),
    );
    assert_eq!((code, body.trim()), (200, r#"{"selected":28}"#));
    let (code, body) = http_raw(
        &st.addr,
        "POST",
        "/api/select/mask?mode=remove",
        &["Content-Type: image/png"],
        &png(64, 64),
    );
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    // Still serving, and nothing changed the session.
    let v = status(&st.addr);
    assert_eq!(
        (v["state"].as_str(), v["generation"].as_u64()),
        (Some("ready"), Some(0))
    );
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 32×16 Radiance HDR sky: warm above the horizon, dim below.
fn sky_hdr() -> Vec<u8> {
    let img = matflow_scene::Image::from_fn(32, 16, |_, y| {
        if y < 8 {
            glam::Vec3::new(2.0, 1.4, 0.8)
        } else {
            glam::Vec3::splat(0.2)
        }
    });
    matflow_scene::io::encode_hdr(Path::new("sky.hdr"), &img).unwrap()
}

/// A change while the result of the one before is rendering stops that
/// render (between its tiles; nothing of it is shown or stored) and
/// renders the newer one. The room's renders take 2048 samples per
/// pixel here, so that the stop lands inside one.
#[test]
fn a_newer_change_stops_the_render_it_supersedes() {
    let dir = scratch("studio", "stop");
    room_pipeline_at(&dir, 2048);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    result_of(&st.addr, 0);
    assert_eq!(status(&st.addr)["stopped"], 0);
    let (code, body) = post(&st.addr, "/api/light", json!({"rotation": 90}));
    assert_eq!(code, 204, "{body}");
    let t0 = Instant::now();
    loop {
        let v = status(&st.addr);
        assert_ne!(v["state"], "failed", "{v}");
        let done = v["shown"] == 1 && v["image"] == "result";
        assert!(!done, "the result came before it was superseded: {v}");
        if v["generation"] == 1 && v["stage"] == "result" {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(60), "{v}");
        std::thread::sleep(Duration::from_millis(20));
    }
    let (code, body) = post(&st.addr, "/api/light", json!({"rotation": 180}));
    assert_eq!(code, 204, "{body}");
    let v = result_of(&st.addr, 2);
    assert_eq!(v["stopped"], 1, "{v}");
    assert_eq!(v["history"].as_array().unwrap().len(), 2, "{v}");
    // Undone to the first light, its result renders whole: the stopped
    // render left no entry behind to be served.
    let (code, body) = post(&st.addr, "/api/undo", json!({}));
    assert_eq!(code, 204, "{body}");
    let v = result_of(&st.addr, 3);
    assert!(v["message"].as_str().unwrap().contains("1 executed"), "{v}");
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A photo uploaded starts a session on it: saved in the session's
/// folder by its contents, predicted (`matnet`), its maps shown; a file
/// that is not a photo, or one too small to predict from, is refused and
/// the session stays as it was.
#[test]
fn a_photo_opened_by_upload_starts_a_session_on_it() {
    let dir = scratch("studio", "open");
    room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    result_of(&st.addr, 0);
    let octets = ["Content-Type: application/octet-stream"];
    let refused = [(b"hello".to_vec(), "not a photo"), (png(16, 16), "16x16")];
    for (body, says) in refused {
        let (code, answer) = http_raw(&st.addr, "POST", "/api/open", &octets, &body);
        let answer = String::from_utf8_lossy(&answer);
        assert_eq!(code, 422, "{answer}");
        assert!(answer.contains(says), "{answer}");
    }
    assert_eq!(status(&st.addr)["input"], "room.yaml");
    // The room's own photo, as a user would upload a picture.
    let (_, photo) = get(&st.addr, "/api/maps/photo.png");
    let (code, answer) = http_raw(&st.addr, "POST", "/api/open", &octets, &photo);
    assert_eq!(code, 204, "{}", String::from_utf8_lossy(&answer));
    let (_, yaml) = get(&st.addr, "/api/pipeline.yaml");
    let yaml = String::from_utf8_lossy(&yaml).into_owned();
    let name = yaml
        .lines()
        .find_map(|l| l.trim().strip_prefix("photo: photo-"))
        .unwrap_or_else(|| panic!("a matnet stage on the upload:\n{yaml}"));
    assert!(yaml.contains("kind: matnet"), "{yaml}");
    assert!(dir.join("session").join(format!("photo-{name}")).is_file());
    // Predicted: the maps are MatNet's, at 512².
    let t0 = Instant::now();
    loop {
        let v = status(&st.addr);
        assert_ne!(v["state"], "failed", "{v}");
        if v["width"] == 512 && !v["maps"].as_array().unwrap().is_empty() {
            assert!(v["input"].as_str().unwrap().starts_with("photo-"), "{v}");
            assert_eq!(v["history"], json!([]));
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "{v}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (code, albedo) = get(&st.addr, "/api/maps/albedo.png");
    assert_eq!(code, 200);
    assert_eq!(rgb(&albedo).dimensions(), (512, 512));
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The studio on workers (a real `matflow worker` and a real cache server,
/// buildbox-casd): the session's stages run there, an edit's result is
/// the same bytes as in-process, and `run` of the export on the shared
/// store is served from it.
#[test]
fn on_workers_the_studio_renders_what_it_renders_in_process() {
    let dir = scratch("studio", "workers");
    room_pipeline(&dir);
    let casd = support::Casd::start(&dir.join("casd"));
    let bin = Path::new(env!("CARGO_BIN_EXE_matflow"));
    let w = support::Worker::start(bin, &dir.join("worker-cache"), &[], &[]);
    let remote = [
        "--workers",
        w.addr.as_str(),
        "--remote-cache",
        casd.endpoint.as_str(),
    ];
    let edit = |st: &Studio| {
        result_of(&st.addr, 0);
        assert_eq!(
            post(&st.addr, "/api/select", json!({"x": BOX.0, "y": BOX.1})).0,
            200
        );
        let (code, body) = post(&st.addr, "/api/edit", json!({"hue_shift": 90}));
        assert_eq!(code, 204, "{body}");
        result_of(&st.addr, 1);
        get(&st.addr, "/api/images/result.exr").1
    };
    let st = start_with(&dir, Path::new("room.yaml"), "on-workers", &[], &remote);
    let there = edit(&st);
    assert!(w.said("start "), "the worker ran nothing");
    drop(st);
    let st = start(&dir, Path::new("room.yaml"), "in-process", &[]);
    let here = edit(&st);
    drop(st);
    assert!(
        there == here,
        "the workers' result differs from the in-process one"
    );
    drop(w);
    drop(casd);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The geometry past the frame is the page's to change: what the mesh
/// stage took is shown, and another choice runs the recovery again.
#[test]
fn the_geometry_past_the_frame_is_shown_and_changed() {
    let dir = scratch("studio", "geometry");
    room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    let v = result_of(&st.addr, 0);
    // The room pipeline asks for none.
    assert_eq!(v["geometry"], "none", "{v}");
    assert_eq!(v["geometry_taken"], "past the frame: none", "{v}");
    // An edit (without one the result is the photo, whatever the
    // geometry), then the geometry: the recovery runs again, and the
    // edit's render with it.
    assert_eq!(
        post(&st.addr, "/api/select", json!({"x": BOX.0, "y": BOX.1})).0,
        200
    );
    assert_eq!(
        post(&st.addr, "/api/edit", json!({"roughness": 0.1})).0,
        204
    );
    result_of(&st.addr, 1);
    let (_, before) = get(&st.addr, "/api/images/result.exr");
    let (code, body) = post(&st.addr, "/api/geometry", json!({"complete": "closed"}));
    assert_eq!(code, 204, "{body}");
    let v = result_of(&st.addr, 2);
    assert_eq!(v["geometry"], "closed", "{v}");
    assert_eq!(v["geometry_taken"], "past the frame: closed", "{v}");
    assert_ne!(get(&st.addr, "/api/images/result.exr").1, before);
    let (_, yaml) = get(&st.addr, "/api/pipeline.yaml");
    assert!(String::from_utf8_lossy(&yaml).contains("complete: closed"));
    let (code, body) = post(&st.addr, "/api/geometry", json!({"complete": "cave"}));
    assert_eq!(code, 422, "{body}");
    assert!(body.contains("complete"), "{body}");
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// In Chromium, a photo picked in the page's *open a photo* is uploaded,
/// predicted and recovered (the session's own recovery settings), the
/// recovery's fit so far shown as it goes, and its result shown; two
/// browsers on one studio see the same session.
#[test]
fn in_chromium_a_photo_opened_in_the_page_is_predicted_and_recovered() {
    let dir = scratch("studio", "chromium-open");
    room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    result_of(&st.addr, 0);
    let (_, photo) = get(&st.addr, "/api/maps/photo.png");
    let file = dir.join("my photo.png");
    std::fs::write(&file, &photo).unwrap();
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("studio");
    std::fs::create_dir_all(&shots).unwrap();
    let a = Browser::start(&dir.join("profile-a"), 1280, 900);
    let b = Browser::start(&dir.join("profile-b"), 1280, 900);
    for br in [&a, &b] {
        br.open(&format!("http://{}/", st.addr));
        br.wait_for(
            "the first result",
            "return document.body.dataset.shown === '0/result';",
            Duration::from_secs(60),
        );
    }
    // Every image the page shows, as it shows it.
    a.eval(
        "window.seen = []; new MutationObserver(() => window.seen.push(document.body.dataset.shown))\
         .observe(document.body, {attributes: true, attributeFilter: ['data-shown']});",
        json!([]),
    );
    a.choose_file("#open", &file);
    // The recovery's fit so far is shown while it runs: screenshot it.
    a.wait_for(
        "the recovery's fit so far",
        "return (document.body.dataset.shown || '').startsWith('1/recovery/');",
        Duration::from_secs(300),
    );
    a.screenshot(&shots.join("8-photo-recovering.png"));
    // Both browsers follow the session onto the photo: predicted (512²)
    // and recovered.
    for br in [&a, &b] {
        let input = br.wait_for(
            "the photo's result",
            "return document.body.dataset.shown === '1/result' && \
             document.getElementById('view').width === 512 && \
             document.getElementById('input').textContent;",
            Duration::from_secs(300),
        );
        assert!(input.as_str().unwrap().starts_with("photo-"), "{input}");
    }
    a.screenshot(&shots.join("10-photo-opened.png"));
    let v = status(&st.addr);
    assert_eq!(
        (v["width"].as_u64(), v["state"].as_str()),
        (Some(512), Some("ready"))
    );
    // The page showed the fit after each of the recovery's fitting
    // stages it heard of, then the preview, then the result; the latest
    // fit is served at the photo's size.
    let seen = a.eval("return window.seen;", json!([]));
    let seen: Vec<&str> = seen
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    let fits = seen.iter().filter(|k| k.starts_with("1/recovery/")).count();
    let shots_taken = v["recovery_shots"].as_u64().unwrap();
    assert!(
        fits >= 1 && shots_taken >= 3,
        "{seen:?}, {shots_taken} shots"
    );
    assert_eq!(seen.last(), Some(&"1/result"), "{seen:?}");
    let (code, fit) = get(&st.addr, "/api/images/recovery.png");
    assert_eq!(code, 200);
    assert_eq!(rgb(&fit).dimensions(), (512, 512));
    std::fs::write(shots.join("9-photo-recovered-fit.png"), &fit).unwrap();
    drop((a, b));
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A white `w`×`h` PNG.
fn png(w: u32, h: u32) -> Vec<u8> {
    let img = image::GrayImage::from_pixel(w, h, image::Luma([255]));
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png).unwrap();
    buf.into_inner()
}

/// A PNG signature and an IHDR claiming 100000×100000, nothing more
/// (and an empty IDAT and IEND: a valid header, no pixels).
fn huge_png_header() -> Vec<u8> {
    let mut b = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |name: &[u8], data: &[u8]| {
        let mut c = name.to_vec();
        c.extend_from_slice(data);
        b.extend_from_slice(&(data.len() as u32).to_be_bytes());
        b.extend_from_slice(&c);
        b.extend_from_slice(&crc32(&c).to_be_bytes());
    };
    let mut ihdr = 100_000u32.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&100_000u32.to_be_bytes());
    ihdr.extend_from_slice(&[8, 0, 0, 0, 0]);
    chunk(b"IHDR", &ihdr);
    chunk(b"IDAT", &[]);
    chunk(b"IEND", &[]);
    b
}

fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xffff_ffffu32;
    for &byte in data {
        c ^= byte as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xedb8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

#[test]
fn off_loopback_a_token_is_required_and_then_asked_of_every_request() {
    let dir = scratch("studio", "token");
    let input = room_pipeline(&dir);
    // Any address but loopback, without a token: refused at the start.
    let o = Command::new(env!("CARGO_BIN_EXE_matflow"))
        .args(["studio", s(&input), "--listen", "0.0.0.0:0"])
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
    let st = start(&dir, &input, "session", &[("MATFLOW_TOKEN", secret)]);
    assert_eq!(get(&st.addr, "/").0, 401);
    let wrong = ["Authorization: Bearer wrong-token-000000"];
    assert_eq!(
        http_raw(&st.addr, "GET", "/api/session", &wrong, b"").0,
        401
    );
    let bearer = format!("Authorization: Bearer {secret}");
    assert_eq!(
        http_raw(&st.addr, "GET", "/api/session", &[&bearer], b"").0,
        200
    );
    assert_eq!(get(&st.addr, &format!("/?token={secret}")).0, 200);
    let (code, _) = http_raw(
        &st.addr,
        "POST",
        "/api/select/clear",
        &["Content-Type: application/json"],
        b"{}",
    );
    assert_eq!(code, 401);
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The page in headless Chromium over WebDriver, as a user works: it
/// opens, waits for the recovery, clicks the box, picks a colour and
/// applies it; the canvas read back has changed inside the box and not
/// outside; undo brings the old image back. Screenshots of each step are
/// kept under the target folder (`target/tmp/studio/`) for a person to
/// look at.
#[test]
fn in_chromium_a_click_and_a_colour_change_the_object_and_nothing_else() {
    let dir = scratch("studio", "chromium");
    room_pipeline(&dir);
    let st = start(&dir, Path::new("room.yaml"), "session", &[]);
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("studio");
    std::fs::create_dir_all(&shots).unwrap();
    let b = Browser::start(&dir.join("profile"), 1280, 900);
    b.open(&format!("http://{}/", st.addr));
    let long = Duration::from_secs(120);
    b.wait_for(
        "the first result",
        "return document.body.dataset.shown === '0/result' && document.body.dataset.state === 'ready';",
        long,
    );
    b.screenshot(&shots.join("1-opened.png"));
    let pixels = "const c = document.getElementById('view'); \
                  return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data);";
    let before = b.eval(pixels, json!([]));
    // A click on the box, in the canvas's CSS pixels.
    let size = b.eval(
        "const r = document.getElementById('overlay').getBoundingClientRect(); return [r.width, r.height];",
        json!([]),
    );
    let (w, h) = (size[0].as_f64().unwrap(), size[1].as_f64().unwrap());
    b.click_at(
        "#overlay",
        (BOX.0 + 0.5) * w / 64.0,
        (BOX.1 + 0.5) * h / 64.0,
    );
    b.wait_for(
        "the selection",
        "return /px selected/.test(document.getElementById('selected').textContent);",
        long,
    );
    b.screenshot(&shots.join("2-selected.png"));
    let mask = selection(&st.addr);
    assert!(mask.iter().filter(|&&m| m).count() > 100);
    // A colour from the picker (set as a user's pick sets it), applied.
    b.eval(
        "const c = document.getElementById('albedo'); c.value = '#1a4de6'; \
         c.dispatchEvent(new Event('input', {bubbles: true}));",
        json!([]),
    );
    b.click("#apply");
    b.wait_for(
        "the edited result",
        "return document.body.dataset.shown === '1/result';",
        long,
    );
    b.screenshot(&shots.join("3-edited.png"));
    let after = b.eval(pixels, json!([]));
    let to_img = |v: &Value| {
        let d: Vec<u8> = v
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as u8)
            .collect();
        image::RgbImage::from_fn(64, 64, |x, y| {
            let i = 4 * (y as usize * 64 + x as usize);
            image::Rgb([d[i], d[i + 1], d[i + 2]])
        })
    };
    let (inside, outside) = change_in_and_out(&to_img(&before), &to_img(&after), &mask);
    assert!(
        inside > 20.0 && outside < inside / 20.0,
        "the canvas changed {inside:.1} inside the box and {outside:.2} outside"
    );
    // The canvas shows what `/api/images/result.png` serves.
    assert_eq!(
        to_img(&after),
        rgb(&get(&st.addr, "/api/images/result.png").1)
    );
    b.click("#undo");
    b.wait_for(
        "the undone result",
        "return document.body.dataset.shown === '2/result';",
        long,
    );
    assert_eq!(b.eval(pixels, json!([])), before);
    b.screenshot(&shots.join("4-undone.png"));
    // The recovered light turned half round and a stop darker: the whole
    // image changes.
    b.eval(
        "for (const [id, v] of [['rotation', 180], ['exposure', -1]]) {            const e = document.getElementById(id); e.value = v;            e.dispatchEvent(new Event('input', {bubbles: true})); }",
        json!([]),
    );
    b.click("#relight");
    b.wait_for(
        "the relit result",
        "return document.body.dataset.shown === '3/result';",
        long,
    );
    b.screenshot(&shots.join("5-relit.png"));
    let relit = to_img(&b.eval(pixels, json!([])));
    let (_, all) = change_in_and_out(&to_img(&before), &relit, &[false; 64 * 64]);
    assert!(all > 5.0, "the new light changed the canvas by {all:.1}");
    // A sphere placed on the floor with the place tool, then dragged by
    // its marker to the right.
    b.click("input[name=tool][value=place]");
    b.eval(
        "const m = document.getElementById('obj-mesh'); m.value = 'sphere';          m.dispatchEvent(new Event('change', {bubbles: true}));",
        json!([]),
    );
    let css = |x: f64, y: f64| ((x + 0.5) * w / 64.0, (y + 0.5) * h / 64.0);
    let (px, py) = css(20.0, 58.0);
    b.click_at("#overlay", px, py);
    b.wait_for(
        "the inserted sphere",
        "return document.body.dataset.shown === '4/result';",
        long,
    );
    b.screenshot(&shots.join("6-inserted.png"));
    let inserted = to_img(&b.eval(pixels, json!([])));
    let near: Vec<bool> = (0..64 * 64u32)
        .map(|i| (i % 64).abs_diff(20) <= 6 && (i / 64).abs_diff(54) <= 8)
        .collect();
    let (inside, outside) = change_in_and_out(&relit, &inserted, &near);
    assert!(
        inside > 10.0 && outside < inside / 4.0,
        "the sphere changed the canvas {inside:.1} near it and {outside:.1} elsewhere"
    );
    b.drag("#overlay", css(20.0, 58.0), css(34.0, 58.0));
    let moved = b.wait_for(
        "the moved sphere",
        "return document.body.dataset.shown === '5/result' &&          JSON.stringify(document.getElementById('objects').textContent);",
        long,
    );
    assert!(moved.as_str().unwrap().contains("at 34"), "{moved}");
    b.screenshot(&shots.join("7-moved.png"));
    // The wheel over its marker scales it up a tenth.
    let (mx, my) = css(34.0, 58.0);
    b.wheel("#overlay", mx, my, -100);
    let scaled = b.wait_for(
        "the scaled sphere",
        "return document.body.dataset.shown === '6/result' && \
         JSON.stringify(document.getElementById('objects').textContent);",
        long,
    );
    assert!(scaled.as_str().unwrap().contains("×0.55"), "{scaled}");
    assert_eq!(status(&st.addr)["objects"][0]["scale"], 0.55);
    // Shift-drag on its marker turns it: across a quarter of the image,
    // half a turn.
    b.drag_holding(
        "#overlay",
        css(34.0, 58.0),
        css(50.0, 58.0),
        Some("\u{E008}"),
    );
    b.wait_for(
        "the turned sphere",
        "return document.body.dataset.shown === '7/result';",
        long,
    );
    let turned = status(&st.addr)["objects"][0]["rotate"].as_f64().unwrap();
    assert!((turned.abs() - 180.0).abs() <= 12.0, "turned to {turned}°");
    b.screenshot(&shots.join("7b-turned.png"));
    drop(b);
    drop(st);
    let _ = std::fs::remove_dir_all(&dir);
}
