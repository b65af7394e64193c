//! `matflow invert`: the `bundle_invert` kind on its own, as a one-stage
//! pipeline: recover envmap and materials from a bundle and write the
//! reference's `best_results/` layout plus `summary.json`. Its flags are
//! the kind's parameters; the same stage in a pipeline is the same action
//! (same key, cached alike).

use anyhow::Result;
use clap::Args;

use crate::stage_flags::{StageFlags, StageKind, StageRun};

/// `matflow invert`: the `bundle_invert` kind.
pub struct InvertCmd;

impl StageKind for InvertCmd {
    const KIND: &'static str = "bundle_invert";
    /// The routes offered with their docs.
    fn adjust(cmd: clap::Command) -> clap::Command {
        use crate::routes::route_parser;
        use matflow_inverse::routes::Side;
        cmd.mut_arg("env_route", |a| a.value_parser(route_parser(Side::Env)))
            .mut_arg("mat_route", |a| a.value_parser(route_parser(Side::Mat)))
    }
    /// An option of a route that is not chosen is refused by flag.
    fn validate(p: &matflow_engine::node::Params) -> Result<(), clap::Error> {
        use matflow_inverse::routes::{env_route_given, mat_route_given, RouteError};
        let given = |q: &str| p.opt_f64(q);
        let checked = env_route_given(p.str("env_route"), &given)
            .map(|_| ())
            .and_then(|_| mat_route_given(p.str("mat_route"), &given).map(|_| ()));
        checked.map_err(|e| match e {
            RouteError::NotChosen {
                side,
                option,
                route,
                chosen,
            } => clap::Error::raw(
                clap::error::ErrorKind::ArgumentConflict,
                format!(
                    "--{} applies to --{side}-route {route}, but the route is {chosen}\n",
                    option.replace('_', "-")
                ),
            ),
            e => clap::Error::raw(clap::error::ErrorKind::ValueValidation, format!("{e}\n")),
        })
    }
}

#[derive(Args, Clone)]
pub struct InvertArgs {
    #[command(flatten)]
    pub stage: StageFlags<InvertCmd>,
    #[command(flatten)]
    pub run: StageRun,
}

pub fn invert_cmd(a: InvertArgs) -> Result<()> {
    let report = crate::stage_flags::run_stage(InvertCmd::KIND, &a.stage.0, &a.run)?;
    if let Some(b) = report.peak_memory_bytes {
        outln!("peak memory {:.0} MB", b as f64 / 1e6);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        a: InvertArgs,
    }

    fn cli(extra: &[&str]) -> matflow_engine::node::Params {
        let mut args = vec!["invert", "--bundle", "b", "--out", "o"];
        args.extend_from_slice(extra);
        Cli::try_parse_from(args).unwrap().a.stage.0
    }

    /// The `material_opt` stage's parameters as the engine fills them:
    /// the kind's defaults, then `given` (YAML text, as a pipeline says).
    fn stage(given: &[(&str, &str)]) -> matflow_engine::node::Params {
        use matflow_engine::value::parse_override;
        let reg = matflow_nodes::registry();
        let node = reg.get("material_opt").unwrap();
        let mut p = matflow_engine::node::Params::default();
        for s in node.params() {
            let text = given
                .iter()
                .find(|(n, _)| *n == s.name)
                .map(|(_, v)| *v)
                .or(s.default)
                .unwrap_or("~");
            let v = parse_override(text).unwrap();
            p.0.insert(s.name.into(), s.ty.normalize(&v).unwrap_or(v));
        }
        p
    }

    /// What `invert` and a `material_opt` stage share they read the same
    /// way: the same defaults, and the same values for the same words.
    #[test]
    fn invert_and_the_material_stage_read_shared_options_alike() {
        use matflow_inverse::invert::InvertOptions;
        use matflow_nodes::recovery::{budget_options, material_options};
        let read = |p: &matflow_engine::node::Params| {
            material_options(p, budget_options(p, InvertOptions::default()))
        };
        let same = |a: &InvertOptions, b: &InvertOptions| {
            assert_eq!(a.budget_seconds, b.budget_seconds);
            assert_eq!(a.trust_rm, b.trust_rm);
            assert_eq!(a.delta.to_bits(), b.delta.to_bits());
            assert_eq!(a.loops, b.loops);
            assert_eq!(a.level_from_pred, b.level_from_pred);
            assert_eq!(a.level_band.to_bits(), b.level_band.to_bits());
            assert_eq!(a.albedo_structure, b.albedo_structure);
        };
        same(&read(&cli(&[])), &read(&stage(&[])));
        same(
            &read(&cli(&[
                "--budget-seconds",
                "7.5",
                "--trust-rm",
                "--delta",
                "0.3",
                "--loops",
                "2",
                "--albedo-level",
                "free",
                "--albedo-level-band",
                "0.4",
                "--albedo-structure",
                "photo",
            ])),
            &read(&stage(&[
                ("budget_seconds", "7.5"),
                ("trust_rm", "true"),
                ("delta", "0.3"),
                ("loops", "2"),
                ("albedo_level", "free"),
                ("albedo_level_band", "0.4"),
                ("albedo_structure", "photo"),
            ])),
        );
        // And the defaults are the library's where it has one.
        let d = read(&cli(&[]));
        assert_eq!(d.level_band, matflow_inverse::invert::LEVEL_BAND);
        assert!(d.level_from_pred);
        assert!(d.albedo_structure.is_none());
    }
}
