//! The radiosity solve on a matrix distributed by rows over the ranks of a run
//! ([`crate::cluster`]): Jacobi, with the iterate all-gathered once per sweep.
//!
//! Each rank holds a contiguous block of full rows of `F` (`crate::matrix::Block`, as
//! `crate::formfactor::shard` leaves it) and every patch's `rho`, `E` and area (`O(n)`,
//! replicated). A sweep computes the rank's rows of `B^{k+1} = E + diag(rho) F B^k` and
//! their residuals from the whole `B^k`; the residual measures (per channel: the largest
//! absolute residual and the largest per-patch measure, six numbers) are reduced by a
//! maximum over ranks, and, unless the iteration stops there, the new rows are
//! all-gathered into the whole `B^{k+1}` on every rank (`24 n` bytes per sweep in all).
//!
//! Everything a rank computes is what [`super::Jacobi`] computes for the same rows: the
//! same arithmetic in the same order per row (`gather_row`), and reductions
//! that are maxima (exact in any order). So the iterates, the residuals, the stopping
//! sweep and the returned `B` are those of one process **bit for bit**, on any number of
//! ranks, and the stopping rule is the one of the [module docs](super): the relative
//! residual and the per-patch measure both within `tolerance`.
//!
//! Jacobi because its sweep reads only the previous iterate: Gauss–Seidel's sweep is
//! sequential (row `i` reads rows `< i` of the same sweep), and conjugate gradients on
//! the symmetric form needs the transposed rows and two global dot products per
//! iteration, whose sums would depend on the number of ranks. The other methods run on
//! rank 0 with the whole matrix gathered there (the pipeline decides; see README).

use std::time::Instant;

use rayon::prelude::*;

use super::{
    check_matrix, check_patches, divergence, diverging, finish, gather_row, jacobi, max3, worst,
    Floor, Gain, Options, Outcome, Rows, Scale, SolveReport,
};
use crate::cluster::{in_pool, Cluster};
use crate::error::{Error, Result};
use crate::matrix::Csr;

/// Rows `lo..lo + f.rows()` of the radiosity system, held by one rank.
#[derive(Clone, Copy, Debug)]
pub struct BlockSystem<'a> {
    /// First row.
    pub lo: usize,
    /// The rows of `F` (all columns), stored by rows.
    pub f: &'a Csr,
    /// Diffuse reflectance of every patch.
    pub rho: &'a [[f64; 3]],
    /// Emitted exitance of every patch.
    pub emit: &'a [[f64; 3]],
    /// Area of every patch.
    pub area: &'a [f64],
}

impl BlockSystem<'_> {
    /// The checks of [`super::System::new`] that concern this block's rows, and those of
    /// every patch's values (the same on every rank).
    pub fn validate(&self) -> Result<()> {
        let n = self.rho.len();
        if self.f.cols() != n || self.emit.len() != n || self.area.len() != n {
            return Err(Error::Config(format!(
                "a block of {} columns with {} reflectances, {} emissions and {} areas",
                self.f.cols(),
                n,
                self.emit.len(),
                self.area.len()
            )));
        }
        if self.lo + self.f.rows() > n || !self.f.is_csr() {
            return Err(Error::Config(format!(
                "rows {}..{} of {n} patches, stored by rows",
                self.lo,
                self.lo + self.f.rows()
            )));
        }
        check_patches(self.rho, self.emit, self.area)?;
        check_matrix(self.f, self.lo, self.rho)
    }
}

/// The gain bound of the whole matrix from every rank's block, on every rank.
fn all_gain(local: Gain, cluster: &dyn Cluster) -> Result<Gain> {
    let k = cluster.size();
    let mine = [
        local.gain[0],
        local.gain[1],
        local.gain[2],
        local.patch as f64,
        local.row_sum,
        local.rho,
        local.best,
    ];
    let mut all = vec![0.0; 7 * k];
    cluster.all_gather_f64(&mine, &vec![7; k], &mut all)?;
    Ok(all
        .chunks_exact(7)
        .map(|v| Gain {
            gain: [v[0], v[1], v[2]],
            patch: v[3] as usize,
            row_sum: v[4],
            rho: v[5],
            best: v[6],
        })
        .reduce(Gain::merge)
        .unwrap_or(local))
}

/// Bytes the all-gathers of one sweep move, over all ranks: the ones a solve of `n`
/// patches on `ranks` ranks sends per sweep (each rank receives the others' rows).
pub fn bytes_per_sweep(n: usize, ranks: usize) -> u64 {
    (24 * n * ranks.saturating_sub(1)) as u64
}

/// Jacobi on the distributed system ([module docs](self)); collective. Returns the whole
/// `B` on every rank, and the report one process's [`super::Jacobi`] would give.
pub fn jacobi(
    sys: &BlockSystem,
    opts: &Options,
    cluster: &dyn Cluster,
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    let start = Instant::now();
    opts.validate()?;
    sys.validate()?;
    let rows = Rows::new(sys.f);
    let scale = Scale::new(sys.emit);
    let floor = Floor::new(opts, &scale);
    let gain = all_gain(Gain::of_rows(sys.rho, &rows, sys.lo), cluster)?;
    let notes = gain.notes();
    let (n, k, lo) = (sys.rho.len(), cluster.size(), sys.lo);
    // Rows per rank, as f64 counts (three per row).
    let mut per_rank = vec![0.0; k];
    cluster.all_gather_f64(&[rows.len() as f64], &vec![1; k], &mut per_rank)?;
    let counts: Vec<usize> = per_rank.iter().map(|&r| 3 * r as usize).collect();
    if counts.iter().sum::<usize>() != 3 * n {
        return Err(cluster.fail(format!(
            "the blocks hold {} rows of {n}",
            counts.iter().sum::<usize>() / 3
        )));
    }
    let mut b = sys.emit.to_vec();
    let mut next = b.clone();
    let mut mine = vec![[0.0; 3]; rows.len()];
    let mut history = Vec::new();
    let mut it = 0;
    let pool = cluster.compute_pool();
    loop {
        let (abs, per_patch) = in_pool(pool, || {
            mine.par_iter_mut()
                .enumerate()
                .map(|(r, out)| {
                    let i = lo + r;
                    *out = gather_row(rows.row(r), sys.emit[i], sys.rho[i], &b);
                    let res = [0, 1, 2].map(|c| out[c] - b[i][c]);
                    (
                        res.map(f64::abs),
                        floor.of_residual_at(sys.emit[i], res, b[i]),
                    )
                })
                .reduce(
                    || ([0.0; 3], [0.0; 3]),
                    |x, y| (max3(x.0, y.0), max3(x.1, y.1)),
                )
        });
        let mut m = [
            abs[0],
            abs[1],
            abs[2],
            per_patch[0],
            per_patch[1],
            per_patch[2],
        ];
        cluster.all_max(&mut m)?;
        let r = scale.rel([m[0], m[1], m[2]]);
        let p = worst([m[3], m[4], m[5]]);
        history.push(r);
        if diverging(r) {
            return Err(divergence(jacobi::NAME, it, r, opts, &gain));
        }
        if (r <= opts.tolerance && p <= opts.tolerance) || it >= opts.max_iterations {
            let out = Outcome {
                b,
                iterations: it,
                residual: r,
                patch_residual: p,
                history,
                notes,
            };
            return finish(jacobi::NAME, out, opts, &gain, start);
        }
        cluster.all_gather_f64(mine.as_flattened(), &counts, next.as_flattened_mut())?;
        std::mem::swap(&mut b, &mut next);
        it += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use super::*;
    use crate::cluster::Local;

    /// On 1 to 4 ranks, any split of the rows: the radiosity and the report of one
    /// process's Jacobi, bit for bit.
    #[test]
    fn distributed_jacobi_is_the_single_process_jacobi() {
        let owned = random(97, 9, 5);
        let sys = owned.sys();
        let (want, report) = Jacobi.solve(&sys, &Options::default()).unwrap();
        assert!(report.converged && report.iterations > 3);
        for k in 1..=4 {
            let out = Local::run(k, |c| {
                let n = owned.f.rows();
                let (lo, hi) = (n * c.rank() / k, n * (c.rank() + 1) / k);
                let mut t = crate::matrix::Triplets::new((hi - lo, n));
                for i in lo..hi {
                    for (j, &v) in owned.f.outer_view(i).unwrap().iter() {
                        t.add_triplet(i - lo, j, v);
                    }
                }
                let f = t.to_csr();
                let block = BlockSystem {
                    lo,
                    f: &f,
                    rho: &owned.rho,
                    emit: &owned.emit,
                    area: &owned.area,
                };
                jacobi(&block, &Options::default(), c).unwrap()
            });
            for (b, r) in out {
                assert_eq!(b, want, "{k} ranks");
                assert_eq!(r.iterations, report.iterations);
                assert_eq!(r.history, report.history);
                assert_eq!(r.residual, report.residual);
                assert_eq!(r.patch_residual, report.patch_residual);
                assert_eq!(r.notes, report.notes);
            }
        }
    }
}
