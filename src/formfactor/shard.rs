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
//! 2. **Share.** [`Target::Blocks`]: [`assign`] deals the rows out by cost (longest
//!    processing time first: rows by decreasing estimate, each to the rank with the
//!    least estimated work so far, ties to the lower row and the lower rank), the same
//!    on every rank and in every run. [`Target::Root`]: rank 0 deals consecutive chunks
//!    of rows, of decreasing estimated cost (`deal_chunks`), to the ranks as they ask
//!    (`gather_on_root`): a rank that is slower (sharing its core, or rank 0 doing
//!    the receiving) computes fewer.
//! 3. **Rows.** Each rank computes its rows in parallel on its threads, exactly as one
//!    process computes them (the same estimator, the same random streams keyed on
//!    `(seed, i, j, replicate)`, each row sorted the same way): a row's entries do not
//!    depend on which rank computes it.
//! 4. **Assembly.** [`Target::Root`]: each rank sends its finished chunks to rank 0 while
//!    it computes the next (point to point, [`Cluster::send`]), so that the transfer
//!    overlaps the rows. Rank 0 keeps the received bytes and assembles straight from
//!    them ([`crate::matrix::RowEntries`]; no copy into vectors first), with the code one
//!    process uses ([`CsrBuilder::from_upper`] for the estimators that compute each pair
//!    once, [`CsrBuilder::push_rows`] for the others): the matrix is the one process's,
//!    bit for bit, and so are the files written from it. [`Target::Blocks`]: each rank
//!    ends with a contiguous block of full rows ([`Block`], bounds balanced by stored
//!    entries), the same rows bit for bit, for the distributed solve: each entry goes to
//!    the rank of its row and, when its mirror (the estimators that compute each pair
//!    once) or its back entry (the others) falls elsewhere, to the rank of its column
//!    too (one collective exchange).
//!
//! On the wire a row is `row (u32), length (u32)` and then `column (u32), value (f64),
//! standard error (f64)` per entry, little-endian: 20 bytes per entry (the mirror needs
//! the standard error before its rounding to `f32`). A message to rank 0 starts with its
//! kind (`u32`): `ASK` (for a chunk; the answer is the chunk's index as a `u64`, or
//! `NONE_LEFT`) or `ROWS` (row parts follow).

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::OnceLock;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::{rows_par, Context, Entry, Estimator};
use crate::cluster::{in_pool, Cluster, Packed, Traffic};
use crate::error::Result;
use crate::matrix::{Block, BlockBuilder, CsrBuilder, FormFactors, RowEntries};

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
    /// Seconds after its own rows that the rows' travel did not hide. Gather to rank 0
    /// ([`Target::Root`], streamed): from the end of its rows until the last chunk was
    /// on rank 0. Blocks: from the end of its rows until every rank had finished theirs,
    /// and from the end of its packing until every rank had packed.
    pub wait_seconds: f64,
    /// Seconds packing its rows for the other ranks; on rank 0 of a gather, checking and
    /// indexing the rows received. Streamed, these overlap the rows.
    pub pack_seconds: f64,
    /// Seconds in the exchanges of rows (the transfer). Streamed, these overlap the rows.
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
    let word = |b: &[u8]| word(b) as usize;
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
    let len = word(&buf[4..8]) as usize;
    entries.clear();
    entries.reserve(len);
    for rec in buf[8..8 + 20 * len].chunks_exact(20) {
        let e = wire_entry(rec);
        if e.j as usize >= n {
            return None;
        }
        entries.push(e);
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
    let total: f64 = costs.iter().sum();
    report.cost_seconds = t.elapsed().as_secs_f64();
    if target == Target::Root {
        let chunks = deal_chunks(&costs, k);
        return gather_on_root(
            ctx,
            est,
            cluster,
            (&chunks, &costs),
            report,
            (start, traffic0),
            progress,
        );
    }
    let owner = assign(&costs, k);
    let mine: Vec<usize> = (0..n).filter(|&i| owner[i] as usize == me).collect();
    let my_cost: f64 = mine.iter().map(|&i| costs[i]).sum();
    report.cost_share = if total > 0.0 { my_cost / total } else { 0.0 };
    report.rows = mine.len();

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

    // Target::Blocks. Stored entries per full row, to cut balanced contiguous blocks.
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
    let parts = |i: usize, r: &[Entry], f: &mut dyn FnMut(usize, std::ops::Range<usize>)| {
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
    let unresolved = est.unresolved();
    let block = in_pool(cluster.compute_pool(), || b.finish(unresolved));
    report.assembly_seconds = t.elapsed().as_secs_f64();
    let share = Share::Block(block, all_rays);
    let tr: Traffic = cluster.traffic() - traffic0;
    report.sent = tr.sent;
    report.received = tr.received;
    Ok((share, vec![report]))
}

/// The smallest chunk of rows [`deal_chunks`] makes, as a fraction of the whole cost
/// over the ranks (`1 / (MIN_CHUNK_PARTS x ranks)`): small enough that the ranks finish
/// within about one such chunk of each other, large enough that a chunk's two messages
/// and its row bookkeeping are nothing beside its rows.
const MIN_CHUNK_PARTS: f64 = 128.0;

/// Largest message of rows sent to rank 0 (MPI counts are `int`s), unless one row is
/// longer.
const MESSAGE_BYTES: usize = 1 << 30;

/// Rows `0..n` cut into consecutive chunks for [`gather_on_root`], by estimated cost
/// (`costs` by row), guided self-scheduling (Polychronopoulos and Kuck, 1987): each
/// chunk holds a quarter of the remaining cost over the `ranks`, and at least
/// `1 / (MIN_CHUNK_PARTS x ranks)` of the whole, so that the first chunks are large (few
/// messages) and the last small (the ranks end together). The same on every rank.
fn deal_chunks(costs: &[f64], ranks: usize) -> Vec<std::ops::Range<usize>> {
    let key = |c: f64| if c.is_finite() { c.max(0.0) } else { 0.0 };
    let total: f64 = costs.iter().map(|&c| key(c)).sum();
    let floor = total / (MIN_CHUNK_PARTS * ranks as f64);
    let mut chunks = Vec::new();
    let (mut lo, mut left) = (0, total);
    while lo < costs.len() {
        let want = (left / (4.0 * ranks as f64)).max(floor);
        let (mut hi, mut sum) = (lo, 0.0);
        while hi < costs.len() && (hi == lo || sum + key(costs[hi]) <= want) {
            sum += key(costs[hi]);
            hi += 1;
        }
        chunks.push(lo..hi);
        left -= sum;
        lo = hi;
    }
    chunks
}

/// What a rank other than 0 sends rank 0 in [`gather_on_root`]: a message starts with
/// its kind.
const ASK: u32 = 0;
/// Row parts follow ([module docs](self), wire format).
const ROWS: u32 = 1;
/// Rank 0's answer to [`ASK`]: 8 bytes, the chunk's index, or `u64::MAX` for none left.
const NONE_LEFT: u64 = u64::MAX;

/// [`Target::Root`]: every rank computes chunks of rows (`deal_chunks`) on its compute
/// threads while its main thread talks to rank 0, which deals the chunks out as they are
/// asked for (dynamic scheduling: a rank that is slower, sharing its core or doing rank
/// 0's receiving, simply computes fewer) and receives the finished rows while computing
/// its own, so that the transfer overlaps the rows instead of following them. A rank
/// keeps up to two chunks queued for its threads, so that they never wait for an
/// answer. Rank 0 keeps the received bytes and assembles straight from them. Every
/// rank's report is gathered before rank 0 assembles the matrix.
fn gather_on_root(
    ctx: &Context,
    est: &dyn Estimator,
    cluster: &dyn Cluster,
    (chunks, costs): (&[std::ops::Range<usize>], &[f64]),
    mut report: RankReport,
    (start, traffic0): (Instant, Traffic),
    progress: &(dyn Fn(u64) + Sync),
) -> Result<(Share, Vec<RankReport>)> {
    let (n, k, me) = (ctx.patches.len(), cluster.size(), cluster.rank());
    let upper = est.upper_only();
    let stop = AtomicBool::new(false);
    let rows_done: OnceLock<(Instant, f64)> = OnceLock::new();
    // Chunks to compute here (from rank 0's answers; rank 0 takes its own from `next`),
    // and the rows computed, to the main thread.
    let (job_tx, job_rx) = std::sync::mpsc::channel::<usize>();
    let (row_tx, row_rx) = std::sync::mpsc::channel::<(usize, Vec<Vec<Entry>>, u64)>();
    let next = AtomicUsize::new(0);
    let (t_rows, cpu) = (Instant::now(), crate::cluster::cpu_seconds());
    let done = AtomicU64::new(0);
    // Rank 0: where each row is (received messages, or its own rows).
    let mut received: Vec<Vec<u8>> = Vec::new();
    let mut at_root: Vec<Option<Place>> = if me == 0 {
        (0..n).map(|_| None).collect()
    } else {
        Vec::new()
    };
    let (mut rays, mut entries, mut mine) = (0u64, 0u64, Vec::new());
    let mut take = |c: usize, rows: &Vec<Vec<Entry>>, r: u64| {
        rays += r;
        entries += rows.iter().map(|r| r.len() as u64).sum::<u64>();
        mine.push(c);
    };
    let talk = || -> Result<()> {
        // Dropped when this returns: the compute threads then stop asking.
        let job_tx = job_tx;
        if me != 0 {
            let ask = || -> Result<Option<usize>> {
                cluster.send(0, &ASK.to_le_bytes())?;
                let (from, answer) = cluster.receive_any()?;
                match <[u8; 8]>::try_from(&answer[..]) {
                    Ok(b) if from == 0 => {
                        let c = u64::from_le_bytes(b);
                        Ok((c != NONE_LEFT).then_some(c as usize))
                    }
                    _ => Err(cluster.fail(format!(
                        "an answer of {} bytes from rank {from}",
                        answer.len()
                    ))),
                }
            };
            let (mut queued, mut exhausted) = (0, false);
            loop {
                while queued < 2 && !exhausted {
                    match ask()? {
                        Some(c) if c < chunks.len() => {
                            let _ = job_tx.send(c);
                            queued += 1;
                        }
                        Some(c) => {
                            return Err(cluster.fail(format!("chunk {c} of {}", chunks.len())))
                        }
                        None => exhausted = true,
                    }
                }
                if queued == 0 {
                    return Ok(());
                }
                let Ok((c, rows, r)) = row_rx.recv() else {
                    return Err(cluster.fail("the rows stopped before the last chunk".into()));
                };
                queued -= 1;
                take(c, &rows, r);
                // Messages of whole rows, each under MESSAGE_BYTES when rows allow.
                let ids = chunks[c].clone();
                let mut lo = 0;
                while lo < rows.len() {
                    let t = Instant::now();
                    let mut bytes = 4 + row_bytes(rows[lo].len());
                    let mut hi = lo + 1;
                    while hi < rows.len() && bytes + row_bytes(rows[hi].len()) <= MESSAGE_BYTES {
                        bytes += row_bytes(rows[hi].len());
                        hi += 1;
                    }
                    let mut buf = vec![0u8; bytes];
                    buf[..4].copy_from_slice(&ROWS.to_le_bytes());
                    let mut at = 4;
                    for (i, r) in ids.clone().skip(lo).zip(&rows[lo..hi]) {
                        at = put_row(&mut buf, at, i, r);
                    }
                    report.pack_seconds += t.elapsed().as_secs_f64();
                    let t = Instant::now();
                    cluster.send(0, &buf)?;
                    report.exchange_seconds += t.elapsed().as_secs_f64();
                    lo = hi;
                }
            }
        }
        // Rank 0: deal chunks, place rows, until every row is here and every other rank
        // has been told that none is left.
        let (mut missing, mut told) = (n, 0);
        let mut nap = crate::cluster::NAP_FIRST;
        while missing > 0 || told + 1 < k {
            let mut busy = false;
            while let Ok((c, rows, r)) = row_rx.try_recv() {
                take(c, &rows, r);
                for (i, r) in chunks[c].clone().zip(rows) {
                    if at_root[i].is_some() {
                        return Err(cluster.fail(format!("row {i} came twice")));
                    }
                    at_root[i] = Some(Place::Own(r));
                    missing -= 1;
                }
                busy = true;
            }
            let t = Instant::now();
            let got = if k > 1 { cluster.try_receive()? } else { None };
            report.exchange_seconds += t.elapsed().as_secs_f64();
            if let Some((src, bytes)) = got {
                busy = true;
                let t = Instant::now();
                let kind = bytes.get(..4).map(word);
                if kind == Some(ASK) {
                    let c = next.fetch_add(1, Ordering::Relaxed);
                    let answer = if c < chunks.len() {
                        c as u64
                    } else {
                        NONE_LEFT
                    };
                    told += usize::from(answer == NONE_LEFT);
                    cluster.send(src, &answer.to_le_bytes())?;
                } else if kind == Some(ROWS) {
                    let (mut bad, mut placed) = (None, 0);
                    each_part(cluster, &bytes[4..], n, |i, at| {
                        if bad.is_some() {
                            return;
                        }
                        if !check_part(&bytes[4 + at..], i, n, upper) {
                            bad = Some(format!(
                                "malformed row {i} from rank {src}: a column past the patch \
                                 count, out of order, or (upper triangle) not past the row"
                            ));
                        } else if at_root[i].is_some() {
                            bad = Some(format!("row {i} came twice"));
                        } else {
                            at_root[i] = Some(Place::Received(received.len(), 4 + at));
                            missing -= 1;
                            placed += 1;
                        }
                    })?;
                    if let Some(msg) = bad {
                        return Err(cluster.fail(msg));
                    }
                    progress(done.fetch_add(placed, Ordering::Relaxed) + placed);
                    received.push(bytes);
                } else {
                    return Err(cluster.fail(format!(
                        "a message of {} bytes from rank {src}",
                        bytes.len()
                    )));
                }
                report.pack_seconds += t.elapsed().as_secs_f64();
            }
            if busy {
                nap = crate::cluster::NAP_FIRST;
            } else {
                std::thread::sleep(nap);
                nap = (nap * 2).min(crate::cluster::NAP_LAST);
            }
        }
        Ok(())
    };
    let talked = in_place_scope_in(cluster.compute_pool(), |s| {
        let (stop, rows_done, done, next) = (&stop, &rows_done, &done, &next);
        let total = n as u64;
        s.spawn(move |_| {
            let job = || {
                if me == 0 {
                    let c = next.fetch_add(1, Ordering::Relaxed);
                    (c < chunks.len()).then_some(c)
                } else {
                    job_rx.recv().ok()
                }
            };
            while let Some(c) = job() {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                let (rows, r) = rows_par(ctx, est, chunks[c].clone(), done, total, progress);
                if row_tx.send((c, rows, r)).is_err() {
                    break;
                }
            }
            let _ = rows_done.set((Instant::now(), crate::cluster::cpu_seconds()));
        });
        let r = talk();
        if r.is_err() {
            stop.store(true, Ordering::Relaxed);
        }
        r
    });
    talked?;
    let end = Instant::now();
    if let Some(&(t, c)) = rows_done.get() {
        report.rows_seconds = t.duration_since(t_rows).as_secs_f64();
        report.rows_cpu_seconds = c - cpu;
        report.wait_seconds = end.duration_since(t).as_secs_f64();
    }
    mine.sort_unstable();
    let total: f64 = costs.iter().sum();
    let my_cost: f64 = mine
        .iter()
        .flat_map(|&c| chunks[c].clone())
        .map(|i| costs[i])
        .sum();
    report.cost_share = if total > 0.0 { my_cost / total } else { 0.0 };
    report.rows = mine.iter().map(|&c| chunks[c].len()).sum();
    report.rays = rays;
    report.entries = entries;
    let mut counters = [rays];
    cluster.all_sum_u64(&mut counters)?;
    let all_rays = counters[0];
    let tr: Traffic = cluster.traffic() - traffic0;
    (report.sent, report.received) = (tr.sent, tr.received);
    // Every rank's report now, before rank 0 assembles alone: the others are done.
    let mut ranks = report.gather(cluster)?;
    if me != 0 {
        return Ok((Share::Elsewhere, ranks));
    }
    let t = Instant::now();
    let mut rows = Vec::with_capacity(n);
    for (i, p) in at_root.into_iter().enumerate() {
        rows.push(match p {
            None => return Err(cluster.fail(format!("row {i} came from no rank"))),
            Some(Place::Own(r)) => GatheredRow::Own(r),
            Some(Place::Received(m, at)) => GatheredRow::Wire(&received[m][at..]),
        });
    }
    let ff = assemble(ctx, est, rows, all_rays, start.elapsed().as_secs_f64());
    ranks[0].assembly_seconds = t.elapsed().as_secs_f64();
    Ok((Share::Whole(ff), ranks))
}

/// Where rank 0 holds row `i` of a gather: computed there, or in a received message
/// (`(message, offset of the row's header)`).
enum Place {
    Own(Vec<Entry>),
    Received(usize, usize),
}

/// A row of a gather as the assembly reads it on rank 0: computed there, or the bytes
/// of the row part another rank sent, from its header on (checked by [`check_part`]),
/// read in place.
enum GatheredRow<'a> {
    Own(Vec<Entry>),
    Wire(&'a [u8]),
}

impl RowEntries for GatheredRow<'_> {
    fn len(&self) -> usize {
        match self {
            GatheredRow::Own(r) => r.len(),
            GatheredRow::Wire(b) => word(&b[4..8]) as usize,
        }
    }

    fn at(&self, k: usize) -> Entry {
        match self {
            GatheredRow::Own(r) => r[k],
            GatheredRow::Wire(b) => wire_entry(&b[8 + 20 * k..8 + 20 * (k + 1)]),
        }
    }
}

/// A little-endian `u32`.
fn word(b: &[u8]) -> u32 {
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// The entry of a 20-byte wire record ([module docs](self)).
fn wire_entry(rec: &[u8]) -> Entry {
    let f64_at = |o: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&rec[o..o + 8]);
        f64::from_bits(u64::from_le_bytes(b))
    };
    Entry {
        j: word(rec),
        f: f64_at(4),
        se: f64_at(12),
    }
}

/// True when the row part whose header starts `buf` (found by [`each_part`], row `i`)
/// has its columns under `n` and increasing, and past `i` when only the upper triangle is
/// sent: what the assembly relies on.
fn check_part(buf: &[u8], i: usize, n: usize, upper: bool) -> bool {
    let len = word(&buf[4..8]) as usize;
    let mut last: Option<u32> = None;
    buf[8..8 + 20 * len].chunks_exact(20).all(|rec| {
        let j = word(rec);
        let ok = (j as usize) < n && last.is_none_or(|l| l < j) && (!upper || j as usize > i);
        last = Some(j);
        ok
    })
}

/// `f` on the calling thread inside a scope whose spawned work runs on `pool` (the
/// global pool when `None`): `rayon::in_place_scope` there.
fn in_place_scope_in<'s, T>(
    pool: Option<&rayon::ThreadPool>,
    f: impl FnOnce(&rayon::Scope<'s>) -> T,
) -> T {
    match pool {
        Some(p) => p.in_place_scope(f),
        None => rayon::in_place_scope(f),
    }
}

/// The whole matrix from every row (`rows[i]` as [`rows_par`] leaves it), assembled as
/// [`super::compute_timed`] assembles it.
fn assemble<R: RowEntries>(
    ctx: &Context,
    est: &dyn Estimator,
    rows: Vec<R>,
    rays: u64,
    seconds: f64,
) -> FormFactors {
    let area = &ctx.patches.area;
    let csr = if est.upper_only() {
        CsrBuilder::from_upper(&rows, area)
    } else {
        let nnz: usize = rows.iter().map(R::len).sum();
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

    /// Chunks cover every row once, in order; they shrink (guided self-scheduling) to a
    /// floor, and there are few of them.
    #[test]
    fn chunks_cover_the_rows_and_shrink() {
        let costs: Vec<f64> = (0..6144).map(|i| (6144 - i) as f64).collect();
        for k in 1..=4 {
            let chunks = deal_chunks(&costs, k);
            assert_eq!(chunks[0].start, 0);
            assert_eq!(chunks.last().unwrap().end, costs.len());
            assert!(chunks.windows(2).all(|w| w[0].end == w[1].start));
            let cost = |c: &std::ops::Range<usize>| costs[c.clone()].iter().sum::<f64>();
            let total: f64 = costs.iter().sum();
            // The first holds a quarter of the whole over the ranks, the last little.
            assert!(
                (cost(&chunks[0]) / total - 0.25 / k as f64).abs() < 0.01,
                "{k}"
            );
            assert!(cost(chunks.last().unwrap()) < 2.0 * total / (MIN_CHUNK_PARTS * k as f64));
            assert!(chunks.len() < 64 * k, "{k}: {}", chunks.len());
        }
        assert!(deal_chunks(&[], 2).is_empty());
        assert_eq!(deal_chunks(&[0.0; 5], 2), vec![0..5]);
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
