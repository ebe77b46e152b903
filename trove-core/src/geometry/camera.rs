//! The pinhole camera of SPEC §4.1.

use glam::DVec3;
use thiserror::Error;

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

/// The rays of an image's pixels ([`Camera::pixel_rays`]): `Camera::ray` evaluated in the
/// same order, `forward + x·right` (per column) then `+ y·up` (per row), then normalised, so
/// every ray is the same to the bit.
#[derive(Clone, Debug)]
pub(crate) struct PixelRays {
    eye: DVec3,
    up: DVec3,
    tan_half_fov: f64,
    height: u32,
    /// `forward + x·right` of each column.
    columns: Vec<DVec3>,
}

impl PixelRays {
    /// The row's part of its rays' directions, `y·up`.
    #[inline]
    pub(crate) fn row(&self, row: u32) -> DVec3 {
        let y = (1.0 - 2.0 * (row as f64 + 0.5) / self.height as f64) * self.tan_half_fov;
        y * self.up
    }

    /// `forward + x·right` of each column.
    #[inline]
    pub(crate) fn columns(&self) -> &[DVec3] {
        &self.columns
    }

    /// The eye, where every ray starts.
    #[inline]
    pub(crate) fn eye(&self) -> DVec3 {
        self.eye
    }

    /// The ray of pixel (`col`, a row whose [`PixelRays::row`] is `row_part`).
    #[cfg(test)]
    pub(crate) fn ray(&self, col: u32, row_part: DVec3) -> Ray {
        Ray { origin: self.eye, dir: (self.columns[col as usize] + row_part).normalize() }
    }
}

/// Which camera input an error is about; the scene loader turns it into a key path
/// (`camera.up`), so the camera itself knows nothing of TOML.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraField {
    /// The eye point.
    Eye,
    /// The point looked at.
    Target,
    /// The up direction.
    Up,
    /// The vertical field of view.
    FovY,
}

/// Why [`Camera::new`] refused its inputs.
#[derive(Clone, Copy, Debug, PartialEq, Error)]
pub enum CameraError {
    /// A point or direction with a NaN or infinite coordinate.
    #[error("expected three finite numbers, got {value:?}")]
    NotFinite {
        /// Which input.
        field: CameraField,
        /// Its value.
        value: [f64; 3],
    },
    /// A field of view outside (0°, 180°) (NaN included).
    #[error("expected degrees in (0, 180), got {fov_y}")]
    FovOutOfRange {
        /// The value given, in degrees.
        fov_y: f64,
    },
    /// The eye is the target, so there is no view direction.
    #[error("expected a target different from the eye")]
    TargetIsEye,
    /// `up` is zero or parallel to the view direction, so it fixes no frame.
    #[error("expected a direction not parallel to the view direction, got {up:?}")]
    UpParallelToView {
        /// The `up` given.
        up: [f64; 3],
    },
}

impl CameraError {
    /// The input the error is about.
    pub fn field(&self) -> CameraField {
        match self {
            CameraError::NotFinite { field, .. } => *field,
            CameraError::FovOutOfRange { .. } => CameraField::FovY,
            CameraError::TargetIsEye => CameraField::Target,
            CameraError::UpParallelToView { .. } => CameraField::Up,
        }
    }
}

impl Camera {
    /// A camera at `eye` looking at `target`; refuses a non-finite input, `fov_y` outside
    /// (0°, 180°), eye = target, and `up` parallel to the view direction.
    pub fn new(eye: DVec3, target: DVec3, up: DVec3, fov_y_degrees: f64) -> Result<Camera, CameraError> {
        for (field, v) in [(CameraField::Eye, eye), (CameraField::Target, target), (CameraField::Up, up)] {
            if !v.is_finite() {
                return Err(CameraError::NotFinite { field, value: v.to_array() });
            }
        }
        if !(fov_y_degrees > 0.0 && fov_y_degrees < 180.0) {
            return Err(CameraError::FovOutOfRange { fov_y: fov_y_degrees });
        }
        let view = target - eye;
        if view.length() == 0.0 {
            return Err(CameraError::TargetIsEye);
        }
        let forward = view.normalize();
        let side = forward.cross(up);
        if side.length() <= 1e-12 * up.length() || up.length() == 0.0 {
            return Err(CameraError::UpParallelToView { up: up.to_array() });
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

    /// [`Camera::ray`] for every pixel of a `width` × `height` image, with the part of the
    /// direction that depends on the column alone worked out once per column and the part
    /// that depends on the row once per row: what intersecting a band of rows asks for every
    /// pixel (two divisions and a dozen products a ray fewer).
    pub(crate) fn pixel_rays(&self, width: u32, height: u32) -> PixelRays {
        let aspect = width as f64 / height as f64;
        let s = self.tan_half_fov;
        let columns = (0..width)
            .map(|col| {
                let x = (2.0 * (col as f64 + 0.5) / width as f64 - 1.0) * aspect * s;
                self.forward + x * self.right
            })
            .collect();
        PixelRays { eye: self.eye, up: self.up, tan_half_fov: s, height, columns }
    }

    /// An upper bound on how many pixels' rays can meet the convex hull of `points`
    /// ([`Camera::pixels_reaching`]).
    pub(crate) fn pixels_covering(&self, points: &[DVec3], width: u32, height: u32) -> u64 {
        self.pixels_reaching(points, width, height).pixels()
    }

    /// The pixels whose rays can meet the convex hull of `points`: its projected bounding
    /// rectangle, with a pixel of margin for rounding; the whole image when a point is not
    /// in front of the eye (the projection would wrap).
    pub(crate) fn pixels_reaching(&self, points: &[DVec3], width: u32, height: u32) -> PixelRect {
        let all = PixelRect::whole(width, height);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for &p in points {
            let d = p - self.eye;
            let depth = d.dot(self.forward);
            // Not `depth <= …`: a NaN depth must take the whole image too.
            if depth.partial_cmp(&(1e-9 * d.length())) != Some(std::cmp::Ordering::Greater) {
                return all;
            }
            let aspect = width as f64 / height as f64;
            // Inverse of `ray`: the continuous column and row the point projects to.
            let x = d.dot(self.right) / depth / (aspect * self.tan_half_fov);
            let y = d.dot(self.up) / depth / self.tan_half_fov;
            let (col, row) = ((x + 1.0) * width as f64 / 2.0, (1.0 - y) * height as f64 / 2.0);
            lo = [lo[0].min(col), lo[1].min(row)];
            hi = [hi[0].max(col), hi[1].max(row)];
        }
        // Pixel c's ray passes through c + ½; NaN bounds (a NaN point) take the whole axis.
        let span = |lo: f64, hi: f64, n: u32| -> [u32; 2] {
            if lo.is_nan() || hi.is_nan() {
                return [0, n];
            }
            let first = (lo.floor() - 1.0).clamp(0.0, n as f64);
            let last = (hi.ceil() + 1.0).clamp(0.0, n as f64);
            [first as u32, (last as u32).max(first as u32)]
        };
        PixelRect { cols: span(lo[0], hi[0], width), rows: span(lo[1], hi[1], height) }
    }
}

/// A rectangle of pixels, `[first, end)` per axis: where an object's rays can be.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct PixelRect {
    cols: [u32; 2],
    rows: [u32; 2],
}

impl PixelRect {
    /// Every pixel of a `width` × `height` image.
    pub(crate) fn whole(width: u32, height: u32) -> PixelRect {
        PixelRect { cols: [0, width], rows: [0, height] }
    }

    /// Whether pixel (`col`, `row`) is inside.
    #[inline]
    pub(crate) fn contains(&self, col: u32, row: u32) -> bool {
        (self.cols[0]..self.cols[1]).contains(&col) && (self.rows[0]..self.rows[1]).contains(&row)
    }

    /// Whether some pixel of image row `row` is inside.
    #[inline]
    pub(crate) fn has_row(&self, row: u32) -> bool {
        (self.rows[0]..self.rows[1]).contains(&row)
    }

    /// Whether column `col` of a row it has ([`PixelRect::has_row`]) is inside.
    #[inline]
    pub(crate) fn has_col(&self, col: u32) -> bool {
        (self.cols[0]..self.cols[1]).contains(&col)
    }

    /// Its columns.
    #[inline]
    pub(crate) fn cols(&self) -> std::ops::Range<u32> {
        self.cols[0]..self.cols[1]
    }

    /// How many pixels are inside.
    pub(crate) fn pixels(&self) -> u64 {
        u64::from(self.cols[1] - self.cols[0]) * u64::from(self.rows[1] - self.rows[0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_rays_are_the_cameras_rays_to_the_bit() {
        for (eye, fov, (w, h)) in [
            (DVec3::new(0.3, 0.2, 5.0), 40.0, (61, 47)),
            (DVec3::new(-2.0, 7.5, 0.1), 75.0, (33, 100)),
            (DVec3::new(1e-3, -4.0, 2.0), 12.5, (1024, 3)),
        ] {
            let cam = Camera::new(eye, DVec3::new(0.1, -0.2, 0.3), DVec3::Y, fov).unwrap();
            let rays = cam.pixel_rays(w, h);
            for row in 0..h {
                let part = rays.row(row);
                for col in 0..w {
                    let (a, b) = (cam.ray(col, row, w, h), rays.ray(col, part));
                    assert_eq!(a.origin.to_array().map(f64::to_bits), b.origin.to_array().map(f64::to_bits));
                    assert_eq!(
                        a.dir.to_array().map(f64::to_bits),
                        b.dir.to_array().map(f64::to_bits),
                        "({col}, {row})"
                    );
                }
            }
        }
    }

    #[test]
    fn pixels_covering_holds_every_pixel_whose_ray_meets_the_points() {
        let cam = Camera::new(DVec3::new(0.3, 0.2, 5.0), DVec3::ZERO, DVec3::Y, 40.0).unwrap();
        let (w, h) = (64, 48);
        let corners: Vec<DVec3> =
            (0..8).map(|i| DVec3::new((i & 1) as f64 - 0.5, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64)).collect();
        let bound = cam.pixels_covering(&corners, w, h);
        // Every pixel whose ray passes within the box's bounds is inside the bound's rectangle.
        let mut hit = 0;
        for row in 0..h {
            for col in 0..w {
                let r = cam.ray(col, row, w, h);
                let t = (0.5 - r.origin.z) / r.dir.z;
                let p = r.at(t);
                if (-0.5..=0.5).contains(&p.x) && (0.0..=1.0).contains(&p.y) {
                    hit += 1;
                }
            }
        }
        assert!(hit > 0 && bound >= hit && bound < (w * h) as u64 / 2, "hit {hit}, bound {bound}");
        // A point behind the eye: the whole image.
        assert_eq!(cam.pixels_covering(&[DVec3::new(0.0, 0.0, 9.0)], w, h), (w * h) as u64);
    }

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
    fn refuses_bad_cameras_naming_the_field() {
        let e = DVec3::new(0.0, 0.0, 4.0);
        let err = |eye, target, up, fov| Camera::new(eye, target, up, fov).unwrap_err();
        assert_eq!(err(e, DVec3::ZERO, DVec3::Z, 40.0), CameraError::UpParallelToView { up: [0.0, 0.0, 1.0] });
        assert_eq!(err(e, DVec3::ZERO, DVec3::Y, 180.0), CameraError::FovOutOfRange { fov_y: 180.0 });
        assert_eq!(err(e, DVec3::ZERO, DVec3::Y, 0.0).field(), CameraField::FovY);
        assert_eq!(err(e, e, DVec3::Y, 40.0), CameraError::TargetIsEye);
        assert_eq!(err(e, e, DVec3::Y, 40.0).field(), CameraField::Target);
        let nan = err(DVec3::NAN, e, DVec3::Y, 40.0);
        assert!(matches!(nan, CameraError::NotFinite { field: CameraField::Eye, .. }), "{nan:?}");
        assert_eq!(err(e, DVec3::ZERO, DVec3::ZERO, 40.0).field(), CameraField::Up);
    }
}
