//! The thermal mode's tables as CSV: `patches.csv` (one row per patch) and `surfaces.csv`
//! (one row per surface, then the scene's total and the environment), every value with its
//! propagated standard error (see [`crate::thermal`] for how each is obtained).
//!
//! Units: K, W/m² and W when the scene is in metres (areas are in scene units squared,
//! fluxes per unit area). Numbers are written with 10 significant digits (`1.234567890e3`).

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{Error, Result};
use crate::scene::Boundary;
use crate::thermal::{Problem, Solution, SurfaceResult};

use super::write_atomic;

/// `temperature` or `flux` and the given value.
pub fn condition(b: Boundary) -> (&'static str, f64) {
    match b {
        Boundary::Temperature(t) => ("temperature", t),
        Boundary::Flux(q) => ("flux", q),
    }
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, |tmp| {
        std::fs::write(tmp, text).map_err(|e| Error::io(tmp, e))
    })
}

/// Writes `patches.csv`: `patch,surface,area,emissivity,condition,given,T,T_se,J,J_se,G,
/// G_se,q,q_se,Q,Q_se` (`Q = q A`; per-patch errors from the tangent replicates).
pub fn write_patches(
    path: &Path,
    p: &Problem,
    sol: &Solution,
    surface: &[u32],
    names: &[String],
) -> Result<()> {
    let mut o = String::from(
        "patch,surface,area,emissivity,condition,given,T_K,T_se,J_W_m2,J_se,G_W_m2,G_se,\
         q_W_m2,q_se,Q_W,Q_se\n",
    );
    for i in 0..p.len() {
        let (kind, given) = condition(p.boundary[i]);
        let a = p.area[i];
        let _ = writeln!(
            o,
            "{i},{},{:.10e},{},{kind},{given},{:.10e},{:.3e},{:.10e},{:.3e},{:.10e},{:.3e},\
             {:.10e},{:.3e},{:.10e},{:.3e}",
            names[surface[i] as usize],
            a,
            p.emissivity[i],
            sol.t[i],
            sol.se_t[i],
            sol.j[i],
            sol.se_j[i],
            sol.g[i],
            sol.se_g[i],
            sol.q[i],
            sol.se_q[i],
            sol.q[i] * a,
            sol.se_q[i] * a,
        );
    }
    write_text(path, &o)
}

/// One surface's fixed description for `surfaces.csv`.
#[derive(Clone, Debug)]
pub struct SurfaceInfo {
    /// Name (the material's).
    pub name: String,
    /// Patches.
    pub patches: usize,
    /// Emissivity.
    pub emissivity: f64,
    /// Boundary condition.
    pub boundary: Boundary,
}

/// Writes `surfaces.csv`: `surface,patches,area,emissivity,condition,given,T_mean_K,T_se,
/// J_mean,G_mean,q_W_m2,Q_W,Q_se`, one row per surface, then `[total]` (every patch) and
/// `[environment]` (the net power to the environment, `Q` column).
pub fn write_surfaces(
    path: &Path,
    info: &[SurfaceInfo],
    results: &[SurfaceResult],
    sol: &Solution,
) -> Result<()> {
    let mut o = String::from(
        "surface,patches,area,emissivity,condition,given,T_mean_K,T_se,J_mean_W_m2,\
         G_mean_W_m2,q_W_m2,Q_W,Q_se\n",
    );
    for (s, r) in info.iter().zip(results) {
        let (kind, given) = condition(s.boundary);
        let _ = writeln!(
            o,
            "{},{},{:.10e},{},{kind},{given},{:.10e},{:.3e},{:.10e},{:.10e},{:.10e},{:.10e},{:.3e}",
            s.name,
            s.patches,
            r.area,
            s.emissivity,
            r.t,
            r.se_t,
            r.j,
            r.g,
            r.flow.q / r.area,
            r.flow.q,
            r.flow.se
        );
    }
    if let Some(t) = results.get(info.len()) {
        let _ = writeln!(
            o,
            "[total],{},{:.10e},,,,,,,,{:.10e},{:.10e},{:.3e}",
            info.iter().map(|s| s.patches).sum::<usize>(),
            t.area,
            t.flow.q / t.area,
            t.flow.q,
            t.flow.se
        );
    }
    let _ = writeln!(
        o,
        "[environment],,,,,,,,,,,{:.10e},{:.3e}",
        sol.to_environment, sol.se_to_environment
    );
    write_text(path, &o)
}
