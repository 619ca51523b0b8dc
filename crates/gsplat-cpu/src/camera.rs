//! Pinhole camera: intrinsics in pixels, pose as a world-to-camera rigid transform.

use glam::{Mat3, Vec2, Vec3};

use crate::Error;

/// Default near plane, metres: Gaussians whose centre is closer to the camera (along its
/// viewing axis) are culled.
pub const DEFAULT_NEAR_M: f32 = 0.01;

/// The most pixels a [`Camera`] may have: 64 megapixels (8192 × 8192), 1.3 GB of frame
/// buffers; beyond it [`Camera::validate`] refuses the size instead of the allocation failing.
pub const MAX_PIXELS: usize = 1 << 26;

/// A pinhole camera.
///
/// Camera frame (OpenCV convention): `x` right, `y` down, `z` forward (viewing direction).
/// A camera-frame point `p` with `p.z > 0` projects to the continuous pixel coordinate
/// `(fx p.x / p.z + cx, fy p.y / p.z + cy)`; pixel `(i, j)` (column, row) covers
/// `[i, i + 1) × [j, j + 1)` and is sampled at its centre `(i + 0.5, j + 0.5)`.
///
/// World frame: metres, z up (the datasets' convention); [`Camera::look_at`] builds a camera
/// from an eye point and a target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Focal length along x, pixels.
    pub fx: f32,
    /// Focal length along y, pixels.
    pub fy: f32,
    /// Principal point x, pixels (continuous coordinate; `width / 2` is the image centre).
    pub cx: f32,
    /// Principal point y, pixels.
    pub cy: f32,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Near plane, metres along the viewing axis; must be positive.
    pub near: f32,
    /// Rotation part of world-to-camera: `p_cam = rotation * p_world + translation`.
    pub rotation: Mat3,
    /// Translation part of world-to-camera, metres.
    pub translation: Vec3,
}

impl Camera {
    /// A camera at `eye` looking at `target` (world coordinates, metres), with `up` giving the
    /// image's up direction (usually `Vec3::Z`), a vertical field of view of `fov_y_rad`
    /// radians, square pixels, the principal point at the image centre and the default near
    /// plane ([`DEFAULT_NEAR_M`]).
    ///
    /// # Errors
    /// Zero image size, a field of view outside `(0, π)`, non-finite vectors, `eye == target`
    /// or `up` parallel to the viewing direction.
    ///
    /// ```
    /// use gsplat::Camera;
    /// use glam::Vec3;
    /// let cam = Camera::look_at(Vec3::new(1.0, 0.0, 0.5), Vec3::new(0.0, 0.0, 0.5), Vec3::Z,
    ///                           50f32.to_radians(), 64, 48)?;
    /// // The target projects to the image centre.
    /// let (uv, depth) = cam.project(Vec3::new(0.0, 0.0, 0.5)).unwrap();
    /// assert!((uv.x - 32.0).abs() < 1e-4 && (uv.y - 24.0).abs() < 1e-4 && (depth - 1.0).abs() < 1e-6);
    /// # Ok::<(), gsplat::Error>(())
    /// ```
    pub fn look_at(
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        fov_y_rad: f32,
        width: usize,
        height: usize,
    ) -> Result<Self, Error> {
        if !(eye.is_finite() && target.is_finite() && up.is_finite()) {
            return Err(Error::Camera(
                "look_at: non-finite eye, target or up".into(),
            ));
        }
        if !(fov_y_rad > 0.0 && fov_y_rad < std::f32::consts::PI) {
            return Err(Error::Camera(format!(
                "look_at: vertical field of view {fov_y_rad} rad outside (0, pi)"
            )));
        }
        let forward = (target - eye).normalize_or_zero();
        if forward == Vec3::ZERO {
            return Err(Error::Camera("look_at: eye and target coincide".into()));
        }
        let right = forward.cross(up);
        // A relative test: `up` nearly parallel to the view leaves the roll undefined.
        if right.length() <= 1e-6 * up.length() || up.length() == 0.0 {
            return Err(Error::Camera(
                "look_at: up is zero or parallel to the viewing direction".into(),
            ));
        }
        let right = right.normalize();
        let down = forward.cross(right);
        let rotation = Mat3::from_cols(right, down, forward).transpose();
        let fy = 0.5 * height as f32 / (0.5 * fov_y_rad).tan();
        let cam = Camera {
            fx: fy,
            fy,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            width,
            height,
            near: DEFAULT_NEAR_M,
            rotation,
            translation: -(rotation * eye),
        };
        cam.validate()?;
        Ok(cam)
    }

    /// A [`Camera::look_at`] camera that looks along `view_dir` at the centre of the bounding
    /// box of `points`, backed off so that the points span about `fill` (in `(0, 1]`) of the
    /// image half-width or half-height, whichever is tighter: e.g. one camera for every frame
    /// of an episode, from all its positions.
    ///
    /// # Errors
    /// No points, non-finite points or direction, `fill` outside `(0, 1]`, and the
    /// [`Camera::look_at`] errors.
    ///
    /// ```
    /// use gsplat::Camera;
    /// use glam::Vec3;
    /// let pts = [Vec3::new(-0.3, 0.0, 0.0), Vec3::new(0.3, 0.1, 0.05)];
    /// let cam = Camera::framing(&pts, Vec3::new(0.0, 1.0, -0.5), Vec3::Z, 0.7, 160, 120, 0.8)?;
    /// assert!(pts.iter().all(|p| cam.project(*p).is_some_and(|(uv, _)| uv.x > 0.0 && uv.x < 160.0)));
    /// # Ok::<(), gsplat::Error>(())
    /// ```
    #[allow(clippy::too_many_arguments)]
    pub fn framing(
        points: &[Vec3],
        view_dir: Vec3,
        up: Vec3,
        fov_y_rad: f32,
        width: usize,
        height: usize,
        fill: f32,
    ) -> Result<Self, Error> {
        if points.is_empty() || !points.iter().all(|p| p.is_finite()) {
            return Err(Error::Camera(
                "framing: no points, or non-finite ones".into(),
            ));
        }
        if !(fill > 0.0 && fill <= 1.0) {
            return Err(Error::Camera(format!(
                "framing: fill {fill} outside (0, 1]"
            )));
        }
        let dir = view_dir.normalize_or_zero();
        if !dir.is_finite() || dir == Vec3::ZERO {
            return Err(Error::Camera(
                "framing: zero or non-finite view direction".into(),
            ));
        }
        let lo = points.iter().copied().fold(Vec3::INFINITY, Vec3::min);
        let hi = points.iter().copied().fold(Vec3::NEG_INFINITY, Vec3::max);
        let centre = (lo + hi) / 2.0;
        // The used fraction shrinks as the camera backs off (for points in front of it), so
        // bisect the distance between just outside the bounding sphere and far enough.
        let radius = ((hi - lo).length() / 2.0).max(1e-3);
        let at = |d: f32| Camera::look_at(centre - dir * d, centre, up, fov_y_rad, width, height);
        let used = |cam: &Camera| {
            points
                .iter()
                .map(|p| match cam.project(*p) {
                    Some((uv, _)) => {
                        ((uv.x - cam.cx).abs() / cam.cx).max((uv.y - cam.cy).abs() / cam.cy)
                    }
                    None => f32::INFINITY,
                })
                .fold(0.0, f32::max)
        };
        let mut near = radius * 1.05 + DEFAULT_NEAR_M;
        let mut far = 2.0 * near;
        for _ in 0..60 {
            if used(&at(far)?) <= fill {
                break;
            }
            far *= 2.0;
        }
        if used(&at(near)?) <= fill {
            return at(near);
        }
        for _ in 0..40 {
            let mid = 0.5 * (near + far);
            if used(&at(mid)?) <= fill {
                far = mid;
            } else {
                near = mid;
            }
        }
        at(far)
    }

    /// The same camera with another near plane (metres).
    pub fn with_near(mut self, near_m: f32) -> Self {
        self.near = near_m;
        self
    }

    /// Checks sizes, finiteness, positive focal lengths and near plane, and that `rotation` is
    /// a rotation (orthonormal, determinant +1, to 1e-3).
    ///
    /// # Errors
    /// [`Error::Camera`] naming the first problem.
    pub fn validate(&self) -> Result<(), Error> {
        let bad = |m: String| Err(Error::Camera(m));
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size {} x {} has no pixels",
                self.width, self.height
            ));
        }
        // Tile and pixel indices are kept in u32/i32; the pixel count bounds the frame's
        // buffers (20 bytes a pixel), which must fit in memory rather than abort.
        if self.width > 1 << 20 || self.height > 1 << 20 || self.width * self.height > MAX_PIXELS {
            return bad(format!(
                "image size {} x {} too large (at most {} pixels, 2^20 a side)",
                self.width, self.height, MAX_PIXELS
            ));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy), ("near", self.near)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} = {v} must be finite and positive"));
            }
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return bad("non-finite principal point".into());
        }
        if !(self.rotation.is_finite() && self.translation.is_finite()) {
            return bad("non-finite pose".into());
        }
        let r = self.rotation;
        let err = (r * r.transpose() - Mat3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0f32, |m, v| m.max(v.abs()));
        if err > 1e-3 || (r.determinant() - 1.0).abs() > 1e-3 {
            return bad("rotation is not a proper rotation matrix".into());
        }
        Ok(())
    }

    /// World point (metres) to camera frame (metres).
    pub fn world_to_camera(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }

    /// Camera centre in world coordinates, metres.
    pub fn eye(&self) -> Vec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// Projects a world point: its continuous pixel coordinate and its depth (camera z,
    /// metres), or `None` when it is not in front of the near plane.
    pub fn project(&self, p: Vec3) -> Option<(Vec2, f32)> {
        let c = self.world_to_camera(p);
        if c.z <= self.near {
            return None;
        }
        Some((
            Vec2::new(self.fx * c.x / c.z + self.cx, self.fy * c.y / c.z + self.cy),
            c.z,
        ))
    }

    /// Number of pixels, `width * height`.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }
}
