//! Solving on the hierarchy: every leaf gathers over the links of its whole ancestor
//! chain, and parents take the visible-area average of their children (the gather and
//! pull of Hanrahan, Salzman and Aupperle 1991, section 4), iterated Jacobi-style to a
//! per-element tolerance.
//!
//! **Gathering at the leaves.** HSA push irradiance gathered at a coarse receiver down to
//! its children unchanged: every child is given the parent's mean factor `F_as`. That
//! errs in the same direction for every link near a receiver's edge (a leaf in a corner
//! sees each adjacent wall more than its parent does on average), and the errors add up
//! along the chain: in the closed cube, leaves at the corners summed their factors to
//! 1.3 at a link tolerance of 2%, so a furnace came out non-uniform and power was not
//! conserved. Here each leaf `l` under a link `a ← s` uses its own unoccluded factor
//! `F(l → s)` (the exact integral, [`super::link::open_factor`]) times a visible fraction:
//! the link's when the link is wholly visible, and the leaf's own, traced like a link's,
//! when it is partly visible (a coarse link's mean visibility says nothing of where its
//! shadow falls: beside a box, leaves in its shade would get the light of the open floor).
//! The coarse link still decides what the receiver sees of `s` and how finely
//! `s` is resolved, so the cost stays that of the links (the gather lists are as long as
//! the leaves' ancestor chains). Because `Σ_s F(l → s) = 1` for every leaf of a closed
//! scene, the closed cube gives `B = E / (1 - ρ)` on every leaf and emitted power equals
//! absorbed power, to the quadrature tolerance.
//!
//! One iteration: `H_l = Σ f_ls B_s` over the leaf's gather list (in parallel over
//! leaves), `B_l = E_l + ρ_l H_l` (0 for buried leaves), then the pull pass (children are
//! numbered after their parents, so one backward pass over the elements).
//!
//! The iteration stops when no visible leaf's radiosity changes by more than `tol` times
//! its own value (with a floor of `1e-9` times the scene's mean radiosity, for leaves that
//! receive nothing), in every channel: a per-element rule, so that dim surfaces lit only at
//! second order converge as well as bright ones. With reflectances below one and factor
//! sums at most one, the iteration is a contraction (as Jacobi on the flat system).

use rayon::prelude::*;

use super::clusters::{self, Radiosity, Tree};
use super::element::{Elements, NONE};

/// Radiosity per element and what the refinement oracle reads from it.
#[derive(Clone, Debug, Default)]
pub struct State {
    /// Radiosity of every element (leaves solved, parents the visible-area average).
    pub b: Vec<[f64; 3]>,
    /// Spread of radiosity over each element, per channel: for a leaf its estimated
    /// variation ([`estimate_spread`]), for a parent the range covered by its leaves.
    pub spread: Vec<[f64; 3]>,
    /// Irradiance each leaf received in the last iteration (0 for parents).
    pub h: Vec<[f64; 3]>,
    /// Radiosity of the clusters ([`super::clusters`]), when there are any.
    pub clusters: Radiosity,
}

impl State {
    /// Makes room for `n` elements (new ones start at 0).
    fn fit(&mut self, n: usize) {
        self.b.resize(n, [0.0; 3]);
        self.spread.resize(n, [0.0; 3]);
        self.h.resize(n, [0.0; 3]);
    }

    /// Radiosity of node `n`: an element, or a cluster when [`clusters::CLUSTER`] is set.
    pub fn source(&self, n: u32) -> [f64; 3] {
        if clusters::is_cluster(n) {
            self.clusters.b[(n & !clusters::CLUSTER) as usize]
        } else {
            self.b[n as usize]
        }
    }

    /// Pulls the clusters of `tree` (if any) from the roots.
    pub fn pull_clusters(&mut self, tree: Option<&Tree>, vis: &[f64]) {
        if let Some(t) = tree {
            self.clusters.pull(t, vis, &self.b, &self.spread);
        }
    }
}

/// What a solve did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SolveStats {
    /// Iterations run.
    pub iterations: usize,
    /// The largest relative change of the last iteration.
    pub change: f64,
    /// True when `change <= tol`.
    pub converged: bool,
}

/// Per-element material data the solve needs.
pub struct Materials<'a> {
    /// Reflectance per element.
    pub rho: &'a [[f64; 3]],
    /// Emission per element.
    pub emit: &'a [[f64; 3]],
}

/// One element's gather list: `Σ f[j] B[src[j]]` over its entries, in this order (the
/// sum's order, so the same bits on any number of threads). `src[j]` is an element, or a
/// cluster node with [`super::clusters::CLUSTER`] set; `f[j]` the factor to it,
/// visibility included. Held as two arrays of exact length: these lists are most of a
/// large bake's memory (3.7 GB at 10^6 input triangles with factors in `f64`). Factors are
/// held in `f32` (8 bytes an entry) where the settings ask no more of a factor than
/// `--link-quadrature` 1e-6, 16 times the `f32` rounding (6e-8 relative); whoever builds
/// a list then adds each factor's rounding (the exact difference) to the entry's bound.
/// Tighter settings keep `f64` (12 bytes an entry).
#[derive(Clone, Debug)]
pub struct List {
    /// Sources.
    pub src: Box<[u32]>,
    /// Factors.
    pub f: Factors,
}

/// A list's factors, in the precision the settings need ([`List`]).
#[derive(Clone, Debug)]
pub enum Factors {
    /// Rounded to `f32`.
    Narrow(Box<[f32]>),
    /// Full precision.
    Wide(Box<[f64]>),
}

impl Default for List {
    fn default() -> Self {
        List {
            src: Box::default(),
            f: Factors::Wide(Box::default()),
        }
    }
}

impl List {
    /// A list of `(source, factor)` entries, factors held in full precision.
    pub fn new(entries: impl ExactSizeIterator<Item = (u32, f64)>) -> Self {
        let (src, f): (Vec<u32>, Vec<f64>) = entries.unzip();
        List {
            src: src.into_boxed_slice(),
            f: Factors::Wide(f.into_boxed_slice()),
        }
    }

    /// Number of entries.
    pub fn len(&self) -> usize {
        self.src.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.src.is_empty()
    }

    /// The entries.
    pub fn iter(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        let (narrow, wide): (&[f32], &[f64]) = match &self.f {
            Factors::Narrow(f) => (f, &[]),
            Factors::Wide(f) => (&[], f),
        };
        let f = narrow
            .iter()
            .map(|&f| f64::from(f))
            .chain(wide.iter().copied());
        self.src.iter().copied().zip(f)
    }
}

/// Per-leaf gather lists: leaf `leaves[k]` gathers `Σ f B[src]` over `lists[k]`.
#[derive(Clone, Debug, Default)]
pub struct Gather {
    /// The leaves, in element order.
    pub leaves: Vec<u32>,
    /// Each leaf's entries, in a fixed order (the sum's order, so the same bits on any
    /// number of threads).
    pub lists: Vec<List>,
    /// Per leaf: the sum of its factors and its error bar (the entries' quadrature bounds
    /// added linearly, their visibility standard errors in quadrature:
    /// [`crate::matrix::Bar`]).
    pub row_sum: Vec<(f64, crate::matrix::Bar)>,
    /// Per leaf: the error bar of its reflected irradiance `ρ_l H_l` that its factors'
    /// bars allow (as `row_sum`'s, each entry weighted by `max over channels of ρ_l B_s`,
    /// with the radiosity the lists were built from).
    pub carried: Vec<crate::matrix::Bar>,
}

impl Gather {
    /// Number of entries.
    pub fn len(&self) -> usize {
        self.lists.iter().map(|l| l.len()).sum()
    }

    /// True when no leaf gathers anything.
    pub fn is_empty(&self) -> bool {
        self.lists.iter().all(|l| l.is_empty())
    }
}

/// Adds `Σ f B[src]` over `list` to `h`, per channel.
fn gather_into(list: &List, state: &State, h: &mut [f64; 3]) {
    // One loop per precision: this is the solve's inner loop, over every entry each sweep.
    fn sum(src: &[u32], f: impl Iterator<Item = f64>, state: &State, h: &mut [f64; 3]) {
        for (&s, f) in src.iter().zip(f) {
            let bs = state.source(s);
            for c in 0..3 {
                h[c] += f * bs[c];
            }
        }
    }
    match &list.f {
        Factors::Narrow(f) => sum(&list.src, f.iter().map(|&f| f64::from(f)), state, h),
        Factors::Wide(f) => sum(&list.src, f.iter().copied(), state, h),
    }
}

/// Iterates gather and pull from `state` until the relative change is at most `tol`
/// (or `max_iterations`); `b_ref` is the scene's mean radiosity (for the floor).
#[allow(clippy::too_many_arguments)]
pub fn solve(
    e: &Elements,
    tree: Option<&Tree>,
    g: &Gather,
    m: &Materials,
    state: &mut State,
    b_ref: f64,
    tol: f64,
    max_iterations: usize,
) -> SolveStats {
    let n = e.len();
    let vis = e.visible_areas();
    state.fit(n);
    let floor = 1e-9 * b_ref.max(f64::MIN_POSITIVE);
    let mut stats = SolveStats::default();
    let mut new: Vec<([f64; 3], [f64; 3])> = vec![([0.0; 3], [0.0; 3]); g.leaves.len()];
    for it in 0..max_iterations.max(1) {
        new.par_iter_mut().enumerate().for_each(|(k, out)| {
            let l = g.leaves[k] as usize;
            if e.buried[l] {
                *out = ([0.0; 3], [0.0; 3]);
                return;
            }
            let mut h = [0.0; 3];
            gather_into(&g.lists[k], state, &mut h);
            *out = (
                std::array::from_fn(|c| m.emit[l][c] + m.rho[l][c] * h[c]),
                h,
            );
        });
        let mut change = 0.0f64;
        for (k, &(b, h)) in new.iter().enumerate() {
            let l = g.leaves[k] as usize;
            if !e.buried[l] {
                change = change.max(relative_change(&b, &state.b[l], floor));
            }
            state.b[l] = b;
            state.h[l] = h;
        }
        pull(e, &vis, state);
        state.pull_clusters(tree, &vis);
        stats = iteration_stats(it, change, tol);
        if stats.converged {
            break;
        }
    }
    stats
}

/// HSA's own iteration, for the passes before the last (cheaper: no gather lists): each
/// element gathers over its own links (whose factors are per visible area, so the
/// irradiance is that of the element's unburied part), irradiance is pushed down
/// unchanged, leaves get `B = E + ρ H`, then pull. Same stopping rule as [`solve`].
///
/// With clusters, `extra` brings each root the irradiance of the cluster links on its
/// chain, gathered node by node ([`super::transfer`]), added to what its own links bring.
#[allow(clippy::too_many_arguments)]
pub fn solve_push(
    e: &Elements,
    tree: Option<&Tree>,
    extra: Option<&super::transfer::Transfer>,
    links: &[Vec<super::link::Link>],
    m: &Materials,
    state: &mut State,
    b_ref: f64,
    tol: f64,
    max_iterations: usize,
) -> SolveStats {
    let n = e.len();
    let vis = e.visible_areas();
    state.fit(n);
    let floor = 1e-9 * b_ref.max(f64::MIN_POSITIVE);
    let mut stats = SolveStats::default();
    let mut gathered = vec![[0.0f64; 3]; n];
    let mut down = vec![[0.0f64; 3]; n];
    for it in 0..max_iterations.max(1) {
        // 1. Gather, from the previous iteration's radiosities.
        let from_clusters = match (extra, tree) {
            (Some(x), Some(t)) => x.gather(t, e, state),
            _ => Vec::new(),
        };
        gathered.par_iter_mut().enumerate().for_each(|(p, g)| {
            let mut s = [0.0; 3];
            for l in &links[p] {
                let bs = state.b[l.src as usize];
                for c in 0..3 {
                    s[c] += l.f() * bs[c];
                }
            }
            if let Some(h) = from_clusters.get(p) {
                for c in 0..3 {
                    s[c] += h[c];
                }
            }
            *g = s;
        });
        // 2. Push (parents first) and leaf radiosity.
        let mut change = 0.0f64;
        for p in 0..n {
            let parent = e.parent[p];
            let above = if parent == NONE {
                [0.0; 3]
            } else {
                down[parent as usize]
            };
            let h = std::array::from_fn(|c| above[c] + gathered[p][c]);
            down[p] = h;
            if e.first_child[p] == NONE {
                let new = if e.buried[p] {
                    [0.0; 3]
                } else {
                    std::array::from_fn(|c| m.emit[p][c] + m.rho[p][c] * h[c])
                };
                if !e.buried[p] {
                    change = change.max(relative_change(&new, &state.b[p], floor));
                }
                state.b[p] = new;
                state.h[p] = if e.buried[p] { [0.0; 3] } else { h };
            }
        }
        // 3. Pull (children first).
        pull(e, &vis, state);
        state.pull_clusters(tree, &vis);
        stats = iteration_stats(it, change, tol);
        if stats.converged {
            break;
        }
    }
    stats
}

/// The stopping rule's measure for one leaf: the largest change over channels, relative to
/// the new value (at least `floor`).
fn relative_change(new: &[f64; 3], old: &[f64; 3], floor: f64) -> f64 {
    new.iter()
        .zip(old)
        .map(|(&n, &o)| (n - o).abs() / n.abs().max(floor))
        .fold(0.0, f64::max)
}

/// The stats after iteration `it` (0-based) with the given change.
fn iteration_stats(it: usize, change: f64, tol: f64) -> SolveStats {
    SolveStats {
        iterations: it + 1,
        change,
        converged: change <= tol,
    }
}

/// Sets every parent's radiosity to the visible-area average of its children, and its
/// spread to the range covered by the leaves below it, each leaf standing for the interval
/// `B ± spread / 2` (its own estimated variation, [`estimate_spread`]).
pub fn pull(e: &Elements, vis: &[f64], state: &mut State) {
    let mut lo = vec![[f64::INFINITY; 3]; e.len()];
    let mut hi = vec![[f64::NEG_INFINITY; 3]; e.len()];
    for p in (0..e.len()).rev() {
        if e.first_child[p] == NONE {
            if !e.buried[p] {
                for k in 0..3 {
                    lo[p][k] = state.b[p][k] - 0.5 * state.spread[p][k];
                    hi[p][k] = state.b[p][k] + 0.5 * state.spread[p][k];
                }
            }
            continue;
        }
        let c0 = e.first_child[p] as usize;
        let mut sum = [0.0; 3];
        for c in c0..c0 + 4 {
            for k in 0..3 {
                sum[k] += vis[c] * state.b[c][k];
                lo[p][k] = lo[p][k].min(lo[c][k]);
                hi[p][k] = hi[p][k].max(hi[c][k]);
            }
        }
        state.b[p] = if vis[p] > 0.0 {
            sum.map(|s| s / vis[p])
        } else {
            [0.0; 3]
        };
        state.spread[p] = std::array::from_fn(|k| (hi[p][k] - lo[p][k]).max(0.0));
    }
}

/// Estimates how much radiosity varies over each leaf, for the oracle's source term, then
/// pulls the spreads up the tree. A leaf's radiosity is one number; what it stands for
/// varies by about `ρ_l Σ ΔF_k B_k` over it, the sum over the links into the leaf and its
/// ancestors of each link's factor variation times its source's radiosity, a link into an
/// ancestor `a` counting `√(A_l / A_a)` of its variation (a variation linear across `a`).
/// Without it a source that was never split would look uniform however its radiosity
/// varies, and a receiver that sees more of the bright part of a source than of its dark
/// part (the middle of a floor lit from above, seen from the ceiling) would be
/// systematically under-lit.
pub fn estimate_spread(
    e: &Elements,
    links: &[Vec<super::link::Link>],
    rho: &[[f64; 3]],
    state: &mut State,
) {
    let leaves: Vec<u32> = e.leaves().collect();
    let b = &state.b;
    let spread: Vec<[f64; 3]> = leaves
        .par_iter()
        .map(|&l| {
            let li = l as usize;
            if e.buried[li] {
                return [0.0; 3];
            }
            let mut sum = [0.0; 3];
            let mut a = l;
            while a != NONE {
                let scale = (e.area[li] / e.area[a as usize]).sqrt();
                for k in &links[a as usize] {
                    let bs = b[k.src as usize];
                    for c in 0..3 {
                        sum[c] += scale * k.df * bs[c];
                    }
                }
                a = e.parent[a as usize];
            }
            std::array::from_fn(|c| rho[li][c] * sum[c])
        })
        .collect();
    for (&l, s) in leaves.iter().zip(spread) {
        state.spread[l as usize] = s;
    }
    pull(e, &e.visible_areas(), state);
}

/// Power balance of a solved hierarchy: `(emitted, absorbed)`, each `Σ A_vis (·)` over
/// visible leaves of the luminance-free channel sum: emitted `E`, absorbed `(1 - ρ) H`.
/// In a closed scene they agree to the accuracy of the factors and the solve; the rest
/// escapes through openings.
pub fn power(e: &Elements, m: &Materials, state: &State) -> ([f64; 3], [f64; 3]) {
    let (mut emitted, mut absorbed) = ([0.0; 3], [0.0; 3]);
    for p in 0..e.len() {
        if e.first_child[p] != NONE || e.buried[p] {
            continue;
        }
        let a = e.visible_area(p as u32);
        for c in 0..3 {
            emitted[c] += a * m.emit[p][c];
            absorbed[c] += a * (1.0 - m.rho[p][c]) * state.h[p][c];
        }
    }
    (emitted, absorbed)
}
