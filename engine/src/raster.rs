//! Z-buffered triangle rasteriser: per-pixel face, perspective-correct barycentrics and depth,
//! and per-vertex visibility. The hot path of inference and training.
//!
//! Pixel (row i, col j) is sampled at its centre `(j + 0.5, i + 0.5)` (METHOD.md §2). Pixels on a
//! shared edge belong to exactly one triangle (top-left rule), so a closed mesh has no cracks and
//! no double coverage. All buffers live in the [`Rasterizer`] and are reused across calls.

use rayon::prelude::*;

use crate::camera::{Camera, Pose, View};
use crate::error::{EngineError, Result};
use crate::mesh::Mesh;

/// Face index of a pixel that no triangle covers.
pub const NO_FACE: u32 = u32::MAX;
/// Depth tolerance of the visibility test, relative to the mesh's depth range (METHOD.md §5).
pub const VISIBILITY_TOLERANCE: f64 = 1e-3;
/// Images with fewer pixels are rasterised on the calling thread: below this, splitting into
/// row bands costs more than it saves (measured by `cargo bench -p udapose-engine`).
pub const PARALLEL_MIN_PIXELS: usize = 64 * 1024;

/// The rasteriser's result, borrowed from its buffers (row-major, `width × height`).
#[derive(Debug)]
pub struct Fragments<'a> {
    pub width: usize,
    pub height: usize,
    /// Front-most face per pixel, or [`NO_FACE`].
    pub face: &'a [u32],
    /// Perspective-correct barycentric weights of the face's three vertices (sum 1).
    pub barycentric: &'a [[f32; 3]],
    /// Depth along the optical axis; `f32::INFINITY` where no face covers the pixel.
    pub depth: &'a [f32],
    /// Per vertex `[col, row, depth]`.
    pub projected: &'a [[f64; 3]],
    /// Per vertex: inside the image and not hidden by a nearer face.
    pub visible: &'a [bool],
}

/// Screen-space set-up of one triangle that can cover pixels.
#[derive(Clone, Copy, Debug)]
struct Triangle {
    face: u32,
    p: [[f64; 2]; 3],
    inv_depth: [f64; 3],
    inv_area: f64,
    /// Whether a pixel centre exactly on the edge opposite vertex k belongs to this triangle.
    owns_edge: [bool; 3],
    /// Pixel-centre ranges `[first, end)` to test.
    rows: [usize; 2],
    cols: [usize; 2],
    /// Pixel cells `[first, end)` per axis (col, row) the bounding box overlaps.
    cells: [[usize; 2]; 2],
    /// Bounding box `[[col_lo, row_lo], [col_hi, row_hi]]` and nearest depth: cheap rejections
    /// for point queries.
    bbox: [[f64; 2]; 2],
    near: f64,
}

/// Reusable rasteriser: after the first call at a given size no call allocates.
#[derive(Debug)]
pub struct Rasterizer {
    parallel_min_pixels: usize,
    width: usize,
    height: usize,
    face: Vec<u32>,
    barycentric: Vec<[f32; 3]>,
    depth: Vec<f32>,
    projected: Vec<[f64; 3]>,
    visible: Vec<bool>,
    triangles: Vec<Triangle>,
    /// Triangles overlapping each pixel cell (CSR: `cell_start[c]..cell_start[c + 1]` into
    /// `cell_triangles`), for exact point queries in the visibility test.
    cell_start: Vec<u32>,
    cell_triangles: Vec<u32>,
}

impl Default for Rasterizer {
    fn default() -> Self {
        Self::with_parallel_threshold(PARALLEL_MIN_PIXELS)
    }
}

impl Rasterizer {
    pub fn new() -> Self {
        Self::default()
    }

    /// A rasteriser that splits images of at least `min_pixels` pixels into row bands drawn in
    /// parallel (`usize::MAX`: never).
    pub fn with_parallel_threshold(min_pixels: usize) -> Self {
        Rasterizer {
            parallel_min_pixels: min_pixels,
            width: 0,
            height: 0,
            face: Vec::new(),
            barycentric: Vec::new(),
            depth: Vec::new(),
            projected: Vec::new(),
            visible: Vec::new(),
            triangles: Vec::new(),
            cell_start: Vec::new(),
            cell_triangles: Vec::new(),
        }
    }

    /// Renders `mesh` seen from `pose` through `camera`, with per-vertex visibility.
    pub fn render(&mut self, mesh: &Mesh, camera: &Camera, pose: &Pose) -> Result<Fragments<'_>> {
        self.project_and_rasterize(mesh, camera, pose)?;
        self.update_visibility();
        Ok(self.fragments())
    }

    /// Like [`Rasterizer::render`] without the visibility test (`visible` is empty): what a pose
    /// solver needs for each pose it tries.
    pub fn render_faces(&mut self, mesh: &Mesh, camera: &Camera, pose: &Pose) -> Result<Fragments<'_>> {
        self.project_and_rasterize(mesh, camera, pose)?;
        self.visible.clear();
        Ok(self.fragments())
    }

    fn project_and_rasterize(&mut self, mesh: &Mesh, camera: &Camera, pose: &Pose) -> Result<()> {
        check_size(camera.width, camera.height)?;
        let view = View::new(camera, pose)?;
        self.projected.clear();
        self.projected.extend(mesh.vertices().iter().map(|&v| view.project(v)));
        self.rasterize(mesh.faces(), camera.width, camera.height, mesh.is_closed_outward());
        Ok(())
    }

    /// Renders triangles already in screen space: `projected[k] = [col, row, depth]`.
    pub fn render_projected(
        &mut self,
        projected: &[[f64; 3]],
        faces: &[[u32; 3]],
        width: usize,
        height: usize,
    ) -> Result<Fragments<'_>> {
        check_size(width, height)?;
        if let Some(f) = faces.iter().position(|f| f.iter().any(|&i| i as usize >= projected.len())) {
            return Err(EngineError::InvalidMesh(format!("face {f} indexes past {} vertices", projected.len())));
        }
        self.projected.clear();
        self.projected.extend_from_slice(projected);
        self.rasterize(faces, width, height, false);
        self.update_visibility();
        Ok(self.fragments())
    }

    fn fragments(&self) -> Fragments<'_> {
        Fragments {
            width: self.width,
            height: self.height,
            face: &self.face,
            barycentric: &self.barycentric,
            depth: &self.depth,
            projected: &self.projected,
            visible: &self.visible,
        }
    }

    /// With `cull_back_faces` (closed, outward-wound meshes only) faces turned away from the
    /// camera are skipped: they are always behind a front face, so nothing changes but the time.
    fn rasterize(&mut self, faces: &[[u32; 3]], width: usize, height: usize, cull_back_faces: bool) {
        let n = width * height;
        (self.width, self.height) = (width, height);
        self.face.clear();
        self.face.resize(n, NO_FACE);
        self.barycentric.clear();
        self.barycentric.resize(n, [0.0; 3]);
        self.depth.clear();
        self.depth.resize(n, f32::INFINITY);

        self.triangles.clear();
        let projected = &self.projected;
        self.triangles.extend(faces.iter().enumerate().filter_map(|(f, idx)| {
            Triangle::new(f as u32, idx.map(|i| projected[i as usize]), width, height, cull_back_faces)
        }));

        let bands = if n < self.parallel_min_pixels { 1 } else { rayon::current_num_threads() * 4 };
        let band_rows = height.div_ceil(bands).max(1);
        let chunk = band_rows * width;
        let triangles = &self.triangles;
        if bands == 1 {
            Band { row0: 0, width, face: &mut self.face, bary: &mut self.barycentric, depth: &mut self.depth }
                .draw_all(triangles);
        } else {
            self.face
                .par_chunks_mut(chunk)
                .zip(self.barycentric.par_chunks_mut(chunk))
                .zip(self.depth.par_chunks_mut(chunk))
                .enumerate()
                .for_each(|(b, ((face, bary), depth))| {
                    Band { row0: b * band_rows, width, face, bary, depth }.draw_all(triangles)
                });
        }
    }

    /// Bins every triangle into the pixel cells its bounding box overlaps.
    fn bin_triangles(&mut self) {
        let cells = self.width * self.height;
        self.cell_start.clear();
        self.cell_start.resize(cells + 1, 0);
        for t in &self.triangles {
            t.for_each_cell(self.width, |c| self.cell_start[c + 1] += 1);
        }
        for c in 0..cells {
            self.cell_start[c + 1] += self.cell_start[c];
        }
        self.cell_triangles.clear();
        self.cell_triangles.resize(self.cell_start[cells] as usize, 0);
        // Fill using cell_start[c] as the cursor, then shift the starts back.
        for (i, t) in self.triangles.iter().enumerate() {
            t.for_each_cell(self.width, |c| {
                self.cell_triangles[self.cell_start[c] as usize] = i as u32;
                self.cell_start[c] += 1;
            });
        }
        for c in (1..=cells).rev() {
            self.cell_start[c] = self.cell_start[c - 1];
        }
        self.cell_start[0] = 0;
    }

    /// A vertex is visible when it projects inside the image and no triangle covering its exact
    /// screen point is nearer there (by more than the tolerance). This is the z-buffer test done
    /// at the vertex's point instead of a pixel centre: on a stride-8 grid a triangle is smaller
    /// than a pixel, and sampling centres calls hidden vertices visible near the silhouette and
    /// hides vertices of steep faces behind their own depth slope.
    fn update_visibility(&mut self) {
        self.bin_triangles();
        let (lo, hi) = self
            .projected
            .iter()
            .map(|p| p[2])
            .filter(|d| d.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), d| (lo.min(d), hi.max(d)));
        let tol = VISIBILITY_TOLERANCE * (hi - lo).max(0.0) + 1e-9 * hi.abs().max(1.0);
        let (w, h) = (self.width as f64, self.height as f64);
        self.visible.clear();
        for k in 0..self.projected.len() {
            let [col, row, depth] = self.projected[k];
            let inside = depth > 0.0 && (0.0..w).contains(&col) && (0.0..h).contains(&row);
            let visible = inside && {
                let c = row as usize * self.width + col as usize;
                let range = self.cell_start[c] as usize..self.cell_start[c + 1] as usize;
                !self.cell_triangles[range]
                    .iter()
                    .any(|&t| self.triangles[t as usize].occludes([col, row], depth - tol))
            };
            self.visible.push(visible);
        }
    }
}

fn check_size(width: usize, height: usize) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(EngineError::EmptyImage { width, height });
    }
    width
        .checked_mul(height)
        .filter(|&n| n <= 1 << 28)
        .map(|_| ())
        .ok_or_else(|| EngineError::InvalidInput(format!("raster {width}x{height} is too large")))
}

/// Twice the signed area of `(a, b, q)`: positive when q is left of a→b in (col, row) axes.
#[inline(always)]
pub(crate) fn edge(a: [f64; 2], b: [f64; 2], q: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (q[1] - a[1]) - (b[1] - a[1]) * (q[0] - a[0])
}

impl Triangle {
    fn new(face: u32, v: [[f64; 3]; 3], width: usize, height: usize, cull_back_faces: bool) -> Option<Self> {
        if v.iter().flatten().any(|c| !c.is_finite()) || v.iter().any(|p| p[2] <= 0.0) {
            return None; // not clipped: a triangle reaching behind the camera is dropped
        }
        let p = v.map(|v| [v[0], v[1]]);
        let area = edge(p[0], p[1], p[2]);
        // Counter-clockwise seen from the camera is clockwise in (col, row), whose row axis
        // points down: front faces have negative area here.
        if area == 0.0 || (cull_back_faces && area > 0.0) {
            return None;
        }
        // Pixel centres (c + 0.5) inside the bounding box, and the pixel cells it overlaps;
        // a triangle can overlap cells without covering any centre.
        let mut centres = [[0; 2]; 2];
        let mut cells = [[0; 2]; 2];
        let mut bbox = [[0.0; 2]; 2];
        for (axis, len) in [(0, width), (1, height)] {
            let lo = p[0][axis].min(p[1][axis]).min(p[2][axis]);
            let hi = p[0][axis].max(p[1][axis]).max(p[2][axis]);
            if hi < 0.0 || lo >= len as f64 {
                return None;
            }
            bbox[0][axis] = lo;
            bbox[1][axis] = hi;
            // Casts of non-negative values floor them; f64::floor is a libm call on baseline x86-64.
            let end = |x: f64| (x.max(0.0) as usize + 1).min(len);
            let (first, last) = ((lo - 0.5).max(0.0), hi - 0.5);
            let first = first as usize + usize::from(first.fract() > 0.0);
            centres[axis] = [first, if last < 0.0 { first } else { end(last).max(first) }];
            cells[axis] = [lo.max(0.0) as usize, end(hi)];
        }
        // Orient so that inside is positive; then an edge's inward normal n = s·(−dy, dx). The
        // edge owns its pixels when it is a "left" edge (n points to +col) or a "top" edge
        // (horizontal, n points to +row, i.e. down the image).
        let s = area.signum();
        let owns = |a: [f64; 2], b: [f64; 2]| {
            let n = [-(b[1] - a[1]) * s, (b[0] - a[0]) * s];
            n[0] > 0.0 || (n[0] == 0.0 && n[1] > 0.0)
        };
        Some(Triangle {
            face,
            p,
            inv_depth: v.map(|v| 1.0 / v[2]),
            inv_area: 1.0 / area,
            owns_edge: [owns(p[1], p[2]), owns(p[2], p[0]), owns(p[0], p[1])],
            cols: centres[0],
            rows: centres[1],
            cells,
            bbox,
            near: v[0][2].min(v[1][2]).min(v[2][2]),
        })
    }

    #[inline]
    fn for_each_cell(&self, width: usize, mut f: impl FnMut(usize)) {
        for r in self.cells[1][0]..self.cells[1][1] {
            (self.cells[0][0]..self.cells[0][1]).for_each(|c| f(r * width + c));
        }
    }

    /// Whether the triangle covers screen point `q` at a depth below `depth`.
    #[inline]
    fn occludes(&self, q: [f64; 2], depth: f64) -> bool {
        let [lo, hi] = self.bbox;
        self.near < depth
            && (lo[0]..=hi[0]).contains(&q[0])
            && (lo[1]..=hi[1]).contains(&q[1])
            && self.depth_at(q).is_some_and(|z| z < depth)
    }

    /// Depth at a screen point inside the triangle (1/depth is affine in screen space), `None`
    /// outside it.
    fn depth_at(&self, q: [f64; 2]) -> Option<f64> {
        let p = self.p;
        let l = [edge(p[1], p[2], q), edge(p[2], p[0], q), edge(p[0], p[1], q)].map(|e| e * self.inv_area);
        if l.iter().any(|&l| l < -1e-9) {
            return None;
        }
        Some(1.0 / (l[0] * self.inv_depth[0] + l[1] * self.inv_depth[1] + l[2] * self.inv_depth[2]))
    }
}

/// A band of consecutive image rows being drawn into.
struct Band<'a> {
    row0: usize,
    width: usize,
    face: &'a mut [u32],
    bary: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
}

impl Band<'_> {
    fn draw_all(mut self, triangles: &[Triangle]) {
        triangles.iter().for_each(|t| self.draw(t));
    }

    #[inline]
    fn draw(&mut self, t: &Triangle) {
        let r0 = t.rows[0].max(self.row0);
        let r1 = t.rows[1].min(self.row0 + self.face.len() / self.width);
        for r in r0..r1 {
            let y = r as f64 + 0.5;
            let line = (r - self.row0) * self.width;
            for c in t.cols[0]..t.cols[1] {
                let q = [c as f64 + 0.5, y];
                // Scaled by 1/area, so positive inside whatever the winding.
                let l = [
                    edge(t.p[1], t.p[2], q) * t.inv_area,
                    edge(t.p[2], t.p[0], q) * t.inv_area,
                    edge(t.p[0], t.p[1], q) * t.inv_area,
                ];
                if (0..3).any(|k| l[k] < 0.0 || (l[k] == 0.0 && !t.owns_edge[k])) {
                    continue;
                }
                let w = [l[0] * t.inv_depth[0], l[1] * t.inv_depth[1], l[2] * t.inv_depth[2]];
                let inv = w[0] + w[1] + w[2];
                let z = (1.0 / inv) as f32;
                let i = line + c;
                if z < self.depth[i] {
                    self.depth[i] = z;
                    self.face[i] = t.face;
                    self.bary[i] = [(w[0] / inv) as f32, (w[1] / inv) as f32, (w[2] / inv) as f32];
                }
            }
        }
    }
}
