//! The Gauss-Seidel iteration for the radiosity system (Cohen and Wallace 1993, *Radiosity
//! and Realistic Image Synthesis*, §5.3.2; Cohen and Greenberg 1985, "The hemi-cube", which
//! solved the system this way), and its over-relaxed form, successive over-relaxation.
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
//!
//! ## Over-relaxation ([`Sor`])
//! Successive over-relaxation (Young 1950; Varga, *Matrix Iterative Analysis*, 2nd ed.
//! 2000, §3.1) moves each patch past its Gauss-Seidel value by a factor `omega`:
//!
//! ```text
//! B_i <- (1 - omega) B_i + omega (E_i + rho_i sum_{j != i} F_ij B_j) / (1 - rho_i F_ii)
//! ```
//!
//! `omega = 1` is Gauss-Seidel. When is `omega > 1` safe? Write `J` for the Jacobi matrix
//! (`J_ij = rho_i F_ij / (1 - rho_i F_ii)`, `j != i`) and `g` for the gain bound
//! `max_i rho_i sum_j |F_ij|` the solvers already compute; when `g < 1`, every row of `|J|`
//! sums to at most `g` (`rho (S - F_ii) / (1 - rho F_ii) <= rho S` exactly when `rho S <= 1`,
//! with `S` the row's sum). Let `e` be the error before a sweep and `e'` after it; if the rows
//! before `i` already satisfy `|e'_j| <= t ||e||_inf`, row `i` gives
//!
//! ```text
//! |e'_i| <= |1 - omega| ||e|| + omega (l_i t + u_i) ||e|| <= (|1 - omega| + omega g) ||e||
//! ```
//!
//! (`l_i`, `u_i`: the row's sums of `|J|` before and after the diagonal, `t <= 1`), so by
//! induction each sweep contracts the error's infinity norm by `t = |1 - omega| + omega g`,
//! below 1 for every `0 < omega < 2 / (1 + g)`. That bound is the classical one for
//! H-matrices (Varga, §3.6), proved here in the norm the solvers measure. It says when the
//! iteration converges, not how fast: the factor that pays is found by measurement. On the
//! radiosity systems of this project's scenes (the Cornell box, the closed cube, a room of
//! spheres, a closed furnace; hemisphere factors, 6,000 to 30,000 patches) Gauss-Seidel
//! needed 12-20 sweeps to the default tolerance and `omega = 1.1` 8-15, a quarter to a third
//! fewer, while 1.05, 1.15, 1.2, 1.3 and 1.4 did no better (docs/PERFORMANCE.md). So
//! [`Sor`] takes, channel by channel from that channel's gain `g_c`,
//!
//! ```text
//! omega_c = min(1.1, 1 + 0.9 (2 / (1 + g_c) - 1))
//! ```
//!
//! inside the proven range by a tenth of its width above 1, and plain Gauss-Seidel
//! (`omega_c = 1`) when `g_c >= 1`, where the bound proves nothing. A system with bright
//! walls (`g` near 1) gets `omega` near 1: there the conjugate-gradient solver
//! ([`Cg`](super::Cg)) is the one that pays (`radiosity study-solvers`).

use super::{
    max3, sweep_loop, sweeps, Floor, Options, Prologue, Rows, SolveReport, Solver, System,
};
use crate::error::{Error, Result};

pub(crate) const NAME: &str = "gauss-seidel";
pub(crate) const SOR_NAME: &str = "sor";

/// The largest factor [`Sor`] chooses by itself (module docs).
pub const MAX_RELAXATION: f64 = 1.1;

/// The Gauss-Seidel iteration; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct GaussSeidel;

impl Solver for GaussSeidel {
    fn name(&self) -> &'static str {
        NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        let mut both = Vec::new();
        sweep_loop(NAME, sys, opts, |rows, floor, old, b| {
            sweep(sys, rows, floor, [1.0; 3], &mut both, old, b)
        })
    }
}

/// Successive over-relaxation: Gauss-Seidel sweeps moving each patch `omega` times as far
/// (module docs, *Over-relaxation*).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sor {
    /// The factor, the same for every channel; `None` chooses one per channel from the
    /// system's gain bound ([`relaxation`]).
    pub omega: Option<f64>,
}

impl Sor {
    /// The factor chosen from the system.
    pub const AUTO: Sor = Sor { omega: None };
}

/// The factor [`Sor`] chooses for a channel whose gain bound (`max_i rho_i sum_j |F_ij|`) is
/// `gain`: `min(1.1, 1 + 0.9 (2 / (1 + gain) - 1))`, inside the range where the sweeps
/// provably converge, or 1 (Gauss-Seidel) when `gain` is not in `[0, 1)`.
pub fn relaxation(gain: f64) -> f64 {
    if !(0.0..1.0).contains(&gain) {
        return 1.0;
    }
    (1.0 + 0.9 * (2.0 / (1.0 + gain) - 1.0)).min(MAX_RELAXATION)
}

impl Solver for Sor {
    fn name(&self) -> &'static str {
        SOR_NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        if let Some(w) = self.omega {
            if !(w > 0.0 && w < 2.0) {
                return Err(Error::Config(format!(
                    "over-relaxation factor {w} is not in (0, 2), where successive \
                     over-relaxation can converge"
                )));
            }
        }
        let pro = Prologue::new(sys, opts)?;
        let omega = match self.omega {
            Some(w) => [w; 3],
            None => pro.gain.gain.map(relaxation),
        };
        let mut both = Vec::new();
        let (b, mut report) = sweeps(SOR_NAME, sys, opts, pro, |rows, floor, old, b| {
            sweep(sys, rows, floor, omega, &mut both, old, b)
        })?;
        report.relaxation = Some(omega);
        Ok((b, report))
    }
}

/// One sweep with factors `omega` (1: Gauss-Seidel): from `old`, the iterate the sweep
/// starts from, the next one into `b`; returns `old`'s residuals (see [`sweep_loop`]).
/// `both` is the sweep's scratch.
#[inline(always)]
fn sweep(
    sys: &System,
    rows: &Rows,
    floor: &Floor,
    omega: [f64; 3],
    both: &mut Vec<Both>,
    old: &[[f64; 3]],
    b: &mut [[f64; 3]],
) -> ([f64; 3], [f64; 3]) {
    // Both values of patch j a row reads, the sweep's start and its current one, in one
    // cache line: a row's columns are scattered over the patches, so each entry costs one
    // line read instead of two.
    both.clear();
    both.extend(
        old.iter()
            .map(|&o| Both([o[0], o[1], o[2], o[0], o[1], o[2], 0.0, 0.0])),
    );
    let mut res = [0.0f64; 3];
    let mut per_patch = [0.0f64; 3];
    for i in 0..rows.len() {
        let (ind, val) = rows.row(i);
        // `all`: F_i . old (for the residual of `old`); `off`: the sweep's sum over j != i
        // with current values; `fii`: the diagonal.
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
        let new = [0, 1, 2].map(|c| {
            let gs = (e[c] + rho[c] * off[c]) / (1.0 - rho[c] * fii);
            if omega[c] == 1.0 {
                gs
            } else {
                old[i][c] + omega[c] * (gs - old[i][c])
            }
        });
        b[i] = new;
        both[i].0[3..6].copy_from_slice(&new);
    }
    (res, per_patch)
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

    #[test]
    fn sor_at_one_is_gauss_seidel() {
        let owned = random(200, 12, 7);
        let opts = Options {
            tolerance: 1e-10,
            ..Options::default()
        };
        let (gs_b, gs) = GaussSeidel.solve(&owned.sys(), &opts).unwrap();
        let sor = Sor { omega: Some(1.0) };
        let (b, report) = sor.solve(&owned.sys(), &opts).unwrap();
        assert_eq!(b, gs_b);
        assert_eq!(report.history, gs.history);
        assert_eq!(report.solver, "sor");
        assert_eq!(report.relaxation, Some([1.0; 3]));
    }

    #[test]
    fn relaxation_stays_in_the_proven_range() {
        for k in 0..=1000 {
            let g = k as f64 / 1000.0 * 0.9999;
            let w = relaxation(g);
            assert!(
                (1.0..=super::MAX_RELAXATION).contains(&w),
                "g {g}: omega {w}"
            );
            // The sweep's contraction bound |1 - omega| + omega g stays below 1.
            assert!((w - 1.0) + w * g < 1.0, "g {g}: omega {w}");
            if g > 0.0 {
                assert!(w < 2.0 / (1.0 + g));
            }
        }
        for g in [1.0, 1.5, f64::INFINITY, f64::NEG_INFINITY, f64::NAN, -0.5] {
            assert_eq!(relaxation(g), 1.0, "{g}");
        }
        assert_eq!(relaxation(0.5), super::MAX_RELAXATION);
    }

    #[test]
    fn sor_contracts_as_proved() {
        // Every sweep shrinks the error's infinity norm by at most |1 - omega| + omega g
        // (module docs), for factors up to the edge of the proven range, on systems whose
        // gain g is near 1 (rho up to 0.95, rows summing to up to 0.98).
        let owned = random(120, 10, 11);
        let sys = owned.sys();
        let exact = Direct.solve(&sys, &Options::default()).unwrap().0;
        let g = Gain::new(&sys, &Rows::new(sys.f)).max();
        assert!(g > 0.8 && g < 1.0, "gain {g}");
        let edge = 2.0 / (1.0 + g);
        for omega in [0.6, 1.0, relaxation(g), 0.5 * (1.0 + edge), 0.99 * edge] {
            let t = (1.0 - omega).abs() + omega * g;
            let mut last = f64::NAN;
            for k in 0..12 {
                let opts = Options {
                    tolerance: 0.0,
                    max_iterations: k,
                    keep_partial: true,
                    floor: None,
                };
                let (b, _) = Sor { omega: Some(omega) }.solve(&sys, &opts).unwrap();
                let err = b
                    .iter()
                    .zip(&exact)
                    .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs()))
                    .fold(0.0, f64::max);
                if k > 0 {
                    assert!(
                        err <= t * last + 1e-13,
                        "omega {omega}, sweep {k}: {err:e} > {t} x {last:e}"
                    );
                }
                last = err;
            }
        }
    }

    #[test]
    fn sor_needs_fewer_sweeps_and_agrees_with_direct() {
        // Closed furnaces (rows sum to 1): the chosen factor takes fewer sweeps than
        // Gauss-Seidel to the same tolerance, and both answers agree with the dense solve.
        // (Not on every matrix: on `random`'s, whose rows pick columns at random, it can
        // take a sweep more; `tests/stability.rs` checks the Cornell box's factors.)
        let opts = Options {
            tolerance: 1e-10,
            ..Options::default()
        };
        let cases = [
            furnace(300, [0.5, 0.8, 0.7], [1.0, 0.5, 2.0]),
            furnace(200, [0.3, 0.3, 0.6], [1.0, 1.0, 1.0]),
        ];
        for (n, owned) in cases.iter().enumerate() {
            let sys = owned.sys();
            let exact = Direct.solve(&sys, &Options::default()).unwrap().0;
            let (gs_b, gs) = GaussSeidel.solve(&sys, &opts).unwrap();
            let (b, sor) = Sor::AUTO.solve(&sys, &opts).unwrap();
            eprintln!(
                "case {n}: sor {:?} {} sweeps, gauss-seidel {}",
                sor.relaxation, sor.iterations, gs.iterations
            );
            assert!(
                sor.iterations < gs.iterations,
                "case {n}: sor {} sweeps, gauss-seidel {}",
                sor.iterations,
                gs.iterations
            );
            for (x, y) in [(&b, &exact), (&gs_b, &exact)] {
                for (p, q) in x.iter().zip(y) {
                    for c in 0..3 {
                        assert!((p[c] - q[c]).abs() <= 1e-8 * q[c].abs().max(1e-3));
                    }
                }
            }
        }
    }

    #[test]
    fn sor_refuses_a_factor_outside_0_2() {
        let owned = random(20, 4, 1);
        for w in [0.0, 2.0, -1.0, f64::NAN, 3.0] {
            let err = Sor { omega: Some(w) }
                .solve(&owned.sys(), &Options::default())
                .unwrap_err();
            assert!(err.to_string().contains("(0, 2)"), "{w}: {err}");
        }
    }
}
