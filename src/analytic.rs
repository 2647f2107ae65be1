//! Closed-form configuration factors: the validation catalogue.
//!
//! Every estimator in [`crate::formfactor`] is checked against these. Each function is a
//! pure `f64` formula and names its source; the catalogue numbers are those of Howell's
//! "A Catalog of Radiation Heat Transfer Configuration Factors" (3rd ed., section B:
//! differential element to finite area; section C: finite area to finite area), the same
//! formulas as in Siegel and Howell, "Thermal Radiation Heat Transfer".
//!
//! | function | configuration | source |
//! |---|---|---|
//! | [`parallel_rectangles`] | directly opposed parallel rectangles | Howell C-11 |
//! | [`perpendicular_rectangles`] | perpendicular rectangles with a common edge | Howell C-14 |
//! | [`coaxial_disks`] | parallel coaxial disks | Howell C-41 |
//! | [`diff_to_parallel_rectangle`] | element facing a parallel rectangle, on the normal through a corner | Howell B-3 |
//! | [`diff_to_perpendicular_rectangle`] | element in a plane perpendicular to a rectangle | Howell B-8 with Φ = 90° |
//! | [`sphere_interior`] | two areas on the inside of one sphere | Siegel and Howell |
//! | [`crossed_strings`], [`strips_common_edge`], [`parallel_strips`], [`shelf_factors`] | infinitely long strips (2D) | Hottel's crossed strings |
//! | [`point_to_polygon`] | differential element to any planar polygon, unoccluded | Lambert's contour integral |
//!
//! In 3D a factor from a finite area is `F_ij = 1/A_i ∫∫ cos θ_x cos θ_y / (π r²) dA_y dA_x`
//! (radiosidade.md, "Fator de Forma"); from a differential element it is the inner integral
//! alone. In 2D (infinitely long strips, per unit length) the kernel is
//! `cos θ_x cos θ_y / (2 r)`.
//!
//! The unit tests at the bottom check every formula against an independent tensor
//! Gauss–Legendre quadrature of its defining integral (graded toward singular edges), and
//! against the published values (unit squares: C-11 gives 0.1998249, C-14 gives 0.2000438).
//!
//! ```
//! use radiosity::analytic::{parallel_rectangles, perpendicular_rectangles};
//! assert!((parallel_rectangles(1.0, 1.0, 1.0) - 0.1998249).abs() < 1e-7);
//! assert!((perpendicular_rectangles(1.0, 1.0, 1.0) - 0.2000438).abs() < 1e-7);
//! ```

use std::f64::consts::PI;

use glam::DVec3;

/// Directly opposed parallel rectangles `a x b`, a distance `c` apart (Howell C-11).
///
/// With `X = a/c`, `Y = b/c`:
///
/// `F = 2/(π X Y) [ ln sqrt((1+X²)(1+Y²)/(1+X²+Y²)) + X sqrt(1+Y²) atan(X/sqrt(1+Y²))
///      + Y sqrt(1+X²) atan(Y/sqrt(1+X²)) - X atan X - Y atan Y ]`.
///
/// Symmetric in `a` and `b`, and the same in both directions (equal areas). Unit squares
/// at distance 1 give 0.1998249. Loses digits to cancellation when `a, b << c`.
pub fn parallel_rectangles(a: f64, b: f64, c: f64) -> f64 {
    let (x, y) = (a / c, b / c);
    let (x2, y2) = (x * x, y * y);
    let (sx, sy) = ((1.0 + x2).sqrt(), (1.0 + y2).sqrt());
    let log = 0.5 * ((1.0 + x2) * (1.0 + y2) / (1.0 + x2 + y2)).ln();
    2.0 / (PI * x * y)
        * (log + x * sy * (x / sy).atan() + y * sx * (y / sx).atan() - x * x.atan() - y * y.atan())
}

/// Perpendicular rectangles with a common edge of length `l` (Howell C-14): the factor
/// **from** the rectangle `w x l` (width `w` measured away from the common edge) **to**
/// the rectangle `h x l` (height `h` measured away from the common edge).
///
/// With `H = h/l`, `W = w/l`:
///
/// `F = 1/(π W) [ W atan(1/W) + H atan(1/H) - sqrt(H²+W²) atan(1/sqrt(H²+W²))
///      + 1/4 ln( (1+W²)(1+H²)/(1+W²+H²) · [W²(1+W²+H²)/((1+W²)(W²+H²))]^(W²)
///                · [H²(1+H²+W²)/((1+H²)(H²+W²))]^(H²) ) ]`.
///
/// The reverse factor follows by reciprocity: `perpendicular_rectangles(w, l, h)`.
/// Unit squares give 0.2000438.
pub fn perpendicular_rectangles(h: f64, l: f64, w: f64) -> f64 {
    let (hh, ww) = (h / l, w / l);
    let (h2, w2) = (hh * hh, ww * ww);
    let s2 = h2 + w2;
    let s = s2.sqrt();
    let log = ((1.0 + w2) * (1.0 + h2) / (1.0 + s2)).ln()
        + w2 * (w2 * (1.0 + s2) / ((1.0 + w2) * s2)).ln()
        + h2 * (h2 * (1.0 + s2) / ((1.0 + h2) * s2)).ln();
    (ww * (1.0 / ww).atan() + hh * (1.0 / hh).atan() - s * (1.0 / s).atan() + 0.25 * log)
        / (PI * ww)
}

/// From a disk of radius `r1` to a parallel coaxial disk of radius `r2`, a distance `h`
/// apart (Howell C-41).
///
/// With `R1 = r1/h`, `R2 = r2/h`, `X = 1 + (1 + R2²)/R1²`:
/// `F = 1/2 [X - sqrt(X² - 4 (R2/R1)²)]`.
pub fn coaxial_disks(r1: f64, r2: f64, h: f64) -> f64 {
    let (q1, q2) = (r1 / h, r2 / h);
    let x = 1.0 + (1.0 + q2 * q2) / (q1 * q1);
    let k = q2 / q1;
    0.5 * (x - (x * x - 4.0 * k * k).sqrt())
}

/// From a differential element to a parallel rectangle `a x b` facing it, the element on
/// the normal to the rectangle through one of its corners, a distance `c` away
/// (Howell B-3).
///
/// With `A = a/c`, `B = b/c`:
/// `F = 1/(2π) [ A/sqrt(1+A²) atan(B/sqrt(1+A²)) + B/sqrt(1+B²) atan(A/sqrt(1+B²)) ]`.
pub fn diff_to_parallel_rectangle(a: f64, b: f64, c: f64) -> f64 {
    let (aa, bb) = (a / c, b / c);
    let (sa, sb) = ((1.0 + aa * aa).sqrt(), (1.0 + bb * bb).sqrt());
    (aa / sa * (bb / sa).atan() + bb / sb * (aa / sb).atan()) / (2.0 * PI)
}

/// From a differential element to a rectangle in a plane perpendicular to the element's
/// plane (Howell B-8 with the planes at Φ = 90°; Hamilton and Morgan 1952).
///
/// The rectangle has one edge of length `b` on the line where the two planes meet, and
/// extends a height `a` from that line (on the side the element faces). The element lies
/// in its own plane a distance `c` from that line, on the perpendicular to it through one
/// corner of the rectangle. In coordinates: element at the origin with normal `+z`,
/// rectangle in the plane `x = c`, `0 <= y <= b`, `0 <= z <= a`.
///
/// `F = 1/(2π) [ atan(b/c) - c/sqrt(a²+c²) atan(b/sqrt(a²+c²)) ]`,
///
/// which is also what [`point_to_polygon`] gives edge by edge (two edges of the rectangle
/// lie in planes through the element normal and contribute nothing).
pub fn diff_to_perpendicular_rectangle(a: f64, b: f64, c: f64) -> f64 {
    let s = (a * a + c * c).sqrt();
    ((b / c).atan() - c / s * (b / s).atan()) / (2.0 * PI)
}

/// From any area to an area `a_j` on the inside of a sphere of total area `a_total`
/// (Siegel and Howell; Cohen and Wallace 1993, sec. 4.x exercises): for two points on a
/// sphere of radius `R`, `cos θ_x = cos θ_y = r / (2R)`, so the kernel is the constant
/// `1/(4π R²)` and `F = a_j / a_total`, independent of the emitter.
pub fn sphere_interior(a_j: f64, a_total: f64) -> f64 {
    a_j / a_total
}

/// Hottel's crossed-strings rule for two infinitely long strips, given by their
/// cross-sections: from strip `a0 -> a1` to strip `b0 -> b1` (2D points, per unit length).
///
/// `F_ab = [(|a0 b1| + |a1 b0|) - (|a0 b0| + |a1 b1|)] / (2 |a0 a1|)`
/// (Hottel and Sarofim 1967; Modest, "Radiative Heat Transfer", sec. 4.8): crossed strings
/// minus uncrossed strings over twice the emitter width. Valid when the strips face each
/// other and nothing blocks the strings (each strip sees all of the other, so the strings
/// are straight). The absolute value is returned, so the order of the end points does not
/// matter: in a convex quadrilateral the diagonals are longer than either pair of opposite
/// sides. Strips sharing an end point (a zero-length string) are allowed.
pub fn crossed_strings(a0: [f64; 2], a1: [f64; 2], b0: [f64; 2], b1: [f64; 2]) -> f64 {
    let d = |p: [f64; 2], q: [f64; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
    let crossed = d(a0, b1) + d(a1, b0);
    let uncrossed = d(a0, b0) + d(a1, b1);
    (crossed - uncrossed).abs() / (2.0 * d(a0, a1))
}

/// Two infinitely long strips with a common edge, of widths `w1` (emitter) and `w2`, at
/// interior angle `angle` (radians, in (0, π)) between them (crossed strings):
///
/// `F_12 = (w1 + w2 - sqrt(w1² + w2² - 2 w1 w2 cos angle)) / (2 w1)`.
pub fn strips_common_edge(w1: f64, w2: f64, angle: f64) -> f64 {
    (w1 + w2
        - (w1 * w1 + w2 * w2 - 2.0 * w1 * w2 * angle.cos())
            .max(0.0)
            .sqrt())
        / (2.0 * w1)
}

/// Two directly opposed parallel infinitely long strips of width `w`, a distance `h` apart
/// (crossed strings): `F = sqrt(1 + (h/w)²) - h/w`.
pub fn parallel_strips(w: f64, h: f64) -> f64 {
    let g = h / w;
    (1.0 + g * g).sqrt() - g
}

/// The infinite shelf of the notes (radiosidade.md, "prateleira infinita"; shared NOTES.md):
/// floor A (width a), back wall B (width b, perpendicular to A, common edge), top C (width
/// a, parallel to A, common edge with B); `g = b / a`. Returns `(F_AB, F_AC, F_BC)`:
///
/// - `F_AB = (1 + g - sqrt(1 + g²)) / 2`
/// - `F_AC = sqrt(1 + g²) - g`
/// - `F_BC = (1 + 1/g - sqrt(1 + 1/g²)) / 2`
///
/// (the crossed-strings rule: [`strips_common_edge`] at 90° and [`parallel_strips`]).
pub fn shelf_factors(g: f64) -> (f64, f64, f64) {
    let f_ab = (1.0 + g - (1.0 + g * g).sqrt()) / 2.0;
    let f_ac = (1.0 + g * g).sqrt() - g;
    let ig = 1.0 / g;
    let f_bc = (1.0 + ig - (1.0 + ig * ig).sqrt()) / 2.0;
    (f_ab, f_ac, f_bc)
}

/// Exact unoccluded factor from a differential element at `x` with normal `n_x` to the
/// planar polygon `poly` (any winding, convex or not), by Lambert's contour integral
/// (Baum, Rushmeier and Winget 1989, eq. 6; Cohen and Wallace 1993, eq. 4.20):
///
/// `F = 1/(2π) Σ_k γ_k (n_x · u_k)`,
///
/// where for edge k from `p_k` to `p_{k+1}`, `γ_k` is the angle it subtends at `x` and
/// `u_k` the unit normal of the plane through `x` and the edge,
/// `(p_k - x) × (p_{k+1} - x)` normalised. The angle is `atan2(|R_k × R_{k+1}|,
/// R_k · R_{k+1})`, accurate for all angles.
///
/// - The formula holds only for the part of the polygon in front of `x`'s plane, so the
///   polygon is first clipped (Sutherland–Hodgman) to the half-space `n_x · (p - x) >= 0`;
///   the clipped edge lying in that plane contributes its full angle (`n_x · u = ±1`).
/// - The polygon is treated as two-sided: the winding seen from `x` only fixes the sign
///   of the sum, and its absolute value is returned. A caller with one-sided receivers
///   must itself return 0 when `x` is behind the receiver.
/// - Degenerate edges (x on the edge's line, or at a vertex: `|R_k × R_{k+1}|` below
///   `1e-12 |R_k| |R_{k+1}|`) contribute 0, so there is no NaN for `x` on the polygon's
///   edge or plane. On the polygon's boundary the value is then not the one-sided limit;
///   that set has measure zero for any integral over `x`.
/// - A polygon with no corner strictly in front of `x`'s plane (relative tolerance
///   `1e-12`) gives 0; this includes `x` inside a polygon lying in its own plane.
/// - `n_x` need not be unit length; a zero normal or fewer than 3 corners give 0.
pub fn point_to_polygon(x: DVec3, n_x: DVec3, poly: &[DVec3]) -> f64 {
    let n = n_x.normalize_or_zero();
    if n == DVec3::ZERO || poly.len() < 3 {
        return 0.0;
    }
    point_to_polygon_unit(x, n, poly)
}

/// [`point_to_polygon`] for a unit normal `n`: the absolute value of
/// [`point_to_polygon_oriented`].
#[inline]
pub fn point_to_polygon_unit(x: DVec3, n: DVec3, poly: &[DVec3]) -> f64 {
    point_to_polygon_oriented(x, n, poly).abs()
}

/// The contour sum of [`point_to_polygon`] with its sign (unit normal `n`): positive where
/// `x` sees the side of `poly` about which its corners turn counter-clockwise (the front of
/// a polygon wound by the right-hand rule about its normal), negative where it sees the
/// back. Its absolute value is [`point_to_polygon_unit`]. For a planar polygon the sign is
/// the same wherever `x` sees any of it; for a warped one (corners off a common plane)
/// seen nearly edge-on the sum can pass through 0, where the absolute value has a kink and
/// this does not: a quadrature over `x` converges on this one.
///
/// When every corner of a polygon of at most [`MOST_CORNERS`] corners is strictly in front
/// of `x` (the common case inside a room), no clipping is needed and each corner's
/// distance is computed once.
#[inline]
pub fn point_to_polygon_oriented(x: DVec3, n: DVec3, poly: &[DVec3]) -> f64 {
    let m = poly.len();
    if (3..=MOST_CORNERS).contains(&m) {
        let mut r = [DVec3::ZERO; MOST_CORNERS];
        let mut len2 = [0.0f64; MOST_CORNERS];
        let (mut all_front, mut front, mut reach2) = (true, f64::NEG_INFINITY, 0.0f64);
        for k in 0..m {
            r[k] = poly[k] - x;
            let d = n.dot(r[k]);
            // Corners on the plane need no clipping either (no edge crosses it).
            all_front &= d >= 0.0;
            front = front.max(d);
            len2[k] = r[k].length_squared();
            reach2 = reach2.max(len2[k]);
        }
        if all_front {
            // The same tests as the general path, squared.
            if front <= 0.0 || front * front <= 1e-24 * reach2 {
                return 0.0;
            }
            let mut sum = 0.0;
            for k in 0..m {
                let k1 = if k + 1 == m { 0 } else { k + 1 };
                let c = r[k].cross(r[k1]);
                let cl2 = c.length_squared();
                if cl2 > 1e-24 * len2[k] * len2[k1] {
                    let cl = cl2.sqrt();
                    sum += angle(cl, r[k].dot(r[k1])) * n.dot(c) / cl;
                }
            }
            return -sum / (2.0 * PI);
        }
    }
    point_to_polygon_clipped(x, n, poly)
}

/// Most corners of a polygon that [`point_to_polygon_oriented`] and
/// [`point_to_polygon_lanes`] take without the general (clipping) path: a quadrilateral
/// clipped by a plane has at most 5.
pub const MOST_CORNERS: usize = 5;

/// Points evaluated together by [`point_to_polygon_lanes`].
pub const LANES: usize = 8;

/// [`point_to_polygon_oriented`] at up to [`LANES`] points `xs` against one polygon of 3 to
/// [`MOST_CORNERS`] corners, written as structure-of-arrays passes over the lanes, without
/// branches, so that the compiler vectorizes them (run it under
/// [`crate::simd::with_widest`]). Every lane computes the same IEEE operations in the
/// same order as the scalar function, so `out[l]` is `point_to_polygon_oriented(xs[l], n, poly)` bit for bit (test
/// `lanes_match_the_scalar_factor_bit_for_bit`), except in the lanes whose bit is set in
/// the returned mask: there the polygon has a corner behind `xs[l]`'s plane and needs the
/// clipped path, which the caller takes. Lanes past `xs.len()` are left at 0.
///
/// One point costs about 4 divisions, a square root and a rational `atan` per edge, all
/// in a chain; side by side, 8 points go through them in about the time of 3.
#[inline(always)]
pub fn point_to_polygon_lanes(
    xs: &[DVec3],
    n: DVec3,
    poly: &[DVec3],
    out: &mut [f64; LANES],
) -> u32 {
    debug_assert!((3..=MOST_CORNERS).contains(&poly.len()) && xs.len() <= LANES);
    let used = xs.len();
    let (mut px, mut py, mut pz) = ([0.0f64; LANES], [0.0f64; LANES], [0.0f64; LANES]);
    for l in 0..LANES {
        // Idle lanes repeat the first point: their work is discarded.
        let x = xs[if l < used { l } else { 0 }];
        (px[l], py[l], pz[l]) = (x.x, x.y, x.z);
    }
    factor_lanes(
        poly.len(),
        n,
        used,
        #[inline(always)]
        |k, l| {
            let c = poly[k];
            (c.x - px[l], c.y - py[l], c.z - pz[l])
        },
        out,
    )
}

/// Polygons evaluated together by [`point_to_polygons_lanes`].
pub const POLYGON_LANES: usize = 4;

/// [`point_to_polygon_oriented`] from one point `x` to up to [`POLYGON_LANES`] polygons
/// `polys`, each of 3 to [`MOST_CORNERS`] corners, lane by lane as
/// [`point_to_polygon_lanes`] goes over points: `out[l]` is
/// `point_to_polygon_oriented(x, n, polys[l])` bit for bit (test
/// `polygon_lanes_match_the_scalar_factor_bit_for_bit`), except in the lanes whose bit is
/// set in the returned mask (a corner behind `x`'s plane: the clipped path, which the
/// caller takes). A polygon with fewer corners than the most of the batch repeats its
/// last corner: the edge from it to itself is degenerate and adds `+0.0`, so its edges'
/// terms are added in the scalar function's order. Lanes past `polys.len()` are left at 0.
#[inline(always)]
pub fn point_to_polygons_lanes(
    x: DVec3,
    n: DVec3,
    polys: &[&[DVec3]],
    out: &mut [f64; POLYGON_LANES],
) -> u32 {
    debug_assert!(polys.len() <= POLYGON_LANES && !polys.is_empty());
    debug_assert!(polys.iter().all(|p| (3..=MOST_CORNERS).contains(&p.len())));
    let used = polys.len();
    let m = polys.iter().map(|p| p.len()).max().unwrap_or(3);
    let mut c = [[DVec3::ZERO; MOST_CORNERS]; POLYGON_LANES];
    for l in 0..POLYGON_LANES {
        // Idle lanes repeat the first polygon: their work is discarded.
        let p = polys[if l < used { l } else { 0 }];
        for k in 0..m {
            c[l][k] = p[k.min(p.len() - 1)];
        }
    }
    factor_lanes(
        m,
        n,
        used,
        #[inline(always)]
        |k, l| {
            let c = c[l][k];
            (c.x - x.x, c.y - x.y, c.z - x.z)
        },
        out,
    )
}

/// The lanes of [`point_to_polygon_lanes`] and [`point_to_polygons_lanes`]: lane `l` of
/// `L` is the factor of the polygon whose corner `k` (of `m`), less lane `l`'s point, is
/// `r(k, l)`, seen from a point of unit normal `n`; in the scalar function's operations and
/// order. Returns the mask of the lanes (below `used`) that need the clipped path.
#[inline(always)]
fn factor_lanes<const L: usize>(
    m: usize,
    n: DVec3,
    used: usize,
    r: impl Fn(usize, usize) -> (f64, f64, f64),
    out: &mut [f64; L],
) -> u32 {
    let mut rx = [[0.0f64; L]; MOST_CORNERS];
    let mut ry = [[0.0f64; L]; MOST_CORNERS];
    let mut rz = [[0.0f64; L]; MOST_CORNERS];
    let mut len2 = [[0.0f64; L]; MOST_CORNERS];
    let mut all_front = [true; L];
    let mut front = [f64::NEG_INFINITY; L];
    let mut reach2 = [0.0f64; L];
    for k in 0..m {
        for l in 0..L {
            let (x, y, z) = r(k, l);
            let d = n.x * x + n.y * y + n.z * z;
            all_front[l] &= d >= 0.0;
            front[l] = front[l].max(d);
            let q = x * x + y * y + z * z;
            reach2[l] = reach2[l].max(q);
            (rx[k][l], ry[k][l], rz[k][l], len2[k][l]) = (x, y, z, q);
        }
    }
    let mut sum = [0.0f64; L];
    for k in 0..m {
        let k1 = if k + 1 == m { 0 } else { k + 1 };
        for l in 0..L {
            let (ax, ay, az) = (rx[k][l], ry[k][l], rz[k][l]);
            let (bx, by, bz) = (rx[k1][l], ry[k1][l], rz[k1][l]);
            let (cx, cy, cz) = (ay * bz - by * az, az * bx - bz * ax, ax * by - bx * ay);
            let cl2 = cx * cx + cy * cy + cz * cz;
            let cl = cl2.sqrt();
            let dot = ax * bx + ay * by + az * bz;
            let term = angle_lane(cl, dot) * (n.x * cx + n.y * cy + n.z * cz) / cl;
            // A degenerate edge adds nothing: `+ 0.0` leaves the sum as it is (it starts
            // at +0, and a sum in round-to-nearest never becomes -0 from there).
            let keep = cl2 > 1e-24 * len2[k][l] * len2[k1][l];
            sum[l] += if keep { term } else { 0.0 };
        }
    }
    let mut clip = 0u32;
    for l in 0..L {
        let zero = front[l] <= 0.0 || front[l] * front[l] <= 1e-24 * reach2[l];
        out[l] = if zero || l >= used {
            0.0
        } else {
            -sum[l] / (2.0 * PI)
        };
        clip |= u32::from(!all_front[l] && l < used) << l;
    }
    clip
}

/// [`angle`] without branches: the quotient's operands are chosen lane by lane, so each
/// lane divides what the scalar function divides (`0 + a` is `a` for the `a >= 0` of
/// [`atan_nonneg`]).
#[inline(always)]
fn angle_lane(s: f64, c: f64) -> f64 {
    let pos = c >= 0.0;
    let (num, den) = if pos { (s, c) } else { (-c, s) };
    let base = if pos {
        0.0
    } else {
        std::f64::consts::FRAC_PI_2
    };
    base + atan_lane(num / den)
}

/// [`atan_nonneg`] without branches: the reduction the scalar function takes is chosen
/// lane by lane (`-1 / x` or `(x - 1) / (x + 1)` by one division), then one rational
/// approximation.
#[inline(always)]
fn atan_lane(x: f64) -> f64 {
    const T3P8: f64 = 2.414_213_562_373_095;
    const MOREBITS: f64 = 6.123_233_995_736_766e-17;
    let big = x > T3P8;
    let small = x <= 0.66;
    let (num, den) = if big { (-1.0, x) } else { (x - 1.0, x + 1.0) };
    let quo = num / den;
    let y0 = if big {
        std::f64::consts::FRAC_PI_2
    } else if small {
        0.0
    } else {
        std::f64::consts::FRAC_PI_4
    };
    let more = if big {
        MOREBITS
    } else if small {
        0.0
    } else {
        0.5 * MOREBITS
    };
    atan_tail(y0, if small { x } else { quo }, more)
}

/// `atan2(s, c)` for `s > 0`: the angle in `(0, π)` whose sine and cosine are proportional
/// to `s` and `c`, by [`atan_nonneg`] of `s / c` or of `-c / s`.
#[inline]
fn angle(s: f64, c: f64) -> f64 {
    if c >= 0.0 {
        atan_nonneg(s / c)
    } else {
        std::f64::consts::FRAC_PI_2 + atan_nonneg(-c / s)
    }
}

/// `atan(x)` for `x >= 0` (including `+inf`), to about one unit in the last place: the
/// Cephes `atan` (Moshier 1989): reduction to `|x| <= tan(π/8)` by the identities
/// `atan x = π/2 - atan(1/x)` and `atan x = π/4 + atan((x - 1)/(x + 1))`, then a
/// degree 4/5 rational approximation in `x²`. About twice as fast as libm's `atan2`, which
/// dominated the cost of [`point_to_polygon`].
#[inline]
pub fn atan_nonneg(x: f64) -> f64 {
    const T3P8: f64 = 2.414_213_562_373_095; // tan(3π/8)
    const MOREBITS: f64 = 6.123_233_995_736_766e-17; // π/2 - fl(π/2)
    let (y0, x, more) = if x > T3P8 {
        (std::f64::consts::FRAC_PI_2, -1.0 / x, MOREBITS)
    } else if x <= 0.66 {
        (0.0, x, 0.0)
    } else {
        (
            std::f64::consts::FRAC_PI_4,
            (x - 1.0) / (x + 1.0),
            0.5 * MOREBITS,
        )
    };
    atan_tail(y0, x, more)
}

/// The rational approximation of [`atan_nonneg`] on the reduced argument `x`, added to
/// `y0` with the low bits `more`.
#[inline(always)]
fn atan_tail(y0: f64, x: f64, more: f64) -> f64 {
    let z = x * x;
    let p = (((-8.750_608_600_031_904e-1 * z - 1.615_753_718_733_365e1) * z
        - 7.500_855_792_314_705e1)
        * z
        - 1.228_866_684_490_136e2)
        * z
        - 6.485_021_904_942_025e1;
    let q = ((((z + 2.485_846_490_142_306e1) * z + 1.650_270_098_316_988_6e2) * z
        + 4.328_810_604_912_903e2)
        * z
        + 4.853_903_996_359_137e2)
        * z
        + 1.945_506_571_482_614e2;
    y0 + (x * (z * p / q) + x + more)
}

/// The general case of [`point_to_polygon_oriented`]: clips the polygon to `x`'s front
/// side (the clipped polygon keeps the winding).
fn point_to_polygon_clipped(x: DVec3, n: DVec3, poly: &[DVec3]) -> f64 {
    // Nothing strictly in front (this includes a polygon lying in x's own plane, whose
    // projected solid angle is 0 from any point approaching x from the front).
    let front = poly
        .iter()
        .map(|&p| n.dot(p - x))
        .fold(f64::NEG_INFINITY, f64::max);
    let reach = poly.iter().map(|&p| (p - x).length()).fold(0.0, f64::max);
    if front.is_nan() || front <= 1e-12 * reach {
        return 0.0;
    }
    // Streams the clipped polygon's vertices (relative to x) and sums edge terms on the fly.
    let mut first: Option<DVec3> = None;
    let mut last = DVec3::ZERO;
    let mut sum = 0.0;
    let mut emit = |r: DVec3| {
        if first.is_some() {
            sum += edge_term(last, r, n);
        } else {
            first = Some(r);
        }
        last = r;
    };
    let m = poly.len();
    for k in 0..m {
        let (p, q) = (poly[k] - x, poly[(k + 1) % m] - x);
        let (dp, dq) = (n.dot(p), n.dot(q));
        if dp >= 0.0 {
            emit(p);
        }
        if (dp > 0.0 && dq < 0.0) || (dp < 0.0 && dq > 0.0) {
            let t = dp / (dp - dq);
            let mut s = p + (q - p) * t;
            // Put the crossing exactly on the plane, so the horizon edge is exact.
            s -= n * n.dot(s);
            emit(s);
        }
    }
    if let Some(f) = first {
        sum += edge_term(last, f, n);
    }
    -sum / (2.0 * PI)
}

/// One edge of the contour integral: `γ (n · u)` for the edge from `x + a` to `x + b`.
#[inline]
fn edge_term(a: DVec3, b: DVec3, n: DVec3) -> f64 {
    let c = a.cross(b);
    let cl = c.length();
    let scale = a.length() * b.length();
    if cl.is_nan() || cl <= 1e-12 * scale {
        return 0.0;
    }
    let gamma = cl.atan2(a.dot(b));
    gamma * n.dot(c) / cl
}

/// Gauss–Legendre rule with `n` nodes on `[0, 1]`: `(node, weight)` pairs, exact for
/// polynomials of degree `2n - 1` (Golub and Welsch 1969 give the same nodes; here the
/// roots of `P_n` are found by Newton's method from Tricomi's initial guesses, as in
/// Numerical Recipes `gauleg`). Used to integrate [`point_to_polygon`] over a patch and by
/// the reference quadratures of the tests.
pub fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    let mut out = vec![(0.0, 0.0); n];
    let nf = n as f64;
    for i in 0..n.div_ceil(2) {
        let mut z = (PI * (i as f64 + 0.75) / (nf + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // P_n(z) and P_n'(z) by the three-term recurrence.
            let (mut p0, mut p1) = (1.0, 0.0);
            for k in 0..n {
                let p2 = p1;
                p1 = p0;
                p0 = ((2 * k + 1) as f64 * z * p1 - k as f64 * p2) / (k + 1) as f64;
            }
            dp = nf * (z * p0 - p1) / (z * z - 1.0);
            let dz = p0 / dp;
            z -= dz;
            if dz.abs() <= 1e-16 {
                break;
            }
        }
        let w = 2.0 / ((1.0 - z * z) * dp * dp);
        // Map [-1, 1] to [0, 1].
        out[i] = ((1.0 - z) / 2.0, w / 2.0);
        out[n - 1 - i] = ((1.0 + z) / 2.0, w / 2.0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform numbers in [-1, 1) from the stream keyed by `key`.
    fn uniform(key: u64) -> impl FnMut() -> f64 {
        let mut rng = crate::sampling::Pcg32::keyed(7, key, 0, 0);
        move || rng.next_f64() * 2.0 - 1.0
    }

    /// Lane `l` of a lanes function's answer (`clip` mask, value `got`) for the point `x`
    /// of normal `n` and the polygon `poly`: the clipped path asked for exactly when a
    /// corner is behind `x`'s plane, else the scalar factor bit for bit (counted in
    /// `checked` by whether it is 0).
    fn check_lane(
        (clip, l, got): (u32, usize, f64),
        x: DVec3,
        n: DVec3,
        poly: &[DVec3],
        checked: &mut [usize; 2],
        what: &str,
    ) {
        let front = poly.iter().all(|&p| n.dot(p - x) >= 0.0);
        assert_eq!(clip >> l & 1 == 0, front, "{what}");
        if front {
            let want = point_to_polygon_oriented(x, n, poly);
            assert_eq!(
                got.to_bits(),
                want.to_bits(),
                "{what}: {got} against {want}"
            );
            checked[usize::from(want != 0.0)] += 1;
        }
    }

    /// The scale and shift of the lane tests' case `case`: tiny, unit and huge polygons, at
    /// the origin, near it and far from it.
    fn placement(u: &mut impl FnMut() -> f64, case: usize) -> (f64, DVec3) {
        let scale = [1e-6, 1.0, 1e6][case % 3];
        let shift = DVec3::new(u(), u(), u()) * [0.0, 10.0, 1e7][case / 3 % 3];
        (scale, shift)
    }

    /// A planar polygon of `corners` (3 to 5) corners jittered about a convex pentagon's,
    /// moved by `lift`, then scaled and shifted; in the other winding when `reverse`.
    fn test_polygon(
        u: &mut impl FnMut() -> f64,
        corners: usize,
        lift: DVec3,
        (scale, shift): (f64, DVec3),
        reverse: bool,
    ) -> Vec<DVec3> {
        let mut poly: Vec<DVec3> = [(0.0, 0.0), (1.0, 0.1), (1.1, 0.7), (0.9, 1.2), (-0.1, 0.8)]
            .iter()
            .take(corners)
            .map(|&(a, b)| (DVec3::new(a + 0.2 * u(), b + 0.2 * u(), 0.0) + lift) * scale + shift)
            .collect();
        if reverse {
            poly.reverse();
        }
        poly
    }

    /// The lanes give the scalar factor bit for bit at every vector width, on points in
    /// general position and on the awkward ones: on a corner, on an edge's line, in the
    /// polygon's plane, behind it (those lanes must ask for the clipped path), far away.
    #[test]
    fn lanes_match_the_scalar_factor_bit_for_bit() {
        use crate::simd::{set_limit, with_widest, Width};
        let mut u = uniform(11);
        let mut checked = [0usize; 2];
        for case in 0..400 {
            let (scale, shift) = placement(&mut u, case);
            // Triangles, quadrilaterals and pentagons (a quadrilateral clipped by a plane).
            let corners = 3 + case / 9 % 3;
            let poly = test_polygon(&mut u, corners, DVec3::ZERO, (scale, shift), case % 5 == 0);
            let n = DVec3::new(u(), u(), u()).normalize();
            let mut xs: Vec<DVec3> = (0..13)
                .map(|_| DVec3::new(u(), u(), u() * 2.0) * scale * 2.0 + shift)
                .collect();
            // A corner, a point on an edge's line, a point in the plane, a far point.
            xs[0] = poly[1];
            xs[1] = poly[0] + (poly[1] - poly[0]) * 2.5;
            xs[2] = (poly[0] + poly[2]) * 0.5;
            xs[3] = shift + DVec3::new(0.3, 0.4, 1e4) * scale;
            for w in Width::ALL.into_iter().filter(|w| w.supported()) {
                set_limit(w);
                for chunk in xs.chunks(LANES) {
                    let mut out = [f64::NAN; LANES];
                    let clip = with_widest(
                        #[inline(always)]
                        || point_to_polygon_lanes(chunk, n, &poly, &mut out),
                    );
                    for (l, &x) in chunk.iter().enumerate() {
                        let what = format!("case {case} lane {l} at {w}");
                        check_lane((clip, l, out[l]), x, n, &poly, &mut checked, &what);
                    }
                    assert!(out[chunk.len()..].iter().all(|&v| v == 0.0));
                }
            }
        }
        set_limit(Width::Avx512);
        // Both outcomes were exercised.
        assert!(checked[0] > 100 && checked[1] > 1000, "{checked:?}");
    }

    /// One point against batches of polygons of 3 to 5 corners, mixed within a batch (the
    /// shorter repeat their last corner): the scalar factor bit for bit at every vector
    /// width, in general position and from a corner, an edge's line, the plane, behind.
    #[test]
    fn polygon_lanes_match_the_scalar_factor_bit_for_bit() {
        use crate::simd::{set_limit, with_widest, Width};
        let mut u = uniform(12);
        let mut checked = [0usize; 2];
        for case in 0..600 {
            let (scale, shift) = placement(&mut u, case);
            let used = 1 + case % POLYGON_LANES;
            let polys: Vec<Vec<DVec3>> = (0..used)
                .map(|q| {
                    let corners = 3 + (case + q) % 3;
                    let lift = DVec3::new(0.3 * q as f64, 0.1, 0.2 * u());
                    test_polygon(&mut u, corners, lift, (scale, shift), (case + q) % 5 == 0)
                })
                .collect();
            let refs: Vec<&[DVec3]> = polys.iter().map(|p| p.as_slice()).collect();
            let n = DVec3::new(u(), u(), u()).normalize();
            let x = match case % 7 {
                0 => polys[0][1],
                1 => polys[0][0] + (polys[0][1] - polys[0][0]) * 2.5,
                2 => (polys[0][0] + polys[0][2]) * 0.5,
                _ => DVec3::new(u(), u(), u() * 2.0) * scale * 2.0 + shift,
            };
            for w in Width::ALL.into_iter().filter(|w| w.supported()) {
                set_limit(w);
                let mut out = [f64::NAN; POLYGON_LANES];
                let clip = with_widest(
                    #[inline(always)]
                    || point_to_polygons_lanes(x, n, &refs, &mut out),
                );
                for (l, poly) in polys.iter().enumerate() {
                    let what = format!("case {case} lane {l} at {w}");
                    check_lane((clip, l, out[l]), x, n, poly, &mut checked, &what);
                }
                assert!(out[used..].iter().all(|&v| v == 0.0));
            }
        }
        set_limit(Width::Avx512);
        assert!(checked[0] > 10 && checked[1] > 1000, "{checked:?}");
    }

    #[test]
    fn atan_matches_libm() {
        let mut worst = 0.0f64;
        for k in 0..200_001 {
            let x = (k as f64 / 10_000.0 - 10.0).exp(); // 4.5e-5 .. 2.2e4
            for x in [
                x,
                1.0 / x,
                x * 0.66 / 0.66,
                0.66,
                1.0,
                2.414_213_562_373_095,
            ] {
                let (got, want) = (atan_nonneg(x), x.atan());
                worst = worst.max((got - want).abs() / want);
            }
        }
        assert!(worst < 4.0 * f64::EPSILON, "worst relative error {worst:e}");
        assert_eq!(atan_nonneg(0.0), 0.0);
        assert!((atan_nonneg(f64::INFINITY) - std::f64::consts::FRAC_PI_2).abs() < 1e-16);
        for (s, c) in [
            (1.0, 1.0),
            (1.0, -1.0),
            (1e-9, -1.0),
            (1.0, 1e-9),
            (3.0, -4.0),
        ] {
            assert!((angle(s, c) - f64::atan2(s, c)).abs() < 4e-16, "{s} {c}");
        }
    }

    /// Composite Gauss–Legendre nodes on `[lo, hi]`: `m` equal panels of `n` nodes.
    fn panels(lo: f64, hi: f64, m: usize, n: usize) -> Vec<(f64, f64)> {
        let g = gauss_legendre(n);
        let h = (hi - lo) / m as f64;
        let mut out = Vec::with_capacity(m * n);
        for k in 0..m {
            let a = lo + k as f64 * h;
            out.extend(g.iter().map(|&(t, w)| (a + t * h, w * h)));
        }
        out
    }

    /// Composite Gauss–Legendre nodes on `[lo, hi]`, graded geometrically (ratio 1/2)
    /// toward `lo` over `levels` panels, for integrands singular at `lo`: a panel at
    /// distance d from the singularity has width d, where `n` = 10 nodes are exact to
    /// about 1e-15; the last panel, of width `2^-levels (hi - lo)`, holds what is left.
    fn graded(lo: f64, hi: f64, levels: usize, n: usize) -> Vec<(f64, f64)> {
        let g = gauss_legendre(n);
        let mut out = Vec::new();
        let mut b = hi;
        for k in 0..=levels {
            let a = if k == levels { lo } else { lo + (b - lo) * 0.5 };
            out.extend(g.iter().map(|&(t, w)| (a + t * (b - a), w * (b - a))));
            b = a;
        }
        out
    }

    /// Graded toward both ends of `[lo, hi]`.
    fn graded2(lo: f64, hi: f64, levels: usize, n: usize) -> Vec<(f64, f64)> {
        let mid = 0.5 * (lo + hi);
        let mut v = graded(lo, mid, levels, n);
        v.extend(graded(hi, mid, levels, n).into_iter().map(|(x, w)| (x, -w)));
        v
    }

    fn close(got: f64, want: f64, tol: f64, what: &str) {
        assert!(
            (got - want).abs() <= tol,
            "{what}: got {got:.12}, want {want:.12}, diff {:.3e}",
            got - want
        );
    }

    #[test]
    fn gauss_legendre_is_exact_for_polynomials() {
        for n in [1, 2, 5, 10, 17] {
            let g = gauss_legendre(n);
            for d in 0..2 * n {
                let s: f64 = g.iter().map(|&(x, w)| w * x.powi(d as i32)).sum();
                close(s, 1.0 / (d as f64 + 1.0), 1e-14, &format!("n={n} d={d}"));
            }
        }
    }

    #[test]
    fn published_values() {
        close(
            parallel_rectangles(1.0, 1.0, 1.0),
            0.1998249,
            5e-8,
            "C-11 unit squares",
        );
        close(
            perpendicular_rectangles(1.0, 1.0, 1.0),
            0.2000438,
            5e-8,
            "C-14 unit squares",
        );
        // C-41 with r1 = r2 = h: X = 3, F = (3 - sqrt 5)/2.
        close(
            coaxial_disks(1.0, 1.0, 1.0),
            (3.0 - 5f64.sqrt()) / 2.0,
            1e-15,
            "C-41",
        );
        // Shelf of the notes with g = sqrt 3: F_BC = (3 - sqrt 3)/6 = 0.2113249.
        let (f_ab, f_ac, f_bc) = shelf_factors(3f64.sqrt());
        close(f_ab, (1.0 + 3f64.sqrt() - 2.0) / 2.0, 1e-15, "F_AB");
        close(f_ac, 2.0 - 3f64.sqrt(), 1e-15, "F_AC");
        close(f_bc, (3.0 - 3f64.sqrt()) / 6.0, 1e-15, "F_BC");
    }

    /// C-11 against 4D tensor Gauss–Legendre of the double area integral (the integrand is
    /// analytic with poles at distance >= c, so panels of width <= c/2 converge fast).
    #[test]
    fn parallel_rectangles_match_quadrature() {
        for &(a, b, c) in &[
            (1.0, 1.0, 1.0),
            (2.0, 1.0, 0.5),
            (0.5, 3.0, 1.5),
            (1.3, 0.7, 0.4),
        ] {
            let qa = panels(0.0, a, (2.0 * a / c).ceil() as usize, 8);
            let qb = panels(0.0, b, (2.0 * b / c).ceil() as usize, 8);
            let mut s = 0.0;
            for &(x1, w1) in &qa {
                for &(y1, v1) in &qa {
                    let dx2 = (x1 - y1) * (x1 - y1) + c * c;
                    let mut inner = 0.0;
                    for &(x2, w2) in &qb {
                        for &(y2, v2) in &qb {
                            let r2 = dx2 + (x2 - y2) * (x2 - y2);
                            inner += w2 * v2 / (r2 * r2);
                        }
                    }
                    s += w1 * v1 * inner;
                }
            }
            let f = s * c * c / (PI * a * b);
            close(
                parallel_rectangles(a, b, c),
                f,
                1e-9,
                &format!("C-11 {a} {b} {c}"),
            );
            close(parallel_rectangles(b, a, c), f, 1e-9, "C-11 symmetric");
        }
    }

    /// C-14 against quadrature of the double area integral. The rectangles are
    /// `x = (s, t, 0)`, `0<=s<=w`, and `y = (0, t', u)`, `0<=u<=h`, `0<=t,t'<=l`; the kernel
    /// `s u / (π (s² + u² + (t-t')²)²)` depends on `t - t'` only, so the two integrals along
    /// the common edge are the exact weighted single integral
    /// `∫_0^l ∫_0^l g(t - t') = 2 ∫_0^l (l - τ) g(τ) dτ` (g even). The remaining 3D integral
    /// is singular at the origin only, and tensor rules graded toward 0 in s, u and τ
    /// resolve it (the unresolved corner cube of side 2^-30 holds O(2^-30)).
    #[test]
    fn perpendicular_rectangles_match_quadrature() {
        for &(h, l, w) in &[
            (1.0, 1.0, 1.0),
            (2.0, 1.0, 0.5),
            (0.3, 2.0, 1.7),
            (1.5, 0.4, 0.8),
        ] {
            let qs = graded(0.0, w, 30, 10);
            let qu = graded(0.0, h, 30, 10);
            let qt = graded(0.0, l, 30, 10);
            let mut sum = 0.0;
            for &(s, ws) in &qs {
                for &(u, wu) in &qu {
                    let a2 = s * s + u * u;
                    let mut inner = 0.0;
                    for &(t, wt) in &qt {
                        let r2 = a2 + t * t;
                        inner += wt * (l - t) / (r2 * r2);
                    }
                    sum += ws * wu * s * u * inner;
                }
            }
            let f = 2.0 * sum / (PI * w * l);
            close(
                perpendicular_rectangles(h, l, w),
                f,
                1e-8,
                &format!("C-14 {h} {l} {w}"),
            );
            // Reciprocity: w l F(w->h) = h l F(h->w).
            close(
                w * perpendicular_rectangles(h, l, w),
                h * perpendicular_rectangles(w, l, h),
                1e-14,
                "C-14 reciprocity",
            );
        }
    }

    /// C-41 against quadrature in polar coordinates; by symmetry only the angle difference
    /// φ matters (a factor 2π), integrated by the trapezoid rule (periodic integrand,
    /// geometric convergence).
    #[test]
    fn coaxial_disks_match_quadrature() {
        for &(r1, r2, h) in &[
            (1.0, 1.0, 1.0),
            (0.5, 2.0, 0.7),
            (1.5, 0.8, 2.0),
            (1.0, 3.0, 0.5),
        ] {
            let q1 = panels(0.0, r1, (2.0 * r1 / h).ceil() as usize, 10);
            let q2 = panels(0.0, r2, (2.0 * r2 / h).ceil() as usize, 10);
            let nphi = 400;
            let mut sum = 0.0;
            for &(p1, w1) in &q1 {
                for &(p2, w2) in &q2 {
                    let mut inner = 0.0;
                    for k in 0..nphi {
                        let phi = 2.0 * PI * k as f64 / nphi as f64;
                        let r2 = h * h + p1 * p1 + p2 * p2 - 2.0 * p1 * p2 * phi.cos();
                        inner += 1.0 / (r2 * r2);
                    }
                    sum += w1 * w2 * p1 * p2 * inner * 2.0 * PI / nphi as f64;
                }
            }
            let f = 2.0 * PI * sum * h * h / (PI * PI * r1 * r1);
            close(
                coaxial_disks(r1, r2, h),
                f,
                1e-9,
                &format!("C-41 {r1} {r2} {h}"),
            );
        }
    }

    /// B-3 and B-8 (90°) against 2D quadrature of the single area integral.
    #[test]
    fn differential_factors_match_quadrature() {
        for &(a, b, c) in &[
            (1.0, 1.0, 1.0),
            (2.0, 0.5, 0.7),
            (0.3, 1.7, 0.4),
            (3.0, 2.0, 5.0),
        ] {
            let qa = panels(0.0, a, (2.0 * a / c).ceil() as usize, 10);
            let qb = panels(0.0, b, (2.0 * b / c).ceil() as usize, 10);
            // B-3: element at the origin facing +z, rectangle [0,a]x[0,b] in z = c.
            let mut s3 = 0.0;
            // B-8: element at the origin facing +z, rectangle x = c, y in [0,b], z in [0,a].
            let mut s8 = 0.0;
            for &(p, wp) in &qa {
                for &(q, wq) in &qb {
                    let r2 = p * p + q * q + c * c;
                    s3 += wp * wq * c * c / (r2 * r2);
                    s8 += wp * wq * p * c / (r2 * r2);
                }
            }
            let what = format!("{a} {b} {c}");
            close(
                diff_to_parallel_rectangle(a, b, c),
                s3 / PI,
                1e-10,
                &format!("B-3 {what}"),
            );
            close(
                diff_to_perpendicular_rectangle(a, b, c),
                s8 / PI,
                1e-10,
                &format!("B-8 {what}"),
            );
        }
    }

    /// Points on a sphere: the kernel cos cos / (π r²) is the constant 1/(4π R²).
    #[test]
    fn sphere_kernel_is_constant() {
        let radius = 1.7;
        let dirs = [
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(-0.3, 0.1, 0.9),
            DVec3::new(0.2, -1.0, -0.4),
            DVec3::new(-2.0, -1.0, 0.5),
        ];
        for a in dirs {
            for b in dirs {
                if a == b {
                    continue;
                }
                let (x, y) = (a.normalize() * radius, b.normalize() * radius);
                // Inward normals.
                let (n_x, n_y) = (-x / radius, -y / radius);
                let d = y - x;
                let r2 = d.length_squared();
                let k = n_x.dot(d) * (-n_y.dot(d)) / (PI * r2 * r2);
                close(
                    k,
                    1.0 / (4.0 * PI * radius * radius),
                    1e-15,
                    "sphere kernel",
                );
            }
        }
        close(sphere_interior(2.0, 8.0), 0.25, 0.0, "sphere");
    }

    /// 2D factors against quadrature of `1/w1 ∫∫ cos cos / (2 r)`, graded toward the
    /// common edge (kernel ~ 1/r there).
    #[test]
    fn strips_match_quadrature() {
        let strip2d =
            |a0: [f64; 2], a1: [f64; 2], b0: [f64; 2], b1: [f64; 2], graded_at_0: bool| {
                let rule = |len: f64| {
                    if graded_at_0 {
                        graded(0.0, len, 40, 10)
                    } else {
                        panels(0.0, len, 16, 10)
                    }
                };
                let len = |p: [f64; 2], q: [f64; 2]| (q[0] - p[0]).hypot(q[1] - p[1]);
                let (la, lb) = (len(a0, a1), len(b0, b1));
                let ta = [(a1[0] - a0[0]) / la, (a1[1] - a0[1]) / la];
                let tb = [(b1[0] - b0[0]) / lb, (b1[1] - b0[1]) / lb];
                // Normals: pointing toward the other strip's midpoint.
                let mid = |p: [f64; 2], q: [f64; 2]| [(p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0];
                let norm = |t: [f64; 2], from: [f64; 2], to: [f64; 2]| {
                    let n = [-t[1], t[0]];
                    let s = (to[0] - from[0]) * n[0] + (to[1] - from[1]) * n[1];
                    if s >= 0.0 {
                        n
                    } else {
                        [-n[0], -n[1]]
                    }
                };
                let na = norm(ta, mid(a0, a1), mid(b0, b1));
                let nb = norm(tb, mid(b0, b1), mid(a0, a1));
                let mut sum = 0.0;
                for &(s, ws) in &rule(la) {
                    let x = [a0[0] + ta[0] * s, a0[1] + ta[1] * s];
                    for &(u, wu) in &rule(lb) {
                        let y = [b0[0] + tb[0] * u, b0[1] + tb[1] * u];
                        let d = [y[0] - x[0], y[1] - x[1]];
                        let r2 = d[0] * d[0] + d[1] * d[1];
                        let cx = d[0] * na[0] + d[1] * na[1];
                        let cy = -(d[0] * nb[0] + d[1] * nb[1]);
                        sum += ws * wu * cx * cy / (2.0 * r2 * r2.sqrt());
                    }
                }
                sum / la
            };
        // Common edge at the origin, strips along angle 0 and `angle`.
        for &(w1, w2, angle) in &[
            (1.0, 1.0, PI / 2.0),
            (1.0, 3f64.sqrt(), PI / 2.0),
            (2.0, 0.7, 1.0),
            (0.5, 1.5, 2.5),
        ] {
            let (a0, a1) = ([0.0, 0.0], [w1, 0.0]);
            let (b0, b1) = ([0.0, 0.0], [w2 * angle.cos(), w2 * angle.sin()]);
            let q = strip2d(a0, a1, b0, b1, true);
            let what = format!("common edge {w1} {w2} {angle}");
            close(strips_common_edge(w1, w2, angle), q, 1e-9, &what);
            close(crossed_strings(a0, a1, b0, b1), q, 1e-9, &what);
            close(crossed_strings(a1, a0, b0, b1), q, 1e-9, "reversed ends");
        }
        // Opposed strips, and a skewed pair.
        for &(w, h) in &[(1.0, 1.0), (1.0, 3f64.sqrt()), (2.0, 0.5)] {
            let (a0, a1, b0, b1) = ([0.0, 0.0], [w, 0.0], [0.0, h], [w, h]);
            let q = strip2d(a0, a1, b0, b1, false);
            close(
                parallel_strips(w, h),
                q,
                1e-9,
                &format!("parallel strips {w} {h}"),
            );
            close(
                crossed_strings(a0, a1, b0, b1),
                q,
                1e-9,
                "crossed strings, parallel",
            );
        }
        let (a0, a1, b0, b1) = ([0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [2.0, 1.8]);
        let q = strip2d(a0, a1, b0, b1, false);
        close(crossed_strings(a0, a1, b0, b1), q, 1e-9, "skewed strips");
        // The shelf formulas are the same rule.
        for g in [0.5, 1.0, 3f64.sqrt(), 4.0] {
            let (f_ab, f_ac, f_bc) = shelf_factors(g);
            close(
                f_ab,
                strips_common_edge(1.0, g, PI / 2.0),
                1e-15,
                "shelf F_AB",
            );
            close(f_ac, parallel_strips(1.0, g), 1e-15, "shelf F_AC");
            close(
                f_bc,
                strips_common_edge(g, 1.0, PI / 2.0),
                1e-15,
                "shelf F_BC",
            );
            // Reciprocity a F_AB = b F_BA with F_BA = F_BC by symmetry.
            close(f_ab, g * f_bc, 1e-15, "shelf reciprocity");
        }
    }

    /// Quadrature of the single area integral from (x, n_x) over the parallelogram
    /// `o + s e1 + t e2`, `s, t` in the given rules (two-sided receiver, the emitter's
    /// cosine clamped at 0).
    fn point_quad(
        x: DVec3,
        n_x: DVec3,
        o: DVec3,
        e1: DVec3,
        e2: DVec3,
        qs: &[(f64, f64)],
        qt: &[(f64, f64)],
    ) -> f64 {
        let n_x = n_x.normalize();
        let cr = e1.cross(e2);
        let (jac, n_y) = (cr.length(), cr.normalize());
        let mut sum = 0.0;
        for &(s, ws) in qs {
            for &(t, wt) in qt {
                let d = o + e1 * s + e2 * t - x;
                let r2 = d.length_squared();
                let cx = n_x.dot(d).max(0.0);
                let cy = n_y.dot(d).abs();
                sum += ws * wt * cx * cy / (r2 * r2);
            }
        }
        sum * jac / PI
    }

    #[test]
    fn point_to_polygon_matches_quadrature() {
        let quad = |o: DVec3, e1: DVec3, e2: DVec3| [o, o + e1, o + e1 + e2, o + e2];
        // A tilted parallelogram fully in front of a tilted element.
        let x = DVec3::new(0.1, -0.2, 0.3);
        let n_x = DVec3::new(0.3, 0.2, 1.0);
        let (o, e1, e2) = (
            DVec3::new(-0.5, -0.4, 1.2),
            DVec3::new(1.1, 0.2, 0.3),
            DVec3::new(-0.2, 0.9, 0.4),
        );
        let q = panels(0.0, 1.0, 8, 10);
        let want = point_quad(x, n_x, o, e1, e2, &q, &q);
        close(
            point_to_polygon(x, n_x, &quad(o, e1, e2)),
            want,
            1e-10,
            "tilted",
        );
        // Same polygon, reversed winding.
        let mut rev = quad(o, e1, e2);
        rev.reverse();
        close(
            point_to_polygon(x, n_x, &rev),
            want,
            1e-10,
            "reversed winding",
        );
        // A triangle: the half s + t <= 1 of the parallelogram (collapsed rule t <= 1 - s).
        let mut tri = 0.0;
        let n_u = n_x.normalize();
        let (jac, n_y) = (e1.cross(e2).length(), e1.cross(e2).normalize());
        for &(s, ws) in &q {
            for &(v, wv) in &q {
                let t = v * (1.0 - s);
                let d = o + e1 * s + e2 * t - x;
                let r2 = d.length_squared();
                tri += ws * wv * (1.0 - s) * n_u.dot(d).max(0.0) * n_y.dot(d).abs() / (r2 * r2);
            }
        }
        close(
            point_to_polygon(x, n_x, &[o, o + e1, o + e2]),
            tri * jac / PI,
            1e-10,
            "triangle",
        );

        // Partly behind x's plane: element at the origin facing +z, rectangle in x = 1,
        // y in [-1, 1], z in [-0.5, 1.5]. The rule is split at z = 0, where the clamped
        // cosine has its kink.
        let (x, n_x) = (DVec3::ZERO, DVec3::Z);
        let (o, e1, e2) = (
            DVec3::new(1.0, -1.0, -0.5),
            DVec3::new(0.0, 2.0, 0.0),
            DVec3::new(0.0, 0.0, 2.0),
        );
        let mut qt = panels(0.0, 0.25, 4, 10);
        qt.extend(panels(0.25, 1.0, 8, 10));
        let want = point_quad(x, n_x, o, e1, e2, &panels(0.0, 1.0, 8, 10), &qt);
        close(
            point_to_polygon(x, n_x, &quad(o, e1, e2)),
            want,
            1e-10,
            "partly behind",
        );
        // By symmetry it is twice B-8 with a = 1.5, b = 1, c = 1.
        close(
            want,
            2.0 * diff_to_perpendicular_rectangle(1.5, 1.0, 1.0),
            1e-10,
            "B-8 sym",
        );

        // A tilted element whose plane cuts a parallel rectangle along a diagonal line;
        // the rule is split along that line by mapping each side separately.
        let (x, n_x) = (DVec3::ZERO, DVec3::new(1.0, 0.0, 1.0));
        // Rectangle z = 1, x in [-2, 1], y in [-1, 1]; front part: x >= -1.
        let (o, e1, e2) = (
            DVec3::new(-1.0, -1.0, 1.0),
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(0.0, 2.0, 0.0),
        );
        let want = point_quad(x, n_x, o, e1, e2, &q, &q);
        let poly = quad(DVec3::new(-2.0, -1.0, 1.0), DVec3::new(3.0, 0.0, 0.0), e2);
        close(
            point_to_polygon(x, n_x, &poly),
            want,
            1e-10,
            "clipped by tilted plane",
        );
        // Wholly behind.
        close(point_to_polygon(x, -DVec3::Z, &poly), 0.0, 0.0, "behind");
    }

    #[test]
    fn point_to_polygon_matches_closed_forms() {
        for &(a, b, c) in &[(1.0, 1.0, 1.0), (2.0, 0.5, 0.7), (0.3, 1.7, 0.4)] {
            let (x, n_x) = (DVec3::ZERO, DVec3::Z);
            let par = [
                DVec3::new(0.0, 0.0, c),
                DVec3::new(a, 0.0, c),
                DVec3::new(a, b, c),
                DVec3::new(0.0, b, c),
            ];
            close(
                point_to_polygon(x, n_x, &par),
                diff_to_parallel_rectangle(a, b, c),
                1e-14,
                "B-3",
            );
            let perp = [
                DVec3::new(c, 0.0, 0.0),
                DVec3::new(c, b, 0.0),
                DVec3::new(c, b, a),
                DVec3::new(c, 0.0, a),
            ];
            close(
                point_to_polygon(x, n_x, &perp),
                diff_to_perpendicular_rectangle(a, b, c),
                1e-14,
                "B-8",
            );
        }
    }

    /// Integrating the point factor over the emitter by Gauss quadrature gives the area
    /// factors: C-11 (smooth integrand) and C-14 (rule graded toward the common edge and
    /// the ends of it, where the point factor is not smooth).
    #[test]
    fn point_to_polygon_integrates_to_area_factors() {
        for &(a, b, c) in &[(1.0, 1.0, 1.0), (2.0, 1.0, 0.5)] {
            let recv = [
                DVec3::new(0.0, 0.0, c),
                DVec3::new(a, 0.0, c),
                DVec3::new(a, b, c),
                DVec3::new(0.0, b, c),
            ];
            let (qa, qb) = (panels(0.0, a, 4, 10), panels(0.0, b, 4, 10));
            let mut s = 0.0;
            for &(p, wp) in &qa {
                for &(q, wq) in &qb {
                    s += wp * wq * point_to_polygon(DVec3::new(p, q, 0.0), DVec3::Z, &recv);
                }
            }
            close(
                s / (a * b),
                parallel_rectangles(a, b, c),
                1e-10,
                "C-11 via points",
            );
        }
        for &(h, l, w) in &[(1.0, 1.0, 1.0), (2.0, 1.0, 0.5), (0.3, 2.0, 1.7)] {
            // Emitter (s, t, 0) facing +z; receiver (0, t, u) facing +x.
            let recv = [
                DVec3::new(0.0, 0.0, 0.0),
                DVec3::new(0.0, l, 0.0),
                DVec3::new(0.0, l, h),
                DVec3::new(0.0, 0.0, h),
            ];
            let (qs, qt) = (graded(0.0, w, 24, 10), graded2(0.0, l, 24, 10));
            let mut s = 0.0;
            for &(p, wp) in &qs {
                for &(t, wt) in &qt {
                    s += wp * wt * point_to_polygon(DVec3::new(p, t, 0.0), DVec3::Z, &recv);
                }
            }
            close(
                s / (w * l),
                perpendicular_rectangles(h, l, w),
                1e-9,
                "C-14 via points",
            );
        }
    }

    /// A point inside a closed box sees all of it: the six faces sum to 1.
    #[test]
    fn point_in_cube_sees_everything() {
        let c = |x: f64, y: f64, z: f64| DVec3::new(x, y, z);
        let faces = [
            [c(0., 0., 0.), c(1., 0., 0.), c(1., 1., 0.), c(0., 1., 0.)],
            [c(0., 0., 1.), c(0., 1., 1.), c(1., 1., 1.), c(1., 0., 1.)],
            [c(0., 0., 0.), c(0., 0., 1.), c(1., 0., 1.), c(1., 0., 0.)],
            [c(0., 1., 0.), c(1., 1., 0.), c(1., 1., 1.), c(0., 1., 1.)],
            [c(0., 0., 0.), c(0., 1., 0.), c(0., 1., 1.), c(0., 0., 1.)],
            [c(1., 0., 0.), c(1., 0., 1.), c(1., 1., 1.), c(1., 1., 0.)],
        ];
        let points = [
            c(0.5, 0.5, 0.5),
            c(0.1, 0.7, 0.3),
            c(0.9, 0.05, 0.6),
            c(0.01, 0.99, 0.5),
        ];
        let normals = [
            c(0., 0., 1.),
            c(1., 2., 3.),
            c(-0.3, 0.1, -0.9),
            c(0.0, -1.0, 1e-3),
        ];
        for &x in &points {
            for &n in &normals {
                let s: f64 = faces.iter().map(|f| point_to_polygon(x, n, f)).sum();
                close(s, 1.0, 1e-12, &format!("cube from {x} along {n}"));
            }
        }
        // On a face, looking in: the five other faces sum to 1 (the own face gives 0).
        let x = c(0.3, 0.6, 0.0);
        let s: f64 = faces.iter().map(|f| point_to_polygon(x, DVec3::Z, f)).sum();
        close(s, 1.0, 1e-12, "cube from the floor");
    }

    #[test]
    fn point_to_polygon_degenerate_cases_are_finite() {
        let sq = [DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y];
        let cases = [
            (DVec3::ZERO, DVec3::Z),                  // at a vertex, in the plane
            (DVec3::new(0.5, 0.0, 0.0), DVec3::Z),    // on an edge
            (DVec3::new(0.5, 0.0, 0.0), DVec3::Y),    // on an edge, facing along the plane
            (DVec3::new(0.5, 0.5, 0.0), DVec3::X),    // inside, facing along the plane
            (DVec3::new(2.0, 0.5, 0.0), DVec3::Z),    // in the plane, outside
            (DVec3::new(2.0, 0.0, 0.0), -DVec3::X),   // on an edge's line, outside
            (DVec3::new(0.5, 0.5, 1.0), DVec3::ZERO), // no normal
        ];
        for (x, n) in cases {
            let f = point_to_polygon(x, n, &sq);
            assert!(
                f.is_finite() && (0.0..=1.0 + 1e-12).contains(&f),
                "{x} {n}: {f}"
            );
        }
        close(
            point_to_polygon(DVec3::new(2.0, 0.5, 0.0), DVec3::Z, &sq),
            0.0,
            1e-15,
            "edge-on",
        );
        close(
            point_to_polygon(DVec3::ZERO, DVec3::Z, &sq[..2]),
            0.0,
            0.0,
            "two corners",
        );
    }
}
