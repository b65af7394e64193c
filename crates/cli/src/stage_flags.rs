//! Command-line flags declared by a node kind's parameter specs: a
//! command that does what a stage does takes that stage's parameters as
//! flags (`budget_seconds` → `--budget-seconds`), with the kind's doc,
//! unit, default and range, and hands them back as the same validated
//! [`Params`] the stage would get. Nothing here names a parameter; the
//! kinds declare them once.

use clap::builder::PossibleValuesParser;
use clap::error::ErrorKind;
use clap::{Arg, ArgAction, ArgMatches, Command};
use matflow_engine::node::Params;
use matflow_engine::value::parse_override;
use matflow_engine::{ParamSpec, ParamType, Value};

/// The spec of parameter `name` of node kind `kind`. Both are the code's
/// own constants: a missing one is a programming error that the tests of
/// every command using it catch.
pub fn spec(kind: &str, name: &str) -> &'static ParamSpec {
    let node = REGISTRY
        .get_or_init(matflow_nodes::registry)
        .get(kind)
        .unwrap_or_else(|| panic!("no node kind {kind}"));
    let info: &'static matflow_engine::NodeInfo = node.info();
    info.params
        .iter()
        .find(|p| p.name == name)
        .unwrap_or_else(|| panic!("node kind {kind} has no parameter {name}"))
}

static REGISTRY: std::sync::OnceLock<matflow_engine::Registry> = std::sync::OnceLock::new();

fn flag(name: &str) -> String {
    name.replace('_', "-")
}

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}

/// The help of a parameter as a flag: its doc with a capital, its unit.
fn help(p: &ParamSpec) -> String {
    let mut doc = p.doc.to_string();
    if let Some(c) = doc.get(..1) {
        doc.replace_range(..1, &c.to_uppercase());
    }
    match p.unit {
        "" => format!("{doc} ({})", p.ty.describe()),
        u => format!("{doc} ({}; {u})", p.ty.describe()),
    }
}

/// Adds one flag per named parameter of `kind` to `cmd`. A boolean whose
/// default is false is a switch (`--trust-rm`); a choice offers its
/// words; a number is checked against the kind's range when parsed; a
/// parameter without a default is required; the file a stage writes
/// (`output`) is `--out`.
pub fn augment(cmd: Command, kind: &str, names: &[&str]) -> Command {
    augment_with(cmd, kind, names, &[])
}

/// [`augment`], the parameters in `positional` taken in that order as
/// positional arguments instead of flags.
pub fn augment_with(mut cmd: Command, kind: &str, names: &[&str], positional: &[&str]) -> Command {
    for name in names {
        let p = spec(kind, name);
        let mut a = Arg::new(p.name).help(help(p));
        a = match (&p.ty, p.name) {
            _ if positional.contains(name) => a
                .index(positional.iter().position(|n| n == name).unwrap_or(0) + 1)
                .value_name(leak(p.name.to_uppercase())),
            (ParamType::OutPath, "output") => a.long("out").alias("output"),
            _ => a.long(leak(flag(p.name))),
        };
        if p.default.is_none() {
            a = a.required(true);
        }
        a = match (&p.ty, p.default) {
            (ParamType::Bool, Some("false")) => a.action(ArgAction::SetTrue),
            (ParamType::Choice(words), _) => a
                .value_name(leak(p.name.to_uppercase()))
                .value_parser(PossibleValuesParser::new(*words)),
            _ => a.value_name(leak(p.name.to_uppercase())),
        };
        if let Some(d) = p
            .default
            .filter(|d| *d != "~" && !matches!(p.ty, ParamType::Bool))
        {
            a = a.default_value(d);
        }
        cmd = cmd.arg(a);
    }
    cmd
}

/// The named parameters of `kind` as the stage would get them: each value
/// parsed as `--set` parses it, checked against the kind's type and
/// range, defaults filled in. An error names the flag and what it takes.
pub fn params(m: &ArgMatches, kind: &str, names: &[&str]) -> Result<Params, clap::Error> {
    let mut out = Params::default();
    for name in names {
        let p = spec(kind, name);
        let v = match (&p.ty, p.default) {
            (ParamType::Bool, Some("false")) => Value::Bool(m.get_flag(p.name)),
            _ => match m.get_one::<String>(p.name) {
                None => Value::Null,
                Some(text) => {
                    let bad = || {
                        clap::Error::raw(
                            ErrorKind::ValueValidation,
                            format!(
                                "invalid value '{text}' for '--{}': expected {}\n",
                                flag(p.name),
                                p.ty.describe()
                            ),
                        )
                    };
                    let v = parse_override(text).map_err(|_| bad())?;
                    p.ty.normalize(&v).ok_or_else(bad)?
                }
            },
        };
        out.0.insert(p.name.to_string(), v);
    }
    Ok(out)
}

/// A command that runs one node kind on its own: its flags are the
/// kind's parameters ([`augment`]), and it runs as a one-stage pipeline
/// ([`run_stage`]), so the command and a pipeline stage with the same
/// parameters are one action: the same key, cached alike.
pub trait StageKind {
    /// The node kind.
    const KIND: &'static str;
    /// Parameters the command does not take as flags (it sets them
    /// itself, e.g. from a file).
    const SKIP: &'static [&'static str] = &[];
    /// Parameters taken as positional arguments, in this order.
    const POSITIONAL: &'static [&'static str] = &[];
    /// Command-line touches on the generated flags (a flag given alone
    /// meaning one of its words).
    fn adjust(cmd: Command) -> Command {
        cmd
    }
    /// Checks across the flags, worded as flags (the kind checks them
    /// again, worded as parameters).
    fn validate(_params: &Params) -> Result<(), clap::Error> {
        Ok(())
    }
}

/// The flags of a [`StageKind`]: every parameter of its kind, as the
/// stage's validated parameters.
pub struct StageFlags<K: StageKind>(pub Params, std::marker::PhantomData<K>);

impl<K: StageKind> Clone for StageFlags<K> {
    fn clone(&self) -> Self {
        StageFlags(self.0.clone(), std::marker::PhantomData)
    }
}

impl<K: StageKind> clap::FromArgMatches for StageFlags<K> {
    fn from_arg_matches(m: &ArgMatches) -> Result<Self, clap::Error> {
        let p = params(m, K::KIND, &flags_of::<K>())?;
        K::validate(&p)?;
        Ok(StageFlags(p, std::marker::PhantomData))
    }
    fn update_from_arg_matches(&mut self, m: &ArgMatches) -> Result<(), clap::Error> {
        *self = Self::from_arg_matches(m)?;
        Ok(())
    }
}

impl<K: StageKind> clap::Args for StageFlags<K> {
    fn augment_args(cmd: Command) -> Command {
        K::adjust(augment_with(cmd, K::KIND, &flags_of::<K>(), K::POSITIONAL))
    }
    fn augment_args_for_update(cmd: Command) -> Command {
        Self::augment_args(cmd)
    }
}

/// The parameters a [`StageKind`]'s command takes as flags.
fn flags_of<K: StageKind>() -> Vec<&'static str> {
    names(K::KIND)
        .into_iter()
        .filter(|n| !K::SKIP.contains(n))
        .collect()
}

/// The parameter names of node kind `kind`, in its order.
pub fn names(kind: &str) -> Vec<&'static str> {
    REGISTRY
        .get_or_init(matflow_nodes::registry)
        .get(kind)
        .unwrap_or_else(|| panic!("no node kind {kind}"))
        .params()
        .iter()
        .map(|p| p.name)
        .collect()
}

/// Runs node kind `kind` with `params` as a one-stage pipeline (stage
/// `kind`), through the engine and its cache as `matflow run` runs a
/// stage: relative paths resolve against the current folder. Returns the
/// run's report, printed; a failed stage is an error.
pub fn run_stage(
    kind: &str,
    params: &Params,
    how: &StageRun,
) -> anyhow::Result<matflow_engine::Report> {
    use matflow_engine::spec::{self, Override};
    let reg = matflow_nodes::registry();
    let overrides: Vec<Override> = params
        .0
        .iter()
        .filter(|(_, v)| !matches!(v, Value::Null))
        .map(|(name, v)| Override {
            stage: kind.into(),
            param: name.clone(),
            value: v.clone(),
            text: format!("--{}", flag(name)),
        })
        .collect();
    let text =
        format!("pipeline: {kind}\noutputs: [{kind}]\nstages:\n  {kind}:\n    kind: {kind}\n");
    let here = std::path::PathBuf::from(format!("(matflow {kind})"));
    let p = spec::parse(&text, &here, &reg, &overrides)
        .map_err(|e| anyhow::anyhow!("{}", e.message))?;
    if !how.allow_expensive {
        crate::run::refuse_if_expensive(&here, &spec::estimate_seconds(&p, &reg))?;
    }
    let label = match params.get("bundle") {
        Value::Str(b) => b.clone(),
        _ => kind.to_string(),
    };
    crate::run::execute(
        &p,
        reg,
        &crate::run::Execution {
            cache: how.cache.as_deref(),
            remote: &crate::cluster::RemoteArgs::default(),
            parallel: 1,
            quiet: how.quiet,
            report: how.report.as_deref(),
            label: &label,
        },
    )
}

/// How a [`StageKind`]'s command runs: the cache, the report, the bars.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct StageRun {
    /// Cache folder (as for `run`).
    #[arg(long)]
    pub cache: Option<std::path::PathBuf>,
    /// Write the run's JSON report here.
    #[arg(long)]
    pub report: Option<std::path::PathBuf>,
    /// No progress bars.
    #[arg(long)]
    pub quiet: bool,
    /// Run even when estimated to take more than an hour (on the
    /// reference 2-core machine).
    #[arg(long)]
    pub allow_expensive: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cmd() -> Command {
        augment(
            Command::new("t"),
            "material_opt",
            &["budget_seconds", "trust_rm", "albedo_level", "loops"],
        )
    }

    #[test]
    fn flags_take_the_kinds_defaults_ranges_and_words() {
        let m = cmd().try_get_matches_from(["t"]).unwrap();
        let p = params(
            &m,
            "material_opt",
            &["budget_seconds", "trust_rm", "albedo_level", "loops"],
        )
        .unwrap();
        let kind_default = |n| parse_override(spec("material_opt", n).default.unwrap()).unwrap();
        assert_eq!(
            p.f64("budget_seconds"),
            kind_default("budget_seconds").as_f64().unwrap()
        );
        assert!(!p.bool("trust_rm"));
        assert_eq!(p.str("albedo_level"), "pred");
        assert!(!p.is_set("loops"));

        let m = cmd()
            .try_get_matches_from(["t", "--budget-seconds", "5", "--trust-rm", "--loops", "3"])
            .unwrap();
        let p = params(&m, "material_opt", &["budget_seconds", "trust_rm", "loops"]).unwrap();
        assert_eq!(p.f64("budget_seconds"), 5.0);
        assert!(p.bool("trust_rm"));
        assert_eq!(p.opt_i64("loops"), Some(3));

        // Out of the kind's range, or not a number: refused by flag name.
        for bad in ["0.5", "x", "1e9"] {
            let m = cmd()
                .try_get_matches_from(["t", "--budget-seconds", bad])
                .unwrap();
            let e = params(&m, "material_opt", &["budget_seconds"]).unwrap_err();
            assert!(e.to_string().contains("--budget-seconds"), "{e}");
            assert!(e.to_string().contains("a number in [1, 86400]"), "{e}");
        }
        assert!(cmd()
            .try_get_matches_from(["t", "--albedo-level", "brighter"])
            .is_err());
    }
}
