//! The bake pipeline: the only place that knows the order of the stages, and times them.
//!
//! `load → mesh → BVH → form factors → solve → per-vertex → EXR, PLY, glTF, preview`.
//! Each stage takes the previous result by reference and returns a new value; the
//! [`Observer`] hears about stage starts, progress and ends (the CLI draws bars from it),
//! and the returned [`BakeSummary`] carries times, peak memory and accuracy figures.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::budget;
use crate::cluster::{Cluster, Single};
use crate::error::{Error, Result};
use crate::formfactor::shard::RankReport;
use crate::formfactor::{
    self, AreaMc, Context, Estimator, Hemicube, Hemisphere, Nodes, Pattern, SemiAnalytic,
};
use crate::hierarchy;
use crate::matrix::{Diagnostics, FormFactors, Reciprocity};
use crate::mesh::{PatchSet, Resolution};
use crate::output::{self, Exposure, FolderKind};
use crate::repair::{self, Repair, RepairReport};
use crate::scene::{Scene, Units};
use crate::solve::{self, Method, Options, SolveReport, System};
use crate::store;
use crate::visibility::Visibility;

pub mod distributed;

/// Which form-factor estimator to use.
#[derive(Clone, Debug, PartialEq)]
pub enum EstimatorChoice {
    /// Area-to-area Monte Carlo with stratified point pairs.
    AreaStratified {
        /// Strata per side per replicate.
        strata: usize,
        /// Replicates.
        replicates: usize,
    },
    /// Area-to-area Monte Carlo with independent uniform point pairs.
    AreaUniform {
        /// Points per replicate are `strata²`.
        strata: usize,
        /// Replicates.
        replicates: usize,
    },
    /// Area-to-area randomized QMC: Owen-scrambled Sobol point pairs.
    AreaSobol {
        /// Points per replicate are `strata²` (a power of 2 suits Sobol best).
        strata: usize,
        /// Replicates (independent scrambles).
        replicates: usize,
    },
    /// The hemicube: delta form factors of `res x res` cells, one ray per cell centre.
    Hemicube {
        /// Cells per side of the top face.
        res: usize,
    },
    /// Hemisphere shooting: cosine-weighted rays from each patch, first hits counted.
    Hemisphere {
        /// Rays per replicate are `strata²`.
        strata: usize,
        /// Replicates.
        replicates: usize,
    },
    /// Exact point-to-polygon factor integrated over the emitter, times ray visibility.
    SemiAnalytic {
        /// Points per side on the emitter (Gauss–Legendre or stratified).
        points: usize,
        /// Visibility rays per emitter point.
        rays: usize,
        /// Replicates.
        replicates: usize,
        /// Relative tolerance of the deterministic integral of unoccluded pairs.
        tol: f64,
    },
}

impl EstimatorChoice {
    /// Builds the estimator.
    pub fn build(&self) -> Box<dyn Estimator> {
        match *self {
            EstimatorChoice::AreaStratified { strata, replicates } => {
                Box::new(AreaMc::new(Pattern::Stratified, strata, replicates))
            }
            EstimatorChoice::AreaUniform { strata, replicates } => {
                Box::new(AreaMc::new(Pattern::Uniform, strata, replicates))
            }
            EstimatorChoice::AreaSobol { strata, replicates } => {
                Box::new(AreaMc::new(Pattern::Sobol, strata, replicates))
            }
            EstimatorChoice::Hemicube { res } => Box::new(Hemicube { res }),
            EstimatorChoice::Hemisphere { strata, replicates } => {
                Box::new(Hemisphere { strata, replicates })
            }
            EstimatorChoice::SemiAnalytic {
                points,
                rays,
                replicates,
                tol,
            } => Box::new(SemiAnalytic::new(Nodes::Gauss, points, rays, replicates).with_tol(tol)),
        }
    }
}

/// Everything a bake needs, resolved.
#[derive(Clone, Debug)]
pub struct BakeConfig {
    /// Built-in scene name or OBJ path.
    pub scene: String,
    /// Output folder.
    pub out_dir: PathBuf,
    /// Patch resolution.
    pub resolution: Resolution,
    /// Form-factor estimator.
    pub estimator: EstimatorChoice,
    /// Seed of all random streams.
    pub seed: u64,
    /// Solver.
    pub method: Method,
    /// Solver options.
    pub solve: Options,
    /// Preview size in pixels.
    pub preview: (u32, u32),
    /// Preview exposure.
    pub exposure: Exposure,
    /// Crease angle (degrees) for per-vertex averaging.
    pub crease_deg: f32,
    /// Reuse the form factors stored in this folder instead of casting rays.
    pub factors: Option<PathBuf>,
    /// Progressive-refinement steps after which to write `preview-step-NNNN.png` (with the
    /// ambient term, as in the notes' real example); empty for none.
    pub steps: Vec<usize>,
    /// Physical constraints to restore in the form factors before solving.
    pub repair: Repair,
    /// Which stored pairs the diagnostics check for reciprocity.
    pub reciprocity: Reciprocity,
    /// Solve hierarchically with these settings instead of on the flat patch matrix
    /// ([`crate::hierarchy`]); `resolution` then sets the root patches.
    pub hierarchy: Option<hierarchy::Settings>,
    /// With `hierarchy` chosen by default rather than asked for: the flat bake's
    /// resolution, to bake with instead (and say so) where the scene has faces the
    /// hierarchy does not support (two-sided, or a closed room's faces pointing out).
    pub fallback: Option<Resolution>,
    /// Memory the run may plan to use, in bytes (`None`: what the system has available);
    /// a larger estimate is refused before any work ([`crate::budget`]).
    pub max_memory: Option<u64>,
    /// Preview camera over the scene's `#@camera` (or the framing one).
    pub camera: Option<crate::scene::Camera>,
    /// Length unit of the scene's coordinates, over its `#@units` line: `mesh.glb` is
    /// scaled by it to metres (none at all: the coordinates are taken as metres).
    pub units: Option<Units>,
    /// Every face two-sided ([`Scene::make_two_sided`]), over the MTL's `#@two-sided`
    /// materials.
    pub two_sided: bool,
    /// Also write a lightmap of this many texels a side per object and side, in the OBJ's
    /// texture coordinates ([`output::lightmap`]); every face must have them.
    pub lightmap: Option<usize>,
}

impl Default for BakeConfig {
    fn default() -> Self {
        BakeConfig {
            scene: "cornell".into(),
            out_dir: PathBuf::from("out"),
            resolution: Resolution::Patches(1000),
            estimator: EstimatorChoice::SemiAnalytic {
                points: 3,
                rays: 2,
                replicates: 4,
                tol: SemiAnalytic::DEFAULT_TOL,
            },
            seed: 1,
            method: Method::default(),
            solve: Options::default(),
            preview: (512, 512),
            exposure: Exposure::Auto,
            crease_deg: 30.0,
            factors: None,
            steps: Vec::new(),
            repair: Repair::None,
            reciprocity: Reciprocity::Auto,
            hierarchy: None,
            fallback: None,
            max_memory: None,
            camera: None,
            units: None,
            two_sided: false,
            lightmap: None,
        }
    }
}

/// Hears about the pipeline's progress.
pub trait Observer: Sync {
    /// Something the user should know now, found before the expensive work (it is also in
    /// the run's summary).
    fn warn(&self, _msg: &str) {}
    /// A stage begins; `total` units of work (0 when unknown).
    fn begin(&self, _stage: &str, _total: u64) {}
    /// `done` units of the current stage are finished.
    fn advance(&self, _done: u64) {}
    /// The stage ended after `seconds`.
    fn end(&self, _stage: &str, _seconds: f64) {}
}

/// An observer that ignores everything.
pub struct Quiet;
impl Observer for Quiet {}

/// Time of one stage.
#[derive(Clone, Debug)]
pub struct StageTime {
    /// Stage name.
    pub stage: &'static str,
    /// Wall-clock seconds.
    pub seconds: f64,
}

/// What a bake did, for the summary screen.
#[derive(Clone, Debug)]
pub struct BakeSummary {
    /// Scene name.
    pub scene: String,
    /// Patches.
    pub patches: usize,
    /// Triangles traced against.
    pub triangles: usize,
    /// Output vertices.
    pub vertices: usize,
    /// Rays cast for form factors.
    pub rays: u64,
    /// Estimator name.
    pub estimator: String,
    /// Form-factor diagnostics.
    pub diagnostics: Diagnostics,
    /// Bounds found (rows over 1, entries out of range) and the repair applied.
    pub repair: RepairReport,
    /// Solver report.
    pub solve: SolveReport,
    /// Time per stage.
    pub stages: Vec<StageTime>,
    /// Peak resident memory in bytes (0 when unknown).
    pub peak_memory: u64,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Loader warnings.
    pub warnings: Vec<String>,
    /// Embree version in use.
    pub embree: String,
    /// What the hierarchical solution did (hierarchical bakes only).
    pub hierarchy: Option<hierarchy::Report>,
    /// What each rank did, for a bake on several ranks (empty for one process).
    pub ranks: Vec<RankReport>,
}

impl BakeSummary {
    /// Seconds of the form-factor stage.
    pub fn stage_seconds(&self, stage: &str) -> f64 {
        self.stages
            .iter()
            .filter(|s| s.stage == stage)
            .map(|s| s.seconds)
            .sum()
    }
}

/// Peak resident set size of this process (Linux `VmHWM`), in bytes.
pub fn peak_memory() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<u64>().ok())
            })
        })
        .map(|kb| kb * 1024)
        .unwrap_or(0)
}

struct Timer<'a> {
    obs: &'a dyn Observer,
    stages: Vec<StageTime>,
}

impl Timer<'_> {
    fn run<T>(&mut self, stage: &'static str, total: u64, f: impl FnOnce() -> T) -> T {
        self.obs.begin(stage, total);
        let t = Instant::now();
        let out = f();
        let seconds = t.elapsed().as_secs_f64();
        self.obs.end(stage, seconds);
        self.stages.push(StageTime { stage, seconds });
        out
    }
}

/// Refuses a run whose memory estimate ([`budget::Estimate`]) exceeds `max_memory` (or
/// the available memory), before the scene is meshed: `estimator` is `None` when the form
/// factors are read from a folder, `preview` the preview size of a bake.
pub fn check_budget(
    scene: &Scene,
    resolution: Resolution,
    estimator: Option<&EstimatorChoice>,
    method: Option<Method>,
    preview: Option<(u32, u32)>,
    max_memory: Option<u64>,
) -> Result<()> {
    let per_row = match estimator {
        None => 0,
        Some(EstimatorChoice::Hemisphere { strata, replicates }) => {
            strata.saturating_mul(*strata).saturating_mul(*replicates)
        }
        Some(EstimatorChoice::Hemicube { res }) => res.saturating_mul(*res).saturating_mul(3),
        Some(_) => usize::MAX,
    };
    let pixels = preview.map_or(0, |(w, h)| w as u64 * h as u64);
    let estimate = |patches: usize| {
        let dense = method == Some(Method::Direct) && patches <= solve::DIRECT_MAX_PATCHES;
        budget::Estimate::new(patches, per_row, dense, pixels)
    };
    let patches = crate::mesh::expected_patches(scene, resolution).max(scene.faces.len());
    budget::check(&estimate(patches), max_memory, estimate)
}

/// Share of the patches that may see nothing before a bake warns about normals.
const BLIND_SHARE: f64 = 0.1;

/// Loads a scene by name or path ([`Scene::load`], which makes the faces of `#@two-sided`
/// materials two-sided), makes every face two-sided when `two_sided`, and then raises
/// the faces (sides) that lie on other faces facing the same way
/// ([`Scene::raise_coincident`]).
pub fn load_scene(name: &str, two_sided: bool) -> Result<Scene> {
    let mut scene = Scene::load(name)?;
    if two_sided {
        scene.make_two_sided(true);
    }
    scene.raise_coincident();
    Ok(scene)
}

/// The checks every run makes on a loaded scene before the expensive work: a closed room
/// whose faces point out ([`Scene::inside_out_warning`]) is warned about now, through
/// `obs`, and the warning is returned for the summary.
fn early_warnings(scene: &Scene, obs: &dyn Observer) -> Vec<String> {
    let w: Vec<String> = scene.inside_out_warning().into_iter().collect();
    for m in &w {
        obs.warn(m);
    }
    w
}

/// Patches that see nothing (`row_sum` exactly 0) and whose other side, when they have
/// one, sees nothing either: the back of a two-sided wall facing out of a room sees
/// nothing, but its front does, and the surface is fine.
fn blind_patches(patches: &PatchSet, ff: &FormFactors) -> usize {
    let empty: Vec<bool> = (0..ff.len()).map(|i| ff.row_is_empty(i)).collect();
    (0..ff.len())
        .filter(|&i| empty[i] && patches.twin_of(i).is_none_or(|t| empty[t]))
        .count()
}

/// A warning, with the likely cause and its fix, when at least [`BLIND_SHARE`] of the
/// `n` patches see nothing (`empty` of them, counted by [`blind_patches`]): surfaces emit
/// and receive only on the side their counter-clockwise winding faces, and a closed room
/// modelled as a box with normals out (Blender's default cube) sees nothing from inside.
fn blind_warning(empty: usize, n: usize) -> Option<String> {
    (empty > 0 && empty as f64 >= BLIND_SHARE * n as f64).then(|| {
        format!(
            "{empty} of {n} patches ({:.0}%) see nothing: their fronts face away from the \
             rest of the scene. Faces emit and receive only on the side their \
             counter-clockwise winding faces; if walls were modelled with normals pointing \
             out of the room, bake with --two-sided (or `#@two-sided` in their material) \
             or flip them (Blender: Mesh > Normals > Flip, then export again)",
            100.0 * empty as f64 / n as f64
        )
    })
}

/// Reads a stored factors folder for `patches` ([`store::read`]) and refuses it when a
/// row is over 1 beyond chance and `repair` does not restore row sums ([`check_rows`]):
/// every consumer of stored factors (bake, thermal) goes through here.
fn read_factors(dir: &Path, patches: &PatchSet, repair: Repair) -> Result<FormFactors> {
    let (ff, matrix) = store::read_located(dir, patches)?;
    check_rows(&matrix, &ff, repair)?;
    Ok(ff)
}

/// Refuses stored factors with a row over 1 by more than its bar allows
/// ([`FormFactors::row_over_one_beyond_chance`]), unless `repair` restores the row sums.
/// `matrix` is the file the matrix was read from.
fn check_rows(matrix: &Path, ff: &FormFactors, repair: Repair) -> Result<()> {
    if matches!(repair, Repair::Closure | Repair::Both) {
        return Ok(());
    }
    let Some(r) = ff.row_over_one_beyond_chance() else {
        return Ok(());
    };
    let bar = crate::matrix::Bar {
        se: r.se,
        bound: r.bound,
    };
    let by = if r.se > 0.0 {
        format!(
            "{:.1} standard errors beyond its bound of {:.1e} ({:.1} allowed by chance over {} \
             rows at a false-alarm rate of {:.0e}, {:.0} degrees of freedom)",
            (r.sum - 1.0 - r.bound) / r.se,
            r.bound,
            r.k,
            ff.len(),
            crate::matrix::ROW_ALARM,
            r.dof
        )
    } else if r.bound > 0.0 {
        format!(
            "more than its bound ({:.1e}, the entries' bounds added)",
            r.bound
        )
    } else {
        String::from("more than rounding, with no error bar")
    };
    Err(Error::Mismatch {
        path: matrix.to_path_buf(),
        msg: format!(
            "row {} of the matrix (patch {}) sums to {:.6} {}, over 1 by {by}: no physical row \
             sums over 1; bake with --repair closure (or both) to restore the row sums, or \
             recompute the factors with more samples",
            r.row + 1,
            r.row,
            r.sum,
            bar
        ),
    })
}

/// The form factors of a run, as [`factors_of`] returns them.
struct Factors {
    ff: FormFactors,
    /// The Embree version used ("not used" when read).
    embree: String,
    repair: RepairReport,
    /// What each rank did, for a distributed run (empty for one process).
    ranks: Vec<RankReport>,
}

/// The form factors of a run: read from the folder `stored` when given (refused there
/// when a row is over 1 beyond chance, see [`read_factors`]), else computed by the
/// estimator with the seed (shared between the ranks of `cluster` and gathered on rank 0,
/// [`distributed::form_factors_root`]); then repaired as `repair` says. `None` on the
/// ranks other than 0.
fn factors_of(
    patches: &PatchSet,
    stored: Option<&Path>,
    (estimator, seed): (&EstimatorChoice, u64),
    repair: Repair,
    timer: &mut Timer,
    cluster: &dyn Cluster,
) -> Result<Option<Factors>> {
    let (ff, embree, ranks) = match stored {
        Some(dir) => (
            timer.run("read factors", 0, || read_factors(dir, patches, repair))?,
            String::from("not used"),
            Vec::new(),
        ),
        None if cluster.size() > 1 => {
            let (ff, stages, embree, ranks) =
                distributed::form_factors_root(patches, estimator, seed, timer.obs, cluster)?;
            timer.stages.extend(stages);
            let Some(ff) = ff else {
                return Ok(None);
            };
            (ff, embree, ranks)
        }
        None => {
            let (ff, stages, embree) = form_factors(patches, estimator, seed, timer.obs)?;
            timer.stages.extend(stages);
            (ff, embree, Vec::new())
        }
    };
    let (ff, repair) = timer.run("repair", 0, || repair::apply(ff, repair));
    Ok(Some(Factors {
        ff,
        embree,
        repair,
        ranks,
    }))
}

/// Computes the form factors of a patch set (builds the BVH as its own stage).
pub fn form_factors(
    patches: &PatchSet,
    estimator: &EstimatorChoice,
    seed: u64,
    obs: &dyn Observer,
) -> Result<(FormFactors, Vec<StageTime>, String)> {
    let mut timer = Timer {
        obs,
        stages: Vec::new(),
    };
    let vis = timer.run("bvh", 0, || Visibility::new(patches))?;
    let embree = vis.embree_version();
    let est = estimator.build();
    let ctx = Context {
        patches,
        vis: &vis,
        seed,
    };
    let ff = timer.run("form factors", patches.len() as u64, || {
        formfactor::compute(&ctx, est.as_ref(), &|d| obs.advance(d))
    });
    Ok((ff, timer.stages, embree))
}

/// Solves for patch radiosity.
///
/// `opts.max_iterations` is read as a command-line cap and scaled per method by
/// [`Method::iteration_cap`] (progressive refinement gets `max_iterations * patches` shots).
/// When some row has `rho_i * sum_j F_ij >= 1` (Monte Carlo noise in a closed scene with high
/// reflectances), those rows are scaled to sum to 1 first ([`crate::matrix::repair_row_sums`])
/// so that the solve stays bounded, and the report's notes say so.
pub fn solve_radiosity(
    patches: &PatchSet,
    ff: &FormFactors,
    method: Method,
    opts: &Options,
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    let rho: Vec<[f64; 3]> = (0..patches.len()).map(|i| patches.rho(i)).collect();
    let emit: Vec<[f64; 3]> = (0..patches.len()).map(|i| patches.emit(i)).collect();
    let repaired = crate::matrix::repair_row_sums(&ff.f, &rho);
    let f = repaired.as_ref().map_or(&ff.f, |r| &r.0);
    let sys = System::new(f, &rho, &emit, &patches.area)?;
    let opts = Options {
        max_iterations: method.iteration_cap(opts.max_iterations, patches.len()),
        ..*opts
    };
    let (b, mut report) = solve::solve(method, &sys, &opts)?;
    if let Some((_, rep)) = &repaired {
        report.notes.insert(
            0,
            format!(
                "{} rows of F had rho * (row sum) >= 1 (worst {:.4} at patch {}, row sum {:.4}, \
                 row-sum bar {}) and were scaled to sum to 1, so that the solve stays \
                 bounded: raise the samples if this is more than noise",
                rep.rows.len(),
                rep.worst_gain,
                rep.worst.0,
                rep.worst.1,
                ff.row_sum_bar(rep.worst.0)
            ),
        );
    }
    Ok((b, report))
}

/// Writes `preview-step-NNNN.png` in `dir` for each of `steps` progressive-refinement steps,
/// with the ambient term ([`solve::progressive_steps`]), rows repaired as in
/// [`solve_radiosity`]. All steps share `exposure` (the bake passes the final preview's), so
/// that they can be compared.
pub fn write_step_previews(
    patches: &PatchSet,
    ff: &FormFactors,
    steps: &[usize],
    cfg: &BakeConfig,
    dir: &Path,
    camera: &crate::scene::Camera,
    exposure: Exposure,
) -> Result<Vec<PathBuf>> {
    let rho: Vec<[f64; 3]> = (0..patches.len()).map(|i| patches.rho(i)).collect();
    let emit: Vec<[f64; 3]> = (0..patches.len()).map(|i| patches.emit(i)).collect();
    let repaired = crate::matrix::repair_row_sums(&ff.f, &rho);
    let f = repaired.as_ref().map_or(&ff.f, |r| &r.0);
    let sys = System::new(f, &rho, &emit, &patches.area)?;
    let mut files = Vec::new();
    for (k, b) in solve::progressive_steps(&sys, steps)? {
        let verts = output::interpolate(patches, &b, cfg.crease_deg);
        let (w, h) = cfg.preview;
        let image = output::render_preview(&verts, camera, w, h, exposure);
        let png = dir.join(format!("preview-step-{k:04}.png"));
        output::write_png(&png, &image)?;
        files.push(png);
    }
    Ok(files)
}

/// Runs the whole bake and writes `radiosity.exr`, `mesh.ply`, `mesh.glb` and
/// `preview.png`.
pub fn bake(cfg: &BakeConfig, obs: &dyn Observer) -> Result<BakeSummary> {
    let s = bake_gathered(cfg, obs, &Single)?;
    Ok(s.expect("one process is rank 0"))
}

/// The bake of one process, or of the ranks of `cluster` with the form factors gathered
/// on rank 0, which goes on alone ([`distributed::bake_on`]); `None` on the other ranks.
fn bake_gathered(
    cfg: &BakeConfig,
    obs: &dyn Observer,
    cluster: &dyn Cluster,
) -> Result<Option<BakeSummary>> {
    let mut timer = Timer {
        obs,
        stages: Vec::new(),
    };
    if cluster.is_root() {
        output::check_folder(&cfg.out_dir, FolderKind::Bake)?;
    }
    let scene = timer.run("load", 0, || load_scene(&cfg.scene, cfg.two_sided))?;
    scene.require_emitter()?;
    let mut early = match cfg.lightmap {
        Some(res) => output::lightmap::check(&scene, res)?,
        None => Vec::new(),
    };
    // A scene the default hierarchy cannot bake is baked flat, and the summary says why.
    let flat;
    let checked = match cfg.hierarchy {
        Some(_) => check_hierarchical(&scene),
        None => Ok(()),
    };
    let cfg = match (checked, cfg.fallback) {
        (Err(Error::Config(why)), Some(resolution)) => {
            early.push(format!(
                "baked with the flat method (uniform patches), as the default hierarchical \
                 method cannot bake this scene: {why}"
            ));
            flat = BakeConfig {
                hierarchy: None,
                fallback: None,
                resolution,
                ..cfg.clone()
            };
            &flat
        }
        (Err(e), _) => return Err(e),
        (Ok(()), _) => cfg,
    };
    for w in &early {
        obs.warn(w);
    }
    early.extend(early_warnings(&scene, obs));
    if let Some(h) = &cfg.hierarchy {
        // The roots and the preview, before they are meshed (the hierarchy checks its own
        // links and gather against the memory as it goes).
        check_budget(
            &scene,
            cfg.resolution,
            None,
            None,
            Some(cfg.preview),
            cfg.max_memory,
        )
        .map_err(|e| match e {
            Error::Config(m) => Error::Config(format!(
                "{m} (an estimate for the hierarchy's root patches alone: its elements and \
                 links need more, and are checked as they grow)"
            )),
            e => e,
        })?;
        return bake_hierarchical(cfg, h, scene, early, timer).map(Some);
    }
    check_budget(
        &scene,
        cfg.resolution,
        cfg.factors.is_none().then_some(&cfg.estimator),
        Some(cfg.method),
        Some(cfg.preview),
        cfg.max_memory,
    )?;
    let patches = timer.run("mesh", 0, || PatchSet::build(&scene, cfg.resolution))?;
    if cfg.method == Method::Direct {
        // Known now, not only after the form factors.
        solve::direct::check_size(patches.len())?;
    }
    let Some(Factors {
        ff,
        embree,
        repair: repair_report,
        ranks,
    }) = factors_of(
        &patches,
        cfg.factors.as_deref(),
        (&cfg.estimator, cfg.seed),
        cfg.repair,
        &mut timer,
        cluster,
    )?
    else {
        return Ok(None);
    };
    // Side by side: the diagnostics are parallel reads of the matrix, and the default
    // solver's sweeps (Gauss-Seidel) are sequential, leaving the other cores idle.
    let (solved, diagnostics) = timer.run("solve and diagnostics", 0, || {
        rayon::join(
            || solve_radiosity(&patches, &ff, cfg.method, &cfg.solve),
            || ff.diagnostics_with(cfg.reciprocity),
        )
    });
    let (b, report) = solved?;
    check_storable(&scene, &b)?;
    let verts = timer.run("per-vertex", 0, || {
        output::interpolate(&patches, &b, cfg.crease_deg)
    });
    let (files, late) = timer.run("write", 0, || -> Result<(Vec<PathBuf>, Vec<String>)> {
        write_bake(cfg, &scene, &patches, &verts, |dir, camera, exposure| {
            if cfg.steps.is_empty() {
                return Ok(Vec::new());
            }
            write_step_previews(
                &patches,
                &ff,
                &cfg.steps,
                cfg,
                dir,
                camera,
                Exposure::Fixed(exposure),
            )
        })
    })?;
    Ok(Some(BakeSummary {
        scene: scene.name.clone(),
        patches: patches.len(),
        triangles: patches.triangles.len(),
        vertices: verts.positions.len(),
        rays: ff.rays,
        estimator: ff.estimator.clone(),
        diagnostics,
        repair: repair_report,
        solve: report,
        stages: timer.stages,
        peak_memory: peak_memory(),
        files,
        warnings: scene
            .warnings
            .iter()
            .cloned()
            .chain(early.iter().cloned())
            .chain(
                blind_warning(blind_patches(&patches, &ff), patches.len())
                    .filter(|_| !early.iter().any(|w| w.contains("point out of it"))),
            )
            .chain(late)
            .collect(),
        embree,
        hierarchy: None,
        ranks,
    }))
}

/// Refuses, before any work, what the hierarchical method does not support: two-sided
/// faces (its contact and burial tests take a face's back for the inside of a solid, and
/// the two sides of a two-sided face lie on each other), and so a closed room whose faces
/// point out ([`Scene::inside_out_warning`]): the flat method's remedy, `--two-sided`, is
/// not open here, and the bake would come out unlit.
fn check_hierarchical(scene: &Scene) -> Result<()> {
    if scene.inside_out_warning().is_some() {
        return Err(Error::Config(format!(
            "`{}` looks like a closed room whose faces point out of it (rays from the centre \
             of its bounds leave through the back of its outermost faces), and faces emit \
             and receive only on their front, so a hierarchical bake would see nothing from \
             inside. --method hierarchical does not support two-sided faces: flip the \
             normals (Blender: Mesh > Normals > Flip, then export again), or bake with \
             --method flat --two-sided",
            scene.source
        )));
    }
    if let Some(f) = scene.faces.iter().find(|f| f.is_two_sided()) {
        let m = &scene.materials[f.material as usize];
        let why = if m.two_sided {
            format!("material `{}` is `#@two-sided`", m.name)
        } else {
            "--two-sided was given".to_string()
        };
        return Err(Error::Config(format!(
            "--method hierarchical does not support two-sided faces ({why}, line {} of {}): \
             bake them with --method flat, or make the faces one-sided (drop --two-sided, \
             or flip the normals of walls that face out of the room)",
            f.line, scene.source
        )));
    }
    Ok(())
}

/// Writes `radiosity.exr`, `preview.png`, `mesh.ply` and `mesh.glb` of a bake (`patches`
/// are the ones `verts` was made from: they name each triangle's object), and what
/// `extra` writes into the same folder (given the folder, the camera and the preview's
/// exposure), as one folder ([`output::write_folder`]); returns the files' final paths.
fn write_bake(
    cfg: &BakeConfig,
    scene: &Scene,
    patches: &PatchSet,
    verts: &output::VertexRadiosity,
    extra: impl FnOnce(&std::path::Path, &crate::scene::Camera, f32) -> Result<Vec<PathBuf>>,
) -> Result<(Vec<PathBuf>, Vec<String>)> {
    let mut warnings = Vec::new();
    let names = output::write_folder(&cfg.out_dir, FolderKind::Bake, |dir| {
        output::write_exr(&dir.join("radiosity.exr"), verts, &scene.name)?;
        let camera = cfg.camera.unwrap_or_else(|| scene.camera_or_framing());
        let (w, h) = cfg.preview;
        let image = output::render_preview(verts, &camera, w, h, cfg.exposure);
        output::write_png(&dir.join("preview.png"), &image)?;
        let units = cfg.units.or(scene.units);
        output::write_ply(&dir.join("mesh.ply"), verts, image.exposure, units)?;
        let of_triangle: Vec<u32> = verts
            .patch_of_triangle
            .iter()
            .map(|&p| patches.object[p as usize])
            .collect();
        let unit_name = units.map_or("not given: taken as m", Units::symbol);
        output::write_glb(
            &dir.join("mesh.glb"),
            verts,
            output::Objects {
                names: &patches.objects,
                of_triangle: &of_triangle,
            },
            &output::GlbSettings {
                scene: &scene.name,
                metres_per_unit: units.map_or(1.0, Units::metres),
                units: unit_name,
                exposure: image.exposure,
            },
        )?;
        let mut names: Vec<PathBuf> = vec![
            "radiosity.exr".into(),
            "mesh.ply".into(),
            "mesh.glb".into(),
            "preview.png".into(),
        ];
        if let Some(res) = cfg.lightmap {
            let (files, w) =
                output::lightmap::write_all(dir, scene, patches, verts, res, image.exposure)?;
            names.extend(files.into_iter().map(PathBuf::from));
            warnings = w;
        }
        let more = extra(dir, &camera, image.exposure)?;
        names.extend(more.iter().filter_map(|p| p.file_name()).map(PathBuf::from));
        Ok(names)
    })?;
    Ok((
        names.iter().map(|n| cfg.out_dir.join(n)).collect(),
        warnings,
    ))
}

/// The hierarchical bake after loading: root patches, BVH, refine-and-solve passes, the
/// leaf mesh, per-vertex values, files.
fn bake_hierarchical(
    cfg: &BakeConfig,
    settings: &hierarchy::Settings,
    scene: Scene,
    early: Vec<String>,
    mut timer: Timer,
) -> Result<BakeSummary> {
    settings.validate()?;
    let obs = timer.obs;
    let patches = timer.run("mesh", 0, || PatchSet::build(&scene, cfg.resolution))?;
    let vis = timer.run("bvh", 0, || Visibility::new(&patches))?;
    let embree = vis.raw().version();
    let total = settings.max_passes as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let sol = timer.run("hierarchy", total, || {
        hierarchy::run(&patches, &vis, settings, &|_| {
            let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            obs.advance(d);
        })
    })?;
    let (leaves, b, _) = hierarchy::leaves::leaf_mesh(&sol.elements, &patches, &sol.state.b);
    if let Some(k) = b.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
        return Err(Error::Scene {
            scene: scene.source.clone(),
            msg: format!("the solve produced a non-finite radiosity at leaf {k}"),
        });
    }
    let verts = timer.run("per-vertex", 0, || {
        output::interpolate_with(&leaves, &b, cfg.crease_deg, output::Nodal::Linear)
    });
    let (files, late) = timer.run("write", 0, || {
        write_bake(cfg, &scene, &leaves, &verts, |_, _, _| Ok(Vec::new()))
    })?;
    let r = sol.report;
    let last = r.passes.last().copied().unwrap_or_default();
    let solve = SolveReport {
        solver: "hierarchical (gather, push-pull)".into(),
        iterations: r.passes.iter().map(|p| p.solve.iterations).sum(),
        residual: last.solve.change,
        patch_residual: last.solve.change,
        history: Vec::new(),
        seconds: r.passes.iter().map(|p| p.solve_seconds).sum(),
        converged: last.solve.converged,
        notes: r.notes.clone(),
        relaxation: None,
        coarse: 0,
    };
    Ok(BakeSummary {
        scene: scene.name.clone(),
        patches: r.leaves,
        triangles: leaves.triangles.len(),
        vertices: verts.positions.len(),
        rays: r.rays,
        estimator: format!(
            "hierarchical(error={:e}, min-area={:.3e}, link rays={}x{})",
            settings.error, r.min_area, settings.rays, settings.rays
        ),
        diagnostics: Diagnostics::default(),
        repair: RepairReport::default(),
        solve,
        stages: timer.stages,
        peak_memory: peak_memory(),
        files,
        warnings: scene
            .warnings
            .iter()
            .cloned()
            .chain(early)
            .chain(late)
            .collect(),
        embree,
        hierarchy: Some(r),
        ranks: Vec::new(),
    })
}

/// What `factors` did.
#[derive(Clone, Debug)]
pub struct FactorsSummary {
    /// The stored provenance.
    pub provenance: store::Provenance,
    /// Form-factor diagnostics.
    pub diagnostics: Diagnostics,
    /// Bounds found and the repair applied.
    pub repair: RepairReport,
    /// Time per stage.
    pub stages: Vec<StageTime>,
    /// Peak resident memory in bytes.
    pub peak_memory: u64,
    /// Warnings about the scene (a closed room whose faces point out).
    pub warnings: Vec<String>,
    /// What each rank did, for factors computed on several ranks (empty for one process).
    pub ranks: Vec<RankReport>,
}

/// Computes form factors for a scene and stores them in `out_dir` (see [`store`]), within
/// the available memory, in the default layout ([`store::Format::Auto`]).
pub fn factors(
    scene: &str,
    resolution: Resolution,
    estimator: &EstimatorChoice,
    seed: u64,
    out_dir: &std::path::Path,
    repair: Repair,
    obs: &dyn Observer,
) -> Result<FactorsSummary> {
    factors_within(
        scene,
        resolution,
        estimator,
        seed,
        out_dir,
        repair,
        store::Format::Auto,
        None,
        false,
        obs,
    )
}

/// [`factors`] in the layout `format`, with a memory limit in bytes (`None`: the available
/// memory) checked by [`check_budget`] before any work.
#[allow(clippy::too_many_arguments)]
pub fn factors_within(
    scene: &str,
    resolution: Resolution,
    estimator: &EstimatorChoice,
    seed: u64,
    out_dir: &std::path::Path,
    repair: Repair,
    format: store::Format,
    max_memory: Option<u64>,
    two_sided: bool,
    obs: &dyn Observer,
) -> Result<FactorsSummary> {
    let job = FactorsJob {
        scene,
        resolution,
        estimator,
        seed,
        out_dir,
        repair,
        reciprocity: Reciprocity::Auto,
        format,
        max_memory,
        two_sided,
    };
    let s = factors_on(&job, obs, &Single)?;
    Ok(s.expect("one process is rank 0"))
}

/// What `radiosity factors` is asked to do ([`factors_within`], [`factors_on`]).
#[derive(Clone, Copy, Debug)]
pub struct FactorsJob<'a> {
    /// Built-in scene name or OBJ path.
    pub scene: &'a str,
    /// Patch resolution.
    pub resolution: Resolution,
    /// Estimator.
    pub estimator: &'a EstimatorChoice,
    /// Seed of the random streams.
    pub seed: u64,
    /// The folder to write.
    pub out_dir: &'a Path,
    /// Repair after estimation.
    pub repair: Repair,
    /// Which stored pairs the diagnostics check for reciprocity.
    pub reciprocity: Reciprocity,
    /// Matrix layout.
    pub format: store::Format,
    /// Memory limit in bytes (`None`: the available memory).
    pub max_memory: Option<u64>,
    /// Every face two-sided (`--two-sided`).
    pub two_sided: bool,
}

/// [`factors_within`] on the ranks of `cluster`: every rank loads the scene and builds
/// its own BVH, the rows are shared between the ranks and gathered on rank 0
/// ([`distributed::form_factors_root`]), which repairs, checks and writes the folder:
/// the files one process writes, bit for bit. `None` on the other ranks.
pub fn factors_on(
    job: &FactorsJob,
    obs: &dyn Observer,
    cluster: &dyn Cluster,
) -> Result<Option<FactorsSummary>> {
    let mut timer = Timer {
        obs,
        stages: Vec::new(),
    };
    if cluster.is_root() {
        output::check_folder(job.out_dir, FolderKind::Factors)?;
    }
    let scene = timer.run("load", 0, || load_scene(job.scene, job.two_sided))?;
    let warnings = if cluster.is_root() {
        early_warnings(&scene, obs)
    } else {
        Vec::new()
    };
    check_budget(
        &scene,
        job.resolution,
        Some(job.estimator),
        None,
        None,
        job.max_memory,
    )?;
    let patches = timer.run("mesh", 0, || PatchSet::build(&scene, job.resolution))?;
    let Some(Factors {
        ff,
        repair: repair_report,
        ranks,
        ..
    }) = factors_of(
        &patches,
        None,
        (job.estimator, job.seed),
        job.repair,
        &mut timer,
        cluster,
    )?
    else {
        return Ok(None);
    };
    // Side by side: the diagnostics are parallel arithmetic over the matrix, the write
    // (three large files, then their hashes) leaves cores idle while a file finishes.
    let (diagnostics, provenance) = timer.run("diagnostics and write", 0, || {
        rayon::join(
            || ff.diagnostics_with(job.reciprocity),
            || store::write(job.out_dir, &patches, &ff, job.repair, job.format),
        )
    });
    let provenance = provenance?;
    // The loader's warnings, then one about the normals (the early one, or else the
    // blind patches': they tell the same thing).
    let normals = warnings
        .into_iter()
        .chain(blind_warning(blind_patches(&patches, &ff), patches.len()))
        .take(1);
    let warnings = scene.warnings.iter().cloned().chain(normals).collect();
    Ok(Some(FactorsSummary {
        provenance,
        diagnostics,
        repair: repair_report,
        stages: timer.stages,
        peak_memory: peak_memory(),
        warnings,
        ranks,
    }))
}

pub use crate::solve::mib;

/// `time: STAGE SECONDS, ..., total SECONDS; peak memory MIB`: the last line of a summary.
pub fn format_times(stages: &[StageTime], peak_memory: u64) -> String {
    use std::fmt::Write;
    let mut o = String::from("time:");
    for t in stages {
        let _ = write!(o, " {} {:.2}s,", t.stage, t.seconds);
    }
    let total: f64 = stages.iter().map(|t| t.seconds).sum();
    let _ = write!(o, " total {total:.2}s; peak memory {}", mib(peak_memory));
    o
}

/// The one-screen summary printed after a bake.
pub fn format_summary(s: &BakeSummary) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let ff_s = s.stage_seconds("form factors");
    if let Some(h) = &s.hierarchy {
        format_hierarchy(&mut o, s, h);
        return o;
    }
    let _ = writeln!(
        o,
        "baked `{}`: {} patches, {} triangles, {} vertices",
        s.scene, s.patches, s.triangles, s.vertices
    );
    if ff_s > 0.0 {
        let _ = writeln!(
            o,
            "form factors: {} ({} rays, {:.2} Mrays/s, Embree {})",
            s.estimator,
            s.rays,
            s.rays as f64 / ff_s / 1e6,
            s.embree
        );
    } else {
        let _ = writeln!(
            o,
            "form factors: {}, read from the stored folder (no rays cast now; {} when \
             they were computed)",
            s.estimator, s.rays
        );
    }
    let d = &s.diagnostics;
    let _ = writeln!(
        o,
        "  row sums in [{:.5}, {:.5}] (row-sum bar <= {}); {} rows over 1 beyond 3 std. errors plus bounds; {} patches see nothing",
        d.min_row_sum.max(0.0),
        d.max_row_sum,
        d.max_row_sum_bar,
        d.rows_over_one,
        d.empty_rows
    );
    let _ = writeln!(
        o,
        "  reciprocity{}: worst relative gap {:.1e} over factors >= {:.0e}, {:.2}% of pairs beyond 3 std. errors; {} stored factors{}",
        d.reciprocity_scope(s.patches),
        d.reciprocity_significant,
        crate::matrix::SIGNIFICANT,
        100.0 * d.reciprocity_beyond_3se,
        d.nnz,
        if d.out_of_range > 0 { format!("; {} OUT OF [0, 1]", d.out_of_range) } else { String::new() }
    );
    let _ = writeln!(o, "  bounds: {}", s.repair.before.summary());
    if s.repair.repair != Repair::None {
        let _ = writeln!(
            o,
            "  repair {:?}: entries moved by <= {:.2} standard errors; after: {}",
            s.repair.repair,
            s.repair.max_shift_sigmas,
            s.repair.after.summary()
        );
    }
    let _ = writeln!(
        o,
        "solve: {}{} in {} iterations, relative residual {:.2e}, worst patch {:.2e}{}",
        s.solve.solver,
        relaxation_note(s.solve.relaxation, s.solve.coarse),
        s.solve.iterations,
        s.solve.residual,
        s.solve.patch_residual,
        if s.solve.converged {
            ""
        } else {
            " (NOT converged)"
        }
    );
    format_tail(&mut o, s);
    wrap(&o, WIDTH)
}

/// Width of the summaries, in columns.
pub const WIDTH: usize = 80;

/// Breaks every line of `text` longer than `width` columns at spaces, continuing with
/// four more spaces of indent than the line began with. A word longer than the width
/// (a path) stays whole on its own line.
pub fn wrap(text: &str, width: usize) -> String {
    let mut out = String::with_capacity(text.len() + text.len() / 16);
    for line in text.lines() {
        if line.chars().count() <= width {
            out.push_str(line);
            out.push('\n');
            continue;
        }
        let indent = line.len() - line.trim_start().len();
        let cont = " ".repeat(indent + 4);
        let mut col = 0;
        for (k, word) in line.split_whitespace().enumerate() {
            let len = word.chars().count();
            if k == 0 {
                out.push_str(&line[..indent]);
                col = indent;
            } else if col + 1 + len > width {
                out.push('\n');
                out.push_str(&cont);
                col = cont.len();
            } else {
                out.push(' ');
                col += 1;
            }
            out.push_str(word);
            col += len;
        }
        out.push('\n');
    }
    out
}

/// ` (omega 1.1)`, or ` (omega 1.1/1.1/1.08)` when the channels differ, for an
/// over-relaxed solve, with `, coarse correction over N aggregates` when it had one;
/// empty otherwise.
fn relaxation_note(omega: Option<[f64; 3]>, aggregates: usize) -> String {
    let coarse = if aggregates > 0 {
        format!(", coarse correction over {aggregates} aggregates")
    } else {
        String::new()
    };
    match omega {
        Some([r, g, b]) if r == g && g == b => format!(" (omega {r:.4}{coarse})"),
        Some([r, g, b]) => format!(" (omega {r:.4}/{g:.4}/{b:.4}{coarse})"),
        None => String::new(),
    }
}

/// The lines every bake summary ends with: notes, ranks, times, warnings, files.
fn format_tail(o: &mut String, s: &BakeSummary) {
    use std::fmt::Write;
    for n in &s.solve.notes {
        let _ = writeln!(o, "note: {n}");
    }
    o.push_str(&distributed::format_ranks(&s.ranks));
    let _ = writeln!(o, "{}", format_times(&s.stages, s.peak_memory));
    for w in &s.warnings {
        let _ = writeln!(o, "warning: {w}");
    }
    let _ = write!(o, "wrote:");
    for f in &s.files {
        let _ = write!(o, " {}", f.display());
    }
    o.push('\n');
}

/// The summary of a hierarchical bake.
fn format_hierarchy(o: &mut String, s: &BakeSummary, h: &hierarchy::Report) {
    use std::fmt::Write;
    let _ = writeln!(
        o,
        "baked `{}` hierarchically: {} roots -> {} elements, {} leaves ({} buried), {} triangles, {} vertices",
        s.scene, h.roots, h.elements, h.leaves, h.buried, s.triangles, s.vertices
    );
    let _ = writeln!(
        o,
        "  links: {} ({} partly visible; {} at the start), leaf gather entries {}{}, {} rays, {} point-factor evaluations, Embree {}",
        h.links,
        h.partial_links,
        h.initial_links,
        h.gather,
        if h.clusters > 0 {
            format!(" ({} from cluster links)", h.gather_from_clusters)
        } else {
            String::new()
        },
        h.rays,
        h.evals,
        s.embree
    );
    if h.clusters > 0 {
        let _ = writeln!(
            o,
            "  clusters: {} over the roots{}, {} cluster links at the end, {} node pairs examined",
            h.clusters,
            if h.auto_clusters {
                " (chosen by --clusters auto for this many roots)"
            } else {
                ""
            },
            h.cluster_links,
            h.cluster_pairs
        );
    }
    let _ = writeln!(
        o,
        "  start: contacts, buried leaves and cluster tree {:.2}s; {} initial links {:.2}s",
        h.prepare_seconds, h.initial_links, h.start_seconds
    );
    for (k, p) in h.passes.iter().enumerate() {
        let _ = writeln!(
            o,
            "  pass {}: {} links refined -> {} links, {} elements, {} rays; solve {} iterations (change {:.1e}); {:.2}s + {:.2}s{}",
            k + 1,
            p.refined,
            p.links,
            p.elements,
            p.rays,
            p.solve.iterations,
            p.solve.change,
            p.refine_seconds,
            p.solve_seconds,
            if p.gather_seconds > 0.0 {
                format!(" (of which the gather lists {:.2}s)", p.gather_seconds)
            } else {
                String::new()
            }
        );
    }
    let _ = writeln!(
        o,
        "  leaf factor sums: largest {:.6} {}; {} leaves over 1 beyond 3 standard errors plus bounds",
        h.max_row_sum.0, h.max_row_sum.1, h.rows_over_one
    );
    let lum = |c: [f64; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
    let (em, ab) = (lum(h.emitted), lum(h.absorbed));
    let _ = writeln!(
        o,
        "  estimated error per leaf (its factors' bars carried through the interreflections): max {:.2e}, mean {:.2e} of the mean radiosity {:.4e} (link tolerance {:.2e}); {} links at the minimum area {:.3e} still over it",
        h.max_error, h.mean_error, h.mean_radiosity, h.eps, h.unresolved, h.min_area
    );
    let _ = writeln!(
        o,
        "  power: emitted {:.6e}, absorbed {:.6e} ({:+.2e} relative: escaped or error)",
        em,
        ab,
        if em > 0.0 { (em - ab) / em } else { 0.0 }
    );
    format_tail(o, s);
    *o = wrap(o, WIDTH);
}

/// Everything a thermal run needs, resolved ([`thermal`]).
#[derive(Clone, Debug)]
pub struct ThermalConfig {
    /// Built-in scene name or OBJ path (its MTL may carry `#@thermal` lines).
    pub scene: String,
    /// Output folder.
    pub out_dir: PathBuf,
    /// Patch resolution.
    pub resolution: Resolution,
    /// Form-factor estimator (unused with `factors`).
    pub estimator: EstimatorChoice,
    /// Seed of the form factors' random streams and of the error-bar replicates.
    pub seed: u64,
    /// Reuse the form factors stored in this folder instead of casting rays.
    pub factors: Option<PathBuf>,
    /// Boundary-conditions file ([`crate::thermal::bc`]), applied over the MTL's.
    pub bc: Option<PathBuf>,
    /// Ambient (environment) temperature, K.
    pub ambient: f64,
    /// Solve with each surface (material) as one zone of uniform radiosity
    /// ([`crate::objects::lump`]) instead of patch by patch.
    pub zones: bool,
    /// Solver and error-bar settings.
    pub settings: crate::thermal::Settings,
    /// Physical constraints to restore in the form factors before solving.
    pub repair: Repair,
    /// Memory the run may plan to use, in bytes.
    pub max_memory: Option<u64>,
    /// Every face two-sided, over the MTL's `#@two-sided` materials.
    pub two_sided: bool,
}

impl Default for ThermalConfig {
    fn default() -> Self {
        let b = BakeConfig::default();
        ThermalConfig {
            scene: b.scene,
            out_dir: PathBuf::from("thermal"),
            resolution: b.resolution,
            estimator: b.estimator,
            seed: b.seed,
            factors: None,
            bc: None,
            ambient: 0.0,
            zones: false,
            settings: crate::thermal::Settings::default(),
            repair: Repair::None,
            max_memory: None,
            two_sided: false,
        }
    }
}

/// One surface of a thermal run, for the summary.
#[derive(Clone, Debug)]
pub struct ThermalSurface {
    /// Name, emissivity, condition, patches.
    pub info: output::thermal::SurfaceInfo,
    /// Results with their error bars.
    pub result: crate::thermal::SurfaceResult,
}

/// What a thermal run did.
#[derive(Clone, Debug)]
pub struct ThermalSummary {
    /// Scene name.
    pub scene: String,
    /// Patches.
    pub patches: usize,
    /// Unknowns of the solve (patches, or surfaces with `zones`).
    pub unknowns: usize,
    /// Estimator name (or that of the stored folder).
    pub estimator: String,
    /// Rays cast for form factors (0 when read from a folder).
    pub rays: u64,
    /// Form-factor diagnostics.
    pub diagnostics: Diagnostics,
    /// Bounds found and the repair applied.
    pub repair: RepairReport,
    /// Per surface (material), in material order.
    pub surfaces: Vec<ThermalSurface>,
    /// Every surface together.
    pub total: crate::thermal::SurfaceResult,
    /// Net power to the environment and its standard error, W.
    pub to_environment: (f64, f64),
    /// Ambient temperature, K.
    pub ambient: f64,
    /// Gauss–Seidel sweeps and final relative residual of the main solve.
    pub solve: (usize, f64),
    /// Largest |q| on adiabatic (flux 0) patches, W/m², when there are any.
    pub adiabatic_max_q: Option<f64>,
    /// Notes of the solve.
    pub notes: Vec<String>,
    /// Time per stage.
    pub stages: Vec<StageTime>,
    /// Peak resident memory in bytes.
    pub peak_memory: u64,
    /// Files written.
    pub files: Vec<PathBuf>,
    /// Loader warnings.
    pub warnings: Vec<String>,
}

/// Loads a scene for the thermal mode: the MTL's `#@thermal` lines, then the
/// boundary-conditions file over them; every material a face uses must end with thermal
/// properties ([`crate::thermal::bc::require`]).
pub fn thermal_scene(scene: &str, bc: Option<&Path>) -> Result<Scene> {
    thermal_scene_sided(scene, bc, false)
}

/// [`thermal_scene`], every face two-sided when `two_sided`.
pub fn thermal_scene_sided(scene: &str, bc: Option<&Path>, two_sided: bool) -> Result<Scene> {
    let mut s = load_scene(scene, two_sided)?;
    if let Some(path) = bc {
        let rows = crate::thermal::bc::read(path)?;
        crate::thermal::bc::apply(&mut s, path, &rows)?;
    }
    crate::thermal::bc::require(&s)?;
    Ok(s)
}

/// Runs the thermal mode: load (with boundary conditions), mesh, form factors (computed or
/// read from a folder), repair, the net-radiation solve with error bars
/// ([`crate::thermal`]), and `patches.csv`, `surfaces.csv`, the per-vertex `thermal.exr`
/// and `mesh.ply` ([`output::thermal`]) written whole into `out_dir`.
/// Every setting and input is checked before the form factors.
pub fn thermal(cfg: &ThermalConfig, obs: &dyn Observer) -> Result<ThermalSummary> {
    use crate::thermal::{self as th, Problem};
    let mut timer = Timer {
        obs,
        stages: Vec::new(),
    };
    output::check_folder(&cfg.out_dir, FolderKind::Thermal)?;
    if !(cfg.ambient.is_finite() && (0.0..=crate::scene::MAX_TEMPERATURE).contains(&cfg.ambient)) {
        return Err(Error::Config(format!(
            "ambient temperature {} K is outside [0, {:e}] K",
            cfg.ambient,
            crate::scene::MAX_TEMPERATURE
        )));
    }
    let s = &cfg.settings;
    if !(s.tolerance.is_finite() && s.tolerance > 0.0 && s.tolerance < 1.0) {
        return Err(Error::Config(format!(
            "thermal tolerance {} is not in (0, 1)",
            s.tolerance
        )));
    }
    let scene = timer.run("load", 0, || {
        thermal_scene_sided(&cfg.scene, cfg.bc.as_deref(), cfg.two_sided)
    })?;
    let early = early_warnings(&scene, obs);
    check_budget(
        &scene,
        cfg.resolution,
        cfg.factors.is_none().then_some(&cfg.estimator),
        None,
        None,
        cfg.max_memory,
    )?;
    let patches = timer.run("mesh", 0, || PatchSet::build(&scene, cfg.resolution))?;
    let Factors {
        ff,
        repair: repair_report,
        ..
    } = factors_of(
        &patches,
        cfg.factors.as_deref(),
        (&cfg.estimator, cfg.seed),
        cfg.repair,
        &mut timer,
        &Single,
    )?
    .expect("one process is rank 0");
    // Its summary reports row sums, not reciprocity: every pair is not worth checking.
    let diagnostics = timer.run("diagnostics", 0, || ff.diagnostics_with(Reciprocity::Auto));
    // Surfaces: the materials the patches use, in material order.
    let used: Vec<usize> = (0..patches.materials.len())
        .filter(|&m| patches.material.iter().any(|&k| k as usize == m))
        .collect();
    let surface_of: Vec<u32> = patches
        .material
        .iter()
        .map(|&m| used.iter().position(|&u| u == m as usize).unwrap_or(0) as u32)
        .collect();
    let thermal_of = |m: usize| {
        patches.materials[m].thermal.ok_or_else(|| Error::Scene {
            scene: scene.source.clone(),
            msg: format!(
                "material `{}` has no thermal properties",
                patches.materials[m].name
            ),
        })
    };
    let infos: Vec<output::thermal::SurfaceInfo> = used
        .iter()
        .map(|&m| {
            let t = thermal_of(m)?;
            Ok(output::thermal::SurfaceInfo {
                name: patches.materials[m].name.clone(),
                patches: patches
                    .material
                    .iter()
                    .filter(|&&k| k as usize == m)
                    .count(),
                emissivity: t.emissivity,
                boundary: t.boundary,
            })
        })
        .collect::<Result<_>>()?;
    let groups = infos.len();
    let settings = th::Settings {
        seed: cfg.seed,
        ..cfg.settings
    };
    let ((sol, results, problem_patch), unknowns) = timer.run("thermal solve", 0, || {
        // Per-patch arrays.
        let eps: Vec<f64> = surface_of
            .iter()
            .map(|&s| infos[s as usize].emissivity)
            .collect();
        let bc: Vec<_> = surface_of
            .iter()
            .map(|&s| infos[s as usize].boundary)
            .collect();
        if cfg.zones {
            let (zf, zse, za) = crate::objects::lump(&ff.f, &ff.se, &ff.area, &surface_of, groups)?;
            // Stored as every bar is, in f32.
            let zse: Vec<f32> = zse.iter().map(|b| b.stored_f32()).collect();
            let zeps: Vec<f64> = infos.iter().map(|s| s.emissivity).collect();
            let zbc: Vec<_> = infos.iter().map(|s| s.boundary).collect();
            let zp = Problem {
                f: &zf,
                se: &zse,
                area: &za,
                emissivity: &zeps,
                boundary: &zbc,
                ambient: cfg.ambient,
            };
            let zsol = th::solve(&zp, &settings)?;
            let ids: Vec<u32> = (0..groups as u32).collect();
            let results = th::surfaces(&zp, &zsol, &ids, groups, &settings)?;
            // Every patch carries its zone's values.
            let sol = zsol.spread(&surface_of);
            Ok::<_, Error>(((sol, results, (eps, bc)), groups))
        } else {
            let p = Problem {
                f: &ff.f,
                se: &ff.se,
                area: &ff.area,
                emissivity: &eps,
                boundary: &bc,
                ambient: cfg.ambient,
            };
            let sol = th::solve(&p, &settings)?;
            let results = th::surfaces(&p, &sol, &surface_of, groups, &settings)?;
            Ok(((sol, results, (eps, bc)), patches.len()))
        }
    })?;
    let (eps, bc) = problem_patch;
    let adiabatic_max_q = bc
        .iter()
        .zip(&sol.q)
        .filter(|(b, _)| matches!(b, crate::scene::Boundary::Flux(q) if *q == 0.0))
        .map(|(_, q)| q.abs())
        .reduce(f64::max);
    let names: Vec<String> = infos.iter().map(|s| s.name.clone()).collect();
    // The per-vertex files store f32: refuse a value past its range (or not a number)
    // before interpolating, naming the patch.
    let per_patch = [
        ("T", &sol.t),
        ("T_se", &sol.se_t),
        ("J", &sol.j),
        ("J_se", &sol.se_j),
        ("G", &sol.g),
        ("G_se", &sol.se_g),
        ("q", &sol.q),
        ("q_se", &sol.se_q),
    ];
    for (name, x) in per_patch {
        if let Some(k) = x.iter().position(|&v| !(v as f32).is_finite()) {
            return Err(Error::Scene {
                scene: scene.source.clone(),
                msg: format!(
                    "the thermal solve produced {name} = {} at patch {k}, not finite in f32 \
                     (thermal.exr and mesh.ply store f32, up to {:e})",
                    x[k],
                    f32::MAX
                ),
            });
        }
    }
    let verts = timer.run("per-vertex", 0, || {
        output::thermal::vertex_fields(&patches, &sol)
    });
    let files = timer.run("write", 0, || {
        output::write_folder(&cfg.out_dir, FolderKind::Thermal, |dir| {
            let p = Problem {
                f: &ff.f,
                se: &ff.se,
                area: &ff.area,
                emissivity: &eps,
                boundary: &bc,
                ambient: cfg.ambient,
            };
            output::thermal::write_patches(
                &dir.join("patches.csv"),
                &p,
                &sol,
                &surface_of,
                &names,
            )?;
            output::thermal::write_surfaces(&dir.join("surfaces.csv"), &infos, &results, &sol)?;
            output::thermal::write_exr(&dir.join("thermal.exr"), &verts, &scene.name)?;
            output::thermal::write_ply(&dir.join("mesh.ply"), &verts)?;
            Ok(["patches.csv", "surfaces.csv", "thermal.exr", "mesh.ply"]
                .iter()
                .map(|n| cfg.out_dir.join(n))
                .collect())
        })
    })?;
    let total = results.get(groups).copied().unwrap_or_default();
    Ok(ThermalSummary {
        scene: scene.name.clone(),
        patches: patches.len(),
        unknowns,
        estimator: ff.estimator.clone(),
        rays: ff.rays,
        diagnostics,
        repair: repair_report,
        surfaces: infos
            .into_iter()
            .zip(results)
            .map(|(info, result)| ThermalSurface { info, result })
            .collect(),
        total,
        to_environment: (sol.to_environment, sol.se_to_environment),
        ambient: cfg.ambient,
        solve: (sol.iterations, sol.residual),
        adiabatic_max_q,
        notes: sol.notes.clone(),
        stages: timer.stages,
        peak_memory: peak_memory(),
        files,
        warnings: scene.warnings.iter().cloned().chain(early).collect(),
    })
}

/// A surface flow's bar: its standard error and its bound ([`crate::matrix::Bar`]).
fn flow_bar(f: &crate::thermal::Flow) -> crate::matrix::Bar {
    crate::matrix::Bar {
        se: f.se,
        bound: f.bound,
    }
}

/// The one-screen summary of a thermal run: per surface `T`, `q`, `Q` with their error
/// bars, and the energy balance.
pub fn format_thermal_summary(s: &ThermalSummary) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "thermal `{}`: {} patches, {} unknowns ({}), ambient {} K",
        s.scene,
        s.patches,
        s.unknowns,
        if s.unknowns == s.patches {
            "patch by patch"
        } else {
            "one zone per surface"
        },
        s.ambient
    );
    let d = &s.diagnostics;
    let _ = writeln!(
        o,
        "form factors: {} ({} rays); row sums in [{:.6}, {:.6}]; bounds: {}",
        s.estimator,
        s.rays,
        d.min_row_sum.max(0.0),
        d.max_row_sum,
        s.repair.before.summary()
    );
    if s.repair.repair != Repair::None {
        let _ = writeln!(
            o,
            "  repair {:?}: entries moved by <= {:.2} standard errors",
            s.repair.repair, s.repair.max_shift_sigmas
        );
    }
    let _ = writeln!(
        o,
        "solve: net-radiation SOR, {} sweeps, relative residual {:.1e}",
        s.solve.0, s.solve.1
    );
    let _ = writeln!(
        o,
        "{:<12} {:>4} {:>18} {:>20} {:>21}",
        "surface", "eps", "T (K)", "q (W/m2)", "Q (W)"
    );
    for x in &s.surfaces {
        let r = &x.result;
        let t = match x.info.boundary {
            crate::scene::Boundary::Temperature(t) => format!("{t} (given)"),
            _ => format!("{:.4} ± {:.1e}", r.t, r.se_t),
        };
        let q = match x.info.boundary {
            crate::scene::Boundary::Flux(q) => format!("{q} (given)"),
            _ => format!(
                "{:.6e} {}",
                r.flow.q / r.area,
                flow_bar(&r.flow).times(1.0 / r.area)
            ),
        };
        let _ = writeln!(
            o,
            "{:<12} {:>4} {:>18} {:>20} {:>21}",
            x.info.name,
            x.info.emissivity,
            t,
            q,
            format!("{:.6e} {}", r.flow.q, flow_bar(&r.flow))
        );
    }
    let scale = s
        .surfaces
        .iter()
        .map(|x| x.result.flow.q.abs())
        .fold(0.0, f64::max);
    let _ = writeln!(
        o,
        "energy balance: sum of Q = {:.6e} {} W ({:+.1e} of the largest |Q|); to the \
         environment {:.6e} ± {:.1e} W",
        s.total.flow.q,
        flow_bar(&s.total.flow),
        if scale > 0.0 {
            s.total.flow.q / scale
        } else {
            0.0
        },
        s.to_environment.0,
        s.to_environment.1
    );
    if let Some(q) = s.adiabatic_max_q {
        let _ = writeln!(o, "adiabatic patches: largest |q| {q:.1e} W/m2");
    }
    for n in &s.notes {
        let _ = writeln!(o, "note: {n}");
    }
    let _ = writeln!(o, "{}", format_times(&s.stages, s.peak_memory));
    for w in &s.warnings {
        let _ = writeln!(o, "warning: {w}");
    }
    let _ = write!(o, "wrote:");
    for f in &s.files {
        let _ = write!(o, " {}", f.display());
    }
    o.push('\n');
    wrap(&o, WIDTH)
}

/// The outputs store f32: a radiosity past its range would be written as infinite, so a
/// solve whose result does not fit is refused, naming the first patch that does not.
pub(crate) fn check_storable(scene: &Scene, b: &[[f64; 3]]) -> Result<()> {
    match b
        .iter()
        .position(|v| v.iter().any(|&c| !(c as f32).is_finite()))
    {
        None => Ok(()),
        Some(k) => Err(Error::Scene {
            scene: scene.source.clone(),
            msg: format!(
                "the solve produced radiosity {:?} at patch {k}, not finite in f32 (the EXR and \
                 PLY store f32, up to {:e}): scale the emissions down",
                b[k],
                f32::MAX
            ),
        }),
    }
}
