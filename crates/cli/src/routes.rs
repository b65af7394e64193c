//! The inverse route registry ([`matflow_inverse::routes`]) on the
//! command line: the registered routes of a side as a value parser (with
//! each route's doc in `--help`) and by name. `matflow invert`'s route
//! flags come from the `bundle_invert` kind's parameters, which the
//! registry builds; the benchmarks take routes with these.

use clap::builder::{PossibleValue, PossibleValuesParser};
use matflow_inverse::routes::{Side, ENV_ROUTES, MAT_ROUTES};

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
