//! The pinhole camera of the reference implementation.
//!
//! Camera at the origin looking down −z, +y up, horizontal field of view
//! 35°. Pixel `(i, j)` (column i, row j) covers the film square
//! `[i, i+1) × [j, j+1)`; its centre `(i + 0.5, j + 0.5)` maps to the
//! direction `((i − cx)/f, −(j − cy)/f, −1)` with `f = (W/2)/tan(fov/2)` and
//! principal point `(cx, cy) = ((W−1)/2, (H−1)/2)`: 255.5 for 512 pixels.

use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub width: usize,
    pub height: usize,
    /// Horizontal field of view in degrees.
    pub fov_x_deg: f32,
}

pub const DEFAULT_FOV_X_DEG: f32 = 35.0;

impl Camera {
    pub fn new(width: usize, height: usize) -> Self {
        Camera {
            width,
            height,
            fov_x_deg: DEFAULT_FOV_X_DEG,
        }
    }

    /// Focal length in pixels.
    #[inline]
    pub fn focal(&self) -> f32 {
        (self.width as f64 * 0.5 / (self.fov_x_deg as f64 * 0.5).to_radians().tan()) as f32
    }

    #[inline]
    pub fn principal_point(&self) -> Vec2 {
        Vec2::new(
            (self.width as f32 - 1.0) * 0.5,
            (self.height as f32 - 1.0) * 0.5,
        )
    }

    /// Unnormalised direction (z = −1) through the continuous film position
    /// `film` (pixel i spans [i, i+1)).
    #[inline]
    pub fn film_to_dir(&self, film: Vec2) -> Vec3 {
        let c = self.principal_point();
        let f = self.focal();
        Vec3::new((film.x - 0.5 - c.x) / f, -(film.y - 0.5 - c.y) / f, -1.0)
    }

    /// Camera-space point of the pixel centre (i, j) at camera-space depth
    /// `z > 0` (the point lies at −z).
    #[inline]
    pub fn backproject(&self, i: f32, j: f32, z: f32) -> Vec3 {
        self.film_to_dir(Vec2::new(i + 0.5, j + 0.5)) * z
    }

    /// Continuous film position of a camera-space point, or `None` when it is
    /// not in front of the camera.
    #[inline]
    pub fn project(&self, p: Vec3) -> Option<Vec2> {
        let depth = -p.z;
        if depth.is_nan() || depth <= 1e-8 {
            return None;
        }
        let c = self.principal_point();
        let f = self.focal();
        Some(Vec2::new(
            f * p.x / depth + c.x + 0.5,
            -f * p.y / depth + c.y + 0.5,
        ))
    }

    /// The pixel a camera-space point projects into, clamped to the image,
    /// or `None` behind the camera.
    #[inline]
    pub fn project_to_pixel(&self, p: Vec3) -> Option<(usize, usize)> {
        let film = self.project(p)?;
        if !film.x.is_finite() || !film.y.is_finite() {
            return None;
        }
        let x = film.x.floor().clamp(0.0, self.width as f32 - 1.0) as usize;
        let y = film.y.floor().clamp(0.0, self.height as f32 - 1.0) as usize;
        Some((x, y))
    }
}

impl Default for Camera {
    fn default() -> Self {
        Camera::new(512, 512)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn focal_matches_reference() {
        let cam = Camera::default();
        let f = 256.0 / 17.5f64.to_radians().tan();
        assert!((cam.focal() as f64 - f).abs() < 1e-3);
        assert_eq!(cam.principal_point(), Vec2::new(255.5, 255.5));
    }

    #[test]
    fn centre_ray_is_minus_z_and_up_is_plus_y() {
        let cam = Camera::default();
        let d = cam.film_to_dir(Vec2::new(256.0, 256.0));
        assert!(d.x.abs() < 1e-6 && d.y.abs() < 1e-6 && d.z == -1.0);
        // Top row of the image looks up (+y), left column looks left (−x).
        assert!(cam.film_to_dir(Vec2::new(256.0, 0.5)).y > 0.0);
        assert!(cam.film_to_dir(Vec2::new(0.5, 256.0)).x < 0.0);
        // The image edge is at half the field of view.
        let edge = cam.film_to_dir(Vec2::new(512.0, 256.0));
        assert!((edge.x.atan().to_degrees() - 17.5).abs() < 1e-3);
    }

    #[test]
    fn project_inverts_backproject() {
        let cam = Camera::new(64, 48);
        for (i, j, z) in [(0.0, 0.0, 1.0), (63.0, 47.0, 20.0), (10.3, 30.7, 3.0)] {
            let p = cam.backproject(i, j, z);
            let f = cam.project(p).unwrap();
            assert!((f.x - (i + 0.5)).abs() < 1e-3 && (f.y - (j + 0.5)).abs() < 1e-3);
        }
        assert!(cam.project(Vec3::new(0.0, 0.0, 1.0)).is_none());
    }
}
