//! Progressive refinement: Cohen, Chen, Wallace and Greenberg 1988, "A progressive
//! refinement approach to fast radiosity image generation" (SIGGRAPH '88), the method of the
//! lecture notes' "real example" (radiosidade.md: 1, 2, 24 and 100 steps with an ambient
//! term).
//!
//! Instead of gathering whole rows, each step *shoots*: the patch with the most unshot power
//! `ΔB_i A_i` (summed over channels) sends its unshot radiosity to every patch that sees it.
//! It is the Southwell iteration on `(I - diag(rho) F) B = E` (Gortler, Cohen and Slusallek
//! 1993, "Radiosity and relaxation methods"; Cohen and Wallace 1993, §5.3.3):
//!
//! ```text
//! start   B = E, ΔB = E
//! step    pick i maximising A_i (ΔB_i,r + ΔB_i,g + ΔB_i,b)
//!         s = ΔB_i / (1 - rho_i F_ii)
//!         for j != i:  B_j += rho_j F_ji s,  ΔB_j += rho_j F_ji s
//!         B_i += rho_i F_ii s,  ΔB_i = 0
//! ```
//!
//! Cohen et al. write the increment as `rho_j F_ij (A_i / A_j) ΔB_i`, which is
//! `rho_j F_ji ΔB_i` by reciprocity (`A_i F_ij = A_j F_ji`). A Monte Carlo `F` is only
//! reciprocal up to noise, so the column `F_ji` is read from the matrix itself (its
//! transpose, built once, gives column access): every step then keeps the invariant
//! `B = E + diag(rho) F (B - ΔB)` exactly, and the method converges to the same `B` as
//! [`Jacobi`](super::Jacobi) and [`GaussSeidel`](super::GaussSeidel). Dividing by
//! `1 - rho_i F_ii` shoots at once what a concave patch would send back to itself, so its
//! unshot radiosity really is zero after its step.
//!
//! ## Residual
//! By the invariant the true residual is `E + diag(rho) F B - B = diag(rho) F ΔB`, so
//! `|residual| <= max_i rho_i sum_j |F_ij| * ||ΔB||_inf` per channel. The report's
//! `history[k]` is this bound after `k` shots, relative as in the [module
//! docs](super) (cheap: no pass over `F`); it is an upper bound on the true relative residual.
//! The true residual is computed when the bound falls within tolerance and, since it is often
//! well below the bound, also every `n` shots for `n` patches (one pass over `F`, about what
//! those shots cost), with the per-patch measure of the [module docs](super) from the same
//! pass; the run stops as soon as both are within tolerance (when only the dimmest patches
//! lack, the next measurement waits until the bound has fallen by what they lack), and the
//! report's final `residual` is always the true one. An iteration is one shot, so a scene of `n`
//! patches typically needs a few times `n` iterations.
//!
//! ## Ambient term
//! For display, Cohen et al. add an estimate of the light not yet shot (their §4, "Ambient
//! contribution"): `ambient = R * sum_i ΔB_i A_i / sum_i A_i` with the overall
//! interreflection factor `R = 1 / (1 - rho_avg)`, `rho_avg` the area-weighted average
//! reflectance, and show `B_i + rho_i * ambient`. See [`ambient_term`], [`ambient`] and
//! [`progressive_steps`].

use crate::matrix::Csr;

use super::{
    divergence, diverging, finish, max3, measure, worst, Gain, Options, Outcome, Prologue, Rows,
    Scale, SolveReport, Solver, System,
};
use crate::error::Result;

pub(crate) const NAME: &str = "progressive";

/// Progressive refinement by shooting; see the [module docs](self).
#[derive(Clone, Copy, Debug, Default)]
pub struct Progressive;

/// Radiosity and unshot radiosity during shooting.
struct State {
    b: Vec<[f64; 3]>,
    unshot: Vec<[f64; 3]>,
}

impl State {
    fn new(sys: &System) -> State {
        State {
            b: sys.emit.to_vec(),
            unshot: sys.emit.to_vec(),
        }
    }

    /// The patch with the most unshot power (the first of equals; none when all is shot),
    /// and the largest `|ΔB|` per channel.
    fn select(&self, area: &[f64]) -> (Option<usize>, [f64; 3]) {
        let mut best = (None, 0.0f64);
        let mut umax = [0.0f64; 3];
        for (i, (u, &a)) in self.unshot.iter().zip(area).enumerate() {
            let abs = u.map(f64::abs);
            umax = max3(umax, abs);
            let power = a * (abs[0] + abs[1] + abs[2]);
            if power > best.1 {
                best = (Some(i), power);
            }
        }
        (best.0, umax)
    }

    /// Shoots the unshot radiosity of patch `i`; `cols` are the rows of `F^T`.
    fn shoot(&mut self, sys: &System, cols: &Rows, i: usize) {
        let (ind, val) = cols.row(i);
        let fii: f64 = ind
            .iter()
            .zip(val)
            .filter(|(&j, _)| j as usize == i)
            .map(|(_, &f)| f)
            .sum();
        let (d, rho_i) = (self.unshot[i], sys.rho[i]);
        let s = [0, 1, 2].map(|c| d[c] / (1.0 - rho_i[c] * fii));
        for (&j, &f_ji) in ind.iter().zip(val) {
            let j = j as usize;
            if j == i {
                continue;
            }
            let rho_j = sys.rho[j];
            for c in 0..3 {
                let add = rho_j[c] * f_ji * s[c];
                self.b[j][c] += add;
                self.unshot[j][c] += add;
            }
        }
        for c in 0..3 {
            self.b[i][c] += rho_i[c] * fii * s[c];
        }
        self.unshot[i] = [0.0; 3];
    }
}

/// The rows of `F^T` (the columns of `F`), for shooting.
fn transpose(f: &Csr) -> Csr {
    f.transpose_view().to_csr()
}

/// The bound on the relative residual from the unshot radiosity (see the module docs).
fn bound(scale: &Scale, gain: &Gain, umax: [f64; 3]) -> f64 {
    scale.rel([0, 1, 2].map(|c| gain.gain[c] * umax[c]))
}

impl Solver for Progressive {
    fn name(&self) -> &'static str {
        NAME
    }

    fn solve(&self, sys: &System, opts: &Options) -> Result<(Vec<[f64; 3]>, SolveReport)> {
        let Prologue {
            start,
            rows,
            scale,
            floor,
            gain,
            notes,
        } = Prologue::new(sys, opts)?;
        let cols_f = transpose(sys.f);
        let cols = Rows::new(&cols_f);
        let mut state = State::new(sys);
        let mut history = Vec::new();
        let mut shots = 0;
        // The bound at which to compute the true residual next.
        let mut check_at = opts.tolerance;
        loop {
            let (pick, umax) = state.select(sys.area);
            let r_bound = bound(&scale, &gain, umax);
            history.push(r_bound);
            if diverging(r_bound) {
                return Err(divergence(NAME, shots, r_bound, opts, &gain));
            }
            let at_cap = shots >= opts.max_iterations;
            // Every n shots (about the cost of one pass over F) the true residual is measured
            // too, since it is often well below the bound.
            let periodic = shots > 0 && shots % sys.len().max(1) == 0;
            if r_bound <= check_at || pick.is_none() || at_cap || periodic {
                let (abs, per_patch) = measure(sys, &rows, &state.b, &floor);
                let (r, p) = (scale.rel(abs), worst(per_patch));
                let done = r <= opts.tolerance && p <= opts.tolerance;
                if done || pick.is_none() || at_cap {
                    let out = Outcome {
                        b: state.b,
                        iterations: shots,
                        residual: r,
                        patch_residual: p,
                        history,
                        notes,
                    };
                    return finish(NAME, out, opts, &gain, start);
                }
                if r_bound <= check_at {
                    // Within the bound but not the true residual (only rounding can do
                    // that), or the dimmest patches not yet converged: measure again once
                    // the bound has fallen by what they lack.
                    let lack = if p > opts.tolerance {
                        opts.tolerance / p
                    } else {
                        1.0
                    };
                    check_at = r_bound * lack.min(0.5);
                }
            }
            if let Some(i) = pick {
                state.shoot(sys, &cols, i);
                shots += 1;
            }
        }
    }
}

/// The ambient term of Cohen et al. 1988 (§4), per channel:
/// `R * sum_i ΔB_i A_i / sum_i A_i` with `R = 1 / (1 - rho_avg)` and `rho_avg` the
/// area-weighted average reflectance. Zero for an empty system. Patches past the shorter of
/// `unshot` and the system are left out.
pub fn ambient_term(sys: &System, unshot: &[[f64; 3]]) -> [f64; 3] {
    let (mut area, mut rho_a, mut unshot_a) = (0.0, [0.0; 3], [0.0; 3]);
    for ((u, r), &a) in unshot.iter().zip(sys.rho).zip(sys.area) {
        area += a;
        for c in 0..3 {
            rho_a[c] += r[c] * a;
            unshot_a[c] += u[c] * a;
        }
    }
    if !area.is_finite() || area <= 0.0 {
        return [0.0; 3];
    }
    [0, 1, 2].map(|c| {
        let rho_avg = rho_a[c] / area;
        unshot_a[c] / area / (1.0 - rho_avg)
    })
}

/// Radiosity for display during progressive refinement (Cohen et al. 1988, §4):
/// `B_i + rho_i * ambient` with `ambient` from [`ambient_term`]. One entry per entry of `b`
/// that has a patch in the system.
pub fn ambient(sys: &System, b: &[[f64; 3]], unshot: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let amb = ambient_term(sys, unshot);
    b.iter()
        .zip(sys.rho)
        .map(|(b, rho)| [0, 1, 2].map(|c| b[c] + rho[c] * amb[c]))
        .collect()
}

/// Display radiosity ([`ambient`]) after exactly each listed number of shooting steps, as
/// in the notes' real example (1, 2, 24 and 100 steps). The results come in the order of
/// `steps` (repeats allowed); step 0 is `E` plus its ambient term. Once nothing is left to
/// shoot, more steps change nothing.
///
/// Fails on an invalid system and when the shooting diverges (the unshot radiosity growing
/// past [`DIVERGENCE`](super::DIVERGENCE) times the emission).
pub fn progressive_steps(sys: &System, steps: &[usize]) -> Result<Vec<(usize, Vec<[f64; 3]>)>> {
    sys.validate()?;
    let rows = Rows::new(sys.f);
    let scale = Scale::new(sys.emit);
    let gain = Gain::new(sys, &rows);
    let cols_f = transpose(sys.f);
    let cols = Rows::new(&cols_f);
    let mut state = State::new(sys);
    let mut order: Vec<usize> = (0..steps.len()).collect();
    order.sort_by_key(|&k| steps[k]);
    let mut out = vec![Vec::new(); steps.len()];
    let mut shots = 0;
    let mut exhausted = false;
    let diverged = |shots: usize, r: f64| divergence(NAME, shots, r, &Options::default(), &gain);
    for k in order {
        while shots < steps[k] && !exhausted {
            let (pick, umax) = state.select(sys.area);
            let r = bound(&scale, &gain, umax);
            if diverging(r) {
                return Err(diverged(shots, r));
            }
            match pick {
                Some(i) => {
                    state.shoot(sys, &cols, i);
                    shots += 1;
                }
                None => exhausted = true,
            }
        }
        let display = ambient(sys, &state.b, &state.unshot);
        if display.iter().flatten().any(|v| !v.is_finite()) {
            return Err(diverged(shots, f64::INFINITY));
        }
        out[k] = display;
    }
    Ok(steps.iter().copied().zip(out).collect())
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;
    use super::super::*;
    use super::*;

    #[test]
    fn furnace_display_is_exact_from_the_start() {
        // Uniform rho and E, equal areas: the ambient term alone gives E / (1 - rho).
        let rho = [0.2, 0.5, 0.8];
        let owned = furnace(8, rho, [1.0, 1.0, 2.0]);
        let got = progressive_steps(&owned.sys(), &[0]).unwrap();
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].0, 0);
        for b in &got[0].1 {
            for c in 0..3 {
                let want = [1.0, 1.0, 2.0][c] / (1.0 - rho[c]);
                assert!((b[c] - want).abs() < 1e-12, "{} not {want}", b[c]);
            }
        }
    }

    #[test]
    fn first_shot_is_from_the_brightest_patch() {
        // Shelf row 4: A and B emit 1, B is sqrt 3 wider, so B shoots first.
        let (rho, emit, _) = shelf_table()[3];
        let owned = shelf(rho, emit);
        let sys = owned.sys();
        let mut state = State::new(&sys);
        let (pick, umax) = state.select(sys.area);
        assert_eq!(pick, Some(1));
        assert_eq!(umax, [1.0; 3]);
        let cols_f = transpose(sys.f);
        state.shoot(&sys, &Rows::new(&cols_f), 1);
        let f_ab = sys.f.get(0, 1).copied().unwrap();
        let f_cb = sys.f.get(2, 1).copied().unwrap();
        assert!((state.b[0][0] - (1.0 + 0.1 * f_ab)).abs() < 1e-15);
        assert!((state.b[2][0] - 0.5 * f_cb).abs() < 1e-15);
        assert_eq!(state.unshot[1], [0.0; 3]);
        assert_eq!(state.b[1], [1.0; 3]);
        // The invariant B = E + diag(rho) F (B - ΔB).
        let shot: Vec<[f64; 3]> = state
            .b
            .iter()
            .zip(&state.unshot)
            .map(|(b, u)| [0, 1, 2].map(|c| b[c] - u[c]))
            .collect();
        let rows = Rows::new(sys.f);
        for (i, b) in state.b.iter().enumerate() {
            let g = gather(&sys, &rows, &shot, i);
            assert!((g[0] - b[0]).abs() < 1e-15);
        }
    }

    #[test]
    fn steps_in_given_order_and_converging() {
        let owned = random(50, 8, 21);
        let sys = owned.sys();
        let got = progressive_steps(&sys, &[24, 0, 2, 24, 1, 5000]).unwrap();
        let counts: Vec<usize> = got.iter().map(|g| g.0).collect();
        assert_eq!(counts, [24, 0, 2, 24, 1, 5000]);
        assert_eq!(got[0].1, got[3].1);
        assert_ne!(got[2].1, got[4].1);
        let tight = Options {
            tolerance: 1e-13,
            ..Options::default()
        };
        let (exact, _) = GaussSeidel.solve(&sys, &tight).unwrap();
        // With nothing left to shoot the ambient term vanishes.
        assert!(rel_diff(&exact, &got[5].1) < 1e-9);
        // Early displays are closer with the ambient term than without.
        let (b24, report) = Progressive
            .solve(
                &sys,
                &Options {
                    max_iterations: 24,
                    keep_partial: true,
                    ..tight
                },
            )
            .unwrap();
        assert_eq!(report.iterations, 24);
        assert!(rel_diff(&exact, &got[0].1) < rel_diff(&exact, &b24));
    }

    #[test]
    fn ambient_of_nothing_unshot_is_b() {
        let owned = shelf([0.5; 3], [1.0, 0.0, 0.0]);
        let sys = owned.sys();
        let b = vec![[1.0, 2.0, 3.0]; 3];
        assert_eq!(ambient(&sys, &b, &[[0.0; 3]; 3]), b);
        // R = 1 / (1 - 0.5), unshot average (1 + 0 + 0) / (1 + sqrt 3 + 1).
        let a = ambient_term(&sys, &[[1.0; 3], [0.0; 3], [0.0; 3]]);
        assert!((a[0] - 2.0 / (2.0 + 3f64.sqrt())).abs() < 1e-15);
    }

    #[test]
    fn history_bounds_the_true_residual() {
        let owned = random(50, 8, 4);
        let sys = owned.sys();
        for cap in [0, 1, 10, 100, 400] {
            let opts = Options {
                tolerance: 1e-14,
                max_iterations: cap,
                keep_partial: true,
                floor: None,
            };
            let (b, report) = Progressive.solve(&sys, &opts).unwrap();
            assert_eq!(report.history.len(), cap + 1);
            let r = residual(&sys, &b);
            assert_eq!(r, report.residual);
            assert!(
                r <= report.history[cap] * (1.0 + 1e-12),
                "{r} > {}",
                report.history[cap]
            );
        }
    }

    #[test]
    fn steps_refuse_divergence() {
        let f = dense(&[&[0.0, 1.5], &[1.5, 0.0]]);
        let (rho, emit, area) = ([[0.9; 3]; 2], [[1.0; 3]; 2], [1.0; 2]);
        let sys = System::new(&f, &rho, &emit, &area).unwrap();
        assert!(progressive_steps(&sys, &[10]).is_ok());
        match progressive_steps(&sys, &[100_000]) {
            Err(Error::NotConverged { hint, .. }) => assert!(hint.contains("spectral radius")),
            other => panic!("expected divergence, got {other:?}"),
        }
    }
}
