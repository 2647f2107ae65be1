//! Measurements behind `radiosity bench`: the form-factor stage against raw Embree
//! queries over the same rays, time and peak memory per stage, and scaling in N and in
//! threads. Nothing here asserts a time: it measures and reports, and every ratio it prints
//! compares numbers taken in the same run (interleaved, median of `repeats`).
//!
//! - [`ratio`]: for one estimator, the exact rays its stage casts are recorded once (each
//!   estimator's `row_with` takes its queries through a [`visibility::Tracer`], here a
//!   recorder, and the rays do not depend on the answers); then the whole stage ([`formfactor::compute`]) and two raw loops over the
//!   recorded rays, one query per ray (`rtcOccluded1`, or `rtcIntersect1` for the
//!   hemisphere's closest hits) and 16-ray packets of consecutive rays (`rtcOccluded16`,
//!   `rtcIntersect16`), run alternately on the same rayon pool. The ratio printed is the
//!   stage's rate over the better raw rate.
//! - [`stages`]: load, mesh, BVH, form-factor rows, assembly, solve, output, each with its
//!   wall time and the peak resident memory during it (Linux: `VmHWM` reset through
//!   `/proc/self/clear_refs` before the stage, read after; it includes what earlier stages
//!   still hold).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::formfactor::{
    self, AreaMc, Context, Hemisphere, Nodes, Pattern, Row, Scratch, SemiAnalytic,
};
use crate::mesh::{PatchSet, Resolution};
use crate::output;
use crate::output::chart::{line_chart, Series};
use crate::pipeline::{self, EstimatorChoice};
use crate::scene::Scene;
use crate::solve::{Method, Options};
use crate::visibility::{self, Rays, Segments, Tracer, Visibility, SEGMENT_TNEAR};

/// The rays a form-factor stage casts, recorded.
pub enum Recorded {
    /// Segment rays `(origin, direction, tfar)` for occlusion queries.
    Segments(Vec<(Vec3, Vec3, f32)>),
    /// Rays `(origin, unit direction)` for closest-hit queries.
    Rays(Vec<(Vec3, Vec3)>),
}

impl Recorded {
    /// Number of rays.
    pub fn len(&self) -> usize {
        match self {
            Recorded::Segments(v) => v.len(),
            Recorded::Rays(v) => v.len(),
        }
    }

    /// True when no ray was recorded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A [`Tracer`] that answers every query with a stub (segments free, rays missing) and,
/// when `keep`, records the rays asked for, in order.
struct Recorder {
    keep: bool,
    segments: std::cell::RefCell<Vec<(Vec3, Vec3, f32)>>,
    rays: std::cell::RefCell<Vec<(Vec3, Vec3)>>,
}

impl Recorder {
    fn new(keep: bool) -> Recorder {
        Recorder {
            keep,
            segments: Default::default(),
            rays: Default::default(),
        }
    }
}

impl Tracer for Recorder {
    fn segments_visible(&self, segs: &Segments, out: &mut [bool]) {
        if self.keep {
            let mut v = self.segments.borrow_mut();
            v.extend((0..segs.len()).map(|k| segs.ray(k)));
        }
        out.fill(true);
    }

    fn first_front_hits(&self, rays: &Rays, out: &mut [u32]) {
        if self.keep {
            let mut v = self.rays.borrow_mut();
            v.extend((0..rays.len()).map(|k| rays.ray(k)));
        }
        out.fill(visibility::NO_HIT);
    }
}

/// Records the rays the stage of `choice` casts, in row order.
pub fn record(ctx: &Context, choice: &EstimatorChoice) -> Recorded {
    replay(ctx, choice, true).0
}

/// The stage of `choice` with its queries answered by a stub: the rays are made and, when
/// `keep`, recorded in row order; otherwise only counted (the rate of everything but the
/// queries, with no memory traffic of its own). Returns the rays recorded and their count.
fn replay(ctx: &Context, choice: &EstimatorChoice, keep: bool) -> (Recorded, u64) {
    let n = ctx.patches.len();
    let count = AtomicU64::new(0);
    let rec = match *choice {
        EstimatorChoice::Hemisphere { strata, replicates } => {
            let est = Hemisphere { strata, replicates };
            Recorded::Rays(
                (0..n)
                    .into_par_iter()
                    .map_init(
                        || (Recorder::new(keep), Scratch::default()),
                        |(rec, scratch), i| {
                            // One reused buffer per worker, copied out at its exact size.
                            rec.rays.borrow_mut().clear();
                            let mut row = Row::default();
                            est.row_with(ctx, i, &mut row, rec, scratch);
                            count.fetch_add(row.rays, Ordering::Relaxed);
                            rec.rays.borrow().clone()
                        },
                    )
                    .collect::<Vec<_>>()
                    .concat(),
            )
        }
        _ => {
            let semi = match *choice {
                EstimatorChoice::SemiAnalytic {
                    points,
                    rays,
                    replicates,
                    tol,
                } => Some(SemiAnalytic::new(Nodes::Gauss, points, rays, replicates).with_tol(tol)),
                _ => None,
            };
            let area = match *choice {
                EstimatorChoice::AreaStratified { strata, replicates } => {
                    Some(AreaMc::new(Pattern::Stratified, strata, replicates))
                }
                EstimatorChoice::AreaUniform { strata, replicates } => {
                    Some(AreaMc::new(Pattern::Uniform, strata, replicates))
                }
                EstimatorChoice::AreaSobol { strata, replicates } => {
                    Some(AreaMc::new(Pattern::Sobol, strata, replicates))
                }
                _ => None,
            };
            Recorded::Segments(
                (0..n)
                    .into_par_iter()
                    .map_init(
                        || (Recorder::new(keep), Scratch::default()),
                        |(rec, scratch), i| {
                            rec.segments.borrow_mut().clear();
                            let mut row = Row::default();
                            match *choice {
                                EstimatorChoice::AreaStratified { .. }
                                | EstimatorChoice::AreaUniform { .. }
                                | EstimatorChoice::AreaSobol { .. } => area
                                    .as_ref()
                                    .expect("built above")
                                    .row_with(ctx, i, &mut row, rec, scratch),
                                EstimatorChoice::SemiAnalytic { .. } => semi
                                    .as_ref()
                                    .expect("built above")
                                    .row_with(ctx, i, &mut row, rec, scratch),
                                // Measured by the closest-hit branch above, or not ray-driven per
                                // pair (the hemicube casts one ray per cell): nothing to record.
                                EstimatorChoice::Hemisphere { .. }
                                | EstimatorChoice::Hemicube { .. } => {}
                            }
                            count.fetch_add(row.rays, Ordering::Relaxed);
                            rec.segments.borrow().clone()
                        },
                    )
                    .collect::<Vec<_>>()
                    .concat(),
            )
        }
    };
    (rec, count.into_inner())
}

/// The raw Embree loop over recorded rays, one query per ray (`rtcOccluded1` or
/// `rtcIntersect1`), in chunks over the current rayon pool. Returns a checksum.
pub fn raw_loop(vis: &Visibility, rec: &Recorded) -> u64 {
    let (e, tnear) = (vis.raw(), vis.offsets().floor);
    match rec {
        Recorded::Segments(v) => v
            .par_chunks(4096)
            .map(|ch| {
                ch.iter()
                    .filter(|r| e.occluded1(r.0, r.1, SEGMENT_TNEAR, r.2))
                    .count() as u64
            })
            .sum(),
        Recorded::Rays(v) => v
            .par_chunks(4096)
            .map(|ch| {
                ch.iter()
                    .filter_map(|r| e.intersect1(r.0, r.1, tnear, f32::INFINITY))
                    .map(|h| h.prim as u64)
                    .sum::<u64>()
            })
            .sum(),
    }
}

/// The raw loop with 16-ray packets over consecutive recorded rays: `rtcOccluded16` for
/// segments, `rtcIntersect16` for closest-hit rays. Returns a checksum.
pub fn raw_loop16(vis: &Visibility, rec: &Recorded) -> u64 {
    let (e, tnear) = (vis.raw(), vis.offsets().floor);
    match rec {
        // The copies into packets at the sampling passes' width, as in the stage.
        Recorded::Segments(v) => v
            .par_chunks(4096)
            .map(|ch| {
                crate::simd::with_widest(
                    #[inline(always)]
                    || {
                        let mut out = [false; 16];
                        let mut rays = [(Vec3::ZERO, Vec3::ZERO, 0.0, 0.0); 16];
                        let mut c = 0u64;
                        for p in ch.chunks(16) {
                            for (k, r) in p.iter().enumerate() {
                                rays[k] = (r.0, r.1, SEGMENT_TNEAR, r.2);
                            }
                            e.occluded16(&rays[..p.len()], &mut out);
                            c += out[..p.len()].iter().filter(|&&o| o).count() as u64;
                        }
                        c
                    },
                )
            })
            .sum(),
        Recorded::Rays(v) => v
            .par_chunks(4096)
            .map(|ch| {
                crate::simd::with_widest(
                    #[inline(always)]
                    || {
                        let (mut out, mut against) = ([0u32; 16], [false; 16]);
                        let mut packet = visibility::HitPacket16::new();
                        let mut soa = [[0f32; 16]; 6];
                        let mut c = 0u64;
                        for p in ch.chunks(16) {
                            for (k, r) in p.iter().enumerate() {
                                for (a, v) in soa
                                    .iter_mut()
                                    .zip([r.0.x, r.0.y, r.0.z, r.1.x, r.1.y, r.1.z])
                                {
                                    a[k] = v;
                                }
                            }
                            let n = p.len();
                            let [ox, oy, oz, dx, dy, dz] = &soa;
                            e.intersect16_soa(
                                &mut packet,
                                [&ox[..n], &oy[..n], &oz[..n]],
                                [&dx[..n], &dy[..n], &dz[..n]],
                                tnear,
                                &mut out,
                                &mut against,
                            );
                            c += out[..n].iter().map(|&h| h as u64).sum::<u64>();
                        }
                        c
                    },
                )
            })
            .sum(),
    }
}

/// One line of the stage-versus-raw table.
#[derive(Clone, Debug)]
pub struct RatioLine {
    /// Estimator name.
    pub estimator: String,
    /// Patches.
    pub patches: usize,
    /// Rays per stage run.
    pub rays: u64,
    /// Form-factor stage, rays per second (median).
    pub stage: f64,
    /// Raw single-ray loop, rays per second (median).
    pub raw: f64,
    /// Raw 16-ray packet loop, rays per second (median).
    pub raw16: f64,
    /// The stage with the queries replaced by a recorder, rays per second (one run).
    pub sampling: f64,
    /// Per repeat, the stage rate over the best raw rate of the same repeat (the three
    /// samples run back to back, so that load on the machine lasting longer than one
    /// repeat weighs on both sides of the ratio), in time order.
    pub ratios: Vec<f64>,
}

impl RatioLine {
    /// Stage rate over the best raw rate (single rays or packets, whichever Embree runs
    /// faster on these rays): how close the stage comes to Embree's own limit. The median
    /// over the repeats of the ratio within each repeat ([`RatioLine::ratios`]).
    pub fn ratio(&self) -> f64 {
        median(self.ratios.clone())
    }

    /// Smallest and largest ratio within a repeat.
    pub fn ratio_range(&self) -> (f64, f64) {
        let lo = self.ratios.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = self
            .ratios
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        (lo, hi)
    }
}

/// `slow[r] / fast[r]` for every repeat r.
fn paired(slow: &[f64], fast: &[f64]) -> Vec<f64> {
    slow.iter().zip(fast).map(|(s, f)| s / f).collect()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Shortest timed sample: a sample repeats its loop until it lasts about this long, so that
/// short stages are not timed at the resolution of scheduler noise.
pub const MIN_SAMPLE: f64 = 0.2;

/// Times the form-factor stage of `choice` against the raw loops over the same rays,
/// alternating, `repeats` samples each, on the current rayon pool. Every sample runs its
/// loop `k` times back to back, `k` chosen once (from a first, untimed stage run) so that a
/// sample lasts about [`MIN_SAMPLE`]; the rates are medians over the samples.
pub fn ratio(ctx: &Context, choice: &EstimatorChoice, repeats: usize) -> RatioLine {
    let est = choice.build();
    let t = Instant::now();
    let (_, made) = replay(ctx, choice, false);
    let sampling = made as f64 / t.elapsed().as_secs_f64();
    let rec = record(ctx, choice);
    let t = Instant::now();
    let rays = formfactor::compute(ctx, est.as_ref(), &|_| {}).rays;
    let k = (MIN_SAMPLE / t.elapsed().as_secs_f64())
        .ceil()
        .clamp(1.0, 1000.0) as usize;
    debug_assert_eq!(rays as usize, rec.len());
    let per = (k as u64 * rays) as f64;
    let time = |f: &dyn Fn()| {
        let t = Instant::now();
        for _ in 0..k {
            f();
        }
        per / t.elapsed().as_secs_f64()
    };
    let (mut stage, mut raw, mut raw16) = (Vec::new(), Vec::new(), Vec::new());
    let mut ratios = Vec::new();
    for _ in 0..repeats.max(1) {
        stage.push(time(&|| {
            drop(formfactor::compute(ctx, est.as_ref(), &|_| {}))
        }));
        raw.push(time(&|| {
            std::hint::black_box(raw_loop(ctx.vis, &rec));
        }));
        raw16.push(time(&|| {
            std::hint::black_box(raw_loop16(ctx.vis, &rec));
        }));
        let best = raw.last().unwrap().max(*raw16.last().unwrap());
        ratios.push(stage.last().unwrap() / best);
    }
    RatioLine {
        estimator: est.name(),
        patches: ctx.patches.len(),
        rays,
        stage: median(stage),
        raw: median(raw),
        raw16: median(raw16),
        sampling,
        ratios,
    }
}

/// Formats the stage-versus-raw table.
pub fn format_ratios(lines: &[RatioLine], threads: usize) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let _ = writeln!(
        o,
        "form-factor stage vs raw Embree over the same rays ({threads} threads, medians):"
    );
    let _ = writeln!(
        o,
        "{:<40} {:>8} {:>11} {:>13} {:>13} {:>15} {:>10} {:>13} {:>16}",
        "estimator",
        "patches",
        "rays",
        "stage Mray/s",
        "raw1 Mray/s",
        "raw16 Mray/s",
        "stage/best",
        "range",
        "no-query Mray/s"
    );
    for l in lines {
        let (lo, hi) = l.ratio_range();
        let _ = writeln!(
            o,
            "{:<40} {:>8} {:>11} {:>13.3} {:>13.3} {:>15.3} {:>10.3} {:>13} {:>16.3}",
            l.estimator,
            l.patches,
            l.rays,
            l.stage / 1e6,
            l.raw / 1e6,
            l.raw16 / 1e6,
            l.ratio(),
            format!("{lo:.3}-{hi:.3}"),
            l.sampling / 1e6
        );
    }
    let _ = writeln!(
        o,
        "stage/best: median over the repeats of the stage rate over the faster raw loop, each \
         repeat's three samples timed back to back; range: its smallest and largest value"
    );
    o
}

/// Wall time and peak resident memory of one stage.
#[derive(Clone, Debug)]
pub struct StageLine {
    /// Stage name.
    pub stage: &'static str,
    /// Wall-clock seconds.
    pub seconds: f64,
    /// Peak resident bytes during the stage (0 when unknown).
    pub peak: u64,
}

/// Resets the kernel's peak-RSS mark (Linux >= 4.0); false when it cannot.
fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

struct Stages(Vec<StageLine>);

impl Stages {
    fn run<T>(&mut self, stage: &'static str, f: impl FnOnce() -> T) -> T {
        reset_peak();
        let t = Instant::now();
        let out = f();
        let seconds = t.elapsed().as_secs_f64();
        self.0.push(StageLine {
            stage,
            seconds,
            peak: pipeline::peak_memory(),
        });
        out
    }
}

/// What [`stages`] measured.
#[derive(Clone, Debug)]
pub struct StageReport {
    /// Scene name.
    pub scene: String,
    /// Patches.
    pub patches: usize,
    /// Estimator name.
    pub estimator: String,
    /// Rays cast.
    pub rays: u64,
    /// Stored factors.
    pub nnz: usize,
    /// Bytes the factor matrix's entries held per stored factor (measured).
    pub bytes_per_factor: f64,
    /// Bytes of the matrix's row pointers.
    pub row_pointer_bytes: usize,
    /// Per stage.
    pub stages: Vec<StageLine>,
    /// Solver iterations.
    pub iterations: usize,
    /// Why the solve failed, if it did.
    pub solve_error: Option<String>,
    /// CPU seconds of the whole run, every stage and thread
    /// ([`crate::cluster::cpu_seconds`]).
    pub cpu_seconds: f64,
    /// CPU seconds of the form-factor stage (rows and assembly).
    pub factor_cpu_seconds: f64,
    /// Seconds inside Embree's queries, summed over threads, timed around each call
    /// ([`Visibility::time_queries`]).
    pub query_seconds: f64,
    /// Wall seconds of the form-factor stage times the threads that ran it.
    pub factor_thread_seconds: f64,
}

impl StageReport {
    /// Share of the form-factor stage's thread time spent inside Embree's calls: the
    /// calls' wall time over the stage's wall time times its threads. Both are wall
    /// times, so time the system gives to other processes counts on both sides in
    /// proportion (a ratio of wall time in the calls to CPU time would not be).
    pub fn embree_share_of_factors(&self) -> f64 {
        self.query_seconds / self.factor_thread_seconds.max(1e-12)
    }

    /// Share of the whole run's CPU time spent inside Embree's calls: the stage's share
    /// ([`StageReport::embree_share_of_factors`]) of the stage's CPU time, over the CPU
    /// time of every stage.
    pub fn embree_share_of_bake(&self) -> f64 {
        self.embree_share_of_factors() * self.factor_cpu_seconds / self.cpu_seconds.max(1e-12)
    }
}

impl StageReport {
    /// Seconds of a stage (0 when absent).
    pub fn seconds(&self, stage: &str) -> f64 {
        self.stages
            .iter()
            .filter(|s| s.stage == stage)
            .map(|s| s.seconds)
            .sum()
    }

    /// Largest peak over all stages.
    pub fn peak(&self) -> u64 {
        self.stages.iter().map(|s| s.peak).max().unwrap_or(0)
    }
}

/// Runs the bake's stages once, timing each: load, mesh, BVH, form-factor rows,
/// assembly, solve (Gauss–Seidel, default options), output (per-vertex values and the EXR,
/// written into `out_dir`).
pub fn stages(
    scene: &str,
    resolution: Resolution,
    choice: &EstimatorChoice,
    seed: u64,
    out_dir: &Path,
) -> Result<StageReport> {
    let cpu0 = crate::cluster::cpu_seconds();
    let mut st = Stages(Vec::new());
    let scene = st.run("load", || crate::pipeline::load_scene(scene, false))?;
    let patches = st.run("mesh", || PatchSet::build(&scene, resolution))?;
    let vis = st.run("bvh", || Visibility::new(&patches))?;
    let est = choice.build();
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed,
    };
    reset_peak();
    vis.time_queries(true);
    let ff_cpu0 = crate::cluster::cpu_seconds();
    let ff_wall = Instant::now();
    let (ff, split) = formfactor::compute_timed(&ctx, est.as_ref(), &|_| {});
    let factor_thread_seconds =
        ff_wall.elapsed().as_secs_f64() * rayon::current_num_threads() as f64;
    let factor_cpu_seconds = crate::cluster::cpu_seconds() - ff_cpu0;
    let query_seconds = vis.query_seconds();
    vis.time_queries(false);
    let peak = pipeline::peak_memory();
    st.0.push(StageLine {
        stage: "form factors",
        seconds: split.rows,
        peak,
    });
    st.0.push(StageLine {
        stage: "assembly",
        seconds: split.assembly,
        peak,
    });
    drop(vis);
    let (rays, nnz) = (ff.rays, ff.f.nnz());
    let bytes_per_factor = ff.entry_bytes() as f64 / nnz.max(1) as f64;
    let row_pointer_bytes = ff.row_pointer_bytes();
    let solved = st.run("solve", || {
        pipeline::solve_radiosity(&patches, &ff, Method::default(), &Options::default())
    });
    // A solve that fails (e.g. area-to-area rows summing far above 1 on the cube's shared
    // edges) is reported, and the output stage then writes the emission only.
    let (b, iterations, solve_error) = match solved {
        Ok((b, report)) => (b, report.iterations, None),
        Err(e) => (
            (0..patches.len()).map(|i| patches.emit(i)).collect(),
            0,
            Some(e.to_string()),
        ),
    };
    let name = ff.estimator.clone();
    drop(ff);
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    st.run("output", || -> Result<()> {
        let verts = output::interpolate(&patches, &b, output::DEFAULT_CREASE_DEG);
        output::write_exr(&out_dir.join("radiosity.exr"), &verts, &scene.name)
    })?;
    Ok(StageReport {
        scene: scene.name.clone(),
        patches: patches.len(),
        estimator: name,
        rays,
        nnz,
        bytes_per_factor,
        row_pointer_bytes,
        stages: st.0,
        iterations,
        solve_error,
        cpu_seconds: crate::cluster::cpu_seconds() - cpu0,
        factor_cpu_seconds,
        query_seconds,
        factor_thread_seconds,
    })
}

/// Formats stage reports as one table (seconds and peak MiB per stage).
pub fn format_stages(reports: &[StageReport]) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let Some(first) = reports.first() else {
        return o;
    };
    let _ = write!(
        o,
        "{:<8} {:>8} {:<34} {:>11} {:>11}",
        "scene", "patches", "estimator", "rays", "factors"
    );
    for s in &first.stages {
        let _ = write!(o, " {:>22}", format!("{} s / MiB", s.stage));
    }
    let _ = writeln!(
        o,
        " {:>9} {:>10} {:>11}",
        "B/factor", "Embree/ff", "Embree/bake"
    );
    for r in reports {
        let _ = write!(
            o,
            "{:<8} {:>8} {:<34} {:>11} {:>11}",
            r.scene, r.patches, r.estimator, r.rays, r.nnz
        );
        for s in &r.stages {
            let _ = write!(
                o,
                " {:>22}",
                format!("{:.3} / {:.0}", s.seconds, s.peak as f64 / 1048576.0)
            );
        }
        let _ = writeln!(
            o,
            " {:>9.2} {:>10.3} {:>11.3}",
            r.bytes_per_factor,
            r.embree_share_of_factors(),
            r.embree_share_of_bake()
        );
        if let Some(e) = &r.solve_error {
            let _ = writeln!(
                o,
                "  (solve failed: {})",
                e.chars().take(160).collect::<String>()
            );
        }
    }
    o
}

/// What a benchmark table says about where it was measured.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Machine {
    /// CPU model (`/proc/cpuinfo`'s `model name`; empty when unknown).
    pub cpu: String,
    /// Logical cores the system offers.
    pub cores: usize,
    /// Worker threads the run used.
    pub threads: usize,
    /// Program name and version.
    pub version: String,
    /// When the table was written: UTC, ISO 8601.
    pub date: String,
}

impl Machine {
    /// This machine, for a run on `threads` workers.
    pub fn here(threads: usize) -> Machine {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|t| {
                t.lines()
                    .find(|l| l.starts_with("model name"))
                    .and_then(|l| l.split_once(':'))
                    .map(|(_, v)| v.trim().to_string())
            })
            .unwrap_or_default();
        let secs = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        Machine {
            cpu,
            cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            threads,
            version: format!("radiosity {}", env!("CARGO_PKG_VERSION")),
            date: utc_iso8601(secs),
        }
    }
}

/// `secs` after the Unix epoch as `YYYY-MM-DDTHH:MM:SSZ` (the proleptic Gregorian
/// calendar; days to civil date by Hinnant's algorithm, "chrono-Compatible Low-Level Date
/// Algorithms").
pub fn utc_iso8601(secs: u64) -> String {
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem / 60 % 60,
        rem % 60
    )
}

/// JSON of stage reports with the machine they were measured on: `{"machine": {...},
/// "cases": [{"scene", "patches", "estimator", "rays", "factors", "bytes_per_factor",
/// "row_pointer_bytes", "stages": [{"stage", "seconds", "peak_bytes"}]}]}`.
pub fn stages_json(reports: &[StageReport], machine: &Machine) -> String {
    let cases: Vec<serde_json::Value> = reports
        .iter()
        .map(|r| {
            serde_json::json!({
                "scene": r.scene,
                "patches": r.patches,
                "estimator": r.estimator,
                "rays": r.rays,
                "factors": r.nnz,
                "bytes_per_factor": r.bytes_per_factor,
                "row_pointer_bytes": r.row_pointer_bytes,
                "solve_error": r.solve_error,
                "cpu_seconds": r.cpu_seconds,
                "form_factor_cpu_seconds": r.factor_cpu_seconds,
                "embree_query_seconds": r.query_seconds,
                "form_factor_thread_seconds": r.factor_thread_seconds,
                "embree_share_of_form_factors": r.embree_share_of_factors(),
                "embree_share_of_bake": r.embree_share_of_bake(),
                "stages": r.stages.iter().map(|s| serde_json::json!({
                    "stage": s.stage,
                    "seconds": s.seconds,
                    "peak_bytes": s.peak,
                })).collect::<Vec<_>>(),
            })
        })
        .collect();
    let doc = serde_json::json!({ "machine": machine, "cases": cases });
    serde_json::to_string_pretty(&doc).unwrap_or_default() + "\n"
}

/// The scaling run as a chart (`base.svg`, `base.png`): seconds of the form-factor stage
/// (rows and assembly) against patches, log-log, a line per scene and estimator.
pub fn scaling_chart(base: &Path, reports: &[StageReport]) -> Result<Vec<std::path::PathBuf>> {
    let mut series: Vec<Series> = Vec::new();
    for r in reports {
        let name = format!("{} {}", r.scene, r.estimator);
        let point = (
            r.patches as f64,
            (r.seconds("form factors") + r.seconds("assembly")).max(1e-6),
        );
        match series.iter_mut().find(|s| s.name == name) {
            Some(s) => s.points.push(point),
            None => series.push(Series::new(name, vec![point])),
        }
    }
    line_chart(
        base,
        "form factors: time against patches",
        "patches",
        "seconds (form factors + assembly)",
        true,
        true,
        &series,
    )
}

/// JSON of a `radiosity bench` run: `{"machine", "scene", "ratios": [{"estimator",
/// "patches", "rays", "stage_rays_per_s", "raw1_rays_per_s", "raw16_rays_per_s",
/// "no_query_rays_per_s", "stage_over_best", "per_repeat"}], "stages": [as in
/// [`stages_json`]]}`: the printed tables, for scripts.
pub fn bench_json(
    scene: &str,
    lines: &[RatioLine],
    reports: &[StageReport],
    machine: &Machine,
) -> String {
    let ratios: Vec<serde_json::Value> = lines
        .iter()
        .map(|l| {
            serde_json::json!({
                "estimator": l.estimator,
                "patches": l.patches,
                "rays": l.rays,
                "stage_rays_per_s": l.stage,
                "raw1_rays_per_s": l.raw,
                "raw16_rays_per_s": l.raw16,
                "no_query_rays_per_s": l.sampling,
                "stage_over_best": l.ratio(),
                "per_repeat": l.ratios,
            })
        })
        .collect();
    let stages: serde_json::Value = serde_json::from_str(&stages_json(reports, machine))
        .map(|mut v: serde_json::Value| v["cases"].take())
        .unwrap_or_default();
    let doc = serde_json::json!({
        "machine": machine,
        "scene": scene,
        "ratios": ratios,
        "stages": stages,
    });
    serde_json::to_string_pretty(&doc).unwrap_or_default() + "\n"
}

/// CSV of stage reports: one line per (case, stage).
pub fn stages_csv(reports: &[StageReport]) -> String {
    let mut o = String::from("scene,patches,estimator,rays,factors,stage,seconds,peak_bytes\n");
    for r in reports {
        for s in &r.stages {
            o.push_str(&format!(
                "{},{},\"{}\",{},{},{},{:.6},{}\n",
                r.scene, r.patches, r.estimator, r.rays, r.nnz, s.stage, s.seconds, s.peak
            ));
        }
    }
    o
}

/// Least-squares slope of `log y` against `log x` (NaN with fewer than two usable points).
pub fn loglog_slope(points: &[(f64, f64)]) -> f64 {
    let p: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 0.0)
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    crate::study::ls_slope(&p)
}

/// A rayon pool of `threads` workers, each with flush-to-zero and denormals-are-zero
/// set when `ftz` (see [`visibility::flush_denormals`]).
pub fn pool(threads: usize, ftz: bool) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .start_handler(move |_| {
            if ftz {
                visibility::flush_denormals();
            }
        })
        .build()
        .map_err(|e| Error::Config(format!("cannot build a {threads}-thread pool: {e}")))
}

/// What `radiosity bench` runs.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// Scene of the ratio table.
    pub scene: String,
    /// Patches of the ratio table.
    pub patches: usize,
    /// Repeats per measurement (medians are reported).
    pub repeats: usize,
    /// Worker threads (0: all cores).
    pub threads: usize,
    /// Set flush-to-zero / denormals-are-zero on the workers.
    pub ftz: bool,
    /// Widest vector width the sampling passes may use ([`crate::simd`]).
    pub simd: crate::simd::Width,
    /// How 16-ray packets go to Embree (None: as the library runs them natively).
    pub packets: Option<crate::visibility::PacketWidth>,
    /// Seed.
    pub seed: u64,
    /// Patch counts of the scaling run (empty: no scaling run).
    pub scaling: Vec<usize>,
    /// Largest patch count at which the scaling run also does area-to-area.
    pub area_max: usize,
    /// Where the scaling CSV and the EXR files go.
    pub out_dir: std::path::PathBuf,
}

fn estimators() -> [EstimatorChoice; 3] {
    [
        EstimatorChoice::AreaStratified {
            strata: 4,
            replicates: 4,
        },
        EstimatorChoice::Hemisphere {
            strata: 16,
            replicates: 4,
        },
        EstimatorChoice::SemiAnalytic {
            points: 3,
            rays: 2,
            replicates: 4,
            tol: SemiAnalytic::DEFAULT_TOL,
        },
    ]
}

/// True for estimators whose rays grow as N² (all pairs).
fn quadratic(c: &EstimatorChoice) -> bool {
    !matches!(c, EstimatorChoice::Hemisphere { .. })
}

/// Runs `radiosity bench`, printing as it goes through `print`.
pub fn run(cfg: &BenchConfig, print: &mut dyn FnMut(&str)) -> Result<()> {
    let threads = if cfg.threads == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        cfg.threads
    };
    let pool = pool(threads, cfg.ftz)?;
    crate::simd::set_limit(cfg.simd);
    if cfg.scaling.is_empty() {
        let scene = crate::pipeline::load_scene(&cfg.scene, false)?;
        let patches = PatchSet::build(&scene, Resolution::Patches(cfg.patches))?;
        let mut vis = Visibility::new(&patches)?;
        if let Some(w) = cfg.packets {
            vis.set_packet_width(w);
        }
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: cfg.seed,
        };
        let lines: Vec<RatioLine> = pool.install(|| {
            estimators()
                .iter()
                .filter(|c| cfg.patches <= cfg.area_max || !quadratic(c))
                .map(|c| ratio(&ctx, c, cfg.repeats))
                .collect()
        });
        print(&format!(
            "scene `{}`, Embree {}, packets {}, ftz/daz {}, sampling passes {}",
            cfg.scene,
            vis.embree_version(),
            vis.packet_width(),
            if cfg.ftz { "on" } else { "off" },
            crate::simd::active()
        ));
        print(&format_ratios(&lines, threads));
        let reports = pool.install(|| -> Result<Vec<StageReport>> {
            estimators()
                .iter()
                .filter(|c| cfg.patches <= cfg.area_max || !quadratic(c))
                .map(|c| {
                    stages(
                        &cfg.scene,
                        Resolution::Patches(cfg.patches),
                        c,
                        cfg.seed,
                        &cfg.out_dir,
                    )
                })
                .collect()
        })?;
        print(
            "time and peak memory per stage (one run each); Embree/ff and Embree/bake: the \
             time inside Embree's calls (timed around each, summed over threads) over the \
             form-factor stage's thread time, and that share of its CPU time over the whole \
             run's CPU time:",
        );
        print(&format_stages(&reports));
        std::fs::create_dir_all(&cfg.out_dir).map_err(|e| Error::io(&cfg.out_dir, e))?;
        let json = cfg.out_dir.join("bench.json");
        let doc = bench_json(&cfg.scene, &lines, &reports, &Machine::here(threads));
        std::fs::write(&json, doc).map_err(|e| Error::io(&json, e))?;
        print(&format!("wrote {}", json.display()));
        return Ok(());
    }
    scaling(cfg, &pool, threads, print)
}

fn scaling(
    cfg: &BenchConfig,
    pool: &rayon::ThreadPool,
    threads: usize,
    print: &mut dyn FnMut(&str),
) -> Result<()> {
    let hemi = EstimatorChoice::Hemisphere {
        strata: 16,
        replicates: 4,
    };
    let area = EstimatorChoice::AreaStratified {
        strata: 4,
        replicates: 4,
    };
    let mut all = Vec::new();
    for scene in ["cornell", "cube"] {
        for choice in [&hemi, &area] {
            let mut reports = Vec::new();
            for &n in &cfg.scaling {
                if matches!(choice, EstimatorChoice::AreaStratified { .. }) && n > cfg.area_max {
                    continue;
                }
                let r = pool.install(|| {
                    stages(
                        scene,
                        Resolution::Patches(n),
                        choice,
                        cfg.seed,
                        &cfg.out_dir,
                    )
                })?;
                print(&format_stages(std::slice::from_ref(&r)));
                reports.push(r);
            }
            // A slope from two sizes is a ratio, not a fit: at least three.
            if reports.len() >= 3 {
                let mut line = format!(
                    "log-log slope in N ({} sizes), {scene}, {}:",
                    reports.len(),
                    reports[0].estimator
                );
                for s in &reports[0].stages {
                    let pts: Vec<(f64, f64)> = reports
                        .iter()
                        .map(|r| (r.patches as f64, r.seconds(s.stage)))
                        .collect();
                    line.push_str(&format!(" {} {:.2},", s.stage, loglog_slope(&pts)));
                }
                let pts: Vec<(f64, f64)> = reports
                    .iter()
                    .map(|r| (r.patches as f64, r.peak() as f64))
                    .collect();
                line.push_str(&format!(" peak memory {:.2}", loglog_slope(&pts)));
                print(&line);
            }
            all.extend(reports);
        }
    }
    print("\nall cases:");
    print(&format_stages(&all));
    std::fs::create_dir_all(&cfg.out_dir).map_err(|e| Error::io(&cfg.out_dir, e))?;
    let csv = cfg.out_dir.join("scaling.csv");
    std::fs::write(&csv, stages_csv(&all)).map_err(|e| Error::io(&csv, e))?;
    let json = cfg.out_dir.join("scaling.json");
    let table = stages_json(&all, &Machine::here(threads));
    std::fs::write(&json, table).map_err(|e| Error::io(&json, e))?;
    print(&format!("wrote {} and {}", csv.display(), json.display()));
    let charts = scaling_chart(&cfg.out_dir.join("scaling"), &all)?;
    let names: Vec<String> = charts.iter().map(|p| p.display().to_string()).collect();
    print(&format!("wrote {}", names.join(" and ")));

    // Acceptance case and parallel efficiency: cube 32 x 32 per face, 1,024 rays per patch.
    let scene = Scene::load("cube")?;
    let patches = PatchSet::build(&scene, Resolution::MaxEdge(1.0 / 32.0))?;
    let vis = Visibility::new(&patches)?;
    let ctx = Context {
        patches: &patches,
        vis: &vis,
        seed: cfg.seed,
    };
    let est = hemi.build();
    let one = self::pool(1, cfg.ftz)?;
    let (mut t1, mut tn) = (Vec::new(), Vec::new());
    let mut rays = 0;
    for _ in 0..cfg.repeats.max(1) {
        for (p, v) in [(&one, &mut t1), (pool, &mut tn)] {
            // The matrix is freed on the pool that made it (untimed), where its memory is
            // reused: freed on another thread, it waits in the heap of a worker that may
            // sleep through the next run, which then takes fresh pages from the kernel.
            let (dt, r) = p.install(|| {
                let t = Instant::now();
                let ff = formfactor::compute(&ctx, est.as_ref(), &|_| {});
                let dt = t.elapsed().as_secs_f64();
                (dt, ff.rays)
            });
            v.push(dt);
            rays = r;
        }
    }
    // Speed-up within each repeat (1 thread, then all, back to back), then the median.
    let speedups = paired(&t1, &tn);
    let (t1, tn) = (median(t1), median(tn));
    // The ceiling this machine allows: the raw packet loop over the same rays, 1 thread
    // against all, interleaved the same way.
    let rec = record(&ctx, &hemi);
    let (mut r1, mut rn) = (Vec::new(), Vec::new());
    for _ in 0..cfg.repeats.max(1) {
        for (p, v) in [(&one, &mut r1), (pool, &mut rn)] {
            v.push(p.install(|| {
                let t = Instant::now();
                std::hint::black_box(raw_loop16(&vis, &rec));
                t.elapsed().as_secs_f64()
            }));
        }
    }
    let raw_speedups = paired(&r1, &rn);
    let range = |v: &[f64]| {
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        format!("{lo:.2}-{hi:.2}")
    };
    let speedup = median(speedups.clone());
    print(&format!(
        "cube 32x32 per face ({} patches, {} rays, {}): form factors {:.3} s with {threads} threads, {:.3} s with 1 (medians); speed-up {:.2}x (median of {} repeats, range {}; efficiency {:.0}%); the raw rtcIntersect16 loop over the same rays: speed-up {:.2}x (range {})",
        patches.len(),
        rays,
        est.name(),
        tn,
        t1,
        speedup,
        speedups.len(),
        range(&speedups),
        100.0 * speedup / threads as f64,
        median(raw_speedups.clone()),
        range(&raw_speedups)
    ));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_are_utc_iso8601() {
        assert_eq!(utc_iso8601(0), "1970-01-01T00:00:00Z");
        assert_eq!(utc_iso8601(951_782_400), "2000-02-29T00:00:00Z");
        // As `date -u -d @1796180645` prints it.
        assert_eq!(utc_iso8601(1_796_180_645), "2026-12-02T03:04:05Z");
    }

    #[test]
    fn the_json_table_names_the_machine() {
        let m = Machine::here(2);
        assert_eq!(m.threads, 2);
        assert!(m.cores >= 1 && m.version.starts_with("radiosity ") && m.date.ends_with('Z'));
        let r = StageReport {
            scene: "cube".into(),
            patches: 6,
            estimator: "semi".into(),
            rays: 10,
            nnz: 30,
            bytes_per_factor: 16.0,
            row_pointer_bytes: 56,
            stages: vec![StageLine {
                stage: "form factors",
                seconds: 0.5,
                peak: 1024,
            }],
            iterations: 3,
            solve_error: None,
            cpu_seconds: 1.0,
            factor_cpu_seconds: 0.8,
            query_seconds: 0.6,
            factor_thread_seconds: 1.2,
        };
        let v: serde_json::Value =
            serde_json::from_str(&stages_json(std::slice::from_ref(&r), &m)).unwrap();
        assert_eq!(v["machine"]["threads"], 2);
        assert_eq!(v["cases"][0]["stages"][0]["stage"], "form factors");
        assert_eq!(v["cases"][0]["factors"], 30);
        // 0.6 s in Embree over 1.2 thread-seconds of the stage; the stage's 0.8 CPU-s of
        // the run's 1.0.
        assert!(
            (v["cases"][0]["embree_share_of_form_factors"]
                .as_f64()
                .unwrap()
                - 0.5)
                .abs()
                < 1e-12
        );
        assert!((v["cases"][0]["embree_share_of_bake"].as_f64().unwrap() - 0.4).abs() < 1e-12);
        // The plain bench's table: ratios and stages, with the machine.
        let line = RatioLine {
            estimator: "hemisphere".into(),
            patches: 6,
            rays: 10,
            stage: 9.0,
            raw: 8.0,
            raw16: 10.0,
            sampling: 100.0,
            ratios: vec![0.8, 0.9, 1.0],
        };
        let v: serde_json::Value =
            serde_json::from_str(&bench_json("cube", std::slice::from_ref(&line), &[r], &m))
                .unwrap();
        assert_eq!(v["machine"]["cores"], m.cores);
        assert_eq!(v["scene"], "cube");
        assert_eq!(v["ratios"][0]["stage_over_best"], line.ratio());
        assert_eq!(v["ratios"][0]["per_repeat"][2], 1.0);
        assert_eq!(v["stages"][0]["bytes_per_factor"], 16.0);
    }

    #[test]
    fn slope_of_a_power_law() {
        let pts: Vec<(f64, f64)> = [1.0, 2.0, 4.0, 8.0]
            .iter()
            .map(|&x| (x, 3.0 * x * x))
            .collect();
        assert!((loglog_slope(&pts) - 2.0).abs() < 1e-12);
    }

    #[test]
    fn query_time_is_counted_only_while_timing_is_on() {
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::Patches(60)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 1,
        };
        let est = EstimatorChoice::Hemisphere {
            strata: 8,
            replicates: 2,
        }
        .build();
        formfactor::compute(&ctx, est.as_ref(), &|_| {});
        assert_eq!(vis.query_seconds(), 0.0);
        vis.time_queries(true);
        // (Not checked against the process's CPU time: other tests' threads that exit
        // meanwhile take theirs out of it, `crate::cluster::cpu_seconds`.)
        formfactor::compute(&ctx, est.as_ref(), &|_| {});
        let q = vis.query_seconds();
        vis.time_queries(false);
        assert!(q > 0.0, "query {q} s");
        assert_eq!(
            vis.query_seconds(),
            0.0,
            "turning timing off resets the total"
        );
    }

    #[test]
    fn recorded_rays_are_the_rays_cast() {
        let scene = Scene::load("cube").unwrap();
        let patches = PatchSet::build(&scene, Resolution::Patches(96)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 1,
        };
        for choice in [
            EstimatorChoice::AreaStratified {
                strata: 2,
                replicates: 2,
            },
            EstimatorChoice::Hemisphere {
                strata: 4,
                replicates: 2,
            },
            EstimatorChoice::SemiAnalytic {
                points: 2,
                rays: 2,
                replicates: 2,
                tol: SemiAnalytic::DEFAULT_TOL,
            },
        ] {
            let ff = formfactor::compute(&ctx, choice.build().as_ref(), &|_| {});
            assert_eq!(record(&ctx, &choice).len() as u64, ff.rays, "{choice:?}");
        }
    }

    #[test]
    fn factors_do_not_depend_on_the_thread_count() {
        let scene = Scene::load("cornell").unwrap();
        let patches = PatchSet::build(&scene, Resolution::Patches(60)).unwrap();
        let vis = Visibility::new(&patches).unwrap();
        let ctx = Context {
            patches: &patches,
            vis: &vis,
            seed: 5,
        };
        for choice in [
            EstimatorChoice::AreaStratified {
                strata: 2,
                replicates: 2,
            },
            EstimatorChoice::Hemisphere {
                strata: 4,
                replicates: 2,
            },
        ] {
            let est = choice.build();
            let run = |t: usize, ftz: bool| {
                pool(t, ftz)
                    .unwrap()
                    .install(|| formfactor::compute(&ctx, est.as_ref(), &|_| {}))
            };
            let (a, b) = (run(1, false), run(3, true));
            assert_eq!(a.f, b.f, "{choice:?}");
            assert_eq!(a.se, b.se, "{choice:?}");
        }
    }
}
