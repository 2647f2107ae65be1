//! Semi-analytic form factors: the exact point-to-polygon factor, integrated over the
//! emitter, times a visible fraction estimated by rays.
//!
//! For patches i and j,
//!
//! `F_ij = 1/A_i ∫_{A_i} F(x → P_j) v(x) dA_x`,
//!
//! where `F(x → P_j)` is the exact unoccluded differential-area-to-polygon factor
//! ([`crate::analytic::point_to_polygon`], Lambert's contour integral; Baum, Rushmeier and
//! Winget 1989) and `v(x)` the kernel-weighted visible fraction of `P_j` from `x`,
//! `v(x) = ∫ G V dA_y / ∫ G dA_y` with `G = cos θ_x cos θ_y / (π r²)`. Only `v` is
//! sampled: it is estimated at each node `x` by rays to `vis_rays²` jittered points `y` on
//! `P_j` as `Σ G V / Σ G` (a ratio estimator: consistent, with an `O(1/n)` bias where the
//! pair is partly occluded, and exact, 1, where nothing blocks). Receivers are one-sided:
//! nodes behind `P_j`'s plane contribute 0.
//!
//! The integral over `x` uses either
//! - [`Nodes::Gauss`] (the default of `radiosity bake`): the tensor Gauss–Legendre rule of
//!   order `points` on the patch's
//!   parameter square (bilinear map for quads, collapsed map for triangles). The point
//!   factor is analytic inside the patch for unoccluded pairs, with weak singularities only
//!   where the patch touches `P_j` (a shared edge), so the rule converges quickly: for the
//!   two unit-square plates (Howell C-11, and C-14 with its shared edge) 4 nodes per side
//!   give 1e-5 relative, 8 give 1e-10 and 12 reach rounding error. The nodes are the same in every replicate and for every receiver j, so
//!   in a closed scene the unoccluded part of each row sums to 1 exactly (the point
//!   factors of a point inside a closed surface sum to 1). Replicates differ only in their
//!   visibility rays; the reported error adds, in quadrature, the replicate standard error
//!   of the visibility and the difference between the order-`points` and order
//!   `points - 1` rules (a conservative estimate of the deterministic quadrature error).
//! - [`Nodes::Stratified`]: one jittered point in each of `points²` strata of the patch
//!   (uniform by area), independently in each replicate; the standard error then covers
//!   the whole estimate.
//!
//! The standard error is the standard deviation of the replicate means over `sqrt(R)`.
//!
//! **Provably unoccluded pairs cast no rays.** A patch k can block a segment from
//! `x ∈ P_i` to `y ∈ P_j` only if it meets the convex hull of the two patches. It cannot
//! when all its corners lie on or behind the plane of i or of j (the segment's interior is
//! strictly in front of both), nor when both patches lie wholly on the front side of k's
//! plane (segments between them cannot cross it: the walls of a convex room), nor when its
//! bounding box misses the bounding box of the two
//! patches' corners. When every other patch is excluded by these tests, `v = 1` exactly and
//! the entry is deterministic (standard error 0). The test costs `O(N)` per pair, small
//! next to the rays it saves or casts; it is conservative (a box overlap does not prove an
//! occlusion, so some unoccluded pairs still cast rays, and give `v = 1` from the rays).
//!
//! Pairs with one patch wholly behind the other's plane are culled without rays, as in
//! [`super::area`]. Each stream is keyed on `(seed, i, j, replicate)`, so the result does
//! not depend on the thread count.

use glam::{DVec3, Vec3};

use super::area::kernel;
use super::{Context, Entry, Estimator, Row};
use crate::analytic::{gauss_legendre, point_to_polygon};
use crate::mesh::PatchSet;
use crate::sampling::{jittered, Pcg32};
use crate::visibility::SegmentRay;

/// How the nodes `x` on the emitter are placed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Nodes {
    /// Tensor Gauss–Legendre nodes, the same in every replicate.
    Gauss,
    /// A jittered point per stratum, drawn anew in every replicate.
    Stratified,
}

/// Semi-analytic estimator: exact point-to-polygon factors times ray-estimated visibility.
#[derive(Clone, Debug)]
pub struct SemiAnalytic {
    /// Node placement on the emitter.
    pub nodes: Nodes,
    /// Nodes per side on the emitter: `points²` nodes per replicate.
    pub points: usize,
    /// Visibility strata per side: `vis_rays²` rays per node, for pairs not provably
    /// unoccluded.
    pub vis_rays: usize,
    /// Independent replicates (>= 2) for the standard error.
    pub replicates: usize,
}

impl Default for SemiAnalytic {
    fn default() -> Self {
        SemiAnalytic {
            nodes: Nodes::Gauss,
            points: 4,
            vis_rays: 4,
            replicates: 4,
        }
    }
}

/// Corners of patch `i` in f64.
fn corners(p: &PatchSet, i: usize) -> ([DVec3; 4], usize) {
    let (c, k) = p.corner_points(i);
    (c.map(|q| q.as_dvec3()), k)
}

/// Signed distances of the corners of `b` from the plane of `a`, as (min, max).
fn plane_range(p: &PatchSet, a: usize, b: usize) -> (f32, f32) {
    let (n, c) = (p.normal[a], p.centroid[a]);
    let (pts, k) = p.corner_points(b);
    pts[..k]
        .iter()
        .map(|&q| n.dot(q - c))
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), d| {
            (lo.min(d), hi.max(d))
        })
}

/// Axis-aligned bounding box of patch `i`'s corners.
fn bounds(p: &PatchSet, i: usize) -> (Vec3, Vec3) {
    let (pts, k) = p.corner_points(i);
    pts[..k]
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &q| {
            (lo.min(q), hi.max(q))
        })
}

/// Gauss–Legendre nodes on patch `i`: `(x, weight)` with weights summing to the area.
fn gauss_nodes(p: &PatchSet, i: usize, rule: &[(f64, f64)], out: &mut Vec<(DVec3, f64)>) {
    out.clear();
    let (c, k) = corners(p, i);
    for &(u, wu) in rule {
        for &(v, wv) in rule {
            let (x, jac) = if k == 3 {
                // Collapsed map: x = c0 + u (c1 - c0 + v (c2 - c1)), |J| = u |e1 x e2|.
                let (e1, e2) = (c[1] - c[0], c[2] - c[1]);
                (c[0] + (e1 + e2 * v) * u, u * e1.cross(e2).length())
            } else {
                // Bilinear map of the quad.
                let x = c[0] * ((1.0 - u) * (1.0 - v))
                    + c[1] * (u * (1.0 - v))
                    + c[2] * (u * v)
                    + c[3] * ((1.0 - u) * v);
                let du = (c[1] - c[0]) * (1.0 - v) + (c[2] - c[3]) * v;
                let dv = (c[3] - c[0]) * (1.0 - u) + (c[2] - c[1]) * u;
                (x, du.cross(dv).length())
            };
            out.push((x, wu * wv * jac));
        }
    }
}

/// Quadrature nodes: (point, weight).
type NodeList = Vec<(DVec3, f64)>;

/// The part of a convex polygon on the front side of the plane through `c` with normal
/// `n` (Sutherland–Hodgman against one plane).
fn clip_front(poly: &[DVec3], n: DVec3, c: DVec3) -> Vec<DVec3> {
    let mut out = Vec::with_capacity(poly.len() + 1);
    for k in 0..poly.len() {
        let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
        let (da, db) = (n.dot(a - c), n.dot(b - c));
        if da >= 0.0 {
            out.push(a);
        }
        if (da >= 0.0) != (db >= 0.0) {
            out.push(a + (b - a) * (da / (da - db)));
        }
    }
    out
}

/// Gauss–Legendre nodes on a convex polygon: the collapsed tensor rule on each triangle of
/// a fan from the first corner; weights sum to the polygon's area.
fn gauss_nodes_polygon(poly: &[DVec3], rule: &[(f64, f64)], out: &mut Vec<(DVec3, f64)>) {
    out.clear();
    for k in 1..poly.len().saturating_sub(1) {
        let (c0, e1, e2) = (poly[0], poly[k] - poly[0], poly[k + 1] - poly[k]);
        let area2 = e1.cross(e2).length();
        for &(u, wu) in rule {
            for &(v, wv) in rule {
                out.push((c0 + (e1 + e2 * v) * u, wu * wv * u * area2));
            }
        }
    }
}

impl SemiAnalytic {
    /// True when no other patch can block any segment between patches `i` and `j` (see
    /// the module docs). `others` are the patches with a corner strictly in front of i.
    fn unoccluded(
        &self,
        p: &PatchSet,
        i: usize,
        j: usize,
        others: &[u32],
        boxes: &[(Vec3, Vec3)],
    ) -> bool {
        let tol = 1e-6 * p.diagonal as f32;
        let (lo_i, hi_i) = boxes[i];
        let (lo_j, hi_j) = boxes[j];
        let (lo, hi) = (lo_i.min(lo_j) - tol, hi_i.max(hi_j) + tol);
        others.iter().all(|&k| {
            let k = k as usize;
            // Cheapest test first: k's box misses the box of the two patches.
            let (lk, hk) = boxes[k];
            if k == j || lk.cmpgt(hi).any() || hk.cmplt(lo).any() {
                return true;
            }
            if plane_range(p, j, k).1 <= tol {
                return true;
            }
            // Both patches wholly on the front side of k's plane: segments between them
            // cannot cross that plane, so k cannot block (every wall of a convex room).
            plane_range(p, k, i).0 >= -tol && plane_range(p, k, j).0 >= -tol
        })
    }
}

impl Estimator for SemiAnalytic {
    fn name(&self) -> String {
        let kind = match self.nodes {
            Nodes::Gauss => "semi-gauss",
            Nodes::Stratified => "semi-stratified",
        };
        let (p, v) = (self.points, self.vis_rays);
        format!(
            "{kind}(points={p}x{p}x{}, vis={v}x{v})",
            self.replicates.max(2)
        )
    }

    fn row(&self, ctx: &Context, i: usize, row: &mut Row) {
        let vis = ctx.vis;
        self.row_with(ctx, i, row, &mut |segs, out| {
            vis.segments_visible(segs, out)
        });
    }
}

impl SemiAnalytic {
    /// Row `i` with `visible(segments, out)` answering visibility for a batch of segment
    /// rays ([`crate::visibility::Visibility::segment_ray`], one batch per node); the rays
    /// asked for do not depend on the answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        visible: &mut dyn FnMut(&[SegmentRay], &mut [bool]),
    ) {
        let p = ctx.patches;
        let reps = self.replicates.max(2);
        let m = self.points.max(1);
        let tol = 1e-6 * p.diagonal as f32;
        let n_i = p.normal[i];
        let n_x = n_i.as_dvec3();
        // Patches that could block anything leaving i: a corner strictly in front of i.
        let boxes: Vec<(Vec3, Vec3)> = (0..p.len()).map(|k| bounds(p, k)).collect();
        let others: Vec<u32> = (0..p.len())
            .filter(|&k| k != i && plane_range(p, i, k).1 > tol)
            .map(|k| k as u32)
            .collect();
        let rule = gauss_legendre(m);
        let mut nodes = Vec::with_capacity(m * m);
        // Gauss mode: the rule of order m - 1 on the same patch estimates the quadrature
        // error of the order-m rule (|Q_m - Q_{m-1}|, conservative for a converging rule).
        let mut nodes_lo = Vec::new();
        let rule_lo = gauss_legendre(m.saturating_sub(1).max(1));
        if self.nodes == Nodes::Gauss {
            gauss_nodes(p, i, &rule, &mut nodes);
            if m >= 2 {
                gauss_nodes(p, i, &rule_lo, &mut nodes_lo);
            }
        }
        let (mut clip_nodes, mut clip_nodes_lo) = (Vec::new(), Vec::new());
        let mut strat_nodes = Vec::with_capacity(m * m);
        let area_i = p.area[i];
        let mut strata = Vec::new();
        let mut ys = Vec::new();
        let (mut segs, mut gs, mut seen) = (Vec::new(), Vec::new(), Vec::new());
        let mut means = vec![0.0f64; reps];
        for j in 0..p.len() {
            if j == i || plane_range(p, i, j).1 <= tol || plane_range(p, j, i).1 <= tol {
                continue;
            }
            let (cj, kj) = corners(p, j);
            let poly = &cj[..kj];
            let (n_j, c_j) = (p.normal[j], p.centroid[j].as_dvec3());
            let n_y = n_j.as_dvec3();
            let free = self.unoccluded(p, i, j, &others, &boxes);
            // Gauss nodes only where nothing can block: there the integrand is smooth and
            // the rule exact to rounding. Where something may block, visibility jumps across
            // the emitter and fixed nodes can all miss a visible sliver, so fresh stratified
            // nodes are drawn in each replicate and the error bar is a true standard error.
            let gauss = self.nodes == Nodes::Gauss && free;
            // Gauss mode: when patch i straddles the plane of j, only its part in front of
            // that plane sees j; the integrand drops to 0 across the plane, which a tensor
            // rule over the whole patch resolves badly. Integrate over the clipped part.
            let straddles = gauss && plane_range(p, j, i).0 < -tol;
            if straddles {
                let (ci, ki) = corners(p, i);
                let front = clip_front(&ci[..ki], n_y, c_j);
                gauss_nodes_polygon(&front, &rule, &mut clip_nodes);
                if m >= 2 {
                    gauss_nodes_polygon(&front, &rule_lo, &mut clip_nodes_lo);
                }
            }
            let (nodes_j, nodes_lo_j): (&NodeList, &NodeList) = if straddles {
                (&clip_nodes, &clip_nodes_lo)
            } else {
                (&nodes, &nodes_lo)
            };
            let on_j = p.sampler(j);
            // Exact unoccluded point factors at fixed nodes are the same in every replicate.
            let fixed: Vec<f64> = if gauss {
                nodes_j
                    .iter()
                    .map(|&(x, _)| point_factor(x, n_x, poly, n_y, c_j))
                    .collect()
            } else {
                Vec::new()
            };
            for (r, mean) in means.iter_mut().enumerate() {
                let mut rng = Pcg32::keyed(ctx.seed, i as u64, j as u64, r as u64);
                if !gauss {
                    jittered(&mut rng, m, &mut strata);
                    let w = p.area[i] / (m * m) as f64;
                    strat_nodes.clear();
                    strat_nodes.extend(
                        strata
                            .iter()
                            .map(|&(u, v)| (p.sample_point(i, u, v).as_dvec3(), w)),
                    );
                }
                let node_set = if gauss { nodes_j } else { &strat_nodes };
                let mut sum = 0.0;
                for (k, &(x, w)) in node_set.iter().enumerate() {
                    let f = if gauss {
                        fixed[k]
                    } else {
                        point_factor(x, n_x, poly, n_y, c_j)
                    };
                    if f <= 0.0 {
                        continue;
                    }
                    let v = if free {
                        1.0
                    } else {
                        jittered(&mut rng, self.vis_rays.max(1), &mut ys);
                        let xf = x.as_vec3();
                        segs.clear();
                        gs.clear();
                        for &(u, v) in &ys {
                            let y = on_j.point(u, v);
                            if let Some(g) = kernel(xf, n_i, y, n_j) {
                                segs.push(ctx.vis.segment_ray(xf, n_i, y, n_j));
                                gs.push(g);
                            }
                        }
                        row.rays += segs.len() as u64;
                        seen.clear();
                        seen.resize(segs.len(), false);
                        visible(&segs, &mut seen);
                        let (mut g_all, mut g_vis) = (0.0, 0.0);
                        for (&g, &f) in gs.iter().zip(&seen) {
                            g_all += g;
                            if f {
                                g_vis += g;
                            }
                        }
                        // No sample in view: the visible sliver of P_j is below the
                        // sampling resolution and counts as hidden.
                        if g_all > 0.0 {
                            g_vis / g_all
                        } else {
                            0.0
                        }
                    };
                    sum += w * f * v;
                }
                *mean = sum / area_i;
            }
            let avg = means.iter().sum::<f64>() / reps as f64;
            if avg > 0.0 {
                let var = means.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / (reps - 1) as f64;
                let mut se2 = var / reps as f64;
                if gauss && !nodes_lo_j.is_empty() {
                    // Quadrature error of the unoccluded factor, scaled by the visible fraction.
                    let q_hi: f64 = nodes_j
                        .iter()
                        .zip(&fixed)
                        .map(|(n, f)| n.1 * f)
                        .sum::<f64>()
                        / area_i;
                    let q_lo: f64 = nodes_lo_j
                        .iter()
                        .map(|&(x, w)| w * point_factor(x, n_x, poly, n_y, c_j))
                        .sum::<f64>()
                        / area_i;
                    let visible = if q_hi > 0.0 {
                        (avg / q_hi).min(1.0)
                    } else {
                        1.0
                    };
                    se2 += ((q_hi - q_lo) * visible).powi(2);
                }
                row.entries.push(Entry {
                    j: j as u32,
                    f: avg,
                    se: se2.sqrt(),
                });
            }
        }
    }
}

/// `F(x → P_j)` for a one-sided receiver: 0 when `x` is not in front of `P_j`'s plane.
#[inline]
fn point_factor(x: DVec3, n_x: DVec3, poly: &[DVec3], n_y: DVec3, c_y: DVec3) -> f64 {
    if n_y.dot(x - c_y) <= 0.0 {
        return 0.0;
    }
    point_to_polygon(x, n_x, poly)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::{parallel_rectangles, perpendicular_rectangles};
    use crate::formfactor::{compute, Context};
    use crate::mesh::{PatchSet, Resolution};
    use crate::scene::Scene;
    use crate::visibility::Visibility;

    fn plates(name: &str, est: &SemiAnalytic) -> (f64, f64, u64) {
        let scene = Scene::load(name).unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 1,
        };
        let ff = compute(&ctx, est, &|_| {});
        (ff.get(0, 1), ff.get(1, 0), ff.rays)
    }

    fn rel(got: f64, want: f64) -> f64 {
        (got - want).abs() / want
    }

    #[test]
    fn plates_match_closed_forms() {
        let est = SemiAnalytic {
            nodes: Nodes::Gauss,
            points: 12,
            vis_rays: 4,
            replicates: 2,
        };
        let (f01, f10, rays) = plates("plates-parallel", &est);
        let want = parallel_rectangles(1.0, 1.0, 1.0);
        assert!(
            rel(f01, want) < 1e-6 && rel(f10, want) < 1e-6,
            "{f01} {f10} vs {want}"
        );
        assert_eq!(rays, 0, "two lone plates are provably unoccluded");
        let (f01, f10, rays) = plates("plates-perpendicular", &est);
        let want = perpendicular_rectangles(1.0, 1.0, 1.0);
        assert!(
            rel(f01, want) < 1e-6 && rel(f10, want) < 1e-6,
            "{f01} {f10} vs {want}"
        );
        assert_eq!(rays, 0);
    }

    #[test]
    fn stratified_nodes_agree_within_error_bars() {
        let est = SemiAnalytic {
            nodes: Nodes::Stratified,
            points: 8,
            vis_rays: 2,
            replicates: 16,
        };
        let scene = Scene::load("plates-perpendicular").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 3,
        };
        let ff = compute(&ctx, &est, &|_| {});
        let (f, se) = (ff.get(0, 1), ff.stderr(0, 1));
        let want = perpendicular_rectangles(1.0, 1.0, 1.0);
        assert!(se > 0.0 && se < 1e-2 * want, "{f} +- {se}");
        assert!((f - want).abs() < 5.0 * se, "{f} +- {se} vs {want}");
    }

    /// A closed cube: every pair is proven unoccluded (each wall has the whole room on its
    /// front side), so no ray is cast and every row sums to 1 to rounding.
    #[test]
    fn closed_cube_rows_sum_to_one() {
        let scene = Scene::load("cube").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(0.5)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 5,
        };
        let est = SemiAnalytic {
            nodes: Nodes::Gauss,
            points: 8,
            vis_rays: 3,
            replicates: 2,
        };
        let ff = compute(&ctx, &est, &|_| {});
        assert_eq!(ff.rays, 0);
        for i in 0..patches.len() {
            let s = ff.row_sum(i);
            assert!((s - 1.0).abs() < 1e-6, "row {i} sums to {s}");
        }
    }

    /// The Cornell box (occluding blocks): agrees with area-to-area Monte Carlo within
    /// the combined error bars, up to the ratio estimator's small bias.
    #[test]
    fn cornell_matches_area_monte_carlo() {
        use crate::formfactor::{AreaMc, Pattern};
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::Patches(40)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 7,
        };
        let semi = SemiAnalytic {
            nodes: Nodes::Stratified,
            points: 6,
            vis_rays: 4,
            replicates: 8,
        };
        let mc = AreaMc {
            pattern: Pattern::Stratified,
            strata: 24,
            replicates: 8,
        };
        let (a, b) = (compute(&ctx, &semi, &|_| {}), compute(&ctx, &mc, &|_| {}));
        let n = patches.len();
        let (mut checked, mut worst) = (0, 0.0f64);
        for i in 0..n {
            for j in 0..n {
                let (fa, fb) = (a.get(i, j), b.get(i, j));
                let shares_corner = {
                    let (ci, ki) = patches.corner_points(i);
                    let (cj, kj) = patches.corner_points(j);
                    ci[..ki]
                        .iter()
                        .any(|p| cj[..kj].iter().any(|q| (*p - *q).length() < 1e-4))
                };
                if shares_corner || fa.max(fb) < 1e-3 {
                    continue; // area MC error bars are unreliable at shared edges
                }
                let sigma = a.stderr(i, j).hypot(b.stderr(i, j));
                let z = (fa - fb).abs() / (sigma + 2e-3 * fa.max(fb));
                worst = worst.max(z);
                checked += 1;
            }
        }
        assert!(checked > 50, "{checked}");
        // About 800 comparisons: the largest |z| of normal errors would be near 3.5.
        assert!(worst < 6.0, "worst z {worst}");
    }
}
