//! Hemisphere shooting (Malley's method): a whole row from `k` rays, whatever the patch count.
//!
//! From stratified points x on patch i, rays leave in cosine-weighted directions
//! (p(ω) = cos θ / π); the first surface hit is found with Embree's closest-hit query.
//! Since `F_ij = 1/A_i ∫_{A_i} ∫_{Ω} cos θ / π · [ray (x, ω) first hits the front of j] dω dA_x`
//! (Malley 1988; Cohen and Wallace 1993, §4.9.3), the fraction of rays whose first hit is
//! the front of patch j is an unbiased estimate of `F_ij`. A hit on the back of a patch
//! carries the energy to no front face and counts for nothing (one-sided surfaces, as in
//! the area estimators). In a closed scene every ray hits something, so rows sum to 1 up to
//! back-face hits.
//!
//! Positions are jittered on an `s x s` grid of the patch and directions on an `s x s`
//! grid of the unit square mapped by Shirley and Chiu's concentric disk map (1997) lifted to
//! the hemisphere, strata paired by a random permutation. `R` independent replicates give
//! the standard error of each entry.

use glam::Vec3;

use super::{Context, Entry, Estimator, Row};
use crate::sampling::{jittered, shuffle, Pcg32};
use crate::visibility::Hit;

/// Hemisphere-shooting estimator.
#[derive(Clone, Debug)]
pub struct Hemisphere {
    /// Strata per side: each replicate casts `strata²` rays.
    pub strata: usize,
    /// Independent replicates (>= 2).
    pub replicates: usize,
}

impl Default for Hemisphere {
    fn default() -> Self {
        Hemisphere {
            strata: 16,
            replicates: 4,
        }
    }
}

/// Orthonormal basis around a unit normal (Duff et al. 2017, "Building an orthonormal
/// basis, revisited").
#[inline]
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// Cosine-weighted direction in the local frame (z up) from `(u, v)` in the unit square:
/// the concentric disk map (Shirley and Chiu 1997) lifted by Malley's method.
#[inline]
pub fn cosine_direction(u: f64, v: f64) -> Vec3 {
    let (a, b) = (2.0 * u - 1.0, 2.0 * v - 1.0);
    let (r, phi) = if a == 0.0 && b == 0.0 {
        (0.0, 0.0)
    } else if a.abs() > b.abs() {
        (a, std::f64::consts::FRAC_PI_4 * (b / a))
    } else {
        (
            b,
            std::f64::consts::FRAC_PI_2 - std::f64::consts::FRAC_PI_4 * (a / b),
        )
    };
    // f32 trigonometry: the direction is f32 anyway, and sincosf is about twice as fast.
    let (sin, cos) = (phi as f32).sin_cos();
    let (x, y) = (r as f32 * cos, r as f32 * sin);
    let z = (1.0 - x * x - y * y).max(0.0).sqrt();
    Vec3::new(x, y, z)
}

impl Estimator for Hemisphere {
    fn name(&self) -> String {
        format!(
            "hemisphere(rays={}x{}x{})",
            self.strata, self.strata, self.replicates
        )
    }

    fn row(&self, ctx: &Context, i: usize, row: &mut Row) {
        let vis = ctx.vis;
        self.row_with(ctx, i, row, &mut |org, dir| vis.first_hit_from(org, dir));
    }
}

/// Per-thread buffers of [`Hemisphere::row_with`], kept between rows.
#[derive(Default)]
struct Scratch {
    pos: Vec<(f64, f64)>,
    dirs: Vec<(f64, f64)>,
    /// Rays `(origin, direction)` of one replicate.
    rays: Vec<(Vec3, Vec3)>,
    /// `(patch hit, replicate)` of the rays that hit the front of another patch.
    keyed: Vec<(u32, u32)>,
    counts: Vec<u32>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::default();
}

impl Hemisphere {
    /// Row `i` with `first_hit(origin, direction)` answering the closest-hit query for the
    /// ray from `origin` (already offset off patch i, see
    /// [`crate::visibility::Visibility::first_hit_origin`]) in unit `direction`; the rays
    /// asked for do not depend on the answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        first_hit: &mut dyn FnMut(Vec3, Vec3) -> Option<Hit>,
    ) {
        SCRATCH.with(|s| self.row_in(ctx, i, row, first_hit, &mut s.borrow_mut()));
    }

    fn row_in(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        first_hit: &mut dyn FnMut(Vec3, Vec3) -> Option<Hit>,
        s: &mut Scratch,
    ) {
        let p = ctx.patches;
        let reps = self.replicates.max(2);
        let m = self.strata * self.strata;
        let n_i = p.normal[i];
        let (t, b) = basis(n_i);
        let on_i = p.sampler(i);
        s.keyed.clear();
        for r in 0..reps {
            let mut rng = Pcg32::keyed(ctx.seed, i as u64, u64::MAX, r as u64);
            jittered(&mut rng, self.strata, &mut s.pos);
            jittered(&mut rng, self.strata, &mut s.dirs);
            shuffle(&mut rng, &mut s.dirs);
            // Sample the replicate's rays first, then trace them in a tight loop.
            s.rays.clear();
            s.rays.extend((0..m).map(|k| {
                let x = on_i.point(s.pos[k].0, s.pos[k].1);
                let l = cosine_direction(s.dirs[k].0, s.dirs[k].1);
                let w = (t * l.x + b * l.y + n_i * l.z).normalize();
                (ctx.vis.first_hit_origin(x, n_i, w), w)
            }));
            for &(org, w) in &s.rays {
                if let Some(h) = first_hit(org, w) {
                    if h.patch as usize != i && p.normal[h.patch as usize].dot(w) < 0.0 {
                        s.keyed.push((h.patch, r as u32));
                    }
                }
            }
        }
        row.rays += (m * reps) as u64;
        // Count hits per (patch, replicate).
        s.keyed.sort_unstable();
        let inv_m = 1.0 / m as f64;
        s.counts.clear();
        s.counts.resize(reps, 0);
        let keyed = &s.keyed;
        let mut k = 0;
        while k < keyed.len() {
            let j = keyed[k].0;
            s.counts.iter_mut().for_each(|c| *c = 0);
            while k < keyed.len() && keyed[k].0 == j {
                s.counts[keyed[k].1 as usize] += 1;
                k += 1;
            }
            let avg = s.counts.iter().map(|&c| c as f64 * inv_m).sum::<f64>() / reps as f64;
            let var = s
                .counts
                .iter()
                .map(|&c| (c as f64 * inv_m - avg).powi(2))
                .sum::<f64>()
                / (reps - 1) as f64;
            row.entries.push(Entry {
                j,
                f: avg,
                se: (var / reps as f64).sqrt(),
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.5, 0.8).normalize(),
        ] {
            let (t, b) = basis(n);
            assert!(t.dot(b).abs() < 1e-6 && t.dot(n).abs() < 1e-6 && b.dot(n).abs() < 1e-6);
            assert!((t.length() - 1.0).abs() < 1e-6 && (b.length() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn cosine_directions_have_the_right_mean() {
        // E[cos θ] under p = cos θ / π is 2/3.
        let mut rng = Pcg32::keyed(3, 0, 0, 0);
        let n = 100_000;
        let mean: f64 = (0..n)
            .map(|_| cosine_direction(rng.next_f64(), rng.next_f64()).z as f64)
            .sum::<f64>()
            / n as f64;
        // Var[cos] = 1/2 - 4/9 = 1/18; 5 sigma.
        assert!(
            (mean - 2.0 / 3.0).abs() < 5.0 * (1.0 / 18.0 / n as f64).sqrt(),
            "{mean}"
        );
    }
}
