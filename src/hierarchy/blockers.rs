//! Occlusion proofs: which root patches may block a segment between two elements, and a
//! test that none of them can, in `f64` and without a ray.
//!
//! A *hull face* is a patch whose plane has the whole scene on or in front of it (a wall of
//! a convex room): a segment between two points of the scene never passes behind it, so it
//! blocks nothing. The other patches are the *candidates*. For a pair of elements `a`, `b`
//! a candidate `k` is harmless when
//! - its bounding box misses the pair's (every segment lies in the pair's box, the convex
//!   hull of both), or
//! - it lies on or behind the plane of `a` or of `b` (a segment leaves `a` forwards, toward
//!   `b`, and stays in front of both planes), or
//! - both elements lie on one side of its plane (a segment between them never crosses it).
//!
//! The pair is *unoccluded* when every candidate is harmless: the semi-analytic
//! estimator's hull and plane tests ([`crate::formfactor::semi`]), here on elements. The
//! candidates sit in a bounding-volume tree of their boxes (median split on the longest
//! axis, pbrt-v4's "equal counts" rule, Pharr, Jakob and Humphreys, *Physically Based
//! Rendering*, 4th ed., sec. 7.3), so a proof reads only the candidates whose box meets the
//! pair's: a room holding a 2048-face sphere proves a wall leaf's view of a sphere face in
//! a few box tests (every other face of a convex object is behind the face's plane), where
//! a scan of all candidates made the proof too dear to attempt.

use glam::DVec3;

use super::element::Elements;

/// Candidates per leaf of the tree, at most.
const LEAF: usize = 4;

/// A node of the candidates' tree: bounds, and either a leaf's range of
/// [`Blockers::order`] (`count > 0`) or the index of its second child (the first follows it).
#[derive(Clone, Copy, Debug)]
struct Node {
    lo: DVec3,
    hi: DVec3,
    start: u32,
    count: u32,
}

/// The patches that may block a segment between two elements: every root patch that is
/// not a hull face, with its bounding box, plane and corners, in a tree of their boxes.
pub struct Blockers {
    boxes: Vec<(DVec3, DVec3)>,
    planes: Vec<(DVec3, DVec3)>,
    corners: Vec<Vec<DVec3>>,
    /// The non-hull patches' tree.
    tree: BoxTree,
    /// Scale-relative tolerance of the plane tests.
    tol: f64,
}

/// A bounding-volume tree over some of a list of boxes (median split on the longest axis,
/// at most `LEAF` boxes a leaf): the candidate blockers' tree, and the contact search's
/// ([`super::refine::contacts`]), which without it compared every pair of roots (61% of
/// the first two minutes of a 245,760-face bake).
#[derive(Clone, Debug, Default)]
pub struct BoxTree {
    /// The boxes' indices, in the tree's leaf order.
    order: Vec<u32>,
    nodes: Vec<Node>,
}

impl BoxTree {
    /// The tree over `items`, indices into `boxes`.
    pub fn new(boxes: &[(DVec3, DVec3)], mut items: Vec<u32>) -> BoxTree {
        let mut nodes = Vec::new();
        if !items.is_empty() {
            build(boxes, &mut items, 0, &mut nodes);
        }
        BoxTree {
            order: items,
            nodes,
        }
    }

    /// Appends to `out` the items whose box (in `boxes`, the tree's) meets `[lo, hi]`, in
    /// increasing order.
    pub fn overlapping(&self, boxes: &[(DVec3, DVec3)], lo: DVec3, hi: DVec3, out: &mut Vec<u32>) {
        let from = out.len();
        let misses = |l: DVec3, h: DVec3| l.cmpgt(hi).any() || h.cmplt(lo).any();
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let Some(&node) = self.nodes.get(i) else {
                break;
            };
            if misses(node.lo, node.hi) {
                continue;
            }
            if node.count == 0 {
                stack.push(node.start as usize);
                stack.push(i + 1);
                continue;
            }
            let (s, c) = (node.start as usize, node.count as usize);
            out.extend(self.order[s..s + c].iter().copied().filter(|&k| {
                let (lk, hk) = boxes[k as usize];
                !misses(lk, hk)
            }));
        }
        out[from..].sort_unstable();
    }
}

impl Blockers {
    /// The candidate blockers of the roots of `e`, in a scene of diagonal `diagonal`.
    pub fn new(e: &Elements, diagonal: f64) -> Blockers {
        let corners = (0..e.roots as u32).map(|k| e.corners(k).to_vec()).collect();
        let planes = (0..e.roots).map(|k| (e.normal[k], e.centre[k])).collect();
        Blockers::from_parts(corners, planes, 1e-9 * diagonal)
    }

    /// The candidate blockers among patches given by their corners and planes (unit
    /// normal, a point), with the plane tests' tolerance `tol`.
    pub fn from_parts(corners: Vec<Vec<DVec3>>, planes: Vec<(DVec3, DVec3)>, tol: f64) -> Blockers {
        let n = corners.len();
        let boxes: Vec<(DVec3, DVec3)> = corners.iter().map(|c| bounds(c)).collect();
        let all: Vec<DVec3> = corners.iter().flatten().copied().collect();
        let (lo, hi) = boxes
            .iter()
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(a, b), &(l, h)| {
                (a.min(l), b.max(h))
            });
        let order: Vec<u32> = (0..n)
            .filter(|&k| {
                let (nk, ck) = planes[k];
                // The box's lowest point along n bounds every corner; else scan.
                let bound = (nk * lo).min(nk * hi).element_sum() - nk.dot(ck);
                let hull = bound >= -tol || all.iter().all(|&q| nk.dot(q - ck) >= -tol);
                !hull
            })
            .map(|k| k as u32)
            .collect();
        let tree = BoxTree::new(&boxes, order);
        Blockers {
            boxes,
            planes,
            corners,
            tree,
            tol,
        }
    }

    /// Number of patches that may block something.
    pub fn len(&self) -> usize {
        self.tree.order.len()
    }

    /// True when nothing can block anything (a convex room).
    pub fn is_empty(&self) -> bool {
        self.tree.order.is_empty()
    }

    /// True when no patch can block any segment between points of `a` and `b` (roots
    /// `ra`, `rb`), by the tests of the module docs.
    pub fn unoccluded(&self, a: &[DVec3], ra: u32, b: &[DVec3], rb: u32) -> bool {
        self.unoccluded_within(a, ra, b, rb, usize::MAX) == Some(true)
    }

    /// [`Blockers::unoccluded`] within `budget` steps (a node of the tree whose box meets
    /// the pair's, or a candidate given the plane tests): `None` when that does not settle
    /// it. A pair
    /// seen across a crowd of small faces costs more to prove than a few rays cost to
    /// trace.
    pub fn unoccluded_within(
        &self,
        a: &[DVec3],
        ra: u32,
        b: &[DVec3],
        rb: u32,
        budget: usize,
    ) -> Option<bool> {
        if self.tree.order.is_empty() {
            return Some(true);
        }
        let mut left = budget;
        let (lo, hi) = self.pair_box(a, b);
        let harmless = |k: u32| self.harmless(k, a, ra, b, rb);
        let misses = |l: DVec3, h: DVec3| l.cmpgt(hi).any() || h.cmplt(lo).any();
        let mut stack = vec![0usize];
        while let Some(i) = stack.pop() {
            let node = self.tree.nodes[i];
            if misses(node.lo, node.hi) {
                continue;
            }
            if left == 0 {
                return None;
            }
            left -= 1;
            if node.count == 0 {
                stack.push(node.start as usize);
                stack.push(i + 1);
                continue;
            }
            let (s, c) = (node.start as usize, node.count as usize);
            for &k in &self.tree.order[s..s + c] {
                let (lk, hk) = self.boxes[k as usize];
                if misses(lk, hk) {
                    continue;
                }
                if left == 0 {
                    return None;
                }
                left -= 1;
                if !harmless(k) {
                    return Some(false);
                }
            }
        }
        Some(true)
    }
}

impl Blockers {
    /// The pair's box, grown by the tolerance.
    fn pair_box(&self, a: &[DVec3], b: &[DVec3]) -> (DVec3, DVec3) {
        let (la, ha) = bounds(a);
        let (lb, hb) = bounds(b);
        (la.min(lb) - self.tol, ha.max(hb) + self.tol)
    }

    /// True when candidate `k` blocks no segment between `a` and `b` by its planes (the
    /// second and third tests of the module docs).
    fn harmless(&self, k: u32, a: &[DVec3], ra: u32, b: &[DVec3], rb: u32) -> bool {
        if k == ra || k == rb {
            return true;
        }
        let tol = self.tol;
        let (pa, pb) = (self.planes[ra as usize], self.planes[rb as usize]);
        let ck = &self.corners[k as usize];
        if range(pa, ck).1 <= tol || range(pb, ck).1 <= tol {
            return true;
        }
        let pk = self.planes[k as usize];
        let (ra_, rb_) = (range(pk, a), range(pk, b));
        (ra_.0 >= -tol && rb_.0 >= -tol) || (ra_.1 <= tol && rb_.1 <= tol)
    }
}

/// Builds the subtree over `items` (a slice of the leaf order starting at `offset`) into
/// `nodes`, its root first; returns nothing: the root's index is the length of `nodes` on
/// entry.
fn build(boxes: &[(DVec3, DVec3)], items: &mut [u32], offset: usize, nodes: &mut Vec<Node>) {
    let (lo, hi) = items
        .iter()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(l, h), &k| {
            let (bl, bh) = boxes[k as usize];
            (l.min(bl), h.max(bh))
        });
    let me = nodes.len();
    nodes.push(Node {
        lo,
        hi,
        start: offset as u32,
        count: items.len() as u32,
    });
    if items.len() <= LEAF {
        return;
    }
    let centre = |k: u32| {
        let (l, h) = boxes[k as usize];
        l + h
    };
    let ext = hi - lo;
    let axis = if ext.x >= ext.y && ext.x >= ext.z {
        0
    } else if ext.y >= ext.z {
        1
    } else {
        2
    };
    let mid = items.len() / 2;
    // Ties broken by index, so that the tree does not depend on the sort's internals.
    items.select_nth_unstable_by(mid, |&p, &q| {
        centre(p)[axis].total_cmp(&centre(q)[axis]).then(p.cmp(&q))
    });
    let (left, right) = items.split_at_mut(mid);
    build(boxes, left, offset, nodes);
    let second = nodes.len();
    build(boxes, right, offset + mid, nodes);
    nodes[me].start = second as u32;
    nodes[me].count = 0;
}

/// Axis-aligned bounds of some points.
pub fn bounds(p: &[DVec3]) -> (DVec3, DVec3) {
    p.iter()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &q| {
            (lo.min(q), hi.max(q))
        })
}

/// Signed distances of `pts` from the plane `(normal, point)`, as (min, max).
pub fn range(plane: (DVec3, DVec3), pts: &[DVec3]) -> (f64, f64) {
    let (n, c) = plane;
    pts.iter()
        .map(|&q| n.dot(q - c))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), d| {
            (lo.min(d), hi.max(d))
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Pcg32;

    /// The proof by a scan of every candidate, as it was before the tree.
    fn by_scan(bl: &Blockers, a: &[DVec3], ra: u32, b: &[DVec3], rb: u32) -> bool {
        let (lo, hi) = bl.pair_box(a, b);
        bl.tree.order.iter().all(|&k| {
            let (lk, hk) = bl.boxes[k as usize];
            lk.cmpgt(hi).any() || hk.cmplt(lo).any() || bl.harmless(k, a, ra, b, rb)
        })
    }

    /// A unit cube room (six inward walls) holding `n` random triangles of size about
    /// `size`.
    fn room(n: usize, size: f64, seed: u64) -> (Vec<Vec<DVec3>>, Vec<(DVec3, DVec3)>) {
        let mut rng = Pcg32::keyed(seed, 1, 0, 0);
        let mut u = || rng.next_f64();
        let mut corners = Vec::new();
        for axis in 0..3 {
            for side in [0.0, 1.0] {
                let q = |a: f64, b: f64| {
                    let mut p = [0.0; 3];
                    p[axis] = side;
                    p[(axis + 1) % 3] = a;
                    p[(axis + 2) % 3] = b;
                    DVec3::from(p)
                };
                corners.push(vec![q(0.0, 0.0), q(1.0, 0.0), q(1.0, 1.0), q(0.0, 1.0)]);
            }
        }
        for _ in 0..n {
            let c = DVec3::new(0.1 + 0.8 * u(), 0.1 + 0.8 * u(), 0.1 + 0.8 * u());
            let mut d = || DVec3::new(u() - 0.5, u() - 0.5, u() - 0.5) * size;
            corners.push(vec![c + d(), c + d(), c + d()]);
        }
        let planes = corners
            .iter()
            .map(|c| {
                let mut nrm = (c[1] - c[0]).cross(c[2] - c[0]).normalize();
                let centre = (c[0] + c[1] + c[2]) / 3.0;
                // Walls face the room's centre.
                if c.len() == 4 && nrm.dot(DVec3::splat(0.5) - centre) < 0.0 {
                    nrm = -nrm;
                }
                (nrm, centre)
            })
            .collect();
        (corners, planes)
    }

    #[test]
    fn the_tree_proves_exactly_what_a_scan_proves() {
        for (n, size, seed) in [(0, 0.0, 1), (3, 0.2, 2), (40, 0.1, 3), (600, 0.03, 4)] {
            let (corners, planes) = room(n, size, seed);
            let bl = Blockers::from_parts(corners.clone(), planes, 1e-9);
            // The walls of a convex room block nothing; every triangle may.
            assert_eq!(bl.len(), n, "{n} triangles");
            let m = corners.len() as u32;
            let mut rng = Pcg32::keyed(seed, 7, 0, 0);
            let (mut proved, mut pairs) = (0, 0);
            for _ in 0..4000 {
                let (ra, rb) = (rng.next_u32() % m, rng.next_u32() % m);
                if ra == rb {
                    continue;
                }
                let (a, b) = (&corners[ra as usize], &corners[rb as usize]);
                let tree = bl.unoccluded(a, ra, b, rb);
                assert_eq!(tree, by_scan(&bl, a, ra, b, rb), "{n}: pair ({ra}, {rb})");
                // A budget may leave it open, never give another answer.
                for budget in [0, 1, 8] {
                    let within = bl.unoccluded_within(a, ra, b, rb, budget);
                    assert!(within.is_none() || within == Some(tree), "{n}: {within:?}");
                }
                pairs += 1;
                proved += usize::from(tree);
            }
            // Both answers occur, so the comparison means something.
            if n == 0 {
                assert_eq!(proved, pairs);
            } else if n >= 40 {
                assert!(
                    proved > 0 && proved < pairs,
                    "{n}: {proved} of {pairs} proved"
                );
            }
        }
    }

    #[test]
    fn range_and_bounds() {
        let pts = [DVec3::new(0.0, 0.0, 1.0), DVec3::new(1.0, 2.0, -1.0)];
        assert_eq!(range((DVec3::Z, DVec3::ZERO), &pts), (-1.0, 1.0));
        let (lo, hi) = bounds(&pts);
        assert_eq!(lo, DVec3::new(0.0, 0.0, -1.0));
        assert_eq!(hi, DVec3::new(1.0, 2.0, 1.0));
    }
}
