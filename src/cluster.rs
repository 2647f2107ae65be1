//! Processes working on one run together: the [`Cluster`] trait the distributed stages
//! talk through, one process alone ([`Single`]), and ranks on threads of one process
//! ([`Local`], for tests of the distributed paths without MPI).
//!
//! The MPI implementation (`crate::mpi`, cargo feature `mpi`) lives downstream of
//! everything and is only built with the feature; the form factors
//! ([`crate::formfactor::shard`]), the solver ([`crate::solve::distributed`]) and the
//! pipeline see nothing but this trait.
//!
//! Every operation but [`Cluster::send`] and [`Cluster::receive_any`] is collective:
//! every rank calls it, in the same order, or the run hangs. Those two are point to
//! point: every message sent must be received, in the order of the protocol of their
//! caller. A rank that fails does not return from a collective with an error to the
//! others; under MPI it aborts the whole job (see `crate::mpi`).

use std::cell::Cell;
use std::collections::VecDeque;
use std::sync::{Arc, Barrier, Mutex};

use crate::error::{Error, Result};

/// First sleep between two tests of a pending operation (a message, a barrier): short
/// enough for a latency well under a chunk of rows' computing.
pub const NAP_FIRST: std::time::Duration = std::time::Duration::from_micros(50);

/// Longest such sleep, each one doubling the last: long enough to leave the core to the
/// rank's compute threads (Open MPI's blocking calls spin).
pub const NAP_LAST: std::time::Duration = std::time::Duration::from_millis(2);

/// Bytes this rank has sent to and received from other ranks (its own share, which
/// never leaves the process, is not counted).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Traffic {
    /// Bytes sent to other ranks.
    pub sent: u64,
    /// Bytes received from other ranks.
    pub received: u64,
}

impl std::ops::Sub for Traffic {
    type Output = Traffic;
    fn sub(self, o: Traffic) -> Traffic {
        Traffic {
            sent: self.sent - o.sent,
            received: self.received - o.received,
        }
    }
}

/// One byte buffer per rank, end to end in one allocation (what [`Cluster::exchange`]
/// sends and returns): rank `r`'s bytes are `data[offsets[r]..offsets[r + 1]]`.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Packed {
    /// The bytes of every rank, in rank order.
    pub data: Vec<u8>,
    /// `ranks + 1` offsets into `data`, from 0 to its length.
    pub offsets: Vec<usize>,
}

impl Packed {
    /// Zeroed buffers of `sizes[r]` bytes for each rank `r` (the zeros cost nothing until
    /// written: the allocation is zeroed by the system), with a spare byte of capacity
    /// so that the allocation is real even when every buffer is empty.
    pub fn zeroed(sizes: &[usize]) -> Packed {
        let mut offsets = Vec::with_capacity(sizes.len() + 1);
        offsets.push(0);
        for &b in sizes {
            offsets.push(offsets[offsets.len() - 1] + b);
        }
        let total = offsets[sizes.len()];
        let mut data = vec![0u8; total + 1];
        data.truncate(total);
        Packed { data, offsets }
    }

    /// The buffers `parts` end to end (moved, not copied, when at most one is not empty).
    pub fn from_parts(mut parts: Vec<Vec<u8>>) -> Packed {
        let mut offsets = Vec::with_capacity(parts.len() + 1);
        offsets.push(0);
        for p in &parts {
            offsets.push(offsets[offsets.len() - 1] + p.len());
        }
        let full: Vec<usize> = (0..parts.len()).filter(|&r| !parts[r].is_empty()).collect();
        let data = if full.len() == 1 {
            std::mem::take(&mut parts[full[0]])
        } else {
            parts.concat()
        };
        Packed { data, offsets }
    }

    /// Number of ranks.
    pub fn ranks(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// Rank `r`'s bytes.
    pub fn part(&self, r: usize) -> &[u8] {
        &self.data[self.offsets[r]..self.offsets[r + 1]]
    }

    /// Rank `r`'s bytes, to write.
    pub fn part_mut(&mut self, r: usize) -> &mut [u8] {
        &mut self.data[self.offsets[r]..self.offsets[r + 1]]
    }

    /// Every rank's bytes, as separate buffers.
    pub fn into_parts(self) -> Vec<Vec<u8>> {
        (0..self.ranks()).map(|r| self.part(r).to_vec()).collect()
    }
}

/// The processes of one run, and the few operations the distributed stages need. Of the
/// collectives only [`Cluster::exchange`] must be implemented; the others have defaults
/// built on it (an implementation may replace them by native collectives with the same
/// result). The point-to-point [`Cluster::send`] and [`Cluster::try_receive`] must be
/// implemented too ([`Cluster::receive_any`] waits on the latter).
pub trait Cluster {
    /// This process's rank, `0..size`.
    fn rank(&self) -> usize;

    /// Number of ranks.
    fn size(&self) -> usize;

    /// The thread pool this rank computes its share of the rows on, when it is not the
    /// global one: under MPI, rank 0's global pool also has the threads of the node's other
    /// ranks, for what it does alone after they are done (`crate::mpi`).
    fn compute_pool(&self) -> Option<&rayon::ThreadPool> {
        None
    }

    /// True on rank 0, the one that writes files and prints summaries.
    fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Personalised all-to-all: `send.part(r)` goes to rank `r` (`send.ranks() == size`;
    /// this rank's own part comes back too). Returns what every rank sent to this one, by
    /// rank.
    fn exchange(&self, send: Packed) -> Result<Packed>;

    /// All-gather: every rank's `mine` (`counts[r]` values from rank `r`, the same
    /// `counts` on every rank) concatenated in rank order into `out`
    /// (`sum(counts)` long).
    fn all_gather_f64(&self, mine: &[f64], counts: &[usize], out: &mut [f64]) -> Result<()> {
        check_counts(self, mine.len(), counts, out.len())?;
        let got = self.all_gather_bytes(f64s_to_bytes(mine))?;
        let mut at = 0;
        for (r, b) in got.iter().enumerate() {
            let v = bytes_to_f64s(b);
            if v.len() != counts[r] {
                return Err(self.fail(format!(
                    "rank {r} sent {} values to an all-gather of {}",
                    v.len(),
                    counts[r]
                )));
            }
            out[at..at + v.len()].copy_from_slice(&v);
            at += v.len();
        }
        Ok(())
    }

    /// Element-wise maximum over ranks, in place; NaN wins (as `solve::max3` keeps it),
    /// so that a NaN on any rank is seen by all.
    fn all_max(&self, v: &mut [f64]) -> Result<()> {
        let k = v.len();
        let counts = vec![k; self.size()];
        let mut all = vec![0.0; k * self.size()];
        self.all_gather_f64(v, &counts, &mut all)?;
        for (c, x) in v.iter_mut().enumerate() {
            *x = all
                .iter()
                .skip(c)
                .step_by(k)
                .copied()
                .fold(f64::NEG_INFINITY, |a, b| {
                    if a.is_nan() || b.is_nan() {
                        f64::NAN
                    } else {
                        a.max(b)
                    }
                });
        }
        Ok(())
    }

    /// Element-wise sum over ranks of counters, in place.
    fn all_sum_u64(&self, v: &mut [u64]) -> Result<()> {
        let mine: Vec<u8> = v.iter().flat_map(|x| x.to_le_bytes()).collect();
        let got = self.all_gather_bytes(mine)?;
        v.iter_mut().for_each(|x| *x = 0);
        for b in &got {
            if b.len() != 8 * v.len() {
                return Err(self.fail("a rank sent counters of another length".into()));
            }
            for (x, c) in v.iter_mut().zip(b.chunks_exact(8)) {
                *x += u64::from_le_bytes(c.try_into().expect("8 bytes"));
            }
        }
        Ok(())
    }

    /// Every rank's bytes, by rank (all-gather of variable length).
    fn all_gather_bytes(&self, mine: Vec<u8>) -> Result<Vec<Vec<u8>>> {
        Ok(self
            .exchange(Packed::from_parts(vec![mine; self.size()]))?
            .into_parts())
    }

    /// A barrier that waits without keeping a core busy, for the places where ranks may
    /// wait long (for the slowest rank's rows; for rank 0 alone at the end): MPI's
    /// blocking collectives poll at full speed, which takes a core from ranks still at
    /// work when there are more ranks than cores. Without MPI there is nothing to wait for.
    fn wait_for_all(&self) -> Result<()> {
        Ok(())
    }

    /// Sends `bytes` to rank `to` (not collective: `to` takes them with
    /// [`Cluster::receive_any`]). Returns once the bytes have left `bytes`; waiting
    /// sleeps rather than spins, so that a rank's compute threads keep its cores.
    fn send(&self, to: usize, bytes: &[u8]) -> Result<()>;

    /// The next bytes some rank sent to this one with [`Cluster::send`], and its rank,
    /// when some have arrived (messages of one sender arrive in the order it sent them).
    fn try_receive(&self) -> Result<Option<(usize, Vec<u8>)>>;

    /// [`Cluster::try_receive`] until bytes arrive, sleeping from [`NAP_FIRST`] to
    /// [`NAP_LAST`] in between rather than spinning.
    fn receive_any(&self) -> Result<(usize, Vec<u8>)> {
        let mut nap = NAP_FIRST;
        loop {
            if let Some(m) = self.try_receive()? {
                return Ok(m);
            }
            std::thread::sleep(nap);
            nap = (nap * 2).min(NAP_LAST);
        }
    }

    /// Bytes this rank has sent and received so far.
    fn traffic(&self) -> Traffic;

    /// The error for a failure on this rank.
    fn fail(&self, msg: String) -> Error {
        Error::Cluster {
            rank: self.rank(),
            size: self.size(),
            msg,
        }
    }
}

fn check_counts<C: Cluster + ?Sized>(
    c: &C,
    mine: usize,
    counts: &[usize],
    out: usize,
) -> Result<()> {
    if counts.len() != c.size() || counts[c.rank()] != mine || counts.iter().sum::<usize>() != out {
        return Err(c.fail(format!(
            "all-gather of {mine} values with counts {counts:?} into {out}"
        )));
    }
    Ok(())
}

/// The number of processes an MPI launcher (`mpirun`, `mpiexec`) started together, when
/// the environment says (Open MPI's `OMPI_COMM_WORLD_SIZE`, PMI's `PMI_SIZE`): a binary
/// built without MPI refuses to run as one of several, each of which would do the whole
/// run and write the same folder.
pub fn launched_size() -> Option<usize> {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"]
        .iter()
        .find_map(|v| std::env::var(v).ok()?.trim().parse().ok())
}

/// CPU seconds of this process so far (every thread): the sum of its threads' run times
/// in `/proc/self/task/*/schedstat` (nanoseconds; the kernel's scheduler accounting), or
/// where that is missing, user + system time from `/proc/self/stat` (fields 14 and 15, in
/// clock ticks of 1/100 s); 0 where there is no `/proc`. A rank's CPU time, unlike its wall
/// time, does not count the time the system gave to other ranks sharing its cores. Threads
/// that have exited no longer count in the first form: take differences across work done
/// by a pool that outlives it (rayon's).
pub fn cpu_seconds() -> f64 {
    schedstat_seconds().unwrap_or_else(stat_seconds)
}

fn schedstat_seconds() -> Option<f64> {
    let mut ns: u64 = 0;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let path = task.ok()?.path().join("schedstat");
        // A thread may exit between the listing and the read: it no longer counts.
        let Ok(text) = std::fs::read_to_string(&path) else {
            continue;
        };
        ns += text.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(ns as f64 * 1e-9)
}

fn stat_seconds() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let rest = s.rsplit_once(')')?.1;
            let f: Vec<&str> = rest.split_whitespace().collect();
            let u: f64 = f.get(11)?.parse().ok()?;
            let k: f64 = f.get(12)?.parse().ok()?;
            Some((u + k) / 100.0)
        })
        .unwrap_or(0.0)
}

/// Runs `f` on `pool` when given (a rank's [`Cluster::compute_pool`]), else here.
pub fn in_pool<T: Send>(pool: Option<&rayon::ThreadPool>, f: impl FnOnce() -> T + Send) -> T {
    match pool {
        Some(p) => p.install(f),
        None => f(),
    }
}

/// `f64`s as little-endian bytes.
pub fn f64s_to_bytes(v: &[f64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_bits().to_le_bytes()).collect()
}

/// Little-endian bytes as `f64`s (a trailing partial value is ignored).
pub fn bytes_to_f64s(b: &[u8]) -> Vec<f64> {
    b.chunks_exact(8)
        .map(|c| f64::from_bits(u64::from_le_bytes(c.try_into().expect("8 bytes"))))
        .collect()
}

/// One process alone: rank 0 of 1.
#[derive(Clone, Copy, Debug, Default)]
pub struct Single;

impl Cluster for Single {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn exchange(&self, send: Packed) -> Result<Packed> {
        if send.ranks() != 1 {
            return Err(self.fail(format!("{} buffers for one rank", send.ranks())));
        }
        Ok(send)
    }
    fn all_gather_f64(&self, mine: &[f64], counts: &[usize], out: &mut [f64]) -> Result<()> {
        check_counts(self, mine.len(), counts, out.len())?;
        out.copy_from_slice(mine);
        Ok(())
    }
    fn all_max(&self, _: &mut [f64]) -> Result<()> {
        Ok(())
    }
    fn all_sum_u64(&self, _: &mut [u64]) -> Result<()> {
        Ok(())
    }
    fn send(&self, to: usize, _: &[u8]) -> Result<()> {
        Err(self.fail(format!("a message to rank {to} of a run of one process")))
    }
    fn try_receive(&self) -> Result<Option<(usize, Vec<u8>)>> {
        Err(self.fail("a message awaited in a run of one process".into()))
    }
    fn traffic(&self) -> Traffic {
        Traffic::default()
    }
}

/// What the ranks of a [`Local`] cluster share: a barrier and one mailbox per ordered
/// pair of ranks.
/// A point-to-point message: its sender and its bytes.
type Message = (usize, Vec<u8>);

struct Hub {
    barrier: Barrier,
    mail: Mutex<Vec<Vec<u8>>>,
    /// Point-to-point messages waiting, per receiving rank.
    inbox: Mutex<Vec<VecDeque<Message>>>,
}

/// Ranks on threads of one process, talking through shared memory: the distributed code
/// paths, tested without MPI ([`Local::run`]). Each rank should run in its own thread;
/// work inside a rank still goes to the (shared) rayon pool.
pub struct Local {
    rank: usize,
    size: usize,
    hub: Arc<Hub>,
    traffic: Cell<Traffic>,
}

impl Local {
    /// Runs `f` on `size` ranks, each on its own thread, and returns their results by
    /// rank. A rank that returns early while the others wait in a collective hangs the
    /// run: it is for tests.
    pub fn run<T: Send>(size: usize, f: impl Fn(&Local) -> T + Sync) -> Vec<T> {
        let hub = Arc::new(Hub {
            barrier: Barrier::new(size),
            mail: Mutex::new(vec![Vec::new(); size * size]),
            inbox: Mutex::new(vec![VecDeque::new(); size]),
        });
        std::thread::scope(|s| {
            let handles: Vec<_> = (0..size)
                .map(|rank| {
                    let (hub, f) = (hub.clone(), &f);
                    s.spawn(move || {
                        f(&Local {
                            rank,
                            size,
                            hub,
                            traffic: Cell::new(Traffic::default()),
                        })
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().expect("a rank panicked"))
                .collect()
        })
    }
}

impl Cluster for Local {
    fn rank(&self) -> usize {
        self.rank
    }
    fn size(&self) -> usize {
        self.size
    }
    fn exchange(&self, send: Packed) -> Result<Packed> {
        if send.ranks() != self.size {
            return Err(self.fail(format!("{} buffers for {} ranks", send.ranks(), self.size)));
        }
        let mut t = self.traffic.get();
        {
            let mut mail = self.hub.mail.lock().unwrap_or_else(|e| e.into_inner());
            for (to, b) in send.into_parts().into_iter().enumerate() {
                if to != self.rank {
                    t.sent += b.len() as u64;
                }
                mail[self.rank * self.size + to] = b;
            }
        }
        self.hub.barrier.wait();
        let got: Vec<Vec<u8>> = {
            let mut mail = self.hub.mail.lock().unwrap_or_else(|e| e.into_inner());
            (0..self.size)
                .map(|from| std::mem::take(&mut mail[from * self.size + self.rank]))
                .collect()
        };
        for (from, b) in got.iter().enumerate() {
            if from != self.rank {
                t.received += b.len() as u64;
            }
        }
        self.traffic.set(t);
        // Nobody writes the mailboxes again before everyone has read theirs.
        self.hub.barrier.wait();
        Ok(Packed::from_parts(got))
    }
    fn send(&self, to: usize, bytes: &[u8]) -> Result<()> {
        if to >= self.size || to == self.rank {
            return Err(self.fail(format!("a message to rank {to}")));
        }
        let mut inbox = self.hub.inbox.lock().unwrap_or_else(|e| e.into_inner());
        inbox[to].push_back((self.rank, bytes.to_vec()));
        let mut t = self.traffic.get();
        t.sent += bytes.len() as u64;
        self.traffic.set(t);
        Ok(())
    }
    fn try_receive(&self) -> Result<Option<(usize, Vec<u8>)>> {
        let mut inbox = self.hub.inbox.lock().unwrap_or_else(|e| e.into_inner());
        let got = inbox[self.rank].pop_front();
        if let Some((_, bytes)) = &got {
            let mut t = self.traffic.get();
            t.received += bytes.len() as u64;
            self.traffic.set(t);
        }
        Ok(got)
    }
    fn traffic(&self) -> Traffic {
        self.traffic.get()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn local_collectives() {
        let out = Local::run(3, |c| {
            let r = c.rank();
            let got = c
                .exchange(Packed::from_parts(
                    (0..3).map(|to| vec![r as u8, to as u8]).collect(),
                ))
                .unwrap();
            for from in 0..3 {
                assert_eq!(got.part(from), &[from as u8, r as u8]);
            }
            let counts = [1, 2, 3];
            let mine: Vec<f64> = (0..counts[r]).map(|k| (10 * r + k) as f64).collect();
            let mut all = vec![0.0; 6];
            c.all_gather_f64(&mine, &counts, &mut all).unwrap();
            assert_eq!(all, [0.0, 10.0, 11.0, 20.0, 21.0, 22.0]);
            let mut m = [r as f64, -(r as f64), if r == 1 { f64::NAN } else { 0.0 }];
            c.all_max(&mut m).unwrap();
            assert_eq!(&m[..2], &[2.0, 0.0]);
            assert!(m[2].is_nan());
            let mut s = [r as u64, 1];
            c.all_sum_u64(&mut s).unwrap();
            assert_eq!(s, [3, 3]);
            c.traffic()
        });
        // Rank 0 sent 2 bytes to each of two others in the exchange, and so on.
        assert!(out.iter().all(|t| t.sent > 0 && t.received > 0));
        let sent: u64 = out.iter().map(|t| t.sent).sum();
        let received: u64 = out.iter().map(|t| t.received).sum();
        assert_eq!(sent, received);
    }
}
