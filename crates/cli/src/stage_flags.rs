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
/// words; a number is checked against the kind's range when parsed.
pub fn augment(mut cmd: Command, kind: &str, names: &[&str]) -> Command {
    for name in names {
        let p = spec(kind, name);
        let mut a = Arg::new(p.name).long(leak(flag(p.name))).help(help(p));
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
