//! Rows of the form-factor matrix shared between the ranks of a distributed run
//! ([`crate::cluster`]), assembled into the same bits one process assembles.
//!
//! Every rank holds the whole scene, its patches and its own Embree scene (geometry is
//! replicated: it is small next to the matrix), and computes a share of the rows:
//!
//! 1. **Cost.** Each rank estimates the cost of a contiguous `1/K` of the rows with
//!    [`Estimator::row_costs`] (for the semi-analytic and area estimators: a stratified
//!    sample of [`COST_SAMPLES`] of the row's pairs, each priced by its class: culled,
//!    integrated without rays at the evaluations its quadrature order implies, or sampled
//!    with rays, see [`cost`]), and the estimates are all-gathered, so every rank holds
//!    the same vector.
//! 2. **Share.** [`assign`] deals the rows out by cost (longest processing time first:
//!    rows by decreasing estimate, each to the rank with the least estimated work so far,
//!    ties to the lower row and the lower rank). The share depends on the estimates alone:
//!    the same on every rank and in every run.
//! 3. **Rows.** Each rank computes its rows in parallel on its threads, exactly as one
//!    process computes them (the same estimator, the same random streams keyed on
//!    `(seed, i, j, replicate)`, each row sorted the same way): a row's entries do not
//!    depend on which rank computes it.
//! 4. **Assembly.** [`Target::Root`]: the rows go to rank 0, which assembles them with the
//!    code one process uses ([`CsrBuilder::from_upper`] for the estimators that compute
//!    each pair once, [`CsrBuilder::push_rows`] for the others): the matrix is the one
//!    process's, bit for bit, and so are the files written from it. [`Target::Blocks`]:
//!    each rank ends with a contiguous block of full rows ([`Block`], bounds balanced by
//!    stored entries), the same rows bit for bit, for the distributed solve: each entry
//!    goes to the rank of its row and, when its mirror (the estimators that compute each
//!    pair once) or its back entry (the others) falls elsewhere, to the rank of its
//!    column too.
//!
//! On the wire a row is `row (u32), length (u32)` and then `column (u32), value (f64),
//! standard error (f64)` per entry, little-endian: 20 bytes per entry (the mirror needs
//! the standard error before its rounding to `f32`).

use std::sync::atomic::AtomicU64;
use std::time::Instant;

use rayon::prelude::*;

use serde::{Deserialize, Serialize};

use super::{rows_par, Context, Entry, Estimator};
use crate::cluster::{in_pool, Cluster, Packed, Traffic};
use crate::error::Result;
use crate::matrix::{Block, BlockBuilder, CsrBuilder, FormFactors};

/// Rough costs in nanoseconds of one core (measured on the development machine's
/// release build; only their ratios matter) that [`Estimator::row_costs`] adds up.
pub mod cost {
    /// Fixed cost of a row (its setup, its sort and copy).
    pub const ROW: f64 = 2000.0;
    /// A pair culled by the plane tests (one patch behind the other).
    pub const CULL: f64 = 15.0;
    /// The tests and bookkeeping of a pair that is not culled.
    pub const PAIR: f64 = 40.0;
    /// One point-to-polygon factor evaluation (Lambert's contour integral).
    pub const EVAL: f64 = 110.0;
    /// One segment ray, with the sampling of its end points.
    pub const RAY: f64 = 150.0;
}

/// Pairs of a row priced by [`sampled_row_cost`].
pub const COST_SAMPLES: usize = 32;

/// An estimate of the summed cost of row `i`'s pairs `(i, j > i)` of `n` patches: one
/// pair from each of [`COST_SAMPLES`] equal strata of `i + 1..n` (at a position hashed
/// from `(i, stratum)`), priced by `pair_cost(j)`, scaled to the row's pair count (every
/// pair when there are fewer).
pub fn sampled_row_cost(i: usize, n: usize, mut pair_cost: impl FnMut(usize) -> f64) -> f64 {
    let m = n.saturating_sub(i + 1);
    if m <= COST_SAMPLES {
        return (i + 1..n).map(pair_cost).sum();
    }
    let mut sum = 0.0;
    for k in 0..COST_SAMPLES {
        let (a, b) = (k * m / COST_SAMPLES, (k + 1) * m / COST_SAMPLES);
        let h = crate::sampling::mix64(((i as u64) << 20) ^ k as u64);
        sum += pair_cost(i + 1 + a + (h % (b - a) as u64) as usize);
    }
    sum * m as f64 / COST_SAMPLES as f64
}

/// Rows `lo..hi` of the `r`-th of `k` equal contiguous parts of `n`.
pub fn part(n: usize, k: usize, r: usize) -> std::ops::Range<usize> {
    n * r / k..n * (r + 1) / k
}

/// Every row's estimated cost ([`Estimator::row_costs`]), each rank estimating a
/// contiguous `1/K` of them in parallel; the same vector on every rank.
pub fn estimate_costs(
    ctx: &Context,
    est: &dyn Estimator,
    cluster: &dyn Cluster,
) -> Result<Vec<f64>> {
    let (n, k) = (ctx.patches.len(), cluster.size());
    let range = part(n, k, cluster.rank());
    let mine: Vec<f64> = in_pool(cluster.compute_pool(), || est.row_costs(ctx, range));
    let counts: Vec<usize> = (0..k).map(|r| part(n, k, r).len()).collect();
    let mut all = vec![0.0; n];
    cluster.all_gather_f64(&mine, &counts, &mut all)?;
    Ok(all)
}

/// The rank of each row: longest processing time first ([module docs](self)).
pub fn assign(costs: &[f64], ranks: usize) -> Vec<u32> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let ranks = ranks.max(1);
    let mut order: Vec<usize> = (0..costs.len()).collect();
    // Decreasing cost, then increasing row; a cost that is not a number counts as 0.
    let key = |c: f64| if c.is_nan() { 0.0 } else { c };
    order.sort_by(|&a, &b| key(costs[b]).total_cmp(&key(costs[a])).then(a.cmp(&b)));
    // Least loaded first, then lowest rank. Loads are compared exactly as f64 bits of
    // non-negative numbers (which order as the numbers do).
    let mut heap: BinaryHeap<Reverse<(u64, u32)>> = (0..ranks as u32)
        .map(|r| Reverse((0f64.to_bits(), r)))
        .collect();
    let mut owner = vec![0u32; costs.len()];
    for i in order {
        let Reverse((load, r)) = heap.pop().expect("at least one rank");
        owner[i] = r;
        let load = f64::from_bits(load) + key(costs[i]).max(0.0);
        heap.push(Reverse((load.to_bits(), r)));
    }
    owner
}

/// Contiguous row blocks, one per rank, balanced by `weight` (stored entries of each
/// row, plus one for the row itself): `bounds[r]..bounds[r + 1]` are rank r's rows, the
/// first rows whose running weight reaches `r / ranks` of the total.
pub fn blocks(weight: &[u64], ranks: usize) -> Vec<usize> {
    let total: u128 = weight.iter().map(|&w| w as u128 + 1).sum();
    let mut bounds = vec![0usize; ranks + 1];
    let (mut acc, mut i) = (0u128, 0usize);
    for (r, b) in bounds.iter_mut().enumerate().skip(1) {
        let target = total * r as u128 / ranks as u128;
        while i < weight.len() && acc < target {
            acc += weight[i] as u128 + 1;
            i += 1;
        }
        *b = i;
    }
    bounds[ranks] = weight.len();
    bounds
}

/// Where the computed rows go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// The whole matrix on rank 0 (to write it, or to solve it there).
    Root,
    /// A contiguous block of full rows on every rank (for the distributed solve).
    Blocks,
}

/// What a rank holds after [`compute`].
#[derive(Debug)]
pub enum Share {
    /// The whole matrix ([`Target::Root`], on rank 0).
    Whole(FormFactors),
    /// This rank's block of rows ([`Target::Blocks`]), with the rays cast by all ranks.
    Block(Block, u64),
    /// Nothing: the matrix went to rank 0.
    Elsewhere,
}

/// What one rank did in a distributed stage, for the run's summary and for the
/// scaling model of `docs/PERFORMANCE.md`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RankReport {
    /// The rank.
    pub rank: usize,
    /// Its worker threads.
    pub threads: usize,
    /// Rows it computed.
    pub rows: usize,
    /// Its share of the estimated cost (0 to 1).
    pub cost_share: f64,
    /// Stored entries of the rows it computed.
    pub entries: u64,
    /// Rays it cast.
    pub rays: u64,
    /// Seconds estimating its part of the costs (and waiting for the others').
    pub cost_seconds: f64,
    /// Seconds computing its rows.
    pub rows_seconds: f64,
    /// CPU seconds computing its rows (all its threads; [`crate::cluster::cpu_seconds`]).
    pub rows_cpu_seconds: f64,
    /// Seconds waiting for the slowest rank: from the end of its rows until every rank
    /// had finished theirs, and from the end of its packing until every rank had packed.
    pub wait_seconds: f64,
    /// Seconds packing its rows for the other ranks.
    pub pack_seconds: f64,
    /// Seconds in the exchange of rows: the transfer, and on rank 0 of a gather the
    /// unpacking.
    pub exchange_seconds: f64,
    /// Seconds assembling what it received.
    pub assembly_seconds: f64,
    /// Seconds in the distributed solve (0 when the solve was not distributed).
    pub solve_seconds: f64,
    /// Bytes sent to other ranks (all stages).
    pub sent: u64,
    /// Bytes received from other ranks (all stages).
    pub received: u64,
}

impl RankReport {
    /// Every rank's report, on every rank, by rank (collective).
    pub fn gather(&self, cluster: &dyn Cluster) -> Result<Vec<RankReport>> {
        let mine = serde_json::to_vec(self).map_err(|e| cluster.fail(e.to_string()))?;
        cluster
            .all_gather_bytes(mine)?
            .iter()
            .map(|b| serde_json::from_slice(b).map_err(|e| cluster.fail(e.to_string())))
            .collect()
    }
}

/// Writes row `i`'s `entries` into `buf` at `at` in the wire format ([module
/// docs](self)); returns where the next row goes.
fn put_row(buf: &mut [u8], at: usize, i: usize, entries: &[Entry]) -> usize {
    let out = &mut buf[at..at + row_bytes(entries.len())];
    out[..4].copy_from_slice(&(i as u32).to_le_bytes());
    out[4..8].copy_from_slice(&(entries.len() as u32).to_le_bytes());
    for (rec, e) in out[8..].chunks_exact_mut(20).zip(entries) {
        rec[..4].copy_from_slice(&e.j.to_le_bytes());
        rec[4..12].copy_from_slice(&e.f.to_bits().to_le_bytes());
        rec[12..].copy_from_slice(&e.se.to_bits().to_le_bytes());
    }
    at + out.len()
}

/// Bytes of row `entries` in the wire format.
fn row_bytes(entries: usize) -> usize {
    8 + 20 * entries
}

/// Calls `f(i, at)` for each row part in `buf` (the wire format: `at` is where its header
/// starts), refusing a malformed buffer or a row past `n` (columns are checked by
/// [`decode_part`]).
fn each_part(
    cluster: &dyn Cluster,
    buf: &[u8],
    n: usize,
    mut f: impl FnMut(usize, usize),
) -> Result<()> {
    let word = |b: &[u8]| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize;
    let mut at = 0;
    while at < buf.len() {
        if buf.len() - at < 8 {
            return Err(
                cluster.fail("malformed rows from another rank: truncated row header".into())
            );
        }
        let (i, len) = (word(&buf[at..at + 4]), word(&buf[at + 4..at + 8]));
        if i >= n || (buf.len() - at - 8) / 20 < len {
            return Err(cluster.fail(format!(
                "malformed rows from another rank: row {i} of {n}, {len} entries, truncated"
            )));
        }
        f(i, at);
        at += row_bytes(len);
    }
    Ok(())
}

/// The entries of the row part whose header starts `buf` (found by [`each_part`]), or
/// `None` when a column is past `n`.
fn decode_part(buf: &[u8], n: usize, entries: &mut Vec<Entry>) -> Option<()> {
    let word = |b: &[u8]| u32::from_le_bytes(b.try_into().expect("4 bytes"));
    let len = word(&buf[4..8]) as usize;
    entries.clear();
    entries.reserve(len);
    for rec in buf[8..8 + 20 * len].chunks_exact(20) {
        let j = word(&rec[..4]);
        if j as usize >= n {
            return None;
        }
        entries.push(Entry {
            j,
            f: f64::from_bits(u64::from_le_bytes(rec[4..12].try_into().expect("8 bytes"))),
            se: f64::from_bits(u64::from_le_bytes(rec[12..20].try_into().expect("8 bytes"))),
        });
    }
    Some(())
}

/// Every row part in `got`, as `(row, source rank, offset)`, sorted by row; refuses a row
/// that comes twice (the rank that computed a row sends each rank one part of it at most).
fn index_parts(
    cluster: &dyn Cluster,
    got: &Packed,
    n: usize,
) -> Result<Vec<(usize, usize, usize)>> {
    let mut parts = Vec::new();
    for src in 0..got.ranks() {
        each_part(cluster, got.part(src), n, |i, at| parts.push((i, src, at)))?;
    }
    parts.sort_unstable();
    if let Some(w) = parts.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(cluster.fail(format!("row {} came twice", w[0].0)));
    }
    Ok(parts)
}

/// Computes this rank's share of the matrix with `est` and sends the rows where `target`
/// says ([module docs](self)); collective. `progress(rows_done)` counts this rank's rows.
/// Returns the share and the reports: with [`Target::Root`], every rank's (gathered
/// before rank 0 assembles alone), with [`Target::Blocks`] this rank's (the run goes on
/// together; [`RankReport::gather`] them at its end).
pub fn compute(
    ctx: &Context,
    est: &dyn Estimator,
    cluster: &dyn Cluster,
    target: Target,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(Share, Vec<RankReport>)> {
    let (n, k, me) = (ctx.patches.len(), cluster.size(), cluster.rank());
    let traffic0 = cluster.traffic();
    let start = Instant::now();
    let mut report = RankReport {
        rank: me,
        threads: in_pool(cluster.compute_pool(), rayon::current_num_threads),
        ..RankReport::default()
    };

    let t = Instant::now();
    let costs = estimate_costs(ctx, est, cluster)?;
    let owner = assign(&costs, k);
    let mine: Vec<usize> = (0..n).filter(|&i| owner[i] as usize == me).collect();
    let total: f64 = costs.iter().sum();
    let my_cost: f64 = mine.iter().map(|&i| costs[i]).sum();
    report.cost_share = if total > 0.0 { my_cost / total } else { 0.0 };
    report.rows = mine.len();
    report.cost_seconds = t.elapsed().as_secs_f64();

    let (t, cpu) = (Instant::now(), crate::cluster::cpu_seconds());
    let done = AtomicU64::new(0);
    let (rows, rays) = in_pool(cluster.compute_pool(), || {
        rows_par(ctx, est, mine.clone(), &done, mine.len() as u64, progress)
    });
    report.rows_seconds = t.elapsed().as_secs_f64();
    report.rows_cpu_seconds = crate::cluster::cpu_seconds() - cpu;
    report.rays = rays;
    report.entries = rows.iter().map(|r| r.len() as u64).sum();

    let t = Instant::now();
    cluster.wait_for_all()?;
    report.wait_seconds = t.elapsed().as_secs_f64();
    let mut counters = [rays];
    cluster.all_sum_u64(&mut counters)?;
    let all_rays = counters[0];
    let upper = est.upper_only();
    let t_pack = Instant::now();

    let share = match target {
        Target::Root => {
            // Rank 0 keeps its own rows as they are; the others send theirs.
            let mut own: Vec<(usize, Vec<Entry>)> = Vec::new();
            let mut sizes = vec![0usize; k];
            if me != 0 {
                sizes[0] = rows.iter().map(|r| row_bytes(r.len())).sum();
            }
            let mut send = Packed::zeroed(&sizes);
            if me == 0 {
                own = mine.iter().copied().zip(rows).collect();
            } else {
                let mut at = 0;
                let buf = send.part_mut(0);
                for (&i, r) in mine.iter().zip(rows) {
                    at = put_row(buf, at, i, &r);
                }
            }
            report.pack_seconds = t_pack.elapsed().as_secs_f64();
            let got = exchange_timed(cluster, send, &mut report)?;
            let tr: Traffic = cluster.traffic() - traffic0;
            (report.sent, report.received) = (tr.sent, tr.received);
            // Every rank's report now, before rank 0 assembles alone: the others are done.
            let mut ranks = report.gather(cluster)?;
            if me != 0 {
                return Ok((Share::Elsewhere, ranks));
            }
            // Unpacked in parallel (rank 0's pool has the node's threads by now).
            let t = Instant::now();
            let parts = index_parts(cluster, &got, n)?;
            let decoded: Vec<Option<(usize, Vec<Entry>)>> = parts
                .par_iter()
                .map(|&(i, src, at)| {
                    let mut es = Vec::new();
                    decode_part(&got.part(src)[at..], n, &mut es).map(|()| (i, es))
                })
                .collect();
            drop(got);
            let mut all: Vec<Option<Vec<Entry>>> = vec![None; n];
            for (i, r) in own {
                all[i] = Some(r);
            }
            for d in decoded {
                let Some((i, es)) = d else {
                    return Err(cluster.fail("a column past the patch count in the rows".into()));
                };
                if all[i].is_some() {
                    return Err(cluster.fail(format!("row {i} came twice")));
                }
                all[i] = Some(es);
            }
            if let Some(i) = all.iter().position(Option::is_none) {
                return Err(cluster.fail(format!("row {i} came from no rank")));
            }
            let rows: Vec<Vec<Entry>> = all.into_iter().map(Option::unwrap_or_default).collect();
            ranks[0].exchange_seconds += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let ff = assemble(ctx, est, rows, all_rays, start.elapsed().as_secs_f64());
            ranks[0].assembly_seconds = t.elapsed().as_secs_f64();
            return Ok((Share::Whole(ff), ranks));
        }
        Target::Blocks => {
            // Stored entries per full row, to cut balanced contiguous blocks.
            let mut weight = vec![0u64; n];
            for (&i, r) in mine.iter().zip(&rows) {
                weight[i] += r.len() as u64;
                if upper {
                    for e in r {
                        weight[e.j as usize] += 1;
                    }
                }
            }
            cluster.all_sum_u64(&mut weight)?;
            let bounds = blocks(&weight, k);
            drop(weight);
            let block_of = |x: usize| bounds.partition_point(|&b| b <= x) - 1;
            // Each row to the rank of its row; the parts whose columns fall in another
            // rank's block (their mirrors or back entries live there) to that rank too;
            // this rank's own parts into its own buffer, read back like the others.
            // The parts of row i: (destination, range of its entries).
            let parts =
                |i: usize, r: &[Entry], f: &mut dyn FnMut(usize, std::ops::Range<usize>)| {
                    let home = block_of(i);
                    let mut at = 0;
                    while at < r.len() {
                        let d = block_of(r[at].j as usize);
                        let end = at + r[at..].partition_point(|e| (e.j as usize) < bounds[d + 1]);
                        if d != home {
                            f(d, at..end);
                        }
                        at = end;
                    }
                    f(home, 0..r.len());
                };
            // Sized first, then written in place.
            let mut bytes = vec![0usize; k];
            for (&i, r) in mine.iter().zip(&rows) {
                parts(i, r, &mut |d, range| bytes[d] += row_bytes(range.len()));
            }
            let mut send = Packed::zeroed(&bytes);
            let mut at = send.offsets.clone();
            for (&i, r) in mine.iter().zip(rows) {
                parts(i, &r, &mut |d, range| {
                    at[d] = put_row(&mut send.data, at[d], i, &r[range]);
                });
            }
            report.pack_seconds = t_pack.elapsed().as_secs_f64();
            let got = exchange_timed(cluster, send, &mut report)?;
            let t = Instant::now();
            // Every part received, by row: the rank that computed a row sends each rank
            // one part of it at most (the whole row to its home, the columns of their
            // blocks to the others).
            let parts = index_parts(cluster, &got, n)?;
            let area = &ctx.patches.area;
            let mut b = BlockBuilder::new(bounds[me], bounds[me + 1], upper, area);
            let mut entries = Vec::new();
            let bad = || cluster.fail("a column past the patch count in the rows".into());
            for &(i, src, at) in &parts {
                decode_part(&got.part(src)[at..], n, &mut entries).ok_or_else(bad)?;
                b.count(i, &entries);
            }
            for &(i, src, at) in &parts {
                decode_part(&got.part(src)[at..], n, &mut entries).ok_or_else(bad)?;
                b.fill(i, &entries);
            }
            drop(got);
            let block = in_pool(cluster.compute_pool(), || b.finish());
            report.assembly_seconds = t.elapsed().as_secs_f64();
            Share::Block(block, all_rays)
        }
    };
    let tr: Traffic = cluster.traffic() - traffic0;
    report.sent = tr.sent;
    report.received = tr.received;
    Ok((share, vec![report]))
}

/// The whole matrix from every row (`rows[i]` as [`rows_par`] leaves it), assembled as
/// [`super::compute_timed`] assembles it.
fn assemble(
    ctx: &Context,
    est: &dyn Estimator,
    rows: Vec<Vec<Entry>>,
    rays: u64,
    seconds: f64,
) -> FormFactors {
    let area = &ctx.patches.area;
    let csr = if est.upper_only() {
        CsrBuilder::from_upper(&rows, area)
    } else {
        let nnz: usize = rows.iter().map(Vec::len).sum();
        let mut csr = CsrBuilder::with_capacity(rows.len(), 0);
        csr.reserve_exact(nnz);
        csr.push_rows(&rows);
        csr
    };
    drop(rows);
    let mut ff = csr.finish(area.clone(), rays, seconds, est.name(), ctx.seed);
    ff.replicates = est.replicates();
    ff.unresolved = est.unresolved();
    ff
}

/// Waits for every rank (a rank done packing sleeps here rather than spinning in the
/// exchange), then exchanges `send`, adding both times to `report`.
fn exchange_timed(cluster: &dyn Cluster, send: Packed, report: &mut RankReport) -> Result<Packed> {
    let t = Instant::now();
    cluster.wait_for_all()?;
    report.wait_seconds += t.elapsed().as_secs_f64();
    let t = Instant::now();
    let got = cluster.exchange(send)?;
    report.exchange_seconds = t.elapsed().as_secs_f64();
    Ok(got)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cluster::{Local, Single};
    use crate::formfactor::{
        compute as compute_one, AreaMc, Hemisphere, Nodes, Pattern, SemiAnalytic,
    };
    use crate::matrix::Diagnostics;
    use crate::mesh::{PatchSet, Resolution};
    use crate::scene::Scene;
    use crate::visibility::Visibility;

    #[test]
    fn assignment_is_balanced_and_total() {
        let costs: Vec<f64> = (0..1000).map(|i| (1000 - i) as f64).collect();
        for k in 1..=7 {
            let owner = assign(&costs, k);
            let mut load = vec![0.0; k];
            for (i, &r) in owner.iter().enumerate() {
                load[r as usize] += costs[i];
            }
            let (lo, hi) = load
                .iter()
                .fold((f64::MAX, 0.0f64), |(a, b), &l| (a.min(l), b.max(l)));
            // LPT: within the largest single cost of each other.
            assert!(hi - lo <= 1000.0, "{k}: {load:?}");
            assert_eq!(owner, assign(&costs, k));
        }
        assert_eq!(blocks(&[5, 5, 5, 5], 2), vec![0, 2, 4]);
        assert_eq!(blocks(&[0; 3], 4), vec![0, 0, 1, 2, 3]);
        assert_eq!(blocks(&[], 2), vec![0, 0, 0]);
    }

    fn scene(name: &str, edge: f64) -> PatchSet {
        PatchSet::build(&Scene::load(name).unwrap(), Resolution::MaxEdge(edge)).unwrap()
    }

    /// The matrix assembled on rank 0 from rows computed on 1 to 4 ranks is the one
    /// process's bit for bit, and so are the blocks of full rows (values, standard errors,
    /// and the diagnostics merged from the blocks).
    #[test]
    fn shards_assemble_the_single_process_matrix() {
        let cases: Vec<(PatchSet, Box<dyn Estimator>)> = vec![
            (
                scene("cornell", 120.0),
                Box::new(SemiAnalytic::new(Nodes::Gauss, 2, 2, 2)),
            ),
            (
                scene("cube", 0.25),
                Box::new(AreaMc::new(Pattern::Stratified, 2, 2)),
            ),
            (
                scene("cornell", 150.0),
                Box::new(Hemisphere {
                    strata: 4,
                    replicates: 2,
                }),
            ),
        ];
        for (patches, est) in &cases {
            let vis = Visibility::new(patches).unwrap();
            let ctx = Context {
                patches,
                vis: &vis,
                seed: 7,
            };
            let one = compute_one(&ctx, est.as_ref(), &|_| {});
            let want = one.diagnostics();
            let (single, _) = compute(&ctx, est.as_ref(), &Single, Target::Root, &|_| {}).unwrap();
            let Share::Whole(single) = single else {
                panic!()
            };
            assert_eq!(single.f, one.f);
            assert_eq!(single.se, one.se);
            for k in 1..=4 {
                let out = Local::run(k, |c| {
                    let vis = Visibility::new(patches).unwrap();
                    let ctx = Context {
                        patches,
                        vis: &vis,
                        seed: 7,
                    };
                    let root = compute(&ctx, est.as_ref(), c, Target::Root, &|_| {}).unwrap();
                    let blocks = compute(&ctx, est.as_ref(), c, Target::Blocks, &|_| {}).unwrap();
                    (root, blocks)
                });
                let mut diag = Diagnostics::empty();
                let mut lo = 0;
                for (r, ((root, reps), (block, rep))) in out.into_iter().enumerate() {
                    // Every rank's report, on every rank; one's own for blocks.
                    assert_eq!(reps.len(), k);
                    assert!(reps.iter().enumerate().all(|(q, x)| x.rank == q));
                    assert!(reps.iter().map(|x| x.rows).sum::<usize>() == patches.len());
                    assert_eq!(rep.len(), 1);
                    assert_eq!(rep[0].rank, r);
                    match root {
                        Share::Whole(ff) => {
                            assert_eq!(r, 0);
                            assert_eq!(ff.f, one.f, "{} on {k}", est.name());
                            assert_eq!(ff.se, one.se);
                            assert_eq!(ff.rays, one.rays);
                        }
                        _ => assert_ne!(r, 0),
                    }
                    let Share::Block(b, rays) = block else {
                        panic!()
                    };
                    assert_eq!(rays, one.rays);
                    assert_eq!(b.lo, lo);
                    for (q, row) in b.f.outer_iterator().enumerate() {
                        let i = lo + q;
                        let want_row = one.f.outer_view(i).unwrap();
                        assert_eq!(row.indices(), want_row.indices(), "row {i}");
                        assert_eq!(row.data(), want_row.data(), "row {i}");
                    }
                    let (a, z) = (one.f.indptr().index(lo), one.f.indptr().index(b.hi()));
                    assert_eq!(b.se, one.se[a..z]);
                    diag = Diagnostics::merge(diag, b.diagnostics);
                    lo = b.hi();
                }
                assert_eq!(lo, patches.len());
                assert_eq!(diag.finish(one.f.nnz(), lo), want, "{} on {k}", est.name());
            }
        }
    }
}
