//! The analytic gradient of the render-and-compare loss with respect to `(a, e, θ, log d)`.
//!
//! Per covered pixel `q` whose face has vertices `k = 0, 1, 2` at screen points `p_k`, depths
//! `z_k` and similarities `s_k = S[v_k, q]`: the screen barycentrics are `l_k = E_k/A` with
//! `E_k = edge(p_{k+1}, p_{k+2}, q)` and `A = ΣE`, the perspective-correct ones
//! `w_k = (l_k/z_k)/H` with `H = Σ l_j/z_j`, and `obj = Σ w_k s_k`. Then
//!
//! ```text
//! ∂obj/∂z_k = −(s_k − obj)·w_k/z_k
//! ∂obj/∂l_k = c_k = (s_k − obj)/(z_k·H),  and with c̄ = Σ c_k l_k:  d obj = Σ_k (c_k − c̄)·dE_k/A
//! ```
//!
//! and `dE_k` is bilinear in the two screen points of edge k. A pixel adds to the loss only where
//! `obj > clu` (elsewhere `max(obj, clu)` does not depend on the pose). The per-vertex sums
//! `∂L/∂(col, row, depth)` are then chained through the projection: with `(x, y, z) = R·X` and
//! depth `δ = d − z` (the camera looks at the origin), `col = px + M·x/δ`, `row = py − M·y/δ`.

use nalgebra::{Matrix3, Vector3};

use super::caster::{CuboidCaster, PoseGradient, Rays};
use super::{Problem, Scratch};
use crate::camera::{Pose, rot_x, rot_z};
use crate::error::Result;
use crate::raster::{NO_FACE, edge};

/// `∂R/∂a`, `∂R/∂e`, `∂R/∂θ` of `R = Rz(θ)·Rx(e − π/2)·Rz(−a)`.
pub(super) fn rotation_derivatives(pose: &Pose) -> [Matrix3<f64>; 3] {
    // Generators: d/dt Rz(t) = Kz·Rz(t), d/dt Rx(t) = Kx·Rx(t).
    let kz = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let kx = Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
    let (rt, rx, ra) = (rot_z(pose.theta), rot_x(pose.elevation - std::f64::consts::FRAC_PI_2), rot_z(-pose.azimuth));
    [-(rt * rx * kz * ra), rt * kx * rx * ra, kz * rt * rx * ra]
}

pub(super) fn loss_and_gradient(problem: &Problem, scratch: &mut Scratch, pose: &Pose) -> Result<(f64, [f64; 4])> {
    if let Some(caster) = &problem.caster {
        return cast(problem, caster, &mut scratch.runs, pose, true);
    }
    let Scratch { raster, vertex_grad, .. } = scratch;
    let frags = raster.render_faces(problem.mesh, &problem.grid, pose)?;
    let (faces, r, width) = (problem.mesh.faces(), problem.vertices, frags.width);
    let projected = frags.projected;
    vertex_grad.clear();
    vertex_grad.resize(r, [0.0; 3]);

    // Pass 1: the loss, and ∂(Σ_p obj)/∂(col, row, depth) per vertex over the active pixels.
    let mut sum = 0.0f64;
    for (p, (&f, w)) in frags.face.iter().zip(frags.barycentric).enumerate() {
        if f == NO_FACE {
            continue;
        }
        let idx = faces[f as usize].map(|v| v as usize);
        let s32 = idx.map(|v| problem.similarity.get(p, v));
        let obj32 = w[0] * s32[0] + w[1] * s32[1] + w[2] * s32[2];
        let clu = problem.clutter[p];
        sum += f64::from(obj32.max(clu) - problem.clutter_pos[p]);
        if obj32 <= clu {
            continue;
        }
        let q = [(p % width) as f64 + 0.5, (p / width) as f64 + 0.5];
        let v = idx.map(|i| projected[i]);
        let pt = v.map(|v| [v[0], v[1]]);
        let z = v.map(|v| v[2]);
        let e = [edge(pt[1], pt[2], q), edge(pt[2], pt[0], q), edge(pt[0], pt[1], q)];
        let area = e[0] + e[1] + e[2];
        let l = e.map(|e| e / area);
        let h = [l[0] / z[0], l[1] / z[1], l[2] / z[2]];
        let hs = h[0] + h[1] + h[2];
        let wk = h.map(|h| h / hs);
        let s = s32.map(f64::from);
        let obj = wk[0] * s[0] + wk[1] * s[1] + wk[2] * s[2];
        let c = [0, 1, 2].map(|k| (s[k] - obj) / (z[k] * hs));
        let cbar = c[0] * l[0] + c[1] * l[1] + c[2] * l[2];
        for k in 0..3 {
            let (ia, ib) = ((k + 1) % 3, (k + 2) % 3);
            let coef = (c[k] - cbar) / area;
            let (a, b) = (pt[ia], pt[ib]);
            let ga = &mut vertex_grad[idx[ia]];
            ga[0] += coef * (b[1] - q[1]);
            ga[1] += coef * (q[0] - b[0]);
            let gb = &mut vertex_grad[idx[ib]];
            gb[0] += coef * (q[1] - a[1]);
            gb[1] += coef * (a[0] - q[0]);
            vertex_grad[idx[k]][2] -= (s[k] - obj) * wk[k] / z[k];
        }
    }
    let loss = 1.0 - (problem.base + sum) / problem.pixels as f64;

    // Pass 2: chain through the projection.
    let rotation = pose.rotation();
    let derivs = rotation_derivatives(pose);
    let (m, d) = (problem.grid.viewport, pose.distance);
    let mut grad = [0.0f64; 4];
    for (k, g) in vertex_grad.iter().enumerate() {
        if *g == [0.0; 3] {
            continue;
        }
        let x = Vector3::from(problem.mesh.vertices()[k]);
        let rx = rotation * x;
        let depth = d - rx.z;
        let inv = 1.0 / depth;
        // d col = M(dx/δ − x·dδ/δ²), d row = −M(dy/δ − y·dδ/δ²).
        let chain = |dx: f64, dy: f64, ddepth: f64| {
            let dcol = m * (dx - rx.x * ddepth * inv) * inv;
            let drow = -m * (dy - rx.y * ddepth * inv) * inv;
            g[0] * dcol + g[1] * drow + g[2] * ddepth
        };
        for (j, dr) in derivs.iter().enumerate() {
            let dx = dr * x;
            grad[j] += chain(dx.x, dx.y, -dx.z);
        }
        grad[3] += chain(0.0, 0.0, d); // ∂δ/∂log d = d
    }
    let scale = -1.0 / problem.pixels as f64;
    Ok((loss, grad.map(|g| g * scale)))
}

/// The loss (and with `gradient`, its gradient) by ray casting the cuboid: the same sums as the
/// rasteriser's path, in the same cell order, with the gradient of `caster`'s module docs.
pub(super) fn cast(
    problem: &Problem,
    caster: &CuboidCaster,
    runs: &mut Vec<[usize; 3]>,
    pose: &Pose,
    gradient: bool,
) -> Result<(f64, [f64; 4])> {
    let camera = &problem.grid;
    caster.runs(camera, pose, runs)?;
    let rays = Rays::new(camera, pose);
    let mut sum = 0.0f64;
    let mut grad = PoseGradient::default();
    for &[row, col0, col1] in runs.iter() {
        for col in col0..col1 {
            let Some(hit) = caster.cast(&rays, col, row) else { continue };
            let p = row * camera.width + col;
            let s32 = hit.vertices.map(|v| problem.similarity.get(p, v as usize));
            let w = hit.weights.map(|w| w as f32);
            let obj = w[0] * s32[0] + w[1] * s32[1] + w[2] * s32[2];
            let clu = problem.clutter[p];
            sum += f64::from(obj.max(clu) - problem.clutter_pos[p]);
            if gradient && obj > clu {
                grad.add(&hit, s32.map(f64::from), [col as f64 + 0.5, row as f64 + 0.5], camera, pose.distance);
            }
        }
    }
    let loss = 1.0 - (problem.base + sum) / problem.pixels as f64;
    let scale = -1.0 / problem.pixels as f64;
    Ok((loss, if gradient { grad.finish(pose).map(|g| g * scale) } else { [0.0; 4] }))
}
