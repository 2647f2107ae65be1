//! The thermal mode's files: the tables `patches.csv` (one row per patch) and
//! `surfaces.csv` (one row per surface, then the scene's total and the environment), every
//! value with its propagated standard error (see [`crate::thermal`] for how each is
//! obtained), and the per-vertex `thermal.exr` and `mesh.ply`.
//!
//! Units: K, W/m² and W when the scene is in metres (areas are in scene units squared,
//! fluxes per unit area). Numbers in the tables are written with 10 significant digits
//! (`1.234567890e3`).
//!
//! ## Per-vertex files
//! The per-patch values are interpolated onto the mesh vertices as the bake interpolates
//! radiosity ([`vertex_fields`]: [`interpolate_fields`] with the area-weighted average,
//! split at creases and between surfaces, so a surface of one given temperature carries
//! that temperature exactly at every vertex). A standard error is interpolated the same
//! way: the area-weighted average of the patches' standard errors, which bounds the
//! standard error of the averaged value from above whatever their correlation.
//!
//! - `thermal.exr`: the layout of the bake's `radiosity.exr` ([`super::exr`]: one pixel per
//!   vertex, `P` and `N` channels, the same header attributes) with `radiosity:layout`
//!   [`EXR_LAYOUT`] and, instead of `R G B`, the channels [`EXR_CHANNELS`], named as the
//!   columns of `patches.csv`: `T_K` (K), `J_W_m2`, `G_W_m2`, `q_W_m2` (W/m²) and their
//!   standard errors `T_se`, `J_se`, `G_se`, `q_se`. No channel is called `R`, `G` or `B`,
//!   so no viewer shows them as a colour image.
//! - `mesh.ply`: the layout of the bake's `mesh.ply` ([`super::ply`]) with the float
//!   properties `temperature` (K), `flux` (`q`, W/m², leaving the surface) and `quality`
//!   (the temperature again: MeshLab colours and filters by `quality`), and `red green
//!   blue` a false colour of the temperature ([`false_colour`]) between its smallest and
//!   largest vertex values; a header comment names the units and the colour range.
//!
//! Every value is checked finite in f32 before anything is written: a NaN or an infinity
//! is refused, naming the channel and the vertex.

use std::fmt::Write as _;
use std::path::Path;

use crate::error::{Error, Result};
use crate::mesh::PatchSet;
use crate::scene::Boundary;
use crate::thermal::{Problem, Solution, SurfaceResult};

use super::vertex::{interpolate_fields, Nodal, VertexFields, DEFAULT_CREASE_DEG};
use super::{write_atomic, write_ply_with, write_vertex_channels};

/// The `radiosity:layout` attribute of `thermal.exr`.
pub const EXR_LAYOUT: &str = "radiosity-thermal-vertex/1 (pixel k = vertex k, row-major, \
                              width = min(vertexCount, 4096); T_K temperature K, J_W_m2 \
                              radiosity, G_W_m2 irradiation, q_W_m2 net flux leaving, W/m2, \
                              *_se standard errors; P position, N normal)";

/// The part of [`EXR_LAYOUT`] a reader checks.
pub const EXR_LAYOUT_ID: &str = "radiosity-thermal-vertex/1";

/// The value channels of `thermal.exr`, in the order of [`VertexFields::values`] made by
/// [`vertex_fields`].
pub const EXR_CHANNELS: [&str; 8] = [
    "T_K", "T_se", "J_W_m2", "J_se", "G_W_m2", "G_se", "q_W_m2", "q_se",
];

/// Index of the temperature and of the flux in [`EXR_CHANNELS`].
const T: usize = 0;
const Q: usize = 6;

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
/// J_mean,G_mean,q_W_m2,Q_W,Q_se,Q_bound`, one row per surface, then `[total]` (every patch)
/// and `[environment]` (the net power to the environment, `Q` column). `Q_se` is the
/// standard error propagated from the factors' standard errors, `Q_bound` the bound
/// propagated from their bounds (add them as `k Q_se + Q_bound`: [`crate::matrix::Bar`]).
pub fn write_surfaces(
    path: &Path,
    info: &[SurfaceInfo],
    results: &[SurfaceResult],
    sol: &Solution,
) -> Result<()> {
    let mut o = String::from(
        "surface,patches,area,emissivity,condition,given,T_mean_K,T_se,J_mean_W_m2,\
         G_mean_W_m2,q_W_m2,Q_W,Q_se,Q_bound\n",
    );
    for (s, r) in info.iter().zip(results) {
        let (kind, given) = condition(s.boundary);
        let _ = writeln!(
            o,
            "{},{},{:.10e},{},{kind},{given},{:.10e},{:.3e},{:.10e},{:.10e},{:.10e},{:.10e},{:.3e},{:.3e}",
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
            r.flow.se,
            r.flow.bound
        );
    }
    if let Some(t) = results.get(info.len()) {
        let _ = writeln!(
            o,
            "[total],{},{:.10e},,,,,,,,{:.10e},{:.10e},{:.3e},{:.3e}",
            info.iter().map(|s| s.patches).sum::<usize>(),
            t.area,
            t.flow.q / t.area,
            t.flow.q,
            t.flow.se,
            t.flow.bound
        );
    }
    let _ = writeln!(
        o,
        "[environment],,,,,,,,,,,{:.10e},{:.3e}",
        sol.to_environment, sol.se_to_environment
    );
    write_text(path, &o)
}

/// The solution's per-patch values interpolated onto the vertices of `patches` as the bake
/// does (see the module docs), in the order of [`EXR_CHANNELS`].
pub fn vertex_fields(patches: &PatchSet, sol: &Solution) -> VertexFields {
    let fields: [&[f64]; 8] = [
        &sol.t, &sol.se_t, &sol.j, &sol.se_j, &sol.g, &sol.se_g, &sol.q, &sol.se_q,
    ];
    interpolate_fields(patches, &fields, DEFAULT_CREASE_DEG, Nodal::Average)
}

/// Refuses `v` unless it holds the [`EXR_CHANNELS`] and every value is finite.
fn check(path: &Path, v: &VertexFields) -> Result<()> {
    let n = v.mesh.checked_len(path)?;
    let refuse = |msg: String| {
        Err(Error::Output {
            path: path.to_path_buf(),
            msg,
        })
    };
    if v.values.len() != EXR_CHANNELS.len() || v.values.iter().any(|x| x.len() != n) {
        return refuse(format!(
            "{} per-vertex fields for the {} thermal channels of {n} vertices",
            v.values.len(),
            EXR_CHANNELS.len()
        ));
    }
    for (name, x) in EXR_CHANNELS.iter().zip(&v.values) {
        if let Some(k) = x.iter().position(|x| !x.is_finite()) {
            return refuse(format!(
                "`{name}` is {} at vertex {k} (position {:?}): not written",
                x[k], v.mesh.positions[k]
            ));
        }
    }
    Ok(())
}

/// Writes `thermal.exr` (module docs) for scene `scene_name`.
pub fn write_exr(path: &Path, v: &VertexFields, scene_name: &str) -> Result<()> {
    check(path, v)?;
    let values: Vec<(&str, &[f32])> = EXR_CHANNELS
        .iter()
        .zip(&v.values)
        .map(|(name, x)| (*name, &x[..]))
        .collect();
    write_vertex_channels(path, EXR_LAYOUT, &v.mesh, scene_name, &values)
}

/// Writes the thermal `mesh.ply` (module docs).
pub fn write_ply(path: &Path, v: &VertexFields) -> Result<()> {
    check(path, v)?;
    let (t, q) = (&v.values[T], &v.values[Q]);
    let (lo, hi) = t
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &x| {
            (l.min(x), h.max(x))
        });
    let colours: Vec<[u8; 3]> = t.iter().map(|&x| false_colour(x, lo, hi)).collect();
    let comment = format!(
        "radiosity {} per-vertex thermal solution; temperature and quality in K, flux = net \
         radiative flux leaving the surface in W/m2 (scene in metres); red green blue = \
         inferno false colour of temperature, black {lo} K to pale yellow {hi} K",
        env!("CARGO_PKG_VERSION")
    );
    write_ply_with(
        path,
        &v.mesh,
        &[&comment, super::ply::UP],
        &colours,
        &[("temperature", t), ("flux", q), ("quality", t)],
    )
}

/// Nine samples of the inferno colour map (van der Walt and Smith, matplotlib, 2015), 8-bit
/// sRGB, at 0, 1/8, ..., 1.
const INFERNO: [[u8; 3]; 9] = [
    [0, 0, 4],
    [31, 12, 72],
    [85, 15, 109],
    [136, 34, 106],
    [186, 54, 85],
    [227, 89, 51],
    [249, 140, 10],
    [249, 201, 50],
    [252, 255, 164],
];

/// The false colour of `x` on `[lo, hi]`: piecewise linear through `INFERNO`, from black
/// at `lo` to pale yellow at `hi`; the middle colour when the range is empty.
pub fn false_colour(x: f32, lo: f32, hi: f32) -> [u8; 3] {
    let s = if hi > lo {
        ((x - lo) / (hi - lo)).clamp(0.0, 1.0)
    } else {
        0.5
    };
    let at = s * (INFERNO.len() - 1) as f32;
    let k = (at.floor() as usize).min(INFERNO.len() - 2);
    let w = at - k as f32;
    let (a, b) = (INFERNO[k], INFERNO[k + 1]);
    [0, 1, 2].map(|c| (f32::from(a[c]) * (1.0 - w) + f32::from(b[c]) * w).round() as u8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::test_dir;
    use glam::Vec3;

    fn fields(t: [f32; 3]) -> VertexFields {
        let mesh = crate::output::VertexRadiosity {
            two_sided: Vec::new(),
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            normals: vec![Vec3::Z; 3],
            rgb: vec![[0.0; 3]; 3],
            triangles: vec![[0, 1, 2]],
            patch_of_triangle: vec![0],
            emits: Vec::new(),
        };
        let mut values = vec![vec![1.0; 3]; EXR_CHANNELS.len()];
        values[T] = t.to_vec();
        VertexFields { mesh, values }
    }

    #[test]
    fn false_colour_runs_black_to_pale_yellow() {
        assert_eq!(false_colour(300.0, 300.0, 900.0), INFERNO[0]);
        assert_eq!(false_colour(900.0, 300.0, 900.0), INFERNO[8]);
        assert_eq!(false_colour(600.0, 300.0, 900.0), INFERNO[4]);
        assert_eq!(false_colour(5.0, 5.0, 5.0), INFERNO[4]);
    }

    #[test]
    fn non_finite_values_are_refused_and_nothing_written() {
        let dir = test_dir("thermal-nan");
        for bad in [f32::NAN, f32::INFINITY] {
            let v = fields([300.0, bad, 400.0]);
            let exr = dir.join("thermal.exr");
            let err = write_exr(&exr, &v, "s").unwrap_err();
            assert!(err.to_string().contains("`T_K` is"), "{err}");
            let ply = dir.join("mesh.ply");
            let err = write_ply(&ply, &v).unwrap_err();
            assert!(err.to_string().contains("vertex 1"), "{err}");
            assert!(!exr.exists() && !ply.exists());
        }
        let v = fields([300.0, 350.0, 400.0]);
        write_exr(&dir.join("thermal.exr"), &v, "s").unwrap();
        let back = super::super::read_vertex_channels(
            &dir.join("thermal.exr"),
            EXR_LAYOUT_ID,
            &EXR_CHANNELS,
        )
        .unwrap();
        assert_eq!(back.values, v.values);
        assert_eq!(back.positions, v.mesh.positions);
    }
}
