//! Triangle meshes, the cuboid neural-mesh geometry (METHOD.md §3) and OFF/OBJ files.

use std::io::{BufRead, Write};

use serde::{Deserialize, Serialize};

use crate::error::{EngineError, Result};

/// A validated triangle mesh: finite vertices, faces indexing existing vertices, and at least
/// one face of non-zero area (zero-area faces are kept, they cover no pixel).
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    vertices: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
    closed_outward: bool,
}

impl Mesh {
    /// Bytes of its vertices and faces.
    pub fn bytes(&self) -> usize {
        std::mem::size_of_val(self.vertices.as_slice()) + std::mem::size_of_val(self.faces.as_slice())
    }

    pub fn new(vertices: Vec<[f64; 3]>, faces: Vec<[u32; 3]>) -> Result<Self> {
        let bad = |m: String| Err(EngineError::InvalidMesh(m));
        if vertices.is_empty() {
            return bad("no vertices".into());
        }
        if faces.is_empty() {
            return bad("no faces".into());
        }
        if vertices.len() > u32::MAX as usize {
            return bad(format!("{} vertices is too many", vertices.len()));
        }
        if let Some(i) = vertices.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return bad(format!("vertex {i} is not finite: {:?}", vertices[i]));
        }
        let n = vertices.len();
        for (f, face) in faces.iter().enumerate() {
            if let Some(&i) = face.iter().find(|&&i| i as usize >= n) {
                return bad(format!("face {f} uses vertex {i}, but there are only {n}"));
            }
        }
        let mesh = Mesh { vertices, faces, closed_outward: false };
        if (0..mesh.faces.len()).all(|f| mesh.face_area(f) == 0.0) {
            return bad("every face has zero area".into());
        }
        Ok(mesh)
    }

    /// Whether the mesh is closed with every face wound counter-clockwise seen from outside:
    /// then a face turned away from the camera is always hidden, and the rasteriser skips it.
    pub fn is_closed_outward(&self) -> bool {
        self.closed_outward
    }

    pub fn vertices(&self) -> &[[f64; 3]] {
        &self.vertices
    }

    pub fn faces(&self) -> &[[u32; 3]] {
        &self.faces
    }

    fn face_area(&self, f: usize) -> f64 {
        let [a, b, c] = self.faces[f].map(|i| self.vertices[i as usize]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
    }
}

/// An axis-aligned box in mesh coordinates (z up), the shape of a category's neural mesh.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cuboid {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

/// Share of the CAD vertices each axis interval must contain (METHOD.md §3).
pub const CAD_COVERAGE: f64 = 0.99;
/// Target vertex count of the cuboid mesh.
pub const TARGET_VERTICES: usize = 1000;

impl Cuboid {
    /// A box of the given `[x, y, z]` extents, centred at the origin.
    pub fn from_dimensions(dims: [f64; 3]) -> Result<Self> {
        if dims.iter().any(|d| !(d.is_finite() && *d > 0.0)) {
            return Err(EngineError::InvalidMesh(format!("cuboid dimensions must be finite and > 0, got {dims:?}")));
        }
        Ok(Cuboid { min: dims.map(|d| -d / 2.0), max: dims.map(|d| d / 2.0) })
    }

    /// Per axis, the narrowest interval holding `coverage` of the points (pooled CAD vertices).
    pub fn from_cad_vertices(points: &[[f64; 3]], coverage: f64) -> Result<Self> {
        if !(coverage > 0.0 && coverage <= 1.0) {
            return Err(EngineError::InvalidInput(format!("coverage must be in (0, 1], got {coverage}")));
        }
        if points.is_empty() || points.iter().flatten().any(|c| !c.is_finite()) {
            return Err(EngineError::InvalidMesh("CAD vertices must be non-empty and finite".into()));
        }
        let keep = ((coverage * points.len() as f64).ceil() as usize).clamp(1, points.len());
        let mut min = [0.0; 3];
        let mut max = [0.0; 3];
        for axis in 0..3 {
            let mut v: Vec<f64> = points.iter().map(|p| p[axis]).collect();
            v.sort_by(f64::total_cmp);
            let start = (0..=v.len() - keep)
                .min_by(|&i, &j| (v[i + keep - 1] - v[i]).total_cmp(&(v[j + keep - 1] - v[j])))
                .unwrap_or(0);
            (min[axis], max[axis]) = (v[start], v[start + keep - 1]);
        }
        let cuboid = Cuboid { min, max };
        Cuboid::from_dimensions(cuboid.dimensions())?; // rejects flat boxes
        Ok(cuboid)
    }

    pub fn dimensions(&self) -> [f64; 3] {
        [0, 1, 2].map(|a| self.max[a] - self.min[a])
    }

    /// Samples per axis: spacing `s = sqrt(area / target)`, `n = ⌊side/s + 1⌋` (METHOD.md §3).
    pub fn grid_counts(&self, target_vertices: usize) -> [usize; 3] {
        let [x, y, z] = self.dimensions();
        let area = 2.0 * (x * y + y * z + z * x);
        let s = (area / target_vertices.max(1) as f64).sqrt();
        [x, y, z].map(|side| ((side / s + 1.0).floor() as usize).max(2))
    }

    /// The surface mesh: each face a regular grid of its own vertices (faces share none), two
    /// triangles per cell, wound counter-clockwise seen from outside.
    pub fn mesh(&self, target_vertices: usize) -> Mesh {
        self.mesh_with_counts(self.grid_counts(target_vertices))
    }

    /// [`Cuboid::mesh`] with `n` samples along x, y and z (each at least 2).
    pub fn mesh_with_counts(&self, n: [usize; 3]) -> Mesh {
        let n = n.map(|k| k.max(2));
        let mut vertices = Vec::new();
        let mut faces = Vec::new();
        for axis in 0..3 {
            // (u, v, axis) is a right-handed frame, so u × v points along +axis.
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            for outward in [false, true] {
                let base = vertices.len() as u32;
                for i in 0..n[u] {
                    for j in 0..n[v] {
                        let mut p = [0.0; 3];
                        p[axis] = if outward { self.max[axis] } else { self.min[axis] };
                        p[u] = lerp(self.min[u], self.max[u], i, n[u]);
                        p[v] = lerp(self.min[v], self.max[v], j, n[v]);
                        vertices.push(p);
                    }
                }
                let id = |i: usize, j: usize| base + (i * n[v] + j) as u32;
                for i in 0..n[u] - 1 {
                    for j in 0..n[v] - 1 {
                        let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                        if outward {
                            faces.extend([[a, b, c], [a, c, d]]);
                        } else {
                            faces.extend([[a, c, b], [a, d, c]]);
                        }
                    }
                }
            }
        }
        let mesh = Mesh::new(vertices, faces).expect("a cuboid with positive extents is a valid mesh");
        Mesh { closed_outward: true, ..mesh }
    }
}

fn lerp(lo: f64, hi: f64, i: usize, n: usize) -> f64 {
    if i + 1 == n { hi } else { lo + (hi - lo) * i as f64 / (n - 1) as f64 }
}

fn format_err(line: usize, message: impl Into<String>) -> EngineError {
    EngineError::MeshFormat { line, message: message.into() }
}

fn parse_f64(tok: Option<&str>, line: usize) -> Result<f64> {
    let tok = tok.ok_or_else(|| format_err(line, "missing coordinate"))?;
    tok.parse().map_err(|_| format_err(line, format!("bad number {tok:?}")))
}

/// Splits a polygon into a triangle fan.
fn fan(poly: &[u32], faces: &mut Vec<[u32; 3]>) {
    for k in 1..poly.len().saturating_sub(1) {
        faces.push([poly[0], poly[k], poly[k + 1]]);
    }
}

/// Reads an OFF file; polygons are split into triangle fans.
pub fn read_off(reader: impl BufRead) -> Result<Mesh> {
    // Meaningful lines, numbered from 1, without comments.
    let mut lines = reader.lines().enumerate().filter_map(|(i, l)| match l {
        Ok(l) => {
            let body = l.split('#').next().unwrap_or("").trim().to_string();
            (!body.is_empty()).then_some(Ok((i + 1, body)))
        }
        Err(e) => Some(Err(EngineError::from(e))),
    });
    let mut next = |what: &str| {
        lines.next().unwrap_or_else(|| Err(format_err(0, format!("unexpected end of file, expected {what}"))))
    };
    let (line, header) = next("OFF header")?;
    let counts = match header.strip_prefix("OFF") {
        Some(rest) if rest.trim().is_empty() => next("counts")?,
        Some(rest) => (line, rest.trim().to_string()),
        None => return Err(format_err(line, "missing OFF header")),
    };
    let nums: Vec<usize> = counts
        .1
        .split_whitespace()
        .map(|t| t.parse().map_err(|_| format_err(counts.0, format!("bad count {t:?}"))))
        .collect::<Result<_>>()?;
    let [nv, nf] = match nums[..] {
        [nv, nf, ..] => [nv, nf],
        _ => return Err(format_err(counts.0, "expected vertex and face counts")),
    };
    let mut vertices = Vec::with_capacity(nv.min(1 << 20));
    for _ in 0..nv {
        let (line, l) = next("a vertex")?;
        let mut t = l.split_whitespace();
        vertices.push([parse_f64(t.next(), line)?, parse_f64(t.next(), line)?, parse_f64(t.next(), line)?]);
    }
    let mut faces = Vec::with_capacity(nf.min(1 << 20));
    for _ in 0..nf {
        let (line, l) = next("a face")?;
        let idx: Vec<u32> = l
            .split_whitespace()
            .map(|t| t.parse().map_err(|_| format_err(line, format!("bad index {t:?}"))))
            .collect::<Result<_>>()?;
        let k = *idx.first().ok_or_else(|| format_err(line, "empty face"))? as usize;
        if k < 3 || idx.len() < k + 1 {
            return Err(format_err(line, format!("face needs at least 3 indices, has {k} (of {})", idx.len() - 1)));
        }
        fan(&idx[1..=k], &mut faces);
    }
    Mesh::new(vertices, faces)
}

pub fn write_off(mesh: &Mesh, mut w: impl Write) -> Result<()> {
    writeln!(w, "OFF\n{} {} 0", mesh.vertices.len(), mesh.faces.len())?;
    for v in &mesh.vertices {
        writeln!(w, "{} {} {}", v[0], v[1], v[2])?;
    }
    for f in &mesh.faces {
        writeln!(w, "3 {} {} {}", f[0], f[1], f[2])?;
    }
    Ok(())
}

/// Reads the geometry of an OBJ file (`v` and `f`; texture and normal indices are ignored;
/// negative indices count back from the last vertex).
pub fn read_obj(reader: impl BufRead) -> Result<Mesh> {
    let mut vertices = Vec::new();
    let mut faces = Vec::new();
    for (i, l) in reader.lines().enumerate() {
        let (line, l) = (i + 1, l?);
        let mut t = l.split_whitespace();
        match t.next() {
            Some("v") => {
                vertices.push([parse_f64(t.next(), line)?, parse_f64(t.next(), line)?, parse_f64(t.next(), line)?])
            }
            Some("f") => {
                let poly: Vec<u32> = t.map(|tok| obj_index(tok, vertices.len(), line)).collect::<Result<_>>()?;
                if poly.len() < 3 {
                    return Err(format_err(line, "face needs at least 3 vertices"));
                }
                fan(&poly, &mut faces);
            }
            _ => {}
        }
    }
    Mesh::new(vertices, faces)
}

fn obj_index(tok: &str, n: usize, line: usize) -> Result<u32> {
    let first = tok.split('/').next().unwrap_or("");
    let i: i64 = first.parse().map_err(|_| format_err(line, format!("bad index {tok:?}")))?;
    let resolved = match i {
        0 => None,
        i if i > 0 => Some(i - 1),
        i => Some(n as i64 + i),
    };
    resolved
        .filter(|&r| r >= 0 && r < n as i64)
        .map(|r| r as u32)
        .ok_or_else(|| format_err(line, format!("index {i} out of range for {n} vertices so far")))
}

pub fn write_obj(mesh: &Mesh, mut w: impl Write) -> Result<()> {
    for v in &mesh.vertices {
        writeln!(w, "v {} {} {}", v[0], v[1], v[2])?;
    }
    for f in &mesh.faces {
        writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1)?;
    }
    Ok(())
}
