//! Clusters: a tree of groups of root patches above the element trees, and links between
//! groups, so that a scene of many small faces does not start with a link between every
//! pair of them (Smits, Arvo and Greenberg, "A clustering algorithm for radiosity in
//! complex environments", SIGGRAPH 1994; Sillion, "A unified hierarchical algorithm for
//! global illumination with scattering volumes and object clusters", IEEE TVCG 1995).
//!
//! **The tree.** A binary tree built top-down over the roots: each cluster's roots are cut
//! in two at the median of their centroids along the longest axis of the centroids' box
//! (a spatial median split), down to single roots, which are the tree's leaves. A
//! cluster keeps its bounding box and sphere, its visible area, the largest reflectance
//! of its roots, and a cone holding its normals (axis and half-angle, Sillion's oriented
//! clusters; a full cone when the normals spread over more than a hemisphere). A *node* is
//! a cluster (handle with [`CLUSTER`] set) or an element: a root, or, on the receiving
//! side of a link, an element below a root.
//!
//! **Links.** Refinement starts from the self-link of the top cluster. A pair of nodes
//! `R ← S`, one of them a cluster, whose bounding spheres (centres `d` apart, radii
//! summing to `s`) do not overlap carries at most
//!
//! `F_up = min(A_S c_S, P_S(w) + 2 A_S sin(α/2)) c_R / (π (d - s)²)`
//!
//! (every point kernel `cos θ_x cos θ_y / (π r²)` over `S` with `r ≥ d - s`; `c_S`, `c_R`
//! the cone bounds of the cosines, [`max_cos`]; `P_S(w)` the source's projected area
//! toward the receiver's centre, below, and `α = asin(s/d)`). The second term bounds
//! `Σ_j A_j max(0, n_j·u)` for any direction `u` within `α` of `w`, as `max(0, n·u)` is
//! 1-Lipschitz in `u` and `|u - w| ≤ 2 sin(α/2)`: a sphere's projected area is a quarter
//! of its area, so a cluster of whole objects seen from afar is bounded about four times
//! closer than by its area and normal cone (on `room-spheres-80`, 13% fewer cluster
//! links; docs/HIERARCHY.md, *The cluster bound by projected area*). The link is a
//! cluster-to-element transfer: a receiving leaf `l` gathers `f_lS = v F_lS` with `F_lS =
//! (1/A_l) ∫_S F(y → l) dA_y` the unoccluded factor and `v` the visible fraction from `n²`
//! rays between area-sampled points of the two nodes, weighted by the kernel (a transmittance
//! estimate). `F_lS` is estimated without bias ([`piece_factor`]): the point source at
//! the source's centre `c_S`,
//!
//! `P_S(w) Ω_l / (π A_l)`,
//!
//! with `P_S(w) = Σ_j A_j max(0, n_j·w)` the projected area of the source's faces toward
//! the receiver (`w` from the source's centre to the receiver's; Sillion's oriented
//! emission) and `Ω_l` the leaf's solid angle from `c_S`, is a control variate for the
//! exact factors of [`POINTS`] stratified area-sampled points of the source's roots to
//! the leaf's polygon. (The point source alone errs with one sign near the source: it
//! overestimates, as `1/d²` does `1/(d² + a²)` for a facing disc of radius `a`, and the
//! errors of a receiver's many links add up.) Where the settings ask for the transfer to a
//! tolerance ([`Expansion::quadrature`]), a piece whose sampled factor is less accurate is
//! integrated over its roots instead ([`exact_piece`]). Where the leaf's view may differ from the
//! link's `v` by more than its tolerance allows, summed over the links on its chain, it
//! checks its own view of some of those points ([`Sight`], [`Expansion::entries`]). The
//! source radiosity is the visible-area
//! mean over its roots (Smits et al.'s cluster radiosity; each receiving leaf uses its
//! own orientation and position, so irradiance is pushed down by orientation, not
//! isotropically: a cluster's faces that turn away from the source receive nothing).
//! Error bound, as the elements' brightness-weighted error ([`super::refine`]):
//!
//! `ε = ρ_R (B_S ΔF + ΔB_S F_up)`, `ΔF = F_up min(1, (4ds/(d - s)² + 2α)/√K + δ_v)`,
//!
//! where `4ds/(d - s)²` bounds the relative change of `1/r²` over the spheres and `α =
//! asin(s/d)` the change of each cosine (1-Lipschitz in the direction): together they
//! bound the difference of the exact and the point kernel at each of the `K` points, so
//! that `1/√K` of it bounds the standard error of their mean ([`Refiner::noise`]; the
//! whole term without points). `δ_v` is the visibility term: the binomial standard error
//! of an all-free sample, or 1 when the rays disagree (a shadow boundary crosses the
//! pair, as for a partly visible element link). A pair is accepted when `ε ≤ eps` and
//! its relative term `(4ds/(d - s)² + 2α)/√K + δ_v` is at most
//! [`super::Settings::cluster_accuracy`] (by default any: the transfer bound alone
//! decides, as in Smits et al.'s BF refinement); pairs of two elements become element
//! links ([`super::link::evaluate`]); otherwise the node with the larger sphere is split:
//! a cluster into its two children; an element only with
//! [`super::Settings::split_receivers`] (a receiving element larger than its source
//! cluster into its four element children, on demand, to the minimum area; Sillion's
//! links between clusters and elements at any level), else the other node. Splitting
//! only clusters links a large root (a floor under a group of spheres) to every face of
//! the group by element links, and each of its leaves then gathers from every face: at
//! 61,440 sphere faces a floor leaf's chain held 1,590 element links, 83 with receivers
//! split (as at 15,360). A link whose rays were all blocked is refined unless `3/n` of
//! `F_up` is within the share `hide` of the tolerance; then rays of its own (an
//! independent stream) estimate it: it is dropped when they are all blocked too, else
//! taken as a link at their fraction. Dropped on the first rays, a pair whose few open
//! rays they missed (`(1 - v)^n` of the time) would give nothing, and one they found its
//! children's light: on average less than it sends (on `room-spheres-24` at `--error
//! 0.05`, 0.79% of the power unaccounted for, 0.54% with the second rays). A
//! link whose source has no projected area toward the receiver's centre (`P_S(w) = 0`)
//! is dropped only when no root of either side has a corner in front of a root of the
//! other ([`Refiner::facing`]): the faces of mixed clusters (a floor and a ceiling in one
//! slab of a room, seen edge-on from the slab's centre) exchange light in other
//! directions.
//!
//! Links are re-examined each pass with the new radiosities (multigridding), and a link
//! whose error grew past the tolerance is replaced by its children's pairs.

use std::f64::consts::PI;

use glam::DVec3;
use rayon::prelude::*;

use super::element::{Elements, NONE};
use crate::formfactor::exact::{self, point_factor, Receiver};
use crate::formfactor::far::{self, Small};
use crate::sampling::{fraction_se, Pcg32};
use crate::visibility::{SegmentRay, Visibility};
use smallvec::SmallVec;

/// Set in a node handle that names a cluster (its index in the low bits); clear for a root
/// element.
pub const CLUSTER: u32 = 1 << 31;

/// True when node `n` is a cluster.
pub fn is_cluster(n: u32) -> bool {
    n & CLUSTER != 0
}

/// The cluster tree over the roots, in flat arrays indexed by cluster; children come after
/// their parents.
#[derive(Clone, Debug, Default)]
pub struct Tree {
    /// The two children of each cluster (node handles).
    pub children: Vec<[u32; 2]>,
    /// Parent cluster of each cluster ([`NONE`] for the top).
    pub parent: Vec<u32>,
    /// Parent cluster of each root ([`NONE`] when there is only one root).
    pub root_parent: Vec<u32>,
    /// Position of each root in [`Tree::members`].
    pub slot: Vec<u32>,
    /// Members of each cluster: a range of [`Tree::members`].
    pub range: Vec<(u32, u32)>,
    /// The roots in tree order.
    pub members: Vec<u32>,
    /// Running sum of the members' visible areas (one more entry than members).
    pub cum: Vec<f64>,
    /// Bounding box of each cluster.
    pub bounds: Vec<(DVec3, DVec3)>,
    /// Centre of the bounding sphere (the box's centre) and its radius.
    pub sphere: Vec<(DVec3, f64)>,
    /// Visible area of each cluster.
    pub area: Vec<f64>,
    /// Largest reflectance (over channels and roots) of each cluster.
    pub rho: Vec<f64>,
    /// Normal cone of each cluster: axis and cosine of the half-angle (`-1` for a full
    /// cone).
    pub cone: Vec<(DVec3, f64)>,
}

/// The node at the top of the tree: the top cluster, or root 0 when there is one root.
pub fn top(t: &Tree) -> u32 {
    if t.children.is_empty() {
        0
    } else {
        CLUSTER
    }
}

impl Tree {
    /// Builds the tree over the roots of `e`, with `rho_max[k]` the largest reflectance of
    /// root `k`; `visible` are the elements' visible areas.
    pub fn build(e: &Elements, visible: &[f64], rho_max: &[f64]) -> Tree {
        let n = e.roots;
        let mut t = Tree {
            root_parent: vec![NONE; n],
            members: (0..n as u32).collect(),
            ..Default::default()
        };
        if n < 2 {
            t.slot = vec![0; n];
            t.cum = vec![0.0, visible.first().copied().unwrap_or(0.0)];
            return t;
        }
        // Top-down, a stack of (cluster, lo, hi) to cut.
        t.push_cluster(NONE, 0, n as u32);
        let mut stack = vec![0u32];
        while let Some(c) = stack.pop() {
            let (lo, hi) = t.range[c as usize];
            let slice = &mut t.members[lo as usize..hi as usize];
            let (mut a, mut b) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            for &m in slice.iter() {
                a = a.min(e.centre[m as usize]);
                b = b.max(e.centre[m as usize]);
            }
            let ext = b - a;
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            let mid = slice.len() / 2;
            slice.select_nth_unstable_by(mid, |&p, &q| {
                let (x, y) = (e.centre[p as usize][axis], e.centre[q as usize][axis]);
                x.total_cmp(&y).then(p.cmp(&q))
            });
            let halves = [(lo, lo + mid as u32), (lo + mid as u32, hi)];
            let mut kids = [0u32; 2];
            for (k, &(l, h)) in halves.iter().enumerate() {
                if h - l == 1 {
                    let r = t.members[l as usize];
                    t.root_parent[r as usize] = c;
                    kids[k] = r;
                } else {
                    let id = t.push_cluster(c, l, h);
                    kids[k] = CLUSTER | id;
                    stack.push(id);
                }
            }
            t.children[c as usize] = kids;
        }
        t.slot = vec![0; n];
        for (k, &m) in t.members.iter().enumerate() {
            t.slot[m as usize] = k as u32;
        }
        // Sums, bounds and cones, children first.
        t.cum = Vec::with_capacity(n + 1);
        t.cum.push(0.0);
        for &m in &t.members {
            let last = *t.cum.last().unwrap_or(&0.0);
            t.cum.push(last + visible[m as usize]);
        }
        for c in (0..t.children.len()).rev() {
            let (lo, hi) = t.range[c];
            let (mut a, mut b) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            let (mut rho, mut axis) = (0.0f64, DVec3::ZERO);
            for &m in &t.members[lo as usize..hi as usize] {
                for &p in e.corners(m) {
                    a = a.min(p);
                    b = b.max(p);
                }
                rho = rho.max(rho_max[m as usize]);
                axis += visible[m as usize].max(1e-300) * e.normal[m as usize];
            }
            let centre = 0.5 * (a + b);
            let mut radius = 0.0f64;
            for &m in &t.members[lo as usize..hi as usize] {
                for &p in e.corners(m) {
                    radius = radius.max(p.distance(centre));
                }
            }
            let len = axis.length();
            let cone = if len > 0.0 {
                let axis = axis / len;
                let cos = t.members[lo as usize..hi as usize]
                    .iter()
                    .map(|&m| axis.dot(e.normal[m as usize]))
                    .fold(1.0f64, f64::min);
                (axis, if cos > 0.0 { cos } else { -1.0 })
            } else {
                (DVec3::Z, -1.0)
            };
            t.bounds[c] = (a, b);
            t.sphere[c] = (centre, radius);
            t.area[c] = t.cum[hi as usize] - t.cum[lo as usize];
            t.rho[c] = rho;
            t.cone[c] = cone;
        }
        t
    }

    fn push_cluster(&mut self, parent: u32, lo: u32, hi: u32) -> u32 {
        let id = self.children.len() as u32;
        self.children.push([NONE; 2]);
        self.parent.push(parent);
        self.range.push((lo, hi));
        self.bounds.push((DVec3::ZERO, DVec3::ZERO));
        self.sphere.push((DVec3::ZERO, 0.0));
        self.area.push(0.0);
        self.rho.push(0.0);
        self.cone.push((DVec3::Z, -1.0));
        id
    }

    /// Number of clusters.
    pub fn len(&self) -> usize {
        self.children.len()
    }

    /// True when there are none (one root or none).
    pub fn is_empty(&self) -> bool {
        self.children.is_empty()
    }

    /// The roots under node `n`.
    pub fn roots_of(&self, n: u32) -> &[u32] {
        let (lo, hi) = if is_cluster(n) {
            self.range[(n & !CLUSTER) as usize]
        } else {
            let k = self.slot[n as usize];
            (k, k + 1)
        };
        &self.members[lo as usize..hi as usize]
    }

    /// The roots of node `n` ([`Tree::roots_of`]) with the span `[a, b)` of their
    /// cumulative areas `cum`, from which a point of the node is drawn by area.
    fn area_span(&self, n: u32) -> (&[u32], usize, f64, f64) {
        let roots = self.roots_of(n);
        let lo = if is_cluster(n) {
            self.range[(n & !CLUSTER) as usize].0 as usize
        } else {
            self.slot[n as usize] as usize
        };
        (roots, lo, self.cum[lo], self.cum[lo + roots.len()])
    }
}

/// What the link rules read of a node.
#[derive(Clone, Copy, Debug)]
pub struct Shape {
    /// Centre of the bounding sphere.
    pub centre: DVec3,
    /// Its radius.
    pub radius: f64,
    /// Visible area.
    pub area: f64,
    /// Largest reflectance.
    pub rho: f64,
    /// Normal cone: axis and cosine of the half-angle (`-1`: full).
    pub cone: (DVec3, f64),
}

/// The largest `max(0, n·u)` over normals `n` in `cone` and directions `u` within angle
/// `alpha` of the unit vector `w`: `cos(max(0, φ - θ - α))`, with `φ` the angle between the
/// cone's axis and `w` and `θ` the cone's half-angle (0 past a right angle).
pub fn max_cos(cone: (DVec3, f64), w: DVec3, alpha: f64) -> f64 {
    if cone.1 < 0.0 {
        return 1.0;
    }
    let phi = cone.0.dot(w).clamp(-1.0, 1.0).acos();
    let x = phi - cone.1.clamp(-1.0, 1.0).acos() - alpha;
    if x <= 0.0 {
        1.0
    } else if x >= std::f64::consts::FRAC_PI_2 {
        0.0
    } else {
        x.cos()
    }
}

/// A link into a node (a cluster, or a root receiving from a cluster).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClusterLink {
    /// The source node.
    pub src: u32,
    /// Centre of the source's bounding sphere (where receiving leaves aim).
    pub at: DVec3,
    /// Projected area `P_S(w)` of the source toward the receiver.
    pub p: f64,
    /// Visible fraction.
    pub v: f64,
    /// Its standard error (binomial, Jeffreys).
    pub v_se: f64,
    /// Upper bound of the point factor over the pair.
    pub f_up: f64,
    /// Bound on the link's factor error, `F_up min(1, (4ds/(d - s)² + 2α)/√K + δ_v)`
    /// ([`Refiner::noise`]).
    pub df: f64,
    /// Largest reflectance of the receiver.
    pub rho: f64,
}

/// The cluster links, by receiver.
#[derive(Clone, Debug, Default)]
pub struct Links {
    /// Links into each cluster.
    pub cluster: Vec<Vec<ClusterLink>>,
    /// Links (from clusters) into each element: a root, or an element below one (a large
    /// root split so that a cluster's light is resolved over it).
    pub element: Vec<Vec<ClusterLink>>,
}

impl Links {
    /// Empty lists for `t` over `elements` elements.
    pub fn new(t: &Tree, elements: usize) -> Links {
        Links {
            cluster: vec![Vec::new(); t.len()],
            element: vec![Vec::new(); elements],
        }
    }

    /// The links into node `n` (none for an element made after the lists).
    pub fn into_node(&self, n: u32) -> &[ClusterLink] {
        if is_cluster(n) {
            &self.cluster[(n & !CLUSTER) as usize]
        } else {
            self.element.get(n as usize).map_or(&[], Vec::as_slice)
        }
    }

    fn list_mut(&mut self, n: u32) -> &mut Vec<ClusterLink> {
        if is_cluster(n) {
            &mut self.cluster[(n & !CLUSTER) as usize]
        } else {
            let k = n as usize;
            if k >= self.element.len() {
                self.element.resize(k + 1, Vec::new());
            }
            &mut self.element[k]
        }
    }

    /// Number of links.
    pub fn len(&self) -> usize {
        self.cluster.iter().chain(&self.element).map(Vec::len).sum()
    }

    /// True when there are none (stops at the first list with a link: it is asked per
    /// element, and the count is over every node).
    pub fn is_empty(&self) -> bool {
        self.cluster.iter().chain(&self.element).all(Vec::is_empty)
    }
}

/// Radiosity of every cluster: the visible-area mean over its roots, and the range its
/// leaves cover (each root standing for `B ± spread / 2`).
#[derive(Clone, Debug, Default)]
pub struct Radiosity {
    /// Mean radiosity per cluster.
    pub b: Vec<[f64; 3]>,
    /// Range per cluster.
    pub spread: Vec<[f64; 3]>,
}

impl Radiosity {
    /// Recomputes every cluster from the roots' radiosity `b` and spread `spread`
    /// (children first).
    pub fn pull(&mut self, t: &Tree, visible: &[f64], b: &[[f64; 3]], spread: &[[f64; 3]]) {
        let n = t.len();
        self.b.resize(n, [0.0; 3]);
        self.spread.resize(n, [0.0; 3]);
        let mut lo = vec![[f64::INFINITY; 3]; n];
        let mut hi = vec![[f64::NEG_INFINITY; 3]; n];
        for c in (0..n).rev() {
            let mut sum = [0.0; 3];
            for &k in &t.children[c] {
                let (a, bk, l, h) = if is_cluster(k) {
                    let i = (k & !CLUSTER) as usize;
                    (t.area[i], self.b[i], lo[i], hi[i])
                } else {
                    let i = k as usize;
                    let bk = b[i];
                    let s = spread[i];
                    if visible[i] > 0.0 {
                        (
                            visible[i],
                            bk,
                            std::array::from_fn(|j| bk[j] - 0.5 * s[j]),
                            std::array::from_fn(|j| bk[j] + 0.5 * s[j]),
                        )
                    } else {
                        (0.0, bk, [f64::INFINITY; 3], [f64::NEG_INFINITY; 3])
                    }
                };
                for j in 0..3 {
                    sum[j] += a * bk[j];
                    lo[c][j] = lo[c][j].min(l[j]);
                    hi[c][j] = hi[c][j].max(h[j]);
                }
            }
            self.b[c] = if t.area[c] > 0.0 {
                sum.map(|s| s / t.area[c])
            } else {
                [0.0; 3]
            };
            self.spread[c] = std::array::from_fn(|j| (hi[c][j] - lo[c][j]).max(0.0));
        }
    }
}

/// What the cluster refinement reads.
pub struct Refiner<'a> {
    /// The tree.
    pub tree: &'a Tree,
    /// The elements (roots are what the tree groups).
    pub elements: &'a Elements,
    /// Visible area per element.
    pub visible: &'a [f64],
    /// Largest reflectance per root.
    pub rho_max: &'a [f64],
    /// Visibility queries.
    pub vis: &'a Visibility,
    /// Element radiosity and spread.
    pub b: &'a [[f64; 3]],
    /// See `b`.
    pub spread: &'a [[f64; 3]],
    /// Cluster radiosity.
    pub clusters: &'a Radiosity,
    /// Radiosity assumed for sources not solved yet (0 once solved).
    pub floor: f64,
    /// Absolute link tolerance.
    pub eps: f64,
    /// Distance below which a point counts as on a plane ([`super::link::facing`]).
    pub tol: f64,
    /// Share of `eps` a link whose rays were all blocked may carry and be dropped.
    pub hide: f64,
    /// Rays per side: `rays²` per link.
    pub rays: usize,
    /// Seed of the random streams.
    pub seed: u64,
    /// Largest relative error term `(4ds/(d - s)² + 2α)/√K + δ_v` of an accepted link
    /// ([`super::Settings::cluster_accuracy`]).
    pub accuracy: f64,
    /// Points per piece of a link's source for the near-field correction
    /// ([`piece_factor`]; [`POINTS`]); 0 for the point source alone.
    pub points: usize,
    /// Per cluster, `Σ_j A_j n_j` over its roots (today's visible areas), made on first
    /// use ([`Refiner::projected`]).
    pub moments: std::sync::OnceLock<Vec<DVec3>>,
    /// Smallest area an element split for a cluster link's receiver may have (a quarter
    /// of its parent's at least this).
    pub min_area: f64,
    /// Whether a receiving element larger than its source cluster is split
    /// ([`super::Settings::split_receivers`]); else the source is.
    pub split_receivers: bool,
}

/// What a pair of nodes becomes.
#[derive(Clone, Debug)]
enum Outcome {
    Link(ClusterLink),
    Elements(u32, u32),
    Split(Vec<(u32, u32)>),
    /// The receiver, an element not split yet, is to be split, and its children paired
    /// with the source.
    Subdivide(u32, u32),
    Drop,
}

impl Refiner<'_> {
    /// The shape of node `n`.
    pub fn shape(&self, n: u32) -> Shape {
        let t = self.tree;
        if is_cluster(n) {
            let c = (n & !CLUSTER) as usize;
            Shape {
                centre: t.sphere[c].0,
                radius: t.sphere[c].1,
                area: t.area[c],
                rho: t.rho[c],
                cone: t.cone[c],
            }
        } else {
            let e = self.elements;
            let k = n as usize;
            let centre = e.centre[k];
            let radius = e
                .corners(n)
                .iter()
                .map(|p| p.distance(centre))
                .fold(0.0, f64::max);
            Shape {
                centre,
                radius,
                area: self.visible[k],
                rho: self.rho_max[e.root[k] as usize],
                cone: (e.normal[k], 1.0),
            }
        }
    }

    fn source(&self, n: u32) -> ([f64; 3], [f64; 3]) {
        if is_cluster(n) {
            let c = (n & !CLUSTER) as usize;
            (self.clusters.b[c], self.clusters.spread[c])
        } else {
            (self.b[n as usize], self.spread[n as usize])
        }
    }

    /// The bound-and-transfer terms of a source: the largest channel of `max(B_S, floor)`
    /// and of its spread.
    fn brightness(&self, n: u32) -> (f64, f64) {
        let (b, s) = self.source(n);
        let b = b.iter().copied().fold(0.0, f64::max).max(self.floor);
        (b, s.iter().copied().fold(0.0, f64::max))
    }

    /// What replaces `r ← s`: the pairs of the larger node's children (by sphere radius).
    /// With [`Refiner::split_receivers`], a receiving element larger than its source
    /// cluster is split into its four element children ([`Outcome::Subdivide`] when it
    /// has none yet), down to [`Refiner::min_area`]:
    /// else a floor under a group of spheres would be linked to every face of the group
    /// (the source split down to its roots, as the larger node), and each of its leaves
    /// would gather from all of them. A source root and a cluster receiver: the receiver.
    fn split(&self, r: u32, s: u32, rs: &Shape, ss: &Shape) -> Outcome {
        let t = self.tree;
        if is_cluster(r) && (rs.radius >= ss.radius || !is_cluster(s)) {
            let kids = t.children[(r & !CLUSTER) as usize];
            return Outcome::Split(kids.iter().map(|&c| (c, s)).collect());
        }
        let e = self.elements;
        let k = r as usize;
        if self.split_receivers
            && !is_cluster(r)
            && rs.radius > ss.radius
            && e.area[k] / 4.0 >= self.min_area
        {
            if e.is_leaf(r) {
                return Outcome::Subdivide(r, s);
            }
            return Outcome::Split(e.children(r).iter().map(|&c| (c, s)).collect());
        }
        let kids = t.children[(s & !CLUSTER) as usize];
        Outcome::Split(kids.iter().map(|&c| (r, c)).collect())
    }

    /// The faces of node `n`: a cluster's roots, or the element itself.
    fn faces<'b>(&'b self, n: &'b u32) -> &'b [u32] {
        if is_cluster(*n) {
            self.tree.roots_of(*n)
        } else {
            std::slice::from_ref(n)
        }
    }

    /// The factor by which the geometric term `4ds/(d - s)² + 2α` scales in a link's
    /// error: 1 for the point source alone, whose error it bounds and which errs with one
    /// sign; `1/√K` with `K` [`Refiner::points`] points a piece, whose estimate is
    /// unbiased and whose error is the mean of `K` stratified differences each within the
    /// geometric term (a standard error, as `δ_v` is).
    pub fn noise(&self) -> f64 {
        if self.points == 0 {
            1.0
        } else {
            1.0 / (self.points as f64).sqrt()
        }
    }

    /// Error of an existing link with today's radiosity.
    pub fn error(&self, l: &ClusterLink) -> f64 {
        let (b, ds) = self.brightness(l.src);
        l.rho * (b * l.df + ds * l.f_up)
    }

    fn decide(&self, r: u32, s: u32) -> (Outcome, u64) {
        let t = self.tree;
        if r == s {
            if !is_cluster(r) {
                return (Outcome::Drop, 0);
            }
            let k = t.children[(r & !CLUSTER) as usize];
            let pairs = k.iter().flat_map(|&a| k.iter().map(move |&b| (a, b)));
            return (Outcome::Split(pairs.collect()), 0);
        }
        if !is_cluster(r) && !is_cluster(s) {
            // Pairs that cannot exchange light (on `room-spheres-12-s5`, 72% of them:
            // neighbours on the spheres) are not handed on to be evaluated.
            if !super::link::facing(self.elements, self.tol, r, s) {
                return (Outcome::Drop, 0);
            }
            return (Outcome::Elements(r, s), 0);
        }
        let (rs, ss) = (self.shape(r), self.shape(s));
        if rs.area <= 0.0 || ss.area <= 0.0 {
            return (Outcome::Drop, 0);
        }
        let gap = rs.centre - ss.centre;
        let d = gap.length();
        let sum = rs.radius + ss.radius;
        if d <= sum * (1.0 + 1e-9) {
            return (self.split(r, s, &rs, &ss), 0);
        }
        let w = gap / d;
        let alpha = (sum / d).min(1.0).asin();
        let c_s = max_cos(ss.cone, w, alpha);
        let c_r = max_cos(rs.cone, -w, alpha);
        let near = d - sum;
        // The source's projected area toward any direction within `alpha` of `w`: at most
        // `P_S(w) + A_S · 2 sin(alpha / 2)`, as `max(0, n·u)` is 1-Lipschitz in `u` and
        // `|u - w| ≤ 2 sin(alpha / 2)`.
        let p_w = is_cluster(s).then(|| self.projected(s, w));
        let seen_area = match p_w {
            Some(p) => (p + 2.0 * ss.area * (0.5 * alpha).sin()).min(ss.area * c_s),
            None => ss.area * c_s,
        };
        let f_up = seen_area * c_r / (std::f64::consts::PI * near * near);
        if f_up <= 0.0 {
            return (Outcome::Drop, 0);
        }
        let geo = (4.0 * d * sum / (near * near) + 2.0 * alpha) * self.noise();
        let (b, ds) = self.brightness(s);
        let err = |rel: f64| rs.rho * (b * f_up * rel.min(1.0) + ds * f_up);
        if err(geo) > self.eps {
            return (self.split(r, s, &rs, &ss), 0);
        }
        let n = (self.rays * self.rays) as f64;
        // The least visibility term any set of rays can give is that of all rays free: a
        // pair over the tolerance even then splits whatever the rays say, unless all of
        // them blocked could drop it. Those rays are not cast.
        let least = geo + fraction_se(1.0, n);
        if (err(least) > self.eps || least > self.accuracy)
            && rs.rho * b * f_up * 3.0 / n > self.hide * self.eps
        {
            return (self.split(r, s, &rs, &ss), 0);
        }
        let mut seen = self.transmittance(r, s, 0);
        let mut rays = seen.rays;
        // Whether the pair is taken as a link whatever its bound says.
        let mut small = false;
        if seen.free == 0 && seen.blocked > 0 {
            if rs.rho * b * f_up * 3.0 / n > self.hide * self.eps {
                return (self.split(r, s, &rs, &ss), rays);
            }
            // Its whole transfer is within the share `hide` of the tolerance unless some
            // of it is seen. Dropped on these rays, the pair would give nothing where
            // they all happened to be blocked, `(1 - v)^n` of the time, and its children
            // their light otherwise: on average less than it sends. Rays of their own
            // (an independent stream) estimate the link instead: nothing when they are
            // all blocked too, else their fraction.
            let again = self.transmittance(r, s, 1);
            rays += again.rays;
            if again.free == 0 {
                return (Outcome::Drop, rays);
            }
            (seen, small) = (again, true);
        }
        let dv = if seen.free > 0 && seen.blocked > 0 || seen.free == 0 || small {
            1.0
        } else {
            fraction_se(1.0, n)
        };
        if !small && (err(geo + dv) > self.eps || geo + dv > self.accuracy) {
            return (self.split(r, s, &rs, &ss), rays);
        }
        let p = p_w.unwrap_or_else(|| self.projected(s, w));
        if p <= 0.0 && (self.points == 0 || !self.facing(r, s)) {
            return (Outcome::Drop, rays);
        }
        let link = ClusterLink {
            src: s,
            at: ss.centre,
            p,
            v: seen.v,
            v_se: fraction_se(seen.v, n),
            f_up,
            df: f_up * (geo + dv).min(1.0),
            rho: rs.rho,
        };
        (Outcome::Link(link), rays)
    }

    /// Bounding box of node `n`.
    fn bounds(&self, n: u32) -> (DVec3, DVec3) {
        if is_cluster(n) {
            self.tree.bounds[(n & !CLUSTER) as usize]
        } else {
            let (mut a, mut b) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            for &p in self.elements.corners(n) {
                a = a.min(p);
                b = b.max(p);
            }
            (a, b)
        }
    }

    /// True when some root of `a` has part of the bounding box of `b` strictly in front of
    /// its plane (the support function of the box along the root's normal): else nothing
    /// of `b` can receive from `a` (coplanar or facing away).
    pub fn front(&self, a: u32, b: u32) -> bool {
        self.front_by(a, b, 1e-9)
    }

    /// [`Refiner::front`] with the margin `rel` times the distances (0 for a test that
    /// every corner found strictly in front by [`Refiner::facing`] also passes).
    fn front_by(&self, a: u32, b: u32, rel: f64) -> bool {
        let e = self.elements;
        let (lo, hi) = self.bounds(b);
        let (c, h) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        self.faces(&a).iter().any(|&m| {
            let (n, q) = (e.normal[m as usize], e.centre[m as usize]);
            let reach = n.dot(c - q) + n.abs().dot(h);
            reach > rel * ((c - q).length() + h.length())
        })
    }

    /// True when some root of `r` and some root of `s` each have a corner strictly in
    /// front of the other's plane: else no light passes between them (coplanar roots, the
    /// faces of a convex solid, roots turned away). Decided root by root for small pairs
    /// (at most [`FACING_PAIRS`] root pairs), else by the roots' planes against the other
    /// node's bounding box ([`Refiner::front`], a superset).
    pub fn facing(&self, r: u32, s: u32) -> bool {
        let (rr, sr) = (self.faces(&r), self.faces(&s));
        if rr.len() * sr.len() > FACING_PAIRS {
            return self.front(s, r) && self.front(r, s);
        }
        // A corner of `j` strictly in front of root `i`'s plane puts `j`'s node's box in
        // front of it: a pair the boxes rule out needs no root-by-root look.
        if !(self.front_by(s, r, 0.0) && self.front_by(r, s, 0.0)) {
            return false;
        }
        let e = self.elements;
        let sees = |i: u32, j: u32| {
            let (n, q) = (e.normal[i as usize], e.centre[i as usize]);
            e.corners(j).iter().any(|&p| {
                let d = p - q;
                n.dot(d) > 1e-9 * d.length()
            })
        };
        rr.iter()
            .any(|&i| sr.iter().any(|&j| sees(i, j) && sees(j, i)))
    }

    /// `P_S(w) = Σ_j A_j max(0, n_j·w)` over the roots of `s`. Where a cluster's normal
    /// cone lies wholly on one side of `w`'s plane every term has the same sign, and the
    /// sum is `max(0, M·w)` with `M = Σ_j A_j n_j` the cluster's area-weighted normal
    /// ([`Refiner::moments`]); only clusters straddling the plane are opened, so that a
    /// cluster of `m` roots costs about the roots along that plane instead of `m`.
    pub fn projected(&self, s: u32, w: DVec3) -> f64 {
        let moments = self
            .moments
            .get_or_init(|| moments(self.tree, self.elements, self.visible));
        projected(self.tree, self.elements, self.visible, moments, s, w)
    }

    /// A point of node `n` drawn by visible area: the point, its normal, its area weight
    /// (Jacobian over the root's area) and the exposed fraction of the leaf it lies on
    /// (below 1 on a partly buried leaf: [`Elements::exposed`]). A root is drawn by its
    /// visible area; on a split root, points on buried leaves are drawn again (within
    /// [`super::link::BURIED_TRIES`] draws, else `None`).
    fn sample(&self, n: u32, rng: &mut Pcg32) -> Option<(DVec3, DVec3, f64, f64)> {
        let t = self.tree;
        let e = self.elements;
        let m = if !is_cluster(n) && n as usize >= e.roots {
            // An element below a root: drawn by area over it, as a root is.
            if self.visible[n as usize] <= 0.0 {
                return None;
            }
            rng.next_f64();
            n
        } else {
            let (roots, lo, a, b) = t.area_span(n);
            if b <= a {
                return None;
            }
            let x = a + rng.next_f64() * (b - a);
            let k = t.cum[lo + 1..lo + roots.len()].partition_point(|&c| c <= x);
            roots[k.min(roots.len() - 1)]
        };
        for _ in 0..super::link::BURIED_TRIES {
            let (u, v) = (rng.next_f64(), rng.next_f64());
            let leaf = e.locate(m, u, v).0 as usize;
            if !e.buried[leaf] {
                let (p, j) = e.point(m, u, v);
                let area = e.area[m as usize];
                return Some((
                    p,
                    e.normal[m as usize],
                    j / area.max(1e-300),
                    e.exposed[leaf],
                ));
            }
        }
        None
    }

    /// Kernel-weighted visible fraction between nodes `r` and `s` from `rays²` segments
    /// between area-sampled points (a transmittance estimate; pairs that do not face each
    /// other carry no weight and cast no ray). A point on a partly buried leaf may lie
    /// inside the solid, where its ray is blocked as expected and says nothing of the
    /// pair's shadow: each segment's weight counts in the denominator times the exposed
    /// fractions of its two ends (their chance of lying outside), as a partly buried
    /// leaf's element factors are divided by its exposed fraction. Without it, the
    /// ceiling's root around the light of `room-spheres-8` (45% of it above the light)
    /// summed its factors to 0.960 clustered against 1.004 unclustered. `stream` picks
    /// one of the pair's independent sets of points.
    fn transmittance(&self, r: u32, s: u32, stream: u64) -> Seen {
        let mut rng = Pcg32::keyed(
            self.seed,
            0x434c_5553_0000_0000 | u64::from(r),
            u64::from(s),
            stream,
        );
        let cells = self.rays * self.rays;
        let mut segs: Vec<SegmentRay> = Vec::with_capacity(cells);
        let mut weights = Vec::with_capacity(cells);
        for _ in 0..cells {
            let (Some((x, nx, jx, ex)), Some((y, ny, jy, ey))) =
                (self.sample(r, &mut rng), self.sample(s, &mut rng))
            else {
                continue;
            };
            let Some(w) = super::link::kernel_weight((x, nx, jx), (y, ny, jy)) else {
                continue;
            };
            weights.push((w, ex * ey));
            segs.push(self.vis.segment_ray(x, nx, y, ny));
        }
        if segs.is_empty() {
            return Seen {
                v: 1.0,
                free: 0,
                blocked: 0,
                rays: 0,
            };
        }
        let mut free = vec![false; segs.len()];
        self.vis.segments_visible(&segs, &mut free);
        let (mut num, mut den) = (0.0, 0.0);
        for (&(w, exposed), &f) in weights.iter().zip(&free) {
            den += w * exposed;
            if f {
                num += w;
            }
        }
        let nfree = free.iter().filter(|&&f| f).count();
        Seen {
            v: if den > 0.0 { (num / den).min(1.0) } else { 0.0 },
            free: nfree,
            blocked: free.len() - nfree,
            rays: segs.len() as u64,
        }
    }
}

/// What the rays between two nodes found.
struct Seen {
    v: f64,
    free: usize,
    blocked: usize,
    rays: u64,
}

/// What a round of cluster refinement produced.
#[derive(Clone, Debug, Default)]
pub struct Made {
    /// Pairs of elements, for element links.
    pub specs: Vec<(u32, u32)>,
    /// Receiving elements to split, each with the source cluster its children are then
    /// paired with ([`split_receivers`]).
    pub subdivide: Vec<(u32, u32)>,
    /// Cluster links made.
    pub links: usize,
    /// Pairs examined.
    pub pairs: usize,
    /// Rays cast.
    pub rays: u64,
}

/// Refines the pairs `start` until every pair is a cluster link (added to `links`), a pair
/// of elements (returned, for element links), a receiving element to split (returned), or
/// dropped; a level of pairs at a time, in parallel, in a fixed order.
pub fn refine(f: &Refiner, start: Vec<(u32, u32)>, links: &mut Links) -> Made {
    let mut made = Made::default();
    let mut frontier = start;
    while !frontier.is_empty() {
        made.pairs += frontier.len();
        let out: Vec<(Outcome, u64)> = frontier
            .par_iter()
            .with_max_len(super::PAR_RUN)
            .map(|&(r, s)| f.decide(r, s))
            .collect();
        let mut next = Vec::new();
        for (&(r, _), (o, rays)) in frontier.iter().zip(out) {
            made.rays += rays;
            match o {
                Outcome::Link(l) => {
                    links.list_mut(r).push(l);
                    made.links += 1;
                }
                Outcome::Elements(a, b) => made.specs.push((a, b)),
                Outcome::Split(p) => next.extend(p),
                Outcome::Subdivide(r, s) => made.subdivide.push((r, s)),
                Outcome::Drop => {}
            }
        }
        frontier = next;
    }
    made
}

/// Re-examines every cluster link with today's radiosity; those over the tolerance are
/// replaced by their children's pairs, refined as in [`refine`]. Returns what was made
/// and the number of links replaced.
pub fn recheck(f: &Refiner, links: &mut Links) -> (Made, usize) {
    let mut start = Vec::new();
    let mut subdivide = Vec::new();
    let mut replaced = 0;
    let t = f.tree;
    let nodes: Vec<u32> = (0..t.len() as u32)
        .map(|c| c | CLUSTER)
        .chain(0..links.element.len() as u32)
        .collect();
    for &r in &nodes {
        let list = links.list_mut(r);
        let mut kept = Vec::with_capacity(list.len());
        for l in list.drain(..) {
            if f.error(&l) > f.eps {
                let (rs, ss) = (f.shape(r), f.shape(l.src));
                match f.split(r, l.src, &rs, &ss) {
                    Outcome::Split(p) => start.extend(p),
                    Outcome::Subdivide(a, b) => subdivide.push((a, b)),
                    _ => unreachable!("a split is pairs or a receiver to split"),
                }
                replaced += 1;
            } else {
                kept.push(l);
            }
        }
        *links.list_mut(r) = kept;
    }
    let mut made = refine(f, start, links);
    subdivide.append(&mut made.subdivide);
    made.subdivide = subdivide;
    (made, replaced)
}

/// The pairs that replace `made.subdivide` once its receivers are split: each receiver's
/// four children with its source.
pub fn split_receivers(e: &Elements, subdivide: &[(u32, u32)]) -> Vec<(u32, u32)> {
    subdivide
        .iter()
        .flat_map(|&(r, s)| e.children(r).map(move |c| (c, s)))
        .collect()
}

/// Points a piece of a link's source is sampled at for the near-field correction
/// ([`piece_factor`]). Measured on the cube furnace (docs/HIERARCHY.md, Clustering): 1
/// point already takes the power unaccounted for from 2.4% to 0.06%; 8 bring the worst
/// leaf from 6.9% to 0.2%, for 2.8 times the user CPU of that test with the point
/// source alone (16% more on `scenes/room-sphere.obj`).
pub const POINTS: usize = 8;

/// Most root pairs [`Refiner::facing`] examines one by one.
pub const FACING_PAIRS: usize = 4096;

/// Most pieces a link's source is cut into for the gather.
pub const MAX_PIECES: usize = 64;

/// A piece of a cluster link's source, as the gather sees it.
#[derive(Clone, Debug, PartialEq)]
pub struct Piece {
    /// The node.
    pub node: u32,
    /// Its centre.
    pub at: DVec3,
    /// Its projected area `P_n(w)` toward the receiver's centre.
    pub p: f64,
    /// The direction `w` from its centre to the receiver's. Its near-field points
    /// ([`sample_points`], keyed on the receiving node and this node) are drawn where
    /// they are used, not held: at 10^5 triangles they took about 2 GB.
    pub w: DVec3,
}

/// A point of a piece's source: `weight` is its share of the piece's visible area (the
/// weights' expectation sums to the visible area), `facing` is `weight max(0, n·w)` with
/// `w` the direction the piece's projected area is taken in (their expectation sums to
/// `P_n(w)`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    /// The point.
    pub at: DVec3,
    /// Its root.
    pub root: u32,
    /// Area weight.
    pub weight: f64,
    /// Area weight times the cosine toward the receiver's centre.
    pub facing: f64,
}

/// The pieces of every cluster link's source, by receiver (parallel to [`Links`]).
#[derive(Clone, Debug, Default)]
pub struct Pieces {
    cluster: Vec<Vec<Vec<Piece>>>,
    element: Vec<Vec<Vec<Piece>>>,
}

impl Pieces {
    fn of(&self, n: u32) -> &[Vec<Piece>] {
        if is_cluster(n) {
            &self.cluster[(n & !CLUSTER) as usize]
        } else {
            self.element.get(n as usize).map_or(&[], Vec::as_slice)
        }
    }
}

impl Refiner<'_> {
    /// The source of link `l` into `r` as the gather sees it. A cluster's mean radiosity
    /// times its projected area is not its exitance toward `r` when its radiosity varies
    /// with orientation (the tops of spheres under a light are brighter than their
    /// bottoms, and they are what the ceiling sees): the source is cut into its children,
    /// each with its own radiosity, centre and projected area, while the share of the
    /// link it carries times its spread, `ρ_R F_up (P_n / P_S) ΔB_n`, is above
    /// `descend × eps` (at most [`MAX_PIECES`] pieces), as the element gather does with
    /// split sources. Each piece carries its sample points (`Refiner::samples`); a
    /// piece with no projected area toward `r`'s centre is left out only when it faces
    /// nothing of `r` ([`Refiner::facing`]).
    pub fn pieces(&self, r: u32, l: &ClusterLink, descend: f64) -> Vec<Piece> {
        let rc = self.shape(r).centre;
        let mut out = Vec::new();
        let mut stack = vec![l.src];
        while let Some(n) = stack.pop() {
            let c = self.shape(n).centre;
            let w = (rc - c).normalize_or_zero();
            let p = self.projected(n, w);
            if p <= 0.0 && (self.points == 0 || !self.facing(r, n)) {
                continue;
            }
            let ds = self.source(n).1.iter().copied().fold(0.0, f64::max);
            let share = l.rho * l.f_up * (p / l.p.max(1e-300)).min(1.0) * ds;
            if is_cluster(n)
                && share > descend * self.eps
                && out.len() + stack.len() + 2 <= MAX_PIECES
            {
                stack.extend(self.tree.children[(n & !CLUSTER) as usize]);
            } else {
                out.push(Piece {
                    node: n,
                    at: c,
                    p,
                    w,
                });
            }
        }
        out
    }

    /// [`Refiner::pieces`] of every link.
    pub fn all_pieces(&self, links: &Links, descend: f64) -> Pieces {
        let per = |lists: &[Vec<ClusterLink>], cluster: bool| -> Vec<Vec<Vec<Piece>>> {
            lists
                .par_iter()
                .enumerate()
                .map(|(k, list)| {
                    let r = if cluster {
                        k as u32 | CLUSTER
                    } else {
                        k as u32
                    };
                    list.iter().map(|l| self.pieces(r, l, descend)).collect()
                })
                .collect()
        };
        Pieces {
            cluster: per(&links.cluster, true),
            element: per(&links.element, false),
        }
    }
}

/// Per cluster of `t`, the area-weighted normal `Σ_j A_j n_j` over its roots, with areas
/// `visible`.
pub fn moments(t: &Tree, e: &Elements, visible: &[f64]) -> Vec<DVec3> {
    let mut m = vec![DVec3::ZERO; t.len()];
    // Children come after their parents.
    for c in (0..t.len()).rev() {
        m[c] = t.children[c]
            .iter()
            .map(|&k| {
                if is_cluster(k) {
                    m[(k & !CLUSTER) as usize]
                } else {
                    visible[k as usize] * e.normal[k as usize]
                }
            })
            .sum();
    }
    m
}

/// `P_n(w) = Σ_j A_j max(0, n_j·w)` over the roots of node `n` ([`Refiner::projected`]),
/// with `moments` from [`moments`].
pub fn projected(
    t: &Tree,
    e: &Elements,
    visible: &[f64],
    moments: &[DVec3],
    n: u32,
    w: DVec3,
) -> f64 {
    let mut sum = 0.0;
    let mut stack = vec![n];
    while let Some(n) = stack.pop() {
        if !is_cluster(n) {
            let k = n as usize;
            sum += visible[k] * e.normal[k].dot(w).max(0.0);
            continue;
        }
        let c = (n & !CLUSTER) as usize;
        let (axis, cos_half) = t.cone[c];
        if cos_half > -1.0 {
            let theta = cos_half.clamp(-1.0, 1.0).acos();
            let phi = axis.dot(w).clamp(-1.0, 1.0).acos();
            if phi + theta <= std::f64::consts::FRAC_PI_2 {
                sum += moments[c].dot(w).max(0.0);
                continue;
            }
            if phi - theta >= std::f64::consts::FRAC_PI_2 {
                continue;
            }
        }
        stack.extend(t.children[c]);
    }
    sum
}

/// `k` points of node `n` for the receiver `r` (the key of their stream), drawn by visible area
/// and stratified: a Latin hypercube over (the running visible area of the node's
/// roots in tree order, the root's second parameter), so that a node of one root gets
/// one point per row and per column of its parameter square, and a node of many roots
/// one point per `1/k` of its area. Triangles are mapped by `u = √ξ` (uniform by
/// area); the weights carry the remaining Jacobian, and the ratio of each root's visible
/// area today (`visible`) to the one the tree was built with, so that the weights'
/// expectation is today's visible area and that of `facing` today's `P_n(w)`.
#[allow(clippy::too_many_arguments)]
pub fn sample_points(
    t: &Tree,
    e: &Elements,
    visible: &[f64],
    seed: u64,
    k: usize,
    r: u32,
    n: u32,
    w: DVec3,
) -> Vec<Sample> {
    if k == 0 {
        return Vec::new();
    }
    let (roots, lo, a, b) = t.area_span(n);
    if b <= a {
        return Vec::new();
    }
    let mut rng = Pcg32::keyed(seed, 0x434c_5054_0000_0000 | u64::from(r), u64::from(n), 0);
    let mut perm: Vec<u32> = (0..k as u32).collect();
    for i in (1..k).rev() {
        let j = rng.below(i as u32 + 1) as usize;
        perm.swap(i, j);
    }
    let inv = 1.0 / k as f64;
    let mut out = Vec::with_capacity(k);
    for (i, &pi) in perm.iter().enumerate() {
        let x = a + (i as f64 + rng.next_f64()) * inv * (b - a);
        let q = t.cum[lo + 1..lo + roots.len()]
            .partition_point(|&c| c <= x)
            .min(roots.len() - 1);
        let m = roots[q];
        let vis = t.cum[lo + q + 1] - t.cum[lo + q];
        let xi = if vis > 0.0 {
            ((x - t.cum[lo + q]) / vis).clamp(0.0, 1.0)
        } else {
            rng.next_f64()
        };
        let v = (f64::from(pi) + rng.next_f64()) * inv;
        let mi = m as usize;
        let (p, wj) = match e.piece[mi] {
            crate::formfactor::exact::Piece::Tri(_) => {
                let u = xi.sqrt();
                let (p, j) = e.piece[mi].at(u, 1.0 - u, v, 1.0 - v);
                (p, j / (2.0 * u).max(1e-300))
            }
            crate::formfactor::exact::Piece::Quad(_) => e.piece[mi].at(xi, 1.0 - xi, v, 1.0 - v),
        };
        let today = if vis > 0.0 { visible[mi] / vis } else { 0.0 };
        let weight = (b - a) * inv * wj / e.area[mi].max(1e-300) * today;
        out.push(Sample {
            at: p,
            root: m,
            weight,
            facing: weight * e.normal[mi].dot(w).max(0.0),
        });
    }
    out
}

/// Solid angle of the planar polygon `poly` (corners counter-clockwise from its front,
/// normal `n`) seen from `y`, 0 when `y` is not in front of it: the sum over a fan of
/// triangles of Van Oosterom and Strackee's formula ("The solid angle of a plane triangle",
/// IEEE Trans. Biomed. Eng. 30, 1983), `tan(Ω/2) = |a·(b×c)| / (abc + (a·b)c + (a·c)b +
/// (b·c)a)` with `a, b, c` the corners relative to `y`.
pub fn solid_angle(y: DVec3, poly: &[DVec3], n: DVec3) -> f64 {
    if poly.len() < 3 || n.dot(y - poly[0]) <= 0.0 {
        return 0.0;
    }
    let mut sum = 0.0;
    for k in 1..poly.len() - 1 {
        let (a, b, c) = (poly[0] - y, poly[k] - y, poly[k + 1] - y);
        let (la, lb, lc) = (a.length(), b.length(), c.length());
        let num = a.dot(b.cross(c)).abs();
        let den = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
        sum += 2.0 * num.atan2(den);
    }
    sum
}

/// The factor of element `l` from a piece of a link's source seen through visible
/// fraction `v`, the standard error of its sampling, and the bound on its one-point rules
/// (`small` is `l`'s polygon as [`far::Small`]).
///
/// The point estimate treats the piece as a point source of intensity `B P / π` at its
/// centre `c`, so that the element's mean irradiance is `B P Ω_c / (π A_l)` with `Ω_c` the
/// element's solid angle from `c` ([`solid_angle`]; the element's own extent is integrated
/// exactly, not sampled at its centre, whose `1/r²` would be biased low by convexity).
/// Near the source this overestimates: for a disc of radius `a` facing a point at
/// distance `d` the exact factor is `a²/(d² + a²)`, the point estimate `a²/d²`.
///
/// The exact factor is `F_lS = (1/A_l) ∫_S F(y → l) dA_y`, with `F(y → l)` the factor of
/// a differential area at `y` to the element's polygon (Lambert's contour integral,
/// [`crate::analytic::point_to_polygon_unit`]). Over the piece's points `y_k` (area
/// weights `w_k`, [`Sample`]) the estimate is the point estimate as a control variate:
///
/// `A_l F = P Ω_c / π + Σ_k (w_k F(y_k → l) - w_k max(0, n_k·w) Ω_c / π)`,
///
/// unbiased for `A_l F_lS` because `E[Σ_k w_k max(0, n_k·w)] = P` (Glasserman, "Monte
/// Carlo Methods in Financial Engineering", 2003, §4.1: a control variate with known mean
/// leaves the estimator unbiased), and with a small variance where the point source is
/// close already (the two terms of each point agree in the far field). Its standard
/// error is that of the mean of the points' differences (conservative for stratified
/// points). With no points, the point estimate and no sampling error.
///
/// An element small beside its distance from a point (at 10^6 input triangles, most are
/// millimetres across and metres from the sources) takes `F(y → l)` and `Ω_c` by its
/// centroid ([`far::point_factor`], [`far::solid_angle`]) where the rule's bound is within
/// [`FAR`] of the value; the bounds, weighted as their terms are, make the entry's
/// `bound` (deterministic, added linearly as the quadrature's are).
pub fn piece_factor(
    piece: &Piece,
    samples: &[Sample],
    v: f64,
    e: &Elements,
    l: u32,
    small: &Small,
) -> PieceFactor {
    let mut spread = Spread::default();
    piece_terms(
        piece,
        cone(piece, e, l, small),
        samples,
        e,
        l,
        small,
        |_, wg, fc| spread.add(wg - fc),
    )
    .map_or(PieceFactor::default(), |t| t.factor(v, &spread, false))
}

/// The terms of [`piece_factor`] before the visibility is applied: the point estimate
/// `P Ω_c / π` and its rule's bound, for element `l` (`small`) of a piece whose cone is
/// `cone` ([`cone`]); each point's terms `w_k F(y_k → l)` and `w_k max(0, n_k·w) Ω_c /
/// π` go to `each` with the point's index. `None` for an element of no area.
#[allow(clippy::too_many_arguments)]
fn piece_terms(
    piece: &Piece,
    (cone, cone_bound): (f64, f64),
    samples: &[Sample],
    e: &Elements,
    l: u32,
    small: &Small,
    mut each: impl FnMut(usize, f64, f64),
) -> Option<Terms> {
    let li = l as usize;
    let a = e.area[li];
    if a <= 0.0 {
        return None;
    }
    let mut t = Terms {
        base: piece.p * cone,
        bound: piece.p.abs() * cone_bound,
        area: a,
    };
    if samples.is_empty() {
        return Some(t);
    }
    let rec = Receiver::new(e.corners(l), e.normal[li], e.centre[li]);
    for (i, s) in samples.iter().enumerate() {
        let n_s = e.normal[s.root as usize];
        let g = match far::point_factor(s.at, n_s, small) {
            Some((g, b)) if b <= FAR * g => {
                t.bound += s.weight.abs() * b;
                g
            }
            _ => point_factor(s.at, n_s, &rec),
        };
        t.bound += s.facing.abs() * cone_bound;
        each(i, s.weight * g, s.facing * cone);
    }
    Some(t)
}

/// `Ω_c / π` of element `l` from the centre of `piece` with the bound of its one-point
/// rule: the rule where its bound is within `FAR` of the value
/// ([`crate::formfactor::far`]), Van Oosterom and Strackee's formula elsewhere (bound 0).
fn cone(piece: &Piece, e: &Elements, l: u32, small: &Small) -> (f64, f64) {
    match far::solid_angle(piece.at, small) {
        Some((w, b)) if b <= FAR * w => (w / PI, b / PI),
        _ => (
            solid_angle(piece.at, e.corners(l), e.normal[l as usize]) / PI,
            0.0,
        ),
    }
}

/// `A_l F_lS` of element `l` from the roots of node `n`, integrated (`emitter` is `l`'s
/// polygon, [`exact::Emitter`]), with the bound on its error and the point factors spent
/// ([`exact::Integral`]): `Σ_j e_j ∫_l F(x → P_j)
/// dA_x` over the roots `j` of `n`, with `F(x → P_j)` Lambert's point-to-polygon factor
/// and `e_j` the exposed share of root `j` (its visible area over its area: the sampled
/// points are weighted so, [`sample_points`]). By reciprocity `∫_l F(x → P_j) dA_x = A_j
/// F_jl`, the integral [`piece_factor`] samples. Each root's integral is held to `tol`
/// of its value, and not below `floor` (area units): the element links' quadrature
/// ([`super::link`], [`exact::integrate`]).
#[allow(clippy::too_many_arguments)]
pub fn exact_piece(
    t: &Tree,
    e: &Elements,
    visible: &[f64],
    n: u32,
    l: u32,
    emitter: &mut exact::Emitter,
    tol: f64,
    floor: f64,
) -> exact::Integral {
    let n_l = e.normal[l as usize];
    let mut out = exact::Integral::default();
    for &j in t.roots_of(n) {
        let ji = j as usize;
        let exposed = visible[ji] / e.area[ji].max(1e-300);
        if exposed <= 0.0 {
            continue;
        }
        let receiver = Receiver::new(e.corners(j), e.normal[ji], e.centre[ji]);
        let i = exact::integrate(emitter, n_l, &receiver, tol, floor, &|| {
            exact::Contact::Kinked
        });
        out.value += exposed * i.value.max(0.0);
        out.err += exposed * i.err;
        out.evals += i.evals;
    }
    out
}

/// A piece's point estimate `P Ω_c / π` with its rules' bound ([`piece_terms`]).
#[derive(Clone, Copy, Debug)]
struct Terms {
    base: f64,
    bound: f64,
    /// The element's area.
    area: f64,
}

/// The sum of a piece's point differences `d_k` and of their squares ([`Terms::factor`]).
#[derive(Clone, Copy, Debug, Default)]
struct Spread {
    k: usize,
    sum: f64,
    sum2: f64,
}

impl Spread {
    fn add(&mut self, d: f64) {
        self.k += 1;
        self.sum += d;
        self.sum2 += d * d;
    }
}

impl Terms {
    /// The factor through visible fraction `v` ([`piece_factor`]) from the points'
    /// differences: `d_k = w_k F(y_k → l) - w_k max(0, n_k·w) Ω_c / π`, the whole taken
    /// through `v`; or, where the element checked its own view of the points (`seen`,
    /// with `s_k` the weight each point's first term takes, [`Expansion::checked`]), `d_k
    /// = w_k F(y_k → l) s_k - v w_k max(0, n_k·w) Ω_c / π` and `A_l F = v P Ω_c / π + Σ_k
    /// d_k`: the same control variate with coefficient `v`, unbiased for the element's
    /// visible factor whatever `v` (docs/HIERARCHY.md, *A leaf's own view of a cluster*).
    fn factor(&self, v: f64, d: &Spread, seen: bool) -> PieceFactor {
        let kf = d.k as f64;
        // Variance of the sum of k terms, from their spread: k (Σd² - (Σd)²/k) / (k - 1).
        let var = if d.k > 1 {
            (kf * (d.sum2 - d.sum * d.sum / kf) / (kf - 1.0)).max(0.0)
        } else {
            0.0
        };
        let (f, se) = if seen {
            (v * self.base + d.sum, var.sqrt())
        } else {
            (v * (self.base + d.sum), v * var.sqrt())
        };
        PieceFactor {
            f: f / self.area,
            se: se / self.area,
            bound: v * self.bound / self.area,
        }
    }
}

/// Largest bound of a one-point rule, relative to its value, for [`piece_factor`] to take
/// it: the rules' error then stays two orders below the entry, and below the sampling's
/// standard error of its near-field correction.
pub const FAR: f64 = 1e-2;

/// What [`piece_factor`] returns.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PieceFactor {
    /// The factor.
    pub f: f64,
    /// The standard error of its sampling.
    pub se: f64,
    /// The bound on the one-point rules' error in it (0 where none was used).
    pub bound: f64,
}

/// Segments with which an element checks its view of a cluster link's source
/// (`Expansion::checked`).
pub const CHECK_POINTS: usize = 4;

/// Draws of a point of the element in front of a checked point's plane
/// ([`Expansion::checked`]).
const CHECK_TRIES: usize = 8;

/// What a leaf needs to trace its own view of a cluster link's source
/// ([`Expansion::entries`]).
pub struct Sight<'a> {
    /// Visibility queries.
    pub vis: &'a Visibility,
    /// What the link from node `src` (first argument), whose pieces' point estimates of
    /// the unoccluded factor to the element sum to `F` (second), adds to the element's
    /// radiosity where nothing hides it, in the tolerance's units. Taking the link's
    /// visible fraction `v` could be off by `max(v, 1 - v)` of that: the element may see
    /// anything from none to all of the source.
    pub score: &'a dyn Fn(u32, f64) -> f64,
    /// How much the links the element does not trace may move it by together: the loudest
    /// are traced until the others' scores sum to within it.
    pub budget: f64,
}

/// The cluster links with their sources cut into pieces: what an element gathers from
/// clusters ([`Expansion::entries`]).
pub struct Expansion<'a> {
    /// The cluster tree.
    pub tree: &'a Tree,
    /// The cluster links.
    pub links: &'a Links,
    /// Share of an element's tolerance that the links it takes at their own fractions may
    /// move it by together ([`Sight::budget`]; infinite: no check).
    pub sight: f64,
    /// Their sources' pieces ([`Refiner::all_pieces`]).
    pub pieces: Pieces,
    /// Visible area per element (the pieces' points are drawn by it).
    pub visible: Vec<f64>,
    /// Seed of the points' streams.
    pub seed: u64,
    /// Points per piece ([`POINTS`]).
    pub points: usize,
    /// Relative tolerance of a piece's unoccluded factor: a piece whose sampled factor's
    /// bar (twice its standard error plus its rules' bound) is wider is integrated over its
    /// roots instead ([`exact_piece`]). Infinite: the sampled factor, whose error the
    /// link's bound covers.
    pub quadrature: f64,
}

impl Expansion<'_> {
    /// The cluster links on the chain of `l`'s root (the root's own and its clusters') as
    /// `(source node, factor, standard error, bound)` entries appended to `out`, one per
    /// piece of the link's source ([`Refiner::pieces`], [`piece_factor`]), the standard
    /// error combining the visible fraction's and the piece's sampling, the bound the
    /// one-point rules'; nothing for a buried element. With `sight`, the element traces its
    /// own view of the loudest links' sources ([`Sight`], `Terms::factor`). Returns the
    /// rays cast and the point factors spent on pieces integrated
    /// ([`Expansion::quadrature`]; not the sampled points'). Called per element where its list is used, so that no list of every
    /// element's entries is held at once (at 10^5 triangles they were most of the bake's
    /// memory).
    pub fn entries(
        &self,
        e: &Elements,
        l: u32,
        out: &mut Vec<(u32, f64, f64, f64)>,
        cache: &mut PointCache,
        sight: Option<&Sight>,
    ) -> (u64, u64) {
        // No test of `self.links.is_empty()` here: this runs per leaf, and a node with no
        // links adds nothing below.
        if e.buried[l as usize] {
            return (0, 0);
        }
        let li = l as usize;
        let small = Small::new(e.corners(l), e.normal[li]);
        let PointCache { drawn, scratch } = cache;
        let Scratch {
            cones,
            scores,
            traced,
        } = scratch;
        // First every piece's point-source cone (its solid angle from the piece, with the
        // rule's bound), and every link's score from their point estimates `P Ω_c / π`:
        // which links are traced is decided over all of them.
        cones.clear();
        scores.clear();
        for node in chain(self.tree, e, l) {
            let links = self.links.into_node(node).iter().zip(self.pieces.of(node));
            for (k, ps) in links {
                let first = cones.len();
                cones.extend(ps.iter().map(|p| cone(p, e, l, &small)));
                if let Some(s) = sight {
                    let open: f64 = ps
                        .iter()
                        .zip(&cones[first..])
                        .map(|(p, c)| p.p * c.0)
                        .sum::<f64>()
                        / e.area[li];
                    scores.push((s.score)(k.src, open) * k.v.max(1.0 - k.v));
                }
            }
        }
        // The loudest links are traced until what the others could move the leaf by sums
        // to within the budget.
        traced.clear();
        traced.resize(scores.len(), false);
        if let Some(s) = sight.filter(|_| e.exposed[li] >= 1.0) {
            let mut left: f64 = scores.iter().sum();
            if left > s.budget {
                let mut order: Vec<usize> = (0..scores.len()).collect();
                order.sort_by(|&i, &j| scores[j].total_cmp(&scores[i]));
                for i in order {
                    if left <= s.budget {
                        break;
                    }
                    traced[i] = true;
                    left -= scores[i];
                }
            }
        }
        // Then the entries, link by link.
        let mut rays = 0;
        let (mut emitter, mut evals) = (None, 0);
        let (mut at_link, mut at_piece) = (0, 0);
        drawn.next_chain();
        for node in chain(self.tree, e, l) {
            let samples = drawn.of(node, || self.draw(e, node));
            let mut at = 0;
            let links = self.links.into_node(node).iter().zip(self.pieces.of(node));
            for (j, (k, ps)) in links.enumerate() {
                let own = traced.get(at_link).copied().unwrap_or(false);
                at_link += 1;
                let samples = &samples[at..at + ps.len()];
                at += ps.len();
                let link_cones = &cones[at_piece..at_piece + ps.len()];
                at_piece += ps.len();
                let rel = k.v_se / k.v.max(1e-300);
                if !own {
                    for ((p, pts), &c) in ps.iter().zip(samples).zip(link_cones) {
                        let mut d = Spread::default();
                        let t = piece_terms(p, c, pts, e, l, &small, |_, wg, fc| d.add(wg - fc));
                        let Some(mut t) = t else {
                            continue;
                        };
                        let mut pf = t.factor(k.v, &d, false);
                        if self.wants_integral(&pf) {
                            let i = self.integral(e, p.node, l, &mut emitter);
                            (t.base, t.bound) = (i.value, i.err);
                            evals += i.evals;
                            pf = t.factor(k.v, &Spread::default(), false);
                        }
                        if pf.f > 0.0 {
                            out.push((p.node, pf.f, (pf.f * rel).hypot(pf.se), pf.bound));
                        }
                    }
                    continue;
                }
                // Traced: every piece's point terms first, then the leaf's view of them.
                let Some(s) = sight else { continue };
                let mut points: Vec<(&Sample, f64, f64)> = Vec::new();
                let mut terms: SmallVec<[(u32, Terms); 4]> = ps
                    .iter()
                    .zip(samples)
                    .zip(link_cones)
                    .filter_map(|((p, pts), &c)| {
                        let t = piece_terms(p, c, pts, e, l, &small, |i, wg, fc| {
                            points.push((&pts[i], wg, fc))
                        });
                        Some((p.node, t?))
                    })
                    .collect();
                // A piece integrated instead of sampled: the integral is the control's
                // mean, and each point's own term its control (`Terms::factor`).
                if self.quadrature.is_finite() {
                    let mut at = 0;
                    for ((src, t), pts) in terms.iter_mut().zip(samples) {
                        let range = at..at + pts.len();
                        at += pts.len();
                        let mut d = Spread::default();
                        for &(_, wg, fc) in &points[range.clone()] {
                            d.add(wg - fc);
                        }
                        if self.wants_integral(&t.factor(k.v, &d, false)) {
                            let i = self.integral(e, *src, l, &mut emitter);
                            (t.base, t.bound) = (i.value, i.err);
                            evals += i.evals;
                            for point in &mut points[range] {
                                point.2 = point.1;
                            }
                        }
                    }
                }
                let seen = self.checked(s, e, l, (node, j), k.v, &points, &mut rays);
                let mut at = 0;
                for ((src, t), pts) in terms.iter().zip(samples) {
                    let (mut d, mut open_sum) = (Spread::default(), 0.0);
                    let range = at..at + pts.len();
                    for (&(_, wg, fc), &v_k) in points[range.clone()].iter().zip(&seen[range]) {
                        d.add(wg * v_k - k.v * fc);
                        open_sum += wg - fc;
                    }
                    at += pts.len();
                    let pf = t.factor(k.v, &d, true);
                    // The bar keeps the link's fraction's: the leaf's few segments found its
                    // view only where they went (as a checked element entry's bar is at
                    // least its own rays'). It is the fraction's standard error times the
                    // piece's unoccluded factor, as for an entry not traced: the traced
                    // factor times the fraction's relative bar would grow without bound
                    // where the link is almost hidden and the leaf sees the source (on
                    // `room-spheres-24`, links with `v` near 1e-7 gave a sphere leaf of
                    // radiosity 0.043 a bar of 7.9).
                    let open = ((t.base + open_sum) / t.area).abs();
                    let se = (open * k.v_se).hypot(pf.se);
                    // A traced estimate below 0 stays: it is unbiased only so.
                    if pf.f != 0.0 {
                        out.push((*src, pf.f, se, pf.bound));
                    }
                }
            }
        }
        (rays, evals)
    }

    /// True when a piece's sampled factor `pf` is less accurate than
    /// [`Expansion::quadrature`] asks, or its points all gave the same value (a standard
    /// error of 0 from a few points, as where every point lies on a root facing away from
    /// the leaf, says nothing of the piece's accuracy).
    fn wants_integral(&self, pf: &PieceFactor) -> bool {
        self.quadrature.is_finite()
            && (pf.se == 0.0 || 2.0 * pf.se + pf.bound > self.quadrature * pf.f.abs())
    }

    /// `A_l F_lS` of element `l` from node `n`, integrated to [`Expansion::quadrature`],
    /// with its error bound ([`exact_piece`]; `emitter` holds `l`'s polygon once made).
    fn integral(
        &self,
        e: &Elements,
        n: u32,
        l: u32,
        emitter: &mut Option<exact::Emitter>,
    ) -> exact::Integral {
        let em = emitter.get_or_insert_with(|| exact::Emitter::new(e.piece[l as usize]));
        let floor = 1e-15 * e.area[l as usize];
        exact_piece(
            self.tree,
            e,
            &self.visible,
            n,
            l,
            em,
            self.quadrature,
            floor,
        )
    }

    /// Element `l`'s own view of a link's `points` (each with its terms `w_k F(y_k → l)`
    /// and `w_k max(0, n_k·w) Ω_c / π`), as the weight each point's first term takes in
    /// [`Terms::factor`], checked by [`CHECK_POINTS`] segments to points drawn with
    /// probability proportional to their terms (stratified over their running sum `W`),
    /// each from a point drawn on `l`. With `V_k` the segment's answer and `e_k` the exposed
    /// fraction of the point's root (the points are drawn over whole roots; a point on a
    /// buried part is hidden from every leaf), the weight of a point drawn `c_k` times of
    /// `m` is `v + c_k W / (m w_k F(y_k → l)) (V_k / e_k - v)`, and `v`, the link's
    /// fraction, where not drawn ([`check_weights`]): its mean is `V_k / e_k`, so the
    /// estimate is unbiased for the element's own view, and it is the link's estimate
    /// where every answer agrees with `v`.
    #[allow(clippy::too_many_arguments)]
    fn checked(
        &self,
        sight: &Sight,
        e: &Elements,
        l: u32,
        key: (u32, usize),
        v: f64,
        points: &[(&Sample, f64, f64)],
        rays: &mut u64,
    ) -> Vec<f64> {
        let terms: Vec<f64> = points.iter().map(|&(_, wg, _)| wg).collect();
        if !terms.iter().any(|&t| t > 0.0) {
            return vec![v; terms.len()];
        }
        let mut rng = Pcg32::keyed(
            self.seed,
            0x4c43_484b_0000_0000 | u64::from(l),
            u64::from(key.0),
            key.1 as u64,
        );
        let drawn = check_draws(&terms, &mut rng);
        let n_l = e.normal[l as usize];
        let segs: SmallVec<[SegmentRay; CHECK_POINTS]> = drawn
            .iter()
            .map(|&k| {
                let s = points[k].0;
                let n_s = e.normal[s.root as usize];
                // A point of the element behind the source point's plane sees nothing of
                // it, and its term `F(y_k → l)` counts only the part in front (a leaf of
                // a sphere beside another): drawn again, up to `CHECK_TRIES` times.
                let mut at = e.point(l, rng.next_f64(), rng.next_f64()).0;
                for _ in 1..CHECK_TRIES {
                    if n_s.dot(at - s.at) > 0.0 {
                        break;
                    }
                    at = e.point(l, rng.next_f64(), rng.next_f64()).0;
                }
                sight.vis.segment_ray(at, n_l, s.at, n_s)
            })
            .collect();
        let mut free: SmallVec<[bool; CHECK_POINTS]> = smallvec::smallvec![false; segs.len()];
        sight.vis.segments_visible(&segs, &mut free);
        *rays += segs.len() as u64;
        let seen: SmallVec<[f64; CHECK_POINTS]> = drawn
            .iter()
            .zip(&free)
            .map(|(&k, &f)| {
                let r = points[k].0.root as usize;
                let exposed = self.visible[r] / e.area[r].max(1e-300);
                if f && exposed > 0.0 {
                    1.0 / exposed
                } else {
                    0.0
                }
            })
            .collect();
        check_weights(&terms, &drawn, &seen, v)
    }

    /// The near-field points of node `n`'s pieces, links in order, pieces in order
    /// ([`sample_points`], keyed on the node and the piece).
    fn draw(&self, e: &Elements, n: u32) -> Vec<Vec<Sample>> {
        let mut all = Vec::new();
        for ps in self.pieces.of(n) {
            for p in ps {
                all.push(sample_points(
                    self.tree,
                    e,
                    &self.visible,
                    self.seed,
                    self.points,
                    n,
                    p.node,
                    p.w,
                ));
            }
        }
        all
    }

    /// Entries [`Expansion::entries`] gives at most for element `l`: the pieces of the
    /// cluster links on its chain.
    pub fn pieces_on_chain(&self, e: &Elements, l: u32) -> usize {
        chain(self.tree, e, l)
            .map(|node| self.pieces.of(node).iter().map(Vec::len).sum::<usize>())
            .sum()
    }
}

/// [`CHECK_POINTS`] indices of `terms` (non-negative, not all 0) drawn with probability
/// proportional to them, stratified over their running sum ([`Expansion::checked`]).
fn check_draws(terms: &[f64], rng: &mut Pcg32) -> SmallVec<[usize; CHECK_POINTS]> {
    let total: f64 = terms.iter().map(|&t| t.max(0.0)).sum();
    // The last term above 0 (there is one), where the walk stops.
    let last = terms.iter().rposition(|&t| t > 0.0).unwrap_or(0);
    let m = CHECK_POINTS;
    let (mut k, mut below) = (0, 0.0);
    let mut drawn = SmallVec::new();
    for j in 0..m {
        let x = (j as f64 + rng.next_f64()) / m as f64 * total;
        while k < last && (terms[k] <= 0.0 || below + terms[k] <= x) {
            below += terms[k].max(0.0);
            k += 1;
        }
        drawn.push(k);
    }
    drawn
}

/// The weight of each of `terms` from the answers `seen` (`V_k / e_k`) at the `drawn`
/// indices ([`check_draws`]), around `v`: `v + c_k W / (m t_k) (seen_k - v)` for a term
/// `t_k` drawn `c_k` times of `m`, with `W` the terms' sum; `v` where not drawn. Its mean
/// over the draws is `seen_k` for every term above 0 (Horvitz and Thompson's estimator of
/// the difference from `v`).
fn check_weights(terms: &[f64], drawn: &[usize], seen: &[f64], v: f64) -> Vec<f64> {
    let total: f64 = terms.iter().map(|&t| t.max(0.0)).sum();
    let m = drawn.len() as f64;
    let mut weight = vec![v; terms.len()];
    for (&k, &s) in drawn.iter().zip(seen) {
        weight[k] += total / (m * terms[k]) * (s - v);
    }
    weight
}

/// The near-field points of the pieces of the links into recently used nodes
/// ([`Expansion::entries`]): a leaf's neighbours in element order share most of its chain
/// of clusters, and the points depend only on the node and the piece, so one thread draws
/// them once per run of leaves instead of once per leaf. Bounded: past
/// [`PointCache::NODES`] nodes, those the last two chains did not use are dropped (the
/// shared upper nodes, with the most links and points, stay; emptying the whole cache
/// made a tenth of the final gather's time at 10^6 triangles redrawing them).
#[derive(Debug, Default)]
pub struct PointCache {
    drawn: Drawn,
    scratch: Scratch,
}

/// The points of [`PointCache`].
#[derive(Debug, Default)]
struct Drawn {
    nodes: std::collections::HashMap<u32, (u64, Vec<Vec<Sample>>)>,
    chain: u64,
}

/// A thread's buffers for one element's cluster entries ([`Expansion::entries`]), kept
/// from element to element so that each does not allocate its own.
#[derive(Debug, Default)]
struct Scratch {
    /// Each piece's cone ([`cone`]), links in chain order.
    cones: Vec<(f64, f64)>,
    /// Each link's score ([`Sight::score`]), in chain order.
    scores: Vec<f64>,
    /// Whether each link is traced.
    traced: Vec<bool>,
}

impl PointCache {
    /// Most nodes held.
    pub const NODES: usize = 256;
}

impl Drawn {
    /// Starts the next chain.
    fn next_chain(&mut self) {
        self.chain += 1;
    }

    /// The points of node `n`'s pieces (links in order, pieces in order), drawn by `draw`
    /// when not held.
    fn of(&mut self, n: u32, draw: impl FnOnce() -> Vec<Vec<Sample>>) -> &[Vec<Sample>] {
        let now = self.chain;
        if !self.nodes.contains_key(&n) && self.nodes.len() >= PointCache::NODES {
            self.nodes.retain(|_, (used, _)| *used + 1 >= now);
        }
        let slot = self.nodes.entry(n).or_insert_with(|| (now, draw()));
        slot.0 = now;
        &slot.1
    }
}

/// Element `l`, the elements above it up to its root, and the clusters above the root,
/// as nodes, from `l` up.
fn chain<'a>(t: &'a Tree, e: &'a Elements, l: u32) -> impl Iterator<Item = u32> + 'a {
    let r = e.root[l as usize];
    let elements = std::iter::successors(Some(l), move |&k| {
        let p = e.parent[k as usize];
        (k != r && p != NONE).then_some(p)
    });
    let first = t.root_parent.get(r as usize).copied().unwrap_or(NONE);
    elements.chain(
        std::iter::successors((first != NONE).then_some(first), move |&c| {
            let p = t.parent[c as usize];
            (p != NONE).then_some(p)
        })
        .map(|c| c | CLUSTER),
    )
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::formfactor::exact::Piece as Shape2;

    /// An `n × n` floor of unit squares (z = 0, facing +z) and an `n × n` wall (x = 0,
    /// facing +x).
    pub(in crate::hierarchy) fn grid(n: usize) -> Elements {
        let mut e = Elements::default();
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (i as f64, j as f64);
                e.add_root(
                    Shape2::Quad([
                        DVec3::new(x, y, 0.0),
                        DVec3::new(x + 1.0, y, 0.0),
                        DVec3::new(x + 1.0, y + 1.0, 0.0),
                        DVec3::new(x, y + 1.0, 0.0),
                    ]),
                    DVec3::Z,
                );
                e.add_root(
                    Shape2::Quad([
                        DVec3::new(0.0, y, x),
                        DVec3::new(0.0, y + 1.0, x),
                        DVec3::new(0.0, y + 1.0, x + 1.0),
                        DVec3::new(0.0, y, x + 1.0),
                    ]),
                    DVec3::X,
                );
            }
        }
        e
    }

    #[test]
    fn projected_area_by_cones_is_the_sum_over_roots() {
        // Floor and wall of 6 x 6 roots each, in many directions: the cone shortcut gives
        // the root-by-root sum (to rounding), and opens few clusters far from the planes.
        let e = grid(6);
        let vis = e.visible_areas();
        let t = Tree::build(&e, &vis, &vec![0.5; e.roots]);
        let m = moments(&t, &e, &vis);
        let mut rng = Pcg32::keyed(7, 0, 0, 0);
        for _ in 0..500 {
            let w = loop {
                let v = DVec3::new(
                    2.0 * rng.next_f64() - 1.0,
                    2.0 * rng.next_f64() - 1.0,
                    2.0 * rng.next_f64() - 1.0,
                );
                if v.length() > 0.1 && v.length() <= 1.0 {
                    break v.normalize();
                }
            };
            for n in (0..t.len() as u32)
                .map(|c| c | CLUSTER)
                .chain(0..e.roots as u32)
            {
                let brute: f64 = t
                    .roots_of(n)
                    .iter()
                    .map(|&k| vis[k as usize] * e.normal[k as usize].dot(w).max(0.0))
                    .sum();
                let got = projected(&t, &e, &vis, &m, n, w);
                assert!(
                    (got - brute).abs() <= 1e-12 * (1.0 + brute),
                    "{got} vs {brute}"
                );
            }
        }
    }

    #[test]
    fn tree_areas_sum_and_bounds_hold_their_roots() {
        let e = grid(5);
        let vis = e.visible_areas();
        let t = Tree::build(&e, &vis, &vec![0.5; e.roots]);
        assert_eq!(t.len(), e.roots - 1);
        assert!((t.area[0] - 50.0).abs() < 1e-9, "{}", t.area[0]);
        for c in 0..t.len() {
            let kids: f64 = t.children[c]
                .iter()
                .map(|&k| {
                    if is_cluster(k) {
                        t.area[(k & !CLUSTER) as usize]
                    } else {
                        vis[k as usize]
                    }
                })
                .sum();
            assert!((kids - t.area[c]).abs() < 1e-9);
            let (centre, r) = t.sphere[c];
            for &m in t.roots_of(c as u32 | CLUSTER) {
                for &p in e.corners(m) {
                    assert!(p.distance(centre) <= r + 1e-12);
                }
                assert!(t.cone[c].1 <= e.normal[m as usize].dot(t.cone[c].0) + 1e-12);
            }
        }
        // Every root is a leaf of the tree exactly once.
        let mut seen = vec![0; e.roots];
        for c in 0..t.len() {
            for &k in &t.children[c] {
                if !is_cluster(k) {
                    seen[k as usize] += 1;
                }
            }
        }
        assert!(seen.iter().all(|&k| k == 1));
    }

    /// A unit square at height `z`, wound to face up (+z) or down.
    fn unit_square(z: f64, up: bool) -> Shape2 {
        let c = [
            DVec3::new(0.0, 0.0, z),
            DVec3::new(1.0, 0.0, z),
            DVec3::new(1.0, 1.0, z),
            DVec3::new(0.0, 1.0, z),
        ];
        if up {
            Shape2::Quad(c)
        } else {
            Shape2::Quad([c[0], c[3], c[2], c[1]])
        }
    }

    #[test]
    fn near_field_factor_is_unbiased_where_the_point_source_is_not() {
        // Two unit squares facing each other a distance c apart: the exact factor is
        // Howell's closed form; the point source at the centre overestimates it.
        for c in [0.25f64, 1.0, 4.0] {
            let mut e = Elements::default();
            e.add_root(unit_square(0.0, true), DVec3::Z);
            e.add_root(unit_square(c, false), -DVec3::Z);
            let vis = e.visible_areas();
            let t = Tree::build(&e, &vis, &[0.5, 0.5]);
            let exact = crate::analytic::parallel_rectangles(1.0, 1.0, c);
            let w = DVec3::Z;
            let piece = Piece {
                node: 0,
                at: e.centre[0],
                p: 1.0,
                w,
            };
            let small = Small::new(e.corners(1), e.normal[1]);
            let point = piece_factor(&piece, &[], 1.0, &e, 1, &small).f;
            assert!(point > exact * 1.01, "c {c}: point {point} vs {exact}");
            // Over many streams the mean is the exact factor, and each estimate's
            // standard error covers its spread.
            let runs = 400;
            let (mut sum, mut sq_err, mut se2) = (0.0, 0.0, 0.0);
            for r in 0..runs {
                let samples = sample_points(&t, &e, &vis, 1, POINTS, r, 0, w);
                let pf = piece_factor(&piece, &samples, 1.0, &e, 1, &small);
                let (f, se) = (pf.f, pf.se);
                sum += f;
                sq_err += (f - exact).powi(2);
                se2 += se * se;
            }
            let mean = sum / runs as f64;
            let (rms, se) = ((sq_err / runs as f64).sqrt(), (se2 / runs as f64).sqrt());
            assert!(
                (mean - exact).abs() < 4.0 * rms / (runs as f64).sqrt() + 1e-12,
                "c {c}: mean {mean} vs {exact} (rms {rms})"
            );
            assert!(rms <= 1.5 * se + 1e-12, "c {c}: rms {rms} vs se {se}");
        }
    }

    /// A leaf's own view of a link's points ([`Terms::factor`] with `seen`) is unbiased for
    /// its visible factor whatever the link's fraction it is estimated around: two unit
    /// squares facing each other with the half `x < 1/2` of the source hidden from the
    /// receiver, against a 400 × 200 midpoint rule of Lambert's point-to-polygon factor
    /// over the visible half, over 400 streams each, within 4 standard errors of the mean
    /// (a false alarm about once in 10^4 runs per case).
    #[test]
    fn a_leafs_own_view_of_a_cluster_is_unbiased() {
        for c in [0.25f64, 1.0] {
            let mut e = Elements::default();
            e.add_root(unit_square(0.0, true), DVec3::Z);
            e.add_root(unit_square(c, false), -DVec3::Z);
            let vis = e.visible_areas();
            let t = Tree::build(&e, &vis, &[0.5, 0.5]);
            let rec = Receiver::new(e.corners(1), e.normal[1], e.centre[1]);
            let (nx, ny) = (400, 200);
            let mut exact = 0.0;
            for i in 0..nx {
                for j in 0..ny {
                    let y = DVec3::new(
                        0.5 + (j as f64 + 0.5) * 0.5 / ny as f64,
                        (i as f64 + 0.5) / nx as f64,
                        0.0,
                    );
                    exact += point_factor(y, DVec3::Z, &rec) * 0.5 / (nx * ny) as f64;
                }
            }
            let piece = Piece {
                node: 0,
                at: e.centre[0],
                p: 1.0,
                w: DVec3::Z,
            };
            let small = Small::new(e.corners(1), e.normal[1]);
            for prior in [0.3, 1.0] {
                let runs = 400;
                let (mut sum, mut sq_err) = (0.0, 0.0);
                for r in 0..runs {
                    let samples = sample_points(&t, &e, &vis, 1, POINTS, r, 0, DVec3::Z);
                    // The leaf's view of each point: hidden where `x < 1/2`.
                    let mut d = Spread::default();
                    let c = cone(&piece, &e, 1, &small);
                    let terms = piece_terms(&piece, c, &samples, &e, 1, &small, |i, wg, fc| {
                        let v_k = f64::from(u8::from(samples[i].at.x >= 0.5));
                        d.add(wg * v_k - prior * fc)
                    })
                    .unwrap();
                    let f = terms.factor(prior, &d, true).f;
                    sum += f;
                    sq_err += (f - exact).powi(2);
                }
                let mean = sum / runs as f64;
                let rms = (sq_err / runs as f64).sqrt();
                assert!(
                    (mean - exact).abs() < 4.0 * rms / (runs as f64).sqrt(),
                    "c {c}, prior {prior}: mean {mean} vs {exact} (rms {rms})"
                );
            }
        }
    }

    /// A leaf's check of a cluster link ([`check_draws`], [`check_weights`]) is unbiased
    /// term by term whatever the link's fraction it is taken around: over 200,000 streams
    /// each term's mean weight is its answer `V_k / e_k` within 4.5 standard errors (6
    /// terms checked, a false alarm about once in 2·10^4 runs), every weight is the
    /// link's fraction where every answer is, and zero terms are never drawn.
    #[test]
    fn a_leafs_check_of_a_cluster_link_is_unbiased() {
        let terms = [0.5, 0.0, 2.0, 1.0, 0.1, 3.0, 0.0, 0.7];
        let seen_of = [0.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 1.25];
        let runs = 200_000;
        let (mut sum, mut sum2) = ([0.0; 8], [0.0; 8]);
        for r in 0..runs {
            let mut rng = Pcg32::keyed(7, r, 0, 0);
            let drawn = check_draws(&terms, &mut rng);
            assert!(drawn.iter().all(|&k| terms[k] > 0.0), "{drawn:?}");
            let ones = check_weights(&terms, &drawn, &[0.25; CHECK_POINTS], 0.25);
            assert!(ones.iter().all(|&w| w == 0.25), "{ones:?}");
            let seen: Vec<f64> = drawn.iter().map(|&k| seen_of[k]).collect();
            for (k, w) in check_weights(&terms, &drawn, &seen, 0.6)
                .into_iter()
                .enumerate()
            {
                sum[k] += w;
                sum2[k] += w * w;
            }
        }
        let n = runs as f64;
        for k in (0..8).filter(|&k| terms[k] > 0.0) {
            let mean = sum[k] / n;
            let se = ((sum2[k] / n - mean * mean).max(0.0) / n).sqrt();
            assert!(
                (mean - seen_of[k]).abs() <= 4.5 * se + 1e-12,
                "term {k}: mean weight {mean} vs {} (se {se})",
                seen_of[k]
            );
        }
    }

    #[test]
    fn solid_angle_of_a_rectangle_matches_its_closed_form() {
        // An a x b rectangle seen from height h above its centre:
        // Ω = 4 asin(ab / √((a² + 4h²)(b² + 4h²))).
        let (a, b) = (2.0f64, 1.0f64);
        let poly = [
            DVec3::new(-1.0, -0.5, 0.0),
            DVec3::new(1.0, -0.5, 0.0),
            DVec3::new(1.0, 0.5, 0.0),
            DVec3::new(-1.0, 0.5, 0.0),
        ];
        for h in [0.01f64, 0.3, 1.0, 10.0] {
            let exact =
                4.0 * (a * b / ((a * a + 4.0 * h * h) * (b * b + 4.0 * h * h)).sqrt()).asin();
            let got = solid_angle(DVec3::new(0.0, 0.0, h), &poly, DVec3::Z);
            assert!(
                (got - exact).abs() < 1e-12 * exact.max(1.0),
                "h {h}: {got} vs {exact}"
            );
            assert_eq!(solid_angle(DVec3::new(0.0, 0.0, -h), &poly, DVec3::Z), 0.0);
        }
    }

    #[test]
    fn cone_bound_is_a_bound() {
        let mut rng = Pcg32::keyed(7, 1, 2, 3);
        let unit = |rng: &mut Pcg32| {
            let z: f64 = 2.0 * rng.next_f64() - 1.0;
            let phi = std::f64::consts::TAU * rng.next_f64();
            let s = (1.0 - z * z).sqrt();
            DVec3::new(s * phi.cos(), s * phi.sin(), z)
        };
        for _ in 0..2000 {
            let axis = unit(&mut rng);
            let half: f64 = 1.2 * rng.next_f64();
            let w = unit(&mut rng);
            let alpha = 0.5 * rng.next_f64();
            let bound = max_cos((axis, half.cos()), w, alpha);
            // A normal in the cone and a direction within alpha of w.
            let n = (axis + half * rng.next_f64() * unit(&mut rng)).normalize();
            if n.dot(axis) < half.cos() {
                continue;
            }
            let u = (w + alpha * rng.next_f64() * unit(&mut rng)).normalize();
            if u.dot(w) < alpha.cos() {
                continue;
            }
            assert!(n.dot(u).max(0.0) <= bound + 1e-12);
        }
    }
}
