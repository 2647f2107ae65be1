//! Solving on the hierarchy: gather over links, then push-pull through the element tree
//! (Hanrahan, Salzman and Aupperle 1991, section 4, "SolveSystem", "Gather",
//! "PushPullRad"), iterated Jacobi-style to a per-element tolerance.
//!
//! One iteration:
//!
//! 1. **Gather.** Every element `p` with links collects `H_p = Σ_{p ← s} F_ps B_s`, the
//!    irradiance (in radiosity units: what `ρ` multiplies) its links bring, in parallel
//!    over elements. The power this brings, `H_p A_p`, is spread over the element's
//!    *visible* area (buried leaves excluded), so `H_p` is scaled by `A_p / A_vis,p`.
//! 2. **Push.** Irradiance accumulates down the tree: a leaf receives the sum of what its
//!    ancestors and itself gathered, and gets `B = E + ρ H`.
//! 3. **Pull.** A parent's radiosity is the visible-area average of its children's, so a
//!    link to a coarse source sees the mean of the finer solution below it.
//!
//! Children are numbered after their parents ([`super::element`]), so push is one forward
//! pass over the elements and pull one backward pass.
//!
//! The iteration stops when no visible leaf's radiosity changes by more than `tol` times
//! its own value (with a floor of `1e-9` times the scene's mean radiosity, for leaves that
//! receive nothing), in every channel: a per-element rule, so that dim surfaces lit only at
//! second order converge as well as bright ones. With reflectances below one and factor
//! sums at most one, the iteration is a contraction (as Jacobi on the flat system).

use rayon::prelude::*;

use super::element::{Elements, NONE};
use super::link::Link;

/// Radiosity per element and what the refinement oracle reads from it.
#[derive(Clone, Debug, Default)]
pub struct State {
    /// Radiosity of every element (leaves solved, parents the visible-area average).
    pub b: Vec<[f64; 3]>,
    /// Spread `max - min` of leaf radiosity below each element, per channel.
    pub spread: Vec<[f64; 3]>,
    /// Irradiance each leaf received in the last iteration (0 for parents).
    pub h: Vec<[f64; 3]>,
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

/// Iterates gather and push-pull from `state` until the relative change is at most `tol`
/// (or `max_iterations`); `b_ref` is the scene's mean radiosity (for the floor).
pub fn solve(
    e: &Elements,
    links: &[Vec<Link>],
    m: &Materials,
    state: &mut State,
    b_ref: f64,
    tol: f64,
    max_iterations: usize,
) -> SolveStats {
    let n = e.len();
    let vis = e.visible_areas();
    let scale: Vec<f64> = (0..n)
        .map(|k| {
            if vis[k] > 0.0 {
                e.area[k] / vis[k]
            } else {
                0.0
            }
        })
        .collect();
    if state.b.len() != n {
        state.b.resize(n, [0.0; 3]);
        state.spread.resize(n, [0.0; 3]);
        state.h.resize(n, [0.0; 3]);
    }
    let floor = 1e-9 * b_ref.max(f64::MIN_POSITIVE);
    let mut stats = SolveStats::default();
    let mut gathered = vec![[0.0f64; 3]; n];
    let mut down = vec![[0.0f64; 3]; n];
    for it in 0..max_iterations.max(1) {
        // 1. Gather, from the previous iteration's radiosities.
        gathered.par_iter_mut().enumerate().for_each(|(p, g)| {
            let mut s = [0.0; 3];
            for l in &links[p] {
                let bs = state.b[l.src as usize];
                for c in 0..3 {
                    s[c] += l.f * bs[c];
                }
            }
            *g = s.map(|v| v * scale[p]);
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
                    for c in 0..3 {
                        let d = (new[c] - state.b[p][c]).abs() / new[c].abs().max(floor);
                        change = change.max(d);
                    }
                }
                state.b[p] = new;
                state.h[p] = if e.buried[p] { [0.0; 3] } else { h };
                state.spread[p] = [0.0; 3];
            }
        }
        // 3. Pull (children first).
        pull(e, &vis, state);
        stats = SolveStats {
            iterations: it + 1,
            change,
            converged: change <= tol,
        };
        if stats.converged {
            break;
        }
    }
    stats
}

/// Sets every parent's radiosity to the visible-area average of its children, and its
/// spread to the range of the leaves below it.
pub fn pull(e: &Elements, vis: &[f64], state: &mut State) {
    let mut lo = vec![[f64::INFINITY; 3]; e.len()];
    let mut hi = vec![[f64::NEG_INFINITY; 3]; e.len()];
    for p in (0..e.len()).rev() {
        if e.first_child[p] == NONE {
            if !e.buried[p] {
                lo[p] = state.b[p];
                hi[p] = state.b[p];
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
        let a = e.area[p];
        for c in 0..3 {
            emitted[c] += a * m.emit[p][c];
            absorbed[c] += a * (1.0 - m.rho[p][c]) * state.h[p][c];
        }
    }
    (emitted, absorbed)
}
