//! Inverse routes as plug-ins: how an envmap stage and a material stage
//! fit their parameters.
//!
//! A route is one file here. It declares its name, a one-line doc and its
//! options ([`RouteOption`]), prices its work for the budget plan (its own
//! cost constants), and fits. [`invert`](crate::invert::invert) only
//! orchestrates: trace, alternate envmap and material stages, re-render.
//!
//! Adding a route: write the file (an [`Entry`] constant and a type
//! implementing [`EnvRoute`] or [`MatRoute`]), then add one line to
//! [`ENV_ROUTES`] or [`MAT_ROUTES`]. The CLI (`matflow invert
//! --env-route/--mat-route` and one flag per option), the pipeline schema
//! (`matflow kinds`: the `env_route`/`mat_route` choices and one parameter
//! per option) and `matflow-bench invert` are built from these lists.

use std::collections::BTreeMap;
use std::fmt;

use glam::Vec3;
use matflow_render::Material;

use crate::envfit::{EnvTransport, FitTrace};
use crate::loss::Target;
use crate::matfit::{MatFit, Parts};
use crate::tables::PixelTable;

pub mod env_mlp;
pub mod env_texel;
pub mod mat_mlp;
pub mod mat_pixel;
pub mod mat_solve;

/// The envmap routes; the first is the default.
pub const ENV_ROUTES: &[EnvEntry] = &[env_texel::ROUTE, env_mlp::ROUTE];

/// The material routes; the first is the default.
pub const MAT_ROUTES: &[MatEntry] = &[mat_solve::ROUTE, mat_pixel::ROUTE, mat_mlp::ROUTE];

/// Names of [`ENV_ROUTES`], in order (for schemas built at compile time).
pub const ENV_ROUTE_NAMES: [&str; ENV_ROUTES.len()] = {
    let mut a = [""; ENV_ROUTES.len()];
    let mut i = 0;
    while i < a.len() {
        a[i] = ENV_ROUTES[i].name;
        i += 1;
    }
    a
};

/// Names of [`MAT_ROUTES`], in order.
pub const MAT_ROUTE_NAMES: [&str; MAT_ROUTES.len()] = {
    let mut a = [""; MAT_ROUTES.len()];
    let mut i = 0;
    while i < a.len() {
        a[i] = MAT_ROUTES[i].name;
        i += 1;
    }
    a
};

/// What an option accepts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OptionKind {
    Int { min: i64, max: i64 },
    Float { min: f64, max: f64 },
}

impl OptionKind {
    pub fn describe(&self) -> String {
        match self {
            OptionKind::Int { min, max } => format!("an integer in [{min}, {max}]"),
            OptionKind::Float { min, max } => format!("a number in [{min}, {max}]"),
        }
    }
}

/// One option of a route.
#[derive(Clone, Copy, Debug)]
pub struct RouteOption {
    pub name: &'static str,
    pub kind: OptionKind,
    /// The default as text; `None`: chosen by the route (from the budget
    /// or the other options), as [`RouteOption::doc`] says.
    pub default: Option<&'static str>,
    pub doc: &'static str,
}

/// The options of a positional-encoding MLP route (width, depth,
/// octaves, learning rate); the defaults and the rate's doc are the
/// route's.
pub(crate) const fn network_options(
    width: &'static str,
    width_doc: &'static str,
    lr: &'static str,
    lr_doc: &'static str,
) -> [RouteOption; 4] {
    [
        RouteOption {
            name: "width",
            kind: OptionKind::Int { min: 4, max: 1024 },
            default: Some(width),
            doc: width_doc,
        },
        RouteOption {
            name: "depth",
            kind: OptionKind::Int { min: 2, max: 16 },
            default: Some("4"),
            doc: "hidden layers (the reference: 4)",
        },
        RouteOption {
            name: "octaves",
            kind: OptionKind::Int { min: 0, max: 16 },
            default: Some("2"),
            doc: "positional-encoding octaves (the reference: 2)",
        },
        RouteOption {
            name: "lr",
            kind: OptionKind::Float {
                min: 1e-7,
                max: 1.0,
            },
            default: Some(lr),
            doc: lr_doc,
        },
    ]
}

/// A network route's settings: width, depth, octaves and learning rate,
/// each set or the route's default.
pub(crate) struct Network {
    pub width: usize,
    pub depth: usize,
    pub octaves: usize,
    pub lr: f32,
}

impl Network {
    pub fn of(s: &Settings, options: &[RouteOption]) -> Network {
        Network {
            width: s.usize_or(options, "width", 0),
            depth: s.usize_or(options, "depth", 0),
            octaves: s.usize_or(options, "octaves", 0),
            lr: s.f32_or(options, "lr", 0.0),
        }
    }
}

/// A route's registration: what the CLI, the pipeline schema and the
/// benchmarks know it by, and how to build it from its settings.
pub struct Entry<R: ?Sized + 'static> {
    pub name: &'static str,
    pub doc: &'static str,
    pub options: &'static [RouteOption],
    /// Builds the route from validated settings (every option either set
    /// in range or absent).
    pub build: fn(&Settings) -> Box<R>,
}

pub type EnvEntry = Entry<dyn EnvRoute>;
pub type MatEntry = Entry<dyn MatRoute>;

/// Which side of the alternation a route fits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    Env,
    Mat,
}

impl Side {
    pub fn prefix(self) -> &'static str {
        match self {
            Side::Env => "env",
            Side::Mat => "mat",
        }
    }
}

/// The name an option goes by outside its route: `env_mlp_width` in a
/// pipeline, `--env-mlp-width` on the command line.
pub fn qualified_name(side: Side, route: &str, option: &str) -> String {
    format!("{}_{route}_{option}", side.prefix())
}

/// Every route option of one side with its qualified name.
pub fn all_options(side: Side) -> Vec<(String, &'static str, &'static RouteOption)> {
    let mut v = Vec::new();
    let entries: Vec<(&'static str, &'static [RouteOption])> = match side {
        Side::Env => ENV_ROUTES.iter().map(|e| (e.name, e.options)).collect(),
        Side::Mat => MAT_ROUTES.iter().map(|e| (e.name, e.options)).collect(),
    };
    for (route, opts) in entries {
        for o in opts {
            v.push((qualified_name(side, route, o.name), route, o));
        }
    }
    v
}

/// A bad route name or option value.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RouteError {
    #[error("unknown {side} route `{name}`; the routes are {known}")]
    UnknownRoute {
        side: &'static str,
        name: String,
        known: String,
    },
    #[error("route `{route}` has no option `{option}`; its options are {known}")]
    UnknownOption {
        route: &'static str,
        option: String,
        known: String,
    },
    #[error("`{option}` is an option of {side}_route `{route}`, but the route is `{chosen}`")]
    NotChosen {
        side: &'static str,
        /// The qualified name (`mat_mlp_width`).
        option: String,
        route: &'static str,
        chosen: String,
    },
    #[error("route `{route}`, option `{option}`: expected {expected}, got {got}")]
    BadValue {
        route: &'static str,
        option: &'static str,
        expected: String,
        got: String,
    },
}

/// A route's option values, checked against its [`RouteOption`]s.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Settings(BTreeMap<&'static str, f64>);

impl Settings {
    /// Checks `values` (option name, value) against `options`: known
    /// names, numbers in range, integers where an integer is asked for.
    pub fn check(
        route: &'static str,
        options: &'static [RouteOption],
        values: &[(String, f64)],
    ) -> Result<Settings, RouteError> {
        let mut m = BTreeMap::new();
        for (name, v) in values {
            let Some(o) = options.iter().find(|o| o.name == name) else {
                return Err(RouteError::UnknownOption {
                    route,
                    option: name.clone(),
                    known: known(options.iter().map(|o| o.name)),
                });
            };
            let ok = match o.kind {
                OptionKind::Int { min, max } => {
                    v.fract() == 0.0 && *v >= min as f64 && *v <= max as f64
                }
                OptionKind::Float { min, max } => v.is_finite() && *v >= min && *v <= max,
            };
            if !ok {
                return Err(RouteError::BadValue {
                    route,
                    option: o.name,
                    expected: o.kind.describe(),
                    got: v.to_string(),
                });
            }
            m.insert(o.name, *v);
        }
        Ok(Settings(m))
    }

    /// The value set for `name`, if any.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.0.get(name).copied()
    }

    /// The value set for `name`, or the option's declared default.
    fn value(&self, options: &[RouteOption], name: &str) -> Option<f64> {
        self.get(name).or_else(|| {
            options
                .iter()
                .find(|o| o.name == name)
                .and_then(|o| o.default)
                .and_then(|d| d.parse().ok())
        })
    }

    pub fn f32_or(&self, options: &[RouteOption], name: &str, fallback: f32) -> f32 {
        self.value(options, name).map_or(fallback, |v| v as f32)
    }

    pub fn usize_or(&self, options: &[RouteOption], name: &str, fallback: usize) -> usize {
        self.value(options, name).map_or(fallback, |v| v as usize)
    }

    pub fn iter(&self) -> impl Iterator<Item = (&'static str, f64)> + '_ {
        self.0.iter().map(|(k, v)| (*k, *v))
    }
}

fn known<'a>(names: impl Iterator<Item = &'a str>) -> String {
    let v: Vec<String> = names.map(|n| format!("`{n}`")).collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

/// A chosen route and its settings.
pub struct Chosen<R: ?Sized + 'static> {
    pub entry: &'static Entry<R>,
    pub settings: Settings,
}

impl<R: ?Sized> Clone for Chosen<R> {
    fn clone(&self) -> Self {
        Chosen {
            entry: self.entry,
            settings: self.settings.clone(),
        }
    }
}

impl<R: ?Sized> fmt::Debug for Chosen<R> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.entry.name)?;
        for (k, v) in self.settings.iter() {
            write!(f, " {k}={v}")?;
        }
        Ok(())
    }
}

impl<R: ?Sized> PartialEq for Chosen<R> {
    fn eq(&self, o: &Self) -> bool {
        self.entry.name == o.entry.name && self.settings == o.settings
    }
}

impl<R: ?Sized> Chosen<R> {
    pub fn name(&self) -> &'static str {
        self.entry.name
    }
    pub fn build(&self) -> Box<R> {
        (self.entry.build)(&self.settings)
    }
}

/// The chosen route's option values among what a front end was given by
/// qualified name (`given("mat_mlp_width")`); a value given for an option
/// of another route is an error (it would silently do nothing).
fn given_values(
    side: Side,
    chosen: &str,
    given: &dyn Fn(&str) -> Option<f64>,
) -> Result<Vec<(String, f64)>, RouteError> {
    let mut v = Vec::new();
    for (q, route, o) in all_options(side) {
        let Some(x) = given(&q) else {
            continue;
        };
        if route != chosen {
            return Err(RouteError::NotChosen {
                side: side.prefix(),
                option: q,
                route,
                chosen: chosen.to_string(),
            });
        }
        v.push((o.name.to_string(), x));
    }
    Ok(v)
}

/// The envmap route `name` with its options taken from what a front end
/// was given by qualified name (see [`qualified_name`]).
pub fn env_route_given(
    name: &str,
    given: &dyn Fn(&str) -> Option<f64>,
) -> Result<Chosen<dyn EnvRoute>, RouteError> {
    env_route(name, &given_values(Side::Env, name, given)?)
}

/// The material route `name` with its options given by qualified name.
pub fn mat_route_given(
    name: &str,
    given: &dyn Fn(&str) -> Option<f64>,
) -> Result<Chosen<dyn MatRoute>, RouteError> {
    mat_route(name, &given_values(Side::Mat, name, given)?)
}

fn choose<R: ?Sized>(
    side: Side,
    entries: &'static [Entry<R>],
    name: &str,
    values: &[(String, f64)],
) -> Result<Chosen<R>, RouteError> {
    let entry =
        entries
            .iter()
            .find(|e| e.name == name)
            .ok_or_else(|| RouteError::UnknownRoute {
                side: side.prefix(),
                name: name.to_string(),
                known: known(entries.iter().map(|e| e.name)),
            })?;
    Ok(Chosen {
        entry,
        settings: Settings::check(entry.name, entry.options, values)?,
    })
}

/// The envmap route called `name` with option values (by unqualified
/// option name).
pub fn env_route(name: &str, values: &[(String, f64)]) -> Result<Chosen<dyn EnvRoute>, RouteError> {
    choose(Side::Env, ENV_ROUTES, name, values)
}

/// The material route called `name` with option values.
pub fn mat_route(name: &str, values: &[(String, f64)]) -> Result<Chosen<dyn MatRoute>, RouteError> {
    choose(Side::Mat, MAT_ROUTES, name, values)
}

/// What a route's cost model sees (all counted, none timed): the budget,
/// the image and the seconds the plan has for the loops.
#[derive(Clone, Copy, Debug)]
pub struct PlanInputs {
    pub budget_seconds: f64,
    /// Pixels of the image.
    pub pixels: f64,
    /// Pixels an envmap stage fits (the image, strided).
    pub env_pixels: f64,
    /// Share of pixels whose paths start on a surface (in [0.1, 1]).
    pub surface_fraction: f64,
    /// Seconds of the budget left after the fixed costs.
    pub available: f64,
    /// The budget's default step count for an optimisation stage.
    pub steps: usize,
}

/// What an envmap fit starts from.
#[derive(Clone, Copy, Debug)]
pub struct EnvStart {
    pub width: usize,
    pub height: usize,
    /// The closed-form exposure of a flat envmap for the scout's paths.
    pub exposure: f32,
    pub seed: u64,
    /// Predicted roughness/metallic are trusted (synthetic data).
    pub trust_rm: bool,
}

/// One envmap stage's settings from the orchestration.
#[derive(Clone, Copy, Debug)]
pub struct EnvStage {
    pub steps: usize,
    pub early_stop: bool,
    /// With lamps: the weight of their sparsity prior
    /// ([`crate::envfit::EnvFitOptions::lamp_sparsity`]).
    pub lamp_sparsity: f32,
}

/// An envmap route: how envmap stages are priced and fitted.
pub trait EnvRoute: Send + Sync {
    /// Steps of one envmap stage for this budget.
    fn steps(&self, p: &PlanInputs) -> usize;
    /// Seconds one envmap stage of `steps` steps is planned to take.
    fn stage_seconds(&self, p: &PlanInputs, steps: usize) -> f64;
    /// Whether a given starting envmap can seed it (free texels can; a
    /// network cannot be set to one).
    fn takes_start_envmap(&self) -> bool;
    /// Whether it fits lamps after the envmap's texels
    /// ([`crate::paths::light_len`]).
    fn fits_lamps(&self) -> bool {
        false
    }
    /// A fitter holding the route's state across the stages of one run.
    fn start(&self, s: &EnvStart) -> Box<dyn EnvFitter>;
}

/// The state of an envmap route within one recovery.
pub trait EnvFitter: Send {
    /// Fits the envmap on the frozen transport from `current` (the last
    /// stage's envmap); returns the new envmap and what the stage did.
    fn fit(
        &mut self,
        tr: &EnvTransport,
        target: &Target,
        current: &[Vec3],
        stage: &EnvStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> (Vec<Vec3>, FitTrace);
    /// The orchestration scaled its copy of the envmap by `s` per channel
    /// (a material stage's exposure ratio, or the albedo's level handed to
    /// the light); a route with hidden state follows.
    fn rescale(&mut self, _s: Vec3) {}
}

/// What a material fit starts from.
#[derive(Clone, Debug)]
pub struct MatStart<'a> {
    pub width: usize,
    pub height: usize,
    /// The starting materials (the predictions, R and M replaced for
    /// photos): the consistency anchor.
    pub pred: &'a [Material],
    pub seed: u64,
    pub budget_seconds: f64,
    pub env_width: usize,
    pub env_height: usize,
}

/// One material stage's settings from the orchestration.
#[derive(Clone, Copy, Debug)]
pub struct MatStage {
    pub parts: Parts,
    pub steps: usize,
    /// 0 for the first loop.
    pub loop_index: usize,
    pub delta: f32,
    pub zeta: f32,
    pub early_stop: bool,
    pub rescale: bool,
}

/// A material route: how material stages are scheduled, priced and
/// fitted.
pub trait MatRoute: Send + Sync {
    /// The stages of one loop, fitted in turn (e.g. R+M, then A).
    fn stages(&self) -> &'static [Parts];
    /// Steps of one material stage for this budget.
    fn steps(&self, p: &PlanInputs) -> usize;
    /// Seconds one loop's material stages are planned to take, given the
    /// cost of building (and denoising) the tables once; `warm`: a loop
    /// after the first.
    fn loop_seconds(&self, p: &PlanInputs, tables: f64, steps: usize, warm: bool) -> f64;
    /// A fitter holding the route's state across the stages of one run.
    fn start(&self, s: &MatStart) -> Box<dyn MatFitter>;
}

/// The state of a material route within one recovery.
pub trait MatFitter: Send {
    /// Fits materials on the per-pixel tables from `current`.
    fn fit(
        &mut self,
        tables: &[PixelTable],
        target: &Target,
        pred: &[Material],
        current: &[Material],
        stage: &MatStage,
        progress: &(dyn Fn(usize, f64) + Sync),
    ) -> MatFit;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_options_checked() {
        for names in [&ENV_ROUTE_NAMES[..], &MAT_ROUTE_NAMES[..]] {
            let mut v = names.to_vec();
            v.sort();
            v.dedup();
            assert_eq!(v.len(), names.len());
        }
        assert_eq!(ENV_ROUTE_NAMES[0], "texel");
        assert_eq!(MAT_ROUTE_NAMES[0], "solve");
        assert!(matches!(
            mat_route("nope", &[]),
            Err(RouteError::UnknownRoute { .. })
        ));
        assert!(matches!(
            mat_route("mlp", &[("colour".into(), 1.0)]),
            Err(RouteError::UnknownOption { .. })
        ));
        assert!(matches!(
            mat_route("mlp", &[("width".into(), 2.5)]),
            Err(RouteError::BadValue { .. })
        ));
        assert!(matches!(
            env_route("texel", &[("smooth".into(), f64::NAN)]),
            Err(RouteError::BadValue { .. })
        ));
        let r = mat_route("mlp", &[("width".into(), 16.0)]).unwrap();
        assert_eq!(r.settings.get("width"), Some(16.0));
        // Every declared default parses and lies in range.
        for (side, entries) in [
            (
                Side::Env,
                ENV_ROUTES
                    .iter()
                    .map(|e| (e.name, e.options))
                    .collect::<Vec<_>>(),
            ),
            (
                Side::Mat,
                MAT_ROUTES.iter().map(|e| (e.name, e.options)).collect(),
            ),
        ] {
            for (route, options) in entries {
                for o in options {
                    if let Some(d) = o.default {
                        let v: f64 = d.parse().unwrap();
                        let values = [(o.name.to_string(), v)];
                        let ok = match side {
                            Side::Env => env_route(route, &values).map(|_| ()),
                            Side::Mat => mat_route(route, &values).map(|_| ()),
                        };
                        assert_eq!(ok, Ok(()), "{route}.{}", o.name);
                    }
                }
            }
        }
    }
}
