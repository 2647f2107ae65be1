//! Area-to-area Monte Carlo: point pairs on both patches, one occlusion ray per pair.
//!
//! For the unordered pair (a, b), a < b, each of `R` independent replicates draws `n`
//! points `x_k` on a and `n` points `y_k` on b and forms
//!
//! `I = 1/n Σ_k cos θ_x cos θ_y V(x_k, y_k) / (π r_k²)`,
//!
//! an unbiased estimate of `1/(A_a A_b) ∫∫ cos cos V / (π r²)`, so that `F_ab = A_b I` and
//! `F_ba = A_a I` (radiosidade.md, "Fator de Forma" and "Teorema da Reciprocidade").
//! Points are independent uniform ([`Pattern::Uniform`]) or jittered on an `s x s` grid of
//! strata of each patch with the strata of b randomly paired with those of a
//! ([`Pattern::Stratified`], a Latin pairing that keeps the 4D estimate unbiased). The
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
use crate::sampling::{jittered, shuffle, Pcg32};
use crate::visibility::SegmentRay;

/// How points are placed on each patch.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pattern {
    /// Independent uniform points.
    Uniform,
    /// Jittered strata on each patch, strata paired by a random permutation.
    Stratified,
}

/// Area-to-area Monte Carlo estimator.
#[derive(Clone, Debug)]
pub struct AreaMc {
    /// Point placement.
    pub pattern: Pattern,
    /// Strata per side: each replicate uses `strata²` point pairs.
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
    /// Point pairs per patch pair.
    pub fn pairs(&self) -> usize {
        self.strata * self.strata * self.replicates
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
        };
        format!(
            "{kind}(pairs={}x{}x{})",
            self.strata, self.strata, self.replicates
        )
    }

    fn upper_only(&self) -> bool {
        true
    }

    fn row(&self, ctx: &Context, a: usize, row: &mut Row) {
        let vis = ctx.vis;
        self.row_with(ctx, a, row, &mut |segs, out| {
            vis.segments_visible(segs, out)
        });
    }
}

impl AreaMc {
    /// Row `a` (pairs `b > a`) with `visible(segments, out)` answering visibility for a
    /// batch of segment rays ([`crate::visibility::Visibility::segment_ray`], one batch per
    /// replicate of a pair); the rays asked for do not depend on the answers, so a recorder
    /// sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        a: usize,
        row: &mut Row,
        visible: &mut dyn FnMut(&[SegmentRay], &mut [bool]),
    ) {
        let p = ctx.patches;
        let m = self.strata * self.strata;
        let reps = self.replicates.max(2);
        let mut xs = Vec::with_capacity(m);
        let mut ys = Vec::with_capacity(m);
        let mut means = vec![0.0f64; reps];
        let mut segs = Vec::with_capacity(m);
        let mut gs = Vec::with_capacity(m);
        let mut free = vec![false; m];
        let n_a = p.normal[a];
        for b in a + 1..p.len() {
            if behind(ctx, a, b) || behind(ctx, b, a) {
                continue;
            }
            let n_b = p.normal[b];
            let (on_a, on_b) = (p.sampler(a), p.sampler(b));
            for (r, mean) in means.iter_mut().enumerate() {
                let mut rng = Pcg32::keyed(ctx.seed, a as u64, b as u64, r as u64);
                match self.pattern {
                    Pattern::Stratified => {
                        jittered(&mut rng, self.strata, &mut xs);
                        jittered(&mut rng, self.strata, &mut ys);
                        shuffle(&mut rng, &mut ys);
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
                segs.clear();
                gs.clear();
                for k in 0..m {
                    let x = on_a.point(xs[k].0, xs[k].1);
                    let y = on_b.point(ys[k].0, ys[k].1);
                    if let Some(g) = kernel(x, n_a, y, n_b) {
                        segs.push(ctx.vis.segment_ray(x, n_a, y, n_b));
                        gs.push(g);
                    }
                }
                row.rays += segs.len() as u64;
                visible(&segs, &mut free[..segs.len()]);
                let sum: f64 = gs.iter().zip(&free).filter(|p| *p.1).map(|p| *p.0).sum();
                *mean = sum / m as f64;
            }
            let avg = means.iter().sum::<f64>() / reps as f64;
            if avg > 0.0 {
                let var = means.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / (reps - 1) as f64;
                let se = (var / reps as f64).sqrt();
                let area_b = p.area[b];
                row.entries.push(Entry {
                    j: b as u32,
                    f: avg * area_b,
                    se: se * area_b,
                });
            }
        }
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
