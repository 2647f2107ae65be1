//! The form-factor matrix: rows assembled into a `sprs` CSR matrix, with per-entry
//! standard errors and the physical diagnostics (row sums, reciprocity).
//!
//! Properties checked (radiosidade.md, "Teorema da Reciprocidade"): in a closed
//! environment every row sums to 1, and `A_i F_ij = A_j F_ji`.

use sprs::{CsMat, TriMat};

use crate::formfactor::Entry;

/// A form-factor matrix and how it was made.
#[derive(Clone, Debug)]
pub struct FormFactors {
    /// `F[i, j]`: fraction of the energy leaving patch i that arrives at patch j (CSR).
    pub f: CsMat<f64>,
    /// Standard error of each stored entry, aligned with `f.data()`.
    pub se: Vec<f64>,
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
}

/// Builds the CSR arrays one row at a time, so that rows can be freed as they are added
/// (no dense `N x N` anything, and no second copy of the whole matrix).
#[derive(Debug, Default)]
pub struct CsrBuilder {
    indptr: Vec<usize>,
    indices: Vec<usize>,
    data: Vec<f64>,
    se: Vec<f64>,
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

    /// Appends the next row (entries in any order; duplicates are merged).
    pub fn push_row(&mut self, row: &mut Vec<Entry>) {
        row.sort_unstable_by_key(|e| e.j);
        row.dedup_by(|b, a| {
            // Merge duplicates (cannot happen with the built-in estimators).
            if a.j == b.j {
                a.f += b.f;
                a.se = (a.se * a.se + b.se * b.se).sqrt();
                true
            } else {
                false
            }
        });
        for e in row.iter() {
            self.indices.push(e.j as usize);
            self.data.push(e.f);
            self.se.push(e.se);
        }
        self.indptr.push(self.indices.len());
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
        let f = CsMat::new((n, n), self.indptr, self.indices, self.data);
        FormFactors {
            f,
            se: self.se,
            area,
            rays,
            seconds,
            estimator,
            seed,
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
    /// Entries outside [0, 1] or not finite.
    pub out_of_range: usize,
    /// Stored entries.
    pub nnz: usize,
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
        std::mem::size_of::<usize>() + 2 * std::mem::size_of::<f64>();
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

    /// Standard error of `F[i, j]` (0 when not stored).
    pub fn stderr(&self, i: usize, j: usize) -> f64 {
        self.f.nnz_index(i, j).map(|k| self.se[k.0]).unwrap_or(0.0)
    }

    /// Sum of row `i`.
    pub fn row_sum(&self, i: usize) -> f64 {
        self.f
            .outer_view(i)
            .map(|r| r.data().iter().sum())
            .unwrap_or(0.0)
    }

    /// Standard error of the sum of row `i` (entries' errors added in quadrature).
    pub fn row_sum_stderr(&self, i: usize) -> f64 {
        let (lo, hi) = (self.f.indptr().index(i), self.f.indptr().index(i + 1));
        self.se[lo..hi].iter().map(|s| s * s).sum::<f64>().sqrt()
    }

    /// Row sums, reciprocity and range checks.
    pub fn diagnostics(&self) -> Diagnostics {
        let n = self.len();
        let mut d = Diagnostics {
            min_row_sum: f64::INFINITY,
            max_row_sum: f64::NEG_INFINITY,
            nnz: self.f.nnz(),
            ..Default::default()
        };
        for (i, row) in self.f.outer_iterator().enumerate() {
            let s: f64 = row.data().iter().sum();
            if s < d.min_row_sum {
                d.min_row_sum = s;
            }
            if s > d.max_row_sum {
                d.max_row_sum = s;
                d.max_row = i;
            }
            for (j, &f) in row.iter() {
                if !f.is_finite() || !(0.0..=1.0).contains(&f) {
                    d.out_of_range += 1;
                }
                let fij = self.area[i] * f;
                let fji = self.area[j] * self.get(j, i);
                let m = fij.abs().max(fji.abs());
                if m > 0.0 {
                    d.reciprocity = d.reciprocity.max((fij - fji).abs() / m);
                }
            }
        }
        if n == 0 {
            d.min_row_sum = 0.0;
            d.max_row_sum = 0.0;
        }
        d
    }

    /// The matrix as triplets, for writers.
    pub fn triplets(&self) -> TriMat<f64> {
        let mut t = TriMat::with_capacity(self.f.shape(), self.f.nnz());
        for (i, row) in self.f.outer_iterator().enumerate() {
            for (j, &v) in row.iter() {
                t.add_triplet(i, j, v);
            }
        }
        t
    }
}
