//! The pipeline on several ranks ([`crate::cluster`]; under MPI, `mpirun -np K
//! radiosity ...`): which stages are shared, and where the others run.
//!
//! Every rank loads the scene, meshes it and builds its own Embree scene (geometry is
//! replicated), then computes its share of the form-factor rows
//! ([`crate::formfactor::shard`]). After that:
//!
//! - **`factors`**, and **`bake`** with any solver but Jacobi (or with `--repair` or
//!   `--steps`): the rows are gathered on rank 0, which goes on exactly as one process
//!   does (repair, diagnostics, solve, files): the same files, bit for bit. The other
//!   ranks are done. This needs the whole matrix in rank 0's memory, as one process does.
//! - **`bake --solver jacobi`**: the matrix stays distributed, each rank with a contiguous
//!   block of full rows; the diagnostics and the bounds are computed per block and
//!   reduced, the solve is the distributed Jacobi ([`crate::solve::distributed`]), whose
//!   radiosity is one process's Jacobi radiosity bit for bit; rank 0 writes the files.
//!   No rank ever holds the whole matrix.
//!
//! `bake --method hierarchical`, `bake --factors` and `thermal` run as one process.

use super::{
    bake_gathered, blind_warning, check_budget, peak_memory, write_bake, BakeConfig, BakeSummary,
    EstimatorChoice, Observer, StageTime, Timer,
};
use crate::cluster::Cluster;
use crate::error::{Error, Result};
use crate::formfactor::shard::{self, RankReport, Share, Target};
use crate::formfactor::Context;
use crate::matrix::{repair_rows_from, sum_bar, Bar, Block, Diagnostics, FormFactors};
use crate::mesh::PatchSet;
use crate::output::{self, FolderKind};
use crate::repair::{check_rows, Bounds, Repair, RepairReport, RowOver};
use crate::solve::distributed::{jacobi, BlockSystem};
use crate::solve::{Method, Options, SolveReport};
use crate::visibility::Visibility;

/// True when a bake on several ranks keeps the matrix distributed and solves it there
/// (Jacobi, no repair, no progressive previews); else it gathers the matrix on rank 0.
pub fn solves_distributed(cfg: &BakeConfig) -> bool {
    cfg.method == Method::Jacobi
        && cfg.repair == Repair::None
        && cfg.steps.is_empty()
        && cfg.factors.is_none()
        && cfg.hierarchy.is_none()
}

/// The BVH and this rank's share of the form factors, sent where `target` says.
fn shared(
    patches: &PatchSet,
    estimator: &EstimatorChoice,
    seed: u64,
    obs: &dyn Observer,
    cluster: &dyn Cluster,
    target: Target,
) -> Result<(Share, Vec<StageTime>, String, Vec<RankReport>)> {
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
    let (share, report) = timer.run("form factors", 0, || {
        shard::compute(&ctx, est.as_ref(), cluster, target, &|d| obs.advance(d))
    })?;
    Ok((share, timer.stages, embree, report))
}

/// What [`form_factors_root`] returns: the matrix on rank 0 (`None` on the others), the
/// stages' times, the Embree version and every rank's report.
pub type Gathered = (Option<FormFactors>, Vec<StageTime>, String, Vec<RankReport>);

/// The form factors computed by the ranks of `cluster` and gathered on rank 0.
pub fn form_factors_root(
    patches: &PatchSet,
    estimator: &EstimatorChoice,
    seed: u64,
    obs: &dyn Observer,
    cluster: &dyn Cluster,
) -> Result<Gathered> {
    let (share, stages, embree, ranks) =
        shared(patches, estimator, seed, obs, cluster, Target::Root)?;
    let ff = match share {
        Share::Whole(ff) => Some(ff),
        _ => None,
    };
    Ok((ff, stages, embree, ranks))
}

/// A bake on the ranks of `cluster` (see the [module docs](self)): the summary on rank 0,
/// `None` on the others. On one rank, the bake of one process.
pub fn bake_on(
    cfg: &BakeConfig,
    obs: &dyn Observer,
    cluster: &dyn Cluster,
) -> Result<Option<BakeSummary>> {
    if cluster.size() == 1 {
        return super::bake(cfg, obs).map(Some);
    }
    if cfg.hierarchy.is_some() {
        return Err(Error::Config(
            "--method hierarchical runs as one process: its refinement is not shared \
             between ranks (docs/PERFORMANCE.md, section 8, plans it); run it without mpirun"
                .into(),
        ));
    }
    if cfg.factors.is_some() {
        return Err(Error::Config(
            "--factors reads a stored matrix and casts no rays: there is nothing to share \
             between ranks; run it without mpirun"
                .into(),
        ));
    }
    if solves_distributed(cfg) {
        bake_rows(cfg, obs, cluster)
    } else {
        bake_gathered(cfg, obs, cluster)
    }
}

/// Every rank's bounds, in row order (the blocks are in rank order).
fn all_bounds(local: &Bounds, cluster: &dyn Cluster) -> Result<Bounds> {
    let mut mine = vec![
        local.rows_over_one.len() as f64,
        local.out_of_range.len() as f64,
    ];
    for r in &local.rows_over_one {
        mine.extend([r.row as f64, r.sum, r.bar.se, r.bar.bound]);
    }
    for &(i, j, f) in &local.out_of_range {
        mine.extend([i as f64, j as f64, f]);
    }
    let mut all = Bounds::default();
    for bytes in cluster.all_gather_bytes(crate::cluster::f64s_to_bytes(&mine))? {
        let v = crate::cluster::bytes_to_f64s(&bytes);
        let (a, b) = (v[0] as usize, v[1] as usize);
        let rest = &v[2..];
        for t in rest[..4 * a].chunks_exact(4) {
            all.rows_over_one.push(RowOver {
                row: t[0] as usize,
                sum: t[1],
                bar: Bar {
                    se: t[2],
                    bound: t[3],
                },
            });
        }
        for t in rest[4 * a..4 * a + 3 * b].chunks_exact(3) {
            all.out_of_range.push((t[0] as usize, t[1] as usize, t[2]));
        }
    }
    Ok(all)
}

/// Every rank's diagnostics merged in rank order and finished ([`Diagnostics::finish`])
/// for `nnz` stored entries in `n` rows.
fn all_diagnostics(
    local: Diagnostics,
    (nnz, n): (usize, usize),
    cluster: &dyn Cluster,
) -> Result<Diagnostics> {
    let k = cluster.size();
    let m = Diagnostics::NUMBERS;
    let mut all = vec![0.0; m * k];
    cluster.all_gather_f64(&local.to_numbers(), &vec![m; k], &mut all)?;
    Ok(all
        .chunks_exact(m)
        .map(Diagnostics::from_numbers)
        .fold(Diagnostics::empty(), Diagnostics::merge)
        .finish(nnz, n))
}

/// The distributed solve of the bake's system: rows over `1 / rho` scaled as
/// [`super::solve_radiosity`] scales them (per block, the note from the worst over all
/// ranks), then [`jacobi`].
fn solve_block(
    patches: &PatchSet,
    block: &Block,
    opts: &Options,
    cluster: &dyn Cluster,
) -> Result<(Vec<[f64; 3]>, SolveReport)> {
    let n = patches.len();
    let rho: Vec<[f64; 3]> = (0..n).map(|i| patches.rho(i)).collect();
    let emit: Vec<[f64; 3]> = (0..n).map(|i| patches.emit(i)).collect();
    let repaired = repair_rows_from(&block.f, &rho, block.lo);
    // Rows scaled and the worst gain, over all ranks: (count, gain, patch, sum, its bar).
    let mine = match &repaired {
        Some((_, rep)) => {
            let (a, z) = (
                block.f.indptr().index(rep.worst.0 - block.lo),
                block.f.indptr().index(rep.worst.0 - block.lo + 1),
            );
            let bar = sum_bar(&block.se[a..z]);
            [
                rep.rows.len() as f64,
                rep.worst_gain,
                rep.worst.0 as f64,
                rep.worst.1,
                bar.se,
                bar.bound,
            ]
        }
        None => [0.0; 6],
    };
    let k = cluster.size();
    let mut all = vec![0.0; 6 * k];
    cluster.all_gather_f64(&mine, &vec![6; k], &mut all)?;
    let rows: f64 = all.chunks_exact(6).map(|v| v[0]).sum();
    let worst = all
        .chunks_exact(6)
        .filter(|v| v[0] > 0.0)
        .fold(None::<&[f64]>, |w, v| match w {
            Some(w) if v[1] <= w[1] => Some(w),
            _ => Some(v),
        });
    let f = repaired.as_ref().map_or(&block.f, |r| &r.0);
    let sys = BlockSystem {
        lo: block.lo,
        f,
        rho: &rho,
        emit: &emit,
        area: &patches.area,
    };
    let opts = Options {
        max_iterations: Method::Jacobi.iteration_cap(opts.max_iterations, n),
        ..*opts
    };
    let (b, mut report) = jacobi(&sys, &opts, cluster)?;
    if let Some(w) = worst {
        report.notes.insert(
            0,
            format!(
                "{} rows of F had rho * (row sum) >= 1 (worst {:.4} at patch {}, row sum {:.4}, \
                 row-sum bar {}) and were scaled to sum to 1, so that the solve stays \
                 bounded: raise the samples if this is more than noise",
                rows as usize,
                w[1],
                w[2] as usize,
                w[3],
                Bar {
                    se: w[4],
                    bound: w[5]
                }
            ),
        );
    }
    Ok((b, report))
}

/// The bake with the matrix distributed by rows and solved by the distributed Jacobi
/// (see the [module docs](self)).
fn bake_rows(
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
    let scene = timer.run("load", 0, || super::load_scene(&cfg.scene, cfg.two_sided))?;
    scene.require_emitter()?;
    check_budget(
        &scene,
        cfg.resolution,
        Some(&cfg.estimator),
        Some(cfg.method),
        Some(cfg.preview),
        cfg.max_memory,
    )?;
    let patches = timer.run("mesh", 0, || PatchSet::build(&scene, cfg.resolution))?;
    let (share, stages, embree, reports) = shared(
        &patches,
        &cfg.estimator,
        cfg.seed,
        obs,
        cluster,
        Target::Blocks,
    )?;
    let mut report = reports.into_iter().next().unwrap_or_default();
    timer.stages.extend(stages);
    let Share::Block(block, rays) = share else {
        return Err(cluster.fail("no block of rows after the exchange".into()));
    };
    let n = patches.len();
    let bounds = timer.run("repair", 0, || {
        all_bounds(&check_rows(&block.f, &block.se, block.lo), cluster)
    })?;
    let diagnostics = timer.run("diagnostics", 0, || {
        let mut nnz = [block.f.nnz() as u64];
        cluster.all_sum_u64(&mut nnz)?;
        all_diagnostics(block.diagnostics, (nnz[0] as usize, n), cluster)
    })?;
    let traffic0 = cluster.traffic();
    let t = std::time::Instant::now();
    let (b, solve) = timer.run("solve", 0, || {
        solve_block(&patches, &block, &cfg.solve, cluster)
    })?;
    report.solve_seconds = t.elapsed().as_secs_f64();
    let tr = cluster.traffic() - traffic0;
    report.sent += tr.sent;
    report.received += tr.received;
    drop(block);
    let ranks = report.gather(cluster)?;
    if !cluster.is_root() {
        return Ok(None);
    }
    super::check_storable(&scene, &b)?;
    let verts = timer.run("per-vertex", 0, || {
        output::interpolate(&patches, &b, cfg.crease_deg)
    });
    let (files, written) = timer.run("write", 0, || {
        write_bake(cfg, &scene, &patches, &verts, |_, _, _| Ok(Vec::new()))
    })?;
    Ok(Some(BakeSummary {
        scene: scene.name.clone(),
        patches: n,
        triangles: patches.triangles.len(),
        vertices: verts.positions.len(),
        rays,
        estimator: cfg.estimator.build().name(),
        diagnostics,
        repair: RepairReport {
            repair: Repair::None,
            after: bounds.clone(),
            before: bounds,
            max_shift_sigmas: 0.0,
            rounds: 0,
        },
        solve,
        stages: timer.stages,
        peak_memory: peak_memory(),
        files,
        warnings: scene
            .warnings
            .iter()
            .cloned()
            .chain(blind_warning(diagnostics.empty_rows, n))
            .chain(written)
            .collect(),
        embree,
        hierarchy: None,
        ranks,
    }))
}

/// The table of a run on several ranks: per rank its threads, rows, estimated cost
/// share, seconds per part (the rows also in CPU seconds) and bytes to and from the other
/// ranks; then the load imbalance (the slowest rank's rows against the mean), the bytes
/// moved in all and the longest pricing of the rows.
pub fn format_ranks(ranks: &[RankReport]) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    if ranks.is_empty() {
        return o;
    }
    let mb = |b: u64| b as f64 / 1e6;
    let _ = writeln!(
        o,
        "ranks: {}; per rank (seconds; MB to and from the other ranks):",
        ranks.len()
    );
    let _ = writeln!(
        o,
        " rank thr  rows cost%   rows   cpu  wait  pack  xchg assem solve sent MB recv MB"
    );
    for r in ranks {
        let _ = writeln!(
            o,
            "{:>5}{:>4}{:>6}{:>6.1}{:>7.2}{:>6.1}{:>6.2}{:>6.2}{:>6.2}{:>6.2}{:>6.2}{:>8.1}{:>8.1}",
            r.rank,
            r.threads,
            r.rows,
            100.0 * r.cost_share,
            r.rows_seconds,
            r.rows_cpu_seconds,
            r.wait_seconds,
            r.pack_seconds,
            r.exchange_seconds,
            r.assembly_seconds,
            r.solve_seconds,
            mb(r.sent),
            mb(r.received)
        );
    }
    let imbalance = |t: &dyn Fn(&RankReport) -> f64| {
        let mean = ranks.iter().map(t).sum::<f64>() / ranks.len() as f64;
        let top = ranks.iter().map(t).fold(0.0, f64::max);
        if mean > 0.0 {
            top / mean
        } else {
            1.0
        }
    };
    let moved: u64 = ranks.iter().map(|r| r.sent).sum();
    let pricing = ranks.iter().map(|r| r.cost_seconds).fold(0.0, f64::max);
    let _ = writeln!(
        o,
        "  load imbalance (slowest rank's rows / mean) {:.3}, in CPU time {:.3}; {:.1} MB \
         between ranks; pricing the rows took {pricing:.2}s",
        imbalance(&|r| r.rows_seconds),
        imbalance(&|r| r.rows_cpu_seconds),
        mb(moved)
    );
    o
}
