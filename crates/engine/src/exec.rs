//! Running a pipeline: keys, cache lookups, execution, reports.
//!
//! The scheduler walks the needed stages; a stage becomes ready when its
//! inputs are done, and up to `parallel` ready stages run at once. For each
//! stage it computes the node key from the kind, version, parameters and
//! the *output digests* of its inputs, serves the stage from the action
//! cache when the entry exists and every blob verifies, and otherwise hands
//! the node to the [`Executor`] and stores what comes back. Executors
//! differ only in where `execute` runs; the in-process one calls the node.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Instant;

use crate::key::{node_key, node_seed};
use crate::node::{Node, NodeError, ParamType, Params, Registry, RunContext};
use crate::plan;
use crate::spec::Pipeline;
use crate::store::{Action, Digest, Store};
use crate::tier::Tiered;

/// What happened to a stage in a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Computed in this run.
    Executed,
    /// Served from the action cache.
    Cached,
    /// Not needed for the requested outputs (or blocked by a failure).
    Skipped,
    Failed,
}

impl Status {
    pub fn as_str(&self) -> &'static str {
        match self {
            Status::Executed => "executed",
            Status::Cached => "cached",
            Status::Skipped => "skipped",
            Status::Failed => "failed",
        }
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct StageReport {
    pub name: String,
    pub kind: String,
    pub status: Status,
    pub seconds: f64,
    /// The node key (hex), when it could be computed.
    pub key: Option<String>,
    /// Output name → BLAKE3 hex digest of its bytes.
    pub outputs: BTreeMap<String, String>,
    /// Files written for the user (render outputs).
    pub files: Vec<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Where it ran: `local` or a worker's address (absent when it did
    /// not start).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<String>,
    /// Attempts started (more than one after a retry).
    pub attempts: u32,
    /// Why earlier attempts did not count (a worker died, hung, an input
    /// was recomputed).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub retries: Vec<String>,
    /// Lines the stage left for the report (its outputs of type `note`:
    /// e.g. which backend and model a prediction used), cached or not.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// Bytes of inputs the stage read and outputs it wrote.
    pub bytes_in: u64,
    pub bytes_out: u64,
    #[serde(skip)]
    started: Option<Instant>,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct Report {
    pub pipeline: String,
    pub file: String,
    pub cache: String,
    /// Where stages ran: `local (N threads)` or the workers.
    pub executor: String,
    pub seconds: f64,
    /// Bytes sent to and fetched from the remote store tier.
    pub bytes_uploaded: u64,
    pub bytes_downloaded: u64,
    pub stages: Vec<StageReport>,
    /// This process's peak resident memory at the end of the run (Linux).
    pub peak_memory_bytes: Option<u64>,
}

impl StageReport {
    fn new(name: &str, kind: &str, status: Status) -> StageReport {
        StageReport {
            name: name.to_string(),
            kind: kind.to_string(),
            status,
            seconds: 0.0,
            key: None,
            outputs: BTreeMap::new(),
            files: vec![],
            error: None,
            worker: None,
            attempts: 0,
            retries: vec![],
            notes: vec![],
            bytes_in: 0,
            bytes_out: 0,
            started: None,
        }
    }
}

impl Report {
    pub fn stage(&self, name: &str) -> Option<&StageReport> {
        self.stages.iter().find(|s| s.name == name)
    }
    /// The first failure, as a message naming the stage.
    pub fn failure(&self) -> Option<String> {
        self.stages.iter().find_map(|s| {
            s.error
                .as_ref()
                .map(|e| format!("stage `{}` ({}): {e}", s.name, s.kind))
        })
    }
}

/// Progress callbacks (a front end draws bars from these).
pub trait Observer: Sync {
    /// The stage started on `worker` (`local` or a worker's address).
    fn started(&self, _stage: &str, _kind: &str, _worker: &str) {}
    fn progress(&self, _stage: &str, _done: u64, _total: u64) {}
    /// A named number the stage reported (e.g. `loss` per step; stages run
    /// in this process only).
    fn metric(&self, _stage: &str, _name: &str, _value: f64) {}
    /// An attempt failed for a reason that is not the stage's own (a
    /// worker died or hung, an input had to be recomputed); it runs again.
    fn retried(&self, _stage: &str, _reason: &str) {}
    fn finished(&self, _report: &StageReport) {}
    /// Whether the run is no longer wanted: asked between stages, it then
    /// submits nothing more (stages already out finish; the rest are
    /// reported skipped). A front end whose newer request supersedes a run
    /// says so here.
    fn cancelled(&self) -> bool {
        false
    }
    /// What stages running in this process may ask of the front end as
    /// they go (see [`Watch`]); `None`: nobody watches.
    fn watch(&self) -> Option<Watch> {
        None
    }
    /// An intermediate image a stage showed ([`crate::RunContext::image`]):
    /// `rgb` is linear, `width × height × 3`, row by row.
    fn image(&self, _stage: &str, _name: &str, _width: usize, _height: usize, _rgb: &[f32]) {}
}

/// A front end's hold on the stages of its run that execute in this
/// process: whether they are still wanted, asked as they run (a newer
/// edit superseding a render stops it between tiles), and whether it
/// wants their intermediate images. Stages on workers finish regardless.
#[derive(Clone)]
pub struct Watch {
    pub cancelled: Arc<dyn Fn() -> bool + Send + Sync>,
    pub images: bool,
}

impl std::fmt::Debug for Watch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Watch")
            .field("images", &self.images)
            .finish_non_exhaustive()
    }
}

/// An observer that shows nothing.
pub struct Silent;
impl Observer for Silent {}

/// One stage, ready to run: everything a worker needs, and nothing from
/// the submitter's disk except through the store.
#[derive(Clone, Debug)]
pub struct Job {
    pub stage: String,
    pub kind: String,
    pub pipeline: String,
    /// Validated, default-filled parameters.
    pub params: Params,
    /// The node key; the executor stores the result under it.
    pub key: Digest,
    /// Reference parameter → digest of the upstream output.
    pub inputs: BTreeMap<String, Digest>,
    /// Do not serve it from the cache (its entry turned out unreadable,
    /// or the scheduler has just looked it up and found none).
    pub skip_cache: bool,
    /// It reads files on the submitter's disk: it runs there.
    pub local_only: bool,
    /// The front end's hold on it while it runs in this process (never
    /// sent to a worker).
    pub watch: Option<Watch>,
}

/// How a job ended well.
#[derive(Clone, Debug)]
pub struct Done {
    pub status: Status,
    pub outputs: BTreeMap<String, Digest>,
    /// Where it ran.
    pub worker: String,
    /// Bytes of inputs read and outputs written.
    pub bytes_in: u64,
    pub bytes_out: u64,
}

/// How a job failed.
#[derive(Clone, Debug)]
pub enum Failure {
    /// The node itself failed: deterministic, running it again would fail
    /// again.
    Node(String),
    /// These reference parameters' blobs are gone or corrupt: the stages
    /// producing them must run again.
    InputsMissing(Vec<String>),
    /// The infrastructure failed (store, network, every attempt used up).
    Infra(String),
    /// The run no longer wanted it ([`Watch::cancelled`]); nothing stored.
    Cancelled,
}

impl Failure {
    /// A node's failure: the node's own, or the machine's (an
    /// [`Failure::Infra`], retried where a retry can help).
    pub fn of(e: NodeError) -> Failure {
        match e.kind() {
            crate::node::NodeErrorKind::Stage => Failure::Node(e.0),
            crate::node::NodeErrorKind::Machine => Failure::Infra(e.0),
            crate::node::NodeErrorKind::Cancelled => Failure::Cancelled,
        }
    }

    pub fn message(&self) -> String {
        match self {
            Failure::Node(m) | Failure::Infra(m) => m.clone(),
            Failure::InputsMissing(ps) => {
                format!("inputs missing or corrupt in the store: {}", ps.join(", "))
            }
            Failure::Cancelled => "cancelled: the run no longer wanted it".into(),
        }
    }
}

/// What an executor tells the scheduler about a job.
pub enum Event {
    Started {
        stage: String,
        worker: String,
    },
    Progress {
        stage: String,
        done: u64,
        total: u64,
    },
    Retry {
        stage: String,
        reason: String,
    },
    Metric {
        stage: String,
        name: String,
        value: f64,
    },
    /// An intermediate image ([`crate::RunContext::image`]).
    Image {
        stage: String,
        name: String,
        width: usize,
        height: usize,
        rgb: Vec<f32>,
    },
    /// Exactly once per submitted job.
    Finished {
        stage: String,
        result: Result<Done, Failure>,
    },
}

pub type Sink = Arc<dyn Fn(Event) + Send + Sync>;

/// Where stages run. `submit` returns at once; the executor reports
/// through the sink, ending with one [`Event::Finished`].
pub trait Executor: Send + Sync {
    fn submit(&self, job: Job, sink: Sink);
    /// Named in reports: `local`, or the workers.
    fn describe(&self) -> String;
    /// Whether the scheduler may serve cache hits itself, from the store
    /// it shares with this executor, instead of submitting them: a hit
    /// then costs no thread hand-off (a chain of 10,000 cached stages is
    /// otherwise 20,000 wake-ups). Executors whose workers report where
    /// a hit was served keep it false.
    fn serves_cache_inline(&self) -> bool {
        false
    }
}

/// Whether a stage reads files on the submitter's disk (an input path is
/// set), so it must run there.
pub fn reads_local_files(node: &dyn Node, params: &Params) -> bool {
    node.params()
        .iter()
        .any(|sp| sp.ty.reads_files(params.get(sp.name)))
}

/// Runs one job against a store: a cache hit when the entry and its blobs
/// are there, else the node, its outputs stored and the entry written.
/// The same function serves the in-process executor and workers.
pub fn execute_job(
    reg: &Registry,
    store: &Tiered,
    job: &Job,
    worker: &str,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<Done, Failure> {
    execute_job_observed(reg, store, job, worker, progress, &|_, _| {}, None)
}

/// [`execute_job`], the stage's metrics (see [`RunContext::metric`]) to
/// `metric` and its intermediate images to `image` (when the job's
/// [`Watch`] wants them); it stops early when the watch cancels it.
pub fn execute_job_observed(
    reg: &Registry,
    store: &Tiered,
    job: &Job,
    worker: &str,
    progress: &(dyn Fn(u64, u64) + Sync),
    metric: &(dyn Fn(&str, f64) + Sync),
    image: Option<&crate::node::LiveImage<'_>>,
) -> Result<Done, Failure> {
    let infra = |e: crate::store::StoreError| Failure::Infra(e.to_string());
    let node = reg
        .get(&job.kind)
        .ok_or_else(|| Failure::Node(format!("unknown node kind `{}`", job.kind)))?;
    if !job.skip_cache {
        if let Some(ds) = store.lookup(&job.key).map_err(infra)? {
            return Ok(Done {
                status: Status::Cached,
                outputs: ds,
                worker: worker.to_string(),
                bytes_in: 0,
                bytes_out: 0,
            });
        }
    }
    let mut in_bytes = BTreeMap::new();
    let mut missing = Vec::new();
    let mut bytes_in = 0;
    for (param, d) in &job.inputs {
        // An input that is not the artifact type the parameter takes (a
        // damaged or forged cache entry upstream) counts as missing: its
        // producer is sent back to run uncached.
        let accepts = node
            .params()
            .iter()
            .find(|p| p.name == param)
            .and_then(|p| match p.ty {
                ParamType::Ref(a) => Some(a),
                _ => None,
            });
        match store.get(d).map_err(infra)? {
            Some(b) if accepts.is_some_and(|a| !reg.artifact_is(&b, a)) => {
                missing.push(param.clone())
            }
            Some(b) => {
                bytes_in += b.len() as u64;
                in_bytes.insert(param.clone(), b);
            }
            None => missing.push(param.clone()),
        }
    }
    if !missing.is_empty() {
        return Err(Failure::InputsMissing(missing));
    }
    let cancelled = || job.watch.as_ref().is_some_and(|w| (w.cancelled)());
    let ctx = RunContext {
        stage: &job.stage,
        params: &job.params,
        inputs: in_bytes,
        seed: node_seed(node, &job.params),
        progress,
        metric,
        cancelled: &cancelled,
        image: image.filter(|_| job.watch.as_ref().is_some_and(|w| w.images)),
    };
    let ts = Instant::now();
    let outs = run_node(node, &ctx).map_err(Failure::of)?;
    let seconds = ts.elapsed().as_secs_f64();
    let mut ds = BTreeMap::new();
    let mut bytes_out = 0;
    for (name, b) in outs {
        bytes_out += b.len() as u64;
        let d = store.put(&Arc::new(b)).map_err(infra)?;
        ds.insert(name, d);
    }
    store
        .put_action(
            &job.key,
            &Action {
                kind: job.kind.clone(),
                stage: job.stage.clone(),
                pipeline: job.pipeline.clone(),
                outputs: ds.iter().map(|(k, d)| (k.clone(), d.hex())).collect(),
                seconds,
                worker: worker.to_string(),
            },
        )
        .map_err(infra)?;
    Ok(Done {
        status: Status::Executed,
        outputs: ds,
        worker: worker.to_string(),
        bytes_in,
        bytes_out,
    })
}

/// Calls the node; a panic becomes an error naming it, and so does an
/// output the node kind does not declare (nothing is stored then).
pub fn run_node(node: &dyn Node, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
    match catch_unwind(AssertUnwindSafe(|| node.run(ctx))) {
        Ok(Ok(outs)) => {
            let declared = node.outputs();
            let extra: Vec<&str> = outs
                .keys()
                .map(String::as_str)
                .filter(|k| !declared.iter().any(|o| o.name == *k))
                .collect();
            if extra.is_empty() {
                Ok(outs)
            } else {
                Err(NodeError::new(format!(
                    "internal error: node kind `{}` returned undeclared output(s) {} (declared: {})",
                    node.kind(),
                    extra.join(", "),
                    declared.iter().map(|o| o.name).collect::<Vec<_>>().join(", ")
                )))
            }
        }
        Ok(Err(e)) => Err(e),
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(NodeError::new(format!("internal error: {msg}")))
        }
    }
}

type Queue = Arc<Mutex<mpsc::Receiver<(Job, Sink)>>>;

/// Runs jobs in this process on a fixed number of threads (the embedded
/// default, and the part of a distributed run that reads local files).
pub struct LocalExecutor {
    tx: Mutex<Option<mpsc::Sender<(Job, Sink)>>>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
    n: usize,
}

impl LocalExecutor {
    pub fn new(reg: Arc<Registry>, store: Arc<Tiered>, threads: usize) -> LocalExecutor {
        let (tx, rx) = mpsc::channel::<(Job, Sink)>();
        let rx: Queue = Arc::new(Mutex::new(rx));
        let n = threads.max(1);
        let handles = (0..n)
            .map(|_| {
                let (rx, reg, store) = (rx.clone(), reg.clone(), store.clone());
                std::thread::spawn(move || loop {
                    let next = rx.lock().unwrap().recv();
                    let Ok((job, sink)) = next else { return };
                    sink(Event::Started {
                        stage: job.stage.clone(),
                        worker: "local".into(),
                    });
                    let progress = |done: u64, total: u64| {
                        sink(Event::Progress {
                            stage: job.stage.clone(),
                            done,
                            total,
                        })
                    };
                    let metric = |name: &str, value: f64| {
                        sink(Event::Metric {
                            stage: job.stage.clone(),
                            name: name.into(),
                            value,
                        })
                    };
                    let image = |name: &str, width: usize, height: usize, rgb: &[f32]| {
                        sink(Event::Image {
                            stage: job.stage.clone(),
                            name: name.into(),
                            width,
                            height,
                            rgb: rgb.to_vec(),
                        })
                    };
                    let result = execute_job_observed(
                        &reg,
                        &store,
                        &job,
                        "local",
                        &progress,
                        &metric,
                        Some(&image),
                    );
                    sink(Event::Finished {
                        stage: job.stage.clone(),
                        result,
                    });
                })
            })
            .collect();
        LocalExecutor {
            tx: Mutex::new(Some(tx)),
            threads: Mutex::new(handles),
            n,
        }
    }
}

impl Drop for LocalExecutor {
    fn drop(&mut self) {
        self.tx.lock().unwrap().take();
        for h in self.threads.lock().unwrap().drain(..) {
            let _ = h.join();
        }
    }
}

impl Executor for LocalExecutor {
    fn submit(&self, job: Job, sink: Sink) {
        let tx = self.tx.lock().unwrap();
        if let Some(tx) = tx.as_ref() {
            if let Err(mpsc::SendError((job, sink))) = tx.send((job, sink)) {
                sink(Event::Finished {
                    stage: job.stage,
                    result: Err(Failure::Infra("the local executor has stopped".into())),
                });
            }
        }
    }
    fn describe(&self) -> String {
        format!("local ({} threads)", self.n)
    }
    fn serves_cache_inline(&self) -> bool {
        true
    }
}

/// How often one stage may be recomputed because a blob it produced
/// turned out missing or corrupt when read.
const MAX_RECOMPUTES: u32 = 2;

enum State {
    /// Waiting for these upstream stages.
    Waiting(BTreeSet<String>),
    Running,
    Done(BTreeMap<String, Digest>),
    Failed,
}

struct Slot {
    state: State,
    skip_cache: bool,
    recomputes: u32,
    report: Option<StageReport>,
    key: Option<Digest>,
}

impl Slot {
    /// The stage failed for good: its report says why.
    fn fail(&mut self, mut rep: StageReport, message: String, obs: &dyn Observer) {
        rep.status = Status::Failed;
        rep.error = Some(message);
        obs.finished(&rep);
        self.state = State::Failed;
        self.report = Some(rep);
    }
}

/// Runs the stages `p.outputs` need; returns a report whether or not a
/// stage failed (see [`Report::failure`]).
///
/// The scheduler is one loop over the executors' events: a stage is
/// submitted as soon as its last input is done, with its node key computed
/// from the inputs' output digests; the executor serves it from the cache
/// or runs it. A stage whose input blob turns out missing or corrupt sends
/// the producing stage back to run uncached (bounded); a stage that fails
/// blocks only what depends on it.
pub fn run_pipeline(
    p: &Pipeline,
    reg: &Registry,
    store: &Tiered,
    exec: &dyn Executor,
    obs: &dyn Observer,
) -> Report {
    let t0 = Instant::now();
    let (tx, rx) = mpsc::channel::<Event>();
    let tx = Mutex::new(tx);
    let sink: Sink = Arc::new(move |e| {
        let _ = tx.lock().unwrap().send(e);
    });
    let mut s = Scheduler::new(p, reg, store, exec, obs, sink);
    loop {
        if !obs.cancelled() {
            s.submit_ready();
        }
        if s.in_flight == 0 {
            break;
        }
        let Ok(ev) = rx.recv() else { break };
        match ev {
            Event::Started { stage, worker } => s.on_started(&stage, &worker),
            Event::Progress { stage, done, total } => obs.progress(&stage, done, total),
            Event::Retry { stage, reason } => s.on_retry(&stage, &reason),
            Event::Metric { stage, name, value } => obs.metric(&stage, &name, value),
            Event::Image {
                stage,
                name,
                width,
                height,
                rgb,
            } => obs.image(&stage, &name, width, height, &rgb),
            Event::Finished { stage, result } => s.on_finished(&stage, result),
        }
    }
    let (up, down) = store.moved();
    Report {
        pipeline: p.name.clone(),
        file: p.file.display().to_string(),
        cache: store.describe(),
        executor: exec.describe(),
        seconds: t0.elapsed().as_secs_f64(),
        bytes_uploaded: up,
        bytes_downloaded: down,
        stages: s.stage_reports(),
        peak_memory_bytes: peak_memory_bytes(),
    }
}

/// Peak resident memory of this process (Linux: `VmHWM`), in bytes.
pub fn peak_memory_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// The state of one run: each needed stage's slot, who waits for whom,
/// what is ready to submit and how many stages are out.
struct Scheduler<'a> {
    p: &'a Pipeline,
    reg: &'a Registry,
    store: &'a Tiered,
    exec: &'a dyn Executor,
    obs: &'a dyn Observer,
    sink: Sink,
    by_name: HashMap<&'a str, &'a crate::spec::Stage>,
    needed: BTreeSet<String>,
    dependents: BTreeMap<String, BTreeSet<String>>,
    slots: BTreeMap<String, Slot>,
    ready: std::collections::VecDeque<String>,
    in_flight: usize,
}

impl<'a> Scheduler<'a> {
    fn new(
        p: &'a Pipeline,
        reg: &'a Registry,
        store: &'a Tiered,
        exec: &'a dyn Executor,
        obs: &'a dyn Observer,
        sink: Sink,
    ) -> Scheduler<'a> {
        let order = plan::order(p);
        let by_name: HashMap<&str, &crate::spec::Stage> =
            p.stages.iter().map(|s| (s.name.as_str(), s)).collect();
        let mut dependents: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        let mut slots: BTreeMap<String, Slot> = BTreeMap::new();
        for n in &order {
            let s = by_name[n.as_str()];
            let ups: BTreeSet<String> = s.refs.values().map(|(u, _)| u.clone()).collect();
            for u in &ups {
                dependents.entry(u.clone()).or_default().insert(n.clone());
            }
            slots.insert(
                n.clone(),
                Slot {
                    state: State::Waiting(ups),
                    skip_cache: false,
                    recomputes: 0,
                    report: None,
                    key: None,
                },
            );
        }
        let ready = order
            .iter()
            .filter(|n| matches!(&slots[*n].state, State::Waiting(w) if w.is_empty()))
            .cloned()
            .collect();
        Scheduler {
            p,
            reg,
            store,
            exec,
            obs,
            sink,
            by_name,
            needed: order.into_iter().collect(),
            dependents,
            slots,
            ready,
            in_flight: 0,
        }
    }

    /// Submits everything ready, in plan order.
    fn submit_ready(&mut self) {
        while let Some(n) = self.ready.pop_front() {
            self.submit(n);
        }
    }

    /// Keys stage `n` from its inputs' digests and serves it from the
    /// cache here, or hands it to the executor.
    fn submit(&mut self, n: String) {
        let stage = self.by_name[n.as_str()];
        let node = self.reg.get(&stage.kind).expect("validated kind");
        let mut inputs = BTreeMap::new();
        let mut problem = None;
        for (param, (up, out)) in &stage.refs {
            if let State::Done(ds) = &self.slots[up].state {
                match ds.get(out) {
                    Some(d) => {
                        inputs.insert(param.clone(), *d);
                    }
                    None => {
                        problem = Some(format!(
                            "input `{up}.{out}` was not produced (stage `{up}` has no such result)"
                        ))
                    }
                }
            }
        }
        let key = match problem {
            Some(e) => Err(e),
            None => {
                node_key(node, &stage.params, &inputs).map_err(|e| format!("reading inputs: {e}"))
            }
        };
        let key = match key {
            Ok(key) => key,
            Err(e) => {
                let mut rep = StageReport::new(&n, &stage.kind, Status::Failed);
                rep.error = Some(e);
                self.obs.finished(&rep);
                let slot = self.slots.get_mut(&n).unwrap();
                slot.state = State::Failed;
                slot.report = Some(rep);
                return;
            }
        };
        let slot = self.slots.get_mut(&n).unwrap();
        let slot_skip = slot.skip_cache;
        slot.key = Some(key);
        slot.state = State::Running;
        self.in_flight += 1;
        // A hit served here goes through the same events as one the
        // executor serves.
        let inline = self.exec.serves_cache_inline() && !slot_skip && !self.store.has_remote();
        let hit = if inline {
            self.store.lookup(&key).ok().flatten()
        } else {
            None
        };
        if let Some(ds) = hit {
            (self.sink)(Event::Started {
                stage: n.clone(),
                worker: "local".into(),
            });
            (self.sink)(Event::Finished {
                stage: n,
                result: Ok(Done {
                    status: Status::Cached,
                    outputs: ds,
                    worker: "local".into(),
                    bytes_in: 0,
                    bytes_out: 0,
                }),
            });
            return;
        }
        self.exec.submit(
            Job {
                stage: n,
                kind: stage.kind.clone(),
                pipeline: self.p.name.clone(),
                params: stage.params.clone(),
                key,
                inputs,
                // A miss found here is not looked up again.
                skip_cache: slot_skip || inline,
                local_only: reads_local_files(node, &stage.params),
                watch: self.obs.watch(),
            },
            self.sink.clone(),
        );
    }

    fn on_started(&mut self, stage: &str, worker: &str) {
        let kind = &self.by_name[stage].kind;
        let slot = self.slots.get_mut(stage).unwrap();
        let rep = slot
            .report
            .get_or_insert_with(|| StageReport::new(stage, kind, Status::Executed));
        rep.worker = Some(worker.to_string());
        rep.attempts += 1;
        rep.started = Some(Instant::now());
        self.obs.started(stage, kind, worker);
    }

    fn on_retry(&mut self, stage: &str, reason: &str) {
        let kind = &self.by_name[stage].kind;
        let slot = self.slots.get_mut(stage).unwrap();
        slot.report
            .get_or_insert_with(|| StageReport::new(stage, kind, Status::Executed))
            .retries
            .push(reason.to_string());
        self.obs.retried(stage, reason);
    }

    fn on_finished(&mut self, name: &str, result: Result<Done, Failure>) {
        self.in_flight -= 1;
        let stage = self.by_name[name];
        let slot = self.slots.get_mut(name).unwrap();
        let key = slot.key.expect("submitted stages have keys");
        let mut rep = slot
            .report
            .take()
            .unwrap_or_else(|| StageReport::new(name, &stage.kind, Status::Executed));
        rep.seconds += rep
            .started
            .take()
            .map(|t| t.elapsed().as_secs_f64())
            .unwrap_or(0.0);
        rep.key = Some(key.hex());
        match result {
            Ok(done) => self.on_done(name, key, rep, done),
            Err(Failure::InputsMissing(params)) => self.on_inputs_missing(name, rep, params),
            Err(Failure::Cancelled) => {
                // Stopped for the run's front end: no failure, nothing
                // stored; what depends on it is reported skipped.
                rep.status = Status::Skipped;
                rep.notes.push("cancelled while running".into());
                self.obs.finished(&rep);
                slot.state = State::Failed;
                slot.report = Some(rep);
            }
            Err(f) => slot.fail(rep, f.message(), self.obs),
        }
    }

    /// A stage's results are in: the files asked for are written here, on
    /// the submitter, and its dependents may become ready. If its own
    /// result cannot be read back, it runs again uncached (bounded).
    fn on_done(&mut self, name: &str, key: Digest, mut rep: StageReport, done: Done) {
        let stage = self.by_name[name];
        let node = self.reg.get(&stage.kind).expect("validated kind");
        let slot = self.slots.get_mut(name).unwrap();
        match materialize(node, stage, &key, &done.outputs, self.store) {
            Ok(files) => {
                rep.status = done.status;
                rep.worker = Some(done.worker);
                rep.bytes_in += done.bytes_in;
                rep.bytes_out += done.bytes_out;
                rep.outputs = done
                    .outputs
                    .iter()
                    .map(|(k, d)| (k.clone(), d.hex()))
                    .collect();
                rep.files = files;
                rep.notes = notes(node, &done.outputs, self.store);
                rep.error = None;
                self.obs.finished(&rep);
                slot.state = State::Done(done.outputs);
                slot.report = Some(rep);
                for dn in self.dependents.get(name).into_iter().flatten() {
                    let ds = self.slots.get_mut(dn).unwrap();
                    if let State::Waiting(w) = &mut ds.state {
                        if w.remove(name) && w.is_empty() {
                            self.ready.push_back(dn.clone());
                        }
                    }
                }
            }
            Err(Failure::InputsMissing(_)) if slot.recomputes < MAX_RECOMPUTES => {
                // Its own result is unreadable: run it again.
                slot.recomputes += 1;
                slot.skip_cache = true;
                self.store.remove_action(&key);
                let why = "its cached result is missing or corrupt".to_string();
                rep.retries.push(why.clone());
                self.obs.retried(name, &why);
                slot.report = Some(rep);
                slot.state = State::Waiting(BTreeSet::new());
                self.ready.push_back(name.to_string());
            }
            Err(f) => slot.fail(rep, f.message(), self.obs),
        }
    }

    /// A stage found inputs missing or corrupt: the producers are sent
    /// back to run uncached and the stage waits for them again, unless a
    /// producer has been recomputed too often.
    fn on_inputs_missing(&mut self, name: &str, mut rep: StageReport, params: Vec<String>) {
        let stage = self.by_name[name];
        let mut ups = BTreeSet::new();
        let mut exhausted = None;
        for param in &params {
            let Some((up, out)) = stage.refs.get(param) else {
                continue;
            };
            if let State::Done(ds) = &self.slots[up].state {
                if let Some(d) = ds.get(out) {
                    self.store.invalidate(d);
                }
            }
            ups.insert(up.clone());
        }
        for up in &ups {
            if self.slots[up].recomputes >= MAX_RECOMPUTES {
                exhausted = Some(up.clone());
            }
        }
        let slot = self.slots.get_mut(name).unwrap();
        if ups.is_empty() || exhausted.is_some() {
            let msg = format!(
                "{} (after recomputing {} {MAX_RECOMPUTES} times)",
                Failure::InputsMissing(params).message(),
                exhausted.unwrap_or_default()
            );
            slot.fail(rep, msg, self.obs);
            return;
        }
        let why = format!(
            "input{} from {} missing or corrupt: recomputing",
            if params.len() > 1 { "s" } else { "" },
            ups.iter().cloned().collect::<Vec<_>>().join(", ")
        );
        rep.retries.push(why.clone());
        self.obs.retried(name, &why);
        slot.report = Some(rep);
        slot.state = State::Waiting(ups.clone());
        for up in ups {
            self.recompute(&up, name);
        }
    }

    /// Producer `up` runs again uncached because `reader` found its
    /// result missing or corrupt.
    fn recompute(&mut self, up: &str, reader: &str) {
        let us = self.slots.get_mut(up).unwrap();
        let why = format!(
            "recomputed: its result was missing or corrupt in the store when `{reader}` read it"
        );
        if let Some(r) = us.report.as_mut() {
            r.retries.push(why.clone());
        }
        self.obs.retried(up, &why);
        us.recomputes += 1;
        us.skip_cache = true;
        if let Some(k) = us.key {
            self.store.remove_action(&k);
        }
        if matches!(us.state, State::Done(_)) {
            us.state = State::Waiting(BTreeSet::new());
            self.ready.push_back(up.to_string());
        }
        // Every other consumer already waiting for it keeps waiting; ones
        // not yet submitted wait for the new result.
        for dn in self.dependents.get(up).into_iter().flatten() {
            if dn == reader {
                continue;
            }
            if let State::Waiting(w) = &mut self.slots.get_mut(dn).unwrap().state {
                w.insert(up.to_string());
            }
        }
    }

    /// Every stage's report, in the file's order: a stage not run is
    /// skipped (not needed, or blocked by a failure upstream).
    fn stage_reports(&mut self) -> Vec<StageReport> {
        self.p
            .stages
            .iter()
            .map(
                |s| match self.slots.get_mut(&s.name).and_then(|sl| sl.report.take()) {
                    Some(r) => r,
                    None => {
                        let mut r = StageReport::new(&s.name, &s.kind, Status::Skipped);
                        let blocked = self.slots.get(&s.name).is_some_and(|sl| {
                            matches!(sl.state, State::Waiting(_) | State::Failed)
                        });
                        if self.needed.contains(&s.name) && !blocked {
                            r.error = Some("not run".into());
                        }
                        r
                    }
                },
            )
            .collect()
    }
}

/// The text of a stage's `note` outputs (an unreadable one is left out:
/// notes are for the reader, not for the results).
fn notes(node: &dyn Node, outputs: &BTreeMap<String, Digest>, store: &Tiered) -> Vec<String> {
    node.outputs()
        .iter()
        .filter(|o| o.ty == "note")
        .filter_map(|o| outputs.get(o.name))
        .filter_map(|d| store.get(d).ok().flatten())
        .map(|b| String::from_utf8_lossy(&b).trim().to_string())
        .collect()
}

/// Writes the user's files for a stage (render outputs); a blob that
/// cannot be read is reported as missing. Files already on the disk with
/// the bytes this stage (its key, its outputs, the paths asked) wrote
/// last time are left as they are: a re-run that changes nothing upstream
/// of them neither reads their blobs nor encodes them again.
fn materialize(
    node: &dyn Node,
    stage: &crate::spec::Stage,
    key: &Digest,
    outputs: &BTreeMap<String, Digest>,
    store: &Tiered,
) -> Result<Vec<String>, Failure> {
    let wants_files = node
        .params()
        .iter()
        .any(|sp| matches!(sp.ty, ParamType::OutPath) && stage.params.is_set(sp.name));
    if !wants_files {
        return Ok(vec![]);
    }
    let shown = |v: &[std::path::PathBuf]| v.iter().map(|p| p.display().to_string()).collect();
    let stamp = written_stamp(node, stage, key, outputs);
    if let Some(files) = stamp
        .as_ref()
        .and_then(|s| store.local().written_up_to_date(s))
    {
        return Ok(shown(&files));
    }
    let mut bytes = BTreeMap::new();
    for (name, d) in outputs {
        match store.get(d) {
            Ok(Some(b)) => {
                bytes.insert(name.clone(), b);
            }
            Ok(None) => return Err(Failure::InputsMissing(vec![name.clone()])),
            Err(e) => return Err(Failure::Infra(e.to_string())),
        }
    }
    let files = node
        .materialize(&stage.params, &bytes)
        .map_err(Failure::of)?;
    if let Some(s) = &stamp {
        // Only a shortcut for the next run: without the record the files
        // are written again.
        let _ = store.local().put_written(s, &files);
    }
    Ok(shown(&files))
}

/// What a stage's files are a function of: its key (kind, version,
/// parameters, inputs), its outputs and the absolute paths it writes.
/// `None` when a path cannot be made absolute.
fn written_stamp(
    node: &dyn Node,
    stage: &crate::spec::Stage,
    key: &Digest,
    outputs: &BTreeMap<String, Digest>,
) -> Option<Digest> {
    let mut h = blake3::Hasher::new();
    h.update(b"matflow written v1\0");
    h.update(env!("CARGO_PKG_VERSION").as_bytes());
    h.update(&key.0);
    for (name, d) in outputs {
        h.update(name.as_bytes());
        h.update(b"\0");
        h.update(&d.0);
    }
    for p in node.output_files(&stage.params) {
        let abs = std::path::absolute(&p).ok()?;
        h.update(abs.as_os_str().as_encoded_bytes());
        h.update(b"\0");
    }
    Some(Digest(*h.finalize().as_bytes()))
}

/// The action keys a pipeline's needed stages currently resolve to, for
/// `gc`: walks the plan with the cache alone (nothing executes) and stops
/// where an entry is missing.
pub fn cached_keys(p: &Pipeline, reg: &Registry, store: &Store) -> CachedKeys {
    let mut done: BTreeMap<String, BTreeMap<String, Digest>> = BTreeMap::new();
    let mut keys = BTreeSet::new();
    let mut unresolved = BTreeSet::new();
    // Stages whose own entry is damaged (unreadable, or naming missing
    // blobs), or below such a stage: what is under them cannot be known.
    let mut damaged: BTreeSet<String> = BTreeSet::new();
    let by_name: HashMap<&str, &crate::spec::Stage> =
        p.stages.iter().map(|s| (s.name.as_str(), s)).collect();
    for n in plan::order(p) {
        let s = by_name[n.as_str()];
        let node = reg.get(&s.kind).expect("validated");
        let mut inputs = BTreeMap::new();
        let mut ok = true;
        for (param, (up, out)) in &s.refs {
            match done.get(up).and_then(|m| m.get(out)) {
                Some(d) => {
                    inputs.insert(param.clone(), *d);
                }
                None => {
                    ok = false;
                    if damaged.contains(up) {
                        damaged.insert(n.clone());
                    }
                }
            }
        }
        if !ok {
            if damaged.contains(&n) {
                unresolved.insert((p.name.clone(), n.clone()));
            }
            continue;
        }
        let Ok(key) = node_key(node, &s.params, &inputs) else {
            continue;
        };
        match store.peek_action(&key) {
            Some(a) => {
                let ds = a.digests().unwrap_or_default();
                if ds.values().all(|d| store.has_blob(d)) {
                    keys.insert(key);
                    done.insert(n.clone(), ds);
                } else {
                    damaged.insert(n.clone());
                }
            }
            // An entry file that does not read is damaged; no file at all
            // is a stage not cached (e.g. its parameters changed), whose
            // old entries are stale.
            None if store.action_path(&key).exists() => {
                damaged.insert(n.clone());
            }
            None => {}
        }
    }
    CachedKeys { keys, unresolved }
}

/// What [`cached_keys`] found: the keys of a pipeline's cached stages,
/// and the (pipeline, stage) pairs whose key it could not work out because
/// an entry above them is damaged.
#[derive(Debug, Default)]
pub struct CachedKeys {
    pub keys: BTreeSet<Digest>,
    pub unresolved: BTreeSet<(String, String)>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::node::{NodeInfo, OutputSpec, Params};

    /// Declares `image`, returns `image` and `extra`.
    struct Sloppy;
    static SLOPPY: NodeInfo = NodeInfo {
        kind: "sloppy",
        version: 1,
        doc: "returns an output it does not declare",
        params: &[],
        outputs: &[OutputSpec {
            name: "image",
            ty: "rgb",
            doc: "an image",
        }],
    };
    impl Node for Sloppy {
        fn info(&self) -> &'static NodeInfo {
            &SLOPPY
        }
        fn run(&self, _ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
            Ok(BTreeMap::from([
                ("image".to_string(), vec![1, 2, 3]),
                ("extra".to_string(), vec![4]),
            ]))
        }
    }

    #[test]
    fn a_node_returning_an_undeclared_output_fails_and_stores_nothing() {
        let dir = std::env::temp_dir().join(format!("matflow-exec-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Tiered::new(crate::store::Store::open(&dir).unwrap(), None);
        let mut reg = Registry::default();
        reg.add(Box::new(Sloppy));
        let job = Job {
            stage: "s".into(),
            kind: "sloppy".into(),
            pipeline: "p.yaml".into(),
            params: Params(BTreeMap::new()),
            key: crate::store::Digest::of(b"sloppy job"),
            inputs: BTreeMap::new(),
            skip_cache: false,
            local_only: false,
            watch: None,
        };
        match execute_job(&reg, &store, &job, "here", &|_, _| {}) {
            Err(Failure::Node(msg)) => {
                assert!(msg.contains("`sloppy`") && msg.contains("extra"), "{msg}");
                assert!(msg.contains("declared: image"), "{msg}");
            }
            other => panic!("expected a node failure, got {other:?}"),
        }
        assert!(store.lookup(&job.key).unwrap().is_none(), "no action entry");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// An error wrapping an I/O error, as the libraries' typed errors do.
    #[derive(Debug, thiserror::Error)]
    #[error("reading the bundle")]
    struct Wrapped(#[source] std::io::Error);

    #[test]
    fn a_full_disk_is_the_machines_failure_and_a_missing_file_the_stages() {
        use crate::node::NodeErrorKind::{Machine, Stage};
        use std::io::{Error, ErrorKind};
        let kind = |k: ErrorKind| NodeError::kind_of(&Wrapped(Error::from(k)));
        for k in [
            ErrorKind::StorageFull,
            ErrorKind::OutOfMemory,
            ErrorKind::Interrupted,
        ] {
            assert_eq!(kind(k), Machine, "{k:?}");
        }
        for k in [
            ErrorKind::NotFound,
            ErrorKind::PermissionDenied,
            ErrorKind::InvalidData,
        ] {
            assert_eq!(kind(k), Stage, "{k:?}");
        }
        // The executor retries the machine's failures, not the stage's.
        assert!(matches!(
            Failure::of(NodeError::machine("disk full")),
            Failure::Infra(_)
        ));
        assert!(matches!(
            Failure::of(NodeError::new("no depth")),
            Failure::Node(_)
        ));
    }

    /// One number out, after an optional stage of its kind.
    struct Step;
    /// The test chains' parameter: the stage before (optional).
    const AFTER: &[crate::node::ParamSpec] = &[crate::node::ParamSpec {
        name: "after",
        ty: crate::node::ParamType::Ref(&["n"]),
        default: Some("~"),
        unit: "",
        doc: "the stage before",
    }];
    /// The test chains' output: a number.
    const N: &[OutputSpec] = &[OutputSpec {
        name: "n",
        ty: "n",
        doc: "a number",
    }];
    static STEP: NodeInfo = NodeInfo {
        kind: "step",
        version: 1,
        doc: "a link of a chain",
        params: AFTER,
        outputs: N,
    };
    impl Node for Step {
        fn info(&self) -> &'static NodeInfo {
            &STEP
        }
        fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
            let n = ctx.opt_input("after").map_or(0, |b| b[0]) + 1;
            (ctx.metric)("n", n as f64);
            Ok(BTreeMap::from([("n".to_string(), vec![n])]))
        }
    }

    /// Cancels the run once `stop_after` has finished.
    struct CancelAfter {
        stop_after: &'static str,
        seen: Mutex<Vec<String>>,
    }
    impl Observer for CancelAfter {
        fn finished(&self, r: &StageReport) {
            self.seen.lock().unwrap().push(r.name.clone());
        }
        fn cancelled(&self) -> bool {
            self.seen
                .lock()
                .unwrap()
                .iter()
                .any(|s| s == self.stop_after)
        }
    }

    /// A run its observer cancels submits nothing more: the stage out
    /// finishes, the rest are skipped, nothing fails.
    #[test]
    fn a_cancelled_run_submits_nothing_more() {
        let dir = std::env::temp_dir().join(format!("matflow-cancel-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Arc::new(Tiered::new(crate::store::Store::open(&dir).unwrap(), None));
        let mut reg = Registry::default();
        reg.add(Box::new(Step));
        let yaml = "pipeline: chain\noutputs: [c]\nstages:\n  a:\n    kind: step\n  \
                    b:\n    kind: step\n    after: a\n  c:\n    kind: step\n    after: b\n";
        let p = crate::spec::parse(yaml, &dir.join("chain.yaml"), &reg, &[]).unwrap();
        let reg = Arc::new(reg);
        let exec = crate::LocalExecutor::new(reg.clone(), store.clone(), 1);
        let obs = CancelAfter {
            stop_after: "a",
            seen: Mutex::new(vec![]),
        };
        let r = run_pipeline(&p, &reg, &store, &exec, &obs);
        assert_eq!(r.failure(), None);
        let status: Vec<(&str, Status)> = r
            .stages
            .iter()
            .map(|s| (s.name.as_str(), s.status))
            .collect();
        assert_eq!(
            status,
            [
                ("a", Status::Executed),
                ("b", Status::Skipped),
                ("c", Status::Skipped)
            ]
        );
        // Not cancelled, the same pipeline runs to its end.
        let r = run_pipeline(&p, &reg, &store, &exec, &Silent);
        assert!(
            r.stages.iter().all(|s| s.status != Status::Skipped),
            "{:?}",
            r.stages
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Collects the metrics it hears: (stage, name, value).
    struct Metrics(Mutex<Vec<(String, String, f64)>>);
    impl Observer for Metrics {
        fn metric(&self, stage: &str, name: &str, value: f64) {
            self.0
                .lock()
                .unwrap()
                .push((stage.into(), name.into(), value));
        }
    }

    /// What a stage reports as it runs reaches the run's observer.
    #[test]
    fn a_stages_metrics_reach_the_observer() {
        let dir = std::env::temp_dir().join(format!("matflow-metric-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Arc::new(Tiered::new(crate::store::Store::open(&dir).unwrap(), None));
        let mut reg = Registry::default();
        reg.add(Box::new(Step));
        let yaml = "pipeline: chain\noutputs: [b]\nstages:\n  a:\n    kind: step\n  \
                    b:\n    kind: step\n    after: a\n";
        let p = crate::spec::parse(yaml, &dir.join("chain.yaml"), &reg, &[]).unwrap();
        let reg = Arc::new(reg);
        let exec = crate::LocalExecutor::new(reg.clone(), store.clone(), 1);
        let obs = Metrics(Mutex::new(vec![]));
        let r = run_pipeline(&p, &reg, &store, &exec, &obs);
        assert_eq!(r.failure(), None);
        let seen = obs.0.lock().unwrap().clone();
        assert_eq!(
            seen,
            [("a".into(), "n".into(), 1.0), ("b".into(), "n".into(), 2.0)]
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Shows an image, then works in small pieces until its run no longer
    /// wants it (or 10 s pass: a broken watch fails the test, not hangs it).
    struct Spin;
    static SPIN: NodeInfo = NodeInfo {
        kind: "spin",
        version: 1,
        doc: "works until cancelled",
        params: AFTER,
        outputs: N,
    };
    impl Node for Spin {
        fn info(&self) -> &'static NodeInfo {
            &SPIN
        }
        fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
            if let Some(show) = ctx.image {
                show("current", 2, 1, &[0.5, 0.5, 0.5, 1.0, 0.0, 0.0]);
            }
            let t0 = Instant::now();
            while t0.elapsed().as_secs() < 10 {
                ctx.check_cancelled()?;
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
            Ok(BTreeMap::from([("n".to_string(), vec![1])]))
        }
    }

    /// Watches a run: keeps the images shown and cancels the run once it
    /// has seen one.
    /// An image a stage showed: `stage/name`, width, height, pixels.
    type Shown = (String, usize, usize, Vec<f32>);
    struct CancelOnImage {
        images: Mutex<Vec<Shown>>,
        flag: Arc<std::sync::atomic::AtomicBool>,
    }
    impl Observer for CancelOnImage {
        fn watch(&self) -> Option<Watch> {
            let flag = self.flag.clone();
            Some(Watch {
                cancelled: Arc::new(move || flag.load(std::sync::atomic::Ordering::SeqCst)),
                images: true,
            })
        }
        fn image(&self, stage: &str, name: &str, width: usize, height: usize, rgb: &[f32]) {
            self.images.lock().unwrap().push((
                format!("{stage}/{name}"),
                width,
                height,
                rgb.to_vec(),
            ));
            self.flag.store(true, std::sync::atomic::Ordering::SeqCst);
        }
        fn cancelled(&self) -> bool {
            self.flag.load(std::sync::atomic::Ordering::SeqCst)
        }
    }

    /// A stage its front end stops while it runs: its image reached the
    /// front end, it ends early, nothing fails, nothing is stored (the next
    /// run executes it again), and what depends on it is skipped.
    #[test]
    fn a_running_stage_stops_when_its_run_is_cancelled() {
        let dir = std::env::temp_dir().join(format!("matflow-stop-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = Arc::new(Tiered::new(crate::store::Store::open(&dir).unwrap(), None));
        let mut reg = Registry::default();
        reg.add(Box::new(Spin));
        reg.add(Box::new(Step));
        let yaml = "pipeline: stop\noutputs: [b]\nstages:\n  a:\n    kind: spin\n  \
                    b:\n    kind: step\n    after: a\n";
        let p = crate::spec::parse(yaml, &dir.join("stop.yaml"), &reg, &[]).unwrap();
        let reg = Arc::new(reg);
        let exec = crate::LocalExecutor::new(reg.clone(), store.clone(), 1);
        for round in 0..2 {
            let obs = CancelOnImage {
                images: Mutex::new(vec![]),
                flag: Arc::new(false.into()),
            };
            let t0 = Instant::now();
            let r = run_pipeline(&p, &reg, &store, &exec, &obs);
            assert!(
                t0.elapsed().as_secs_f64() < 5.0,
                "round {round}: not stopped"
            );
            assert_eq!(r.failure(), None);
            let a = r.stage("a").unwrap();
            assert_eq!(a.status, Status::Skipped, "round {round}");
            assert_eq!(a.notes, ["cancelled while running"]);
            assert_eq!(r.stage("b").unwrap().status, Status::Skipped);
            let images = obs.images.lock().unwrap().clone();
            assert_eq!(
                images,
                [("a/current".into(), 2, 1, vec![0.5, 0.5, 0.5, 1.0, 0.0, 0.0])]
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
