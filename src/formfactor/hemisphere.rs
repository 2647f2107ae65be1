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
//! the hemisphere, strata paired by a random permutation (Kensler's hashed permutation,
//! rotated by a uniform offset so that every ray's position cell is uniform: each ray's
//! estimate, hence the row, stays unbiased). `R` independent replicates give the standard
//! error of each entry.
//!
//! Sampling runs in `f32` over chunks of rays (structure of arrays, 24 random bits per
//! coordinate from a counter-based [`SplitMix`] stream, a polynomial sine and cosine in the
//! concentric map, compiled for AVX2 or AVX-512 where available: [`crate::simd`]). The rays of a
//! replicate go out in Z-order of their direction cells, so that each packet of 16 is
//! coherent, and are traced 16 at a time (`rtcIntersect16`); the side of a patch a ray
//! meets comes from the hit triangle's normal. Hits are tallied per (patch, replicate) in a
//! per-worker array kept zero between rows (a patch's replicates side by side), and the
//! patches hit are found by a scan of the tallies (small scenes) or marked in a bit set as
//! they come (large ones, whose rows then cost one bit per patch they do not hit).
//!
//! **Patches no ray hit.** A row stores only the patches its `N = strata² × replicates`
//! rays hit. A patch no ray hit is not known to be hidden: its factor is estimated as 0,
//! and a factor below about `1/N` is missed by most rows of rays. Such a pair's bar is the
//! Jeffreys bar of a fraction seen 0 times in `N` trials, [`crate::sampling::fraction_se`]
//! `(0, N) ≈ 0.71 / N`, never 0 ([`Estimator::unresolved`], kept once for the whole matrix
//! as [`crate::matrix::FormFactors::unresolved`]). It is also the bar of the sum of all of
//! a row's unhit factors, since together they too were hit 0 times in the same `N` rays:
//! the *unresolved mass* of the row. One number serves every pair and row, because `N` is
//! the same for every row: no entry is stored for pairs no ray hit (storing one per pair
//! would fill the matrix, `n²` entries), and no per-pair test of whether the two can see
//! each other is run (it would cost what the rays save). The bar is one-sided (a factor is
//! `>= 0`, the estimate 0), so it widens the lower side of a row sum, not the upper: it
//! does not excuse a row over 1. For a one-sided 95% bound, `1 - 0.05^(1/N) ≈ 3 / N` (the
//! rule of three) is `4.2` such bars.

use glam::Vec3;

use super::{Context, Entry, Estimator, Row, Scratch as Buffers};
use crate::sampling::{below, fraction_se, hashed_permutation, jitter4, SplitMix};
use crate::visibility::{Rays, Tracer, NO_HIT};

/// Rays made, traced and counted together: a chunk's sampling buffers (about 24 KB) stay
/// in a 48 KB L1 data cache beside Embree's traversal data.
const CHUNK: usize = 256;

/// Fraction of an origin's distance to the patch centroid by which it is pulled inward.
const PULL: f32 = 1.0 / 16384.0;

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

    fn unresolved(&self) -> f64 {
        let n = self.strata.max(1).pow(2) * self.replicates.max(2);
        fraction_se(0.0, n as f64)
    }

    fn replicates(&self) -> usize {
        self.replicates.max(2)
    }

    fn row_bound(&self, n: usize) -> usize {
        // One entry per ray at most.
        let st = self.strata.max(1);
        n.min(st * st * self.replicates.max(2))
    }

    fn row(&self, ctx: &Context, i: usize, row: &mut Row, scratch: &mut Buffers) {
        self.row_with(ctx, i, row, ctx.vis, scratch);
    }
}

/// `sin x` and `cos x` for `|x| <= π/4`, by their Taylor polynomials to degree 11 and 12
/// (truncation error below 2e-9, under half an `f32` ulp): no branches and no calls, so a
/// loop of them runs four at a time.
#[inline(always)]
fn sin_cos_quarter(x: f32) -> (f32, f32) {
    let x2 = x * x;
    let sin = x
        * (1.0
            + x2 * (-1.0 / 6.0
                + x2 * (1.0 / 120.0
                    + x2 * (-1.0 / 5040.0 + x2 * (1.0 / 362_880.0 - x2 * (1.0 / 39_916_800.0))))));
    let cos = 1.0
        + x2 * (-0.5
            + x2 * (1.0 / 24.0
                + x2 * (-1.0 / 720.0
                    + x2 * (1.0 / 40_320.0
                        + x2 * (-1.0 / 3_628_800.0 + x2 * (1.0 / 479_001_600.0))))));
    (sin, cos)
}

/// [`cosine_direction`] in `f32` for every `(u[k], v[k])`, into `out = [x, y, z]`
/// (local frame, z up): the concentric map with the octant chosen by selects, not branches,
/// and a polynomial sine and cosine (`sin_cos_quarter`).
#[inline(always)]
pub fn cosine_directions(u: &[f32], v: &[f32], out: &mut [Vec<f32>; 3]) {
    let len = u.len();
    let v = &v[..len];
    let [x, y, z] = out;
    let (x, y, z) = (&mut x[..len], &mut y[..len], &mut z[..len]);
    for k in 0..len {
        let (a, b) = (2.0 * u[k] - 1.0, 2.0 * v[k] - 1.0);
        // |a| > |b|: r = a, φ = π/4 b/a; else r = b, φ = π/2 - π/4 a/b.
        let first = a.abs() > b.abs();
        let (r, num) = if first { (a, b) } else { (b, a) };
        let q = if r != 0.0 { num / r } else { 0.0 };
        let (sin, cos) = sin_cos_quarter(std::f32::consts::FRAC_PI_4 * q);
        let (c, s) = if first { (cos, sin) } else { (sin, cos) };
        x[k] = r * c;
        y[k] = r * s;
        z[k] = (1.0 - r * r).max(0.0).sqrt();
    }
}

/// Strata per side up to which [`cells_of`] finds a cell's column and row in `f32`
/// arithmetic: `(c + 1/2) / s` is then off by less than `s 2^-23`, under the `1 / 2s`
/// that separates its fraction from 0 and 1, so its floor is exact.
const ARITHMETIC_CELLS: usize = 2048;

/// The column and row of cell `perm[k]` of the `st x st` grid (row-major), as floats, into
/// `out[0][k]`, `out[1][k]`: by arithmetic in a vector pass when `st` is below
/// [`ARITHMETIC_CELLS`], else read from the table `cells` (gathers).
#[inline(always)]
fn cells_of(perm: &[u32], st: usize, cells: &[Vec<f32>; 2], out: [&mut [f32]; 2]) {
    let [col, row] = out;
    let m = perm.len();
    let (col, row) = (&mut col[..m], &mut row[..m]);
    if st < ARITHMETIC_CELLS {
        let (s, inv) = (st as f32, 1.0 / st as f32);
        for k in 0..m {
            let c = perm[k] as f32;
            let r = ((c + 0.5) * inv).floor();
            col[k] = c - r * s;
            row[k] = r;
        }
    } else {
        let (c0, c1) = (&cells[0][..], &cells[1][..]);
        for k in 0..m {
            let c = perm[k] as usize;
            col[k] = c0[c];
            row[k] = c1[c];
        }
    }
}

/// Buffers of [`Hemisphere::row_with`], kept between rows (in the driver's
/// [`super::Scratch`]).
#[derive(Default)]
pub(crate) struct Scratch {
    /// Cells of the `s x s` grid, `(column, row)` as floats, for `cells_of` strata.
    cells: [Vec<f32>; 2],
    cells_of: usize,
    /// Direction cells in Z-order (Morton order of `(column, row)`), as floats.
    zc: [Vec<f32>; 2],
    /// Random permutation pairing position strata with direction strata, and the
    /// position cells it picks.
    perm: Vec<u32>,
    pc: [Vec<f32>; 2],
    /// Random words of one replicate, two per ray.
    words: Vec<u64>,
    /// Unit-square coordinates of positions and of directions, one replicate's worth.
    u: [Vec<f32>; 4],
    /// Points on the patch and local directions.
    x: [Vec<f32>; 3],
    d: [Vec<f32>; 3],
    /// Rays of one replicate in world space (origins, directions), and what they hit.
    org: [Vec<f32>; 3],
    dir: [Vec<f32>; 3],
    hits: Vec<u32>,
    /// Hit tallies `counts[j * R + r]` of patch j in replicate r for patches `j < n` and a
    /// spare slot `j = n` that takes misses; all zero between rows.
    counts: Vec<u32>,
    /// Bit j set when slot j was hit in this row; all zero between rows.
    bits: Vec<u64>,
    /// The patches hit in a row, in order.
    hit: Vec<u32>,
    /// Hits of a row as keys `slot << 32 | r` (misses and the row's own patch left out),
    /// for scenes whose tallies would not stay in the cache ([`sorts_hits`]), and the
    /// radix sort's second buffer and histogram.
    keys: Vec<u64>,
    sorted: Vec<u64>,
    histogram: Vec<u32>,
}

impl Hemisphere {
    /// Row `i` with `tracer` answering the closest-hit query ([`Tracer::first_front_hits`])
    /// for batches of rays (origins already offset off patch i, see
    /// [`crate::visibility::Visibility::first_hit_origin`]; [`NO_HIT`] for a miss or a back
    /// side met first), one batch per chunk of a replicate; the rays asked for do not
    /// depend on the answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        tracer: &dyn Tracer,
        scratch: &mut Buffers,
    ) {
        let s = &mut scratch.hemisphere;
        let sorted = sorts_hits(ctx.patches.len(), self.replicates.max(2));
        crate::simd::with_widest(
            #[inline(always)]
            || self.row_in(ctx, i, row, tracer, s, sorted),
        )
    }

    /// Row `i` as [`Hemisphere::row_with`] makes it, its hits counted in tallies or, when
    /// `sorted`, sorted.
    #[inline(always)]
    fn row_in(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        tracer: &dyn Tracer,
        s: &mut Scratch,
        sorted: bool,
    ) {
        let p = ctx.patches;
        let reps = self.replicates.max(2);
        let st = self.strata.max(1);
        let m = st * st;
        s.prepare(st, m, p.len(), reps, sorted);
        let n_i = p.normal[i].as_vec3();
        let (t, b) = basis(n_i);
        let off = n_i * ctx.vis.eps();
        // Origins are pulled toward the centroid by PULL of their distance: a jittered point
        // can round onto the patch's edge, i.e. onto the plane of the wall meeting it there,
        // and a ray from there into that wall starts at t = 0 and escapes through it (one
        // ray in 6.3 M leaked so on the 32 x 32 cube). The pull keeps origins strictly
        // inside the patch, a relative shift of the sampled region far below the noise.
        let centroid = p.centroid[i].as_vec3();
        let on_i = p.sampler(i);
        let inv = 1.0 / st as f32;
        let n = p.len();
        // Small scenes find the patches hit by a scan of the tallies after the row, at
        // most four words per ray cast (a word scanned costs a few hundredths of a ray
        // traced); larger ones mark them in a bit set as they come; the largest sort
        // their hits ([`sorts_hits`]) and keep no tallies.
        let dense = n <= 4 * m && !sorted;
        let mut nk = 0;
        // One replicate at a time (its buffers stay in the L1 cache next to Embree's).
        for r in 0..reps {
            // Ray k leaves a jittered point of position cell perm[k] in a jittered
            // direction of direction cell k, the direction cells taken in Z-order: a
            // random pairing of the two stratifications (a hashed permutation keyed from
            // the (seed, i, replicate) stream), with consecutive rays close in direction, so
            // that each packet of 16 is coherent.
            let mut rng = SplitMix::keyed(ctx.seed, i as u64, u64::MAX, r as u64);
            let key = rng.next_u64();
            let perm = &mut s.perm[..m];
            hashed_permutation(perm, key as u32, below((key >> 32) as u32, m as u32));
            // Two words per ray, then converted in a vector pass: word 2k jitters the
            // position, word 2k + 1 the direction.
            rng.fill(&mut s.words[..2 * m]);
            let [pc0, pc1] = &mut s.pc;
            cells_of(perm, st, &s.cells, [&mut pc0[..m], &mut pc1[..m]]);
            // The replicate's rays in chunks of CHUNK, each made, traced and counted in
            // turn, so that the sampling buffers stay small next to Embree's data.
            for lo in (0..m).step_by(CHUNK) {
                let hi = (lo + CHUNK).min(m);
                let len = hi - lo;
                // Positions jittered in their cells pc, directions in the Z-ordered cells.
                let (pc, zc) = (&s.pc, &s.zc);
                let cells = [
                    &pc[0][lo..hi],
                    &pc[1][lo..hi],
                    &zc[0][lo..hi],
                    &zc[1][lo..hi],
                ];
                jitter4(&s.words[2 * lo..2 * hi], Some(cells), inv, &mut s.u);
                on_i.points32(&s.u[0][..len], &s.u[1][..len], &mut s.x);
                cosine_directions(&s.u[2][..len], &s.u[3][..len], &mut s.d);
                // World directions (unit up to rounding: the basis is orthonormal), origins
                // offset along the normal: every direction leaves the front side (z >= 0).
                let frame = (t, b, n_i);
                world(
                    len, &s.x, &s.d, frame, centroid, off, &mut s.org, &mut s.dir,
                );
                let (o, d) = (&s.org, &s.dir);
                let rays = Rays {
                    org: [&o[0][..len], &o[1][..len], &o[2][..len]],
                    dir: [&d[0][..len], &d[1][..len], &d[2][..len]],
                };
                tracer.first_front_hits(&rays, &mut s.hits[..len]);
                // Count front-side hits per (patch, replicate), without branches: a miss
                // (or a back side met first) and a hit on patch i itself count in the
                // spare slot n.
                let (counts, bits) = (&mut s.counts[..], &mut s.bits[..]);
                if sorted {
                    let keys = &mut s.keys[..];
                    for &j in &s.hits[..len] {
                        let jj = (j as usize).min(n);
                        let slot = if jj != i { jj } else { n };
                        keys[nk] = (slot as u64) << 32 | r as u64;
                        nk += (slot != n) as usize;
                    }
                } else if dense {
                    for &j in &s.hits[..len] {
                        let jj = (j as usize).min(n);
                        let slot = if jj != i { jj } else { n };
                        counts[slot * reps + r] += 1;
                    }
                } else {
                    for &j in &s.hits[..len] {
                        let jj = (j as usize).min(n);
                        let slot = if jj != i { jj } else { n };
                        counts[slot * reps + r] += 1;
                        bits[slot >> 6] |= 1 << (slot & 63);
                    }
                }
            }
        }
        row.rays += (m * reps) as u64;
        // Entries in column order (the bit set's order: the matrix assembly then finds each
        // row sorted), mean and variance of the replicate means from exact integer sums:
        // with S = Σ c_r and Q = Σ c_r², Var = (R Q - S²) / (R (R - 1) m²). The squared
        // standard error of the mean is Var / R.
        let rf = reps as f64;
        let (inv_mr, inv_se2) = (
            1.0 / (m as f64 * rf),
            1.0 / (rf * rf * (rf - 1.0) * (m as f64).powi(2)),
        );
        let entry = |j: usize, sum: i64, sq: i64| {
            let f = sum as f64 * inv_mr;
            let spread = reps as i64 * sq - sum * sum;
            Entry {
                j: j as u32,
                f,
                // Replicates that all counted the same hits (one each, say) have no
                // spread, but a handful of hits does not make the factor exact: the bar
                // of the fraction of hits then ([`fraction_se`]).
                se: if spread > 0 {
                    (spread as f64 * inv_se2).sqrt()
                } else {
                    fraction_se(f, m as f64 * rf)
                },
            }
        };
        if sorted {
            // The hits sorted by patch (stable: each patch's replicates stay in order), then
            // counted run by run.
            let bits = usize::BITS - n.leading_zeros();
            let keys = radix_sort_high(&mut s.keys, &mut s.sorted, &mut s.histogram, nk, bits);
            let mut k = 0;
            while k < nk {
                let j = keys[k] >> 32;
                let (mut sum, mut sq) = (0i64, 0i64);
                while k < nk && keys[k] >> 32 == j {
                    let (key, from) = (keys[k], k);
                    while k < nk && keys[k] == key {
                        k += 1;
                    }
                    let c = (k - from) as i64;
                    (sum, sq) = (sum + c, sq + c * c);
                }
                row.entries.push(entry(j as usize, sum, sq));
            }
            return;
        }
        // The patches hit, in order (the spare slot n is none): by a scan of the tallies,
        // or from the bit set.
        let mut hit = 0;
        if dense {
            for (j, t) in s.counts[..n * reps].chunks_exact(reps).enumerate() {
                s.hit[hit] = j as u32;
                hit += (t.iter().fold(0, |a, &c| a | c) != 0) as usize;
            }
        } else {
            s.bits[n >> 6] &= !(1 << (n & 63));
            for (w, word) in s.bits.iter_mut().enumerate() {
                let mut bits = std::mem::take(word);
                while bits != 0 {
                    s.hit[hit] = (w * 64) as u32 + bits.trailing_zeros();
                    hit += 1;
                    bits &= bits - 1;
                }
            }
        }
        let counts = &mut s.counts;
        row.entries.extend(s.hit[..hit].iter().map(|&j| {
            let (mut sum, mut sq) = (0i64, 0i64);
            let j = j as usize;
            // Read, then back to zero for the next row.
            for c in &mut counts[j * reps..(j + 1) * reps] {
                let v = std::mem::take(c) as i64;
                (sum, sq) = (sum + v, sq + v * v);
            }
            entry(j, sum, sq)
        }));
        s.counts[n * reps..(n + 1) * reps].fill(0);
    }
}

/// Size of a row's tallies (`(n + 1) R` counters) above which the row sorts its hits
/// instead of counting them in the table: the table then no longer stays in a core's
/// level-2 cache next to Embree's data, and every hit missed it twice, counted and read
/// back (docs/PERFORMANCE.md, section 1, *Hemisphere shooting: sorted hits at scale*).
const SORTED_TALLY_BYTES: usize = 256 << 10;

/// Whether rows of a scene of `n` patches and `reps` replicates sort their hits.
fn sorts_hits(n: usize, reps: usize) -> bool {
    (n + 1) * reps * std::mem::size_of::<u32>() > SORTED_TALLY_BYTES
}

/// Sorts `keys[..len]` by their bits `32..32 + bits` (a least-significant-digit radix sort,
/// stable), with `tmp` and `histogram` as scratch; returns the sorted keys (in `keys` or
/// in `tmp`).
fn radix_sort_high<'a>(
    keys: &'a mut [u64],
    tmp: &'a mut [u64],
    histogram: &mut Vec<u32>,
    len: usize,
    bits: u32,
) -> &'a [u64] {
    let passes = bits.div_ceil(RADIX_BITS).max(1);
    let width = bits.div_ceil(passes);
    let buckets = 1usize << width;
    histogram.resize(buckets, 0);
    let (mut from, mut to) = (&mut keys[..len], &mut tmp[..len]);
    for pass in 0..passes {
        let shift = 32 + pass * width;
        let mask = (buckets - 1) as u64;
        histogram.fill(0);
        for &k in from.iter() {
            histogram[((k >> shift) & mask) as usize] += 1;
        }
        let mut at = 0;
        for h in histogram.iter_mut() {
            (*h, at) = (at, at + *h);
        }
        for &k in from.iter() {
            let b = &mut histogram[((k >> shift) & mask) as usize];
            to[*b as usize] = k;
            *b += 1;
        }
        std::mem::swap(&mut from, &mut to);
    }
    from
}

/// Digit width of [`radix_sort_high`]'s passes, at most: a histogram of 4 KB.
const RADIX_BITS: u32 = 10;

/// World-space rays from local points `x` and local directions `d` (frame `(t, b, n)`,
/// z along the normal): origins pulled toward the centroid by [`PULL`] and offset by
/// `off`, into `org`/`dir` (structure of arrays).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn world(
    len: usize,
    x: &[Vec<f32>; 3],
    d: &[Vec<f32>; 3],
    (t, b, n): (Vec3, Vec3, Vec3),
    centroid: Vec3,
    off: Vec3,
    org: &mut [Vec<f32>; 3],
    dir: &mut [Vec<f32>; 3],
) {
    let (x0, x1, x2) = (&x[0][..len], &x[1][..len], &x[2][..len]);
    let (d0, d1, d2) = (&d[0][..len], &d[1][..len], &d[2][..len]);
    let [o0, o1, o2] = org;
    let (o0, o1, o2) = (&mut o0[..len], &mut o1[..len], &mut o2[..len]);
    let [w0, w1, w2] = dir;
    let (w0, w1, w2) = (&mut w0[..len], &mut w1[..len], &mut w2[..len]);
    for k in 0..len {
        let w = t * d0[k] + b * d1[k] + n * d2[k];
        let x = Vec3::new(x0[k], x1[k], x2[k]);
        let o = x + (centroid - x) * PULL + off;
        (o0[k], o1[k], o2[k]) = (o.x, o.y, o.z);
        (w0[k], w1[k], w2[k]) = (w.x, w.y, w.z);
    }
}

impl Scratch {
    /// Sizes the buffers for `len` rays (one replicate), `st x st` strata per replicate,
    /// `reps` replicates and a scene of `n` patches, whose rows count their hits in
    /// tallies or, when `sorted`, sort them.
    fn prepare(&mut self, st: usize, len: usize, n: usize, reps: usize, sorted: bool) {
        if sorted {
            self.keys.resize(len * reps, 0);
            self.sorted.resize(len * reps, 0);
        } else {
            // Sized exactly: the end of the row walks the whole bit set.
            self.bits.resize((n + 1).div_ceil(64), 0);
            self.hit.resize(n + 1, 0);
            if self.counts.len() < (n + 1) * reps {
                self.counts.resize((n + 1) * reps, 0);
            }
        }
        if self.cells_of != st {
            let [c0, c1] = &mut self.cells;
            c0.clear();
            c1.clear();
            for b in 0..st {
                for a in 0..st {
                    c0.push(a as f32);
                    c1.push(b as f32);
                }
            }
            // Z-order: cells sorted by the Morton code of (column, row), so that every run
            // of 4^k consecutive cells is a 2^k x 2^k block when st is a power of 2.
            let morton = |c: usize| {
                let (a, b) = ((c % st) as u64, (c / st) as u64);
                (0..32).fold(0u64, |z, bit| {
                    z | ((a >> bit) & 1) << (2 * bit) | ((b >> bit) & 1) << (2 * bit + 1)
                })
            };
            let mut order: Vec<usize> = (0..st * st).collect();
            order.sort_by_cached_key(|&c| morton(c));
            let [z0, z1] = &mut self.zc;
            z0.clear();
            z1.clear();
            for c in order {
                z0.push(c0[c]);
                z1.push(c1[c]);
            }
            self.cells_of = st;
        }
        self.perm.resize(st * st, 0);
        self.words.resize(2 * len, 0);
        for v in self
            .u
            .iter_mut()
            .chain(&mut self.x)
            .chain(&mut self.d)
            .chain(&mut self.pc)
            .chain(&mut self.org)
            .chain(&mut self.dir)
        {
            v.resize(len, 0.0);
        }
        self.hits.resize(len, NO_HIT);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Pcg32;

    /// The three ways a row finds its entries (a scan of the tallies, a bit set of the
    /// patches hit, sorted hits) give the same entries, bit for bit.
    #[test]
    fn sorted_hits_give_the_tallies_entries() {
        use crate::formfactor::Context;
        use crate::mesh::{PatchSet, Resolution};
        use crate::scene::Scene;
        use crate::visibility::Visibility;
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::Patches(500)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 11,
        };
        let n = patches.len();
        let mut s = Scratch::default();
        // 4 x 4 strata: n > 4 m, the bit set; 16 x 16: n <= 4 m, the scan.
        for (strata, replicates) in [(4, 2), (4, 3), (16, 4)] {
            let est = Hemisphere { strata, replicates };
            assert_eq!(n <= 4 * strata * strata, strata == 16, "{n}");
            let mut entries = 0;
            for i in (0..n).step_by(7) {
                let (mut tallied, mut sorted) = (Row::default(), Row::default());
                est.row_in(&ctx, i, &mut tallied, &vis, &mut s, false);
                est.row_in(&ctx, i, &mut sorted, &vis, &mut s, true);
                assert_eq!(tallied.entries, sorted.entries, "row {i}, {strata} strata");
                assert_eq!(tallied.rays, sorted.rays);
                entries += sorted.entries.len();
            }
            assert!(entries > n, "{entries}");
        }
        assert!(!sorts_hits(n, 4) && sorts_hits(100_000, 4));
    }

    #[test]
    fn f32_directions_match_the_f64_map() {
        let mut rng = Pcg32::keyed(5, 0, 0, 0);
        let mut uv: Vec<(f32, f32)> = (0..1000)
            .map(|_| (rng.next_f64() as f32, rng.next_f64() as f32))
            .collect();
        uv.extend([(0.5, 0.5), (0.0, 0.0), (1.0, 0.5), (0.5, 0.0), (0.25, 0.75)]);
        let (u, v): (Vec<f32>, Vec<f32>) = uv.iter().copied().unzip();
        let mut out = [vec![0.0; u.len()], vec![0.0; u.len()], vec![0.0; u.len()]];
        cosine_directions(&u, &v, &mut out);
        for (k, &(a, b)) in uv.iter().enumerate() {
            let want = cosine_direction(a as f64, b as f64);
            let got = Vec3::new(out[0][k], out[1][k], out[2][k]);
            // z = sqrt(1 - r²) is ill-conditioned at the rim (r -> 1): f32 rounding of x, y
            // gives up to ~3e-4 there.
            let close = (want.x - got.x).abs() < 1e-6 && (want.y - got.y).abs() < 1e-6;
            assert!(
                close && (want.z - got.z).abs() < 5e-4,
                "({a}, {b}): {want} vs {got}"
            );
            assert!((got.length() - 1.0).abs() < 1e-5 && got.z >= 0.0);
        }
    }

    #[test]
    fn cell_arithmetic_is_exact() {
        // Every cell of grids up to the largest side computed in f32, against integer
        // division, and the gather path beyond it.
        for st in [
            1usize,
            2,
            3,
            7,
            16,
            100,
            1023,
            1999,
            ARITHMETIC_CELLS - 1,
            ARITHMETIC_CELLS,
        ] {
            let m = st * st;
            let perm: Vec<u32> = (0..m as u32).rev().collect();
            let mut cells = [Vec::new(), Vec::new()];
            if st >= ARITHMETIC_CELLS {
                cells = [
                    (0..m).map(|c| (c % st) as f32).collect(),
                    (0..m).map(|c| (c / st) as f32).collect(),
                ];
            }
            let (mut col, mut row) = (vec![0.0; m], vec![0.0; m]);
            cells_of(&perm, st, &cells, [&mut col, &mut row]);
            for (k, &c) in perm.iter().enumerate() {
                let c = c as usize;
                assert_eq!(
                    (col[k], row[k]),
                    ((c % st) as f32, (c / st) as f32),
                    "{st} {c}"
                );
            }
        }
    }

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
