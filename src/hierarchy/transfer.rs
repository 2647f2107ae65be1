//! Cluster links gathered node by node, without a list per receiving root.
//!
//! A cluster link `R ← S` ([`super::clusters`]) brings each root `l` under `R` the
//! irradiance `v B_S F_lS` of its source. Expanding it root by root (what
//! [`super::clusters::Expansion`] does for the final gather) costs one entry per root of
//! `R` and piece of `S`: at 10^5 triangles about a hundred million entries, rebuilt every
//! refinement pass. Here the source is the point source of [`super::clusters`] (intensity
//! `B P / π` at the piece's centre `c`, `P` its projected area toward `R`), and the
//! receiving side is cut only as far as the cosine needs:
//!
//! - a cluster `Q` under `R` whose every root faces `c` (the angle between its normal cone's
//!   axis and the direction `u` to `c`, plus the cone's half-angle and `asin(r_Q / d)` for
//!   its extent, below a right angle) receives the vector `v P u / (π d²)` at its centre
//!   (`d` the distance from it): a root `l` below takes `n_l · (that) B`, the far-field
//!   kernel `cos θ_l / (π d²)` of the point source, linear in the root's normal, so that
//!   the vectors of all the links above a root add up before it reads them;
//! - a cluster whose every root faces away receives nothing;
//! - a cluster with roots on both sides is cut into its children;
//! - an element (a root, or a receiver below one) receives the exact solid angle of its
//!   polygon from `c`, `v P Ω_l / (π A_l)` (as [`super::clusters::piece_factor`]'s point
//!   term), along its normal; what lands on an element below a root is pushed down its
//!   element tree by the solve with the rest of its irradiance.
//!
//! The kernel's variation over the pair (`1/d²` and the cosines over both bounding
//! spheres) is the link bound's geometric term `4ds/(d - s)² + 2α` without the near-field
//! points' `1/√K` ([`super::clusters::Refiner::noise`]). This transfer serves the
//! refinement passes, whose solutions only steer which links are refined next (the
//! brightness `B_s` of each source, multigridding); the answer comes from the final
//! gather, where each leaf gathers every cluster link on its chain with its own
//! near-field factors ([`super::clusters::Expansion`]). On `room-spheres-8` at `--error
//! 0.05` the passes' entries fell from 5.65 M (root by root, 8 near-field points each) to
//! 0.61 M, their solves from 1.2 s to 0.25 s a pass, and the final answer moved by
//! rounding-level amounts (power unaccounted 0.587% → 0.589%).
//!
//! Per iteration the cost is one multiply-add per entry (a target node and a source
//! piece), then one walk down the cluster tree and one dot product per root; the entries
//! are built once per pass and number a few per cluster link.

use std::f64::consts::{FRAC_PI_2, PI};

use glam::DVec3;
use rayon::prelude::*;

use super::clusters::{is_cluster, solid_angle, Links, Refiner, Tree, CLUSTER};
use super::element::{Elements, NONE};
use super::solve::State;

/// The cluster links as entries `(target node, source node, vector)`, grouped by target.
#[derive(Clone, Debug, Default)]
pub struct Transfer {
    /// The receiving nodes, each once, in increasing handle order.
    target: Vec<u32>,
    /// Entries of `target[k]`: `start[k]..start[k + 1]`.
    start: Vec<usize>,
    /// Source node of each entry (a cluster or a root).
    src: Vec<u32>,
    /// The entry's vector: the factor per unit radiosity of the source along the
    /// receiving normal.
    w: Vec<DVec3>,
}

/// Where the light of a point source at `at` (projected area times visible fraction
/// `base`) lands below the receiving node `r`: `(target, vector)` pairs, the vector being
/// the target's factor per unit source radiosity along a receiving normal.
fn land(
    t: &Tree,
    e: &Elements,
    visible: &[f64],
    r: u32,
    at: DVec3,
    base: f64,
    out: &mut Vec<(u32, DVec3)>,
) {
    let mut stack = vec![r];
    while let Some(q) = stack.pop() {
        if !is_cluster(q) {
            let k = q as usize;
            let a = e.area[k];
            if a <= 0.0 || visible[k] <= 0.0 {
                continue;
            }
            let omega = solid_angle(at, e.corners(q), e.normal[k]);
            if omega > 0.0 {
                out.push((q, e.normal[k] * (base * omega / (PI * a))));
            }
            continue;
        }
        let c = (q & !CLUSTER) as usize;
        if t.area[c] <= 0.0 {
            continue;
        }
        let (centre, radius) = t.sphere[c];
        let to = at - centre;
        let d = to.length();
        let split = || t.children[c];
        if d <= radius * (1.0 + 1e-9) || t.cone[c].1 <= -1.0 {
            stack.extend(split());
            continue;
        }
        let u = to / d;
        let alpha = (radius / d).min(1.0).asin();
        let (axis, cos_half) = t.cone[c];
        let theta = cos_half.clamp(-1.0, 1.0).acos();
        let phi = axis.dot(u).clamp(-1.0, 1.0).acos();
        if phi + theta + alpha < FRAC_PI_2 {
            out.push((q, u * (base / (PI * d * d))));
        } else if phi - theta - alpha > FRAC_PI_2 {
            continue;
        } else {
            stack.extend(split());
        }
    }
}

impl Transfer {
    /// The entries of every cluster link of `links`, their sources cut into pieces as
    /// [`Refiner::pieces`] does with `descend` (`f` should take no near-field points: they
    /// are not used here).
    pub fn build(f: &Refiner, links: &Links, descend: f64) -> Transfer {
        let t = f.tree;
        let receivers: Vec<u32> = (0..t.len() as u32)
            .map(|c| c | CLUSTER)
            .chain(0..links.element.len() as u32)
            .filter(|&n| !links.into_node(n).is_empty())
            .collect();
        let mut all: Vec<(u32, u32, DVec3)> = receivers
            .par_iter()
            .flat_map_iter(|&r| {
                let mut out = Vec::new();
                let mut landed = Vec::new();
                for l in links.into_node(r) {
                    for p in f.pieces(r, l, descend) {
                        if p.p <= 0.0 || l.v <= 0.0 {
                            continue;
                        }
                        landed.clear();
                        land(t, f.elements, f.visible, r, p.at, l.v * p.p, &mut landed);
                        out.extend(landed.iter().map(|&(q, w)| (q, p.node, w)));
                    }
                }
                out
            })
            .collect();
        // A stable sort: the order within a target, and so the sums' bits, do not depend
        // on the thread count.
        all.par_sort_by_key(|x| x.0);
        let mut tr = Transfer {
            target: Vec::new(),
            start: Vec::new(),
            src: Vec::with_capacity(all.len()),
            w: Vec::with_capacity(all.len()),
        };
        for (k, &(q, s, w)) in all.iter().enumerate() {
            if tr.target.last() != Some(&q) {
                tr.target.push(q);
                tr.start.push(k);
            }
            tr.src.push(s);
            tr.w.push(w);
        }
        tr.start.push(all.len());
        tr
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.src.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.src.is_empty()
    }

    /// Irradiance per element from today's radiosities (`state.b` for roots,
    /// `state.clusters` for clusters): for a root, the vectors of the nodes on its chain
    /// of clusters, summed down the tree, read along its normal; for an element below a
    /// root, the vectors landed on it (what its ancestors receive is pushed down by the
    /// solve).
    pub fn gather(&self, t: &Tree, e: &Elements, state: &State) -> Vec<[f64; 3]> {
        let at: Vec<[DVec3; 3]> = (0..self.target.len())
            .into_par_iter()
            .map(|k| {
                let mut v = [DVec3::ZERO; 3];
                for i in self.start[k]..self.start[k + 1] {
                    let b = state.source(self.src[i]);
                    for c in 0..3 {
                        v[c] += self.w[i] * b[c];
                    }
                }
                v
            })
            .collect();
        let mut down = vec![[DVec3::ZERO; 3]; t.len()];
        let mut own = vec![[DVec3::ZERO; 3]; e.len()];
        for (&q, v) in self.target.iter().zip(at) {
            if is_cluster(q) {
                down[(q & !CLUSTER) as usize] = v;
            } else {
                own[q as usize] = v;
            }
        }
        // Parents come before their children in the tree's arrays.
        for c in 0..t.len() {
            let p = t.parent[c];
            if p != NONE {
                let above = down[p as usize];
                for k in 0..3 {
                    down[c][k] += above[k];
                }
            }
        }
        (0..e.len())
            .into_par_iter()
            .map(|r| {
                let mut v = own[r];
                let p = t.root_parent.get(r).copied().unwrap_or(NONE);
                if r < e.roots && p != NONE {
                    for k in 0..3 {
                        v[k] += down[p as usize][k];
                    }
                }
                let n = e.normal[r];
                std::array::from_fn(|k| n.dot(v[k]).max(0.0))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 5 x 5 floor of unit squares and a 5 x 5 wall facing +x.
    fn corner() -> Elements {
        super::super::clusters::tests::grid(5)
    }

    /// Per root: what the landed vectors bring it (summed over the nodes above it), and
    /// the largest bound of the far-field kernel's error over those nodes.
    fn per_root(t: &Tree, e: &Elements, landed: &[(u32, DVec3)], at: DVec3) -> Vec<(f64, f64)> {
        let mut out = vec![(0.0, 0.0); e.roots];
        for &(q, w) in landed {
            let roots: Vec<u32> = if is_cluster(q) {
                t.roots_of(q).to_vec()
            } else {
                vec![q]
            };
            // The kernel cos/(π r²) over the node's sphere against its value at the
            // centre: 1/r² within 2ds/(d - s)², the cosine within asin(s/d).
            let (d, s) = if is_cluster(q) {
                let (c, r) = t.sphere[(q & !CLUSTER) as usize];
                (at.distance(c), r)
            } else {
                (1.0, 0.0)
            };
            let bound = if s > 0.0 {
                ((s / d).asin() + 2.0 * d * s / (d - s).powi(2)) / (PI * (d - s).powi(2))
            } else {
                0.0
            };
            for m in roots {
                let k = m as usize;
                out[k].0 += e.normal[k].dot(w);
                out[k].1 = f64::max(out[k].1, bound);
            }
        }
        out
    }

    fn exact(e: &Elements, m: u32, at: DVec3) -> f64 {
        let k = m as usize;
        solid_angle(at, e.corners(m), e.normal[k]) / (PI * e.area[k])
    }

    #[test]
    fn a_far_source_lands_on_clusters_and_agrees_with_each_roots_solid_angle() {
        let e = corner();
        let vis = e.visible_areas();
        let t = Tree::build(&e, &vis, &vec![0.5; e.roots]);
        let at = DVec3::new(40.0, 2.5, 40.0);
        let mut landed = Vec::new();
        land(&t, &e, &vis, CLUSTER, at, 1.0, &mut landed);
        // Far away and in front of every root: a few cluster targets, not 50 roots.
        assert!(landed.len() < 10, "{} targets", landed.len());
        assert!(landed.iter().any(|&(q, _)| is_cluster(q)));
        for (m, (got, bound)) in per_root(&t, &e, &landed, at).into_iter().enumerate() {
            let want = exact(&e, m as u32, at);
            assert!(want > 0.0);
            assert!(
                (got - want).abs() <= bound + 1e-12 * want,
                "root {m}: {got} vs {want} (bound {bound})"
            );
            // The bound is not vacuous here.
            assert!(bound < want, "root {m}: bound {bound} vs {want}");
        }
    }

    #[test]
    fn a_source_behind_the_wall_lights_only_the_floor() {
        let e = corner();
        let vis = e.visible_areas();
        let t = Tree::build(&e, &vis, &vec![0.5; e.roots]);
        let at = DVec3::new(-6.0, 2.5, 8.0);
        let mut landed = Vec::new();
        land(&t, &e, &vis, CLUSTER, at, 1.0, &mut landed);
        for (m, (got, bound)) in per_root(&t, &e, &landed, at).into_iter().enumerate() {
            let want = exact(&e, m as u32, at);
            if e.normal[m] == DVec3::X {
                assert_eq!(want, 0.0);
                assert_eq!(got, 0.0, "wall root {m} lit from behind");
            } else {
                assert!(want > 0.0 && got > 0.0, "floor root {m}: {got} vs {want}");
                assert!(
                    (got - want).abs() <= bound + 1e-12 * want,
                    "root {m}: {got} vs {want} (bound {bound})"
                );
            }
        }
    }
}
