//! The solver study (`radiosity study-solvers`): residual against iterations and against
//! time for every solver, on the closed cube (`rho` = 0.5, 0.9, 0.99, 0.999, every face
//! emitting, and again lit by its ceiling only) and on the Cornell box; CSV files and SVG/PNG
//! charts. It lives beside the estimator study, outside [`crate::solve`], so that the
//! solvers depend on nothing downstream (the study drives the whole pipeline and writes
//! files).
//!
//! What is plotted, so that the methods are comparable (Cohen and Wallace 1993, §5.3, compare
//! them the same way):
//! - x = *sweep equivalents*: an iteration of Jacobi or Gauss-Seidel is one pass over `F`, a
//!   CG iteration two (one over the symmetrised matrix, one for the exact residual) and is
//!   counted as 2, and `n` shots of progressive refinement read `n` columns, one pass: shots
//!   are divided by `n`. The direct solve is one point at its factorisation.
//! - y = the relative residual of the original system (see the [`crate::solve`] docs); for
//!   progressive refinement the recorded history is its cheap upper bound (see
//!   [`Progressive`](crate::solve::Progressive)) and the final point is exact.
//! - time: each run's wall-clock time spread evenly over its iterations (the solvers record
//!   one total time, and their iterations cost the same).
//!
//! F comes from the semi-analytic estimator (reciprocal by construction), computed once per
//! scene and material, and the system is solved as in a bake ([`crate::pipeline::solve_radiosity`]:
//! rows with `rho * (row sum) >= 1` repaired, with a note). A solver that refuses or does not
//! converge within the cap is recorded with its reason, not dropped.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::mesh::{PatchSet, Resolution};
use crate::output::chart::{line_chart, Series};
use crate::pipeline::{self, EstimatorChoice, Quiet};
use crate::scene::Scene;
use crate::solve::{Method, Options};

/// What to run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Output folder.
    pub out_dir: PathBuf,
    /// Cube reflectances.
    pub rhos: Vec<f64>,
    /// Longest patch edge on the unit cube (0.125 gives 6 x 8 x 8 patches).
    pub cube_edge: f64,
    /// Cornell box patches.
    pub cornell_patches: usize,
    /// Solver tolerance.
    pub tolerance: f64,
    /// Iteration cap (sweeps; scaled for progressive refinement as in a bake).
    pub max_iterations: usize,
    /// Form-factor estimator.
    pub estimator: EstimatorChoice,
}

impl Settings {
    /// The full study, as committed under `docs/solvers/`.
    pub fn full(out_dir: PathBuf) -> Settings {
        Settings {
            out_dir,
            rhos: vec![0.5, 0.9, 0.99, 0.999],
            cube_edge: 0.125,
            cornell_patches: 1000,
            tolerance: 1e-8,
            max_iterations: 50_000,
            estimator: EstimatorChoice::SemiAnalytic {
                points: 2,
                rays: 1,
                replicates: 2,
                tol: crate::formfactor::SemiAnalytic::DEFAULT_TOL,
            },
        }
    }

    /// A small study for tests.
    pub fn quick(out_dir: PathBuf) -> Settings {
        Settings {
            rhos: vec![0.5, 0.9],
            cube_edge: 0.5,
            cornell_patches: 60,
            max_iterations: 2_000,
            ..Settings::full(out_dir)
        }
    }
}

/// One solver on one case.
#[derive(Clone, Debug)]
pub struct Run {
    /// Case name (`cube-rho-0.99`, `cornell`).
    pub case: String,
    /// Solver name.
    pub solver: String,
    /// Iterations reported.
    pub iterations: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Final relative residual (NaN when refused).
    pub residual: f64,
    /// `ok`, `not converged`, or the refusal.
    pub status: String,
    /// `(sweep equivalents, seconds, residual)` per recorded iteration.
    pub curve: Vec<(f64, f64, f64)>,
}

/// What the study did.
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Every run.
    pub runs: Vec<Run>,
    /// Files written.
    pub files: Vec<PathBuf>,
}

/// Points kept per curve (CSV and charts): progressive refinement records millions of shots.
pub const MAX_POINTS: usize = 400;

/// Keeps at most `max` points, evenly spaced by index, always the first and the last.
fn thin<T: Copy>(v: Vec<T>, max: usize) -> Vec<T> {
    if v.len() <= max || max < 2 {
        return v;
    }
    let last = v.len() - 1;
    let mut out: Vec<T> = (0..max - 1).map(|k| v[k * last / (max - 1)]).collect();
    out.push(v[last]);
    out
}

fn run_case(
    case: &str,
    patches: &PatchSet,
    settings: &Settings,
    report: &mut Report,
) -> Result<()> {
    let (ff, _, _) = pipeline::form_factors(patches, &settings.estimator, 1, &Quiet)?;
    let n = patches.len().max(1) as f64;
    let opts = Options {
        tolerance: settings.tolerance,
        max_iterations: settings.max_iterations,
        keep_partial: true,
        floor: None,
    };
    for method in Method::ALL {
        let per_iteration = match method {
            Method::Progressive => 1.0 / n,
            Method::Cg => 2.0,
            _ => 1.0,
        };
        let run = match pipeline::solve_radiosity(patches, &ff, method, &opts) {
            Ok((_, r)) => {
                let k = r.history.len().saturating_sub(1).max(1) as f64;
                let mut curve: Vec<(f64, f64, f64)> = r
                    .history
                    .iter()
                    .enumerate()
                    .map(|(i, &h)| (i as f64 * per_iteration, r.seconds * i as f64 / k, h))
                    .collect();
                if let Some(last) = curve.last_mut() {
                    last.2 = r.residual;
                }
                let curve = thin(curve, MAX_POINTS);
                Run {
                    case: case.into(),
                    solver: r.solver.clone(),
                    iterations: r.iterations,
                    seconds: r.seconds,
                    residual: r.residual,
                    status: if r.converged {
                        "ok".into()
                    } else {
                        "not converged".into()
                    },
                    curve,
                }
            }
            Err(e) => Run {
                case: case.into(),
                solver: method.name().into(),
                iterations: 0,
                seconds: 0.0,
                residual: f64::NAN,
                status: format!("refused: {e}"),
                curve: Vec::new(),
            },
        };
        report.runs.push(run);
    }
    let runs: Vec<&Run> = report.runs.iter().filter(|r| r.case == case).collect();
    let series = |x: fn(&(f64, f64, f64)) -> f64| -> Vec<Series> {
        runs.iter()
            .filter(|r| !r.curve.is_empty())
            .map(|r| {
                Series::new(
                    r.solver.clone(),
                    r.curve.iter().map(|p| (x(p), p.2)).collect(),
                )
            })
            .collect()
    };
    let dir = &settings.out_dir;
    report.files.extend(line_chart(
        &dir.join(format!("residual-vs-iterations-{case}")),
        &format!("{case}: residual against work"),
        "sweep equivalents (passes over F)",
        "relative residual",
        false,
        true,
        &series(|p| p.0),
    )?);
    report.files.extend(line_chart(
        &dir.join(format!("residual-vs-time-{case}")),
        &format!("{case}: residual against time"),
        "seconds",
        "relative residual",
        false,
        true,
        &series(|p| p.1),
    )?);
    Ok(())
}

/// Runs the study and writes `solvers.csv` (every point), `solvers-summary.csv` (one line per
/// run) and the charts into `settings.out_dir`.
pub fn run(settings: &Settings) -> Result<Report> {
    let dir = &settings.out_dir;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut report = Report::default();
    for &rho in &settings.rhos {
        let mut scene = Scene::load("cube")?;
        scene.set_material("wall", [rho; 3], [1.0; 3])?;
        let patches = PatchSet::build(&scene, Resolution::MaxEdge(settings.cube_edge))?;
        run_case(&format!("cube-rho-{rho}"), &patches, settings, &mut report)?;
        // The same cube lit by its ceiling (y = 1) only: with every face emitting, B is
        // nearly constant and CG finds it at once; this case shows the methods' rates.
        let mut lit = patches.clone();
        let wall = lit.material[0] as usize;
        lit.materials[wall].emit = [0.0; 3];
        let mut ceiling = lit.materials[wall].clone();
        ceiling.name = "ceiling".into();
        ceiling.emit = [1.0; 3];
        lit.materials.push(ceiling);
        let id = (lit.materials.len() - 1) as u32;
        for i in 0..lit.len() {
            if lit.centroid[i].y > 1.0 - 1e-3 {
                lit.material[i] = id;
            }
        }
        run_case(
            &format!("cube-ceiling-rho-{rho}"),
            &lit,
            settings,
            &mut report,
        )?;
    }
    let scene = Scene::load("cornell")?;
    let patches = PatchSet::build(&scene, Resolution::Patches(settings.cornell_patches))?;
    run_case("cornell", &patches, settings, &mut report)?;
    let mut points = String::from("case,solver,sweep_equivalents,seconds,residual\n");
    let mut summary = String::from("case,solver,iterations,seconds,residual,status\n");
    for r in &report.runs {
        for p in &r.curve {
            let _ = writeln!(
                points,
                "{},{},{},{:.6e},{:.6e}",
                r.case, r.solver, p.0, p.1, p.2
            );
        }
        let _ = writeln!(
            summary,
            "{},{},{},{:.6e},{:.6e},\"{}\"",
            r.case,
            r.solver,
            r.iterations,
            r.seconds,
            r.residual,
            r.status.replace('"', "'")
        );
    }
    for (name, text) in [("solvers.csv", points), ("solvers-summary.csv", summary)] {
        let path = dir.join(name);
        write_text(&path, &text)?;
        report.files.push(path);
    }
    Ok(report)
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    crate::output::write_atomic(path, |tmp| {
        std::fs::write(tmp, text).map_err(|e| Error::io(tmp, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quick_study_writes_csv_and_charts() {
        let dir =
            std::env::temp_dir().join(format!("radiosity-solver-study-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let report = run(&Settings::quick(dir.clone())).unwrap();
        // 2 x 2 cube cases + Cornell, every solver on each.
        assert_eq!(report.runs.len(), 5 * Method::ALL.len());
        for r in &report.runs {
            assert_eq!(r.status, "ok", "{} {}", r.case, r.solver);
            assert!(r.residual.is_finite() && r.residual <= 1e-8);
            assert!(r.curve.iter().all(|p| p.0.is_finite() && p.1.is_finite()));
        }
        let summary = std::fs::read_to_string(dir.join("solvers-summary.csv")).unwrap();
        assert_eq!(summary.lines().count(), 5 * Method::ALL.len() + 1);
        assert!(dir.join("residual-vs-iterations-cornell.svg").exists());
        assert!(report.runs.iter().all(|r| r.curve.len() <= MAX_POINTS));
        assert_eq!(thin((0..10).collect(), 4), vec![0, 3, 6, 9]);
        assert!(dir.join("residual-vs-time-cube-rho-0.9.png").exists());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
