//! Conjugate gradients on the symmetric form of the radiosity system (Hestenes and Stiefel
//! 1952; Saad 2003, *Iterative Methods for Sparse Linear Systems*, §9.2, preconditioned CG
//! with a Jacobi preconditioner; for radiosity, Neumann, Neumann and Schmid 1994, "Fast
//! radiosity by parallelization" and Cohen and Wallace 1993, §5.3, which note the symmetric
//! form).
//!
//! ## The symmetric form
//! Multiplying row `i` of `(I - diag(rho) F) B = E` by `A_i / rho_i` gives
//!
//! ```text
//! M B = diag(A / rho) E,    M = diag(A / rho) - diag(A) F
//! ```
//!
//! and with reciprocity (`A_i F_ij = A_j F_ji`) `diag(A) F` is symmetric, so `M` is; for
//! `rho < 1` and rows of `F` summing to at most 1 it is strictly diagonally dominant with a
//! positive diagonal, hence positive definite. Patches with `rho_i = 0` (per channel) have
//! `B_i = E_i`: they are eliminated, their known radiosity moving to the right-hand side.
//!
//! ## Monte Carlo F is only approximately reciprocal
//! The solver symmetrises explicitly, `S_ij = (A_i F_ij + A_j F_ji) / 2`, and runs
//! preconditioned CG (diagonal of `M_s = diag(A / rho) - S`) on `M_s`. So that the answer
//! solves the *original* system, not the symmetrised one, the right-hand side is the true
//! residual of the original system, weighted by `A / rho` (defect correction, Saad §9.4
//! "flexible" variants; Golub and Van Loan §3.5.3): `M_s d = diag(A / rho) (E + diag(rho) F B
//! - B)`, `B += d`. For a reciprocal `F` (relative asymmetry below [`RECIPROCAL`], as the
//! estimators that sample pairs once produce) this is plain CG; otherwise CG restarts from a
//! freshly computed true residual each time the symmetrised residual has fallen by
//! [`RESTART_FACTOR`], which converges when the antisymmetric part is small against `M_s`
//! (Golub and Van Loan, Theorem 11.2.1). The report's notes give the asymmetry and the number
//! of restarts. If a restart cycle fails to halve the true residual, `F` is too far from
//! reciprocal for this method and the run stops with a hint to use `gauss-seidel` or `direct`.
//!
//! ## Residual, cost, failures
//! Every iteration computes the exact residual of the original system with the same
//! definition as the other solvers (see the [module docs](super)), so an iteration costs two
//! passes over the matrix (one over `S`, one over `F`). All three channels run in lockstep,
//! each with its own CG scalars; a channel stops updating once it is within tolerance, by
//! the relative residual and by the per-patch rule (measured from the same true residual).
//! If `p^T M_s p <= 0` the symmetric form is not positive definite (rows of `F` summing above
//! `1 / rho`): the run stops with [`Error::Singular`].

use crate::matrix::{Csr, Triplets};
use rayon::prelude::*;

use super::{
    divergence, diverging, finish, gather, max3, worst, Options, Outcome, Prologue, Rows,
    SolveReport, Solver, System,
};
use crate::error::{Error, Result};

pub(crate) const NAME: &str = "cg";

/// Relative asymmetry of `diag(A) F` below which `F` counts as reciprocal (no restarts).
pub const RECIPROCAL: f64 = 1e-10;

/// For a non-reciprocal `F`, CG restarts from the true residual once the symmetrised
/// residual (2-norm, per channel) has fallen by this factor.
pub const RESTART_FACTOR: f64 = 1e-2;

/// Preconditioned conjugate gradients on the symmetric form; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct Cg;

/// `S = (diag(A) F + (diag(A) F)^T) / 2` and the relative asymmetry
/// `sum_ij |A_i F_ij - A_j F_ji| / (2 sum_ij |A_i F_ij|)`.
pub fn symmetrise(f: &Csr, area: &[f64]) -> (Csr, f64) {
    let n = f.rows();
    let mut t = Triplets::with_capacity((n, n), 2 * f.nnz());
    let mut total = 0.0;
    for (i, row) in f.outer_iterator().enumerate() {
        for (j, &v) in row.iter() {
            let a = area[i] * v;
            total += a.abs();
            t.add_triplet(i, j, 0.5 * a);
            t.add_triplet(j, i, 0.5 * a);
        }
    }
    // Summing duplicates gives S; the asymmetry comes from S and diag(A) F together.
    let s: Csr = t.to_csr();
    let mut diff = 0.0;
    for (i, row) in s.outer_iterator().enumerate() {
        for (j, &sij) in row.iter() {
            // A_i F_ij - A_j F_ji = 2 (A_i F_ij - S_ij).
            let a = area[i] * f.get(i, j).copied().unwrap_or(0.0);
            diff += 2.0 * (a - sij).abs();
        }
    }
    let asym = if total > 0.0 {
        diff / (2.0 * total)
    } else {
        0.0
    };
    (s, asym)
}

/// Per-channel dot product.
fn dot(x: &[[f64; 3]], y: &[[f64; 3]]) -> [f64; 3] {
    x.par_iter()
        .zip(y)
        .map(|(a, b)| [a[0] * b[0], a[1] * b[1], a[2] * b[2]])
        .reduce(|| [0.0; 3], |a, b| [a[0] + b[0], a[1] + b[1], a[2] + b[2]])
}

/// The true residual `E + diag(rho) F b - b`, per row.
fn true_residual(sys: &System, rows: &Rows, b: &[[f64; 3]]) -> Vec<[f64; 3]> {
    (0..b.len())
        .into_par_iter()
        .map(|i| {
            let g = gather(sys, rows, b, i);
            [0, 1, 2].map(|c| g[c] - b[i][c])
        })
        .collect()
}

fn inf_norm(t: &[[f64; 3]]) -> [f64; 3] {
    t.iter()
        .fold([0.0f64; 3], |m, v| super::max3(m, v.map(f64::abs)))
}

impl Solver for Cg {
    fn name(&self) -> &'static str {
        NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        let Prologue {
            start,
            rows,
            scale,
            floor,
            gain,
            mut notes,
        } = Prologue::new(sys, opts)?;
        // The per-patch measure of the rule, per channel, from the true residual `t`.
        let per_patch = |t: &[[f64; 3]], b: &[[f64; 3]]| -> [f64; 3] {
            t.par_iter()
                .zip(b)
                .enumerate()
                .map(|(i, (ti, bi))| floor.of_residual(sys, i, *ti, *bi))
                .reduce(|| [0.0; 3], max3)
        };
        let n = sys.len();
        let (s, asym) = symmetrise(sys.f, sys.area);
        let srows = Rows::new(&s);
        let reciprocal = asym <= RECIPROCAL;
        // w = A / rho on free patches (rho > 0), 0 on eliminated ones; d = diag(M_s).
        let w: Vec<[f64; 3]> = (0..n)
            .map(|i| sys.rho[i].map(|r| if r > 0.0 { sys.area[i] / r } else { 0.0 }))
            .collect();
        let diag: Vec<[f64; 3]> = (0..n)
            .map(|i| {
                let sii = s.get(i, i).copied().unwrap_or(0.0);
                w[i].map(|wi| if wi > 0.0 { wi - sii } else { 1.0 })
            })
            .collect();
        let mut b = sys.emit.to_vec();
        let mut t = true_residual(sys, &rows, &b);
        let mut abs = inf_norm(&t);
        let mut pp = per_patch(&t, &b);
        let mut history = vec![scale.rel(abs)];
        let mut iterations = 0;
        let mut restarts = 0;
        let mut stalled = None;
        'outer: loop {
            // r = W t (the symmetrised system's residual for the correction), z = r / D.
            let mut r: Vec<[f64; 3]> = t
                .iter()
                .zip(&w)
                .map(|(ti, wi)| [0, 1, 2].map(|c| wi[c] * ti[c]))
                .collect();
            let precond = |r: &[[f64; 3]]| -> Vec<[f64; 3]> {
                r.iter()
                    .zip(&diag)
                    .map(|(ri, di)| [0, 1, 2].map(|c| ri[c] / di[c]))
                    .collect()
            };
            let mut z = precond(&r);
            let mut p = z.clone();
            let mut rz = dot(&r, &z);
            let r0 = dot(&r, &r).map(f64::sqrt);
            let cycle_start = *history.last().unwrap_or(&0.0);
            loop {
                let res = *history.last().unwrap_or(&0.0);
                if diverging(res) {
                    return Err(divergence(NAME, iterations, res, opts, &gain));
                }
                let done = res <= opts.tolerance && worst(pp) <= opts.tolerance;
                if done || iterations >= opts.max_iterations {
                    break 'outer;
                }
                let active: [bool; 3] = [0, 1, 2].map(|c| {
                    (abs[c] / scale.0[c] > opts.tolerance || pp[c] > opts.tolerance) && rz[c] > 0.0
                });
                // q = M_s p on free patches.
                let q: Vec<[f64; 3]> = (0..n)
                    .into_par_iter()
                    .map(|i| {
                        let (ind, val) = srows.row(i);
                        let mut acc = [0.0; 3];
                        for (&j, &v) in ind.iter().zip(val) {
                            let j = j as usize;
                            for c in 0..3 {
                                acc[c] += v * p[j][c];
                            }
                        }
                        [0, 1, 2].map(|c| {
                            if w[i][c] > 0.0 {
                                w[i][c] * p[i][c] - acc[c]
                            } else {
                                0.0
                            }
                        })
                    })
                    .collect();
                let pq = dot(&p, &q);
                let mut alpha = [0.0; 3];
                for c in 0..3 {
                    if !active[c] {
                        continue;
                    }
                    if !(pq[c] > 0.0 && pq[c].is_finite()) {
                        return Err(Error::Singular {
                            solver: NAME.into(),
                            msg: format!(
                                "channel {c}: p^T M p = {:.3e} after {iterations} iterations, so \
                                 the symmetric form diag(A / rho) - diag(A) F is not positive \
                                 definite (rho * (row sum of F) reaches {:.4} at patch {}): \
                                 rows of F sum above 1, check the form factors or use \
                                 --solver direct",
                                pq[c],
                                gain.max(),
                                gain.patch
                            ),
                        });
                    }
                    alpha[c] = rz[c] / pq[c];
                }
                b.par_iter_mut()
                    .zip(&mut r)
                    .zip(p.par_iter().zip(&q))
                    .for_each(|((bi, ri), (pi, qi))| {
                        for c in 0..3 {
                            bi[c] += alpha[c] * pi[c];
                            ri[c] -= alpha[c] * qi[c];
                        }
                    });
                iterations += 1;
                t = true_residual(sys, &rows, &b);
                abs = inf_norm(&t);
                pp = per_patch(&t, &b);
                history.push(scale.rel(abs));
                if !reciprocal {
                    let rn = dot(&r, &r).map(f64::sqrt);
                    if (0..3).all(|c| !active[c] || rn[c] <= RESTART_FACTOR * r0[c]) {
                        restarts += 1;
                        let now = *history.last().unwrap_or(&0.0);
                        if now > 0.5 * cycle_start && now > opts.tolerance {
                            stalled = Some((cycle_start, now));
                            break 'outer;
                        }
                        continue 'outer;
                    }
                }
                z = precond(&r);
                let rz_new = dot(&r, &z);
                let mut beta = [0.0; 3];
                for c in 0..3 {
                    if active[c] && rz[c] > 0.0 {
                        beta[c] = rz_new[c] / rz[c];
                    }
                }
                p.par_iter_mut().zip(&z).for_each(|(pi, zi)| {
                    for c in 0..3 {
                        pi[c] = if active[c] {
                            zi[c] + beta[c] * pi[c]
                        } else {
                            0.0
                        };
                    }
                });
                for c in 0..3 {
                    if active[c] {
                        rz[c] = rz_new[c];
                    }
                }
            }
        }
        if reciprocal {
            notes.push(format!(
                "F is reciprocal to rounding (relative asymmetry {asym:.1e}): plain conjugate \
                 gradients on diag(A / rho) - diag(A) F"
            ));
        } else {
            notes.push(format!(
                "F is not reciprocal (relative asymmetry {asym:.1e}): conjugate gradients ran on \
                 the symmetrised S = (A_i F_ij + A_j F_ji) / 2 and were corrected against the \
                 original system ({restarts} restarts); the residual is that of the original \
                 system"
            ));
        }
        let residual = *history.last().unwrap_or(&0.0);
        let stall_hint = stalled.map(|(before, after)| {
            format!(
                "; F is too far from reciprocal for conjugate gradients (relative asymmetry \
                 {asym:.1e}: a restart cycle took the residual only from {before:.2e} to \
                 {after:.2e}): use --solver gauss-seidel or direct"
            )
        });
        if let Some(h) = &stall_hint {
            notes.push(h.trim_start_matches("; ").to_string());
        }
        let out = Outcome {
            b,
            iterations,
            residual,
            patch_residual: worst(pp),
            history,
            notes,
        };
        finish(NAME, out, opts, &gain, start).map_err(|e| match (e, stall_hint) {
            (
                Error::NotConverged {
                    solver,
                    iterations,
                    residual,
                    tolerance,
                    ..
                },
                Some(hint),
            ) => Error::NotConverged {
                solver,
                iterations,
                residual,
                tolerance,
                hint,
            },
            (other, _) => other,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use super::*;
    use crate::matrix::Triplets as TriMat;

    /// A reciprocal random system: `F_ji = A_i F_ij / A_j` for a symmetric pattern.
    fn reciprocal(n: usize, seed: u64) -> Owned {
        let mut owned = random(n, 8, seed);
        let (s, _) = symmetrise(&owned.f, &owned.area);
        // F = diag(1 / A) S, then scale rows to sum at most 0.95.
        let mut t = TriMat::new((n, n));
        let mut max_sum = 0.0f64;
        for (i, row) in s.outer_iterator().enumerate() {
            let sum: f64 = row.data().iter().sum::<f64>() / owned.area[i];
            max_sum = max_sum.max(sum);
        }
        for (i, row) in s.outer_iterator().enumerate() {
            for (j, &v) in row.iter() {
                t.add_triplet(i, j, 0.95 * v / owned.area[i] / max_sum);
            }
        }
        owned.f = t.to_csr();
        owned
    }

    #[test]
    fn reciprocal_system_matches_direct() {
        let owned = reciprocal(60, 3);
        let (s, asym) = symmetrise(&owned.f, &owned.area);
        assert!(asym < 1e-14, "{asym}");
        assert_eq!(s.nnz(), owned.f.nnz());
        let (b, report) = Cg.solve(&owned.sys(), &tight(1e-12)).unwrap();
        let (exact, _) = Direct.solve(&owned.sys(), &tight(1e-12)).unwrap();
        assert!(report.converged);
        assert!(rel_diff(&exact, &b) < 1e-10);
        assert_eq!(report.history.len(), report.iterations + 1);
        assert!(report
            .notes
            .iter()
            .any(|n| n.contains("reciprocal to rounding")));
        assert!((residual(&owned.sys(), &b) - report.residual).abs() < 1e-15);
    }

    #[test]
    fn non_reciprocal_system_solves_the_original() {
        let owned = random(60, 8, 5);
        let (_, asym) = symmetrise(&owned.f, &owned.area);
        assert!(asym > 0.1);
        let opts = tight(1e-12);
        match Cg.solve(&owned.sys(), &opts) {
            Ok((b, report)) => {
                let (exact, _) = Direct.solve(&owned.sys(), &opts).unwrap();
                assert!(rel_diff(&exact, &b) < 1e-9);
                assert!(report.notes.iter().any(|n| n.contains("symmetrised")));
            }
            // A random F is far from reciprocal: a clear refusal is acceptable too.
            Err(Error::NotConverged { hint, .. }) => assert!(hint.contains("reciprocal"), "{hint}"),
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn nearly_reciprocal_system_is_corrected() {
        // Perturb a reciprocal F by 1%: CG restarts and still solves the original system.
        let mut owned = reciprocal(60, 8);
        let mut rng = Rng::new(99);
        owned
            .f
            .data_mut()
            .iter_mut()
            .for_each(|v| *v *= 1.0 + 0.01 * (rng.uniform() - 0.5));
        let (b, report) = Cg.solve(&owned.sys(), &tight(1e-12)).unwrap();
        let (exact, _) = Direct.solve(&owned.sys(), &tight(1e-12)).unwrap();
        assert!(rel_diff(&exact, &b) < 1e-10, "{}", rel_diff(&exact, &b));
        assert!(
            report.notes.iter().any(|n| n.contains("restarts")),
            "{:?}",
            report.notes
        );
    }

    #[test]
    fn black_patches_are_eliminated() {
        // rho = 0 on patch 0 in every channel, and on patch 1 in the blue channel only.
        let mut owned = reciprocal(30, 4);
        owned.rho[0] = [0.0; 3];
        owned.rho[1][2] = 0.0;
        owned.emit[0] = [1.0, 2.0, 3.0];
        let (b, report) = Cg.solve(&owned.sys(), &tight(1e-12)).unwrap();
        let (exact, _) = Direct.solve(&owned.sys(), &tight(1e-12)).unwrap();
        assert!(report.converged);
        assert_eq!(b[0], owned.emit[0]);
        assert!(rel_diff(&exact, &b) < 1e-10);
    }

    #[test]
    fn furnace_and_cap() {
        let owned = furnace(10, [0.3, 0.6, 0.9], [1.0; 3]);
        let (b, _) = Cg.solve(&owned.sys(), &tight(1e-12)).unwrap();
        for bi in &b {
            assert!((bi[2] - 10.0).abs() < 1e-9, "{bi:?}");
        }
        let owned = reciprocal(60, 6);
        let opts = Options {
            max_iterations: 2,
            keep_partial: true,
            ..tight(1e-12)
        };
        let (_, report) = Cg.solve(&owned.sys(), &opts).unwrap();
        assert!(!report.converged && report.iterations == 2);
    }
}
