//! The transmittance towards one light through the *other* objects of a scene, on a lattice
//! over one object's box (`render::shadow` computes it, SPEC §6's S less the object's own
//! share): lattice point (i, j, k) lies at box coordinates (i/(n₀−1), j/(n₁−1), k/(n₂−1)),
//! and a point between them takes the trilinear blend ([`Transmittance::at`]).
//!
//! A lattice fine enough everywhere for SPEC §6's 2/255 would be mostly wasted: the
//! transmittance is flat (1 in light, a constant in shadow) or close to linear except near
//! shadow edges. So a lattice is *refined* where blending it is poor: each cell in which it
//! bends by more than [`REFINE_BEND`] gets a block of its own, [`REFINE`] sub-cells a side,
//! and a point in such a cell takes the blend of its block instead. The blocks lie on one
//! lattice [`REFINE`] times finer than the coarse one, so neighbouring blocks share their
//! points, and a block's points that are coarse points take the coarse values: only the
//! other points are computed ([`Transmittance::refinement`]). Which cells are refined is a
//! function of the coarse values alone ([`Transmittance::cells_to_refine`]), so a farm
//! worker that holds the coarse lattice knows the fine points to compute without being
//! told, and a map on the wire carries only the fine values.

use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

/// Sub-cells per side of a refined cell (docs/shadows.md measures the error it leaves).
pub const REFINE: u32 = 3;

/// A cell is refined where the lattice bends by more than this inside it
/// (`Transmittance::bends`). Trilinear blending is off by about an eighth of a cell's bend,
/// so a cell left coarse is off by about 1/255 at most, within SPEC §6's 2/255.
pub const REFINE_BEND: f32 = 8.0 / 255.0;

/// Points in one refined cell's block: (REFINE + 1)³.
pub const BLOCK_POINTS: usize = ((REFINE + 1) * (REFINE + 1) * (REFINE + 1)) as usize;

/// The most fine points in one lattice (16 MiB of f32): past it, only the cells where the
/// lattice bends most are refined.
pub const MAX_FINE_POINTS: usize = 1 << 22;

/// A lattice of transmittances, each in [0, 1], with its refined cells' blocks when it has
/// them.
#[derive(Clone, Debug, PartialEq)]
pub struct Transmittance {
    dims: [u32; 3],
    values: Arc<[f32]>,
    fine: Option<Fine>,
}

/// The blocks of a lattice's refined cells.
#[derive(Clone, Debug, PartialEq)]
struct Fine {
    /// Per cell (x fastest), the index of its block, or [`NO_BLOCK`].
    block_of: Arc<[u32]>,
    /// [`BLOCK_POINTS`] values per block, blocks in cell order, points x fastest.
    values: Arc<[f32]>,
    /// The fine points' values as given ([`Transmittance::fine_values`]).
    given: Arc<[f32]>,
}

const NO_BLOCK: u32 = u32::MAX;

/// Why a lattice of transmittances is refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TransmittanceError {
    /// A side with fewer than two points, or more than [`Transmittance::MAX_SIDE`].
    #[error("expected 2 to {max} lattice points a side, got {got:?}", max = Transmittance::MAX_SIDE)]
    Dims {
        /// The sides given.
        got: [u32; 3],
    },
    /// Not one value per lattice point (or per point of the refined cells' blocks).
    #[error("expected {expected} values (one per lattice point), got {got}")]
    Length {
        /// Lattice points.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// A value outside [0, 1] (or NaN).
    #[error("expected transmittances in [0, 1], got {got} at lattice point {index}")]
    Value {
        /// Its index.
        index: usize,
        /// The value.
        got: f32,
    },
}

/// The index of the first value outside [0, 1], and that value.
fn out_of_range(values: &[f32]) -> Option<(usize, f32)> {
    values.iter().enumerate().find(|(_, v)| !(0.0..=1.0).contains(*v)).map(|(i, &v)| (i, v))
}

/// Cells per side of a lattice of `dims` points.
fn cell_dims(dims: [u32; 3]) -> [usize; 3] {
    dims.map(|n| n as usize - 1)
}

/// Points per side of the lattice [`REFINE`] times finer than a lattice of `dims` points.
fn fine_dims(dims: [u32; 3]) -> [u64; 3] {
    dims.map(|n| u64::from(n - 1) * u64::from(REFINE) + 1)
}

/// Box coordinates of point `index` (x fastest) of the lattice [`REFINE`] times finer than a
/// lattice of `dims` points ([`Refinement::points`] lists the ones a pass computes).
pub fn fine_point(dims: [u32; 3], index: u64) -> DVec3 {
    let [fx, fy, _] = fine_dims(dims);
    let p = [index % fx, (index / fx) % fy, index / (fx * fy)];
    let r = u64::from(REFINE);
    DVec3::from_array(std::array::from_fn(|a| p[a] as f64 / (u64::from(dims[a] - 1) * r) as f64))
}

/// The points of refined cell `cell`'s block of a lattice of `dims` points (x fastest), each
/// as its index on the lattice [`REFINE`] times finer and, for the block's corners, its index
/// on the coarse lattice.
fn block_points(dims: [u32; 3], cell: u32) -> impl Iterator<Item = (u64, Option<usize>)> {
    let [cx, cy, _] = cell_dims(dims);
    let [nx, ny, _] = dims.map(|n| n as usize);
    let [fx, fy, _] = fine_dims(dims);
    let r = REFINE as usize;
    let c = cell as usize;
    let base = [c % cx, (c / cx) % cy, c / (cx * cy)];
    (0..BLOCK_POINTS).map(move |n| {
        let sub = [n % (r + 1), (n / (r + 1)) % (r + 1), n / ((r + 1) * (r + 1))];
        let [x, y, z] = std::array::from_fn(|a| (base[a] * r + sub[a]) as u64);
        let corner = sub.iter().all(|&s| s % r == 0).then(|| {
            let [i, j, k] = std::array::from_fn(|a| base[a] + sub[a] / r);
            i + nx * (j + ny * k)
        });
        (x + fx * (y + fy * z), corner)
    })
}

/// A lattice's refined cells and the fine points their blocks need
/// ([`Transmittance::refinement`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Refinement {
    dims: [u32; 3],
    cells: Vec<u32>,
    points: Vec<u64>,
}

impl Refinement {
    /// The fine points to compute, as indices on the lattice [`REFINE`] times finer
    /// ([`fine_point`]), in index order.
    pub fn points(&self) -> &[u64] {
        &self.points
    }

    /// The refined cells (x fastest), in index order.
    pub fn cells(&self) -> &[u32] {
        &self.cells
    }
}

impl Transmittance {
    /// The most lattice points along one side.
    pub const MAX_SIDE: u32 = 1024;

    /// A lattice of `dims` points whose values are `values`, x fastest, with no cell refined.
    pub fn new(dims: [u32; 3], values: Vec<f32>) -> Result<Transmittance, TransmittanceError> {
        if dims.iter().any(|&n| !(2..=Transmittance::MAX_SIDE).contains(&n)) {
            return Err(TransmittanceError::Dims { got: dims });
        }
        let expected = dims.iter().map(|&n| n as usize).product();
        if values.len() != expected {
            return Err(TransmittanceError::Length { expected, got: values.len() });
        }
        if let Some((index, got)) = out_of_range(&values) {
            return Err(TransmittanceError::Value { index, got });
        }
        Ok(Transmittance { dims, values: values.into(), fine: None })
    }

    /// The cells (x fastest) that [`Transmittance::with_fine`] refines: those where the
    /// lattice bends more than [`REFINE_BEND`] (`Transmittance::bends`), in index order;
    /// where their blocks would pass [`MAX_FINE_POINTS`], the ones that bend most (ties by
    /// index).
    pub fn cells_to_refine(&self) -> Vec<u32> {
        let mut picked: Vec<(f32, u32)> = self
            .bends()
            .into_iter()
            .enumerate()
            .filter(|&(_, bend)| bend > REFINE_BEND)
            .map(|(c, bend)| (bend, c as u32))
            .collect();
        // Each cell adds at most its block's points less its eight corners.
        let most = MAX_FINE_POINTS / (BLOCK_POINTS - 8);
        if picked.len() > most {
            picked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            picked.truncate(most);
            picked.sort_by_key(|&(_, c)| c);
        }
        picked.into_iter().map(|(_, c)| c).collect()
    }

    /// How much the lattice bends inside each cell (x fastest): over the cell's twelve edges,
    /// the smaller of the second differences |v(p − e) − 2v(p) + v(p + e)| at the edge's two
    /// ends along it (a side's missing neighbour counting as a bend without bound, and an
    /// edge with neither end's neighbours counting as none), the largest. Both ends of an
    /// edge see a step or a kink that lies between them, while a kink at a lattice point
    /// (which the blend reproduces) shows at that end only, and a linear ramp (also
    /// reproduced) shows at neither; trilinear blending is off by about an eighth of this
    /// inside the cell.
    fn bends(&self) -> Vec<f32> {
        let [nx, ny, nz] = self.dims.map(|n| n as usize);
        let [cx, cy, cz] = cell_dims(self.dims);
        let v = &self.values;
        let stride = [1, nx, nx * ny];
        let n = [nx, ny, nz];
        // Per axis, per edge along it (named by its lower end): the smaller second difference.
        let edges: [Vec<f32>; 3] = std::array::from_fn(|a| {
            let second = |p: usize, coord: usize| -> f32 {
                if coord == 0 || coord + 1 == n[a] {
                    f32::INFINITY
                } else {
                    (v[p - stride[a]] - 2.0 * v[p] + v[p + stride[a]]).abs()
                }
            };
            let mut e = vec![0.0f32; v.len()];
            e.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slab)| {
                for j in 0..ny {
                    for i in 0..nx {
                        let coord = [i, j, k][a];
                        if coord + 1 == n[a] {
                            continue;
                        }
                        let p = i + nx * (j + ny * k);
                        let m = second(p, coord).min(second(p + stride[a], coord + 1));
                        slab[i + nx * j] = if m.is_finite() { m } else { 0.0 };
                    }
                }
            });
            e
        });
        let mut bends = vec![0.0f32; cx * cy * cz];
        bends.par_chunks_mut(cx * cy).enumerate().for_each(|(k, slab)| {
            for j in 0..cy {
                for i in 0..cx {
                    let p = i + nx * (j + ny * k);
                    let mut bend = 0.0f32;
                    for (a, e) in edges.iter().enumerate() {
                        let (b, c) = (stride[(a + 1) % 3], stride[(a + 2) % 3]);
                        bend = bend.max(e[p]).max(e[p + b]).max(e[p + c]).max(e[p + b + c]);
                    }
                    slab[i + cx * j] = bend;
                }
            }
        });
        bends
    }

    /// Which cells are refined and which fine points their blocks need:
    /// [`Transmittance::cells_to_refine`], and the points of those cells' blocks on the
    /// lattice [`REFINE`] times finer ([`fine_point`]) that are not coarse points, each once,
    /// in index order. Worked out once from the coarse values, for the pass that computes
    /// the points' values and again for the lattice that takes them
    /// ([`Transmittance::with_fine`]).
    pub fn refinement(&self) -> Refinement {
        let cells = self.cells_to_refine();
        let mut points: Vec<u64> = cells
            .iter()
            .flat_map(|&c| block_points(self.dims, c))
            .filter_map(|(fine, corner)| corner.is_none().then_some(fine))
            .collect();
        points.sort_unstable();
        points.dedup();
        Refinement { dims: self.dims, cells, points }
    }

    /// This lattice with the blocks of its refined cells: `refinement` is this lattice's
    /// ([`Transmittance::refinement`]), and `values` holds one value per point of it, in
    /// its order.
    pub fn with_fine(self, refinement: &Refinement, values: Vec<f32>) -> Result<Transmittance, TransmittanceError> {
        if refinement.dims != self.dims && !refinement.cells.is_empty() {
            return Err(TransmittanceError::Dims { got: refinement.dims });
        }
        let Refinement { cells, points, .. } = refinement;
        if values.len() != points.len() {
            return Err(TransmittanceError::Length { expected: points.len(), got: values.len() });
        }
        if let Some((index, got)) = out_of_range(&values) {
            return Err(TransmittanceError::Value { index, got });
        }
        if cells.is_empty() {
            return Ok(Transmittance { fine: None, ..self });
        }
        let [cx, cy, cz] = cell_dims(self.dims);
        let mut block_of = vec![NO_BLOCK; cx * cy * cz];
        let mut blocks = Vec::with_capacity(cells.len() * BLOCK_POINTS);
        for (b, &c) in cells.iter().enumerate() {
            block_of[c as usize] = b as u32;
            blocks.extend(block_points(self.dims, c).map(|(fine, corner)| match corner {
                Some(i) => self.values[i],
                None => values[points.binary_search(&fine).expect("a block's point is a fine point")],
            }));
        }
        Ok(Transmittance {
            fine: Some(Fine { block_of: block_of.into(), values: blocks.into(), given: values.into() }),
            ..self
        })
    }

    /// Lattice points per side.
    pub fn dims(&self) -> [u32; 3] {
        self.dims
    }

    /// The values, x fastest.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// The fine points' values, as [`Transmittance::with_fine`] took them; empty where no
    /// cell is refined.
    pub fn fine_values(&self) -> &[f32] {
        self.fine.as_ref().map_or(&[], |f| &f.given)
    }

    /// The transmittance at box coordinates `q` (clamped to the box): the trilinear blend of
    /// the eight lattice points around it, or of the eight points of its cell's block around
    /// it where the cell is refined.
    #[inline]
    pub fn at(&self, q: DVec3) -> f64 {
        let mut base = [0usize; 3];
        let mut frac = [0.0f64; 3];
        for a in 0..3 {
            let last = f64::from(self.dims[a] - 1);
            let u = (q[a] * last).clamp(0.0, last);
            let i = (u.floor() as usize).min(self.dims[a] as usize - 2);
            base[a] = i;
            frac[a] = u - i as f64;
        }
        let [i, j, k] = base;
        if let Some(fine) = &self.fine {
            let [cx, cy, _] = cell_dims(self.dims);
            let block = fine.block_of[i + cx * (j + cy * k)];
            if block != NO_BLOCK {
                let r = REFINE as usize;
                let mut sub = [0usize; 3];
                let mut f = [0.0f64; 3];
                for a in 0..3 {
                    let u = frac[a] * r as f64;
                    sub[a] = (u.floor() as usize).min(r - 1);
                    f[a] = u - sub[a] as f64;
                }
                let values = &fine.values[block as usize * BLOCK_POINTS..][..BLOCK_POINTS];
                return blend(values, r + 1, r + 1, sub, f);
            }
        }
        blend(&self.values, self.dims[0] as usize, self.dims[1] as usize, base, frac)
    }
}

/// The trilinear blend at fractions `f` of the cell at `base` of a lattice `nx` × `ny` × …
/// of `values` (x fastest).
#[inline]
fn blend(values: &[f32], nx: usize, ny: usize, base: [usize; 3], f: [f64; 3]) -> f64 {
    let at = |i: usize, j: usize, k: usize| f64::from(values[i + nx * (j + ny * k)]);
    let [i, j, k] = base;
    let [fx, fy, fz] = f;
    let lerp = |a: f64, b: f64, f: f64| a + (b - a) * f;
    let x00 = lerp(at(i, j, k), at(i + 1, j, k), fx);
    let x10 = lerp(at(i, j + 1, k), at(i + 1, j + 1, k), fx);
    let x01 = lerp(at(i, j, k + 1), at(i + 1, j, k + 1), fx);
    let x11 = lerp(at(i, j + 1, k + 1), at(i + 1, j + 1, k + 1), fx);
    lerp(lerp(x00, x10, fy), lerp(x01, x11, fy), fz)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transmittance_lattices_blend_trilinearly_and_refuse_bad_values() {
        // T = (1 + x + 2y + 4z)/8 over a 3 × 2 × 2 lattice is linear, so every blend is exact.
        let dims = [3, 2, 2];
        let f = |q: DVec3| (1.0 + q.x + 2.0 * q.y + 4.0 * q.z) / 8.0;
        let values =
            (0..12).map(|n| f(DVec3::new((n % 3) as f64 / 2.0, ((n / 3) % 2) as f64, (n / 6) as f64)) as f32).collect();
        let t = Transmittance::new(dims, values).unwrap();
        for q in [DVec3::ZERO, DVec3::ONE, DVec3::new(0.3, 0.7, 0.2), DVec3::new(0.75, 0.5, 0.9)] {
            assert!((t.at(q) - f(q)).abs() < 1e-7, "at {q}: {} vs {}", t.at(q), f(q));
        }
        // Outside the box it is clamped to the box.
        assert_eq!(t.at(DVec3::new(-1.0, 2.0, 0.5)), t.at(DVec3::new(0.0, 1.0, 0.5)));
        assert!(matches!(Transmittance::new([1, 2, 2], vec![1.0; 4]), Err(TransmittanceError::Dims { .. })));
        assert!(matches!(Transmittance::new([2, 2, 2], vec![1.0; 7]), Err(TransmittanceError::Length { .. })));
        let mut bad = vec![1.0; 8];
        bad[5] = f32::NAN;
        assert!(matches!(Transmittance::new([2, 2, 2], bad), Err(TransmittanceError::Value { index: 5, .. })));
    }

    /// A shadow edge: a step in x in the middle of the first sub-cell of the third cell
    /// (x from 0.4 to 0.6) of [`coarse_edge`].
    fn edge(x: f64) -> f64 {
        if x < 0.4 + 0.1 / f64::from(REFINE) {
            0.2
        } else {
            1.0
        }
    }

    /// [`edge`] on a 6 × 3 × 2 lattice (x at 0, 0.2, … 1).
    fn coarse_edge() -> Transmittance {
        let dims = [6, 3, 2];
        let values = (0..36).map(|n| edge((n % 6) as f64 / 5.0) as f32).collect();
        Transmittance::new(dims, values).unwrap()
    }

    #[test]
    fn only_cells_the_lattice_bends_in_are_refined_and_their_blocks_are_used() {
        let t = coarse_edge();
        // The step lies in the third column of cells (x from 0.4 to 0.6): cells 2 and 7 (the
        // two rows of cells of the one layer). Its neighbours bend at one end only.
        assert_eq!(t.cells_to_refine(), vec![2, 7]);
        // Two blocks sharing a face of (R + 1)² points; their 12 coarse corners are not computed.
        let refinement = t.refinement();
        assert_eq!(refinement.cells(), [2, 7]);
        let points = refinement.points();
        let r = REFINE as usize;
        assert_eq!(points.len(), 2 * BLOCK_POINTS - (r + 1) * (r + 1) - 12);
        assert!(points.windows(2).all(|w| w[0] < w[1]));
        let fine: Vec<f32> = points.iter().map(|&p| edge(fine_point([6, 3, 2], p).x) as f32).collect();
        // The middle of the cell's last sub-cell, past the step.
        let x = 0.6 - 0.1 / f64::from(REFINE);
        let coarse_at = t.at(DVec3::new(x, 0.3, 0.4));
        let refined = t.with_fine(&refinement, fine.clone()).unwrap();
        // In the refined cells the blend is the block's: exact away from the step's sub-cell.
        assert!((refined.at(DVec3::new(x, 0.3, 0.4)) - 1.0).abs() < 1e-7);
        assert!((refined.at(DVec3::new(x, 0.9, 0.1)) - 1.0).abs() < 1e-7);
        assert!((coarse_at - 1.0).abs() > 0.1, "the coarse blend blurs the step: {coarse_at}");
        // Elsewhere the coarse lattice, unchanged; the blocks' corners are the cells' corners.
        assert_eq!(refined.at(DVec3::new(0.1, 0.5, 0.5)), coarse_edge().at(DVec3::new(0.1, 0.5, 0.5)));
        assert_eq!(refined.at(DVec3::new(0.4, 0.5, 1.0)), coarse_edge().at(DVec3::new(0.4, 0.5, 1.0)));
        assert_eq!(fine_point([6, 3, 2], 1), DVec3::new(1.0 / (5.0 * f64::from(REFINE)), 0.0, 0.0));
        assert_eq!(refined.fine_values(), &fine[..]);
    }

    #[test]
    fn a_linear_ramp_or_a_kink_at_a_lattice_point_is_not_refined() {
        let dims = [5, 4, 3];
        let ramp = (0..60).map(|n| (0.1 + 0.2 * (n % 5) as f64 / 4.0 + 0.3 * ((n / 20) as f64 / 2.0)) as f32).collect();
        assert!(Transmittance::new(dims, ramp).unwrap().cells_to_refine().is_empty());
        // |x − 0.5| bends at x = 0.5, a lattice point: the blend is exact on either side.
        let kink = (0..60).map(|n| ((n % 5) as f32 / 4.0 - 0.5).abs()).collect();
        assert!(Transmittance::new(dims, kink).unwrap().cells_to_refine().is_empty());
    }

    #[test]
    fn fine_values_must_fit_the_cells_the_coarse_values_refine() {
        let t = coarse_edge();
        let refinement = t.refinement();
        let n = refinement.points().len();
        let short = t.clone().with_fine(&refinement, vec![1.0; n - 1]);
        assert_eq!(short, Err(TransmittanceError::Length { expected: n, got: n - 1 }));
        let mut bad = vec![1.0; n];
        bad[7] = 1.5;
        assert!(matches!(t.clone().with_fine(&refinement, bad), Err(TransmittanceError::Value { index: 7, .. })));
        // A flat lattice refines nothing and takes no fine values.
        let flat = Transmittance::new([2, 2, 2], vec![0.5; 8]).unwrap();
        assert!(flat.cells_to_refine().is_empty());
        assert_eq!(flat.clone().with_fine(&flat.refinement(), Vec::new()), Ok(flat.clone()));
        // Another lattice's refinement is refused.
        assert!(matches!(flat.with_fine(&refinement, vec![1.0; n]), Err(TransmittanceError::Dims { .. })));
    }
}
