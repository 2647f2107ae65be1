//! The estimator study: every estimator against closed forms, over ray budgets and seeds.
//!
//! For each configuration of [`configs::all`] (a pair of patches with a known `F_ij`), each
//! estimator of [`Kind`] is run at a sweep of budgets `N` (samples per pair: point pairs
//! for the area estimators, rays per row for hemisphere and hemicube, emitter nodes times
//! visibility rays for the semi-analytic estimator) and several seeds. Each run records the
//! rays actually cast, the wall time, the estimate, its standard error and its error
//! against the exact value; [`run`] writes them to `study.csv`, draws `|error|` against
//! budget and against time per configuration, fits convergence slopes, and measures the
//! calibration of the error bars (how often `|error| <= 2 SE`) over many seeds.
//!
//! Runs are independent tasks spread over rayon's pool; each task is keyed on its seed,
//! so the numbers (but not the times) are the same on any thread count. The hemicube has
//! no randomness: its seeds repeat the same number.
//!
//! The solver study ([`solvers`], `radiosity study-solvers`) and the bake study ([`bakes`],
//! `radiosity study-bakes`) live here too: the studies
//! drive the pipeline and write files, so they sit downstream of every stage.

pub mod bakes;
pub mod configs;
pub mod solvers;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::formfactor::{
    AreaMc, Context, Estimator, Hemicube, Hemisphere, Nodes, Pattern, Row, Scratch, SemiAnalytic,
};
use crate::mesh::{PatchSet, Resolution};
use crate::output::chart::{line_chart, Series};
use crate::output::write_atomic;
use crate::visibility::Visibility;

pub use configs::Config;

/// The estimators compared (the library's estimator names).
pub use crate::formfactor::EstimatorKind as Kind;

/// Replicates of every randomized estimator in the study. With `R` replicates the error
/// bar is a t-statistic with `R - 1` degrees of freedom: for normal replicate means
/// `P(|error| <= 2 SE) = 0.936` at `R = 16` (not 0.954, which needs a known variance).
pub const REPLICATES: usize = 16;

/// Estimator of `kind` at a budget of about `budget` samples per pair.
pub fn estimator(kind: Kind, budget: usize) -> Box<dyn Estimator> {
    let r = REPLICATES;
    // Points per side per replicate: strata² × R ≈ budget.
    let s = ((budget as f64 / r as f64).sqrt().round() as usize).max(1);
    match kind {
        Kind::Uniform | Kind::Stratified | Kind::Sobol => Box::new(area_estimator(kind, s)),
        Kind::Hemisphere => Box::new(Hemisphere {
            strata: s,
            replicates: r,
        }),
        Kind::Semi => {
            // Up to 16 Gauss nodes per side, the rest of the budget to visibility rays.
            let points = s.clamp(2, 16);
            Box::new(SemiAnalytic::new(
                Nodes::Gauss,
                points,
                (s / points).max(1),
                r,
            ))
        }
        Kind::Hemicube => Box::new(Hemicube {
            res: ((budget as f64 / 3.0).sqrt().round() as usize).max(2),
        }),
    }
}

/// The area-to-area estimator of `kind` (uniform, stratified or Sobol) with `strata`
/// samples per side and the study's replicates.
fn area_estimator(kind: Kind, strata: usize) -> AreaMc {
    let pattern = match kind {
        Kind::Uniform => Pattern::Uniform,
        Kind::Stratified => Pattern::Stratified,
        _ => Pattern::Sobol,
    };
    AreaMc::new(pattern, strata, REPLICATES)
}

/// One run of one estimator on one configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Run {
    /// Configuration name.
    pub config: &'static str,
    /// Estimator.
    pub kind: Kind,
    /// Nominal samples per pair.
    pub budget: usize,
    /// Seed.
    pub seed: u64,
    /// Rays actually cast.
    pub rays: u64,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Estimated `F_ij`.
    pub estimate: f64,
    /// Its standard error (0 where its error is deterministic).
    pub stderr: f64,
    /// Bound on its deterministic error (the semi-analytic quadrature of unoccluded pairs;
    /// 0 where its error is random: [`crate::matrix::Bar`]).
    pub bound: f64,
    /// Exact `F_ij`.
    pub exact: f64,
}

impl Run {
    /// Signed error.
    pub fn error(&self) -> f64 {
        self.estimate - self.exact
    }
}

/// A configuration ready to trace: patches and visibility.
pub struct Prepared {
    /// The configuration.
    pub config: Config,
    /// One patch per face.
    pub patches: PatchSet,
    /// Visibility over the patches.
    pub vis: Visibility,
}

/// Builds the patches (one per face) and the BVH of each configuration.
pub fn prepare(configs: Vec<Config>) -> Result<Vec<Prepared>> {
    configs
        .into_iter()
        .map(|config| {
            let patches = PatchSet::build(&config.scene, Resolution::MaxEdge(1e3))?;
            if patches.len() != config.scene.faces.len() {
                return Err(Error::Scene {
                    scene: config.scene.source.clone(),
                    msg: "a face was subdivided; the study needs one patch per face".into(),
                });
            }
            let vis = Visibility::new(&patches)?;
            Ok(Prepared {
                config,
                patches,
                vis,
            })
        })
        .collect()
}

/// Runs `kind` at `budget` with `seed` on `p` and returns `F_ij`.
pub fn run_one(p: &Prepared, kind: Kind, budget: usize, seed: u64) -> Run {
    let ctx = Context {
        patches: &p.patches,
        vis: &p.vis,
        seed,
    };
    let (i, j) = (p.config.i, p.config.j);
    let est = estimator(kind, budget);
    let start = Instant::now();
    let mut row = Row::default();
    let entry = match kind {
        Kind::Uniform | Kind::Stratified | Kind::Sobol => {
            // Only the studied pair, so that rays and time are those of one pair.
            let strata = ((budget as f64 / REPLICATES as f64).sqrt().round() as usize).max(1);
            let area = area_estimator(kind, strata);
            let (a, b) = (i.min(j), i.max(j));
            let mut s = Scratch::default();
            area.pair_with(&ctx, a, b, &mut row.rays, &p.vis, &mut s)
                .map(|e| {
                    if a == i {
                        (e.f, e.bar())
                    } else {
                        // Stored as F_ab with a = j: F_ij = F_ji A_j / A_i.
                        let s = p.patches.area[j] / p.patches.area[i];
                        (e.f * s, e.bar().times(s))
                    }
                })
        }
        _ => {
            est.row(&ctx, i, &mut row, &mut Scratch::default());
            row.entries
                .iter()
                .find(|e| e.j as usize == j)
                .map(|e| (e.f, e.bar()))
        }
    };
    let seconds = start.elapsed().as_secs_f64();
    let (estimate, bar) = entry.unwrap_or((0.0, crate::matrix::Bar::ZERO));
    Run {
        config: p.config.name,
        kind,
        budget,
        seed,
        rays: row.rays,
        seconds,
        estimate,
        stderr: bar.se,
        bound: bar.bound,
        exact: p.config.exact,
    }
}

/// What to run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Budgets (samples per pair).
    pub budgets: Vec<usize>,
    /// Seeds per budget for the convergence curves.
    pub seeds: u64,
    /// Seeds for the calibration.
    pub calibration_seeds: u64,
    /// Budget of the calibration runs.
    pub calibration_budget: usize,
    /// Output folder.
    pub out_dir: PathBuf,
}

impl Settings {
    /// The default study: budgets 256 to 1 048 576 in steps of 4, 4 seeds, calibration
    /// over 200 seeds at 4096 samples per pair.
    pub fn full(out_dir: PathBuf) -> Settings {
        Settings {
            budgets: (0..7).map(|k| 256usize << (2 * k)).collect(),
            seeds: 4,
            calibration_seeds: 200,
            calibration_budget: 4096,
            out_dir,
        }
    }

    /// A small study for tests: three budgets, two seeds, 20 calibration seeds.
    pub fn quick(out_dir: PathBuf) -> Settings {
        Settings {
            budgets: vec![256, 1024, 4096],
            seeds: 2,
            calibration_seeds: 20,
            calibration_budget: 256,
            out_dir,
        }
    }
}

/// Fitted convergence slope of one estimator on one configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Slope {
    /// Configuration.
    pub config: &'static str,
    /// Estimator.
    pub kind: Kind,
    /// Least-squares slope of `log |error|` against `log budget`, averaged over seeds.
    pub slope: f64,
    /// Slope of the RMS error over seeds.
    pub slope_rms: f64,
}

/// Calibration of one estimator on one configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// Configuration.
    pub config: &'static str,
    /// Estimator.
    pub kind: Kind,
    /// Runs (seeds).
    pub runs: usize,
    /// Fraction of runs with `|error| <= 2 SE + bound` ([`crate::matrix::Bar::allowance`]).
    pub covered: f64,
    /// Median of `|error| / (SE + bound)`.
    pub median_z: f64,
    /// Every run's bar is a bound (no random part): `covered` is then the fraction of runs
    /// within their bound, which should be all of them, not a coverage near 95%. (The area
    /// estimators integrate near pairs by quadrature: [`crate::formfactor::area::near`].)
    pub bounded: bool,
}

/// Everything the study measured and wrote.
#[derive(Clone, Debug)]
pub struct Report {
    /// All convergence runs.
    pub runs: Vec<Run>,
    /// Slopes per configuration and estimator.
    pub slopes: Vec<Slope>,
    /// Calibration per configuration and estimator.
    pub calibration: Vec<Calibration>,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Wall-clock seconds of the whole study.
    pub seconds: f64,
}

/// Configurations on which the calibration is measured: all seven.
pub const CALIBRATION_CONFIGS: [&str; 7] = [
    "far",
    "near",
    "occluded",
    "adjacent",
    "grazing",
    "small-large",
    "shelf",
];

/// Runs the convergence sweep: every configuration, estimator, budget and seed.
pub fn sweep(prepared: &[Prepared], budgets: &[usize], seeds: u64) -> Vec<Run> {
    let mut tasks = Vec::new();
    for (c, _) in prepared.iter().enumerate() {
        for kind in Kind::ALL {
            for &b in budgets {
                for s in 0..seeds {
                    tasks.push((c, kind, b, s));
                }
            }
        }
    }
    // Big tasks first, so that the pool does not end on one long task.
    tasks.sort_by_key(|t| std::cmp::Reverse(t.2));
    let mut runs: Vec<Run> = tasks
        .par_iter()
        .with_min_len(1)
        .map(|&(c, kind, b, s)| run_one(&prepared[c], kind, b, 1000 + s))
        .collect();
    runs.sort_by(|a, b| {
        (a.config, a.kind.name(), a.budget, a.seed).cmp(&(
            b.config,
            b.kind.name(),
            b.budget,
            b.seed,
        ))
    });
    runs
}

/// Calibration of every randomized estimator on `configs` over `seeds` seeds at `budget`.
pub fn calibrate(
    prepared: &[Prepared],
    configs: &[&str],
    budget: usize,
    seeds: u64,
) -> Vec<Calibration> {
    let mut out = Vec::new();
    for p in prepared.iter().filter(|p| configs.contains(&p.config.name)) {
        for kind in Kind::ALL.into_iter().filter(|k| k.random()) {
            // The semi-analytic estimator is exact up to quadrature on unoccluded pairs.
            if kind == Kind::Semi && p.config.unoccluded {
                continue;
            }
            let runs: Vec<Run> = (0..seeds)
                .into_par_iter()
                .map(|s| run_one(p, kind, budget, 50_000 + s))
                .collect();
            out.push(calibration_of(p.config.name, kind, &runs));
        }
    }
    out
}

/// Coverage and median standardized error of `runs`.
pub fn calibration_of(config: &'static str, kind: Kind, runs: &[Run]) -> Calibration {
    let covered = runs
        .iter()
        .filter(|r| r.error().abs() <= 2.0 * r.stderr + r.bound)
        .count();
    let mut z: Vec<f64> = runs
        .iter()
        .map(|r| r.error().abs() / (r.stderr + r.bound).max(f64::MIN_POSITIVE))
        .collect();
    let bounded = !runs.is_empty() && runs.iter().all(|r| r.stderr == 0.0 && r.bound > 0.0);
    z.sort_by(f64::total_cmp);
    Calibration {
        config,
        kind,
        runs: runs.len(),
        covered: covered as f64 / runs.len().max(1) as f64,
        median_z: z.get(z.len() / 2).copied().unwrap_or(f64::NAN),
        bounded,
    }
}

/// Least-squares slope of `ys` against `xs`.
pub fn ls_slope(pts: &[(f64, f64)]) -> f64 {
    let n = pts.len() as f64;
    if pts.len() < 2 {
        return f64::NAN;
    }
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// Slopes of `log |error|` against `log budget` (zero errors, exact to rounding, skipped).
pub fn slopes(runs: &[Run], configs: &[&'static str]) -> Vec<Slope> {
    let mut out = Vec::new();
    for &c in configs {
        for kind in Kind::ALL {
            let rs: Vec<&Run> = runs
                .iter()
                .filter(|r| r.config == c && r.kind == kind)
                .collect();
            let mut seeds: Vec<u64> = rs.iter().map(|r| r.seed).collect();
            seeds.sort_unstable();
            seeds.dedup();
            let per_seed: Vec<f64> = seeds
                .iter()
                .map(|&s| {
                    let pts: Vec<(f64, f64)> = rs
                        .iter()
                        .filter(|r| r.seed == s && r.error() != 0.0)
                        .map(|r| ((r.budget as f64).ln(), r.error().abs().ln()))
                        .collect();
                    ls_slope(&pts)
                })
                .filter(|v| v.is_finite())
                .collect();
            let slope = per_seed.iter().sum::<f64>() / per_seed.len().max(1) as f64;
            let rms: Vec<(f64, f64)> = rms_by_budget(&rs)
                .into_iter()
                .filter(|p| p.1 > 0.0)
                .map(|(b, e)| (b.ln(), e.ln()))
                .collect();
            out.push(Slope {
                config: c,
                kind,
                slope: if per_seed.is_empty() { f64::NAN } else { slope },
                slope_rms: ls_slope(&rms),
            });
        }
    }
    out
}

/// `(budget, RMS error over seeds)` in budget order.
fn rms_by_budget(rs: &[&Run]) -> Vec<(f64, f64)> {
    let mut budgets: Vec<usize> = rs.iter().map(|r| r.budget).collect();
    budgets.sort_unstable();
    budgets.dedup();
    budgets
        .into_iter()
        .map(|b| {
            let e: Vec<f64> = rs
                .iter()
                .filter(|r| r.budget == b)
                .map(|r| r.error().powi(2))
                .collect();
            (b as f64, (e.iter().sum::<f64>() / e.len() as f64).sqrt())
        })
        .collect()
}

/// Writes the runs as CSV.
pub fn write_csv(path: &Path, runs: &[Run]) -> Result<()> {
    let mut s = String::from(
        "config,estimator,budget,seed,rays,seconds,estimate,stderr,exact,error,bound\n",
    );
    for r in runs {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{:.6e},{:.12e},{:.6e},{:.12e},{:.6e},{:.6e}",
            r.config,
            r.kind.name(),
            r.budget,
            r.seed,
            r.rays,
            r.seconds,
            r.estimate,
            r.stderr,
            r.exact,
            r.error(),
            r.bound
        );
    }
    write_atomic(path, |tmp| {
        std::fs::write(tmp, s).map_err(|e| Error::io(tmp, e))
    })
}

/// Runs the whole study and writes `study.csv`, `slopes.csv`, `calibration.csv`,
/// `summary.md` and the charts into `settings.out_dir`.
pub fn run(settings: &Settings) -> Result<Report> {
    let start = Instant::now();
    let dir = &settings.out_dir;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let prepared = prepare(configs::all())?;
    let names: Vec<&'static str> = prepared.iter().map(|p| p.config.name).collect();
    let runs = sweep(&prepared, &settings.budgets, settings.seeds);
    let slopes = slopes(&runs, &names);
    let calibration = calibrate(
        &prepared,
        &CALIBRATION_CONFIGS,
        settings.calibration_budget,
        settings.calibration_seeds,
    );
    let mut files = Vec::new();
    let csv = dir.join("study.csv");
    write_csv(&csv, &runs)?;
    files.push(csv);
    for p in &prepared {
        files.extend(charts(dir, &p.config, &runs)?);
    }
    files.extend(calibration_chart(dir, &calibration)?);
    let seconds = start.elapsed().as_secs_f64();
    let report = Report {
        runs,
        slopes,
        calibration,
        files,
        seconds,
    };
    let md = dir.join("summary.md");
    let text = summary(&report, settings, &prepared);
    write_atomic(&md, |tmp| {
        std::fs::write(tmp, &text).map_err(|e| Error::io(tmp, e))
    })?;
    let mut report = report;
    report.files.push(md);
    Ok(report)
}

/// `|error|` against budget and against seconds, one line per estimator (RMS over seeds
/// against the budget, median time against time).
fn charts(dir: &Path, c: &Config, runs: &[Run]) -> Result<Vec<PathBuf>> {
    let mut by_budget = Vec::new();
    let mut by_time = Vec::new();
    for kind in Kind::ALL {
        let rs: Vec<&Run> = runs
            .iter()
            .filter(|r| r.config == c.name && r.kind == kind)
            .collect();
        let rms = rms_by_budget(&rs);
        let times: Vec<(f64, f64)> = rms
            .iter()
            .map(|&(b, e)| {
                let mut t: Vec<f64> = rs
                    .iter()
                    .filter(|r| r.budget as f64 == b)
                    .map(|r| r.seconds)
                    .collect();
                t.sort_by(f64::total_cmp);
                (t[t.len() / 2], e)
            })
            .collect();
        by_budget.push(Series::new(kind.name(), rms));
        by_time.push(Series::new(kind.name(), times));
    }
    let title = format!("{}: F = {:.7}", c.name, c.exact);
    let mut files = line_chart(
        &dir.join(format!("error-vs-rays-{}", c.name)),
        &title,
        "samples per pair (rays per row for hemisphere / hemicube)",
        "RMS |error| over seeds",
        true,
        true,
        &by_budget,
    )?;
    files.extend(line_chart(
        &dir.join(format!("error-vs-time-{}", c.name)),
        &title,
        "wall time per run (s)",
        "RMS |error| over seeds",
        true,
        true,
        &by_time,
    )?);
    Ok(files)
}

/// Coverage of the 2-SE bars per estimator, one line per configuration.
fn calibration_chart(dir: &Path, cal: &[Calibration]) -> Result<Vec<PathBuf>> {
    let mut series = Vec::new();
    for &c in &CALIBRATION_CONFIGS {
        let pts: Vec<(f64, f64)> = Kind::ALL
            .iter()
            .enumerate()
            .filter_map(|(k, &kind)| {
                cal.iter()
                    .find(|x| x.config == c && x.kind == kind && !x.bounded)
                    .map(|x| (k as f64, x.covered))
            })
            .collect();
        series.push(Series::new(c, pts));
    }
    series.push(Series::new(
        "t(15) target 0.936",
        vec![(0.0, 0.936), (Kind::ALL.len() as f64 - 2.0, 0.936)],
    ));
    crate::output::chart::scatter_chart(
        &dir.join("calibration"),
        "fraction of runs with |error| <= 2 SE",
        "estimator: 0 uniform, 1 stratified, 2 sobol, 3 hemisphere, 4 semi",
        "coverage",
        false,
        false,
        &series,
    )
}

/// The tables of the study as Markdown.
pub fn summary(r: &Report, s: &Settings, prepared: &[Prepared]) -> String {
    let mut o = String::new();
    let _ = writeln!(o, "# Form-factor estimator study\n");
    let _ = writeln!(
        o,
        "Budgets {:?} samples per pair, {} seeds each; calibration over {} seeds at {} samples per pair; {} replicates per estimate; {:.1} s in all.\n",
        s.budgets, s.seeds, s.calibration_seeds, s.calibration_budget, REPLICATES, r.seconds
    );
    let _ = writeln!(
        o,
        "## Configurations\n\n| name | exact F_ij | description |\n|---|---|---|"
    );
    for p in prepared {
        let _ = writeln!(
            o,
            "| {} | {:.9} | {} |",
            p.config.name, p.config.exact, p.config.about
        );
    }
    let _ = writeln!(
        o,
        "\n## Slopes of log |error| against log budget (mean over seeds / of the RMS)\n"
    );
    let _ = write!(o, "| config |");
    for k in Kind::ALL {
        let _ = write!(o, " {} |", k.name());
    }
    let _ = writeln!(o, "\n|---|{}", "---|".repeat(Kind::ALL.len()));
    for p in prepared {
        let _ = write!(o, "| {} |", p.config.name);
        for k in Kind::ALL {
            match r
                .slopes
                .iter()
                .find(|x| x.config == p.config.name && x.kind == k)
            {
                Some(x) if x.slope.is_finite() => {
                    let _ = write!(o, " {:.2} / {:.2} |", x.slope, x.slope_rms);
                }
                _ => {
                    let _ = write!(o, " exact |");
                }
            }
        }
        let _ = writeln!(o);
    }
    let top = *s.budgets.iter().max().unwrap_or(&0);
    let _ = writeln!(o, "\n## RMS error at {top} samples per pair\n");
    let _ = write!(o, "| config |");
    for k in Kind::ALL {
        let _ = write!(o, " {} |", k.name());
    }
    let _ = writeln!(o, "\n|---|{}", "---|".repeat(Kind::ALL.len()));
    for p in prepared {
        let _ = write!(o, "| {} |", p.config.name);
        for k in Kind::ALL {
            let rs: Vec<&Run> = r
                .runs
                .iter()
                .filter(|x| x.config == p.config.name && x.kind == k && x.budget == top)
                .collect();
            let rms = rms_by_budget(&rs).first().map(|x| x.1).unwrap_or(f64::NAN);
            let _ = write!(o, " {rms:.2e} |");
        }
        let _ = writeln!(o);
    }
    let _ = writeln!(
        o,
        "\n## Calibration: fraction of runs with |error| <= 2 SE (median |error|/SE)\n\nWhere every run's bar is a bound (\"bound\": near pairs of the area estimators, integrated by quadrature), the fraction within the bound and the median |error|/bound.\n\n| config | estimator | runs | coverage | median z |\n|---|---|---|---|---|"
    );
    for c in &r.calibration {
        let _ = writeln!(
            o,
            "| {} | {} | {} | {:.1}%{} | {:.2} |",
            c.config,
            c.kind.name(),
            c.runs,
            100.0 * c.covered,
            if c.bounded { " (bound)" } else { "" },
            c.median_z
        );
    }
    o
}
