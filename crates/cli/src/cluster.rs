//! `matflow worker` and the distributed side of `matflow run`: the store
//! tiers, the workers, the token and TLS files.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use matflow_engine::{Executor, LocalExecutor, Registry, Store, StoreTier, Tiered};
use matflow_rpc::auth::{CheckToken, Token};
use matflow_rpc::net::TlsFiles;
use matflow_rpc::reapi::RemoteCas;
use matflow_rpc::remote::{RemoteExecutor, RemoteOptions};
use matflow_rpc::worker::{NodeSvc, WorkerOptions};

/// Options of `run` for running on workers and sharing a remote cache.
#[derive(Args, Clone, Default)]
pub struct RemoteArgs {
    /// Workers to run stages on (HOST:PORT, comma-separated; dns:NAME:PORT
    /// is one worker per address NAME resolves to, e.g. a Kubernetes
    /// headless Service). Without workers every stage runs in this process.
    #[arg(long, value_delimiter = ',', value_name = "ADDR,ADDR,...")]
    pub workers: Vec<String>,
    /// A file listing workers, one HOST:PORT per line (`#` comments).
    #[arg(long, value_name = "FILE")]
    pub workers_file: Option<PathBuf>,
    #[command(flatten)]
    pub store: StoreArgs,
    /// A worker silent this long (no heartbeat) loses its stage.
    #[arg(long, default_value_t = 10.0, value_name = "SECONDS")]
    pub heartbeat_timeout: f64,
    /// A stage running longer than this on a worker is sent elsewhere.
    #[arg(long, value_name = "SECONDS")]
    pub stage_timeout: Option<f64>,
    /// Attempts per stage before the run gives up on it.
    #[arg(long, default_value_t = 3)]
    pub max_attempts: u32,
    /// Stages per worker (default: what each worker says).
    #[arg(long)]
    pub slots: Option<u32>,
}

/// The store, token and TLS options `run` and `worker` share.
#[derive(Args, Clone, Default)]
pub struct StoreArgs {
    /// A Remote Execution API cache server as the shared store
    /// (grpc://HOST:PORT or grpcs://HOST:PORT). For `run` it overrides the
    /// pipeline's `remote_cache:`; a worker without one uses the store each
    /// submitter names.
    #[arg(long, value_name = "ENDPOINT")]
    pub remote_cache: Option<String>,
    /// The REAPI instance name on the cache server.
    #[arg(long, default_value = "")]
    pub remote_instance: String,
    /// The shared token (else $MATFLOW_TOKEN).
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// CA bundle (PEM) to check grpcs:// endpoints against; a worker
    /// serving TLS also requires client certificates signed by it.
    #[arg(long, value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
    /// Certificate and key (PEM): a worker serves TLS with them; `run`
    /// presents them to servers that ask for a client certificate.
    #[arg(long, value_name = "PEM")]
    pub tls_cert: Option<PathBuf>,
    #[arg(long, value_name = "PEM")]
    pub tls_key: Option<PathBuf>,
}

impl StoreArgs {
    fn tls(&self) -> TlsFiles {
        TlsFiles {
            ca: self.tls_ca.clone(),
            cert: self.tls_cert.clone(),
            key: self.tls_key.clone(),
        }
    }
    fn token(&self) -> Result<Option<Token>> {
        Token::load(self.token_file.as_deref()).map_err(anyhow::Error::msg)
    }
}

fn workers_from(a: &RemoteArgs) -> Result<Vec<String>> {
    let mut ws: Vec<String> = a
        .workers
        .iter()
        .map(|w| w.trim().to_string())
        .filter(|w| !w.is_empty())
        .collect();
    if let Some(f) = &a.workers_file {
        let text = std::fs::read_to_string(f)
            .with_context(|| format!("--workers-file {}", f.display()))?;
        for (i, line) in text.lines().enumerate() {
            let l = line.split('#').next().unwrap_or("").trim();
            if l.is_empty() {
                continue;
            }
            if !l.starts_with("dns:") {
                matflow_rpc::net::parse_endpoint(l)
                    .map_err(|e| anyhow::anyhow!("{}:{}: {e}", f.display(), i + 1))?;
            }
            ws.push(l.to_string());
        }
    }
    let mut out = Vec::new();
    for w in ws {
        if let Some(name) = w.strip_prefix("dns:") {
            out.extend(resolve_all(name)?);
        } else {
            matflow_rpc::net::parse_endpoint(&w).map_err(|e| anyhow::anyhow!("--workers: {e}"))?;
            out.push(w);
        }
    }
    Ok(out)
}

/// `dns:NAME:PORT`: one worker per address the name resolves to (a
/// Kubernetes headless Service lists its ready pods this way).
fn resolve_all(name: &str) -> Result<Vec<String>> {
    use std::net::ToSocketAddrs;
    let (host, port) = name
        .rsplit_once(':')
        .filter(|(h, p)| !h.is_empty() && p.parse::<u16>().is_ok())
        .with_context(|| format!("--workers dns:{name}: expected dns:NAME:PORT"))?;
    let mut addrs: Vec<SocketAddr> = (host, port.parse::<u16>().unwrap_or(0))
        .to_socket_addrs()
        .with_context(|| format!("--workers dns:{name}: resolving {host}"))?
        .collect();
    addrs.sort();
    addrs.dedup();
    if addrs.is_empty() {
        bail!("--workers dns:{name}: {host} resolves to no address (no worker ready yet?)");
    }
    Ok(addrs.iter().map(|a| a.to_string()).collect())
}

/// The store (local tier + the remote one, if any) and the executor for a
/// run, with a line saying where things run.
pub fn executor(
    a: &RemoteArgs,
    pipeline_cache: Option<&str>,
    cache_dir: &Path,
    reg: Arc<Registry>,
    parallel: usize,
) -> Result<(Arc<Tiered>, Box<dyn Executor>)> {
    let token = a.store.token()?;
    let files = a.store.tls();
    let remote_ep = a
        .store
        .remote_cache
        .clone()
        .or(pipeline_cache.map(str::to_string));
    let remote: Option<Arc<dyn StoreTier>> = match &remote_ep {
        Some(ep) => Some(Arc::new(
            RemoteCas::connect(ep, &a.store.remote_instance, &files, token.clone())
                .map_err(anyhow::Error::msg)?,
        )),
        None => None,
    };
    let store = Arc::new(Tiered::new(Store::open(cache_dir)?, remote));
    let workers = workers_from(a)?;
    if workers.is_empty() {
        return Ok((
            store.clone(),
            Box::new(LocalExecutor::new(reg, store, parallel)),
        ));
    }
    let Some(ep) = remote_ep else {
        bail!(
            "--workers needs a store the workers share with this run: give --remote-cache \
             grpc://HOST:PORT (or `remote_cache:` in the pipeline): any Remote Execution API \
             cache server, e.g. buildbox-casd or bazel-remote (cluster/local/workers.sh starts one)"
        );
    };
    let secs = |s: f64, what: &str| -> Result<Duration> {
        if s.is_finite() && s > 0.0 {
            Ok(Duration::from_secs_f64(s))
        } else {
            bail!("--{what} {s}: give a number of seconds > 0")
        }
    };
    let hb_timeout = secs(a.heartbeat_timeout, "heartbeat-timeout")?;
    let opts = RemoteOptions {
        heartbeat: (hb_timeout / 4).clamp(Duration::from_millis(50), Duration::from_secs(2)),
        heartbeat_timeout: hb_timeout,
        stage_timeout: a
            .stage_timeout
            .map(|s| secs(s, "stage-timeout"))
            .transpose()?,
        max_attempts: a.max_attempts.max(1),
        store_endpoint: ep,
        tls: files,
        token,
        slots: a.slots,
    };
    let (ex, _) = RemoteExecutor::connect(&workers, reg, store.clone(), parallel, opts)
        .map_err(anyhow::Error::msg)?;
    Ok((store, Box::new(ex)))
}

#[derive(Args)]
pub struct WorkerArgs {
    /// Address to serve on (HOST:PORT; port 0 picks a free one).
    #[arg(long, default_value = "127.0.0.1:0")]
    pub listen: String,
    /// Stages run at once.
    #[arg(long, default_value_t = 1)]
    pub slots: usize,
    /// Threads each stage's numerics use (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// The worker's local cache folder (a tier in front of the store).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    #[command(flatten)]
    pub store: StoreArgs,
    /// Serve without a token on a non-loopback address.
    #[arg(long)]
    pub insecure: bool,
    /// A name for reports (default: HOSTNAME:PORT).
    #[arg(long)]
    pub id: Option<String>,
    /// The host name submitters reach this worker by (default: the
    /// listening address, or $HOSTNAME when that is 0.0.0.0 or ::).
    #[arg(long, value_name = "HOST")]
    pub advertise: Option<String>,
    /// Once listening, write the worker's address (HOST:PORT) to this file,
    /// for launchers that collect a workers file (Slurm, the local one).
    #[arg(long, value_name = "FILE")]
    pub address_file: Option<PathBuf>,
}

pub fn worker(a: WorkerArgs, cache_dir: PathBuf) -> Result<()> {
    let addr: SocketAddr = a.listen.parse().with_context(|| {
        format!(
            "--listen {}: expected HOST:PORT with a numeric address",
            a.listen
        )
    })?;
    let token = a.store.token()?;
    if token.is_none() && !addr.ip().is_loopback() && !a.insecure {
        bail!(
            "--listen {addr} is reachable from other machines: give a token (--token-file or \
             ${}) or say --insecure",
            matflow_rpc::auth::TOKEN_ENV
        );
    }
    if let Some(t) = a.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t.max(1))
            .build_global()
            .context("setting the worker's thread count")?;
    }
    let server_tls = matflow_rpc::net::server_tls(&a.store.tls()).map_err(anyhow::Error::msg)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("--listen {addr}"))?;
        let bound = listener.local_addr()?;
        let host = match &a.advertise {
            Some(h) => h.clone(),
            None if bound.ip().is_unspecified() => std::env::var("HOSTNAME")
                .ok()
                .filter(|h| !h.is_empty())
                .unwrap_or_else(|| bound.ip().to_string()),
            None => bound.ip().to_string(),
        };
        let reach = if host.contains(':') {
            format!("[{host}]:{}", bound.port())
        } else {
            format!("{host}:{}", bound.port())
        };
        let id = a.id.clone().unwrap_or_else(|| reach.clone());
        let svc = Arc::new(NodeSvc::new(
            Arc::new(matflow_nodes::registry()),
            WorkerOptions {
                id: id.clone(),
                slots: a.slots.max(1),
                cache_dir,
                store: a.store.remote_cache.clone(),
                instance: a.store.remote_instance.clone(),
                store_tls: TlsFiles {
                    ca: a.store.tls_ca.clone(),
                    ..TlsFiles::default()
                },
                store_token: token.clone(),
            },
        ));
        let service = matflow_rpc::pb::node_service_server::NodeServiceServer::with_interceptor(
            svc,
            CheckToken(token.clone()),
        );
        let mut builder = tonic::transport::Server::builder();
        if let Some(t) = server_tls {
            builder = builder.tls_config(t)?;
        }
        outln!(
            "matflow worker {id} listening on {bound} ({} slots, token {}, {})",
            a.slots.max(1),
            if token.is_some() { "required" } else { "off" },
            if a.store.tls_cert.is_some() {
                "TLS"
            } else {
                "plaintext"
            }
        );
        use std::io::Write;
        std::io::stdout().flush()?;
        if let Some(f) = &a.address_file {
            matflow_scene::io::write_atomic(f, format!("{reach}\n").as_bytes())
                .with_context(|| format!("--address-file {}", f.display()))?;
        }
        let incoming = tokio_stream::wrappers::TcpListenerStream::new(listener);
        builder
            .add_service(service)
            .serve_with_incoming_shutdown(incoming, async {
                let _ = tokio::signal::ctrl_c().await;
            })
            .await
            .context("serving")?;
        Ok::<_, anyhow::Error>(())
    })
}
