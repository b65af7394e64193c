//! The remote executor: stages on workers.
//!
//! Ready stages wait in one queue; a dispatcher places each on the worker
//! with the most free slots (stages that read the submitter's files run
//! in-process). An attempt is a streaming `Execute` call: the worker
//! accepts, sends progress and heartbeats, and ends with a result or a
//! typed error. A worker that cannot be reached, drops the stream, or
//! goes quiet for longer than the heartbeat timeout (or past the stage
//! deadline) loses the stage, which goes to another worker — at least
//! once, as in the Remote Execution API; nodes are pure, so running one
//! twice is harmless. Attempts are bounded and each retry is reported. A
//! failure that is the stage's own (the node failed, a bad parameter)
//! ends the stage at once with the worker's message.

use std::cmp::Reverse;
use std::collections::{BTreeSet, BinaryHeap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Notify;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

use matflow_engine::store::Action;
use matflow_engine::{
    execute_job, Done, Event, Executor, Failure, Job, LocalExecutor, Registry, Sink,
    Status as StageStatus, Tiered,
};

use crate::auth::{AddToken, Token};
use crate::convert::{blob_from_pb, blob_ref, params_to_pb};
use crate::net::TlsFiles;
use crate::pb::{
    self, execute_event::Event as Ev, node_service_client::NodeServiceClient, ErrorCode,
};
use crate::reapi::{status_text, OwnRuntime};

type Client = NodeServiceClient<InterceptedService<Channel, AddToken>>;

#[derive(Clone, Debug)]
pub struct RemoteOptions {
    /// Heartbeat interval asked of workers.
    pub heartbeat: Duration,
    /// A worker silent this long has lost its stage.
    pub heartbeat_timeout: Duration,
    /// A stage still running after this long is taken away (None: no
    /// limit beyond heartbeats).
    pub stage_timeout: Option<Duration>,
    /// Attempts per stage before the run gives up on it.
    pub max_attempts: u32,
    /// The store endpoint told to workers that have none of their own.
    pub store_endpoint: String,
    pub tls: TlsFiles,
    pub token: Option<Token>,
    /// Slots per worker, overriding what the worker says.
    pub slots: Option<u32>,
}

impl Default for RemoteOptions {
    fn default() -> Self {
        RemoteOptions {
            heartbeat: Duration::from_millis(1000),
            heartbeat_timeout: Duration::from_secs(10),
            stage_timeout: None,
            max_attempts: 3,
            store_endpoint: String::new(),
            tls: TlsFiles::default(),
            token: None,
            slots: None,
        }
    }
}

/// How stages reach a worker.
enum Conn {
    /// A `matflow worker` over the node service.
    Grpc(Client),
    /// A worker inside this process with its own store tiers: the
    /// scheduler benchmark's simulated workers (everything but the wire).
    InProcess(Arc<Tiered>),
}

struct Worker {
    addr: String,
    conn: Conn,
    slots: u32,
    /// The pause after its next failure (doubling to 30 s; reset by a
    /// success).
    backoff: Mutex<Duration>,
}

const FIRST_BACKOFF: Duration = Duration::from_millis(500);

/// Free slots of every worker, kept in placement order: the usable worker
/// with the most free slots (lowest index on ties) is found in O(log W),
/// and so are the updates, so dispatch cost does not grow with the pool.
pub(crate) struct Slots {
    free: Vec<u32>,
    /// Usable workers with a free slot, as (free, Reverse(index)).
    ready: BTreeSet<(u32, Reverse<usize>)>,
    /// Backed off until then, after a failure.
    down_until: Vec<Option<Instant>>,
    revivals: BinaryHeap<Reverse<(Instant, usize)>>,
}

impl Slots {
    pub(crate) fn new(caps: &[u32]) -> Slots {
        Slots {
            free: caps.to_vec(),
            ready: caps
                .iter()
                .enumerate()
                .filter(|(_, &c)| c > 0)
                .map(|(i, &c)| (c, Reverse(i)))
                .collect(),
            down_until: vec![None; caps.len()],
            revivals: BinaryHeap::new(),
        }
    }

    fn unlist(&mut self, i: usize) {
        self.ready.remove(&(self.free[i], Reverse(i)));
    }

    fn list(&mut self, i: usize) {
        if self.down_until[i].is_none() && self.free[i] > 0 {
            self.ready.insert((self.free[i], Reverse(i)));
        }
    }

    /// Workers whose back-off has ended become usable again.
    fn revive(&mut self, now: Instant) {
        while let Some(Reverse((t, i))) = self.revivals.peek().copied() {
            if t > now {
                break;
            }
            self.revivals.pop();
            if self.down_until[i] == Some(t) {
                self.down_until[i] = None;
                self.list(i);
            }
        }
    }

    /// Takes a slot on the usable worker with the most free slots,
    /// preferring any other worker to `avoid` (where the stage last
    /// failed) when one is free.
    pub(crate) fn take(&mut self, avoid: Option<usize>, now: Instant) -> Option<usize> {
        self.revive(now);
        let mut best = self.ready.iter().rev();
        let first = *best.next()?;
        let pick = if Some(first.1 .0) == avoid {
            best.next().copied().unwrap_or(first)
        } else {
            first
        };
        let i = pick.1 .0;
        self.unlist(i);
        self.free[i] -= 1;
        self.list(i);
        Some(i)
    }

    /// Gives a slot back.
    pub(crate) fn release(&mut self, i: usize) {
        self.unlist(i);
        self.free[i] += 1;
        self.list(i);
    }

    /// Leaves worker `i` out until `until`.
    pub(crate) fn back_off(&mut self, i: usize, until: Instant) {
        self.unlist(i);
        self.down_until[i] = Some(until);
        self.revivals.push(Reverse((until, i)));
    }
}

/// The ready queue and the slots, under one lock.
struct Sched {
    queue: VecDeque<Queued>,
    slots: Slots,
}

struct Queued {
    job: Job,
    sink: Sink,
    attempts: u32,
    reasons: Vec<String>,
    avoid: Option<usize>,
}

struct Inner {
    workers: Vec<Arc<Worker>>,
    store: Arc<Tiered>,
    reg: Arc<Registry>,
    opts: RemoteOptions,
    sched: Mutex<Sched>,
    notify: Notify,
}

pub struct RemoteExecutor {
    inner: Arc<Inner>,
    local: LocalExecutor,
    /// Runs the dispatcher and the calls; shut down on drop.
    _rt: OwnRuntime,
}

/// What a worker said about itself.
#[derive(Clone, Debug)]
pub struct WorkerInfo {
    pub addr: String,
    pub id: String,
    pub slots: u32,
}

impl RemoteExecutor {
    /// Connects to every worker (Describe) and checks it serves the same
    /// node kinds at the same versions. A worker that refuses the token
    /// or runs other node versions is an error; one that cannot be reached
    /// is left out with a warning (it is tried again if it comes back)
    /// unless none can be reached.
    pub fn connect(
        addrs: &[String],
        reg: Arc<Registry>,
        store: Arc<Tiered>,
        local_threads: usize,
        opts: RemoteOptions,
    ) -> Result<(RemoteExecutor, Vec<WorkerInfo>), String> {
        let rt = OwnRuntime::new(2, "matflow-dispatch");
        let mut workers = Vec::new();
        let mut infos = Vec::new();
        let mut unreachable = Vec::new();
        for a in addrs {
            let ch = {
                let _g = rt.get().enter();
                crate::net::channel(a, &opts.tls).map_err(|e| format!("worker {e}"))?
            };
            let client = NodeServiceClient::with_interceptor(ch, AddToken(opts.token.clone()));
            let mut c = client.clone();
            let r = rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(10), c.describe(pb::DescribeRequest {}))
                    .await
            });
            let slots = match r {
                Ok(Ok(resp)) => {
                    let d = resp.into_inner();
                    check_kinds(a, &reg, &d)?;
                    infos.push(WorkerInfo {
                        addr: a.clone(),
                        id: d.worker_id.clone(),
                        slots: d.slots,
                    });
                    opts.slots.unwrap_or(d.slots).max(1)
                }
                Ok(Err(s)) if s.code() == tonic::Code::Unauthenticated => {
                    return Err(format!(
                        "worker {a} refused this run's token: {}",
                        s.message()
                    ))
                }
                Ok(Err(s)) => {
                    unreachable.push(format!("{a} ({})", status_text(&s)));
                    continue;
                }
                Err(_) => {
                    unreachable.push(format!("{a} (no answer in 10 s)"));
                    continue;
                }
            };
            workers.push(Arc::new(Worker {
                addr: a.clone(),
                conn: Conn::Grpc(client),
                slots,
                backoff: Mutex::new(FIRST_BACKOFF),
            }));
        }
        if workers.is_empty() {
            return Err(format!(
                "no worker could be reached: {}",
                unreachable.join(", ")
            ));
        }
        for u in &unreachable {
            tracing::warn!("worker {u} left out of this run");
        }
        Ok((
            RemoteExecutor::start(rt, workers, reg, store, local_threads, opts),
            infos,
        ))
    }

    /// The same scheduler with `workers` simulated workers of `slots`
    /// slots each, inside this process: each runs its stages with
    /// [`execute_job`] on `worker_store` (its tiers in front of the store
    /// shared with `store`), so everything but the network is real. For
    /// measuring the scheduler (`matflow-bench pipeline`).
    pub fn simulated(
        workers: usize,
        slots: u32,
        reg: Arc<Registry>,
        store: Arc<Tiered>,
        worker_store: Arc<Tiered>,
    ) -> RemoteExecutor {
        let rt = OwnRuntime::new(2, "matflow-dispatch");
        let ws = (0..workers)
            .map(|i| {
                Arc::new(Worker {
                    addr: format!("sim-{i}"),
                    conn: Conn::InProcess(worker_store.clone()),
                    slots: slots.max(1),
                    backoff: Mutex::new(FIRST_BACKOFF),
                })
            })
            .collect();
        RemoteExecutor::start(rt, ws, reg, store, 1, RemoteOptions::default())
    }

    fn start(
        rt: OwnRuntime,
        workers: Vec<Arc<Worker>>,
        reg: Arc<Registry>,
        store: Arc<Tiered>,
        local_threads: usize,
        opts: RemoteOptions,
    ) -> RemoteExecutor {
        let caps: Vec<u32> = workers.iter().map(|w| w.slots).collect();
        let inner = Arc::new(Inner {
            workers,
            store: store.clone(),
            reg: reg.clone(),
            opts,
            sched: Mutex::new(Sched {
                queue: VecDeque::new(),
                slots: Slots::new(&caps),
            }),
            notify: Notify::new(),
        });
        let i2 = inner.clone();
        rt.get().spawn(async move { dispatcher(i2).await });
        let local = LocalExecutor::new(reg, store, local_threads);
        RemoteExecutor {
            inner,
            local,
            _rt: rt,
        }
    }
}

fn check_kinds(addr: &str, reg: &Registry, d: &pb::DescribeResponse) -> Result<(), String> {
    for n in reg.iter() {
        match d.kinds.iter().find(|k| k.kind == n.kind()) {
            Some(k) if k.version == n.version() => {}
            Some(k) => {
                return Err(format!(
                    "worker {addr} runs {} version {}, this submitter version {}: \
                     use the same matflow build on both",
                    n.kind(),
                    k.version,
                    n.version()
                ))
            }
            None => {
                return Err(format!(
                    "worker {addr} does not serve the node kind {} (matflow {})",
                    n.kind(),
                    d.matflow_version
                ))
            }
        }
    }
    Ok(())
}

impl Executor for RemoteExecutor {
    fn submit(&self, job: Job, sink: Sink) {
        if job.local_only {
            return self.local.submit(job, sink);
        }
        self.inner.sched.lock().unwrap().queue.push_back(Queued {
            job,
            sink,
            attempts: 0,
            reasons: vec![],
            avoid: None,
        });
        self.inner.notify.notify_one();
    }
    fn describe(&self) -> String {
        let ws: Vec<String> = self
            .inner
            .workers
            .iter()
            .map(|w| format!("{} ({} slots)", w.addr, w.slots))
            .collect();
        format!("workers {}", ws.join(", "))
    }
}

/// Picks the next (job, worker): the queue's first job on the usable
/// worker with the most free slots, avoiding the one the job last failed
/// on when another is free.
fn pick(inner: &Inner) -> Option<(Queued, usize)> {
    let mut s = inner.sched.lock().unwrap();
    let avoid = s.queue.front()?.avoid;
    let w = s.slots.take(avoid, Instant::now())?;
    s.queue.pop_front().map(|q| (q, w))
}

async fn dispatcher(inner: Arc<Inner>) {
    loop {
        while let Some((q, w)) = pick(&inner) {
            let i2 = inner.clone();
            tokio::spawn(async move { attempt(i2, w, q).await });
        }
        tokio::select! {
            _ = inner.notify.notified() => {}
            _ = tokio::time::sleep(Duration::from_millis(250)) => {}
        }
    }
}

enum Outcome {
    Done(
        Done,
        Vec<(
            String,
            matflow_engine::Digest,
            Option<matflow_engine::CasRef>,
        )>,
        f64,
    ),
    /// The stage's own failure: final.
    Final(Failure),
    /// The attempt failed for the worker's reasons: try elsewhere.
    Retry(String),
}

async fn attempt(inner: Arc<Inner>, wi: usize, mut q: Queued) {
    let w = inner.workers[wi].clone();
    let outcome = try_once(&inner, &w, &q).await;
    {
        let mut s = inner.sched.lock().unwrap();
        s.slots.release(wi);
        let mut b = w.backoff.lock().unwrap();
        if matches!(outcome, Outcome::Retry(_)) {
            s.slots.back_off(wi, Instant::now() + *b);
            *b = (*b * 2).min(Duration::from_secs(30));
        } else {
            *b = FIRST_BACKOFF;
        }
    }
    inner.notify.notify_one();
    let stage = q.job.stage.clone();
    match outcome {
        Outcome::Done(done, outs, seconds) => {
            // Remember the entry here too, so the next run's lookup is
            // answered without a worker.
            let store = inner.store.clone();
            let job = q.job.clone();
            let worker = done.worker.clone();
            let _ = tokio::task::spawn_blocking(move || {
                for (_, d, r) in &outs {
                    if let Some(r) = r {
                        store.learn(d, r);
                    }
                }
                let a = Action {
                    kind: job.kind.clone(),
                    stage: job.stage.clone(),
                    pipeline: job.pipeline.clone(),
                    outputs: outs.iter().map(|(n, d, _)| (n.clone(), d.hex())).collect(),
                    seconds,
                    worker,
                };
                let _ = store.local().put_action(&job.key, &a);
            })
            .await;
            (q.sink)(Event::Finished {
                stage,
                result: Ok(done),
            });
        }
        Outcome::Final(f) => {
            (q.sink)(Event::Finished {
                stage,
                result: Err(f),
            });
        }
        Outcome::Retry(reason) => {
            q.attempts += 1;
            let reason = format!("attempt {} on {}: {reason}", q.attempts, w.addr);
            q.reasons.push(reason.clone());
            if q.attempts >= inner.opts.max_attempts {
                (q.sink)(Event::Finished {
                    stage,
                    result: Err(Failure::Infra(format!(
                        "gave up after {} attempts: {}",
                        q.attempts,
                        q.reasons.join("; ")
                    ))),
                });
            } else {
                (q.sink)(Event::Retry { stage, reason });
                q.avoid = Some(wi);
                inner.sched.lock().unwrap().queue.push_front(q);
                inner.notify.notify_one();
            }
        }
    }
}

async fn try_once(inner: &Arc<Inner>, w: &Arc<Worker>, q: &Queued) -> Outcome {
    let job = &q.job;
    let Some(node) = inner.reg.get(&job.kind) else {
        return Outcome::Final(Failure::Node(format!("unknown node kind `{}`", job.kind)));
    };
    // Inputs must be in the shared store before a worker can read them.
    let store = inner.store.clone();
    let inputs: Vec<(String, matflow_engine::Digest)> =
        job.inputs.iter().map(|(k, d)| (k.clone(), *d)).collect();
    let (skip, key) = (job.skip_cache || q.attempts > 0, job.key);
    let prep = tokio::task::spawn_blocking(move || {
        if !skip {
            if let Some(ds) = store.lookup(&key)? {
                return Ok(Err(ds));
            }
        }
        let mut refs = Vec::new();
        for (name, d) in inputs {
            let r = store.ensure_remote(&d)?;
            refs.push((name, d, r));
        }
        Ok::<_, matflow_engine::StoreError>(Ok(refs))
    })
    .await;
    let refs = match prep {
        Ok(Ok(Ok(refs))) => refs,
        Ok(Ok(Err(cached))) => {
            return Outcome::Done(
                Done {
                    status: StageStatus::Cached,
                    outputs: cached,
                    worker: "cache".into(),
                    bytes_in: 0,
                    bytes_out: 0,
                },
                vec![],
                0.0,
            )
        }
        Ok(Err(e)) => return Outcome::Final(Failure::Infra(e.to_string())),
        Err(e) => return Outcome::Final(Failure::Infra(e.to_string())),
    };
    let mut missing = Vec::new();
    let req = pb::ExecuteRequest {
        action_key: job.key.0.to_vec(),
        kind: job.kind.clone(),
        kind_version: node.version(),
        stage: job.stage.clone(),
        pipeline: job.pipeline.clone(),
        params: params_to_pb(node.info(), &job.params),
        inputs: refs
            .iter()
            .map(|(n, d, r)| {
                if r.is_none() {
                    missing.push(n.clone());
                }
                (n.clone(), blob_ref(d, r.as_ref()))
            })
            .collect(),
        store: inner.opts.store_endpoint.clone(),
        skip_cache_lookup: job.skip_cache,
        heartbeat_ms: inner.opts.heartbeat.as_millis() as u32,
    };
    if !missing.is_empty() {
        return Outcome::Final(Failure::InputsMissing(missing));
    }
    let client = match &w.conn {
        Conn::Grpc(c) => c,
        Conn::InProcess(ws) => return in_process(inner, w, ws.clone(), q).await,
    };
    let t0 = Instant::now();
    let deadline = inner.opts.stage_timeout.map(|d| t0 + d);
    let hb = inner.opts.heartbeat_timeout;
    let mut client = client.clone();
    let call = tokio::time::timeout(hb, client.execute(req)).await;
    let mut stream = match call {
        Err(_) => return Outcome::Retry(format!("no answer within {:.1} s", hb.as_secs_f64())),
        Ok(Err(s)) if s.code() == tonic::Code::Unauthenticated => {
            return Outcome::Final(Failure::Infra(format!(
                "worker {} refused the token",
                w.addr
            )))
        }
        Ok(Err(s)) => return Outcome::Retry(format!("unreachable: {}", status_text(&s))),
        Ok(Ok(r)) => r.into_inner(),
    };
    loop {
        let wait = match deadline {
            Some(d) => hb.min(d.saturating_duration_since(Instant::now())),
            None => hb,
        };
        let msg = match tokio::time::timeout(wait, stream.message()).await {
            Err(_) => {
                if deadline.is_some_and(|d| Instant::now() >= d) {
                    return Outcome::Retry(format!(
                        "still running after the stage deadline ({:.0} s)",
                        inner.opts.stage_timeout.unwrap_or_default().as_secs_f64()
                    ));
                }
                return Outcome::Retry(format!("silent for {:.1} s (hung?)", hb.as_secs_f64()));
            }
            Ok(Err(s)) => return Outcome::Retry(format!("stream broke: {}", status_text(&s))),
            Ok(Ok(None)) => return Outcome::Retry("stream ended without a result".into()),
            Ok(Ok(Some(m))) => m,
        };
        match msg.event {
            Some(Ev::Accepted(_)) => (q.sink)(Event::Started {
                stage: job.stage.clone(),
                worker: w.addr.clone(),
            }),
            Some(Ev::Progress(p)) => (q.sink)(Event::Progress {
                stage: job.stage.clone(),
                done: p.done,
                total: p.total,
            }),
            Some(Ev::Log(l)) => tracing::info!("{} on {}: {}", job.stage, w.addr, l.line),
            Some(Ev::Heartbeat(_)) | None => {}
            Some(Ev::Result(r)) => {
                let mut outs = Vec::new();
                let mut outputs = std::collections::BTreeMap::new();
                for (name, b) in &r.outputs {
                    match blob_from_pb(b) {
                        Ok((d, cr)) => {
                            outputs.insert(name.clone(), d);
                            outs.push((name.clone(), d, cr));
                        }
                        Err(e) => return Outcome::Retry(format!("malformed result: {e}")),
                    }
                }
                return Outcome::Done(
                    Done {
                        status: if r.cached {
                            StageStatus::Cached
                        } else {
                            StageStatus::Executed
                        },
                        outputs,
                        worker: w.addr.clone(),
                        bytes_in: r.bytes_in,
                        bytes_out: r.bytes_out,
                    },
                    outs,
                    r.seconds,
                );
            }
            Some(Ev::Error(e)) => {
                let code = ErrorCode::try_from(e.code).unwrap_or(ErrorCode::Unspecified);
                let m = format!("worker {}: {}", w.addr, e.message);
                return match code {
                    ErrorCode::InputMissing => {
                        Outcome::Final(Failure::InputsMissing(e.missing_inputs))
                    }
                    ErrorCode::Unavailable | ErrorCode::Unspecified => Outcome::Retry(e.message),
                    _ => Outcome::Final(Failure::Node(m)),
                };
            }
        }
    }
}

/// Where stage `(layer, j)` of [`layered_pipeline`] takes its second
/// input from in the layer before.
pub fn layered_second_input(j: usize, width: usize) -> usize {
    (j * 7 + 3) % width.max(1)
}

/// A pipeline file of `layers × width` stages of node kind `kind` (with an
/// integer parameter `i` and optional references `a`, `b`), each stage past
/// the first layer reading two of the layer before: the scheduler
/// benchmark's and tests' workload. Stage `(l, j)` is `s{l}_{j}`; the last
/// layer is the output.
pub fn layered_pipeline(kind: &str, layers: usize, width: usize) -> String {
    let mut y = String::from("pipeline: layered\noutputs: [");
    y += &(0..width)
        .map(|j| format!("s{}_{j}", layers.max(1) - 1))
        .collect::<Vec<_>>()
        .join(", ");
    y += "]\nstages:\n";
    for l in 0..layers {
        for j in 0..width {
            let i = l * width + j;
            if l == 0 {
                y += &format!("  s0_{j}: {{kind: {kind}, i: {i}}}\n");
            } else {
                y += &format!(
                    "  s{l}_{j}: {{kind: {kind}, i: {i}, a: s{}_{j}, b: s{}_{}}}\n",
                    l - 1,
                    l - 1,
                    layered_second_input(j, width)
                );
            }
        }
    }
    y
}

/// A simulated worker's attempt: the stage runs here, through the same
/// `execute_job` a `matflow worker` runs, on the worker's own tiers.
async fn in_process(inner: &Arc<Inner>, w: &Arc<Worker>, ws: Arc<Tiered>, q: &Queued) -> Outcome {
    (q.sink)(Event::Started {
        stage: q.job.stage.clone(),
        worker: w.addr.clone(),
    });
    let (reg, job, id) = (inner.reg.clone(), q.job.clone(), w.addr.clone());
    let t0 = Instant::now();
    let r = tokio::task::spawn_blocking(move || {
        let r = execute_job(&reg, &ws, &job, &id, &|_, _| {});
        r.map(|done| {
            let outs = done
                .outputs
                .iter()
                .map(|(n, d)| (n.clone(), *d, ws.cas_ref(d)))
                .collect::<Vec<_>>();
            (done, outs)
        })
    })
    .await;
    match r {
        Ok(Ok((done, outs))) => Outcome::Done(done, outs, t0.elapsed().as_secs_f64()),
        Ok(Err(Failure::Infra(m))) => Outcome::Retry(m),
        Ok(Err(f)) => Outcome::Final(f),
        Err(e) => Outcome::Retry(format!("the worker's task failed: {e}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The placement rule, stated the slow way.
    fn brute(free: &[u32], down: &[bool], avoid: Option<usize>) -> Option<usize> {
        (0..free.len())
            .filter(|&i| free[i] > 0 && !down[i])
            .max_by_key(|&i| (Some(i) != avoid, free[i], Reverse(i)))
    }

    #[test]
    fn slots_place_like_the_rule_under_random_traffic() {
        let caps = [3u32, 1, 2, 2, 4, 1, 3];
        let mut s = Slots::new(&caps);
        let mut free = caps.to_vec();
        let mut down = vec![false; caps.len()];
        let mut held: Vec<usize> = Vec::new();
        let t0 = Instant::now();
        let mut x = 0x9e3779b97f4a7c15u64;
        for step in 0..5000u64 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let now = t0 + Duration::from_millis(step);
            match x % 5 {
                0..=2 => {
                    let avoid = (x >> 8) as usize % (caps.len() + 1);
                    let avoid = (avoid < caps.len()).then_some(avoid);
                    // Revive exactly as the structure does: back-offs here
                    // end 3 ms after they start.
                    for (i, d) in down.iter_mut().enumerate() {
                        if *d && s.down_until[i].is_some_and(|t| t <= now) {
                            *d = false;
                        }
                    }
                    let want = brute(&free, &down, avoid);
                    let got = s.take(avoid, now);
                    assert_eq!(got, want, "step {step}");
                    if let Some(i) = got {
                        free[i] -= 1;
                        held.push(i);
                    }
                }
                3 if !held.is_empty() => {
                    let i = held.swap_remove((x >> 8) as usize % held.len());
                    s.release(i);
                    free[i] += 1;
                }
                4 if !held.is_empty() => {
                    let i = held.swap_remove((x >> 8) as usize % held.len());
                    s.release(i);
                    free[i] += 1;
                    if !down[i] {
                        s.back_off(i, now + Duration::from_millis(3));
                        down[i] = true;
                    }
                }
                _ => {}
            }
        }
    }

    #[test]
    fn a_backed_off_worker_returns_when_its_time_comes() {
        let mut s = Slots::new(&[1, 1]);
        let t = Instant::now();
        s.back_off(0, t + Duration::from_secs(1));
        assert_eq!(s.take(None, t), Some(1));
        assert_eq!(s.take(None, t), None, "worker 0 is backed off");
        assert_eq!(s.take(None, t + Duration::from_secs(1)), Some(0));
    }
}
