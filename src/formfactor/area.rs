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
//! pair facing away (cos <= 0) contributes 0 without a ray. Each pair's samples come from
//! a counter-based stream keyed on `(seed, a, b)` (replicate r takes the words from
//! `2 r m` on, [`SplitMix`]), so the result does not depend on the thread count.
//!
//! The inner loop works in `f32` over all the samples of a pair at once (structure of
//! arrays): unit-square coordinates with 24 random bits each from a counter-based
//! [`SplitMix`] stream (each word a function of the key and its position only, so the words
//! come out of one vector pass, where wyrand's 128-bit products run one at a time:
//! docs/PERFORMANCE.md §1), points on both patches, kernel and segment rays; the replicate
//! sums are accumulated in `f64`. The points are made in `f32` (from corners rounded once
//! from the f64 geometry) because they are the segment rays' ends, which Embree takes in
//! `f32`; the kernel's rounding error (a few ulp, about 1e-7 relative) is far below any
//! standard error. Culling is decided in f64 on the exact corners.
//!
//! Patches that share an edge make `cos cos / r²` unbounded: the estimate stays finite and
//! unbiased but its variance is infinite, and the replicate error bar would say little.
//! Such *near* pairs (patches closer than the larger one's side, [`near`]) are therefore
//! not sampled by point pairs: they get the semi-analytic integral ([`super::semi`]: the
//! exact point-to-polygon factor, whose integrand is bounded), by deterministic quadrature
//! with an error bound where nothing can block the pair, and at random stratified nodes
//! with the same replicates where something may. The row's random part then comes only
//! from pairs whose kernel is bounded by `1/π` per sample.

use glam::{DVec3, Vec3};

use super::shard::{self, cost};
use super::{Context, Entry, Estimator, Nodes, Row, Scratch as Buffers, SemiAnalytic};
use std::f64::consts::FRAC_1_PI;
use std::sync::{Arc, OnceLock};

use crate::mesh::PatchSampler;
use crate::sampling::{jitter4, SplitMix, Wy};
use crate::visibility::{Offsets, Rays, Segments, Tracer, SEGMENT_TFAR};

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
    /// The estimator of near pairs ([`near`]), made on first use from the settings above.
    near: Arc<OnceLock<SemiAnalytic>>,
}

impl Default for AreaMc {
    fn default() -> Self {
        AreaMc::new(Pattern::Stratified, 4, 4)
    }
}

/// How close, relative to the side `√A` of the larger patch, two patches must come for
/// the pair to be *near* ([`near`]): 1, so that no point pair of a sampled pair adds more
/// than `A_b / (π d²) ≤ 1/π` to a row.
pub const NEAR: f64 = 1.0;

/// True when patches `a` and `b` (corners `pa`, `pb`) come closer than [`NEAR`] times
/// `√A` of the larger one.
///
/// A sample pair `(x, y)` adds `A_b cos θ_x cos θ_y / (π r²)` to `F_ab` (and `A_a` times
/// the same to `F_ba`), at most `A / (π d²)` for patches a distance `d` apart. Where they
/// touch (`d = 0`: walls meeting at a corner, a box on a floor) the kernel is unbounded and
/// its variance infinite: the replicates' spread then says little, most runs fall short and
/// a rare sample near the common edge throws a row far over 1 (5.5 with two strips meeting
/// in a wedge). Below `d = NEAR √A` a sample may add more than `1 / (π NEAR²) = 1/π`; such
/// pairs are handed to the semi-analytic integral (the exact inner integral
/// `F(x → P_b) ≤ 1` is bounded): deterministic quadrature with an error bound where the
/// pair is provably unoccluded, random nodes with honest standard errors where it is not
/// (see [`AreaMc::row_with`]). With a quarter side (the first choice) the nearest sampled
/// pairs, one or two per row, still dominated a row's variance with the 3 degrees of
/// freedom of 4 replicates, and 1 to 2 rows of 1000 on the wedge and the gap of
/// `tests/rows.rs` went over 1 by more than 3 bars at the default seed (17 rows in 120
/// matrices of 20 seeds at one side with random nodes); at one side with quadrature, none.
pub fn near(
    p: &crate::mesh::PatchSet,
    (a, pa): (usize, &[DVec3]),
    (b, pb): (usize, &[DVec3]),
) -> bool {
    Near::of(p, a, pa).to(p, b, pb)
}

/// Patch a's side of the [`near`] test, made once for all of a's pairs.
struct Near<'a> {
    corners: &'a [DVec3],
    centroid: DVec3,
    /// `√A_a`.
    side: f64,
    /// Largest distance of a corner from the centroid.
    radius: f64,
}

impl<'a> Near<'a> {
    fn of(p: &crate::mesh::PatchSet, a: usize, corners: &'a [DVec3]) -> Near<'a> {
        let centroid = p.centroid[a];
        Near {
            corners,
            centroid,
            side: p.area[a].sqrt(),
            radius: radius(centroid, corners),
        }
    }

    /// [`near`] of a and b: first the two patches' bounding balls, then the distance
    /// between the polygons. (`NEAR √A` of the larger patch is `NEAR` times the larger
    /// `√A`: the square root is monotonic and correctly rounded, so the two agree to the
    /// bit, as do the radii below.)
    #[inline]
    fn to(&self, p: &crate::mesh::PatchSet, b: usize, pb: &[DVec3]) -> bool {
        let reach = NEAR * self.side.max(p.area[b].sqrt());
        let cb = p.centroid[b];
        if (self.centroid - cb).length() - self.radius - radius(cb, pb) >= reach {
            return false;
        }
        super::exact::polygon_distance(self.corners, pb) < reach
    }
}

/// Largest distance from `c` to a point of `q`: the square root of the largest squared
/// distance, one root for all.
#[inline]
fn radius(c: DVec3, q: &[DVec3]) -> f64 {
    q.iter()
        .map(|&v| (v - c).length_squared())
        .fold(0.0, f64::max)
        .sqrt()
}

impl AreaMc {
    /// An estimator with the given pattern, samples per side and replicates.
    pub fn new(pattern: Pattern, strata: usize, replicates: usize) -> Self {
        AreaMc {
            pattern,
            strata,
            replicates,
            near: Arc::default(),
        }
    }

    /// The estimator of near pairs: the semi-analytic integral, by quadrature to the relative
    /// tolerance [`AreaMc::near_tol`] where nothing can block the pair, else with `strata²`
    /// random stratified nodes per replicate, `2 × 2` visibility rays per node and the same
    /// replicates.
    fn near_estimator(&self) -> &SemiAnalytic {
        self.near.get_or_init(|| {
            SemiAnalytic::new(Nodes::Gauss, self.strata.max(1), 2, self.replicates.max(2))
                .with_tol(self.near_tol())
        })
    }

    /// Relative tolerance of the near pairs' quadrature: `1/m` for `m` point pairs per
    /// replicate, at most 1e-2. A touching pair's tensor tanh–sinh rule costs hundreds of
    /// point-to-polygon factors even at 1e-2 (two levels for the check); at 1e-6 it halved the
    /// stage's speed on the Cornell box. 1e-2 of a near pair's factor is below the point
    /// pairs' noise at the default budgets, and the bound, reported as such, adds to the
    /// row's bar linearly; larger budgets tighten it (`radiosity study`).
    pub fn near_tol(&self) -> f64 {
        (1.0 / self.pairs_per_replicate() as f64).min(1e-2)
    }

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
    let (pts, k) = ctx.patches.corner_points(b);
    behind_plane(ctx, a, &pts[..k])
}

/// [`behind`] with the corners of patch `b` given.
#[inline]
fn behind_plane(ctx: &Context, a: usize, corners: &[DVec3]) -> bool {
    let p = ctx.patches;
    let (n, c) = (p.normal[a], p.centroid[a]);
    let tol = p.plane_tol();
    corners.iter().all(|&q| n.dot(q - c) <= tol)
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

    fn replicates(&self) -> usize {
        self.replicates.max(2)
    }

    fn row(&self, ctx: &Context, a: usize, row: &mut Row, scratch: &mut Buffers) {
        self.row_with(ctx, a, row, ctx.vis, scratch);
    }

    /// A sample of the row's pairs ([`shard::sampled_row_cost`]): culled, or
    /// `pairs x replicates` rays.
    fn row_costs(&self, ctx: &Context, rows: std::ops::Range<usize>) -> Vec<f64> {
        use rayon::prelude::*;
        let p = ctx.patches;
        let rays = self.pairs() as f64;
        rows.into_par_iter()
            .map(|a| {
                let (pa, ka) = p.corner_points(a);
                cost::ROW
                    + shard::sampled_row_cost(a, p.len(), |b| {
                        let (pb, kb) = p.corner_points(b);
                        if behind_plane(ctx, a, &pb[..kb]) || behind_plane(ctx, b, &pa[..ka]) {
                            cost::CULL
                        } else {
                            cost::PAIR + rays * cost::RAY
                        }
                    })
            })
            .collect()
    }
}

impl AreaMc {
    /// Row `a` (pairs `b > a`) with `tracer` answering visibility, one batch of segment
    /// rays per pair (all its replicates); the rays asked for do not depend on the
    /// answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        a: usize,
        row: &mut Row,
        tracer: &dyn Tracer,
        scratch: &mut Buffers,
    ) {
        let p = ctx.patches;
        let (pa, ka) = p.corner_points(a);
        let on_a = PatchSampler::of_corners(pa, ka);
        let m = self.pairs_per_replicate();
        crate::simd::with_widest(
            #[inline(always)]
            || self.pairs_of(ctx, a, (&pa[..ka], &on_a), m, row, tracer, scratch),
        )
    }

    /// The pairs `(a, b > a)` of row a, given a's corners and sampler: culling, then
    /// [`AreaMc::pair_in`] for each pair left, or the semi-analytic integral for a
    /// [`near`] pair.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn pairs_of(
        &self,
        ctx: &Context,
        a: usize,
        (pa, on_a): (&[DVec3], &PatchSampler),
        m: usize,
        row: &mut Row,
        tracer: &dyn Tracer,
        scratch: &mut Buffers,
    ) {
        let p = ctx.patches;
        let near_a = Near::of(p, a, pa);
        // The possible blockers of a's near pairs, looked up at the first of them.
        let mut blockers = None;
        for b in a + 1..p.len() {
            // The corners of b serve both culling tests and b's sampler.
            let (pb, kb) = p.corner_points(b);
            if behind_plane(ctx, a, &pb[..kb]) || behind_plane(ctx, b, pa) {
                continue;
            }
            let got = if near_a.to(p, b, &pb[..kb]) {
                let semi = self.near_estimator();
                let blockers = blockers.get_or_insert_with(|| semi.blockers(p, a));
                semi.single_pair(ctx, (a, b), blockers, row, tracer, &mut scratch.semi)
            } else {
                let on_b = PatchSampler::of_corners(pb, kb);
                let (ons, rays) = ((on_a, &on_b), &mut row.rays);
                self.pair_in(ctx, a, b, ons, m, rays, tracer, &mut scratch.area)
            };
            if let Some(e) = got {
                row.entries.push(e);
            }
        }
    }

    /// The entry `F_ab` of the unordered pair (a, b) (`F_ba` follows by reciprocity), or
    /// `None` when the pair is culled or no sample sees anything; `rays` counts the rays.
    /// `tracer` answers visibility for the pair's batch of segment rays.
    pub fn pair_with(
        &self,
        ctx: &Context,
        a: usize,
        b: usize,
        rays: &mut u64,
        tracer: &dyn Tracer,
        scratch: &mut Buffers,
    ) -> Option<Entry> {
        if behind(ctx, a, b) || behind(ctx, b, a) {
            return None;
        }
        let p = ctx.patches;
        let ((pa, ka), (pb, kb)) = (p.corner_points(a), p.corner_points(b));
        if near(p, (a, &pa[..ka]), (b, &pb[..kb])) {
            let mut row = Row::default();
            let semi = self.near_estimator();
            let blockers = semi.blockers(p, a);
            let got = semi.single_pair(ctx, (a, b), &blockers, &mut row, tracer, &mut scratch.semi);
            *rays += row.rays;
            return got;
        }
        let ons = (&p.sampler(a), &p.sampler(b));
        let m = self.pairs_per_replicate();
        self.pair_in(ctx, a, b, ons, m, rays, tracer, &mut scratch.area)
    }

    /// [`AreaMc::pair_with`] after the culling test, with the samplers of patches a and b
    /// and the sample pairs per replicate `m`.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn pair_in(
        &self,
        ctx: &Context,
        a: usize,
        b: usize,
        (on_a, on_b): (&PatchSampler, &PatchSampler),
        m: usize,
        rays: &mut u64,
        tracer: &dyn Tracer,
        s: &mut Scratch,
    ) -> Option<Entry> {
        let p = ctx.patches;
        let reps = self.replicates.max(2);
        let len = m * reps;
        s.resize(len);
        // Structure of arrays over all the pair's samples (replicate after replicate), in
        // passes simple enough for the compiler to run 4 samples at a time: unit-square
        // coordinates, points on both patches, then kernel and segment rays.
        self.unit_square(ctx.seed, a, b, m, reps, s);
        let (n_a, n_b) = (p.normal[a].as_vec3(), p.normal[b].as_vec3());
        on_a.points32(&s.u[0], &s.u[1], &mut s.x);
        on_b.points32(&s.u[2], &s.u[3], &mut s.y);
        let off = ctx.vis.offsets();
        // Kernel, facing test and segment ray of every sample pair, as structure of arrays
        // (the layout of Embree's packets); then, in the rare pairs where some samples do
        // not face each other, those are dropped.
        segments(
            &s.x, n_a, &s.y, n_b, off, &mut s.g, &mut s.ok, &mut s.org, &mut s.dir,
        );
        s.ends.clear();
        let n = if s.ok[..len].iter().all(|&v| v) {
            s.ends.extend((1..=reps).map(|r| r * m));
            len
        } else {
            let mut n = 0;
            for r in 0..reps {
                for k in r * m..(r + 1) * m {
                    if s.ok[k] {
                        for c in 0..3 {
                            s.org[c][n] = s.org[c][k];
                            s.dir[c][n] = s.dir[c][k];
                        }
                        s.g[n] = s.g[k];
                        n += 1;
                    }
                }
                s.ends.push(n);
            }
            n
        };
        *rays += n as u64;
        s.seen.resize(len, false);
        let (o, d) = (&s.org, &s.dir);
        let segs = Segments {
            rays: Rays {
                org: [&o[0][..n], &o[1][..n], &o[2][..n]],
                dir: [&d[0][..n], &d[1][..n], &d[2][..n]],
            },
            tfar: SEGMENT_TFAR,
        };
        tracer.segments_visible(&segs, &mut s.seen[..n]);
        let (mut avg, mut lo) = (0.0, 0);
        s.means.clear();
        for &hi in &s.ends {
            let sum: f64 = s.g[lo..hi]
                .iter()
                .zip(&s.seen[lo..hi])
                .map(|(&g, &v)| if v { g as f64 } else { 0.0 })
                .sum();
            let mean = sum * FRAC_1_PI / m as f64;
            s.means.push(mean);
            avg += mean;
            lo = hi;
        }
        avg /= reps as f64;
        if avg <= 0.0 {
            return None;
        }
        let var = s.means.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / (reps - 1) as f64;
        let se = (var / reps as f64).sqrt();
        let area_b = p.area[b];
        Some(Entry {
            j: b as u32,
            f: avg * area_b,
            se: se * area_b,
        })
    }

    /// The pair's sample coordinates `(x_u, x_v, y_u, y_v)` in the unit square into
    /// `s.u[0..4]`, `m` per replicate, from the pair's `(seed, a, b)` stream ([`AreaMc::words`];
    /// the Sobol pattern's scrambles from substream `r` of a [`Wy`] stream).
    #[inline(always)]
    fn unit_square(&self, seed: u64, a: usize, b: usize, m: usize, reps: usize, s: &mut Scratch) {
        let len = m * reps;
        match self.pattern {
            Pattern::Stratified => {
                // One jittered pair in every cell of a t x t x t x t grid of the 4D domain
                // (x on a, y on b): the joint dependence of the kernel on x and y is
                // stratified too, not only its margins. Two 64-bit words per pair, 24 bits
                // per coordinate: the words first, then one vector pass.
                self.cells(m, reps, &mut s.cells);
                // 1 / t, with t⁴ = m.
                let inv = 1.0 / (m as f32).sqrt().sqrt().round();
                self.words(seed, a, b, m, reps, &mut s.words);
                let [c0, c1, c2, c3] = &s.cells;
                let cells = [&c0[..len], &c1[..len], &c2[..len], &c3[..len]];
                jitter4(&s.words[..2 * len], Some(cells), inv, &mut s.u);
            }
            Pattern::Sobol => {
                let pair = Wy::keyed(seed, a as u64, b as u64, 0);
                for r in 0..reps {
                    // Owen scrambling with a fresh seed per replicate.
                    let scramble = pair.substream(r as u64).next_u64() as u32;
                    for k in 0..m {
                        let q = sobol_burley::sample_4d(k as u32, 0, scramble);
                        for (u, q) in s.u.iter_mut().zip(q) {
                            u[r * m + k] = q;
                        }
                    }
                }
            }
            Pattern::Uniform => {
                self.words(seed, a, b, m, reps, &mut s.words);
                jitter4(&s.words[..2 * len], None, 1.0, &mut s.u);
            }
        }
    }

    /// Two words per sample pair into `words`, all replicates' from the pair's `(seed, a,
    /// b)` counter-based stream in one vector pass (replicate r's `m` pairs from word
    /// `2 r m` on: the words are independent of each other, [`SplitMix`]).
    #[inline(always)]
    fn words(&self, seed: u64, a: usize, b: usize, m: usize, reps: usize, words: &mut Vec<u64>) {
        words.resize(2 * m * reps, 0);
        SplitMix::keyed(seed, a as u64, b as u64, 0).fill(words);
    }

    /// The integer coordinates of the cells of the stratified pattern's 4D grid, last one
    /// fastest, `m = t⁴` of them, repeated for `reps` replicates, into `cells` (unchanged
    /// when it already holds them).
    fn cells(&self, m: usize, reps: usize, cells: &mut [Vec<f32>; 4]) {
        if cells[0].len() == m * reps {
            return;
        }
        let t = self.grid();
        cells.iter_mut().for_each(|c| c.clear());
        for _ in 0..reps {
            for a1 in 0..t {
                for a2 in 0..t {
                    for b1 in 0..t {
                        for b2 in 0..t {
                            for (c, v) in cells.iter_mut().zip([a1, a2, b1, b2]) {
                                c.push(v as f32);
                            }
                        }
                    }
                }
            }
        }
    }
}

/// For each sample pair `(x_k, y_k)`: the kernel `cos θ_x cos θ_y / r²` (without the 1/π)
/// into `g`, whether the two points face each other into `ok` (the kernel is positive and a
/// ray is needed), and the segment ray between them into `org`/`dir` (structure of
/// arrays): both ends moved off their surfaces along their own normals by the one offset
/// policy ([`Offsets::ends`]) and kept `floor` in front of each other's plane, the case
/// [`crate::visibility::Visibility::segment_ray`] selects for facing points, without its
/// two tests.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn segments(
    x: &[Vec<f32>; 3],
    n_x: Vec3,
    y: &[Vec<f32>; 3],
    n_y: Vec3,
    off: Offsets,
    g: &mut [f32],
    ok: &mut [bool],
    org: &mut [Vec<f32>; 3],
    dir: &mut [Vec<f32>; 3],
) {
    let len = g.len();
    let (x0, x1, x2) = (&x[0][..len], &x[1][..len], &x[2][..len]);
    let (y0, y1, y2) = (&y[0][..len], &y[1][..len], &y[2][..len]);
    let ok = &mut ok[..len];
    let [o0, o1, o2] = org;
    let (o0, o1, o2) = (&mut o0[..len], &mut o1[..len], &mut o2[..len]);
    let [d0, d1, d2] = dir;
    let (d0, d1, d2) = (&mut d0[..len], &mut d1[..len], &mut d2[..len]);
    for k in 0..len {
        let (dx, dy, dz) = (y0[k] - x0[k], y1[k] - x1[k], y2[k] - x2[k]);
        let r2 = dx * dx + dy * dy + dz * dz;
        let cx = n_x.x * dx + n_x.y * dy + n_x.z * dz;
        let cy = -(n_y.x * dx + n_y.y * dy + n_y.z * dz);
        let inv = 1.0 / r2;
        g[k] = (cx * inv) * (cy * inv);
        ok[k] = (cx > 0.0) & (cy > 0.0) & (r2 > 0.0);
        let (ex, ey) = off.ends(cx.abs(), cy.abs());
        // Each end also kept `floor` in front of the other end's plane (the same policy).
        let (ox, oy) = (
            n_x * ex + n_y * (off.floor - cy).max(0.0),
            n_y * ey + n_x * (off.floor - cx).max(0.0),
        );
        let org = (x0[k] + ox.x, x1[k] + ox.y, x2[k] + ox.z);
        let end = (y0[k] + oy.x, y1[k] + oy.y, y2[k] + oy.z);
        (o0[k], o1[k], o2[k]) = org;
        (d0[k], d1[k], d2[k]) = (end.0 - org.0, end.1 - org.1, end.2 - org.2);
    }
}

/// Buffers of [`AreaMc::pair_with`], kept between pairs (in the driver's
/// [`super::Scratch`]): one entry per sample pair of all replicates, as structure of arrays.
#[derive(Default)]
pub(crate) struct Scratch {
    /// Cells of the stratified pattern ([`AreaMc::cells`]), one replicate's worth.
    cells: [Vec<f32>; 4],
    /// Unit-square coordinates `(x_u, x_v, y_u, y_v)`.
    u: [Vec<f32>; 4],
    /// Points on patch a and on patch b.
    x: [Vec<f32>; 3],
    y: [Vec<f32>; 3],
    /// Random words, two per sample pair.
    words: Vec<u64>,
    /// Kernel values and facing tests of every pair.
    g: Vec<f32>,
    ok: Vec<bool>,
    /// The segment rays (structure of arrays), replicate after replicate, and their
    /// visibility; after a facing test drops samples, `g` and the rays are compacted.
    org: [Vec<f32>; 3],
    dir: [Vec<f32>; 3],
    seen: Vec<bool>,
    /// End of each replicate's rays.
    ends: Vec<usize>,
    means: Vec<f64>,
}

impl Scratch {
    /// Sizes the per-sample arrays for `len` sample pairs.
    fn resize(&mut self, len: usize) {
        if self.g.len() == len {
            return;
        }
        for v in self.u.iter_mut().chain(&mut self.x).chain(&mut self.y) {
            v.resize(len, 0.0);
        }
        for v in self.org.iter_mut().chain(&mut self.dir) {
            v.resize(len, 0.0);
        }
        self.g.resize(len, 0.0);
        self.ok.resize(len, false);
    }
}
