//! `best_results/lamps.json`: the lamps `matflow invert` fitted (point
//! lights in camera space, [`matflow_render::Lamp`]), which `matflow
//! render` of those maps lights the scene with unless told otherwise.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use matflow_render::Lamp;

/// Where a bundle keeps the lamps fitted with its `best_results/` maps.
pub const LAMPS_FILE: &str = "best_results/lamps.json";

#[derive(serde::Serialize, serde::Deserialize)]
struct LampEntry {
    /// Camera space (x right, y up, −z forward), the depth map's units.
    position: [f32; 3],
    /// Radiant intensity per channel: the envmap's radiance units times
    /// the depth map's units squared.
    intensity: [f32; 3],
}

#[derive(serde::Serialize, serde::Deserialize)]
struct LampsDoc {
    lamps: Vec<LampEntry>,
}

/// Writes `lamps` to `path` (atomically).
pub fn write_lamps(path: &Path, lamps: &[Lamp]) -> Result<()> {
    let doc = LampsDoc {
        lamps: lamps
            .iter()
            .map(|l| LampEntry {
                position: l.position.to_array(),
                intensity: l.intensity.to_array(),
            })
            .collect(),
    };
    let text = serde_json::to_string_pretty(&doc)?;
    matflow_scene::io::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The lamps in `path`; an error names the file and what is wrong
/// (unparsable, or which lamp is not finite or has a negative intensity).
pub fn read_lamps(path: &Path) -> Result<Vec<Lamp>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let doc: LampsDoc = serde_json::from_slice(&bytes)
        .with_context(|| format!("{}: not a lamps file", path.display()))?;
    let lamps: Vec<Lamp> = doc
        .lamps
        .iter()
        .map(|e| Lamp {
            position: Vec3::from(e.position),
            intensity: Vec3::from(e.intensity),
        })
        .collect();
    if let Some(k) = lamps.iter().position(|l| !l.is_valid()) {
        bail!(
            "{}: lamps[{k}] has a non-finite position or a negative or non-finite intensity",
            path.display()
        );
    }
    Ok(lamps)
}

/// The lamps of a bundle's `best_results/` maps, if it has any.
pub fn bundle_lamps(bundle: &Path) -> Result<Option<Vec<Lamp>>> {
    let p = bundle.join(LAMPS_FILE);
    if p.exists() {
        read_lamps(&p).map(Some)
    } else {
        Ok(None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lamps_round_trip_and_bad_files_are_named_errors() {
        let dir = std::env::temp_dir().join(format!("matflow-lamps-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("lamps.json");
        let lamps = vec![Lamp {
            position: Vec3::new(0.5, 1.25, -3.0),
            intensity: Vec3::new(2.0, 1.5, 0.25),
        }];
        write_lamps(&p, &lamps).unwrap();
        assert_eq!(read_lamps(&p).unwrap(), lamps);
        std::fs::write(
            &p,
            br#"{"lamps": [{"position": [0, 0, 0], "intensity": [1, -1, 0]}]}"#,
        )
        .unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("lamps[0]") && e.contains("lamps.json"), "{e}");
        std::fs::write(&p, b"{\"lamps\": 3}").unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("not a lamps file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
