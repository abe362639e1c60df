//! The cuboid's own renderer: one ray per feature cell, in closed form.
//!
//! A category's neural mesh is a box whose six sides are regular vertex grids
//! ([`Cuboid::mesh`]), so what the z-buffer finds at a pixel centre can be computed directly:
//! the ray through the centre enters the box through one side (the slab test), the entry point
//! falls in one grid cell, and the cell's diagonal picks the triangle. On a planar triangle the
//! barycentrics are affine in the 3D point, so the entry point's barycentrics *are* the
//! rasteriser's perspective-correct ones. No vertex is projected and no triangle set up: a pose
//! evaluation costs a few dozen flops per cell inside the box's projected bounds, where the
//! general rasteriser spent most of its time on the ~2000 triangles of a 1054-vertex mesh
//! (`reports/solver.md`).
//!
//! The gradient follows from the same picture. With `Y` the entry point in camera coordinates
//! (`Y = R·X`), holding the cell fixed, the point moves with the pose as
//! `dX = (I − U·nᵀ/(n·U))·(dR)ᵀ·Y` (it slides along the ray to stay on the side of normal `n`;
//! `U` is the ray's direction in mesh coordinates), so with `g = ∂obj/∂X` (in the side's plane)
//! and `g' = g − (g·U/U_n)·n`: `∂obj/∂p = Yᵀ·(∂R/∂p)·g'` for each angle `p`, and
//! `∂obj/∂log d = d·(R·g')_z`. Summed over the active cells as `A = Σ Y·g'ᵀ` and `Σ g'`, the
//! pose gradient is four contractions at the end.

use nalgebra::Matrix3;

use super::gradient::rotation_derivatives;
use crate::camera::{Camera, Pose, View};
use crate::error::Result;
use crate::mesh::{Cuboid, Mesh};

/// A mesh known to be [`Cuboid::mesh_with_counts`] of its bounding box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CuboidCaster {
    min: [f64; 3],
    max: [f64; 3],
    /// Vertex samples along x, y, z.
    counts: [usize; 3],
    /// First vertex of each side, indexed `2·axis + outward` as `Cuboid::mesh` lays them out.
    first: [u32; 6],
    /// Grid cells per unit length along x, y, z (hoisted out of the per-cell cast).
    per_unit: [f64; 3],
}

/// The axis after each axis, cyclically (`(k + 1) % 3` without a division in the hot loop).
const NEXT: [usize; 3] = [1, 2, 0];

/// Where a ray enters the box: the triangle's vertices, their weights, and the weights'
/// derivatives along the side's two in-plane axes.
#[derive(Clone, Copy, Debug)]
pub(super) struct Hit {
    pub vertices: [u32; 3],
    pub weights: [f64; 3],
    pub dw_du: [f64; 3],
    pub dw_dv: [f64; 3],
    /// The axis the entered side is normal to.
    pub axis: usize,
    /// The ray's direction in mesh coordinates and the entry's depth (the ray's parameter:
    /// the direction has optical-axis component 1).
    pub dir: [f64; 3],
    pub depth: f64,
}

/// One pose's rays: through the centre of cell `(col, row)` the ray is `origin + t·dir` with
/// `dir = base + (col + ½)·dcol + (row + ½)·drow`, in mesh coordinates, `t` the depth.
#[derive(Clone, Copy, Debug)]
pub(super) struct Rays {
    origin: [f64; 3],
    base: [f64; 3],
    dcol: [f64; 3],
    drow: [f64; 3],
}

impl Rays {
    /// The camera at `Rᵀ·(0, 0, d)` looking along `−z` of its frame; a cell centre `(c, r)` is
    /// the camera direction `((c − px)/M, −(r − py)/M, −1)`, turned into mesh coordinates.
    pub fn new(camera: &Camera, pose: &Pose) -> Self {
        let rot = pose.rotation();
        let row = |i: usize| [rot[(i, 0)], rot[(i, 1)], rot[(i, 2)]];
        let (r0, r1, r2) = (row(0), row(1), row(2));
        let m = camera.viewport;
        let [px, py] = camera.principal;
        let at_origin: [f64; 3] = std::array::from_fn(|k| (0.5 - px) / m * r0[k] - (0.5 - py) / m * r1[k] - r2[k]);
        Rays {
            origin: r2.map(|c| pose.distance * c),
            base: at_origin,
            dcol: r0.map(|c| c / m),
            drow: r1.map(|c| -c / m),
        }
    }

    #[inline]
    fn dir(&self, col: usize, row: usize) -> [f64; 3] {
        let (c, r) = (col as f64, row as f64);
        std::array::from_fn(|k| self.base[k] + c * self.dcol[k] + r * self.drow[k])
    }
}

impl CuboidCaster {
    /// The caster of `mesh` when it is exactly the cuboid mesh of its bounding box (same
    /// vertices, same faces, same order); `None` for any other mesh, which the rasteriser
    /// renders instead.
    pub fn detect(mesh: &Mesh) -> Option<Self> {
        let vs = mesh.vertices();
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for v in vs {
            for k in 0..3 {
                min[k] = min[k].min(v[k]);
                max[k] = max[k].max(v[k]);
            }
        }
        if (0..3).any(|k| max[k] <= min[k]) {
            return None;
        }
        let counts = [0, 1, 2].map(|k| {
            let mut c: Vec<u64> = vs.iter().map(|v| v[k].to_bits()).collect();
            c.sort_unstable();
            c.dedup();
            c.len()
        });
        if counts.iter().any(|&n| n < 2) || vs.len() > u32::MAX as usize {
            return None;
        }
        let cuboid = Cuboid { min, max };
        if cuboid.mesh_with_counts(counts) != *mesh {
            return None;
        }
        let mut first = [0u32; 6];
        let mut next = 0usize;
        for axis in 0..3 {
            let side = counts[(axis + 1) % 3] * counts[(axis + 2) % 3];
            for outward in 0..2 {
                first[2 * axis + outward] = next as u32;
                next += side;
            }
        }
        let per_unit = std::array::from_fn(|k| (counts[k] - 1) as f64 / (max[k] - min[k]));
        Some(CuboidCaster { min, max, counts, first, per_unit })
    }

    /// The cells whose centres can see the box, as `[row, first col, end col)` runs: per row,
    /// the cells inside the box's silhouette, the convex polygon its projected corners span,
    /// whose edges are box edges (a convex solid's outline is made of its own edges); widened
    /// by a hair so that rounding never drops a cell the ray would hit. Every cell when a
    /// corner is not in front of the camera.
    pub(super) fn runs(&self, camera: &Camera, pose: &Pose, out: &mut Vec<[usize; 3]>) -> Result<()> {
        out.clear();
        let view = View::new(camera, pose)?;
        let mut corners = [[0.0f64; 2]; 8];
        for (i, c) in corners.iter_mut().enumerate() {
            let x = std::array::from_fn(|k| if i >> k & 1 == 0 { self.min[k] } else { self.max[k] });
            let [col, row, depth] = view.project(x);
            if depth <= 0.0 {
                out.extend((0..camera.height).map(|r| [r, 0, camera.width]));
                return Ok(());
            }
            *c = [col, row];
        }
        const HAIR: f64 = 1e-6;
        let width = camera.width as f64;
        for row in 0..camera.height {
            let y = row as f64 + 0.5;
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            // The 12 box edges: corners differing in one coordinate bit.
            for a in 0..8 {
                for b in (0..3).map(|k| a | 1 << k).filter(|&b| b != a) {
                    let ([xa, ya], [xb, yb]) = (corners[a], corners[b]);
                    if (ya - y) * (yb - y) > 0.0 {
                        continue;
                    }
                    let (x0, x1) = if ya == yb {
                        (xa.min(xb), xa.max(xb))
                    } else {
                        let x = xa + (y - ya) * (xb - xa) / (yb - ya);
                        (x, x)
                    };
                    (lo, hi) = (lo.min(x0), hi.max(x1));
                }
            }
            // Cell c's centre is c + ½: the first centre at or right of lo, the last at or left of hi.
            let first = (lo - 0.5 - HAIR).ceil().clamp(0.0, width) as usize;
            let end = ((hi - 0.5 + HAIR).floor() + 1.0).clamp(0.0, width) as usize;
            if lo <= hi && end > first {
                out.push([row, first, end]);
            }
        }
        Ok(())
    }

    /// Where the ray through cell `(col, row)`'s centre enters the box, if it does in front of
    /// the camera.
    #[inline]
    pub(super) fn cast(&self, rays: &Rays, col: usize, row: usize) -> Option<Hit> {
        let dir = rays.dir(col, row);
        let o = rays.origin;
        let (mut t_in, mut t_out, mut axis) = (f64::NEG_INFINITY, f64::INFINITY, 3);
        for k in 0..3 {
            if dir[k] == 0.0 {
                if o[k] < self.min[k] || o[k] > self.max[k] {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / dir[k];
            let (a, b) = ((self.min[k] - o[k]) * inv, (self.max[k] - o[k]) * inv);
            let (near, far) = if inv > 0.0 { (a, b) } else { (b, a) };
            if near > t_in {
                (t_in, axis) = (near, k);
            }
            t_out = t_out.min(far);
        }
        if axis == 3 || t_in >= t_out || t_in <= 0.0 {
            return None;
        }
        // A ray going down the axis enters through the side at its maximum (outward normal +).
        let outward = usize::from(dir[axis] < 0.0);
        let (u, v) = (NEXT[axis], NEXT[NEXT[axis]]);
        let (nu, nv) = (self.counts[u], self.counts[v]);
        let cell = |k: usize, n: usize| {
            let per_unit = self.per_unit[k];
            let f = (o[k] + t_in * dir[k] - self.min[k]) * per_unit;
            // `as` truncates and saturates: floor for f ≥ 0, and 0 for an entry a rounding error
            // outside the box (no libm call in the hot loop).
            let i = (f as usize).min(n - 2);
            (i, f - i as f64, per_unit)
        };
        let ((i, fu, su), (j, fv, sv)) = (cell(u, nu), cell(v, nv));
        let id = |i: usize, j: usize| self.first[2 * axis + outward] + (i * nv + j) as u32;
        let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
        // The cell's diagonal runs a–c: triangle (a, b, c) below it (fu ≥ fv), (a, c, d) above.
        let hit = if fu >= fv {
            Hit {
                vertices: [a, b, c],
                weights: [1.0 - fu, fu - fv, fv],
                dw_du: [-su, su, 0.0],
                dw_dv: [0.0, -sv, sv],
                axis,
                dir,
                depth: t_in,
            }
        } else {
            Hit {
                vertices: [a, c, d],
                weights: [1.0 - fv, fu, fv - fu],
                dw_du: [0.0, su, -su],
                dw_dv: [-sv, 0.0, sv],
                axis,
                dir,
                depth: t_in,
            }
        };
        Some(hit)
    }
}

/// Sums of the active cells' `∂obj/∂X` terms, contracted into the pose gradient by
/// [`PoseGradient::finish`].
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct PoseGradient {
    /// `Σ Y·g'ᵀ`.
    outer: [[f64; 3]; 3],
    /// `Σ g'`.
    sum: [f64; 3],
}

impl PoseGradient {
    /// Adds one active cell: `s` the similarities of the hit's vertices, `centre` the cell
    /// centre `[col, row]` on `camera`.
    #[inline]
    pub fn add(&mut self, hit: &Hit, s: [f64; 3], centre: [f64; 2], camera: &Camera, distance: f64) {
        let gu = s[0] * hit.dw_du[0] + s[1] * hit.dw_du[1] + s[2] * hit.dw_du[2];
        let gv = s[0] * hit.dw_dv[0] + s[1] * hit.dw_dv[1] + s[2] * hit.dw_dv[2];
        let (n, u, v) = (hit.axis, NEXT[hit.axis], NEXT[NEXT[hit.axis]]);
        let mut g = [0.0; 3];
        g[u] = gu;
        g[v] = gv;
        g[n] = -(gu * hit.dir[u] + gv * hit.dir[v]) / hit.dir[n];
        let t = hit.depth;
        let m = camera.viewport;
        let y = [t * (centre[0] - camera.principal[0]) / m, -t * (centre[1] - camera.principal[1]) / m, distance - t];
        for (row, yi) in self.outer.iter_mut().zip(y) {
            for (a, gj) in row.iter_mut().zip(g) {
                *a += yi * gj;
            }
        }
        for (a, gj) in self.sum.iter_mut().zip(g) {
            *a += gj;
        }
    }

    /// `∂(Σ obj)/∂(a, e, θ, log d)`.
    pub fn finish(&self, pose: &Pose) -> [f64; 4] {
        let contract = |d: &Matrix3<f64>| {
            (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).map(|(i, j)| d[(i, j)] * self.outer[i][j]).sum::<f64>()
        };
        let [da, de, dt] = rotation_derivatives(pose);
        let rot = pose.rotation();
        let logd = pose.distance * (0..3).map(|j| rot[(2, j)] * self.sum[j]).sum::<f64>();
        [contract(&da), contract(&de), contract(&dt), logd]
    }
}
