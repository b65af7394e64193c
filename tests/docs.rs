//! The references in `docs/reference/` are generated from the code (clap's
//! help, the node kinds' parameter specs): each page must equal what the
//! code generates now. `MATFLOW_BLESS=1` rewrites a stale page instead of
//! failing.

mod support;

use matflow_cli::reference;

fn check(page: &str, want: String) {
    let path = support::repo().join(page);
    let have = std::fs::read_to_string(&path).unwrap_or_default();
    if have == want {
        return;
    }
    if std::env::var_os("MATFLOW_BLESS").is_some() {
        std::fs::write(&path, want).unwrap();
        return;
    }
    let line = have
        .lines()
        .zip(want.lines())
        .position(|(a, b)| a != b)
        .unwrap_or(have.lines().count().min(want.lines().count()));
    panic!(
        "{page} is stale from line {}: regenerate it with `MATFLOW_BLESS=1 cargo test \
         --release --workspace -- reference`",
        line + 1
    );
}

#[test]
fn reference_of_the_command_line_is_current() {
    check("docs/reference/cli.md", reference::cli_page());
}

#[test]
fn reference_of_the_node_kinds_is_current() {
    check("docs/reference/nodes.md", reference::nodes_page());
}

/// `matflow kinds` prints the node reference the page holds (the page
/// with its headings one level up).
#[test]
fn matflow_kinds_prints_the_node_reference() {
    let o = support::matflow(&["kinds"], None);
    assert!(o.status.success());
    let kinds = String::from_utf8_lossy(&o.stdout).replace("#### `", "## `");
    let page = std::fs::read_to_string(support::repo().join("docs/reference/nodes.md")).unwrap();
    assert!(
        page.contains(kinds.trim()),
        "docs/reference/nodes.md differs from `matflow kinds`"
    );
}
