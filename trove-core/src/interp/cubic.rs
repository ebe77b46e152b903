//! The paper's cubic interpolation (§2.3.4 eq. 4, SPEC §3.3).
//!
//! # The field
//!
//! Inside one cell (cell coordinates `(x, y, z)`, corners at 0 and 1) the value is the 20-term cubic of eq. 4
//!
//! ```text
//! Q = λ1 x³ + λ2 y³ + λ3 z³ + λ4 x²y + λ5 x²z + λ6 y²x + λ7 y²z + λ8 z²x + λ9 z²y + λ10 xyz
//!   + λ11 x² + λ12 y² + λ13 z² + λ14 xy + λ15 yz + λ16 zx + λ17 x + λ18 y + λ19 z + λ20.
//! ```
//!
//! These are *all* monomials of total degree ≤ 3 in three variables (there are C(6,3) = 20 of them: 10 of
//! degree 3, 6 of degree 2, 3 of degree 1, 1 constant), so nothing is missing: eq. 4 is the full cubic
//! space, and every cubic polynomial whose samples are fed in is reproduced exactly (see below).
//!
//! # Sample ordering (the renderer gathers values in this order)
//!
//! * indices `0..8`: the cell corners, `c = x + 2y + 4z` for `(x, y, z) ∈ {0,1}³`;
//! * index `8 + 3c + a` (`a` = axis 0, 1, 2): the extended neighbour one step further out from corner `c`
//!   along axis `a` — that coordinate is −1 if the corner's is 0 and 2 if it is 1, the other two are the
//!   corner's. (The renderer clamps the grid indices to the dataset, SPEC §3.3, before reading.)
//!
//! # Why an equality-constrained least-squares fit
//!
//! The paper fixes λ from the 8 corners "plus another 12 points chosen from the 24 extended neighbouring
//! points", without saying which 12. Any choice of 12 breaks the cube's symmetry, so SPEC §3.3 uses all 24:
//! the field must still *interpolate* the data (a value read at a grid point is the stored voxel, as for
//! every other interpolation), so the corners are hard constraints, and the 24 extended neighbours — 32
//! conditions for 20 unknowns in total — are matched as well as possible. That is
//!
//! ```text
//! minimise ‖E λ − e‖²  subject to  C λ = c,
//! ```
//!
//! with `C` the 8×20 matrix of the monomials at the corners and `E` the 24×20 matrix at the extended points.
//!
//! *The constraints have full row rank 8.* On `{0,1}³` the multilinear monomials `1, x, y, z, xy, yz, zx, xyz`
//! are all present in eq. 4 and are linearly independent there (they are the trilinear basis), so the 8
//! corner rows are independent; a particular solution is the trilinear interpolant `T` of the corners.
//!
//! *The null space of `C` is 12-dimensional* and has the explicit basis `s(s−1)·{1, s, r, p}` for each
//! axis variable `s` with `r, p` the other two (e.g. `x²−x, x³−x², x²y−xy, x²z−xz`): each vanishes at every
//! corner, they have distinct leading monomials, hence are independent, and 20 − 8 = 12.
//!
//! *The reduced least-squares problem is well posed and decouples by axis.* At an extended point along axis
//! `s` the other two variables are 0 or 1, so the factors `r(r−1)` and `p(p−1)` of the other axes' basis
//! functions vanish and only the `s` group is seen, with factor `s(s−1) = 2` (at `s = −1` and at `s = 2`).
//! Writing `Q = T + Σ_s s(s−1)·g_s` with `g_s` affine in `(x, y, z)`, the problem splits into three
//! independent fits of an affine function `g_s` to the 8 residuals `(v − T)/2` at the points
//! `{−1, 2} × {0, 1} × {0, 1}` (axis `s` first). That is a full two-level factorial design, whose 8×4 design
//! matrix `[1, s, r, p]` has rank 4, so each fit — and the whole 24×12 reduced problem — has full column
//! rank and a unique solution. (It is also orthogonal after centring: `g_s` = mean residual + slopes, with
//! slope along `s` = difference of the two end means / 3 and along `r`, `p` = difference of the means.)
//! Equivalently, `[C; E]` (32×20) has rank 20, which together with rank `C` = 8 is exactly the condition
//! for the KKT system of the constrained problem to be non-singular. The tests check all three ranks and
//! that the KKT solution agrees with the null-space one.
//!
//! The fitted λ is linear in the 32 values: `λ = F · values` with one fixed 20×32 matrix `F`, the same for
//! every cell ([`fit_matrix`]). [`weights`] folds `F` with the monomials at the evaluation point, so
//! `Q(t) = Σ wᵢ·valuesᵢ`.
//!
//! *Exactness.* If the 32 values are samples of a cubic `p`, then `p`'s coefficients satisfy the constraints
//! with zero residual, and since the minimiser is unique, `Q = p`: cubics (hence constants and linear fields)
//! are reproduced exactly. The weights therefore sum to 1.
//!
//! # Not continuous across cell faces
//!
//! Neighbouring cells share the corners on their common face, so `Q` agrees at grid points, but each cell's
//! correction terms `s(s−1)·g_s` are fitted to *its own* 24 extended neighbours. On a face `x = 1`, say, the
//! `x` group vanishes, but the `y` and `z` groups do not, and their affine fits use points at `x = 0` and
//! `x = −1` in one cell and at `x = 2` in the other: the two cells' cubics differ on the face (and even along
//! shared edges). So the field jumps across cell faces, which is why SPEC §4.5 fixes which cell a point on a
//! face belongs to (the one whose lower corner it is).
//!
//! # Numerics
//!
//! `F` is computed once, in f64, from the null-space formulation above (the reduced normal equations are
//! 12×12, block diagonal with three well-conditioned 4×4 blocks), on first use through a [`OnceLock`].
use std::sync::OnceLock;

/// Number of terms of the cubic field of eq. 4.
pub const TERMS: usize = 20;
/// Number of samples the fit reads: 8 corners then 24 extended neighbours (see the module documentation).
pub const SAMPLES: usize = 32;

/// Exponents `(x, y, z)` of the monomials of eq. 4, in the paper's order `λ1 .. λ20`.
const MONOMIALS: [[u8; 3]; TERMS] = [
    [3, 0, 0],
    [0, 3, 0],
    [0, 0, 3],
    [2, 1, 0],
    [2, 0, 1],
    [1, 2, 0],
    [0, 2, 1],
    [1, 0, 2],
    [0, 1, 2],
    [1, 1, 1],
    [2, 0, 0],
    [0, 2, 0],
    [0, 0, 2],
    [1, 1, 0],
    [0, 1, 1],
    [1, 0, 1],
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [0, 0, 0],
];

/// The monomials of eq. 4 evaluated at `t`, in the order `λ1 .. λ20`.
pub fn basis(t: [f64; 3]) -> [f64; TERMS] {
    let [x, y, z] = t;
    let (x2, y2, z2) = (x * x, y * y, z * z);
    [
        x2 * x,
        y2 * y,
        z2 * z,
        x2 * y,
        x2 * z,
        y2 * x,
        y2 * z,
        z2 * x,
        z2 * y,
        x * y * z,
        x2,
        y2,
        z2,
        x * y,
        y * z,
        z * x,
        x,
        y,
        z,
        1.0,
    ]
}

/// The cell-coordinate position of sample `i` (`0 ≤ i < 32`) in the fixed ordering of the module
/// documentation: corners `c = x + 2y + 4z` first, then `8 + 3c + a` one step out from corner `c` along
/// axis `a`.
///
/// # Panics
/// If `i ≥ 32` (a programming error: the ordering has exactly 32 entries).
pub fn sample_point(i: usize) -> [f64; 3] {
    assert!(i < SAMPLES, "cubic sample index {i} out of range 0..32");
    let corner = |c: usize| [(c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64];
    if i < 8 {
        return corner(i);
    }
    let (c, a) = ((i - 8) / 3, (i - 8) % 3);
    let mut p = corner(c);
    p[a] = if p[a] == 0.0 { -1.0 } else { 2.0 };
    p
}

/// The fixed 20×32 fitting matrix `F`: `λ = F · values`, row `k` giving `λ_{k+1}` of eq. 4 and column `i`
/// sample `i` of the ordering in the module documentation. Computed once, on first use.
pub fn fit_matrix() -> &'static [[f64; SAMPLES]; TERMS] {
    static FIT: OnceLock<[[f64; SAMPLES]; TERMS]> = OnceLock::new();
    FIT.get_or_init(compute_fit_matrix)
}

/// Interpolation weights at cell coordinates `t` (normally in `[0,1]³`): `Q(t) = Σ wᵢ·valuesᵢ` with the
/// values in the documented sample order. This is `Fᵀ · basis(t)`; the weights sum to 1 and at a corner
/// they are that corner's unit vector (the fit interpolates the corners).
pub fn weights(t: [f64; 3]) -> [f64; SAMPLES] {
    let f = fit_matrix();
    let m = basis(t);
    let mut w = [0.0; SAMPLES];
    for (row, &mk) in f.iter().zip(m.iter()) {
        for (wi, &fi) in w.iter_mut().zip(row.iter()) {
            *wi += fi * mk;
        }
    }
    w
}

/// A bound on the sum of the negative weights, Σᵢ max(0, −wᵢ(t)), over the cell t ∈ [0, 1]³:
/// with Σ wᵢ = 1 the fitted value then lies within N·(max − min) of the values it reads,
/// which is how far empty-space skipping must widen a macrocell's range for the cubic.
///
/// Each weight is a polynomial of degree ≤ 3 per axis. On each of 8³ sub-cubes its tensor
/// Bernstein coefficients of degree (3, 3, 3) bound it from below (convex hull property), so
/// on that sub-cube Σᵢ max(0, −wᵢ) ≤ Σᵢ max(0, −min coefficient of wᵢ); N is the largest of
/// these over the sub-cubes, widened for rounding. Computed once.
pub fn negative_weight_bound() -> f64 {
    static BOUND: OnceLock<f64> = OnceLock::new();
    *BOUND.get_or_init(|| {
        const PARTS: usize = 8;
        let f = fit_matrix();
        // Each weight as a 4×4×4 tensor of monomial coefficients c[x power][y power][z power].
        let tensors: Vec<[[[f64; 4]; 4]; 4]> = (0..SAMPLES)
            .map(|sample| {
                let mut c = [[[0.0; 4]; 4]; 4];
                for (&[a, b, e], row) in MONOMIALS.iter().zip(f.iter()) {
                    c[a as usize][b as usize][e as usize] += row[sample];
                }
                c
            })
            .collect();
        let choose = |n: usize, k: usize| -> f64 {
            const C: [[f64; 4]; 4] =
                [[1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 0.0, 0.0], [1.0, 2.0, 1.0, 0.0], [1.0, 3.0, 3.0, 1.0]];
            C[n][k]
        };
        // Per axis, the substitution x = a + h·s followed by the change to the Bernstein basis
        // of degree 3 in s is one 4×4 matrix: bernstein[i] = Σ_p m[i][p]·monomial[p].
        let axis_matrix = |a: f64, h: f64| -> [[f64; 4]; 4] {
            let mut m = [[0.0; 4]; 4];
            for (i, row) in m.iter_mut().enumerate() {
                for (p, out) in row.iter_mut().enumerate() {
                    // x^p = Σ_q C(p, q)·a^(p−q)·h^q·s^q, and s^q has Bernstein coefficient
                    // C(i, q)/C(3, q) at index i.
                    *out = (0..=p.min(i))
                        .map(|q| choose(p, q) * a.powi((p - q) as i32) * h.powi(q as i32) * choose(i, q) / choose(3, q))
                        .sum();
                }
            }
            m
        };
        let h = 1.0 / PARTS as f64;
        let matrices: Vec<[[f64; 4]; 4]> = (0..PARTS).map(|k| axis_matrix(k as f64 * h, h)).collect();
        // Applied one axis at a time: 3·4⁴ products per weight and sub-cube.
        type Tensor = [[[f64; 4]; 4]; 4];
        let along = |c: &Tensor, m: &[[f64; 4]; 4], axis: usize| -> Tensor {
            let mut out = [[[0.0; 4]; 4]; 4];
            for i in 0..4 {
                for u in 0..4 {
                    for v in 0..4 {
                        out[i][u][v] = (0..4)
                            .map(|p| {
                                m[i][p]
                                    * match axis {
                                        0 => c[p][u][v],
                                        1 => c[u][p][v],
                                        _ => c[u][v][p],
                                    }
                            })
                            .sum();
                    }
                }
            }
            // Put the transformed axis back in its place.
            let mut placed = [[[0.0; 4]; 4]; 4];
            for i in 0..4 {
                for u in 0..4 {
                    for v in 0..4 {
                        match axis {
                            0 => placed[i][u][v] = out[i][u][v],
                            1 => placed[u][i][v] = out[i][u][v],
                            _ => placed[u][v][i] = out[i][u][v],
                        }
                    }
                }
            }
            placed
        };
        let mut worst = 0.0f64;
        for mx in &matrices {
            let along_x: Vec<Tensor> = tensors.iter().map(|c| along(c, mx, 0)).collect();
            for my in &matrices {
                let along_xy: Vec<Tensor> = along_x.iter().map(|c| along(c, my, 1)).collect();
                for mz in &matrices {
                    let negative: f64 = along_xy
                        .iter()
                        .map(|c| {
                            let b = along(c, mz, 2);
                            let lowest = b.iter().flatten().flatten().copied().fold(f64::INFINITY, f64::min);
                            (-lowest).max(0.0)
                        })
                        .sum();
                    worst = worst.max(negative);
                }
            }
        }
        worst * (1.0 + 1e-9) + 1e-9
    })
}

/// Monomial-coefficient vector of `Σ coef · x^e0 y^e1 z^e2` (all exponents must be among eq. 4's).
fn poly(terms: &[(f64, [u8; 3])]) -> [f64; TERMS] {
    let mut out = [0.0; TERMS];
    for &(coef, e) in terms {
        // The exponents come from the fixed tables in this file, all of total degree ≤ 3.
        let k = MONOMIALS.iter().position(|&m| m == e).expect("monomial of degree ≤ 3");
        out[k] += coef;
    }
    out
}

/// Solves `A X = B` by Gaussian elimination with partial pivoting (`A` n×n, `B` n×m, both row-major).
/// Only used on the small, provably non-singular systems of this module.
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
    let n = a.len();
    for col in 0..n {
        let piv = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        let p = a[col][col];
        assert!(p != 0.0, "singular system in the cubic fit (cannot happen: see the rank argument)");
        for r in col + 1..n {
            let f = a[r][col] / p;
            if f != 0.0 {
                let (upper, lower) = a.split_at_mut(r);
                for (x, y) in lower[0][col..].iter_mut().zip(&upper[col][col..]) {
                    *x -= f * y;
                }
                let (upper, lower) = b.split_at_mut(r);
                for (x, y) in lower[0].iter_mut().zip(&upper[col]) {
                    *x -= f * y;
                }
            }
        }
    }
    for col in (0..n).rev() {
        for c in 0..b[col].len() {
            let mut s = b[col][c];
            for k in col + 1..n {
                s -= a[col][k] * b[k][c];
            }
            b[col][c] = s / a[col][col];
        }
    }
    b
}

/// The null-space construction of `F` described in the module documentation.
fn compute_fit_matrix() -> [[f64; SAMPLES]; TERMS] {
    let rows: Vec<[f64; TERMS]> = (0..SAMPLES).map(|i| basis(sample_point(i))).collect();

    // Particular solution: the trilinear interpolant of the corners, in the multilinear monomials.
    const MULTILINEAR: [[u8; 3]; 8] =
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]];
    let ml_index: Vec<usize> =
        MULTILINEAR.iter().map(|e| MONOMIALS.iter().position(|m| m == e).expect("multilinear monomial")).collect();
    let ct: Vec<Vec<f64>> = (0..8).map(|c| ml_index.iter().map(|&k| rows[c][k]).collect()).collect();
    let identity8: Vec<Vec<f64>> = (0..8).map(|r| (0..8).map(|c| f64::from(u8::from(r == c))).collect()).collect();
    let tri = solve(ct, identity8); // 8 multilinear coefficients × 8 corner values
                                    // P: 20×32, λ_T = P · values (only corner columns are non-zero).
    let mut p = vec![vec![0.0; SAMPLES]; TERMS];
    for (j, &k) in ml_index.iter().enumerate() {
        p[k][..8].copy_from_slice(&tri[j]);
    }

    // Null-space basis of the corner constraints: s(s−1)·{1, s, r, p} per axis s.
    let mut null = Vec::with_capacity(12);
    for s in 0..3 {
        let e = |axis: usize, k: u8| {
            let mut v = [0u8; 3];
            v[axis] = k;
            v
        };
        let (r, q) = ((s + 1) % 3, (s + 2) % 3);
        let add = |a: [u8; 3], b: [u8; 3]| [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
        for extra in [[0u8; 3], e(s, 1), e(r, 1), e(q, 1)] {
            null.push(poly(&[(1.0, add(e(s, 2), extra)), (-1.0, add(e(s, 1), extra))]));
        }
    }

    // Reduced problem: A = E·N (24×12); residual data R = [−E·P_corners | I24] (24×32).
    let ext = &rows[8..];
    let a: Vec<Vec<f64>> =
        ext.iter().map(|row| null.iter().map(|n| row.iter().zip(n).map(|(r, v)| r * v).sum()).collect()).collect();
    let mut resid = vec![vec![0.0; SAMPLES]; 24];
    for (i, row) in ext.iter().enumerate() {
        for j in 0..SAMPLES {
            resid[i][j] = -(0..TERMS).map(|k| row[k] * p[k][j]).sum::<f64>();
        }
        resid[i][8 + i] += 1.0;
    }
    // Normal equations (AᵀA) M = Aᵀ R; AᵀA is block diagonal with three non-singular 4×4 blocks.
    let ata: Vec<Vec<f64>> =
        (0..12).map(|r| (0..12).map(|c| (0..24).map(|i| a[i][r] * a[i][c]).sum()).collect()).collect();
    let atr: Vec<Vec<f64>> =
        (0..12).map(|r| (0..SAMPLES).map(|c| (0..24).map(|i| a[i][r] * resid[i][c]).sum()).collect()).collect();
    let mu = solve(ata, atr); // 12×32

    let mut f = [[0.0; SAMPLES]; TERMS];
    for k in 0..TERMS {
        for j in 0..SAMPLES {
            f[k][j] = p[k][j] + (0..12).map(|b| null[b][k] * mu[b][j]).sum::<f64>();
        }
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Numerical rank by Gaussian elimination with full pivoting.
    fn rank(mut m: Vec<Vec<f64>>, tol: f64) -> usize {
        let (rows, cols) = (m.len(), m[0].len());
        let mut r = 0;
        for _ in 0..rows.min(cols) {
            let mut best = (0.0, 0, 0);
            for (i, row) in m.iter().enumerate().skip(r) {
                for (j, v) in row.iter().enumerate() {
                    if v.abs() > best.0 {
                        best = (v.abs(), i, j);
                    }
                }
            }
            if best.0 <= tol {
                break;
            }
            m.swap(r, best.1);
            for row in m.iter_mut() {
                row.swap(r, best.2);
            }
            for i in r + 1..rows {
                let f = m[i][r] / m[r][r];
                let (upper, lower) = m.split_at_mut(i);
                for (x, y) in lower[0][r..cols].iter_mut().zip(&upper[r][r..cols]) {
                    *x -= f * y;
                }
            }
            r += 1;
        }
        r
    }

    fn rows() -> Vec<Vec<f64>> {
        (0..SAMPLES).map(|i| basis(sample_point(i)).to_vec()).collect()
    }

    #[test]
    fn eq4_is_the_full_cubic_space() {
        let mut seen = std::collections::BTreeSet::new();
        for e in MONOMIALS {
            assert!(e.iter().map(|&k| u32::from(k)).sum::<u32>() <= 3);
            assert!(seen.insert(e), "duplicate monomial {e:?}");
        }
        let mut all = 0;
        for a in 0..=3u8 {
            for b in 0..=3 - a {
                for c in 0..=3 - a - b {
                    all += 1;
                    assert!(seen.contains(&[a, b, c]), "monomial x^{a} y^{b} z^{c} missing from eq. 4");
                }
            }
        }
        assert_eq!(all, TERMS);
    }

    #[test]
    fn sample_ordering() {
        assert_eq!(sample_point(5), [1.0, 0.0, 1.0]);
        assert_eq!(sample_point(8), [-1.0, 0.0, 0.0]); // corner 0, axis x
        assert_eq!(sample_point(8 + 3 * 7 + 2), [1.0, 1.0, 2.0]); // corner 7, axis z
        assert_eq!(sample_point(8 + 3 * 2 + 1), [0.0, 2.0, 0.0]); // corner 2, axis y
        let mut pts: Vec<[i64; 3]> = (0..SAMPLES).map(|i| sample_point(i).map(|v| v as i64)).collect();
        pts.sort_unstable();
        pts.dedup();
        assert_eq!(pts.len(), SAMPLES);
    }

    #[test]
    fn ranks_make_the_fit_well_posed() {
        let r = rows();
        assert_eq!(rank(r[..8].to_vec(), 1e-12), 8, "corner constraints must have full row rank");
        assert_eq!(rank(r.clone(), 1e-12), 20, "[C; E] must have full column rank");
        // Reduced problem: E restricted to the null space of C. Build a null-space basis numerically
        // (independently of the hand-made one) from the rank: ker C has dimension 12.
        assert_eq!(TERMS - rank(r[..8].to_vec(), 1e-12), 12);
        let ata_rank = {
            // E·N with the hand-made basis must have rank 12.
            let mut null = Vec::new();
            for s in 0..3usize {
                for extra in 0..4usize {
                    let f = move |p: [f64; 3]| {
                        let v = p[s];
                        let m = [1.0, v, p[(s + 1) % 3], p[(s + 2) % 3]][extra];
                        v * (v - 1.0) * m
                    };
                    null.push(f);
                }
            }
            let en: Vec<Vec<f64>> = (8..SAMPLES).map(|i| null.iter().map(|f| f(sample_point(i))).collect()).collect();
            // and those functions really vanish at the corners
            for c in 0..8 {
                for f in &null {
                    assert_eq!(f(sample_point(c)), 0.0);
                }
            }
            rank(en, 1e-12)
        };
        assert_eq!(ata_rank, 12);
    }

    /// The KKT system [2EᵀE Cᵀ; C 0][λ; ν] = [2Eᵀe; c], solved independently, gives the same F.
    #[test]
    fn kkt_agrees_with_null_space() {
        let r = rows();
        let n = TERMS + 8;
        let mut k = vec![vec![0.0; n]; n];
        let mut rhs = vec![vec![0.0; SAMPLES]; n];
        for i in 0..TERMS {
            for j in 0..TERMS {
                k[i][j] = 2.0 * (8..SAMPLES).map(|s| r[s][i] * r[s][j]).sum::<f64>();
            }
            for c in 0..8 {
                k[i][TERMS + c] = r[c][i];
                k[TERMS + c][i] = r[c][i];
            }
            for s in 8..SAMPLES {
                rhs[i][s] = 2.0 * r[s][i];
            }
        }
        for c in 0..8 {
            rhs[TERMS + c][c] = 1.0;
        }
        let sol = solve(k, rhs);
        let f = fit_matrix();
        for i in 0..TERMS {
            for j in 0..SAMPLES {
                assert!((sol[i][j] - f[i][j]).abs() < 1e-10, "F[{i}][{j}]: KKT {} vs {}", sol[i][j], f[i][j]);
            }
        }
    }

    #[test]
    fn corners_are_reproduced_exactly() {
        for c in 0..8 {
            let w = weights(sample_point(c));
            for (i, wi) in w.iter().enumerate() {
                let want = if i == c { 1.0 } else { 0.0 };
                assert!((wi - want).abs() < 1e-12, "corner {c}, weight {i} = {wi}");
            }
        }
    }

    #[test]
    fn mirror_symmetry_of_the_ordering() {
        // Mirroring axis a maps sample i to sample σ(i); the weights must follow.
        for a in 0..3 {
            let sigma = |i: usize| {
                let mut p = sample_point(i);
                p[a] = 1.0 - p[a];
                (0..SAMPLES).find(|&j| sample_point(j) == p).expect("mirror image is a sample")
            };
            let t = [0.21, 0.67, 0.43];
            let mut tm = t;
            tm[a] = 1.0 - t[a];
            let (w, wm) = (weights(t), weights(tm));
            for i in 0..SAMPLES {
                assert!((w[i] - wm[sigma(i)]).abs() < 1e-12, "axis {a}, sample {i}");
            }
        }
    }

    #[test]
    fn negative_weights_stay_within_their_bound_over_the_cell() {
        let bound = negative_weight_bound();
        let mut worst = 0.0f64;
        let steps = 12;
        for i in 0..=steps {
            for j in 0..=steps {
                for k in 0..=steps {
                    let t = [i, j, k].map(|v| v as f64 / steps as f64);
                    let negative: f64 = weights(t).iter().map(|w| (-w).max(0.0)).sum();
                    worst = worst.max(negative);
                }
            }
        }
        assert!(worst > 0.0, "the fitted cubic overshoots somewhere");
        assert!(worst <= bound, "sampled {worst} exceeds the bound {bound}");
        // A bound, but not a loose one.
        assert!(bound < 1.5 * worst, "bound {bound} against sampled {worst}");
    }

    fn eval(lambda: &[f64], p: [f64; 3]) -> f64 {
        basis(p).iter().zip(lambda).map(|(m, l)| m * l).sum()
    }

    proptest! {
        #[test]
        fn cubics_are_reproduced(lambda in prop::collection::vec(-10.0f64..10.0, TERMS),
                                 t in prop::array::uniform3(0.0f64..=1.0)) {
            let values: Vec<f64> = (0..SAMPLES).map(|i| eval(&lambda, sample_point(i))).collect();
            let w = weights(t);
            let q: f64 = w.iter().zip(&values).map(|(w, v)| w * v).sum();
            let scale = lambda.iter().map(|l| l.abs()).sum::<f64>().max(1.0);
            prop_assert!((q - eval(&lambda, t)).abs() <= 1e-9 * scale);
        }

        #[test]
        fn weights_sum_to_one_and_linear_fields_are_reproduced(
            t in prop::array::uniform3(-0.5f64..=1.5), a in prop::array::uniform4(-100.0f64..100.0)) {
            let w = weights(t);
            prop_assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            let lin = |p: [f64; 3]| a[0] + a[1] * p[0] + a[2] * p[1] + a[3] * p[2];
            let q: f64 = (0..SAMPLES).map(|i| w[i] * lin(sample_point(i))).sum();
            prop_assert!((q - lin(t)).abs() < 1e-10 * 400.0);
        }
    }
}
