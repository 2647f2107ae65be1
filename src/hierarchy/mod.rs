//! Hierarchical radiosity: elements and links where the light needs them, not a uniform
//! grid (Hanrahan, Salzman and Aupperle, "A rapid hierarchical radiosity algorithm",
//! SIGGRAPH 1991; the patches-and-elements idea of Cohen, Greenberg, Immel and Brock 1986,
//! and the lecture notes' adaptive subdivision).
//!
//! The flat path computes a factor between every pair of patches of a uniform mesh. Here
//! the patches of a coarse mesh are only the *roots* of a tree of elements
//! ([`element`]); light moves along *links* between elements of any level ([`link`]),
//! each with a form factor from the exact point-to-polygon integral and Embree visibility.
//! A link whose brightness-weighted error is above the tolerance is replaced by four finer
//! ones, splitting the receiver or the source ([`refine`]); the system is solved on the
//! tree by gathering over links and push-pull ([`solve`]); and refinement is repeated with
//! the new radiosities until no link changes (multigridding, HSA section 4.2):
//!
//! `roots → contact splits, buried leaves → links between roots →
//!  (refine links ⇄ solve) until stable → leaf mesh → output`.
//!
//! With clusters ([`clusters`]) the start is one self-link of a tree of groups of roots;
//! the passes gather cluster links node by node ([`transfer`]), and the last one leaf by
//! leaf with near-field factors.
//!
//! The result is a set of leaves of very different sizes: large where light is smooth,
//! down to the minimum area along shadow boundaries, contacts and bright nearby sources.
//! [`leaves`] turns them into a mesh without T-vertex cracks for the output stage.
//!
//! **Tolerances.** `error` is relative to the scene's mean radiosity `B̄` (area-weighted
//! luminance, first estimated from the emission as `Σ E A / Σ A / (1 - ρ̄)`, then taken from
//! each solve): a link is refined while it may carry an error above `error × B̄` in the
//! radiosity it brings, or, with `relative_low` below 1 (or `relative_high` above), above
//! `error` times its receiver's own radiosity between those shares of `B̄`
//! ([`refine::Relative`]). The minimum area defaults to `(d / 512)²` for a scene of
//! diagonal `d`.
//!
//! **Determinism.** Links are evaluated in parallel but elements are created on one
//! thread, in the order of the decisions (which are collected in element order), and
//! random streams are keyed on `(seed, receiver, source)`: the same seed gives the same
//! hierarchy and the same bits on any number of threads.

pub mod blockers;
pub mod clusters;
pub mod element;
pub mod leaves;
pub mod link;
pub mod near;
pub mod refine;
pub mod solve;
pub mod transfer;

use std::time::Instant;

use rayon::prelude::*;
use smallvec::SmallVec;

use crate::budget;
use crate::formfactor::exact;
use crate::matrix::Bar;
use crate::mesh::PatchSet;
use crate::sampling::fraction_se;
use crate::scene::luminance;
use crate::visibility::Visibility;
use blockers::Blockers;
use clusters::{Links, Refiner, Tree};
use element::Elements;
use link::{Context, Cost, Link, Tolerance};
use refine::{Decision, Oracle, Relative};
use solve::{Gather, Materials, SolveStats, State};

/// Default [`Settings::hide`].
pub const HIDE: f64 = 0.1;

/// Default [`Settings::relative_low`].
pub const RELATIVE_LOW: f64 = 1.0;

/// Default [`Settings::relative_high`].
pub const RELATIVE_HIGH: f64 = 1.0;

/// Default [`Settings::split_shadows`].
pub const SPLIT_SHADOWS: bool = true;

/// Default [`Settings::descend`].
pub const DESCEND: f64 = 0.03;

/// Default [`Settings::descend_low`]: the cut is absolute.
pub const DESCEND_LOW: f64 = 1.0;

/// Default [`Settings::kernel_cut`].
pub const KERNEL_CUT: f64 = 3e-5;

/// Whether the hierarchy starts from a cluster tree over the roots ([`Settings::clusters`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Clustering {
    /// A link between every pair of roots (refused when their evaluation does not fit).
    Off,
    /// From the self-link of a cluster tree over the roots.
    On,
    /// Clusters for scenes of more than [`AUTO_CLUSTER_ROOTS`] roots, or where the links
    /// between every pair of roots would not fit the memory limit; else none.
    Auto,
}

/// Roots above which [`Clustering::Auto`] clusters. The candidate links between every
/// pair of roots grow as their square: `room-spheres-2` (2,603 roots) baked in 106.5 s of
/// user CPU without clusters and 59.0 s with them (`--method hierarchical`, this 2-core
/// host), `room-spheres-8` (10,240 faces) in 564 s and 64 s (docs/HIERARCHY.md,
/// Clustering). Up to this many, the unclustered start is kept: it is the one checked
/// against closed forms to 1e-6 and against the path tracer on the Cornell box and the
/// room with a sphere (2,091 roots), and costs at most about twice the clustered one.
pub const AUTO_CLUSTER_ROOTS: usize = 4096;

impl Clustering {
    /// Whether a scene of `roots` roots is clustered under the memory limit `max_memory`
    /// (or the available memory): [`Clustering::Auto`] clusters above
    /// [`AUTO_CLUSTER_ROOTS`] roots and where the links between every pair of roots would
    /// not fit (the check that refuses them with [`Clustering::Off`]).
    pub fn resolve(self, roots: usize, max_memory: Option<u64>) -> bool {
        match self {
            Clustering::Off => false,
            Clustering::On => true,
            Clustering::Auto => {
                roots > AUTO_CLUSTER_ROOTS || check_initial_pairs(roots, max_memory).is_err()
            }
        }
    }
}

/// Default [`Settings::clusters`].
pub const CLUSTERS: Clustering = Clustering::Auto;

/// Whether cluster links split receiving elements by default ([`Settings::split_receivers`]).
pub const SPLIT_RECEIVERS: bool = true;

/// Settings of a hierarchical solution.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    /// Link tolerance, relative to the receiver's radiosity between `relative_low` and
    /// `relative_high` times the mean radiosity ([`Relative`]).
    pub error: f64,
    /// Floor of a receiver's radiosity in its link tolerance, as a share of the mean
    /// radiosity (1 with `relative_high` 1: the absolute tolerance `error × mean`).
    pub relative_low: f64,
    /// Cap of a receiver's radiosity in its link tolerance, as a share of the mean.
    pub relative_high: f64,
    /// Smallest element area (scene units²); `None` for `(diagonal / 512)²`.
    pub min_area: Option<f64>,
    /// Visibility strata per side: `rays²` rays per link that is not provably unoccluded.
    pub rays: usize,
    /// Relative tolerance of each link's unoccluded integral.
    pub quadrature: f64,
    /// Share of the link tolerance a link's quadrature error may take: its factor is
    /// integrated to an absolute error of `accuracy × ε / (ρ_r B_s)` when that is looser
    /// than `quadrature` (set it tiny for factors to full precision everywhere).
    pub accuracy: f64,
    /// Share of the link tolerance that a link whose rays were all blocked may carry and
    /// be kept unrefined, instead of being refined: an element link gathered by Russian
    /// roulette ([`link::Basis::Roulette`]), a cluster link estimated by rays of its own
    /// ([`clusters`]).
    pub hide: f64,
    /// Share of the link tolerance above which the final gather replaces a split source
    /// by its children, and a cluster source by its sub-clusters ([`gather_lists`]).
    /// Larger: fewer gather entries, sources' mean radiosity used where it varies more.
    /// Measured (docs/HIERARCHY.md, *The gather's sources*): 0.1 instead of 0.03 cuts
    /// `room-spheres-12-s3`'s entries by 40% and its CPU by 36%, within the bake's noise,
    /// but doubles the Cornell box's worst face error (0.69% to 1.34% at `--error 0.01`).
    pub descend: f64,
    /// Floor, as a share of the mean radiosity, of the receiver radiosity that the final
    /// gather's source cut is relative to (`descend` times `error` times the leaf's own
    /// radiosity, floored here and capped at the mean); 1 (the default) keeps the cut
    /// absolute. Below 1, dark receivers cut their sources finer: on the Cornell box,
    /// 0.25 brings the short block's dark face 8 from +0.64% to within 0.3% of the path
    /// tracer for 17% more rays (docs/HIERARCHY.md, *What does not hold yet*).
    pub descend_low: f64,
    /// Share of the source cut's tolerance (`descend_low` applied) above which the final
    /// gather also cuts a source that a leaf sees whole (no rays of its own) when the
    /// leaf's view weights the source's children otherwise than their areas do:
    /// `ρ F |Σ_c (F_c / Σ F_c - A_c / A_s) B_c|`, with `F_c` the point factors from the
    /// leaf's centre to the children (four evaluations, no rays). That error has one sign
    /// over a leaf's many entries (a leaf sees the near part of a wall, darker by the
    /// corner, more than the wall's mean), so the share is small; the range test of
    /// `descend` misses it where the radiosity varies smoothly. 0 turns it off. On the
    /// Cornell box at `--error 0.01` the default takes every face within 0.3% of the path
    /// tracer (15 of 19 without) for the same rays and 1.5 times the CPU time
    /// (docs/HIERARCHY.md, *The sources' mean radiosity*).
    pub kernel_cut: f64,
    /// Share of a leaf's tolerance that the cluster links it takes at their own visible
    /// fractions may move its radiosity by together, in the final gather; it checks its
    /// own view of the others' sources ([`CLUSTER_SIGHT_SHARE`], the default). Infinite:
    /// every leaf takes every cluster link's fraction.
    pub cluster_sight: f64,
    /// Share of a leaf's tolerance that the visibility noise of its element entries may
    /// reach, at one standard error, in the final gather (`--gather-noise`): where the
    /// entries' standard errors, weighted by what each source sends, add up (in
    /// quadrature) to more, the loudest entries are traced again from the leaf with more
    /// rays ([`GATHER_NOISE_RAYS`]), each once, from a stream of its own, and the new
    /// estimate replaces the first. Infinite (the default): no entry is traced again.
    /// docs/HIERARCHY.md, *The gather's visibility noise*.
    pub gather_noise: f64,
    /// Per-element relative change at which the solve stops.
    pub tolerance: f64,
    /// Iteration cap of each solve.
    pub max_iterations: usize,
    /// Cap on refine-and-solve passes.
    pub max_passes: usize,
    /// Refinement stops (with a note) once there are this many links.
    pub max_links: usize,
    /// Seed of the random streams.
    pub seed: u64,
    /// Start from the self-link of a cluster tree over the roots ([`clusters`]) instead of
    /// a link between every pair of roots: always, never, or as the scene's size asks
    /// ([`Clustering`]).
    pub clusters: Clustering,
    /// Largest relative error bound of a cluster link (the geometric and visibility terms
    /// of [`clusters`], before the transfer they scale): infinite to let the link
    /// tolerance alone decide; 1 to 3 trade links for agreement with unclustered bakes
    /// (docs/HIERARCHY.md, Clustering).
    pub cluster_accuracy: f64,
    /// Relative tolerance of a cluster link's transfer in the final gather: a piece of its
    /// source whose sampled factor to a leaf is less accurate than this (twice its standard
    /// error plus its rules' bound) is integrated over the piece's faces to this tolerance
    /// instead ([`clusters::exact_piece`]). Infinite (the default): the sampled factor,
    /// whose error the link's own bound covers. Tight values make closed scenes conserve
    /// their light to the quadrature's precision with cluster links in use, at the cost of
    /// a factor per leaf and source face (docs/HIERARCHY.md, Clustering).
    pub cluster_quadrature: f64,
    /// Split a receiving element larger than its source cluster into its element children
    /// (cluster links below the roots; [`clusters`]) instead of splitting the source down
    /// to its faces. Measured (docs/HIERARCHY.md, Clustering): on `room-spheres-12-s5`
    /// 510 s of user CPU and 3.5 GiB instead of 837 s and 4.5 GiB, and the power
    /// unaccounted for 0.78% instead of 1.08%; but at 10^4 triangles (`room-spheres-8`)
    /// the root averages differ from the unclustered bake's by 2.55% at the 99th
    /// percentile instead of 0.80% (single sphere faces, within both bakes' estimated
    /// errors). Against a path tracer (Mitsuba 3) the switch is the more accurate of the
    /// two on the floor of `room-spheres-8`: within 4.9% on average at points in the
    /// spheres' shadows, where the unclustered bake and the switch off are 17% off. On by
    /// default ([`SPLIT_RECEIVERS`]).
    pub split_receivers: bool,
    /// A receiver whose shadows vary across it by more than its tolerance, as the tilts of
    /// its partly visible links add up ([`refine::Oracle::shadowed`]), is split, its
    /// partly visible links going to its children (`--split-shadows`). Without it the
    /// larger element of a link is split, often the source (a light), and each piece's
    /// link then falls within the tolerance while the receiver keeps the shadow boundaries
    /// of all the pieces across it. Measured (docs/HIERARCHY.md, *Shadows across
    /// receivers*): on `room-spheres-8` at the default tolerance, every point in the
    /// spheres' shadows within 1.7% of Mitsuba 3 instead of 5.5%, for 26% more CPU; on
    /// the Cornell box the shadow line within 1.6% instead of 3.7%. On by default
    /// ([`SPLIT_SHADOWS`]).
    pub split_shadows: bool,
    /// Memory the solution may take (`--max-memory`); `None` for the available memory
    /// ([`budget::limit_of`]). Checked before the initial links and as links are added.
    pub max_memory: Option<u64>,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            error: 0.01,
            relative_low: RELATIVE_LOW,
            relative_high: RELATIVE_HIGH,
            min_area: None,
            rays: 4,
            quadrature: 1e-6,
            accuracy: 0.01,
            hide: HIDE,
            descend: DESCEND,
            descend_low: DESCEND_LOW,
            kernel_cut: KERNEL_CUT,
            cluster_sight: CLUSTER_SIGHT_SHARE,
            gather_noise: f64::INFINITY,
            tolerance: 1e-7,
            max_iterations: 10_000,
            max_passes: 8,
            max_links: 40_000_000,
            seed: 1,
            clusters: CLUSTERS,
            cluster_accuracy: f64::INFINITY,
            cluster_quadrature: f64::INFINITY,
            split_receivers: SPLIT_RECEIVERS,
            split_shadows: SPLIT_SHADOWS,
            max_memory: None,
        }
    }
}

impl Settings {
    /// The link tolerance per receiver, for a scene of mean radiosity `mean`.
    pub fn relative(&self, mean: f64) -> Relative {
        Relative {
            error: self.error,
            mean,
            low: self.relative_low,
            high: self.relative_high,
        }
    }

    /// Checks the ranges, before any work.
    pub fn validate(&self) -> crate::Result<()> {
        let bad = |m: String| Err(crate::Error::Config(m));
        if !(self.error > 0.0 && self.error.is_finite()) {
            return bad(format!(
                "--error must be a positive number, got {}",
                self.error
            ));
        }
        if !(self.relative_low > 0.0
            && self.relative_low <= self.relative_high
            && !self.relative_high.is_nan())
        {
            return bad(format!(
                "--relative-low and --relative-high must satisfy 0 < low <= high, got {} and {}",
                self.relative_low, self.relative_high
            ));
        }
        if let Some(a) = self.min_area {
            if !(a > 0.0 && a.is_finite()) {
                return bad(format!("--min-area must be a positive number, got {a}"));
            }
        }
        if !(1..=64).contains(&self.rays) {
            return bad(format!("--link-rays must be in 1..=64, got {}", self.rays));
        }
        if !(self.accuracy >= 0.0 && self.accuracy.is_finite()) {
            return bad(format!("link accuracy must be >= 0, got {}", self.accuracy));
        }
        if !(self.hide >= 0.0 && self.hide.is_finite()) {
            return bad(format!("hide share must be >= 0, got {}", self.hide));
        }
        if !(self.descend > 0.0 && self.descend.is_finite()) {
            return bad(format!(
                "--descend must be a positive number, got {}",
                self.descend
            ));
        }
        if !(self.descend_low > 0.0 && self.descend_low <= 1.0) {
            return bad(format!(
                "--descend-low must be in (0, 1], got {}",
                self.descend_low
            ));
        }
        if self.cluster_sight.is_nan() || self.cluster_sight < 0.0 {
            return bad(format!(
                "--cluster-sight must be a number >= 0 (or inf), got {}",
                self.cluster_sight
            ));
        }
        if self.gather_noise.is_nan() || self.gather_noise <= 0.0 {
            return bad(format!(
                "--gather-noise must be a positive number (or inf), got {}",
                self.gather_noise
            ));
        }
        if !(self.kernel_cut >= 0.0 && self.kernel_cut.is_finite()) {
            return bad(format!(
                "--kernel-cut must be a number >= 0, got {}",
                self.kernel_cut
            ));
        }
        if self.cluster_accuracy.is_nan() || self.cluster_accuracy <= 0.0 {
            return bad(format!(
                "--cluster-accuracy must be a positive number (or inf), got {}",
                self.cluster_accuracy
            ));
        }
        if !(self.cluster_quadrature > 0.0 && self.cluster_quadrature < 1.0
            || self.cluster_quadrature == f64::INFINITY)
        {
            return bad(format!(
                "--cluster-quadrature must be in (0, 1) (or inf), got {}",
                self.cluster_quadrature
            ));
        }
        if !(self.quadrature > 0.0 && self.quadrature < 1.0) {
            return bad(format!(
                "quadrature tolerance must be in (0, 1), got {}",
                self.quadrature
            ));
        }
        if !(self.tolerance > 0.0 && self.tolerance < 1.0) {
            return bad(format!(
                "--tolerance must be in (0, 1), got {}",
                self.tolerance
            ));
        }
        Ok(())
    }
}

/// One refine-and-solve pass.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pass {
    /// Links replaced by finer ones.
    pub refined: usize,
    /// Links after the pass.
    pub links: usize,
    /// Elements after the pass.
    pub elements: usize,
    /// Rays cast by the pass (links and buried tests).
    pub rays: u64,
    /// The solve that followed.
    pub solve: SolveStats,
    /// Seconds refining.
    pub refine_seconds: f64,
    /// Seconds building the leaves' gather lists (the last pass; 0 before it).
    pub gather_seconds: f64,
    /// Seconds solving (with the gather lists on the last pass).
    pub solve_seconds: f64,
}

/// What a hierarchical solution did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Report {
    /// Root patches.
    pub roots: usize,
    /// Elements in all.
    pub elements: usize,
    /// Leaves (the output's patches).
    pub leaves: usize,
    /// Leaves inside closed solids.
    pub buried: usize,
    /// Element splits made along contacts before linking.
    pub contact_splits: usize,
    /// Links at the end.
    pub links: usize,
    /// Of which partly visible.
    pub partial_links: usize,
    /// Initial links: between roots, plus cluster links when clustering.
    pub initial_links: usize,
    /// Clusters in the tree over the roots (0 without clustering).
    pub clusters: usize,
    /// True when [`Clustering::Auto`] chose clusters for this scene.
    pub auto_clusters: bool,
    /// Cluster links at the end.
    pub cluster_links: usize,
    /// Node pairs the cluster refinement examined.
    pub cluster_pairs: usize,
    /// Entries of the leaves' gather lists (their ancestor chains' links).
    pub gather: usize,
    /// Of those, the entries from cluster links (a piece of a source cluster each,
    /// [`clusters::Expansion::entries`]); the rest are from element links.
    pub gather_from_clusters: usize,
    /// Largest factor sum of a visible leaf (its gather list), and that sum's error bar.
    pub max_row_sum: (f64, crate::matrix::Bar),
    /// Visible leaves whose factor sum exceeds 1 by more than 3 standard errors plus its
    /// bound ([`crate::matrix::over_one`]: the quadrature bounds add linearly, the
    /// visibility standard errors in quadrature).
    pub rows_over_one: usize,
    /// Rays cast in all.
    pub rays: u64,
    /// Point-to-polygon evaluations in all.
    pub evals: u64,
    /// Seconds before the links: contact splits, buried leaves, the blockers' index and
    /// the cluster tree.
    pub prepare_seconds: f64,
    /// Seconds making and evaluating the initial links (with clusters, the first cluster
    /// refinement from the top cluster's self-link).
    pub start_seconds: f64,
    /// Passes, in order.
    pub passes: Vec<Pass>,
    /// Absolute link tolerance of the last pass.
    pub eps: f64,
    /// Mean radiosity (area-weighted luminance) of the solution.
    pub mean_radiosity: f64,
    /// Minimum element area used.
    pub min_area: f64,
    /// Links still over the tolerance because their elements are at the minimum area.
    pub unresolved: usize,
    /// Largest estimated error of a visible leaf's radiosity, relative to the mean
    /// radiosity: the error that the bars of its factors allow, carried through the
    /// interreflections. Each entry `l ← s` of the leaf's gather list errs by its
    /// quadrature bound plus one visibility standard error, weighted by `ρ_l B_s` (the
    /// leaf's reflected irradiance's bar, [`solve::Gather::carried`], `d_l`), and the
    /// sources' own errors arrive through the same factors: `x = d + ρ F x` (solved over
    /// the gather lists; see `propagate` in the source for the derivation, after Arvo,
    /// Torrance and Smits 1994). It tracks the error of the factors; it is not a strict
    /// bound (the bars hold one standard error), and it does not count the error of taking
    /// a source's mean radiosity where that varies, the light of links dropped as hidden,
    /// nor cluster links' sources. On the Cornell furnace (`B = 2` everywhere) its mean is
    /// 2.5 times the actual mean error, and the actual error is above it on 5% of the
    /// visible area (docs/HIERARCHY.md, *The error estimate*).
    pub max_error: f64,
    /// The same, visible-area-weighted mean over visible leaves.
    pub mean_error: f64,
    /// Emitted and absorbed power (`Σ A E`, `Σ A (1 - ρ) H`, RGB).
    pub emitted: [f64; 3],
    /// See `emitted`.
    pub absorbed: [f64; 3],
    /// Things the user should know (a cap reached, a solve not converged).
    pub notes: Vec<String>,
}

/// A solved hierarchy.
pub struct Solution {
    /// The element tree.
    pub elements: Elements,
    /// Links per receiving element.
    pub links: Vec<Vec<Link>>,
    /// Radiosity per element.
    pub state: State,
    /// Estimated error of each element's radiosity (the largest channel's), absolute: for a leaf, what its factors' bars allow, carried through the
    /// interreflections ([`Report::max_error`]); for a parent, the visible-area mean of its
    /// leaves'; 0 for buried leaves.
    pub error: Vec<f64>,
    /// What was done.
    pub report: Report,
}

/// Builds, refines and solves the hierarchy over the root patches `patches` (whose
/// triangles `vis` traces); `progress` hears about each finished pass.
pub fn run(
    patches: &PatchSet,
    vis: &Visibility,
    s: &Settings,
    progress: &(dyn Fn(&Pass) + Sync),
) -> crate::Result<Solution> {
    s.validate()?;
    let t_prepare = Instant::now();
    let diag = patches.diagonal;
    let tol = 1e-9 * diag;
    let min_area = s.min_area.unwrap_or((diag / 512.0).powi(2));
    let mut e = Elements::from_patches(patches);
    let mut report = Report {
        roots: e.roots,
        min_area,
        ..Default::default()
    };
    let material =
        |e: &Elements, k: usize| &patches.materials[patches.material[e.root[k] as usize] as usize];
    // Contacts, then buried leaves.
    let contacts = refine::contacts(&e, 1e-6 * diag);
    report.contact_splits = refine::split_along_contacts(&mut e, &contacts, min_area, tol);
    let standing = refine::standing(&e, &contacts, 1e-6 * diag);
    report.contact_splits += refine::split_along_contacts(&mut e, &standing, min_area, -tol);
    let normals: Vec<glam::DVec3> = e.normal[..e.roots].to_vec();
    let blockers = Blockers::new(&e, diag);
    // Nothing is buried where nothing can block (a convex room has no solids inside).
    let solids = !blockers.is_empty();
    if solids {
        let leaves: Vec<u32> = e.leaves().collect();
        let (_, bury_rays) = refine::bury(&mut e, &leaves, vis, &normals, s.seed);
        report.rays += bury_rays;
    }

    // Radiosity starts at the emission; the mean from the furnace estimate.
    let mut state = State::default();
    let (rho, emit) = materials(&e, &material);
    state.b = emit.clone();
    state.spread = vec![[0.0; 3]; e.len()];
    state.h = vec![[0.0; 3]; e.len()];
    solve::pull(&e, &e.visible_areas(), &mut state);
    let (mut sum_ea, mut sum_a, mut sum_rho) = (0.0, 0.0, 0.0);
    for k in 0..e.roots {
        let a = e.area[k];
        sum_ea += a * luminance(emit[k]);
        sum_rho += a * luminance(rho[k]);
        sum_a += a;
    }
    let mut b_ref = sum_ea / sum_a / (1.0 - sum_rho / sum_a).max(1e-3);

    // Initial links: from the top cluster's self-link, or between every pair of roots.
    let n = e.roots as u32;
    let visible = e.visible_areas();
    let rho_max: Vec<f64> = rho[..e.roots]
        .iter()
        .map(|r| r.iter().copied().fold(0.0, f64::max))
        .collect();
    let clustered = s.clusters.resolve(e.roots, s.max_memory);
    report.auto_clusters = clustered && s.clusters == Clustering::Auto;
    let tree = (clustered && e.roots >= 2).then(|| Tree::build(&e, &visible, &rho_max));
    let tree = tree.as_ref();
    report.prepare_seconds = t_prepare.elapsed().as_secs_f64();
    let t_start = Instant::now();
    let mut clinks = tree.map_or_else(Links::default, |t| Links::new(t, e.len()));
    state.pull_clusters(tree, &visible);
    let mut links: Vec<Vec<Link>> = vec![Vec::new(); e.len()];
    let specs: Vec<(u32, u32)> = match tree {
        Some(t) => {
            let mut grow = Grow {
                e: &mut e,
                state: &mut state,
                links: &mut links,
                vis,
                normals: &normals,
                solids,
                seed: s.seed,
            };
            let top = clusters::top(t);
            let (specs, _) = refine_clusters(
                t,
                &mut grow,
                &mut clinks,
                &rho_max,
                Some(vec![(top, top)]),
                (b_ref, s.error * b_ref, min_area, tol),
                s,
                &mut report,
            );
            report.clusters = t.len();
            specs
        }
        None => {
            check_initial_pairs(e.roots, s.max_memory)?;
            (0..n)
                .flat_map(|r| (0..n).filter(move |&t| t != r).map(move |t| (r, t)))
                .collect()
        }
    };
    {
        // The cluster refinement may have split receivers.
        let (rho, _) = materials(&e, &material);
        let ctx = Context::new(&e, patches, vis, &blockers, s, tol);
        let tols = tolerances(&specs, &rho, &state.b, s.relative(b_ref).unknown(), s);
        let cost = evaluate_into(&ctx, &specs, &tols, &mut links);
        report.rays += cost.rays;
        report.evals += cost.evals;
    }
    report.initial_links = links.iter().map(Vec::len).sum::<usize>() + clinks.len();
    report.start_seconds = t_start.elapsed().as_secs_f64();

    let mut error: Vec<f64> = Vec::new();
    let mut rel = s.relative(b_ref);
    for pass_no in 0..s.max_passes.max(1) {
        let t0 = Instant::now();
        // Cluster links keep the absolute tolerance; element links the receiver's, once
        // a solve has given the receivers their radiosity.
        let eps = s.error * b_ref;
        rel = if pass_no == 0 {
            s.relative(b_ref).unknown()
        } else {
            s.relative(b_ref)
        };
        report.eps = eps;
        let rays_before = report.rays;
        // Cluster links that today's radiosity puts over the tolerance go down a level.
        let mut regrouped = 0;
        if let (Some(t), true) = (tree, pass_no > 0) {
            let mut grow = Grow {
                e: &mut e,
                state: &mut state,
                links: &mut links,
                vis,
                normals: &normals,
                solids,
                seed: s.seed,
            };
            let (specs, replaced) = refine_clusters(
                t,
                &mut grow,
                &mut clinks,
                &rho_max,
                None,
                (0.0, eps, min_area, tol),
                s,
                &mut report,
            );
            regrouped = replaced;
            let (rho, _) = materials(&e, &material);
            let ctx = Context::new(&e, patches, vis, &blockers, s, tol);
            let tols = tolerances(&specs, &rho, &state.b, rel, s);
            let cost = evaluate_into(&ctx, &specs, &tols, &mut links);
            report.rays += cost.rays;
            report.evals += cost.evals;
        }
        let refined = regrouped
            + refine_links(
                &mut e,
                &mut links,
                &mut state,
                patches,
                vis,
                &blockers,
                s,
                rel,
                min_area,
                tol,
                &normals,
                &mut report,
            );
        let refine_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let mut gather_seconds = 0.0;
        let (rho, emit) = materials(&e, &material);
        let m = Materials {
            rho: &rho,
            emit: &emit,
        };
        // HSA's push-pull while the hierarchy still changes; the leaves gather over their
        // ancestor chains once it is final, all but settled ([`SETTLED`]), or the passes
        // run out.
        let total: usize = links.iter().map(Vec::len).sum();
        let settled = pass_no > 0 && refined as f64 <= SETTLED * total as f64;
        let last = settled || pass_no + 1 == s.max_passes.max(1);
        let stats = if last {
            // The links no longer grow: their lists' spare room (up to half of them, from
            // growth by doubling) is given back before the gather lists are built beside them.
            for l in &mut links {
                l.shrink_to_fit();
            }
            let ctx = Context {
                gather: true,
                ..Context::new(&e, patches, vis, &blockers, s, tol)
            };
            let extra = expansion(tree, &e, &clinks, vis, &state, eps, s);
            check_gather(&e, &links, extra.as_ref(), tree.is_some(), s)?;
            let (gather, cost, from_clusters) = gather_lists(
                &ctx,
                &links,
                extra.as_ref(),
                &rho,
                &state,
                rel,
                s.accuracy,
                (s.descend, s.descend_low, s.kernel_cut),
                s.gather_noise,
            );
            gather_seconds = t1.elapsed().as_secs_f64();
            report.evals += cost.evals;
            report.rays += cost.rays;
            report.gather = gather.len();
            report.gather_from_clusters = from_clusters;
            report.max_row_sum = (0.0, crate::matrix::Bar::ZERO);
            report.rows_over_one = 0;
            for &(sum, bar) in &gather.row_sum {
                if sum > report.max_row_sum.0 {
                    report.max_row_sum = (sum, bar);
                }
                if crate::matrix::over_one(sum, bar, 3.0) {
                    report.rows_over_one += 1;
                }
            }
            let st = solve::solve(
                &e,
                tree,
                &gather,
                &m,
                &mut state,
                b_ref,
                s.tolerance,
                s.max_iterations,
            );
            let carried: Vec<f64> = gather.carried.iter().map(|b| b.bound + b.se).collect();
            error = propagate(&e, &gather, &rho, &carried);
            st
        } else {
            let extra = transfer(tree, &e, &clinks, vis, &state, eps, s);
            solve::solve_push(
                &e,
                tree,
                extra.as_ref(),
                &links,
                &m,
                &mut state,
                b_ref,
                pass_tolerance(s),
                s.max_iterations,
            )
        };
        solve::estimate_spread(&e, &links, &rho, &mut state);
        state.pull_clusters(tree, &e.visible_areas());
        b_ref = mean_radiosity(&e, &state).max(f64::MIN_POSITIVE);
        let pass = Pass {
            refined,
            links: links.iter().map(Vec::len).sum(),
            elements: e.len(),
            rays: report.rays - rays_before,
            solve: stats,
            refine_seconds,
            gather_seconds,
            solve_seconds: t1.elapsed().as_secs_f64(),
        };
        progress(&pass);
        report.passes.push(pass);
        if !stats.converged {
            report.notes.push(format!(
                "pass {}: the solve stopped after {} iterations at a relative change of {:.1e} \
                 (tolerance {:.1e})",
                pass_no + 1,
                stats.iterations,
                stats.change,
                if last { s.tolerance } else { pass_tolerance(s) }
            ));
        }
        if settled {
            break;
        }
        if pass_no + 1 == s.max_passes.max(1) && refined > 0 {
            report.notes.push(format!(
                "refinement was still changing {refined} links after {} passes (--max-passes)",
                s.max_passes
            ));
        }
    }
    report.cluster_links = clinks.len();
    finish_report(
        &e,
        &links,
        &state,
        &error,
        min_area,
        b_ref,
        rel,
        &material,
        &mut report,
    );
    Ok(Solution {
        elements: e,
        links,
        state,
        error,
        report,
    })
}

/// The cluster links with their sources cut into pieces where their radiosity varies
/// ([`clusters::Expansion`]); none without clusters.
#[allow(clippy::too_many_arguments)]
fn expansion<'a>(
    tree: Option<&'a Tree>,
    e: &Elements,
    clinks: &'a Links,
    vis: &Visibility,
    state: &State,
    eps: f64,
    s: &Settings,
) -> Option<clusters::Expansion<'a>> {
    let t = tree?;
    let visible = e.visible_areas();
    let rho_max = vec![0.0; e.roots];
    let f = refiner(
        t,
        e,
        &visible,
        &rho_max,
        vis,
        state,
        (0.0, eps, 0.0, 0.0),
        s,
    );
    let pieces = f.all_pieces(clinks, s.descend);
    Some(clusters::Expansion {
        tree: t,
        links: clinks,
        sight: s.cluster_sight,
        pieces,
        seed: f.seed,
        points: f.points,
        visible,
        quadrature: s.cluster_quadrature,
    })
}

/// The cluster links gathered node by node ([`transfer`]); none without clusters.
fn transfer(
    tree: Option<&Tree>,
    e: &Elements,
    clinks: &Links,
    vis: &Visibility,
    state: &State,
    eps: f64,
    s: &Settings,
) -> Option<transfer::Transfer> {
    let t = tree?;
    let visible = e.visible_areas();
    let rho_max = vec![0.0; e.roots];
    let mut f = refiner(
        t,
        e,
        &visible,
        &rho_max,
        vis,
        state,
        (0.0, eps, 0.0, 0.0),
        s,
    );
    f.points = 0;
    Some(transfer::Transfer::build(&f, clinks, s.descend))
}

/// The cluster refinement's view of the current solution: `floor` the radiosity assumed
/// for sources not solved yet, `eps` the absolute link tolerance, `min_area` the smallest
/// receiver it may split, `tol` the distance below which a point counts as on a plane
/// (0 where the refiner only cuts sources into pieces).
#[allow(clippy::too_many_arguments)]
fn refiner<'a>(
    tree: &'a Tree,
    e: &'a Elements,
    visible: &'a [f64],
    rho_max: &'a [f64],
    vis: &'a Visibility,
    state: &'a State,
    (floor, eps, min_area, tol): (f64, f64, f64, f64),
    s: &Settings,
) -> Refiner<'a> {
    Refiner {
        split_receivers: s.split_receivers,
        tree,
        elements: e,
        visible,
        rho_max,
        vis,
        b: &state.b,
        spread: &state.spread,
        clusters: &state.clusters,
        floor,
        eps,
        tol,
        hide: s.hide,
        rays: s.rays,
        seed: s.seed,
        accuracy: s.cluster_accuracy,
        points: clusters::POINTS,
        moments: std::sync::OnceLock::new(),
        min_area,
    }
}

/// What splitting an element during refinement touches: the elements, the solution's
/// per-element arrays and the element links' lists, and what burying new leaves needs.
struct Grow<'a> {
    e: &'a mut Elements,
    state: &'a mut State,
    links: &'a mut Vec<Vec<Link>>,
    vis: &'a Visibility,
    normals: &'a [glam::DVec3],
    /// True when something can bury a leaf ([`refine::bury`]).
    solids: bool,
    seed: u64,
}

impl Grow<'_> {
    /// Splits the leaves among `targets` (each once, in order), children starting from
    /// their parent's radiosity; buries the new leaves that lie inside solids. Returns the
    /// rays cast.
    fn split(&mut self, targets: impl IntoIterator<Item = u32>) -> u64 {
        let mut new_leaves = Vec::new();
        for target in targets {
            if !self.e.is_leaf(target) {
                continue;
            }
            let kids = self.e.split(target);
            for c in kids {
                self.state.b.push(self.state.b[target as usize]);
                self.state.spread.push([0.0; 3]);
                self.state.h.push([0.0; 3]);
                debug_assert_eq!(self.state.b.len() - 1, c as usize);
            }
            new_leaves.extend(kids);
        }
        let mut rays = 0;
        if self.solids && !new_leaves.is_empty() {
            rays = refine::bury(self.e, &new_leaves, self.vis, self.normals, self.seed).1;
        }
        self.links.resize(self.e.len(), Vec::new());
        rays
    }
}

/// Cluster refinement from the pairs `start`, or (with `None`) the re-examination of the
/// cluster links with today's radiosity ([`clusters::recheck`]), splitting the receiving
/// elements it asks for and refining their children's pairs, round after round, until
/// none is asked for. `(floor, eps, min_area, tol)` as in [`refiner`]. Returns the pairs of
/// elements for element links and the number of cluster links replaced.
#[allow(clippy::too_many_arguments)]
fn refine_clusters(
    t: &Tree,
    grow: &mut Grow,
    clinks: &mut Links,
    rho_max: &[f64],
    start: Option<Vec<(u32, u32)>>,
    (floor, eps, min_area, tol): (f64, f64, f64, f64),
    s: &Settings,
    report: &mut Report,
) -> (Vec<(u32, u32)>, usize) {
    let mut specs = Vec::new();
    let mut replaced = 0;
    let mut frontier = start;
    loop {
        let visible = grow.e.visible_areas();
        let f = refiner(
            t,
            grow.e,
            &visible,
            rho_max,
            grow.vis,
            grow.state,
            (floor, eps, min_area, tol),
            s,
        );
        let mut made = match frontier.take() {
            Some(pairs) => clusters::refine(&f, pairs, clinks),
            None => {
                let (made, r) = clusters::recheck(&f, clinks);
                replaced = r;
                made
            }
        };
        report.rays += made.rays;
        report.cluster_pairs += made.pairs;
        specs.append(&mut made.specs);
        if made.subdivide.is_empty() {
            break;
        }
        report.rays += grow.split(made.subdivide.iter().map(|&(r, _)| r));
        frontier = Some(clusters::split_receivers(grow.e, &made.subdivide));
    }
    (specs, replaced)
}

/// Reflectance and emission per element, from its root's material.
fn materials<'a>(
    e: &Elements,
    material: &impl Fn(&Elements, usize) -> &'a crate::scene::Material,
) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    (0..e.len())
        .map(|k| {
            let m = material(e, k);
            (m.rho, m.emit)
        })
        .unzip()
}

/// Area-weighted mean luminance of the visible leaves' radiosity.
fn mean_radiosity(e: &Elements, state: &State) -> f64 {
    let (mut sum, mut area) = (0.0, 0.0);
    for l in e.leaves() {
        let li = l as usize;
        if !e.buried[li] {
            let a = e.visible_area(l);
            sum += a * luminance(state.b[li]);
            area += a;
        }
    }
    if area > 0.0 {
        sum / area
    } else {
        0.0
    }
}

/// The tolerances of each candidate link `r ← s` on its factor `F_rs`, from the
/// receiver's link tolerance `ε` and channel weights `k` ([`Relative::weights`]): what it
/// may lose by being dropped as hidden, `hide × ε / w`, and its quadrature error,
/// `accuracy × ε / w`, with `w = max over channels of k ρ_r B_s` (`hide`, `accuracy` from
/// the settings `set`). A source
/// whose radiosity is not known yet (0 before the first solve) is taken at the mean
/// radiosity, so that links made early are neither dropped nor integrated more coarsely
/// than later ones.
fn tolerances(
    specs: &[(u32, u32)],
    rho: &[[f64; 3]],
    b: &[[f64; 3]],
    rel: Relative,
    set: &Settings,
) -> Vec<Tolerance> {
    specs
        .iter()
        .map(|&(r, t)| {
            let (eps, k) = rel.weights(b[r as usize]);
            let w = (0..3)
                .map(|c| k[c] * rho[r as usize][c] * b[t as usize][c].max(rel.mean))
                .fold(0.0, f64::max);
            if w > 0.0 {
                Tolerance {
                    factor: set.accuracy * eps / w,
                    hide: set.hide * eps / w,
                }
            } else {
                Tolerance {
                    factor: f64::INFINITY,
                    hide: f64::INFINITY,
                }
            }
        })
        .collect()
}

/// Bytes a candidate pair of roots holds while the initial links of an unclustered
/// hierarchy are evaluated: the pair, its tolerances, its evaluation, and the link kept.
const BYTES_PER_INITIAL_PAIR: u64 = (std::mem::size_of::<(u32, u32)>()
    + std::mem::size_of::<Tolerance>()
    + std::mem::size_of::<(Option<Link>, Cost)>()
    + std::mem::size_of::<Link>()) as u64;

/// Bytes a link holds in its receiver's list, with room for the list's growth by doubling.
const BYTES_PER_LINK: u64 = 2 * std::mem::size_of::<Link>() as u64;

/// The least `--link-quadrature` at which gather factors are held in `f32` ([`solve::List`]):
/// 16 times their rounding.
const NARROW_QUADRATURE: f64 = 1e-6;

/// Bytes a leaf's gather list holds per entry: its source and factor ([`solve::List`]), at
/// the default settings (`f64` factors take 4 more).
const BYTES_PER_ENTRY: u64 = (std::mem::size_of::<u32>() + std::mem::size_of::<f32>()) as u64;

/// Bytes a leaf holds besides its entries: its list's two arrays, its factor sum and bars,
/// and the slot of its list while the lists are built.
const BYTES_PER_LIST: u64 = (2 * std::mem::size_of::<solve::List>()
    + 2 * std::mem::size_of::<Bar>()
    + std::mem::size_of::<(f64, Cost)>()) as u64;

/// Share of the links a pass may refine and still be the last (after the first): it then
/// runs the final gather over the links it just made instead of a push-pull solve and a
/// pass that would find them settled. On `room-spheres-12-s6` the passes after the fifth
/// refined 23 and 3 of 30.4 M links, at about 4.5 s each; the Cornell box and `-s4` end
/// on a pass that refines none.
pub const SETTLED: f64 = 1e-5;

/// Share of the link tolerance (`--error`) at which the solves of the passes before the
/// last stop ([`pass_tolerance`]).
pub const PASS_SOLVE_SHARE: f64 = 1e-3;

/// The relative change at which a pass before the last stops its solve: the looser of
/// the solver tolerance (`--tolerance`, at most 1e-7) and [`PASS_SOLVE_SHARE`] ×
/// `--error`. Those radiosities only decide which links to refine, against a tolerance of
/// `error × B`; the solve's error is about its last change over `1 - ρ` (a geometric
/// series), so even at `ρ = 0.99` it stays a tenth of that tolerance. The last pass, whose
/// radiosities are the result, solves to the solver tolerance, starting from these. On
/// `room-spheres-12-s6` the passes' solves to 1e-7 took 58 of the bake's 717 s
/// (docs/PERFORMANCE.md, §9).
pub fn pass_tolerance(s: &Settings) -> f64 {
    s.tolerance.max(PASS_SOLVE_SHARE * s.error)
}

/// The final gather's entries as estimated from the links: one for each link on a leaf's
/// ancestor chain (its own included) and each piece of a cluster link on its root's chain.
/// Sources the gather cuts into pieces add entries, and entries with no factor are left
/// out. Measured (lists held / estimate): the Cornell box 3.3 (15.5 M / 4.7 M entries at the
/// default `--error`; its split sources), the room with a sphere 1.35 (39.9 M / 29.5 M),
/// `room-spheres-8` with clusters at `--error 0.05` 0.93 (19.8 M / 21.3 M).
fn gather_entries(e: &Elements, links: &[Vec<Link>], extra: Option<&clusters::Expansion>) -> u64 {
    // Per element, the links on its chain, parents first (they come before their children).
    let mut chain = vec![0u64; e.len()];
    for k in 0..e.len() {
        let up = match e.parent[k] {
            element::NONE => 0,
            p => chain[p as usize],
        };
        chain[k] = up + links[k].len() as u64;
    }
    let leaves: Vec<u32> = e.leaves().filter(|&l| !e.buried[l as usize]).collect();
    leaves
        .par_iter()
        .map(|&l| chain[l as usize] + extra.map_or(0, |x| x.pieces_on_chain(e, l) as u64))
        .sum()
}

/// Refuses the final gather when its lists, as [`gather_entries`] estimates them, do not
/// fit: with `--max-memory`, beside the links held; else in the memory available now. A
/// refusal names the settings that make fewer entries.
fn check_gather(
    e: &Elements,
    links: &[Vec<Link>],
    extra: Option<&clusters::Expansion>,
    clustered: bool,
    s: &Settings,
) -> crate::Result<()> {
    let Some((limit, source)) = budget::limit_of(s.max_memory) else {
        return Ok(());
    };
    let held = if s.max_memory.is_some() {
        links.iter().map(Vec::len).sum::<usize>() as u64 * BYTES_PER_LINK
    } else {
        0
    };
    let entries = gather_entries(e, links, extra);
    let leaves = e.leaves().count() as u64;
    let per_entry = if s.quadrature >= NARROW_QUADRATURE {
        BYTES_PER_ENTRY
    } else {
        BYTES_PER_ENTRY + 4
    };
    let bytes = entries
        .saturating_mul(per_entry)
        .saturating_add(leaves.saturating_mul(BYTES_PER_LIST));
    if held.saturating_add(bytes) <= limit {
        return Ok(());
    }
    let clusters = if clustered {
        ""
    } else {
        ", --clusters on (links between groups of faces)"
    };
    Err(crate::Error::Config(format!(
        "the final gather of the hierarchy needs about {entries} entries over {leaves} leaves \
         (every link on a leaf's ancestor chain), about {}{}, more than the {} of {source}; use a \
         larger --error (now {}) or --min-area{clusters}, or set --max-memory if the estimate \
         is too pessimistic",
        budget::size(bytes),
        if held > 0 {
            format!(" beside the links' {}", budget::size(held))
        } else {
            String::new()
        },
        budget::size(limit),
        s.error
    )))
}

/// Refuses, before any link is evaluated, an unclustered hierarchy whose candidate links
/// between every pair of its `roots` root patches do not fit the memory limit (`max_memory`,
/// else the available memory): a scene of 10^5 faces would ask for 10^10 of them.
fn check_initial_pairs(roots: usize, max_memory: Option<u64>) -> crate::Result<()> {
    let Some((limit, source)) = budget::limit_of(max_memory) else {
        return Ok(());
    };
    let pairs = (roots as u64).saturating_mul(roots.saturating_sub(1) as u64);
    let bytes = pairs.saturating_mul(BYTES_PER_INITIAL_PAIR);
    if bytes <= limit {
        return Ok(());
    }
    // The most roots whose pairs fit: n (n - 1) <= limit / bytes per pair.
    let fit = ((limit / BYTES_PER_INITIAL_PAIR) as f64).sqrt().floor() as u64;
    Err(crate::Error::Config(format!(
        "--method hierarchical without clusters starts from a link between every pair of its \
         {roots} root patches: {pairs} candidate links, about {} to evaluate, more than the {} \
         {source}; use --clusters on (links between groups of faces), or about {fit} root \
         patches or fewer (a longer --max-edge, where the scene has fewer faces), or set \
         --max-memory if the estimate is too pessimistic",
        budget::gib(bytes),
        budget::gib(limit)
    )))
}

/// Gather entries to expect per link when the refinement's links are capped by memory:
/// the final lists held 40 (the Cornell box), 43 (`room-spheres-8` with clusters) and 70
/// (the room with a sphere) entries per link.
pub const GATHER_ENTRIES_PER_LINK: u64 = 64;

/// Memory a link is counted at while the refinement runs: its own bytes and its share of
/// the final gather's lists ([`GATHER_ENTRIES_PER_LINK`] entries), which are most of it.
pub const MEMORY_PER_LINK: u64 = BYTES_PER_LINK + GATHER_ENTRIES_PER_LINK * BYTES_PER_ENTRY;

/// The most links the refinement may hold, `now` being held: what fits the memory limit
/// at [`MEMORY_PER_LINK`] each (`--max-memory` for the whole solution, else `now` plus
/// what the memory available now holds), and [`Settings::max_links`] at most. True when
/// the memory sets it. The final gather is checked against the limit again from the links
/// it will expand ([`check_gather`]).
fn link_cap(s: &Settings, now: usize) -> (usize, bool) {
    let room = match s.max_memory {
        Some(limit) => limit / MEMORY_PER_LINK,
        None => budget::available().map_or(u64::MAX, |a| now as u64 + a / MEMORY_PER_LINK),
    };
    if room < s.max_links as u64 {
        (room as usize, true)
    } else {
        (s.max_links, false)
    }
}

/// Candidate links [`evaluate_into`] evaluates at a time.
const EVALUATE_CHUNK: usize = 1 << 18;

/// Evaluates the candidate links `specs` (with absolute factor tolerances `tols`) in
/// parallel and appends those that carry light to their receivers' lists, each list in
/// the order of `specs`.
fn evaluate_into(
    ctx: &Context,
    specs: &[(u32, u32)],
    tols: &[Tolerance],
    links: &mut [Vec<Link>],
) -> Cost {
    // By receiver (a stable sort, so that each receiver's links keep the order of `specs`),
    // so that the links into one receiver run together and map its Gauss nodes once.
    let mut order: Vec<u32> = (0..specs.len() as u32).collect();
    order.par_sort_by_key(|&k| specs[k as usize].0);
    // In chunks, so that the evaluated links wait for their lists in a bounded buffer (at
    // 10^6 input triangles the 16 M initial links, held all at once, took 1.3 GB).
    let mut cost = Cost::default();
    let mut out: Vec<(Option<Link>, Cost)> = Vec::new();
    for chunk in order.chunks(EVALUATE_CHUNK) {
        chunk
            .par_iter()
            .with_max_len(PAR_RUN)
            .map_init(
                || None,
                |near, &k| {
                    let (r, t) = specs[k as usize];
                    link::evaluate(ctx, near, r, t, tols[k as usize])
                },
            )
            .collect_into_vec(&mut out);
        for (&k, (l, c)) in chunk.iter().zip(out.drain(..)) {
            cost += c;
            if let Some(l) = l {
                links[specs[k as usize].0 as usize].push(l);
            }
        }
    }
    cost
}

/// Share of a leaf's tolerance `ε_l` that the cluster links it takes at their own visible
/// fractions may move its radiosity by together; it checks its own view of the others'
/// sources, loudest first ([`clusters::Sight`]). Each link counts for its point estimate
/// times `max(v, 1 - v)`: the leaf may see anything from none to all of the source. On
/// `city-32 --error 0.05` that took the leaves whose factors sum over 1 beyond 3 bars from
/// 1,715 to 14 for 2.5% more rays (docs/HIERARCHY.md, *A leaf's own view of a cluster*).
pub const CLUSTER_SIGHT_SHARE: f64 = 0.1;

/// Rays per side with which a leaf checks its view of a source its ancestor's link found
/// visible: `CHECK_RAYS²` rays, whose estimate around the link's fraction is the entry's
/// (see the `Check` arm of [`gather_lists`]), or more for a bright source
/// ([`check_rays`]).
const CHECK_RAYS: usize = 2;

/// Most rays per side of a leaf's check of a bright source ([`check_rays`]).
const MAX_CHECK_RAYS: usize = 8;

/// Share of a leaf's tolerance `ε_l` that what a check's free rays leave unknown may move
/// its radiosity by, for one source ([`check_rays`]).
const CHECK_SHARE: f64 = 0.5;

/// Rays per side with which a leaf checks its view of a source that its ancestor's link
/// found visible, for the entry's weight `wf` (the source's radiosity times the leaf's
/// reflectance, weighed by channel as the tolerance is, times the unoccluded factor) and
/// the leaf's tolerance `eps`: from [`CHECK_RAYS`] up to [`MAX_CHECK_RAYS`], until the bar
/// of an answer whose rays all come out free ([`fraction_se`] at 1), times `wf`, is within
/// [`CHECK_SHARE`] `× eps`. Where a block hides a sliver of the light from a leaf beside
/// it, `2 × 2` free rays read the whole light, and the leaf's radiosity is as much too
/// high as the sliver's share of its light: on the Cornell box, the floor 10 mm from the
/// short block's corner read 3.4% high at one seed of eight (the light's four pieces each
/// weigh about 20 `ε_l` there; with this rule 6 × 6 rays each, and 1.9%). The count
/// depends on the entry's weight and not on what the rays find, so the estimate stays
/// unbiased.
fn check_rays(wf: f64, eps: f64) -> usize {
    let mut m = CHECK_RAYS;
    while m < MAX_CHECK_RAYS && wf * fraction_se(1.0, (m * m) as f64) > CHECK_SHARE * eps {
        m += 1;
    }
    m
}

/// Rays per side with which a leaf traces its visibility of the pieces of a split source
/// (`PIECE_RAYS²` each): the pieces' fractions average over the source, so fewer rays
/// than a link's do (on the Cornell box at `--error 0.01`, 2 instead of 4 halved the rays
/// of the whole bake for 0.1% on the worst face average). It is also the least number of
/// the leaf's rays to the whole source that must start on a piece for them to judge it
/// instead ([`link::Traced::pieces`]).
const PIECE_RAYS: usize = 2;

/// True when `s` is not a leaf and is near `l` by [`near::NEAR_CUT`] ([`near::is_near`], no
/// floor): the final gather cuts it for `l` whatever its radiosity.
fn near_source(e: &Elements, l: u32, s: u32) -> bool {
    !e.is_leaf(s) && near::is_near(e, l, s, 0.0, near::NEAR_CUT)
}

/// Most items one thread takes at a time in the long parallel loops (the final gather's
/// leaves, a chunk of links to evaluate, a cluster frontier). Left to itself, rayon splits
/// a range only as often as threads steal, so the last run of a loop could be long: the
/// final gather of `room-spheres-12-s5` ended with 6 s on one core of two.
pub const PAR_RUN: usize = 4096;

/// A [`clusters::PointCache`] taken from a pool, and given back when dropped.
struct Pooled<'a> {
    cache: clusters::PointCache,
    pool: &'a std::sync::Mutex<Vec<clusters::PointCache>>,
}

impl<'a> Pooled<'a> {
    fn take(pool: &'a std::sync::Mutex<Vec<clusters::PointCache>>) -> Pooled<'a> {
        let cache = pool
            .lock()
            .ok()
            .and_then(|mut p| p.pop())
            .unwrap_or_default();
        Pooled { cache, pool }
    }
}

impl Drop for Pooled<'_> {
    fn drop(&mut self) {
        if let Ok(mut p) = self.pool.lock() {
            p.push(std::mem::take(&mut self.cache));
        }
    }
}

/// [`Entry::traced`] of an entry traced from the leaf whose rays were not kept.
const NO_RAYS: u32 = u32::MAX;

/// Where a gather entry's visible fraction comes from.
#[derive(Clone, Copy)]
enum Sight {
    /// The link's (fraction, relative standard error).
    Given(f64, f64),
    /// The link's, if a few rays from the leaf confirm it; else traced.
    Check(f64, f64),
    /// Traced from the leaf, around a prior fraction known from other rays
    /// ([`link::Traced::seen_around`]).
    Trace(f64),
    /// Traced again from the leaf, with rays independent of its link's, around its link's
    /// fraction.
    Again(f64),
    /// Traced from the leaf already: (fraction, relative standard error, the prior it was
    /// traced around).
    Seen(f64, f64, f64),
}

/// One entry of a leaf's gather list while it is built.
#[derive(Clone, Copy)]
struct Entry {
    src: u32,
    /// Factor, visibility included.
    f: f64,
    /// Visible fraction.
    v: f64,
    /// Relative standard error of the entry's factor from its visibility rays (random).
    v_bar: f64,
    /// Absolute quadrature bar of the unoccluded factor (deterministic).
    q_bar: f64,
    /// Set when the visibility was traced from this leaf (and is traced again for pieces of
    /// the source): the index of its rays in the leaf's kept rays, or [`NO_RAYS`] where
    /// they were not kept.
    traced: Option<u32>,
    /// The unoccluded factor: what decides whether the source is cut into pieces (not the
    /// traced estimate, whose noise would then pick which entries are kept).
    open: f64,
    /// How many entries the entry stands for: `1 / ROULETTE` for one that the leaf's
    /// Russian roulette kept ([`link::Basis::Roulette`], [`stands_for`]), else 1.
    count: f64,
    /// The prior its visibility was traced around ([`Sight::Trace`]), for the pieces of
    /// the source judged from the same rays.
    prior: f64,
}

/// How many entries leaf `l`'s entry for the link `k` stands for ([`Entry::count`]): for a
/// hidden link ([`link::Basis::Roulette`]) `1 / ROULETTE` when the leaf's roulette keeps
/// it, else `None` (no entry); 1 for any other link.
fn stands_for(k: &Link, l: u32, seed: u64) -> Option<f64> {
    if k.basis != link::Basis::Roulette {
        Some(1.0)
    } else if link::roulette_keeps(seed, l, k.src) {
        Some(1.0 / link::ROULETTE)
    } else {
        None
    }
}

/// The leaves' gather lists: for each leaf, its own links as they are, and for every link
/// `a ← s` of an ancestor `a`, the leaf's own unoccluded factor to `s` times a visible
/// fraction: the link's when it is wholly visible, the leaf's own, traced, when the link
/// is partly visible or the leaf partly buried; see [`solve`].
///
/// **Sources as fine as they are.** An entry takes the source's mean radiosity; where the
/// source was split (for other links) and its radiosity varies, that mean is biased for a
/// leaf that sees one part of the source more than another (the ceiling above the bright
/// middle of a floor). An entry whose source-side error `ρ_l F_ls ΔB_s` is above
/// `descend × ε_l` (the leaf's link tolerance, channels weighted by
/// [`Relative::weights`]) is therefore replaced by entries to the source's children, each
/// with the leaf's own factor, down to where the error is below it or the source is a
/// leaf.
///
/// `descend` is `(share, low, kernel)`: the cut is judged against the leaf's tolerance
/// relative to its own radiosity floored at `low` times the mean (capped at the mean), so
/// that with `low` 1 it is the link tolerance itself ([`Settings::descend_low`]). An
/// entry without rays of its own is also cut where the leaf's view of the source's children moves its
/// radiosity from their area mean by more than `kernel` times that tolerance
/// ([`Settings::kernel_cut`], `kernel_weighting_error`).
///
/// Factors are integrated to `accuracy × ε_l / (ρ_l B_s)` (as in `tolerances`). With a
/// finite `noise` ([`Settings::gather_noise`]) the loudest noisy entries are traced again
/// (`more_rays`). Returns the lists, the work spent and how many of the entries came
/// from cluster links.
#[allow(clippy::too_many_arguments)]
pub fn gather_lists(
    ctx: &Context,
    links: &[Vec<Link>],
    extra: Option<&clusters::Expansion>,
    rho: &[[f64; 3]],
    state: &State,
    rel: Relative,
    accuracy: f64,
    (descend, descend_low, kernel): (f64, f64, f64),
    noise: f64,
) -> (Gather, Cost, usize) {
    let e = ctx.elements;
    let (b, spread) = (&state.b, &state.spread);
    let leaves: Vec<u32> = e.leaves().collect();
    let n = (ctx.rays * ctx.rays) as f64;
    // Factors in `f32` unless the settings ask for more than its rounding ([`solve::List`]).
    let narrow = ctx.quadrature >= NARROW_QUADRATURE;
    // Per leaf: its list, factor sum with bar, carried bar, the work spent and its entries
    // from cluster links. Each list is made compact as soon as it is built, so that only
    // the compact lists are held.
    type Built = (solve::List, (f64, Bar), Bar, Cost, usize);
    // Each run of leaves takes a cache of cluster points that earlier runs filled, so that
    // cutting the leaves into runs ([`PAR_RUN`]) does not redraw the shared upper nodes'.
    let caches = std::sync::Mutex::new(Vec::new());
    let per_leaf: Vec<Built> = leaves
        .par_iter()
        .with_max_len(PAR_RUN)
        .map_init(
            || {
                let kept: std::cell::RefCell<Vec<link::Traced>> = Default::default();
                (Vec::new(), Pooled::take(&caches), kept)
            },
            |(cluster, points, kept), &l| {
                let points = &mut points.cache;
                let li = l as usize;
                // (source, factor, quadrature bound, visibility standard error) entries.
                let mut out: Vec<(u32, f64, f64, f64)> = Vec::new();
                let mut cost = Cost::default();
                cluster.clear();
                kept.borrow_mut().clear();
                if e.buried[li] {
                    let (list, sum, carried) =
                        finish_list(e, li, &out, cluster, rho, state, narrow);
                    return (list, sum, carried, cost, 0);
                }
                let (eps, k) = rel.weights(b[li]);
                // The source cut's tolerance: relative to the leaf's own radiosity down to
                // `descend_low` times the mean ([`Settings::descend_low`]).
                let cut = Relative {
                    low: rel.low.min(descend_low),
                    ..rel
                };
                let (eps_cut, k_cut) = cut.weights(b[li]);
                // The leaf's side of every open factor it asks for (its Gauss nodes mapped once).
                let near = std::cell::RefCell::new(link::Near::new(e, l));
                // `max over channels of k_c ρ_l x_c` for the source's values `x`, with the
                // channel weights of the link tolerance (`k`) or of the source cut (`k_cut`).
                let weighted = |k: &[f64; 3], src: u32, x: &[[f64; 3]]| {
                    (0..3)
                        .map(|c| k[c] * rho[li][c] * x[src as usize][c])
                        .fold(0.0, f64::max)
                };
                let weight = |src: u32, x: &[[f64; 3]]| weighted(&k, src, x);
                let f_tol = |src: u32| {
                    let w = weight(src, b);
                    if w > 0.0 {
                        accuracy * eps / w
                    } else {
                        f64::INFINITY
                    }
                };
                // The leaf's factor to `src` with its visibility: given, checked (a link found
                // visible from an ancestor, confirmed by rays from the leaf ([`check_rays`]),
                // else traced), or traced.
                //
                // `known`: the pair's unoccluded factor and its error as its link holds them,
                // taken where that error is within what the gather would ask of its own rule
                // (the one-point rule's share of the tolerance, [`link::FAR_SHARE`]).
                let open = |src: u32, known: Option<(f64, f64)>, cost: &mut Cost| {
                    let t = f_tol(src);
                    match known {
                        Some((f, err)) if err <= link::FAR_SHARE * t.max(ctx.quadrature * f) => {
                            (f, err)
                        }
                        _ => {
                            let open = link::open_factor_near(ctx, &mut near.borrow_mut(), src, t);
                            cost.evals += open.evals;
                            (open.value, open.err)
                        }
                    }
                };
                // A traced fraction's relative bar: `se(v) / |v|` on `f v`.
                let relative = |v: f64, rays: f64| fraction_se(v, rays) / v.abs().max(1e-300);
                // The entry for `src` of unoccluded factor `f` (with its error `q_err`,
                // from `open`), its visibility as `v` says.
                // `count`: how many links the entry stands for ([`Entry::count`]).
                let piece =
                    |src: u32, v: Sight, (f, q_err): (f64, f64), count: f64, cost: &mut Cost| {
                        if f <= 0.0 {
                            return None;
                        }
                        // A partly buried leaf's rays from inside the solid are blocked as expected
                        // (see `link::visible_fraction_partly`).
                        // The rays are kept for the pieces of the source ([`link::Traced::pieces`]).
                        let keep = |t: link::Traced, prior: f64, cost: &mut Cost| {
                            let seen = t.seen_around(prior);
                            cost.rays += seen.rays;
                            let mut kept = kept.borrow_mut();
                            kept.push(t);
                            (
                                seen.v,
                                relative(seen.v, n),
                                Some(kept.len() as u32 - 1),
                                prior,
                            )
                        };
                        let trace = |prior: f64, cost: &mut Cost| {
                            let t = link::traced(ctx, l, src, Some(f), e.partly[li]);
                            keep(t, prior, cost)
                        };
                        let (v, v_bar, traced, prior) = match v {
                            Sight::Given(v, bar) => (v, bar, None, v),
                            Sight::Seen(v, bar, prior) => (v, bar, Some(NO_RAYS), prior),
                            Sight::Trace(prior) => trace(prior, cost),
                            Sight::Again(prior) => {
                                let t = link::traced_again(ctx, l, src, Some(f));
                                keep(t, prior, cost)
                            }
                            Sight::Check(v, bar) => {
                                // The leaf's own `m²` rays ([`check_rays`]), estimated around the link's
                                // fraction: unbiased whatever they see, and `v` itself when
                                // none is blocked (for a link found visible, `v = 1`). Taking
                                // `v` when they are all free and tracing more rays otherwise
                                // is biased high by `v^n (1 - v)` for a leaf whose true
                                // fraction is `v`: it put the closed Cornell box's radiosity
                                // 0.06% and its power 0.11% over their exact values, and
                                // Russian roulette on more rays, unbiased too, was noisier
                                // (docs/HIERARCHY.md, *Unbiased visible fractions*).
                                let m = check_rays(weight(src, b) * f, eps);
                                let t = link::traced_n(ctx, l, src, m, Some(f));
                                let seen = t.seen_around(v);
                                cost.rays += seen.rays;
                                let rays = (m * m) as f64;
                                let v_bar = if t.all_free() && seen.rays > 0 {
                                    // What the leaf knows of its own view is these free rays,
                                    // not the ancestor's: the bar is at least theirs (with the
                                    // ancestor's bar alone, 21 leaves of the room with a sphere
                                    // summed their factors over 1 beyond 3 bars).
                                    bar.max(relative(1.0, rays))
                                } else {
                                    relative(seen.v, rays)
                                };
                                (seen.v, v_bar, None, v)
                            }
                        };
                        // An estimate around a prior may be below 0 without the source being
                        // hidden: it stays, as it is unbiased only so.
                        let entry: Option<Entry> = (v != 0.0).then_some(Entry {
                            src,
                            f: f * v,
                            v,
                            v_bar,
                            // The quadrature's own estimate: the integral stops at the looser of
                            // the relative tolerance and `t`.
                            q_bar: q_err * v.abs(),
                            traced,
                            open: f,
                            count,
                            prior,
                        });
                        entry
                    };
                // How many entries the leaf's entry for link `k` stands for, given the
                // leaf's own unoccluded factor `f` to its source: a hidden link is sent to
                // the roulette only where the roulette's own spread in the leaf's
                // radiosity, `√(1/ROULETTE - 1) ρ_l B_s f`, is within the leaf's tolerance;
                // else the leaf gathers it as any other ([`stands_for`]). A link found
                // hidden from a large receiver may be wide open to a leaf of it (a strip of
                // ground at the foot of a wall, the rest of its parent inside the
                // building): on `city-16` at `--error 0.05`, ground leaves beside walls
                // drew dozens of such entries four times over and summed their factors to
                // 2 (docs/HIERARCHY.md, *Near sources*).
                let roulette_sd = (1.0 / link::ROULETTE - 1.0).sqrt();
                let keeps = |k: &Link, f: f64| {
                    if k.basis == link::Basis::Roulette && roulette_sd * weight(k.src, b) * f > eps
                    {
                        Some(1.0)
                    } else {
                        stands_for(k, l, ctx.seed)
                    }
                };
                // A partly buried leaf traces every entry: its rays from points inside the solid
                // are blocked, so its traced factors are per whole area, and are divided by its
                // exposed fraction below (a factor is per visible area).
                let exposed = e.exposed[li];
                let partly = exposed < 1.0;
                let mut stack: Vec<Entry> = if partly {
                    links[li]
                        .iter()
                        .filter_map(|k| {
                            let fq = open(k.src, None, &mut cost);
                            let count = keeps(k, fq.0)?;
                            piece(k.src, Sight::Trace(k.vis), fq, count, &mut cost)
                        })
                        .collect()
                } else {
                    // The leaf's own links as they are where they were proved unoccluded; traced
                    // again where rays decided them (whether a link was partly visible, and so
                    // refined further, hung on those rays: kept, their estimate would be biased
                    // low for partly visible links and high for those all of whose rays were
                    // free).
                    links[li]
                        .iter()
                        .filter_map(|k| {
                            if k.basis == link::Basis::Proved {
                                Some(Entry {
                                    src: k.src,
                                    f: k.f(),
                                    v: k.vis,
                                    v_bar: 0.0,
                                    q_bar: k.err,
                                    traced: None,
                                    open: k.open,
                                    count: 1.0,
                                    prior: k.vis,
                                })
                            } else {
                                let fq = open(k.src, Some((k.open, k.err)), &mut cost);
                                let count = keeps(k, fq.0)?;
                                piece(k.src, Sight::Again(k.vis), fq, count, &mut cost)
                            }
                        })
                        .collect()
                };
                let mut a = e.parent[li];
                while a != element::NONE {
                    for k in &links[a as usize] {
                        // A partly visible link says nothing of where in `a` its shadow falls:
                        // the leaf's own visible fraction is traced (streams keyed on the leaf
                        // and the source, as for a link). Nor does a link that rays found
                        // visible from `a` prove that the leaf sees all of `s` (a leaf beside a
                        // box sees less of the wall behind it than its parent): unless the
                        // blockers' proof holds for the ancestor's link (then for every piece of
                        // the pair) or for the leaf itself, it checks its own.
                        let bar = if k.f() > 0.0 { k.se / k.f() } else { 0.0 };
                        let v = if k.partial || partly || k.basis == link::Basis::Roulette {
                            Sight::Trace(k.vis)
                        } else if k.basis == link::Basis::Proved
                            || ctx.blockers.unoccluded_within(
                                e.corners(l),
                                e.root[li],
                                e.corners(k.src),
                                e.root[k.src as usize],
                                link::PROOF_BUDGET,
                            ) == Some(true)
                        {
                            Sight::Given(k.vis, bar)
                        } else {
                            Sight::Check(k.vis, bar)
                        };
                        let fq = open(k.src, None, &mut cost);
                        let Some(count) = keeps(k, fq.0) else {
                            continue;
                        };
                        if let Some(en) = piece(k.src, v, fq, count, &mut cost) {
                            stack.push(en);
                        }
                    }
                    a = e.parent[a as usize];
                }
                // Sources as fine as they are, where their radiosity varies. What the
                // source's mean misses is judged on the factor the leaf sees: the unoccluded
                // one times the prior fraction (floored at `3 / n`, what `n` rays all blocked
                // still allow), not the traced estimate, whose noise would then pick the
                // entries cut. A mostly hidden source is cut less: on the Cornell box this
                // saved 7 M of 57 M rays for the same face averages.
                let hidden_floor = 3.0 / n;
                let mut again: Vec<Again> = Vec::new();
                while let Some(en) = stack.pop() {
                    let s = en.src;
                    let seen = en.open * en.prior.clamp(0.0, 1.0).max(hidden_floor);
                    let whole = e.is_leaf(s)
                        || weighted(&k_cut, s, spread) * seen <= descend * eps_cut
                            && !near_source(e, l, s)
                            && !(kernel > 0.0 && en.traced.is_none() && {
                                cost.evals += 4;
                                kernel_weighting_error(e, li, s, b, rho, &k_cut) * seen
                                    > kernel * eps_cut
                            });
                    if whole {
                        let f = en.f * en.count / exposed;
                        // A roulette entry's bar adds the roulette's own spread: the entry is
                        // `count` times the traced value, or nothing, so its variance is
                        // about `(1 - ROULETTE) f²`.
                        // (`f` may be below 0, an estimate around a prior; its bar is not.)
                        let se = if en.count > 1.0 {
                            f.abs() * (en.v_bar.powi(2) + 1.0 - link::ROULETTE).sqrt()
                        } else {
                            f.abs() * en.v_bar
                        };
                        if noise.is_finite() && !partly && en.count == 1.0 && en.v_bar > 0.0 {
                            again.push(Again {
                                at: out.len(),
                                open: en.open,
                                v: en.v,
                                prior: en.prior,
                            });
                        }
                        out.push((s, f, en.q_bar * en.count / exposed, se));
                        continue;
                    }
                    let children = e
                        .children(s)
                        .into_iter()
                        .filter(|&c| ctx.visible[c as usize] > 0.0);
                    if let Some(t) = en.traced {
                        // Traced from the leaf: from the source's own rays that start on each
                        // piece, where at least `PIECE_RAYS²` do; else `PIECE_RAYS²` rays
                        // each, all those pieces' rays in one batch (full packets where each
                        // alone went ray by ray).
                        let opened: SmallVec<[(u32, (f64, f64)); 4]> = children
                            .map(|c| (c, open(c, None, &mut cost)))
                            .filter(|&(_, (f, _))| f > 0.0)
                            .collect();
                        let sources: SmallVec<[(u32, f64); 4]> =
                            opened.iter().map(|&(c, (f, _))| (c, f)).collect();
                        let least = PIECE_RAYS * PIECE_RAYS;
                        let mut seen: SmallVec<[Option<(link::Seen, f64, f64)>; 4]> = match t {
                            NO_RAYS => smallvec::smallvec![None; sources.len()],
                            t => kept.borrow()[t as usize]
                                .pieces(ctx, s, &sources, least, Some(en.prior))
                                .into_iter()
                                .map(|p| p.map(|(seen, rays)| (seen, rays as f64, en.prior)))
                                .collect(),
                        };
                        let fresh: SmallVec<[(u32, f64); 4]> = sources
                            .iter()
                            .zip(&seen)
                            .filter(|(_, p)| p.is_none())
                            .map(|(&c, _)| c)
                            .collect();
                        if !fresh.is_empty() {
                            let mut traced = link::visible_fractions_n(
                                ctx,
                                l,
                                &fresh,
                                PIECE_RAYS,
                                e.partly[li],
                                Some(en.v),
                            )
                            .into_iter();
                            for p in seen.iter_mut().filter(|p| p.is_none()) {
                                *p = traced.next().map(|x| (x, least as f64, en.v));
                            }
                        }
                        for (&(c, fq), p) in opened.iter().zip(seen) {
                            let Some((seen, rays, prior)) = p else {
                                continue;
                            };
                            cost.rays += seen.rays;
                            let v = Sight::Seen(seen.v, relative(seen.v, rays), prior);
                            if let Some(child) = piece(c, v, fq, en.count, &mut cost) {
                                stack.push(child);
                            }
                        }
                    } else {
                        for c in children {
                            let v = Sight::Given(en.v, en.v_bar);
                            let fq = open(c, None, &mut cost);
                            if let Some(child) = piece(c, v, fq, en.count, &mut cost) {
                                stack.push(child);
                            }
                        }
                    }
                }
                if !again.is_empty() {
                    let weights: Vec<f64> = again.iter().map(|a| weight(out[a.at].0, b)).collect();
                    for (a, m) in again
                        .iter()
                        .zip(more_rays(&again, &weights, &out, noise * eps))
                    {
                        let Some(m) = m else { continue };
                        let (s, _, q_bar, _) = out[a.at];
                        let t = link::traced_more(ctx, l, s, m, Some(a.open));
                        let seen = t.seen_around(a.prior);
                        cost.rays += seen.rays;
                        let v = seen.v;
                        let q = if a.v != 0.0 {
                            q_bar * (v / a.v).abs()
                        } else {
                            q_bar
                        };
                        out[a.at] = (s, a.open * v, q, a.open * fraction_se(v, (m * m) as f64));
                    }
                }
                if let Some(x) = extra {
                    // A cluster link's visible fraction is its pair's, not the leaf's: the
                    // leaf checks its own view of the loudest links' sources until what
                    // the others could move its radiosity by sums to within
                    // `--cluster-sight × ε_l` ([`clusters::Sight`]).
                    let score = |src: u32, f: f64| {
                        let bs = state.source(src);
                        let w = (0..3)
                            .map(|c| k[c] * rho[li][c] * bs[c])
                            .fold(0.0, f64::max);
                        w * f
                    };
                    let sight = clusters::Sight {
                        vis: ctx.vis,
                        score: &score,
                        budget: x.sight * eps,
                    };
                    let sight = x.sight.is_finite().then_some(&sight);
                    let (rays, evals) = x.entries(e, l, cluster, points, sight);
                    cost.rays += rays;
                    cost.evals += evals;
                }
                let (list, sum, carried) = finish_list(e, li, &out, cluster, rho, state, narrow);
                (list, sum, carried, cost, cluster.len())
            },
        )
        .collect();
    let mut g = Gather {
        leaves,
        lists: Vec::with_capacity(per_leaf.len()),
        row_sum: Vec::with_capacity(per_leaf.len()),
        carried: Vec::with_capacity(per_leaf.len()),
    };
    let (mut cost, mut from_clusters) = (Cost::default(), 0);
    for (list, sum, carried, c, k) in per_leaf {
        cost += c;
        from_clusters += k;
        g.lists.push(list);
        g.row_sum.push(sum);
        g.carried.push(carried);
    }
    (g, cost, from_clusters)
}

/// Largest rays per side with which a leaf traces an entry again to bring its gather's
/// visibility noise within [`Settings::gather_noise`] (`GATHER_NOISE_RAYS²` rays).
pub const GATHER_NOISE_RAYS: usize = 32;

/// An element entry of a leaf's gather list that may be traced again ([`more_rays`]): its
/// place in the list, its unoccluded factor, its estimated visible fraction and the prior
/// that estimate was made around.
struct Again {
    at: usize,
    open: f64,
    v: f64,
    prior: f64,
}

/// Which of a leaf's entries `again` (with `weights`, what a unit of each entry's factor
/// moves the leaf's radiosity by, and `out`, the list holding their factors and standard
/// errors) are traced again, with how many rays per side, so that the entries' standard
/// errors weighted and added in quadrature fall within `target`: the loudest first, each
/// taken to the next of 4, 8, 16 and 32 rays per side that its own estimate says would
/// lower it (the binomial bar at its estimated fraction), until the projected sum is
/// within `target` or every entry is at [`GATHER_NOISE_RAYS`]. The choice reads only the
/// first estimates, and each chosen entry is traced once, from a stream of its own
/// ([`link::traced_more`]): the estimate that replaces it is independent of the choice,
/// so unbiased.
fn more_rays(
    again: &[Again],
    weights: &[f64],
    out: &[(u32, f64, f64, f64)],
    target: f64,
) -> Vec<Option<usize>> {
    let mut chosen = vec![None; again.len()];
    let mut var: Vec<f64> = again
        .iter()
        .zip(weights)
        .map(|(a, &w)| (w * out[a.at].3).powi(2))
        .collect();
    let mut total: f64 = var.iter().sum();
    let projected = |a: &Again, w: f64, m: usize| {
        let p = a.v.clamp(0.0, 1.0);
        (w * a.open * fraction_se(p, (m * m) as f64)).powi(2)
    };
    while total > target * target {
        // The loudest entry that more rays would still quiet.
        let mut best: Option<(usize, usize, f64)> = None;
        for (i, (a, &w)) in again.iter().zip(weights).enumerate() {
            if var[i] <= 0.0 || best.is_some_and(|(_, _, v)| var[i] <= v) {
                continue;
            }
            let from: usize = chosen[i].map_or(4, |m: usize| 2 * m);
            let next = (0..)
                .map(|k| from << k)
                .take_while(|&m| m <= GATHER_NOISE_RAYS)
                .find(|&m| projected(a, w, m) < var[i]);
            if let Some(m) = next {
                best = Some((i, m, var[i]));
            }
        }
        let Some((i, m, _)) = best else { break };
        let (a, w) = (&again[i], weights[i]);
        let v = projected(a, w, m);
        total += v - var[i];
        var[i] = v;
        chosen[i] = Some(m);
    }
    chosen
}

/// How far the radiosity that leaf `l` gathers from source `s` through an unoccluded
/// view moves from the source's mean when the source is cut into its children:
/// `max over channels of k_c ρ_l |Σ_c (F_c / Σ F_c - A_c / A_s) B_c|`, per unit of the
/// entry's factor, with `F_c` Lambert's point-to-polygon factor from the leaf's centre to
/// each child ([`exact::point_factor`]) and `k` the channel weights of the source cut.
/// 0 where the leaf sees none of the children.
fn kernel_weighting_error(
    e: &Elements,
    l: usize,
    s: u32,
    b: &[[f64; 3]],
    rho: &[[f64; 3]],
    k: &[f64; 3],
) -> f64 {
    let (x, n) = (e.centre[l], e.normal[l]);
    let kids = e.children(s);
    let polys = kids.map(|c| {
        let ci = c as usize;
        exact::Receiver::new(e.corners(c), e.normal[ci], e.centre[ci])
    });
    let seen = exact::point_factors_to(x, n, &polys);
    let (total, area) = (
        seen.iter().sum::<f64>(),
        kids.iter().map(|&c| e.area[c as usize]).sum::<f64>(),
    );
    if total <= 0.0 {
        return 0.0;
    }
    (0..3)
        .map(|ch| {
            let moved: f64 = kids
                .iter()
                .zip(&seen)
                .map(|(&c, &f)| (f / total - e.area[c as usize] / area) * b[c as usize][ch])
                .sum();
            k[ch] * rho[l][ch] * moved.abs()
        })
        .fold(0.0, f64::max)
}

/// Leaf `x`'s compact gather list from its element entries `(source, factor, quadrature
/// bound, standard error)` and its cluster entries `(source, factor, standard error,
/// bound)`,
/// with its factor sum and bar and the bar of its reflected irradiance (each entry
/// weighted by `max over channels of ρ_l B_s`).
fn finish_list(
    e: &Elements,
    x: usize,
    elements: &[(u32, f64, f64, f64)],
    cluster: &[(u32, f64, f64, f64)],
    rho: &[[f64; 3]],
    state: &State,
    narrow: bool,
) -> (solve::List, (f64, Bar), Bar) {
    // The entry's weight in the leaf's radiosity, `max over channels of ρ_l B_s`.
    let w = |s: u32| {
        let bs = state.source(s);
        (0..3).map(|c| rho[x][c] * bs[c]).fold(0.0, f64::max)
    };
    let mut src = Vec::with_capacity(elements.len() + cluster.len());
    let mut fs: Vec<f64> = Vec::with_capacity(src.capacity());
    let (mut sum, mut bound, mut var) = (0.0, 0.0, 0.0);
    let (mut gathered, mut w_bound, mut w_var) = (0.0, 0.0, 0.0);
    let cluster = cluster.iter().map(|&(s, f, se, q)| (s, f, q, se));
    for (s, f, q, se) in elements.iter().copied().chain(cluster) {
        // Held in `f32` where the settings allow ([`solve::List`]): the rounding joins the
        // entry's bound.
        let (f, q) = if narrow {
            let held = f64::from(f as f32);
            (held, q + (f - held).abs())
        } else {
            (f, q)
        };
        src.push(s);
        fs.push(f);
        sum += f;
        bound += q;
        var += se * se;
        let ws = w(s);
        gathered += f * ws;
        w_bound += q * ws;
        w_var += (se * ws).powi(2);
    }
    // A partly buried leaf's factors are divided by its measured exposed fraction, whose
    // standard error scales them all alike.
    if e.exposed[x] < 1.0 {
        var += (sum * e.exposed_se[x] / e.exposed[x]).powi(2);
        w_var += (gathered * e.exposed_se[x] / e.exposed[x]).powi(2);
    }
    let list = solve::List {
        src: src.into_boxed_slice(),
        f: if narrow {
            solve::Factors::Narrow(fs.iter().map(|&f| f as f32).collect())
        } else {
            solve::Factors::Wide(fs.into_boxed_slice())
        },
    };
    (
        list,
        (
            sum,
            Bar {
                se: var.sqrt(),
                bound,
            },
        ),
        Bar {
            se: w_var.sqrt(),
            bound: w_bound,
        },
    )
}

/// Carries per-leaf errors `d` (indexed like `g.leaves`) through the interreflections:
/// the solution of `x_l = d_l + ρ_l Σ_s f_ls x_s` over the gather lists (`ρ_l` the largest
/// channel's, a source's `x` the visible-area mean of its leaves', cluster sources 0), by
/// Jacobi iteration from 0 (from below: each iterate is at most the solution) to a
/// relative change of `1e-3` per leaf (at most 100 iterations).
/// Returns `x` per element.
///
/// Why: if the computed factors `F̃` differ from the true `F` by `δF`, the computed
/// radiosity `B̃ = E + ρ F̃ B̃` differs from the true `B = E + ρ F B` by
/// `B - B̃ = (I - ρF)⁻¹ ρ (F - F̃) B̃`; with `(I - ρF)⁻¹ = Σ (ρF)ⁿ ≥ 0` (Neumann series)
/// `|B - B̃| ≤ (I - ρF)⁻¹ ρ |δF| B̃` componentwise, which is `x` for
/// `d = ρ |δF| B̃` (to first order, `F̃` for `F`): the perturbation form of the error
/// analysis of Arvo, Torrance and Smits, "A framework for the analysis of error in global
/// illumination algorithms", SIGGRAPH 1994, with the resolvent applied to the per-leaf
/// errors rather than bounded by its norm `1 / (1 - ρ_max)`.
fn propagate(e: &Elements, g: &Gather, rho: &[[f64; 3]], d: &[f64]) -> Vec<f64> {
    let vis = e.visible_areas();
    let mut x = vec![0.0f64; e.len()];
    for _ in 0..100 {
        let new: Vec<f64> = (0..g.leaves.len())
            .into_par_iter()
            .map(|k| {
                let l = g.leaves[k] as usize;
                if e.buried[l] {
                    return 0.0;
                }
                let r = rho[l].iter().copied().fold(0.0, f64::max);
                let mut h = 0.0;
                for (s, f) in g.lists[k].iter() {
                    if !clusters::is_cluster(s) {
                        h += f * x[s as usize];
                    }
                }
                d[k] + r * h
            })
            .collect();
        let mut change = 0.0f64;
        for (k, v) in new.into_iter().enumerate() {
            let l = g.leaves[k] as usize;
            change = change.max((v - x[l]).abs() / v.max(1e-300));
            x[l] = v;
        }
        for p in (0..e.len()).rev() {
            if e.first_child[p] == element::NONE {
                continue;
            }
            let c0 = e.first_child[p] as usize;
            let sum: f64 = (c0..c0 + 4).map(|c| vis[c] * x[c]).sum();
            x[p] = if vis[p] > 0.0 { sum / vis[p] } else { 0.0 };
        }
        if change < 1e-3 {
            break;
        }
    }
    x
}

/// Refines links until none needs it (or the link cap); returns the number replaced.
#[allow(clippy::too_many_arguments)]
fn refine_links(
    e: &mut Elements,
    links: &mut Vec<Vec<Link>>,
    state: &mut State,
    patches: &PatchSet,
    vis: &Visibility,
    blockers: &Blockers,
    s: &Settings,
    rel: Relative,
    min_area: f64,
    tol: f64,
    normals: &[glam::DVec3],
    report: &mut Report,
) -> usize {
    let mut refined = 0;
    let (cap, from_memory) = link_cap(s, links.iter().map(Vec::len).sum());
    loop {
        let material = |e: &Elements, k: usize| {
            &patches.materials[patches.material[e.root[k] as usize] as usize]
        };
        let (rho, _) = materials(e, &material);
        let decisions: Vec<(u32, usize, Decision)> = {
            let oracle = Oracle {
                elements: e,
                rho: &rho,
                b: &state.b,
                spread: &state.spread,
                tol: rel,
                min_area,
                shadows: s.split_shadows,
                rays: s.rays,
            };
            (0..links.len())
                .into_par_iter()
                .flat_map_iter(|r| {
                    let oracle = &oracle;
                    let shadowed = oracle.shadowed(r as u32, &links[r]);
                    links[r].iter().enumerate().filter_map(move |(k, l)| {
                        match oracle.decide(r as u32, l, shadowed) {
                            Decision::Keep => None,
                            d => Some((r as u32, k, d)),
                        }
                    })
                })
                .collect()
        };
        if decisions.is_empty() {
            break;
        }
        let total: usize = links.iter().map(Vec::len).sum();
        if total + 3 * decisions.len() > cap {
            let why = if from_memory {
                "set by the memory limit"
            } else {
                "the settings' cap"
            };
            report.notes.push(format!(
                "refinement stopped at {total} links ({cap}, {why}): raise --error or --min-area"
            ));
            break;
        }
        // Split, on this thread, in decision order.
        let targets: Vec<u32> = decisions
            .iter()
            .map(|&(r, k, d)| match d {
                Decision::SplitReceiver => r,
                _ => links[r as usize][k].src,
            })
            .collect();
        let mut grow = Grow {
            e: &mut *e,
            state: &mut *state,
            links: &mut *links,
            vis,
            normals,
            solids: !blockers.is_empty(),
            seed: s.seed,
        };
        report.rays += grow.split(targets);
        // The replacements, and the replaced links removed.
        let mut specs = Vec::with_capacity(4 * decisions.len());
        for &(r, k, d) in &decisions {
            let l = links[r as usize][k];
            match d {
                Decision::SplitReceiver => specs.extend(e.children(r).map(|c| (c, l.src))),
                _ => specs.extend(e.children(l.src).map(|c| (r, c))),
            }
        }
        let mut at = 0;
        while at < decisions.len() {
            let r = decisions[at].0 as usize;
            let mut end = at;
            while end < decisions.len() && decisions[end].0 as usize == r {
                end += 1;
            }
            let gone: Vec<usize> = decisions[at..end].iter().map(|d| d.1).collect();
            let mut idx = 0;
            links[r].retain(|_| {
                let keep = gone.binary_search(&idx).is_err();
                idx += 1;
                keep
            });
            at = end;
        }
        let ctx = Context::new(e, patches, vis, blockers, s, tol);
        let (rho, _) = materials(e, &material);
        let tols = tolerances(&specs, &rho, &state.b, rel, s);
        let cost = evaluate_into(&ctx, &specs, &tols, links);
        report.rays += cost.rays;
        report.evals += cost.evals;
        refined += decisions.len();
    }
    refined
}

/// Fills the report's totals and error estimates (`error`: [`Solution::error`]).
#[allow(clippy::too_many_arguments)]
fn finish_report<'a>(
    e: &Elements,
    links: &[Vec<Link>],
    state: &State,
    error: &[f64],
    min_area: f64,
    b_ref: f64,
    rel: Relative,
    material: &impl Fn(&Elements, usize) -> &'a crate::scene::Material,
    report: &mut Report,
) {
    let (rho, emit) = materials(e, material);
    report.elements = e.len();
    report.leaves = e.leaves().count();
    report.buried = e.leaves().filter(|&l| e.buried[l as usize]).count();
    report.links = links.iter().map(Vec::len).sum();
    report.partial_links = links.iter().flatten().filter(|l| l.partial).count();
    report.mean_radiosity = b_ref;
    let oracle = Oracle {
        elements: e,
        rho: &rho,
        b: &state.b,
        spread: &state.spread,
        tol: rel,
        min_area,
        // Only `error` is asked of this oracle: the shadow rule and its rays do not count.
        shadows: false,
        rays: 0,
    };
    report.unresolved = (0..e.len())
        .map(|p| {
            links[p]
                .iter()
                .filter(|l| {
                    let (var, spr, eps) = oracle.error(p as u32, l);
                    var + spr > eps
                })
                .count()
        })
        .sum();
    let (mut worst, mut sum, mut area) = (0.0f64, 0.0, 0.0);
    for l in e.leaves() {
        let li = l as usize;
        if e.buried[li] {
            continue;
        }
        let x = error.get(li).copied().unwrap_or(0.0);
        worst = worst.max(x);
        sum += e.visible_area(l) * x;
        area += e.visible_area(l);
    }
    let scale = b_ref.max(f64::MIN_POSITIVE);
    report.max_error = worst / scale;
    report.mean_error = if area > 0.0 { sum / area / scale } else { 0.0 };
    let (emitted, absorbed) = solve::power(
        e,
        &Materials {
            rho: &rho,
            emit: &emit,
        },
        state,
    );
    report.emitted = emitted;
    report.absorbed = absorbed;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formfactor::exact::Piece;
    use glam::DVec3;

    /// The gather's noise allocation takes the loudest entries first, to the fewest rays
    /// that bring the projected sum within the target, leaves quiet lists alone, and stops
    /// at the cap where the target cannot be met.
    #[test]
    fn more_rays_quiets_the_loudest_entries_first() {
        let entry = |at: usize, open: f64, v: f64| Again {
            at,
            open,
            v,
            prior: v,
        };
        // Three entries of 8 x 8 rays: a bright source 1% hidden, a dim one half hidden,
        // a bright one seen whole.
        let again = [entry(0, 0.2, 0.99), entry(1, 0.05, 0.5), entry(2, 0.3, 1.0)];
        let weights = [1.0, 0.1, 1.0];
        let out: Vec<(u32, f64, f64, f64)> = again
            .iter()
            .map(|a| (0, a.open * a.v, 0.0, a.open * fraction_se(a.v, 64.0)))
            .collect();
        let sd = |chosen: &[Option<usize>]| {
            again
                .iter()
                .zip(&weights)
                .zip(chosen)
                .map(|((a, &w), m)| match m {
                    Some(m) => (w * a.open * fraction_se(a.v, (m * m) as f64)).powi(2),
                    None => (w * out[a.at].3).powi(2),
                })
                .sum::<f64>()
                .sqrt()
        };
        let first = sd(&[None, None, None]);
        assert!(more_rays(&again, &weights, &out, 1.01 * first)
            .iter()
            .all(Option::is_none));
        let half = more_rays(&again, &weights, &out, 0.5 * first);
        assert!(sd(&half) <= 0.5 * first, "{half:?}");
        // The dim source is the quietest: left alone while the bright ones meet the target.
        assert_eq!(half[1], None, "{half:?}");
        assert!(half[0].is_some() || half[2].is_some(), "{half:?}");
        let all = more_rays(&again, &weights, &out, 1e-9);
        assert!(all.iter().all(|&m| m == Some(GATHER_NOISE_RAYS)), "{all:?}");
    }

    /// A check casts `2 × 2` rays for a dim source, the fewest whose all-free bar times the
    /// entry's weight is within its share of the tolerance for a bright one, and no more
    /// than the cap.
    #[test]
    fn a_brighter_source_is_checked_with_more_rays() {
        let bar = |m: usize| fraction_se(1.0, (m * m) as f64);
        assert_eq!(check_rays(0.0, 1.0), CHECK_RAYS);
        assert_eq!(check_rays(1.0, 1.0), CHECK_RAYS);
        assert_eq!(check_rays(1e9, 1.0), MAX_CHECK_RAYS);
        // The light's pieces as a floor leaf beside the Cornell box's short block weighs
        // them: about 22 tolerances each.
        assert_eq!(check_rays(22.0, 1.0), 6);
        let mut last = CHECK_RAYS;
        for k in 0..200 {
            let wf = 1.1f64.powi(k) / 10.0;
            let m = check_rays(wf, 1.0);
            assert!(m >= last, "fewer rays for a brighter source at {wf}");
            last = m;
            if m < MAX_CHECK_RAYS {
                assert!(
                    wf * bar(m) <= CHECK_SHARE,
                    "{m} rays per side too few at {wf}"
                );
            }
            if m > CHECK_RAYS {
                assert!(
                    wf * bar(m - 1) > CHECK_SHARE,
                    "{m} rays per side more than needed"
                );
            }
        }
        // The rule scales with the tolerance alone.
        assert_eq!(check_rays(2.2, 0.1), check_rays(22.0, 1.0));
    }

    /// A unit square split three levels down (64 leaves) whose root has 100 links: every
    /// leaf gathers over all of them.
    fn deep() -> (Elements, Vec<Vec<Link>>) {
        let mut e = Elements::default();
        e.add_root(
            Piece::Quad([DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y]),
            DVec3::Z,
        );
        let mut level = vec![0u32];
        for _ in 0..3 {
            level = level.iter().flat_map(|&p| e.split(p)).collect();
        }
        let link = Link {
            src: 0,
            err: 0.0,
            se: 0.0,
            df: 0.0,
            partial: false,
            tilt: link::Tilt::default(),
            vis: 1.0,
            basis: link::Basis::Proved,
            open: 0.01,
        };
        let mut links = vec![Vec::new(); e.len()];
        links[0] = vec![link; 100];
        (e, links)
    }

    /// The kernel cut's estimate ([`kernel_weighting_error`]): 0 for a source of uniform
    /// radiosity; large for a leaf beside the source's bright half, which it sees more
    /// of than its area share; small for a leaf far away, whose view weights the
    /// children as their areas do.
    #[test]
    fn the_kernel_cut_sees_what_a_near_leaf_weights_and_a_far_one_does_not() {
        let mut e = Elements::default();
        let floor = e.add_root(
            Piece::Quad([DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y]),
            DVec3::Z,
        );
        // Small wall leaves facing +x: one at the floor's edge, one 1000 away.
        let wall = |x: f64, e: &mut Elements| {
            let (lo, hi) = (0.45, 0.55);
            e.add_root(
                Piece::Quad([
                    DVec3::new(x, hi, 0.05),
                    DVec3::new(x, lo, 0.05),
                    DVec3::new(x, lo, 0.15),
                    DVec3::new(x, hi, 0.15),
                ]),
                DVec3::X,
            )
        };
        let near = wall(0.0, &mut e) as usize;
        let far = wall(-1000.0, &mut e) as usize;
        let kids = e.split(floor);
        let rho = vec![[0.5; 3]; e.len()];
        let k = [1.0; 3];
        let mut b = vec![[1.0; 3]; e.len()];
        assert!(kernel_weighting_error(&e, near, floor, &b, &rho, &k) < 1e-12);
        for &c in &kids {
            if e.centre[c as usize].x < 0.5 {
                b[c as usize] = [2.0; 3];
            }
        }
        let (n, f) = (
            kernel_weighting_error(&e, near, floor, &b, &rho, &k),
            kernel_weighting_error(&e, far, floor, &b, &rho, &k),
        );
        // Near: the bright half holds most of what the leaf sees (the area share is 1/2).
        assert!(n > 0.1 && n < 0.25, "near {n}");
        assert!(f < 1e-3 * n, "far {f} against near {n}");
    }

    #[test]
    fn settings_out_of_range_are_refused_by_name() {
        assert!(Settings::default().validate().is_ok());
        let refused = |s: Settings, flag: &str| {
            let msg = s.validate().unwrap_err().to_string();
            assert!(msg.contains(flag), "{msg}");
        };
        for d in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let s = Settings {
                descend: d,
                ..Settings::default()
            };
            refused(s, "--descend");
        }
        for d in [0.0, -1.0, 1.5, f64::NAN, f64::INFINITY] {
            let s = Settings {
                descend_low: d,
                ..Settings::default()
            };
            refused(s, "--descend-low");
        }
        for d in [-1.0, f64::NAN, f64::INFINITY] {
            let s = Settings {
                kernel_cut: d,
                ..Settings::default()
            };
            refused(s, "--kernel-cut");
        }
        for d in [-1.0, f64::NAN] {
            let s = Settings {
                cluster_sight: d,
                ..Settings::default()
            };
            refused(s, "--cluster-sight");
        }
        for x in [0.0, f64::NAN] {
            let s = Settings {
                error: x,
                ..Settings::default()
            };
            refused(s, "--error");
            let s = Settings {
                cluster_accuracy: x,
                ..Settings::default()
            };
            refused(s, "--cluster-accuracy");
        }
        for x in [0.0, 1.0, -1.0, f64::NAN, f64::NEG_INFINITY] {
            let s = Settings {
                cluster_quadrature: x,
                ..Settings::default()
            };
            refused(s, "--cluster-quadrature");
        }
    }

    #[test]
    fn the_gather_is_estimated_and_refused_when_it_does_not_fit() {
        let (e, links) = deep();
        assert_eq!(e.leaves().count(), 64);
        assert_eq!(gather_entries(&e, &links, None), 6_400);
        let held = 100 * BYTES_PER_LINK;
        let lists = 6_400 * BYTES_PER_ENTRY + 64 * BYTES_PER_LIST;
        let with = |bytes: u64| Settings {
            error: 0.03,
            max_memory: Some(bytes),
            ..Settings::default()
        };
        assert!(check_gather(&e, &links, None, false, &with(held + lists)).is_ok());
        let msg = check_gather(&e, &links, None, false, &with(held + lists - 1))
            .unwrap_err()
            .to_string();
        assert!(msg.contains("6400 entries over 64 leaves"), "{msg}");
        assert!(msg.contains("--error (now 0.03)"), "{msg}");
        assert!(msg.contains("--clusters on"), "{msg}");
    }

    /// `--clusters auto` clusters above [`AUTO_CLUSTER_ROOTS`] roots and where the pairs of
    /// roots would not fit the memory limit, and nowhere else; on and off do as they say.
    #[test]
    fn auto_clustering_follows_the_roots_and_the_memory() {
        let small = Some(64 << 20);
        // 2,091 roots (the room with a sphere): 4.4 M pairs, 0.62 GiB; 64 MiB hold 665.
        assert!(Clustering::Auto.resolve(2_091, small));
        assert!(!Clustering::Auto.resolve(2_091, Some(1 << 30)));
        assert!(!Clustering::Auto.resolve(19, small));
        assert!(!Clustering::Auto.resolve(AUTO_CLUSTER_ROOTS, Some(4 << 30)));
        assert!(Clustering::Auto.resolve(AUTO_CLUSTER_ROOTS + 1, Some(u64::MAX)));
        assert!(!Clustering::Off.resolve(1_000_000, small));
        assert!(Clustering::On.resolve(2, None));
        assert_eq!(Settings::default().clusters, Clustering::Auto);
    }
}
