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

pub mod session;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use matflow_rpc::auth::Token;

const INDEX_HTML: &str = include_str!("../web/index.html");
const STUDIO_JS: &str = include_str!("../web/studio.js");
const STUDIO_CSS: &str = include_str!("../web/studio.css");

/// How a studio serves.
pub struct StudioOptions {
    /// A photo, a bundle folder or a pipeline file to open.
    pub input: PathBuf,
    /// The session's folder (its `session.yaml`).
    pub session: PathBuf,
    /// The engine's cache (shared with `matflow run`).
    pub cache: PathBuf,
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

/// Where the session stands, as `/api/session` says it.
#[derive(Clone, serde::Serialize)]
struct Status {
    /// `running`, `ready` or `failed`.
    state: &'static str,
    input: String,
    message: String,
    width: usize,
    height: usize,
    /// The images `/api/maps/NAME.png` serves.
    maps: Vec<&'static str>,
}

struct Shared {
    status: Mutex<Status>,
    maps: Mutex<Vec<(&'static str, Vec<u8>)>>,
    pipeline: Mutex<String>,
    token: Option<Token>,
}

/// Checks the address against the token rule, writes the session's
/// pipeline, and returns the router with its session started (running in
/// the background; `/api/session` says when it is ready).
pub fn start(opts: StudioOptions, listen: SocketAddr) -> Result<Router, StudioError> {
    if !listen.ip().is_loopback() && opts.token.is_none() {
        return Err(StudioError::NeedsToken(listen));
    }
    // The session's pipeline lives in its own folder: a relative input
    // is taken from where the studio was started.
    let input = std::path::absolute(&opts.input).map_err(|source| StudioError::Io {
        path: opts.input.clone(),
        source,
    })?;
    let yaml = session::starting_pipeline(&input)?;
    std::fs::create_dir_all(&opts.session).map_err(|source| StudioError::Io {
        path: opts.session.clone(),
        source,
    })?;
    let file = opts.session.join("session.yaml");
    std::fs::write(&file, &yaml).map_err(|source| StudioError::Io { path: file, source })?;
    let shared = Arc::new(Shared {
        status: Mutex::new(Status {
            state: "running",
            input: opts.input.display().to_string(),
            message: "running the session's pipeline".into(),
            width: 0,
            height: 0,
            maps: vec![],
        }),
        maps: Mutex::new(vec![]),
        pipeline: Mutex::new(yaml),
        token: opts.token.clone(),
    });
    let bg = shared.clone();
    let (dir, cache) = (opts.session.clone(), opts.cache.clone());
    std::thread::spawn(move || {
        let result = session::run(&dir, &cache);
        let mut st = bg.status.lock().unwrap_or_else(|e| e.into_inner());
        match result {
            Ok((maps, summary)) => {
                st.state = "ready";
                st.message = summary;
                st.width = maps.width;
                st.height = maps.height;
                st.maps = maps.images.iter().map(|(n, _)| *n).collect();
                *bg.maps.lock().unwrap_or_else(|e| e.into_inner()) = maps.images;
            }
            Err(e) => {
                st.state = "failed";
                st.message = e.to_string();
            }
        }
    });
    Ok(router(shared))
}

fn router(shared: Arc<Shared>) -> Router {
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
        .route("/api/pipeline.yaml", get(pipeline))
        .route("/api/maps/{file}", get(map))
        .fallback(|| async { (StatusCode::NOT_FOUND, "no such page\n") })
        .layer(middleware::from_fn_with_state(shared.clone(), authorize))
        .with_state(shared)
}

fn page(body: &'static str, ty: &'static str) -> Response {
    ([(header::CONTENT_TYPE, ty)], body).into_response()
}

#[derive(serde::Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// Every request presents the token, when the studio has one.
async fn authorize(
    State(s): State<Arc<Shared>>,
    Query(q): Query<TokenQuery>,
    headers: HeaderMap,
    req: Request,
    next: Next,
) -> Response {
    if let Some(t) = &s.token {
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
    next.run(req).await
}

async fn session_status(State(s): State<Arc<Shared>>) -> Json<Status> {
    Json(s.status.lock().unwrap_or_else(|e| e.into_inner()).clone())
}

async fn pipeline(State(s): State<Arc<Shared>>) -> Response {
    let yaml = s.pipeline.lock().unwrap_or_else(|e| e.into_inner()).clone();
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

/// `/api/maps/NAME.png`: one of the session's images, by its fixed name.
async fn map(State(s): State<Arc<Shared>>, UrlPath(file): UrlPath<String>) -> Response {
    let Some(name) = file.strip_suffix(".png") else {
        return (StatusCode::NOT_FOUND, "maps are NAME.png\n").into_response();
    };
    if !session::MAP_NAMES.contains(&name) {
        return (
            StatusCode::NOT_FOUND,
            format!(
                "no map {name:?}: one of {}\n",
                session::MAP_NAMES.join(", ")
            ),
        )
            .into_response();
    }
    let maps = s.maps.lock().unwrap_or_else(|e| e.into_inner());
    match maps.iter().find(|(n, _)| *n == name) {
        Some((_, png)) => ([(header::CONTENT_TYPE, "image/png")], png.clone()).into_response(),
        None => (
            StatusCode::NOT_FOUND,
            format!("the session has no {name} (yet)\n"),
        )
            .into_response(),
    }
}

/// Serves `router` on `listener` until the process ends.
pub async fn serve(listener: tokio::net::TcpListener, router: Router) -> std::io::Result<()> {
    axum::serve(listener, router).await
}
