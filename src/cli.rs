//! Argument syntax (clap) and its resolution into the library's configuration types.
//! Nothing here computes: it parses, resolves, calls the pipeline and prints.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::Mutex;

use anyhow::{bail, Context as _, Result};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use radiosity::cluster::{Cluster, Single};
use radiosity::formfactor::EstimatorKind;
use radiosity::matrix::Reciprocity;
use radiosity::mesh::Resolution;
use radiosity::output::Exposure;
use radiosity::pipeline::{self, BakeConfig, EstimatorChoice, Observer};
use radiosity::repair::Repair;
use radiosity::scene::builtin;
use radiosity::solve::{Method, Options};
use radiosity::store::Format;
use radiosity::study;

#[derive(Parser, Debug)]
#[command(
    name = "radiosity",
    version,
    about = "Monte Carlo radiosity form factors on Embree 4, solved and baked into OpenEXR"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

// One command is parsed per run: the size of its largest variant does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Subcommand, Debug)]
enum Command {
    /// Compute form factors, solve, and write radiosity.exr, mesh.ply, mesh.glb and
    /// preview.png.
    Bake(BakeArgs),
    /// Compute form factors only and store them (Matrix Market or SciPy npz, CSV, JSON) for reuse.
    Factors(FactorsArgs),
    /// Radiative heat transfer between gray surfaces: temperatures, net fluxes and heat
    /// flows with error bars (patches.csv, surfaces.csv; per vertex thermal.exr, mesh.ply);
    /// see docs/THERMAL.md.
    Thermal(ThermalArgs),
    /// List the built-in scenes.
    Scenes,
    /// Compare every estimator against closed forms: CSV, charts, slopes, calibration.
    Study(StudyArgs),
    /// Compare the solvers: residual against work and time on the closed cube (rho 0.5 to
    /// 0.999) and the Cornell box; CSV and charts.
    StudySolvers(StudySolversArgs),
    /// Hierarchical against uniform bakes of the Cornell box, scored against a path-traced
    /// reference: CSV and error-vs-CPU-time and error-vs-rays charts.
    StudyBakes(StudyBakesArgs),
    /// Measure: form-factor stage vs raw Embree rays/s, time and memory per stage, scaling.
    Bench(BenchArgs),
    /// The benchmark suite: cases with exact answers, a scorer, a leaderboard.
    #[command(subcommand)]
    Suite(SuiteCommand),
}

#[derive(Subcommand, Debug)]
enum SuiteCommand {
    /// Write every case as OBJ/MTL and the table of exact values (suite.json, suite.csv).
    Export {
        /// Output folder.
        dir: PathBuf,
    },
    /// Compute this program's answers: one factors folder per case, for `suite score --factors`.
    Run(SuiteRunArgs),
    /// Score a program's answers against the exact values.
    Score(SuiteScoreArgs),
    /// Put several scores (JSON from `suite score --json`) on one board: BASE.md, BASE.svg, BASE.png.
    Board {
        /// Output path without extension.
        #[arg(short, long)]
        output: PathBuf,
        /// Score files.
        #[arg(required = true)]
        scores: Vec<PathBuf>,
    },
}

#[derive(Args, Debug)]
struct SuiteRunArgs {
    /// The exported suite (folder with suite.json).
    #[arg(long, default_value = "suite")]
    suite: PathBuf,
    /// Output folder (one factors folder per case).
    #[arg(short, long)]
    output: PathBuf,
    /// Only these cases (comma-separated).
    #[arg(long, value_delimiter = ',')]
    cases: Vec<String>,
    /// Target number of patches per case (default: each face one patch, about).
    #[arg(long, conflicts_with = "max_edge")]
    patches: Option<usize>,
    /// Subdivide so that no patch edge is longer than this (scene units).
    #[arg(long)]
    max_edge: Option<f64>,
    #[command(flatten)]
    factors: FactorArgs,
}

#[derive(Args, Debug)]
struct SuiteScoreArgs {
    /// The exported suite (folder with suite.json).
    #[arg(long, default_value = "suite")]
    suite: PathBuf,
    /// Answers as one folder per case (DIR/CASE/): F.mtx (Matrix Market) with patches.csv
    /// (area and surface, material or face per patch), optionally stderr.mtx and
    /// provenance.json; `radiosity factors` writes such folders.
    #[arg(
        long,
        visible_alias = "matrix",
        conflicts_with = "csv",
        required_unless_present = "csv"
    )]
    factors: Option<PathBuf>,
    /// Answers as a CSV: case,from,to,value[,stderr][,seconds].
    #[arg(long)]
    csv: Option<PathBuf>,
    /// Name of the program scored (and its settings).
    #[arg(long, default_value = "unnamed")]
    tool: String,
    /// The command that made the answers (recorded in the score).
    #[arg(long, default_value = "")]
    command: String,
    /// Relative error above which a case may be flagged.
    #[arg(long, default_value_t = 1e-3)]
    tolerance: f64,
    /// A case with a bar is flagged only when its error is also above this many bars.
    #[arg(long, default_value_t = 3.0)]
    sigmas: f64,
    /// Write the score as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write the per-case scores as CSV here.
    #[arg(long = "csv-out")]
    csv_out: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct StudyBakesArgs {
    /// Scene: a name in scenes/ or an OBJ path (the reference must describe the same
    /// faces, in the same order).
    #[arg(long, default_value = "cornell")]
    scene: String,
    /// Output folder.
    #[arg(short, long, default_value = "docs/hierarchy")]
    output: PathBuf,
    /// Reference table (face averages and probe points).
    #[arg(long, default_value = "docs/reference/cornell-mitsuba.csv")]
    reference: PathBuf,
    /// Patch counts of the uniform bakes.
    #[arg(long, value_delimiter = ',', default_value = "500,1000,2000,4000")]
    flat: Vec<usize>,
    /// Link tolerances of the hierarchical bakes.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0.04,0.02,0.01,0.005,0.0025"
    )]
    errors: Vec<f64>,
    /// Visibility rays per side of the hierarchical bakes' links.
    #[arg(long, default_value_t = 4)]
    link_rays: usize,
    /// Floor of a receiver's radiosity in its link tolerance, as a share of the mean (see
    /// `bake --relative-low`).
    #[arg(long, default_value_t = radiosity::hierarchy::RELATIVE_LOW)]
    relative_low: f64,
    /// Cap of a receiver's radiosity in its link tolerance, as a share of the mean.
    #[arg(long, default_value_t = radiosity::hierarchy::RELATIVE_HIGH)]
    relative_high: f64,
    /// Share of the link tolerance above which the final gather cuts a source into its
    /// children (see `bake --descend`).
    #[arg(long, default_value_t = radiosity::hierarchy::DESCEND)]
    descend: f64,
    /// Floor of a receiver's radiosity in the final gather's source cut, as a share of
    /// the mean (see `bake --descend-low`).
    #[arg(long, default_value_t = radiosity::hierarchy::DESCEND_LOW)]
    descend_low: f64,
    /// Share of the source cut's tolerance above which the final gather cuts a source
    /// the leaf's view weights otherwise than its area (see `bake --kernel-cut`).
    #[arg(long, default_value_t = radiosity::hierarchy::KERNEL_CUT)]
    kernel_cut: f64,
    /// Share of a leaf's tolerance its final gather's visibility noise may reach (see
    /// `bake --gather-noise`).
    #[arg(long, default_value_t = f64::INFINITY)]
    gather_noise: f64,
    /// Split receivers whose shadows vary across them by more than the tolerance (see
    /// `bake --split-shadows`).
    #[arg(long, value_enum, default_value_t = if radiosity::hierarchy::SPLIT_SHADOWS { Switch::On } else { Switch::Off })]
    split_shadows: Switch,
    /// Seed of the hierarchical bakes' random streams (another seed shows how far the
    /// scores move with the Monte Carlo visibility alone).
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Args, Debug)]
struct StudySolversArgs {
    /// Output folder.
    #[arg(short, long, default_value = "docs/solvers")]
    output: PathBuf,
    /// A small study (coarse meshes, two reflectances), for tests.
    #[arg(long)]
    quick: bool,
}

#[derive(Args, Debug)]
struct BenchArgs {
    /// Scene of the stage-vs-raw table.
    #[arg(default_value = "cornell")]
    scene: String,
    /// Patches of the stage-vs-raw table.
    #[arg(long, default_value_t = 500)]
    patches: usize,
    /// Repeats of each timing (medians are printed).
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Worker threads (default: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Leave flush-to-zero / denormals-are-zero off on the workers.
    #[arg(long)]
    no_ftz: bool,
    /// Widest vector width of the sampling passes: avx512, avx2 or baseline (the widest
    /// the processor has, up to this one), to measure what each gains (results are the
    /// same).
    #[arg(long, default_value = "avx512", value_parser = parse_width)]
    simd: radiosity::simd::Width,
    /// How 16-ray packets go to Embree in the ratio table: native (one 16-wide query
    /// where Embree runs 16-wide packets natively, AVX-512, else two 8-wide), 16 or 8, to
    /// measure what each gains (results are the same).
    #[arg(long, default_value = "native", value_parser = parse_packets)]
    packets: Packets,
    /// Scaling run instead: Cornell box and cube at these patch counts (comma-separated).
    #[arg(long, value_delimiter = ',', num_args = 0.., default_missing_value = "1024,4096,16384,65536,262144")]
    scaling: Option<Vec<usize>>,
    /// Largest patch count that also runs the all-pairs estimators (area, semi).
    #[arg(long, default_value_t = 1024)]
    area_max: usize,
    /// Folder for scaling.csv and scratch EXR files.
    #[arg(short, long, default_value = "bench-out")]
    output: PathBuf,
}

#[derive(Args, Debug)]
struct StudyArgs {
    /// Output folder.
    #[arg(short, long, default_value = "study")]
    output: PathBuf,
    /// A small study (three budgets, two seeds, 20 calibration seeds), for tests.
    #[arg(long)]
    quick: bool,
    /// Study the solvers instead (same as `study-solvers`; default folder docs/solvers).
    #[arg(long)]
    solvers: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

#[derive(Args, Debug)]
struct MeshArgs {
    /// Target number of patches (the edge length is chosen to get close to it). With a bake's
    /// hierarchical method (its default) these are the root patches, and the default is
    /// roots no longer than a quarter of the scene's diagonal; otherwise 1000.
    #[arg(long, conflicts_with = "max_edge")]
    patches: Option<usize>,
    /// Subdivide so that no patch edge is longer than this (scene units).
    #[arg(long)]
    max_edge: Option<f64>,
}

impl MeshArgs {
    fn resolution(&self) -> Result<Resolution> {
        self.resolution_or(Resolution::Patches(1000))
    }

    /// The resolution asked for, or `default` when neither option is given.
    fn resolution_or(&self, default: Resolution) -> Result<Resolution> {
        Ok(match (self.max_edge, self.patches) {
            (Some(h), _) if h > 0.0 && h.is_finite() => Resolution::MaxEdge(h),
            (Some(h), _) => bail!("--max-edge must be a positive length, got {h}"),
            (None, Some(0)) => bail!("--patches must be at least 1"),
            (None, Some(n)) if n > radiosity::budget::MAX_PATCHES => bail!(
                "--patches must be at most {}, got {n}",
                radiosity::budget::MAX_PATCHES
            ),
            (None, Some(n)) => Resolution::Patches(n),
            (None, None) => default,
        })
    }
}

/// How a bake solves for radiosity.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum MethodArg {
    /// Hierarchical, unless the command line gives a setting only the flat method has
    /// (--factors, --estimator, --samples, --rays, --tol, --replicates, --repair,
    /// --solver, --steps, --floor, --keep-partial, --two-sided), the bake runs on several
    /// MPI ranks, or the scene has faces the hierarchy does not support (two-sided ones,
    /// or a closed room's faces pointing out of it): then flat, and the summary says why.
    Auto,
    /// Form factors between every pair of patches of a uniform mesh, then a matrix solver.
    Flat,
    /// Hierarchical radiosity: elements and links refined where the light needs them.
    Hierarchical,
}

/// On or off.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum Switch {
    /// On.
    On,
    /// Off.
    Off,
}

/// `--clusters`: on, off, or as the scene's size asks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum ClusterArg {
    /// Always.
    On,
    /// Never (a link between every pair of faces to start).
    Off,
    /// For scenes of more than 4096 root patches, or where their pairs would not fit in
    /// memory.
    Auto,
}

impl From<radiosity::hierarchy::Clustering> for ClusterArg {
    fn from(c: radiosity::hierarchy::Clustering) -> Self {
        use radiosity::hierarchy::Clustering;
        match c {
            Clustering::On => ClusterArg::On,
            Clustering::Off => ClusterArg::Off,
            Clustering::Auto => ClusterArg::Auto,
        }
    }
}

impl From<ClusterArg> for radiosity::hierarchy::Clustering {
    fn from(c: ClusterArg) -> Self {
        use radiosity::hierarchy::Clustering;
        match c {
            ClusterArg::On => Clustering::On,
            ClusterArg::Off => Clustering::Off,
            ClusterArg::Auto => Clustering::Auto,
        }
    }
}

#[derive(Args, Debug)]
struct HierarchyArgs {
    /// Radiosity method.
    #[arg(long, value_enum, default_value_t = MethodArg::Auto)]
    method: MethodArg,
    /// Hierarchical: link tolerance, relative to the receiver's radiosity (taken between
    /// --relative-low and --relative-high times the scene's mean radiosity).
    #[arg(long, default_value_t = 0.01)]
    error: f64,
    /// Hierarchical: floor of a receiver's radiosity in its link tolerance, as a share of
    /// the scene's mean radiosity (1, with --relative-high 1: the tolerance is --error
    /// times the mean for every receiver).
    #[arg(long, default_value_t = radiosity::hierarchy::RELATIVE_LOW)]
    relative_low: f64,
    /// Hierarchical: cap of a receiver's radiosity in its link tolerance, as a share of
    /// the scene's mean radiosity (inf: none).
    #[arg(long, default_value_t = radiosity::hierarchy::RELATIVE_HIGH)]
    relative_high: f64,
    /// Hierarchical: smallest element area (scene units²); default (diagonal / 512)².
    #[arg(long)]
    min_area: Option<f64>,
    /// Hierarchical: visibility strata per side of each link (rays² rays).
    #[arg(long, default_value_t = 4)]
    link_rays: usize,
    /// Hierarchical: start from a cluster tree over the input faces (links between groups
    /// of faces far enough apart) instead of a link between every pair of them; auto:
    /// for scenes of more than 4096 root patches, or where their pairs would not fit in
    /// memory.
    #[arg(long, value_enum, default_value_t = ClusterArg::from(radiosity::hierarchy::CLUSTERS))]
    clusters: ClusterArg,
    /// Hierarchical with clusters: largest relative error bound of a cluster link (inf:
    /// the link tolerance alone decides; 1 to 3: fewer savings, closer to unclustered).
    #[arg(long, default_value_t = f64::INFINITY)]
    cluster_accuracy: f64,
    /// Hierarchical with clusters: relative tolerance of a cluster link's transfer to each
    /// leaf (inf: sampled, its error within the link's bound; e.g. 1e-9: integrated over the
    /// source's faces, for closed scenes that conserve light to that precision).
    #[arg(long, default_value_t = f64::INFINITY)]
    cluster_quadrature: f64,
    /// Hierarchical with clusters: split a receiving face larger than its source cluster
    /// into elements (cluster links below the faces; faster and leaner on large faces, and
    /// sharper shadows on them: docs/HIERARCHY.md, Clustering).
    #[arg(long, value_enum, default_value_t = if radiosity::hierarchy::SPLIT_RECEIVERS { Switch::On } else { Switch::Off })]
    split_receivers: Switch,
    /// Hierarchical: split a receiver whose shadows vary across it by more than the
    /// tolerance (sharper shadows, for more CPU: docs/HIERARCHY.md, Shadows across
    /// receivers).
    #[arg(long, value_enum, default_value_t = if radiosity::hierarchy::SPLIT_SHADOWS { Switch::On } else { Switch::Off })]
    split_shadows: Switch,
    /// Hierarchical: share of the link tolerance above which the final gather cuts a
    /// source whose radiosity varies into its children (larger: a faster, leaner gather
    /// that takes sources' mean radiosity more often; docs/HIERARCHY.md).
    #[arg(long, default_value_t = radiosity::hierarchy::DESCEND)]
    descend: f64,
    /// Hierarchical: make the final gather's source cut relative to each receiver's own
    /// radiosity, floored at this share of the mean (in (0, 1]; 1, the default, keeps it
    /// absolute). Dark receivers then take finer sources: 0.25 brings the Cornell box's
    /// darkest face within 0.3% of a path tracer for 17% more rays (docs/HIERARCHY.md).
    #[arg(long, default_value_t = radiosity::hierarchy::DESCEND_LOW)]
    descend_low: f64,
    /// Hierarchical: share of the source cut's tolerance above which the final gather
    /// also cuts a source a leaf sees whole where its view weights the source's children
    /// otherwise than their areas (four point factors per entry, no rays; 0: off). The
    /// default takes every face of the Cornell box within 0.3% of a path tracer for 1.5
    /// times the CPU time (docs/HIERARCHY.md).
    #[arg(long, default_value_t = radiosity::hierarchy::KERNEL_CUT)]
    kernel_cut: f64,
    /// Hierarchical with clusters: share of a leaf's tolerance that the cluster links it
    /// takes at their own visible fractions may move its radiosity by together, in the
    /// final gather; it checks its own view of the loudest others' sources (4 rays each).
    /// inf: every leaf takes every cluster link's fraction (docs/HIERARCHY.md, *A leaf's
    /// own view of a cluster*).
    #[arg(long, default_value_t = radiosity::hierarchy::CLUSTER_SIGHT_SHARE)]
    cluster_sight: f64,
    /// Hierarchical: share of a leaf's tolerance that the visibility noise of its element
    /// entries may reach (one standard error) in the final gather; the loudest are traced
    /// again with up to 32 x 32 rays each. inf (the default): off (docs/HIERARCHY.md, *The
    /// gather's visibility noise*).
    #[arg(long, default_value_t = f64::INFINITY)]
    gather_noise: f64,
    /// Hierarchical: cap on refine-and-solve passes.
    #[arg(long, default_value_t = 8)]
    max_passes: usize,
    /// Hierarchical: relative tolerance of each link's unoccluded integral.
    #[arg(long, default_value_t = 1e-6)]
    link_quadrature: f64,
    /// Hierarchical: share of the link tolerance a link's quadrature error may take (0:
    /// every factor to `--link-quadrature`).
    #[arg(long, default_value_t = 0.01)]
    link_accuracy: f64,
}
/// Set once the threads are set for the whole run (by `radiosity::mpi::World::init`).
static THREADS_SET: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Caps of count arguments (a larger value is a typo or a memory bomb, not a setting).
const MAX_REPLICATES: usize = 1024;
const MAX_RAYS: usize = 256;
const MAX_THREADS: usize = 4096;
const MAX_STEPS: usize = 1000;
const MAX_ITERATIONS: usize = 1_000_000_000;

#[derive(Args, Debug)]
struct FactorArgs {
    /// Form-factor estimator.
    #[arg(long, value_enum, default_value_t = EstimatorKind::Semi)]
    estimator: EstimatorKind,
    /// Samples per side: emitter points per side (semi), strata per side (area estimators)
    /// or cells per side of the top face (hemicube).
    #[arg(long, default_value_t = 3)]
    samples: usize,
    /// Visibility strata per side for each emitter point (semi estimator): rays² rays.
    #[arg(long, default_value_t = 2)]
    rays: usize,
    /// Relative tolerance of the semi estimator's deterministic integral over pairs that
    /// nothing can block (no rays there; the error estimate is the reported error).
    #[arg(long, default_value_t = 1e-6)]
    tol: f64,
    /// Independent replicates, for the standard errors (at least 2).
    #[arg(long, default_value_t = 4)]
    replicates: usize,
    /// Seed of all random streams; results do not depend on the thread count.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Restore physical constraints using the standard errors, keeping the sparsity
    /// pattern (closure assumes a closed scene).
    #[arg(long, value_enum, default_value_t = Repair::None)]
    repair: Repair,
    /// Memory the run may plan to use (bytes, or with K, M, G, T); default: what the system
    /// has available. A run estimated to need more is refused before any work.
    #[arg(long, value_name = "SIZE", value_parser = parse_memory)]
    max_memory: Option<u64>,
}

impl FactorArgs {
    fn choice(&self) -> Result<EstimatorChoice> {
        if self.samples == 0 || self.samples > 256 {
            bail!("--samples must be between 1 and 256, got {}", self.samples);
        }
        if !(2..=MAX_REPLICATES).contains(&self.replicates) {
            bail!(
                "--replicates must be between 2 (standard errors need two) and \
                 {MAX_REPLICATES}, got {}",
                self.replicates
            );
        }
        if !(1..=MAX_RAYS).contains(&self.rays) {
            bail!("--rays must be between 1 and {MAX_RAYS}, got {}", self.rays);
        }
        if !(self.tol >= 1e-14 && self.tol < 1.0) {
            bail!("--tol must be in [1e-14, 1), got {}", self.tol);
        }
        Ok(match self.estimator {
            EstimatorKind::Semi => EstimatorChoice::SemiAnalytic {
                points: self.samples,
                rays: self.rays,
                replicates: self.replicates,
                tol: self.tol,
            },
            EstimatorKind::Stratified => EstimatorChoice::AreaStratified {
                strata: self.samples,
                replicates: self.replicates,
            },
            EstimatorKind::Hemisphere => EstimatorChoice::Hemisphere {
                strata: self.samples,
                replicates: self.replicates,
            },
            EstimatorKind::Uniform => EstimatorChoice::AreaUniform {
                strata: self.samples,
                replicates: self.replicates,
            },
            EstimatorKind::Sobol => EstimatorChoice::AreaSobol {
                strata: self.samples,
                replicates: self.replicates,
            },
            EstimatorKind::Hemicube => EstimatorChoice::Hemicube { res: self.samples },
        })
    }

    fn init_threads(&self) -> Result<()> {
        if THREADS_SET.load(std::sync::atomic::Ordering::Relaxed) {
            return Ok(());
        }
        if let Some(n) = self.threads {
            if !(1..=MAX_THREADS).contains(&n) {
                bail!("--threads must be between 1 and {MAX_THREADS}, got {n}");
            }
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build_global()
                .context("cannot set the thread count")?;
        }
        Ok(())
    }
}

#[derive(Args, Debug)]
struct BakeArgs {
    /// Built-in scene name or path to an OBJ file.
    #[arg(default_value = "cornell")]
    scene: String,
    /// Output folder.
    #[arg(short, long, default_value = "out")]
    output: PathBuf,
    #[command(flatten)]
    mesh: MeshArgs,
    #[command(flatten)]
    est: FactorArgs,
    /// Which stored pairs the diagnostics check for reciprocity (row sums and ranges are
    /// checked on every row).
    #[arg(long, value_enum, default_value_t = Reciprocity::Auto)]
    reciprocity: Reciprocity,
    #[command(flatten)]
    hier: HierarchyArgs,
    /// Radiosity solver.
    #[arg(long, value_enum, default_value_t = Method::default())]
    solver: Method,
    /// Relative residual at which the solver stops; every patch must also be converged to
    /// it, relative to its own radiosity (see --floor).
    #[arg(long, default_value_t = 1e-6)]
    tolerance: f64,
    /// Absolute floor of the per-patch stopping rule (radiosity units): a patch dimmer than
    /// this is converged to `tolerance * floor` instead of to its own value. Default: 1e-12
    /// times the largest emission of each channel.
    #[arg(long)]
    floor: Option<f64>,
    /// Iteration cap of the solver: sweeps (jacobi, gauss-seidel), iterations (cg); for
    /// progressive, this times the patch count shots (n shots cost about one sweep).
    #[arg(long, default_value_t = 10_000)]
    max_iterations: usize,
    /// Write the result even when the solver stops before its tolerance.
    #[arg(long)]
    keep_partial: bool,
    /// Preview size, WIDTHxHEIGHT.
    #[arg(long, default_value = "512x512")]
    size: String,
    /// Preview exposure: `auto` or a multiplier of the radiosity.
    #[arg(long, default_value = "auto", allow_hyphen_values = true)]
    exposure: String,
    /// Preview camera, `EX,EY,EZ,TX,TY,TZ[,UX,UY,UZ[,FOV]]`: eye, target, up (default
    /// +Y) and vertical field of view in degrees (default 40), over the scene's
    /// `#@camera` comment.
    #[arg(long, value_name = "EYE,TARGET[,UP[,FOV]]", allow_hyphen_values = true)]
    camera: Option<String>,
    /// Length unit of the scene's coordinates, over its `#@units` line: mesh.glb is
    /// written in metres, scaled by it (with neither, coordinates are taken as metres).
    #[arg(long, value_name = "mm|cm|m", value_parser = parse_units)]
    units: Option<radiosity::scene::Units>,
    /// Reuse form factors stored by `radiosity factors` (same scene and subdivision).
    #[arg(long, value_name = "DIR")]
    factors: Option<PathBuf>,
    /// Also write preview-step-NNNN.png after these progressive-refinement steps (shots),
    /// with the ambient term, e.g. `--steps 1,2,24,100`.
    #[arg(long, value_delimiter = ',', value_name = "N,N,...")]
    steps: Vec<usize>,
    /// Make every face two-sided: it emits, receives and reflects on both sides (each side
    /// its own patches), as for walls modelled with their normals out of the room.
    #[arg(long)]
    two_sided: bool,
    /// Also write a lightmap per object (and side), RES x RES texels in the OBJ's own
    /// texture coordinates (`vt`): lightmap-OBJECT.exr, lightmaps.json.
    #[arg(long, value_name = "RES")]
    lightmap: Option<usize>,
}

#[derive(Args, Debug)]
struct FactorsArgs {
    /// Built-in scene name or path to an OBJ file.
    scene: String,
    /// Output folder.
    #[arg(short, long, default_value = "factors")]
    output: PathBuf,
    #[command(flatten)]
    mesh: MeshArgs,
    #[command(flatten)]
    factors: FactorArgs,
    /// Which stored pairs the diagnostics check for reciprocity (row sums and ranges are
    /// checked on every row).
    #[arg(long, value_enum, default_value_t = Reciprocity::Auto)]
    reciprocity: Reciprocity,
    /// Layout of the matrix files: Matrix Market text or SciPy's sparse npz.
    #[arg(long, value_enum, default_value_t = Format::Auto)]
    format: Format,
    /// Make every face two-sided (see `bake --two-sided`).
    #[arg(long)]
    two_sided: bool,
}

#[derive(Args, Debug)]
struct ThermalArgs {
    /// Built-in scene name or path to an OBJ file (its MTL may give `#@thermal` lines).
    scene: String,
    /// Output folder.
    #[arg(short, long, default_value = "thermal")]
    output: PathBuf,
    #[command(flatten)]
    mesh: MeshArgs,
    #[command(flatten)]
    est: FactorArgs,
    /// Reuse form factors stored by `radiosity factors` (same scene and subdivision): new
    /// temperatures need no new rays.
    #[arg(long, value_name = "DIR")]
    factors: Option<PathBuf>,
    /// Boundary conditions, CSV `material,emissivity,temperature,flux` (over the MTL's).
    #[arg(long, value_name = "FILE")]
    bc: Option<PathBuf>,
    /// Ambient (environment) temperature in K: radiation leaving the scene reaches a black
    /// environment at this temperature.
    #[arg(long, default_value_t = 0.0)]
    ambient: f64,
    /// Treat each surface (material) as one zone of uniform radiosity, as the textbook
    /// closed forms do, instead of solving patch by patch.
    #[arg(long)]
    zones: bool,
    /// Relative residual at which the net-radiation solve stops.
    #[arg(long, default_value_t = 1e-12)]
    tolerance: f64,
    /// Cap on Gauss-Seidel sweeps per solve.
    #[arg(long, default_value_t = 100_000)]
    max_iterations: usize,
    /// Random tangent solves for the per-patch error bars (0: none; surface totals always
    /// get their exact first-order bars).
    #[arg(long, default_value_t = 16)]
    error_replicates: usize,
    /// Make every face two-sided (see `bake --two-sided`).
    #[arg(long)]
    two_sided: bool,
}

/// Draws progress bars on a terminal, nothing otherwise.
struct Bars {
    bar: Mutex<Option<ProgressBar>>,
    tty: bool,
}

impl Observer for Bars {
    fn warn(&self, msg: &str) {
        let line = pipeline::wrap(&format!("warning: {msg}"), pipeline::WIDTH);
        match self.bar.lock().ok().as_ref().and_then(|b| b.as_ref()) {
            Some(bar) => bar.suspend(|| eprint!("{line}")),
            None => eprint!("{line}"),
        }
    }
    fn begin(&self, stage: &str, total: u64) {
        if !self.tty || total == 0 {
            return;
        }
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template("{msg:>14} [{bar:40}] {pos}/{len} rows, eta {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        bar.set_message(stage.to_string());
        if let Ok(mut b) = self.bar.lock() {
            *b = Some(bar);
        }
    }
    fn advance(&self, done: u64) {
        if let Ok(b) = self.bar.lock() {
            if let Some(bar) = b.as_ref() {
                bar.set_position(done);
            }
        }
    }
    fn end(&self, _stage: &str, _seconds: f64) {
        if let Ok(mut b) = self.bar.lock() {
            if let Some(bar) = b.take() {
                bar.finish_and_clear();
            }
        }
    }
}

fn parse_size(s: &str) -> Result<(u32, u32)> {
    let (w, h) = s
        .split_once('x')
        .with_context(|| format!("--size `{s}`: expected WIDTHxHEIGHT, e.g. 512x512"))?;
    let w: u32 = w
        .parse()
        .with_context(|| format!("--size `{s}`: bad width"))?;
    let h: u32 = h
        .parse()
        .with_context(|| format!("--size `{s}`: bad height"))?;
    if !(16..=8192).contains(&w) || !(16..=8192).contains(&h) {
        bail!("--size `{s}`: each side must be between 16 and 8192 pixels");
    }
    Ok((w, h))
}

fn parse_memory(s: &str) -> Result<u64> {
    radiosity::budget::parse_bytes(s).map_err(|e| anyhow::anyhow!("--max-memory {e}"))
}

fn parse_width(s: &str) -> Result<radiosity::simd::Width> {
    radiosity::simd::Width::parse(s)
        .with_context(|| format!("--simd `{s}`: expected avx512, avx2 or baseline"))
}

/// `bench --packets`: a packet width, or None for the library's native one.
#[derive(Clone, Copy, Debug)]
struct Packets(Option<radiosity::visibility::PacketWidth>);

fn parse_packets(s: &str) -> Result<Packets> {
    use radiosity::visibility::PacketWidth;
    Ok(Packets(match s {
        "native" => None,
        "16" => Some(PacketWidth::Sixteen),
        "8" => Some(PacketWidth::Eight),
        _ => bail!("--packets `{s}`: expected native, 16 or 8"),
    }))
}

/// Parses `--camera`: 6, 9 or 10 comma-separated numbers (see [`BakeArgs::camera`]).
fn parse_units(s: &str) -> std::result::Result<radiosity::scene::Units, String> {
    radiosity::scene::Units::parse(s)
        .ok_or_else(|| format!("`{s}` is not a unit: give mm, cm or m"))
}

fn parse_camera(s: &str) -> Result<radiosity::scene::Camera> {
    use glam::Vec3;
    let form = "expected EX,EY,EZ,TX,TY,TZ[,UX,UY,UZ[,FOV]]";
    let v: Vec<f32> = s
        .split(',')
        .map(|w| w.trim().parse::<f32>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("--camera `{s}`: {form}"))?;
    if ![6, 9, 10].contains(&v.len()) || v.iter().any(|x| !x.is_finite()) {
        bail!(
            "--camera `{s}`: {form}, all finite (got {} numbers)",
            v.len()
        );
    }
    let (eye, target) = (Vec3::new(v[0], v[1], v[2]), Vec3::new(v[3], v[4], v[5]));
    let up = if v.len() >= 9 {
        Vec3::new(v[6], v[7], v[8])
    } else {
        Vec3::Y
    };
    let fov = v.get(9).copied().unwrap_or(40.0);
    let view = target - eye;
    if view.length() == 0.0 {
        bail!("--camera `{s}`: the eye and the target are the same point");
    }
    if view.normalize().cross(up.normalize_or_zero()).length() < 1e-3 {
        bail!("--camera `{s}`: the up direction is zero or along the line of sight");
    }
    if !(1.0..179.0).contains(&fov) {
        bail!("--camera `{s}`: the field of view must be between 1 and 179 degrees");
    }
    Ok(radiosity::scene::Camera {
        eye,
        target,
        up,
        vfov_deg: fov,
    })
}

fn parse_exposure(s: &str) -> Result<Exposure> {
    if s == "auto" {
        return Ok(Exposure::Auto);
    }
    match s.parse::<f32>() {
        Ok(x) if x > 0.0 && x.is_finite() => Ok(Exposure::Fixed(x)),
        _ => bail!("--exposure `{s}`: expected `auto` or a positive number"),
    }
}

/// Form-factor settings that a stored matrix (`--factors`) or the hierarchical method
/// makes meaningless: given on the command line with either, they are refused rather than
/// silently ignored.
const ESTIMATOR_FLAGS: [&str; 5] = ["estimator", "samples", "rays", "tol", "replicates"];

/// Settings of the flat method's matrix that the hierarchical method has no use for
/// (beyond [`ESTIMATOR_FLAGS`]): given, they make `--method auto` flat, and are refused
/// with `--method hierarchical`.
const MATRIX_FLAGS: [&str; 7] = [
    "factors",
    "repair",
    "reciprocity",
    "solver",
    "steps",
    "floor",
    "keep_partial",
];

/// Whether the argument `id` was given on the command line (not taken by default).
fn given(m: &clap::ArgMatches, id: &str) -> bool {
    use clap::parser::ValueSource;
    matches!(
        m.try_get_raw(id).map(|_| m.value_source(id)),
        Ok(Some(ValueSource::CommandLine))
    )
}

/// The method a bake runs: `--method` as given, or for `auto` hierarchical unless the
/// command line (`m`) asks for the flat method's settings, two-sided faces, or several
/// ranks.
fn resolve_method(method: MethodArg, m: &clap::ArgMatches, ranks: usize) -> MethodArg {
    if method != MethodArg::Auto {
        return method;
    }
    let flat = ESTIMATOR_FLAGS
        .iter()
        .chain(&MATRIX_FLAGS)
        .chain(&["two_sided"])
        .any(|id| given(m, id));
    if flat || ranks > 1 {
        MethodArg::Flat
    } else {
        MethodArg::Hierarchical
    }
}

/// Refuses, before any work, flags that the rest of the command line makes meaningless:
/// estimator flags with a stored matrix (`factors`), and the flat method's flags
/// ([`ESTIMATOR_FLAGS`], [`MATRIX_FLAGS`]) with the hierarchical method.
fn check_meaningless(
    factors: Option<&std::path::Path>,
    hierarchical: bool,
    m: &clap::ArgMatches,
) -> Result<()> {
    let given = |id: &str| given(m, id);
    if let Some(dir) = factors {
        for id in ESTIMATOR_FLAGS.iter().chain(&["seed"]) {
            if given(id) {
                bail!(
                    "--{id} has no effect with --factors: the matrix in {} was computed \
                     with the settings its provenance.json records (drop --{id}, or run \
                     `radiosity factors` again with it)",
                    dir.display()
                );
            }
        }
        if hierarchical {
            bail!(
                "--factors stores a flat matrix; --method hierarchical computes its own \
                 links (drop one of them)"
            );
        }
    }
    if hierarchical {
        for id in ESTIMATOR_FLAGS {
            if given(id) {
                bail!(
                    "--{id} sets the flat form-factor estimator and has no effect with \
                     --method hierarchical (its links are set by --error, --link-rays, \
                     --min-area)"
                );
            }
        }
        for id in MATRIX_FLAGS.iter().filter(|&&id| id != "factors") {
            if given(id) {
                bail!(
                    "--{id} sets the flat method's matrix solve and has no effect with \
                     --method hierarchical (it gathers over its links, with --tolerance \
                     and --max-iterations): drop --{id}, or give --method flat"
                );
            }
        }
    }
    Ok(())
}

/// Bakes with `method` (resolved from `--method`; `auto` when it was chosen by default).
fn bake(args: &BakeArgs, method: MethodArg, auto: bool, cluster: &dyn Cluster) -> Result<()> {
    args.est.init_threads()?;
    if !(args.tolerance > 0.0 && args.tolerance < 1.0) {
        bail!("--tolerance must be in (0, 1), got {}", args.tolerance);
    }
    if let Some(f) = args.floor {
        if !(f.is_finite() && f >= 0.0) {
            bail!("--floor must be a finite number >= 0, got {f}");
        }
    }
    let hierarchy = match method {
        MethodArg::Flat | MethodArg::Auto => None,
        MethodArg::Hierarchical => {
            let h = radiosity::hierarchy::Settings {
                error: args.hier.error,
                relative_low: args.hier.relative_low,
                relative_high: args.hier.relative_high,
                min_area: args.hier.min_area,
                rays: args.hier.link_rays,
                tolerance: args.tolerance.min(1e-7),
                max_iterations: args.max_iterations,
                max_passes: args.hier.max_passes,
                quadrature: args.hier.link_quadrature,
                accuracy: args.hier.link_accuracy,
                seed: args.est.seed,
                clusters: args.hier.clusters.into(),
                cluster_accuracy: args.hier.cluster_accuracy,
                cluster_quadrature: args.hier.cluster_quadrature,
                split_receivers: args.hier.split_receivers == Switch::On,
                descend: args.hier.descend,
                descend_low: args.hier.descend_low,
                kernel_cut: args.hier.kernel_cut,
                cluster_sight: args.hier.cluster_sight,
                gather_noise: args.hier.gather_noise,
                split_shadows: args.hier.split_shadows == Switch::On,
                max_memory: args.est.max_memory,
                ..Default::default()
            };
            h.validate()?;
            Some(h)
        }
    };
    let resolution = match hierarchy {
        Some(_) => args
            .mesh
            .resolution_or(Resolution::DiagonalFraction(0.25))?,
        None => args.mesh.resolution()?,
    };
    let fallback = match (&hierarchy, auto) {
        (Some(_), true) => Some(args.mesh.resolution()?),
        _ => None,
    };
    if !(1..=MAX_ITERATIONS).contains(&args.max_iterations) {
        bail!(
            "--max-iterations must be between 1 and {MAX_ITERATIONS}, got {}",
            args.max_iterations
        );
    }
    if args.steps.len() > MAX_STEPS {
        bail!(
            "--steps lists {} steps; at most {MAX_STEPS} previews are written",
            args.steps.len()
        );
    }
    let cfg = BakeConfig {
        scene: args.scene.clone(),
        out_dir: args.output.clone(),
        resolution,
        estimator: args.est.choice()?,
        seed: args.est.seed,
        method: args.solver,
        solve: Options {
            tolerance: args.tolerance,
            max_iterations: args.max_iterations,
            keep_partial: args.keep_partial,
            floor: args.floor,
        },
        preview: parse_size(&args.size)?,
        exposure: parse_exposure(&args.exposure)?,
        camera: args.camera.as_deref().map(parse_camera).transpose()?,
        units: args.units,
        crease_deg: 30.0,
        factors: args.factors.clone(),
        steps: args.steps.clone(),
        repair: args.est.repair,
        reciprocity: args.reciprocity,
        max_memory: args.est.max_memory,
        hierarchy,
        fallback,
        two_sided: args.two_sided,
        lightmap: args.lightmap,
    };
    let bars = Bars {
        bar: Mutex::new(None),
        tty: std::io::stderr().is_terminal() && cluster.is_root(),
    };
    let Some(summary) = pipeline::distributed::bake_on(&cfg, &bars, cluster)? else {
        return Ok(());
    };
    print!("{}", pipeline::format_summary(&summary));
    if !summary.solve.converged {
        eprintln!(
            "warning: {} stopped before its tolerance (relative residual {:.3e}); the result \
             was written because of --keep-partial",
            summary.solve.solver, summary.solve.residual
        );
    }
    Ok(())
}

fn thermal(args: &ThermalArgs) -> Result<()> {
    args.est.init_threads()?;
    if !(args.tolerance > 0.0 && args.tolerance < 1.0) {
        bail!("--tolerance must be in (0, 1), got {}", args.tolerance);
    }
    if !(1..=MAX_ITERATIONS).contains(&args.max_iterations) {
        bail!(
            "--max-iterations must be between 1 and {MAX_ITERATIONS}, got {}",
            args.max_iterations
        );
    }
    if args.error_replicates > MAX_REPLICATES {
        bail!(
            "--error-replicates must be at most {MAX_REPLICATES}, got {}",
            args.error_replicates
        );
    }
    if !(args.ambient.is_finite() && args.ambient >= 0.0) {
        bail!(
            "--ambient must be a temperature in K (>= 0), got {}",
            args.ambient
        );
    }
    let cfg = pipeline::ThermalConfig {
        scene: args.scene.clone(),
        out_dir: args.output.clone(),
        resolution: args.mesh.resolution()?,
        estimator: args.est.choice()?,
        seed: args.est.seed,
        factors: args.factors.clone(),
        bc: args.bc.clone(),
        ambient: args.ambient,
        zones: args.zones,
        settings: radiosity::thermal::Settings {
            tolerance: args.tolerance,
            max_iterations: args.max_iterations,
            replicates: args.error_replicates,
            seed: args.est.seed,
        },
        repair: args.est.repair,
        max_memory: args.est.max_memory,
        two_sided: args.two_sided,
    };
    let bars = Bars {
        bar: Mutex::new(None),
        tty: std::io::stderr().is_terminal(),
    };
    let summary = pipeline::thermal(&cfg, &bars)?;
    print!("{}", pipeline::format_thermal_summary(&summary));
    Ok(())
}

fn study_bakes(args: &StudyBakesArgs) -> Result<()> {
    use radiosity::study::bakes;
    let settings = bakes::Settings {
        scene: args.scene.clone(),
        reference: args.reference.clone(),
        flat: args.flat.clone(),
        errors: args.errors.clone(),
        rays: args.link_rays,
        relative: (args.relative_low, args.relative_high),
        descend: (args.descend, args.descend_low, args.kernel_cut),
        gather_noise: args.gather_noise,
        split_shadows: args.split_shadows == Switch::On,
        seed: args.seed,
        ..bakes::Settings::full(args.output.clone())
    };
    let (runs, refs) = bakes::run(&settings)?;
    println!(
        "{:<13} {:>9} {:>8} {:>8} {:>10} {:>8} {:>8} {:>9} {:>9} {:>9}",
        "method",
        "parameter",
        "patches",
        "links",
        "rays",
        "cpu s",
        "wall s",
        "faces",
        "contact",
        "shadow"
    );
    for r in &runs {
        let (m, p) = match r.method {
            bakes::BakeKind::Flat(n) => ("uniform", format!("{n}")),
            bakes::BakeKind::Hierarchical(e) => ("hierarchical", format!("{e}")),
        };
        let pct = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{:.2}%", 100.0 * v));
        println!(
            "{m:<13} {p:>9} {:>8} {:>8} {:>10} {:>8.2} {:>8.2} {:>9} {:>9} {:>9}",
            r.patches,
            r.links,
            r.rays,
            r.cpu,
            r.wall,
            pct(Some(r.face_max)),
            pct(bakes::group_max(r, &refs, "block-")),
            pct(bakes::group_max(r, &refs, "shadow"))
        );
    }
    println!("wrote {}/bakes.csv and charts", args.output.display());
    Ok(())
}

fn study_solvers(args: &StudySolversArgs) -> Result<()> {
    let settings = if args.quick {
        radiosity::study::solvers::Settings::quick(args.output.clone())
    } else {
        radiosity::study::solvers::Settings::full(args.output.clone())
    };
    let report = radiosity::study::solvers::run(&settings)?;
    for r in &report.runs {
        println!(
            "{:<16} {:<13} {:>8} iterations {:>9.3}s residual {:.2e} {}",
            r.case, r.solver, r.iterations, r.seconds, r.residual, r.status
        );
    }
    println!(
        "wrote {} files to {}",
        report.files.len(),
        args.output.display()
    );
    Ok(())
}

/// Prints `e` and its chain of causes on stderr, each line after `prefix`.
pub fn print_error(e: &anyhow::Error, prefix: &str) {
    let mut said = e.to_string();
    eprintln!("error: {prefix}{said}");
    // A cause whose text the message already carries (an I/O error named in
    // `path: error`) is not printed again.
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !said.contains(&text) {
            eprintln!("  caused by: {text}");
            said.push_str(&text);
        }
        source = s.source();
    }
}

/// Parses the command line and runs it: as one process, or, when `mpirun` started it
/// (and the `mpi` feature is built), as one rank of several.
pub fn run() -> Result<()> {
    use clap::{CommandFactory, FromArgMatches};
    let matches = Cli::command().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    #[cfg(feature = "mpi")]
    if radiosity::mpi::launched() {
        return run_mpi(&cli, &matches);
    }
    #[cfg(not(feature = "mpi"))]
    if let Some(k) = radiosity::cluster::launched_size().filter(|&k| k > 1) {
        bail!(
            "started as one of {k} MPI processes, but this binary was built without MPI: \
             each would do the whole run and write the same folder. Build it with \
             `cargo build --release --features mpi` (or `./dev mpirun NP ...`), or run it \
             without mpirun"
        );
    }
    dispatch(&cli, &matches, &Single)
}

/// One rank of a run under `mpirun`: MPI and the threads are set up first
/// ([`radiosity::mpi::World::init`]); `factors` and `bake` share their work between the
/// ranks, other commands run only with one rank. On a failure with several ranks the
/// rank prints its error and ends the whole job (`MPI_Abort`): ranks other than 0 wait a
/// second first, so that an error every rank meets (a bad argument, a missing scene) is
/// printed once, by rank 0, whose abort ends the others before they print.
#[cfg(feature = "mpi")]
fn run_mpi(cli: &Cli, matches: &clap::ArgMatches) -> Result<()> {
    let threads = match &cli.command {
        Command::Bake(a) => a.est.threads,
        Command::Thermal(a) => a.est.threads,
        Command::Factors(a) => a.factors.threads,
        _ => None,
    };
    if let Some(n) = threads {
        if !(1..=MAX_THREADS).contains(&n) {
            bail!("--threads must be between 1 and {MAX_THREADS}, got {n}");
        }
    }
    let world = radiosity::mpi::World::init(threads)?;
    THREADS_SET.store(true, std::sync::atomic::Ordering::Relaxed);
    let shared = matches!(cli.command, Command::Bake(_) | Command::Factors(_));
    let result = if world.size() > 1 && !shared {
        Err(anyhow::anyhow!(
            "only `factors` and `bake` run on several ranks; run `{}` as one process \
             (without mpirun, or with -np 1)",
            matches.subcommand_name().unwrap_or("this command")
        ))
    } else {
        dispatch(cli, matches, &world)
    };
    // Ranks done before rank 0 wait here, without spinning, until it has written.
    let result = result.and_then(|()| Ok(world.wait_for_all()?));
    match result {
        Ok(()) => Ok(()),
        Err(e) if world.size() == 1 => Err(e),
        Err(e) => {
            if world.rank() != 0 {
                std::thread::sleep(std::time::Duration::from_secs(1));
            }
            let prefix = format!("rank {} of {}: ", world.rank(), world.size());
            let prefix = if e.to_string().starts_with(&prefix) {
                String::new()
            } else {
                prefix
            };
            print_error(&e, &prefix);
            eprintln!(
                "error: ending every rank of the job (MPI_Abort); no output folder was written"
            );
            world.abort(1)
        }
    }
}

/// Runs the parsed command on `cluster` (one process: [`Single`]).
fn dispatch(cli: &Cli, matches: &clap::ArgMatches, cluster: &dyn Cluster) -> Result<()> {
    match &cli.command {
        Command::Bake(args) => {
            let Some(m) = matches.subcommand_matches("bake") else {
                bail!("internal error: the bake command's arguments were not parsed")
            };
            let method = resolve_method(args.hier.method, m, cluster.size());
            let hierarchical = method == MethodArg::Hierarchical;
            check_meaningless(args.factors.as_deref(), hierarchical, m)?;
            bake(args, method, args.hier.method == MethodArg::Auto, cluster)
        }
        Command::Thermal(args) => {
            if let Some(("thermal", m)) = matches.subcommand() {
                check_meaningless(args.factors.as_deref(), false, m)?;
            }
            thermal(args)
        }
        Command::Factors(args) => {
            args.factors.init_threads()?;
            let bars = Bars {
                bar: Mutex::new(None),
                tty: std::io::stderr().is_terminal() && cluster.is_root(),
            };
            let job = pipeline::FactorsJob {
                scene: &args.scene,
                resolution: args.mesh.resolution()?,
                estimator: &args.factors.choice()?,
                seed: args.factors.seed,
                out_dir: &args.output,
                repair: args.factors.repair,
                reciprocity: args.reciprocity,
                format: args.format,
                max_memory: args.factors.max_memory,
                two_sided: args.two_sided,
            };
            let Some(s) = pipeline::factors_on(&job, &bars, cluster)? else {
                return Ok(());
            };
            use std::fmt::Write;
            let mut o = String::new();
            let p = &s.provenance;
            let d = &s.diagnostics;
            writeln!(
                o,
                "factors of `{}`: {} patches, {} stored, {} rays by {} in {}s",
                p.scene,
                p.patches,
                p.nnz,
                p.rays,
                p.estimator,
                significant(p.seconds, 4)
            )?;
            writeln!(
                o,
                "row sums in [{:.5}, {:.5}], reciprocity error <= {:.1e}{}",
                d.min_row_sum,
                d.max_row_sum,
                d.reciprocity,
                d.reciprocity_scope(p.patches),
            )?;
            writeln!(o, "bounds: {}", s.repair.before.summary())?;
            if p.unresolved > 0.0 {
                writeln!(
                    o,
                    "pairs no ray hit: F = 0 ± {:.1e} (s.e., one-sided; also the bar of each \
                     row's unhit mass)",
                    p.unresolved
                )?;
            }
            if s.repair.repair != Repair::None {
                writeln!(
                    o,
                    "repair {:?}: entries moved by <= {:.2} standard errors; after: {}",
                    s.repair.repair,
                    s.repair.max_shift_sigmas,
                    s.repair.after.summary()
                )?;
            }
            o.push_str(&pipeline::distributed::format_ranks(&s.ranks));
            writeln!(o, "{}", pipeline::format_times(&s.stages, s.peak_memory))?;
            if !p.objects_skipped.is_empty() {
                writeln!(o, "warning: no object tables: {}", p.objects_skipped)?;
            }
            for w in &s.warnings {
                writeln!(o, "warning: {w}")?;
            }
            writeln!(
                o,
                "wrote {}/{{{}, provenance.json, manifest.json}}",
                args.output.display(),
                p.sha256.keys().cloned().collect::<Vec<_>>().join(", ")
            )?;
            print!("{}", pipeline::wrap(&o, pipeline::WIDTH));
            Ok(())
        }
        Command::Study(args) if args.solvers => {
            let output = if args.output == std::path::Path::new("study") {
                PathBuf::from("docs/solvers")
            } else {
                args.output.clone()
            };
            study_solvers(&StudySolversArgs {
                output,
                quick: args.quick,
            })
        }
        Command::StudySolvers(args) => study_solvers(args),
        Command::StudyBakes(args) => study_bakes(args),
        Command::Study(args) => {
            if let Some(n) = args.threads {
                if n == 0 {
                    bail!("--threads must be at least 1");
                }
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build_global()
                    .context("cannot set the thread count")?;
            }
            let settings = if args.quick {
                study::Settings::quick(args.output.clone())
            } else {
                study::Settings::full(args.output.clone())
            };
            let report = study::run(&settings)?;
            print!(
                "{}",
                std::fs::read_to_string(args.output.join("summary.md")).unwrap_or_default()
            );
            println!(
                "study: {} runs in {:.1}s; wrote {} files to {}",
                report.runs.len(),
                report.seconds,
                report.files.len(),
                args.output.display()
            );
            Ok(())
        }
        Command::Bench(a) => {
            let cfg = radiosity::bench::BenchConfig {
                scene: a.scene.clone(),
                patches: a.patches,
                repeats: a.repeats,
                threads: a.threads,
                ftz: !a.no_ftz,
                simd: a.simd,
                packets: a.packets.0,
                seed: 1,
                scaling: a.scaling.clone().unwrap_or_default(),
                area_max: a.area_max,
                out_dir: a.output.clone(),
            };
            radiosity::bench::run(&cfg, &mut |s| println!("{s}"))?;
            Ok(())
        }
        Command::Suite(cmd) => suite(cmd),
        Command::Scenes => {
            use radiosity::scene::generated;
            let width = builtin::NAMES
                .iter()
                .chain(generated::LISTED)
                .chain(generated::LISTED_CITY)
                .map(|n| n.len())
                .max()
                .unwrap_or(0);
            for name in builtin::NAMES {
                let what = builtin::describe(name).unwrap_or_default();
                println!("{name:width$}  {what}");
            }
            for name in generated::LISTED.iter().chain(generated::LISTED_CITY) {
                let what = generated::describe(name).unwrap_or_default();
                println!("{name:width$}  {what}");
            }
            println!(
                "(generated: room-spheres-N for any N in 1..={}, {} triangles per sphere; \
                 room-spheres-N-sL with L in 0..={} subdivisions, 20·4^L triangles per \
                 sphere, at most {} triangles; city-N for any N in 1..={}, N x N buildings)",
                generated::MAX_SPHERES,
                generated::SPHERE_TRIANGLES,
                generated::MAX_SUBDIVISIONS,
                generated::MAX_TRIANGLES,
                generated::MAX_CITY
            );
            Ok(())
        }
    }
}

/// `x` with `digits` significant digits (at least), in plain notation: 17.52, 0.0004120.
fn suite(cmd: &SuiteCommand) -> Result<()> {
    use radiosity::suite::{board, cases, export, run, score};
    match cmd {
        SuiteCommand::Export { dir } => {
            let table = export::export(dir, &cases::all())?;
            let classes: std::collections::BTreeSet<&str> =
                table.cases.iter().map(|c| c.class.as_str()).collect();
            println!(
                "{}: {} cases in {} classes written to {}/{{suite.json, suite.csv, cases/}}",
                table.suite,
                table.cases.len(),
                classes.len(),
                dir.display()
            );
            Ok(())
        }
        SuiteCommand::Run(a) => {
            a.factors.init_threads()?;
            let mesh = MeshArgs {
                patches: a.patches,
                max_edge: a.max_edge,
            };
            let settings = run::Settings {
                resolution: mesh.resolution_or(Resolution::DiagonalFraction(1.0))?,
                estimator: a.factors.choice()?,
                seed: a.factors.seed,
                repair: a.factors.repair,
            };
            let done = run::run(&a.suite, &a.output, &settings, &a.cases, &mut |d| {
                println!(
                    "{:<28} {:>6} patches {:>12} rays {:>10.4}s",
                    d.case, d.patches, d.rays, d.seconds
                )
            })?;
            let total: f64 = done.iter().map(|d| d.seconds).sum();
            println!(
                "{} cases in {}s of form-factor stages; score with `radiosity suite score --suite {} --factors {}`",
                done.len(),
                significant(total, 4),
                a.suite.display(),
                a.output.display()
            );
            Ok(())
        }
        SuiteCommand::Score(a) => {
            if !(a.tolerance >= 0.0 && a.sigmas >= 0.0) {
                bail!("--tolerance and --sigmas must be >= 0");
            }
            let (table, _) = export::read_table(&a.suite)?;
            let answers = match (&a.factors, &a.csv) {
                (Some(dir), _) => score::read_folders(dir, &table)?,
                (None, Some(csv)) => score::read_csv(csv, &table)?,
                (None, None) => bail!("give --factors DIR or --csv FILE"),
            };
            let rule = score::Rule {
                tolerance: a.tolerance,
                sigmas: a.sigmas,
            };
            let s = score::score(&table, &answers, rule, &a.tool, &a.command);
            print!("{}", score::report(&s));
            if let Some(p) = &a.json {
                score::write(p, &s)?;
            }
            if let Some(p) = &a.csv_out {
                score::write(p, &s)?;
            }
            Ok(())
        }
        SuiteCommand::Board { output, scores } => {
            let s = scores
                .iter()
                .map(|p| score::read(p))
                .collect::<radiosity::Result<Vec<_>>>()?;
            for p in board::write(output, &s)? {
                println!("wrote {}", p.display());
            }
            Ok(())
        }
    }
}

fn significant(x: f64, digits: i32) -> String {
    if x <= 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let decimals = (digits - 1 - x.log10().floor() as i32).max(0) as usize;
    format!("{x:.decimals$}")
}
