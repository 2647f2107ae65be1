//! Radiosity solvers for `B = E + diag(rho) F B`, i.e. `(I - diag(rho) F) B = E`
//! (radiosidade.md, "Sistema Linear"; Goral, Torrance, Greenberg and Battaile 1984).
//!
//! The module owns the solve stage of the pipeline: it takes a form-factor matrix and the
//! patches' reflectances, emissions and areas ([`System`]), and returns the radiosity of every
//! patch together with a [`SolveReport`]. It does no I/O and knows nothing of scenes or
//! meshes. The three RGB channels are solved at once; `B` is a `Vec<[f64; 3]>`.
//!
//! ## Methods
//! One file per method, all behind the [`Solver`] trait (Cohen and Wallace 1993,
//! *Radiosity and Realistic Image Synthesis*, ch. 5, "Radiosity Matrix Solutions"):
//! - [`Jacobi`] (`jacobi.rs`): `B^{k+1} = E + diag(rho) F B^k`, rows in parallel.
//! - [`GaussSeidel`] (`gauss_seidel.rs`): the same sweep in place, row by row, solving each
//!   row for its own `B_i` so a non-zero diagonal `F_ii` (concave patches) is handled.
//! - [`Sor`] (`gauss_seidel.rs`): successive over-relaxation, the Gauss-Seidel sweep moving
//!   each patch `omega` times as far, starting from a factor proven to converge and then
//!   taking Young's factor for the rate the sweeps show; the default.
//! - [`Progressive`] (`progressive.rs`): progressive refinement by shooting, Cohen, Chen,
//!   Wallace and Greenberg 1988, "A progressive refinement approach to fast radiosity image
//!   generation" (SIGGRAPH '88), with its ambient term for display ([`ambient`],
//!   [`progressive_steps`]).
//! - [`Cg`] (`cg.rs`): preconditioned conjugate gradients on the symmetric form
//!   `diag(A / rho) - diag(A) F` (symmetric by reciprocity), with black patches eliminated
//!   and a defect correction that makes the answer solve the original system when a Monte
//!   Carlo `F` is only approximately reciprocal.
//! - [`Direct`] (`direct.rs`): dense LU with partial pivoting (`faer`), up to
//!   [`DIRECT_MAX_PATCHES`] patches; the reference the others are tested against.
//!
//! ## The residual
//! Every solver measures the same quantity, returned by [`residual`]: the relative residual
//!
//! ```text
//! r(B) = max over channels c of  || E_c + diag(rho_c) F B_c - B_c ||_inf / s_c
//! ```
//!
//! where `s_c = ||E_c||_inf`, the largest emission in channel `c`. A channel that emits
//! nothing is measured against the largest emission of any channel instead (its exact
//! solution is zero, so a relative measure of its own would be undefined), and a system that
//! emits nothing at all is measured in absolute terms. A non-finite `B` has residual `inf`.
//! The solvers start from `B = E`; the report's `residual` is always `r` of the returned
//! `B`, computed exactly.
//!
//! ## The stopping rule, per patch
//! `r(B)` is relative to the brightest emission, so it says nothing about patches far
//! dimmer than the light: in a scene with every reflectance at 0.001, surfaces lit at second
//! order have `B ~ 1e-8 E`, and `r(B) = 1e-6` leaves them 90% low. So a solve stops only when
//! every patch is converged too, by its own value:
//!
//! ```text
//! p(B) = max over patches i and channels c of  |E_ic + rho_ic (F B_c)_i - B_ic| / max(|B_ic|, floor_c)
//! ```
//!
//! and the run converges when `r(B) <= tolerance` and `p(B) <= tolerance` (reported as
//! `patch_residual`). `floor_c` is [`Options::floor`] (absolute, radiosity units) or, by
//! default, [`DEFAULT_FLOOR`] times `s_c`; it keeps patches that receive no light, or almost
//! none, from asking for a relative accuracy that means nothing. A row whose residual is
//! within 64 ulps of its own terms (`|E_i| + |rho_i (F B)_i| + |B_i|`) counts as converged:
//! that residual is the rounding of its evaluation. With every `rho` and `F` non-negative
//! the residual bounds the error of each patch about as it bounds the global one (the error
//! is `(I - diag(rho) F)^-1` applied to the residual, a sum of non-negative terms).
//!
//! ## Failures
//! - Invalid input (lengths, non-finite values, `rho` outside `[0, 1)`, a patch that would
//!   reflect onto itself all it receives) is refused by [`System::new`] with
//!   [`Error::Config`] naming the patch or the mismatch.
//! - Before iterating, the largest `rho_i * sum_j |F_ij|` is checked. Below 1 it bounds the
//!   spectral radius of `diag(rho) F` and every method converges; at 1 or above (rows of `F`
//!   summing above 1, which a physical `F` never does) the iteration may still converge,
//!   since not every row need be that large, and a note is added to the report.
//! - A run that reaches `max_iterations` returns [`Error::NotConverged`] with a hint, or,
//!   with `keep_partial`, the partial `B` and `converged: false`.
//! - A run whose residual grows past `1e12` or stops being finite is diverging (the spectral
//!   radius of `diag(rho) F` is at least 1): it stops at once with [`Error::NotConverged`],
//!   whatever `keep_partial` says. No solver returns NaN or infinite values.
//!
//! ## Example
//! ```
//! use radiosity::matrix::Triplets;
//! use radiosity::solve::{solve, Method, Options, System};
//!
//! // Two patches facing each other, each seeing half of the other.
//! let mut t = Triplets::new((2, 2));
//! t.add_triplet(0, 1, 0.5);
//! t.add_triplet(1, 0, 0.5);
//! let f = t.to_csr();
//! let (rho, emit, area) = ([[0.5; 3]; 2], [[1.0; 3], [0.0; 3]], [1.0; 2]);
//! let sys = System::new(&f, &rho, &emit, &area)?;
//! let (b, report) = solve(Method::GaussSeidel, &sys, &Options::default())?;
//! // B_1 = 0.25 B_0 and B_0 = 1 + 0.25 B_1, so B_0 = 16/15.
//! assert!((b[0][0] - 16.0 / 15.0).abs() < 1e-5);
//! assert!(report.converged && report.residual <= 1e-6);
//! # Ok::<(), radiosity::Error>(())
//! ```

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use crate::matrix::{Csr, ROWS_PER_TASK};
use rayon::prelude::*;

use crate::error::{Error, Result};

pub mod cg;
mod coarse;
pub mod direct;
pub mod distributed;
pub mod gauss_seidel;
pub mod jacobi;
pub mod progressive;

pub use cg::Cg;
pub use direct::{Direct, DIRECT_MAX_PATCHES};
pub use gauss_seidel::{relaxation, GaussSeidel, Sor};
pub use jacobi::Jacobi;
pub use progressive::{ambient, ambient_term, progressive_steps, Progressive};

/// Formats bytes as MiB with one decimal (memory needs in messages and summaries).
pub fn mib(bytes: u64) -> String {
    format!("{:.1} MiB", bytes as f64 / (1024.0 * 1024.0))
}

/// Relative residual above which an iteration is taken to diverge.
pub const DIVERGENCE: f64 = 1e12;

/// The radiosity system `B = E + diag(rho) F B`, borrowed from the pipeline's results.
///
/// Build it with [`System::new`], which validates it; the solvers validate again, so a
/// `System` written as a struct literal is safe too.
#[derive(Clone, Copy, Debug)]
pub struct System<'a> {
    /// `F[i, j]`, stored by rows (CSR): the fraction of the energy leaving patch i that
    /// arrives at patch j.
    pub f: &'a Csr,
    /// Diffuse reflectance of each patch, per channel, in `[0, 1)`.
    pub rho: &'a [[f64; 3]],
    /// Emitted exitance of each patch, per channel.
    pub emit: &'a [[f64; 3]],
    /// Area of each patch (used by progressive refinement to rank patches by power).
    pub area: &'a [f64],
}

impl<'a> System<'a> {
    /// Validates and borrows the system: `f` square and stored by rows, one `rho`, `emit` and
    /// `area` per row of `f`, every value finite, `rho` in `[0, 1)`, areas positive, and
    /// `rho_i * F_ii < 1` (a patch may not reflect onto itself all it receives).
    pub fn new(
        f: &'a Csr,
        rho: &'a [[f64; 3]],
        emit: &'a [[f64; 3]],
        area: &'a [f64],
    ) -> Result<System<'a>> {
        let sys = System { f, rho, emit, area };
        sys.validate()?;
        Ok(sys)
    }

    /// Number of patches.
    pub fn len(&self) -> usize {
        self.f.rows()
    }

    /// True when there are no patches.
    pub fn is_empty(&self) -> bool {
        self.f.rows() == 0
    }

    /// The checks of [`System::new`].
    pub fn validate(&self) -> Result<()> {
        let f = self.f;
        if f.rows() != f.cols() {
            return Err(Error::Config(format!(
                "the form-factor matrix is {}x{}, not square",
                f.rows(),
                f.cols()
            )));
        }
        if !f.is_csr() {
            return Err(Error::Config(
                "the form-factor matrix must be stored by rows (CSR); convert it with to_csr()"
                    .into(),
            ));
        }
        let n = f.rows();
        let mismatched: Vec<String> = [
            ("rho", self.rho.len()),
            ("emit", self.emit.len()),
            ("area", self.area.len()),
        ]
        .iter()
        .filter(|(_, len)| *len != n)
        .map(|(name, len)| format!("{name} has {len} entries"))
        .collect();
        if !mismatched.is_empty() {
            return Err(Error::Config(format!(
                "{} but the form-factor matrix has {n} rows (one per patch)",
                mismatched.join(", ")
            )));
        }
        check_patches(self.rho, self.emit, self.area)?;
        check_matrix(f, 0, self.rho)
    }
}

/// Refuses reflectances, emissions or areas [`System::new`] refuses.
pub(crate) fn check_patches(rho: &[[f64; 3]], emit: &[[f64; 3]], area: &[f64]) -> Result<()> {
    {
        for (i, rho) in rho.iter().enumerate() {
            if rho.iter().any(|r| !r.is_finite()) {
                return Err(Error::Config(format!(
                    "patch {i}: rho = {rho:?} is not a finite number"
                )));
            }
            if rho.iter().any(|r| !(0.0..1.0).contains(r)) {
                return Err(Error::Config(format!(
                    "patch {i}: rho = {rho:?} is outside [0, 1) (a reflectance of 1 or more \
                     absorbs nothing: in a closed scene I - diag(rho) F is then singular and \
                     the radiosity system has no bounded solution)"
                )));
            }
        }
        for (i, e) in emit.iter().enumerate() {
            if e.iter().any(|v| !v.is_finite()) {
                return Err(Error::Config(format!(
                    "patch {i}: emit = {e:?} is not a finite number"
                )));
            }
        }
        for (i, &a) in area.iter().enumerate() {
            if !(a.is_finite() && a > 0.0) {
                return Err(Error::Config(format!(
                    "patch {i}: area {a} is not a positive number"
                )));
            }
        }
    }
    Ok(())
}

/// Refuses a non-finite entry of `f`, and a patch that would reflect onto itself all it
/// receives (`rho_i F_ii >= 1`), in one pass over the rows; `f`'s rows are the matrix's rows
/// `lo..`, `rho` of every patch (checked finite before: [`check_patches`]).
pub(crate) fn check_matrix(f: &Csr, lo: usize, rho: &[[f64; 3]]) -> Result<()> {
    let (ptr, ind, val) = (f.indptr(), f.indices(), f.data());
    // The row's diagonal, or the first entry that is not finite.
    let row = |r: usize| -> std::result::Result<f64, (usize, f64)> {
        let i = lo + r;
        let mut fii = 0.0;
        for k in ptr.index(r)..ptr.index(r + 1) {
            let (j, v) = (ind[k] as usize, val[k]);
            if !v.is_finite() {
                return Err((j, v));
            }
            if j == i {
                fii = v;
            }
        }
        Ok(fii)
    };
    let worst = |r: usize, fii: f64| rho[lo + r].iter().fold(0.0f64, |m, x| m.max(x * fii));
    // Rows in parallel; the first row refused is reported, whatever the threads.
    let bad = (0..f.rows())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .find_first(|&r| row(r).map_or(true, |fii| worst(r, fii) >= 1.0));
    let Some(r) = bad else {
        return Ok(());
    };
    let i = lo + r;
    match row(r) {
        Err((j, v)) => Err(Error::Config(format!("F[{i}, {j}] = {v} is not finite"))),
        Ok(fii) => Err(Error::Config(format!(
            "patch {i}: rho * F_ii = {:.6} >= 1 (F_ii = {fii:.6}): the patch would reflect \
             onto itself at least all it receives",
            worst(r, fii)
        ))),
    }
}

/// Stopping rules of the iterative solvers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Options {
    /// Stop when the relative residual (see the [module docs](self)) is at most this.
    pub tolerance: f64,
    /// Iteration cap: sweeps for Jacobi and Gauss-Seidel, shots (one patch each) for
    /// progressive refinement.
    pub max_iterations: usize,
    /// On reaching `max_iterations`, return the partial `B` with `converged: false` instead
    /// of [`Error::NotConverged`].
    pub keep_partial: bool,
    /// Absolute floor of the per-patch rule (radiosity units): a patch is converged when its
    /// residual is at most `tolerance * max(|B_i|, floor)`. `None`: [`DEFAULT_FLOOR`] times
    /// the largest emission of the channel (see the [module docs](self)).
    pub floor: Option<f64>,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            tolerance: 1e-6,
            max_iterations: 10_000,
            keep_partial: false,
            floor: None,
        }
    }
}

impl Options {
    /// Refuses a tolerance that is negative or not a number.
    pub fn validate(&self) -> Result<()> {
        if !(self.tolerance.is_finite() && self.tolerance >= 0.0) {
            return Err(Error::Config(format!(
                "solver tolerance {} is not a non-negative number",
                self.tolerance
            )));
        }
        if let Some(f) = self.floor {
            if !(f.is_finite() && f >= 0.0) {
                return Err(Error::Config(format!(
                    "solver floor {f} is not a finite non-negative number"
                )));
            }
        }
        Ok(())
    }
}

/// Default floor of the per-patch rule, relative to the largest emission of each channel:
/// a patch dimmer than this is converged to `tolerance * DEFAULT_FLOOR` of that emission
/// rather than to its own value (light that weak is below anything an f32 output or an
/// eye resolves next to the emitter).
pub const DEFAULT_FLOOR: f64 = 1e-12;

/// Residuals at most this many ulps of a row's own terms are rounding, not error: the
/// per-patch rule counts them as converged.
const ROUNDING_ULPS: f64 = 64.0;

/// What a solver did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolveReport {
    /// The solver's name.
    pub solver: String,
    /// Iterations applied to the returned `B` (sweeps, or shots for progressive refinement).
    pub iterations: usize,
    /// Relative residual of the returned `B`, computed exactly: the largest over channels of
    /// `||E + diag(rho) F B - B||_inf / ||E||_inf` (see the [module docs](self)).
    pub residual: f64,
    /// `history[k]`: the residual after `k` iterations, `history[0]` for the start `B = E`.
    /// Jacobi and Gauss-Seidel record the exact residual; progressive refinement records a
    /// bound on it from the unshot radiosity (see [`Progressive`]).
    pub history: Vec<f64>,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// The worst patch's relative residual: the largest over patches and channels of
    /// `|E_i + rho_i (F B)_i - B_i| / max(|B_i|, floor)` (residuals at the rounding level of
    /// their row count as 0; see the [module docs](self)).
    pub patch_residual: f64,
    /// Whether `residual <= tolerance` and `patch_residual <= tolerance`.
    pub converged: bool,
    /// Warnings found on the way (rows of `F` summing above 1, an early stop).
    pub notes: Vec<String>,
    /// The over-relaxation factor of each channel, for [`Sor`]; `None` for the others.
    pub relaxation: Option<[f64; 3]>,
    /// Aggregates of the coarse correction between [`Sor`]'s sweeps in a bright room
    /// (`coarse` module), 0 when none was used.
    pub coarse: usize,
}

/// A method for solving the radiosity system.
pub trait Solver {
    /// The method's name, as in reports and errors.
    fn name(&self) -> &'static str;

    /// Solves `sys`, starting from `B = E`; see the [module docs](self) for what is returned
    /// and when it fails.
    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)>;
}

/// The available solvers, by name (also the command line's `--solver` values).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Method {
    /// Jacobi sweeps, rows in parallel ([`Jacobi`]).
    #[value(help = "Jacobi sweeps, rows in parallel")]
    Jacobi,
    /// Gauss-Seidel sweeps ([`GaussSeidel`]).
    #[value(help = "Gauss-Seidel sweeps")]
    GaussSeidel,
    /// Gauss-Seidel sweeps over-relaxed by a factor chosen from the system ([`Sor`]).
    #[default]
    #[value(help = "Gauss-Seidel sweeps over-relaxed by a factor chosen from the system")]
    Sor,
    /// Progressive refinement by shooting ([`Progressive`]).
    #[value(help = "Progressive refinement by shooting")]
    Progressive,
    /// Preconditioned conjugate gradients on the symmetric form ([`Cg`]).
    #[value(help = "Preconditioned conjugate gradients on the symmetric form")]
    Cg,
    /// Dense LU with partial pivoting, up to 4096 patches ([`Direct`]).
    #[value(help = "Dense LU with partial pivoting, up to 4096 patches")]
    Direct,
}

impl Method {
    /// Every method.
    pub const ALL: [Method; 6] = [
        Method::Jacobi,
        Method::GaussSeidel,
        Method::Sor,
        Method::Progressive,
        Method::Cg,
        Method::Direct,
    ];

    /// The method's name: `jacobi`, `gauss-seidel`, `sor`, `progressive`, `cg` or `direct`.
    pub fn name(self) -> &'static str {
        self.solver().name()
    }

    fn solver(self) -> &'static (dyn Solver + Sync) {
        match self {
            Method::Jacobi => &Jacobi,
            Method::GaussSeidel => &GaussSeidel,
            Method::Sor => &Sor::AUTO,
            Method::Progressive => &Progressive,
            Method::Cg => &Cg,
            Method::Direct => &Direct,
        }
    }

    /// The iteration cap to give this method for a command-line `--max-iterations` on `n`
    /// patches. Sweeps (Jacobi, Gauss-Seidel) and CG iterations each cost about one pass over
    /// `F`; a progressive-refinement iteration is one shot, which reads one column, so its
    /// cap is `max_iterations * n` shots (the same number of passes' worth of work).
    pub fn iteration_cap(self, max_iterations: usize, n: usize) -> usize {
        match self {
            Method::Progressive => max_iterations.saturating_mul(n.max(1)),
            _ => max_iterations,
        }
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Method {
    type Err = Error;

    /// Parses `jacobi`, `gauss-seidel` (or `gauss_seidel`, `gs`), `sor` (or
    /// `over-relaxation`), `progressive`, `cg` (or `conjugate-gradient`) and `direct` (or
    /// `lu`).
    fn from_str(s: &str) -> Result<Method> {
        match s.to_ascii_lowercase().as_str() {
            "jacobi" => Ok(Method::Jacobi),
            "gauss-seidel" | "gauss_seidel" | "gaussseidel" | "gs" => Ok(Method::GaussSeidel),
            "sor" | "over-relaxation" => Ok(Method::Sor),
            "progressive" => Ok(Method::Progressive),
            "cg" | "conjugate-gradient" => Ok(Method::Cg),
            "direct" | "lu" => Ok(Method::Direct),
            _ => Err(Error::Config(format!(
                "unknown solver `{s}` (known: jacobi, gauss-seidel, sor, progressive, cg, direct)"
            ))),
        }
    }
}

/// Solves `sys` with `method`.
pub fn solve(method: Method, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    method.solver().solve(sys, opts)
}

/// The relative residual of `b` (see the [module docs](self)); `inf` when `b` does not have
/// one entry per patch or is not finite.
pub fn residual(sys: &System, b: &[[f64; 3]]) -> f64 {
    if b.len() != sys.len() || sys.validate().is_err() {
        return f64::INFINITY;
    }
    Scale::new(sys.emit).rel(abs_residual(sys, &Rows::new(sys.f), b))
}

// ---------------------------------------------------------------------------------------
// Shared machinery of the solvers.

/// Row access to a CSR matrix: `(indices, values)` of row `i`.
pub(crate) struct Rows<'a> {
    ptr: Vec<usize>,
    ind: &'a [u32],
    val: &'a [f64],
}

impl<'a> Rows<'a> {
    /// Rows of `f` (CSR, checked by [`System::validate`]).
    pub(crate) fn new(f: &'a Csr) -> Rows<'a> {
        Rows {
            ptr: f.indptr().to_proper().into_owned(),
            ind: f.indices(),
            val: f.data(),
        }
    }

    /// Number of rows.
    pub(crate) fn len(&self) -> usize {
        self.ptr.len().saturating_sub(1)
    }

    /// Column indices and values of row `i`.
    #[inline]
    pub(crate) fn row(&self, i: usize) -> (&'a [u32], &'a [f64]) {
        let (lo, hi) = (self.ptr[i], self.ptr[i + 1]);
        (&self.ind[lo..hi], &self.val[lo..hi])
    }
}

/// `E_i + rho_i sum_j F_ij b_j`, one row of the Jacobi map.
#[inline]
pub(crate) fn gather(sys: &System, rows: &Rows, b: &[[f64; 3]], i: usize) -> [f64; 3] {
    gather_row(rows.row(i), sys.emit[i], sys.rho[i], b)
}

/// `e + rho sum_j F_j b_j` over one row's columns and values: [`gather`], for any row.
#[inline]
pub(crate) fn gather_row(
    (ind, val): (&[u32], &[f64]),
    e: [f64; 3],
    rho: [f64; 3],
    b: &[[f64; 3]],
) -> [f64; 3] {
    let mut acc = [0.0; 3];
    for (&j, &f) in ind.iter().zip(val) {
        let j = j as usize;
        let bj = b[j];
        for c in 0..3 {
            acc[c] += f * bj[c];
        }
    }
    [
        e[0] + rho[0] * acc[0],
        e[1] + rho[1] * acc[1],
        e[2] + rho[2] * acc[2],
    ]
}

/// Per-channel `||E + diag(rho) F b - b||_inf`, rows in parallel.
pub(crate) fn abs_residual(sys: &System, rows: &Rows, b: &[[f64; 3]]) -> [f64; 3] {
    (0..rows.len())
        .into_par_iter()
        .map(|i| {
            let g = gather(sys, rows, b, i);
            [
                (g[0] - b[i][0]).abs(),
                (g[1] - b[i][1]).abs(),
                (g[2] - b[i][2]).abs(),
            ]
        })
        .reduce(|| [0.0; 3], max3)
}

/// Channel-wise maximum that keeps NaN.
#[inline]
pub(crate) fn max3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    let m = |x: f64, y: f64| {
        if x.is_nan() || y.is_nan() {
            f64::NAN
        } else {
            x.max(y)
        }
    };
    [m(a[0], b[0]), m(a[1], b[1]), m(a[2], b[2])]
}

/// The divisors of the relative residual, per channel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Scale([f64; 3]);

impl Scale {
    /// `||E_c||_inf` per channel; a dark channel uses the brightest one; all dark, 1.
    pub(crate) fn new(emit: &[[f64; 3]]) -> Scale {
        let e = emit.iter().fold([0.0f64; 3], |m, e| {
            [
                m[0].max(e[0].abs()),
                m[1].max(e[1].abs()),
                m[2].max(e[2].abs()),
            ]
        });
        let top = e[0].max(e[1]).max(e[2]);
        let top = if top > 0.0 { top } else { 1.0 };
        Scale(e.map(|s| if s > 0.0 { s } else { top }))
    }

    /// The relative measure of per-channel absolute norms: their largest ratio; `inf` for
    /// anything not finite.
    pub(crate) fn rel(&self, abs: [f64; 3]) -> f64 {
        let mut r = 0.0f64;
        for (a, s) in abs.iter().zip(&self.0) {
            let q = a / s;
            if !q.is_finite() {
                return f64::INFINITY;
            }
            r = r.max(q);
        }
        r
    }
}

/// The per-patch part of the stopping rule (see the [module docs](self)).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Floor([f64; 3]);

impl Floor {
    /// The floor of `opts` per channel, or the default relative to `scale`.
    pub(crate) fn new(opts: &Options, scale: &Scale) -> Floor {
        Floor(match opts.floor {
            Some(f) => [f; 3],
            None => scale.0.map(|s| DEFAULT_FLOOR * s),
        })
    }

    /// Relative residual of one row per channel: residual `r`, iterate `b`, and the
    /// magnitude `terms` of what the row's evaluation summed (for the rounding allowance).
    #[inline]
    pub(crate) fn row(&self, r: [f64; 3], b: [f64; 3], terms: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|c| {
            let r = r[c].abs();
            if r.is_nan() {
                return f64::NAN;
            }
            if r <= ROUNDING_ULPS * f64::EPSILON * terms[c].abs() {
                return 0.0;
            }
            r / b[c].abs().max(self.0[c]).max(f64::MIN_POSITIVE)
        })
    }

    /// The row measure of a residual `r` of iterate `b` at patch `i`, with the row's terms
    /// taken as `|E_i| + |B_i + r| + |B_i|` (exact for non-negative systems).
    #[inline]
    pub(crate) fn of_residual(&self, sys: &System, i: usize, r: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        self.of_residual_at(sys.emit[i], r, b)
    }

    /// [`Floor::of_residual`] for a patch of emission `e`.
    #[inline]
    pub(crate) fn of_residual_at(&self, e: [f64; 3], r: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        self.row(
            r,
            b,
            [0, 1, 2].map(|c| e[c].abs() + (b[c] + r[c]).abs() + b[c].abs()),
        )
    }
}

/// Per channel: the absolute residual `||E + diag(rho) F b - b||_inf` and the per-patch
/// measure of the rule (see [`Floor`]), in one pass over `F`, rows in parallel.
pub(crate) fn measure(
    sys: &System,
    rows: &Rows,
    b: &[[f64; 3]],
    floor: &Floor,
) -> ([f64; 3], [f64; 3]) {
    (0..rows.len())
        .into_par_iter()
        .map(|i| {
            let g = gather(sys, rows, b, i);
            let r = [0, 1, 2].map(|c| g[c] - b[i][c]);
            (r.map(f64::abs), floor.of_residual(sys, i, r, b[i]))
        })
        .reduce(
            || ([0.0; 3], [0.0; 3]),
            |a, b| (max3(a.0, b.0), max3(a.1, b.1)),
        )
}

/// The largest of three, keeping NaN.
#[inline]
pub(crate) fn worst(v: [f64; 3]) -> f64 {
    let m = max3(v, [v[1], v[2], v[0]]);
    max3(m, [m[2], m[0], m[1]])[0]
}

/// The worst patch's relative residual of `b` (see the [module docs](self)) with the floor
/// of `opts`; `inf` when `b` does not have one entry per patch or is not finite.
pub fn patch_residual(sys: &System, b: &[[f64; 3]], opts: &Options) -> f64 {
    if b.len() != sys.len() || sys.validate().is_err() || opts.validate().is_err() {
        return f64::INFINITY;
    }
    let floor = Floor::new(opts, &Scale::new(sys.emit));
    let p = worst(measure(sys, &Rows::new(sys.f), b, &floor).1);
    if p.is_finite() {
        p
    } else {
        f64::INFINITY
    }
}

/// How much `diag(rho) F` can amplify: `max_i rho_ic sum_j |F_ij|` per channel, which bounds
/// its spectral radius (and its infinity norm).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Gain {
    /// The bound, per channel.
    pub(crate) gain: [f64; 3],
    /// The patch where the largest bound is reached.
    pub(crate) patch: usize,
    /// That patch's row sum `sum_j F_ij`.
    pub(crate) row_sum: f64,
    /// That patch's largest reflectance.
    pub(crate) rho: f64,
    /// The largest `max_c rho_ic * sum_j |F_ij|`, reached at `patch` (`-inf` for no rows).
    pub(crate) best: f64,
}

impl Gain {
    pub(crate) fn new(sys: &System, rows: &Rows) -> Gain {
        Gain::of_rows(sys.rho, rows, 0)
    }

    /// The bound over `rows`, which are the matrix's rows `lo..` (`rho` of every patch).
    pub(crate) fn of_rows(rho: &[[f64; 3]], rows: &Rows, lo: usize) -> Gain {
        let g = Gain {
            gain: [0.0; 3],
            patch: 0,
            row_sum: 0.0,
            rho: 0.0,
            best: f64::NEG_INFINITY,
        };
        // Rows in parallel, runs of rows merged in order ([`Gain::merge`] keeps the first of
        // equal bounds), so the patch named is the same whatever the threads.
        (0..rows.len())
            .into_par_iter()
            .with_min_len(ROWS_PER_TASK)
            .fold(
                || g,
                |mut g, r| {
                    let i = lo + r;
                    let (_, val) = rows.row(r);
                    let abs_sum: f64 = val.iter().map(|v| v.abs()).sum();
                    let rho = rho[i];
                    for (g, r) in g.gain.iter_mut().zip(&rho) {
                        *g = g.max(r * abs_sum);
                    }
                    let here = rho[0].max(rho[1]).max(rho[2]) * abs_sum;
                    if here > g.best {
                        g.best = here;
                        g.patch = i;
                        g.row_sum = val.iter().sum();
                        g.rho = rho[0].max(rho[1]).max(rho[2]);
                    }
                    g
                },
            )
            .reduce(|| g, Gain::merge)
    }

    /// The bound over rows `a` then rows `b`: as [`Gain::of_rows`] over both (of equal
    /// largest bounds, `a`'s patch is kept).
    pub(crate) fn merge(a: Gain, b: Gain) -> Gain {
        let at = if b.best > a.best { b } else { a };
        Gain {
            gain: [0, 1, 2].map(|c| a.gain[c].max(b.gain[c])),
            ..at
        }
    }

    /// The largest bound over channels.
    pub(crate) fn max(&self) -> f64 {
        self.gain[0].max(self.gain[1]).max(self.gain[2])
    }

    /// True when the bound does not guarantee convergence.
    pub(crate) fn suspicious(&self) -> bool {
        self.max() >= 1.0
    }

    /// A bound on the condition number of `I - diag(rho) F` in the infinity norm, from the
    /// gain `g` (`||A|| <= 1 + g`, `||A^-1|| <= 1 / (1 - g)`): `(1 + g) / (1 - g)`;
    /// infinite when `g >= 1`.
    pub(crate) fn condition_bound(&self) -> f64 {
        let g = self.max();
        if g < 1.0 {
            (1.0 + g) / (1.0 - g)
        } else {
            f64::INFINITY
        }
    }

    /// The notes to put in a report before iterating.
    pub(crate) fn notes(&self) -> Vec<String> {
        let cond = self.condition_bound();
        if !self.suspicious() && cond > NEAR_SINGULAR {
            return vec![format!(
                "the system is near singular: rho * (row sum of F) reaches {:.7} at patch {} \
                 (rho {:.7}), so its condition number may be up to {cond:.1e}; a relative \
                 residual r bounds the relative error of B only by about {cond:.0e} x r \
                 (lower --tolerance, or check reflectances this close to 1)",
                self.max(),
                self.patch,
                self.rho
            )];
        }
        if self.suspicious() {
            vec![format!(
                "rho * (row sum of F) reaches {:.4} at patch {} (row sum {:.4}, rho {:.3}): \
                 rows of a physical F sum to at most 1, and the iteration may diverge",
                self.max(),
                self.patch,
                self.row_sum,
                self.rho
            )]
        } else {
            Vec::new()
        }
    }

    /// The part of a hint that blames `F`, or nothing.
    fn blame(&self) -> String {
        if self.suspicious() {
            format!(
                "; rows of F sum above 1 (max {:.4} at patch {}) with rho up to {:.3}: check \
                 the form factors",
                self.row_sum, self.patch, self.rho
            )
        } else {
            String::new()
        }
    }
}

/// Condition-number bound ([`Gain::condition_bound`]) above which a report notes that the
/// system is near singular.
pub(crate) const NEAR_SINGULAR: f64 = 1e5;

/// True when a relative residual says the iteration is diverging.
#[inline]
pub(crate) fn diverging(r: f64) -> bool {
    !r.is_finite() || r > DIVERGENCE
}

/// The error for a diverging run: always an error, whatever `keep_partial` says.
pub(crate) fn divergence(
    solver: &str,
    iterations: usize,
    residual: f64,
    opts: &Options,
    gain: &Gain,
) -> Error {
    Error::NotConverged {
        solver: solver.to_string(),
        iterations,
        residual,
        tolerance: opts.tolerance,
        hint: format!(
            "; the iteration diverges (residual past {DIVERGENCE:.0e} or not finite): the \
             spectral radius of diag(rho) F is at least 1{}",
            gain.blame()
        ),
    }
}

/// The hint of a run stopped by the iteration cap.
fn cap_hint(solver: &str, history: &[f64], tolerance: f64, gain: &Gain) -> String {
    let blame = gain.blame();
    if !blame.is_empty() {
        return blame;
    }
    let mut hint = String::from("; raise --max-iterations");
    // Average rate over the last few iterations, to say how many more would do.
    let len = history.len();
    let window = (len.saturating_sub(1)).min(20);
    if window > 0 {
        let (first, last) = (history[len - 1 - window], history[len - 1]);
        if first > 0.0 && last > 0.0 && last < first {
            let rate = (last / first).powf(1.0 / window as f64);
            let more = ((tolerance.max(f64::MIN_POSITIVE) / last).ln() / rate.ln()).ceil();
            if more.is_finite() && more > 0.0 {
                hint.push_str(&format!(
                    " (the residual falls by {rate:.4} per iteration: about {more:.0} more{})",
                    if solver == progressive::NAME {
                        " shots; for progressive the flag counts patches x N shots"
                    } else {
                        ""
                    }
                ));
            }
        }
    }
    hint
}

/// What a solver hands to [`finish`].
pub(crate) struct Outcome {
    pub(crate) b: Vec<[f64; 3]>,
    pub(crate) iterations: usize,
    pub(crate) residual: f64,
    /// The per-patch measure of `b` ([`SolveReport::patch_residual`]).
    pub(crate) patch_residual: f64,
    pub(crate) history: Vec<f64>,
    pub(crate) notes: Vec<String>,
}

/// Turns a finished run into the result: converged, partial (`keep_partial`) or
/// [`Error::NotConverged`].
pub(crate) fn finish(
    solver: &str,
    out: Outcome,
    opts: &Options,
    gain: &Gain,
    start: Instant,
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    if diverging(out.residual) || out.b.iter().flatten().any(|v| !v.is_finite()) {
        return Err(divergence(solver, out.iterations, out.residual, opts, gain));
    }
    let converged = out.residual <= opts.tolerance && out.patch_residual <= opts.tolerance;
    let mut report = SolveReport {
        solver: solver.to_string(),
        iterations: out.iterations,
        residual: out.residual,
        history: out.history,
        seconds: start.elapsed().as_secs_f64(),
        patch_residual: out.patch_residual,
        converged,
        notes: out.notes,
        relaxation: None,
        coarse: 0,
    };
    if converged {
        return Ok((out.b, report));
    }
    let mut hint = cap_hint(solver, &report.history, opts.tolerance, gain);
    if out.residual <= opts.tolerance {
        hint = format!(
            "; the worst patch's relative residual is still {:.3e} (the per-patch rule; \
             a dim patch next to a bright emitter converges last: raise --floor or \
             --max-iterations){hint}",
            out.patch_residual
        );
    }
    if opts.keep_partial {
        report.notes.push(format!(
            "stopped after {} iterations at residual {:.3e} (tolerance {:.1e}){hint}",
            out.iterations, out.residual, opts.tolerance
        ));
        return Ok((out.b, report));
    }
    Err(Error::NotConverged {
        solver: solver.to_string(),
        iterations: out.iterations,
        residual: out.residual,
        tolerance: opts.tolerance,
        hint,
    })
}

/// What every solver does first: starts the clock, checks the options and the system, and
/// builds the row view of `F`, the residual scale and the gain bound with its notes.
pub(crate) struct Prologue<'a> {
    pub(crate) start: Instant,
    pub(crate) rows: Rows<'a>,
    pub(crate) scale: Scale,
    pub(crate) floor: Floor,
    pub(crate) gain: Gain,
    pub(crate) notes: Vec<String>,
}

impl<'a> Prologue<'a> {
    /// The prologue of a solve of `sys` with `opts`; fails on invalid options or system.
    pub(crate) fn new(sys: &System<'a>, opts: &Options) -> Result<Prologue<'a>> {
        let start = Instant::now();
        opts.validate()?;
        sys.validate()?;
        let rows = Rows::new(sys.f);
        let scale = Scale::new(sys.emit);
        let floor = Floor::new(opts, &scale);
        let gain = Gain::new(sys, &rows);
        let notes = gain.notes();
        Ok(Prologue {
            start,
            rows,
            scale,
            floor,
            gain,
            notes,
        })
    }
}

/// The loop shared by the sweeping solvers (Jacobi, Gauss-Seidel, SOR).
///
/// `pass(rows, floor, b, next)` writes the next iterate into `next` and returns the
/// per-channel absolute residual of `b` and its per-patch measure ([`Floor::row`]), so each
/// pass over `F` also measures the iterate it starts from. The loop returns the first
/// iterate within tolerance by both measures (the one they were computed for, so the
/// reported residuals are exact), or the last one at the cap.
pub(crate) fn sweep_loop(
    solver: &str,
    sys: &System,
    opts: &Options,
    pass: impl FnMut(&Rows, &Floor, &[[f64; 3]], &mut [[f64; 3]]) -> ([f64; 3], [f64; 3]),
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    sweeps(solver, sys, opts, Prologue::new(sys, opts)?, pass)
}

/// [`sweep_loop`] after its prologue, for a solver that reads the prologue first (the
/// over-relaxation factor of [`Sor`] comes from its gain bound).
pub(crate) fn sweeps(
    solver: &str,
    sys: &System,
    opts: &Options,
    prologue: Prologue,
    mut pass: impl FnMut(&Rows, &Floor, &[[f64; 3]], &mut [[f64; 3]]) -> ([f64; 3], [f64; 3]),
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    let Prologue {
        start,
        rows,
        scale,
        floor,
        gain,
        notes,
    } = prologue;
    let mut b = sys.emit.to_vec();
    let mut next = b.clone();
    let mut history = Vec::new();
    let mut k = 0;
    loop {
        let (abs, per_patch) = pass(&rows, &floor, &b, &mut next);
        let r = scale.rel(abs);
        let p = worst(per_patch);
        history.push(r);
        if diverging(r) {
            return Err(divergence(solver, k, r, opts, &gain));
        }
        if (r <= opts.tolerance && p <= opts.tolerance) || k >= opts.max_iterations {
            let out = Outcome {
                b,
                iterations: k,
                residual: r,
                patch_residual: p,
                history,
                notes,
            };
            return finish(solver, out, opts, &gain, start);
        }
        std::mem::swap(&mut b, &mut next);
        k += 1;
    }
}

#[cfg(test)]
pub(crate) mod testing {
    //! Test systems shared by the solvers' tests.
    use super::*;
    use crate::matrix::Triplets as TriMat;

    /// Options asking for relative residual `tolerance`, with room for as many sweeps as
    /// the hardest test system needs.
    pub fn tight(tolerance: f64) -> Options {
        Options {
            tolerance,
            max_iterations: 1_000_000,
            ..Options::default()
        }
    }

    /// An owned system.
    pub struct Owned {
        pub f: Csr,
        pub rho: Vec<[f64; 3]>,
        pub emit: Vec<[f64; 3]>,
        pub area: Vec<f64>,
    }

    impl Owned {
        pub fn sys(&self) -> System<'_> {
            System::new(&self.f, &self.rho, &self.emit, &self.area).unwrap()
        }
    }

    /// CSR from dense rows, zeros left out.
    pub fn dense(rows: &[&[f64]]) -> Csr {
        let n = rows.len();
        let mut t = TriMat::new((n, rows.first().map_or(0, |r| r.len())));
        for (i, r) in rows.iter().enumerate() {
            for (j, &v) in r.iter().enumerate() {
                if v != 0.0 {
                    t.add_triplet(i, j, v);
                }
            }
        }
        t.to_csr()
    }

    /// The notes' infinite shelf: strips A (floor, width 1), B (back, width g = sqrt 3),
    /// C (top, width 1), exact 2D (crossed-strings) form factors.
    pub fn shelf_f() -> (Csr, Vec<f64>) {
        let g = 3f64.sqrt();
        let (a, b) = (1.0, g);
        let f_ab = (1.0 + g - (1.0 + g * g).sqrt()) / 2.0;
        let f_ac = (1.0 + g * g).sqrt() - g;
        let f_bc = (1.0 + 1.0 / g - (1.0 + 1.0 / (g * g)).sqrt()) / 2.0;
        let f_ba = f_ab * a / b;
        let (f_ca, f_cb) = (f_ac, f_ab);
        let f = dense(&[&[0.0, f_ab, f_ac], &[f_ba, 0.0, f_bc], &[f_ca, f_cb, 0.0]]);
        (f, vec![a, b, a])
    }

    /// The shelf with grey `rho` and `emit` per strip.
    pub fn shelf(rho: [f64; 3], emit: [f64; 3]) -> Owned {
        let (f, area) = shelf_f();
        Owned {
            f,
            rho: rho.map(|r| [r; 3]).to_vec(),
            emit: emit.map(|e| [e; 3]).to_vec(),
            area,
        }
    }

    /// The four rows of the notes' table: (rho, E, B), B_B of row 4 restored to 1.02906
    /// and row 3's exact value.
    pub fn shelf_table() -> [([f64; 3], [f64; 3], [f64; 3]); 4] {
        let third = 1.0 / 3.0;
        let exact = (3.0 - 3f64.sqrt()) / 6.0;
        [
            ([0.0, 0.5, third], [1.0, 0.0, 0.0], [1.0, 0.11660, 0.10354]),
            (
                [0.1, 0.5, third],
                [1.0, 0.0, 0.0],
                [1.00709, 0.11743, 0.10428],
            ),
            ([0.5, 0.0, 0.5], [0.0, 1.0, 0.0], [exact, 1.0, exact]),
            (
                [0.1, 0.1, 0.5],
                [1.0, 1.0, 0.0],
                [1.04647, 1.02906, 0.32853],
            ),
        ]
    }

    /// A small deterministic generator (SplitMix64).
    pub struct Rng(u64);

    impl Rng {
        pub fn new(seed: u64) -> Rng {
            Rng(seed)
        }

        pub fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }

        /// Uniform in [0, 1).
        pub fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// A random-ish sparse system: about `per_row` entries a row (the diagonal included
    /// sometimes), row sums in [0.2, 0.98), rho in [0, 0.95), a fifth of the patches emitting.
    pub fn random(n: usize, per_row: usize, seed: u64) -> Owned {
        let mut rng = Rng::new(seed);
        let mut t = TriMat::new((n, n));
        for i in 0..n {
            let mut cols: Vec<usize> = (0..per_row)
                .map(|_| (rng.next_u64() % n as u64) as usize)
                .collect();
            cols.sort_unstable();
            cols.dedup();
            let w: Vec<f64> = cols.iter().map(|_| 0.05 + rng.uniform()).collect();
            let total: f64 = w.iter().sum();
            let target = 0.2 + 0.78 * rng.uniform();
            for (&j, &wj) in cols.iter().zip(&w) {
                t.add_triplet(i, j, wj / total * target);
            }
        }
        let rho = (0..n)
            .map(|_| [0.0; 3].map(|_: f64| 0.95 * rng.uniform()))
            .collect();
        let emit = (0..n)
            .map(|_| {
                if rng.uniform() < 0.2 {
                    [0.0; 3].map(|_: f64| 0.5 + rng.uniform())
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let area = (0..n).map(|_| 0.5 + 1.5 * rng.uniform()).collect();
        Owned {
            f: t.to_csr(),
            rho,
            emit,
            area,
        }
    }

    /// A closed furnace: rows summing to 1 (the diagonal included), uniform rho and E, equal
    /// areas, and `F` symmetric (so reciprocal): the average of `(Q + Q^T) / 2` over random
    /// permutation matrices `Q` with random weights, each term doubly stochastic.
    pub fn furnace(n: usize, rho: [f64; 3], emit: [f64; 3]) -> Owned {
        let mut rng = Rng::new(7);
        let mut rows = vec![vec![0.0; n]; n];
        let terms = n.max(1);
        let w: Vec<f64> = (0..terms).map(|_| 0.1 + rng.uniform()).collect();
        let total: f64 = w.iter().sum();
        for wk in &w {
            // A random permutation by Fisher-Yates.
            let mut perm: Vec<usize> = (0..n).collect();
            for i in (1..n).rev() {
                let j = (rng.next_u64() % (i as u64 + 1)) as usize;
                perm.swap(i, j);
            }
            for (i, &j) in perm.iter().enumerate() {
                rows[i][j] += 0.5 * wk / total;
                rows[j][i] += 0.5 * wk / total;
            }
        }
        let refs: Vec<&[f64]> = rows.iter().map(Vec::as_slice).collect();
        Owned {
            f: dense(&refs),
            rho: vec![rho; n],
            emit: vec![emit; n],
            area: vec![1.0; n],
        }
    }

    /// Largest |x - y| over the largest |x|.
    pub fn rel_diff(x: &[[f64; 3]], y: &[[f64; 3]]) -> f64 {
        assert_eq!(x.len(), y.len());
        let top = x.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
        let d = x
            .iter()
            .flatten()
            .zip(y.iter().flatten())
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        d / top
    }
}

#[cfg(test)]
mod tests {
    use super::testing::*;
    use super::*;

    #[test]
    fn shelf_table_every_solver() {
        for (rho, emit, want) in shelf_table() {
            let owned = shelf(rho, emit);
            for method in Method::ALL {
                let (b, report) = solve(method, &owned.sys(), &tight(1e-12)).unwrap();
                assert!(report.converged, "{method}");
                for (p, (bp, wp)) in b.iter().zip(want).enumerate() {
                    for v in bp {
                        assert!(
                            (v - wp).abs() < 5e-5,
                            "{method}, rho {rho:?}, E {emit:?}: B[{p}] = {v} not {wp}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn shelf_rows_as_channels() {
        // Rows 1 to 3 of the table in the three channels of one system.
        let (f, area) = shelf_f();
        let table = shelf_table();
        let rho: Vec<[f64; 3]> = (0..3).map(|p| [0, 1, 2].map(|r| table[r].0[p])).collect();
        let emit: Vec<[f64; 3]> = (0..3).map(|p| [0, 1, 2].map(|r| table[r].1[p])).collect();
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        for method in Method::ALL {
            let (b, _) = solve(method, &sys, &tight(1e-12)).unwrap();
            for (p, bp) in b.iter().enumerate() {
                for (c, row) in table.iter().take(3).enumerate() {
                    assert!((bp[c] - row.2[p]).abs() < 5e-5, "{method}: B[{p}][{c}]");
                }
            }
        }
    }

    #[test]
    fn furnace_is_e_over_one_minus_rho() {
        let rho = [0.3, 0.6, 0.9];
        let emit = [1.0, 2.0, 0.5];
        let owned = furnace(12, rho, emit);
        for method in Method::ALL {
            let (b, report) = solve(method, &owned.sys(), &tight(1e-12)).unwrap();
            assert!(report.converged);
            for bi in &b {
                for c in 0..3 {
                    let want = emit[c] / (1.0 - rho[c]);
                    assert!(
                        (bi[c] - want).abs() < 1e-9,
                        "{method}: {} not {want}",
                        bi[c]
                    );
                }
            }
        }
    }

    #[test]
    fn two_by_two_closed_form() {
        // With a diagonal (patch 0 concave): (I - diag(rho) F) B = E by Cramer's rule.
        let f = dense(&[&[0.1, 0.6], &[0.3, 0.2]]);
        let rho = [[0.8, 0.5, 0.0], [0.7, 0.25, 0.9]];
        let emit = [[1.0, 0.0, 2.0], [0.5, 1.0, 0.0]];
        let area = [1.0, 2.0];
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        let mut want = [[0.0; 3]; 2];
        for c in 0..3 {
            let (a, b) = (1.0 - rho[0][c] * 0.1, -rho[0][c] * 0.6);
            let (cc, d) = (-rho[1][c] * 0.3, 1.0 - rho[1][c] * 0.2);
            let det = a * d - b * cc;
            want[0][c] = (emit[0][c] * d - b * emit[1][c]) / det;
            want[1][c] = (a * emit[1][c] - cc * emit[0][c]) / det;
        }
        for method in Method::ALL {
            let (b, report) = solve(method, &sys, &tight(1e-12)).unwrap();
            assert!(rel_diff(&want, &b) < 1e-10, "{method}: {b:?} not {want:?}");
            assert!(report.residual <= 1e-12);
            assert!((residual(&sys, &b) - report.residual).abs() <= 1e-15);
        }
    }

    #[test]
    fn agree_on_random_sparse_system() {
        let owned = random(50, 8, 42);
        let sys = owned.sys();
        let results: Vec<_> = Method::ALL
            .iter()
            .map(|&m| solve(m, &sys, &tight(1e-12)).unwrap())
            .collect();
        for (_, report) in &results {
            assert!(
                report.converged && report.residual <= 1e-12,
                "{}",
                report.solver
            );
        }
        for (b, report) in &results[1..] {
            let d = rel_diff(&results[0].0, b);
            assert!(d < 1e-8, "{} differs from jacobi by {d:e}", report.solver);
        }
        // Sanity: the system is not trivial.
        assert!(results[0].1.iterations > 10);
    }

    #[test]
    fn cap_is_reported() {
        let owned = random(50, 8, 3);
        let sys = owned.sys();
        // The direct solve has no iteration cap.
        for method in Method::ALL.into_iter().filter(|&m| m != Method::Direct) {
            let opts = Options {
                tolerance: 1e-12,
                max_iterations: 2,
                keep_partial: false,
                floor: None,
            };
            match solve(method, &sys, &opts) {
                Err(Error::NotConverged {
                    solver,
                    iterations,
                    residual,
                    tolerance,
                    hint,
                }) => {
                    assert_eq!(solver, method.name());
                    assert_eq!(iterations, 2);
                    assert!(residual > 1e-12 && residual.is_finite());
                    assert_eq!(tolerance, 1e-12);
                    assert!(hint.contains("--max-iterations"), "{hint}");
                }
                other => panic!("{method}: expected NotConverged, got {other:?}"),
            }
            let opts = Options {
                keep_partial: true,
                ..opts
            };
            let (b, report) = solve(method, &sys, &opts).unwrap();
            assert!(!report.converged);
            assert_eq!(report.iterations, 2);
            assert_eq!(report.history.len(), 3);
            assert!(b.iter().flatten().all(|v| v.is_finite()));
            assert!(
                (residual(&sys, &b) - report.residual).abs() <= 1e-15 * report.residual.max(1.0)
            );
            assert!(report.notes.iter().any(|n| n.contains("stopped after 2")));
        }
    }

    #[test]
    fn divergence_stops_with_spectral_radius_error() {
        // Rows summing to 1.5 with rho 0.9: diag(rho) F has spectral radius 1.35.
        let f = dense(&[&[0.0, 1.5], &[1.5, 0.0]]);
        let (rho, emit, area) = ([[0.9; 3]; 2], [[1.0; 3]; 2], [1.0; 2]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        for method in Method::ALL {
            let opts = Options {
                keep_partial: true,
                max_iterations: 1_000_000,
                ..tight(1e-12)
            };
            match solve(method, &sys, &opts) {
                Err(Error::NotConverged { hint, residual, .. }) => {
                    assert!(hint.contains("spectral radius"), "{method}: {hint}");
                    assert!(hint.contains("rows of F sum above 1"), "{method}: {hint}");
                    assert!(residual > DIVERGENCE || !residual.is_finite());
                }
                // CG finds the symmetric form indefinite; the direct solve finds a negative B.
                Err(Error::Singular { solver, msg })
                    if matches!(method, Method::Cg | Method::Direct) =>
                {
                    assert_eq!(solver, method.name());
                    assert!(msg.contains("rows of F sum above 1"), "{method}: {msg}");
                }
                other => panic!("{method}: expected divergence, got {other:?}"),
            }
        }
    }

    #[test]
    fn large_row_sum_is_noted_but_may_converge() {
        // Row 0 reflects 1.08 of what it gathers, row 1 only 0.25: spectral radius ~0.52.
        let f = dense(&[&[0.0, 1.2], &[0.5, 0.0]]);
        let (rho, emit, area) = ([[0.9; 3], [0.5; 3]], [[1.0; 3], [0.0; 3]], [1.0; 2]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        for method in Method::ALL {
            let (b, report) = solve(method, &sys, &tight(1e-12)).unwrap();
            assert!(report.converged);
            assert!(
                report.notes.iter().any(|n| n.contains("patch 0")),
                "{:?}",
                report.notes
            );
            // B_0 = 1 + 1.08 B_1, B_1 = 0.25 B_0.
            assert!((b[0][0] - 1.0 / (1.0 - 0.27)).abs() < 1e-10, "{method}");
        }
    }

    #[test]
    fn near_singular_systems_are_noted() {
        // A closed furnace at rho 0.999999: B = 1e6 exactly, condition number ~2e6. The CG
        // and direct solvers reach the tolerance; the report must say what that is worth.
        let owned = furnace(12, [0.999999; 3], [1.0; 3]);
        for method in [Method::Cg, Method::Direct] {
            let (_, report) = solve(method, &owned.sys(), &Options::default()).unwrap();
            assert!(
                report.notes.iter().any(|n| n.contains("near singular")),
                "{method}: {:?}",
                report.notes
            );
        }
        let owned = furnace(12, [0.9; 3], [1.0; 3]);
        let (_, report) = solve(Method::Cg, &owned.sys(), &Options::default()).unwrap();
        assert!(
            !report.notes.iter().any(|n| n.contains("near singular")),
            "{:?}",
            report.notes
        );
    }

    #[test]
    fn physical_system_has_no_notes() {
        let owned = random(20, 5, 9);
        let (_, report) = solve(Method::Jacobi, &owned.sys(), &Options::default()).unwrap();
        assert!(report.notes.is_empty(), "{:?}", report.notes);
    }

    #[test]
    fn refuses_invalid_systems() {
        let f = dense(&[&[0.0, 0.5], &[0.5, 0.0]]);
        let ok_rho = [[0.5; 3]; 2];
        let ok_emit = [[1.0; 3]; 2];
        let ok_area = [1.0; 2];
        let msg = |r: Result<System>| match r {
            Err(Error::Config(m)) => m,
            other => panic!("expected Config, got {other:?}"),
        };
        let m = msg(System::new(&f, &ok_rho[..1], &ok_emit, &ok_area));
        assert!(
            m.contains("rho has 1 entries") && m.contains("2 rows"),
            "{m}"
        );
        let three = [1.0; 3];
        let m = msg(System::new(&f, &ok_rho, &ok_emit, &three));
        assert!(
            m.contains("area has 3 entries") && !m.contains("rho"),
            "{m}"
        );
        let m = msg(System::new(
            &f,
            &[[0.5, 1.0, 0.5], [0.5; 3]],
            &ok_emit,
            &ok_area,
        ));
        assert!(m.contains("patch 0") && m.contains("[0, 1)"), "{m}");
        let m = msg(System::new(
            &f,
            &[[0.5; 3], [0.5, f64::NAN, 0.5]],
            &ok_emit,
            &ok_area,
        ));
        assert!(m.contains("patch 1") && m.contains("not a finite"), "{m}");
        let m = msg(System::new(&f, &[[-0.1; 3], [0.5; 3]], &ok_emit, &ok_area));
        assert!(m.contains("patch 0"), "{m}");
        let m = msg(System::new(
            &f,
            &ok_rho,
            &[[1.0; 3], [f64::INFINITY; 3]],
            &ok_area,
        ));
        assert!(m.contains("patch 1") && m.contains("emit"), "{m}");
        let m = msg(System::new(&f, &ok_rho, &ok_emit, &[1.0, 0.0]));
        assert!(m.contains("patch 1") && m.contains("area"), "{m}");
        let bad = dense(&[&[0.0, f64::NAN], &[0.5, 0.0]]);
        let m = msg(System::new(&bad, &ok_rho, &ok_emit, &ok_area));
        assert!(m.contains("F[0, 1]"), "{m}");
        let rect = dense(&[&[0.0, 0.5, 0.1], &[0.5, 0.0, 0.1]]);
        let m = msg(System::new(&rect, &ok_rho, &ok_emit, &ok_area));
        assert!(m.contains("2x3"), "{m}");
        let csc = f.to_csc();
        let m = msg(System::new(&csc, &ok_rho, &ok_emit, &ok_area));
        assert!(m.contains("CSR"), "{m}");
        let self_loop = dense(&[&[1.2, 0.0], &[0.5, 0.0]]);
        let m = msg(System::new(
            &self_loop,
            &[[0.9; 3], [0.5; 3]],
            &ok_emit,
            &ok_area,
        ));
        assert!(m.contains("patch 0") && m.contains("F_ii"), "{m}");
        // A literal System is checked by the solvers too.
        let sys = System {
            f: &f,
            rho: &ok_rho[..1],
            emit: &ok_emit,
            area: &ok_area,
        };
        for method in Method::ALL {
            assert!(matches!(
                solve(method, &sys, &Options::default()),
                Err(Error::Config(_))
            ));
        }
        assert_eq!(residual(&sys, &ok_emit), f64::INFINITY);
    }

    /// Rows are checked in parallel; the first refused row is the one reported, and the
    /// gain bound names the first patch where it is reached, however the runs fall.
    #[test]
    fn checks_report_the_first_row_whatever_the_threads() {
        let n = 20_000;
        let mut t = crate::matrix::Triplets::new((n, n));
        for i in 0..n {
            t.add_triplet(i, (i + 1) % n, 0.5);
        }
        // Row 6,001 sees itself too much for its reflectance; row 17,000 holds a NaN.
        t.add_triplet(6_001, 6_001, 1.05);
        t.add_triplet(17_000, 3, f64::NAN);
        let f = t.to_csr();
        let rho = vec![[0.5; 3]; n];
        let mut rho_bad = rho.clone();
        rho_bad[6_001] = [0.5, 0.99, 0.5];
        let (emit, area) = (vec![[1.0; 3]; n], vec![1.0; n]);
        for threads in [1, 2, 5] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let m = match System::new(&f, &rho_bad, &emit, &area) {
                    Err(Error::Config(m)) => m,
                    other => panic!("expected Config, got {other:?}"),
                };
                assert!(m.contains("patch 6001") && m.contains("F_ii"), "{m}");
                let m = match System::new(&f, &rho, &emit, &area) {
                    Err(Error::Config(m)) => m,
                    other => panic!("expected Config, got {other:?}"),
                };
                assert!(m.contains("F[17000, 3]"), "{m}");
                // Rows 100 and 15,000 reach the same largest bound; the first is named.
                let mut g = crate::matrix::Triplets::new((n, n));
                for i in 0..n {
                    let v = if i == 100 || i == 15_000 { 0.8 } else { 0.4 };
                    g.add_triplet(i, (i + 1) % n, v);
                }
                let g = g.to_csr();
                let gain = Gain::of_rows(&rho, &Rows::new(&g), 0);
                assert_eq!((gain.patch, gain.row_sum), (100, 0.8), "{threads} threads");
                assert_eq!(gain.gain, [0.4; 3]);
            });
        }
    }

    #[test]
    fn refuses_bad_tolerance() {
        let owned = shelf([0.5; 3], [1.0, 0.0, 0.0]);
        for tolerance in [f64::NAN, -1.0] {
            let opts = Options {
                tolerance,
                ..Options::default()
            };
            for method in Method::ALL {
                assert!(matches!(
                    solve(method, &owned.sys(), &opts),
                    Err(Error::Config(_))
                ));
            }
        }
    }

    #[test]
    fn dark_and_empty_systems() {
        // Nothing emits: B = 0 at once.
        let owned = shelf([0.5; 3], [0.0; 3]);
        for method in Method::ALL {
            let (b, report) = solve(method, &owned.sys(), &Options::default()).unwrap();
            assert!(report.converged && report.iterations == 0);
            assert!(b.iter().flatten().all(|&v| v == 0.0));
        }
        let f = Csr::zero((0, 0));
        let sys = System::new(&f, &[], &[], &[]).unwrap();
        for method in Method::ALL {
            let (b, report) = solve(method, &sys, &Options::default()).unwrap();
            assert!(b.is_empty() && report.converged);
        }
    }

    #[test]
    fn dark_channel_is_measured_against_the_others() {
        let scale = Scale::new(&[[2.0, 0.0, 0.5], [1.0, 0.0, 0.25]]);
        assert_eq!(scale.0, [2.0, 2.0, 0.5]);
        assert_eq!(scale.rel([0.2, 0.1, 0.1]), 0.2);
        assert_eq!(scale.rel([0.0, f64::NAN, 0.0]), f64::INFINITY);
        assert_eq!(Scale::new(&[[0.0; 3]]).0, [1.0; 3]);
    }

    #[test]
    fn method_names_round_trip() {
        for m in Method::ALL {
            assert_eq!(m.name().parse::<Method>().unwrap(), m);
            assert_eq!(m.to_string(), m.name());
            assert_eq!(m.solver().name(), m.name());
        }
        assert_eq!("GS".parse::<Method>().unwrap(), Method::GaussSeidel);
        assert_eq!("LU".parse::<Method>().unwrap(), Method::Direct);
        assert_eq!("SOR".parse::<Method>().unwrap(), Method::Sor);
        assert!(matches!("ssor".parse::<Method>(), Err(Error::Config(m)) if m.contains("cg")));
    }
}
