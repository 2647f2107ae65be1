//! The form-factor matrix: rows assembled into a `sprs` CSR matrix, with per-entry
//! standard errors and the physical diagnostics (row sums, reciprocity).
//!
//! Properties checked (radiosidade.md, "Teorema da Reciprocidade"): in a closed
//! environment every row sums to 1, and `A_i F_ij = A_j F_ji`.
//!
//! Error bars ([`Bar`]): every stored factor carries one bar, either a standard error (the
//! random part of an estimate: replicates' spread, ray counts) or a deterministic bound (a
//! quadrature's checked error plus rounding). They combine differently in sums of factors
//! (row sums, surface sums): standard errors of independent estimates in quadrature,
//! bounds linearly (the triangle inequality), and they are reported apart.
//!
//! Repair ([`repair_row_sums`]): a Monte Carlo row may sum above 1 by noise; when
//! `rho_i * sum_j F_ij >= 1` somewhere, the bound that guarantees a bounded, convergent solve
//! is lost (Cohen and Wallace 1993, §5.3), so the pipeline scales those rows to sum to 1.

use rayon::prelude::*;
use sprs::{CsMatI, TriMatI};

/// One estimated entry of a row: `F_ij` and its error bar.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    /// Column (receiving patch).
    pub j: u32,
    /// Estimated form factor.
    pub f: f64,
    /// The error bar in its stored form ([`Bar::stored`]): a standard error (sign bit
    /// clear; 0 when exact) or, with the sign bit set, a deterministic bound of magnitude
    /// `|se|`. Read it through [`Bar::of`].
    pub se: f64,
}

/// A row's entries in column order, however they are held: a vector of [`Entry`], or
/// the bytes another rank sent (`crate::formfactor::shard`). What the assembly
/// ([`CsrBuilder::from_upper`], [`CsrBuilder::push_rows`]) reads, so that rows that
/// arrive as bytes are copied into the matrix once, not first into vectors.
pub trait RowEntries: Sync {
    /// Number of entries.
    fn len(&self) -> usize;
    /// Entry `k` (`k < len`).
    fn at(&self, k: usize) -> Entry;
    /// True without entries.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The first entry whose column is at least `j` (`len` when none is).
    fn first_from(&self, j: usize) -> usize {
        let (mut lo, mut hi) = (0, self.len());
        while lo < hi {
            let mid = (lo + hi) / 2;
            if (self.at(mid).j as usize) < j {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        lo
    }
}

impl RowEntries for Row {
    fn len(&self) -> usize {
        self.entries.len()
    }
    fn at(&self, k: usize) -> Entry {
        self.entries[k]
    }
    fn first_from(&self, j: usize) -> usize {
        self.entries.first_from(j)
    }
}

impl RowEntries for Vec<Entry> {
    fn len(&self) -> usize {
        Vec::len(self)
    }
    fn at(&self, k: usize) -> Entry {
        self[k]
    }
    fn first_from(&self, j: usize) -> usize {
        self.partition_point(|e| (e.j as usize) < j)
    }
}

impl Entry {
    /// An entry whose error is deterministic, bounded by `bound` (>= 0).
    pub fn bounded(j: u32, f: f64, bound: f64) -> Entry {
        Entry {
            j,
            f,
            se: Bar::bound(bound).stored(),
        }
    }

    /// The entry's bar.
    pub fn bar(&self) -> Bar {
        Bar::of(self.se)
    }
}

/// The error bar of a factor, or of a sum of factors: a standard error `se` for the random
/// part and a bound `bound` for the deterministic part.
///
/// - A **standard error** belongs to a random estimate (replicates, ray counts); errors of
///   independent estimates add in quadrature, `se(Σ x_k)² = Σ se(x_k)²`.
/// - A **bound** belongs to a deterministic computation (the semi-analytic estimator's
///   quadrature of unoccluded pairs: the a-posteriori check's error estimate plus a rounding
///   term, [`crate::formfactor::exact`]); its error has no distribution and no reason to
///   cancel, so bounds add linearly, `|Σ e_k| <= Σ |e_k|` (the triangle inequality), and are
///   not divided by a count of replicates.
///
/// A value is within `k` bars of the truth when `|x - truth| <= k se + bound`
/// ([`Bar::allowance`]): `k` multiplies only the random part.
///
/// Stored (one `f32` per factor in [`FormFactors::se`], one `f64` in [`Entry::se`]) a bar
/// holds one part, told by the sign bit: clear, a standard error; set, a bound of the
/// value's magnitude. On disk they are two files of the same pattern, `stderr.mtx` and
/// `bound.mtx` ([`crate::store`]). A bar with both parts (a sum, or a repair mixing a
/// bounded entry with a random one) is stored as the standard error `hypot(se, bound)`,
/// which allows at least as much as `k se + bound` whenever `k >= 1`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Bar {
    /// Standard error of the random part.
    pub se: f64,
    /// Bound on the absolute deterministic error.
    pub bound: f64,
}

impl Bar {
    /// No error (an exact value, or one whose error is not known: the hemicube's).
    pub const ZERO: Bar = Bar {
        se: 0.0,
        bound: 0.0,
    };

    /// A standard error alone.
    pub fn se(se: f64) -> Bar {
        Bar { se, bound: 0.0 }
    }

    /// A bound alone.
    pub fn bound(bound: f64) -> Bar {
        Bar { se: 0.0, bound }
    }

    /// Reads a stored bar (sign bit set: a bound).
    pub fn of(stored: impl Into<f64>) -> Bar {
        let s: f64 = stored.into();
        if s.is_sign_negative() {
            Bar::bound(-s)
        } else {
            Bar::se(s)
        }
    }

    /// The stored form: `se` (sign bit clear), `-bound` (sign bit set), or for a bar with
    /// both parts the standard error `hypot(se, bound)`.
    pub fn stored(self) -> f64 {
        if self.bound == 0.0 {
            self.se
        } else if self.se == 0.0 {
            -self.bound
        } else {
            self.se.hypot(self.bound)
        }
    }

    /// The stored form as `f32` (a standard error to nearest; a bound rounded up in
    /// magnitude, so that it stays a bound).
    pub fn stored_f32(self) -> f32 {
        let s = self.stored();
        let r = s as f32;
        if s.is_sign_negative() && f64::from(r).abs() < s.abs() && r.is_finite() {
            // One step away from zero.
            f32::from_bits(r.to_bits() + 1)
        } else {
            r
        }
    }

    /// The bar of the sum of two independent errors: standard errors in quadrature, bounds
    /// linearly.
    pub fn plus(self, o: Bar) -> Bar {
        // `hypot(x, 0) = |x|` exactly: a sum with a bar that has no random part (the
        // reciprocity check of a pair stored one way) skips the library call.
        let se = if o.se == 0.0 {
            self.se.abs()
        } else if self.se == 0.0 {
            o.se.abs()
        } else {
            self.se.hypot(o.se)
        };
        Bar {
            se,
            bound: self.bound + o.bound,
        }
    }

    /// The bar of `s` times the value (`|s|` scales both parts).
    pub fn times(self, s: f64) -> Bar {
        Bar {
            se: self.se * s.abs(),
            bound: self.bound * s.abs(),
        }
    }

    /// How far a value may be from the truth at `k` standard errors: `k se + bound`.
    pub fn allowance(self, k: f64) -> f64 {
        k * self.se + self.bound
    }

    /// One number for weights and for readers that know a single bar:
    /// `hypot(se, bound)` (as [`Bar::stored`] keeps a bar with both parts).
    pub fn magnitude(self) -> f64 {
        self.se.hypot(self.bound)
    }

    /// Each part's larger (for "the largest bar" of a set).
    pub fn max(self, o: Bar) -> Bar {
        Bar {
            se: self.se.max(o.se),
            bound: self.bound.max(o.bound),
        }
    }

    /// True when neither part is NaN, infinite or negative.
    pub fn is_valid(self) -> bool {
        self.se.is_finite() && self.bound.is_finite() && self.se >= 0.0 && self.bound >= 0.0
    }
}

/// `± 1.2e-3 (s.e.)`, `± 4.0e-9 (bound)`, `± 1.2e-3 (s.e.) + 4.0e-9 (bound)`, or `± 0`: the
/// one way summaries print a bar, saying which part is which.
impl std::fmt::Display for Bar {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.se > 0.0, self.bound > 0.0) {
            (false, false) => write!(f, "± 0"),
            (true, false) => write!(f, "± {:.1e} (s.e.)", self.se),
            (false, true) => write!(f, "± {:.1e} (bound)", self.bound),
            (true, true) => write!(f, "± {:.1e} (s.e.) + {:.1e} (bound)", self.se, self.bound),
        }
    }
}

impl std::iter::Sum for Bar {
    fn sum<I: Iterator<Item = Bar>>(it: I) -> Bar {
        let (v, b) = it.fold((0.0, 0.0), |(v, b), x| (v + x.se * x.se, b + x.bound));
        Bar {
            se: v.sqrt(),
            bound: b,
        }
    }
}

/// The bar of the sum of stored bars `bars` (one row's, or any set of independent
/// entries'): standard errors in quadrature, bounds linearly. The one definition every
/// row-sum and surface-sum check uses.
pub fn sum_bar(bars: &[f32]) -> Bar {
    bars.iter().map(|&s| Bar::of(s)).sum()
}

/// A row being computed, reused between rows on the same thread.
#[derive(Clone, Debug, Default)]
pub struct Row {
    /// Non-zero entries (any order).
    pub entries: Vec<Entry>,
    /// Rays cast for this row.
    pub rays: u64,
}

/// True when a row sum `sum` with the bar `bar` ([`sum_bar`] of its entries) is over 1 by
/// more than `k` standard errors plus its bound ([`Bar::allowance`]), and by more than
/// `1e-9` (rounding of rows whose bar is 0, such as the hemicube's): the one definition of
/// a row "over one" that the diagnostics ([`Diagnostics::rows_over_one`], `k = 3`), the
/// repair's bounds ([`crate::repair::Bounds::significant`]), the refusal
/// ([`FormFactors::row_over_one_beyond_chance`]) and the thermal and hierarchy checks use.
/// A physical row sums to at most 1.
pub fn over_one(sum: f64, bar: Bar, k: f64) -> bool {
    sum > 1.0 + bar.allowance(k).max(1e-9)
}

/// Family-wise false-alarm rate of [`FormFactors::row_over_one_beyond_chance`]: an honest
/// matrix is refused with at most this probability, whatever its size.
pub const ROW_ALARM: f64 = 1e-3;

/// A row found over 1 by more than its bar allows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowExcess {
    /// The row (emitting patch).
    pub row: usize,
    /// Its sum.
    pub sum: f64,
    /// Standard error of the sum (random part).
    pub se: f64,
    /// Bound of the sum's deterministic part (bounds added linearly).
    pub bound: f64,
    /// Degrees of freedom of that standard error (Welch–Satterthwaite; infinite when every
    /// entry is exact).
    pub dof: f64,
    /// The multiple of `se` the sum was allowed above 1 (besides `bound`).
    pub k: f64,
}

/// The one-sided Student-t quantile `t` with `P(T > t) = tail` for `dof` degrees of
/// freedom (the normal quantile when `dof` is infinite).
fn t_quantile(tail: f64, dof: f64) -> f64 {
    use statrs::distribution::{ContinuousCDF, Normal, StudentsT};
    if dof.is_finite() {
        StudentsT::new(0.0, 1.0, dof)
            .map(|t| t.inverse_cdf(1.0 - tail))
            .unwrap_or(f64::INFINITY)
    } else {
        Normal::standard().inverse_cdf(1.0 - tail)
    }
}

/// What [`repair_row_sums`] changed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RowRepair {
    /// Rows scaled down to sum to 1.
    pub rows: Vec<usize>,
    /// The largest `rho_i * sum_j F_ij` before the repair (largest channel).
    pub worst_gain: f64,
    /// The patch where it was reached, and its row sum.
    pub worst: (usize, f64),
}

/// Scales to sum 1 every row `i` of `f` with `rho_i * sum_j F_ij >= 1` in some channel (a row
/// of a physical `F` sums to at most 1, so only noise or a broken estimate can do this), and
/// returns the repaired copy, or `None` when no row needs it. After the repair
/// `max_i rho_i sum_j |F_ij| <= max rho < 1`, which bounds the spectral radius of
/// `diag(rho) F` below 1: every solver converges and `B` stays bounded.
pub fn repair_row_sums(f: &Csr, rho: &[[f64; 3]]) -> Option<(Csr, RowRepair)> {
    repair_rows_from(f, rho, 0)
}

/// [`repair_row_sums`] for rows `lo..` of a matrix held as `f` (its row `r` is the
/// matrix's row `lo + r`; `rho` of every patch): the report names the matrix's rows.
pub fn repair_rows_from(f: &Csr, rho: &[[f64; 3]], lo: usize) -> Option<(Csr, RowRepair)> {
    let mut rep = RowRepair::default();
    let mut scale = vec![1.0; f.rows()];
    // The sums in parallel (a pass over the whole matrix), the rest in row order.
    let (ptr, val) = (f.indptr(), f.data());
    let sums: Vec<f64> = (0..f.rows())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .map(|r| val[ptr.index(r)..ptr.index(r + 1)].iter().sum())
        .collect();
    for (r, &sum) in sums.iter().enumerate() {
        let i = lo + r;
        let rho_i = rho.get(i).map_or(0.0, |r| r[0].max(r[1]).max(r[2]));
        let gain = rho_i * sum;
        if gain > rep.worst_gain {
            rep.worst_gain = gain;
            rep.worst = (i, sum);
        }
        if gain >= 1.0 && sum > 0.0 {
            rep.rows.push(i);
            scale[r] = 1.0 / sum;
        }
    }
    if rep.rows.is_empty() {
        return None;
    }
    let mut g = f.clone();
    let ptr = g.indptr().to_proper().into_owned();
    let data = g.data_mut();
    for (i, s) in scale.iter().enumerate() {
        data[ptr[i]..ptr[i + 1]].iter_mut().for_each(|v| *v *= s);
    }
    Some((g, rep))
}

/// Fewest rows a thread takes at a time in the parallel checks over a matrix's rows (row
/// sums, ranges, the solver's checks: each row a few hundred additions).
pub(crate) const ROWS_PER_TASK: usize = 1024;

/// Sorts a row's entries by column and merges duplicates (adding values, and bars as
/// [`Bar::plus`]; the built-in estimators never make duplicates).
pub fn sort_row(row: &mut Vec<Entry>) {
    row.sort_unstable_by_key(|e| e.j);
    row.dedup_by(|b, a| {
        if a.j == b.j {
            a.f += b.f;
            a.se = a.bar().plus(b.bar()).stored();
            true
        } else {
            false
        }
    });
}

/// Grows `v` to `len` zeros; a first allocation is zeroed by the allocator (`calloc`), so its
/// pages are first touched by the parallel copy that fills them, not by a serial memset.
fn grow<T: Clone + Default>(v: &mut Vec<T>, len: usize) {
    if v.is_empty() {
        *v = vec![T::default(); len];
    } else {
        v.resize(len, T::default());
    }
}

/// Most destination rows [`CsrBuilder::from_upper`] fills in one block: each source row
/// scatters one mirrored entry into each of them, so a block is `3 x MIRROR_BLOCK` write
/// streams (columns, values, bars) that stay in cache. On the 32 x 32 cube (6,144
/// patches) 128 took the assembly from 1.79 s to 1.66 s on one thread and from 1.10 s to
/// 0.92 s on two (`n / 8` rows a block before: 768); the cost, one binary search per
/// source row and block, is small beside the `O(n^2)` pairs of the estimators that
/// compute each pair once.
const MIRROR_BLOCK: usize = 128;

/// The CSR storage of `F`: `f64` values, `u32` column indices (a scene has at most
/// `u32::MAX / 4` patches), `usize` row pointers. With the `f32` standard errors of
/// [`FormFactors::se`], 16 bytes per stored factor.
pub type Csr = CsMatI<f64, u32, usize>;

/// Triplets that convert to a [`Csr`] (`.to_csr()`).
pub type Triplets = TriMatI<f64, u32>;

/// A form-factor matrix and how it was made.
#[derive(Clone, Debug)]
pub struct FormFactors {
    /// `F[i, j]`: fraction of the energy leaving patch i that arrives at patch j (CSR).
    pub f: Csr,
    /// Standard error of each stored entry, aligned with `f.data()` (`f32`: an error bar
    /// needs no more than 7 digits).
    pub se: Vec<f32>,
    /// Patch areas.
    pub area: Vec<f64>,
    /// Rays cast.
    pub rays: u64,
    /// Wall-clock seconds of the estimation.
    pub seconds: f64,
    /// Estimator name.
    pub estimator: String,
    /// Seed of the random streams.
    pub seed: u64,
    /// Independent replicates behind each standard error (0 when not known: the checks
    /// then assume the fewest, 2).
    pub replicates: usize,
    /// The standard error of any entry that is not stored, and of the sum of a row's
    /// unstored entries: 0 for estimators that decide every pair; for hemisphere shooting
    /// the bar of a fraction no ray hit ([`crate::formfactor::Estimator::unresolved`]).
    /// One-sided: the true value is `>= 0`, the estimate 0.
    pub unresolved: f64,
}

/// Form factors at least this large count as significant for the reciprocity figure.
pub const SIGNIFICANT: f64 = 1e-3;

/// Which stored pairs [`FormFactors::diagnostics_with`] checks for reciprocity (also the
/// command line's `--reciprocity` values). Row sums and ranges are always checked on every
/// row. The check of every pair reads the whole matrix once per block of a few thousand
/// rows: at 300,000 patches it took as much CPU time as the solve, where
/// [`RECIPROCITY_SAMPLE`] pairs take a fifth of it (`docs/PERFORMANCE.md`, section 1).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Reciprocity {
    /// Every pair of a matrix of up to 2^23 (8.4 million) stored factors; of a larger one,
    /// the pairs of every m-th row, m such that they hold about that many.
    #[default]
    Auto,
    /// Every stored pair, whatever the matrix's size.
    All,
}

/// Stored factors up to which [`Reciprocity::Auto`] checks every pair, and about how many
/// of a larger matrix's it checks.
pub const RECIPROCITY_SAMPLE: usize = 1 << 23;

/// Builds the CSR arrays a row or a block of rows at a time, so that rows can be freed as
/// they are added (no dense `N x N` anything, and no second copy of the whole matrix).
/// Blocks of rows ([`CsrBuilder::push_rows`], [`CsrBuilder::from_upper`]) are copied in
/// parallel, each row into its own slice of the arrays: with several threads the
/// assembly is no serial tail after the parallel rows.
#[derive(Debug, Default)]
pub struct CsrBuilder {
    indptr: Vec<usize>,
    indices: Vec<u32>,
    data: Vec<f64>,
    se: Vec<f32>,
}

impl CsrBuilder {
    /// A builder with room for `rows` rows and `nnz` entries (0 when unknown).
    pub fn with_capacity(rows: usize, nnz: usize) -> CsrBuilder {
        let mut indptr = Vec::with_capacity(rows + 1);
        indptr.push(0);
        CsrBuilder {
            indptr,
            indices: Vec::with_capacity(nnz),
            data: Vec::with_capacity(nnz),
            se: Vec::with_capacity(nnz),
        }
    }

    /// Room for `additional` more entries (amortized growth).
    pub fn reserve(&mut self, additional: usize) {
        self.indices.reserve(additional);
        self.data.reserve(additional);
        self.se.reserve(additional);
    }

    /// Room for exactly `additional` more entries.
    pub fn reserve_exact(&mut self, additional: usize) {
        self.indices.reserve_exact(additional);
        self.data.reserve_exact(additional);
        self.se.reserve_exact(additional);
    }

    /// [`CsrBuilder::reserve_exact`], or an error (and no change in capacity that matters)
    /// when the allocator refuses.
    pub fn try_reserve_exact(
        &mut self,
        additional: usize,
    ) -> Result<(), std::collections::TryReserveError> {
        self.indices.try_reserve_exact(additional)?;
        self.data.try_reserve_exact(additional)?;
        self.se.try_reserve_exact(additional)
    }

    /// Entries pushed so far.
    pub fn len(&self) -> usize {
        self.indices.len()
    }

    /// True before the first entry.
    pub fn is_empty(&self) -> bool {
        self.indices.is_empty()
    }

    /// Entries that fit before the arrays must grow.
    pub fn spare(&self) -> usize {
        let cap = self.indices.capacity().min(self.data.capacity());
        cap.min(self.se.capacity()) - self.indices.len()
    }

    /// Appends the next row (entries in any order; duplicates are merged).
    pub fn push_row(&mut self, row: &mut Vec<Entry>) {
        sort_row(row);
        for e in row.iter() {
            self.indices.push(e.j);
            self.data.push(e.f);
            self.se.push(Bar::of(e.se).stored_f32());
        }
        self.indptr.push(self.indices.len());
    }

    /// Appends the rows of a block, each already in column order without duplicates (as
    /// [`sort_row`] leaves it), copying them in parallel on the current rayon pool straight
    /// into the arrays' spare capacity (no zero fill first: the pages are first touched by
    /// the threads that fill them).
    #[allow(unsafe_code)]
    pub fn push_rows<R: RowEntries>(&mut self, rows: &[R]) {
        debug_assert!(rows
            .iter()
            .all(|r| (1..r.len()).all(|k| r.at(k - 1).j < r.at(k).j)));
        let base = self.indices.len();
        let nnz: usize = rows.iter().map(R::len).sum();
        self.reserve(nnz);
        let mut end = base;
        for r in rows {
            end += r.len();
            self.indptr.push(end);
        }
        let mut ix = &mut self.indices.spare_capacity_mut()[..nnz];
        let mut dx = &mut self.data.spare_capacity_mut()[..nnz];
        let mut sx = &mut self.se.spare_capacity_mut()[..nnz];
        let mut parts = Vec::with_capacity(rows.len());
        for r in rows {
            let (a, rest) = std::mem::take(&mut ix).split_at_mut(r.len());
            ix = rest;
            let (b, rest) = std::mem::take(&mut dx).split_at_mut(r.len());
            dx = rest;
            let (c, rest) = std::mem::take(&mut sx).split_at_mut(r.len());
            sx = rest;
            parts.push((r, a, b, c));
        }
        parts.into_par_iter().for_each(|(r, ix, dx, sx)| {
            for k in 0..r.len() {
                let e = r.at(k);
                ix[k].write(e.j);
                dx[k].write(e.f);
                sx[k].write(Bar::of(e.se).stored_f32());
            }
        });
        // SAFETY: the `nnz` slots after `base` of each array were all written just above
        // (the rows' slices partition them), and `reserve` made room for them.
        unsafe {
            self.indices.set_len(base + nnz);
            self.data.set_len(base + nnz);
            self.se.set_len(base + nnz);
        }
    }

    /// The whole matrix from its upper triangle: `rows[i]` holds the entries `F_ij` with
    /// `j > i` (column order, no duplicates), and the lower triangle follows by reciprocity,
    /// `F_ji = F_ij A_i / A_j` (radiosidade.md, "Teorema da Reciprocidade"), with the
    /// standard error scaled alike. Rows are filled in parallel over blocks of destination
    /// rows; each block gathers its mirrored entries from the source rows in row order, so
    /// every row comes out sorted.
    pub fn from_upper<R: RowEntries>(rows: &[R], area: &[f64]) -> CsrBuilder {
        let n = rows.len();
        debug_assert!(rows.iter().enumerate().all(|(i, r)| {
            (1..r.len()).all(|k| r.at(k - 1).j < r.at(k).j)
                && (0..r.len()).all(|k| r.at(k).j as usize > i)
        }));
        let mut lower = vec![0usize; n];
        for r in rows {
            for k in 0..r.len() {
                lower[r.at(k).j as usize] += 1;
            }
        }
        let mut indptr = Vec::with_capacity(n + 1);
        indptr.push(0);
        for (r, l) in rows.iter().zip(&lower) {
            indptr.push(indptr.last().copied().unwrap_or(0) + r.len() + l);
        }
        let nnz = indptr[n];
        let (mut indices, mut data, mut se) = (Vec::new(), Vec::new(), Vec::new());
        grow(&mut indices, nnz);
        grow(&mut data, nnz);
        grow(&mut se, nnz);
        // Blocks of destination rows, a few per thread and at most MIRROR_BLOCK, each with
        // its slices of the arrays.
        let step = n
            .div_ceil(4 * rayon::current_num_threads())
            .clamp(1, MIRROR_BLOCK);
        let (mut ix, mut dx, mut sx) = (&mut indices[..], &mut data[..], &mut se[..]);
        let mut blocks = Vec::new();
        for j0 in (0..n).step_by(step) {
            let j1 = (j0 + step).min(n);
            let len = indptr[j1] - indptr[j0];
            let (a, rest) = std::mem::take(&mut ix).split_at_mut(len);
            ix = rest;
            let (b, rest) = std::mem::take(&mut dx).split_at_mut(len);
            dx = rest;
            let (c, rest) = std::mem::take(&mut sx).split_at_mut(len);
            sx = rest;
            blocks.push((j0, j1, a, b, c));
        }
        let indptr_ref = &indptr;
        blocks.into_par_iter().for_each(|(j0, j1, ix, dx, sx)| {
            let off = indptr_ref[j0];
            let mut cursor: Vec<usize> = (j0..j1).map(|j| indptr_ref[j] - off).collect();
            // Mirrored entries: source rows i < j1 with columns in [j0, j1), in row order.
            for (i, r) in rows[..j1].iter().enumerate() {
                for e in (r.first_from(j0)..r.len())
                    .map(|k| r.at(k))
                    .take_while(|e| (e.j as usize) < j1)
                {
                    let j = e.j as usize;
                    let s = area[i] / area[j];
                    let p = &mut cursor[j - j0];
                    (ix[*p], dx[*p], sx[*p]) = (i as u32, e.f * s, Bar::of(e.se * s).stored_f32());
                    *p += 1;
                }
            }
            // Then each row's own upper part.
            for (j, p) in (j0..j1).zip(cursor) {
                let r = &rows[j];
                for k in 0..r.len() {
                    let e = r.at(k);
                    (ix[p + k], dx[p + k], sx[p + k]) = (e.j, e.f, Bar::of(e.se).stored_f32());
                }
            }
        });
        CsrBuilder {
            indptr,
            indices,
            data,
            se,
        }
    }

    /// The finished matrix (square, one column per row pushed).
    pub fn finish(
        self,
        area: Vec<f64>,
        rays: u64,
        seconds: f64,
        estimator: String,
        seed: u64,
    ) -> FormFactors {
        let n = self.indptr.len() - 1;
        let f = Csr::new((n, n), self.indptr, self.indices, self.data);
        FormFactors {
            f,
            se: self.se,
            area,
            rays,
            seconds,
            estimator,
            seed,
            replicates: 0,
            unresolved: 0.0,
        }
    }
}

/// Physical diagnostics of a form-factor matrix.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Diagnostics {
    /// Smallest row sum.
    pub min_row_sum: f64,
    /// Largest row sum.
    pub max_row_sum: f64,
    /// Row with the largest sum.
    pub max_row: usize,
    /// Worst `|A_i F_ij - A_j F_ji| / max(A_i F_ij, A_j F_ji)` over stored pairs.
    pub reciprocity: f64,
    /// The same, over pairs where `F_ij` or `F_ji` is at least [`SIGNIFICANT`].
    pub reciprocity_significant: f64,
    /// Fraction of stored pairs whose reciprocity gap exceeds 3 combined bars.
    pub reciprocity_beyond_3se: f64,
    /// Rows with no stored entry (patches that see nothing, e.g. hidden under a block).
    pub empty_rows: usize,
    /// Rows whose sum exceeds 1 by more than 3 of its standard errors plus its bound
    /// ([`over_one`]).
    pub rows_over_one: usize,
    /// Entries outside [0, 1] or not finite.
    pub out_of_range: usize,
    /// Stored entries.
    pub nnz: usize,
    /// The largest bars of the row sums ([`sum_bar`]), each part's largest on its own.
    pub max_row_sum_bar: Bar,
    /// Rows whose stored pairs were checked for reciprocity: every row, or those of evenly
    /// spaced blocks ([`Reciprocity::Auto`]); the three reciprocity figures are over their
    /// pairs.
    pub reciprocity_rows: usize,
}

impl FormFactors {
    /// Assembles rows of entries (any order within a row) into CSR.
    pub fn from_rows(
        rows: Vec<Vec<Entry>>,
        area: Vec<f64>,
        rays: u64,
        seconds: f64,
        estimator: String,
        seed: u64,
    ) -> FormFactors {
        let mut b = CsrBuilder::with_capacity(rows.len(), rows.iter().map(Vec::len).sum());
        for mut row in rows {
            b.push_row(&mut row);
        }
        b.finish(area, rays, seconds, estimator, seed)
    }

    /// Bytes held per stored factor: column index, value and standard error.
    pub const BYTES_PER_ENTRY: usize =
        std::mem::size_of::<u32>() + std::mem::size_of::<f64>() + std::mem::size_of::<f32>();
    /// Bytes the stored entries' arrays hold (columns, values, standard errors), measured
    /// from their lengths; the row pointers ([`FormFactors::row_pointer_bytes`]) are per
    /// row, not per factor.
    pub fn entry_bytes(&self) -> usize {
        use std::mem::size_of_val;
        size_of_val(self.f.indices()) + size_of_val(self.f.data()) + size_of_val(self.se.as_slice())
    }

    /// Bytes of the row pointers (one `usize` per row, and one more).
    pub fn row_pointer_bytes(&self) -> usize {
        std::mem::size_of_val(self.f.indptr().raw_storage())
    }

    /// Number of patches.
    pub fn len(&self) -> usize {
        self.f.rows()
    }

    /// True for an empty matrix.
    pub fn is_empty(&self) -> bool {
        self.f.rows() == 0
    }

    /// `F[i, j]` (0 when not stored).
    pub fn get(&self, i: usize, j: usize) -> f64 {
        self.f.get(i, j).copied().unwrap_or(0.0)
    }

    /// The bar of `F[i, j]` (for an entry not stored, [`FormFactors::unresolved`]).
    pub fn bar(&self, i: usize, j: usize) -> Bar {
        self.f
            .nnz_index(i, j)
            .map(|k| Bar::of(self.se[k.0]))
            .unwrap_or(Bar::se(self.unresolved))
    }

    /// Standard error of `F[i, j]` ([`FormFactors::unresolved`] when not stored; 0 when its
    /// error is a bound: [`FormFactors::bar`]).
    pub fn stderr(&self, i: usize, j: usize) -> f64 {
        self.bar(i, j).se
    }

    /// The stored entries of row `i`: `(j, F_ij, bar)`.
    pub fn row(&self, i: usize) -> impl Iterator<Item = (usize, f64, Bar)> + '_ {
        let (lo, hi) = (self.f.indptr().index(i), self.f.indptr().index(i + 1));
        (lo..hi).map(move |k| {
            let j = self.f.indices()[k] as usize;
            (j, self.f.data()[k], Bar::of(self.se[k]))
        })
    }

    /// Sum of row `i`.
    pub fn row_sum(&self, i: usize) -> f64 {
        self.f
            .outer_view(i)
            .map(|r| r.data().iter().sum::<f64>() + 0.0)
            .unwrap_or(0.0)
    }

    /// The first row whose sum is over 1 by more than its bar allows at the family-wise
    /// rate [`ROW_ALARM`] over all rows, or `None`.
    ///
    /// A row's sum is the sum of independent replicate means, so its estimated standard
    /// error has Welch–Satterthwaite degrees of freedom `ν = (R - 1) (Σ s²)² / Σ s⁴` for
    /// `R` replicates (Satterthwaite 1946), and `(sum - 1) / se` of an honest row is at
    /// most Student-t with `ν` degrees of freedom. With `n` rows, each is allowed up to
    /// the t quantile of tail `ROW_ALARM / n` (Bonferroni) times its standard error, plus
    /// the linear sum of its entries' bounds ([`over_one`]; bounds hold with certainty, so
    /// they take no share of the alarm rate). Rows sharing rays (hemisphere shooting) are
    /// negatively correlated within the row, which only makes the test more lenient.
    pub fn row_over_one_beyond_chance(&self) -> Option<RowExcess> {
        let n = self.len();
        let per_entry = (self.replicates.max(2) - 1) as f64;
        let tail = ROW_ALARM / n.max(1) as f64;
        (0..n).find_map(|i| {
            let sum = self.row_sum(i);
            if sum <= 1.0 {
                return None;
            }
            let (lo, hi) = (self.f.indptr().index(i), self.f.indptr().index(i + 1));
            let bar = sum_bar(&self.se[lo..hi]);
            let s4: f64 = self.se[lo..hi].iter().map(|&s| Bar::of(s).se.powi(4)).sum();
            let s2 = bar.se * bar.se;
            let dof = if s4 > 0.0 {
                per_entry * s2 * s2 / s4
            } else {
                f64::INFINITY
            };
            let k = if bar.se > 0.0 {
                t_quantile(tail, dof)
            } else {
                0.0
            };
            over_one(sum, bar, k).then_some(RowExcess {
                row: i,
                sum,
                se: bar.se,
                bound: bar.bound,
                dof,
                k,
            })
        })
    }

    /// True when row `i` stores no factor: patch `i` sees nothing (as counted by
    /// [`Diagnostics::empty_rows`]).
    pub fn row_is_empty(&self, i: usize) -> bool {
        self.f.indptr().index(i) == self.f.indptr().index(i + 1)
    }

    /// The bar of the sum of row `i` ([`sum_bar`]: standard errors in quadrature, bounds
    /// linearly).
    pub fn row_sum_bar(&self, i: usize) -> Bar {
        let (lo, hi) = (self.f.indptr().index(i), self.f.indptr().index(i + 1));
        sum_bar(&self.se[lo..hi])
    }

    /// Row sums, reciprocity and range checks, reciprocity over every stored pair.
    pub fn diagnostics(&self) -> Diagnostics {
        self.diagnostics_with(Reciprocity::All)
    }

    /// Row sums and range checks over every row; reciprocity over the pairs `which`
    /// says.
    pub fn diagnostics_with(&self, which: Reciprocity) -> Diagnostics {
        if which == Reciprocity::All || self.f.nnz() <= RECIPROCITY_SAMPLE {
            self.diagnostics_in_blocks(DIAGNOSTIC_BLOCK)
        } else {
            self.diagnostics_sampled(RECIPROCITY_SAMPLE)
        }
    }

    /// Row sums and ranges over every row; reciprocity over the pairs of every `m`-th row,
    /// `m` such that they hold about `budget` stored factors. Two passes over the rows
    /// `j`, split among the threads in order: the first takes every row's sum and counts
    /// the entries `F_ji` whose row `i` is picked, the second copies them out, each
    /// part's lined up by picked row (a counting sort). Each picked row is then merged
    /// with its back entries, the parts' in order, so in column order. The copies take
    /// 16 bytes a checked pair.
    fn diagnostics_sampled(&self, budget: usize) -> Diagnostics {
        use rayon::prelude::*;
        let (n, nnz) = (self.len(), self.f.nnz());
        let (ptr, idx, val, se) = (self.f.indptr(), self.f.indices(), self.f.data(), &self.se);
        // At least one row.
        let m = nnz.div_ceil(budget.max(1)).clamp(1, n.max(1));
        // Rows m/2, m/2 + m, ...: picked row `i` is the (i / m)-th.
        let picked: Vec<usize> = (m / 2..n).step_by(m).collect();
        let mut bits = vec![0u64; n.div_ceil(64)];
        for &i in &picked {
            bits[i / 64] |= 1 << (i % 64);
        }
        let is_picked = |i: usize| (bits[i / 64] >> (i % 64)) & 1 != 0;
        let parts: Vec<std::ops::Range<usize>> = {
            let k = (4 * rayon::current_num_threads()).clamp(1, n.max(1));
            (0..k).map(|c| c * n / k..(c + 1) * n / k).collect()
        };
        // Every row's head; per part, where each picked row's back entries start.
        let heads: Vec<(Diagnostics, Vec<usize>)> = parts
            .par_iter()
            .map(|r| {
                let mut start = vec![0usize; picked.len() + 1];
                let mut d = Diagnostics::empty();
                for j in r.clone() {
                    let (lo, hi) = (ptr.index(j), ptr.index(j + 1));
                    d = Diagnostics::merge(d, row_head(j, &val[lo..hi], &se[lo..hi]));
                    for &i in &idx[lo..hi] {
                        if is_picked(i as usize) {
                            start[i as usize / m + 1] += 1;
                        }
                    }
                }
                for t in 0..picked.len() {
                    start[t + 1] += start[t];
                }
                (d, start)
            })
            .collect();
        let backs: Vec<Vec<Back>> = parts
            .par_iter()
            .zip(&heads)
            .map(|(r, (_, start))| {
                let mut at = start.clone();
                let mut out = vec![Back::default(); start[picked.len()]];
                for j in r.clone() {
                    for k in ptr.index(j)..ptr.index(j + 1) {
                        let i = idx[k] as usize;
                        if is_picked(i) {
                            let t = i / m;
                            out[at[t]] = Back {
                                j: j as u32,
                                se: se[k],
                                f: val[k],
                            };
                            at[t] += 1;
                        }
                    }
                }
                out
            })
            .collect();
        let recip = picked
            .par_iter()
            .enumerate()
            .map(|(t, &i)| {
                let (lo, hi) = (ptr.index(i), ptr.index(i + 1));
                let mut mine = backs
                    .iter()
                    .zip(&heads)
                    .flat_map(|(b, (_, start))| &b[start[t]..start[t + 1]]);
                let mut next = mine.next();
                let row = (&idx[lo..hi], &val[lo..hi], &se[lo..hi]);
                row_reciprocity(i, row, &self.area, Bar::se(self.unresolved), |_, j| {
                    // Back entries before column j have no entry of their own in row i.
                    while next.is_some_and(|b| (b.j as usize) < j) {
                        next = mine.next();
                    }
                    let hit = next.filter(|b| b.j as usize == j).map(|b| (b.f, b.se));
                    if hit.is_some() {
                        next = mine.next();
                    }
                    hit
                })
            })
            .reduce(Diagnostics::empty, Diagnostics::merge);
        let d = heads
            .into_iter()
            .fold(Diagnostics::empty(), |d, (h, _)| Diagnostics::merge(d, h));
        Diagnostics::merge(d, recip).finish(nnz, n)
    }

    /// [`FormFactors::diagnostics`] with blocks of `block` rows. Runs of consecutive rows go
    /// in parallel. Within a run, rows come in blocks; for a block, one pass over every
    /// row `j` of the matrix reads its entries `F_ji` whose column `i` lies in the block
    /// (a cursor per row `j` that only moves forward from block to block), and meets each
    /// one with the entry `F_ij` of row `i` (a cursor per row of the block, also moving
    /// forward, since `j` grows): the rows read stream through memory in order, and the
    /// block's rows stay in the caches. A binary search per entry, or a cursor walk
    /// entry by entry into row `j`, read several scattered cache lines a stored factor
    /// (`docs/PERFORMANCE.md`, section 1).
    fn diagnostics_in_blocks(&self, block: usize) -> Diagnostics {
        use rayon::prelude::*;
        let n = self.len();
        let block = block.max(1);
        let runs = (4 * rayon::current_num_threads())
            .min(n.div_ceil(block))
            .max(1);
        let per_run = n.div_ceil(runs).max(1);
        let d = (0..runs)
            .into_par_iter()
            .map(|r| self.diagnostics_of(r * per_run..((r + 1) * per_run).min(n), block))
            .reduce(Diagnostics::empty, Diagnostics::merge);
        d.finish(self.f.nnz(), n)
    }

    /// The diagnostics of the rows `rows`, in blocks of `block` rows (see
    /// [`FormFactors::diagnostics_in_blocks`]), with the two counters
    /// [`FormFactors::diagnostics`] divides at the end carried as counts.
    fn diagnostics_of(&self, rows: std::ops::Range<usize>, block: usize) -> Diagnostics {
        let (ptr, idx, val, se) = (self.f.indptr(), self.f.indices(), self.f.data(), &self.se);
        let mut d = Diagnostics::empty();
        if rows.is_empty() {
            return d;
        }
        let n = self.len();
        // `cursor[j]`: the first position in row j whose column is at least the block's
        // first row.
        let mut cursor: Vec<usize> = (0..n)
            .map(|j| {
                let (a, b) = (ptr.index(j), ptr.index(j + 1));
                a + idx[a..b].partition_point(|&x| (x as usize) < rows.start)
            })
            .collect();
        let mut at: Vec<usize> = Vec::with_capacity(block);
        let (mut pairs, mut beyond) = (0usize, 0usize);
        let mut pair = |d: &mut Diagnostics, i: usize, k: usize, back: Option<(f64, f32)>| {
            let (j, f) = (idx[k] as usize, val[k]);
            let unhit = Bar::se(self.unresolved);
            if let Some(b) = reciprocity_of(&self.area, (i, j), (f, Bar::of(se[k])), back, unhit, d)
            {
                pairs += 1;
                beyond += usize::from(b);
            }
        };
        for b0 in rows.clone().step_by(block) {
            let b1 = (b0 + block).min(rows.end);
            at.clear();
            at.extend((b0..b1).map(|i| ptr.index(i)));
            let mut recip = Diagnostics::empty();
            for (j, cj) in cursor.iter_mut().enumerate() {
                let end = ptr.index(j + 1);
                let mut c = *cj;
                while c < end && (idx[c] as usize) < b1 {
                    // F_ji, the back entry of F_ij in row i of the block. Row i's entries
                    // before column j have no back entry: it would have come earlier.
                    let i = idx[c] as usize;
                    let (k_end, mut k) = (ptr.index(i + 1), at[i - b0]);
                    while k < k_end && (idx[k] as usize) < j {
                        pair(&mut recip, i, k, None);
                        k += 1;
                    }
                    if k < k_end && idx[k] as usize == j {
                        pair(&mut recip, i, k, Some((val[c], se[c])));
                        k += 1;
                    }
                    at[i - b0] = k;
                    c += 1;
                }
                *cj = c;
            }
            for i in b0..b1 {
                for k in at[i - b0]..ptr.index(i + 1) {
                    pair(&mut recip, i, k, None);
                }
                let (lo, hi) = (ptr.index(i), ptr.index(i + 1));
                d = Diagnostics::merge(d, row_head(i, &val[lo..hi], &se[lo..hi]));
            }
            d = Diagnostics::merge(d, recip);
        }
        d.reciprocity_beyond_3se = beyond as f64;
        d.nnz = pairs;
        d.reciprocity_rows = rows.len();
        d
    }
}

/// A back entry `F_ji` copied out by [`FormFactors::diagnostics_with`]'s sampled check:
/// its row `j`, standard error and value.
#[derive(Clone, Copy, Default)]
struct Back {
    j: u32,
    se: f32,
    f: f64,
}

/// Rows per block of [`FormFactors::diagnostics`]: a block's rows, read a few cache lines
/// each at a time, stay within a core's caches, and every row of the matrix is visited
/// once per block.
const DIAGNOSTIC_BLOCK: usize = 4096;

/// The diagnostics of row `i` (its columns, values and standard errors; `area` of every
/// patch), with the two counters [`FormFactors::diagnostics`] divides at the end carried
/// as counts. `back(k, j)` is the stored back entry `F_ji` of the row's `k`-th entry
/// `F_ij`, with its standard error, or `None` when `F_ji` is not stored.
fn row_diagnostics(
    i: usize,
    (cols, vals, ses): (&[u32], &[f64], &[f32]),
    area: &[f64],
    unhit: Bar,
    back: impl FnMut(usize, usize) -> Option<(f64, f32)>,
) -> Diagnostics {
    Diagnostics::merge(
        row_head(i, vals, ses),
        row_reciprocity(i, (cols, vals, ses), area, unhit, back),
    )
}

/// The reciprocity part of [`row_diagnostics`] alone.
fn row_reciprocity(
    i: usize,
    (cols, vals, ses): (&[u32], &[f64], &[f32]),
    area: &[f64],
    unhit: Bar,
    mut back: impl FnMut(usize, usize) -> Option<(f64, f32)>,
) -> Diagnostics {
    let mut d = Diagnostics::empty();
    let (mut pairs, mut beyond) = (0usize, 0usize);
    for (k, ((&j, &f), &se_ij)) in cols.iter().zip(vals).zip(ses).enumerate() {
        let j = j as usize;
        let fs = (f, Bar::of(se_ij));
        if let Some(b) = reciprocity_of(area, (i, j), fs, back(k, j), unhit, &mut d) {
            pairs += 1;
            beyond += usize::from(b);
        }
    }
    d.reciprocity_beyond_3se = beyond as f64;
    d.nnz = pairs;
    d.reciprocity_rows = 1;
    d
}

/// The diagnostics of row `i` that need no other row: its sum (values `vals`, standard
/// errors `ses`), whether it is empty, whether it is over 1 beyond 3 bars, how many of
/// its entries are outside [0, 1] or not finite.
fn row_head(i: usize, vals: &[f64], ses: &[f32]) -> Diagnostics {
    // `+ 0.0`: the sum of no terms is -0.0, printed `-0.00000` for an empty row.
    let s: f64 = vals.iter().sum::<f64>() + 0.0;
    let bar = sum_bar(ses);
    Diagnostics {
        min_row_sum: s,
        max_row_sum: s,
        max_row: i,
        empty_rows: usize::from(vals.is_empty()),
        rows_over_one: usize::from(over_one(s, bar, 3.0)),
        max_row_sum_bar: bar,
        out_of_range: vals
            .iter()
            .filter(|f| !f.is_finite() || !(0.0..=1.0).contains(*f))
            .count(),
        ..Default::default()
    }
}

/// Folds the reciprocity gap `|A_i F_ij - A_j F_ji|` of the stored entry `F_ij = f`
/// (bar `se_ij`), whose back entry `F_ji` is `back` (`None`: not stored, 0 with the bar
/// `unhit` of an entry not stored, [`FormFactors::unresolved`]), into `d.reciprocity` and
/// `d.reciprocity_significant`. Returns `None` when both sides are 0, else whether the gap
/// is beyond 3 combined bars (standard errors in quadrature, bounds linearly:
/// [`Bar::plus`]).
///
/// A back entry not stored is one no ray hit: its truth is at least 0, so the gap
/// `A_i F_ij > 0` is exactly the side its one-sided bar covers. Without that bar a pair
/// hit from one side only would be judged as if the other side were known to be 0: at
/// 1,024 rays a patch, a factor hit once in each of three replicates sits at exactly
/// 3 standard errors, beyond them or not by rounding.
fn reciprocity_of(
    area: &[f64],
    (i, j): (usize, usize),
    (f, se_ij): (f64, Bar),
    back: Option<(f64, f32)>,
    unhit: Bar,
    d: &mut Diagnostics,
) -> Option<bool> {
    let (f_back, se_ji) = back.map_or((0.0, unhit), |(f, s)| (f, Bar::of(s)));
    let fij = area[i] * f;
    let fji = area[j] * f_back;
    let m = fij.abs().max(fji.abs());
    if m <= 0.0 {
        return None;
    }
    let gap = (fij - fji).abs();
    d.reciprocity = d.reciprocity.max(gap / m);
    if f.max(f_back) >= SIGNIFICANT {
        d.reciprocity_significant = d.reciprocity_significant.max(gap / m);
    }
    let bar = se_ij.times(area[i]).plus(se_ji.times(area[j]));
    Some(gap > bar.allowance(3.0) && gap > 1e-12 * m)
}

impl Diagnostics {
    /// Empty when every row's pairs were checked for reciprocity (of `rows` rows); else
    /// which were, to follow the word "reciprocity" in a summary.
    pub fn reciprocity_scope(&self, rows: usize) -> String {
        if self.reciprocity_rows >= rows {
            String::new()
        } else {
            format!(
                " (the pairs of {} evenly spaced rows of {rows}; \
                 `--reciprocity all` for every pair)",
                self.reciprocity_rows
            )
        }
    }

    /// How many numbers [`Diagnostics::to_numbers`] makes.
    pub const NUMBERS: usize = 13;

    /// The neutral element of [`Diagnostics::merge`].
    pub fn empty() -> Diagnostics {
        Diagnostics {
            min_row_sum: f64::INFINITY,
            max_row_sum: f64::NEG_INFINITY,
            ..Default::default()
        }
    }

    /// The diagnostics of rows `a` then rows `b` (both before [`Diagnostics::finish`]:
    /// `reciprocity_beyond_3se` and `nnz` still count pairs). Of equal largest row sums the
    /// one of `a` is kept, so rows merged in order report the first.
    pub fn merge(a: Diagnostics, b: Diagnostics) -> Diagnostics {
        Diagnostics {
            min_row_sum: a.min_row_sum.min(b.min_row_sum),
            max_row_sum: a.max_row_sum.max(b.max_row_sum),
            max_row: if b.max_row_sum > a.max_row_sum {
                b.max_row
            } else {
                a.max_row
            },
            reciprocity: a.reciprocity.max(b.reciprocity),
            reciprocity_significant: a.reciprocity_significant.max(b.reciprocity_significant),
            reciprocity_beyond_3se: a.reciprocity_beyond_3se + b.reciprocity_beyond_3se,
            empty_rows: a.empty_rows + b.empty_rows,
            rows_over_one: a.rows_over_one + b.rows_over_one,
            out_of_range: a.out_of_range + b.out_of_range,
            nnz: a.nnz + b.nnz,
            reciprocity_rows: a.reciprocity_rows + b.reciprocity_rows,
            max_row_sum_bar: a.max_row_sum_bar.max(b.max_row_sum_bar),
        }
    }

    /// Merged diagnostics of all `rows` rows of a matrix of `nnz` stored entries, made
    /// final: the share of pairs beyond 3 standard errors, the entry count.
    pub fn finish(mut self, nnz: usize, rows: usize) -> Diagnostics {
        let pairs = self.nnz;
        self.reciprocity_beyond_3se = if pairs > 0 {
            self.reciprocity_beyond_3se / pairs as f64
        } else {
            0.0
        };
        self.nnz = nnz;
        if rows == 0 {
            self.min_row_sum = 0.0;
            self.max_row_sum = 0.0;
        }
        self
    }

    /// The fields as numbers (exact: the counts are far below 2^53), to send between
    /// ranks; [`Diagnostics::from_numbers`] reads them back.
    pub fn to_numbers(&self) -> [f64; Diagnostics::NUMBERS] {
        [
            self.min_row_sum,
            self.max_row_sum,
            self.max_row as f64,
            self.reciprocity,
            self.reciprocity_significant,
            self.reciprocity_beyond_3se,
            self.empty_rows as f64,
            self.rows_over_one as f64,
            self.out_of_range as f64,
            self.nnz as f64,
            self.reciprocity_rows as f64,
            self.max_row_sum_bar.se,
            self.max_row_sum_bar.bound,
        ]
    }

    /// The inverse of [`Diagnostics::to_numbers`].
    pub fn from_numbers(v: &[f64]) -> Diagnostics {
        Diagnostics {
            min_row_sum: v[0],
            max_row_sum: v[1],
            max_row: v[2] as usize,
            reciprocity: v[3],
            reciprocity_significant: v[4],
            reciprocity_beyond_3se: v[5],
            empty_rows: v[6] as usize,
            rows_over_one: v[7] as usize,
            out_of_range: v[8] as usize,
            nnz: v[9] as usize,
            reciprocity_rows: v[10] as usize,
            max_row_sum_bar: Bar {
                se: v[11],
                bound: v[12],
            },
        }
    }
}

/// Rows `lo..hi` of a form-factor matrix, held by one rank of a distributed run
/// ([`crate::formfactor::shard`]): the same rows, bit for bit, as those of the matrix one
/// process assembles ([`CsrBuilder::from_upper`], [`CsrBuilder::push_rows`]), and their
/// diagnostics, computed while each entry's back entry `F_ji` was at hand.
#[derive(Clone, Debug)]
pub struct Block {
    /// First row.
    pub lo: usize,
    /// The rows (`hi - lo` of them, `n` columns).
    pub f: Csr,
    /// Standard error of each stored entry, aligned with `f.data()`.
    pub se: Vec<f32>,
    /// The rows' diagnostics as [`FormFactors::diagnostics`] computes them row by row,
    /// before [`Diagnostics::finish`] (merge the blocks in order, then finish).
    pub diagnostics: Diagnostics,
}

impl Block {
    /// Rows in the block.
    pub fn rows(&self) -> usize {
        self.f.rows()
    }

    /// One past the last row.
    pub fn hi(&self) -> usize {
        self.lo + self.f.rows()
    }
}

/// Builds a [`Block`] from computed rows in two passes over the same parts of rows:
/// [`BlockBuilder::count`] each, then [`BlockBuilder::fill`] each **in increasing row
/// order**, then [`BlockBuilder::finish`]. A part is (part of) one computed row, sorted by
/// column; the builder keeps what falls in the block: the entries of its rows, and, for
/// estimators that compute only the upper triangle, the entries whose mirror falls in it
/// (written as [`CsrBuilder::from_upper`] writes them: a row's mirrored entries in
/// increasing source row, then its own). The arrays are allocated once, at their size.
#[derive(Debug)]
pub struct BlockBuilder<'a> {
    lo: usize,
    upper: bool,
    area: &'a [f64],
    /// Entries per row, then (after [`BlockBuilder::count`]) row pointers.
    len: Vec<usize>,
    /// Mirrored entries per row (upper only).
    lower: Vec<usize>,
    /// Next free slot of each row's mirrored and own parts.
    cursor: Vec<(usize, usize)>,
    indptr: Vec<usize>,
    ind: Vec<u32>,
    val: Vec<f64>,
    se: Vec<f32>,
    /// Back entry of each slot: `F_ji` (NaN: not stored) and its standard error.
    back: Vec<(f64, f32)>,
    /// Full rows: `(r, i, F_ij, se)` for entries `F_ij` whose column `lo + r` falls in the
    /// block: the back entries of the block's `F_ji`, filled in at the end.
    backs: Vec<(u32, u32, f64, f32)>,
    last: Option<usize>,
}

impl<'a> BlockBuilder<'a> {
    /// A builder of rows `lo..hi`; `upper` when the rows hold only `j > i`; `area` of
    /// every patch.
    pub fn new(lo: usize, hi: usize, upper: bool, area: &'a [f64]) -> BlockBuilder<'a> {
        let rows = hi.saturating_sub(lo);
        BlockBuilder {
            lo,
            upper,
            area,
            len: vec![0; rows],
            lower: vec![0; rows],
            cursor: Vec::new(),
            indptr: Vec::new(),
            ind: Vec::new(),
            val: Vec::new(),
            se: Vec::new(),
            back: Vec::new(),
            backs: Vec::new(),
            last: None,
        }
    }

    fn local(&self, k: usize) -> Option<usize> {
        k.checked_sub(self.lo).filter(|&r| r < self.len.len())
    }

    /// First pass: counts the entries of computed row `i`'s part `entries`.
    pub fn count(&mut self, i: usize, entries: &[Entry]) {
        if let Some(r) = self.local(i) {
            self.len[r] += entries.len();
        }
        if self.upper {
            for e in entries {
                if let Some(r) = self.local(e.j as usize) {
                    self.len[r] += 1;
                    self.lower[r] += 1;
                }
            }
        }
    }

    fn allocate(&mut self) {
        let rows = self.len.len();
        let mut indptr = Vec::with_capacity(rows + 1);
        indptr.push(0);
        for &l in &self.len {
            indptr.push(indptr[indptr.len() - 1] + l);
        }
        let nnz = indptr[rows];
        self.cursor = (0..rows)
            .map(|r| (indptr[r], indptr[r] + self.lower[r]))
            .collect();
        self.indptr = indptr;
        self.ind = vec![0; nnz];
        self.val = vec![0.0; nnz];
        self.se = vec![0.0; nnz];
        self.back = vec![(f64::NAN, 0.0); nnz];
    }

    /// Second pass: writes computed row `i`'s part `entries`; parts must come in
    /// increasing `i` (each row once), after every part was counted.
    ///
    /// # Panics
    /// When parts come out of order, or more entries come than were counted.
    pub fn fill(&mut self, i: usize, entries: &[Entry]) {
        if self.indptr.is_empty() {
            self.allocate();
        }
        assert!(
            self.last.is_none_or(|l| l < i),
            "parts of rows must come in increasing order"
        );
        self.last = Some(i);
        let own = self.local(i);
        for e in entries {
            let j = e.j as usize;
            let theirs = self.local(j);
            if self.upper {
                // As `CsrBuilder::from_upper` computes the mirror, bit for bit.
                let s = self.area[i] / self.area[j];
                let (mf, ms) = (e.f * s, Bar::of(e.se * s).stored_f32());
                if let Some(r) = own {
                    let k = self.cursor[r].1;
                    self.cursor[r].1 += 1;
                    self.put(k, (e.j, e.f, Bar::of(e.se).stored_f32()), (mf, ms));
                }
                if let Some(r) = theirs {
                    let k = self.cursor[r].0;
                    self.cursor[r].0 += 1;
                    self.put(k, (i as u32, mf, ms), (e.f, Bar::of(e.se).stored_f32()));
                }
            } else {
                if let Some(r) = own {
                    let k = self.cursor[r].0;
                    self.cursor[r].0 += 1;
                    self.put(k, (e.j, e.f, Bar::of(e.se).stored_f32()), (f64::NAN, 0.0));
                }
                if let Some(r) = theirs {
                    self.backs
                        .push((r as u32, i as u32, e.f, Bar::of(e.se).stored_f32()));
                }
            }
        }
    }

    #[inline]
    fn put(&mut self, k: usize, (j, f, se): (u32, f64, f32), back: (f64, f32)) {
        self.ind[k] = j;
        self.val[k] = f;
        self.se[k] = se;
        self.back[k] = back;
    }

    /// The block, with its diagnostics from the back entries (which are then dropped);
    /// `unresolved` is the bar of an entry not stored ([`FormFactors::unresolved`]).
    ///
    /// # Panics
    /// When fewer entries came than were counted.
    pub fn finish(mut self, unresolved: f64) -> Block {
        use rayon::prelude::*;
        if self.indptr.is_empty() {
            self.allocate();
        }
        self.len = Vec::new();
        let rows = self.indptr.len() - 1;
        for (r, c) in self.cursor.iter().enumerate() {
            let whole = if self.upper {
                *c == (self.indptr[r] + self.lower[r], self.indptr[r + 1])
            } else {
                c.0 == self.indptr[r + 1]
            };
            assert!(
                whole,
                "row {} of the block got other entries than were counted",
                self.lo + r
            );
        }
        for &(r, i, f, se) in &std::mem::take(&mut self.backs) {
            let (a, z) = (self.indptr[r as usize], self.indptr[r as usize + 1]);
            if let Ok(k) = self.ind[a..z].binary_search(&i) {
                self.back[a + k] = (f, se);
            }
        }
        let n = self.area.len();
        let (lo, area) = (self.lo, self.area);
        let (indptr, ind, val, se, back) = (self.indptr, self.ind, self.val, self.se, self.back);
        let diagnostics = (0..rows)
            .into_par_iter()
            .map(|r| {
                let (a, b) = (indptr[r], indptr[r + 1]);
                let row = (&ind[a..b], &val[a..b], &se[a..b]);
                row_diagnostics(lo + r, row, area, Bar::se(unresolved), |k, _| {
                    let (f, s) = back[a + k];
                    (!f.is_nan()).then_some((f, s))
                })
            })
            .fold(Diagnostics::empty, Diagnostics::merge)
            .reduce(Diagnostics::empty, Diagnostics::merge);
        drop(back);
        Block {
            lo,
            f: Csr::new((rows, n), indptr, ind, val),
            se,
            diagnostics,
        }
    }
}

/// For each stored entry of `f`, the position of its mirror `(j, i)` when the two satisfy
/// reciprocity to rounding in value and standard error (one random variable: the
/// estimators that compute a pair once and fill the other entry by reciprocity), else
/// `None`. Diagonal entries map to `None`.
pub fn reciprocal_pairs(f: &Csr, se: &[f32], area: &[f64]) -> Vec<Option<usize>> {
    use rayon::prelude::*;
    let ptr = f.indptr();
    let ptr = ptr.to_proper();
    (0..f.rows())
        .into_par_iter()
        .flat_map_iter(|i| (ptr[i]..ptr[i + 1]).map(move |k| mirror(f, se, area, i, k)))
        .collect()
}

/// The position of the mirror `(j, i)` of the stored entry `k` of row `i`, when the two
/// are one random variable ([`reciprocal_pairs`]), else `None`.
pub fn mirror(f: &Csr, se: &[f32], area: &[f64], i: usize, k: usize) -> Option<usize> {
    let ptr = f.indptr();
    let (ind, val) = (f.indices(), f.data());
    let j = ind[k] as usize;
    if j == i {
        return None;
    }
    let (lo, hi) = (ptr.index(j), ptr.index(j + 1));
    let m = lo + ind[lo..hi].binary_search(&(i as u32)).ok()?;
    let (g, h) = (area[i] * val[k], area[j] * val[m]);
    let (sg, sh) = (area[i] * f64::from(se[k]), area[j] * f64::from(se[m]));
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs());
    (close(g, h) && close(sg, sh)).then_some(m)
}

#[cfg(test)]
mod tests {
    use super::*;
    type TriMat = Triplets;

    /// `m` matrices of `n` rows of `k` entries whose true row sums are `1 + shift` row
    /// standard errors, each entry the mean of `reps` normal replicates (unequal spreads,
    /// so that some rows' errors are dominated by a few entries); returns how many
    /// matrices [`FormFactors::row_over_one_beyond_chance`] refuses.
    fn refused(m: usize, n: usize, k: usize, reps: usize, shift: f64, seed: u64) -> usize {
        let mut refused = 0;
        for t in 0..m {
            let mut rng = crate::sampling::Pcg32::keyed(seed, t as u64, 0, 0);
            let mut normal = || {
                let (u, v) = (1.0 - rng.next_f64(), rng.next_f64());
                (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
            };
            let mut rows = Vec::new();
            for _ in 0..n {
                let sigma: Vec<f64> = (0..k)
                    .map(|j| 1e-3 * (1.0 + (j % 5) as f64).powi(2))
                    .collect();
                let row_se = (sigma.iter().map(|s| s * s).sum::<f64>() / reps as f64).sqrt();
                let truth = (1.0 + shift * row_se) / k as f64;
                let row: Vec<Entry> = (0..k)
                    .map(|j| {
                        let x: Vec<f64> = (0..reps).map(|_| truth + sigma[j] * normal()).collect();
                        let mean = x.iter().sum::<f64>() / reps as f64;
                        let var =
                            x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (reps - 1) as f64;
                        Entry {
                            j: j as u32,
                            f: mean,
                            se: (var / reps as f64).sqrt(),
                        }
                    })
                    .collect();
                rows.push(row);
            }
            let mut ff =
                FormFactors::from_rows(rows, vec![1.0; n.max(k)], 0, 0.0, "test".into(), seed);
            ff.replicates = reps;
            refused += usize::from(ff.row_over_one_beyond_chance().is_some());
        }
        refused
    }

    /// A pair stored one way only is judged with the bar of an entry not stored on the
    /// other side: 3.5 standard errors from 0 is beyond 3 bars when the missing side is
    /// taken as exactly 0, within them with the bar of a fraction no ray hit (about 0.71
    /// of a hit at N rays a row).
    #[test]
    fn reciprocity_counts_the_bar_of_a_back_entry_not_stored() {
        let rays = 1024.0;
        let hit = 1.0 / rays;
        let ff = |unresolved: f64| {
            let rows = vec![
                vec![Entry {
                    j: 1,
                    f: 3.5 * hit,
                    se: hit,
                }],
                vec![Entry {
                    j: 2,
                    f: 0.5,
                    se: 0.01,
                }],
                vec![Entry {
                    j: 1,
                    f: 0.5,
                    se: 0.01,
                }],
            ];
            let mut ff = FormFactors::from_rows(rows, vec![1.0; 3], 0, 0.0, "t".into(), 0);
            ff.unresolved = unresolved;
            ff
        };
        let unhit = crate::sampling::fraction_se(0.0, rays);
        assert!(unhit > 0.7 * hit && unhit < 0.72 * hit, "{unhit}");
        let as_zero = ff(0.0).diagnostics();
        assert!((as_zero.reciprocity_beyond_3se - 1.0 / 3.0).abs() < 1e-12);
        for which in [Reciprocity::All, Reciprocity::Auto] {
            let d = ff(unhit).diagnostics_with(which);
            assert_eq!(d.reciprocity_beyond_3se, 0.0, "{which:?}");
            assert_eq!(d.reciprocity, as_zero.reciprocity);
        }
        // 4 hits are beyond either way.
        let mut four = ff(unhit);
        four.f.data_mut()[0] = 4.0 * hit;
        assert!((four.diagnostics().reciprocity_beyond_3se - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn bounds_add_linearly_and_standard_errors_in_quadrature() {
        // 100 entries of bound 1e-9 each: the row's bound is 1e-7 (linear), where read as
        // standard errors they would allow only 3 * 1e-8 at 3 bars.
        let row = |excess: f64, bounded: bool| {
            let f = (1.0 + excess) / 100.0;
            (1..101)
                .map(|j| {
                    if bounded {
                        Entry::bounded(j, f, 1e-9)
                    } else {
                        Entry { j, f, se: 1e-9 }
                    }
                })
                .collect::<Vec<_>>()
        };
        let ff = |excess: f64, bounded: bool| {
            let mut r = vec![row(excess, bounded)];
            r.resize(101, Vec::new());
            FormFactors::from_rows(r, vec![1.0; 101], 0, 0.0, "t".into(), 0)
        };
        let bar = ff(0.0, true).row_sum_bar(0);
        assert_eq!(bar.se, 0.0);
        assert!((bar.bound - 1e-7).abs() < 1e-13, "{bar:?}");
        let bar = ff(0.0, false).row_sum_bar(0);
        assert!((bar.se - 1e-8).abs() < 1e-13 && bar.bound == 0.0, "{bar:?}");
        // 1 + 9e-8 is within the bound: not over 1, not refused.
        let ok = ff(9e-8, true);
        assert_eq!(ok.row_over_one_beyond_chance(), None);
        assert_eq!(ok.diagnostics().rows_over_one, 0);
        // 1 + 1.1e-7 is past the bound: over 1 and refused, whatever the alarm rate.
        let bad = ff(1.1e-7, true);
        assert_eq!(bad.diagnostics().rows_over_one, 1);
        let r = bad.row_over_one_beyond_chance().expect("refused");
        assert_eq!((r.row, r.k, r.se), (0, 0.0, 0.0));
        assert!((r.bound - 1e-7).abs() < 1e-13);
        // The same excess with the bars read as standard errors is 11 of them over 1.
        assert_eq!(ff(1.1e-7, false).diagnostics().rows_over_one, 1);
        // A bound survives storage in f32 as a bound, rounded up.
        for b in [1e-9, 3.3e-7, 0.1] {
            let s = Bar::bound(b).stored_f32();
            assert!(s.is_sign_negative() && -f64::from(s) >= b, "{b} -> {s}");
            assert_eq!(Bar::of(s).se, 0.0);
        }
    }

    #[test]
    fn a_stored_factor_takes_sixteen_bytes() {
        let rows = vec![
            vec![
                Entry {
                    j: 1,
                    f: 0.25,
                    se: 0.01,
                },
                Entry {
                    j: 2,
                    f: 0.5,
                    se: 0.02,
                },
            ],
            vec![Entry {
                j: 0,
                f: 0.125,
                se: 1e-3,
            }],
            vec![],
        ];
        let ff = FormFactors::from_rows(rows, vec![1.0; 3], 0, 0.0, "t".into(), 0);
        assert_eq!(ff.f.nnz(), 3);
        assert_eq!(ff.entry_bytes(), 16 * 3);
        assert_eq!(ff.entry_bytes(), FormFactors::BYTES_PER_ENTRY * ff.f.nnz());
        assert_eq!(ff.row_pointer_bytes(), 4 * std::mem::size_of::<usize>());
        // The bar keeps 7 digits.
        assert_eq!(ff.stderr(1, 0), f64::from(1e-3f32));
    }

    #[test]
    fn honest_rows_over_one_are_refused_at_most_at_the_alarm_rate() {
        // 4000 honest matrices of 25 closed rows: expected at most 4 refusals at the
        // family-wise rate 1e-3; more than 14 has probability below 1e-5 if the rate holds.
        for reps in [2, 4] {
            let r = refused(4000, 25, 25, reps, 0.0, 11);
            assert!(
                r <= 14,
                "{r} of 4000 honest matrices refused with {reps} replicates"
            );
        }
    }

    #[test]
    fn a_row_well_over_one_is_refused() {
        // A row 10 of its standard errors over 1 (every row of the matrix is) is caught.
        let r = refused(200, 25, 25, 8, 10.0, 12);
        assert!(r >= 190, "only {r} of 200 caught");
        // Exact rows (bar 0): any excess beyond rounding is refused.
        let rows = vec![
            vec![
                Entry {
                    j: 1,
                    f: 0.6,
                    se: 0.0,
                },
                Entry {
                    j: 2,
                    f: 0.4 + 2e-9,
                    se: 0.0,
                },
            ],
            vec![],
            vec![],
        ];
        let ff = FormFactors::from_rows(rows, vec![1.0; 3], 0, 0.0, "exact".into(), 0);
        let e = ff.row_over_one_beyond_chance().expect("refused");
        assert_eq!((e.row, e.k), (0, 0.0));
    }

    #[test]
    fn repair_scales_only_rows_past_the_bound() {
        let mut t = TriMat::new((3, 3));
        t.add_triplet(0, 1, 0.7);
        t.add_triplet(0, 2, 0.5); // 1.2 * 0.9 >= 1: repaired
        t.add_triplet(1, 0, 0.6);
        t.add_triplet(1, 2, 0.5); // 1.1 * 0.5 < 1: kept
        t.add_triplet(2, 0, 0.3);
        let f: Csr = t.to_csr();
        let rho = [[0.9, 0.1, 0.1], [0.5; 3], [0.5; 3]];
        let (g, rep) = repair_row_sums(&f, &rho).unwrap();
        assert_eq!(rep.rows, vec![0]);
        assert_eq!(rep.worst.0, 0);
        assert!((rep.worst_gain - 1.08).abs() < 1e-12);
        let s0: f64 = g.outer_view(0).unwrap().data().iter().sum();
        assert!((s0 - 1.0).abs() < 1e-15);
        assert_eq!(g.get(1, 2), Some(&0.5));
        assert!(repair_row_sums(&f, &[[0.5; 3]; 3]).is_none());
    }

    #[test]
    fn an_empty_row_sums_to_positive_zero() {
        let rows = vec![
            vec![],
            vec![Entry {
                j: 0,
                f: 0.5,
                se: 0.0,
            }],
        ];
        let ff = FormFactors::from_rows(rows, vec![1.0; 2], 0, 0.0, "test".into(), 0);
        let d = ff.diagnostics();
        assert_eq!(
            format!("{:.5} {:.5}", d.min_row_sum, ff.row_sum(0)),
            "0.00000 0.00000"
        );
    }

    /// The diagnostics with a binary search per back entry, row by row: the reference for
    /// the blocked walk of `FormFactors::diagnostics` (the same per-pair figures).
    fn diagnostics_by_search(ff: &FormFactors) -> Diagnostics {
        diagnostics_of_rows_by_search(ff, |_| true)
    }

    /// Row sums over every row, reciprocity over the rows `checked` picks, each back entry
    /// found by a binary search.
    fn diagnostics_of_rows_by_search(
        ff: &FormFactors,
        checked: impl Fn(usize) -> bool,
    ) -> Diagnostics {
        let mut d = Diagnostics {
            min_row_sum: f64::INFINITY,
            max_row_sum: f64::NEG_INFINITY,
            ..Default::default()
        };
        let (mut pairs, mut beyond) = (0usize, 0usize);
        for i in 0..ff.len() {
            let row = ff.f.outer_view(i).unwrap();
            let (lo, _) = (ff.f.indptr().index(i), ff.f.indptr().index(i + 1));
            let s: f64 = row.data().iter().sum();
            if s > d.max_row_sum {
                (d.max_row_sum, d.max_row) = (s, i);
            }
            d.min_row_sum = d.min_row_sum.min(s);
            if !checked(i) {
                continue;
            }
            d.reciprocity_rows += 1;
            for (k, (j, &f)) in row.iter().enumerate() {
                let back = ff.f.nnz_index(j, i).map(|k| (ff.f.data()[k.0], ff.se[k.0]));
                let fs = (f, Bar::of(ff.se[lo + k]));
                let unhit = Bar::se(ff.unresolved);
                if let Some(b) = reciprocity_of(&ff.area, (i, j), fs, back, unhit, &mut d) {
                    pairs += 1;
                    beyond += usize::from(b);
                }
            }
        }
        d.reciprocity_beyond_3se = beyond as f64 / pairs as f64;
        d.nnz = pairs;
        d
    }

    #[test]
    fn diagnostics_find_every_back_entry() {
        // A full pseudo-random matrix (both triangles, some pairs one-sided) on 4 threads,
        // so that the rows fall into many blocks.
        let n = 300;
        let ff = two_sided_test_matrix(n);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap();
        let want = diagnostics_by_search(&ff);
        let whole = ff.diagnostics();
        // Blocks of one row, of a few, and as many runs as blocks or fewer.
        for block in [1, 7, 64, DIAGNOSTIC_BLOCK] {
            let got = pool.install(|| ff.diagnostics_in_blocks(block));
            assert!(got.reciprocity > 1e-4 && got.reciprocity_beyond_3se > 0.0);
            assert_eq!(got.reciprocity, want.reciprocity, "block {block}");
            assert_eq!(got.reciprocity_significant, want.reciprocity_significant);
            assert_eq!(got.reciprocity_beyond_3se, want.reciprocity_beyond_3se);
            assert_eq!(
                (got.min_row_sum, got.max_row_sum),
                (want.min_row_sum, want.max_row_sum)
            );
            assert_eq!(got.max_row, want.max_row);
            assert_eq!(
                (got.nnz, got.empty_rows, got.rows_over_one, got.out_of_range),
                (
                    whole.nnz,
                    whole.empty_rows,
                    whole.rows_over_one,
                    whole.out_of_range
                )
            );
        }
    }

    /// A pseudo-random matrix of `n` rows with both triangles, a third of its pairs
    /// stored one way, the others slightly off reciprocity.
    fn two_sided_test_matrix(n: usize) -> FormFactors {
        let mut rows = upper(n, 7);
        let mut lower = vec![Vec::new(); n];
        for (i, r) in rows.iter().enumerate() {
            for (k, e) in r.iter().enumerate() {
                // Two pairs in three get their reverse entry, slightly off reciprocity.
                if k % 3 != 0 {
                    lower[e.j as usize].push(Entry {
                        j: i as u32,
                        f: e.f * (1.0 + 1e-3 * (k % 5) as f64),
                        se: e.se,
                    });
                }
            }
        }
        let mut b = CsrBuilder::with_capacity(n, 0);
        for (r, l) in rows.iter_mut().zip(lower) {
            r.extend(l);
            b.push_row(r);
        }
        let area: Vec<f64> = (0..n).map(|i| 1.0 + (i % 7) as f64 * 0.1).collect();
        b.finish(area, 0, 0.0, "test".into(), 0)
    }

    #[test]
    fn sampled_reciprocity_checks_every_mth_row_exactly() {
        // Every row's sum and range; the reciprocity of rows m/2, m/2 + m, ... as a
        // binary search per entry finds it, on 1 and 3 threads.
        let n = 300;
        let ff = two_sided_test_matrix(n);
        let whole = ff.diagnostics();
        for budget in [ff.f.nnz() / 7, ff.f.nnz() / 40, 1] {
            let m = ff.f.nnz().div_ceil(budget).min(n);
            let want = diagnostics_of_rows_by_search(&ff, |i| i >= m / 2 && (i - m / 2) % m == 0);
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let got = pool.install(|| ff.diagnostics_sampled(budget));
                assert_eq!(got.reciprocity_rows, (m / 2..n).step_by(m).count());
                assert!(got.reciprocity_rows < n, "budget {budget}");
                assert_eq!(got.reciprocity_rows, want.reciprocity_rows);
                assert_eq!(got.reciprocity, want.reciprocity, "budget {budget}");
                assert_eq!(got.reciprocity_significant, want.reciprocity_significant);
                assert_eq!(got.reciprocity_beyond_3se, want.reciprocity_beyond_3se);
                let head = |d: &Diagnostics| {
                    (
                        d.min_row_sum,
                        d.max_row_sum,
                        d.max_row,
                        d.empty_rows,
                        d.rows_over_one,
                        d.out_of_range,
                        d.nnz,
                    )
                };
                assert_eq!(head(&got), head(&whole));
            }
        }
        // The automatic choice checks every pair up to its budget.
        assert_eq!(ff.diagnostics_with(Reciprocity::Auto), whole);
        assert_eq!(whole.reciprocity_rows, n);
    }

    /// A pseudo-random sparse upper triangle with up to `n` rows.
    fn upper(n: usize, seed: u64) -> Vec<Vec<Entry>> {
        let mut x = seed;
        let mut next = move || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            x >> 33
        };
        let mut rows = vec![Vec::new(); n];
        for (i, r) in rows.iter_mut().enumerate() {
            for j in i + 1..n {
                if next() % 3 == 0 {
                    let (f, se) = (next() as f64 / 1e9, next() as f64 / 1e12);
                    r.push(Entry { j: j as u32, f, se });
                }
            }
        }
        rows
    }

    fn arrays(b: CsrBuilder) -> (Vec<usize>, Vec<u32>, Vec<f64>, Vec<f32>) {
        (b.indptr, b.indices, b.data, b.se)
    }

    #[test]
    fn parallel_assembly_matches_row_by_row() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        for n in [0, 1, 2, 7, 50] {
            let rows = upper(n, n as u64 + 1);
            let area: Vec<f64> = (0..n).map(|i| 1.0 + i as f64 * 0.25).collect();
            // Reference: mirror by hand, then one row at a time.
            let mut full = rows.clone();
            for (i, r) in rows.iter().enumerate() {
                for e in r {
                    let s = area[i] / area[e.j as usize];
                    full[e.j as usize].push(Entry {
                        j: i as u32,
                        f: e.f * s,
                        se: e.se * s,
                    });
                }
            }
            let mut want = CsrBuilder::with_capacity(n, 0);
            for r in full.iter_mut() {
                want.push_row(r);
            }
            let want = arrays(want);
            let got = pool.install(|| arrays(CsrBuilder::from_upper(&rows, &area)));
            assert_eq!(got, want, "from_upper, n = {n}");
            // Blocks of sorted rows appended in parallel, in two calls.
            let mut b = CsrBuilder::with_capacity(n, 0);
            pool.install(|| {
                b.push_rows(&full[..n / 2]);
                b.push_rows(&full[n / 2..]);
            });
            assert_eq!(arrays(b), want, "push_rows, n = {n}");
        }
    }
}
