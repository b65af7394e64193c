//! The live session: its state behind one lock, and the one thread that
//! runs its pipeline on the engine. A change bumps the session's
//! generation and wakes the runner; the runner works on the newest
//! generation only: a run that a newer change supersedes submits nothing
//! more (the engine asks [`Observer::cancelled`] between stages), its
//! stage running now stops (renders between tiles, the recovery between
//! its inner stages: [`Observer::watch`]), and its renders are never
//! shown. Every change of state is published as JSON
//! for the page's event stream.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use matflow_engine::exec::{Executor, Observer, StageReport, Watch};
use matflow_engine::store::Digest;
use matflow_engine::{run_pipeline, Registry, Status as StageStatus, Tiered};
use matflow_nodes::SceneData;
use matflow_scene::{Camera, GrayImage, Image, RgbImage};

use crate::session::{Session, SessionError};
use crate::view;

/// Where the session stands, as `/api/session` and the event stream say.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Status {
    /// `running`, `ready` or `failed`.
    pub state: &'static str,
    pub input: String,
    pub message: String,
    pub width: usize,
    pub height: usize,
    /// The maps `/api/maps/NAME.png` serves.
    pub maps: Vec<&'static str>,
    /// The stage running now and its progress (`total` 0: steps of an
    /// open-ended count).
    pub stage: String,
    pub done: u64,
    pub total: u64,
    /// How many changes the session has had; `shown` is the one the
    /// image is of, `image` which image that is (`preview` at a few
    /// samples per pixel, then `result`).
    pub generation: u64,
    pub shown: u64,
    pub image: Option<&'static str>,
    /// Seconds from the change to its preview and to its result.
    pub preview_seconds: Option<f64>,
    pub result_seconds: Option<f64>,
    /// The edit history, oldest first, and how many redo can bring back.
    pub history: Vec<String>,
    pub redo: usize,
    /// Pixels selected.
    pub selected: usize,
    /// The loss of each step of the recovery stage running now (or that
    /// ran last), and that stage's name.
    pub loss: Vec<f64>,
    pub loss_stage: String,
    /// How many stages a newer change stopped while they ran.
    pub stopped: u64,
    /// How many of the recovery's intermediate re-renders were shown
    /// (`/api/images/recovery.png` is the latest).
    pub recovery_shots: u64,
    /// The geometry past the frame asked for (`complete` of the `mesh`
    /// stage) and what the mesh stage says it took.
    pub geometry: String,
    pub geometry_taken: String,
    /// The environment maps uploaded to the session, by name.
    pub envmaps: Vec<String>,
    /// The meshes uploaded to the session, by name.
    pub meshes: Vec<String>,
    /// The objects inserted, as `/api/insert` takes them.
    pub objects: serde_json::Value,
}

/// What selection grows over.
pub struct Surfaces {
    pub albedo: RgbImage,
    pub depth: GrayImage,
    pub normals: Option<RgbImage>,
    /// The photo, whose own edges also stop a click (where there is one;
    /// one of another size is ignored).
    pub photo: Option<RgbImage>,
    pub camera: Camera,
}

/// The session's state.
pub struct Live {
    pub session: Session,
    pub status: Status,
    pub surfaces: Option<Surfaces>,
    pub selection: Image<bool>,
    /// PNGs by name (the maps, `preview`, `result`).
    pub images: BTreeMap<String, Vec<u8>>,
    /// The result shown, linear (its EXR is encoded when downloaded).
    pub result: Option<Arc<RgbImage>>,
    /// When the newest change was asked for.
    changed_at: Instant,
}

/// The least time between two progress events sent to the page.
const PROGRESS_EVERY: std::time::Duration = std::time::Duration::from_millis(50);

/// The state, the runner's wake-up and the published status.
pub struct Shared {
    live: Mutex<Live>,
    wake: Condvar,
    pub events: tokio::sync::watch::Sender<String>,
    /// When the status was last sent.
    published: Mutex<Instant>,
    pub registry: Registry,
    /// The newest generation, readable without the lock (a running
    /// stage asks it between tiles, the runner between stages).
    newest: Arc<AtomicU64>,
}

impl Shared {
    pub fn new(session: Session, input: String) -> Arc<Shared> {
        let (events, _) = tokio::sync::watch::channel(String::new());
        let mut status = Status {
            state: "running",
            input,
            message: "running the session's pipeline".into(),
            ..Default::default()
        };
        (status.history, status.redo) = session.history();
        status.envmaps = session.envmaps();
        status.meshes = session.meshes();
        status.geometry = session.geometry();
        status.objects = session.objects_json();
        let s = Arc::new(Shared {
            live: Mutex::new(Live {
                session,
                status,
                surfaces: None,
                selection: Image::new(0, 0, false),
                images: BTreeMap::new(),
                result: None,
                changed_at: Instant::now(),
            }),
            wake: Condvar::new(),
            events,
            published: Mutex::new(Instant::now()),
            registry: matflow_nodes::registry(),
            newest: Arc::new(AtomicU64::new(0)),
        });
        s.publish(&s.lock());
        s
    }

    pub fn lock(&self) -> MutexGuard<'_, Live> {
        self.live.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Sends the status to the event stream.
    pub fn publish(&self, live: &Live) {
        let json = serde_json::to_string(&live.status).unwrap_or_default();
        self.events.send_replace(json);
        *self.published.lock().unwrap_or_else(|e| e.into_inner()) = Instant::now();
    }

    /// [`Shared::publish`] for a stage's steps, which come faster than a
    /// page redraws: at most every [`PROGRESS_EVERY`] (the next state
    /// change sends the latest anyway).
    fn publish_progress(&self, live: &Live) {
        let last = *self.published.lock().unwrap_or_else(|e| e.into_inner());
        if last.elapsed() >= PROGRESS_EVERY {
            self.publish(live);
        }
    }

    /// After a change of the session's stages: a new generation, the
    /// runner woken, the status published.
    pub fn changed(&self, mut live: MutexGuard<'_, Live>) {
        live.status.generation += 1;
        self.newest.store(live.status.generation, Ordering::SeqCst);
        live.changed_at = Instant::now();
        // The result of an older generation is not this one's.
        live.result = None;
        live.images.remove("result");
        (live.status.history, live.status.redo) = live.session.history();
        live.status.objects = live.session.objects_json();
        live.status.geometry = live.session.geometry();
        live.status.state = "running";
        live.status.message = "rendering the change".into();
        self.publish(&live);
        drop(live);
        self.wake.notify_all();
    }
}

impl Shared {
    /// Starts over on another session (a photo opened): its stages, no
    /// maps, no selection, no images until its scene has run.
    pub fn replace(&self, session: Session, input: String) {
        let mut l = self.lock();
        l.session = session;
        l.surfaces = None;
        l.selection = Image::new(0, 0, false);
        l.images.clear();
        l.result = None;
        let generation = l.status.generation;
        let shown = l.status.shown;
        l.status = Status {
            state: "running",
            input,
            message: "opening the photo".into(),
            generation,
            shown,
            envmaps: l.session.envmaps(),
            meshes: l.session.meshes(),
            geometry: l.session.geometry(),
            ..Default::default()
        };
        self.changed(l);
    }
}

/// The engine's progress for one generation, into the status.
struct Progress<'a> {
    shared: &'a Shared,
    generation: u64,
}

impl Observer for Progress<'_> {
    fn started(&self, stage: &str, _kind: &str, _worker: &str) {
        let mut l = self.shared.lock();
        l.status.stage = stage.into();
        (l.status.done, l.status.total) = (0, 0);
        self.shared.publish(&l);
    }
    fn progress(&self, stage: &str, done: u64, total: u64) {
        let mut l = self.shared.lock();
        l.status.stage = stage.into();
        (l.status.done, l.status.total) = (done, total);
        self.shared.publish_progress(&l);
    }
    fn metric(&self, stage: &str, name: &str, value: f64) {
        if name != "loss" {
            return;
        }
        let mut l = self.shared.lock();
        if l.status.loss_stage != stage {
            l.status.loss_stage = stage.into();
            l.status.loss.clear();
        }
        // Bounded: a long recovery keeps every other point.
        if l.status.loss.len() >= 2000 {
            let thinned: Vec<f64> = l.status.loss.iter().step_by(2).copied().collect();
            l.status.loss = thinned;
        }
        l.status.loss.push(value);
        self.shared.publish_progress(&l);
    }
    fn finished(&self, report: &StageReport) {
        if report.notes.iter().any(|n| n == "cancelled while running") {
            let mut l = self.shared.lock();
            l.status.stopped += 1;
            self.shared.publish(&l);
        }
    }
    fn cancelled(&self) -> bool {
        self.shared.newest.load(Ordering::SeqCst) != self.generation
    }
    fn watch(&self) -> Option<Watch> {
        let (newest, generation) = (self.shared.newest.clone(), self.generation);
        Some(Watch {
            cancelled: Arc::new(move || newest.load(Ordering::SeqCst) != generation),
            images: true,
        })
    }
    /// The recovery's current re-render (its frozen paths under the
    /// materials and light fitted so far), shown until the preview comes.
    fn image(&self, stage: &str, name: &str, width: usize, height: usize, rgb: &[f32]) {
        if name != "current" || rgb.len() != width * height * 3 {
            return;
        }
        let img = RgbImage::from_vec(
            width,
            height,
            rgb.chunks_exact(3)
                .map(|c| glam::Vec3::new(c[0], c[1], c[2]))
                .collect(),
        );
        let png = view::png(&img);
        let mut l = self.shared.lock();
        if l.status.generation != self.generation {
            return;
        }
        l.images.insert("recovery".into(), png);
        l.status.image = Some("recovery");
        l.status.shown = self.generation;
        l.status.recovery_shots += 1;
        l.status.message = format!("recovering (`{stage}`): the fit so far");
        self.shared.publish(&l);
    }
}

/// The runner: forever, the newest generation's scene (once), preview
/// and result. Runs on its own thread.
pub fn runner(shared: Arc<Shared>, store: Arc<Tiered>, exec: Box<dyn Executor>) {
    let reg = matflow_nodes::registry();
    let exec = exec.as_ref();
    let mut ran: Option<u64> = None;
    loop {
        let (generation, pipeline, since) = {
            let mut l = shared.lock();
            while ran == Some(l.status.generation) {
                l = shared.wake.wait(l).unwrap_or_else(|e| e.into_inner());
            }
            (l.status.generation, l.session.pipeline(&reg), l.changed_at)
        };
        ran = Some(generation);
        let mut p = match pipeline {
            Ok(p) => p,
            Err(e) => {
                fail(&shared, &e.to_string());
                continue;
            }
        };
        // The studio keeps its images in memory (the EXR is encoded when
        // asked for): no file written per change. A file path is no part
        // of a stage's key, so the result's key is the export's.
        for st in &mut p.stages {
            if st.name == "result" {
                st.params
                    .0
                    .insert("output".into(), matflow_engine::value::Value::Null);
            }
        }
        let obs = Progress {
            shared: &shared,
            generation,
        };
        let mut run = |outputs: &[&str]| -> Result<Option<matflow_engine::Report>, String> {
            p.outputs = outputs.iter().map(|s| s.to_string()).collect();
            let report = run_pipeline(&p, &reg, &store, exec, &obs);
            // Superseded (its running stage may have stopped early): not
            // a failure, and nothing of it is shown.
            if obs.cancelled() {
                return Ok(None);
            }
            if let Some(f) = report.failure() {
                return Err(f);
            }
            if let Some(note) = report
                .stages
                .iter()
                .find(|s| s.name == "mesh")
                .and_then(|s| s.notes.first())
            {
                let mut l = shared.lock();
                if l.status.generation == generation && l.status.geometry_taken != *note {
                    l.status.geometry_taken = note.clone();
                    shared.publish(&l);
                }
            }
            Ok(Some(report))
        };
        let needs_maps = shared.lock().surfaces.is_none();
        if needs_maps {
            match run(&["scene"]).and_then(|r| match r {
                Some(r) => load_scene(&shared, &r, &store, generation),
                None => Ok(()),
            }) {
                Ok(()) => {}
                Err(e) => {
                    fail(&shared, &e);
                    continue;
                }
            }
        }
        for (stage, name) in [("preview", "preview"), ("result", "result")] {
            let report = match run(&[stage]) {
                Ok(Some(r)) => r,
                Ok(None) => break,
                Err(e) => {
                    fail(&shared, &e);
                    break;
                }
            };
            let img = match output_image(&report, &store, stage) {
                Ok(i) => i,
                Err(e) => {
                    fail(&shared, &e);
                    break;
                }
            };
            let png = view::png(&img);
            let mut l = shared.lock();
            if l.status.generation != generation {
                break;
            }
            let seconds = since.elapsed().as_secs_f64();
            l.images.insert(name.into(), png);
            l.status.shown = generation;
            l.status.image = Some(name);
            if name == "result" {
                l.result = Some(Arc::new(img));
                l.status.result_seconds = Some(seconds);
                l.status.state = "ready";
                l.status.message = summary(&report);
            } else {
                l.status.preview_seconds = Some(seconds);
                l.status.result_seconds = None;
                l.status.message =
                    format!("preview at {} spp; refining", crate::session::PREVIEW_SPP);
            }
            l.status.stage.clear();
            shared.publish(&l);
        }
    }
}

fn fail(shared: &Shared, message: &str) {
    let mut l = shared.lock();
    l.status.state = "failed";
    l.status.message = message.into();
    l.status.stage.clear();
    shared.publish(&l);
}

fn summary(r: &matflow_engine::Report) -> String {
    let count = |s: StageStatus| r.stages.iter().filter(|x| x.status == s).count();
    format!(
        "{} executed, {} cached in {:.2} s",
        count(StageStatus::Executed),
        count(StageStatus::Cached),
        r.seconds
    )
}

fn output_bytes(
    r: &matflow_engine::Report,
    store: &Tiered,
    stage: &str,
    output: &str,
) -> Result<Arc<Vec<u8>>, String> {
    let hex = r
        .stages
        .iter()
        .find(|s| s.name == stage)
        .and_then(|s| s.outputs.get(output))
        .ok_or_else(|| format!("the pipeline's `{stage}` stage made no `{output}`"))?;
    let d = Digest::from_hex(hex).ok_or_else(|| format!("bad digest {hex}"))?;
    store
        .get(&d)
        .map_err(|e| e.to_string())?
        .ok_or_else(|| format!("`{stage}`'s {output} is not in the cache"))
}

fn output_image(
    r: &matflow_engine::Report,
    store: &Tiered,
    stage: &str,
) -> Result<RgbImage, String> {
    let b = output_bytes(r, store, stage, "image")?;
    matflow_nodes::artifact::Artifact::decode(&b, "image")
        .and_then(|a| a.rgb("image"))
        .map_err(|e| e.0)
}

/// The scene's maps for the page and its surfaces for selection.
fn load_scene(
    shared: &Shared,
    r: &matflow_engine::Report,
    store: &Tiered,
    generation: u64,
) -> Result<(), String> {
    let b = output_bytes(r, store, "scene", "scene")?;
    let s = SceneData::decode(&b).map_err(|e| e.0)?;
    let maps = view::maps(&s);
    let (w, h) = (maps.width, maps.height);
    let mut l = shared.lock();
    if l.status.generation != generation {
        // Another session took over meanwhile (a photo opened).
        return Ok(());
    }
    l.status.width = w;
    l.status.height = h;
    l.status.maps = maps.images.iter().map(|(n, _)| *n).collect();
    for (n, png) in maps.images {
        l.images.insert(n.into(), png);
    }
    l.selection = Image::new(w, h, false);
    l.surfaces = Some(Surfaces {
        albedo: s.pred.albedo,
        depth: s.depth,
        // The scene's normals where it has them: on the reference's photos
        // they stop a click on the table at the pot and one on a courtyard
        // at the tree, where normals from the depth let it through
        // (`matflow-bench select`); without them, from the depth.
        normals: s.pred.normal,
        photo: s.target,
        camera: Camera::new(w, h),
    });
    l.status.message = "recovering the lighting and materials".into();
    shared.publish(&l);
    Ok(())
}

/// Errors of a request, as the handlers answer them.
pub fn request_error(e: SessionError) -> (axum::http::StatusCode, String) {
    use axum::http::StatusCode;
    match e {
        SessionError::Request(m) => (StatusCode::UNPROCESSABLE_ENTITY, format!("{m}\n")),
        SessionError::Conflict(m) => (StatusCode::CONFLICT, format!("{m}\n")),
        e => (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")),
    }
}
