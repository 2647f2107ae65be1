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
//! H-matrices (Varga, §3.6), proved here in the norm the solvers measure. A wider range
//! holds when `F` is reciprocal (`A_i F_ij = A_j F_ji`, the semi-analytic and area
//! estimators): a sweep's update of row `i` does not change when the row is scaled, and
//! scaling row `i` by `A_i / rho_i` makes the matrix symmetric, and positive definite when
//! `g < 1` (diagonally dominant), so every `0 < omega < 2` converges (Ostrowski and Reich;
//! Varga, §3.4). Black patches (`rho_i = 0`) hold `B_i = E_i` from the first sweep on.
//!
//! ## The factor
//! Which `omega` is fastest is Young's answer for consistently ordered matrices (Young
//! 1954; Varga, §4.3): `omega* = 2 / (1 + sqrt(1 - r²))`, with `r` the spectral radius of
//! `J`; at factor `w` the error falls per sweep by the `lambda` with
//! `(lambda + w - 1)² = lambda w² r²` (at `w = 1`, `lambda = r²`). Radiosity matrices are not
//! consistently ordered, but the formula lands near the measured best on them (a closed
//! furnace of 400 patches with one emitter in 37, `rho` 0.5 to 0.99: best 1.1, 1.3, 1.5 and
//! 1.8 by trial, the formula 1.08, 1.26, 1.40 and 1.76). `r` is not known in advance, so
//! [`Sor`] finds it from the sweeps themselves, channel by channel:
//!
//! 1. It sweeps at the proven factor `omega_c = min(1.1, 1 + 0.9 (2 / (1 + g_c) - 1))`
//!    ([`relaxation`]; Gauss-Seidel when `g_c >= 1`) and watches the channel's residual
//!    fall, until two successive ratios agree within 5% (from the fourth sweep on; at most
//!    12 sweeps).
//! 2. From that rate `lambda` it solves the relation above for `r²` and takes `omega*`
//!    ([`young`], at most 1.95) when it is larger than the proven factor.
//! 3. Over-relaxed sweeps first raise the residual, then lower it faster (10.5 times up at
//!    `omega` 1.91 before it fell). A residual grown past `4 / (2 - omega)` times where the
//!    factor changed, or not back below it within `max(30, 20 / (2 - omega))` sweeps, sends
//!    the channel back to the proven factor, which converges from any start.
//!
//! Measured (hemisphere factors, default tolerance 1e-6; sweeps of Gauss-Seidel against
//! these): the Cornell box at 30,000 patches 16 against 10, `room-spheres-8` at 20,000 20
//! against 14, the closed cube and the closed Cornell furnace at 6,000 12 against 8, and
//! the closed Cornell box with every surface white and one wall emitting (6,000 patches)
//! 27 against 16 at `rho` 0.8, 43 against 20 at 0.9 and 72 against 28 at 0.97. The solver
//! study's closed cubes (`radiosity study-solvers`, docs/SOLVERS.md) show the rest.
//!
//! ## Bright rooms
//! Where the system's gain bound is at least 0.9 (a bright, nearly closed room), [`Sor`]
//! with its factor chosen also corrects the iterate after each sweep on at most 64
//! aggregates of patches, solving the system exactly on their means (the `coarse`
//! module). The solution and the
//! stopping rule are the sweeps' own; what changes is how many it takes. The closed Cornell
//! furnace box with one wall emitting, hemisphere factors at 6,000 patches: 26 sweeps
//! against 11 at `rho` 0.9, 59 against 14 at 0.97, 202 against 17 at 0.995
//! (docs/SOLVERS.md). A factor given by the caller keeps the plain sweeps.

use super::coarse::{self, Coarse};
use super::{
    max3, sweep_loop, sweeps, Floor, Options, Prologue, Rows, SolveReport, Solver, System,
};
use crate::error::{Error, Result};

pub(crate) const NAME: &str = "gauss-seidel";
pub(crate) const SOR_NAME: &str = "sor";

/// The largest proven factor [`Sor`] starts from ([`relaxation`]).
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
    /// The factor, the same for every channel and every sweep; `None` chooses one per
    /// channel, from the system's gain bound and then from the sweeps' rate (module docs,
    /// *The factor*), and in a bright room also corrects the iterate on aggregates between
    /// sweeps (module docs, *Bright rooms*).
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
        self.solve_with(sys, opts, self.omega.is_none())
    }
}

impl Sor {
    /// [`Solver::solve`], with the coarse correction of bright rooms allowed or not.
    fn solve_with(
        &self,
        sys: &System,
        opts: &Options,
        allow_coarse: bool,
    ) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        if let Some(w) = self.omega {
            if !(w > 0.0 && w < 2.0) {
                return Err(Error::Config(format!(
                    "over-relaxation factor {w} is not in (0, 2), where successive \
                     over-relaxation can converge"
                )));
            }
        }
        let pro = Prologue::new(sys, opts)?;
        let safe = pro.gain.gain.map(relaxation);
        // A bright room's slow error, removed on aggregates between sweeps (`coarse`
        // module).
        let gain = pro.gain.gain.into_iter().fold(0.0, f64::max);
        let coarse = allow_coarse
            .then(|| Coarse::new(sys, &pro.rows, gain))
            .flatten();
        let scale = pro.scale;
        let (mut correcting, mut least) = (coarse.is_some(), f64::INFINITY);
        let mut adapt: [Adaptive; 3] = std::array::from_fn(|c| match self.omega {
            Some(w) => Adaptive::fixed(w),
            None => Adaptive::new(safe[c]),
        });
        let mut both = Vec::new();
        let (b, mut report) = sweeps(SOR_NAME, sys, opts, pro, |rows, floor, old, b| {
            let omega = adapt.each_ref().map(|a| a.omega);
            let (res, per_patch) = sweep(sys, rows, floor, omega, &mut both, old, b);
            for (a, &r) in adapt.iter_mut().zip(&res) {
                a.observe(r);
            }
            if let (Some(c), true) = (&coarse, correcting) {
                // Off for good at the tolerance, or should the residual grow far past
                // the least seen (the first correction, lifting a dark start toward the
                // solution, raised it 4.7 times before it fell 20 times a sweep).
                let r = scale.rel(res);
                least = least.min(r);
                correcting = r > opts.tolerance && r <= coarse::GROWTH * least;
                if correcting {
                    c.correct(sys, b);
                }
            }
            (res, per_patch)
        })?;
        report.relaxation = Some(adapt.map(|a| a.omega));
        report.coarse = coarse.as_ref().map_or(0, Coarse::aggregates);
        Ok((b, report))
    }
}

/// The factor of one channel while [`Sor`] sweeps (module docs, *The factor*); also the
/// thermal solve's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Adaptive {
    /// The factor of the next sweep.
    omega: f64,
    /// The proven factor, to fall back on.
    safe: f64,
    phase: Phase,
}

#[derive(Clone, Copy, Debug)]
enum Phase {
    /// Sweeps at the proven factor, watching the residual's ratio from sweep to sweep: the
    /// last residual and ratio, and the sweeps seen.
    Measuring { r: f64, mu: f64, sweeps: usize },
    /// Young's factor, since the sweep whose start had residual `r`, `sweeps` ago.
    Young { r: f64, sweeps: usize },
    /// The factor stays as it is.
    Fixed,
}

/// Sweeps at most at the proven factor before settling for it.
const MEASURE_SWEEPS: usize = 12;
/// Two successive ratios this close (relative) are taken as the asymptotic rate.
const RATE_SETTLED: f64 = 0.05;
/// Sweeps Young's factor gets at least to bring the residual below where it started.
const YOUNG_TRIAL: usize = 30;
/// The largest factor taken.
const MAX_OMEGA: f64 = 1.95;

impl Adaptive {
    /// Starts at the proven factor `safe`, then adapts.
    pub(crate) fn new(safe: f64) -> Adaptive {
        Adaptive {
            omega: safe,
            safe,
            phase: Phase::Measuring {
                r: f64::NAN,
                mu: f64::NAN,
                sweeps: 0,
            },
        }
    }

    fn fixed(omega: f64) -> Adaptive {
        Adaptive {
            omega,
            safe: omega,
            phase: Phase::Fixed,
        }
    }

    /// The factor of the next sweep.
    pub(crate) fn omega(&self) -> f64 {
        self.omega
    }

    /// Takes the residual of the iterate the last sweep started from (or of the one it
    /// made: successive residuals either way), and sets the factor of the next one.
    pub(crate) fn observe(&mut self, res: f64) {
        match self.phase {
            Phase::Fixed => {}
            Phase::Measuring { r, mu, sweeps } => {
                let ratio = res / r;
                let settled = sweeps >= 3
                    && ratio > 0.0
                    && ratio < 1.0
                    && (ratio - mu).abs() <= RATE_SETTLED * ratio;
                if settled {
                    // The rate of these sweeps at factor w gives the Jacobi radius:
                    // (rate + w - 1)² = rate w² radius² (Young 1954, for a consistently
                    // ordered matrix; at w = 1, radius² = rate).
                    let w = self.omega;
                    let radius2 = (ratio + w - 1.0).powi(2) / (ratio * w * w);
                    let better = young(radius2);
                    if better > w {
                        self.omega = better;
                        self.phase = Phase::Young { r: res, sweeps: 0 };
                    } else {
                        self.phase = Phase::Fixed;
                    }
                } else if sweeps + 1 >= MEASURE_SWEEPS || !res.is_finite() {
                    self.settle();
                } else {
                    self.phase = Phase::Measuring {
                        r: res,
                        mu: ratio,
                        sweeps: sweeps + 1,
                    };
                }
            }
            Phase::Young { r, sweeps } => {
                // Over-relaxed sweeps first raise the residual before it falls faster (by
                // about 1 / (2 - omega) at most, measured; 10.5 times at omega 1.91), and
                // take longer to come back the nearer omega is to 2 (about 68 sweeps at
                // 1.85 on the study's ceiling-lit cube at rho 0.999): a residual grown past
                // four times that, or not back below where it started after 20 / (2 -
                // omega) sweeps (30 at least), sends the channel back to the factor that
                // provably converges.
                let slack = 1.0 / (2.0 - self.omega);
                let trial = YOUNG_TRIAL.max((20.0 * slack).ceil() as usize);
                let grown = res.is_nan() || res > 4.0 * slack * r;
                if grown || (sweeps >= trial && res >= r) {
                    self.settle();
                } else {
                    self.phase = Phase::Young {
                        r,
                        sweeps: sweeps + 1,
                    };
                }
            }
        }
    }

    fn settle(&mut self) {
        self.omega = self.safe;
        self.phase = Phase::Fixed;
    }
}

/// Young's optimal factor `2 / (1 + sqrt(1 - mu))` for a Gauss-Seidel rate `mu` (the
/// square of the Jacobi matrix's spectral radius for a consistently ordered matrix; Young
/// 1954), at least 1 and at most 1.95.
pub fn young(mu: f64) -> f64 {
    if !(0.0..1.0).contains(&mu) {
        return 1.0;
    }
    (2.0 / (1.0 + (1.0 - mu).sqrt())).clamp(1.0, MAX_OMEGA)
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
    crate::simd::with_widest(
        #[inline(always)]
        || rows_pass(sys, rows, floor, omega, both, old, b),
    )
}

/// The rows of one [`sweep`], its records of both values made.
#[inline(always)]
fn rows_pass(
    sys: &System,
    rows: &Rows,
    floor: &Floor,
    omega: [f64; 3],
    both: &mut [Both],
    old: &[[f64; 3]],
    b: &mut [[f64; 3]],
) -> ([f64; 3], [f64; 3]) {
    let mut res = [0.0f64; 3];
    let mut per_patch = [0.0f64; 3];
    for i in 0..rows.len() {
        let (ind, val) = rows.row(i);
        // Both halves of each column's record added without a branch: `all` is `F_i . old`
        // (for the residual of `old`), `cur` the sweep's sum with current values, the
        // diagonal included (its current value is still `old_i`) and taken out below;
        // `fii` is the diagonal.
        let (mut all, mut cur, mut fii) = ([0.0f64; 3], [0.0f64; 3], 0.0);
        for (k, (&j, &f)) in ind.iter().zip(val).enumerate() {
            if let Some(&ahead) = ind.get(k + PREFETCH) {
                crate::simd::prefetch(&both[ahead as usize]);
            }
            let j = j as usize;
            let w = &both[j].0;
            // Six sums, each array indexed by constants only, so that the compiler keeps
            // them in registers: a sum of 8 lanes over the whole record, read back through
            // a closure, was kept on the stack and stored and reloaded at every entry in
            // some builds (an unrelated change elsewhere in the crate made the 262k-patch
            // solve 45% slower that way; docs/PERFORMANCE.md, section 2).
            all = [all[0] + f * w[0], all[1] + f * w[1], all[2] + f * w[2]];
            cur = [cur[0] + f * w[3], cur[1] + f * w[4], cur[2] + f * w[5]];
            if j == i {
                fii += f;
            }
        }
        let off = if fii == 0.0 {
            cur
        } else {
            [0, 1, 2].map(|c| cur[c] - fii * old[i][c])
        };
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
const PREFETCH: usize = 32;

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

    /// One sweep, as the module docs write it, entry by entry in scalar arithmetic: the
    /// residual of `old` and the next iterate.
    fn reference_sweep(
        sys: &System,
        omega: [f64; 3],
        old: &[[f64; 3]],
    ) -> (Vec<[f64; 3]>, [f64; 3]) {
        let mut b = old.to_vec();
        let mut res = [0.0f64; 3];
        for (i, row) in sys.f.outer_iterator().enumerate() {
            let (mut all, mut off, mut fii) = ([0.0; 3], [0.0; 3], 0.0);
            for (j, &f) in row.iter() {
                for c in 0..3 {
                    all[c] += f * old[j][c];
                }
                if j == i {
                    fii += f;
                } else {
                    for c in 0..3 {
                        off[c] += f * b[j][c];
                    }
                }
            }
            let (e, rho) = (sys.emit[i], sys.rho[i]);
            for c in 0..3 {
                res[c] = res[c].max((e[c] + rho[c] * all[c] - old[i][c]).abs());
                let gs = (e[c] + rho[c] * off[c]) / (1.0 - rho[c] * fii);
                b[i][c] = if omega[c] == 1.0 {
                    gs
                } else {
                    old[i][c] + omega[c] * (gs - old[i][c])
                };
            }
        }
        (b, res)
    }

    /// The sweep's branch-free sums over each column's record, compiled at every vector
    /// width, give the reference sweep's bits where no patch sees itself, and the same
    /// values to rounding where some do (the diagonal's share is taken out after the sum).
    #[test]
    fn vector_sweep_is_the_scalar_sweep() {
        use crate::simd::{set_limit, Width};
        let with_diagonals = random(300, 12, 11);
        let mut t = crate::matrix::Triplets::new((300, 300));
        for (i, row) in with_diagonals.f.outer_iterator().enumerate() {
            for (j, &f) in row.iter().filter(|&(j, _)| j != i) {
                t.add_triplet(i, j, f);
            }
        }
        let without = Owned {
            f: t.to_csr(),
            ..random(300, 12, 11)
        };
        assert!(with_diagonals.f.nnz() > without.f.nnz());
        let opts = Options::default();
        for (owned, exact) in [(&without, true), (&with_diagonals, false)] {
            let sys = owned.sys();
            let pro = Prologue::new(&sys, &opts).unwrap();
            // A start that is not the emission, so that every term of a row counts.
            let old: Vec<[f64; 3]> = (0..300)
                .map(|i| [0.3, 0.7, 1.1].map(|s| s * (1.0 + (i % 7) as f64)))
                .collect();
            let omega = [1.0, 1.1, 1.37];
            let (want, want_res) = reference_sweep(&sys, omega, &old);
            for w in Width::ALL.into_iter().filter(|w| w.supported()) {
                set_limit(w);
                let (mut both, mut b) = (Vec::new(), vec![[0.0f64; 3]; 300]);
                let (res, _) =
                    super::sweep(&sys, &pro.rows, &pro.floor, omega, &mut both, &old, &mut b);
                for (i, (got, want)) in b.iter().zip(&want).enumerate() {
                    for c in 0..3 {
                        let (g, x) = (got[c], want[c]);
                        if exact {
                            assert_eq!(g.to_bits(), x.to_bits(), "patch {i} channel {c} at {w}");
                        } else {
                            assert!(
                                (g - x).abs() <= 1e-14 * x.abs(),
                                "patch {i} at {w}: {g} {x}"
                            );
                        }
                    }
                }
                assert_eq!(res, want_res, "at {w}");
            }
        }
        set_limit(Width::Avx512);
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

    /// A closed furnace of 400 patches at `rho`, lit by one patch in 37.
    fn lit_furnace(rho: f64) -> Owned {
        let mut owned = furnace(400, [rho; 3], [1.0; 3]);
        for (i, e) in owned.emit.iter_mut().enumerate() {
            *e = if i % 37 == 0 { [1.0; 3] } else { [0.0; 3] };
        }
        owned
    }

    /// Options for [`lit_furnace`]: tolerance 1e-8, room for every sweep it takes.
    fn bright_opts() -> Options {
        Options {
            tolerance: 1e-8,
            max_iterations: 100_000,
            ..Options::default()
        }
    }

    /// Asserts `b` is the dense solve's answer of `sys` to 1e-6 relative (1e-9 absolute).
    fn agrees_with_direct(sys: &System, b: &[[f64; 3]]) {
        let exact = Direct.solve(sys, &Options::default()).unwrap().0;
        for (p, q) in b.iter().zip(&exact) {
            for c in 0..3 {
                assert!((p[c] - q[c]).abs() <= 1e-6 * q[c].abs().max(1e-3));
            }
        }
    }

    #[test]
    fn sor_finds_the_factor_of_bright_furnaces() {
        // Closed furnaces lit by one patch in 37: Gauss-Seidel slows like 1 / (1 - rho);
        // the factor found from the sweeps' rate cuts that by 2, 5 and 15 times at least.
        // (The plain sweeps: the coarse correction of bright rooms is the next test's.)
        let opts = bright_opts();
        for (rho, gain) in [(0.9, 2.0), (0.99, 5.0), (0.999, 15.0)] {
            let owned = lit_furnace(rho);
            let sys = owned.sys();
            let (_, gs) = GaussSeidel.solve(&sys, &opts).unwrap();
            let (b, sor) = Sor::AUTO.solve_with(&sys, &opts, false).unwrap();
            eprintln!(
                "rho {rho}: gauss-seidel {} sweeps, sor {} at {:?}",
                gs.iterations, sor.iterations, sor.relaxation
            );
            assert!(
                (sor.iterations as f64) * gain <= gs.iterations as f64,
                "rho {rho}: sor {} sweeps, gauss-seidel {}",
                sor.iterations,
                gs.iterations
            );
            agrees_with_direct(&sys, &b);
        }
    }

    #[test]
    fn bright_rooms_take_fewer_sweeps_with_the_coarse_correction() {
        // Closed furnaces lit by one patch in 37 (as above), gain rho: the correction on
        // aggregates cuts the sweeps by 4, 10 and 30 times at least (measured 5.5, 19 and
        // 66), and the answer still agrees with the dense solve to the tolerance. Below the
        // gain of 0.9 it is not used.
        let opts = bright_opts();
        for (rho, gain) in [(0.9, 4.0), (0.99, 10.0), (0.999, 30.0)] {
            let owned = lit_furnace(rho);
            let sys = owned.sys();
            let (_, plain) = Sor::AUTO.solve_with(&sys, &opts, false).unwrap();
            let (b, two) = Sor::AUTO.solve(&sys, &opts).unwrap();
            eprintln!(
                "rho {rho}: sor {} sweeps, with the correction {} ({} aggregates)",
                plain.iterations, two.iterations, two.coarse
            );
            assert_eq!(plain.coarse, 0);
            assert!(two.coarse >= 2 && two.coarse <= coarse::MAX_AGGREGATES);
            assert!(
                (two.iterations as f64) * gain <= plain.iterations as f64,
                "rho {rho}: {} sweeps against {}",
                two.iterations,
                plain.iterations
            );
            assert!(two.converged && two.residual <= 1e-8 && two.patch_residual <= 1e-8);
            agrees_with_direct(&sys, &b);
        }
        let dim = furnace(200, [0.8; 3], [1.0; 3]);
        let (_, report) = Sor::AUTO.solve(&dim.sys(), &opts).unwrap();
        assert_eq!(report.coarse, 0, "gain 0.8");
    }

    #[test]
    fn a_factor_that_does_not_pay_goes_back_to_the_proven_one() {
        use super::{Adaptive, Phase};
        // A steady rate of 0.9 from the fourth sweep: Young's factor for it.
        let mut a = Adaptive::new(1.05);
        let mut r = 1.0;
        for _ in 0..6 {
            a.observe(r);
            r *= 0.9;
        }
        assert!(matches!(a.phase, Phase::Young { .. }), "{a:?}");
        let w = a.omega;
        let lambda = 0.9f64;
        let radius2 = (lambda + 1.05 - 1.0).powi(2) / (lambda * 1.05 * 1.05);
        assert!((w - super::young(radius2)).abs() < 1e-12 && w > 1.05);
        // Then the residual grows past 4 / (2 - w) times where the factor changed.
        let Phase::Young { r: start, .. } = a.phase else {
            unreachable!()
        };
        assert_eq!(start, 0.9f64.powi(3));
        a.observe(start * 3.9 / (2.0 - w));
        assert!(matches!(a.phase, Phase::Young { .. }), "{a:?}");
        a.observe(start * 4.1 / (2.0 - w));
        assert!(matches!(a.phase, Phase::Fixed));
        assert_eq!(a.omega, 1.05);
        // Or it never gets back below where it started.
        let mut a = Adaptive::new(1.0);
        for k in 0..6 {
            a.observe(0.5f64.powi(k));
        }
        let w = a.omega;
        assert!(w > 1.0);
        // Above the residual where the factor changed (0.125), within the growth allowed,
        // for the 30 sweeps of the trial (two of them already seen).
        for _ in 0..28 {
            a.observe(0.2);
        }
        assert!(matches!(a.phase, Phase::Young { .. }), "{a:?}");
        a.observe(0.2);
        assert!(matches!(a.phase, Phase::Fixed), "{a:?}");
        assert_eq!(a.omega, 1.0);
        // A rate that never settles: the proven factor after 12 sweeps.
        let mut a = Adaptive::new(1.08);
        for k in 0..12 {
            a.observe(if k % 2 == 0 { 1.0 } else { 0.3 });
        }
        assert!(matches!(a.phase, Phase::Fixed));
        assert_eq!(a.omega, 1.08);
        // A fixed factor stays.
        let mut a = Adaptive::fixed(1.3);
        a.observe(1e9);
        assert_eq!(a.omega, 1.3);
    }

    #[test]
    fn young_factor() {
        assert_eq!(super::young(0.0), 1.0);
        assert!((super::young(0.75) - 4.0 / 3.0).abs() < 1e-15);
        assert_eq!(super::young(0.99999999), super::MAX_OMEGA);
        for mu in [1.0, 2.0, -0.1, f64::NAN, f64::INFINITY] {
            assert_eq!(super::young(mu), 1.0, "{mu}");
        }
    }
}
