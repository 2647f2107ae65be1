//! Random streams and sample patterns.
//!
//! Every random decision is drawn from a stream keyed on `(seed, i, j, replicate)` (the
//! pbrt-v4 rule: work item i has its own stream), so results depend only on the seed and
//! patch ids, never on the thread count or the order rows are computed in.
//!
//! The generators: PCG32 (O'Neill 2014, XSH-RR output, 64-bit state), seeded through
//! SplitMix64 (Steele, Lea and Flood 2014) of the key; wyrand ([`Wy`], a Weyl sequence and
//! a 128-bit product); and SplitMix64 itself as a counter-based stream ([`SplitMix`]),
//! whose words are independent of each other and so come out of vector passes. Random
//! pairings of strata use Kensler's hashed permutation ([`hashed_permutation`]).

use glam::DVec3;

/// SplitMix64 finaliser: a bijective 64-bit mix.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The standard error of a fraction `p` of `n` trials (a visible fraction from `n` rays, a
/// share of hits), never 0.
///
/// The binomial `sqrt(p (1 - p) / n)` is 0 when every trial came out the same, though `n`
/// free rays only say that the hidden fraction is below about `3 / n` (the rule of three,
/// at 95%): a blocker hiding a few percent of a source is missed by 16 rays most of the
/// time. The fraction is therefore shrunk towards 1/2 by half a trial either way,
/// `q = (p n + 1/2) / (n + 1)` (the posterior mean under Jeffreys' prior; Brown, Cai and
/// DasGupta, "Interval estimation for a binomial proportion", Statistical Science 2001),
/// and the bar is `sqrt(q (1 - q) / n)`: about `1 / (n √2)` for a fraction of 0 or 1, close
/// to the binomial bar where both outcomes were seen.
pub fn fraction_se(p: f64, n: f64) -> f64 {
    let n = n.max(1.0);
    let q = (p.clamp(0.0, 1.0) * n + 0.5) / (n + 1.0);
    (q * (1.0 - q) / n).sqrt()
}

/// PCG32 random number generator.
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    /// A stream keyed on a seed and up to three integers.
    pub fn keyed(seed: u64, a: u64, b: u64, c: u64) -> Pcg32 {
        let k = mix64(seed ^ mix64(a ^ mix64(b ^ mix64(c))));
        let mut r = Pcg32 {
            state: 0,
            inc: (mix64(k ^ 0xDA94_2042_E4DD_58B5) << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(k);
        r.next_u32();
        r
    }

    /// Next 32 random bits.
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform double in [0, 1) with 53 random bits.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        let hi = (self.next_u32() as u64) << 21;
        let lo = (self.next_u32() >> 11) as u64;
        ((hi | lo) as f64) * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in [0, n) (Lemire's method without the rejection refinement's bias
    /// for n far below 2^32: the bias is below 2^-32 n).
    #[inline]
    pub fn below(&mut self, n: u32) -> u32 {
        below(self.next_u32(), n)
    }
}

/// A counter-based stream of 64-bit words: wyrand (Wang Yi's generator, the output
/// function `mum(s, s ^ C)` of a Weyl sequence `s += C`), keyed like [`Pcg32::keyed`].
///
/// Each output depends on the key and its position only, through one 64 x 64 -> 128-bit
/// multiply: no serial dependency beyond an add, so consecutive draws overlap in the
/// pipeline. One word gives two `f32` uniforms ([`unit_f32`] of each half).
#[derive(Clone, Copy, Debug)]
pub struct Wy {
    state: u64,
}

const WY_INC: u64 = 0xA076_1D64_78BD_642F;
const WY_XOR: u64 = 0xE703_7ED1_A0B4_28DB;

impl Wy {
    /// A stream keyed on a seed and up to three integers (distinct from the [`Pcg32`]
    /// stream of the same key).
    pub fn keyed(seed: u64, a: u64, b: u64, c: u64) -> Wy {
        Wy {
            state: mix64(seed ^ mix64(a ^ mix64(b ^ mix64(c ^ 0x5741_5952_414E_4421)))),
        }
    }

    /// Substream `r` of this stream: the same Weyl sequence started `r * 2^32` draws
    /// further on, so substreams `r < 2^32` of up to `2^32` draws each never overlap (the
    /// increment is odd, hence invertible modulo 2^64). Keyed on the stream's key and `r`.
    #[inline]
    pub fn substream(&self, r: u64) -> Wy {
        Wy {
            state: self
                .state
                .wrapping_add(r.wrapping_mul(WY_INC.wrapping_shl(32))),
        }
    }

    /// Next 64 random bits.
    #[inline(always)]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(WY_INC);
        let t = (self.state as u128) * ((self.state ^ WY_XOR) as u128);
        ((t >> 64) as u64) ^ (t as u64)
    }

    /// The next `out.len()` words, in order (the same as that many [`Wy::next_u64`]): a
    /// loop of independent multiplies the processor overlaps, kept apart from the float
    /// conversions so that those run as vector passes.
    #[inline]
    pub fn fill(&mut self, out: &mut [u64]) {
        for w in out.iter_mut() {
            *w = self.next_u64();
        }
    }

    /// Two uniform floats in [0, 1) (24 random bits each) from one draw.
    #[inline(always)]
    pub fn next_f32x2(&mut self) -> (f32, f32) {
        let r = self.next_u64();
        (unit_f32(r as u32), unit_f32((r >> 32) as u32))
    }

    /// Uniform integer in [0, n) from 32 bits (Lemire's multiply; bias below 2^-32 n).
    #[inline(always)]
    pub fn below(&mut self, n: u32) -> u32 {
        below(self.next_u64() as u32, n)
    }
}

/// The uniform float in [0, 1) made of the top 24 bits of `x` (every value a multiple of
/// 2^-24, all exactly representable).
#[inline(always)]
pub fn unit_f32(x: u32) -> f32 {
    (x >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// Unit-square coordinates from random words, four per pair of words, into `u`: coordinate
/// c of sample k is `(cells[c][k] + unit_f32(h)) * inv`, `h` the c-th 32-bit half of
/// `words[2k]`, `words[2k + 1]` (low half first), or `unit_f32(h)` alone when there are no
/// cells. A loop the compiler vectorizes; the words come first from [`Wy::fill`] or
/// [`SplitMix::fill`].
#[inline(always)]
pub fn jitter4(words: &[u64], cells: Option<[&[f32]; 4]>, inv: f32, u: &mut [Vec<f32>; 4]) {
    let len = words.len() / 2;
    let [u0, u1, u2, u3] = u;
    let (u0, u1, u2, u3) = (
        &mut u0[..len],
        &mut u1[..len],
        &mut u2[..len],
        &mut u3[..len],
    );
    let w = &words[..2 * len];
    match cells {
        Some([c0, c1, c2, c3]) => {
            let (c0, c1, c2, c3) = (&c0[..len], &c1[..len], &c2[..len], &c3[..len]);
            for k in 0..len {
                let (w0, w1) = (w[2 * k], w[2 * k + 1]);
                u0[k] = (c0[k] + unit_f32(w0 as u32)) * inv;
                u1[k] = (c1[k] + unit_f32((w0 >> 32) as u32)) * inv;
                u2[k] = (c2[k] + unit_f32(w1 as u32)) * inv;
                u3[k] = (c3[k] + unit_f32((w1 >> 32) as u32)) * inv;
            }
        }
        None => {
            for k in 0..len {
                let (w0, w1) = (w[2 * k], w[2 * k + 1]);
                u0[k] = unit_f32(w0 as u32);
                u1[k] = unit_f32((w0 >> 32) as u32);
                u2[k] = unit_f32(w1 as u32);
                u3[k] = unit_f32((w1 >> 32) as u32);
            }
        }
    }
}

/// Jittered samples on an `s x s` grid of strata of the unit square, in stratum order.
pub fn jittered(rng: &mut Pcg32, s: usize, out: &mut Vec<(f64, f64)>) {
    out.clear();
    let inv = 1.0 / s as f64;
    for b in 0..s {
        for a in 0..s {
            out.push((
                (a as f64 + rng.next_f64()) * inv,
                (b as f64 + rng.next_f64()) * inv,
            ));
        }
    }
}

/// A counter-based SplitMix64 stream (Steele, Lea and Flood 2014): word k of the stream
/// keyed `s` is `mix64(s + k γ)`, every word computed on its own, so that a run of them is
/// one vector pass ([`SplitMix::fill`]); the multiplies are 64-bit low halves, which
/// AVX-512 has as one instruction.
#[derive(Clone, Debug)]
pub struct SplitMix {
    state: u64,
}

/// The Weyl increment of [`mix64`] (the golden ratio in 64 bits).
const SM_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

impl SplitMix {
    /// A stream keyed on a seed and up to three integers (distinct from the [`Pcg32`] and
    /// [`Wy`] streams of the same key).
    pub fn keyed(seed: u64, a: u64, b: u64, c: u64) -> SplitMix {
        SplitMix {
            state: mix64(seed ^ mix64(a ^ mix64(b ^ mix64(c ^ 0x5350_4C49_544D_4958)))),
        }
    }

    /// Next 64 random bits.
    #[inline(always)]
    pub fn next_u64(&mut self) -> u64 {
        let w = mix64(self.state);
        self.state = self.state.wrapping_add(SM_GAMMA);
        w
    }

    /// The next `out.len()` words (the same as that many [`SplitMix::next_u64`]), as one
    /// loop of independent words that the compiler vectorizes.
    #[inline(always)]
    pub fn fill(&mut self, out: &mut [u64]) {
        let s = self.state;
        for (k, w) in out.iter_mut().enumerate() {
            *w = mix64(s.wrapping_add((k as u64).wrapping_mul(SM_GAMMA)));
        }
        self.state = s.wrapping_add((out.len() as u64).wrapping_mul(SM_GAMMA));
    }
}

/// `floor(x n / 2^32)`: an integer in [0, n) from 32 random bits `x` (Lemire's multiply;
/// bias below `n / 2^32`).
#[inline(always)]
pub fn below(x: u32, n: u32) -> u32 {
    ((x as u64 * n as u64) >> 32) as u32
}

/// One round of Kensler's hashed permutation ("Correlated multi-jittered sampling",
/// Pixar Technical Memo 13-01, 2013, `permute`): a bijection of `[0, w]` keyed by `p`,
/// for `w = 2^b - 1`.
#[inline(always)]
fn permute_round(mut i: u32, w: u32, p: u32) -> u32 {
    i ^= p;
    i = i.wrapping_mul(0xE170_893D);
    i ^= p >> 16;
    i ^= (i & w) >> 4;
    i ^= p >> 8;
    i = i.wrapping_mul(0x0929_EB3F);
    i ^= p >> 23;
    i ^= (i & w) >> 1;
    i = i.wrapping_mul(1 | p >> 27);
    i = i.wrapping_mul(0x6935_FA69);
    i ^= (i & w) >> 11;
    i = i.wrapping_mul(0x74DC_B303);
    i ^= (i & w) >> 2;
    i = i.wrapping_mul(0x9E50_1CC3);
    i ^= (i & w) >> 2;
    i = i.wrapping_mul(0xC860_A3DF);
    i &= w;
    i ^ (i >> 5)
}

/// A random-looking permutation of `[0, perm.len())` into `perm`, keyed by `key`, then
/// rotated by `offset` (taken modulo the length): Kensler's hashed permutation (2013), its
/// rounds for all indices as one vector pass, then cycle-walking (another round until the
/// value falls inside) for the few that land past the end when the length is not a power
/// of 2. With `offset` uniform, every `perm[k]` is uniform on `[0, len)` whatever the key,
/// as in a Fisher-Yates shuffle, at a fraction of its cost (no chain of dependent swaps).
#[inline(always)]
pub fn hashed_permutation(perm: &mut [u32], key: u32, offset: u32) {
    let l = perm.len() as u32;
    if l == 0 {
        return;
    }
    // The smallest all-ones mask covering l - 1 (0 for a single element).
    let w = u32::MAX.checked_shr((l - 1).leading_zeros()).unwrap_or(0);
    for (k, q) in perm.iter_mut().enumerate() {
        *q = permute_round(k as u32, w, key);
    }
    if w + 1 != l {
        for q in perm.iter_mut() {
            while *q >= l {
                *q = permute_round(*q, w, key);
            }
        }
    }
    let offset = offset % l;
    for q in perm.iter_mut() {
        let v = *q + offset;
        *q = if v >= l { v - l } else { v };
    }
}

/// The spherical triangle that a planar triangle subtends from a point, for directions
/// drawn uniformly in its solid angle (Arvo, "Stratified sampling of spherical triangles",
/// SIGGRAPH 1995): a map of the unit square onto the triangle that preserves area, so that
/// jittered strata of the square stay strata of the solid angle.
#[derive(Clone, Copy, Debug)]
pub struct SphericalTriangle {
    a: DVec3,
    b: DVec3,
    /// Unit tangent at `a` along the arc towards `c`.
    toward_c: DVec3,
    /// The angle at `a`.
    alpha: f64,
    /// `cos` of the arc from `a` to `b`.
    cos_ab: f64,
    area: f64,
}

impl SphericalTriangle {
    /// The triangle of unit directions `a`, `b`, `c`; `None` when it has no solid angle to
    /// speak of (below `1e-12` steradians: a triangle seen edge-on, or its corners nearly
    /// in one direction).
    pub fn new(a: DVec3, b: DVec3, c: DVec3) -> Option<SphericalTriangle> {
        let det = a.dot(b.cross(c)).abs();
        let (ab, bc, ca) = (a.dot(b), b.dot(c), c.dot(a));
        // The solid angle by Van Oosterom and Strackee (IEEE Trans. Biomed. Eng. 1983):
        // no cancellation for small triangles, unlike the angle sum less pi.
        let area = 2.0 * det.atan2(1.0 + ab + bc + ca);
        // The angle at `a` between the arcs to `b` and to `c`: the tangents there are
        // `b - (a.b) a` and `c - (a.c) a`, whose dot product is `b.c - (a.b)(a.c)` and the
        // length of whose cross product is `|a . (b x c)|`.
        let alpha = det.atan2(bc - ab * ca);
        let toward_c = (c - ca * a).normalize_or_zero();
        (area > 1e-12 && area.is_finite() && toward_c != DVec3::ZERO).then_some(SphericalTriangle {
            a,
            b,
            toward_c,
            alpha,
            cos_ab: ab,
            area,
        })
    }

    /// The solid angle, in steradians.
    pub fn area(&self) -> f64 {
        self.area
    }

    /// The unit direction of `(u, v)` in the unit square: `u` picks the sub-triangle
    /// `(a, b, c')` of solid angle `u × area` (its corner `c'` on the arc from `a` to `c`),
    /// `v` the point on the arc from `b` to `c'` that splits that sub-triangle's solid
    /// angle in the ratio `v : 1 - v` (Arvo 1995, section 2).
    pub fn sample(&self, u: f64, v: f64) -> DVec3 {
        let (sin_alpha, cos_alpha) = self.alpha.sin_cos();
        let (s, t) = (u * self.area - self.alpha).sin_cos();
        let (p, q) = (t - cos_alpha, s + sin_alpha * self.cos_ab);
        // cos of the arc from `a` to `c'`.
        let cos_ac =
            (((q * t - p * s) * cos_alpha - q) / ((q * s + p * t) * sin_alpha)).clamp(-1.0, 1.0);
        let c = cos_ac * self.a + (1.0 - cos_ac * cos_ac).max(0.0).sqrt() * self.toward_c;
        let z = 1.0 - v * (1.0 - c.dot(self.b));
        let along = (c - c.dot(self.b) * self.b).normalize_or_zero();
        z * self.b + (1.0 - z * z).max(0.0).sqrt() * along
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Triangles seen from the origin (corners, normal of the point): far, near, and with
    /// the point close to an edge (a solid angle near 2 pi).
    fn triangles() -> Vec<([DVec3; 3], DVec3)> {
        let z = DVec3::Z;
        vec![
            (
                [
                    DVec3::new(-1.0, -1.0, 5.0),
                    DVec3::new(2.0, 0.0, 5.0),
                    DVec3::new(0.0, 1.5, 6.0),
                ],
                z,
            ),
            (
                [
                    DVec3::new(-1.0, -1.0, 0.5),
                    DVec3::new(1.0, -1.0, 0.5),
                    DVec3::new(0.0, 1.0, 0.5),
                ],
                z,
            ),
            (
                [
                    DVec3::new(-3.0, 1e-3, 1e-3),
                    DVec3::new(3.0, 1e-3, 1e-3),
                    DVec3::new(0.0, 4.0, 1e-3),
                ],
                DVec3::new(0.0, 0.6, 0.8),
            ),
            (
                [
                    DVec3::new(1e-4, -1.0, 0.0),
                    DVec3::new(1e-4, 1.0, 0.0),
                    DVec3::new(1e-4, 0.0, 2.0),
                ],
                DVec3::X,
            ),
        ]
    }

    /// Directions fall inside the spherical triangle, and they are uniform in its solid
    /// angle: `Ω / π` times the mean cosine of 128 x 128 jittered directions is the point's
    /// form factor to the triangle (Lambert's closed form), to the jittered rule's error.
    #[test]
    fn spherical_triangle_directions_are_uniform_in_its_solid_angle() {
        let mut rng = Pcg32::keyed(7, 0, 0, 0);
        let mut grid = Vec::new();
        for (corners, n) in triangles() {
            let [a, b, c] = corners.map(|p| p.normalize());
            let tri = SphericalTriangle::new(a, b, c).expect("a proper triangle");
            let det = a.dot(b.cross(c));
            jittered(&mut rng, 128, &mut grid);
            let mut sum = 0.0;
            for &(u, v) in &grid {
                let d = tri.sample(u, v);
                assert!((d.length() - 1.0).abs() < 1e-9, "{d}");
                for (p, q) in [(a, b), (b, c), (c, a)] {
                    assert!(
                        d.dot(p.cross(q)) * det.signum() > -1e-9,
                        "{d} outside {corners:?}"
                    );
                }
                sum += d.dot(n).max(0.0);
            }
            let estimate = tri.area() / std::f64::consts::PI * sum / grid.len() as f64;
            let exact = crate::analytic::point_to_polygon(DVec3::ZERO, n, &corners);
            assert!(
                (estimate - exact).abs() < 2e-4 * exact.max(1e-3),
                "{corners:?}: {estimate} against {exact}"
            );
        }
    }

    /// A triangle seen edge-on has no solid angle to sample.
    #[test]
    fn an_edge_on_triangle_has_no_spherical_triangle() {
        let (a, b, c) = (DVec3::X, DVec3::Y, (DVec3::X + DVec3::Y).normalize());
        assert!(SphericalTriangle::new(a, b, c).is_none());
    }

    /// Mean, variance and lag-one correlation (the two halves of a word, and consecutive
    /// words) of samples that should be uniform on [0, 1): three checks at 5 standard
    /// errors each (the variance's is `sqrt(1/180 / m)`).
    fn assert_uniform_moments(xs: &[f64]) {
        let m = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / m;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / m;
        let cov = xs
            .windows(2)
            .map(|w| (w[0] - 0.5) * (w[1] - 0.5))
            .sum::<f64>()
            / (m - 1.0);
        assert!((mean - 0.5).abs() < 5.0 * (1.0 / 12.0 / m).sqrt(), "{mean}");
        assert!(
            (var - 1.0 / 12.0).abs() < 5.0 * (1.0 / 180.0 / m).sqrt(),
            "{var}"
        );
        assert!(cov.abs() < 5.0 / 12.0 / m.sqrt(), "{cov}");
    }

    #[test]
    fn streams_differ_and_repeat() {
        let a: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 2, 3, 4);
                move |_| r.next_u32()
            })
            .collect();
        let b: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 2, 3, 4);
                move |_| r.next_u32()
            })
            .collect();
        let c: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 3, 2, 4);
                move |_| r.next_u32()
            })
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn wy_streams_repeat_and_have_uniform_moments() {
        let mut a = Wy::keyed(1, 2, 3, 4);
        let mut b = Wy::keyed(1, 2, 3, 4);
        let mut c = Wy::keyed(1, 3, 2, 4);
        let (x, y, z) = (a.next_u64(), b.next_u64(), c.next_u64());
        assert_eq!(x, y);
        assert_ne!(x, z);
        let mut r = Wy::keyed(7, 0, 0, 0);
        let n = 100_000;
        let mut xs = Vec::with_capacity(2 * n);
        for _ in 0..n {
            let (u, v) = r.next_f32x2();
            assert!((0.0..1.0).contains(&u) && (0.0..1.0).contains(&v));
            xs.push(u as f64);
            xs.push(v as f64);
        }
        assert_uniform_moments(&xs);
        assert_eq!(unit_f32(u32::MAX), 1.0 - 1.0 / 16_777_216.0);
        // Substream 0 is the stream itself; substream 1 starts 2^32 draws further on.
        let base = Wy::keyed(1, 2, 3, 0);
        assert_eq!(base.substream(0).next_u64(), base.clone().next_u64());
        let mut far = base;
        far.state = far.state.wrapping_add(WY_INC.wrapping_mul(1 << 32));
        assert_eq!(base.substream(1).next_u64(), far.next_u64());
        assert_ne!(base.substream(1).next_u64(), base.substream(2).next_u64());
    }

    #[test]
    fn splitmix_fill_is_the_stream_and_uniform() {
        let mut a = SplitMix::keyed(1, 2, 3, 4);
        let mut b = a.clone();
        let mut words = vec![0u64; 1001];
        a.fill(&mut words);
        for &w in &words {
            assert_eq!(w, b.next_u64());
        }
        // The stream goes on where the fill stopped.
        assert_eq!(a.next_u64(), b.next_u64());
        assert_ne!(
            SplitMix::keyed(1, 2, 3, 4).next_u64(),
            SplitMix::keyed(1, 3, 2, 4).next_u64()
        );
        // Moments of the 32-bit halves as 24-bit floats, and the lag-one correlation.
        let mut r = SplitMix::keyed(9, 0, 0, 0);
        let mut w = vec![0u64; 100_000];
        r.fill(&mut w);
        let xs: Vec<f64> = w
            .iter()
            .flat_map(|&w| [unit_f32(w as u32) as f64, unit_f32((w >> 32) as u32) as f64])
            .collect();
        assert_uniform_moments(&xs);
    }

    #[test]
    fn hashed_permutations_are_permutations() {
        let mut perm = Vec::new();
        let mut seen = Vec::new();
        for l in (0..=300).chain([511, 512, 513, 1000, 4096, 65_537]) {
            for key in [0u32, 1, 0xDEAD_BEEF, u32::MAX] {
                for offset in [0u32, 1, 77, u32::MAX] {
                    perm.resize(l, 0);
                    hashed_permutation(&mut perm, key, offset);
                    seen.clear();
                    seen.resize(l, false);
                    for &q in &perm {
                        assert!((q as usize) < l && !seen[q as usize], "l {l} key {key}");
                        seen[q as usize] = true;
                    }
                }
            }
        }
        // Different keys give different permutations (not just rotations of one).
        let (mut a, mut b) = (vec![0u32; 256], vec![0u32; 256]);
        hashed_permutation(&mut a, 1, 0);
        hashed_permutation(&mut b, 2, 0);
        assert!((0..256).all(|o| (0..256).any(|k| b[k] != (a[k] + o) % 256)));
    }

    #[test]
    fn hashed_permutation_entries_are_uniform_over_keys() {
        // With a uniform offset, each entry of the permutation is uniform on [0, l): the
        // property that keeps a random pairing of strata unbiased. Chi-square of where
        // entries 0 and 17 land over 20,000 keyed draws, l = 24 (not a power of 2).
        let l = 24usize;
        let n = 20_000;
        let mut rng = SplitMix::keyed(3, 0, 0, 0);
        let mut perm = vec![0u32; l];
        let mut counts = [vec![0usize; l], vec![0usize; l]];
        for _ in 0..n {
            let w = rng.next_u64();
            hashed_permutation(&mut perm, w as u32, below((w >> 32) as u32, l as u32));
            counts[0][perm[0] as usize] += 1;
            counts[1][perm[17] as usize] += 1;
        }
        let e = n as f64 / l as f64;
        for c in &counts {
            let chi2: f64 = c.iter().map(|&o| (o as f64 - e).powi(2) / e).sum();
            // 23 degrees of freedom: P(chi2 > 55) < 2e-4 per check.
            assert!(chi2 < 55.0, "chi2 {chi2}: {c:?}");
        }
    }

    #[test]
    fn uniform_mean_and_variance() {
        let mut r = Pcg32::keyed(7, 0, 0, 0);
        let n = 200_000;
        let xs: Vec<f64> = (0..n).map(|_| r.next_f64()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        // Standard error of the mean is sqrt(1/12 / n) = 6.5e-4; 5 sigma.
        assert!(
            (mean - 0.5).abs() < 5.0 * (1.0f64 / 12.0 / n as f64).sqrt(),
            "{mean}"
        );
        assert!((var - 1.0 / 12.0).abs() < 2e-3, "{var}");
    }
}
