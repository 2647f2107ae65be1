//! The unoccluded patch-to-polygon integral `I = ∫_{A_e} F(x → P_r) dA_x` to a relative
//! tolerance, deterministically: the part of the semi-analytic estimator
//! ([`super::semi`]) where nothing can block.
//!
//! `F(x → P_r)` is Lambert's exact point-to-polygon factor
//! ([`crate::analytic::point_to_polygon`]), so only the outer integral over the emitter is
//! numerical. `I = A_e F_er = A_r F_re` (reciprocity), so one integral gives both entries.
//!
//! As a function of `x`, `F(x → P_r)` is analytic wherever `x` is away from `P_r`; its only
//! singularities are on `P_r` itself (Baum, Rushmeier and Winget 1989). Two rules follow:
//!
//! - **Far pieces: tensor Gauss–Legendre**, with the order chosen *a priori* from the
//!   distance. For a function analytic inside the Bernstein ellipse with foci at the ends
//!   of the interval and semi-axis sum `ρ`, the `m`-point rule's error falls as `ρ^(-2m)`
//!   (Trefethen 2008, "Is Gauss quadrature better than Clenshaw–Curtis?", Theorem 4.5). A
//!   singularity at distance `δ` (in radii of the piece, which bound the half-length of
//!   every parameter line; the distance bounded below by the distance from the piece's
//!   centre to `P_r` less the radius) from the interval gives
//!   `ρ ≥ 1 + δ + sqrt(δ (2 + δ))` (the worst case: on the interval's axis), so the order
//!   is the smallest `m` with `ρ^(-2m) <= tol`. The result is then checked *a posteriori*
//!   against the rules one and two orders below: with geometric convergence the error of
//!   `Q_m` is about `|Q_m - Q_(m-k)| / ρ^(2k)`, and the larger of the two (with a safety
//!   factor of 16, never more than the difference itself) is the reported error. (Both:
//!   consecutive orders can err alike, and a rule two below can land near the integral
//!   by luck.) A failed check moves up one order.
//! - **Near or touching pieces: tensor tanh–sinh** (Takahasi and Mori 1974; Bailey,
//!   Jeyabalan and Li 2005). Where the emitter touches `P_r` (a shared edge or corner, as
//!   between neighbouring patches of a room's walls), the integrand is singular *on the
//!   boundary* of the emitter (like `d ln d` in the distance to the shared edge), where
//!   Gauss–Legendre converges only algebraically. The double-exponential rule clusters
//!   nodes at the boundary and converges exponentially for such endpoint singularities.
//!   Levels halve the step (`h = 1/2, 1/4, 1/8`); the error estimate is the difference of
//!   the last two levels. Nodes next to the boundary are mapped from `1 - u` computed
//!   directly, so no node falls on the boundary by rounding. Before it, Gauss orders 8,
//!   12 and 16 are tried (they settle neighbours meeting at right angles). Neither rule's
//!   difference bounds the error where the integrand has a kink inside the piece (a block
//!   standing across a floor patch) or is nearly singular (a corner just off the
//!   receiver): there the rules converge only algebraically, so unless the caller knows
//!   the two patches meet only along whole edges or at corners ([`Contact`]), the
//!   reported error of a near piece is at least its own tolerance.
//! - A piece that meets neither rule's tolerance is split into four (up to a fixed depth)
//!   and each quarter is integrated to a quarter of the tolerance. A piece *apart* from
//!   its receiver (its nearest corner off the receiver's plane by enough that its quarters
//!   at the deepest level would take an a-priori order) is split as soon as no a-priori
//!   Gauss order settles it, without the near rules: on it they converge slowly, and their
//!   differences can agree while both are wrong (a rug's underside 1 cm over a floor
//!   patch's edge: 7.0e-8 off with 1.1e-9 reported, 65 times under;
//!   `tests::a_piece_apart_but_near_its_receiver_is_within_its_error`).
//!
//! **The reported error is a bound, not a standard error** ([`crate::matrix::Bar`]): the
//! a-posteriori check's estimate (summed linearly over pieces) plus a rounding term
//! ([`rounding`]). Nothing in it is random, so a sum of such integrals (a row of the
//! matrix) adds the errors linearly. Its coverage is tested against the same integrals
//! to 1e-9 on every near pair of the Cornell box, at 1e-2 and 1e-6
//! (`semi::tests::near_pairs_are_within_their_bounds`).
//!
//! The pieces are parameter squares of the emitter: a bilinear map for quads, the collapsed
//! (Duffy) map `x = c0 + u (e1 + v e2)` with Jacobian `u |e1 × e2|` for triangles.

use std::sync::OnceLock;

use glam::DVec3;

use crate::analytic::{
    gauss_legendre, point_to_polygon_lanes, point_to_polygon_oriented, point_to_polygons_lanes,
    LANES, MOST_CORNERS, POLYGON_LANES,
};

/// A parameter map of (part of) an emitter over the unit square.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Piece {
    /// Bilinear quad: `u` runs from `c[0]` to `c[1]`, `v` from `c[0]` to `c[3]`.
    Quad([DVec3; 4]),
    /// Triangle by the collapsed map `x = c0 + u (c1 - c0 + v (c2 - c1))`.
    Tri([DVec3; 3]),
}

impl Piece {
    /// Point and area Jacobian at `(u, v)`; `um = 1 - u` and `vm = 1 - v` are passed in so
    /// that nodes next to `u = 1` or `v = 1` keep their full precision.
    #[inline]
    pub fn at(&self, u: f64, um: f64, v: f64, vm: f64) -> (DVec3, f64) {
        match self {
            Piece::Quad(c) => {
                let x = c[0] * (um * vm) + c[1] * (u * vm) + c[2] * (u * v) + c[3] * (um * v);
                let du = (c[1] - c[0]) * vm + (c[2] - c[3]) * v;
                let dv = (c[3] - c[0]) * um + (c[2] - c[1]) * u;
                (x, du.cross(dv).length())
            }
            Piece::Tri(c) => {
                let (e1, e2) = (c[1] - c[0], c[2] - c[1]);
                // c0 + u e1 + u v e2, written so that u -> 1, v -> 1 keeps precision.
                let x = c[0] * um + c[1] * (u * vm) + c[2] * (u * v);
                (x, u * e1.cross(e2).length())
            }
        }
    }

    /// The four quarters in parameter space. Edge midpoints are computed as
    /// `(a + b) / 2` of the edge's end points, so two pieces that share an edge split it at
    /// the same point, bit for bit.
    pub fn split(&self) -> [Piece; 4] {
        let mid = |a: DVec3, b: DVec3| (a + b) * 0.5;
        match *self {
            Piece::Quad(c) => {
                let (m01, m12, m23, m30) = (
                    mid(c[0], c[1]),
                    mid(c[1], c[2]),
                    mid(c[2], c[3]),
                    mid(c[3], c[0]),
                );
                let ctr = self.at(0.5, 0.5, 0.5, 0.5).0;
                [
                    Piece::Quad([c[0], m01, ctr, m30]),
                    Piece::Quad([m01, c[1], m12, ctr]),
                    Piece::Quad([ctr, m12, c[2], m23]),
                    Piece::Quad([m30, ctr, m23, c[3]]),
                ]
            }
            Piece::Tri(c) => {
                let (m01, m12, m20) = (mid(c[0], c[1]), mid(c[1], c[2]), mid(c[2], c[0]));
                [
                    Piece::Tri([c[0], m01, m20]),
                    Piece::Tri([m01, c[1], m12]),
                    Piece::Tri([m20, m12, c[2]]),
                    Piece::Tri([m12, m20, m01]),
                ]
            }
        }
    }

    /// Centre (image of the parameter centre) and the largest corner distance from it: a
    /// ball that holds the piece.
    pub fn ball(&self) -> (DVec3, f64) {
        let ctr = self.at(0.5, 0.5, 0.5, 0.5).0;
        let r = self
            .corners()
            .iter()
            .map(|&p| (p - ctr).length())
            .fold(0.0, f64::max);
        (ctr, r)
    }

    /// The corners (3 for a triangle, 4 for a quad), counter-clockwise as given.
    pub fn corners(&self) -> &[DVec3] {
        match self {
            Piece::Quad(c) => c,
            Piece::Tri(c) => c,
        }
    }

    /// Area (by a 4 x 4 Gauss rule, exact for the bilinear and collapsed maps).
    pub fn area(&self) -> f64 {
        let rule = &rules().gauss[4];
        let mut a = 0.0;
        for &(u, um, wu) in rule {
            for &(v, vm, wv) in rule {
                a += wu * wv * self.at(u, um, v, vm).1;
            }
        }
        a
    }
}

/// The receiving polygon, with what the integrand needs.
#[derive(Clone, Debug)]
pub struct Receiver<'a> {
    /// Corners (3 or 4, planar to the mesh's tolerance).
    pub poly: &'a [DVec3],
    /// Unit normal (front side).
    pub normal: DVec3,
    /// A point of the plane (the centroid).
    pub centroid: DVec3,
    /// The sign that makes [`point_to_polygon_oriented`] positive on the front: +1 or -1
    /// by the winding of the corners about `normal`, or 0 (take absolute values) where
    /// the corners' vector area is nearly perpendicular to it.
    winding: f64,
}

impl<'a> Receiver<'a> {
    /// A receiver with corners `poly`, front normal `normal` and centroid `centroid`.
    pub fn new(poly: &'a [DVec3], normal: DVec3, centroid: DVec3) -> Receiver<'a> {
        // Twice the vector area of the corners' fan (of any polygon, planar or not).
        let area = (1..poly.len().saturating_sub(1)).fold(DVec3::ZERO, |a, k| {
            a + (poly[k] - poly[0]).cross(poly[k + 1] - poly[0])
        });
        let d = area.dot(normal);
        let winding = if d.abs() > 1e-9 * area.length() * normal.length() {
            d.signum()
        } else {
            0.0
        };
        Receiver {
            poly,
            normal,
            centroid,
            winding,
        }
    }

    /// A value of [`point_to_polygon_oriented`] against this receiver, made positive on
    /// its front. For a planar receiver this is the factor's absolute value; a warped one
    /// seen nearly edge-on from in front of its centroid's plane keeps the sign, so that
    /// the integrand stays smooth where the sum passes through 0.
    #[inline]
    fn front(&self, oriented: f64) -> f64 {
        if self.winding == 0.0 {
            oriented.abs()
        } else {
            self.winding * oriented
        }
    }
}

/// How an emitter meets its receiver, as far as the integrand's smoothness goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Contact {
    /// Touching only along whole shared edges or at shared corners: the integrand is
    /// smooth up to the contact, and the difference of two rules bounds the error of the
    /// higher one.
    Smooth,
    /// Touching where a contact ends inside an edge (a block standing across a floor
    /// patch), clipped by the receiver's plane, apart (a piece near its receiver without
    /// touching it is nearly singular: a block's corner 1.4 from a floor patch 80 wide),
    /// or not known: the near rules may converge only algebraically, and a near piece
    /// reports at least its own tolerance as its error. (Far pieces, whose Gauss order is
    /// chosen a priori, are unaffected.)
    Kinked,
}

/// [`Contact`] of the emitter polygon `e` and the receiver polygon `r`, both convex, each
/// with its plane (unit normal, a point); `Kinked` when either is not planar to `tol` or
/// they are more than `tol` apart.
pub fn contact(
    e: &[DVec3],
    plane_e: (DVec3, DVec3),
    r: &[DVec3],
    plane_r: (DVec3, DVec3),
    tol: f64,
) -> Contact {
    let planar =
        |poly: &[DVec3], (n, c): (DVec3, DVec3)| poly.iter().all(|&x| n.dot(x - c).abs() <= tol);
    if !planar(e, plane_e)
        || !planar(r, plane_r)
        || polygon_distance(e, r) > tol
        || ends_inside(e, r, plane_r, tol)
        || ends_inside(r, e, plane_e, tol)
    {
        Contact::Kinked
    } else {
        Contact::Smooth
    }
}

/// Whether polygon `a` touches polygon `b` (plane: unit normal `n_b`, point `c_b`) other than along whole
/// edges of both or at corners of both: an edge of `a` in `b`'s plane that overlaps `b`
/// only in part or along no edge of `b`, or a corner of `a` on `b` that is not one of
/// `b`'s.
fn ends_inside(a: &[DVec3], b: &[DVec3], (n_b, c_b): (DVec3, DVec3), tol: f64) -> bool {
    let off = |x: DVec3| n_b.dot(x - c_b).abs() <= tol;
    let corner_of_b = |x: DVec3| b.iter().any(|&c| (c - x).length() <= tol);
    for k in 0..a.len() {
        let (p, q) = (a[k], a[(k + 1) % a.len()]);
        if off(p) && inside(p, b, n_b, tol) && !corner_of_b(p) {
            return true;
        }
        if off(p) && off(q) {
            if let Some((t0, t1)) = clip_segment(p, q, b, n_b, tol) {
                let len = (q - p).length();
                let whole = t0 * len <= tol && (1.0 - t1) * len <= tol;
                if !(whole && corner_of_b(p) && corner_of_b(q)) {
                    return true;
                }
            }
        }
    }
    false
}

/// Whether `x` (in the plane of the convex polygon `poly`, unit normal `n`) lies inside
/// it or within `tol` of it.
fn inside(x: DVec3, poly: &[DVec3], n: DVec3, tol: f64) -> bool {
    (0..poly.len()).all(|k| {
        let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
        n.cross(b - a).normalize_or_zero().dot(x - a) >= -tol
    })
}

/// The parameter interval of the segment `p → q` (in the plane of the convex polygon
/// `poly`, unit normal `n`) inside the polygon grown by `tol` (Cyrus–Beck), if longer than
/// `tol`.
fn clip_segment(p: DVec3, q: DVec3, poly: &[DVec3], n: DVec3, tol: f64) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..poly.len() {
        let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
        let inward = n.cross(b - a).normalize_or_zero();
        let (dp, dq) = (inward.dot(p - a) + tol, inward.dot(q - a) + tol);
        if dp < 0.0 && dq < 0.0 {
            return None;
        }
        if dp < 0.0 {
            t0 = t0.max(dp / (dp - dq));
        } else if dq < 0.0 {
            t1 = t1.min(dp / (dp - dq));
        }
    }
    ((t1 - t0) * (q - p).length() > tol).then_some((t0, t1))
}

/// What [`integrate`] returns: `∫ F(x → P_r) dA_x`, a bound on its error (the quadrature
/// check's estimate plus [`rounding`]) and the number of point-factor evaluations.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Integral {
    /// The integral (area units).
    pub value: f64,
    /// Bound on the absolute error of `value`: the quadrature check's estimate plus
    /// rounding.
    pub err: f64,
    /// Point-to-polygon evaluations spent.
    pub evals: u64,
}

impl std::ops::AddAssign for Integral {
    fn add_assign(&mut self, o: Integral) {
        self.value += o.value;
        self.err += o.err;
        self.evals += o.evals;
    }
}

/// Gauss–Legendre orders up to this are tabulated.
const MAX_ORDER: usize = 16;
/// Safety factor of the far Gauss rules' a-posteriori estimate: the rate `ρ` holds only
/// asymptotically. Of the Cornell box's 855 near pairs at 400 patches, 4 left 27 outside
/// their bounds at the tolerance 1e-2 and 13 at 1e-6, 8 left 5 at 1e-6, 16 none.
const SAFE: f64 = 16.0;
/// The Gauss orders tried where no order is chosen a priori.
const NEAR_ORDERS: [usize; 3] = [8, 12, 16];
/// Highest Gauss order chosen a priori; pieces needing more start from order 8.
const GAUSS_LIMIT: usize = 12;
/// Tanh–sinh levels (`h = 1/2^(level+1)`).
const TS_LEVELS: usize = 3;
/// Splits at most this deep.
const MAX_DEPTH: u32 = 4;

/// A rule on `[0, 1]`: `(u, 1 - u, weight)`.
type Rule = Vec<(f64, f64, f64)>;

struct Rules {
    /// `gauss[m]`: the m-point Gauss–Legendre rule.
    gauss: Vec<Rule>,
    /// `ts[l]`: the tanh–sinh nodes with step `1/2^(l+1)`, indexed by `k` in `-K..=K`.
    ts: Vec<Rule>,
}

fn rules() -> &'static Rules {
    static RULES: OnceLock<Rules> = OnceLock::new();
    RULES.get_or_init(|| {
        let gauss = (0..=MAX_ORDER)
            .map(|m| {
                if m == 0 {
                    Vec::new()
                } else {
                    gauss_legendre(m)
                        .into_iter()
                        .map(|(u, w)| (u, 1.0 - u, w))
                        .collect()
                }
            })
            .collect();
        let ts = (0..TS_LEVELS).map(tanh_sinh).collect();
        Rules { gauss, ts }
    })
}

/// Half-width of the tanh–sinh abscissae: beyond `t = 3.5` the nodes are within `1e-22`
/// of the ends and the weights below `1e-21`.
const TS_TMAX: f64 = 3.5;

/// Tanh–sinh rule on `[0, 1]` with step `h = 1/2^(level+1)`:
/// `u = (1 + tanh(π/2 sinh t)) / 2`, `w = h π/4 cosh t / cosh²(π/2 sinh t)`, at `t = k h`
/// for `|k| <= K`. Ordered by `k`, so level `l` is every other node of level `l + 1`.
fn tanh_sinh(level: usize) -> Rule {
    let h = 0.5f64.powi(level as i32 + 1);
    let kmax = (TS_TMAX / h).round() as i64;
    (-kmax..=kmax)
        .map(|k| {
            let t = k as f64 * h;
            let s = std::f64::consts::FRAC_PI_2 * t.sinh();
            // 1 - u = 1 / (1 + e^(2s)) and u = 1 / (1 + e^(-2s)), each without cancellation.
            let (u, um) = (
                1.0 / (1.0 + (-2.0 * s).exp()),
                1.0 / (1.0 + (2.0 * s).exp()),
            );
            let w = h * std::f64::consts::FRAC_PI_4 * t.cosh() / s.cosh().powi(2);
            (u, um, w)
        })
        .collect()
}

/// Distance from `p` to the triangle `abc` (Ericson 2005, "Real-Time Collision Detection",
/// §5.1.5, closest point on a triangle).
fn point_triangle_distance(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> f64 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return ap.length();
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return bp.length();
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (p - (a + ab * v)).length();
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return cp.length();
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (p - (a + ac * w)).length();
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (p - (b + (c - b) * w)).length();
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    (p - (a + ab * v + ac * w)).length()
}

/// The least distance of `corners` from the plane through `c` with unit normal `n` when
/// they all lie on one side of it, else 0: a lower bound of the distance from their convex
/// hull to anything in that plane.
fn plane_gap(corners: &[DVec3], n: DVec3, c: DVec3) -> f64 {
    let (lo, hi) = corners
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &p| {
            let h = n.dot(p - c);
            (lo.min(h), hi.max(h))
        });
    if lo > 0.0 {
        lo
    } else if hi < 0.0 {
        -hi
    } else {
        0.0
    }
}

/// Distance from `p` to a polygon given as a fan of triangles.
fn point_polygon_distance(p: DVec3, poly: &[DVec3]) -> f64 {
    (1..poly.len().saturating_sub(1))
        .map(|k| point_triangle_distance(p, poly[0], poly[k], poly[k + 1]))
        .fold(f64::INFINITY, f64::min)
}

/// Distance between the segments `p0 p1` and `q0 q1` (Ericson 2005, "Real-Time Collision
/// Detection", §5.1.9, closest points of two segments).
fn segment_distance(p0: DVec3, p1: DVec3, q0: DVec3, q1: DVec3) -> f64 {
    let (d1, d2, r) = (p1 - p0, q1 - q0, p0 - q0);
    let (a, e, f) = (d1.length_squared(), d2.length_squared(), d2.dot(r));
    let (s, t) = if a <= f64::MIN_POSITIVE && e <= f64::MIN_POSITIVE {
        (0.0, 0.0)
    } else if a <= f64::MIN_POSITIVE {
        (0.0, (f / e).clamp(0.0, 1.0))
    } else {
        let c = d1.dot(r);
        if e <= f64::MIN_POSITIVE {
            ((-c / a).clamp(0.0, 1.0), 0.0)
        } else {
            let b = d1.dot(d2);
            let denom = a * e - b * b;
            let s = if denom > 0.0 {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let t = (b * s + f) / e;
            if t < 0.0 {
                ((-c / a).clamp(0.0, 1.0), 0.0)
            } else if t > 1.0 {
                (((b - c) / a).clamp(0.0, 1.0), 1.0)
            } else {
                (s, t)
            }
        }
    };
    ((p0 + d1 * s) - (q0 + d2 * t)).length()
}

/// Distance between two convex polygons that do not cross each other: the least of the
/// distances from each one's corners to the other and between their edges (for polygons
/// that do not intersect, the closest points lie on a corner or on two edges). Polygons
/// that pierce each other get the distance of their edges, an upper bound.
pub fn polygon_distance(a: &[DVec3], b: &[DVec3]) -> f64 {
    let corners = a
        .iter()
        .map(|&p| point_polygon_distance(p, b))
        .chain(b.iter().map(|&q| point_polygon_distance(q, a)));
    let edges = (0..a.len()).flat_map(|i| {
        (0..b.len()).map(move |j| {
            let (p0, p1) = (a[i], a[(i + 1) % a.len()]);
            let (q0, q1) = (b[j], b[(j + 1) % b.len()]);
            segment_distance(p0, p1, q0, q1)
        })
    });
    corners.chain(edges).fold(f64::INFINITY, f64::min)
}

/// `F(x → P_r)` with a one-sided receiver: 0 when `x` is not in front of its plane, else
/// Lambert's contour sum signed by the receiver's winding ([`Receiver::new`]): the factor
/// itself for a planar receiver; for a warped one seen nearly edge-on it may be slightly
/// negative, where the factor's absolute value would have a kink inside an emitter.
/// `n_x` is a unit normal.
#[inline]
pub fn point_factor(x: DVec3, n_x: DVec3, r: &Receiver) -> f64 {
    if behind(x, r) {
        return 0.0;
    }
    r.front(point_to_polygon_oriented(x, n_x, r.poly))
}

/// Whether `x` is not in front of the one-sided receiver `r`'s plane (it sees none of it).
#[inline]
fn behind(x: DVec3, r: &Receiver) -> bool {
    r.normal.dot(x - r.centroid) <= 0.0
}

/// [`point_factor`] at every point of `xs`, into `out` (cleared first), bit for bit the
/// same values, [`LANES`] points at a time ([`point_to_polygon_lanes`], at the widest
/// vector width of [`crate::simd::with_widest`]).
pub fn point_factors(xs: &[DVec3], n_x: DVec3, r: &Receiver, out: &mut Vec<f64>) {
    out.clear();
    if !(3..=MOST_CORNERS).contains(&r.poly.len()) {
        out.extend(xs.iter().map(|&x| point_factor(x, n_x, r)));
        return;
    }
    crate::simd::with_widest(
        #[inline(always)]
        || {
            let mut lane = [0.0; LANES];
            for chunk in xs.chunks(LANES) {
                let clip = point_to_polygon_lanes(chunk, n_x, r.poly, &mut lane);
                for (l, &x) in chunk.iter().enumerate() {
                    out.push(if behind(x, r) {
                        0.0
                    } else if clip >> l & 1 == 1 {
                        r.front(point_to_polygon_oriented(x, n_x, r.poly))
                    } else {
                        r.front(lane[l])
                    });
                }
            }
        },
    )
}

/// [`point_factor`] from one point `x` to each receiver of `rs` (at most
/// [`POLYGON_LANES`]), bit for bit the same values, the receivers side by side
/// ([`point_to_polygons_lanes`], at the widest vector width of
/// [`crate::simd::with_widest`]).
pub fn point_factors_to<const K: usize>(x: DVec3, n_x: DVec3, rs: &[Receiver; K]) -> [f64; K] {
    const { assert!(K <= POLYGON_LANES) };
    if rs
        .iter()
        .any(|r| !(3..=MOST_CORNERS).contains(&r.poly.len()))
    {
        return rs.each_ref().map(|r| point_factor(x, n_x, r));
    }
    crate::simd::with_widest(
        #[inline(always)]
        || {
            let polys: [&[DVec3]; K] = rs.each_ref().map(|r| r.poly);
            let mut lane = [0.0; POLYGON_LANES];
            let clip = point_to_polygons_lanes(x, n_x, &polys, &mut lane);
            std::array::from_fn(|l| {
                let r = &rs[l];
                if behind(x, r) {
                    0.0
                } else if clip >> l & 1 == 1 {
                    r.front(point_to_polygon_oriented(x, n_x, r.poly))
                } else {
                    r.front(lane[l])
                }
            })
        },
    )
}

/// An emitter piece with its Gauss–Legendre nodes (point, weight × Jacobian) cached by
/// order, so that one emitter integrated against many receivers maps its nodes once.
#[derive(Clone, Debug)]
pub struct Emitter {
    piece: Piece,
    ball: (DVec3, f64),
    nodes: [Vec<(DVec3, f64)>; MAX_ORDER + 1],
    /// Scratch: the points of the rules evaluated together, and their factors.
    points: Vec<DVec3>,
    values: Vec<f64>,
}

impl Emitter {
    /// An emitter over `piece`.
    pub fn new(piece: Piece) -> Emitter {
        Emitter {
            piece,
            ball: piece.ball(),
            nodes: std::array::from_fn(|_| Vec::new()),
            points: Vec::new(),
            values: Vec::new(),
        }
    }

    /// The nodes of the tensor Gauss rule of order `m`, mapped on first use.
    fn nodes(&mut self, m: usize) -> &[(DVec3, f64)] {
        if self.nodes[m].is_empty() {
            let rule = &rules().gauss[m];
            let piece = self.piece;
            self.nodes[m] = rule
                .iter()
                .flat_map(|&(u, um, wu)| {
                    rule.iter().map(move |&(v, vm, wv)| {
                        let (x, jac) = piece.at(u, um, v, vm);
                        (x, wu * wv * jac)
                    })
                })
                .filter(|&(_, w)| w > 0.0)
                .collect();
        }
        &self.nodes[m]
    }

    /// The tensor Gauss rules of orders `ms` (0 for none) applied to `F(x → P_r)`, their
    /// points evaluated in one batch; `evals` counts the evaluations.
    fn gauss<const K: usize>(
        &mut self,
        ms: [usize; K],
        n_e: DVec3,
        r: &Receiver,
        evals: &mut u64,
    ) -> [f64; K] {
        let mut points = std::mem::take(&mut self.points);
        points.clear();
        for &m in &ms {
            if m > 0 {
                points.extend(self.nodes(m).iter().map(|&(x, _)| x));
            }
        }
        point_factors(&points, n_e, r, &mut self.values);
        *evals += points.len() as u64;
        self.points = points;
        let mut at = 0;
        ms.map(|m| {
            if m == 0 {
                return f64::NAN;
            }
            let nodes = &self.nodes[m];
            let vals = &self.values[at..at + nodes.len()];
            at += nodes.len();
            nodes.iter().zip(vals).map(|(&(_, w), &v)| w * v).sum()
        })
    }
}

/// `∫_{piece} F(x → P_r) dA_x` (emitter normal `n_e`, unit length) to within about
/// `tol_rel` of its value (and never chasing below `abs_floor`).
pub fn integrate(
    emitter: &mut Emitter,
    n_e: DVec3,
    r: &Receiver,
    tol_rel: f64,
    abs_floor: f64,
    contact: &dyn Fn() -> Contact,
) -> Integral {
    let mut evals = 0u64;
    let tol_rel = tol_rel.max(1e-15);
    // Asked only where a near rule runs: most pieces are far.
    let kinked = std::cell::OnceCell::new();
    let floor = || *kinked.get_or_init(|| contact() == Contact::Kinked);
    let mut front = [DVec3::ZERO; MOST_CORNERS];
    let part = match in_front(emitter.piece.corners(), n_e, r.poly, &mut front) {
        Some(0) => return Integral::default(),
        Some(k) => Some(Receiver {
            poly: &front[..k],
            ..r.clone()
        }),
        None => None,
    };
    let seen = part.as_ref().unwrap_or(r);
    let mut out = integrate_piece(
        emitter, n_e, seen, tol_rel, None, abs_floor, &floor, 0, &mut evals,
    );
    out.evals = evals;
    out.err += out.value.abs() * rounding(emitter, r, evals);
    out
}

/// The part of a receiver `poly` that a planar emitter (corners `e`, unit normal `n_e`)
/// sees, when the receiver reaches behind the emitter's plane: its corners, clipped once
/// to the half-space in front of that plane, into `out`, and their count (0: nothing in
/// front). `None` when no clip is needed (no corner more than a rounding behind the
/// plane) or the emitter is not planar to rounding.
///
/// Every point of a planar emitter has the same tangent plane, so the clip each point
/// factor would make ([`point_to_polygon_oriented`]'s general path, scalar, at every node)
/// is the same for all of them; made once, the nodes go through the vector lanes instead.
/// The plane is raised by `δ`, 32 unit roundoffs of the largest coordinate, so that the
/// clipped corners lie in front of every node despite the rounding of `n_e · (p - x)`. A
/// sliver `δ` wide is dropped; seen at a grazing angle from the emitter's plane, it holds
/// about `(δ / d)²` of what a node `d` away sees, so about `δ / ℓ` of the integral (`ℓ`
/// the receiver's size): within the input's share of [`rounding`], `64 ε R / ℓ`.
fn in_front(
    e: &[DVec3],
    n_e: DVec3,
    poly: &[DVec3],
    out: &mut [DVec3; MOST_CORNERS],
) -> Option<usize> {
    if poly.len() > 4 {
        return None;
    }
    let big = e
        .iter()
        .chain(poly)
        .map(|p| p.abs().max_element())
        .fold(0.0, f64::max);
    let delta = 32.0 * f64::EPSILON * big;
    let (lo, hi) = e
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &c| {
            let h = n_e.dot(c);
            (lo.min(h), hi.max(h))
        });
    let planar = hi - lo <= delta;
    if !planar || poly.iter().all(|&p| n_e.dot(p) >= lo - delta) {
        return None;
    }
    let mut k = 0;
    clip_above(poly, n_e, hi + delta, |p| {
        out[k] = p;
        k += 1;
    });
    Some(if k >= 3 { k } else { 0 })
}

/// The corners of `poly` clipped to the half-space `n · p >= level` (Sutherland–Hodgman
/// against one plane), in order, each given to `push`; a corner on the plane is kept once
/// and adds no crossing. A convex polygon of `k` corners gives at most `k + 1`.
pub(crate) fn clip_above(poly: &[DVec3], n: DVec3, level: f64, mut push: impl FnMut(DVec3)) {
    for i in 0..poly.len() {
        let (a, b) = (poly[i], poly[(i + 1) % poly.len()]);
        let (da, db) = (n.dot(a) - level, n.dot(b) - level);
        if da >= 0.0 {
            push(a);
        }
        if (da > 0.0 && db < 0.0) || (da < 0.0 && db > 0.0) {
            push(a + (b - a) * (da / (da - db)));
        }
    }
}

/// Relative rounding of an integral of [`integrate`] that spent `evals` point-factor
/// evaluations, counting the input's rounding: `ε (evals + 64 (1 + R / ℓ))`, with `ε` the
/// f64 unit roundoff, `R` the largest coordinate of either polygon and `ℓ` the smaller
/// polygon's radius.
///
/// - The integrand is `>= 0` and every rule's weights are `> 0`, so a sum of `N` products
///   computed in floating point is off by at most about `N ε` of its value (Higham,
///   *Accuracy and Stability of Numerical Algorithms*, 2nd ed., §4.2); `N <= evals`.
/// - Each point factor (Lambert's formula, a sum of a few edge terms with `atan2` and
///   square roots) is good to some tens of `ε` relative where the point is not on the
///   receiver: the constant 64.
/// - The corners are f64 values, each off by up to `ε |x|` from the geometry it stands
///   for; moving a corner by `δ` changes the factor by about `δ / ℓ` of itself, so the
///   input's rounding is worth `ε R / ℓ` (scenes far from the origin, or tiny patches,
///   pay for it), again times 64.
///
/// This is an a-priori estimate of the rounding, generous by design, not a proof; beside
/// the quadrature's own check (1e-6 of the value by default) it is negligible except at
/// tolerances near `ε`.
pub fn rounding(emitter: &Emitter, r: &Receiver, evals: u64) -> f64 {
    let far = emitter
        .piece
        .corners()
        .iter()
        .chain(r.poly)
        .map(|p| p.abs().max_element())
        .fold(0.0, f64::max);
    let rc = r.poly.iter().fold(DVec3::ZERO, |a, &p| a + p) / r.poly.len().max(1) as f64;
    // The square root of the largest square: the same value (a correctly rounded square
    // root is monotone), one root instead of four.
    let r_radius = r
        .poly
        .iter()
        .map(|&p| (p - rc).length_squared())
        .fold(0.0, f64::max)
        .sqrt();
    let size = emitter.ball.1.min(r_radius).max(f64::MIN_POSITIVE);
    f64::EPSILON * (evals as f64 + 64.0 * (1.0 + far / size))
}

/// Order `m` of the Gauss rule for a piece whose nearest singularity is `delta`
/// half-widths away, and the ellipse parameter `ρ`; `None` when more than
/// [`GAUSS_LIMIT`] points would be needed.
fn gauss_order(delta: f64, tol_rel: f64) -> Option<(usize, f64)> {
    if delta <= 0.0 {
        return None;
    }
    let rho = 1.0 + delta + (delta * (2.0 + delta)).sqrt();
    let m = ((1.0 / tol_rel).ln() / (2.0 * rho.ln())).ceil().max(2.0) as usize;
    (m <= GAUSS_LIMIT).then_some((m, rho))
}

#[allow(clippy::too_many_arguments)]
fn integrate_piece(
    em: &mut Emitter,
    n_e: DVec3,
    r: &Receiver,
    tol_rel: f64,
    tol_abs: Option<f64>,
    abs_floor: f64,
    floor: &dyn Fn() -> bool,
    depth: u32,
    evals: &mut u64,
) -> Integral {
    let rules = rules();
    let piece = em.piece;
    let (ctr, radius) = em.ball;
    // A lower bound of the distance from the piece to P_r, in radii of the piece (a
    // radius bounds the half-length of every parameter line; the tighter half-length of
    // the longest edge was tried and under-estimated errors on the cube).
    let dist = point_polygon_distance(ctr, r.poly) - radius;
    let delta = dist / radius.max(f64::MIN_POSITIVE);
    // Apart from the receiver, so that quarters split down to the deepest level would be
    // far: such a piece is split when no a-priori Gauss rule settles it, never left to the
    // near rules or tanh–sinh. Their differences are no bound on a piece that is apart
    // (smooth, but slowly converging): a rug's underside 1 cm over a floor patch's edge,
    // a quarter 4.6 cm wide, had two tanh–sinh levels agree to 1.9e-10 while both were
    // 7.0e-8 off. The distance here is the tighter one of a piece wholly on one side of
    // the receiver's plane: its nearest corner's from that plane (the centre's bound is
    // negative over a near parallel receiver). The Gauss orders keep the centre's bound,
    // which their error checks are calibrated on (`semi::tests`). A gap of a rounding, as
    // where pieces touch, never qualifies.
    let gap = dist.max(plane_gap(piece.corners(), r.normal, r.centroid));
    let apart = depth < MAX_DEPTH
        && gauss_order(
            gap / radius.max(f64::MIN_POSITIVE) * f64::from(1u32 << (MAX_DEPTH - depth)),
            tol_rel,
        )
        .is_some();
    // The absolute target: from the caller, or relative to a first estimate of this piece.
    let target = |estimate: f64| tol_abs.unwrap_or(tol_rel * estimate.abs()).max(abs_floor);
    // A near piece's least reported error: the relative tolerance of its own value (not
    // the caller's absolute floor, which the hierarchy sets to a share of a link's
    // tolerance and would make every touching link report that share).
    let own = |estimate: f64| {
        if floor() {
            tol_rel * estimate.abs()
        } else {
            0.0
        }
    };
    let mut best: Option<Integral> = None;
    if apart && gauss_order(delta, tol_rel).is_none() {
        // Too near for an a-priori order yet: a first estimate for the quarters' target.
        let q = em.gauss([NEAR_ORDERS[0]], n_e, r, evals)[0];
        best = Some(Integral {
            value: q,
            err: f64::INFINITY,
            evals: 0,
        });
    } else if let Some((m0, rho)) = gauss_order(delta, tol_rel) {
        // Far: Gauss from the a-priori order up, one order at a time, each rule checked
        // against the two below it. With geometric convergence the error of Q_m is about
        // |Q_m - Q_(m-k)| ρ^(-2k); the estimate is the larger of the k = 1 and k = 2 ones,
        // each times `SAFE` and never more than the difference itself. Both checks are
        // needed: consecutive orders can err alike (on the unit parallel plates Q_7 and
        // Q_8 are both off by 8e-12), and a rule two orders below can land near the
        // integral by luck (its error changing sign; on the Cornell box Q_3 was 3.5 times
        // closer than Q_4, and checking Q_5 against Q_3 alone under-estimated its error
        // 11 times over).
        let [mut q2, mut q1, mut q] = em.gauss([m0 - 2, m0 - 1, m0], n_e, r, evals);
        let check = |q: f64, lower: f64, k: i32| {
            if lower.is_nan() {
                return 0.0; // no Q_0
            }
            let diff = (q - lower).abs();
            (SAFE * diff * rho.powi(-2 * k)).min(diff)
        };
        for m in m0..=MAX_ORDER {
            if m > m0 {
                (q2, q1, q) = (q1, q, em.gauss([m], n_e, r, evals)[0]);
            }
            let got = Integral {
                value: q,
                err: check(q, q1, 1).max(check(q, q2, 2)),
                evals: 0,
            };
            if got.err <= target(q) {
                // Reported: at least the tolerance of its own value. The tensor rules'
                // differences can miss an error: the errors along the piece's two
                // parameters can have opposite signs and cancel in Q_(m-1) and Q_(m-2)
                // but not in Q_m (on the Cornell box, a back-wall patch against the slanted
                // wall: +-2.2e-3 at order 2, +1.8e-5 and +1.0e-5 at order 3), and at
                // order 2 there is only the one-point rule to check against.
                return Integral {
                    err: got.err.max(tol_rel * q.abs()),
                    ..got
                };
            }
            best = Some(got);
        }
    } else {
        // Touching or near (no a-priori order): orders 8, 12, 16, the difference being
        // the estimate; this suffices where the touching patches are perpendicular or
        // parallel (the point factor stays smooth up to a shared edge between them) and
        // fails fast elsewhere. Where it does not suffice the rule converges only
        // algebraically, and the difference is no bound (on the Cornell box's near pairs
        // it was up to 13 times too small for 15 of 855 pairs; the values themselves were
        // within the tolerance): unless the contact is smooth ([`Contact`]), the reported
        // error is at least the piece's own tolerance.
        let mut lo = em.gauss([NEAR_ORDERS[0]], n_e, r, evals)[0];
        for &m in &NEAR_ORDERS[1..] {
            let hi = em.gauss([m], n_e, r, evals)[0];
            let diff = (hi - lo).abs();
            let got = Integral {
                value: hi,
                err: diff.max(own(hi)),
                evals: 0,
            };
            if diff <= target(hi) {
                return got;
            }
            best = Some(got);
            lo = hi;
        }
    }
    // Tanh–sinh, nested levels: level l's nodes are the even-indexed nodes of level l + 1.
    let mut prev: Option<f64> = None;
    let mut grid: Vec<f64> = Vec::new();
    let levels = if apart { 0 } else { rules.ts.len() };
    for (level, rule) in rules.ts.iter().enumerate().take(levels) {
        let n = rule.len();
        let mut next = vec![0.0; n * n];
        // The level's new nodes (with a positive Jacobian) are evaluated in one batch.
        let (mut points, mut slots) = (Vec::new(), Vec::new());
        for (a, &(u, um, _)) in rule.iter().enumerate() {
            for (b, &(v, vm, _)) in rule.iter().enumerate() {
                if level > 0 && a % 2 == 0 && b % 2 == 0 {
                    next[a * n + b] = grid[(a / 2) * (n / 2 + 1) + b / 2];
                } else {
                    let (x, jac) = piece.at(u, um, v, vm);
                    if jac > 0.0 {
                        points.push(x);
                        slots.push((a * n + b, jac));
                    }
                }
            }
        }
        let mut values = std::mem::take(&mut em.values);
        point_factors(&points, n_e, r, &mut values);
        *evals += points.len() as u64;
        for (&(k, jac), &f) in slots.iter().zip(&values) {
            next[k] = jac * f;
        }
        em.values = values;
        let mut sum = 0.0;
        for (a, &(_, _, wu)) in rule.iter().enumerate() {
            for (b, &(_, _, wv)) in rule.iter().enumerate() {
                sum += wu * wv * next[a * n + b];
            }
        }
        grid = next;
        if let Some(p) = prev {
            let err = (sum - p).abs();
            let got = Integral {
                value: sum,
                err: err.max(own(sum)),
                evals: 0,
            };
            if err <= target(sum) {
                return got;
            }
            if best.is_none_or(|b: Integral| got.err < b.err) {
                best = Some(got);
            }
        }
        prev = Some(sum);
    }
    let best = best.expect("at least one estimate with an error");
    if depth >= MAX_DEPTH {
        return best;
    }
    // Split: each quarter gets a quarter of this piece's absolute target.
    let quarter = target(best.value) / 4.0;
    let mut total = Integral::default();
    for q in piece.split() {
        let mut sub = Emitter::new(q);
        total += integrate_piece(
            &mut sub,
            n_e,
            r,
            tol_rel,
            Some(quarter),
            abs_floor,
            floor,
            depth + 1,
            evals,
        );
    }
    if total.err <= best.err {
        total
    } else {
        best
    }
}

/// Point-factor evaluations assumed for a piece with no a-priori Gauss order (near or
/// touching the receiver): orders 8 and 12 (208), which settle perpendicular and parallel
/// neighbours, and now and then tanh–sinh (225 + 841 + 3249 nodes); a rough middle.
pub const NEAR_EVALS: f64 = 400.0;

/// The point-factor evaluations [`integrate`] is expected to spend on `piece` against the
/// receiver polygon `poly` at the relative tolerance `tol_rel`, from the a-priori choice
/// alone (`m² + (m - 1)² + (m - 2)²` for the Gauss order `m`; [`NEAR_EVALS`] when near), without
/// integrating: a cost estimate for sharing rows between processes.
pub fn expected_evals(piece: Piece, poly: &[DVec3], tol_rel: f64) -> f64 {
    let (ctr, radius) = piece.ball();
    let dist = point_polygon_distance(ctr, poly) - radius;
    let delta = dist / radius.max(f64::MIN_POSITIVE);
    match gauss_order(delta, tol_rel.max(1e-15)) {
        Some((m, _)) => (m * m + (m - 1) * (m - 1) + (m - 2) * (m - 2)) as f64,
        None => NEAR_EVALS,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::{parallel_rectangles, perpendicular_rectangles};

    fn square(o: DVec3, u: DVec3, v: DVec3) -> [DVec3; 4] {
        [o, o + u, o + u + v, o + v]
    }

    #[test]
    fn tanh_sinh_integrates_endpoint_singularity() {
        // ∫0^1 x ln x dx = -1/4, singular derivative at 0.
        for (level, want_err) in [(1, 1e-6), (2, 1e-12)] {
            let got: f64 = tanh_sinh(level)
                .iter()
                .map(|&(u, _, w)| if u > 0.0 { w * u * u.ln() } else { 0.0 })
                .sum();
            assert!((got + 0.25).abs() < want_err, "level {level}: {got}");
        }
        // Nested: level 0 nodes are every other node of level 1.
        let (l0, l1) = (tanh_sinh(0), tanh_sinh(1));
        assert_eq!(l1.len(), 2 * l0.len() - 1);
        for (k, n) in l0.iter().enumerate() {
            assert_eq!(n.0, l1[2 * k].0);
        }
    }

    #[test]
    fn unit_plates_to_1e12() {
        let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
        // Perpendicular, common edge (C-14): emitter in z = 0, receiver in y = 0.
        let emit = Piece::Quad(square(DVec3::ZERO, x, y));
        let poly = square(DVec3::ZERO, z, x);
        let r = Receiver::new(&poly, y, DVec3::new(0.5, 0.0, 0.5));
        let got = integrate(&mut Emitter::new(emit), z, &r, 1e-12, 0.0, &|| {
            Contact::Smooth
        });
        let want = perpendicular_rectangles(1.0, 1.0, 1.0);
        assert!((got.value - want).abs() < 1e-11, "{got:?} vs {want}");
        assert!(
            got.err < 1e-10 && got.err >= (got.value - want).abs(),
            "{got:?}"
        );
        // Parallel at distance 1 (C-11): far, Gauss.
        let poly = square(z, y, x);
        let r = Receiver::new(&poly, -z, DVec3::new(0.5, 0.5, 1.0));
        let got = integrate(&mut Emitter::new(emit), z, &r, 1e-12, 0.0, &|| {
            Contact::Smooth
        });
        let want = parallel_rectangles(1.0, 1.0, 1.0);
        assert!((got.value - want).abs() < 1e-12, "{got:?} vs {want}");
    }

    #[test]
    fn triangle_pieces_and_splits_cover_the_area() {
        let t = Piece::Tri([DVec3::ZERO, DVec3::X, DVec3::new(0.3, 2.0, 0.0)]);
        assert!((t.area() - 1.0).abs() < 1e-14);
        let s: f64 = t.split().iter().map(Piece::area).sum();
        assert!((s - 1.0).abs() < 1e-14);
        let q = Piece::Quad(square(DVec3::ZERO, DVec3::X * 2.0, DVec3::Y * 3.0));
        let s: f64 = q.split().iter().map(Piece::area).sum();
        assert!((s - 6.0).abs() < 1e-13);
    }

    /// A triangle 1 cm over two floor patches, its middle over their shared edge (a rug's
    /// underside at 8,000 patches of the Blender room): apart from each receiver, but too
    /// near for an a-priori Gauss order. The error reported at 1e-6 must cover the true
    /// error (against the same integral split 256 ways at 1e-12). Before such pieces were
    /// split instead of left to tanh–sinh, each was 7.0e-8 off with a reported 2.3e-9 and
    /// 1.1e-9 (30 and 65 times under).
    #[test]
    fn a_piece_apart_but_near_its_receiver_is_within_its_error() {
        let e = [
            DVec3::new(0.9142857142857144, 0.01, 0.8),
            DVec3::new(0.9714285714285714, 0.01, 0.7133974285714286),
            DVec3::new(0.9714285714285714, 0.01, 0.8866025714285715),
        ];
        let n_e = DVec3::NEG_Y;
        for x in [0.7714285714285714, 0.9428571428571431] {
            let w = 0.1714285714285714;
            let r = square(
                DVec3::new(x, 0.0, 0.7826086956521738),
                DVec3::new(0.0, 0.0, 0.1739130434782608),
                DVec3::new(w, 0.0, 0.0),
            );
            let recv = Receiver::new(&r, DVec3::Y, (r[0] + r[2]) * 0.5);
            let got = integrate(
                &mut Emitter::new(Piece::Tri(e)),
                n_e,
                &recv,
                1e-6,
                0.0,
                &|| Contact::Kinked,
            );
            let mut pieces = vec![Piece::Tri(e)];
            for _ in 0..4 {
                pieces = pieces.iter().flat_map(|q| q.split()).collect();
            }
            let exact: f64 = pieces
                .into_iter()
                .map(|q| {
                    integrate(&mut Emitter::new(q), n_e, &recv, 1e-12, 0.0, &|| {
                        Contact::Kinked
                    })
                    .value
                })
                .sum();
            let off = (got.value - exact).abs();
            assert!(
                off <= got.err,
                "receiver at x = {x}: off by {off:e}, reported {:e}",
                got.err
            );
        }
    }

    #[test]
    fn distance_to_polygon() {
        let poly = square(DVec3::ZERO, DVec3::X, DVec3::Y);
        let d = |p: DVec3| point_polygon_distance(p, &poly);
        assert!((d(DVec3::new(0.5, 0.5, 2.0)) - 2.0).abs() < 1e-15);
        assert!((d(DVec3::new(2.0, 0.5, 0.0)) - 1.0).abs() < 1e-15);
        assert!((d(DVec3::new(2.0, 2.0, 0.0)) - 2f64.sqrt()).abs() < 1e-15);
    }

    #[test]
    fn distance_between_polygons() {
        let a = square(DVec3::ZERO, DVec3::X, DVec3::Y);
        // Parallel, 0.3 above: corner to face.
        let b = square(DVec3::new(0.2, 0.2, 0.3), DVec3::X, DVec3::Y);
        assert!((polygon_distance(&a, &b) - 0.3).abs() < 1e-15);
        // Sharing an edge at 90°.
        let c = square(DVec3::X, DVec3::Z, DVec3::Y);
        assert_eq!(polygon_distance(&a, &c), 0.0);
        // Skew edges: a's edge along x at y = 0, and a segment along y at x = 0.5, z = 2,
        // from y = -3 to 3 (only through its edge, no corner comes as close).
        let d = [
            DVec3::new(0.5, -3.0, 2.0),
            DVec3::new(0.5, 3.0, 2.0),
            DVec3::new(0.5, 3.0, 5.0),
        ];
        assert!((polygon_distance(&a, &d) - 2.0).abs() < 1e-15);
    }

    /// The point factor does not depend on the receiver's winding, and against a planar
    /// receiver it is the absolute value of the contour sum; against a warped one it keeps
    /// the sum's sign, so that it passes smoothly through 0 near the receiver's plane where
    /// the absolute value has a kink.
    #[test]
    fn point_factor_is_signed_by_the_receiver_winding() {
        let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
        let ccw = square(DVec3::ZERO, x, y); // counter-clockwise about +z
        let cw = [ccw[0], ccw[3], ccw[2], ccw[1]];
        let centre = DVec3::new(0.5, 0.5, 0.0);
        for (k, p) in [
            DVec3::new(0.3, 0.2, 0.7),
            DVec3::new(2.0, -1.0, 0.1),
            DVec3::new(0.5, 0.5, 1e-3),
        ]
        .into_iter()
        .enumerate()
        {
            // Facing the receiver, and tilted so that it is clipped by the point's plane.
            for n in [-z, (-x - z).normalize()] {
                let want = crate::analytic::point_to_polygon_unit(p, n, &ccw);
                let a = point_factor(p, n, &Receiver::new(&ccw, z, centre));
                let b = point_factor(p, n, &Receiver::new(&cw, z, centre));
                assert!(want > 0.0, "case {k}");
                assert_eq!(a.to_bits(), want.to_bits(), "case {k}");
                // The reversed corners sum the edges in another order: equal to rounding.
                assert!(
                    (b - want).abs() <= 1e-14 * want,
                    "case {k}: {b} against {want}"
                );
            }
        }
        // A warped quad (one corner 0.2 above the others' plane), seen along a line that
        // approaches its centroid's plane from in front, 3 units away: the contour sum
        // changes sign about 4e-4 in front of the plane, and the signed factor is smooth
        // there (its second differences stay small) where the absolute value turns a
        // corner (a second difference of about twice the slope times the step).
        let warped = [ccw[0], ccw[1], ccw[2] + 0.2 * z, ccw[3]];
        let n_r = (warped[2] - warped[0])
            .cross(warped[3] - warped[1])
            .normalize();
        let c = warped.iter().sum::<DVec3>() / 4.0;
        let r = Receiver::new(&warped, n_r, c);
        let side = n_r.cross(DVec3::Y).normalize(); // in the plane, away from the quad
        let f = |t: f64| point_factor(c + 3.0 * side + t * n_r, -side, &r);
        let h = 1e-5;
        let (mut signs, mut worst) = ([false; 2], 0.0f64);
        for i in 1..200 {
            let t = i as f64 * h;
            let v = f(t);
            signs[usize::from(v > 0.0)] = true;
            worst = worst.max((f(t + h) - 2.0 * v + f(t - h)).abs());
        }
        assert!(
            signs[0] && signs[1],
            "the sum did not change sign along the line"
        );
        let slope = (f(1e-3 + h) - f(1e-3 - h)).abs() / (2.0 * h);
        assert!(
            worst < 1e-2 * slope * h,
            "second difference {worst:e}, slope {slope:e}"
        );
    }

    /// Two plates sharing an edge at 135° (a singular configuration for Gauss–Legendre),
    /// of different widths: the integral over either plate must agree (reciprocity,
    /// `A_1 F_12 = A_2 F_21`), within the sum of the two error estimates, which must be
    /// small.
    /// How patches meet: along a whole shared edge or at a shared corner, smooth; a block
    /// standing across a floor patch, a corner on an edge's middle, a partly shared edge,
    /// a warped patch or patches apart, kinked.
    #[test]
    fn contacts_are_classified() {
        let (z, y) = (DVec3::Z, DVec3::Y);
        let floor = [DVec3::ZERO, DVec3::X, DVec3::new(1.0, 0.0, -1.0), -z];
        let floor_plane = (y, DVec3::new(0.5, 0.0, -0.5));
        // A wall over the floor's edge z = 0: along x from a to b, up to height 1.
        let wall = |a: f64, b: f64| {
            let w = [
                DVec3::new(a, 0.0, 0.0),
                DVec3::new(a, 1.0, 0.0),
                DVec3::new(b, 1.0, 0.0),
                DVec3::new(b, 0.0, 0.0),
            ];
            (w, (-z, DVec3::new((a + b) / 2.0, 0.5, 0.0)))
        };
        let kind = |(w, plane): ([DVec3; 4], (DVec3, DVec3))| {
            let one = contact(&w, plane, &floor, floor_plane, 1e-9);
            assert_eq!(
                one,
                contact(&floor, floor_plane, &w, plane, 1e-9),
                "symmetric"
            );
            one
        };
        assert_eq!(kind(wall(0.0, 1.0)), Contact::Smooth, "whole edge");
        assert_eq!(kind(wall(1.0, 2.0)), Contact::Smooth, "a shared corner");
        assert_eq!(kind(wall(2.0, 3.0)), Contact::Kinked, "apart, in line");
        assert_eq!(kind(wall(0.25, 0.75)), Contact::Kinked, "inside the edge");
        assert_eq!(kind(wall(0.5, 1.5)), Contact::Kinked, "half on the edge");
        assert_eq!(kind(wall(-0.5, 1.5)), Contact::Kinked, "over the edge");
        // A block's face standing across the floor patch, away from its edges.
        let across = [
            DVec3::new(0.2, 0.0, -0.5),
            DVec3::new(0.2, 1.0, -0.5),
            DVec3::new(0.8, 1.0, -0.5),
            DVec3::new(0.8, 0.0, -0.5),
        ];
        let plane = (-z, DVec3::new(0.5, 0.5, -0.5));
        assert_eq!(
            contact(&across, plane, &floor, floor_plane, 1e-9),
            Contact::Kinked
        );
        // A corner touching the middle of the floor's edge.
        let tilted = [
            DVec3::new(0.5, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.5),
            DVec3::new(1.0, 1.0, 0.5),
        ];
        let n = (tilted[1] - tilted[0])
            .cross(tilted[2] - tilted[0])
            .normalize();
        let c = (tilted[0] + tilted[1] + tilted[2]) / 3.0;
        assert_eq!(
            contact(&tilted, (n, c), &floor, floor_plane, 1e-9),
            Contact::Kinked
        );
        // Warped beyond the tolerance.
        let mut warped = wall(0.0, 1.0);
        warped.0[1].z += 1e-6;
        assert_eq!(kind(warped), Contact::Kinked, "warped");
    }

    #[test]
    fn angled_shared_edge_is_reciprocal() {
        let (x, s) = (DVec3::X, std::f64::consts::FRAC_1_SQRT_2);
        let t = DVec3::new(0.0, -s, s) * 0.5; // second plate: width 0.5, at 135°
        let a = [DVec3::ZERO, x, x + DVec3::Y, DVec3::Y];
        let b = [DVec3::ZERO, t, t + x, x];
        let (na, nb) = (DVec3::Z, DVec3::new(0.0, s, s));
        let centre = |p: &[DVec3; 4]| p.iter().copied().sum::<DVec3>() / 4.0;
        let meet = contact(&a, (na, centre(&a)), &b, (nb, centre(&b)), 1e-12);
        assert_eq!(meet, Contact::Smooth, "a whole shared edge");
        for tol in [1e-6, 1e-9] {
            let ab = integrate(
                &mut Emitter::new(Piece::Quad(a)),
                na,
                &Receiver::new(&b, nb, centre(&b)),
                tol,
                0.0,
                &|| meet,
            );
            let ba = integrate(
                &mut Emitter::new(Piece::Quad(b)),
                nb,
                &Receiver::new(&a, na, centre(&a)),
                tol,
                0.0,
                &|| meet,
            );
            let gap = (ab.value - ba.value).abs();
            assert!(gap <= ab.err + ba.err, "tol {tol}: {ab:?} {ba:?}");
            // Within a small multiple of the tolerance (splits stop at a fixed depth).
            assert!(ab.err <= 4.0 * tol * ab.value && ba.err <= 4.0 * tol * ba.value);
        }
    }
}
