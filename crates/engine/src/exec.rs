//! Running a pipeline: keys, cache lookups, execution, reports.
//!
//! The scheduler walks the needed stages; a stage becomes ready when its
//! inputs are done, and up to `parallel` ready stages run at once. For each
//! stage it computes the node key from the kind, version, parameters and
//! the *output digests* of its inputs, serves the stage from the action
//! cache when the entry exists and every blob verifies, and otherwise hands
//! the node to the [`Executor`] and stores what comes back. Executors
//! differ only in where `execute` runs; the in-process one calls the node.

use std::collections::{BTreeMap, BTreeSet};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

use crate::key::{node_key, node_seed};
use crate::node::{Bytes, Node, NodeError, Registry, RunContext};
use crate::plan;
use crate::spec::Pipeline;
use crate::store::{Action, Digest, Store};

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
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct Report {
    pub pipeline: String,
    pub file: String,
    pub cache: String,
    pub seconds: f64,
    pub stages: Vec<StageReport>,
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
    fn started(&self, _stage: &str, _kind: &str) {}
    fn progress(&self, _stage: &str, _done: u64, _total: u64) {}
    fn finished(&self, _report: &StageReport) {}
}

/// An observer that shows nothing.
pub struct Silent;
impl Observer for Silent {}

/// Where nodes run. The engine hands over the node and its context and
/// gets the outputs' bytes back.
pub trait Executor: Sync {
    fn execute(
        &self,
        node: &dyn Node,
        ctx: &RunContext,
    ) -> Result<BTreeMap<String, Vec<u8>>, NodeError>;
}

/// Runs nodes in this process (the embedded default).
pub struct LocalExecutor;

impl Executor for LocalExecutor {
    fn execute(
        &self,
        node: &dyn Node,
        ctx: &RunContext,
    ) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        match catch_unwind(AssertUnwindSafe(|| node.run(ctx))) {
            Ok(r) => r,
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
}

enum State {
    Pending,
    Running,
    Done(BTreeMap<String, Digest>),
    Failed,
}

/// Runs the stages `p.outputs` need; returns a report whether or not a
/// stage failed (see [`Report::failure`]).
pub fn run_pipeline(
    p: &Pipeline,
    reg: &Registry,
    store: &Store,
    exec: &dyn Executor,
    obs: &dyn Observer,
    parallel: usize,
) -> Report {
    let t0 = Instant::now();
    let order = plan::order(p);
    let needed: BTreeSet<String> = order.iter().cloned().collect();
    let states: Mutex<(BTreeMap<String, State>, BTreeMap<String, StageReport>)> = Mutex::new((
        order.iter().map(|n| (n.clone(), State::Pending)).collect(),
        BTreeMap::new(),
    ));
    let cv = Condvar::new();
    // Blobs verified or written in this run, so a stage's inputs are not
    // read and hashed twice.
    let memo: Memo = Mutex::new(BTreeMap::new());
    let worker = || loop {
        // Pick the first ready stage in plan order.
        let (name, inputs) = {
            let mut g = states.lock().unwrap();
            loop {
                let (st, _) = &*g;
                let mut pick = None;
                let mut running = false;
                let mut blocked = Vec::new();
                for n in &order {
                    match st[n] {
                        State::Pending => {
                            let s = p.stage(n).unwrap();
                            let mut ready = true;
                            let mut failed_up = false;
                            for (up, _) in s.refs.values() {
                                match st[up] {
                                    State::Done(_) => {}
                                    State::Failed => failed_up = true,
                                    _ => ready = false,
                                }
                            }
                            if failed_up {
                                blocked.push(n.clone());
                            } else if ready && pick.is_none() {
                                pick = Some(n.clone());
                            }
                        }
                        State::Running => running = true,
                        _ => {}
                    }
                }
                if !blocked.is_empty() {
                    let (st, reps) = &mut *g;
                    for n in blocked {
                        st.insert(n.clone(), State::Failed);
                        let s = p.stage(&n).unwrap();
                        reps.insert(n.clone(), StageReport::new(&n, &s.kind, Status::Skipped));
                    }
                    cv.notify_all();
                    continue;
                }
                if let Some(n) = pick {
                    let s = p.stage(&n).unwrap();
                    let (st, _) = &mut *g;
                    let mut inputs = BTreeMap::new();
                    let mut missing = None;
                    for (param, (up, out)) in &s.refs {
                        if let State::Done(ds) = &st[up] {
                            match ds.get(out) {
                                Some(d) => {
                                    inputs.insert(param.clone(), *d);
                                }
                                None => missing = Some((up.clone(), out.clone())),
                            }
                        }
                    }
                    st.insert(n.clone(), State::Running);
                    let inputs = match missing {
                        Some(x) => Err(x),
                        None => Ok(inputs),
                    };
                    break (n, inputs);
                }
                if !running {
                    return;
                }
                g = cv.wait(g).unwrap();
            }
        };
        let stage = p.stage(&name).unwrap();
        let node = reg.get(&stage.kind).expect("validated kind");
        obs.started(&name, &stage.kind);
        let ts = Instant::now();
        let result = match inputs {
            Err((up, out)) => Err(format!(
                "input `{up}.{out}` was not produced (stage `{up}` has no such result)"
            )),
            Ok(inputs) => run_stage(p, stage, node, &inputs, store, exec, obs, &memo),
        };
        let mut rep = StageReport::new(&name, &stage.kind, Status::Failed);
        rep.seconds = ts.elapsed().as_secs_f64();
        let state = match result {
            Ok(r) => {
                rep.status = r.status;
                rep.key = Some(r.key.hex());
                rep.outputs = r
                    .outputs
                    .iter()
                    .map(|(k, d)| (k.clone(), d.hex()))
                    .collect();
                rep.files = r.files;
                State::Done(r.outputs)
            }
            Err(e) => {
                rep.error = Some(e);
                State::Failed
            }
        };
        obs.finished(&rep);
        let mut g = states.lock().unwrap();
        g.0.insert(name.clone(), state);
        g.1.insert(name, rep);
        cv.notify_all();
    };
    std::thread::scope(|s| {
        for _ in 0..parallel.max(1) {
            s.spawn(worker);
        }
    });
    let (_, mut reps) = states.into_inner().unwrap();
    let stages = p
        .stages
        .iter()
        .map(|s| {
            reps.remove(&s.name).unwrap_or_else(|| {
                let mut r = StageReport::new(&s.name, &s.kind, Status::Skipped);
                if needed.contains(&s.name) {
                    r.error = Some("not run".into());
                }
                r
            })
        })
        .collect();
    Report {
        pipeline: p.name.clone(),
        file: p.file.display().to_string(),
        cache: store.root().display().to_string(),
        seconds: t0.elapsed().as_secs_f64(),
        stages,
    }
}

type Memo = Mutex<BTreeMap<Digest, Bytes>>;

struct StageResult {
    status: Status,
    key: Digest,
    outputs: BTreeMap<String, Digest>,
    files: Vec<String>,
}

#[allow(clippy::too_many_arguments)]
fn run_stage(
    p: &Pipeline,
    stage: &crate::spec::Stage,
    node: &dyn Node,
    inputs: &BTreeMap<String, Digest>,
    store: &Store,
    exec: &dyn Executor,
    obs: &dyn Observer,
    memo: &Memo,
) -> Result<StageResult, String> {
    let key = node_key(node, &stage.params, inputs).map_err(|e| format!("reading inputs: {e}"))?;
    let wants_files = node
        .params()
        .iter()
        .any(|sp| matches!(sp.ty, crate::node::ParamType::OutPath) && stage.params.is_set(sp.name));
    // A cache hit: the entry exists and every blob is intact.
    if let Some(a) = store.get_action(&key) {
        let ds = a.digests().unwrap_or_default();
        let mut bytes = BTreeMap::new();
        let mut intact = true;
        for (name, d) in &ds {
            match store.get_blob(d).map_err(|e| e.to_string())? {
                Some(b) => {
                    let b = Arc::new(b);
                    if wants_files {
                        bytes.insert(name.clone(), b.clone());
                    }
                    memo.lock().unwrap().insert(*d, b);
                }
                None => {
                    intact = false;
                    break;
                }
            }
        }
        if intact {
            let files = materialize(node, stage, &bytes)?;
            return Ok(StageResult {
                status: Status::Cached,
                key,
                outputs: ds,
                files,
            });
        }
        store.remove_action(&key);
    }
    let mut in_bytes = BTreeMap::new();
    for (param, d) in inputs {
        let known = memo.lock().unwrap().get(d).cloned();
        let b =
            match known {
                Some(b) => b,
                None => Arc::new(store.get_blob(d).map_err(|e| e.to_string())?.ok_or_else(
                    || format!("input `{param}` ({d}) is missing or corrupt in the cache"),
                )?),
            };
        in_bytes.insert(param.clone(), b);
    }
    let progress = |d: u64, t: u64| obs.progress(&stage.name, d, t);
    let ctx = RunContext {
        stage: &stage.name,
        params: &stage.params,
        inputs: in_bytes,
        seed: node_seed(node, &stage.params),
        progress: &progress,
    };
    let ts = Instant::now();
    let outs: BTreeMap<String, Bytes> = exec
        .execute(node, &ctx)
        .map_err(|e| e.0)?
        .into_iter()
        .map(|(k, v)| (k, Arc::new(v)))
        .collect();
    let seconds = ts.elapsed().as_secs_f64();
    let mut ds = BTreeMap::new();
    for (name, b) in &outs {
        let d = store.put_blob(b).map_err(|e| e.to_string())?;
        memo.lock().unwrap().insert(d, b.clone());
        ds.insert(name.clone(), d);
    }
    store
        .put_action(
            &key,
            &Action {
                kind: stage.kind.clone(),
                stage: stage.name.clone(),
                pipeline: p.name.clone(),
                outputs: ds.iter().map(|(k, d)| (k.clone(), d.hex())).collect(),
                seconds,
            },
        )
        .map_err(|e| e.to_string())?;
    let files = materialize(node, stage, &outs)?;
    Ok(StageResult {
        status: Status::Executed,
        key,
        outputs: ds,
        files,
    })
}

fn materialize(
    node: &dyn Node,
    stage: &crate::spec::Stage,
    bytes: &BTreeMap<String, Bytes>,
) -> Result<Vec<String>, String> {
    node.materialize(&stage.params, bytes)
        .map(|v| v.iter().map(|p| p.display().to_string()).collect())
        .map_err(|e| e.0)
}

/// The action keys a pipeline's needed stages currently resolve to, for
/// `gc`: walks the plan with the cache alone (nothing executes) and stops
/// where an entry is missing.
pub fn cached_keys(p: &Pipeline, reg: &Registry, store: &Store) -> BTreeSet<Digest> {
    let mut done: BTreeMap<String, BTreeMap<String, Digest>> = BTreeMap::new();
    let mut keys = BTreeSet::new();
    for n in plan::order(p) {
        let s = p.stage(&n).unwrap();
        let node = reg.get(&s.kind).expect("validated");
        let mut inputs = BTreeMap::new();
        let mut ok = true;
        for (param, (up, out)) in &s.refs {
            match done.get(up).and_then(|m| m.get(out)) {
                Some(d) => {
                    inputs.insert(param.clone(), *d);
                }
                None => ok = false,
            }
        }
        if !ok {
            continue;
        }
        let Ok(key) = node_key(node, &s.params, &inputs) else {
            continue;
        };
        if let Some(a) = store.get_action(&key) {
            keys.insert(key);
            done.insert(n.clone(), a.digests().unwrap_or_default());
        }
    }
    keys
}
