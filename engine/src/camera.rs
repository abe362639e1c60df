//! Pose and the PASCAL3D+ camera (METHOD.md §2).
//!
//! Mesh coordinates are z-up. The camera sits at
//! `C = d·(cos e·sin a, −cos e·cos a, sin e)` and looks at the origin; a point projects through
//! `x_c = R(a, e, θ)·(X − C)` to `col = px + M·x_c.x / −x_c.z`, `row = py − M·x_c.y / −x_c.z`,
//! where `R(a, e, θ) = Rz(θ)·Rx(−(π/2 − e))·Rz(−a)`: the in-plane rotation of the image by θ is
//! the same as rotating camera coordinates about the optical axis, so it folds into `R`.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{EngineError, Result};

/// NeMo's viewport: 3000 px focal length at a 256-px-high crop.
pub const VIEWPORT_AT_256: f64 = 3000.0;

/// Object pose relative to the camera, angles in radians, distance in CAD units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub azimuth: f64,
    pub elevation: f64,
    pub theta: f64,
    pub distance: f64,
}

impl Pose {
    pub fn new(azimuth: f64, elevation: f64, theta: f64, distance: f64) -> Self {
        Pose { azimuth, elevation, theta, distance }
    }

    /// Finite angles and a finite, positive distance.
    pub fn validate(&self) -> Result<()> {
        let angles = [self.azimuth, self.elevation, self.theta];
        if angles.iter().any(|v| !v.is_finite()) {
            return Err(EngineError::InvalidPose(format!("non-finite angle in {self:?}")));
        }
        if !(self.distance.is_finite() && self.distance > 0.0) {
            return Err(EngineError::InvalidPose(format!("distance must be finite and > 0, got {}", self.distance)));
        }
        Ok(())
    }

    /// `R(a, e, θ)`, the rotation used for projection and for the pose error.
    pub fn rotation(&self) -> Matrix3<f64> {
        rotation(self.azimuth, self.elevation, self.theta)
    }

    /// The camera centre in mesh coordinates.
    pub fn camera_centre(&self) -> Vector3<f64> {
        let (se, ce) = self.elevation.sin_cos();
        let (sa, ca) = self.azimuth.sin_cos();
        self.distance * Vector3::new(ce * sa, -ce * ca, se)
    }
}

/// `R(a, e, θ) = Rz(θ)·Rx(−(π/2 − e))·Rz(−a)`.
pub fn rotation(azimuth: f64, elevation: f64, theta: f64) -> Matrix3<f64> {
    rot_z(theta) * rot_x(-(std::f64::consts::FRAC_PI_2 - elevation)) * rot_z(-azimuth)
}

pub(crate) fn rot_x(t: f64) -> Matrix3<f64> {
    let (s, c) = t.sin_cos();
    Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
}

pub(crate) fn rot_z(t: f64) -> Matrix3<f64> {
    let (s, c) = t.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// Pinhole camera of an image (or feature map) of `width × height` pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Focal length in pixels (NeMo's "viewport" M).
    pub viewport: f64,
    /// Principal point `(px, py)` = (column, row) in continuous pixel coordinates.
    pub principal: [f64; 2],
    pub width: usize,
    pub height: usize,
}

impl Camera {
    pub fn new(viewport: f64, principal: [f64; 2], width: usize, height: usize) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(EngineError::EmptyImage { width, height });
        }
        if !(viewport.is_finite() && viewport > 0.0) || principal.iter().any(|p| !p.is_finite()) {
            return Err(EngineError::InvalidCamera(format!("viewport {viewport}, principal {principal:?}")));
        }
        Ok(Camera { viewport, principal, width, height })
    }

    /// The camera of a `height × width` crop: `M = 3000·H/256`, principal point at the centre.
    pub fn for_crop(height: usize, width: usize) -> Result<Self> {
        Camera::new(VIEWPORT_AT_256 * height as f64 / 256.0, [width as f64 / 2.0, height as f64 / 2.0], width, height)
    }

    /// The same camera on the feature grid of stride `s`: `M/s`, `(px/s, py/s)`, `⌊W/s⌋ × ⌊H/s⌋`.
    pub fn at_stride(&self, stride: usize) -> Result<Self> {
        if stride == 0 {
            return Err(EngineError::InvalidCamera("stride 0".into()));
        }
        let s = stride as f64;
        Camera::new(
            self.viewport / s,
            [self.principal[0] / s, self.principal[1] / s],
            self.width / stride,
            self.height / stride,
        )
    }
}

/// A camera looking at the object from one pose: projects mesh points to pixels.
#[derive(Clone, Copy, Debug)]
pub struct View {
    /// Rows of `R(a, e, θ)` and the translation `−R·C`, as plain arrays for the hot loop.
    rotation: [[f64; 3]; 3],
    translation: [f64; 3],
    viewport: f64,
    principal: [f64; 2],
}

impl View {
    pub fn new(camera: &Camera, pose: &Pose) -> Result<Self> {
        pose.validate()?;
        let rotation = pose.rotation();
        let translation = -(rotation * pose.camera_centre());
        Ok(View {
            rotation: std::array::from_fn(|i| std::array::from_fn(|j| rotation[(i, j)])),
            translation: translation.into(),
            viewport: camera.viewport,
            principal: camera.principal,
        })
    }

    /// `[col, row, depth]` of a mesh point; depth is the distance along the optical axis
    /// (positive in front of the camera).
    #[inline]
    pub fn project(&self, x: [f64; 3]) -> [f64; 3] {
        let [r0, r1, r2] = &self.rotation;
        let t = &self.translation;
        let cx = r0[0] * x[0] + r0[1] * x[1] + r0[2] * x[2] + t[0];
        let cy = r1[0] * x[0] + r1[1] * x[1] + r1[2] * x[2] + t[1];
        let depth = -(r2[0] * x[0] + r2[1] * x[1] + r2[2] * x[2] + t[2]);
        let m = self.viewport / depth;
        [self.principal[0] + m * cx, self.principal[1] - m * cy, depth]
    }
}

/// The distance at which `vertices` seen at `angles = [a, e, θ]` fill exactly `fill` of the
/// image in its limiting dimension, measured symmetrically about the principal point:
/// `max_v max(2|col_v − px|/W, 2|row_v − py|/H) = fill` (BENCHMARK.md §2, METHOD.md §6).
///
/// Closed form, no search: the camera looks at the origin, so with `(x, y, z) = R(a, e, θ)·X` a
/// vertex lies at depth `d − z` and `|col − px| = M|x|/(d − z)`. Its condition
/// `2M|x|/(W(d − z)) ≤ fill` reads `d ≥ z + 2M|x|/(W·fill)` (likewise for rows), and the fit
/// distance is the largest of these bounds over all vertices. This is the root that a bisection
/// on log-distance converges to, to rounding (tested), at the cost of one pass over the vertices.
pub fn fit_distance(vertices: &[[f64; 3]], angles: [f64; 3], camera: &Camera, fill: f64) -> Result<f64> {
    if vertices.is_empty() {
        return Err(EngineError::InvalidMesh("fit distance of no vertices".into()));
    }
    if !(fill.is_finite() && fill > 0.0) {
        return Err(EngineError::InvalidInput(format!("fill must be finite and > 0, got {fill}")));
    }
    Pose::new(angles[0], angles[1], angles[2], 1.0).validate()?;
    if vertices.iter().flatten().any(|c| !c.is_finite()) {
        return Err(EngineError::InvalidMesh("fit distance of non-finite vertices".into()));
    }
    let r = rotation(angles[0], angles[1], angles[2]);
    let kx = 2.0 * camera.viewport / (camera.width as f64 * fill);
    let ky = 2.0 * camera.viewport / (camera.height as f64 * fill);
    let (mut distance, mut farthest) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    for v in vertices {
        let p = r * Vector3::from(*v);
        distance = distance.max(p.z + kx * p.x.abs()).max(p.z + ky * p.y.abs());
        farthest = farthest.max(p.z);
    }
    // Every vertex must lie in front of the camera; `distance == farthest` means the limiting
    // vertex sits on the optical axis at depth 0, where the extent is undefined.
    if !(distance.is_finite() && distance > 0.0 && distance > farthest) {
        return Err(EngineError::InvalidInput(format!(
            "no distance gives fill {fill}: the vertices project onto the principal point"
        )));
    }
    Ok(distance)
}
