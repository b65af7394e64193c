//! The generated references in `docs/reference/`: every command's help as
//! clap renders it, and every node kind as `matflow kinds` prints it. A
//! test (`tests/docs.rs`) fails when a page differs from what the code
//! generates; `MATFLOW_BLESS=1` makes it rewrite the page instead.

use clap::Command;

/// The first line of every generated page.
pub const GENERATED: &str = "<!-- Generated from the code: do not edit. \
`MATFLOW_BLESS=1 cargo test --release --workspace -- reference` rewrites it. -->";

/// Help is rendered at this width whatever the terminal, so that the page
/// does not depend on who generated it.
const WIDTH: usize = 100;

/// A page for `cmd` and each of its subcommands (hidden ones left out):
/// a section per command with its long help as clap prints it.
pub fn command_page(title: &str, intro: &str, cmd: Command) -> String {
    let mut out = format!("{GENERATED}\n\n# {title}\n\n{intro}\n");
    let mut cmd = cmd.term_width(WIDTH).max_term_width(WIDTH);
    cmd.build();
    section(&mut out, &cmd, cmd.get_name().to_string(), 2);
    out
}

fn section(out: &mut String, cmd: &Command, path: String, level: usize) {
    let mut c = cmd.clone();
    let help = c.render_long_help().to_string();
    out.push_str(&format!(
        "\n{} `{path}`\n\n```text\n{}\n```\n",
        "#".repeat(level.min(6)),
        help.trim_end()
    ));
    for sub in cmd.get_subcommands() {
        if sub.is_hide_set() || sub.get_name() == "help" {
            continue;
        }
        section(out, sub, format!("{path} {}", sub.get_name()), level + 1);
    }
}

/// `docs/reference/nodes.md`: every node kind a pipeline may use.
pub fn nodes_page() -> String {
    let body = matflow_nodes::reference_markdown().replace("\n#### `", "\n## `");
    let body = body
        .strip_prefix("#### `")
        .map_or(body.clone(), |b| format!("## `{b}"));
    format!(
        "{GENERATED}\n\n# Node kinds\n\nEvery node kind a pipeline's stage may use, with its \
         parameters (type, default, unit) and outputs; `matflow kinds` prints the same. The \
         pipeline format itself is in [Pipelines](../pipelines.md).\n\n{}",
        body.trim_end()
    ) + "\n"
}

/// `docs/reference/cli.md`: `matflow` and every subcommand.
pub fn cli_page() -> String {
    use clap::CommandFactory;
    command_page(
        "`matflow` command line",
        "Every command and option, as `matflow … --help` prints them. What the commands \
         are for, with examples: [Command line](../cli.md).",
        crate::Cli::command(),
    )
}
