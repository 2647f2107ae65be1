//! The Gauss-Seidel iteration for the radiosity system (Cohen and Wallace 1993, *Radiosity
//! and Realistic Image Synthesis*, §5.3.2; Cohen and Greenberg 1985, "The hemi-cube", which
//! solved the system this way).
//!
//! A sweep updates `B` in place, row by row, each row gathering from the values already
//! updated in this sweep. Row `i` is solved for its own `B_i`, so a non-zero diagonal
//! `F_ii` (a concave patch seeing itself) is handled exactly rather than lagged:
//!
//! ```text
//! B_i <- (E_i + rho_i sum_{j != i} F_ij B_j) / (1 - rho_i F_ii)
//! ```
//!
//! (`System::new` guarantees `rho_i F_ii < 1`). Convergence holds under the same condition
//! as Jacobi's and is usually about twice as fast for radiosity matrices, at the price of a
//! sequential sweep.
//!
//! The same pass over a row also accumulates `sum_j F_ij B_j` with the values from before
//! the sweep (kept in a copy), which gives the exact residual of the iterate the sweep
//! starts from, and its per-patch measure (see the [module docs](super)). As for
//! [`Jacobi`](super::Jacobi), the solver returns the first iterate within tolerance by both
//! with its exact residuals.

use super::{max3, sweep_loop, Options, SolveReport, Solver, System};
use crate::error::Result;

pub(crate) const NAME: &str = "gauss-seidel";

/// The Gauss-Seidel iteration; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct GaussSeidel;

impl Solver for GaussSeidel {
    fn name(&self) -> &'static str {
        NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        // Both values of patch j a row reads, the sweep's start and its current one, in one
        // cache line: a row's columns are scattered over the patches, so each entry costs
        // one line read instead of two.
        let mut both: Vec<Both> = Vec::new();
        sweep_loop(NAME, sys, opts, |rows, floor, old, b| {
            both.clear();
            both.extend(
                old.iter()
                    .map(|&o| Both([o[0], o[1], o[2], o[0], o[1], o[2], 0.0, 0.0])),
            );
            let mut res = [0.0f64; 3];
            let mut per_patch = [0.0f64; 3];
            for i in 0..rows.len() {
                let (ind, val) = rows.row(i);
                // `all`: F_i . old (for the residual of `old`); `off`: the sweep's sum over
                // j != i with current values; `fii`: the diagonal.
                let (mut all, mut off, mut fii) = ([0.0; 3], [0.0; 3], 0.0);
                for (k, (&j, &f)) in ind.iter().zip(val).enumerate() {
                    if let Some(&ahead) = ind.get(k + PREFETCH) {
                        crate::simd::prefetch(&both[ahead as usize]);
                    }
                    let j = j as usize;
                    let w = &both[j].0;
                    for c in 0..3 {
                        all[c] += f * w[c];
                    }
                    if j == i {
                        fii += f;
                    } else {
                        for c in 0..3 {
                            off[c] += f * w[3 + c];
                        }
                    }
                }
                let (e, rho) = (sys.emit[i], sys.rho[i]);
                let r = [0, 1, 2].map(|c| e[c] + rho[c] * all[c] - old[i][c]);
                per_patch = max3(per_patch, floor.of_residual(sys, i, r, old[i]));
                res = max3(res, r.map(f64::abs));
                let new = [0, 1, 2].map(|c| (e[c] + rho[c] * off[c]) / (1.0 - rho[c] * fii));
                b[i] = new;
                both[i].0[3..6].copy_from_slice(&new);
            }
            (res, per_patch)
        })
    }
}

/// How many entries ahead of the one read a sweep asks for its patch's record.
const PREFETCH: usize = 16;

/// A patch's value at the start of a sweep and its current one, aligned to a cache line.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Both([f64; 8]);

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;

    #[test]
    fn diagonal_is_solved_not_lagged() {
        // One patch seeing itself: a single sweep gives the exact E / (1 - rho F_00), so the
        // second pass finds a zero residual and the answer comes after one iteration.
        let f = dense(&[&[0.5]]);
        let (rho, emit, area) = ([[0.8, 0.4, 0.0]], [[2.0, 1.0, 3.0]], [1.0]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        let (b, report) = GaussSeidel.solve(&sys, &Options::default()).unwrap();
        assert_eq!(report.iterations, 1);
        assert!(report.residual < 1e-15);
        assert!((b[0][0] - 2.0 / 0.6).abs() < 1e-14);
        assert!((b[0][1] - 1.0 / 0.8).abs() < 1e-14);
        assert_eq!(b[0][2], 3.0);
    }

    #[test]
    fn faster_than_jacobi() {
        let owned = random(50, 8, 5);
        let opts = Options {
            tolerance: 1e-10,
            ..Options::default()
        };
        let (_, gs) = GaussSeidel.solve(&owned.sys(), &opts).unwrap();
        let (_, jac) = Jacobi.solve(&owned.sys(), &opts).unwrap();
        assert!(gs.converged && jac.converged);
        assert!(
            gs.iterations < jac.iterations,
            "{} vs {}",
            gs.iterations,
            jac.iterations
        );
        assert_eq!(gs.history.len(), gs.iterations + 1);
        assert!((residual(&owned.sys(), &owned.emit) - gs.history[0]).abs() < 1e-15);
    }
}
