//! The pinhole camera of SPEC §4.1.

use glam::DVec3;

/// A ray: origin and unit direction, so `t` is world distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Where the ray starts (the eye).
    pub origin: DVec3,
    /// Unit direction.
    pub dir: DVec3,
}

impl Ray {
    /// The point at parameter `t`.
    #[inline]
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + t * self.dir
    }
}

/// A perspective camera with a validated, orthonormal frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    eye: DVec3,
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    tan_half_fov: f64,
}

impl Camera {
    /// `Err` names the key that is wrong: eye = target, `up` parallel to the view
    /// direction, a non-finite input, or `fov_y` outside (0°, 180°).
    pub fn new(eye: DVec3, target: DVec3, up: DVec3, fov_y_degrees: f64) -> Result<Camera, (&'static str, String)> {
        for (key, v) in [("camera.eye", eye), ("camera.target", target), ("camera.up", up)] {
            if !v.is_finite() {
                return Err((key, format!("expected three finite numbers, got {:?}", v.to_array())));
            }
        }
        if !(fov_y_degrees > 0.0 && fov_y_degrees < 180.0) {
            return Err(("camera.fov_y", format!("expected degrees in (0, 180), got {fov_y_degrees}")));
        }
        let view = target - eye;
        if view.length() == 0.0 {
            return Err(("camera.target", "expected a target different from the eye".into()));
        }
        let forward = view.normalize();
        let side = forward.cross(up);
        if side.length() <= 1e-12 * up.length() || up.length() == 0.0 {
            return Err((
                "camera.up",
                format!("expected a direction not parallel to the view direction, got {:?}", up.to_array()),
            ));
        }
        let right = side.normalize();
        Ok(Camera {
            eye,
            forward,
            right,
            up: right.cross(forward),
            tan_half_fov: (fov_y_degrees.to_radians() / 2.0).tan(),
        })
    }

    /// The eye.
    pub fn eye(&self) -> DVec3 {
        self.eye
    }

    /// The ray through the centre of pixel (`col`, `row`), row 0 at the top.
    #[inline]
    pub fn ray(&self, col: u32, row: u32, width: u32, height: u32) -> Ray {
        let aspect = width as f64 / height as f64;
        let s = self.tan_half_fov;
        let x = (2.0 * (col as f64 + 0.5) / width as f64 - 1.0) * aspect * s;
        let y = (1.0 - 2.0 * (row as f64 + 0.5) / height as f64) * s;
        Ray { origin: self.eye, dir: (self.forward + x * self.right + y * self.up).normalize() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_pixel_looks_at_target_and_row_zero_is_up() {
        let c = Camera::new(DVec3::new(0.0, 0.0, 4.0), DVec3::ZERO, DVec3::Y, 40.0).unwrap();
        let r = c.ray(50, 50, 101, 101);
        assert!((r.dir - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-15);
        assert!(c.ray(50, 0, 101, 101).dir.y > 0.0);
        assert!(c.ray(100, 50, 101, 101).dir.x > 0.0);
        let top = c.ray(50, 0, 101, 101).dir;
        let half = (top.y / -top.z).atan().to_degrees();
        assert!((half - 20.0 * 100.0 / 101.0).abs() < 0.2, "{half}");
    }

    #[test]
    fn refuses_bad_cameras_naming_the_key() {
        let e = DVec3::new(0.0, 0.0, 4.0);
        assert_eq!(Camera::new(e, DVec3::ZERO, DVec3::Z, 40.0).unwrap_err().0, "camera.up");
        assert_eq!(Camera::new(e, DVec3::ZERO, DVec3::Y, 180.0).unwrap_err().0, "camera.fov_y");
        assert_eq!(Camera::new(e, DVec3::ZERO, DVec3::Y, 0.0).unwrap_err().0, "camera.fov_y");
        assert_eq!(Camera::new(e, e, DVec3::Y, 40.0).unwrap_err().0, "camera.target");
        assert_eq!(Camera::new(DVec3::NAN, e, DVec3::Y, 40.0).unwrap_err().0, "camera.eye");
    }
}
