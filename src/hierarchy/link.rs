//! Links and what the refinement oracle knows about each: the form factor between two
//! elements, how much it varies over the receiver, and whether the pair is partly hidden.
//!
//! A link `r ← s` says "receiver `r` gathers the radiosity of source `s` through `F_rs`"
//! (Hanrahan, Salzman and Aupperle, "A rapid hierarchical radiosity algorithm",
//! SIGGRAPH 1991, section 3). Its factor is
//!
//! `F_rs = 1/A_r ∫_{A_r} F(x → P_s) v(x) dA_x`,
//!
//! with `F(x → P_s)` Lambert's exact point-to-polygon factor and `v` the visible fraction,
//! as in the semi-analytic estimator ([`crate::formfactor::semi`]):
//!
//! - the unoccluded integral comes from [`crate::formfactor::exact::integrate`] to the
//!   relative tolerance [`super::Settings::quadrature`] (deterministic, with its error
//!   estimate);
//! - when no other patch can block the pair ([`Blockers::unoccluded`], the hull-face and
//!   plane tests of the semi estimator, in `f64`), `v = 1` exactly and no ray is cast;
//! - otherwise `n x n` jittered points on the receiver are paired with `n x n` jittered
//!   points on the source (a random permutation of the strata) and each segment is traced;
//!   `v` is the kernel-weighted visible fraction `Σ G V / Σ G` (the Jacobians of both
//!   parameter maps included), with receiver points on its unburied part only. All rays
//!   free: *visible*; some: *partial*, a shadow boundary runs through the pair; none:
//!   *hidden*. A hidden link whose missed light may exceed the hide share of the
//!   tolerance is kept as partial with `v = 0`; one within it is kept unrefined
//!   ([`Basis::Roulette`]), and each leaf below its receiver gathers it by Russian
//!   roulette: with probability [`ROULETTE`], standing for `1 / ROULETTE`, so that what
//!   such links carry is not lost on average (see [`evaluate`] and [`roulette_keeps`]).
//!
//! A link's factor is per *visible* area of the receiver: the mean of `F v` over its
//! unburied part (what a box standing on it covers receives nothing and counts for
//! nothing).
//!
//! The oracle's variation `ΔF`: Lambert's factor is evaluated at a 3 x 3 grid of points of
//! the receiver; a visible link's `ΔF` is their range (plus the quadrature error), a
//! partial link's is their maximum (visibility may go from 0 to 1 across the receiver).
//! The refinement rule itself lives in [`super::refine`].
//!
//! Random streams are keyed on `(seed, r, s)`, and element numbering does not depend on
//! the thread count, so neither do the links.

use glam::DVec3;
use smallvec::SmallVec;

use super::blockers::{range, Blockers};
use super::element::Elements;
use super::near;
use crate::formfactor::exact::{self, Emitter, Receiver};
use crate::formfactor::far;
use crate::mesh::PatchSet;
use crate::sampling::{fraction_se, Pcg32};
use crate::visibility::{SegmentRay, Visibility};

/// A link as stored, in the list of its receiver.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Link {
    /// The source element.
    pub src: u32,
    /// The quadrature's error estimate of `f` (deterministic: added linearly).
    pub err: f64,
    /// The standard error of `f` from its visibility rays: [`fraction_se`] times the
    /// unoccluded factor (random, independent between links: added in quadrature); 0 when
    /// the pair was proved unoccluded.
    pub se: f64,
    /// Variation of the point factor over the receiver (the oracle's `ΔF`).
    pub df: f64,
    /// True when some but not all visibility rays were blocked.
    pub partial: bool,
    /// The visible fraction `v` (1 when unoccluded): the factor is the unoccluded factor
    /// times it ([`Link::f`]).
    pub vis: f64,
    /// How the visible fraction is known: from rays, by proof, or not at all (a hidden
    /// link gathered by Russian roulette, [`Basis::Roulette`]).
    pub basis: Basis,
    /// How the visible fraction changes across the receiver, as its rays saw it: per
    /// parameter of the receiver (`u`, `v`), the fraction of the rays from its upper half
    /// minus that of its lower half, times 127 ([`Tilt`]). A shadow boundary across the
    /// receiver tilts it; one across the source (the receiver sees the same part of the
    /// source from everywhere) does not. [`super::refine::Oracle::shadowed`] adds the
    /// tilts of a receiver's links.
    pub tilt: Tilt,
    /// The unoccluded factor: what the refinement decides on where visibility was
    /// sampled, so that the rays' noise does not pick which links are kept
    /// ([`super::refine::Oracle::error`]).
    pub open: f64,
}

impl Link {
    /// Form factor `F_rs` (receiver to source): the unoccluded factor times the visible
    /// fraction. Computed rather than held, as it is one product of two held values: a
    /// link is 48 bytes instead of 56, and the 10^6-triangle scene holds 33 M of them.
    pub fn f(&self) -> f64 {
        self.open * self.vis
    }
}

/// How a link's visible fraction is known ([`Link::basis`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Basis {
    /// From the link's rays.
    Rays,
    /// [`Blockers`] proved that nothing blocks the pair (no ray was cast): then nothing
    /// blocks any pair of their pieces either.
    Proved,
    /// Every ray was blocked, and the light the rays may have missed is within the hide
    /// share of the tolerance: such a link is kept but never refined, and carries nothing
    /// while the hierarchy is built. In the final gather each leaf below its receiver
    /// traces its own visibility of the source with probability [`ROULETTE`], and that
    /// entry counts `1 / ROULETTE` times (Russian roulette: Arvo and Kirk, "Particle
    /// transport and image synthesis", SIGGRAPH 1990). Dropping all of them lost about
    /// 0.1% of every leaf's view on the closed Cornell box, one bounce after another
    /// (docs/HIERARCHY.md).
    Roulette,
}

/// The probability with which a leaf gathers the source of a link whose rays were all
/// blocked, and whose light is within the hide share of the tolerance
/// ([`Basis::Roulette`]).
pub const ROULETTE: f64 = 0.25;

/// Whether leaf `l` gathers the source `s` of a hidden link above it
/// ([`Basis::Roulette`]): a draw of the pair's own stream, so that the result does not
/// depend on the thread count.
///
/// The draw is the leaf's, not the link's. Kept or dropped per link, a hidden link's
/// light came or went for every leaf below its receiver at once, so that one draw moved a
/// whole region: on the Cornell box at `--error 0.01`, the short block's dark face toward
/// the opening read +0.16% to +0.52% of the path tracer at seeds 1 to 4. Per leaf, the
/// draws of neighbouring leaves are independent and average out over a face or a vertex's
/// leaves (docs/HIERARCHY.md, *Russian roulette per leaf*).
pub fn roulette_keeps(seed: u64, l: u32, s: u32) -> bool {
    let mut rng = Pcg32::keyed(seed, 0x5252_4f55_4c00_0000 | u64::from(l), u64::from(s), 0);
    rng.next_f64() < ROULETTE
}

/// Most steps a proof takes before rays are cast instead
/// ([`Blockers::unoccluded_within`]): about what `2 × 2` rays cost.
pub const PROOF_BUDGET: usize = 32;

/// What evaluating a candidate link costs and finds.
#[derive(Clone, Copy, Debug, Default)]
pub struct Cost {
    /// Rays traced.
    pub rays: u64,
    /// Point-to-polygon evaluations.
    pub evals: u64,
}

impl std::ops::AddAssign for Cost {
    fn add_assign(&mut self, o: Cost) {
        self.rays += o.rays;
        self.evals += o.evals;
    }
}

/// Everything a link evaluation reads.
pub struct Context<'a> {
    /// The elements.
    pub elements: &'a Elements,
    /// The patch set the roots came from (what Embree traces).
    pub patches: &'a PatchSet,
    /// Visibility queries.
    pub vis: &'a Visibility,
    /// Occlusion proofs.
    pub blockers: &'a Blockers,
    /// Seed of the random streams.
    pub seed: u64,
    /// Visibility strata per side: `rays²` rays per traced link.
    pub rays: usize,
    /// Relative tolerance of the unoccluded integral.
    pub quadrature: f64,
    /// Scale-relative tolerance of the facing tests.
    pub tol: f64,
    /// Visible (unburied) area of every element ([`Elements::visible_areas`]).
    pub visible: Vec<f64>,
    /// The final gather's rays: a leaf's rays to a source near it are drawn by its pieces
    /// ([`near::strata`]) and, with those to a source touching it, estimated around a
    /// prior of 1 (`judge`). Off while the hierarchy is refined: there the links'
    /// estimates decide the refinement, and drawn so on the Cornell box they left the
    /// short block's face 8 0.02% brighter on average over eight seeds, none darker (the
    /// refinement changed, not the estimates' mean; docs/HIERARCHY.md, *Near sources*).
    pub gather: bool,
}

impl<'a> Context<'a> {
    /// The context of a solution with settings `s` and facing tolerance `tol`.
    pub fn new(
        elements: &'a Elements,
        patches: &'a PatchSet,
        vis: &'a Visibility,
        blockers: &'a Blockers,
        s: &super::Settings,
        tol: f64,
    ) -> Context<'a> {
        Context {
            elements,
            patches,
            vis,
            blockers,
            seed: s.seed,
            rays: s.rays,
            quadrature: s.quadrature,
            tol,
            visible: elements.visible_areas(),
            gather: false,
        }
    }
}

/// Parameter points of the 3 x 3 grid the oracle evaluates `F(x → P_s)` at.
const GRID: [f64; 3] = [1.0 / 6.0, 0.5, 5.0 / 6.0];

/// The tolerances a candidate link is evaluated to, both on the factor `F_rs`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tolerance {
    /// Absolute tolerance of the unoccluded integral (looser of this and the relative
    /// [`Context::quadrature`]).
    pub factor: f64,
    /// How much factor a link may lose by being dropped as hidden: a share of the link
    /// tolerance over `ρ_r B_s` ([`super::Settings::hide`]).
    pub hide: f64,
}

/// True when some of element `s` is strictly (by more than `tol`) in front of element
/// `r`'s plane and some of `r` in front of `s`'s: else no light passes between them
/// (neighbours on a convex surface, coplanar elements, elements turned away).
pub fn facing(e: &Elements, tol: f64, r: u32, s: u32) -> bool {
    let (ri, si) = (r as usize, s as usize);
    range((e.normal[ri], e.centre[ri]), e.corners(s)).1 > tol
        && range((e.normal[si], e.centre[si]), e.corners(r)).1 > tol
}

/// Evaluates the link `r ← s`; `None` when the two cannot exchange light (one behind the
/// other's plane, one buried, or every visibility ray blocked where even the light the
/// rays could have missed is within the tolerance). The unoccluded integral is taken to
/// the relative tolerance [`Context::quadrature`] or the absolute tolerance
/// `tol.factor` on `F_rs`, whichever is looser: a link that carries little light needs
/// few digits.
///
/// **Hidden or not.** `n` blocked rays out of `n` do not prove the pair hidden: with
/// probability 95% the visible fraction is below `3 / n` (the rule of three), and the
/// rays say nothing of where a small visible part lies (a strip of floor beside a box,
/// when the rest of the receiver is in the box's shadow). A link whose rays are all
/// blocked is dropped only when `3 / n` of its unoccluded factor is within `tol.hide`;
/// otherwise it is kept as a partly visible link with visible fraction 0, so that the
/// oracle refines it like a shadow boundary and the leaves below trace their own
/// visibility.
///
/// `near` keeps the receiving side of the open factor ([`Near`]): taken from there when it
/// is `r`'s, else made there, so that a run of links into one receiver maps its Gauss nodes
/// once.
pub fn evaluate(
    ctx: &Context,
    near: &mut Option<Near>,
    r: u32,
    s: u32,
    tol: Tolerance,
) -> (Option<Link>, Cost) {
    let e = ctx.elements;
    let (ri, si) = (r as usize, s as usize);
    let (pr, ps) = (e.corners(r), e.corners(s));
    let (nr, ns) = (e.normal[ri], e.normal[si]);
    let mut cost = Cost::default();
    if ctx.visible[ri] <= 0.0 || ctx.visible[si] <= 0.0 {
        return (None, cost);
    }
    if !facing(e, ctx.tol, r, s) {
        return (None, cost);
    }
    let receiver = Receiver::new(ps, ns, e.centre[si]);
    // The oracle's samples of F(x -> P_s) over the receiver.
    let (mut fmin, mut fmax) = (f64::INFINITY, 0.0f64);
    for &u in &GRID {
        for &v in &GRID {
            let x = e.point(r, u, v).0;
            let f = exact::point_factor(x, nr, &receiver);
            fmin = fmin.min(f);
            fmax = fmax.max(f);
        }
    }
    cost.evals += 9;
    let near = match near {
        Some(n) if n.l == r => n,
        _ => near.insert(Near::new(e, r)),
    };
    let integral = open_factor_near(ctx, near, s, tol.factor);
    cost.evals += integral.evals;
    let (f_open, q_err) = (integral.value, integral.err);
    if f_open <= 0.0 {
        return (None, cost);
    }
    let (root_r, root_s) = (e.root[ri], e.root[si]);
    if ctx
        .blockers
        .unoccluded_within(pr, root_r, ps, root_s, PROOF_BUDGET)
        == Some(true)
    {
        let link = Link {
            src: s,
            err: q_err,
            se: 0.0,
            df: (fmax - fmin) + q_err,
            partial: false,
            tilt: Tilt::default(),
            vis: 1.0,
            basis: Basis::Proved,
            open: f_open,
        };
        return (Some(link), cost);
    }
    let seen = visible_fraction(ctx, r, s, Some(f_open));
    cost.rays += seen.rays;
    let n = seen.rays.max(1) as f64;
    let link = if seen.v <= 0.0 {
        if 3.0 / n * f_open <= tol.hide {
            let link = Link {
                src: s,
                err: q_err,
                se: f_open * fraction_se(0.0, n),
                df: 0.0,
                partial: false,
                tilt: Tilt::default(),
                vis: 0.0,
                basis: Basis::Roulette,
                open: f_open,
            };
            return (Some(link), cost);
        }
        Link {
            src: s,
            err: q_err,
            se: f_open * fraction_se(0.0, n),
            df: fmax + q_err,
            partial: true,
            tilt: Tilt::default(),
            vis: 0.0,
            basis: Basis::Rays,
            open: f_open,
        }
    } else {
        let partial = seen.v < 1.0;
        Link {
            src: s,
            err: q_err,
            se: f_open * fraction_se(seen.v, n),
            df: if partial { fmax } else { fmax - fmin } + q_err,
            partial,
            tilt: seen.tilt,
            vis: seen.v,
            basis: Basis::Rays,
            open: f_open,
        }
    };
    (Some(link), cost)
}

/// Share of a factor's tolerance the one-point rule's bound may take in [`open_factor`].
pub const FAR_SHARE: f64 = 0.02;

/// What [`open_factor`] needs of its receiving element `l` whatever the source: its
/// one-point summary and its Gauss nodes (an [`Emitter`] caches them by order). The final
/// gather keeps one per leaf across the leaf's hundreds of entries, instead of mapping the
/// same nodes again for each.
#[derive(Clone, Debug)]
pub struct Near {
    l: u32,
    small: far::Small,
    emitter: Emitter,
}

impl Near {
    /// The receiving side of element `l`.
    pub fn new(e: &Elements, l: u32) -> Near {
        let li = l as usize;
        Near {
            l,
            small: far::Small::new(e.corners(l), e.normal[li]),
            emitter: Emitter::new(e.piece[li]),
        }
    }
}

/// The unoccluded factor `F(l → P_s)` from element `l` to the polygon of element `s`,
/// `1/A_l ∫_l F(x → P_s) dA_x`, to the relative tolerance [`Context::quadrature`] or the
/// absolute tolerance `f_tol`: the factor, the quadrature's error estimate of it, and the
/// point-factor evaluations spent. A leaf small beside its distance from the source takes
/// the one-point rule at its centroid with that rule's bound
/// ([`far::centroid_rule_bound`]) instead, where the bound is within [`FAR_SHARE`] of the
/// same tolerance.
pub fn open_factor(ctx: &Context, l: u32, s: u32, f_tol: f64) -> exact::Integral {
    open_factor_near(ctx, &mut Near::new(ctx.elements, l), s, f_tol)
}

/// [`open_factor`] from the receiving side `near` (of element `near.l`).
pub fn open_factor_near(ctx: &Context, near: &mut Near, s: u32, f_tol: f64) -> exact::Integral {
    let e = ctx.elements;
    let l = near.l;
    let (li, si) = (l as usize, s as usize);
    if range((e.normal[li], e.centre[li]), e.corners(s)).1 <= ctx.tol
        || range((e.normal[si], e.centre[si]), e.corners(l)).1 <= ctx.tol
    {
        return exact::Integral::default();
    }
    let receiver = Receiver::new(e.corners(s), e.normal[si], e.centre[si]);
    // A leaf small beside its distance from the source: the factor at its centroid, when
    // the rule's bound is within `FAR_SHARE` of the tolerance the quadrature would be held
    // to (the Gauss rule's a-posteriori estimate usually lands far below that tolerance;
    // a bound at the tolerance itself made the Cornell furnace's estimated errors 21 times
    // the actual).
    let small = &near.small;
    if let Some(bound) =
        far::centroid_rule_bound(small, e.corners(l), e.corners(s), e.normal[si], e.area[si])
    {
        let value = exact::point_factor(small.centroid, e.normal[li], &receiver);
        if bound <= FAR_SHARE * f_tol.max(ctx.quadrature * value) {
            return exact::Integral {
                value,
                err: bound,
                evals: 1,
            };
        }
    }
    let area = e.area[li];
    let i = exact::integrate(
        &mut near.emitter,
        e.normal[li],
        &receiver,
        ctx.quadrature,
        f_tol.max(1e-15) * area,
        // Elements meet at T-junctions everywhere; their contacts are not classified.
        &|| exact::Contact::Kinked,
    );
    exact::Integral {
        value: (i.value / area).max(0.0),
        err: i.err / area,
        evals: i.evals,
    }
}

/// What the visibility rays of a pair found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Seen {
    /// Kernel-weighted visible fraction (0 when no ray could be traced).
    pub v: f64,
    /// Rays traced.
    pub rays: u64,
    /// How the visible fraction changes across the receiver ([`Link::tilt`]).
    pub tilt: Tilt,
}

/// The change of a link's visible fraction across its receiver: per receiver parameter,
/// the visible fraction of the rays from the half where it exceeds 1/2 minus that of the
/// other half, in 1/127ths (0 where a half cast no ray). Held in two bytes, beside the
/// link's flags, so that links are no larger for it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Tilt(pub [i8; 2]);

impl Tilt {
    /// From the differences, each in `[-1, 1]`.
    pub fn new(d: [f64; 2]) -> Tilt {
        Tilt(d.map(|x| (x.clamp(-1.0, 1.0) * 127.0).round() as i8))
    }

    /// The differences, each in `[-1, 1]`.
    pub fn get(self) -> [f64; 2] {
        self.0.map(|x| f64::from(x) / 127.0)
    }
}

/// Tries per stratum at finding a receiver point that is not buried.
pub(super) const BURIED_TRIES: usize = 4;

/// Kernel-weighted visible fraction between `r` and `s` from `rays²` traced segments.
///
/// Receiver points are drawn only on the unburied part of `r` (a point whose leaf is
/// buried is drawn again in its stratum, up to `BURIED_TRIES` times, then the stratum is
/// skipped): the fraction is that of the surface that can receive, matching the link's
/// factor per visible area ([`super::solve`]). Source points cover all of `s`, buried
/// parts included, whose rays are blocked: what `r` sees of the source's radiating part.
///
/// `open` is the unoccluded factor `F(r → P_s)` when the caller has it. For a leaf `r`
/// (every receiver point counts, none is drawn again) the fraction is then estimated
/// without bias by subtracting what the blocked rays hide from the exact unoccluded
/// integral, `v = 1 - Σ_k w_k (1 - V_k) / (n² π A_r F(r → P_s))` with `w_k = cos θ_x cos θ_y
/// / r² × J_x J_y` the kernel of the k-th segment times the area Jacobians of its ends
/// (whose mean over the unit squares is `∫∫ cos cos / r² = π A_r F`): the control variate of
/// the flat semi-analytic estimator ([`crate::formfactor::semi`]). The kernel-weighted
/// ratio `Σ w V / Σ w`, used otherwise, is biased by `O(1/n²)` where a pair is partly
/// hidden.
pub fn visible_fraction(ctx: &Context, r: u32, s: u32, open: Option<f64>) -> Seen {
    visible_fraction_n(ctx, r, s, ctx.rays, open)
}

/// [`visible_fraction`] with `n × n` rays instead of [`Context::rays`]² (a different
/// stream for each `n`).
pub fn visible_fraction_n(ctx: &Context, r: u32, s: u32, n: usize, open: Option<f64>) -> Seen {
    traced_n(ctx, r, s, n, open).seen()
}

/// [`visible_fraction_n`] (the same rays) from a partly buried leaf `r`: its rays from
/// points inside the solid are blocked, or face away from `s` and are not cast, as
/// expected, so neither every ray blocked nor no ray cast shows the pair hidden, and the
/// control variate's estimate is kept (1 where no ray was cast: no blocked kernel).
pub fn visible_fraction_partly(ctx: &Context, r: u32, s: u32, n: usize, open: Option<f64>) -> Seen {
    let tag = if n == ctx.rays { 0 } else { n as u64 };
    traced_keyed(ctx, r, s, n, tag, open, true).seen()
}

/// Stream tag of [`visible_fraction_again`].
const AGAIN: u64 = 1 << 40;

/// Stream tag of [`traced_more`] (with the rays per side in the low bits).
const MORE: u64 = 1 << 41;

/// [`visible_fraction`] with rays independent of those that evaluated the link `r ← s`
/// ([`evaluate`]): a fresh estimate for a link whose first estimate took part in deciding
/// that it is kept.
pub fn visible_fraction_again(ctx: &Context, r: u32, s: u32, open: Option<f64>) -> Seen {
    traced_keyed(ctx, r, s, ctx.rays, AGAIN, open, false).seen()
}

/// The weight of the segment from `x` to `y` (each a point, its surface normal and the area
/// Jacobian of its parameter map) in a visibility estimate: the form-factor kernel
/// `cos θ_x cos θ_y / r²` times the Jacobians, over `r²` again because `cos θ` is taken
/// from the unnormalised direction. `None` when either side faces away (the kernel is 0).
pub fn kernel_weight(x: (DVec3, DVec3, f64), y: (DVec3, DVec3, f64)) -> Option<f64> {
    let w = y.0 - x.0;
    let r2 = w.length_squared();
    let (cx, cy) = (x.1.dot(w), -y.1.dot(w));
    (cx > 0.0 && cy > 0.0 && r2 > 0.0).then(|| cx * cy / (r2 * r2) * x.2 * y.2)
}

/// The `n × n` rays of [`visible_fraction`] from the stream tagged `tag`, traced and
/// kept: what they say of the pair
/// ([`Traced::seen`]) and of the pieces of its source ([`Traced::pieces`]).
fn traced_keyed(
    ctx: &Context,
    r: u32,
    s: u32,
    n: usize,
    tag: u64,
    open: Option<f64>,
    partly: bool,
) -> Traced {
    let drawn = draw(ctx, r, s, n, tag, open, partly);
    let mut free: SmallVec<[bool; 16]> = smallvec::smallvec![false; drawn.segs.len()];
    ctx.vis.segments_visible(&drawn.segs, &mut free);
    Traced { drawn, free }
}

/// The rays of [`visible_fraction`] (or [`visible_fraction_partly`] when `partly`, with
/// [`Context::rays`]² rays), kept.
pub fn traced(ctx: &Context, r: u32, s: u32, open: Option<f64>, partly: bool) -> Traced {
    traced_keyed(ctx, r, s, ctx.rays, 0, open, partly)
}

/// The rays of [`visible_fraction_n`], kept.
pub fn traced_n(ctx: &Context, r: u32, s: u32, n: usize, open: Option<f64>) -> Traced {
    let tag = if n == ctx.rays { 0 } else { n as u64 };
    traced_keyed(ctx, r, s, n, tag, open, false)
}

/// `n × n` rays from `r` to `s` from a stream of their own, independent of every other
/// estimate of the pair's visibility (the link's, the leaf's first, its pieces'): a
/// second estimate that replaces a first whose noise asked for it stays unbiased.
pub fn traced_more(ctx: &Context, r: u32, s: u32, n: usize, open: Option<f64>) -> Traced {
    traced_keyed(ctx, r, s, n, MORE | n as u64, open, false)
}

/// The rays of [`visible_fraction_again`], kept.
pub fn traced_again(ctx: &Context, r: u32, s: u32, open: Option<f64>) -> Traced {
    traced_keyed(ctx, r, s, ctx.rays, AGAIN, open, false)
}

/// Visibility rays of a pair `r ← s`, traced: their segments' weights and answers, and
/// where on the source each starts.
pub struct Traced {
    drawn: Drawn,
    free: SmallVec<[bool; 16]>,
}

impl Traced {
    /// What the rays say of the pair ([`visible_fraction`]).
    pub fn seen(&self) -> Seen {
        judge(&self.drawn, &self.free, None)
    }

    /// Whether no ray was blocked (true where none was cast).
    pub fn all_free(&self) -> bool {
        self.free.iter().all(|&f| f)
    }

    /// What the rays say of the pair, estimated without bias around `prior`, a visible
    /// fraction known from other rays (`judge` in this module).
    pub fn seen_around(&self, prior: f64) -> Seen {
        judge(&self.drawn, &self.free, Some(prior))
    }

    /// What the same rays say of the pair's source split: for each of `pieces` (children
    /// of the source `s`, each with its unoccluded factor `F(r → P_c)`), the fraction from
    /// the rays whose source point lies in it and how many they are, or `None` where fewer
    /// than `least` of them do (those are traced afresh). The source points are uniform over the source's
    /// parameter strata whatever piece they fall in, so each piece's control-variate
    /// estimate `1 - Σ_{k ∈ c} w_k (1 - V_k) / (n² π A_r F(r → P_c))` (or ratio, for a
    /// partly buried receiver) stays unbiased; which piece a ray counts for depends on
    /// where it starts, never on what it met.
    ///
    /// `prior`, as in [`Traced::seen_around`], must not come from these rays.
    pub fn pieces(
        &self,
        ctx: &Context,
        s: u32,
        pieces: &[(u32, f64)],
        least: usize,
        prior: Option<f64>,
    ) -> SmallVec<[Option<(Seen, usize)>; 4]> {
        let e = ctx.elements;
        let d = &self.drawn;
        let child: SmallVec<[u32; 16]> = d
            .at_source
            .iter()
            .map(|&(u, v)| e.child_at(s, u, v).0)
            .collect();
        pieces
            .iter()
            .map(|&(c, f)| {
                let mut sub = Drawn {
                    mean: if d.mean > 0.0 {
                        std::f64::consts::PI * d.area * f
                    } else {
                        0.0
                    },
                    partly: d.partly,
                    alpha_one: d.alpha_one,
                    ..Drawn::empty(d.area, d.cells, 0)
                };
                let mut free: SmallVec<[bool; 16]> = SmallVec::new();
                for k in (0..child.len()).filter(|&k| child[k] == c) {
                    sub.push(d.segs[k], d.weights[k], d.at_source[k], d.quadrant[k]);
                    free.push(self.free[k]);
                }
                (sub.segs.len() >= least.max(1)).then(|| {
                    let seen = Seen {
                        // Rays already counted for the pair.
                        rays: 0,
                        ..judge(&sub, &free, prior)
                    };
                    (seen, sub.segs.len())
                })
            })
            .collect()
    }
}

/// [`visible_fraction_n`] (or [`visible_fraction_partly`] when `partly`) from `r` to each
/// of `sources` (a source and its unoccluded factor), their rays traced as one batch: the
/// pieces of a split source, `n × n` rays each, make full packets together where each
/// alone would go ray by ray ([`Visibility::segments_visible`]). The same rays and
/// fractions as one call each.
///
/// `prior`, as in [`Traced::seen_around`], the same for every source.
pub fn visible_fractions_n(
    ctx: &Context,
    r: u32,
    sources: &[(u32, f64)],
    n: usize,
    partly: bool,
    prior: Option<f64>,
) -> SmallVec<[Seen; 4]> {
    let tag = if n == ctx.rays { 0 } else { n as u64 };
    let drawn: SmallVec<[Drawn; 4]> = sources
        .iter()
        .map(|&(s, f)| draw(ctx, r, s, n, tag, Some(f), partly))
        .collect();
    let segs: SmallVec<[SegmentRay; 64]> =
        drawn.iter().flat_map(|d| d.segs.iter().copied()).collect();
    let mut free: SmallVec<[bool; 64]> = smallvec::smallvec![false; segs.len()];
    ctx.vis.segments_visible(&segs, &mut free);
    let mut at = 0;
    drawn
        .iter()
        .map(|d| {
            let k = d.segs.len();
            at += k;
            judge(d, &free[at - k..at], prior)
        })
        .collect()
}

/// The rays of one pair, drawn and not yet traced ([`draw`], [`judge`]).
struct Drawn {
    segs: SmallVec<[SegmentRay; 16]>,
    /// Kernel weight of each segment.
    weights: SmallVec<[f64; 16]>,
    /// The receiver quadrant of each segment's stratum.
    quadrant: SmallVec<[u8; 16]>,
    /// Each segment's source point, as parameters of the source.
    at_source: SmallVec<[(f64, f64); 16]>,
    /// The kernel's exact mean (0 when not known), for the control variate.
    mean: f64,
    /// The receiver's area.
    area: f64,
    cells: usize,
    partly: bool,
    /// Estimate around a prior of 1 whatever prior is given (see [`judge`]).
    alpha_one: bool,
}

impl Drawn {
    /// No segment yet (room for `room`), for a receiver of area `area` and `cells` strata;
    /// no kernel mean, not partly buried, estimated around the prior given.
    fn empty(area: f64, cells: usize, room: usize) -> Drawn {
        Drawn {
            segs: SmallVec::with_capacity(room),
            weights: SmallVec::with_capacity(room),
            quadrant: SmallVec::with_capacity(room),
            at_source: SmallVec::with_capacity(room),
            mean: 0.0,
            area,
            cells,
            partly: false,
            alpha_one: false,
        }
    }

    /// Adds a segment of kernel weight `w` starting at `at_source` (the source's
    /// parameters), from the receiver's quadrant `q` ([`quadrant`]).
    fn push(&mut self, seg: SegmentRay, w: f64, at_source: (f64, f64), q: u8) {
        self.segs.push(seg);
        self.weights.push(w);
        self.at_source.push(at_source);
        self.quadrant.push(q);
    }
}

/// The quadrant of stratum `c` of a `side × side` grid: bit 0 its upper half along the
/// first parameter, bit 1 along the second.
fn quadrant(c: usize, side: usize) -> u8 {
    u8::from(2 * (c % side) >= side) + 2 * u8::from(2 * (c / side) >= side)
}

/// `0..n` in random order (Fisher–Yates).
fn shuffled(n: usize, rng: &mut Pcg32) -> SmallVec<[u32; 64]> {
    let mut perm: SmallVec<[u32; 64]> = (0..n as u32).collect();
    for k in (1..n).rev() {
        let j = rng.below(k as u32 + 1) as usize;
        perm.swap(k, j);
    }
    perm
}

/// The `n × n` rays from `r` to `s` of the stream tagged `tag`, with what [`judge`] needs.
fn draw(
    ctx: &Context,
    r: u32,
    s: u32,
    n: usize,
    tag: u64,
    open: Option<f64>,
    partly: bool,
) -> Drawn {
    let e = ctx.elements;
    let (nr, ns) = (e.normal[r as usize], e.normal[s as usize]);
    let n = n.max(1);
    let mut rng = Pcg32::keyed(
        ctx.seed,
        0x4852_4c4e_4b00_0000 | u64::from(r),
        u64::from(s),
        tag,
    );
    let whole = e.is_leaf(r);
    if whole && ctx.gather {
        if let Some(strata) = near::strata(e, r, s, n * n) {
            return draw_near(ctx, (r, s), &strata, n * n, rng, open, partly);
        }
    }
    let cells = n * n;
    // Source strata in random order. The batches live on the stack up to 16 rays (the
    // default 4 × 4): the final gather traces tens of millions of them.
    let perm = shuffled(cells, &mut rng);
    let inv = 1.0 / n as f64;
    let mut drawn = Drawn::empty(e.area[r as usize], cells, cells);
    for (c, &d) in perm.iter().enumerate() {
        let (a, b) = ((c % n) as f64, (c / n) as f64);
        let mut at = None;
        for _ in 0..BURIED_TRIES {
            let (u, v) = ((a + rng.next_f64()) * inv, (b + rng.next_f64()) * inv);
            if whole || !e.buried[e.locate(r, u, v).0 as usize] {
                at = Some(e.point(r, u, v));
                break;
            }
        }
        let d = d as usize;
        let (a2, b2) = ((d % n) as f64, (d / n) as f64);
        let (us, vs) = ((a2 + rng.next_f64()) * inv, (b2 + rng.next_f64()) * inv);
        let (y, jy) = e.point(s, us, vs);
        let Some((x, jx)) = at else { continue };
        let Some(w) = kernel_weight((x, nr, jx), (y, ns, jy)) else {
            continue;
        };
        drawn.push(
            ctx.vis.segment_ray(x, nr, y, ns),
            w,
            (us, vs),
            quadrant(c, n),
        );
    }
    drawn.alpha_one = whole && ctx.gather && near::touching(e, r, s, ctx.tol);
    drawn.mean = if whole { kernel_mean(e, r, open) } else { 0.0 };
    drawn.partly = partly && drawn.mean > 0.0;
    drawn
}

/// The kernel's exact mean over the pair, `π A_r F(r → P_s)`, from the unoccluded factor
/// `open` (0 where it is not known), for the control variate.
fn kernel_mean(e: &Elements, r: u32, open: Option<f64>) -> f64 {
    match open {
        Some(f) if f > 0.0 => std::f64::consts::PI * e.area[r as usize] * f,
        _ => 0.0,
    }
}

/// [`draw`] from the leaf `r` to a source `s` near it ([`near::strata`]): the same number
/// of points in each piece (at least `rays` in all), paired with the receiver's strata (a
/// square grid of at least as many, taken in random order), each segment weighted by its
/// kernel times the Jacobians times the number of pieces, so that the weights' sum has the
/// same mean as uniform strata's; estimated around a prior of 1 ([`judge`]).
fn draw_near(
    ctx: &Context,
    (r, s): (u32, u32),
    strata: &[near::Stratum],
    rays: usize,
    mut rng: Pcg32,
    open: Option<f64>,
    partly: bool,
) -> Drawn {
    let e = ctx.elements;
    let (nr, ns) = (e.normal[r as usize], e.normal[s as usize]);
    // Each piece takes `per` points, so that there are at least `rays` of them.
    let per = rays.div_ceil(strata.len()).max(1);
    let cells = strata.len() * per;
    let side = (cells as f64).sqrt().ceil() as usize;
    let perm = shuffled(side * side, &mut rng);
    let inv = 1.0 / side as f64;
    let scale = strata.len() as f64;
    let mut drawn = Drawn::empty(e.area[r as usize], cells, cells);
    let pieces = strata.iter().flat_map(|p| std::iter::repeat_n(p, per));
    for (stratum, &c) in pieces.zip(&perm) {
        let c = c as usize;
        let (a, b) = ((c % side) as f64, (c / side) as f64);
        let (u, v) = ((a + rng.next_f64()) * inv, (b + rng.next_f64()) * inv);
        let (x, jx) = e.point(r, u, v);
        let (us, vs) = (rng.next_f64(), rng.next_f64());
        let (y, jy) = stratum.piece.at(us, 1.0 - us, vs, 1.0 - vs);
        let Some(w) = kernel_weight((x, nr, jx), (y, ns, jy)) else {
            continue;
        };
        let seg = ctx.vis.segment_ray(x, nr, y, ns);
        drawn.push(seg, w * scale, stratum.to_source(us, vs), quadrant(c, side));
    }
    drawn.mean = kernel_mean(e, r, open);
    drawn.partly = partly && drawn.mean > 0.0;
    drawn.alpha_one = true;
    drawn
}

/// The visible fraction from the rays `d` and their answers `free` (true: not blocked).
///
/// Without a `prior`: the control variate's estimate ([`visible_fraction`]), 0 when every
/// ray is blocked, clamped to `[0, 1]`. That is what decides a link; as an estimate it is
/// biased: where the kernel is larger on the visible part of the source than on the hidden
/// part, the rays of a pair all blocked are the ones of smaller kernel, and the control
/// variate's estimate from them is positive on average. Taking it as 0 lost about 0.1% of
/// every leaf's view of the Cornell box, always low (docs/HIERARCHY.md).
///
/// With a `prior` `α` (a visible fraction known from rays independent of these, clamped to
/// `[0, 1]`), for a whole receiver with the kernel's exact mean `m`: the control variate
/// with coefficient `α`,
///
/// `v = α + (Σ_k w_k V_k - α Σ_k w_k) / (n² m)`,
///
/// unbiased for any `α` fixed before the rays are drawn (`E[Σ w_k] = n² m`), neither
/// clamped nor set to 0 when every ray is blocked, and of least variance near `α = v`
/// (the regression coefficient of `w V` on `w`; Glasserman, *Monte Carlo methods in
/// financial engineering*, 2004, section 4.1). `α = 1` is the estimate above before its
/// clamp; `α = 0` plain Monte Carlo, exactly 0 when every ray is blocked.
///
/// That least variance assumes weights of bounded spread. Where the source touches the
/// receiver or is near it ([`near::strata`]), a few segments weigh many times the mean,
/// and they are the short ones, by the contact, which nothing blocks: with `α < 1` each
/// adds `(1 - α) w / (n² m)`, a heavy tail (a wall leaf at the foot of a wall read 15
/// times the ground it can see, on `city-16`). There the prior is taken as 1 whatever is
/// given (`Drawn::alpha_one`), so that only blocked segments move the estimate.
fn judge(d: &Drawn, free: &[bool], prior: Option<f64>) -> Seen {
    let prior = prior
        .filter(|_| d.mean > 0.0 && !d.partly)
        .map(|a| if d.alpha_one { 1.0 } else { a });
    if d.segs.is_empty() && !d.partly && prior.is_none() {
        // No ray could be cast (every stratum faced away or was buried): hidden.
        return Seen {
            v: 0.0,
            rays: 0,
            tilt: Tilt::default(),
        };
    }
    let (weights, quadrant, mean, cells, partly) =
        (&d.weights, &d.quadrant, d.mean, d.cells, d.partly);
    let (mut num, mut den) = (0.0, 0.0);
    let mut any_blocked = false;
    for (w, &f) in weights.iter().zip(free) {
        den += w;
        if f {
            num += w;
        } else {
            any_blocked = true;
        }
    }
    let v = if let Some(a) = prior {
        let a = a.clamp(0.0, 1.0);
        a + (num - a * den) / (cells as f64 * mean)
    } else if !partly && !free.iter().any(|&f| f) {
        // Every ray blocked: hidden, as the rays say (not the control variate's noise).
        0.0
    } else if mean > 0.0 {
        1.0 - (den - num) / (cells as f64 * mean)
    } else if den > 0.0 {
        num / den
    } else {
        0.0
    };
    // All free: exactly visible (the ratio is 1 up to rounding).
    let v = if prior.is_some() {
        v
    } else if any_blocked {
        v.clamp(0.0, 1.0 - 1e-12)
    } else {
        1.0
    };
    // Per half of the receiver along each parameter (bit 0 of the quadrant: u, bit 1:
    // v): rays free and cast.
    let mut per = [[(0u32, 0u32); 2]; 2];
    for (&q, &f) in quadrant.iter().zip(free) {
        for (axis, halves) in per.iter_mut().enumerate() {
            let h = &mut halves[usize::from((q >> axis) & 1)];
            h.0 += u32::from(f);
            h.1 += 1;
        }
    }
    let tilt = per.map(|[lo, hi]| {
        if lo.1 == 0 || hi.1 == 0 {
            0.0
        } else {
            f64::from(hi.0) / f64::from(hi.1) - f64::from(lo.0) / f64::from(lo.1)
        }
    });
    Seen {
        v,
        rays: d.segs.len() as u64,
        tilt: Tilt::new(tilt),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Resolution;
    use crate::scene::Scene;

    /// The roulette keeps a leaf's entry of a hidden link with probability [`ROULETTE`],
    /// independently of the pair and the same on every call: over 200,000 pairs the share
    /// kept is within 5 standard errors of it (a false alarm about once in 3.5 million
    /// runs), and two seeds keep different pairs.
    #[test]
    fn the_roulette_keeps_its_share_of_the_pairs() {
        let n = 200_000u32;
        let kept = (0..n)
            .filter(|&k| roulette_keeps(1, k % 500, k / 500))
            .count() as f64;
        let se = (ROULETTE * (1.0 - ROULETTE) / f64::from(n)).sqrt();
        let share = kept / f64::from(n);
        assert!(
            (share - ROULETTE).abs() < 5.0 * se,
            "kept {share} of the links, expected {ROULETTE} ± {se}"
        );
        assert!((0..1000).all(|k| roulette_keeps(1, k, 7) == roulette_keeps(1, k, 7)));
        assert!((0..1000).any(|k| roulette_keeps(1, k, 7) != roulette_keeps(2, k, 7)));
    }

    /// The pieces of a split source judged from the pair's own rays ([`Traced::pieces`])
    /// are unbiased: over 400 seeds their mean fractions match each piece's fraction from
    /// 4,096 rays of its own, within 4 standard errors of the difference (4 pieces, so
    /// about 3e-4 of a false alarm), on a pair of the Cornell box that the tall block
    /// partly hides.
    #[test]
    fn pieces_from_the_pairs_rays_are_unbiased() {
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(200.0)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let mut e = Elements::from_patches(&patches);
        let settings = crate::hierarchy::Settings::default();
        let tol = 1e-9 * patches.diagonal;
        // A pair that 16 rays find partly hidden, with a quad source.
        let (r, s) = {
            let blockers = Blockers::new(&e, patches.diagonal);
            let ctx = Context::new(&e, &patches, &vis, &blockers, &settings, tol);
            let quad = |s: u32| matches!(e.piece[s as usize], exact::Piece::Quad(_));
            (0..e.roots as u32)
                .flat_map(|r| (0..e.roots as u32).map(move |s| (r, s)))
                .find(|&(r, s)| {
                    r != s && quad(s) && {
                        let v = visible_fraction_n(&ctx, r, s, 8, None).v;
                        (0.3..0.7).contains(&v)
                    }
                })
                .expect("a partly hidden pair")
        };
        let kids = e.split(s);
        let blockers = Blockers::new(&e, patches.diagonal);
        let ctx = Context::new(&e, &patches, &vis, &blockers, &settings, tol);
        let open = |s: u32| open_factor(&ctx, r, s, 1e-12).value;
        let pieces: Vec<(u32, f64)> = kids.iter().map(|&c| (c, open(c))).collect();
        let reference: Vec<Seen> = pieces
            .iter()
            .map(|&(c, f)| visible_fraction_n(&ctx, r, c, 64, Some(f)))
            .collect();
        let seeds = 400;
        let mut sum = [0.0f64; 4];
        let mut sq = [0.0f64; 4];
        let mut judged = 0;
        for seed in 0..seeds {
            let ctx = Context {
                seed,
                ..Context::new(&e, &patches, &vis, &blockers, &settings, tol)
            };
            let t = traced(&ctx, r, s, Some(open(s)), false);
            for (k, p) in t.pieces(&ctx, s, &pieces, 1, None).iter().enumerate() {
                let (seen, rays) = p.expect("every quarter of a quad holds 4 of the 16 strata");
                assert_eq!(seen.rays, 0);
                assert!(rays <= 4);
                sum[k] += seen.v;
                sq[k] += seen.v * seen.v;
                judged += 1;
            }
        }
        assert_eq!(judged, 4 * seeds);
        let m = seeds as f64;
        for k in 0..4 {
            let mean = sum[k] / m;
            let se = ((sq[k] / m - mean * mean) / (m - 1.0)).sqrt();
            let want = reference[k].v;
            let se_ref = fraction_se(want, 4096.0);
            let z = (mean - want) / (se * se + se_ref * se_ref).sqrt();
            assert!(
                z.abs() < 4.0,
                "piece {k}: {mean} ± {se} against {want} ± {se_ref}"
            );
        }
        // Fewer rays on a piece than asked for: traced afresh by the caller.
        let t = traced(&ctx, r, s, Some(open(s)), false);
        assert!(t
            .pieces(&ctx, s, &pieces, 5, None)
            .iter()
            .all(Option::is_none));
    }

    /// A near source's strata ([`near::strata`], in the final gather) keep the visible
    /// fraction unbiased: on pairs of the Cornell box where a small element faces a wall
    /// or block face many times its size close by, partly hidden, the mean over 400 seeds
    /// of the estimate from 16 rays (around a prior of 1, whatever prior is given, as for
    /// every near pair) matches a brute-force fraction from
    /// 2^18 uniform segments (`Σ w V / Σ w`) within 4 standard errors of the difference
    /// (at most 3 pairs checked: about 2e-4 of a false alarm).
    #[test]
    fn a_near_sources_strata_are_unbiased() {
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(200.0)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let mut e = Elements::from_patches(&patches);
        // Small elements: every root split three times.
        for _ in 0..3 {
            let leaves: Vec<u32> = e.leaves().collect();
            for l in leaves {
                e.split(l);
            }
        }
        let settings = crate::hierarchy::Settings::default();
        let tol = 1e-9 * patches.diagonal;
        let blockers = Blockers::new(&e, patches.diagonal);
        let ctx = Context {
            gather: true,
            ..Context::new(&e, &patches, &vis, &blockers, &settings, tol)
        };
        let open = |r: u32, s: u32| open_factor(&ctx, r, s, 1e-12).value;
        let pairs: Vec<(u32, u32)> = e
            .leaves()
            .flat_map(|r| (0..e.roots as u32).map(move |s| (r, s)))
            .filter(|&(r, s)| {
                e.root[r as usize] != s
                    && near::strata(&e, r, s, 16).is_some()
                    && open(r, s) > 1e-3
                    && (0.2..0.8).contains(&visible_fraction_n(&ctx, r, s, 16, None).v)
            })
            .step_by(7)
            .take(3)
            .collect();
        assert!(!pairs.is_empty(), "no near, partly hidden pair");
        for (r, s) in pairs {
            let f = open(r, s);
            // Brute force: uniform points on both, kernel-weighted.
            let mut rng = Pcg32::keyed(99, u64::from(r), u64::from(s), 0);
            let (mut num, mut den, mut terms) = (0.0, 0.0, Vec::new());
            let (nr, ns) = (e.normal[r as usize], e.normal[s as usize]);
            for _ in 0..64 {
                let mut segs = Vec::new();
                let mut ws = Vec::new();
                for _ in 0..4096 {
                    let (x, jx) = e.point(r, rng.next_f64(), rng.next_f64());
                    let (y, jy) = e.point(s, rng.next_f64(), rng.next_f64());
                    if let Some(w) = kernel_weight((x, nr, jx), (y, ns, jy)) {
                        segs.push(ctx.vis.segment_ray(x, nr, y, ns));
                        ws.push(w);
                    }
                }
                let mut free = vec![false; segs.len()];
                ctx.vis.segments_visible(&segs, &mut free);
                for (w, f) in ws.into_iter().zip(free) {
                    den += w;
                    num += if f { w } else { 0.0 };
                    terms.push((w, f));
                }
            }
            let want = num / den;
            let se_ref = terms
                .iter()
                .map(|&(w, f)| (w * (f64::from(u8::from(f)) - want)).powi(2))
                .sum::<f64>()
                .sqrt()
                / den;
            let seeds = 400;
            let (mut sum, mut sq) = (0.0, 0.0);
            for seed in 0..seeds {
                let ctx = Context {
                    seed,
                    gather: true,
                    ..Context::new(&e, &patches, &vis, &blockers, &settings, tol)
                };
                let v = traced_n(&ctx, r, s, 4, Some(f)).seen_around(0.5).v;
                sum += v;
                sq += v * v;
            }
            let m = seeds as f64;
            let mean = sum / m;
            let se = ((sq / m - mean * mean) / (m - 1.0)).sqrt();
            let z = (mean - want) / (se * se + se_ref * se_ref).sqrt();
            assert!(
                z.abs() < 4.0,
                "{r} <- {s}: {mean} ± {se} against {want} ± {se_ref}"
            );
        }
    }

    /// The estimate around a prior ([`Traced::seen_around`]) is unbiased whatever the
    /// prior: over 3,000 seeds, on a pair of the Cornell box that the tall block mostly
    /// hides (its 16 rays are often all blocked), the mean for priors 0, 0.5 and 1 matches
    /// the fraction from 4,096 rays within 4 standard errors of the difference (3 checks:
    /// about 2e-4 of a false alarm). With prior 0 an all-blocked pair is exactly 0.
    #[test]
    fn estimates_around_a_prior_are_unbiased() {
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(200.0)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let e = Elements::from_patches(&patches);
        let settings = crate::hierarchy::Settings::default();
        let tol = 1e-9 * patches.diagonal;
        let blockers = Blockers::new(&e, patches.diagonal);
        let ctx = Context::new(&e, &patches, &vis, &blockers, &settings, tol);
        let open = |r: u32, s: u32| open_factor(&ctx, r, s, 1e-12).value;
        let (r, s) = (0..e.roots as u32)
            .flat_map(|r| (0..e.roots as u32).map(move |s| (r, s)))
            .find(|&(r, s)| {
                r != s && e.is_leaf(r) && open(r, s) > 1e-3 && {
                    let v = visible_fraction_n(&ctx, r, s, 8, None).v;
                    (0.005..0.1).contains(&v)
                }
            })
            .expect("a mostly hidden pair");
        let want = visible_fraction_n(&ctx, r, s, 64, Some(open(r, s))).v;
        let se_ref = fraction_se(want, 4096.0);
        let priors = [0.0, 0.5, 1.0];
        let seeds = 3000;
        let (mut sum, mut sq) = ([0.0f64; 3], [0.0f64; 3]);
        let mut all_blocked = 0;
        for seed in 0..seeds {
            let ctx = Context {
                seed,
                ..Context::new(&e, &patches, &vis, &blockers, &settings, tol)
            };
            let t = traced(&ctx, r, s, Some(open(r, s)), false);
            if !t.free.iter().any(|&f| f) {
                all_blocked += 1;
                assert_eq!(t.seen_around(0.0).v, 0.0);
            }
            for (k, &a) in priors.iter().enumerate() {
                let v = t.seen_around(a).v;
                sum[k] += v;
                sq[k] += v * v;
            }
        }
        assert!(all_blocked > 30, "only {all_blocked} runs all blocked");
        let m = seeds as f64;
        for (k, a) in priors.iter().enumerate() {
            let mean = sum[k] / m;
            let se = ((sq[k] / m - mean * mean) / (m - 1.0)).sqrt();
            let z = (mean - want) / (se * se + se_ref * se_ref).sqrt();
            assert!(
                z.abs() < 4.0,
                "prior {a}: {mean} ± {se} against {want} ± {se_ref}"
            );
        }
    }
}
