//! Which visible vertices fire (METHOD.md §7.3), and the small vector helpers of a run.

use super::*;

/// A model's firing test (METHOD.md §7.3) as a diagnostic against labels, with the vertex
/// features and thresholds on the host once for every image it judges.
pub struct FiringTest<'a> {
    mesh: &'a Mesh,
    crop: &'a Camera,
    stride: usize,
    c: Vec<f32>,
    tau: Vec<f32>,
    dim: usize,
}

impl<'a> FiringTest<'a> {
    pub fn new(neural_mesh: &'a NeuralMesh, crop: &'a Camera, stride: usize, threshold: Threshold) -> Result<Self> {
        let tau = match threshold {
            Threshold::Source => to_host(&neural_mesh.tau)?,
            Threshold::Fixed(t) => vec![t as f32; neural_mesh.tau.size()[0] as usize],
        };
        let (c, dim) = (to_host(&neural_mesh.vertex_features)?, neural_mesh.vertex_features.size()[1] as usize);
        Ok(FiringTest { mesh: &neural_mesh.mesh, crop, stride, c, tau, dim })
    }

    /// The share of an image's visible vertices (at `pose`) whose feature fires: the
    /// diagnostic the paper plots by azimuth.
    pub fn fired_ratio(&self, features: &Features, pose: &Pose) -> Result<f64> {
        let (visible, fired) = self.fired_at(features, pose)?;
        Ok(fired.iter().filter(|&&f| f).count() as f64 / visible.vertices.len().max(1) as f64)
    }

    /// The matches that fire at a `pseudo` pose, judged by the `truth`: `(fired, false)`, where
    /// a match is false when its vertex is hidden at the true pose or lands more than one
    /// feature cell from the matched cell (the paper's false positives, about 2% of its fired
    /// matches).
    pub fn false_matches(&self, features: &Features, pseudo: &Pose, truth: &Pose) -> Result<(usize, usize)> {
        let (visible, fired) = self.fired_at(features, pseudo)?;
        let t = visible_vertices(&mut Rasterizer::new(), self.mesh, self.crop, self.stride, truth)?;
        let true_cells: std::collections::HashMap<i64, i64> = t.vertices.into_iter().zip(t.cells).collect();
        let width = self.crop.at_stride(self.stride)?.width as i64;
        let near = |a: i64, b: i64| (a / width - b / width).abs() <= 1 && (a % width - b % width).abs() <= 1;
        let matches = visible.vertices.iter().zip(&visible.cells).zip(&fired).filter(|(_, f)| **f);
        let (mut total, mut wrong) = (0, 0);
        for ((v, &cell), _) in matches {
            total += 1;
            wrong += usize::from(!true_cells.get(v).is_some_and(|&t| near(t, cell)));
        }
        Ok((total, wrong))
    }

    /// The visible vertices at `pose` and which of them fire.
    fn fired_at(&self, features: &Features, pose: &Pose) -> Result<(VisibleVertices, Vec<bool>)> {
        let visible = visible_vertices(&mut Rasterizer::new(), self.mesh, self.crop, self.stride, pose)?;
        let fired = fires(&visible, features, &self.c, &self.tau, self.dim);
        Ok((visible, fired))
    }
}

/// Which visible vertices fire: `f·C_r > τ_r` (METHOD.md §7.3).
pub(super) fn fires(visible: &VisibleVertices, f: &Features, c: &[f32], tau: &[f32], dim: usize) -> Vec<bool> {
    visible
        .vertices
        .iter()
        .zip(&visible.cells)
        .map(|(&v, &cell)| cosine(f, cell as usize, &c[v as usize * dim..][..dim]) > tau[v as usize])
        .collect()
}

/// Which visible vertices' cells the model assigns to the object: the feature matches its vertex
/// better than every clutter vector (NeMo's occlusion inference; [`Positives::Object`]).
pub(super) fn on_object(visible: &VisibleVertices, f: &Features, c: &[f32], clutter: &[f32], dim: usize) -> Vec<bool> {
    visible
        .vertices
        .iter()
        .zip(&visible.cells)
        .map(|(&v, &cell)| {
            let object = cosine(f, cell as usize, &c[v as usize * dim..][..dim]);
            clutter.chunks(dim).all(|b| object > cosine(f, cell as usize, b))
        })
        .collect()
}

pub(super) fn tch_err(e: tch::TchError) -> EngineError {
    EngineError::InvalidInput(format!("libtorch: {e}"))
}

pub(super) fn step(
    progress: &mut dyn FnMut(Event) -> ControlFlow<()>,
    round: usize,
    phase: Phase,
    done: usize,
    total: usize,
) -> Result<()> {
    match progress(Event::Step { round, phase, done, total }) {
        ControlFlow::Continue(()) => Ok(()),
        ControlFlow::Break(()) => Err(EngineError::Cancelled),
    }
}

/// `f(cell) · c` for a channel-major feature map.
pub(super) fn cosine(f: &Features, cell: usize, c: &[f32]) -> f32 {
    let hw = f.height * f.width;
    c.iter().enumerate().map(|(k, ck)| f.data[k * hw + cell] * ck).sum()
}

pub(super) fn add_feature(sum: &mut [f32], f: &Features, cell: usize) {
    let hw = f.height * f.width;
    sum.iter_mut().enumerate().for_each(|(k, s)| *s += f.data[k * hw + cell]);
}

pub(super) fn normalise(row: &mut [f32]) {
    let norm = row.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    row.iter_mut().for_each(|x| *x /= norm);
}

pub(super) fn pose_changes(a: &[Pose], b: &[Pose]) -> Vec<f64> {
    a.iter().zip(b).map(|(p, q)| rotation_error(&p.rotation(), &q.rotation()).to_degrees()).collect()
}

pub(super) fn mean(v: &[f64]) -> f64 {
    if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 }
}

/// The `q` quantile (nearest rank) of `v`; 0 for an empty `v`.
pub(super) fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(((s.len().max(1) - 1) as f64 * q).round() as usize).copied().unwrap_or(0.0)
}
