//! The remote executor's scheduler (its queue, placement, bookkeeping and
//! the run's event loop) over many simulated in-process workers: the same
//! digests as a local run, every stage run exactly once, and no stage run
//! before its inputs.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use matflow_engine::exec::Silent;
use matflow_engine::{
    run_pipeline, LocalExecutor, NodeError, NodeInfo, OutputSpec, ParamSpec, ParamType, Registry,
    RunContext, Status, Store, StoreTier, Tiered,
};
use matflow_rpc::remote::{layered_pipeline, layered_second_input, RemoteExecutor};

/// Concatenates its index and inputs; records the order stages ran in.
struct Chain(Arc<Mutex<Vec<i64>>>);

static CHAIN: NodeInfo = NodeInfo {
    kind: "chain",
    version: 1,
    doc: "test node",
    params: &[
        ParamSpec {
            name: "i",
            ty: ParamType::Int {
                min: 0,
                max: 1 << 40,
            },
            default: Some("0"),
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "a",
            ty: ParamType::Ref(&["t"]),
            default: Some("~"),
            unit: "",
            doc: "",
        },
        ParamSpec {
            name: "b",
            ty: ParamType::Ref(&["t"]),
            default: Some("~"),
            unit: "",
            doc: "",
        },
    ],
    outputs: &[OutputSpec {
        name: "out",
        ty: "t",
        doc: "",
    }],
};

impl matflow_engine::Node for Chain {
    fn info(&self) -> &'static NodeInfo {
        &CHAIN
    }
    fn run(&self, ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let i = ctx.params.i64("i");
        self.0.lock().unwrap().push(i);
        let mut out = i.to_le_bytes().to_vec();
        for k in ["a", "b"] {
            if let Some(b) = ctx.opt_input(k) {
                out.extend_from_slice(&blake3::hash(b).as_bytes()[..8]);
            }
        }
        Ok(BTreeMap::from([("out".to_string(), out)]))
    }
}

fn pipeline_file(dir: &std::path::Path, layers: usize, width: usize) -> std::path::PathBuf {
    let f = dir.join("p.yaml");
    std::fs::write(&f, layered_pipeline("chain", layers, width)).unwrap();
    f
}

/// The submitter's store and the simulated workers' in `dir`, sharing
/// one remote tier.
fn stores(dir: &std::path::Path) -> (Arc<Tiered>, Arc<Tiered>) {
    let shared: Arc<dyn StoreTier> = Arc::new(Store::open(dir.join("shared")).unwrap());
    let store = Arc::new(Tiered::new(
        Store::open(dir.join("submitter")).unwrap(),
        Some(shared.clone()),
    ));
    let wstore = Arc::new(Tiered::new(
        Store::open(dir.join("workers")).unwrap(),
        Some(shared),
    ));
    (store, wstore)
}

fn digests(r: &matflow_engine::Report) -> BTreeMap<String, BTreeMap<String, String>> {
    r.stages
        .iter()
        .map(|s| (s.name.clone(), s.outputs.clone().into_iter().collect()))
        .collect()
}

#[test]
fn many_simulated_workers_compute_what_a_local_run_computes() {
    let t = tempfile::tempdir().unwrap();
    let (layers, width) = (6, 40);
    let file = pipeline_file(t.path(), layers, width);
    let ran = Arc::new(Mutex::new(Vec::new()));
    let mut reg = Registry::new();
    reg.add(Box::new(Chain(ran.clone())));
    let p = matflow_engine::spec::load(&file, &reg, &[]).unwrap();
    let reg = Arc::new(reg);

    let local_store = Arc::new(Tiered::new(
        Store::open(t.path().join("local")).unwrap(),
        None,
    ));
    let local = LocalExecutor::new(reg.clone(), local_store.clone(), 2);
    let want = run_pipeline(&p, &reg, &local_store, &local, &Silent);
    assert!(want.failure().is_none());
    ran.lock().unwrap().clear();

    let (store, wstore) = stores(t.path());
    let ex = RemoteExecutor::simulated(64, 1, reg.clone(), store.clone(), wstore);
    let got = run_pipeline(&p, &reg, &store, &ex, &Silent);
    assert!(got.failure().is_none(), "{:?}", got.failure());
    assert_eq!(digests(&got), digests(&want), "same digests as local");
    let workers: std::collections::BTreeSet<_> = got
        .stages
        .iter()
        .map(|s| s.worker.clone().unwrap_or_default())
        .collect();
    assert!(workers.len() > 10, "spread over the pool: {workers:?}");
    assert!(got.stages.iter().all(|s| s.status == Status::Executed));

    // Every stage ran once, and after its inputs.
    let order = ran.lock().unwrap().clone();
    assert_eq!(order.len(), layers * width);
    let pos: BTreeMap<i64, usize> = order.iter().enumerate().map(|(k, &i)| (i, k)).collect();
    assert_eq!(pos.len(), layers * width, "no stage ran twice");
    for l in 1..layers {
        for j in 0..width {
            let i = (l * width + j) as i64;
            let a = ((l - 1) * width + j) as i64;
            let b = ((l - 1) * width + layered_second_input(j, width)) as i64;
            assert!(
                pos[&a] < pos[&i] && pos[&b] < pos[&i],
                "stage {i} before its inputs"
            );
        }
    }

    // A second run of the same pipeline is served from the store.
    let again = run_pipeline(&p, &reg, &store, &ex, &Silent);
    assert!(again.stages.iter().all(|s| s.status == Status::Cached));
}

/// Fails its first `fails` runs, with a machine's failure (`machine`) or
/// the stage's own; then gives one byte.
struct Flaky {
    runs: Arc<Mutex<u32>>,
    fails: u32,
    machine: bool,
}

static FLAKY: NodeInfo = NodeInfo {
    kind: "flaky",
    version: 1,
    doc: "test node",
    params: &[],
    outputs: &[OutputSpec {
        name: "out",
        ty: "t",
        doc: "",
    }],
};

impl matflow_engine::Node for Flaky {
    fn info(&self) -> &'static NodeInfo {
        &FLAKY
    }
    fn run(&self, _ctx: &RunContext) -> Result<BTreeMap<String, Vec<u8>>, NodeError> {
        let mut n = self.runs.lock().unwrap();
        *n += 1;
        if *n <= self.fails {
            let io = std::io::Error::from(if self.machine {
                std::io::ErrorKind::StorageFull
            } else {
                std::io::ErrorKind::NotFound
            });
            return Err(NodeError(
                format!("writing scratch: {io}"),
                NodeError::kind_of(&io),
            ));
        }
        Ok(BTreeMap::from([("out".to_string(), vec![1])]))
    }
}

/// A node that fails for want of disk is the machine's failure: the stage
/// is tried again on a worker and completes. One that fails on its own
/// inputs fails once, and is not tried again.
#[test]
fn a_machine_failure_is_retried_and_a_stage_failure_is_final() {
    for machine in [true, false] {
        let t = tempfile::tempdir().unwrap();
        let runs = Arc::new(Mutex::new(0));
        let mut reg = Registry::new();
        reg.add(Box::new(Flaky {
            runs: runs.clone(),
            fails: 1,
            machine,
        }));
        let f = t.path().join("p.yaml");
        std::fs::write(
            &f,
            "pipeline: f\noutputs: [s]\nstages:\n  s: {kind: flaky}\n",
        )
        .unwrap();
        let p = matflow_engine::spec::load(&f, &reg, &[]).unwrap();
        let reg = Arc::new(reg);
        let (store, wstore) = stores(t.path());
        let ex = RemoteExecutor::simulated(2, 1, reg.clone(), store.clone(), wstore);
        let r = run_pipeline(&p, &reg, &store, &ex, &Silent);
        let s = &r.stages[0];
        if machine {
            assert!(r.failure().is_none(), "{:?}", r.failure());
            assert_eq!(s.status, Status::Executed);
            assert_eq!(s.retries.len(), 1, "{:?}", s.retries);
            assert!(s.retries[0].contains("writing scratch"), "{:?}", s.retries);
            assert_eq!(*runs.lock().unwrap(), 2);
        } else {
            let f = r.failure().expect("the stage fails");
            assert!(f.contains("writing scratch"), "{f}");
            assert!(s.retries.is_empty(), "{:?}", s.retries);
            assert_eq!(*runs.lock().unwrap(), 1, "not tried again");
        }
    }
}
