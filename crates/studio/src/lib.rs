//! matflow studio: a session's pipeline and its pictures in the browser,
//! served by the binary itself (the page and its script are compiled in;
//! nothing is fetched at run time). A session is a pipeline in a folder of
//! its own (`session.yaml`), run by the same engine and cache as `matflow
//! run`; the page shows what its scene stage made (the photo, albedo,
//! roughness, metallic, normals, depth) and gives the pipeline back.
//!
//! Secure by default: it listens on loopback; any other address needs a
//! token (as workers do), which every request then presents (`Authorization:
//! Bearer TOKEN`, or `?token=` for what a browser loads). It serves only
//! its own fixed names: nothing on disk is reachable by a path in a URL.

pub mod live;
pub mod session;
pub mod view;

use std::convert::Infallible;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::{header, HeaderMap, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use matflow_rpc::auth::Token;
use matflow_scene::select::{grow_object_within_edges, Grow, PHOTO_EDGE_STEP};
use matflow_scene::Image;

use live::{request_error, Shared};
use session::{Change, Glass, Light, Object, Session, SessionError};

/// The largest photo accepted by upload.
const PHOTO_BYTES: usize = 64 << 20;

/// The largest mesh accepted by upload.
const MESH_BYTES: usize = 64 << 20;

/// The largest environment map accepted by upload (a 4096×2048 float
/// EXR, uncompressed, is 96 MiB; HDR's run-length encoding is smaller).
const ENVMAP_BYTES: usize = 128 << 20;

const INDEX_HTML: &str = include_str!("../web/index.html");
const STUDIO_JS: &str = include_str!("../web/studio.js");
const STUDIO_CSS: &str = include_str!("../web/studio.css");

/// How a studio serves.
pub struct StudioOptions {
    /// A photo, a bundle folder or a pipeline file to open.
    pub input: PathBuf,
    /// The session's folder (its `session.yaml`).
    pub session: PathBuf,
    /// The store (the local cache, and a remote one when given) and the
    /// executor (in-process, or workers) the session's stages run on:
    /// the ones `matflow run` builds from the same flags.
    pub store: Arc<matflow_engine::Tiered>,
    pub executor: Box<dyn matflow_engine::exec::Executor>,
    /// Required of every request when set.
    pub token: Option<Token>,
}

/// What went wrong starting a studio.
#[derive(Debug, thiserror::Error)]
pub enum StudioError {
    #[error(
        "{0} is reachable from other machines: give a token (--token-file or $MATFLOW_TOKEN), \
         which every request must then present"
    )]
    NeedsToken(SocketAddr),
    #[error(transparent)]
    Session(#[from] session::SessionError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

struct App {
    shared: Arc<Shared>,
    token: Option<Token>,
}

/// Checks the address against the token rule, opens the session (its
/// pipeline written to its folder), starts its runner and returns the
/// router.
pub fn start(opts: StudioOptions, listen: SocketAddr) -> Result<Router, StudioError> {
    if !listen.ip().is_loopback() && opts.token.is_none() {
        return Err(StudioError::NeedsToken(listen));
    }
    // A relative input is taken from where the studio was started.
    let input = std::path::absolute(&opts.input).map_err(|source| StudioError::Io {
        path: opts.input.clone(),
        source,
    })?;
    let reg = matflow_nodes::registry();
    let session = Session::open(&input, &opts.session, &reg)?;
    let shared = Shared::new(session, opts.input.display().to_string());
    let bg = shared.clone();
    let (store, executor) = (opts.store, opts.executor);
    std::thread::spawn(move || live::runner(bg, store, executor));
    Ok(router(Arc::new(App {
        shared,
        token: opts.token,
    })))
}

fn router(app: Arc<App>) -> Router {
    Router::new()
        .route(
            "/",
            get(|| async { page(INDEX_HTML, "text/html; charset=utf-8") }),
        )
        .route(
            "/studio.js",
            get(|| async { page(STUDIO_JS, "text/javascript; charset=utf-8") }),
        )
        .route(
            "/studio.css",
            get(|| async { page(STUDIO_CSS, "text/css; charset=utf-8") }),
        )
        .route("/api/session", get(session_status))
        .route("/api/events", get(events))
        .route("/api/pipeline.yaml", get(pipeline))
        .route("/api/export.tar", get(export))
        .route("/api/maps/{file}", get(map))
        .route("/api/images/{file}", get(image_file))
        .route("/api/select", post(select_point))
        .route("/api/select/rect", post(select_rect))
        .route("/api/select/brush", post(select_brush))
        .route("/api/select/mask", post(select_mask))
        .route("/api/select/clear", post(select_clear))
        .route("/api/edit", post(edit))
        .route("/api/glass", post(glass))
        .route("/api/geometry", post(geometry))
        .route("/api/light", post(light))
        .route(
            "/api/light/envmap",
            post(upload_envmap).layer(axum::extract::DefaultBodyLimit::max(ENVMAP_BYTES)),
        )
        .route(
            "/api/open",
            post(open_photo).layer(axum::extract::DefaultBodyLimit::max(PHOTO_BYTES)),
        )
        .route("/api/insert", post(insert))
        .route(
            "/api/insert/mesh",
            post(upload_mesh).layer(axum::extract::DefaultBodyLimit::max(MESH_BYTES)),
        )
        .route("/api/undo", post(undo))
        .route("/api/redo", post(redo))
        .fallback(|| async { (StatusCode::NOT_FOUND, "no such page\n") })
        .layer(middleware::from_fn_with_state(app.clone(), guard))
        .with_state(app)
}

fn page(body: &'static str, ty: &'static str) -> Response {
    ([(header::CONTENT_TYPE, ty)], body).into_response()
}

#[derive(serde::Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// Every request presents the token, when the studio has one; a request
/// that changes the session comes from the studio's own page (a browser
/// names the page's origin, which must be this server's).
async fn guard(
    State(app): State<Arc<App>>,
    Query(q): Query<TokenQuery>,
    headers: HeaderMap,
    req: Request,
    next: Next,
) -> Response {
    if let Some(t) = &app.token {
        let from_header = headers
            .get(header::AUTHORIZATION)
            .is_some_and(|v| t.accepts(v.as_bytes()));
        let from_query = q
            .token
            .is_some_and(|v| t.accepts(format!("Bearer {v}").as_bytes()));
        if !from_header && !from_query {
            return (StatusCode::UNAUTHORIZED, "a token is required\n").into_response();
        }
    }
    if req.method() != Method::GET && req.method() != Method::HEAD {
        if let Some(origin) = headers.get(header::ORIGIN) {
            let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
            let same = origin
                .to_str()
                .ok()
                .and_then(|o| o.strip_prefix("http://"))
                .is_some_and(|o| Some(o) == host);
            if !same {
                return (
                    StatusCode::FORBIDDEN,
                    "a change must come from the studio's own page (Origin differs from Host)\n",
                )
                    .into_response();
            }
        }
    }
    next.run(req).await
}

async fn session_status(State(app): State<Arc<App>>) -> Response {
    let l = app.shared.lock();
    Json(l.status.clone()).into_response()
}

/// Server-sent events: the session's status as JSON, at once and on
/// every change (coalesced: a slow reader gets the newest).
async fn events(State(app): State<Arc<App>>) -> Response {
    use tokio_stream::StreamExt;
    let rx = app.shared.events.subscribe();
    let stream = tokio_stream::wrappers::WatchStream::new(rx)
        .map(|json| Ok::<_, Infallible>(Event::default().data(json)));
    Sse::new(stream)
        .keep_alive(KeepAlive::default())
        .into_response()
}

async fn pipeline(State(app): State<Arc<App>>) -> Response {
    let yaml = app.shared.lock().session.yaml();
    (
        [
            (header::CONTENT_TYPE, "text/yaml; charset=utf-8"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"session.yaml\"",
            ),
        ],
        yaml,
    )
        .into_response()
}

/// The session as a tar: its pipeline and the masks beside it.
async fn export(State(app): State<Arc<App>>) -> Response {
    let tar = app.shared.lock().session.export();
    match tar {
        Ok(b) => (
            [
                (header::CONTENT_TYPE, "application/x-tar"),
                (
                    header::CONTENT_DISPOSITION,
                    "attachment; filename=\"session.tar\"",
                ),
            ],
            b,
        )
            .into_response(),
        Err(e) => request_error(e).into_response(),
    }
}

/// `/api/maps/NAME.png`: one of the session's maps, by its fixed name.
async fn map(State(app): State<Arc<App>>, UrlPath(file): UrlPath<String>) -> Response {
    let Some(name) = file.strip_suffix(".png") else {
        return (StatusCode::NOT_FOUND, "maps are NAME.png\n").into_response();
    };
    if !view::MAP_NAMES.contains(&name) {
        return (
            StatusCode::NOT_FOUND,
            format!("no map {name:?}: one of {}\n", view::MAP_NAMES.join(", ")),
        )
            .into_response();
    }
    served(&app, name, "image/png")
}

fn served(app: &App, name: &str, ty: &'static str) -> Response {
    let l = app.shared.lock();
    match l.images.get(name) {
        Some(b) => (
            [
                (header::CONTENT_TYPE, ty),
                (header::CACHE_CONTROL, "no-store"),
            ],
            b.clone(),
        )
            .into_response(),
        None => (
            StatusCode::NOT_FOUND,
            format!("the session has no {name} (yet)\n"),
        )
            .into_response(),
    }
}

/// `/api/images/NAME`: the renders (`recovery.png`, the recovery's fit so
/// far; `preview.png`, `result.png`,
/// `result.exr`) and the selection's overlay (`selection.png`).
async fn image_file(State(app): State<Arc<App>>, UrlPath(file): UrlPath<String>) -> Response {
    match file.as_str() {
        "recovery.png" => served(&app, "recovery", "image/png"),
        "preview.png" => served(&app, "preview", "image/png"),
        "result.png" => served(&app, "result", "image/png"),
        "result.exr" => {
            let img = app.shared.lock().result.clone();
            match img {
                Some(img) => {
                    let exr = tokio::task::spawn_blocking(move || view::exr(&img))
                        .await
                        .unwrap_or_default();
                    (
                        [
                            (header::CONTENT_TYPE, "image/x-exr"),
                            (header::CACHE_CONTROL, "no-store"),
                        ],
                        exr,
                    )
                        .into_response()
                }
                None => {
                    (StatusCode::NOT_FOUND, "the session has no result (yet)\n").into_response()
                }
            }
        }
        "selection.png" => {
            let png = view::overlay(&app.shared.lock().selection);
            (
                [
                    (header::CONTENT_TYPE, "image/png"),
                    (header::CACHE_CONTROL, "no-store"),
                ],
                png,
            )
                .into_response()
        }
        _ => (
            StatusCode::NOT_FOUND,
            "images are preview.png, result.png, result.exr and selection.png\n",
        )
            .into_response(),
    }
}

/// How a selection step meets the selection so far.
#[derive(Clone, Copy, Debug, Default, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
enum Mode {
    #[default]
    Set,
    Add,
    Remove,
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Point {
    x: f64,
    y: f64,
    #[serde(default)]
    mode: Mode,
    /// The colour tolerance (γ-encoded albedo, per channel).
    tolerance: Option<f32>,
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Rect {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
    #[serde(default)]
    mode: Mode,
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Brush {
    /// Centres of the brush's dabs, pixels.
    points: Vec<[f64; 2]>,
    radius: f64,
    #[serde(default)]
    mode: Mode,
}

type Answer = Result<Response, (StatusCode, String)>;

fn bad(m: impl Into<String>) -> (StatusCode, String) {
    (StatusCode::UNPROCESSABLE_ENTITY, m.into() + "\n")
}

/// Applies `step` (a mask of the image's size) to the selection by `mode`
/// and answers how many pixels are selected.
fn select_with(
    app: &App,
    mode: Mode,
    step: impl FnOnce(&live::Surfaces) -> Result<Image<bool>, (StatusCode, String)>,
) -> Answer {
    let mut l = app.shared.lock();
    let Some(surf) = l.surfaces.as_ref() else {
        return Err((
            StatusCode::CONFLICT,
            "the scene is not ready yet: select once its maps are shown\n".into(),
        ));
    };
    let m = step(surf)?;
    let sel = &mut l.selection;
    for (s, &n) in sel.data.iter_mut().zip(&m.data) {
        *s = match mode {
            Mode::Set => n,
            Mode::Add => *s || n,
            Mode::Remove => *s && !n,
        };
    }
    let count = sel.data.iter().filter(|&&b| b).count();
    l.status.selected = count;
    app.shared.publish(&l);
    Ok(Json(serde_json::json!({ "selected": count })).into_response())
}

/// A pixel of the image: within it and finite, else a message.
fn pixel(x: f64, y: f64, w: usize, h: usize) -> Result<(usize, usize), (StatusCode, String)> {
    if !(x.is_finite() && y.is_finite() && x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64) {
        return Err(bad(format!("({x}, {y}) is outside the {w}x{h} image")));
    }
    Ok((x as usize, y as usize))
}

/// `POST /api/select {x, y, mode, tolerance}`: the object under a pixel.
async fn select_point(State(app): State<Arc<App>>, Json(p): Json<Point>) -> Answer {
    let tol = p.tolerance.unwrap_or(Grow::default().albedo_tol);
    if !(0.0..=1.0).contains(&tol) {
        return Err(bad(format!("tolerance {tol} is outside 0..1")));
    }
    select_with(&app, p.mode, |s| {
        let seed = pixel(p.x, p.y, s.albedo.width, s.albedo.height)?;
        let g = Grow {
            albedo_tol: tol,
            ..Grow::default()
        };
        // Within the photo's own edges, as the `edit` stage's
        // `mask_object`: where the predictions are blurred, they run from
        // an object into what is behind it.
        Ok(grow_object_within_edges(
            &s.albedo,
            &s.depth,
            s.normals.as_ref(),
            s.photo.as_ref().map(|p| (p, PHOTO_EDGE_STEP)),
            &s.camera,
            seed,
            &g,
        ))
    })
}

/// `POST /api/select/rect {x0, y0, x1, y1, mode}`: a rectangle (x1, y1
/// exclusive; clipped to the image).
async fn select_rect(State(app): State<Arc<App>>, Json(r): Json<Rect>) -> Answer {
    if ![r.x0, r.y0, r.x1, r.y1].iter().all(|v| v.is_finite()) {
        return Err(bad("the rectangle's corners must be numbers"));
    }
    select_with(&app, r.mode, |s| {
        let (x0, x1) = (r.x0.min(r.x1), r.x0.max(r.x1));
        let (y0, y1) = (r.y0.min(r.y1), r.y0.max(r.y1));
        Ok(Image::from_fn(s.albedo.width, s.albedo.height, |x, y| {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            px >= x0 && px < x1 && py >= y0 && py < y1
        }))
    })
}

/// `POST /api/select/brush {points, radius, mode}`: round dabs.
async fn select_brush(State(app): State<Arc<App>>, Json(b): Json<Brush>) -> Answer {
    if !(b.radius.is_finite() && b.radius > 0.0 && b.radius <= 4096.0) {
        return Err(bad(format!("radius {} is outside (0, 4096]", b.radius)));
    }
    if b.points.is_empty() || b.points.len() > 10_000 {
        return Err(bad("give 1 to 10000 points"));
    }
    if b.points.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad("the points must be numbers"));
    }
    select_with(&app, b.mode, |s| {
        let (w, h) = (s.albedo.width, s.albedo.height);
        let mut m = Image::new(w, h, false);
        let r2 = b.radius * b.radius;
        for [cx, cy] in &b.points {
            let (xa, xb) = (
                (cx - b.radius).max(0.0) as usize,
                ((cx + b.radius).ceil().max(0.0) as usize).min(w),
            );
            let (ya, yb) = (
                (cy - b.radius).max(0.0) as usize,
                ((cy + b.radius).ceil().max(0.0) as usize).min(h),
            );
            for y in ya..yb {
                for x in xa..xb {
                    let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
                    if dx * dx + dy * dy <= r2 {
                        m.set(x, y, true);
                    }
                }
            }
        }
        Ok(m)
    })
}

#[derive(serde::Deserialize)]
struct MaskQuery {
    #[serde(default)]
    mode: Mode,
}

/// `POST /api/select/mask?mode=` with a PNG body of the image's size
/// (white, opaque pixels selected).
async fn select_mask(
    State(app): State<Arc<App>>,
    Query(q): Query<MaskQuery>,
    body: Bytes,
) -> Answer {
    let m = matflow_scene::io::decode_mask(std::path::Path::new("the uploaded mask"), &body)
        .map_err(|e| bad(e.to_string()))?;
    select_with(&app, q.mode, |s| {
        if m.width != s.albedo.width || m.height != s.albedo.height {
            return Err(bad(format!(
                "the mask is {}x{}; the image is {}x{}",
                m.width, m.height, s.albedo.width, s.albedo.height
            )));
        }
        Ok(m)
    })
}

async fn select_clear(State(app): State<Arc<App>>) -> Answer {
    select_with(&app, Mode::Set, |s| {
        Ok(Image::new(s.albedo.width, s.albedo.height, false))
    })
}

/// A change of the session's stages: `f` on the live state (once the
/// scene is ready, where `needs_scene`), then a new generation for the
/// runner.
fn change(
    app: &App,
    needs_scene: bool,
    f: impl FnOnce(&mut live::Live, &matflow_engine::Registry) -> Result<(), SessionError>,
) -> Answer {
    let mut l = app.shared.lock();
    if needs_scene && l.surfaces.is_none() {
        return Err((StatusCode::CONFLICT, "the scene is not ready yet\n".into()));
    }
    f(&mut l, &app.shared.registry).map_err(request_error)?;
    app.shared.changed(l);
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// `POST /api/edit {albedo, hue_shift, …}`: the selection changed, as a
/// new edit stage; the renders follow.
async fn edit(State(app): State<Arc<App>>, Json(c): Json<Change>) -> Answer {
    change(&app, true, |l, reg| {
        let mask = l.selection.clone();
        l.session.edit(&mask, &c, reg)
    })
}

/// `POST /api/glass {ior, transmission, roughness}`: the selection made
/// glass, its refraction lengths from matflow's network.
async fn glass(State(app): State<Arc<App>>, Json(g): Json<Glass>) -> Answer {
    change(&app, true, |l, reg| {
        let mask = l.selection.clone();
        l.session.glass(&mask, &g, reg)
    })
}

/// `POST /api/light {envmap, rotation, exposure}`: new lighting (the
/// recovered envmap when `envmap` is absent), as a history stage.
async fn light(State(app): State<Arc<App>>, Json(light): Json<Light>) -> Answer {
    if !(light.rotation.is_finite() && light.exposure.is_finite()) {
        return Err(bad("rotation and exposure must be numbers"));
    }
    change(&app, false, |l, reg| l.session.light(&light, reg))
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Objects {
    objects: Vec<Object>,
}

/// `POST /api/insert {objects: [{mesh, anchor, scale, rotate, material}]}`:
/// the objects in the scene, all of them (a new placement in the history).
async fn insert(State(app): State<Arc<App>>, Json(o): Json<Objects>) -> Answer {
    for (i, ob) in o.objects.iter().enumerate() {
        let nums = [ob.anchor[0], ob.anchor[1], ob.scale, ob.rotate];
        if !nums.iter().all(|v| v.is_finite()) || ob.scale <= 0.0 {
            return Err(bad(format!(
                "objects[{i}]: anchor, scale and rotate must be numbers, scale above 0"
            )));
        }
    }
    change(&app, true, |l, reg| l.session.insert(&o.objects, reg))
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Geometry {
    complete: String,
}

/// `POST /api/geometry {complete}`: other geometry past the frame (auto,
/// none, planes, room, closed): the recovery and the renders run again.
async fn geometry(State(app): State<Arc<App>>, Json(g): Json<Geometry>) -> Answer {
    change(&app, false, |l, reg| {
        l.session.set_geometry(&g.complete, reg)?;
        l.status.geometry_taken.clear();
        Ok(())
    })
}

async fn undo(State(app): State<Arc<App>>) -> Answer {
    change(&app, false, |l, _| match l.session.undo()? {
        true => Ok(()),
        false => Err(SessionError::Conflict("nothing to undo".into())),
    })
}

async fn redo(State(app): State<Arc<App>>) -> Answer {
    change(&app, false, |l, _| match l.session.redo()? {
        true => Ok(()),
        false => Err(SessionError::Conflict("nothing to redo".into())),
    })
}

/// A file uploaded to the session's folder by `add` (off the lock: the
/// runner goes on), the status's lists of files refreshed; answers
/// `{KEY: name}`.
async fn upload(
    app: &App,
    body: Bytes,
    key: &'static str,
    add: fn(&std::path::Path, &[u8]) -> Result<String, SessionError>,
) -> Answer {
    let dir = app.shared.lock().session.dir.clone();
    let name = tokio::task::spawn_blocking(move || add(&dir, &body))
        .await
        .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")))?
        .map_err(request_error)?;
    let mut l = app.shared.lock();
    l.status.envmaps = l.session.envmaps();
    l.status.meshes = l.session.meshes();
    app.shared.publish(&l);
    Ok(Json(serde_json::json!({ key: name })).into_response())
}

/// `POST /api/light/envmap` with a Radiance HDR or OpenEXR body: kept in
/// the session (named by its contents) for `/api/light`.
async fn upload_envmap(State(app): State<Arc<App>>, body: Bytes) -> Answer {
    upload(&app, body, "envmap", Session::add_envmap).await
}

/// `POST /api/insert/mesh` with an OBJ or PLY body: kept in the session
/// (named by its contents) for `/api/insert`.
async fn upload_mesh(State(app): State<Arc<App>>, body: Bytes) -> Answer {
    upload(&app, body, "mesh", Session::add_mesh).await
}

/// `POST /api/open` with a PNG, JPEG or EXR body: the session on that
/// photo (predicted, then recovered with the session's settings), its
/// history empty, in the studio's session folder.
async fn open_photo(State(app): State<Arc<App>>, body: Bytes) -> Answer {
    let shared = app.shared.clone();
    tokio::task::spawn_blocking(move || {
        let dir = shared.lock().session.dir.clone();
        let photo = Session::add_photo(&dir, &body)?;
        let session = shared
            .lock()
            .session
            .on_photo(&photo, &shared.registry)
            .map_err(|e| match e {
                SessionError::Pipeline(m) => SessionError::Request(m),
                e => e,
            })?;
        let name = photo
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        shared.replace(session, name);
        Ok::<_, SessionError>(())
    })
    .await
    .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")))?
    .map_err(request_error)?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// Serves `router` on `listener` until the process ends.
pub async fn serve(listener: tokio::net::TcpListener, router: Router) -> std::io::Result<()> {
    axum::serve(listener, router).await
}
