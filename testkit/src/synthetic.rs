//! Synthetic render-and-compare problems whose pose is known: the solver's tests and benchmark.
//!
//! The vertex features are a smooth random function of vertex position (nearby vertices are
//! similar, as in a trained model): `C(X) = normalise(W·cos(Ω·X + b))` with random Fourier
//! features, `Ω ~ N(0, σ²)`. An image's features are the mesh rendered at the true pose on a
//! grid `supersample` times finer than the feature grid (per fine cell the barycentric mix of
//! its face's vertex features, renormalised; elsewhere a clutter-like vector near `β`), averaged
//! down to the feature grid, perturbed by Gaussian noise and renormalised. Rendering finer than
//! the solver does keeps the test from being an inverse crime: boundary cells mix object and
//! clutter, and the solver's pixel-centre samples never reproduce the image exactly.

use udapose_engine::camera::{Camera, Pose, fit_distance};
use udapose_engine::error::{EngineError, Result};
use udapose_engine::mesh::{Cuboid, Mesh, TARGET_VERTICES};
use udapose_engine::raster::{NO_FACE, Rasterizer};

use udapose_engine::solver::{FeatureMap, NeuralMeshView};

/// The SynCar-OOD source car cuboid (METHOD.md §3): 0.433 × 0.992 × 0.270.
pub const CAR_DIMENSIONS: [f64; 3] = [0.433, 0.992, 0.270];

/// A small deterministic generator (SplitMix64), so fixtures need no extra dependency.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u = 1.0 - self.uniform(); // (0, 1]
        let v = self.uniform();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// A uniformly random unit vector.
    pub fn unit_vector(&mut self, dim: usize) -> Vec<f32> {
        let mut v: Vec<f32> = (0..dim).map(|_| self.normal() as f32).collect();
        normalise(&mut v);
        v
    }
}

fn normalise(v: &mut [f32]) {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    v.iter_mut().for_each(|x| *x /= n);
}

/// A neural mesh with smooth random vertex features and one clutter vector.
#[derive(Clone, Debug)]
pub struct SyntheticModel {
    pub mesh: Mesh,
    pub dim: usize,
    /// R × D, unit rows.
    pub vertex_features: Vec<f32>,
    /// 1 × D, unit.
    pub clutter: Vec<f32>,
}

impl SyntheticModel {
    /// The SynCar car cuboid with `dim`-dimensional features whose spatial frequency is
    /// `frequency` (radians per CAD unit; 5 makes features decorrelate over about 0.3 units).
    pub fn car(dim: usize, frequency: f64, rng: &mut SplitMix64) -> Result<Self> {
        if dim == 0 || !(frequency.is_finite() && frequency > 0.0) {
            return Err(EngineError::InvalidInput(format!("dim {dim}, frequency {frequency}")));
        }
        let mesh = Cuboid::from_dimensions(CAR_DIMENSIONS)?.mesh(TARGET_VERTICES);
        let waves = 64;
        let omega: Vec<[f64; 3]> = (0..waves).map(|_| [0; 3].map(|_| frequency * rng.normal())).collect();
        let phase: Vec<f64> = (0..waves).map(|_| rng.range(0.0, std::f64::consts::TAU)).collect();
        let mix: Vec<f64> = (0..dim * waves).map(|_| rng.normal()).collect();
        let mut vertex_features = Vec::with_capacity(mesh.vertices().len() * dim);
        for x in mesh.vertices() {
            let basis: Vec<f64> = (0..waves)
                .map(|j| (omega[j][0] * x[0] + omega[j][1] * x[1] + omega[j][2] * x[2] + phase[j]).cos())
                .collect();
            let mut f: Vec<f32> =
                (0..dim).map(|d| (0..waves).map(|j| mix[d * waves + j] * basis[j]).sum::<f64>() as f32).collect();
            normalise(&mut f);
            vertex_features.extend(f);
        }
        let clutter = rng.unit_vector(dim);
        Ok(SyntheticModel { mesh, dim, vertex_features, clutter })
    }

    pub fn model(&self) -> Result<NeuralMeshView<'_>> {
        NeuralMeshView::new(&self.mesh, &self.vertex_features, &self.clutter, self.dim)
    }
}

/// How a synthetic feature map departs from the clean rendering.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageSettings {
    /// Standard deviation of the Gaussian noise vector (its expected norm) added to every
    /// feature before renormalisation: 0.5 leaves object features at cosine ≈ 0.9 to the clean one.
    pub noise: f64,
    /// Spread of background features around the clutter vector: `normalise(β + spread·n)` with
    /// `n` of expected norm 1; 1.0 puts them at cosine ≈ 0.7 to `β`.
    pub clutter_spread: f64,
    /// Fine grid cells per feature cell along each axis.
    pub supersample: usize,
}

impl Default for ImageSettings {
    fn default() -> Self {
        ImageSettings { noise: 0.5, clutter_spread: 1.0, supersample: 2 }
    }
}

/// A synthetic feature map (`dim × height × width`, channel-major) and its true pose.
#[derive(Clone, Debug)]
pub struct SyntheticImage {
    pub pose: Pose,
    pub features: Vec<f32>,
    pub dim: usize,
    pub height: usize,
    pub width: usize,
}

impl SyntheticImage {
    pub fn feature_map(&self) -> Result<FeatureMap<'_>> {
        FeatureMap::new(&self.features, self.dim, self.height, self.width)
    }
}

/// A pose from SynCar-OOD's source distribution (BENCHMARK.md §2): azimuth U(0, 2π), elevation
/// U(−10°, 40°), θ ~ N(0, 5°) clipped to ±15°, at the fit distance of a fill U(0.80, 0.95).
pub fn source_pose(rng: &mut SplitMix64, mesh: &Mesh, crop: &Camera) -> Result<Pose> {
    let azimuth = rng.range(0.0, std::f64::consts::TAU);
    let elevation = rng.range(-10.0, 40.0).to_radians();
    let theta = (5.0 * rng.normal()).clamp(-15.0, 15.0).to_radians();
    let fill = rng.range(0.80, 0.95);
    let distance = fit_distance(mesh.vertices(), [azimuth, elevation, theta], crop, fill)?;
    Ok(Pose::new(azimuth, elevation, theta, distance))
}

/// The features of `model` seen at `pose` through `crop`, on the grid of `stride`.
pub fn render_features(
    model: &SyntheticModel,
    crop: &Camera,
    stride: usize,
    pose: &Pose,
    settings: &ImageSettings,
    rng: &mut SplitMix64,
) -> Result<SyntheticImage> {
    let ss = settings.supersample;
    if ss == 0 || !stride.is_multiple_of(ss) {
        return Err(EngineError::InvalidInput(format!("supersample {ss} must divide stride {stride}")));
    }
    let grid = crop.at_stride(stride)?;
    let fine = crop.at_stride(stride / ss)?;
    if (fine.width, fine.height) != (grid.width * ss, grid.height * ss) {
        return Err(EngineError::InvalidInput(format!(
            "a {}×{} crop is not a whole number of {stride}-pixel cells",
            crop.height, crop.width
        )));
    }
    let (d, p) = (model.dim, grid.width * grid.height);
    let mut raster = Rasterizer::new();
    let frags = raster.render_faces(&model.mesh, &fine, pose)?;
    let faces = model.mesh.faces();
    let mut sum = vec![0.0f32; p * d];
    let mut f = vec![0.0f32; d];
    for (i, (&face, w)) in frags.face.iter().zip(frags.barycentric).enumerate() {
        if face == NO_FACE {
            let spread = settings.clutter_spread / (d as f64).sqrt();
            f.iter_mut().zip(&model.clutter).for_each(|(f, &b)| *f = b + (spread * rng.normal()) as f32);
        } else {
            let [a, b, c] = faces[face as usize].map(|v| v as usize * d);
            let vf = &model.vertex_features;
            (0..d).for_each(|k| f[k] = w[0] * vf[a + k] + w[1] * vf[b + k] + w[2] * vf[c + k]);
        }
        normalise(&mut f);
        let (row, col) = (i / fine.width / ss, i % fine.width / ss);
        let cell = &mut sum[(row * grid.width + col) * d..][..d];
        cell.iter_mut().zip(&f).for_each(|(s, &x)| *s += x);
    }
    let mut features = vec![0.0f32; d * p];
    let noise = settings.noise / (d as f64).sqrt();
    for (px, cell) in sum.chunks_exact_mut(d).enumerate() {
        normalise(cell);
        cell.iter_mut().for_each(|x| *x += (noise * rng.normal()) as f32);
        normalise(cell);
        (0..d).for_each(|k| features[k * p + px] = cell[k]);
    }
    Ok(SyntheticImage { pose: *pose, features, dim: d, height: grid.height, width: grid.width })
}
