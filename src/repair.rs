//! Physical bounds of a form-factor matrix, and repairs that use the standard errors.
//!
//! Exact form factors obey (radiosidade.md, "Teorema da Reciprocidade"; Cohen and Wallace
//! 1993, §4.2):
//! - `0 <= F_ij <= 1`, and every row sums to at most 1 (exactly 1 in a closed scene);
//! - reciprocity, `A_i F_ij = A_j F_ji`.
//!
//! Estimates break these by their noise. [`check`] reports every row whose sum exceeds 1
//! and every entry outside `[0, 1]`; nothing is ever silently kept or clipped. [`repair`]
//! optionally restores the constraints by the smallest change measured in standard errors,
//! that is, the weighted least-squares projection
//! `min Σ ((F'_ij - F_ij) / σ_ij)²` subject to the constraint:
//!
//! - **reciprocity**: for each stored pair, `g = A_i F_ij` and `g' = A_j F_ji` are replaced
//!   by their inverse-variance weighted mean `(g/v + g'/v') / (1/v + 1/v')`, whose variance
//!   is `1/(1/v + 1/v')` (an entry with standard error 0 is exact and wins);
//! - **closure** (closed scenes only): row i's deficit `1 - S_i` is shared in proportion to
//!   the variances, `δ_ij = σ_ij² (1 - S_i) / Σ_k σ_ik²`; the standard errors become the
//!   conditional ones, `σ_ij² - σ_ij⁴ / Σ_k σ_ik²`. The bound `F_ij >= 0` is kept: an entry
//!   the shift would take below 0 is set to 0 and the others share what is left (the
//!   bound-constrained projection, whose solution `δ_ij = max(-F_ij, λ σ_ij²)` is found by
//!   pinning the entries that cross, as in an active-set method). A row whose entries all
//!   have standard error 0 (a deterministic estimator) is scaled to sum 1 instead;
//! - **both**: the two projections alternate until neither moves an entry by more than
//!   `1e-12` (alternating projections onto two affine sets in the same metric converge to
//!   their intersection).
//!
//! The sparsity pattern is kept: entries that were not stored are not created (a pair
//! stored in one direction only is left as it is by reciprocity).
//!
//! Bounds ([`Bar`]): the weights take each bar's magnitude as its `σ`. The reciprocity mean
//! of two bounded entries is bounded by the same weighted mean of their bounds, and stays a
//! bound; any other repaired entry gets the standard error above (a bound's magnitude
//! counted as a standard error: the repair's shift is a least-squares correction, not a
//! deterministic one).

use crate::matrix::{sum_bar, Bar, Csr, FormFactors, ROWS_PER_TASK};

/// Which constraints [`repair`] enforces (also the command line's `--repair` values).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Repair {
    /// Keep the estimates (rows over 1 are still reported).
    #[default]
    None,
    /// A_i F_ij = A_j F_ji by error-weighted means.
    Reciprocity,
    /// Rows sum to 1 by a least-squares correction (closed scenes only).
    Closure,
    /// Both, alternately until they hold together.
    Both,
}

/// A row whose sum exceeds 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RowOver {
    /// Row (emitting patch).
    pub row: usize,
    /// Its sum.
    pub sum: f64,
    /// The sum's bar ([`crate::matrix::sum_bar`]: standard errors in quadrature, bounds
    /// linearly).
    pub bar: Bar,
}

/// What [`check`] found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Bounds {
    /// Rows summing to more than 1, in row order.
    pub rows_over_one: Vec<RowOver>,
    /// Entries outside `[0, 1]` or not finite: `(i, j, F_ij)`.
    pub out_of_range: Vec<(usize, usize, f64)>,
}

impl Bounds {
    /// Rows over 1 by more than `k` standard errors plus their bounds (not explained by
    /// the noise or the quadrature; see [`crate::matrix::over_one`]).
    pub fn significant(&self, k: f64) -> usize {
        self.rows_over_one
            .iter()
            .filter(|r| crate::matrix::over_one(r.sum, r.bar, k))
            .count()
    }

    /// One line for summaries.
    pub fn summary(&self) -> String {
        let worst = self
            .rows_over_one
            .iter()
            .max_by(|a, b| a.sum.total_cmp(&b.sum));
        let mut s = format!(
            "{} rows sum over 1 ({} by more than 3 standard errors plus their bounds)",
            self.rows_over_one.len(),
            self.significant(3.0)
        );
        if let Some(w) = worst {
            s += &format!(", worst row {} = {:.6} {}", w.row, w.sum, w.bar);
        }
        if !self.out_of_range.is_empty() {
            s += &format!("; {} entries OUT OF [0, 1]", self.out_of_range.len());
        }
        s
    }
}

/// Rows summing over 1 and entries outside `[0, 1]`.
pub fn check(ff: &FormFactors) -> Bounds {
    check_rows(&ff.f, &ff.se, 0)
}

/// [`check`] of rows `lo..` of a matrix held as `f` with the standard errors `se` (its
/// row `r` is the matrix's row `lo + r`, as in a [`crate::matrix::Block`]).
pub fn check_rows(f: &Csr, se: &[f32], lo: usize) -> Bounds {
    use rayon::prelude::*;
    let (ptr, ind, val) = (f.indptr(), f.indices(), f.data());
    // Rows in parallel, each thread's run of rows in order and the runs joined in order,
    // so the lists come out in row order whatever the threads.
    (0..f.rows())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .fold(Bounds::default, |mut b, r| {
            let i = lo + r;
            let (a, z) = (ptr.index(r), ptr.index(r + 1));
            let sum: f64 = val[a..z].iter().sum();
            if sum > 1.0 || !sum.is_finite() {
                b.rows_over_one.push(RowOver {
                    row: i,
                    sum,
                    // As `FormFactors::row_sum_bar`.
                    bar: sum_bar(&se[a..z]),
                });
            }
            for (&j, &f) in ind[a..z].iter().zip(&val[a..z]) {
                if !f.is_finite() || !(0.0..=1.0).contains(&f) {
                    b.out_of_range.push((i, j as usize, f));
                }
            }
            b
        })
        .reduce(Bounds::default, |mut a, b| {
            a.rows_over_one.extend(b.rows_over_one);
            a.out_of_range.extend(b.out_of_range);
            a
        })
}

/// What [`repair`] changed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RepairReport {
    /// The repair applied.
    pub repair: Repair,
    /// Bounds before the repair.
    pub before: Bounds,
    /// Bounds after the repair.
    pub after: Bounds,
    /// Largest `|F'_ij - F_ij| / σ_ij` over entries with `σ_ij > 0`.
    pub max_shift_sigmas: f64,
    /// Alternating rounds (1 for a single constraint, 0 for none).
    pub rounds: usize,
}

/// [`repair`] taking the matrix: with [`Repair::None`] it is returned as it is, with only
/// the bounds checked (no copy: at 10⁵ patches a copy is gigabytes).
pub fn apply(ff: FormFactors, how: Repair) -> (FormFactors, RepairReport) {
    if how != Repair::None {
        return repair(&ff, how);
    }
    let before = check(&ff);
    let report = RepairReport {
        repair: how,
        after: before.clone(),
        before,
        max_shift_sigmas: 0.0,
        rounds: 0,
    };
    (ff, report)
}

/// Applies `how` to a copy of `ff` (same sparsity pattern) and reports bounds before and
/// after.
pub fn repair(ff: &FormFactors, how: Repair) -> (FormFactors, RepairReport) {
    let before = check(ff);
    let mut out = ff.clone();
    let sigma0 = widen(&ff.se);
    let rounds = match how {
        Repair::None => 0,
        Repair::Reciprocity => {
            reciprocity(&mut out, &sigma0, true);
            1
        }
        Repair::Closure => {
            closure(&mut out, &sigma0, true);
            1
        }
        Repair::Both => {
            // Standard errors from one pass of each; values iterate in the fixed metric.
            reciprocity(&mut out, &sigma0, true);
            let metric = widen(&out.se);
            closure(&mut out, &metric, true);
            let mut rounds = 1;
            while rounds < 1000 {
                let prev = out.f.data().to_vec();
                reciprocity(&mut out, &metric, false);
                closure(&mut out, &metric, false);
                rounds += 1;
                let moved = prev
                    .iter()
                    .zip(out.f.data())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                if moved <= 1e-12 {
                    break;
                }
            }
            rounds
        }
    };
    let max_shift_sigmas =
        ff.f.data()
            .iter()
            .zip(out.f.data())
            .zip(&sigma0)
            .filter(|(_, &s)| s > 0.0)
            .map(|((a, b), s)| (a - b).abs() / s)
            .fold(0.0, f64::max);
    let after = check(&out);
    (
        out,
        RepairReport {
            repair: how,
            before,
            after,
            max_shift_sigmas,
            rounds,
        },
    )
}

/// The stored bars' magnitudes ([`Bar::magnitude`]) as `f64` weights.
fn widen(se: &[f32]) -> Vec<f64> {
    se.iter().map(|&s| Bar::of(s).magnitude()).collect()
}

/// Index into `data` of the stored entry (i, j).
fn slot(ff: &FormFactors, i: usize, j: usize) -> Option<usize> {
    ff.f.nnz_index(i, j).map(|k| k.0)
}

/// Inverse-variance weighted mean of `A_i F_ij` and `A_j F_ji` for every pair stored both
/// ways, with `sigma` the standard errors used as weights; `update_se` also stores the
/// standard error of the mean.
fn reciprocity(ff: &mut FormFactors, sigma: &[f64], update_se: bool) {
    let n = ff.len();
    let area = ff.area.clone();
    let mut changes: Vec<(usize, f64, f64)> = Vec::new();
    for i in 0..n {
        let (lo, hi) = (ff.f.indptr().index(i), ff.f.indptr().index(i + 1));
        for k in lo..hi {
            let j = ff.f.indices()[k] as usize;
            if j <= i {
                continue;
            }
            let Some(kt) = slot(ff, j, i) else { continue };
            let (g1, g2) = (area[i] * ff.f.data()[k], area[j] * ff.f.data()[kt]);
            let (v1, v2) = ((area[i] * sigma[k]).powi(2), (area[j] * sigma[kt]).powi(2));
            // Both bounded: the weighted mean's error is within the weighted mean of the
            // bounds, stored as a bound (a negative stored bar).
            let bounds = Bar::of(ff.se[k]).se == 0.0 && Bar::of(ff.se[kt]).se == 0.0;
            let (g, s) = if v1 == 0.0 && v2 == 0.0 {
                (0.5 * (g1 + g2), 0.0)
            } else if v1 == 0.0 {
                (g1, 0.0)
            } else if v2 == 0.0 {
                (g2, 0.0)
            } else {
                let (w1, w2) = (1.0 / v1, 1.0 / v2);
                let g = (g1 * w1 + g2 * w2) / (w1 + w2);
                if bounds {
                    let b = (v1.sqrt() * w1 + v2.sqrt() * w2) / (w1 + w2);
                    (g, -b)
                } else {
                    (g, (1.0 / (w1 + w2)).sqrt())
                }
            };
            changes.push((k, g / area[i], s / area[i]));
            changes.push((kt, g / area[j], s / area[j]));
        }
    }
    for (k, f, s) in changes {
        ff.f.data_mut()[k] = f;
        if update_se {
            ff.se[k] = Bar::of(s).stored_f32();
        }
    }
}

/// Weighted least-squares correction of each row to sum 1 (see the module docs).
#[allow(clippy::needless_range_loop)] // indexes two parallel arrays
fn closure(ff: &mut FormFactors, sigma: &[f64], update_se: bool) {
    let n = ff.len();
    for i in 0..n {
        let (lo, hi) = (ff.f.indptr().index(i), ff.f.indptr().index(i + 1));
        if lo == hi {
            continue;
        }
        let sum: f64 = ff.f.data()[lo..hi].iter().sum();
        // Entries the bound `F >= 0` holds at 0 (a row over 1 takes its excess from the
        // noisiest entries first, and a small noisy one would go below 0): the others share
        // the deficit, until none would cross the bound.
        let mut pinned = vec![false; hi - lo];
        let (lambda, var) = loop {
            let (mut kept, mut v_sum) = (0.0, 0.0);
            for k in lo..hi {
                if !pinned[k - lo] {
                    kept += ff.f.data()[k];
                    v_sum += sigma[k] * sigma[k];
                }
            }
            if v_sum <= 0.0 {
                break (0.0, 0.0);
            }
            let lambda = (1.0 - kept) / v_sum;
            let mut crossed = false;
            for k in lo..hi {
                if !pinned[k - lo] && ff.f.data()[k] + sigma[k] * sigma[k] * lambda < 0.0 {
                    pinned[k - lo] = true;
                    crossed = true;
                }
            }
            if !crossed {
                break (lambda, v_sum);
            }
        };
        if var > 0.0 {
            for k in lo..hi {
                let v = sigma[k] * sigma[k];
                if pinned[k - lo] {
                    ff.f.data_mut()[k] = 0.0;
                    continue;
                }
                ff.f.data_mut()[k] += v * lambda;
                if update_se {
                    ff.se[k] = (v - v * v / var).max(0.0).sqrt() as f32;
                }
            }
        } else if sum > 0.0 {
            for k in lo..hi {
                ff.f.data_mut()[k] /= sum;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matrix::Entry;

    fn matrix(rows: Vec<Vec<(u32, f64, f64)>>, area: Vec<f64>) -> FormFactors {
        let rows = rows
            .into_iter()
            .map(|r| r.into_iter().map(|(j, f, se)| Entry { j, f, se }).collect())
            .collect();
        FormFactors::from_rows(rows, area, 0, 0.0, "test".into(), 0)
    }

    #[test]
    fn a_row_over_one_is_reported_and_never_kept_silently() {
        let ff = matrix(
            vec![
                vec![(1, 0.7, 0.05), (2, 0.5, 0.05)],
                vec![(0, 0.6, 0.01), (2, 0.4, 0.01)],
                vec![(0, 0.5, 0.0), (1, 0.5, 0.0)],
            ],
            vec![1.0, 1.0, 1.0],
        );
        let b = check(&ff);
        assert_eq!(b.rows_over_one.len(), 1);
        assert_eq!(b.rows_over_one[0].row, 0);
        assert!((b.rows_over_one[0].sum - 1.2).abs() < 1e-12);
        assert!(b.summary().contains("1 rows sum over 1"), "{}", b.summary());
        // No repair: still reported, values untouched.
        let (same, rep) = repair(&ff, Repair::None);
        assert_eq!(same.f, ff.f);
        assert_eq!(rep.after.rows_over_one.len(), 1);
        // Closure: the report keeps the finding, the repaired row sums to 1.
        let (fixed, rep) = repair(&ff, Repair::Closure);
        assert_eq!(rep.before.rows_over_one.len(), 1);
        assert!((fixed.row_sum(0) - 1.0).abs() < 1e-12);
        assert!(rep.after.rows_over_one.iter().all(|r| r.sum - 1.0 < 1e-12));
        assert_eq!(fixed.f.nnz(), ff.f.nnz());
    }

    /// Rows are checked in parallel runs; what is found comes out in row order, as one
    /// pass would list it, however the runs fall.
    #[test]
    fn bounds_come_out_in_row_order() {
        let n = 20_000;
        let over = [7usize, 4_099, 4_100, 12_345, 19_999];
        let outside = [(3usize, -0.25), (8_191, 1.5), (15_000, f64::NAN)];
        let rows = (0..n)
            .map(|i| {
                let mut f = if over.contains(&i) { 0.6 } else { 0.3 };
                if let Some(&(_, v)) = outside.iter().find(|&&(r, _)| r == i) {
                    f = v;
                }
                vec![
                    ((i + 1) as u32 % n as u32, f, 0.01),
                    ((i + 2) as u32 % n as u32, 0.45, 0.01),
                ]
            })
            .collect();
        let b = check(&matrix(rows, vec![1.0; n]));
        let got: Vec<usize> = b.rows_over_one.iter().map(|r| r.row).collect();
        // Row 15,000's sum is NaN: reported with the rows over one.
        assert_eq!(got, [7, 4_099, 4_100, 8_191, 12_345, 15_000, 19_999]);
        let got: Vec<usize> = b.out_of_range.iter().map(|e| e.0).collect();
        assert_eq!(got, [3, 8_191, 15_000]);
    }

    /// A row 0.3 over 1 whose noisiest entry is small: the unconstrained shift would take it
    /// to 0.01 - 0.3 × 0.1² / (0.1² + 2 × 0.01²) < 0. It is held at 0, and the two others
    /// share the rest of the excess equally (equal bars), so the row sums to 1 with every
    /// entry in [0, 1].
    #[test]
    fn closure_keeps_entries_non_negative() {
        let ff = matrix(
            vec![
                vec![(1, 0.7, 0.01), (2, 0.59, 0.01), (3, 0.01, 0.1)],
                vec![],
                vec![],
                vec![],
            ],
            vec![1.0; 4],
        );
        let (fixed, _) = repair(&ff, Repair::Closure);
        assert_eq!(fixed.get(0, 3), 0.0);
        assert!((fixed.row_sum(0) - 1.0).abs() < 1e-12);
        // The two others lose (1.29 - 1) / 2 each.
        assert!(
            (fixed.get(0, 1) - (0.7 - 0.145)).abs() < 1e-9,
            "{}",
            fixed.get(0, 1)
        );
        assert!((fixed.get(0, 2) - (0.59 - 0.145)).abs() < 1e-9);
        assert_eq!(fixed.f.nnz(), ff.f.nnz());
    }

    #[test]
    fn reciprocity_takes_the_weighted_mean_and_keeps_the_pattern() {
        // A_0 = 1, A_1 = 2: A_0 F_01 = 0.30 ± 0.01, A_1 F_10 = 2 × 0.16 = 0.32 ± 0.02.
        let ff = matrix(
            vec![
                vec![(1, 0.30, 0.01), (2, 0.1, 0.01)],
                vec![(0, 0.16, 0.01)],
                vec![],
            ],
            vec![1.0, 2.0, 1.0],
        );
        let (r, _) = repair(&ff, Repair::Reciprocity);
        // The weights are those of the stored (f32) standard errors.
        let s = f64::from(0.01f32);
        let (w1, w2) = (1.0 / s.powi(2), 1.0 / (2.0 * s).powi(2));
        let g = (0.30 * w1 + 0.32 * w2) / (w1 + w2);
        assert!((r.get(0, 1) - g).abs() < 1e-12);
        assert!((2.0 * r.get(1, 0) - g).abs() < 1e-12);
        // The repaired bar is stored as f32 too: equal to the rounding of the exact one.
        let se = f64::from((1.0 / (w1 + w2)).sqrt() as f32);
        assert_eq!(r.stderr(0, 1), se);
        // (0, 2) has no transpose stored: kept, and (2, 0) not created.
        assert_eq!(r.get(0, 2), 0.1);
        assert_eq!(r.f.nnz(), ff.f.nnz());
    }

    #[test]
    fn both_constraints_hold_together() {
        let ff = matrix(
            vec![
                vec![(1, 0.45, 0.02), (2, 0.50, 0.03)],
                vec![(0, 0.52, 0.02), (2, 0.50, 0.02)],
                vec![(0, 0.48, 0.03), (1, 0.55, 0.01)],
            ],
            vec![1.0, 1.0, 1.0],
        );
        let (r, rep) = repair(&ff, Repair::Both);
        // Three patches, symmetric, zero diagonal, rows summing to 1: x01 + x02 = x01 + x12
        // = x02 + x12 = 1 has the one solution x = 1/2, whatever the weights.
        for i in 0..3 {
            assert!((r.row_sum(i) - 1.0).abs() < 1e-9, "row {i}");
            for j in 0..3 {
                assert!((r.get(i, j) - r.get(j, i)).abs() < 1e-9);
                if i != j {
                    assert!(
                        (r.get(i, j) - 0.5).abs() < 1e-9,
                        "({i}, {j}) {}",
                        r.get(i, j)
                    );
                }
            }
        }
        // The largest shift is F_21: 0.55 -> 0.50 with a bar of 0.01 (stored as f32), 5 bars.
        let expected = 0.05 / f64::from(0.01f32);
        assert!(rep.rounds > 1, "{rep:?}");
        assert!((rep.max_shift_sigmas - expected).abs() < 1e-6, "{rep:?}");
    }
}
