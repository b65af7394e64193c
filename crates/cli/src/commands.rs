use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use matflow_geom::{mesh_for_view, MeshParams, Silhouettes};
use matflow_render::{
    render as render_scene, scene_from_depth, EnvMap, PixelFilter, RenderOptions, RenderOutput,
    RenderScene,
};
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, Bundle, MaterialSource, RgbImage};

#[derive(Args, Clone)]
pub struct RenderArgs {
    /// Scene bundle folder (reference layout).
    #[arg(long)]
    pub bundle: PathBuf,
    /// Render even when estimated to take more than an hour (on the
    /// reference 2-core machine).
    #[arg(long)]
    pub allow_expensive: bool,
    /// Material maps: best_results, pred or ground_truth.
    #[arg(long, default_value = "best_results")]
    pub materials: MaterialSource,
    /// Environment map (.hdr or .exr); default: the bundle's best_results/envmap.hdr
    /// (or ground_truth/envmap.hdr).
    #[arg(long)]
    pub envmap: Option<PathBuf>,
    /// Samples per pixel.
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    /// Maximum path depth in ray segments (Mitsuba's max_depth).
    #[arg(long, default_value_t = 4)]
    pub depth: u32,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Pixel filter: gaussian (Mitsuba's default) or box. Default: for
    /// `best_results` written by `matflow invert`, the filter it fitted
    /// with (its summary.json says which: box); otherwise gaussian.
    #[arg(long)]
    pub filter: Option<PixelFilter>,
    /// Mesh boundary angle threshold in degrees.
    #[arg(long, default_value_t = 6.0)]
    pub mesh_angle: f64,
    /// The near side of a depth discontinuity: `kept` (an object's edge
    /// keeps its depth and reaches the pixel border; a solid's unseen back
    /// is its front mirrored about its silhouettes) or `reference` (every
    /// boundary pixel takes the background's depth, as the reference
    /// implementation). Default: for `best_results` written by `matflow
    /// invert`, the one it recovered them with; else reference with
    /// `--reference-compat`; otherwise kept.
    #[arg(long)]
    pub silhouettes: Option<Silhouettes>,
    /// Geometry past the frame (matflow_geom::complete), so that unseen
    /// parts of the scene block and reflect light: `room` extends the
    /// view's floor, walls and ceiling and closes the room with assumed
    /// ones where the view shows a room; `closed` the same without
    /// windows; `planes` only extends the planes seen; `none` renders the
    /// depth mesh alone; `auto` renders each of them cheaply under the
    /// light the photo was taken in (the bundle's own envmap, else
    /// `--envmap`) and takes the least assuming whose render agrees with
    /// the bundle's photo within 0.5 dB of the best's (none without a
    /// photo). Default: for `best_results` written by `matflow invert`,
    /// the completion it recovered them with (its summary.json's
    /// `options.complete`); else none with `--reference-compat`; else the
    /// one the bundle declares for its own geometry (geometry.json, which
    /// `matflow synth` writes: none); otherwise auto. The flag alone means
    /// room.
    #[arg(long, num_args = 0..=1, default_missing_value = "room")]
    pub complete: Option<CompleteArg>,
    /// Reproduce the reference renderer's sampling-frame defect and its
    /// optimisation-time envmap layout (for comparing with its stored
    /// renders; physically incorrect).
    #[arg(long)]
    pub reference_compat: bool,
    /// Print PSNR (sRGB, γ 2.2) against this linear EXR.
    #[arg(long)]
    pub compare: Option<PathBuf>,
    /// Denoise the render (as `invert` does its re-render): two halves of
    /// the samples, divided by the pixels' albedo, edge-aware à-trous
    /// filtered, multiplied back. Needs --spp 2 or more; not with --insert.
    #[arg(long)]
    pub denoise: bool,
    /// Output EXR (linear); a gamma-encoded PNG is written beside it.
    #[arg(long)]
    pub out: PathBuf,
    /// Objects to insert: a YAML list of entries (mesh, translate or
    /// anchor, rotate, scale, material), mesh paths relative to the file.
    #[arg(long, value_name = "OBJECTS.yaml")]
    pub insert: Option<PathBuf>,
    /// With --insert: differential (the bundle's input image plus the
    /// change the objects make) or full (the render with the objects).
    #[arg(long, default_value = "differential", value_parser = ["differential", "full"])]
    pub composite: String,
    /// Glass surfaces a path may pass or reflect off beyond --depth.
    #[arg(long, default_value_t = matflow_render::integrator::DEFAULT_GLASS_DEPTH)]
    pub glass_depth: u32,
    /// Guide light samples by what each region of the scene sees of the
    /// sky (on), or sample the envmap by radiance alone (off). Either
    /// converges to the same image; on is less noisy where walls block
    /// most of the sky.
    #[arg(long, default_value = "on")]
    pub light_guide: OnOff,
    /// Aim light samples at the windows of a closed room's assumed walls
    /// too (portals; on), or follow the envmap's density alone (off).
    /// Either converges to the same image; on is less noisy in a closed
    /// room.
    #[arg(long, default_value = "on")]
    pub portals: OnOff,
    /// Light the scene with the lamps of the maps: those `matflow invert`
    /// fitted (best_results/lamps.json) or the true ones
    /// (ground_truth/lamps.json): on, or off (e.g. to relight a room by a
    /// new envmap alone). A sun among them lights the scene only under
    /// the envmap it came with: `--envmap` is a new sky.
    #[arg(long, default_value = "on")]
    pub lamps: OnOff,
}

/// What a render says of its light sampling.
pub fn light_guide_note(scene: &RenderScene) -> String {
    match &scene.light_visibility {
        Some(v) => format!(
            "light guided by visibility in {} of {} regions (the scene sees {:.0} % of the sky)",
            scene.env.guided_clusters(),
            v.clusters(),
            100.0 * v.open_fraction()
        ),
        None => "light sampled by radiance".into(),
    }
}

/// A switch given as `on` or `off`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

impl OnOff {
    pub fn on(self) -> bool {
        self == OnOff::On
    }
}

#[derive(Args)]
pub struct ShapesArgs {
    /// Folder to write jug.obj, torus.obj, sphere.obj and cube.obj into.
    #[arg(long)]
    pub out: PathBuf,
}

/// The OBJ text of a shipped shape (what `matflow shapes` writes).
pub fn shape_obj(name: &str, s: &matflow_procgen::shapes::Shape) -> String {
    let part = matflow_scene::meshfile::MeshPart {
        positions: s.mesh.positions.clone(),
        indices: s.mesh.indices.clone(),
        normals: s.normals.clone(),
        ..Default::default()
    };
    matflow_scene::meshfile::obj_text(
        &part,
        &format!("{name}: generated by `matflow shapes` (matflow_procgen::shapes::shipped)"),
    )
}

pub fn shapes(a: ShapesArgs) -> Result<()> {
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}", a.out.display()))?;
    for (name, s) in matflow_procgen::shapes::shipped() {
        let f = a.out.join(format!("{name}.obj"));
        io::write_atomic(&f, shape_obj(name, &s).as_bytes())?;
        outln!(
            "{}: {} vertices, {} triangles",
            f.display(),
            s.mesh.vertex_count(),
            s.mesh.triangle_count()
        );
    }
    Ok(())
}

#[derive(Args)]
pub struct MeshArgs {
    #[arg(long)]
    pub bundle: PathBuf,
    /// Boundary angle threshold in degrees (the reference's code uses 6).
    #[arg(long, default_value_t = 6.0)]
    pub angle: f64,
    /// The near side of a depth discontinuity: kept (an object's edge
    /// keeps its depth and reaches the pixel border; a solid's unseen back
    /// is its front mirrored about its silhouettes) or reference (every
    /// boundary pixel takes the background's depth, as the reference
    /// implementation's meshes).
    #[arg(long, default_value_t = Silhouettes::Kept)]
    pub silhouettes: Silhouettes,
    /// Geometry past the frame (see `render --complete`): auto, room,
    /// closed, planes, or none (the depth mesh alone). Default: the
    /// completion the bundle declares for its own geometry (geometry.json,
    /// which `matflow synth` and `matflow invert` write), otherwise auto:
    /// the photo tests each under the bundle's own light and materials
    /// (best_results, else ground_truth); room without them (as
    /// `invert`). The flag alone means room.
    #[arg(long, num_args = 0..=1, default_missing_value = "room")]
    pub complete: Option<CompleteArg>,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct SynthArgs {
    /// Scene seed (layout, objects, materials, lighting).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Image side in pixels.
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Samples per pixel for the input image.
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
    /// Output bundle folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Write MatNet-like predictions (blurred, biased, noisy albedo; wrong
    /// roughness and metallic) instead of the ground truth.
    #[arg(long)]
    pub degrade: bool,
    /// Also write a relighting test: ground_truth/relight_envmap.hdr (a
    /// different sky) and ground_truth/relit_image.exr rendered under it
    /// with this many samples per pixel (0: none).
    #[arg(long, default_value_t = 0)]
    pub relight_spp: u32,
}

pub struct LoadedScene {
    pub scene: RenderScene,
    pub maps: matflow_scene::MaterialMaps,
    pub env: EnvMap,
    /// Building mesh and BVH.
    pub seconds: f64,
}

/// How `--complete` completes the geometry past the frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum CompleteMode {
    /// The depth mesh alone.
    None,
    /// Extend the floor, walls and ceiling the view shows, fill them in
    /// behind what hides them in view, and continue objects cut by the
    /// frame border.
    Planes,
    /// As `planes`, and close the room with an assumed ceiling and walls,
    /// each assumed wall with a typical window left open (light from
    /// openings the view does not show). The default.
    #[default]
    Room,
    /// As `room`, the assumed walls without windows.
    Closed,
}

impl CompleteMode {
    pub fn name(self) -> &'static str {
        match self {
            CompleteMode::None => "none",
            CompleteMode::Planes => "planes",
            CompleteMode::Room => "room",
            CompleteMode::Closed => "closed",
        }
    }

    pub fn params(self) -> Option<matflow_geom::CompleteParams> {
        matflow_geom::CompleteParams::for_mode(self.name())
    }
}

/// The setting a render uses: the one `asked` for; else, for the maps
/// `matflow invert` wrote beside its `summary.json`, `options.KEY` there
/// (parsed by `parse`; `why` says so); else the default. Also says why.
fn from_invert<T: Default>(
    bundle: &Path,
    materials: MaterialSource,
    asked: Option<T>,
    key: &str,
    why: &'static str,
    parse: impl Fn(&str) -> Result<T, String>,
) -> Result<(T, &'static str)> {
    if let Some(v) = asked {
        return Ok((v, "as asked"));
    }
    if materials == MaterialSource::BestResults {
        let path = bundle.join("summary.json");
        if let Ok(text) = std::fs::read_to_string(&path) {
            let v: serde_json::Value = serde_json::from_str(&text)
                .with_context(|| format!("{}: not JSON", path.display()))?;
            if let Some(name) = v
                .get("options")
                .and_then(|o| o.get(key))
                .and_then(|f| f.as_str())
            {
                let got = parse(name)
                    .map_err(|e| anyhow::anyhow!("{}: options.{key}: {e}", path.display()))?;
                return Ok((got, why));
            }
        }
    }
    Ok((T::default(), "the default"))
}

/// What `--complete` asks for: a completion, or `auto` (the photo
/// decides, [`evidence_completion`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum CompleteArg {
    /// Test each completion against the photo and take the least assuming
    /// one the photo supports; then, with the photo's light known, where a
    /// closed room's windows are, or which unseen walls an open view shows.
    Auto,
    /// The depth mesh alone.
    None,
    /// Extend the planes seen.
    Planes,
    /// Extend them and close a room, with windows in its assumed walls.
    Room,
    /// As room, without windows.
    Closed,
}

impl CompleteArg {
    pub fn name(self) -> &'static str {
        match self.forced() {
            Some(m) => m.name(),
            None => "auto",
        }
    }

    /// The completion forced, or `None` for auto.
    pub fn forced(self) -> Option<CompleteMode> {
        match self {
            CompleteArg::Auto => None,
            CompleteArg::None => Some(CompleteMode::None),
            CompleteArg::Planes => Some(CompleteMode::Planes),
            CompleteArg::Room => Some(CompleteMode::Room),
            CompleteArg::Closed => Some(CompleteMode::Closed),
        }
    }
}

/// The completions the photo chooses among, from the least assuming to
/// the most.
pub const HYPOTHESES: [CompleteMode; 4] = [
    CompleteMode::None,
    CompleteMode::Planes,
    CompleteMode::Room,
    CompleteMode::Closed,
];

/// The photo's evidence on the geometry past the frame.
#[derive(Clone, Debug)]
pub struct Evidence {
    pub choice: matflow_render::evidence::CompletionChoice,
    /// The light the hypotheses were rendered in (a file, or what it was
    /// built from), and the maps.
    pub light: String,
    pub materials: MaterialSource,
    /// Where the photo put the windows of the room taken (when it took a
    /// closed room).
    pub windows: Option<matflow_render::evidence::WindowChoice>,
    /// Which unseen walls the photo shows the effect of (when it took an
    /// open completion).
    pub walls: Option<matflow_render::evidence::WallChoice>,
}

/// A completion decided, why, and the evidence when the photo decided.
#[derive(Clone, Debug)]
pub struct CompletionDecision {
    pub mode: CompleteMode,
    pub why: String,
    pub evidence: Option<Evidence>,
}

impl CompletionDecision {
    fn given(mode: CompleteMode, why: &str) -> Self {
        CompletionDecision {
            mode,
            why: why.to_string(),
            evidence: None,
        }
    }

    /// The completion decided, with the windows the photo placed.
    pub fn params(&self) -> Option<matflow_geom::CompleteParams> {
        let p = self.mode.params();
        if let Some(w) = self
            .evidence
            .as_ref()
            .and_then(|e| e.walls.as_ref())
            .filter(|w| !w.kept_start)
        {
            return CompleteMode::Room.params().map(|r| w.params(&r));
        }
        match self.evidence.as_ref().and_then(|e| e.windows.as_ref()) {
            Some(w) if !w.typical => p.map(|p| matflow_geom::CompleteParams {
                close: true,
                windows: Some(w.mask),
                ..p
            }),
            _ => p,
        }
    }

    /// For summary.json and geometry.json: the mode, why, and the scores.
    pub fn to_json(&self) -> serde_json::Value {
        let mut v = serde_json::json!({"complete": self.mode.name(), "why": self.why});
        if let Some(e) = &self.evidence {
            let c = &e.choice;
            v["evidence"] = serde_json::json!({
                "light": e.light,
                "materials": e.materials.folder().unwrap_or("pred"),
                "differing_blocks": c.differing,
                "margin_db": c.margin_db,
                "decisive": c.decisive,
                "reason": c.reason,
                "seconds": c.seconds,
                "scores": c.scores.iter().map(|s| serde_json::json!({
                    "complete": s.name,
                    "psnr_differing": s.psnr_differing,
                    "psnr_all": s.psnr_all,
                    "light_gain": s.gain,
                    "psnr_gained": s.psnr_gained,
                    "same_mesh_as": s.same_as,
                })).collect::<Vec<_>>(),
            });
            if let Some(w) = &e.windows {
                v["windows"] = windows_json(w);
            }
            if let Some(w) = &e.walls {
                v["walls"] = walls_json(w);
            }
        }
        v
    }

    /// Prints the decision, and the scores when the photo decided.
    pub fn print(&self) {
        outln!("completion {} ({})", self.mode.name(), self.why);
        if let Some(e) = &self.evidence {
            let c = &e.choice;
            for s in &c.scores {
                match &s.same_as {
                    Some(o) => outln!("  {:<7} the same mesh as {o}", s.name),
                    None => outln!(
                        "  {:<7} {:6.2} dB where the hypotheses differ ({:.0} % of the image), {:6.2} dB overall; needs {:.3}x the light ({:.2} dB with it)",
                        s.name,
                        s.psnr_differing,
                        100.0 * c.differing,
                        s.psnr_all,
                        s.gain,
                        s.psnr_gained
                    ),
                }
            }
            outln!(
                "  margin {:+.2} dB, {}; tested under {} with the {} maps in {:.2} s",
                c.margin_db,
                if c.decisive {
                    "decisive"
                } else {
                    "weak evidence"
                },
                e.light,
                e.materials.folder().unwrap_or("predicted"),
                c.seconds
            );
            if let Some(w) = &e.windows {
                print_windows(w);
            }
            if let Some(w) = &e.walls {
                print_walls(w);
            }
        }
    }
}

/// A greedy search's rounds in words (`what`: windows, walls): what
/// each took, and its best against the hypothesis so far.
fn print_rounds(what: &str, rounds: &[matflow_render::evidence::CompletionChoice]) {
    for (k, r) in rounds.iter().enumerate() {
        let best = (0..r.scores.len())
            .max_by(|&a, &b| {
                r.scores[a]
                    .psnr_differing
                    .total_cmp(&r.scores[b].psnr_differing)
            })
            .unwrap_or(0);
        outln!(
            "  {what}, round {}: {} of {} tested; best {} ({:.2} dB where they differ, {:.2} dB without it)",
            k + 1,
            r.scores[r.chosen].name,
            r.scores.len(),
            r.scores[best].name,
            r.scores[best].psnr_differing,
            r.scores[0].psnr_differing
        );
    }
}

/// The window search in words: each round's best and the room taken.
fn print_windows(w: &matflow_render::evidence::WindowChoice) {
    print_rounds("windows", &w.rounds);
    if let Some(t) = &w.against_typical {
        outln!(
            "  windows found {:.2} dB, typical windows {:.2} dB where they differ: {} taken ({:.2} s in all)",
            t.scores[0].psnr_differing,
            t.scores.get(1).map_or(f64::NAN, |s| s.psnr_differing),
            if w.typical { "typical windows" } else { "the windows found" },
            w.seconds
        );
    }
}

/// The wall search in words: each round's best and what was taken.
fn print_walls(w: &matflow_render::evidence::WallChoice) {
    print_rounds("walls", &w.rounds);
    if let (Some(t), Some(h)) = (&w.height_test, w.height) {
        outln!(
            "  walls' height: {h:.2} camera heights ({:.2} dB where the heights tried last differ)",
            t.scores
                .iter()
                .map(|s| s.psnr_differing)
                .fold(f64::NEG_INFINITY, f64::max)
        );
    }
    match &w.against_start {
        Some(t) => outln!(
            "  walls found {:.2} dB, {} {:.2} dB where they differ: {} taken ({:.2} s in all)",
            t.scores.get(1).map_or(f64::NAN, |s| s.psnr_differing),
            t.scores[0].name,
            t.scores[0].psnr_differing,
            if w.kept_start {
                t.scores[0].name.as_str()
            } else {
                "the walls found"
            },
            w.seconds
        ),
        None => outln!("  walls: none found ({:.2} s)", w.seconds),
    }
}

/// A test's scores for the JSON reports: each hypothesis's name (under
/// `key`) and its PSNR where they differ.
fn scores_json(
    c: &matflow_render::evidence::CompletionChoice,
    key: &str,
) -> Vec<serde_json::Value> {
    c.scores
        .iter()
        .map(|s| serde_json::json!({key: s.name, "psnr_differing": s.psnr_differing}))
        .collect()
}

/// The wall search for summary.json, geometry.json and OUT.json.
fn walls_json(w: &matflow_render::evidence::WallChoice) -> serde_json::Value {
    let plane =
        |p: &matflow_geom::AssumedPlane| serde_json::json!({"bit": p.bit, "where": p.describe()});
    let scores = |c| scores_json(c, "complete");
    serde_json::json!({
        "mask": w.mask,
        "start_kept": w.kept_start,
        "added": w.added.iter().map(plane).collect::<Vec<_>>(),
        "planes": w.planes.iter().map(plane).collect::<Vec<_>>(),
        "rounds": w.rounds.iter().map(scores).collect::<Vec<_>>(),
        "height": w.height,
        "height_test": w.height_test.as_ref().map(scores),
        "against_start": w.against_start.as_ref().map(scores),
        "seconds": w.seconds,
    })
}

/// The window search for summary.json, geometry.json and OUT.json.
fn windows_json(w: &matflow_render::evidence::WindowChoice) -> serde_json::Value {
    let slot =
        |s: &matflow_geom::WindowSlot| serde_json::json!({"bit": s.bit, "where": s.describe()});
    serde_json::json!({
        "mask": w.mask,
        "typical_taken": w.typical,
        "opened": w.opened.iter().map(slot).collect::<Vec<_>>(),
        "slots": w.slots.iter().map(slot).collect::<Vec<_>>(),
        "rounds": w.rounds.iter().map(|r| scores_json(r, "windows")).collect::<Vec<_>>(),
        "against_typical": w.against_typical.as_ref().map(|t| scores_json(t, "windows")),
        "seconds": w.seconds,
    })
}

/// The file in which a bundle declares the completion that reproduces its
/// own geometry (`{"complete": "none", "why": ...}`): `matflow synth`
/// writes it, since its scenes are their depth mesh and nothing else, and
/// `matflow invert` the one it recovered its maps with.
pub const GEOMETRY_FILE: &str = "geometry.json";

/// The completion `bundle` declares for itself in [`GEOMETRY_FILE`], if
/// it declares one (a bad file is an error naming it).
pub fn declared_completion(bundle: &Path) -> Result<Option<CompleteMode>> {
    let path = bundle.join(GEOMETRY_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let name = v
        .get("complete")
        .and_then(|c| c.as_str())
        .with_context(|| format!("{}: no string field `complete`", path.display()))?;
    let mode = <CompleteMode as clap::ValueEnum>::from_str(name, false)
        .map_err(|e| anyhow::anyhow!("{}: complete: {e}", path.display()))?;
    Ok(Some(mode))
}

/// How the photo's evidence is rendered: the render's filter and depth.
#[derive(Clone, Copy, Debug)]
pub struct EvidenceRender {
    pub mesh: MeshParams,
    pub filter: PixelFilter,
    pub max_depth: u32,
}

/// [`HYPOTHESES`] as the evidence module tests them (the same order).
pub fn hypotheses() -> Vec<matflow_render::evidence::Hypothesis> {
    let h = matflow_render::evidence::completion_hypotheses();
    debug_assert!(h.iter().zip(HYPOTHESES).all(|(h, m)| h.name == m.name()));
    h
}

/// The completion the photo supports ([`matflow_render::evidence`]): each
/// of [`HYPOTHESES`] rendered with `materials` in `light` and compared
/// with the bundle's photo. Without a photo or a light there is no
/// evidence, and the least assuming (none) is taken.
pub fn evidence_completion(
    bundle_dir: &Path,
    materials: MaterialSource,
    light: Option<&Path>,
    how: EvidenceRender,
) -> Result<CompletionDecision> {
    let bundle = Bundle::open(bundle_dir)?;
    let Some(light) = light else {
        return Ok(CompletionDecision::given(
            CompleteMode::None,
            "auto: no light to test the geometry past the frame under; the least assuming",
        ));
    };
    let photo =
        match bundle.load_gt_image() {
            Ok(p) => p,
            Err(_) => return Ok(CompletionDecision::given(
                CompleteMode::None,
                "auto: no photo to test the geometry past the frame against; the least assuming",
            )),
        };
    let depth = bundle.load_depth()?;
    let maps = bundle.load_materials(materials)?;
    let env =
        EnvMap::new(&io::read_envmap(light)?).with_context(|| format!("{}", light.display()))?;
    let hyps = hypotheses();
    // The maps' own lamps light the photo too, under their own envmap.
    let own = materials
        .folder()
        .is_some_and(|f| light.parent() == Some(&bundle_dir.join(f)));
    let lamps = match materials.folder().filter(|_| own) {
        Some(f) => matflow_scene::lamps::bundle_lamps(bundle_dir, f)?.unwrap_or_default(),
        None => Vec::new(),
    };
    let opts = matflow_render::evidence::EvidenceOptions {
        filter: how.filter,
        max_depth: how.max_depth,
        lamps,
        ..Default::default()
    };
    let choice = matflow_render::evidence::choose_completion(
        &depth, &maps, &env, how.mesh, &photo, &hyps, &opts,
    )
    .with_context(|| {
        format!(
            "{}: testing the geometry past the frame",
            bundle_dir.display()
        )
    })?;
    let mut mode = HYPOTHESES[choice.chosen];
    let view = matflow_render::evidence::PhotoView {
        depth: &depth,
        maps: &maps,
        env: &env,
        mesh_params: how.mesh,
        photo: &photo,
    };
    // A closed room: where its windows are, the photo tells too.
    let windows = match mode.params() {
        Some(base) if base.close => matflow_render::evidence::choose_windows(
            &view,
            &base,
            // Many more hypotheses: one sample per pixel a half (64 a
            // block) still tells a window's light apart.
            &matflow_render::evidence::EvidenceOptions {
                spp_half: 1,
                ..opts.clone()
            },
        )
        .with_context(|| format!("{}: placing the room's windows", bundle_dir.display()))?,
        _ => None,
    };
    if let Some(w) = windows.as_ref().filter(|w| !w.typical) {
        mode = if w.mask == 0 {
            CompleteMode::Closed
        } else {
            CompleteMode::Room
        };
    }
    // An open view: whether an unseen wall (or a ceiling) shows in it.
    let walls = match (mode, CompleteMode::Room.params()) {
        (CompleteMode::None | CompleteMode::Planes, Some(room)) => {
            matflow_render::evidence::choose_walls(
                &view,
                &matflow_render::evidence::Hypothesis {
                    name: mode.name().to_string(),
                    params: mode.params(),
                },
                &room,
                &matflow_render::evidence::EvidenceOptions {
                    spp_half: 1,
                    ..opts.clone()
                },
            )
            .with_context(|| format!("{}: testing unseen walls", bundle_dir.display()))?
        }
        _ => None,
    };
    if walls.as_ref().is_some_and(|w| !w.kept_start) {
        mode = CompleteMode::Room;
    }
    Ok(CompletionDecision {
        mode,
        why: format!("auto: {}", choice.reason),
        evidence: Some(Evidence {
            choice,
            light: if opts.lamps.is_empty() {
                light.display().to_string()
            } else {
                format!("{} and {} lamp(s)", light.display(), opts.lamps.len())
            },
            materials,
            windows,
            walls,
        }),
    })
}

/// The envmap a maps folder holds of its own: the finer `envmap.exr`
/// where one lies beside `envmap.hdr` (as the validation set's
/// full-resolution capture sky does), else `envmap.hdr`.
fn folder_envmap(folder: &Path) -> Option<PathBuf> {
    ["envmap.exr", "envmap.hdr"]
        .iter()
        .map(|n| folder.join(n))
        .find(|p| p.is_file())
}

/// The light and maps a bundle holds of its own, to test completions
/// with when nothing else is given: `best_results` (with its envmap) if
/// it has them, else `ground_truth`; the envmap as [`capture_light`]
/// takes it (`envmap.exr` before `envmap.hdr`), so `mesh` and `render`
/// test under the same light.
pub fn own_light_and_maps(bundle_dir: &Path) -> Option<(PathBuf, MaterialSource)> {
    [MaterialSource::BestResults, MaterialSource::GroundTruth]
        .into_iter()
        .find_map(|m| {
            let folder = bundle_dir.join(m.folder()?);
            let env = folder_envmap(&folder)?;
            folder.join("albedo.exr").is_file().then_some((env, m))
        })
}

/// The completion a command uses when it renders nothing itself (`mesh`):
/// the one `asked` for; else the one the bundle declares
/// ([`GEOMETRY_FILE`]); else auto with the bundle's own light and maps
/// ([`own_light_and_maps`]); room when it has none (as `invert`).
pub fn completion_or_default(
    bundle: &Path,
    asked: Option<CompleteArg>,
    how: EvidenceRender,
) -> Result<CompletionDecision> {
    if let Some(m) = asked.and_then(CompleteArg::forced) {
        return Ok(CompletionDecision::given(m, "as asked"));
    }
    if asked.is_none() {
        if let Some(m) = declared_completion(bundle)? {
            return Ok(CompletionDecision::given(
                m,
                "the bundle's own geometry, geometry.json",
            ));
        }
    }
    match own_light_and_maps(bundle) {
        Some((light, maps)) => evidence_completion(bundle, maps, Some(&light), how),
        None => Ok(CompletionDecision::given(
            CompleteMode::Room,
            "auto: the bundle has no light of its own to test the completions under; room, as \
             invert takes by default",
        )),
    }
}

/// The completion a render uses: the one asked for; else, for the maps
/// `matflow invert` wrote, the one it recovered them with (`summary.json`'s
/// `options.complete`); else, with `--reference-compat`, none (the
/// reference renders the depth mesh alone); else the one the bundle
/// declares ([`GEOMETRY_FILE`]); else auto: tested under the light the
/// photo was taken in (the bundle's own envmap, else the render's
/// `envmap`) with the render's maps.
pub fn render_completion(
    bundle: &Path,
    materials: MaterialSource,
    asked: Option<CompleteArg>,
    reference_compat: bool,
    envmap: Option<&Path>,
    how: EvidenceRender,
) -> Result<CompletionDecision> {
    if let Some(m) = asked.and_then(CompleteArg::forced) {
        return Ok(CompletionDecision::given(m, "as asked"));
    }
    if asked.is_none() {
        let (from_summary, why) = from_invert(
            bundle,
            materials,
            None,
            "complete",
            "the one matflow invert recovered these maps with",
            |name| <CompleteMode as clap::ValueEnum>::from_str(name, false).map(Some),
        )?;
        if let Some(m) = from_summary {
            return Ok(CompletionDecision::given(m, why));
        }
        if reference_compat {
            return Ok(CompletionDecision::given(
                CompleteMode::None,
                "the reference's, --reference-compat",
            ));
        }
        if let Some(m) = declared_completion(bundle)? {
            return Ok(CompletionDecision::given(
                m,
                "the bundle's own geometry, geometry.json",
            ));
        }
    }
    let light = capture_light(bundle, materials, envmap);
    evidence_completion(bundle, materials, light.as_deref(), how)
}

/// The light the bundle's photo was taken in, as far as the bundle says:
/// its own envmap for these maps (best_results/ or ground_truth/; the
/// finer `envmap.exr` where one lies beside `envmap.hdr`, as the
/// validation set's full-resolution capture sky does: a sun blurred over
/// a 32×16 texel lights other places than the sun), else any of its own,
/// else the one the render was given.
pub fn capture_light(
    bundle: &Path,
    materials: MaterialSource,
    envmap: Option<&Path>,
) -> Option<PathBuf> {
    materials
        .folder()
        .and_then(|f| folder_envmap(&bundle.join(f)))
        .or_else(|| Bundle::open(bundle).ok().and_then(|b| b.envmap_path()))
        .or_else(|| envmap.map(Path::to_path_buf))
}

/// Builds mesh, BVH, materials and envmap for a bundle; with `lamps`,
/// the lamps of the maps' folder light them too (`FOLDER/lamps.json`:
/// those `matflow invert` fitted with its `best_results/` maps, the true
/// ones with `ground_truth/`), the sun among them only under the envmap
/// it came with (a new `envmap` is a new sky, which brings its own sun).
pub fn load_scene(
    bundle_dir: &Path,
    materials: MaterialSource,
    envmap: Option<&Path>,
    mesh: MeshParams,
    reference_compat: bool,
    complete: Option<matflow_geom::CompleteParams>,
    lamps: bool,
) -> Result<LoadedScene> {
    let bundle = Bundle::open(bundle_dir)?;
    let depth = bundle.load_depth()?;
    let maps = bundle.load_materials(materials)?;
    let env_path = match envmap {
        Some(p) => p.to_path_buf(),
        None => bundle.envmap_path().with_context(|| {
            format!(
                "{}: no best_results/envmap.hdr or ground_truth/envmap.hdr; pass --envmap FILE.hdr (or .exr)",
                bundle_dir.display()
            )
        })?,
    };
    let mut env_img = io::read_envmap(&env_path)?;
    if reference_compat {
        env_img = matflow_render::envmap::merge_seam_columns(&env_img);
    }
    let env = EnvMap::new(&env_img).with_context(|| format!("{}", env_path.display()))?;
    let t0 = Instant::now();
    let mut scene = scene_from_depth(&depth, &maps, env.clone(), mesh, complete.as_ref())
        .with_context(|| format!("{}: building the scene", bundle_dir.display()))?
        .0;
    if let Some(folder) = materials.folder().filter(|_| lamps) {
        if let Some(mut l) = matflow_scene::lamps::bundle_lamps(bundle_dir, folder)? {
            if envmap.is_some() {
                l.retain(|l| !l.is_distant());
            }
            scene.set_lamps(l)?;
        }
    }
    Ok(LoadedScene {
        scene,
        maps,
        env,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

pub fn progress_bar(total: u64, msg: &str) -> ProgressBar {
    let pb = ProgressBar::new(total);
    pb.set_style(
        ProgressStyle::with_template(
            "{msg} [{bar:40}] {pos}/{len} tiles, {elapsed} elapsed, eta {eta}",
        )
        .unwrap()
        .progress_chars("=> "),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Renders with a progress bar; returns the output and its wall time in
/// seconds.
pub fn render_with_progress(
    scene: &RenderScene,
    opts: &RenderOptions,
    label: &str,
) -> (RenderOutput, f64) {
    let ts = opts.tile_size.max(1);
    let tiles = scene.camera.width.div_ceil(ts) * scene.camera.height.div_ceil(ts);
    let pb = progress_bar(tiles as u64, label);
    let t0 = Instant::now();
    let out = render_scene(scene, opts, &|d, _| pb.set_position(d as u64));
    pb.finish_and_clear();
    (out, t0.elapsed().as_secs_f64())
}

/// Writes `out` (EXR) and a PNG with the same stem.
pub fn write_outputs(out: &Path, img: &RgbImage) -> Result<PathBuf> {
    io::write_exr_rgb(out, img)?;
    let png = out.with_extension("png");
    io::write_png_gamma(&png, img)?;
    Ok(png)
}

/// The filter a render uses: the one asked for; else, for the maps
/// `matflow invert` wrote, the one it fitted them with (`summary.json`'s
/// `options.pixel_filter`); else Mitsuba's Gaussian. Also says why.
pub fn render_filter(
    bundle: &Path,
    materials: MaterialSource,
    asked: Option<PixelFilter>,
) -> Result<(PixelFilter, &'static str)> {
    from_invert(
        bundle,
        materials,
        asked,
        "pixel_filter",
        "the one matflow invert fitted these maps with",
        |name| name.parse::<PixelFilter>().map_err(|e| e.to_string()),
    )
}

/// The mesh `render` builds: its angle, and the silhouettes asked for,
/// else those `matflow invert` recovered the maps with, else the
/// reference's with `--reference-compat`, else kept.
fn render_mesh(a: &RenderArgs) -> Result<MeshParams> {
    let (recovered, _) = from_invert(
        &a.bundle,
        a.materials,
        a.silhouettes.map(Some),
        "silhouettes",
        "the one matflow invert recovered these maps with",
        |name| name.parse::<Silhouettes>().map(Some),
    )?;
    let silhouettes = recovered.unwrap_or(if a.reference_compat {
        Silhouettes::Reference
    } else {
        Silhouettes::Kept
    });
    Ok(MeshParams {
        min_angle_deg: a.mesh_angle,
        silhouettes,
    })
}

pub fn render(a: RenderArgs) -> Result<()> {
    let t_all = Instant::now();
    let (filter, why) = render_filter(&a.bundle, a.materials, a.filter)?;
    let mesh = render_mesh(&a)?;
    let decision = render_completion(
        &a.bundle,
        a.materials,
        a.complete,
        a.reference_compat,
        a.envmap.as_deref(),
        EvidenceRender {
            mesh,
            filter,
            max_depth: a.depth,
        },
    )?;
    decision.print();
    let complete = decision.mode;
    let mut loaded = load_scene(
        &a.bundle,
        a.materials,
        a.envmap.as_deref(),
        mesh,
        a.reference_compat,
        decision.params(),
        a.lamps.on(),
    )?;
    if !a.light_guide.on() {
        loaded.scene.set_light_guide(None);
    }
    if !a.portals.on() {
        loaded.scene.portals = Default::default();
    }
    let opts = RenderOptions {
        spp: a.spp,
        max_depth: a.depth,
        glass_depth: a.glass_depth,
        seed: a.seed,
        filter,
        reference_compat: a.reference_compat,
        ..Default::default()
    };
    let renders = if a.insert.is_some() && a.composite == "differential" {
        2.0
    } else {
        1.0
    };
    let est = renders
        * matflow_nodes::render_seconds(
            Some((loaded.scene.camera.width, loaded.scene.camera.height)),
            a.spp as i64,
            a.depth as i64,
        );
    if !a.allow_expensive && est > matflow_engine::spec::EXPENSIVE_SECONDS {
        bail!(
            "{}: this render is estimated at {} on the reference 2-core machine; the limit \
             without --allow-expensive is {}. Lower --spp, or pass --allow-expensive",
            a.bundle.display(),
            crate::run::duration(est),
            crate::run::duration(matflow_engine::spec::EXPENSIVE_SECONDS)
        );
    }
    if a.denoise && (a.insert.is_some() || a.spp < 2) {
        bail!(
            "{}: --denoise needs --spp 2 or more (two halves of the samples) and a plain render (not --insert)",
            a.bundle.display()
        );
    }
    if let Some(objects_file) = &a.insert {
        return render_inserted(&a, objects_file, loaded, &opts, t_all, &decision);
    }
    let (out, seconds) = if a.denoise {
        let pb = progress_bar(0, "render (two halves)");
        let t0 = Instant::now();
        let guide = matflow_render::denoise::Guide::build(&loaded.scene);
        let d = matflow_render::denoise::render_denoised(
            &loaded.scene,
            &guide,
            &opts,
            matflow_render::denoise::RENDER_PASSES,
            &|done, total| {
                pb.set_length(total as u64);
                pb.set_position(done as u64)
            },
        )
        .context("denoising needs at least 2 samples per pixel")?;
        pb.finish_and_clear();
        let out = RenderOutput {
            image: d.image,
            stats: d.stats,
        };
        (out, t0.elapsed().as_secs_f64())
    } else {
        render_with_progress(&loaded.scene, &opts, "render")
    };
    let png = write_outputs(&a.out, &out.image)?;
    let s = out.stats;
    outln!(
        "rendered {}x{} at {} spp{}, depth {}, {} filter ({why}), completion {}, {} lamp(s), {} sun(s), {} portal(s), {} in {:.2} s (mesh and BVH {:.2} s, total {:.2} s): {:.1} M rays, {:.2} Mrays/s -> {}, {}",
        loaded.scene.camera.width,
        loaded.scene.camera.height,
        a.spp,
        if a.denoise { " (denoised)" } else { "" },
        a.depth,
        filter.name(),
        complete.name(),
        loaded.scene.lamps.iter().filter(|l| !l.is_distant()).count(),
        loaded.scene.lamps.iter().filter(|l| l.is_distant()).count(),
        loaded.scene.portals.len(),
        light_guide_note(&loaded.scene),
        seconds,
        loaded.seconds,
        t_all.elapsed().as_secs_f64(),
        s.total_rays() as f64 / 1e6,
        s.total_rays() as f64 / 1e6 / seconds.max(1e-9),
        a.out.display(),
        png.display()
    );
    if s.discarded_samples > 0 {
        eprintln!(
            "warning: {} sample(s) with NaN/Inf radiance were dropped",
            s.discarded_samples
        );
    }
    let photo_psnr = explains_photo(&a, &out.image);
    write_report(&a.out, &decision, photo_psnr)?;
    if let Some(c) = &a.compare {
        let reference = io::read_exr_rgb(c)?;
        if !reference.same_size(&out.image) {
            bail!("{}: size differs from the render", c.display());
        }
        outln!(
            "PSNR (sRGB, gamma 2.2) against {}: {:.2} dB",
            c.display(),
            psnr_gamma(&out.image, &reference)
        );
    }
    Ok(())
}

/// Under this PSNR on its own photo a result is reported as not
/// explaining it (`render`, `invert`).
pub const EXPLAINS_PHOTO_DB: f64 = 20.0;

/// Says how well `psnr` on the photo explains it, warning under
/// [`EXPLAINS_PHOTO_DB`].
pub fn report_photo_psnr(what: &str, psnr: f64) {
    outln!("{what} explains the photo at {psnr:.2} dB (sRGB, gamma 2.2)");
    if psnr < EXPLAINS_PHOTO_DB {
        eprintln!(
            "warning: {what} explains the photo at only {psnr:.2} dB (under {EXPLAINS_PHOTO_DB} dB): \
             the geometry or the light does not explain the photo"
        );
    }
}

/// A plain render in the light of the bundle's photo (no `--envmap`, or
/// none of the bundle's own to tell it from) against that photo: the
/// PSNR, reported ([`report_photo_psnr`]); `None` when the render is a
/// relighting or the bundle has no photo.
fn explains_photo(a: &RenderArgs, image: &RgbImage) -> Option<f64> {
    let bundle = Bundle::open(&a.bundle).ok()?;
    if a.envmap.is_some() && bundle.envmap_path().is_some() {
        return None;
    }
    let photo = bundle.load_gt_image().ok()?;
    if !photo.same_size(image) {
        return None;
    }
    let psnr = psnr_gamma(image, &photo);
    report_photo_psnr("the render", psnr);
    Some(psnr)
}

/// The render's report beside its output (OUT.json): the completion, why,
/// the photo's evidence, and how well the render explains the photo.
fn write_report(out: &Path, decision: &CompletionDecision, photo_psnr: Option<f64>) -> Result<()> {
    let report = serde_json::json!({
        "completion": decision.to_json(),
        "photo_psnr": photo_psnr,
    });
    io::write_atomic(
        &out.with_extension("json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    Ok(())
}

/// `render --insert`: the bundle with the objects of `objects_file`,
/// composited into its input image (or the full render).
fn render_inserted(
    a: &RenderArgs,
    objects_file: &Path,
    loaded: LoadedScene,
    opts: &RenderOptions,
    t_all: Instant,
    decision: &CompletionDecision,
) -> Result<()> {
    let specs =
        matflow_nodes::objects::read_objects_file(objects_file).map_err(anyhow::Error::msg)?;
    let cam = loaded.scene.camera;
    let objs = matflow_nodes::objects::place(&specs, &cam, &loaded.scene.mesh)
        .map_err(|e| anyhow::anyhow!("{}: {e}", objects_file.display()))?;
    let photo = if a.composite == "differential" {
        let b = Bundle::open(&a.bundle)?;
        let img = b.load_gt_image().with_context(|| {
            "differential compositing adds the objects to the bundle's input image; pass \
             --composite full for the plain render"
        })?;
        if (img.width, img.height) != (cam.width, cam.height) {
            bail!(
                "{}: the input image is {}x{} but the scene is {}x{}",
                a.bundle.display(),
                img.width,
                img.height,
                cam.width,
                cam.height
            );
        }
        Some(img)
    } else {
        None
    };
    let with_scene = RenderScene::with_objects(
        cam,
        loaded.scene.mesh.clone(),
        &loaded.maps,
        loaded.env.clone(),
        &objs,
    )?;
    let (with, t_with) = render_with_progress(&with_scene, opts, "with objects");
    let (image, t_without) = match &photo {
        Some(photo) => {
            let (without, t) = render_with_progress(&loaded.scene, opts, "without");
            let alpha = with_scene.object_coverage(4);
            (
                matflow_nodes::composite_differential(photo, &with.image, &without.image, &alpha),
                t,
            )
        }
        None => (with.image.clone(), 0.0),
    };
    let png = write_outputs(&a.out, &image)?;
    outln!(
        "inserted {} object(s) ({} triangles) into {}x{} at {} spp: render with objects {:.2} s{} (total {:.2} s) -> {}, {}",
        specs.len(),
        objs.iter().map(|o| o.mesh.triangle_count()).sum::<usize>(),
        cam.width,
        cam.height,
        a.spp,
        t_with,
        if photo.is_some() {
            format!(", without {t_without:.2} s, composited differentially")
        } else {
            String::new()
        },
        t_all.elapsed().as_secs_f64(),
        a.out.display(),
        png.display()
    );
    write_report(&a.out, decision, None)?;
    Ok(())
}

pub fn mesh(a: MeshArgs) -> Result<()> {
    let bundle = Bundle::open(&a.bundle)?;
    let depth = bundle.load_depth()?;
    let t0 = Instant::now();
    let params = MeshParams {
        min_angle_deg: a.angle,
        silhouettes: a.silhouettes,
    };
    let (cam, mut m) = mesh_for_view(&depth, &params)?;
    let decision = completion_or_default(
        &a.bundle,
        a.complete,
        EvidenceRender {
            mesh: params,
            filter: PixelFilter::default(),
            max_depth: 4,
        },
    )?;
    decision.print();
    if let Some(params) = decision.params() {
        let c = matflow_geom::complete_beyond_frame(&mut m.mesh, &depth, &cam, &params);
        for f in &c.extended {
            outln!(
                "extended {:?} n=({:.3}, {:.3}, {:.3}) d={:.3}: {:.1} % of the view, reaches {:?} (left, right, top, bottom)",
                f.kind,
                f.plane.n.x,
                f.plane.n.y,
                f.plane.n.z,
                f.plane.d,
                100.0 * f.fraction,
                f.reaches
            );
        }
        outln!(
            "completion: {} plane(s) extended ({} triangles), {} found but not extended; \
             {} triangles continue objects cut by the border",
            c.extended.len(),
            c.triangles - c.border_triangles,
            c.kept_in,
            c.border_triangles
        );
    }
    let secs = t0.elapsed().as_secs_f64();
    let mut buf = Vec::new();
    m.mesh.write_ply(&mut buf, cam.width, cam.height)?;
    io::write_atomic(&a.out, &buf)?;
    outln!(
        "mesh: {} vertices, {} triangles in {:.3} s ({} silhouettes: {} boundary pixels moved, {} kept as edges; {} copies, {} direct, {} after 1 copy, {} after 2, {} dropped; backs: {} vertices, {} triangles) -> {}",
        m.mesh.vertex_count(),
        m.mesh.triangle_count(),
        secs,
        a.silhouettes,
        m.stats.boundary_pixels - m.stats.kept_edges,
        m.stats.kept_edges,
        m.stats.copies,
        m.stats.emitted_direct,
        m.stats.emitted_one_copy,
        m.stats.emitted_two_copies,
        m.stats.dropped,
        m.stats.back_vertices,
        m.stats.back_triangles,
        a.out.display()
    );
    Ok(())
}

pub fn synth(a: SynthArgs) -> Result<()> {
    if a.size < 8 || a.size > 8192 {
        bail!("--size {} is out of range (8..=8192)", a.size);
    }
    let t0 = Instant::now();
    let s = matflow_procgen::synthetic::generate(a.seed, a.size, a.size);
    let bundle = Bundle::create(&a.out)?;
    bundle.write_depth(&s.depth)?;
    if a.degrade {
        bundle.write_predictions(&matflow_procgen::synthetic::degrade(&s.maps, a.seed))?;
    } else {
        bundle.write_predictions(&s.maps)?;
    }
    bundle.write_materials("ground_truth", &s.maps)?;
    io::write_hdr(&bundle.path("ground_truth/envmap.hdr"), &s.envmap)?;
    // The scene is its depth mesh and nothing else (rendered on it alone,
    // below): commands on the bundle default to completing nothing.
    let geometry = serde_json::json!({
        "complete": "none",
        "why": "a matflow synth scene: the depth mesh is the whole scene (its images were rendered on it alone)",
    });
    io::write_atomic(
        &bundle.path(GEOMETRY_FILE),
        serde_json::to_string_pretty(&geometry)?.as_bytes(),
    )?;
    // Render the input photo with the true materials and lighting.
    let loaded = load_scene(
        &a.out,
        MaterialSource::GroundTruth,
        None,
        MeshParams::default(),
        false,
        None,
        false,
    )?;
    let opts = RenderOptions {
        spp: a.spp,
        seed: a.seed,
        ..Default::default()
    };
    let (out, seconds) = render_with_progress(&loaded.scene, &opts, "render gt_image");
    io::write_exr_rgb(&bundle.path("gt_image.exr"), &out.image)?;
    io::write_png_gamma(&bundle.path("gt_image.png"), &out.image)?;
    if a.relight_spp > 0 {
        let env_path = bundle.path("ground_truth/relight_envmap.hdr");
        io::write_hdr(
            &env_path,
            &matflow_procgen::synthetic::relight_sky(a.seed, 32, 16),
        )?;
        let relit = load_scene(
            &a.out,
            MaterialSource::GroundTruth,
            Some(&env_path),
            MeshParams::default(),
            false,
            None,
            false,
        )?;
        let opts = RenderOptions {
            spp: a.relight_spp,
            seed: a.seed ^ 0x7e11,
            ..Default::default()
        };
        let (img, _) = render_with_progress(&relit.scene, &opts, "render relit_image");
        io::write_exr_rgb(&bundle.path("ground_truth/relit_image.exr"), &img.image)?;
        io::write_png_gamma(&bundle.path("ground_truth/relit_image.png"), &img.image)?;
    }
    outln!(
        "synthetic scene {} ({}x{}): {} triangles, gt_image at {} spp in {:.2} s (total {:.2} s) -> {}",
        a.seed,
        a.size,
        a.size,
        loaded.scene.mesh.triangle_count(),
        a.spp,
        seconds,
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}
