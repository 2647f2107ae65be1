//! Small polygons far away: one-point rules for their factors and solid angles, each with
//! a bound on its error, so that a caller takes the rule only where the bound is within
//! its tolerance and reports the bound beside its other deterministic bounds.
//!
//! A polygon `P` (planar, area `A`, area centroid `c`, every corner within `ρ` of `c`)
//! seen from a point `y` at distance `D = |c - y|`, with `D > ρ`:
//!
//! - **Why one point.** For a kernel `k` smooth over `P`, Taylor's theorem about `c`
//!   gives `∫_P k dA = A k(c) + ∫_P ∇k(c)·(x - c) dA + R`; the first-order term vanishes
//!   because `c` is the area centroid, and `|R| ≤ ½ max_P ‖∇²k‖ ∫_P |x - c|² dA ≤
//!   ½ max_P ‖∇²k‖ A ρ²` (the Hessian's spectral norm; every `x` of `P` is within `ρ`
//!   of `c`, hence at least `D - ρ` from `y`). The error falls as `(ρ/D)²` relative.
//! - **Point to polygon** (`F(y → P)`, the factor from a differential area at `y` with
//!   unit normal `n_y`): the kernel is `h (n_y·d) / (π |d|⁴)` with `d = x - y` and
//!   `h = n_P·(y - c)` the height of `y` over `P`'s plane (the same for every `x` of
//!   `P`). Where all of `P` is in front of `y` (`n_y·(c - y) > ρ`, so no horizon
//!   clipping), the Hessian of `(n·d)|d|⁻⁴` is
//!   `-4 (n dᵀ + d nᵀ)|d|⁻⁶ - 4 (n·d) I |d|⁻⁶ + 24 (n·d) d dᵀ |d|⁻⁸`, of norm at most
//!   `(4 + 4 + 4 + 24) |d|⁻⁵ = 36 |d|⁻⁵`: the bound is `18 h A ρ² / (π (D - ρ)⁵)`.
//! - **Solid angle** (`Ω = ∫_P h |d|⁻³ dA`): the Hessian of `|d|⁻³`, `-3 I |d|⁻⁵ +
//!   15 d dᵀ |d|⁻⁷`, has eigenvalues `-3` and `12` times `|d|⁻⁵`: the bound is
//!   `6 h A ρ² / (D - ρ)⁵`.
//! - **Polygon to polygon by its centroid** (`(1/A) ∫_P F(x → Q) dA_x ≈ F(c → Q)`,
//!   for `P` the small one, `Q` of area `A_Q` at least `G` from every point of `P`): the
//!   kernel `(n_P·d)(-n_Q·d) / (π |d|⁴)` with `d = y - x` is a product of two linear forms
//!   over `|d|⁴`, whose Hessian has norm at most `(2 + 8 + 8 + 4 + 24) |d|⁻⁴ = 46 |d|⁻⁴`;
//!   integrated over `Q` and divided by `A`, the bound on the factor is
//!   `23 A_Q ρ² / (π G⁴)`. It holds where the kernel has no clipping: every corner of `Q`
//!   in front of `P`'s plane and every corner of `P` in front of `Q`'s.
//!
//! Used by the hierarchy's final gather, where at 10⁶ input triangles most receivers are
//! millimetres across and most sources metres away: the exact rules (Lambert's formula
//! per point, a Gauss rule with its check per pair) spent most of the gather's time on
//! digits the one-point rules give within their bounds.

use std::f64::consts::PI;

use glam::DVec3;

/// A planar polygon as the one-point rules see it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Small {
    /// Area centroid.
    pub centroid: DVec3,
    /// Unit normal (front side).
    pub normal: DVec3,
    /// Area.
    pub area: f64,
    /// Largest distance from the centroid to a corner.
    pub radius: f64,
}

impl Small {
    /// The polygon with corners `poly` (3 or more, planar, counter-clockwise seen from
    /// the front) and unit normal `normal`; its area and centroid from a fan of
    /// triangles.
    pub fn new(poly: &[DVec3], normal: DVec3) -> Small {
        let (mut area, mut moment) = (0.0, DVec3::ZERO);
        for k in 1..poly.len().saturating_sub(1) {
            let a = 0.5 * (poly[k] - poly[0]).cross(poly[k + 1] - poly[0]).length();
            area += a;
            moment += a * (poly[0] + poly[k] + poly[k + 1]) / 3.0;
        }
        let centroid = if area > 0.0 {
            moment / area
        } else {
            poly.iter().fold(DVec3::ZERO, |s, &p| s + p) / poly.len().max(1) as f64
        };
        let radius = poly
            .iter()
            .map(|&p| (p - centroid).length())
            .fold(0.0, f64::max);
        Small {
            centroid,
            normal,
            area,
            radius,
        }
    }
}

/// `F(y → P)` for a differential area at `y` with unit normal `n_y`, by `P`'s centroid,
/// and the bound on its error; `None` where the rule does not hold (`y` within `ρ` of
/// the centroid, or `P` not wholly in front of `y`). Exactly 0 with bound 0 when `y` is
/// not in front of `P`'s plane.
pub fn point_factor(y: DVec3, n_y: DVec3, p: &Small) -> Option<(f64, f64)> {
    let d = p.centroid - y;
    let h = -p.normal.dot(d);
    if h <= 0.0 {
        return Some((0.0, 0.0));
    }
    let dist2 = d.length_squared();
    let dist = dist2.sqrt();
    let gap = dist - p.radius;
    let facing = n_y.dot(d);
    if gap <= 0.0 || facing <= p.radius {
        return None;
    }
    let value = p.area * h * facing / (PI * dist2 * dist2);
    let bound = 18.0 * h * p.area * p.radius * p.radius / (PI * gap.powi(5));
    Some((value, bound))
}

/// The solid angle of `P` from `y` by its centroid, and the bound on its error; `None`
/// where `y` is within `ρ` of the centroid. Exactly 0 with bound 0 when `y` is not in
/// front of `P`'s plane.
pub fn solid_angle(y: DVec3, p: &Small) -> Option<(f64, f64)> {
    let d = p.centroid - y;
    let h = -p.normal.dot(d);
    if h <= 0.0 {
        return Some((0.0, 0.0));
    }
    let dist = d.length();
    let gap = dist - p.radius;
    if gap <= 0.0 {
        return None;
    }
    let value = p.area * h / (dist * dist * dist);
    let bound = 6.0 * h * p.area * p.radius * p.radius / gap.powi(5);
    Some((value, bound))
}

/// The bound on `|F(c → Q) - (1/A) ∫_P F(x → Q) dA_x|` for the small polygon `p` and a
/// polygon `q` of area `q_area` with corners `q_corners` and unit normal `q_normal`;
/// `None` where the rule's conditions fail (the polygons closer than `p`'s radius
/// allows, or a corner of either not strictly in front of the other's plane).
pub fn centroid_rule_bound(
    p: &Small,
    p_corners: &[DVec3],
    q_corners: &[DVec3],
    q_normal: DVec3,
    q_area: f64,
) -> Option<f64> {
    let front = |n: DVec3, c: DVec3, pts: &[DVec3]| pts.iter().all(|&x| n.dot(x - c) > 0.0);
    let q_centroid = q_corners.iter().fold(DVec3::ZERO, |s, &x| s + x) / q_corners.len() as f64;
    if !front(p.normal, p.centroid, q_corners) || !front(q_normal, q_centroid, p_corners) {
        return None;
    }
    let q_radius = q_corners
        .iter()
        .map(|&x| (x - q_centroid).length())
        .fold(0.0, f64::max);
    let gap = (q_centroid - p.centroid).length() - p.radius - q_radius;
    if gap <= 0.0 {
        return None;
    }
    Some(23.0 * q_area * p.radius * p.radius / (PI * gap.powi(4)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::point_to_polygon;
    use crate::hierarchy::clusters::solid_angle as exact_solid_angle;
    use crate::sampling::Pcg32;

    fn unit(rng: &mut Pcg32) -> DVec3 {
        loop {
            let v = DVec3::new(
                2.0 * rng.next_f64() - 1.0,
                2.0 * rng.next_f64() - 1.0,
                2.0 * rng.next_f64() - 1.0,
            );
            let l = v.length();
            if l > 0.1 && l <= 1.0 {
                return v / l;
            }
        }
    }

    /// A random triangle or planar quad of size about `s` around `c`, counter-clockwise
    /// about its normal, with the normal.
    fn polygon(rng: &mut Pcg32, c: DVec3, s: f64, quad: bool) -> (Vec<DVec3>, DVec3) {
        let n = unit(rng);
        let t = n.any_orthonormal_vector();
        let b = n.cross(t);
        let k = if quad { 4 } else { 3 };
        let pts = (0..k)
            .map(|i| {
                let a = (i as f64 + 0.4 * rng.next_f64()) / k as f64 * std::f64::consts::TAU;
                let r = s * (0.5 + rng.next_f64());
                c + r * (a.cos() * t + a.sin() * b)
            })
            .collect();
        (pts, n)
    }

    #[test]
    fn one_point_rules_stay_within_their_bounds_and_the_bounds_are_not_vacuous() {
        // Random small polygons against Lambert's formula and Van Oosterom and Strackee's
        // solid angle: every error within its bound, and far away the bound well below
        // the value (it is what decides whether the rule is used).
        let mut rng = Pcg32::keyed(11, 0, 0, 0);
        let (mut used, mut tight) = (0, 0);
        for i in 0..4000 {
            let (poly, n) = polygon(&mut rng, DVec3::ZERO, 1.0, i % 2 == 0);
            let p = Small::new(&poly, n);
            let dist = 1.5 + 200.0 * rng.next_f64().powi(2);
            let y = dist * unit(&mut rng);
            let n_y = unit(&mut rng);
            if let Some((v, b)) = point_factor(y, n_y, &p) {
                // One-sided, as the rule: nothing from behind the polygon's plane.
                let exact = if n.dot(y - p.centroid) > 0.0 {
                    point_to_polygon(y, n_y, &poly)
                } else {
                    0.0
                };
                assert!(
                    (v - exact).abs() <= b + 1e-15,
                    "factor {v} vs {exact}, bound {b}"
                );
                used += 1;
                if b < 1e-2 * v {
                    tight += 1;
                }
            }
            if let Some((v, b)) = solid_angle(y, &p) {
                let exact = exact_solid_angle(y, &poly, n);
                assert!(
                    (v - exact).abs() <= b + 1e-15,
                    "solid angle {v} vs {exact}, bound {b}"
                );
            }
        }
        assert!(used > 1000 && tight > 200, "{used} used, {tight} tight");
    }

    #[test]
    fn the_centroid_rule_stays_within_its_bound() {
        // A small polygon's factor to a larger one by its centroid, against a fine Gauss
        // rule over the small one (Lambert's formula at each node).
        let mut rng = Pcg32::keyed(12, 0, 0, 0);
        let rule = crate::analytic::gauss_legendre(24);
        let mut checked = 0;
        for i in 0..600 {
            let (small, n_p) = polygon(&mut rng, DVec3::ZERO, 0.05, i % 2 == 0);
            let p = Small::new(&small, n_p);
            let at = (0.3 + 3.0 * rng.next_f64()) * unit(&mut rng);
            let (big, n_q) = polygon(&mut rng, at, 0.3, i % 3 == 0);
            let q = Small::new(&big, n_q);
            let Some(bound) = centroid_rule_bound(&p, &small, &big, n_q, q.area) else {
                continue;
            };
            let one = point_to_polygon(p.centroid, n_p, &big);
            // Fan triangles, each by a collapsed tensor Gauss rule.
            let mut integral = 0.0;
            for k in 1..small.len() - 1 {
                let (a, b, c) = (small[0], small[k], small[k + 1]);
                let twice = (b - a).cross(c - a).length();
                for &(u, wu) in &rule {
                    for &(v, wv) in &rule {
                        // Nodes and weights on [0, 1]; the collapsed square's Jacobian.
                        let x = a + u * (b - a) + u * v * (c - b);
                        let jac = twice * u;
                        integral += wu * wv * jac * point_to_polygon(x, n_p, &big);
                    }
                }
            }
            let mean = integral / p.area;
            assert!(
                (one - mean).abs() <= bound + 1e-12 * mean,
                "centroid {one} vs mean {mean}, bound {bound}"
            );
            checked += 1;
        }
        assert!(checked > 100, "{checked} pairs checked");
    }
}
