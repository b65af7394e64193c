//! `matflow studio [PHOTO | BUNDLE | PIPELINE.yaml]`: the session in the
//! browser (see `matflow_studio`).

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;

#[derive(Args)]
pub struct StudioArgs {
    /// What to open: a photo (PNG/JPEG/EXR: predicted), a bundle folder
    /// (its predictions), or a pipeline file (its stages, one of them
    /// named `scene`; an exported session opens with its edits).
    pub input: PathBuf,
    /// The address to listen on. Loopback unless a token is given.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen: SocketAddr,
    /// Cache folder (as for `run`: the studio and `run` share it).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// The session's folder, where its pipeline (`session.yaml`) is kept
    /// (default: `studio/NAME-HASH/` in the cache folder, one per input,
    /// so studios on different inputs keep apart).
    #[arg(long)]
    pub session: Option<PathBuf>,
    /// A token every request must present (else $MATFLOW_TOKEN); needed
    /// to listen on anything but loopback.
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Where the session's stages run and what store they share (as for
    /// `run`: `--workers` and `--remote-cache`; default: in this process
    /// on the local cache).
    #[command(flatten)]
    pub remote: crate::cluster::RemoteArgs,
    /// Write the address the studio listens on here (for scripts and
    /// tests: with `--listen 127.0.0.1:0` the port is the system's pick).
    #[arg(long)]
    pub address_file: Option<PathBuf>,
}

/// The default session folder's name for `input`: its file name and a
/// short digest of its absolute path.
fn session_name(input: &std::path::Path) -> Result<String> {
    let abs = std::path::absolute(input).with_context(|| format!("{}", input.display()))?;
    let digest = matflow_engine::store::Digest::of(abs.to_string_lossy().as_bytes()).hex();
    let stem: String = abs
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .take(40)
        .collect();
    Ok(format!("{stem}-{}", &digest[..12]))
}

pub fn studio(a: StudioArgs) -> Result<()> {
    let cache = crate::run::cache_dir(a.cache.as_deref());
    let token =
        matflow_rpc::auth::Token::load(a.token_file.as_deref()).map_err(anyhow::Error::msg)?;
    let session = match &a.session {
        Some(s) => s.clone(),
        None => cache.join("studio").join(session_name(&a.input)?),
    };
    let reg = std::sync::Arc::new(matflow_nodes::registry());
    let (store, executor) = crate::cluster::executor(&a.remote, None, &cache, reg, 1)?;
    let rt = tokio::runtime::Runtime::new().context("starting the studio's runtime")?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.listen)
            .await
            .with_context(|| format!("listening on {}", a.listen))?;
        let bound = listener.local_addr()?;
        let router = matflow_studio::start(
            matflow_studio::StudioOptions {
                input: a.input.clone(),
                session,
                store,
                executor,
                token,
            },
            bound,
        )?;
        if let Some(f) = &a.address_file {
            matflow_scene::io::write_atomic(f, bound.to_string().as_bytes())
                .with_context(|| format!("writing {}", f.display()))?;
        }
        outln!("matflow studio at http://{bound}/ ({})", a.input.display());
        matflow_studio::serve(listener, router)
            .await
            .context("serving the studio")
    })
}
