//! The node service: a worker runs stages for submitters.
//!
//! Every request is checked as the pipeline loader checks a stage — kind
//! and version known, every parameter of the right type and in range,
//! nothing that reads the submitter's files — and the worker recomputes
//! the action key from what it was given; a request whose key differs is
//! refused (a submitter and worker that disagree on a node's version or
//! encoding must not share cache entries). Inputs come from the store,
//! outputs go to it, and the result names them by digest.

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::{mpsc, Semaphore};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use matflow_engine::key::node_key;
use matflow_engine::node::{ParamType, Params};
use matflow_engine::{
    execute_job, Digest, Failure, Job, Registry, Status as StageStatus, Store, Tiered, Value,
};

use crate::auth::Token;
use crate::convert::{blob_from_pb, blob_ref, node_kind, value_from_pb, MAX_PARAMS};
use crate::net::TlsFiles;
use crate::pb::{self, execute_event::Event as Ev, ErrorCode};
use crate::reapi::RemoteCas;

pub struct WorkerOptions {
    pub id: String,
    /// Stages run at once.
    pub slots: usize,
    /// The worker's local disk tier.
    pub cache_dir: PathBuf,
    /// Its store (`grpc://…`); without one it uses the store each request
    /// names.
    pub store: Option<String>,
    pub instance: String,
    /// TLS and token for reaching the store.
    pub store_tls: TlsFiles,
    pub store_token: Option<Token>,
}

pub struct NodeSvc {
    reg: Arc<Registry>,
    opts: WorkerOptions,
    slots: Arc<Semaphore>,
    running: Arc<AtomicU32>,
    stores: Mutex<HashMap<String, Arc<Tiered>>>,
}

impl NodeSvc {
    pub fn new(reg: Arc<Registry>, opts: WorkerOptions) -> NodeSvc {
        NodeSvc {
            slots: Arc::new(Semaphore::new(opts.slots.max(1))),
            running: Arc::new(AtomicU32::new(0)),
            stores: Mutex::new(HashMap::new()),
            reg,
            opts,
        }
    }

    /// The tiered store for a request (blocking: connects on first use).
    fn store_for(&self, requested: &str) -> Result<Arc<Tiered>, String> {
        let ep = match &self.opts.store {
            Some(s) => s.clone(),
            None if !requested.is_empty() => requested.to_string(),
            None => return Err("neither this worker nor the request names a store".into()),
        };
        if let Some(s) = self.stores.lock().unwrap().get(&ep) {
            return Ok(s.clone());
        }
        let remote = RemoteCas::connect(
            &ep,
            &self.opts.instance,
            &self.opts.store_tls,
            self.opts.store_token.clone(),
        )
        .map_err(|e| e.to_string())?;
        let local = Store::open(&self.opts.cache_dir).map_err(|e| e.to_string())?;
        let t = Arc::new(Tiered::new(local, Some(Arc::new(remote))));
        self.stores.lock().unwrap().insert(ep, t.clone());
        Ok(t)
    }
}

type Refused = (ErrorCode, String);

/// Checks a request exactly as the pipeline loader checks a stage and
/// turns it into a job; the key is recomputed and must match.
pub fn validate(reg: &Registry, req: &pb::ExecuteRequest) -> Result<Job, Refused> {
    let inv = |m: String| (ErrorCode::InvalidArgument, m);
    let key = crate::convert::digest_from_bytes(&req.action_key).ok_or_else(|| {
        inv(format!(
            "action key of {} bytes (32 expected)",
            req.action_key.len()
        ))
    })?;
    let node = reg.get(&req.kind).ok_or_else(|| {
        (
            ErrorCode::UnknownKind,
            format!(
                "this worker has no node kind `{}` (it has: {})",
                req.kind,
                reg.kinds().join(", ")
            ),
        )
    })?;
    if node.version() != req.kind_version {
        return Err((
            ErrorCode::UnknownKind,
            format!(
                "{} is version {} here, the submitter runs version {}",
                req.kind,
                node.version(),
                req.kind_version
            ),
        ));
    }
    if req.params.len() > MAX_PARAMS || req.inputs.len() > MAX_PARAMS {
        return Err(inv(format!("more than {MAX_PARAMS} parameters")));
    }
    if req.stage.len() > 256 || req.pipeline.len() > 256 {
        return Err(inv("stage or pipeline name over 256 bytes".into()));
    }
    let stage = &req.stage;
    for name in req.params.keys() {
        if !node.params().iter().any(|p| p.name == name) {
            return Err(inv(format!(
                "stage `{stage}`: {} has no parameter `{name}`",
                req.kind
            )));
        }
    }
    let mut params = Params::default();
    for p in node.params() {
        let v = match req.params.get(p.name) {
            Some(v) => value_from_pb(v, 0)
                .map_err(|e| inv(format!("stage `{stage}`, `{}`: {e}", p.name)))?,
            None => Value::Null,
        };
        let v = match (&p.ty, v) {
            (_, Value::Null) if p.default.is_some() => Value::Null,
            (_, Value::Null) => {
                return Err(inv(format!(
                    "stage `{stage}`: missing parameter `{}` ({})",
                    p.name,
                    p.ty.describe()
                )))
            }
            (ParamType::InPath, _) => {
                return Err((
                    ErrorCode::LocalOnly,
                    format!(
                        "stage `{stage}` reads `{}` on the submitter's disk: it runs there",
                        p.name
                    ),
                ))
            }
            (ParamType::OutPath, _) => {
                return Err(inv(format!(
                    "stage `{stage}`, `{}`: output paths are written by the submitter, not sent",
                    p.name
                )))
            }
            (ty, v) => ty.normalize(&v).ok_or_else(|| {
                inv(format!(
                    "stage `{stage}`, `{}`: expected {}, got {v}",
                    p.name,
                    ty.describe()
                ))
            })?,
        };
        params.0.insert(p.name.to_string(), v);
    }
    let mut inputs = BTreeMap::new();
    for (name, b) in &req.inputs {
        let is_ref = node
            .params()
            .iter()
            .any(|p| p.name == name && matches!(p.ty, ParamType::Ref(_)));
        if !is_ref || !params.is_set(name) {
            return Err(inv(format!(
                "stage `{stage}`: input `{name}` is not a reference it set"
            )));
        }
        let (d, _) = blob_from_pb(b).map_err(|e| inv(format!("input `{name}`: {e}")))?;
        inputs.insert(name.clone(), d);
    }
    for p in node.params() {
        if matches!(p.ty, ParamType::Ref(_))
            && params.is_set(p.name)
            && !inputs.contains_key(p.name)
        {
            return Err(inv(format!(
                "stage `{stage}`: no input blob for reference `{}`",
                p.name
            )));
        }
    }
    node.check(&params)
        .map_err(|m| inv(format!("stage `{stage}`: {m}")))?;
    let mine = node_key(node, &params, &inputs).map_err(|e| inv(e.to_string()))?;
    if mine != key {
        return Err((
            ErrorCode::KeyMismatch,
            format!(
                "stage `{stage}`: the action key here is {}, the submitter sent {} \
                 (different matflow builds?)",
                &mine.hex()[..12],
                &key.hex()[..12]
            ),
        ));
    }
    Ok(Job {
        stage: req.stage.clone(),
        kind: req.kind.clone(),
        pipeline: req.pipeline.clone(),
        params,
        key,
        inputs,
        skip_cache: req.skip_cache_lookup,
        local_only: false,
        watch: None,
    })
}

fn event(e: Ev) -> Result<pb::ExecuteEvent, Status> {
    Ok(pb::ExecuteEvent { event: Some(e) })
}

fn error(code: ErrorCode, message: String, missing: Vec<String>) -> Ev {
    Ev::Error(pb::ExecuteError {
        code: code as i32,
        message,
        missing_inputs: missing,
    })
}

#[tonic::async_trait]
impl pb::node_service_server::NodeService for Arc<NodeSvc> {
    async fn describe(
        &self,
        _req: Request<pb::DescribeRequest>,
    ) -> Result<Response<pb::DescribeResponse>, Status> {
        Ok(Response::new(pb::DescribeResponse {
            worker_id: self.opts.id.clone(),
            matflow_version: env!("CARGO_PKG_VERSION").into(),
            slots: self.opts.slots.max(1) as u32,
            running: self.running.load(Ordering::Relaxed),
            kinds: self.reg.iter().map(|n| node_kind(n.info())).collect(),
            store: self.opts.store.clone().unwrap_or_default(),
        }))
    }

    type ExecuteStream = ReceiverStream<Result<pb::ExecuteEvent, Status>>;

    async fn execute(
        &self,
        req: Request<pb::ExecuteRequest>,
    ) -> Result<Response<Self::ExecuteStream>, Status> {
        let req = req.into_inner();
        let (tx, rx) = mpsc::channel(64);
        let svc = self.clone();
        tokio::spawn(async move {
            let job = match validate(&svc.reg, &req) {
                Ok(j) => j,
                Err((code, m)) => {
                    let _ = tx.send(event(error(code, m, vec![]))).await;
                    return;
                }
            };
            let Ok(_permit) = svc.slots.clone().acquire_owned().await else {
                return;
            };
            svc.running.fetch_add(1, Ordering::Relaxed);
            println!("start {} ({}) for {}", job.stage, job.kind, job.pipeline);
            let _ = tx
                .send(event(Ev::Accepted(pb::Accepted {
                    worker_id: svc.opts.id.clone(),
                })))
                .await;
            let beat = Duration::from_millis(match req.heartbeat_ms {
                0 => 1000,
                n => n.clamp(50, 60_000) as u64,
            });
            let stage = job.stage.clone();
            let t0 = Instant::now();
            let out = run(&svc, &req, job, &tx, beat).await;
            let how = match &out {
                Ev::Result(r) if r.cached => "cached".to_string(),
                Ev::Result(_) => "done".to_string(),
                Ev::Error(e) => format!("failed: {}", e.message),
                _ => String::new(),
            };
            println!("{how} {stage} in {:.2} s", t0.elapsed().as_secs_f64());
            let _ = tx.send(event(out)).await;
            svc.running.fetch_sub(1, Ordering::Relaxed);
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

/// Runs a validated job and returns the final event. Keeps going when the
/// submitter has gone: the result still lands in the store.
async fn run(
    svc: &Arc<NodeSvc>,
    req: &pb::ExecuteRequest,
    job: Job,
    tx: &mpsc::Sender<Result<pb::ExecuteEvent, Status>>,
    beat: Duration,
) -> Ev {
    let t0 = Instant::now();
    let (ptx, mut prx) = mpsc::unbounded_channel::<(u64, u64)>();
    let svc2 = svc.clone();
    let store_ep = req.store.clone();
    let refs: Vec<(Digest, Option<matflow_engine::CasRef>)> = req
        .inputs
        .values()
        .filter_map(|b| blob_from_pb(b).ok())
        .collect();
    let mut h = tokio::task::spawn_blocking(move || {
        let store = svc2.store_for(&store_ep).map_err(Failure::Infra)?;
        for (d, r) in &refs {
            if let Some(r) = r {
                store.learn(d, r);
            }
        }
        let last = Mutex::new(Instant::now() - Duration::from_secs(1));
        let progress = |d: u64, t: u64| {
            let mut l = last.lock().unwrap();
            if l.elapsed() >= Duration::from_millis(100) || (t > 0 && d >= t) {
                *l = Instant::now();
                let _ = ptx.send((d, t));
            }
        };
        let done = execute_job(&svc2.reg, &store, &job, &svc2.opts.id, &progress)?;
        let mut outs = Vec::new();
        for (name, d) in &done.outputs {
            let r = store
                .ensure_remote(d)
                .map_err(|e| Failure::Infra(e.to_string()))?
                .ok_or_else(|| Failure::Infra(format!("output `{name}` is not in the store")))?;
            outs.push((name.clone(), *d, r));
        }
        Ok::<_, Failure>((done, outs))
    });
    let mut tick = tokio::time::interval(beat);
    let res = loop {
        tokio::select! {
            r = &mut h => break r,
            Some((d, t)) = prx.recv() => {
                let _ = tx.send(event(Ev::Progress(pb::Progress { done: d, total: t }))).await;
            }
            _ = tick.tick() => {
                let _ = tx.send(event(Ev::Heartbeat(pb::Heartbeat { seconds: t0.elapsed().as_secs_f64() }))).await;
            }
        }
    };
    match res {
        Err(e) => error(
            ErrorCode::Unavailable,
            format!("worker task failed: {e}"),
            vec![],
        ),
        Ok(Err(Failure::Node(m))) => error(ErrorCode::NodeFailed, m, vec![]),
        Ok(Err(Failure::InputsMissing(ps))) => error(
            ErrorCode::InputMissing,
            format!("inputs missing or corrupt in the store: {}", ps.join(", ")),
            ps,
        ),
        Ok(Err(Failure::Infra(m))) => error(ErrorCode::Unavailable, m, vec![]),
        // Workers' jobs carry no watch: a node cannot be cancelled here.
        Ok(Err(f @ Failure::Cancelled)) => error(ErrorCode::NodeFailed, f.message(), vec![]),
        Ok(Ok((done, outs))) => Ev::Result(pb::ExecuteResult {
            outputs: outs
                .iter()
                .map(|(n, d, r)| (n.clone(), blob_ref(d, Some(r))))
                .collect(),
            cached: done.status == StageStatus::Cached,
            seconds: t0.elapsed().as_secs_f64(),
            bytes_in: done.bytes_in,
            bytes_out: done.bytes_out,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use matflow_engine::node::{NodeError, NodeInfo, OutputSpec, ParamSpec, RunContext};
    use matflow_engine::Node;

    static INFO: NodeInfo = NodeInfo {
        kind: "scale",
        version: 3,
        doc: "test node",
        params: &[
            ParamSpec {
                name: "factor",
                ty: ParamType::Float { min: 0.0, max: 4.0 },
                default: Some("1"),
                unit: "",
                doc: "",
            },
            ParamSpec {
                name: "source",
                ty: ParamType::Ref(&["image"]),
                default: None,
                unit: "",
                doc: "",
            },
            ParamSpec {
                name: "mask",
                ty: ParamType::InPath,
                default: Some("~"),
                unit: "",
                doc: "",
            },
        ],
        outputs: &[OutputSpec {
            name: "image",
            ty: "image",
            doc: "",
        }],
    };
    struct Scale;
    impl Node for Scale {
        fn info(&self) -> &'static NodeInfo {
            &INFO
        }
        fn run(&self, _: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
            Ok(BTreeMap::new())
        }
    }

    fn request(reg: &Registry, factor: pb::Value) -> pb::ExecuteRequest {
        let input = Digest::of(b"upstream");
        let mut params = Params::default();
        params.0.insert("factor".into(), Value::Float(2.0));
        params.0.insert("source".into(), Value::Str("up".into()));
        params.0.insert("mask".into(), Value::Null);
        let inputs: BTreeMap<String, Digest> =
            [("source".to_string(), input)].into_iter().collect();
        let key = node_key(reg.get("scale").unwrap(), &params, &inputs).unwrap();
        let mut p = crate::convert::params_to_pb(&INFO, &params);
        p.insert("factor".into(), factor);
        pb::ExecuteRequest {
            action_key: key.0.to_vec(),
            kind: "scale".into(),
            kind_version: 3,
            stage: "s".into(),
            params: p,
            inputs: [("source".to_string(), blob_ref(&input, None))]
                .into_iter()
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn requests_are_checked_like_pipeline_stages() {
        let mut reg = Registry::new();
        reg.add(Box::new(Scale));
        let f = |x: f64| crate::convert::value_to_pb(&Value::Float(x));
        let good = request(&reg, f(2.0));
        let job = validate(&reg, &good).expect("a valid request");
        assert_eq!(job.params.f64("factor"), 2.0);
        let code = |r: &pb::ExecuteRequest| validate(&reg, r).unwrap_err().0;
        // Out of range, exactly as the loader bounds it.
        assert_eq!(code(&request(&reg, f(4.5))), ErrorCode::InvalidArgument);
        // A different value than the key was computed for.
        assert_eq!(code(&request(&reg, f(3.0))), ErrorCode::KeyMismatch);
        let mut r = good.clone();
        r.kind_version = 2;
        assert_eq!(code(&r), ErrorCode::UnknownKind);
        let mut r = good.clone();
        r.kind = "nope".into();
        assert_eq!(code(&r), ErrorCode::UnknownKind);
        let mut r = good.clone();
        r.params.insert(
            "mask".into(),
            crate::convert::value_to_pb(&Value::Str("/etc/passwd".into())),
        );
        assert_eq!(code(&r), ErrorCode::LocalOnly);
        let mut r = good.clone();
        r.params.insert("extra".into(), f(1.0));
        assert_eq!(code(&r), ErrorCode::InvalidArgument);
        let mut r = good.clone();
        r.inputs.clear();
        assert_eq!(code(&r), ErrorCode::InvalidArgument);
        let mut r = good.clone();
        r.action_key.truncate(5);
        assert_eq!(code(&r), ErrorCode::InvalidArgument);
    }
}
