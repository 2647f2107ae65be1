//! The dense direct solve: `(I - diag(rho) F) B = E` by LU factorisation with partial
//! (row) pivoting, from the `faer` crate (`faer::linalg::lu::partial_pivoting`; Golub and
//! Van Loan 2013, *Matrix Computations*, 4th ed., §3.4). It is the reference the iterative
//! solvers are tested against.
//!
//! The matrix `I - diag(rho_c) F` depends on the channel's reflectances, so one
//! factorisation is made per distinct reflectance channel (a grey scene needs one, the
//! Cornell box three), each factor solving every channel that shares it. After the solve,
//! the residual is measured on the sparse `F` with the same definition as every other solver
//! (see the [module docs](super)); when it is above tolerance, up to
//! [`REFINEMENT_STEPS`] steps of iterative refinement (Wilkinson; Golub and Van Loan §3.5.3)
//! reuse the factors.
//!
//! ## Limits and failures
//! - The factor is dense: `8 n²` bytes for `n` patches. Above [`DIRECT_MAX_PATCHES`] patches
//!   (4096, i.e. 128 MiB per factor, and about `2/3 n³ = 4.6e10` flops per channel) the solve
//!   is refused with [`Error::Config`], naming the memory it would need.
//! - A pivot below `n * eps` times the largest one means the matrix is singular to working
//!   precision (a closed scene with `rho -> 1`): refused with
//!   [`Error::Singular`].
//! - With `rho >= 0`, `F >= 0` and spectral radius of `diag(rho) F` below 1, the solution is
//!   the Neumann series `sum_k (diag(rho) F)^k E >= 0`. A negative radiosity (beyond rounding)
//!   with non-negative emission therefore proves the spectral radius is at least 1 (rows of
//!   `F` summing far above 1): refused with [`Error::Singular`]
//!   rather than returned. Iterative solvers diverge on such systems; the direct solve would
//!   silently return a wrong answer.
//! - Still above tolerance after refinement: [`Error::NotConverged`]
//!   (or the partial answer with `keep_partial`), with a hint about conditioning.

use dyn_stack::{MemBuffer, MemStack};
use faer::linalg::lu::partial_pivoting::{factor, solve as lu_solve};
use faer::Mat;

use super::{
    finish, measure, worst, Gain, Options, Outcome, Prologue, Rows, SolveReport, Solver, System,
};
use crate::error::{Error, Result};

pub(crate) const NAME: &str = "direct";

/// Largest number of patches the dense direct solve accepts (see the [module docs](self)).
pub const DIRECT_MAX_PATCHES: usize = 4096;

/// Refuses a system of `n` patches above [`DIRECT_MAX_PATCHES`], saying what it would cost
/// and what to use instead: called by the solve, and by the pipeline as soon as the patch
/// count is known (before any form factor).
pub fn check_size(n: usize) -> Result<()> {
    if n > DIRECT_MAX_PATCHES {
        return Err(Error::Config(format!(
            "the direct solve is limited to {DIRECT_MAX_PATCHES} patches ({} per dense \
             factor); {n} patches would need {} per factor and about {:.1e} flops per \
             channel: use --solver cg or gauss-seidel, or fewer patches",
            super::mib(factor_bytes(DIRECT_MAX_PATCHES)),
            super::mib(factor_bytes(n)),
            2.0 / 3.0 * (n as f64).powi(3)
        )));
    }
    Ok(())
}

/// Steps of iterative refinement after the first solve, at most.
pub const REFINEMENT_STEPS: usize = 3;

/// Bytes of one dense factor for `n` patches.
pub fn factor_bytes(n: usize) -> u64 {
    8 * (n as u64) * (n as u64)
}

/// The dense LU solve; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct Direct;

/// A dense LU factorisation with partial (row) pivoting, by `faer`: the direct solve's
/// and the coarse correction's (`coarse` module).
pub(crate) struct Lu {
    lu: Mat<f64>,
    fwd: Vec<usize>,
    inv: Vec<usize>,
}

impl Lu {
    /// Factors the square matrix `a`, and returns the smallest pivot's magnitude (a NaN
    /// pivot counts as the smallest), its step, and the largest pivot's magnitude.
    pub(crate) fn of(mut a: Mat<f64>) -> (Lu, (f64, usize, f64)) {
        let n = a.nrows();
        let par = faer::get_global_parallelism();
        let mut fwd = vec![0usize; n];
        let mut inv = vec![0usize; n];
        let mut buf = MemBuffer::new(factor::lu_in_place_scratch::<usize, f64>(
            n,
            n,
            par,
            Default::default(),
        ));
        factor::lu_in_place(
            a.as_mut(),
            &mut fwd,
            &mut inv,
            par,
            MemStack::new(&mut buf),
            Default::default(),
        );
        let (mut lo, mut lo_at, mut hi) = (f64::INFINITY, 0, 0.0f64);
        for i in 0..n {
            let u = a[(i, i)].abs();
            if u.is_nan() || u < lo {
                lo = u;
                lo_at = i;
            }
            hi = hi.max(u);
        }
        (Lu { lu: a, fwd, inv }, (lo, lo_at, hi))
    }

    /// True when the pivots `(lo, _, hi)` of [`Lu::of`] for `n` unknowns leave the matrix
    /// singular to working precision: the smallest at most `n` ulps of the largest.
    pub(crate) fn singular((lo, _, hi): (f64, usize, f64), n: usize) -> bool {
        n > 0 && !(lo.is_finite() && hi.is_finite() && lo > n as f64 * f64::EPSILON * hi)
    }

    /// Solves for the columns of `m` in place.
    pub(crate) fn solve_in_place(&self, m: &mut Mat<f64>) {
        let (n, k) = (m.nrows(), m.ncols());
        let par = faer::get_global_parallelism();
        let mut buf = MemBuffer::new(lu_solve::solve_in_place_scratch::<usize, f64>(n, k, par));
        let perm = faer::perm::PermRef::new_checked(&self.fwd, &self.inv, n);
        lu_solve::solve_in_place(
            self.lu.as_ref(),
            self.lu.as_ref(),
            perm,
            m.as_mut(),
            par,
            MemStack::new(&mut buf),
        );
    }
}

/// One LU factor of `I - diag(rho_c) F` and the channels it serves.
struct Factor {
    lu: Lu,
    channels: Vec<usize>,
}

impl Factor {
    /// Solves `(I - diag(rho_c) F) x = rhs` in place for the factor's channels.
    fn solve(&self, rhs: &mut [[f64; 3]]) {
        let (n, k) = (rhs.len(), self.channels.len());
        let mut m = Mat::<f64>::from_fn(n, k, |i, c| rhs[i][self.channels[c]]);
        self.lu.solve_in_place(&mut m);
        for (i, r) in rhs.iter_mut().enumerate() {
            for (c, &ch) in self.channels.iter().enumerate() {
                r[ch] = m[(i, c)];
            }
        }
    }
}

/// Factors `I - diag(rho_c) F` for channel `c`; fails when singular to working precision.
fn factorise(sys: &System, rows: &Rows, c: usize, channels: Vec<usize>) -> Result<Factor> {
    let n = sys.len();
    let mut a = Mat::<f64>::zeros(n, n);
    for i in 0..n {
        let (ind, val) = rows.row(i);
        let rho = sys.rho[i][c];
        for (&j, &f) in ind.iter().zip(val) {
            let j = j as usize;
            a[(i, j)] -= rho * f;
        }
        a[(i, i)] += 1.0;
    }
    let (lu, pivots) = Lu::of(a);
    let (lo, lo_at, hi) = pivots;
    if Lu::singular(pivots, n) {
        return Err(Error::Singular {
            solver: NAME.into(),
            msg: format!(
                "channel {c}: LU pivot {lo:.3e} at step {lo_at} against a largest pivot of \
                 {hi:.3e} (I - diag(rho) F is singular to working precision; a closed scene \
                 with rho close to 1 has no bounded solution): lower the reflectances"
            ),
        });
    }
    Ok(Factor { lu, channels })
}

/// Channels grouped by identical reflectances: `(representative, members)`.
fn channel_groups(rho: &[[f64; 3]]) -> Vec<(usize, Vec<usize>)> {
    let mut groups: Vec<(usize, Vec<usize>)> = Vec::new();
    for c in 0..3 {
        match groups
            .iter_mut()
            .find(|(r, _)| rho.iter().all(|p| p[*r] == p[c]))
        {
            Some(g) => g.1.push(c),
            None => groups.push((c, vec![c])),
        }
    }
    groups
}

impl Solver for Direct {
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
            notes,
        } = Prologue::new(sys, opts)?;
        let n = sys.len();
        check_size(n)?;
        let factors = channel_groups(sys.rho)
            .into_iter()
            .map(|(c, members)| factorise(sys, &rows, c, members))
            .collect::<Result<Vec<_>>>()?;
        let mut b = sys.emit.to_vec();
        let (abs, per_patch) = measure(sys, &rows, &b, &floor);
        let mut history = vec![scale.rel(abs)];
        let mut patch_residual = worst(per_patch);
        let mut iterations = 0;
        // The first solve is the refinement step from B = E: d = A^{-1} (E - A E).
        loop {
            let r = *history.last().unwrap_or(&0.0);
            let done = r <= opts.tolerance && patch_residual <= opts.tolerance;
            if done || iterations > REFINEMENT_STEPS {
                break;
            }
            let mut d: Vec<[f64; 3]> = (0..n)
                .map(|i| {
                    let g = super::gather(sys, &rows, &b, i);
                    [0, 1, 2].map(|c| g[c] - b[i][c])
                })
                .collect();
            for f in &factors {
                f.solve(&mut d);
            }
            for (bi, di) in b.iter_mut().zip(&d) {
                for c in 0..3 {
                    bi[c] += di[c];
                }
            }
            iterations += 1;
            let (abs, per_patch) = measure(sys, &rows, &b, &floor);
            history.push(scale.rel(abs));
            patch_residual = worst(per_patch);
        }
        check_physical(sys, &b, &gain)?;
        let residual = *history.last().unwrap_or(&0.0);
        let out = Outcome {
            b,
            iterations,
            residual,
            patch_residual,
            history,
            notes,
        };
        finish(NAME, out, opts, &gain, start).map_err(|e| match e {
            Error::NotConverged {
                solver,
                iterations,
                residual,
                tolerance,
                ..
            } => Error::NotConverged {
                solver,
                iterations,
                residual,
                tolerance,
                hint: format!(
                    "; {REFINEMENT_STEPS} steps of iterative refinement did not reach the \
                     tolerance: the system is ill-conditioned (reflectances close to 1 in a \
                     closed scene)"
                ),
            },
            other => other,
        })
    }
}

/// Refuses a negative radiosity where every emission is non-negative (see the module docs).
fn check_physical(sys: &System, b: &[[f64; 3]], gain: &Gain) -> Result<()> {
    if sys.emit.iter().flatten().any(|&e| e < 0.0) {
        return Ok(());
    }
    let top = b.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    let floor = -1e-9 * top.max(f64::MIN_POSITIVE);
    if let Some((i, c)) = (0..b.len())
        .flat_map(|i| (0..3).map(move |c| (i, c)))
        .find(|&(i, c)| !b[i][c].is_finite() || b[i][c] < floor)
    {
        return Err(Error::Singular {
            solver: NAME.into(),
            msg: format!(
                "the solution has radiosity {:.3e} at patch {i} (channel {c}), impossible with \
                 non-negative emission unless the spectral radius of diag(rho) F is at least 1; \
                 rho * (row sum of F) reaches {:.4} at patch {}: the rows of F sum above 1, \
                 check the form factors",
                b[i][c],
                gain.max(),
                gain.patch
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use super::*;

    #[test]
    fn agrees_with_gauss_seidel_on_random_systems() {
        for seed in [1, 2, 3] {
            let owned = random(80, 10, seed);
            let (exact, report) = Direct.solve(&owned.sys(), &tight(1e-13)).unwrap();
            assert!(report.converged && report.iterations >= 1);
            assert_eq!(report.history.len(), report.iterations + 1);
            let (gs, _) = GaussSeidel.solve(&owned.sys(), &tight(1e-13)).unwrap();
            assert!(rel_diff(&exact, &gs) < 1e-11, "seed {seed}");
        }
    }

    #[test]
    fn grey_scene_needs_one_factor() {
        assert_eq!(channel_groups(&[[0.5; 3], [0.2; 3]]).len(), 1);
        let g = channel_groups(&[[0.5, 0.5, 0.1], [0.2, 0.2, 0.2]]);
        assert_eq!(g, vec![(0, vec![0, 1]), (2, vec![2])]);
    }

    #[test]
    fn refuses_too_many_patches_with_memory() {
        let n = DIRECT_MAX_PATCHES + 1;
        let f = crate::matrix::Csr::zero((n, n));
        let (rho, emit, area) = (vec![[0.5; 3]; n], vec![[1.0; 3]; n], vec![1.0; n]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        match Direct.solve(&sys, &Options::default()) {
            Err(Error::Config(m)) => {
                assert!(m.contains("4096 patches") && m.contains("MiB"), "{m}");
                assert!(m.contains("128.1 MiB per factor"), "{m}");
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn refuses_unphysical_rows() {
        // Rows summing to 1.5 with rho 0.9: spectral radius 1.35, the linear solution is
        // negative and is refused.
        let f = dense(&[&[0.0, 1.5], &[1.5, 0.0]]);
        let (rho, emit, area) = ([[0.9; 3]; 2], [[1.0; 3], [0.0; 3]], [1.0; 2]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        match Direct.solve(&sys, &tight(1e-13)) {
            Err(Error::Singular { msg, .. }) => assert!(msg.contains("spectral radius"), "{msg}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn refuses_singular_matrix() {
        // rho F = [[0, 1], [1, 0]] exactly is singular; rho < 1 keeps System::new happy.
        let rho = 0.75;
        let f = dense(&[&[0.0, 1.0 / rho], &[1.0 / rho, 0.0]]);
        let (rho, emit, area) = ([[rho; 3]; 2], [[1.0; 3]; 2], [1.0; 2]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        match Direct.solve(&sys, &tight(1e-13)) {
            Err(Error::Singular { msg, .. }) => assert!(msg.contains("singular"), "{msg}"),
            other => panic!("expected a refusal, got {other:?}"),
        }
    }
}
