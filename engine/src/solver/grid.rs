//! The grid's renders (METHOD.md §6.4), once per solver: the grid poses and their fit
//! distances depend only on the mesh, the crop camera and the settings, never on the image, so
//! which feature cells each pose covers, with which face's vertices and barycentric weights, is
//! rasterised once; every image's grid losses are then a gather over `S = C·F`. The losses are
//! bit-identical to rendering each pose per image: the same products, summed in the same pixel
//! order ([`Problem::covered_sum`]).
//!
//! The entries the grid reads (7% of `S` for `models/car`) are computed into a compact array in
//! the renders' own (vertex, cell) order, and each render cell holds its three entries' places
//! in it: the dot products write one after the other and the 144 gathers read 200 KB that stay
//! in cache, where the image's memo (5 MB, [`super::similarity`]) cost a cache miss per store
//! and a tag check per read (together two thirds of the grid's time).

use rayon::prelude::*;

use super::{Problem, ScoredPose, Scratch, SolverConfig};
use crate::camera::{Camera, Pose, fit_distance};
use crate::error::{EngineError, Result};
use crate::mesh::Mesh;
use crate::raster::{Fragments, NO_FACE};

/// A feature cell a render covers: its index, the covering face's vertices and weights.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Covered {
    pub pixel: u32,
    pub vertices: [u32; 3],
    pub weights: [f32; 3],
}

/// The cells a render covers, in raster order.
pub(super) fn covered<'a>(frags: &'a Fragments<'a>, faces: &'a [[u32; 3]]) -> impl Iterator<Item = Covered> + 'a {
    frags
        .face
        .iter()
        .zip(frags.barycentric)
        .enumerate()
        .filter(|(_, (f, _))| **f != NO_FACE)
        .map(|(p, (&f, &weights))| Covered { pixel: p as u32, vertices: faces[f as usize], weights })
}

/// A covered cell of a grid render: the three `S` entries it reads, as places in the compact
/// array ([`GridRenders::cells`] order), and the face's weights.
#[derive(Clone, Copy, Debug, PartialEq)]
struct GridCell {
    pixel: u32,
    entries: [u32; 3],
    weights: [f32; 3],
}

/// Every grid pose at its fit distance and the cells its render covers, in raster order.
#[derive(Clone, Debug)]
pub struct GridRenders {
    /// What the renders were made for; a solver whose settings changed renders afresh.
    crop: Camera,
    config: SolverConfig,
    vertices: usize,
    poses: Vec<Pose>,
    covered: Vec<Vec<GridCell>>,
    /// The (cell, vertex) pairs the renders read, by vertex (then cell, ascending): entry `i`
    /// is `S[vertex[i], cells[i]]`.
    cells: Vec<u32>,
    vertex: Vec<u32>,
}

impl GridRenders {
    /// Bytes held on the host (what a loaded model costs beyond its tensors).
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        self.poses.len() * size_of::<Pose>()
            + self.covered.iter().map(|c| c.len() * size_of::<GridCell>()).sum::<usize>()
            + (self.cells.len() + self.vertex.len()) * size_of::<u32>()
    }

    pub fn new(mesh: &Mesh, crop: &Camera, config: &SolverConfig) -> Result<Self> {
        config.validate()?;
        let grid = crop.at_stride(config.stride)?;
        let faces = mesh.faces();
        let renders: Vec<(Pose, Vec<Covered>)> = config
            .grid_angles()
            .into_par_iter()
            .map_init(Scratch::default, |scratch, [a, e, t]| {
                let pose = Pose::new(a, e, t, fit_distance(mesh.vertices(), [a, e, t], crop, config.fill)?);
                let frags = scratch.raster.render_faces(mesh, &grid, &pose)?;
                Ok((pose, covered(&frags, faces).collect()))
            })
            .collect::<Result<_>>()?;
        let (poses, covered): (Vec<Pose>, Vec<Vec<Covered>>) = renders.into_iter().unzip();
        let vertices = mesh.vertices().len();
        let mut by_vertex: Vec<Vec<u32>> = vec![Vec::new(); vertices];
        for c in covered.iter().flatten() {
            for v in c.vertices {
                by_vertex[v as usize].push(c.pixel);
            }
        }
        let (mut cells, mut vertex) = (Vec::new(), Vec::new());
        let mut starts = vec![0];
        for (v, mut list) in by_vertex.into_iter().enumerate() {
            list.sort_unstable();
            list.dedup();
            vertex.extend(std::iter::repeat_n(v as u32, list.len()));
            cells.extend(list);
            starts.push(cells.len());
        }
        // An entry's place: its vertex's first place, then a search among the vertex's cells.
        let place = |v: u32, pixel: u32| {
            let (from, to) = (starts[v as usize], starts[v as usize + 1]);
            (from + cells[from..to].binary_search(&pixel).expect("every covered pair is listed")) as u32
        };
        let covered = covered
            .iter()
            .map(|render| {
                render
                    .iter()
                    .map(|c| GridCell {
                        pixel: c.pixel,
                        entries: c.vertices.map(|v| place(v, c.pixel)),
                        weights: c.weights,
                    })
                    .collect()
            })
            .collect();
        Ok(GridRenders { crop: *crop, config: config.clone(), vertices, poses, covered, cells, vertex })
    }

    /// Whether these renders are the grid of `config` on `crop` (the optimiser and `k` may differ).
    pub fn fits(&self, crop: &Camera, config: &SolverConfig) -> bool {
        let c = &self.config;
        self.crop == *crop
            && (&c.azimuths, &c.elevations, &c.thetas, c.fill, c.stride)
                == (&config.azimuths, &config.elevations, &config.thetas, config.fill, config.stride)
    }

    /// [`super::grid_losses`] of `problem`, from the renders (in parallel over poses).
    pub fn losses(&self, problem: &Problem) -> Result<Vec<ScoredPose>> {
        if !self.fits(problem.crop_camera(), &self.config) || problem.vertices != self.vertices {
            return Err(EngineError::InvalidInput("the grid renders are of another mesh or crop".into()));
        }
        // Every entry the renders read, vertex by vertex: one vertex feature stays in L1 while
        // the cells' features stream past, instead of both fetched per entry in render order.
        const CHUNK: usize = 4096;
        let mut values = vec![0.0f32; self.cells.len()];
        values.par_chunks_mut(CHUNK).enumerate().for_each(|(i, out)| {
            let range = i * CHUNK..i * CHUNK + out.len();
            problem.similarity.compute(&self.vertex[range.clone()], &self.cells[range], out);
        });
        let scored: Vec<ScoredPose> = self
            .poses
            .par_iter()
            .zip(&self.covered)
            .map(|(&pose, covered)| {
                let cells = covered.iter().map(|c| (c.pixel, c.entries.map(|e| values[e as usize]), c.weights));
                ScoredPose { pose, loss: problem.covered_sum(cells) }
            })
            .collect();
        for ((&v, &p), &x) in self.vertex.iter().zip(&self.cells).zip(&values) {
            problem.similarity.remember(p as usize, v as usize, x);
        }
        Ok(scored)
    }
}
