//! The element tree: every root patch and the pieces it is split into, in flat arrays.
//!
//! An element is a handle (an index, `u32`) into [`Elements`], the pbrt-v4 layout the
//! patch set already follows: no element owns geometry. Roots are the patches of the
//! [`PatchSet`] the hierarchy was built on, numbered as there (element `k < roots` is
//! patch `k`). A split makes four children, numbered consecutively from
//! [`Elements::first_child`]: a quad into four quads, a triangle into four triangles
//! ([`Piece::split`], edge midpoints computed from the edge's end points, so neighbours
//! that share an edge split it at the same point bit for bit, which the crack-free output
//! relies on). Children are always made in the order splits are requested, one thread,
//! so the same scene and settings give the same numbering on any number of threads.
//!
//! Geometry is `f64` throughout (corners, area, normal, centroid); only ray ends are
//! converted to `f32`, by the visibility module.

use glam::DVec3;

use crate::formfactor::exact::Piece;
use crate::mesh::PatchSet;

/// Marks "no element" in the parent and child arrays.
pub const NONE: u32 = u32::MAX;

/// The element tree, as flat arrays indexed by element.
#[derive(Clone, Debug, Default)]
pub struct Elements {
    /// Geometry: a bilinear quad or a triangle, corners counter-clockwise from the front.
    pub piece: Vec<Piece>,
    /// Area.
    pub area: Vec<f64>,
    /// Unit normal (of the root patch: elements of one patch are coplanar).
    pub normal: Vec<DVec3>,
    /// Centroid (image of the parameter centre).
    pub centre: Vec<DVec3>,
    /// The root patch the element belongs to.
    pub root: Vec<u32>,
    /// Parent element, [`NONE`] for roots.
    pub parent: Vec<u32>,
    /// First of the four children, [`NONE`] for leaves.
    pub first_child: Vec<u32>,
    /// Depth below the root (roots are 0).
    pub level: Vec<u8>,
    /// A leaf that no ray can reach: its whole surface lies inside a closed solid, such as
    /// floor under a box standing on it. Buried leaves do not count as surface: they are
    /// left out of visible areas, averages and power sums.
    pub buried: Vec<bool>,
    /// A leaf that is not buried but may have a part inside a closed solid: crossed by a
    /// contact line, or some of its buried-test rays met the back of a face. Its
    /// ancestors' visibility (sampled on their unburied leaves) says nothing of it, so it
    /// traces its own.
    pub partly: Vec<bool>,
    /// The fraction of the element's area outside every closed solid: 1 for a leaf in the
    /// open, 0 for a buried one, measured for a partly buried one ([`super::refine::bury`]).
    /// A leaf's *visible area* is this times its area.
    pub exposed: Vec<f64>,
    /// The standard error of `exposed` (0 where it is not measured).
    pub exposed_se: Vec<f64>,
    /// Number of roots (elements `0..roots`).
    pub roots: usize,
}

impl Elements {
    /// The roots: one element per patch of `patches`, with corners welded so that patches
    /// meeting at a point share it bit for bit (see [`weld`]).
    pub fn from_patches(patches: &PatchSet) -> Elements {
        let n = patches.len();
        let mut corners: Vec<DVec3> = Vec::new();
        let mut count = Vec::with_capacity(n);
        for i in 0..n {
            let (c, k) = patches.corner_points(i);
            corners.extend(c[..k].iter().copied());
            count.push(k);
        }
        let welded = weld(&corners, 1e-9 * patches.diagonal);
        let mut e = Elements::default();
        let mut at = 0;
        for (i, &k) in count.iter().enumerate() {
            let c = &welded[at..at + k];
            at += k;
            let piece = if k == 4 {
                Piece::Quad([c[0], c[1], c[2], c[3]])
            } else {
                Piece::Tri([c[0], c[1], c[2]])
            };
            e.add_root(piece, patches.normal[i].normalize());
        }
        e
    }

    /// Adds a root element (before any split); returns its handle.
    pub fn add_root(&mut self, piece: Piece, normal: DVec3) -> u32 {
        assert_eq!(self.roots, self.len(), "roots come before any split");
        let id = self.push(piece, normal, self.roots as u32, NONE, 0);
        self.roots += 1;
        id
    }

    fn push(&mut self, piece: Piece, normal: DVec3, root: u32, parent: u32, level: u8) -> u32 {
        let id = self.piece.len() as u32;
        self.area.push(piece.area());
        self.centre.push(piece.at(0.5, 0.5, 0.5, 0.5).0);
        self.piece.push(piece);
        self.normal.push(normal);
        self.root.push(root);
        self.parent.push(parent);
        self.first_child.push(NONE);
        self.level.push(level);
        self.buried.push(false);
        self.partly.push(false);
        self.exposed.push(1.0);
        self.exposed_se.push(0.0);
        id
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.piece.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.piece.is_empty()
    }

    /// True when `e` has no children.
    pub fn is_leaf(&self, e: u32) -> bool {
        self.first_child[e as usize] == NONE
    }

    /// The four children of `e` (which must have been split).
    pub fn children(&self, e: u32) -> [u32; 4] {
        let c = self.first_child[e as usize];
        debug_assert_ne!(c, NONE);
        [c, c + 1, c + 2, c + 3]
    }

    /// Splits `e` into four children (once: a second call returns the same children).
    pub fn split(&mut self, e: u32) -> [u32; 4] {
        if self.is_leaf(e) {
            let ei = e as usize;
            let (n, root, level) = (self.normal[ei], self.root[ei], self.level[ei]);
            let first = self.len() as u32;
            for q in self.piece[ei].split() {
                self.push(q, n, root, e, level.saturating_add(1));
            }
            self.first_child[ei] = first;
        }
        self.children(e)
    }

    /// Leaves, in element order.
    pub fn leaves(&self) -> impl Iterator<Item = u32> + '_ {
        (0..self.len() as u32).filter(move |&e| self.is_leaf(e))
    }

    /// Corners of `e`.
    pub fn corners(&self, e: u32) -> &[DVec3] {
        self.piece[e as usize].corners()
    }

    /// Visible area of leaf `l`: its area outside closed solids (0 when buried).
    pub fn visible_area(&self, l: u32) -> f64 {
        let li = l as usize;
        if self.buried[li] {
            0.0
        } else {
            self.area[li] * self.exposed[li]
        }
    }

    /// Visible area of every element: a leaf's [`Elements::visible_area`], a parent's the
    /// sum of its children's. Children always have larger indices than their parent, so
    /// one backward pass suffices.
    pub fn visible_areas(&self) -> Vec<f64> {
        let mut vis = vec![0.0; self.len()];
        for e in (0..self.len()).rev() {
            vis[e] = if self.first_child[e] == NONE {
                self.visible_area(e as u32)
            } else {
                let c = self.first_child[e] as usize;
                vis[c..c + 4].iter().sum()
            };
        }
        vis
    }

    /// The leaf below `e` that holds the point of `e` at parameters `(u, v)`, and the
    /// point's parameters in that leaf ([`Elements::child_at`], down to a leaf).
    pub fn locate(&self, mut e: u32, mut u: f64, mut v: f64) -> (u32, f64, f64) {
        while !self.is_leaf(e) {
            (e, u, v) = self.child_at(e, u, v);
        }
        (e, u, v)
    }

    /// The child of the split element `e` that holds the point of `e` at parameters
    /// `(u, v)`, and the point's parameters in that child. Splits are in parameter space: a
    /// quad's child `k` is its quarter `(u, v) ∈ [0, ½]² , [½, 1] × [0, ½], [½, 1]², [0, ½]
    /// × [½, 1]`; a triangle's (collapsed map, barycentrics `λ = (1 - u, u (1 - v), u v)`)
    /// is the corner triangle at `c_k` where `λ_k ≥ ½`, else the middle one.
    pub fn child_at(&self, e: u32, u: f64, v: f64) -> (u32, f64, f64) {
        let c = self.first_child[e as usize];
        debug_assert_ne!(c, NONE);
        match self.piece[e as usize] {
            crate::formfactor::exact::Piece::Quad(_) => {
                let (hu, hv) = (u >= 0.5, v >= 0.5);
                let k = match (hu, hv) {
                    (false, false) => 0,
                    (true, false) => 1,
                    (true, true) => 2,
                    (false, true) => 3,
                };
                let u = if hu { 2.0 * u - 1.0 } else { 2.0 * u };
                let v = if hv { 2.0 * v - 1.0 } else { 2.0 * v };
                (c + k, u, v)
            }
            crate::formfactor::exact::Piece::Tri(_) => {
                let l = [1.0 - u, u * (1.0 - v), u * v];
                // The child's barycentrics, by the corner maps of `Piece::split`.
                let (k, m) = if l[0] >= 0.5 {
                    (0, [1.0 - 2.0 * (l[1] + l[2]), 2.0 * l[1], 2.0 * l[2]])
                } else if l[1] >= 0.5 {
                    (1, [2.0 * l[0], 1.0 - 2.0 * (l[0] + l[2]), 2.0 * l[2]])
                } else if l[2] >= 0.5 {
                    (2, [2.0 * l[0], 2.0 * l[1], 1.0 - 2.0 * (l[0] + l[1])])
                } else {
                    (3, [1.0 - 2.0 * l[0], 1.0 - 2.0 * l[1], 1.0 - 2.0 * l[2]])
                };
                let u = (1.0 - m[0]).clamp(0.0, 1.0);
                let v = if u > 0.0 {
                    (m[2] / u).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                (c + k, u, v)
            }
        }
    }

    /// The point of `e` at parameters `(u, v)` in the unit square, and the area Jacobian.
    pub fn point(&self, e: u32, u: f64, v: f64) -> (DVec3, f64) {
        self.piece[e as usize].at(u, 1.0 - u, v, 1.0 - v)
    }
}

/// Snaps points closer than `tol` to one representative (the first of them), so that
/// corners shared by neighbouring patches, computed separately, become bit-identical. A
/// hash grid of cell `tol` finds the candidates among the 27 cells around each point.
pub fn weld(points: &[DVec3], tol: f64) -> Vec<DVec3> {
    use std::collections::HashMap;
    if !(tol > 0.0 && tol.is_finite()) {
        return points.to_vec();
    }
    let cell = |p: DVec3| -> [i64; 3] {
        let q = (p / tol).floor();
        [q.x as i64, q.y as i64, q.z as i64]
    };
    let mut grid: HashMap<[i64; 3], Vec<DVec3>> = HashMap::new();
    let mut out = Vec::with_capacity(points.len());
    for &p in points {
        let c = cell(p);
        let mut found = None;
        'search: for dz in -1..=1i64 {
            for dy in -1..=1i64 {
                for dx in -1..=1i64 {
                    if let Some(list) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        if let Some(&q) = list.iter().find(|q| q.distance(p) <= tol) {
                            found = Some(q);
                            break 'search;
                        }
                    }
                }
            }
        }
        out.push(found.unwrap_or_else(|| {
            grid.entry(c).or_default().push(p);
            p
        }));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_quad() -> Piece {
        Piece::Quad([
            DVec3::ZERO,
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(2.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ])
    }

    /// Two roots: [`unit_quad`] and a skew triangle.
    fn quad_and_triangle() -> Elements {
        let mut e = Elements::default();
        e.add_root(unit_quad(), DVec3::Z);
        let tri = Piece::Tri([DVec3::ZERO, DVec3::X, DVec3::new(0.3, 1.7, 0.2)]);
        e.add_root(tri, DVec3::Z);
        e
    }

    #[test]
    fn children_areas_sum_to_the_parent() {
        let mut e = quad_and_triangle();
        for root in [0u32, 1] {
            let kids = e.split(root);
            // A second split returns the same children.
            assert_eq!(e.split(root), kids);
            let s: f64 = kids.iter().map(|&k| e.area[k as usize]).sum();
            let a = e.area[root as usize];
            assert!((s - a).abs() <= 1e-14 * a, "{s} vs {a}");
            // And one level further down.
            let g = e.split(kids[2]);
            let s2: f64 = g.iter().map(|&k| e.area[k as usize]).sum();
            assert!((s2 - e.area[kids[2] as usize]).abs() <= 1e-14 * a);
            assert!(kids.iter().all(|&k| e.parent[k as usize] == root));
        }
        let vis = e.visible_areas();
        assert!((vis[0] - 2.0).abs() < 1e-14);
    }

    #[test]
    fn neighbours_split_shared_edges_at_the_same_point() {
        // Two quads sharing the edge from (2,0,0) to (2,1,0), given in opposite directions.
        let a = unit_quad();
        let b = Piece::Quad([
            DVec3::new(2.0, 0.0, 0.0),
            DVec3::new(3.1, 0.0, 0.0),
            DVec3::new(3.3, 1.0, 0.0),
            DVec3::new(2.0, 1.0, 0.0),
        ]);
        let ka = a.split();
        let kb = b.split();
        let mid_a = ka[1].corners()[2]; // m12 of a
        let mid_b = kb[0].corners()[3]; // m30 of b
        assert_eq!(mid_a.to_array(), mid_b.to_array());
    }

    #[test]
    fn locate_finds_the_leaf_holding_a_point() {
        let mut e = quad_and_triangle();
        for root in [0u32, 1] {
            let kids = e.split(root);
            e.split(kids[1]);
            e.split(kids[3]);
        }
        let mut rng = crate::sampling::Pcg32::keyed(7, 1, 2, 3);
        for root in [0u32, 1] {
            for _ in 0..2000 {
                let (u, v) = (rng.next_f64(), rng.next_f64());
                let x = e.point(root, u, v).0;
                let (leaf, lu, lv) = e.locate(root, u, v);
                assert!(e.is_leaf(leaf));
                let mut a = leaf;
                while e.parent[a as usize] != NONE {
                    a = e.parent[a as usize];
                }
                assert_eq!(a, root);
                let y = e.point(leaf, lu, lv).0;
                assert!(x.distance(y) < 1e-12, "{x} vs {y} in leaf {leaf}");
            }
        }
    }

    #[test]
    fn weld_snaps_near_points_only() {
        let p = [
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(1.0 + 1e-12, 2.0, 3.0),
            DVec3::new(1.1, 2.0, 3.0),
        ];
        let w = weld(&p, 1e-9);
        assert_eq!(w[1], p[0]);
        assert_eq!(w[2], p[2]);
    }
}
