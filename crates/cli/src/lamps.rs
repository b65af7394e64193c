//! `best_results/lamps.json`: the lamps `matflow invert` fitted (point
//! lights in camera space, and the sun: a distant light,
//! [`matflow_render::Lamp`]), which `matflow render` of those maps lights
//! the scene with unless told otherwise; `ground_truth/lamps.json`, the
//! same for the true maps (the lamps a generated scene was lit by).

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use matflow_render::{Lamp, LampAt};

/// Where a bundle keeps the lamps fitted with its `best_results/` maps.
pub const LAMPS_FILE: &str = "best_results/lamps.json";

#[derive(serde::Serialize, serde::Deserialize)]
struct LampEntry {
    /// A point light: camera space (x right, y up, −z forward), the depth
    /// map's units.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    position: Option<[f32; 3]>,
    /// A distant light (the sun): the unit direction towards it, camera
    /// space.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    direction: Option<[f32; 3]>,
    /// Per channel: a point's radiant intensity (the envmap's radiance
    /// units times the depth map's units squared), a distant light's
    /// irradiance at normal incidence (radiance units times steradians).
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
            .map(|l| match l.at {
                LampAt::Point(p) => LampEntry {
                    position: Some(p.to_array()),
                    direction: None,
                    intensity: l.intensity.to_array(),
                },
                LampAt::Distant(d) => LampEntry {
                    position: None,
                    direction: Some(d.to_array()),
                    intensity: l.intensity.to_array(),
                },
            })
            .collect(),
    };
    let text = serde_json::to_string_pretty(&doc)?;
    matflow_scene::io::write_atomic(path, text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The lamps in `path`; an error names the file and what is wrong
/// (unparsable, a lamp with both or neither of `position` and
/// `direction`, or which lamp is not finite, has a direction that is not
/// a unit vector or a negative intensity).
pub fn read_lamps(path: &Path) -> Result<Vec<Lamp>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let doc: LampsDoc = serde_json::from_slice(&bytes)
        .with_context(|| format!("{}: not a lamps file", path.display()))?;
    let mut lamps = Vec::with_capacity(doc.lamps.len());
    for (k, e) in doc.lamps.iter().enumerate() {
        let at = match (e.position, e.direction) {
            (Some(p), None) => LampAt::Point(Vec3::from(p)),
            (None, Some(d)) => LampAt::Distant(Vec3::from(d)),
            _ => bail!(
                "{}: lamps[{k}] needs exactly one of `position` (a point light) and `direction` (the sun)",
                path.display()
            ),
        };
        let lamp = Lamp {
            at,
            intensity: Vec3::from(e.intensity),
        };
        if !lamp.is_valid() {
            bail!(
                "{}: lamps[{k}] has a non-finite position, a direction that is not a unit vector, or a negative or non-finite intensity",
                path.display()
            );
        }
        lamps.push(lamp);
    }
    Ok(lamps)
}

/// The lamps that light a bundle's maps in `folder` (`best_results`:
/// those `matflow invert` fitted; `ground_truth`: the true ones, e.g. the
/// validation set's), from `FOLDER/lamps.json`, if it has any.
pub fn bundle_lamps(bundle: &Path, folder: &str) -> Result<Option<Vec<Lamp>>> {
    let p = bundle.join(folder).join("lamps.json");
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
        let lamps = vec![
            Lamp::point(Vec3::new(0.5, 1.25, -3.0), Vec3::new(2.0, 1.5, 0.25)),
            Lamp::sun(Vec3::new(0.0, 0.6, 0.8), Vec3::new(4.0, 3.5, 3.0)),
        ];
        write_lamps(&p, &lamps).unwrap();
        assert_eq!(read_lamps(&p).unwrap(), lamps);
        std::fs::write(
            &p,
            br#"{"lamps": [{"position": [0, 0, 0], "intensity": [1, -1, 0]}]}"#,
        )
        .unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("lamps[0]") && e.contains("lamps.json"), "{e}");
        std::fs::write(
            &p,
            br#"{"lamps": [{"position": [0, 0, 0], "direction": [0, 1, 0], "intensity": [1, 1, 1]}]}"#,
        )
        .unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("lamps[0]") && e.contains("exactly one"), "{e}");
        std::fs::write(
            &p,
            br#"{"lamps": [{"direction": [0, 2, 0], "intensity": [1, 1, 1]}]}"#,
        )
        .unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("lamps[0]") && e.contains("unit vector"), "{e}");
        std::fs::write(&p, b"{\"lamps\": 3}").unwrap();
        let e = format!("{:#}", read_lamps(&p).unwrap_err());
        assert!(e.contains("not a lamps file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
