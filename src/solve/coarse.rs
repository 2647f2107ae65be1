//! A coarse correction between the sweeps of [`Sor`](super::Sor), for bright rooms.
//!
//! In a closed room of high albedo the error a sweep leaves is nearly the same over large
//! groups of patches (light bouncing between whole walls), and a sweep shrinks that part
//! only by about the room's gain per pass: hundreds of sweeps at `rho` 0.995. A two-level
//! step removes it directly (a two-level method with piecewise constant prolongation on
//! aggregates, as in Braess 1995, "Towards algebraic multigrid for elliptic problems of
//! second order", *Computing* 55; for radiosity it is the "ambient" term of Cohen, Chen,
//! Wallace and Greenberg 1988, "A progressive refinement approach to fast radiosity image
//! generation", made exact on aggregates instead of estimated for the whole scene):
//!
//! 1. The patches are grouped into at most [`MAX_AGGREGATES`] aggregates: runs of
//!    consecutive patches with the same reflectance (the mesher numbers a face's patches
//!    one after the other, so a run lies on one face or on neighbouring faces of one
//!    material), cut into equal pieces. Patches that reflect nothing (`rho = 0`) or see
//!    nothing (an empty row) belong to none: after the first sweep their value is exact.
//! 2. With `R` the area-weighted mean over an aggregate and `P` the prolongation that adds
//!    an aggregate's value to each of its patches, the coarse system is
//!    `M_c = R (I - diag(rho) F) P`, `M_c[a][g] = δ_ag - rho_a / A_a sum_{i in a, j in g}
//!    A_i F_ij`: a dense matrix of at most 64 x 64 per channel, factorised once (the
//!    direct solve's LU, `faer`).
//! 3. After a sweep has made the iterate `B`, its aggregated residual `R r(B)`, `r = E +
//!    diag(rho) F B - B`, is `1/A_a (sum_{i in a} A_i (E_i - B_i) + rho_a sum_j D_aj B_j)`
//!    with the couplings `D_aj = sum_{i in a} A_i F_ij` (one pass over `F` to build; `a x n`
//!    numbers, 8 bytes each: 150 MB for 64 aggregates of 300,000 patches), and the iterate
//!    becomes `B + P M_c^-1 R r(B)`: the exact solution on the aggregates' means, where
//!    the sweeps are slowest.
//!
//! It is used when the system's gain bound (`max_i rho_i sum_j F_ij`, which the solvers
//! already compute) is at least [`BRIGHT`] and below 1, and while the residual of the
//! sweeps stays below [`GROWTH`] times the least it has been. Not in dimmer rooms: in the
//! open Cornell box (gain about 0.78) a temporary build that corrected every sweep took
//! 17 sweeps where SOR takes 11 (the slow part of the error there is not constant over
//! aggregates, and the correction moves dim patches by their aggregate's mean, which the
//! per-patch rule then has to see undone). Measured gains in bright closed rooms are in
//! docs/SOLVERS.md. The returned iterate and its residuals are the sweeps' own, so the
//! solution and the stopping rule are unchanged.

use faer::Mat;

use super::direct::Lu;
use super::{Rows, System};

/// Most aggregates: the couplings hold `aggregates x patches` numbers.
pub const MAX_AGGREGATES: usize = 64;

/// The gain bound from which the correction is used.
pub const BRIGHT: f64 = 0.9;

/// The correction stops for good should the residual grow past this many times the least
/// it has been (a correction that does not help; the sweeps alone converge from anywhere).
pub const GROWTH: f64 = 100.0;

/// The aggregates, their couplings and the factorised coarse systems of one solve.
pub(crate) struct Coarse {
    /// The aggregate of each patch, or [`NONE`].
    of: Vec<u32>,
    /// Area of each aggregate.
    area: Vec<f64>,
    /// Reflectance of each aggregate (its patches').
    rho: Vec<[f64; 3]>,
    /// `D_aj`, row `a` from `a * n`.
    couplings: Vec<f64>,
    /// Per channel, the LU factors of the coarse system.
    lu: [Lu; 3],
}

/// No aggregate.
const NONE: u32 = u32::MAX;

impl Coarse {
    /// The correction for `sys`, or `None` when its gain bound `gain` (largest over
    /// channels) is not in `[BRIGHT, 1)` (from 1 on the sweeps may diverge, and the
    /// solvers say so rather than solve an unphysical system), fewer than two patches
    /// belong to an aggregate, there would be more than [`MAX_AGGREGATES`], or a coarse
    /// system is singular.
    pub(crate) fn new(sys: &System, rows: &Rows, gain: f64) -> Option<Coarse> {
        let n = sys.len();
        if !(BRIGHT..1.0).contains(&gain) || n < 2 {
            return None;
        }
        let takes = |i: usize| sys.rho[i].iter().any(|&r| r > 0.0) && !rows.row(i).0.is_empty();
        let members = (0..n).filter(|&i| takes(i)).count();
        if members < 2 {
            return None;
        }
        // Runs of equal reflectance, cut into pieces of at most `piece` patches: at most
        // MAX_AGGREGATES / 2 pieces from the cutting, and each run's last piece.
        let piece = members.div_ceil(MAX_AGGREGATES / 2).max(1);
        let mut of = vec![NONE; n];
        let (mut count, mut run) = (0u32, 0usize);
        let mut last: Option<usize> = None;
        for i in (0..n).filter(|&i| takes(i)) {
            let same = last.is_some_and(|l| l + 1 == i && sys.rho[l] == sys.rho[i]);
            if !same || run == piece {
                count += 1;
                run = 0;
            }
            of[i] = count - 1;
            run += 1;
            last = Some(i);
        }
        let na = count as usize;
        if na > MAX_AGGREGATES {
            return None;
        }
        let mut area = vec![0.0; na];
        let mut rho = vec![[0.0; 3]; na];
        for i in 0..n {
            if of[i] != NONE {
                area[of[i] as usize] += sys.area[i];
                rho[of[i] as usize] = sys.rho[i];
            }
        }
        let couplings = couplings(sys, rows, &of, na);
        // M_c[a][g] = δ_ag - rho_a / A_a sum_{j in g} D_aj.
        let mut sums = vec![0.0f64; na * na];
        for a in 0..na {
            let d = &couplings[a * n..(a + 1) * n];
            for (j, &dj) in d.iter().enumerate() {
                if of[j] != NONE {
                    sums[a * na + of[j] as usize] += dj;
                }
            }
        }
        let lu = [0, 1, 2].map(|c| {
            let m = Mat::<f64>::from_fn(na, na, |a, g| {
                f64::from(u8::from(a == g)) - rho[a][c] / area[a] * sums[a * na + g]
            });
            let (f, pivots) = Lu::of(m);
            (!Lu::singular(pivots, na)).then_some(f)
        });
        let [Some(r), Some(g), Some(b)] = lu else {
            return None;
        };
        let lu = [r, g, b];
        Some(Coarse {
            of,
            area,
            rho,
            couplings,
            lu,
        })
    }

    /// Number of aggregates.
    pub(crate) fn aggregates(&self) -> usize {
        self.area.len()
    }

    /// Adds to `b` the correction `P M_c^-1 R r(b)` (module docs): one pass over `b` and
    /// one over the couplings for all three channels, then a small solve per channel.
    pub(crate) fn correct(&self, sys: &System, b: &mut [[f64; 3]]) {
        let (n, na) = (b.len(), self.area.len());
        let mut rr = vec![[0.0f64; 3]; na];
        for (i, &a) in self.of.iter().enumerate() {
            if a != NONE {
                for c in 0..3 {
                    rr[a as usize][c] += sys.area[i] * (sys.emit[i][c] - b[i][c]);
                }
            }
        }
        for (a, r) in rr.iter_mut().enumerate() {
            let d = &self.couplings[a * n..(a + 1) * n];
            let db = d.iter().zip(b.iter()).fold([0.0f64; 3], |s, (&dj, bj)| {
                [s[0] + dj * bj[0], s[1] + dj * bj[1], s[2] + dj * bj[2]]
            });
            for c in 0..3 {
                r[c] = (r[c] + self.rho[a][c] * db[c]) / self.area[a];
            }
        }
        let delta = [0, 1, 2].map(|c| {
            let mut m = Mat::<f64>::from_fn(na, 1, |a, _| rr[a][c]);
            self.lu[c].solve_in_place(&mut m);
            m
        });
        for (bi, &a) in b.iter_mut().zip(&self.of) {
            if a != NONE {
                for c in 0..3 {
                    bi[c] += delta[c][(a as usize, 0)];
                }
            }
        }
    }
}

/// `D_aj = sum_{i in a} A_i F_ij`, row `a` from `a * n`: each aggregate's rows are summed
/// by one thread (aggregates in parallel).
fn couplings(sys: &System, rows: &Rows, of: &[u32], na: usize) -> Vec<f64> {
    use rayon::prelude::*;
    let n = sys.len();
    let mut d = vec![0.0f64; na * n];
    d.par_chunks_mut(n).enumerate().for_each(|(a, d)| {
        for i in (0..n).filter(|&i| of[i] as usize == a) {
            let (ind, val) = rows.row(i);
            for (&j, &f) in ind.iter().zip(val) {
                d[j as usize] += sys.area[i] * f;
            }
        }
    });
    d
}
