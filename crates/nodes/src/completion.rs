//! Geometry past the frame for the commands on a bundle folder
//! (`bundle_mesh`, `bundle_render`, and `matflow invert`): which completion
//! a bundle's own files declare, which one `matflow invert` recovered its
//! maps with, and which one the photo supports under a known light
//! ([`matflow_render::evidence`]), with the evidence in words and JSON.

use std::path::{Path, PathBuf};

use matflow_engine::NodeError;
use matflow_geom::MeshParams;
use matflow_render::{EnvMap, PixelFilter};
use matflow_scene::{io, Bundle, MaterialSource};

use crate::Context;

/// How `--complete` completes the geometry past the frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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

impl std::str::FromStr for CompleteMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        HYPOTHESES
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("invalid value '{s}': none, planes, room or closed"))
    }
}

/// The setting a render uses: the one `asked` for; else, for the maps
/// `matflow invert` wrote beside its `summary.json`, `options.KEY` there
/// (parsed by `parse`; `why` says so); else the default. Also says why.
pub fn from_invert<T: Default>(
    bundle: &Path,
    materials: MaterialSource,
    asked: Option<T>,
    key: &str,
    why: &'static str,
    parse: impl Fn(&str) -> Result<T, String>,
) -> Result<(T, &'static str), NodeError> {
    if let Some(v) = asked {
        return Ok((v, "as asked"));
    }
    if materials == MaterialSource::BestResults {
        let path = bundle.join("summary.json");
        if let Ok(text) = std::fs::read_to_string(&path) {
            let v: serde_json::Value =
                serde_json::from_str(&text).context(|| format!("{}: not JSON", path.display()))?;
            if let Some(name) = v
                .get("options")
                .and_then(|o| o.get(key))
                .and_then(|f| f.as_str())
            {
                let got = parse(name)
                    .map_err(|e| crate::err(format!("{}: options.{key}: {e}", path.display())))?;
                return Ok((got, why));
            }
        }
    }
    Ok((T::default(), "the default"))
}

/// What `--complete` asks for: a completion, or `auto` (the photo
/// decides, [`evidence_completion`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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

impl std::str::FromStr for CompleteArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "auto" => CompleteArg::Auto,
            _ => match s.parse::<CompleteMode>() {
                Ok(CompleteMode::None) => CompleteArg::None,
                Ok(CompleteMode::Planes) => CompleteArg::Planes,
                Ok(CompleteMode::Room) => CompleteArg::Room,
                Ok(CompleteMode::Closed) => CompleteArg::Closed,
                Err(_) => {
                    return Err(format!(
                        "invalid value '{s}': auto, none, planes, room or closed"
                    ))
                }
            },
        })
    }
}

impl CompleteArg {
    /// Every value, as the command line and the kinds' `complete` take them.
    pub const NAMES: [&'static str; 5] = ["auto", "none", "planes", "room", "closed"];

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
    pub fn given(mode: CompleteMode, why: &str) -> Self {
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

    /// For summary.json and geometry.json: the mode, why, and the scores
    /// (no timings: a bundle's files and a stage's report must not depend
    /// on the clock, or equal work would hash unequal).
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

    /// The decision in words, and the scores when the photo decided.
    pub fn lines(&self) -> Vec<String> {
        let mut out = Vec::new();
        out.push(format!("completion {} ({})", self.mode.name(), self.why));
        if let Some(e) = &self.evidence {
            let c = &e.choice;
            for s in &c.scores {
                match &s.same_as {
                    Some(o) => out.push(format!("  {:<7} the same mesh as {o}", s.name)),
                    None => out.push(format!(
                        "  {:<7} {:6.2} dB where the hypotheses differ ({:.0} % of the image), {:6.2} dB overall; needs {:.3}x the light ({:.2} dB with it)",
                        s.name,
                        s.psnr_differing,
                        100.0 * c.differing,
                        s.psnr_all,
                        s.gain,
                        s.psnr_gained
                    )),
                }
            }
            out.push(format!(
                "  margin {:+.2} dB, {}; tested under {} with the {} maps",
                c.margin_db,
                if c.decisive {
                    "decisive"
                } else {
                    "weak evidence"
                },
                e.light,
                e.materials.folder().unwrap_or("predicted"),
            ));
            if let Some(w) = &e.windows {
                windows_lines(&mut out, w);
            }
            if let Some(w) = &e.walls {
                walls_lines(&mut out, w);
            }
        }
        out
    }
}

/// A greedy search's rounds in words (`what`: windows, walls): what
/// each took, and its best against the hypothesis so far.
fn rounds_lines(
    out: &mut Vec<String>,
    what: &str,
    rounds: &[matflow_render::evidence::CompletionChoice],
) {
    for (k, r) in rounds.iter().enumerate() {
        let best = (0..r.scores.len())
            .max_by(|&a, &b| {
                r.scores[a]
                    .psnr_differing
                    .total_cmp(&r.scores[b].psnr_differing)
            })
            .unwrap_or(0);
        out.push(format!(
            "  {what}, round {}: {} of {} tested; best {} ({:.2} dB where they differ, {:.2} dB without it)",
            k + 1,
            r.scores[r.chosen].name,
            r.scores.len(),
            r.scores[best].name,
            r.scores[best].psnr_differing,
            r.scores[0].psnr_differing
        ));
    }
}

/// The window search in words: each round's best and the room taken.
fn windows_lines(out: &mut Vec<String>, w: &matflow_render::evidence::WindowChoice) {
    rounds_lines(out, "windows", &w.rounds);
    if let Some(t) = &w.against_typical {
        out.push(format!(
            "  windows found {:.2} dB, typical windows {:.2} dB where they differ: {} taken",
            t.scores[0].psnr_differing,
            t.scores.get(1).map_or(f64::NAN, |s| s.psnr_differing),
            if w.typical {
                "typical windows"
            } else {
                "the windows found"
            },
        ));
    }
}

/// The wall search in words: each round's best and what was taken.
fn walls_lines(out: &mut Vec<String>, w: &matflow_render::evidence::WallChoice) {
    rounds_lines(out, "walls", &w.rounds);
    if let (Some(t), Some(h)) = (&w.height_test, w.height) {
        out.push(format!(
            "  walls' height: {h:.2} camera heights ({:.2} dB where the heights tried last differ)",
            t.scores
                .iter()
                .map(|s| s.psnr_differing)
                .fold(f64::NEG_INFINITY, f64::max)
        ));
    }
    match &w.against_start {
        Some(t) => out.push(format!(
            "  walls found {:.2} dB, {} {:.2} dB where they differ: {} taken",
            t.scores.get(1).map_or(f64::NAN, |s| s.psnr_differing),
            t.scores[0].name,
            t.scores[0].psnr_differing,
            if w.kept_start {
                t.scores[0].name.as_str()
            } else {
                "the walls found"
            },
        )),
        None => out.push("  walls: none found".to_string()),
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
    })
}

/// The file in which a bundle declares the completion that reproduces its
/// own geometry (`{"complete": "none", "why": ...}`): `matflow synth`
/// writes it, since its scenes are their depth mesh and nothing else, and
/// `matflow invert` the one it recovered its maps with.
pub const GEOMETRY_FILE: &str = "geometry.json";

/// The completion `bundle` declares for itself in [`GEOMETRY_FILE`], if
/// it declares one (a bad file is an error naming it).
pub fn declared_completion(bundle: &Path) -> Result<Option<CompleteMode>, NodeError> {
    let path = bundle.join(GEOMETRY_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).context(|| format!("reading {}", path.display())),
    };
    let v: serde_json::Value =
        serde_json::from_str(&text).context(|| format!("{}: not JSON", path.display()))?;
    let name = v
        .get("complete")
        .and_then(|c| c.as_str())
        .ok_or_else(|| crate::err(format!("{}: no string field `complete`", path.display())))?;
    let mode = name
        .parse::<CompleteMode>()
        .map_err(|e| crate::err(format!("{}: complete: {e}", path.display())))?;
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
) -> Result<CompletionDecision, NodeError> {
    let bundle = Bundle::open(bundle_dir).node_err()?;
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
    let depth = bundle.load_depth().node_err()?;
    let maps = bundle.load_materials(materials).node_err()?;
    let env = EnvMap::new(&io::read_envmap(light).node_err()?)
        .context(|| format!("{}", light.display()))?;
    let hyps = hypotheses();
    let lamps = own_lamps(bundle_dir, materials, light)?;
    let opts = matflow_render::evidence::EvidenceOptions {
        filter: how.filter,
        max_depth: how.max_depth,
        lamps,
        ..Default::default()
    };
    let choice = matflow_render::evidence::choose_completion(
        &depth, &maps, &env, how.mesh, &photo, &hyps, &opts,
    )
    .context(|| {
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
        .context(|| format!("{}: placing the room's windows", bundle_dir.display()))?,
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
            .context(|| format!("{}: testing unseen walls", bundle_dir.display()))?
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
                light_name(bundle_dir, light)
            } else {
                format!(
                    "{} and {} lamp(s)",
                    light_name(bundle_dir, light),
                    opts.lamps.len()
                )
            },
            materials,
            windows,
            walls,
        }),
    })
}

/// The maps' own lamps, which light the photo too under their own envmap
/// (none under another light).
fn own_lamps(
    bundle_dir: &Path,
    materials: MaterialSource,
    light: &Path,
) -> Result<Vec<matflow_scene::lamps::Lamp>, NodeError> {
    let own = materials
        .folder()
        .is_some_and(|f| light.parent() == Some(&bundle_dir.join(f)));
    Ok(match materials.folder().filter(|_| own) {
        Some(f) => matflow_scene::lamps::bundle_lamps(bundle_dir, f)
            .node_err()?
            .unwrap_or_default(),
        None => Vec::new(),
    })
}

/// An envmap as the evidence names it: inside the bundle, by its path
/// there (`best_results/envmap.hdr`); else by its file name. Never as the
/// command spelled it: a stage's outputs must not depend on how its
/// inputs' paths were written.
fn light_name(bundle_dir: &Path, light: &Path) -> String {
    match light.strip_prefix(bundle_dir) {
        Ok(inside) => inside.display().to_string(),
        Err(_) => light.file_name().map_or_else(
            || light.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        ),
    }
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
) -> Result<CompletionDecision, NodeError> {
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
) -> Result<CompletionDecision, NodeError> {
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
            |name| name.parse::<CompleteMode>().map(Some),
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

/// The filter a render uses: the one asked for; else, for the maps
/// `matflow invert` wrote, the one it fitted them with (`summary.json`'s
/// `options.pixel_filter`); else Mitsuba's Gaussian. Also says why.
pub fn render_filter(
    bundle: &Path,
    materials: MaterialSource,
    asked: Option<PixelFilter>,
) -> Result<(PixelFilter, &'static str), NodeError> {
    from_invert(
        bundle,
        materials,
        asked,
        "pixel_filter",
        "the one matflow invert fitted these maps with",
        |name| name.parse::<PixelFilter>().map_err(|e| e.to_string()),
    )
}
