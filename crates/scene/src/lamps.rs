//! Lamps: lights without area besides the envmap (a lamp in the room, or
//! the sun), and their file, `lamps.json`. `best_results/lamps.json` holds
//! the lamps `matflow invert` fitted (which `matflow render` of those maps
//! lights the scene with unless told otherwise); `ground_truth/lamps.json`
//! the true ones a generated scene was lit by.

use std::path::Path;

use glam::Vec3;

use crate::error::SceneError;

/// Where a bundle keeps the lamps fitted with its `best_results/` maps.
pub const LAMPS_FILE: &str = "best_results/lamps.json";

/// Where a [`Lamp`] is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LampAt {
    /// An isotropic point light inside the scene at this camera-space
    /// position: a surface at distance r receives intensity·cos θ / r²
    /// (radiant intensity, per channel, in the envmap's radiance units
    /// times area).
    Point(Vec3),
    /// A distant light, the sun: in this camera-space direction (unit,
    /// towards the light), seen under a vanishing angle; a surface that
    /// sees it receives intensity·cos θ (the irradiance at normal
    /// incidence, in the envmap's radiance units times solid angle).
    Distant(Vec3),
}

/// A light without area besides the envmap: a lamp in the room or the
/// sun ([`LampAt`]). The camera never sees one (it has no area), and a
/// BSDF sample never meets one; next-event estimation alone brings its
/// light, to every surface it reaches.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lamp {
    pub at: LampAt,
    pub intensity: Vec3,
}

impl Lamp {
    /// An isotropic point light.
    pub fn point(position: Vec3, intensity: Vec3) -> Lamp {
        Lamp {
            at: LampAt::Point(position),
            intensity,
        }
    }

    /// A distant light in `direction` (normalised here; a zero or
    /// non-finite one gives a lamp that is not [`Lamp::is_valid`]) giving
    /// `irradiance` at normal incidence.
    pub fn sun(direction: Vec3, irradiance: Vec3) -> Lamp {
        Lamp {
            at: LampAt::Distant(direction.try_normalize().unwrap_or(Vec3::NAN)),
            intensity: irradiance,
        }
    }

    /// Whether it is the sun.
    pub fn is_distant(&self) -> bool {
        matches!(self.at, LampAt::Distant(_))
    }

    /// Finite position (a unit direction for a distant lamp), finite
    /// non-negative intensity.
    pub fn is_valid(&self) -> bool {
        let at = match self.at {
            LampAt::Point(p) => p.is_finite(),
            LampAt::Distant(d) => d.is_finite() && (d.length() - 1.0).abs() < 1e-3,
        };
        at && self.intensity.is_finite() && self.intensity.min_element() >= 0.0
    }
}

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
pub fn write_lamps(path: &Path, lamps: &[Lamp]) -> Result<(), SceneError> {
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
    let text = serde_json::to_string_pretty(&doc).map_err(|e| SceneError::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    crate::io::write_atomic(path, text.as_bytes())
}

/// The lamps in `path`; an error names the file and what is wrong
/// (unparsable, a lamp with both or neither of `position` and
/// `direction`, or which lamp is not finite, has a direction that is not
/// a unit vector or a negative intensity).
pub fn read_lamps(path: &Path) -> Result<Vec<Lamp>, SceneError> {
    let bytes = std::fs::read(path).map_err(|e| SceneError::io(path, e))?;
    let doc: LampsDoc = serde_json::from_slice(&bytes).map_err(|e| SceneError::Decode {
        path: path.to_path_buf(),
        message: format!("not a lamps file: {e}"),
    })?;
    let invalid = |message: String| SceneError::Invalid {
        path: path.to_path_buf(),
        message,
    };
    let mut lamps = Vec::with_capacity(doc.lamps.len());
    for (k, e) in doc.lamps.iter().enumerate() {
        let at = match (e.position, e.direction) {
            (Some(p), None) => LampAt::Point(Vec3::from(p)),
            (None, Some(d)) => LampAt::Distant(Vec3::from(d)),
            _ => {
                return Err(invalid(format!(
                    "lamps[{k}] needs exactly one of `position` (a point light) and \
                     `direction` (the sun)"
                )))
            }
        };
        let lamp = Lamp {
            at,
            intensity: Vec3::from(e.intensity),
        };
        if !lamp.is_valid() {
            return Err(invalid(format!(
                "lamps[{k}] has a non-finite position, a direction that is not a unit vector, \
                 or a negative or non-finite intensity"
            )));
        }
        lamps.push(lamp);
    }
    Ok(lamps)
}

/// The lamps that light a bundle's maps in `folder` (`best_results`:
/// those `matflow invert` fitted; `ground_truth`: the true ones, e.g. the
/// validation set's), from `FOLDER/lamps.json`, if it has any.
pub fn bundle_lamps(bundle: &Path, folder: &str) -> Result<Option<Vec<Lamp>>, SceneError> {
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
        let e = read_lamps(&p).unwrap_err().to_string();
        assert!(e.contains("lamps[0]") && e.contains("lamps.json"), "{e}");
        std::fs::write(
            &p,
            br#"{"lamps": [{"position": [0, 0, 0], "direction": [0, 1, 0], "intensity": [1, 1, 1]}]}"#,
        )
        .unwrap();
        let e = read_lamps(&p).unwrap_err().to_string();
        assert!(e.contains("lamps[0]") && e.contains("exactly one"), "{e}");
        std::fs::write(
            &p,
            br#"{"lamps": [{"direction": [0, 2, 0], "intensity": [1, 1, 1]}]}"#,
        )
        .unwrap();
        let e = read_lamps(&p).unwrap_err().to_string();
        assert!(e.contains("lamps[0]") && e.contains("unit vector"), "{e}");
        std::fs::write(&p, b"{\"lamps\": 3}").unwrap();
        let e = read_lamps(&p).unwrap_err().to_string();
        assert!(e.contains("not a lamps file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
