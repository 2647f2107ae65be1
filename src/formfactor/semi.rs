//! Semi-analytic form factors: the exact point-to-polygon factor, integrated over the
//! emitter, times a visible fraction estimated by rays.
//!
//! For patches i and j,
//!
//! `A_i F_ij = ∫_{A_i} F(x → P_j) v(x) dA_x`,
//!
//! where `F(x → P_j)` is the exact unoccluded differential-area-to-polygon factor
//! ([`crate::analytic::point_to_polygon`], Lambert's contour integral; Baum, Rushmeier and
//! Winget 1989) and `v(x)` the kernel-weighted visible fraction of `P_j` from `x`,
//! `v(x) = ∫ G V dA_y / ∫ G dA_y` with `G = cos θ_x cos θ_y / (π r²)`. Receivers are
//! one-sided: nodes behind `P_j`'s plane contribute 0.
//!
//! Each unordered pair is computed once ([`Estimator::upper_only`]): the integral is the
//! same from either side, `A_i F_ij = A_j F_ji`, so it is taken over the smaller patch and
//! both entries follow, reciprocal by construction.
//!
//! **Provably unoccluded pairs are integrated deterministically, to a tolerance, with no
//! rays** ([`super::exact`]: Gauss–Legendre of an a-priori order for far pairs,
//! tanh–sinh where the patches touch, both checked a posteriori); `v = 1` exactly there,
//! and the reported error is a *bound* ([`crate::matrix::Bar`], `bound.mtx`): the
//! quadrature check's estimate plus rounding ([`super::exact::rounding`]), which sums of
//! factors add linearly. With [`Nodes::Stratified`]
//! those pairs use random stratified nodes instead (for studies of the estimator).
//!
//! A patch k can block a segment from `x ∈ P_i` to `y ∈ P_j` only if it meets the convex
//! hull of the two patches. It cannot when it is a *hull face* (every corner of the scene
//! lies on or in front of its plane, or every one on or behind it: segments between scene
//! points never cross that plane, as for the walls of a convex room and the outer side of
//! two-sided walls; found once per scene), when all its corners lie on or behind the plane
//! of i or of j, when both patches lie wholly on one side of its plane, or
//! when its bounding box misses the box of the two patches. When every other patch is
//! excluded, the pair is unoccluded. The test is conservative (a box overlap does not prove
//! an occlusion), and costs nothing per pair in a convex room, where every patch is a hull
//! face. It runs in f64 with the tolerance [`PatchSet::plane_tol`] (relative to the scene,
//! far above rounding and far below real separations), so a scene and any scaling or rigid
//! motion of it take the same path.
//!
//! **Other pairs are sampled.** `points²` jittered nodes per replicate on the emitter (one
//! per stratum, uniform by area) and, at each node, `F(x → P_j) v(x)` estimated from rays to
//! `vis_rays²` jittered points `y_k` on the receiver (uniform by area, density `1/A_j`) by
//! subtracting what the blocked rays hide from the exact unoccluded factor:
//!
//! `F(x → P_j) v(x) ≈ F(x → P_j) - (A_j / n) Σ_k G(x, y_k) (1 - V(x, y_k))`.
//!
//! This is the plain Monte Carlo estimate of `∫ G V dA_y` with the exact `∫ G dA_y` as a
//! control variate of coefficient 1 (Glasserman, "Monte Carlo Methods in Financial
//! Engineering", 2003, §4.1): **unbiased** at any ray count, exact where every ray is free,
//! and its noise comes only from the blocked part. Nodes near their receiver (closer to its
//! centroid than its farthest corner) draw the rays' directions in proportion to the
//! kernel instead of their points by area (`SeenFrom`), so that each blocked ray hides
//! `F(x → P_j) / n` and the node's estimate is `F(x → P_j)` times its fraction of free
//! rays: the weights `A_j G` of points drawn by area grow without bound as the receiver
//! comes close, and left a long tail. For a near pair (the spheres about the two centroids
//! through their farthest corners overlap) the unoccluded integral `∫ F(x → P_j) dA_x` is
//! taken from the deterministic quadrature and the nodes estimate only what the blocked
//! rays hide, since nodes drawn over a patch that meets its receiver sample an integrand
//! that peaks at the contact. (The ratio estimator `F Σ G V / Σ G` has
//! about the same noise where the pair is mostly visible but an `O(1/n)` bias where it is
//! partly hidden, which the replicates do not see: with one ray per node its 2-bar coverage
//! is 0% on the occluded study pair.) A node's estimate may be negative where the pair is
//! almost wholly hidden; only the pair's total is clamped (a total `<= 0` is not stored), and
//! a pair whose every ray was blocked is hidden (factor 0, as the rays say, rather than the
//! noise of the control variate: no light through a closed wall). The
//! standard error is the standard deviation of the replicate means over `sqrt(R)`. Each
//! stream is keyed on `(seed, i, j, replicate)`, so the result does not depend on the thread
//! count.
//!
//! Pairs with one patch wholly behind the other's plane are culled without rays, as in
//! [`super::area`].

use std::f64::consts::PI;
use std::sync::{Arc, Mutex};

use glam::DVec3;

use super::exact::{self, Contact, Emitter, Piece, Receiver};
use super::shard::{self, cost};
use super::{kernel, Context, Entry, Estimator, Row, Scratch as Buffers};
use crate::mesh::PatchSet;
use crate::sampling::{fraction_se, jittered, Pcg32, SphericalTriangle};
use crate::visibility::{Rays, Segments, Tracer, SEGMENT_TFAR};

/// How the nodes `x` on the emitter are placed for pairs that nothing can block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Nodes {
    /// Deterministic quadrature to the relative tolerance [`SemiAnalytic::tol`].
    Gauss,
    /// A jittered point per stratum, drawn anew in every replicate.
    Stratified,
}

/// Per-scene data for the occlusion test, computed once per patch set.
#[derive(Debug)]
struct Prepared {
    /// Fingerprint of the patch set it was computed for.
    key: u64,
    /// Bounding box of every patch.
    boxes: Vec<(DVec3, DVec3)>,
    /// Patches that are not hull faces: the only possible blockers.
    blockers: Vec<u32>,
}

/// Semi-analytic estimator: exact point-to-polygon factors times ray-estimated visibility.
#[derive(Debug)]
pub struct SemiAnalytic {
    /// Node placement on the emitter for pairs nothing can block.
    pub nodes: Nodes,
    /// Nodes per side on the emitter for sampled pairs: `points²` nodes per replicate.
    pub points: usize,
    /// Visibility strata per side: `vis_rays²` rays per node, for pairs not provably
    /// unoccluded.
    pub vis_rays: usize,
    /// Independent replicates (>= 2) for the standard error of sampled pairs.
    pub replicates: usize,
    /// Relative tolerance of the deterministic integral of unoccluded pairs.
    pub tol: f64,
    cache: Mutex<Option<Arc<Prepared>>>,
}

impl Clone for SemiAnalytic {
    fn clone(&self) -> Self {
        SemiAnalytic::new(self.nodes, self.points, self.vis_rays, self.replicates)
            .with_tol(self.tol)
    }
}

impl Default for SemiAnalytic {
    fn default() -> Self {
        SemiAnalytic::new(Nodes::Gauss, 4, 4, 4)
    }
}

impl SemiAnalytic {
    /// Default relative tolerance of unoccluded pairs.
    pub const DEFAULT_TOL: f64 = 1e-6;

    /// An estimator with [`SemiAnalytic::DEFAULT_TOL`].
    pub fn new(nodes: Nodes, points: usize, vis_rays: usize, replicates: usize) -> Self {
        SemiAnalytic {
            nodes,
            points,
            vis_rays,
            replicates,
            tol: Self::DEFAULT_TOL,
            cache: Mutex::new(None),
        }
    }

    /// The same with relative tolerance `tol` for unoccluded pairs.
    pub fn with_tol(mut self, tol: f64) -> Self {
        self.tol = tol;
        self
    }
}

/// Corners of patch `i`.
fn corners(p: &PatchSet, i: usize) -> ([DVec3; 4], usize) {
    p.corner_points(i)
}

/// Patch `i`'s reach: its farthest corner's distance from its centroid.
fn reach_of(p: &PatchSet, i: usize) -> f64 {
    let (c, k) = corners(p, i);
    c[..k]
        .iter()
        .map(|c| c.distance(p.centroid[i]))
        .fold(0.0, f64::max)
}

/// Signed distances of the corners of `b` from the plane of `a`, as (min, max). It runs
/// several times for each of the N² pairs, so the corners are read in place
/// ([`PatchSet::corner_iter`]).
#[inline]
fn plane_range(p: &PatchSet, a: usize, b: usize) -> (f64, f64) {
    let (n, c) = (p.normal[a], p.centroid[a]);
    p.corner_iter(b)
        .map(|q| n.dot(q - c))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), d| {
            (lo.min(d), hi.max(d))
        })
}

/// Axis-aligned bounding box of patch `i`'s corners.
fn bounds(p: &PatchSet, i: usize) -> (DVec3, DVec3) {
    let (pts, k) = p.corner_points(i);
    pts[..k]
        .iter()
        .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(lo, hi), &q| {
            (lo.min(q), hi.max(q))
        })
}

/// FNV-1a over the patch count and centroids: tells one patch set from another.
fn fingerprint(p: &PatchSet) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64 ^ p.len() as u64;
    for c in &p.centroid {
        for x in c.to_array() {
            h = (h ^ x.to_bits()).wrapping_mul(0x100_0000_01b3);
        }
    }
    h
}

impl Prepared {
    fn new(p: &PatchSet, key: u64) -> Prepared {
        let tol = p.plane_tol();
        let boxes: Vec<(DVec3, DVec3)> = (0..p.len()).map(|k| bounds(p, k)).collect();
        let (lo, hi) = boxes
            .iter()
            .fold((DVec3::INFINITY, DVec3::NEG_INFINITY), |(a, b), &(l, h)| {
                (a.min(l), b.max(h))
            });
        let corners: Vec<DVec3> = (0..p.len())
            .flat_map(|k| {
                let (c, n) = p.corner_points(k);
                c.into_iter().take(n)
            })
            .collect();
        let blockers = (0..p.len())
            .filter(|&k| {
                let (n, c) = (p.normal[k], p.centroid[k]);
                // Lower bound of min n·(q - c) over the scene's box: proves most walls at
                // once; otherwise scan the corners, stopping at the first one behind.
                let bound = (n * lo).min(n * hi).element_sum() - n.dot(c);
                let hull = bound >= -tol || corners.iter().all(|&q| n.dot(q - c) >= -tol);
                // The whole scene behind the plane (the outer side of a two-sided wall)
                // blocks nothing either: no segment crosses that plane.
                let upper = (n * lo).max(n * hi).element_sum() - n.dot(c);
                let shell = upper <= tol || corners.iter().all(|&q| n.dot(q - c) <= tol);
                !(hull || shell)
            })
            .map(|k| k as u32)
            .collect();
        Prepared {
            key,
            boxes,
            blockers,
        }
    }
}

impl SemiAnalytic {
    /// The per-scene data for `p`, computed on first use.
    fn prepared(&self, p: &PatchSet) -> Arc<Prepared> {
        let key = fingerprint(p);
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        match &*cache {
            Some(prep) if prep.key == key => prep.clone(),
            _ => {
                let prep = Arc::new(Prepared::new(p, key));
                *cache = Some(prep.clone());
                prep
            }
        }
    }

    /// True when no other patch can block any segment between patches `i` and `j` (see
    /// the module docs). `others` are the candidate blockers: the blockers with a corner
    /// strictly in front of i ([`blockers_of`]), or all of them (those not in front of i are
    /// then skipped here, tested only where the other tests leave them as blockers).
    fn unoccluded(
        &self,
        p: &PatchSet,
        i: usize,
        j: usize,
        others: &[u32],
        boxes: &[(DVec3, DVec3)],
    ) -> bool {
        let tol = p.plane_tol();
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
            // Both patches wholly on one side of k's plane: segments between them cannot
            // cross that plane, so k cannot block.
            let (ki, kj) = (plane_range(p, k, i), plane_range(p, k, j));
            (ki.0 >= -tol && kj.0 >= -tol)
                || (ki.1 <= tol && kj.1 <= tol)
                || k == i
                || plane_range(p, i, k).1 <= tol
        })
    }
}

/// The scene's possible blockers, for the pairs of one patch `a` handed over one by one
/// ([`SemiAnalytic::blockers`]).
pub(crate) struct Blockers {
    a: usize,
    prep: Arc<Prepared>,
}

/// Possible blockers of anything leaving `i`: not hull faces, a corner in front of i.
fn blockers_of(p: &PatchSet, prep: &Prepared, i: usize) -> Vec<u32> {
    let tol = p.plane_tol();
    prep.blockers
        .iter()
        .copied()
        .filter(|&k| k as usize != i && plane_range(p, i, k as usize).1 > tol)
        .collect()
}

/// The part of a convex polygon on the front side of the plane through `c` with normal
/// `n` (Sutherland–Hodgman against one plane).
fn clip_front(poly: &[DVec3], n: DVec3, c: DVec3) -> Vec<DVec3> {
    let mut out = Vec::with_capacity(poly.len() + 1);
    exact::clip_above(poly, n, n.dot(c), |p| out.push(p));
    out
}

impl Estimator for SemiAnalytic {
    fn name(&self) -> String {
        let kind = match self.nodes {
            Nodes::Gauss => "semi-gauss",
            Nodes::Stratified => "semi-stratified",
        };
        let (p, v) = (self.points, self.vis_rays);
        format!(
            "{kind}(tol={:.0e}, points={p}x{p}x{}, vis={v}x{v})",
            self.tol,
            self.replicates.max(2)
        )
    }

    fn upper_only(&self) -> bool {
        true
    }

    fn replicates(&self) -> usize {
        self.replicates.max(2)
    }

    fn row(&self, ctx: &Context, i: usize, row: &mut Row, scratch: &mut Buffers) {
        self.row_with(ctx, i, row, ctx.vis, scratch);
    }

    /// A sample of the row's pairs ([`shard::sampled_row_cost`]) sorted as the row sorts
    /// them: culled; provably unoccluded, at the evaluations the a-priori quadrature order
    /// implies ([`exact::expected_evals`]); or sampled, at `replicates x points²` nodes of
    /// one evaluation and `vis_rays²` rays each; plus the row's blocker list.
    fn row_costs(&self, ctx: &Context, rows: std::ops::Range<usize>) -> Vec<f64> {
        use rayon::prelude::*;
        let prep = self.prepared(ctx.patches);
        rows.into_par_iter()
            .map(|i| self.row_cost(ctx.patches, &prep, i))
            .collect()
    }
}

impl SemiAnalytic {
    /// [`Estimator::row_costs`] of row `i`.
    fn row_cost(&self, p: &PatchSet, prep: &Prepared, i: usize) -> f64 {
        let tol = p.plane_tol();
        let others = blockers_of(p, prep, i);
        let (m, v) = (self.points.max(1), self.vis_rays.max(1));
        let nodes = (self.replicates.max(2) * m * m) as f64;
        let sampled = cost::PAIR + nodes * (cost::EVAL + (v * v) as f64 * cost::RAY);
        let pairs = shard::sampled_row_cost(i, p.len(), |j| {
            if plane_range(p, i, j).1 <= tol || plane_range(p, j, i).1 <= tol {
                return cost::CULL;
            }
            let free = self.unoccluded(p, i, j, &others, &prep.boxes);
            if !(free && self.nodes == Nodes::Gauss) {
                return sampled;
            }
            let (e, r) = if p.area[j] < p.area[i] {
                (j, i)
            } else {
                (i, j)
            };
            let ((ce, ke), (cr, kr)) = (corners(p, e), corners(p, r));
            let piece = if ke == 3 {
                Piece::Tri([ce[0], ce[1], ce[2]])
            } else {
                Piece::Quad(ce)
            };
            cost::PAIR + cost::EVAL * exact::expected_evals(piece, &cr[..kr], self.tol)
        });
        cost::ROW + others.len() as f64 * cost::CULL + pairs
    }
}

/// Buffers of the sampled pairs, reused between pairs and rows (in the driver's
/// [`super::Scratch`]).
#[derive(Default)]
pub(crate) struct Scratch {
    strata: Vec<(f64, f64)>,
    ys: Vec<(f64, f64)>,
    /// Every node of a pair (replicate after replicate), its factor, and each replicate's
    /// random stream after the nodes were drawn.
    xs: Vec<DVec3>,
    fs: Vec<f64>,
    rngs: Vec<Pcg32>,
    /// Every node of a pair: its replicate, `F(x → P_r)` and the end of its rays.
    nodes: Vec<(u32, f64, usize)>,
    /// The pair's segment rays (node after node), as structure of arrays, and their
    /// kernels.
    org: [Vec<f32>; 3],
    dir: [Vec<f32>; 3],
    gs: Vec<f64>,
    seen: Vec<bool>,
    means: Vec<f64>,
}

impl SemiAnalytic {
    /// Row `i`, entries `j > i` ([`Estimator::upper_only`]), with `tracer` answering
    /// visibility for batches of segment rays
    /// ([`crate::visibility::Visibility::segment_ray`], one batch per sampled pair); the
    /// rays asked for do not depend on the answers, so a recorder sees the exact ray set.
    pub fn row_with(
        &self,
        ctx: &Context,
        i: usize,
        row: &mut Row,
        tracer: &dyn Tracer,
        buffers: &mut Buffers,
    ) {
        let p = ctx.patches;
        let prep = self.prepared(p);
        let others = blockers_of(p, &prep, i);
        let scratch = &mut buffers.semi;
        // Patch i's Gauss nodes, mapped once for all the receivers it emits towards.
        let mut own: Option<Emitter> = None;
        for j in i + 1..p.len() {
            if let Some(e) = self.pair_entry(
                ctx,
                (i, j),
                (&others, &prep),
                &mut own,
                row,
                tracer,
                scratch,
            ) {
                row.entries.push(e);
            }
        }
    }

    /// The entry `F_ij` of the unordered pair `(i, j)`, `i < j` (`F_ji` follows by
    /// reciprocity), or `None` when the pair is culled or sees nothing; `row.rays` counts
    /// the rays. `others` are the candidate blockers of [`SemiAnalytic::unoccluded`];
    /// `own` caches patch i's Gauss nodes.
    #[allow(clippy::too_many_arguments)]
    fn pair_entry(
        &self,
        ctx: &Context,
        (i, j): (usize, usize),
        (others, prep): (&[u32], &Prepared),
        own: &mut Option<Emitter>,
        row: &mut Row,
        tracer: &dyn Tracer,
        scratch: &mut Scratch,
    ) -> Option<Entry> {
        let p = ctx.patches;
        let tol = p.plane_tol();
        if plane_range(p, i, j).1 <= tol || plane_range(p, j, i).1 <= tol {
            return None;
        }
        let free = self.unoccluded(p, i, j, others, &prep.boxes);
        // The integral A_i F_ij = A_j F_ji, over the smaller patch.
        let (e, r) = if p.area[j] < p.area[i] {
            (j, i)
        } else {
            (i, j)
        };
        let area_i = p.area[i];
        if free && self.nodes == Nodes::Gauss {
            // Deterministic: the error is bounded, not random ([`crate::matrix::Bar`]).
            let got = self.exact_pair(p, e, r, if e == i { Some(own) } else { None });
            return (got.value > 0.0)
                .then(|| Entry::bounded(j as u32, got.value / area_i, got.err / area_i));
        }
        let (value, se) = self.sampled_pair(ctx, (i, j), (e, r), free, row, tracer, scratch);
        (value > 0.0).then(|| Entry {
            j: j as u32,
            f: value / area_i,
            se: se / area_i,
        })
    }

    /// The possible blockers of the pairs `(a, b > a)`, for [`SemiAnalytic::single_pair`]:
    /// the scene's, looked up once for all of a's pairs. They are not narrowed to those in
    /// front of a ([`blockers_of`], a scan of every blocker): a row hands over few pairs,
    /// and [`SemiAnalytic::unoccluded`] tests that only for the blockers its cheaper tests
    /// leave.
    pub(crate) fn blockers(&self, p: &PatchSet, a: usize) -> Blockers {
        Blockers {
            a,
            prep: self.prepared(p),
        }
    }

    /// The entry `F_ab` of one unordered pair `(a, b)`, `a < b`, computed on its own (for
    /// estimators that hand this estimator the pairs they cannot sample well, such as
    /// patches that touch: [`super::area`]); as [`SemiAnalytic::pair_entry`]. `blockers`
    /// are a's ([`SemiAnalytic::blockers`]).
    pub(crate) fn single_pair(
        &self,
        ctx: &Context,
        (a, b): (usize, usize),
        blockers: &Blockers,
        row: &mut Row,
        tracer: &dyn Tracer,
        scratch: &mut Scratch,
    ) -> Option<Entry> {
        debug_assert_eq!(blockers.a, a);
        self.pair_entry(
            ctx,
            (a, b),
            (&blockers.prep.blockers, &blockers.prep),
            &mut None,
            row,
            tracer,
            scratch,
        )
    }

    /// `∫_{A_e} F(x → P_r) dA_x` for an unoccluded pair, to the tolerance. `cache`, when
    /// given, holds patch `e`'s emitter (and its mapped nodes) across calls.
    fn exact_pair(
        &self,
        p: &PatchSet,
        e: usize,
        r: usize,
        cache: Option<&mut Option<Emitter>>,
    ) -> exact::Integral {
        let tol = p.plane_tol();
        let (cr, kr) = corners(p, r);
        let n_e = p.normal[e].normalize();
        let recv = Receiver::new(&cr[..kr], p.normal[r], p.centroid[r]);
        // Below this the integral is not worth chasing: 1e-15 of the scale of the factor.
        let floor = 1e-15 * p.area[e] * p.area[r] / (p.diagonal * p.diagonal);
        let (ce, ke) = corners(p, e);
        let whole = |ce: [DVec3; 4]| {
            if ke == 3 {
                Piece::Tri([ce[0], ce[1], ce[2]])
            } else {
                Piece::Quad(ce)
            }
        };
        if plane_range(p, r, e).0 < -tol {
            // The emitter straddles the receiver's plane: only its part in front sees the
            // receiver, and the integrand drops to 0 across the plane, which a rule over
            // the whole patch resolves badly. Integrate over the clipped part.
            let front = clip_front(&ce[..ke], recv.normal, recv.centroid);
            let mut total = exact::Integral::default();
            for k in 1..front.len().saturating_sub(1) {
                let mut em = Emitter::new(Piece::Tri([front[0], front[k], front[k + 1]]));
                total +=
                    exact::integrate(&mut em, n_e, &recv, self.tol, floor, &|| Contact::Kinked);
            }
            return total;
        }
        let contact = || {
            exact::contact(
                &ce[..ke],
                (n_e, p.centroid[e]),
                &cr[..kr],
                (p.normal[r].normalize(), p.centroid[r]),
                tol,
            )
        };
        match cache {
            Some(slot) => {
                let em = slot.get_or_insert_with(|| Emitter::new(whole(ce)));
                exact::integrate(em, n_e, &recv, self.tol, floor, &contact)
            }
            None => exact::integrate(
                &mut Emitter::new(whole(ce)),
                n_e,
                &recv,
                self.tol,
                floor,
                &contact,
            ),
        }
    }

    /// Sampled estimate of `∫_{A_e} F(x → P_r) v(x) dA_x` and its standard error.
    ///
    /// The nodes of every replicate are drawn first, with their segment rays where
    /// something may block (the rays do not depend on the answers), and traced as one
    /// batch: the pair's rays go to Embree in full packets of 16 (rays from nearby nodes
    /// to one receiver are coherent), not four at a time. The sums then run node by node
    /// in the order of the draws.
    #[allow(clippy::too_many_arguments)]
    fn sampled_pair(
        &self,
        ctx: &Context,
        (i, j): (usize, usize),
        (e, r): (usize, usize),
        free: bool,
        row: &mut Row,
        tracer: &dyn Tracer,
        s: &mut Scratch,
    ) -> (f64, f64) {
        let p = ctx.patches;
        let reps = self.replicates.max(2);
        let m = self.points.max(1);
        let (cr, kr) = corners(p, r);
        let (n_e, n_r) = (p.normal[e], p.normal[r]);
        let recv = Receiver::new(&cr[..kr], n_r, p.centroid[r]);
        let n_x = n_e.normalize();
        // The receiver's reach from its centroid, for [`NEAR_REACH`].
        let centroid_r = p.centroid[r];
        let reach = reach_of(p, r);
        // A near pair (the patches' spheres about their centroids through their farthest
        // corners overlap): its unoccluded integral exactly, so that the nodes estimate only
        // what the blocked rays hide. Nodes drawn over a patch that meets or nearly meets
        // its receiver sample an integrand that peaks at the contact, and the replicates
        // seldom see the peak.
        let near = p.centroid[e].distance(centroid_r) < reach_of(p, e) + reach;
        let exact = (!free && near).then(|| self.exact_pair(p, e, r, None));
        let (on_e, on_r) = (p.sampler(e), p.sampler(r));
        let w = p.area[e] / (m * m) as f64;
        let area_r = p.area[r];
        // Every node of every replicate: its factor `F(x → P_r)` and the end of its rays.
        s.nodes.clear();
        s.org.iter_mut().chain(&mut s.dir).for_each(Vec::clear);
        s.gs.clear();
        let per_node = self.vis_rays.max(1).pow(2);
        // The nodes of every replicate first, each from its replicate's stream, and their
        // factors in one vector batch ([`exact::point_factors`], the same values as one
        // at a time); then each node's rays, from the same streams in the same order.
        s.xs.clear();
        s.rngs.clear();
        for rep in 0..reps {
            let mut rng = Pcg32::keyed(ctx.seed, i as u64, j as u64, rep as u64);
            jittered(&mut rng, m, &mut s.strata);
            s.xs.extend(s.strata.iter().map(|&(u, v)| on_e.point(u, v)));
            s.rngs.push(rng);
        }
        exact::point_factors(&s.xs, n_x, &recv, &mut s.fs);
        let per_rep = s.xs.len() / reps;
        for rep in 0..reps {
            let rng = &mut s.rngs[rep];
            for k in rep * per_rep..(rep + 1) * per_rep {
                let (xf, f) = (s.xs[k], s.fs[k]);
                if f <= 0.0 {
                    continue;
                }
                if !free {
                    jittered(rng, self.vis_rays.max(1), &mut s.ys);
                    // Directions drawn in proportion to the kernel for a node near the
                    // receiver ([`NEAR_REACH`]), unless the receiver lies nearly edge-on to
                    // the node's plane ([`SeenFrom`]); points by area otherwise.
                    let seen_from = (xf.distance(centroid_r) < NEAR_REACH * reach)
                        .then(|| SeenFrom::new(xf, &cr[..kr]))
                        .flatten()
                        .filter(|sf| PI * f >= MIN_MEAN_COS * sf.omega);
                    for &(u, v) in &s.ys {
                        // The point y the ray aims at, and what the ray hides when blocked:
                        // `F(x → P_r)` for a direction drawn by the kernel, `A_r G(x, y)`
                        // for a point drawn by area.
                        let aimed = match &seen_from {
                            Some(sf) => sf.draw((u, v), rng, n_x, n_r).map(|y| (y, f)),
                            None => {
                                let y = on_r.point(u, v);
                                kernel(xf, n_e, y, n_r).map(|g| (y, area_r * g))
                            }
                        };
                        if let Some((y, weight)) = aimed {
                            let (o, d, _) = ctx.vis.segment_ray(xf, n_e, y, n_r);
                            for c in 0..3 {
                                s.org[c].push(o[c]);
                                s.dir[c].push(d[c]);
                            }
                            s.gs.push(weight);
                        }
                    }
                }
                s.nodes.push((rep as u32, f, s.gs.len()));
            }
        }
        let rays = s.gs.len();
        row.rays += rays as u64;
        s.seen.clear();
        s.seen.resize(rays, false);
        if rays > 0 {
            let (o, d) = (&s.org, &s.dir);
            let segs = Segments {
                rays: Rays {
                    org: [&o[0], &o[1], &o[2]],
                    dir: [&d[0], &d[1], &d[2]],
                },
                tfar: SEGMENT_TFAR,
            };
            tracer.segments_visible(&segs, &mut s.seen);
        }
        if !free && !s.seen.iter().any(|&v| v) {
            // Every ray blocked: the pair is taken as hidden, as the blocked rays say (the
            // control variate would leave the noise of its own estimate of the unoccluded
            // factor: light through a closed wall, or a negative factor).
            return (0.0, 0.0);
        }
        s.means.clear();
        s.means.resize(reps, 0.0);
        let mut lo = 0;
        for &(rep, f, hi) in &s.nodes {
            // `F(x → P_r) v(x)`: exact when nothing can block.
            let seen = if free {
                f
            } else {
                // What the blocked rays hide, `∫ G (1 - V) dA_y`, each ray's point weighed
                // by the kernel over its density ([`SeenFrom`]); every drawn point counts,
                // those with G = 0 as 0.
                let hidden: f64 = s.gs[lo..hi]
                    .iter()
                    .zip(&s.seen[lo..hi])
                    .filter(|&(_, &seen)| !seen)
                    .map(|(&g, _)| g)
                    .sum();
                let hidden = hidden / per_node as f64;
                if exact.is_some() {
                    -hidden
                } else {
                    f - hidden
                }
            };
            s.means[rep as usize] += w * seen;
            lo = hi;
        }
        let avg = s.means.iter().sum::<f64>() / reps as f64;
        let var = s.means.iter().map(|v| (v - avg).powi(2)).sum::<f64>() / (reps - 1) as f64;
        let se = (var / reps as f64).sqrt();
        match exact {
            // The quadrature's bound, far below the sampled part's error, joins it in
            // quadrature ([`crate::matrix::Bar`]). Rays that all arrived do not make the
            // pair unoccluded: they say that the hidden share is below about `1 / n` of
            // `n` rays, the bar of a fraction all of whose trials came out the same
            // ([`fraction_se`]).
            Some(x) => {
                let se = if rays > 0 && s.seen.iter().all(|&v| v) {
                    se.max(x.value * fraction_se(1.0, rays as f64))
                } else {
                    se
                };
                (x.value + avg, se.hypot(x.err))
            }
            None => (avg, se),
        }
    }
}

/// Nodes closer to a receiver's centroid than this many times its reach (the farthest
/// corner's distance from the centroid) draw their rays by [`SeenFrom`]. Farther ones draw
/// points by area: their weights `A_r G(x, y)` stay within a few times the factor (short
/// of a node right by a corner), and points stratified over the receiver keep a blocker
/// that splits it from adding noise; directions drawn by [`SeenFrom`] lose most of that
/// stratification to its rejections (on two unit squares 1 apart split by a divider, the
/// estimates' spread was 2.7 times as wide with every node drawing so; docs/ESTIMATORS.md).
const NEAR_REACH: f64 = 1.0;

/// Least mean cosine `π F(x → P_r) / Ω` over a receiver's solid angle for which
/// [`SeenFrom::draw`] draws its directions; below it (a receiver nearly edge-on to the node's
/// plane) the node draws points by area.
const MIN_MEAN_COS: f64 = 1.0 / 16.0;

/// Most candidate directions [`SeenFrom::draw`] tries for one ray: with a mean cosine of at
/// least [`MIN_MEAN_COS`], all of them are rejected with probability below `7e-8`.
const MAX_DRAWS: usize = 256;

/// A receiver as seen from an emitter's node: the spherical triangles of its corners, for
/// visibility rays drawn in proportion to the kernel.
///
/// Points drawn uniformly by area weigh each blocked ray by `A_r G(x, y)`, which grows as
/// `1 / r²` where the receiver comes close to the node (patches meeting at an edge, or a
/// node a hair from its receiver): a rare ray there hides hundreds of times the factor, so
/// the estimate's distribution has a long tail that a few replicates do not show. On two
/// unit squares meeting at an edge under a lid 0.1 above one of them (semi at 3 x 3 nodes,
/// 2 x 2 rays, 4 replicates; docs/ESTIMATORS.md) 35 of 400 seeds were more than 3 standard
/// errors from the closed form where Student's t with 3 degrees of freedom allows 23.
///
/// Here a direction is drawn uniformly in the receiver's solid angle (Arvo 1995, through
/// [`SphericalTriangle`]) and kept with probability `cos θ_x` (else another is drawn):
/// the directions kept have the density `cos θ_x / (π F(x → P_r))`, the kernel's own, so
/// that every ray carries the same share of the factor and the node's estimate is
/// `F(x → P_r)` times the fraction of its rays that arrive: 0 when all are blocked, exact
/// when none is, never more than the factor, and unbiased. The first candidate of each
/// ray is its jittered stratum's point; the later ones are uniform, which leaves the
/// expected density of all the rays kept in proportion to `cos θ_x`.
struct SeenFrom {
    x: DVec3,
    tris: [Option<SphericalTriangle>; 2],
    /// The receiver's corner 0, which both triangles share, and each triangle's normal.
    corner: DVec3,
    normals: [DVec3; 2],
    /// The first triangle's share of the solid angle, and the whole.
    first: f64,
    omega: f64,
}

impl SeenFrom {
    /// The receiver with corners `corners` (3 or 4, a convex planar polygon) seen from `x`,
    /// or `None` when it subtends no solid angle to sample.
    fn new(x: DVec3, corners: &[DVec3]) -> Option<SeenFrom> {
        let d = |k: usize| (corners[k] - x).normalize_or_zero();
        let first = SphericalTriangle::new(d(0), d(1), d(2));
        let second = if corners.len() == 4 {
            SphericalTriangle::new(d(0), d(2), d(3))
        } else {
            None
        };
        let area = |t: &Option<SphericalTriangle>| t.as_ref().map_or(0.0, |t| t.area());
        let (a0, a1) = (area(&first), area(&second));
        let omega = a0 + a1;
        let normal = |k: usize| (corners[k - 1] - corners[0]).cross(corners[k] - corners[0]);
        (omega > 0.0 && omega.is_finite()).then_some(SeenFrom {
            x,
            tris: [first, second],
            corner: corners[0],
            normals: [
                normal(2),
                if corners.len() == 4 {
                    normal(3)
                } else {
                    DVec3::ZERO
                },
            ],
            first: a0 / omega,
            omega,
        })
    }

    /// The direction of `(u, v)` in the unit square, mapped onto the solid angle (the
    /// first triangle taking the share `first` of `u`), and the triangle it lies in.
    fn direction(&self, u: f64, v: f64) -> Option<(DVec3, usize)> {
        let (k, u) = match self.tris {
            [Some(_), _] if u < self.first => (0, u / self.first),
            [_, Some(_)] => (1, ((u - self.first) / (1.0 - self.first)).clamp(0.0, 1.0)),
            [Some(_), None] => (0, u),
            [None, None] => return None,
        };
        Some((self.tris[k]?.sample(u, v), k))
    }

    /// A point of the receiver in a direction drawn with density `cos θ_x / (π F)`: the
    /// first candidate from `(u, v)`, the later ones from `rng`; `None` when
    /// [`MAX_DRAWS`] candidates were all rejected (the ray is then not cast, and counts as
    /// arriving). `n_x` is the node's unit normal, `n_r` the receiver's.
    fn draw(&self, (u, v): (f64, f64), rng: &mut Pcg32, n_x: DVec3, n_r: DVec3) -> Option<DVec3> {
        let (mut u, mut v) = (u, v);
        for _ in 0..MAX_DRAWS {
            if let Some((w, k)) = self.direction(u, v) {
                let cos_x = w.dot(n_x);
                if cos_x > 0.0 && w.dot(n_r) < 0.0 && rng.next_f64() < cos_x {
                    // Where the direction meets the sampled triangle's plane.
                    let m = self.normals[k];
                    let t = (self.corner - self.x).dot(m) / w.dot(m);
                    if t > 0.0 && t.is_finite() {
                        return Some(self.x + t * w);
                    }
                }
            }
            (u, v) = (rng.next_f64(), rng.next_f64());
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::analytic::{parallel_rectangles, perpendicular_rectangles};
    use crate::formfactor::{compute, Context};
    use crate::mesh::{PatchSet, Resolution};
    use crate::scene::Scene;
    use crate::visibility::Visibility;

    /// Two unit squares meeting at an edge (A on the floor, B standing on its edge) under
    /// a lid `0.03` over A: only B's strip below the lid sees A, and from it nothing is in
    /// the way, so `A_B F_BA = 0.03 F(strip → A)` (Howell C-14). Over 300 seeds the
    /// estimates' mean is within 4 standard errors of the mean of it. Points drawn by area
    /// at every node failed this by far (over 1,000 seeds: mean 0.0242 against 0.0142,
    /// 15 standard errors of the mean): a ray from a node by the edge to the strip weighs
    /// `A G`, hundreds of times the factor, and whatever is left when every ray is blocked
    /// counts as a hidden pair.
    #[test]
    fn a_sliver_seen_past_a_lid_is_unbiased() {
        let h = 0.03;
        let dir = std::env::temp_dir().join(format!("semi-sliver-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let obj = format!(
            "o A\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n\
             o B\nv 0 0 0\nv 0 0 1\nv 0 1 1\nv 0 1 0\nf 5 8 7 6\n\
             o Lid\nv 0 0 {h}\nv 0 1 {h}\nv 1 1 {h}\nv 1 0 {h}\nf 9 10 11 12\n"
        );
        let path = dir.join("sliver.obj");
        std::fs::write(&path, obj).unwrap();
        let scene = Scene::load(path.to_str().unwrap()).unwrap();
        std::fs::remove_dir_all(&dir).ok();
        let p = PatchSet::build(&scene, Resolution::MaxEdge(10.0)).unwrap();
        assert_eq!(p.len(), 3);
        let vis = Visibility::new(&p).unwrap();
        let want = h * perpendicular_rectangles(1.0, 1.0, h);
        let est = SemiAnalytic::default();
        let seeds = 300;
        let got: Vec<f64> = (1..=seeds)
            .map(|seed| {
                let ctx = Context {
                    patches: &p,
                    vis: &vis,
                    seed,
                };
                compute(&ctx, &est, &|_| {}).get(1, 0)
            })
            .collect();
        let n = seeds as f64;
        let mean = got.iter().sum::<f64>() / n;
        let sd = (got.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        assert!(
            (mean - want).abs() < 4.0 * sd / n.sqrt(),
            "mean {mean} ± {} against {want}",
            sd / n.sqrt()
        );
    }

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

    /// The facing pairs of the Cornell box at 400 patches that are near (`near`) or not,
    /// each integrated at 1e-2 and 1e-6 and compared with the same integral to 1e-9: the
    /// failures (pairs whose value is off by more than its bound plus the reference's).
    fn bounds_failures(near: bool) -> Vec<String> {
        let scene = Scene::load("cornell").unwrap();
        let p = PatchSet::build(&scene, Resolution::Patches(400)).unwrap();
        let tight = SemiAnalytic::default().with_tol(1e-9);
        let tol = p.plane_tol();
        let mut pairs = Vec::new();
        for a in 0..p.len() {
            let (ca, ka) = corners(&p, a);
            for b in a + 1..p.len() {
                let (cb, kb) = corners(&p, b);
                let facing = plane_range(&p, a, b).1 > tol && plane_range(&p, b, a).1 > tol;
                if facing && super::super::area::near(&p, (a, &ca[..ka]), (b, &cb[..kb])) == near {
                    pairs.push(if p.area[b] < p.area[a] {
                        (b, a)
                    } else {
                        (a, b)
                    });
                }
            }
        }
        let least = if near { 800 } else { 10_000 };
        assert!(pairs.len() > least, "{} pairs", pairs.len());
        let want: Vec<_> = pairs
            .iter()
            .map(|&(e, r)| tight.exact_pair(&p, e, r, None))
            .collect();
        let mut failures = Vec::new();
        for loose in [1e-2, 1e-6] {
            let est = SemiAnalytic::default().with_tol(loose);
            let (mut outside, mut worst, mut evals, mut closest) = (0, 0.0f64, 0, 0.0f64);
            for (&(e, r), want) in pairs.iter().zip(&want) {
                let got = est.exact_pair(&p, e, r, None);
                evals += got.evals;
                let off = (got.value - want.value).abs();
                let allowed = got.err + want.err + 1e-9 * want.value.abs();
                closest = closest.max(off / allowed);
                if off > allowed {
                    outside += 1;
                    worst = worst.max(off / allowed);
                    if outside > 20 {
                        continue; // the first 20 are shown
                    }
                    eprintln!(
                        "tol {loose:.0e}, pair ({e}, {r}): {} ± {:.2e} ({} point factors) \
                         against {} ± {:.2e}",
                        got.value, got.err, got.evals, want.value, want.err
                    );
                }
            }
            eprintln!(
                "tol {loose:.0e}: {outside} of {} pairs outside (worst {worst:.2}x), largest \
                 error / bound {closest:.3}, {evals} point factors",
                pairs.len()
            );
            if outside > 0 {
                failures.push(format!(
                    "tol {loose:.0e}: {outside} of {} pairs outside their bounds, by up to \
                     {worst:.2}x",
                    pairs.len()
                ));
            }
        }
        failures
    }

    /// The deterministic bounds of the near pairs' integrals are bounds: on every near pair
    /// of the Cornell box at 400 patches (walls meeting at edges, the blocks standing on
    /// the floor across its patches), at the area estimators' loose tolerance (1e-2) and
    /// the semi-analytic estimator's default (1e-6), each integral must lie within its
    /// bound (plus the reference's) of the same integral to 1e-9. Before the far rules were
    /// checked one and two orders below with a safety factor of 16, and near pieces' bounds
    /// held to at least their tolerance unless the patches meet along whole edges or at
    /// corners ([`exact::Contact`]), 43 pairs were outside at 1e-2 (by up to 7.3 times) and
    /// 69 at 1e-6 (up to 28.5 times).
    #[test]
    fn near_pairs_are_within_their_bounds() {
        let failures = bounds_failures(true);
        assert!(failures.is_empty(), "{}", failures.join("; "));
    }

    /// The same for the far pairs (every facing pair of the Cornell box at 400 patches that
    /// is not near: a-priori Gauss orders): each integral within its bound (plus the
    /// reference's) of the same integral to 1e-9, at 1e-2 and 1e-6.
    ///
    /// Before far pieces reported at least their tolerance, 1,181 of the 50,168 far pairs
    /// were outside at 1e-2 (by up to 1,184 times: at the a-priori order 2 the check
    /// against the one-point rule sees no rate) and 16 at 1e-6 (up to 2.4 times: the
    /// errors along the two parameters cancelling in the lower rules) and 3 more at 1e-6
    /// (up to 18.5 times: emitters clipped by the slanted, warped wall's plane, where the
    /// point factor's absolute value has a kink). With the floor alone, one of these stayed
    /// outside (1.28 times; its value off by 1.28e-6 of itself); the point factor signed
    /// by the receiver's winding ([`exact::Receiver::new`]) removed it, and a fifth of the
    /// point factors at 1e-6 (1,667,170 to 1,303,182).
    #[test]
    fn far_pairs_are_within_their_bounds() {
        let failures = bounds_failures(false);
        assert!(failures.is_empty(), "{}", failures.join("; "));
    }

    #[test]
    fn plates_match_closed_forms() {
        let est = SemiAnalytic::new(Nodes::Gauss, 12, 4, 2);
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
        let est = SemiAnalytic::new(Nodes::Stratified, 8, 2, 16);
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
        let est = SemiAnalytic::new(Nodes::Gauss, 8, 3, 2);
        let ff = compute(&ctx, &est, &|_| {});
        assert_eq!(ff.rays, 0);
        for i in 0..patches.len() {
            let s = ff.row_sum(i);
            assert!((s - 1.0).abs() < 1e-6, "row {i} sums to {s}");
        }
    }

    /// The Cornell box (occluding blocks): agrees with area-to-area Monte Carlo within
    /// the combined error bars (both are unbiased).
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
        let semi = SemiAnalytic::new(Nodes::Stratified, 6, 4, 8);
        let mc = AreaMc::new(Pattern::Stratified, 24, 8);
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
