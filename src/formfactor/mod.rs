//! Form factors: the [`Estimator`] trait and the parallel row driver.
//!
//! The form factor from patch i to patch j (radiosidade.md, "Fator de Forma"; Cohen and
//! Wallace 1993, eq. 4.13) is
//!
//! `F_ij = 1/A_i ∫_{A_i} ∫_{A_j} cos(θ_x) cos(θ_y) V(x, y) / (π r²) dA_y dA_x`.
//!
//! The driver owns the loop (pbrt-v4 and Mitsuba 3 keep the parallel loop out of the
//! integrator): rows run in parallel with rayon, and an estimator only answers "row i".
//! Estimators that sample each unordered pair once, symmetrically, declare
//! [`Estimator::upper_only`]; the driver then asks only for `j > i` and fills the lower
//! triangle by reciprocity (`A_j F_ji = A_i F_ij`), which halves the rays and makes the
//! matrix reciprocal by construction.

pub mod area;
pub mod exact;
pub mod hemicube;
pub mod hemisphere;
pub mod semi;

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::matrix::{sort_row, CsrBuilder, FormFactors};
use crate::mesh::PatchSet;
use crate::visibility::Visibility;

pub use area::{AreaMc, Pattern};
pub use hemicube::Hemicube;
pub use hemisphere::Hemisphere;
pub use semi::{Nodes, SemiAnalytic};

/// Everything an estimator may read while computing a row.
pub struct Context<'a> {
    /// The patches.
    pub patches: &'a PatchSet,
    /// Visibility queries over the same patches.
    pub vis: &'a Visibility,
    /// Seed of all random streams.
    pub seed: u64,
}

/// One estimated entry of a row: `F_ij` and its standard error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    /// Column (receiving patch).
    pub j: u32,
    /// Estimated form factor.
    pub f: f64,
    /// Standard error of the estimate (0 when exact).
    pub se: f64,
}

/// A row being computed, reused between rows on the same thread.
#[derive(Clone, Debug, Default)]
pub struct Row {
    /// Non-zero entries (any order).
    pub entries: Vec<Entry>,
    /// Rays cast for this row.
    pub rays: u64,
}

/// A way of estimating one row of the form-factor matrix.
pub trait Estimator: Sync {
    /// Short name, used in reports and file provenance.
    fn name(&self) -> String;
    /// True when the estimator samples unordered pairs symmetrically: the driver asks for
    /// `j > i` only and mirrors by reciprocity.
    fn upper_only(&self) -> bool {
        false
    }
    /// Computes row `i` (only `j > i` when [`Estimator::upper_only`]) into `row`, which
    /// arrives cleared.
    fn row(&self, ctx: &Context, i: usize, row: &mut Row);
}

/// Rows computed in parallel per block before they are appended to the CSR arrays (and
/// freed), for estimators that are not [`Estimator::upper_only`]: bounds the memory held
/// in per-row vectors, and lets the next block reuse it: fresh pages, which the kernel
/// zeroes on first touch, were 22% of the 32 x 32 cube's stage profile with blocks of 8192
/// rows and 10% with 1024.
pub const BLOCK_ROWS: usize = 1024;

/// Wall-clock split of [`compute_timed`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Split {
    /// Seconds spent computing rows (rays, sampling, per-row tallies).
    pub rows: f64,
    /// Seconds spent mirroring and assembling rows into CSR.
    pub assembly: f64,
}

/// Computes the whole matrix with `est`, calling `progress(rows_done)` now and then.
pub fn compute(ctx: &Context, est: &dyn Estimator, progress: &(dyn Fn(u64) + Sync)) -> FormFactors {
    compute_timed(ctx, est, progress).0
}

/// Computes rows `range` in parallel, each row's entries in an exactly sized vector.
fn rows_par(
    ctx: &Context,
    est: &dyn Estimator,
    range: std::ops::Range<usize>,
    done: &AtomicU64,
    n: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> (Vec<Vec<Entry>>, u64) {
    let rows: Vec<(Vec<Entry>, u64)> = range
        .into_par_iter()
        .with_min_len(1)
        .map_init(Row::default, |row, i| {
            row.entries.clear();
            row.rays = 0;
            est.row(ctx, i, row);
            // Sorted here, in parallel, so that the assembly only copies.
            sort_row(&mut row.entries);
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            if d % 64 == 0 || d == n {
                progress(d);
            }
            (row.entries.as_slice().to_vec(), row.rays)
        })
        .collect();
    let rays = rows.iter().map(|r| r.1).sum();
    (rows.into_iter().map(|r| r.0).collect(), rays)
}

/// [`compute`], also reporting how long rows and assembly took.
pub fn compute_timed(
    ctx: &Context,
    est: &dyn Estimator,
    progress: &(dyn Fn(u64) + Sync),
) -> (FormFactors, Split) {
    let n = ctx.patches.len();
    let done = AtomicU64::new(0);
    let area = &ctx.patches.area;
    let mut split = Split::default();
    let mut rays = 0u64;
    let mut csr;
    if est.upper_only() {
        let t = Instant::now();
        let (rows, r) = rows_par(ctx, est, 0..n, &done, n as u64, progress);
        rays = r;
        split.rows = t.elapsed().as_secs_f64();
        let t = Instant::now();
        csr = CsrBuilder::from_upper(&rows, area);
        drop(rows);
        split.assembly = t.elapsed().as_secs_f64();
    } else {
        csr = CsrBuilder::with_capacity(n, 0);
        for lo in (0..n).step_by(BLOCK_ROWS) {
            let t = Instant::now();
            let (rows, r) = rows_par(
                ctx,
                est,
                lo..(lo + BLOCK_ROWS).min(n),
                &done,
                n as u64,
                progress,
            );
            rays += r;
            split.rows += t.elapsed().as_secs_f64();
            let t = Instant::now();
            if lo == 0 && rows.len() < n {
                // Room for the whole matrix at the first block's density (plus 10%), so
                // that the arrays do not grow by repeated doubling and copying.
                let nnz: usize = rows.iter().map(Vec::len).sum();
                csr.reserve(nnz * n / rows.len() * 11 / 10);
            }
            csr.push_rows(&rows);
            drop(rows);
            split.assembly += t.elapsed().as_secs_f64();
        }
    }
    let ff = csr.finish(
        area.clone(),
        rays,
        split.rows + split.assembly,
        est.name(),
        ctx.seed,
    );
    (ff, split)
}
