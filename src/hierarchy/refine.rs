//! Refinement: which links are good enough, and which element to split when one is not.
//!
//! **Brightness-weighted error** (Hanrahan, Salzman and Aupperle 1991, section 5,
//! "BF refinement", with the receiver-variation and source-spread terms of Holzschuch and
//! Sillion, "An exhaustive error-bounding algorithm for hierarchical radiosity", Computer
//! Graphics Forum 1998, in their simplest form). A link `r ← s` brings the receiver
//! `ρ_r F_rs B_s`; treating it as one constant over the receiver, from one mean source
//! radiosity, errs by about
//!
//! `ε_rs = max over channels of ρ_r (B_s ΔF_rs + ΔB_s F_rs)`,
//!
//! with `ΔF_rs` the variation of the visible point factor over the receiver
//! ([`super::link`]) and `ΔB_s` the spread of the solved radiosity below the source. A
//! link is refined while `ε_rs` exceeds the receiver's tolerance ([`Relative`]) and an
//! element can still be split without going under the minimum area. Which one: the source when its spread
//! dominates the error, else the larger of the two (the receiver on a tie), as in HSA.
//! Partial links have `ΔF` equal to the largest point factor, so shadow boundaries refine
//! first and furthest.
//!
//! **Contacts.** Where a patch stands on another (an edge of one lying in the other's
//! plane, inside it, the rest of the patch in front: a box on a floor), the elements of
//! the lower patch that the contact line crosses are split down to the minimum area before
//! any link is made, so that no element straddles a contact ([`contacts`],
//! [`split_along_contacts`]); the elements of the standing patch along the contact edge
//! are split as finely, the factor between the two being singular there ([`standing`]). Leaves that no ray can reach, such as floor under the box,
//! are then marked buried ([`bury`]).

use glam::DVec3;
use rayon::prelude::*;

use super::blockers::{bounds, range, BoxTree};
use super::element::Elements;
use super::link::Link;
use crate::formfactor::hemisphere::{basis, cosine_direction};
use crate::sampling::Pcg32;
use crate::visibility::Visibility;

/// What to do with a link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    /// Good enough (or nothing can be split).
    Keep,
    /// Replace by links from the source to the receiver's four children.
    SplitReceiver,
    /// Replace by links from the source's four children.
    SplitSource,
}

/// The link tolerance of each receiver, per channel:
/// `ε_r = error × clamp(B_r, low × B̄, high × B̄)`, with `B_r` the receiver's current
/// radiosity and `B̄` the scene's mean radiosity (luminance).
///
/// With `low = high = 1` this is the absolute tolerance `error × B̄` of HSA's BF
/// refinement: every link may then err by the same radiosity, which is a large *relative*
/// error on a dark receiver (the Cornell box's mean includes the light, so a block's face
/// toward the opening, 1/20 of `B̄`, was allowed 20 times the relative error of the mean).
/// With `low < 1` a receiver darker than the mean is held to the same relative error as
/// the others, down to the floor `low × B̄` (so that unlit or black receivers do not refine
/// without end); with `high > 1`, receivers brighter than the mean are let off in
/// proportion, up to `high × B̄`. This is the simplest form of a receiver-relative
/// criterion: a Weber fraction, where Gibson and Hubbold ("Perceptually-driven radiosity",
/// Computer Graphics Forum 16(2), 1997) stop refinement once successive levels differ by
/// less than a perceptually noticeable amount at the receiver's (tone-mapped) brightness.
/// Before the first solve no receiver's radiosity is known (it is its emission): every
/// receiver is then taken at the mean ([`Relative::unknown`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Relative {
    /// The tolerance relative to the receiver's radiosity (`--error`).
    pub error: f64,
    /// The scene's mean radiosity `B̄`.
    pub mean: f64,
    /// Floor of the receiver's radiosity, as a share of `B̄`.
    pub low: f64,
    /// Cap of the receiver's radiosity, as a share of `B̄`.
    pub high: f64,
}

impl Relative {
    /// The absolute tolerance `error × mean` of a receiver of unknown radiosity, or of
    /// every receiver when `low = high = 1`.
    pub fn absolute(&self) -> f64 {
        self.error * self.mean
    }

    /// The same tolerance for receivers whose radiosity is not known yet: every one at the
    /// mean (`low = high = 1`).
    pub fn unknown(&self) -> Relative {
        Relative {
            low: 1.0,
            high: 1.0,
            ..*self
        }
    }

    /// The tolerance per channel of a receiver of radiosity `b`.
    pub fn eps(&self, b: [f64; 3]) -> [f64; 3] {
        let (lo, hi) = (self.low * self.mean, self.high * self.mean);
        b.map(|x| self.error * x.max(lo).min(hi))
    }

    /// The same as one tolerance and channel weights: the loosest channel's tolerance
    /// `ε`, and per channel `k_c = ε / ε_c` (≥ 1; exactly 1 for every channel when they
    /// share one tolerance), so that an error `x_c` is within channel `c`'s tolerance when
    /// `k_c x_c ≤ ε`.
    pub fn weights(&self, b: [f64; 3]) -> (f64, [f64; 3]) {
        let eps = self.eps(b);
        let top = eps.iter().copied().fold(0.0, f64::max);
        let k = eps.map(|x| if x > 0.0 { top / x } else { 0.0 });
        (top, k)
    }
}

/// The oracle's inputs for one link.
pub struct Oracle<'a> {
    /// The elements.
    pub elements: &'a Elements,
    /// Reflectance per element.
    pub rho: &'a [[f64; 3]],
    /// Current radiosity per element.
    pub b: &'a [[f64; 3]],
    /// Spread of leaf radiosity below each element.
    pub spread: &'a [[f64; 3]],
    /// Tolerance on transported radiosity, per receiver.
    pub tol: Relative,
    /// No element is split into children smaller than this.
    pub min_area: f64,
    /// Split a receiver whose shadows vary across it by more than its tolerance
    /// ([`Oracle::shadowed`]; [`super::Settings::split_shadows`]).
    pub shadows: bool,
    /// Visibility strata per side of a link: `rays²` rays, half of them from each half of
    /// the receiver along either parameter ([`Link::tilt`]).
    pub rays: usize,
}

impl Oracle<'_> {
    /// The brightness-weighted error of link `l` into receiver `r`, split into the
    /// receiver-variation and source-spread terms (the channel maxima of each, each
    /// channel weighted by [`Relative::weights`]), and the receiver's tolerance: the link
    /// is good enough when the two terms add up to at most the tolerance.
    pub fn error(&self, r: u32, l: &Link) -> (f64, f64, f64) {
        let (rho, bs, ds) = (
            self.rho[r as usize],
            self.b[l.src as usize],
            self.spread[l.src as usize],
        );
        let (eps, k) = self.tol.weights(self.b[r as usize]);
        let (mut var, mut spr) = (0.0f64, 0.0f64);
        for c in 0..3 {
            var = var.max(rho[c] * bs[c] * l.df * k[c]);
            spr = spr.max(rho[c] * ds[c] * l.open * k[c]);
        }
        (var, spr, eps)
    }

    /// True when `e` may be split.
    pub fn splittable(&self, e: u32) -> bool {
        self.elements.area[e as usize] / 4.0 >= self.min_area
    }

    /// True when the shadows on receiver `r` from its own links `links` vary across it by
    /// more than its tolerance, beyond the noise of the rays that saw them.
    ///
    /// A link refined by splitting its larger element splits a large light first; each of
    /// its pieces' partly visible links then falls within the tolerance on its own (its
    /// error `ρ B F_max` shrinks with the piece), while their shadow boundaries, which all
    /// run across the same receiver, add up there. So the shadow's contrast is judged per
    /// receiver: each partly visible link's change of irradiance across the receiver is
    /// about `ρ_r B_s F_rs t`, with `t` its tilt ([`Link::tilt`], per receiver parameter,
    /// signed), and these add as vectors over the links,
    ///
    /// `G = Σ_l ρ_r B_l F_l t_l`,
    ///
    /// where the shadows of many light pieces line up and the rays' noise does not. Each
    /// tilt is a difference of two binomial fractions of `n²/2` rays, with variance
    /// `4 v (1 - v) / n²` (`v` the link's visible fraction); the receiver is shadowed when
    /// `|G| - Z σ_G > c ε_r` ([`SHADOW_Z`], [`SHADOW_CONTRAST`]), and then each of its
    /// partly visible links goes to its four children, whatever its own error. Where the
    /// receiver is smaller than the penumbra the tilts fall with its size and the
    /// splitting stops; a sharp shadow is followed down to the minimum area along its
    /// boundary only.
    pub fn shadowed(&self, r: u32, links: &[Link]) -> bool {
        if !self.shadows || !self.splittable(r) {
            return false;
        }
        let rho = self.rho[r as usize];
        let (eps, k) = self.tol.weights(self.b[r as usize]);
        let n2 = (self.rays * self.rays).max(1) as f64;
        let (mut g, mut var) = ([0.0f64; 2], 0.0f64);
        for l in links.iter().filter(|l| l.partial) {
            let bs = self.b[l.src as usize];
            let w = (0..3).map(|c| rho[c] * bs[c] * k[c]).fold(0.0, f64::max) * l.open;
            let t = l.tilt.get();
            g[0] += w * t[0];
            g[1] += w * t[1];
            let v = l.vis.clamp(0.0, 1.0);
            var += w * w * 4.0 * v * (1.0 - v) / n2;
        }
        let (g, sd) = ((g[0] * g[0] + g[1] * g[1]).sqrt(), var.sqrt());
        g - SHADOW_Z * sd > SHADOW_CONTRAST * eps
    }

    /// What to do with link `l` into `r`; `shadowed` is [`Oracle::shadowed`] of `r`.
    pub fn decide(&self, r: u32, l: &Link, shadowed: bool) -> Decision {
        if l.basis == crate::hierarchy::link::Basis::Roulette {
            // Hidden within the hide share: its leaves gather it by Russian roulette;
            // refining it would spend rays on light the tolerance lets go.
            return Decision::Keep;
        }
        if shadowed && l.partial {
            return Decision::SplitReceiver;
        }
        let (var, spr, eps) = self.error(r, l);
        if var + spr <= eps {
            return Decision::Keep;
        }
        let (r_ok, s_ok) = (self.splittable(r), self.splittable(l.src));
        let a = &self.elements.area;
        match (r_ok, s_ok) {
            (false, false) => Decision::Keep,
            (true, false) => Decision::SplitReceiver,
            (false, true) => Decision::SplitSource,
            (true, true) => {
                if spr > var || a[l.src as usize] > a[r as usize] {
                    Decision::SplitSource
                } else {
                    Decision::SplitReceiver
                }
            }
        }
    }
}

/// Standard errors of a receiver's summed shadow tilt that its size must exceed, beyond
/// the tolerance, for [`Oracle::shadowed`] to split it: two, for one side of a test at
/// about 2%.
pub const SHADOW_Z: f64 = 2.0;

/// How many times its tolerance the shadows' contrast across a receiver must be for
/// [`Oracle::shadowed`] to split it. The output's vertex values are planes fitted
/// through the leaves around each vertex, so a vertex on a leaf whose light changes by
/// `G` across it errs by about `G / 2`. Measured (docs/HIERARCHY.md, *Shadows across
/// receivers*): on the Cornell box at `--error 0.01`, 2 instead of 1 takes the rays from
/// 67.2 M to 51.3 M with every point by the blocks and in the shadow still within 2%.
pub const SHADOW_CONTRAST: f64 = 2.0;

/// A contact segment on a root patch: the end points of an edge of another patch that
/// lies in this patch's plane.
pub type Contact = (DVec3, DVec3);

/// The contact segments of every root: for roots `r` and `s` not parallel, each edge of
/// `s` whose two ends lie in the plane of `r` (within `tol`), with the rest of `s` on or in
/// front of it. Segments along the boundary of `r` are kept too; [`crosses`] tells apart
/// those that cut through an element.
pub fn contacts(e: &Elements, tol: f64) -> Vec<Vec<Contact>> {
    let n = e.roots;
    let boxes: Vec<(DVec3, DVec3)> = (0..n as u32).map(|k| bounds(e.corners(k))).collect();
    let tree = BoxTree::new(&boxes, (0..n as u32).collect());
    (0..n)
        .into_par_iter()
        .map(|r| {
            let plane = (e.normal[r], e.centre[r]);
            let (lo, hi) = (boxes[r].0 - tol, boxes[r].1 + tol);
            let mut out = Vec::new();
            let mut near = Vec::new();
            tree.overlapping(&boxes, lo, hi, &mut near);
            for s in near.into_iter().map(|s| s as usize) {
                if s == r || e.normal[r].dot(e.normal[s]).abs() > 1.0 - 1e-9 {
                    continue;
                }
                let c = e.corners(s as u32);
                if range(plane, c).0 < -tol {
                    continue;
                }
                for k in 0..c.len() {
                    let (a, b) = (c[k], c[(k + 1) % c.len()]);
                    let on = |p: DVec3| plane.0.dot(p - plane.1).abs() <= tol;
                    if on(a) && on(b) {
                        out.push((a, b));
                    }
                }
            }
            out
        })
        .collect()
}

/// True when the segment `seg` passes through the interior of element `el` (its plane
/// holding the segment): the segment clipped to the element shrunk by `tol` is not empty
/// (Cyrus–Beck clipping against each edge's inward half-plane).
pub fn crosses(e: &Elements, el: u32, seg: Contact, tol: f64) -> bool {
    let poly = e.corners(el);
    let n = e.normal[el as usize];
    let (a, d) = (seg.0, seg.1 - seg.0);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..poly.len() {
        let (p, q) = (poly[k], poly[(k + 1) % poly.len()]);
        let m = n.cross(q - p);
        let len = m.length();
        if len == 0.0 {
            continue;
        }
        let m = m / len;
        // Inside: m·(x - p) >= tol.
        let (num, den) = (m.dot(a - p) - tol, m.dot(d));
        if den == 0.0 {
            if num < 0.0 {
                return false;
            }
        } else {
            let t = -num / den;
            if den > 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
        if t0 >= t1 {
            return false;
        }
    }
    t1 - t0 > 1e-12
}

/// The contact edges seen from the standing side: for each root `s`, its own edges that
/// [`contacts`] found lying in another root's plane (the foot of a box's side on the
/// floor). The factor between the two sides is singular along such an edge, so the
/// standing side is refined along it as finely as the side it stands on.
pub fn standing(e: &Elements, contacts: &[Vec<Contact>], tol: f64) -> Vec<Vec<Contact>> {
    let mut out: Vec<Vec<Contact>> = vec![Vec::new(); e.roots];
    let boxes: Vec<(DVec3, DVec3)> = (0..e.roots as u32).map(|k| bounds(e.corners(k))).collect();
    let tree = BoxTree::new(&boxes, (0..e.roots as u32).collect());
    let mut near = Vec::new();
    for segs in contacts {
        for &(a, b) in segs {
            // An edge holding both ends has them in its box.
            near.clear();
            tree.overlapping(&boxes, a.min(b) - tol, a.max(b) + tol, &mut near);
            for &s in &near {
                let list = &mut out[s as usize];
                let c = e.corners(s);
                let on_edge = (0..c.len()).any(|k| {
                    let (p, q) = (c[k], c[(k + 1) % c.len()]);
                    (p.distance(a) <= tol && q.distance(b) <= tol)
                        || (p.distance(b) <= tol && q.distance(a) <= tol)
                });
                if on_edge {
                    list.push((a, b));
                }
            }
        }
    }
    out
}

/// Splits, down to `min_area`, every element that a contact of its root crosses (or, with
/// a negative `tol`, touches: the element grown by `|tol|`); returns the number of splits.
pub fn split_along_contacts(
    e: &mut Elements,
    contacts: &[Vec<Contact>],
    min_area: f64,
    tol: f64,
) -> usize {
    let mut splits = 0;
    let mut stack: Vec<u32> = Vec::new();
    for root in 0..e.roots as u32 {
        let segs = &contacts[root as usize];
        if segs.is_empty() {
            continue;
        }
        stack.clear();
        stack.push(root);
        while let Some(el) = stack.pop() {
            let crossed = segs.iter().any(|&s| crosses(e, el, s, tol));
            if e.area[el as usize] / 4.0 < min_area {
                e.partly[el as usize] |= crossed && e.is_leaf(el);
                continue;
            }
            if crossed {
                splits += usize::from(e.is_leaf(el));
                let kids = e.split(el);
                // Reverse, so that children are visited in order.
                stack.extend(kids.iter().rev());
            }
        }
    }
    splits
}

/// Rays per leaf of the buried test.
pub const BURY_RAYS: usize = 16;

/// Strata per side of the grid that measures a partly buried leaf's exposed fraction:
/// `EXPOSED_RAYS²` rays, one from a jittered point of each stratum.
pub const EXPOSED_RAYS: usize = 16;

/// A leaf less exposed than this counts as buried: its visible part is under a
/// sixteenth of the leaf (of the smallest elements, where contacts cross), and fewer than
/// one in sixteen of any of its rays would start there.
pub const MIN_EXPOSED: f64 = 1.0 / 16.0;

/// Which of `n × n` rays from leaf `el` (a jittered point in each stratum of its
/// parameter square when `grid`, else `n²` independent points; cosine-weighted directions)
/// meet the back of a patch first: those points lie inside a closed solid.
fn back_hits(
    e: &Elements,
    el: u32,
    vis: &Visibility,
    normals: &[DVec3],
    mut rng: Pcg32,
    n: usize,
    grid: bool,
) -> Vec<bool> {
    let nr = e.normal[el as usize];
    let (t, b) = basis(nr.as_vec3());
    let (t, b) = (t.as_dvec3(), b.as_dvec3());
    let inv = 1.0 / n as f64;
    (0..n * n)
        .map(|k| {
            let (u, v) = if grid {
                let (a, c) = ((k % n) as f64, (k / n) as f64);
                ((a + rng.next_f64()) * inv, (c + rng.next_f64()) * inv)
            } else {
                (rng.next_f64(), rng.next_f64())
            };
            let (x, _) = e.point(el, u, v);
            let d = cosine_direction(rng.next_f64(), rng.next_f64()).as_dvec3();
            let dir = (t * d.x + b * d.y + nr * d.z).normalize();
            match vis.first_hit(x, nr, dir) {
                Some(h) => normals[h.patch as usize].dot(dir) > 0.0,
                None => false,
            }
        })
        .collect()
}

/// The exposed fraction from the flags of an `n × n` stratified grid (`n` even), and its
/// standard error by collapsed strata (Cochran, *Sampling Techniques*, 3rd ed., §5A.12):
/// strata paired along `u`, `var ≈ Σ_pairs (y_a − y_b)² / N²` with `N = n²`, `y` 1 for an
/// exposed point.
fn exposed_fraction(back: &[bool]) -> (f64, f64) {
    let m = back.len() as f64;
    let exposed = back.iter().filter(|&&b| !b).count() as f64 / m;
    let var: f64 = back
        .chunks_exact(2)
        .map(|p| f64::from(u8::from(p[0] != p[1])))
        .sum::<f64>()
        / (m * m);
    (exposed, var.sqrt())
}

/// Marks as buried each leaf of `leaves` from which all of [`BURY_RAYS`] rays (random
/// points, cosine-weighted directions) meet the back of a patch: its whole surface lies
/// inside a closed solid. A ray that escapes or meets a front side proves its point is
/// surface (from outside every solid, the first face a ray meets shows its front). When
/// some rays do and others meet a back side, or a contact crosses the leaf, the leaf is
/// *partly* buried ([`Elements::partly`]) and its exposed fraction
/// ([`Elements::exposed`]) is measured with [`EXPOSED_RAYS`]² stratified rays, one point
/// each: the share of its area that receives and emits (under [`MIN_EXPOSED`], the leaf
/// counts as buried). Returns the number buried and the rays cast.
pub fn bury(
    e: &mut Elements,
    leaves: &[u32],
    vis: &Visibility,
    normals: &[DVec3],
    seed: u64,
) -> (usize, u64) {
    let found: Vec<((f64, f64), u64)> = leaves
        .par_iter()
        .map(|&el| {
            let rng = Pcg32::keyed(seed, 0x4255_5259, u64::from(el), 0);
            let back = back_hits(e, el, vis, normals, rng, 4, false)
                .into_iter()
                .filter(|&b| b)
                .count();
            let mut rays = BURY_RAYS as u64;
            let crossed = e.partly[el as usize];
            let exposed = if back == BURY_RAYS && !crossed {
                (0.0, 0.0)
            } else if back == 0 && !crossed {
                (1.0, 0.0)
            } else {
                let rng = Pcg32::keyed(seed, 0x4255_5259, u64::from(el), 1);
                let n = EXPOSED_RAYS;
                rays += (n * n) as u64;
                let found = exposed_fraction(&back_hits(e, el, vis, normals, rng, n, true));
                if found.0 < MIN_EXPOSED {
                    (0.0, 0.0)
                } else {
                    found
                }
            };
            (exposed, rays)
        })
        .collect();
    let (mut count, mut rays) = (0, 0);
    for (&el, &((exposed, se), r)) in leaves.iter().zip(&found) {
        let i = el as usize;
        e.buried[i] = exposed <= 0.0;
        e.partly[i] = exposed > 0.0 && exposed < 1.0;
        e.exposed[i] = exposed.max(0.0);
        e.exposed_se[i] = se;
        count += usize::from(e.buried[i]);
        rays += r;
    }
    (count, rays)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formfactor::exact::Piece;

    fn floor() -> Elements {
        // A 4 x 4 quad in z = 0 facing +z, as a root.
        let mut e = Elements::default();
        e.add_root(
            Piece::Quad([
                DVec3::ZERO,
                DVec3::new(4.0, 0.0, 0.0),
                DVec3::new(4.0, 4.0, 0.0),
                DVec3::new(0.0, 4.0, 0.0),
            ]),
            DVec3::Z,
        );
        e
    }

    #[test]
    fn crossing_contacts_split_to_the_minimum_area() {
        let mut e = floor();
        // A segment through the middle, and one along the boundary (not crossing).
        let mid = (DVec3::new(1.0, 1.0, 0.0), DVec3::new(3.0, 1.0, 0.0));
        let edge = (DVec3::new(0.0, 0.0, 0.0), DVec3::new(4.0, 0.0, 0.0));
        assert!(crosses(&e, 0, mid, 1e-9));
        assert!(!crosses(&e, 0, edge, 1e-9));
        let n = split_along_contacts(&mut e, &[vec![mid, edge]], 0.1, 1e-9);
        assert!(n > 0);
        // Every leaf the segment crosses is at the minimum size: area / 4 < min_area.
        for l in e.leaves().collect::<Vec<_>>() {
            if crosses(&e, l, mid, 1e-9) {
                assert!(
                    e.area[l as usize] / 4.0 < 0.1,
                    "leaf {l} area {}",
                    e.area[l as usize]
                );
            }
        }
        // The boundary segment split nothing by itself.
        let mut f = floor();
        assert_eq!(split_along_contacts(&mut f, &[vec![edge]], 0.1, 1e-9), 0);
    }

    #[test]
    fn exposed_fraction_and_its_collapsed_strata_error() {
        // All exposed, all buried: exact, no error.
        assert_eq!(exposed_fraction(&[false; 16]), (1.0, 0.0));
        assert_eq!(exposed_fraction(&[true; 16]), (0.0, 0.0));
        // A boundary between pairs: the pairs agree, so no error is seen.
        let mut half = [false; 16];
        half[..8].fill(true);
        assert_eq!(exposed_fraction(&half), (0.5, 0.0));
        // A boundary through two pairs: each differing pair adds 1 / N².
        let mut split = [false; 16];
        split[3] = true;
        split[5] = true;
        let (x, se) = exposed_fraction(&split);
        assert_eq!(x, 14.0 / 16.0);
        assert!((se - (2.0f64).sqrt() / 16.0).abs() < 1e-15);
    }

    #[test]
    fn shadows_that_line_up_across_a_receiver_split_it_and_noise_does_not() {
        use crate::hierarchy::link::Tilt;
        // One receiver (element 0, ρ 0.5) lit by eight pieces of a light (element 0 as
        // the source too: only its radiosity, 1, is read), each a partly visible link
        // with factor 0.02 within the tolerance 0.01 × 1 on its own (0.5 × 1 × 0.02 t).
        let e = floor();
        let rho = vec![[0.5; 3]];
        let b = vec![[1.0; 3]];
        let spread = vec![[0.0; 3]];
        let piece = |t: [f64; 2], vis: f64| Link {
            src: 0,
            err: 0.0,
            se: 0.0,
            df: 0.02,
            partial: true,
            tilt: Tilt::new(t),
            vis,
            basis: crate::hierarchy::link::Basis::Rays,
            open: 0.02,
        };
        let o = Oracle {
            elements: &e,
            rho: &rho,
            b: &b,
            spread: &spread,
            tol: Relative {
                error: 0.01,
                mean: 1.0,
                low: 1.0,
                high: 1.0,
            },
            min_area: 1e-3,
            shadows: true,
            rays: 4,
        };
        // Every piece's boundary across u the same way: G = 8 × 0.01 × 0.75 = 0.06 against
        // 2 × 0.01 + 2 σ (σ = 0.01 √(8 × 4 × 0.25 / 16) ≈ 0.0071).
        let lined = vec![piece([0.75, 0.0], 0.5); 8];
        assert!(o.shadowed(0, &lined));
        assert_eq!(o.decide(0, &lined[0], true), Decision::SplitReceiver);
        // The same tilts with alternating signs (the rays' noise): they cancel.
        let noise: Vec<Link> = (0..8)
            .map(|k| piece([if k % 2 == 0 { 0.75 } else { -0.75 }, 0.0], 0.5))
            .collect();
        assert!(!o.shadowed(0, &noise));
        // One piece alone (0.0075), or two (0.015): within twice the tolerance.
        assert!(!o.shadowed(0, &lined[..2]));
        assert!(!o.shadowed(0, &lined[..1]));
        // Tilts along both parameters add as a vector: 8 × 0.01 × (0.5, 0.5) has length
        // 0.057.
        assert!(o.shadowed(0, &vec![piece([0.5, 0.5], 0.5); 8]));
        // Not without the switch, nor below the minimum area, nor for visible links.
        assert!(!Oracle {
            shadows: false,
            ..o
        }
        .shadowed(0, &lined));
        assert!(!Oracle { min_area: 5.0, ..o }.shadowed(0, &lined));
        let open: Vec<Link> = lined
            .iter()
            .map(|l| Link {
                partial: false,
                ..*l
            })
            .collect();
        assert!(!o.shadowed(0, &open));
        // A link within its tolerance on a receiver not shadowed is kept.
        assert_eq!(o.decide(0, &lined[0], false), Decision::Keep);
        // A hidden link gathered by Russian roulette is never refined, whatever its error
        // or the receiver's shadows.
        let roulette = Link {
            vis: 0.0,
            df: 10.0,
            open: 10.0,
            basis: crate::hierarchy::link::Basis::Roulette,
            ..lined[0]
        };
        assert_eq!(o.decide(0, &roulette, true), Decision::Keep);
        assert_eq!(o.decide(0, &roulette, false), Decision::Keep);
    }

    #[test]
    fn oracle_stops_at_tolerance_and_minimum_area() {
        let e = floor();
        let rho = vec![[0.5; 3]];
        let b = vec![[1.0; 3]];
        let spread = vec![[0.0; 3]];
        let link = Link {
            src: 0,
            err: 0.0,
            se: 0.0,
            df: 0.2,
            partial: false,
            tilt: crate::hierarchy::link::Tilt::default(),
            vis: 1.0,
            basis: crate::hierarchy::link::Basis::Rays,
            open: 0.1,
        };
        // Absolute: low = high = 1, mean 1.
        let tol = |error: f64| Relative {
            error,
            mean: 1.0,
            low: 1.0,
            high: 1.0,
        };
        let o = Oracle {
            elements: &e,
            rho: &rho,
            b: &b,
            spread: &spread,
            tol: tol(0.05),
            min_area: 1.0,
            shadows: false,
            rays: 4,
        };
        // Error 0.5 * 1 * 0.2 = 0.1 > 0.05: split (receiver on a tie of areas).
        assert_eq!(o.decide(0, &link, false), Decision::SplitReceiver);
        let o2 = Oracle { tol: tol(0.2), ..o };
        assert_eq!(o2.decide(0, &link, false), Decision::Keep);
        let o3 = Oracle {
            min_area: 5.0,
            tol: tol(0.05),
            ..o2
        };
        assert_eq!(o3.decide(0, &link, false), Decision::Keep);
    }

    #[test]
    fn receiver_tolerance_follows_its_radiosity_between_floor_and_cap() {
        let rel = Relative {
            error: 0.01,
            mean: 2.0,
            low: 0.25,
            high: 4.0,
        };
        // Unknown: at the mean; black: at the floor.
        assert_eq!(rel.unknown().eps([0.0, 1.0, 100.0]), [0.02; 3]);
        assert_eq!(rel.eps([0.0; 3]), [0.005; 3]);
        // Dark channels at the floor (0.5), bright ones at the cap (8), others as they are.
        let eps = rel.eps([0.1, 1.0, 100.0]);
        for (x, want) in eps.iter().zip([0.005, 0.01, 0.08]) {
            assert!((x - want).abs() < 1e-15, "{eps:?}");
        }
        // low = high = 1: the absolute tolerance whatever the receiver.
        let abs = Relative {
            low: 1.0,
            high: 1.0,
            ..rel
        };
        assert_eq!(abs.eps([0.1, 1.0, 100.0]), [abs.absolute(); 3]);
        // A link from a source of radiosity 1 (element 2) into a receiver (element 1) of
        // radiosity `b_r`: error 0.5 × 1 × 0.015 = 0.0075, against 0.01 × clamp(b_r, 0.5, 8).
        let mut e = floor();
        e.split(0);
        let rho = vec![[0.5; 3]; 5];
        let spread = vec![[0.0; 3]; 5];
        let link = Link {
            src: 2,
            err: 0.0,
            se: 0.0,
            df: 0.015,
            partial: false,
            tilt: crate::hierarchy::link::Tilt::default(),
            vis: 1.0,
            basis: crate::hierarchy::link::Basis::Rays,
            open: 0.1,
        };
        let decide = |tol: Relative, b_r: f64| {
            let b = vec![[1.0; 3], [b_r; 3], [1.0; 3], [1.0; 3], [1.0; 3]];
            Oracle {
                elements: &e,
                rho: &rho,
                b: &b,
                spread: &spread,
                tol,
                min_area: 1.0,
                shadows: false,
                rays: 4,
            }
            .decide(1, &link, false)
        };
        // Bright receivers keep it, dark ones (to the floor) refine it; the absolute
        // tolerance (0.02) keeps it whatever the receiver.
        assert_eq!(decide(rel, 1.0), Decision::Keep);
        assert_eq!(decide(rel, 0.5), Decision::SplitReceiver);
        assert_eq!(decide(rel, 0.01), Decision::SplitReceiver);
        assert_eq!(decide(abs, 0.01), Decision::Keep);
    }
}
