//! What the kinds that write files to the user's paths share: the files a
//! folder output holds, and writing them (each only when its bytes
//! changed, so a cached run leaves the disk alone).

use std::path::{Path, PathBuf};

use matflow_engine::node::{Bytes, Params};
use matflow_engine::NodeError;
use matflow_scene::io;

use crate::{err, Context};

/// `names` inside the `output` folder, when one is given.
pub(crate) fn in_output(p: &Params, names: &[&str]) -> Vec<PathBuf> {
    match p.path("output") {
        Some(dir) => names.iter().map(|f| dir.join(f)).collect(),
        None => vec![],
    }
}

/// Writes a file output the stage made to `path`.
pub(crate) fn write_file(path: &Path, bytes: Option<&Bytes>) -> Result<(), NodeError> {
    let b = bytes.ok_or_else(|| err(format!("{}: the stage made no such file", path.display())))?;
    io::write_if_changed(path, b).node_err().map(|_| ())
}

/// Writes the files `names` (paths inside `dir`) that `bytes` gives, and
/// removes those it does not: an earlier run's leftover would contradict
/// this one. Returns the files written.
pub(crate) fn write_folder<'a>(
    dir: &Path,
    names: &[&str],
    bytes: impl Fn(&str) -> Option<&'a [u8]>,
) -> Result<Vec<PathBuf>, NodeError> {
    let mut written = vec![];
    for name in names {
        let path = dir.join(name);
        match bytes(name) {
            Some(b) => {
                if let Some(parent) = path.parent() {
                    std::fs::create_dir_all(parent)
                        .context(|| format!("creating {}", parent.display()))?;
                }
                io::write_if_changed(&path, b).node_err()?;
                written.push(path);
            }
            None => match std::fs::remove_file(&path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(NodeError(
                        format!("removing {}: {e}", path.display()),
                        NodeError::kind_of(&e),
                    ))
                }
                _ => {}
            },
        }
    }
    Ok(written)
}
