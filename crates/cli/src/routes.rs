//! Command-line arguments built from the inverse route registry
//! ([`matflow_inverse::routes`]): `--env-route` and `--mat-route` offer
//! every registered route (with its doc in `--help`), and every route
//! option is a flag `--{env,mat}-ROUTE-OPTION`. Nothing here names a
//! route.

use clap::builder::{PossibleValue, PossibleValuesParser};
use clap::{Arg, ArgMatches, Args, Command, FromArgMatches};
use matflow_inverse::routes::{
    self, all_options, Chosen, EnvRoute, MatRoute, RouteOption, Side, ENV_ROUTES, MAT_ROUTES,
};

/// The chosen envmap and material routes with their option values.
#[derive(Clone, Debug)]
pub struct RouteArgs {
    pub env: Chosen<dyn EnvRoute>,
    pub mat: Chosen<dyn MatRoute>,
}

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}

/// A value parser offering the registered routes of one side.
pub fn route_parser(side: Side) -> PossibleValuesParser {
    let values: Vec<PossibleValue> = match side {
        Side::Env => ENV_ROUTES
            .iter()
            .map(|e| PossibleValue::new(e.name).help(e.doc))
            .collect(),
        Side::Mat => MAT_ROUTES
            .iter()
            .map(|e| PossibleValue::new(e.name).help(e.doc))
            .collect(),
    };
    PossibleValuesParser::new(values)
}

/// Names of the registered routes of one side, default first.
pub fn route_names(side: Side) -> Vec<&'static str> {
    match side {
        Side::Env => ENV_ROUTES.iter().map(|e| e.name).collect(),
        Side::Mat => MAT_ROUTES.iter().map(|e| e.name).collect(),
    }
}

fn flag(side: Side) -> &'static str {
    match side {
        Side::Env => "env_route",
        Side::Mat => "mat_route",
    }
}

fn option_help(route: &str, o: &RouteOption) -> String {
    let default = o
        .default
        .map(|d| format!("; default {d}"))
        .unwrap_or_default();
    format!(
        "Route `{route}`: {} ({}{default})",
        o.doc,
        o.kind.describe()
    )
}

/// A route error as the command line words it (flags, not parameters).
fn invalid(e: routes::RouteError) -> clap::Error {
    use clap::error::ErrorKind;
    match e {
        routes::RouteError::NotChosen {
            side,
            option,
            route,
            chosen,
        } => clap::Error::raw(
            ErrorKind::ArgumentConflict,
            format!(
                "--{} applies to --{side}-route {route}, but the route is {chosen}\n",
                option.replace('_', "-")
            ),
        ),
        e => clap::Error::raw(ErrorKind::ValueValidation, format!("{e}\n")),
    }
}

impl FromArgMatches for RouteArgs {
    fn from_arg_matches(m: &ArgMatches) -> Result<Self, clap::Error> {
        let name = |side| {
            m.get_one::<String>(flag(side))
                .cloned()
                .unwrap_or_else(|| route_names(side)[0].to_string())
        };
        let given = |q: &str| m.get_one::<f64>(q).copied();
        Ok(RouteArgs {
            env: routes::env_route_given(&name(Side::Env), &given).map_err(invalid)?,
            mat: routes::mat_route_given(&name(Side::Mat), &given).map_err(invalid)?,
        })
    }
    fn update_from_arg_matches(&mut self, m: &ArgMatches) -> Result<(), clap::Error> {
        *self = RouteArgs::from_arg_matches(m)?;
        Ok(())
    }
}

impl Args for RouteArgs {
    fn augment_args(mut cmd: Command) -> Command {
        for (side, what) in [(Side::Env, "Envmap route"), (Side::Mat, "Material route")] {
            cmd = cmd.arg(
                Arg::new(flag(side))
                    .long(leak(flag(side).replace('_', "-")))
                    .value_parser(route_parser(side))
                    .default_value(route_names(side)[0])
                    .help(what),
            );
            for (q, route, o) in all_options(side) {
                let long = leak(q.replace('_', "-"));
                cmd = cmd.arg(
                    Arg::new(leak(q))
                        .long(long)
                        .value_name("X")
                        .value_parser(clap::value_parser!(f64))
                        .help(option_help(route, o)),
                );
            }
        }
        cmd
    }
    fn augment_args_for_update(cmd: Command) -> Command {
        RouteArgs::augment_args(cmd)
    }
}
