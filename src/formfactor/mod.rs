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
pub mod far;
pub mod hemicube;
pub mod hemisphere;
pub mod semi;
pub mod shard;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use rayon::prelude::*;

use crate::matrix::{sort_row, CsrBuilder, FormFactors, RowEntries};
pub use crate::matrix::{Entry, Row};
use crate::mesh::PatchSet;
use crate::visibility::Visibility;

pub use area::{AreaMc, Pattern};
pub use hemicube::Hemicube;
pub use hemisphere::Hemisphere;
pub use semi::{Nodes, SemiAnalytic};

/// The estimators, by name: the one list the command line (`--estimator`, through clap's
/// [`clap::ValueEnum`]), the pipeline's configuration and the studies use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum EstimatorKind {
    /// Area-to-area Monte Carlo, independent uniform point pairs.
    Uniform,
    /// Area-to-area Monte Carlo, stratified point pairs.
    Stratified,
    /// Area-to-area randomized QMC: Owen-scrambled Sobol point pairs.
    Sobol,
    /// Hemisphere shooting: samples² cosine-weighted rays per patch and replicate.
    Hemisphere,
    /// Exact point-to-polygon factor over emitter points, times ray-traced visibility.
    Semi,
    /// Hemicube with `--samples` cells per side of the top face (deterministic).
    Hemicube,
}

impl EstimatorKind {
    /// All kinds, in table order.
    pub const ALL: [EstimatorKind; 6] = [
        EstimatorKind::Uniform,
        EstimatorKind::Stratified,
        EstimatorKind::Sobol,
        EstimatorKind::Hemisphere,
        EstimatorKind::Semi,
        EstimatorKind::Hemicube,
    ];

    /// Name in tables, legends and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            EstimatorKind::Uniform => "uniform",
            EstimatorKind::Stratified => "stratified",
            EstimatorKind::Sobol => "sobol",
            EstimatorKind::Hemisphere => "hemisphere",
            EstimatorKind::Semi => "semi",
            EstimatorKind::Hemicube => "hemicube",
        }
    }

    /// True for estimators with randomness (and so error bars worth calibrating).
    pub fn random(self) -> bool {
        self != EstimatorKind::Hemicube
    }
}

/// The unoccluded point-to-point kernel `cos θ_x cos θ_y / (π r²)`, or `None` when the
/// points face away from each other (no ray needed).
#[inline]
pub fn kernel(x: glam::DVec3, n_x: glam::DVec3, y: glam::DVec3, n_y: glam::DVec3) -> Option<f64> {
    let d = y - x;
    let r2 = d.length_squared();
    let cx = n_x.dot(d);
    let cy = -n_y.dot(d);
    if cx <= 0.0 || cy <= 0.0 || r2 <= 0.0 {
        return None;
    }
    Some(cx * cy / (std::f64::consts::PI * r2 * r2))
}

/// Buffers an estimator works in, owned by the row driver: one per worker, lent to every
/// row it computes and kept between rows (no thread-local state in the estimators).
#[derive(Default)]
pub struct Scratch {
    pub(crate) area: area::Scratch,
    pub(crate) hemisphere: hemisphere::Scratch,
    pub(crate) semi: semi::Scratch,
}

/// Everything an estimator may read while computing a row.
pub struct Context<'a> {
    /// The patches.
    pub patches: &'a PatchSet,
    /// Visibility queries over the same patches.
    pub vis: &'a Visibility,
    /// Seed of all random streams.
    pub seed: u64,
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
    /// The most entries a row can hold in a scene of `n` patches (`n` unless the estimator
    /// knows better: hemisphere shooting stores at most one entry per ray), used to
    /// reserve the matrix arrays once.
    fn row_bound(&self, n: usize) -> usize {
        n
    }
    /// Independent replicates behind each standard error (0 for an estimator whose
    /// standard errors are not replicate-based).
    fn replicates(&self) -> usize {
        0
    }
    /// The bar of an entry the estimator did not store, and of the sum of all of a row's
    /// unstored entries ([`FormFactors::unresolved`]): 0 for estimators that look at every
    /// pair; for hemisphere shooting the bar of a fraction of rays no ray hit.
    fn unresolved(&self) -> f64 {
        0.0
    }
    /// Computes row `i` (only `j > i` when [`Estimator::upper_only`]) into `row`, which
    /// arrives cleared, working in the driver's `scratch`.
    fn row(&self, ctx: &Context, i: usize, row: &mut Row, scratch: &mut Scratch);

    /// An estimate of the work of each row of `rows`, in nanoseconds of one core, roughly
    /// (only the ratios between rows matter): what [`shard`] balances when ranks share the
    /// rows. It must be cheap next to the rows themselves (it may run in parallel on the
    /// current pool), and depend on nothing but the inputs (every rank must agree). The
    /// default counts the pairs a row computes (`n - 1 - i` when
    /// [`Estimator::upper_only`], else every row alike): right for the estimators whose
    /// cost per row is fixed (hemisphere shooting, the hemicube).
    fn row_costs(&self, ctx: &Context, rows: std::ops::Range<usize>) -> Vec<f64> {
        let n = ctx.patches.len();
        rows.map(|i| {
            if self.upper_only() {
                (n - 1 - i) as f64
            } else {
                n as f64
            }
        })
        .collect()
    }
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

/// Row `i` into `row` (cleared first), sorted by column so that the assembly only copies;
/// counts it in `done` and reports every 64th row and the last of `n` to `progress`.
fn one_row(
    ctx: &Context,
    est: &dyn Estimator,
    i: usize,
    row: &mut Row,
    scratch: &mut Scratch,
    (done, n, progress): (&AtomicU64, u64, &(dyn Fn(u64) + Sync)),
) {
    row.entries.clear();
    row.rays = 0;
    est.row(ctx, i, row, scratch);
    sort_row(&mut row.entries);
    let d = done.fetch_add(1, Ordering::Relaxed) + 1;
    if d % 64 == 0 || d == n {
        progress(d);
    }
}

/// Computes rows `range` (row indices) in parallel, each row's entries in an exactly
/// sized vector, in the order of `range`.
fn rows_par<I>(
    ctx: &Context,
    est: &dyn Estimator,
    range: I,
    done: &AtomicU64,
    n: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> (Vec<Vec<Entry>>, u64)
where
    I: IntoParallelIterator<Item = usize>,
    I::Iter: IndexedParallelIterator,
{
    let rows: Vec<(Vec<Entry>, u64)> = range
        .into_par_iter()
        .with_min_len(1)
        .map_init(
            || (Row::default(), Scratch::default()),
            |(row, scratch), i| {
                one_row(ctx, est, i, row, scratch, (done, n, progress));
                (row.entries.as_slice().to_vec(), row.rays)
            },
        )
        .collect();
    let rays = rows.iter().map(|r| r.1).sum();
    (rows.into_iter().map(|r| r.0).collect(), rays)
}

/// Scratch buffers lent to the rows' workers and given back when a worker's share of a
/// block ends, so that the next block reuses them: buffers made afresh for each share
/// (the hemisphere's tallies are 16 bytes a patch) were faulted in anew, page by page.
#[derive(Default)]
struct Lender(Mutex<Vec<Scratch>>);

/// Scratch lent by a [`Lender`], given back when dropped.
struct Lent<'a> {
    lender: &'a Lender,
    scratch: Scratch,
}

impl Lender {
    fn lend(&self) -> Lent<'_> {
        let scratch = self.0.lock().map(|mut v| v.pop()).ok().flatten();
        Lent {
            lender: self,
            scratch: scratch.unwrap_or_default(),
        }
    }
}

impl Drop for Lent<'_> {
    fn drop(&mut self) {
        if let Ok(mut v) = self.lender.0.lock() {
            v.push(std::mem::take(&mut self.scratch));
        }
    }
}

/// Computes rows `lo..lo + rows.len()` in parallel into `rows`, whose entry vectors keep
/// their capacity from the block before (no fresh pages for them either), with scratch
/// lent by `lender`; returns the rays cast.
#[allow(clippy::too_many_arguments)]
fn rows_into(
    ctx: &Context,
    est: &dyn Estimator,
    lo: usize,
    rows: &mut [Row],
    lender: &Lender,
    done: &AtomicU64,
    n: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> u64 {
    rows.par_iter_mut()
        .enumerate()
        .with_min_len(1)
        .map_init(
            || lender.lend(),
            |lent, (k, row)| {
                one_row(
                    ctx,
                    est,
                    lo + k,
                    row,
                    &mut lent.scratch,
                    (done, n, progress),
                );
                row.rays
            },
        )
        .sum()
}

/// Makes room in `csr` for the block `rows` (rows `lo..` of `n`), reserving for the rest
/// of the matrix at once so that the arrays seldom grow: a growth copies every entry so
/// far and holds both copies at the peak (at 256k patches that was 18 s and a third more
/// memory). A matrix of one block takes exactly its entries. After the first block of
/// several: the estimator's bound on the whole matrix, `n * bound`
/// entries, when that is within 4 times the first block's density (address space that is
/// reserved but never written costs no memory) and the system grants it; else that
/// density plus 10%. A later block that does not fit reserves for the remaining rows at
/// the density so far plus 25%.
fn reserve<R: RowEntries>(csr: &mut CsrBuilder, rows: &[R], lo: usize, n: usize, bound: usize) {
    let nnz: usize = rows.iter().map(R::len).sum();
    let done = lo + rows.len();
    if lo == 0 && done == n {
        csr.reserve_exact(nnz);
    } else if lo == 0 {
        let expected = nnz as f64 * n as f64 / rows.len().max(1) as f64;
        let most = n as f64 * bound as f64;
        if most <= 4.0 * expected && csr.try_reserve_exact(most as usize).is_ok() {
            return;
        }
        csr.reserve_exact(((expected * 1.1) as usize).max(nnz));
    } else if csr.spare() < nnz {
        let so_far = csr.len() + nnz;
        let rest = (so_far as f64 / done as f64 * (n - done) as f64 * 1.25) as usize;
        csr.reserve_exact(nnz + rest);
    }
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
        let mut block = vec![Row::default(); BLOCK_ROWS.min(n)];
        let lender = Lender::default();
        for lo in (0..n).step_by(BLOCK_ROWS) {
            let t = Instant::now();
            let rows = &mut block[..BLOCK_ROWS.min(n - lo)];
            rays += rows_into(ctx, est, lo, rows, &lender, &done, n as u64, progress);
            split.rows += t.elapsed().as_secs_f64();
            let t = Instant::now();
            reserve(&mut csr, rows, lo, n, est.row_bound(n).min(n));
            csr.push_rows(rows);
            split.assembly += t.elapsed().as_secs_f64();
        }
    }
    let mut ff = csr.finish(
        area.clone(),
        rays,
        split.rows + split.assembly,
        est.name(),
        ctx.seed,
    );
    ff.replicates = est.replicates();
    ff.unresolved = est.unresolved();
    (ff, split)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{PatchSet, Resolution};
    use crate::scene::Scene;

    /// Rows of `short` entries in the first block and `long` ones after it.
    struct Uneven {
        short: usize,
        long: usize,
    }

    impl Estimator for Uneven {
        fn name(&self) -> String {
            "uneven".into()
        }
        fn row(&self, ctx: &Context, i: usize, row: &mut Row, _: &mut Scratch) {
            let k = if i < BLOCK_ROWS {
                self.short
            } else {
                self.long
            };
            let n = ctx.patches.len();
            for c in 0..k {
                let j = (i * 7 + c * 13) % n;
                row.entries.push(Entry {
                    j: j as u32,
                    f: (i + 1) as f64 / (j + 2) as f64,
                    se: c as f64,
                });
            }
        }
    }

    /// Matrices of several blocks come out the same as rows assembled one by one, whether
    /// the first block's density reserves for the whole matrix (hemisphere shooting, whose
    /// rows are bounded) or the arrays must grow after it (a first block far sparser than
    /// the rest): the blocked, reserved assembly changes nothing but the memory it takes.
    #[test]
    fn blocked_assembly_matches_row_by_row() {
        let scene = Scene::load("cube").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(1.0 / 20.0)).unwrap();
        let n = patches.len();
        assert!(n > 2 * BLOCK_ROWS, "{n}");
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 3,
        };
        let hemi = Hemisphere {
            strata: 4,
            replicates: 2,
        };
        let uneven = Uneven { short: 2, long: 40 };
        for est in [&hemi as &dyn Estimator, &uneven] {
            let ff = compute(&ctx, est, &|_| {});
            let rows: Vec<Vec<Entry>> = (0..n)
                .map(|i| {
                    let mut row = Row::default();
                    est.row(&ctx, i, &mut row, &mut Scratch::default());
                    row.entries
                })
                .collect();
            let reference =
                FormFactors::from_rows(rows, patches.area.clone(), ff.rays, 0.0, est.name(), 3);
            assert_eq!(ff.f, reference.f, "{}", est.name());
            assert_eq!(ff.se, reference.se, "{}", est.name());
            assert!(ff.f.nnz() > n);
        }
    }
}
