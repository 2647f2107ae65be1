//! The Jacobi iteration for the radiosity system (Cohen and Wallace 1993, *Radiosity and
//! Realistic Image Synthesis*, §5.3.1; radiosidade.md, "Sistema Linear"):
//!
//! ```text
//! B^0 = E,    B^{k+1} = E + diag(rho) F B^k
//! ```
//!
//! Each iterate gathers from the previous one only, so the rows are computed in parallel and
//! the result does not depend on the number of threads. `B^k` is the sum of the first `k + 1`
//! terms of the Neumann series `sum_m (diag(rho) F)^m E`: physically, light after at most `k`
//! bounces. It converges when the spectral radius of `diag(rho) F` is below 1, which holds
//! whenever `rho < 1` and the rows of `F` sum to at most 1 (Cohen and Wallace §5.3).
//!
//! The residual of `B^k` is `B^{k+1} - B^k`, so measuring it costs nothing: each pass over
//! `F` both measures `B^k` and computes `B^{k+1}`, and the solver returns the first `B^k`
//! within tolerance, with its exact residual (one pass more than the iterations reported).
//! Within tolerance means both the relative residual and the per-patch rule of the [module
//! docs](super), measured in the same pass.

use super::{gather, max3, sweep_loop, Options, SolveReport, Solver, System};
use crate::error::Result;
use rayon::prelude::*;

pub(crate) const NAME: &str = "jacobi";

/// The Jacobi iteration; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct Jacobi;

impl Solver for Jacobi {
    fn name(&self) -> &'static str {
        NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        sweep_loop(NAME, sys, opts, |rows, floor, b, next| {
            next.par_iter_mut()
                .enumerate()
                .map(|(i, out)| {
                    *out = gather(sys, rows, b, i);
                    let r = [0, 1, 2].map(|c| out[c] - b[i][c]);
                    (r.map(f64::abs), floor.of_residual(sys, i, r, b[i]))
                })
                .reduce(
                    || ([0.0; 3], [0.0; 3]),
                    |x, y| (max3(x.0, y.0), max3(x.1, y.1)),
                )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;

    #[test]
    fn one_patch_geometric_series() {
        // One concave patch seeing itself: B^k = E (1 + q + ... + q^k), q = rho F_00, and the
        // residual of B^k is E q^{k+1}, relative q^{k+1}.
        let f = dense(&[&[0.5]]);
        let (rho, emit, area) = ([[0.8; 3]], [[2.0; 3]], [1.0]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        let opts = Options {
            tolerance: 1e-6,
            ..Options::default()
        };
        let (b, report) = Jacobi.solve(&sys, &opts).unwrap();
        let q: f64 = 0.4;
        // Smallest k with q^{k+1} <= 1e-6.
        let k = ((1e-6f64).ln() / q.ln()).ceil() as usize - 1;
        assert_eq!(report.iterations, k);
        assert_eq!(report.history.len(), k + 1);
        for (m, h) in report.history.iter().enumerate() {
            assert!(
                (h - q.powi(m as i32 + 1)).abs() < 1e-12,
                "history[{m}] = {h}"
            );
        }
        let want = 2.0 * (1.0 - q.powi(k as i32 + 1)) / (1.0 - q);
        assert!((b[0][0] - want).abs() < 1e-12);
        assert_eq!(report.solver, "jacobi");
    }

    #[test]
    fn history_decreases_on_physical_system() {
        let owned = random(50, 8, 11);
        let (_, report) = Jacobi.solve(&owned.sys(), &Options::default()).unwrap();
        assert!(report.converged);
        assert_eq!(report.history.len(), report.iterations + 1);
        assert!(report
            .history
            .windows(2)
            .all(|w| w[1] <= w[0] * (1.0 + 1e-12)));
        assert_eq!(*report.history.last().unwrap(), report.residual);
    }
}
