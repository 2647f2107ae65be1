//! Area-to-area Monte Carlo: point pairs on both patches, one occlusion ray per pair.
//!
//! For the unordered pair (a, b), a < b, each of `R` independent replicates draws `n`
//! points `x_k` on a and `n` points `y_k` on b and forms
//!
//! `I = 1/n Σ_k cos θ_x cos θ_y V(x_k, y_k) / (π r_k²)`,
//!
//! an unbiased estimate of `1/(A_a A_b) ∫∫ cos cos V / (π r²)`, so that `F_ab = A_b I` and
//! `F_ba = A_a I` (radiosidade.md, "Fator de Forma" and "Teorema da Reciprocidade").
//! Points are independent uniform ([`Pattern::Uniform`]), or one jittered pair in each cell
//! of a `t x t x t x t` grid of the 4D domain `(x_u, x_v, y_u, y_v)` ([`Pattern::Stratified`]:
//! jittered sampling of the whole double integral, so that the kernel's joint dependence on
//! x and y is stratified, not only its margins; `t = round(sqrt(s))`, `t⁴ ≈ s²` pairs), or are
//! the first `n` points of a 4D Owen-scrambled Sobol sequence, `(x_u, x_v, y_u, y_v)`
//! ([`Pattern::Sobol`]: randomized quasi-Monte Carlo with Burley's hash-based Owen
//! scrambling and index shuffling, "Practical Hash-based Owen Scrambling", JCGT 2020, via
//! the `sobol_burley` crate). Each replicate of each pair gets its own scramble seed, drawn
//! from the `(seed, a, b, replicate)` stream, so the replicates are independent and each is
//! unbiased; their spread gives the standard error, as for the other patterns. The
//! standard error is the standard deviation of the replicate means over `sqrt(R)`.
//!
//! Pairs with one patch wholly behind the other's plane are culled without rays; a sample
//! pair facing away (cos <= 0) contributes 0 without a ray. Each stream is keyed on
//! `(seed, a, b, replicate)`, so the result does not depend on the thread count.
//!
//! Patches that share an edge make `cos cos / r²` unbounded: the estimate stays finite and
//! unbiased but its variance is infinite, and the replicate error bar is then only
//! indicative (the heavy tail shows as replicates that disagree).

use glam::Vec3;

use super::{Context, Entry, Estimator, Row};
use crate::sampling::Pcg32;

/// How points are placed on each patch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    /// Independent uniform points.
    Uniform,
    /// One jittered pair per cell of a 4D grid over both patches.
    Stratified,
    /// Owen-scrambled 4D Sobol points (randomized QMC); best with `strata²` a power of 2.
    Sobol,
}

/// Area-to-area Monte Carlo estimator.
#[derive(Clone, Debug)]
pub struct AreaMc {
    /// Point placement.
    pub pattern: Pattern,
    /// Samples per side: each replicate uses `strata²` point pairs (`t⁴`, `t =
    /// round(sqrt(strata))`, for the stratified pattern).
    pub strata: usize,
    /// Independent replicates (>= 2) for the standard error.
    pub replicates: usize,
}

impl Default for AreaMc {
    fn default() -> Self {
        AreaMc {
            pattern: Pattern::Stratified,
            strata: 4,
            replicates: 4,
        }
    }
}

impl AreaMc {
    /// Cells per dimension of the 4D grid of [`Pattern::Stratified`]: `round(sqrt(strata))`,
    /// so that a replicate has `t⁴ ≈ strata²` pairs (exactly, when `strata` is a square).
    pub fn grid(&self) -> usize {
        ((self.strata as f64).sqrt().round() as usize).max(1)
    }

    /// Point pairs per replicate: `strata²`, or `t⁴` for the stratified pattern.
    pub fn pairs_per_replicate(&self) -> usize {
        match self.pattern {
            Pattern::Stratified => self.grid().pow(4),
            _ => self.strata * self.strata,
        }
    }

    /// Point pairs per patch pair.
    pub fn pairs(&self) -> usize {
        self.pairs_per_replicate() * self.replicates.max(2)
    }
}

/// Plane test: true when every corner of patch `b` lies on or behind the plane of `a`.
fn behind(ctx: &Context, a: usize, b: usize) -> bool {
    let p = ctx.patches;
    let (n, c) = (p.normal[a], p.centroid[a]);
    let tol = 1e-6 * p.diagonal as f32;
    let (pts, k) = p.corner_points(b);
    pts[..k].iter().all(|&q| n.dot(q - c) <= tol)
}

impl Estimator for AreaMc {
    fn name(&self) -> String {
        let kind = match self.pattern {
            Pattern::Uniform => "area-uniform",
            Pattern::Stratified => "area-stratified",
            Pattern::Sobol => "area-sobol",
        };
        format!(
            "{kind}(pairs={}x{})",
            self.pairs_per_replicate(),
            self.replicates.max(2)
        )
    }

    fn upper_only(&self) -> bool {
        true
    }

    fn row(&self, ctx: &Context, a: usize, row: &mut Row) {
        let vis = ctx.vis;
        self.row_with(ctx, a, row, &mut |x, n_x, y, n_y| {
            vis.segment_visible(x, n_x, y, n_y)
        });
    }
}

impl AreaMc {
    /// Row `a` (pairs `b > a`) with `visible(x, n_x, y, n_y)` answering visibility; the
    /// rays asked for do not depend on the answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        a: usize,
        row: &mut Row,
        visible: &mut dyn FnMut(Vec3, Vec3, Vec3, Vec3) -> bool,
    ) {
        for b in a + 1..ctx.patches.len() {
            if let Some(e) = self.pair_with(ctx, a, b, &mut row.rays, visible) {
                row.entries.push(e);
            }
        }
    }

    /// The entry `F_ab` of the unordered pair (a, b) (`F_ba` follows by reciprocity), or
    /// `None` when the pair is culled or no sample sees anything; `rays` counts the rays.
    pub fn pair_with(
        &self,
        ctx: &Context,
        a: usize,
        b: usize,
        rays: &mut u64,
        visible: &mut dyn FnMut(Vec3, Vec3, Vec3, Vec3) -> bool,
    ) -> Option<Entry> {
        let p = ctx.patches;
        if behind(ctx, a, b) || behind(ctx, b, a) {
            return None;
        }
        let m = self.pairs_per_replicate();
        let reps = self.replicates.max(2);
        let mut xs = Vec::with_capacity(m);
        let mut ys = Vec::with_capacity(m);
        let mut means = vec![0.0f64; reps];
        let (n_a, n_b) = (p.normal[a], p.normal[b]);
        for (r, mean) in means.iter_mut().enumerate() {
            let mut rng = Pcg32::keyed(ctx.seed, a as u64, b as u64, r as u64);
            match self.pattern {
                Pattern::Stratified => {
                    // One jittered pair in every cell of a t x t x t x t grid of the 4D
                    // domain (x on a, y on b): the joint dependence of the kernel on x and y
                    // is stratified too, not only its margins.
                    let t = self.grid();
                    let inv = 1.0 / t as f64;
                    xs.clear();
                    ys.clear();
                    for a1 in 0..t {
                        for a2 in 0..t {
                            for b1 in 0..t {
                                for b2 in 0..t {
                                    let j =
                                        |c: usize, r: &mut Pcg32| (c as f64 + r.next_f64()) * inv;
                                    xs.push((j(a1, &mut rng), j(a2, &mut rng)));
                                    ys.push((j(b1, &mut rng), j(b2, &mut rng)));
                                }
                            }
                        }
                    }
                }
                Pattern::Sobol => {
                    // Owen scrambling with a fresh seed per replicate.
                    let scramble = rng.next_u32();
                    xs.clear();
                    ys.clear();
                    for k in 0..m as u32 {
                        let q = sobol_burley::sample_4d(k, 0, scramble);
                        xs.push((q[0] as f64, q[1] as f64));
                        ys.push((q[2] as f64, q[3] as f64));
                    }
                }
                Pattern::Uniform => {
                    xs.clear();
                    ys.clear();
                    for _ in 0..m {
                        xs.push((rng.next_f64(), rng.next_f64()));
                        ys.push((rng.next_f64(), rng.next_f64()));
                    }
                }
            }
            let mut sum = 0.0f64;
            for k in 0..m {
                let x = p.sample_point(a, xs[k].0, xs[k].1);
                let y = p.sample_point(b, ys[k].0, ys[k].1);
                if let Some(g) = kernel(x, n_a, y, n_b) {
                    *rays += 1;
                    if visible(x, n_a, y, n_b) {
                        sum += g;
                    }
                }
            }
            *mean = sum / m as f64;
        }
        let avg = means.iter().sum::<f64>() / reps as f64;
        if avg <= 0.0 {
            return None;
        }
        let var = means.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / (reps - 1) as f64;
        let se = (var / reps as f64).sqrt();
        let area_b = p.area[b];
        Some(Entry {
            j: b as u32,
            f: avg * area_b,
            se: se * area_b,
        })
    }
}

/// The unoccluded point-to-point kernel `cos θ_x cos θ_y / (π r²)`, or `None` when the
/// points face away from each other (no ray needed).
#[inline]
pub fn kernel(x: Vec3, n_x: Vec3, y: Vec3, n_y: Vec3) -> Option<f64> {
    let d = (y - x).as_dvec3();
    let r2 = d.length_squared();
    let cx = n_x.as_dvec3().dot(d);
    let cy = -n_y.as_dvec3().dot(d);
    if cx <= 0.0 || cy <= 0.0 || r2 <= 0.0 {
        return None;
    }
    Some(cx * cy / (std::f64::consts::PI * r2 * r2))
}
