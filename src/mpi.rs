//! MPI ranks as a [`Cluster`] (cargo feature `mpi`: rsmpi over Open MPI).
//!
//! `mpirun -np K radiosity factors|bake ...` starts K processes; [`World::init`] makes
//! them one run: it initialises MPI (`MPI_THREAD_FUNNELED`: only the main thread calls
//! MPI, rayon's workers never do) and sets the threads (see [`World::init`]). The
//! distributed stages (`crate::pipeline::distributed`) talk through the [`Cluster`]
//! trait only; this module is the one place that knows MPI.
//!
//! Failures. MPI's default error handler makes any MPI error fatal to the whole job. A
//! rank whose own work fails (an error, not a crash) prints it and calls `MPI_Abort`
//! ([`World::abort`]), which ends every rank: nobody waits forever in a collective, and
//! since only rank 0 writes, and only after every row has arrived, no output folder is
//! left (the folder code writes a hidden sibling and renames it last; a sibling of a
//! killed run is removed by the next run into the same path). A rank that dies (killed,
//! crashed) is noticed by `mpirun`, which ends the others and says which rank died.
//!
//! Fault injection, for the tests of that: `RADIOSITY_FAULT=RANK:error` makes rank RANK
//! fail with an error, `RADIOSITY_FAULT=RANK:kill` makes it kill itself with SIGKILL, both
//! on entering its first exchange of form-factor rows (after its first chunk of rows, when
//! they are streamed to rank 0; after its whole share, for the blocks of a distributed
//! solve).

use std::cell::Cell;

use ::mpi::collective::SystemOperation;
use ::mpi::datatype::{Partition, PartitionMut};
use ::mpi::environment::Universe;
use ::mpi::topology::SimpleCommunicator;
use ::mpi::traits::*;
use ::mpi::{Count, Threading};

use crate::cluster::{Cluster, Packed, Traffic};
use crate::error::{Error, Result};

/// True when this process was started by `mpirun` (or another MPI launcher): the
/// environment of Open MPI, PMIx or a PMI-2 launcher says so. Without a launcher the
/// program runs as one process and never initialises MPI.
pub fn launched() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK", "PMI_SIZE"]
        .iter()
        .any(|v| std::env::var_os(v).is_some())
}

/// Bytes moved per pair of ranks per round of [`World::exchange`], divided by the number
/// of ranks: each `MPI_Alltoallv` stays under 1 GiB (its counts and displacements are
/// `int`s).
const ROUND_BYTES: usize = 1 << 30;

/// The tag of [`Cluster::send`]'s messages.
const ROWS_TAG: i32 = 17;

/// What `RADIOSITY_FAULT` asks of this rank.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Fault {
    Error,
    Kill,
}

/// The ranks of `MPI_COMM_WORLD`.
pub struct World {
    // Dropped last: `MPI_Finalize`.
    _universe: Universe,
    world: SimpleCommunicator,
    local: usize,
    pool: Option<rayon::ThreadPool>,
    traffic: Cell<Traffic>,
    fault: Cell<Option<Fault>>,
}

impl World {
    /// Initialises MPI and the threads. Each rank computes on `threads` worker threads
    /// (default: the node's cores divided among the ranks on the node, at least 1). With
    /// several ranks, rank 0's global pool also gets the threads of the node's other
    /// ranks, for what it does alone once they are done (assembling and writing the
    /// gathered matrix, the single-process solvers); it computes its share of the rows on
    /// a pool of its own ([`Cluster::compute_pool`]). `mpirun` binds each rank to cores of
    /// its own (Open MPI: one core each for up to 2 ranks), which would leave that pool on
    /// rank 0's core: its threads are allowed every CPU the node's ranks were given
    /// (`sched_setaffinity`); the compute pools keep the launcher's binding.
    pub fn init(threads: Option<usize>) -> Result<World> {
        one_node_transport();
        let Some((universe, _)) = ::mpi::initialize_with_threading(Threading::Funneled) else {
            return Err(Error::Config("MPI was initialised twice".into()));
        };
        let world = universe.world();
        let node = world.split_shared(world.rank());
        let local = node.size().max(1) as usize;
        let node_cpus = node_cpus(&node);
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let per_rank = threads.unwrap_or((cores / local).max(1));
        let (size, rank) = (world.size() as usize, world.rank() as usize);
        let fault = std::env::var("RADIOSITY_FAULT").ok().and_then(|v| {
            let (r, what) = v.split_once(':')?;
            (r.trim().parse::<usize>().ok()? == rank).then_some(())?;
            match what.trim() {
                "error" => Some(Fault::Error),
                "kill" => Some(Fault::Kill),
                _ => None,
            }
        });
        let global = if size > 1 && rank == 0 {
            per_rank * local
        } else {
            per_rank
        };
        let fail = |e: rayon::ThreadPoolBuildError| Error::Cluster {
            rank,
            size,
            msg: format!("cannot set {global} threads: {e}"),
        };
        let mut builder = rayon::ThreadPoolBuilder::new().num_threads(global);
        if global != per_rank {
            // `mpirun` binds each rank to its cores: rank 0's pool for its lone work may
            // run on those of every rank of its node (they are idle by then).
            if let Some(cpus) = node_cpus {
                builder = builder.start_handler(move |_| {
                    let mut set = nix::sched::CpuSet::new();
                    for &c in &cpus {
                        let _ = set.set(c);
                    }
                    let _ = nix::sched::sched_setaffinity(nix::unistd::Pid::from_raw(0), &set);
                });
            }
        }
        builder.build_global().map_err(fail)?;
        let pool = if global != per_rank {
            Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(per_rank)
                    .build()
                    .map_err(fail)?,
            )
        } else {
            None
        };
        Ok(World {
            _universe: universe,
            world,
            local,
            pool,
            traffic: Cell::new(Traffic::default()),
            fault: Cell::new(fault),
        })
    }

    /// Ranks on this node (sharing its memory).
    pub fn local_ranks(&self) -> usize {
        self.local
    }

    /// Ends every rank of the job at once (`MPI_Abort`), with exit code `code`.
    pub fn abort(&self, code: i32) -> ! {
        self.world.abort(code)
    }

    fn add_traffic(&self, sent: usize, received: usize) {
        let mut t = self.traffic.get();
        t.sent += sent as u64;
        t.received += received as u64;
        self.traffic.set(t);
    }

    /// Acts on `RADIOSITY_FAULT` (once).
    fn fault_point(&self) -> Result<()> {
        match self.fault.take() {
            None => Ok(()),
            Some(Fault::Error) => Err(self
                .fail("injected failure (RADIOSITY_FAULT) before sending this rank's rows".into())),
            Some(Fault::Kill) => {
                let pid = std::process::id().to_string();
                let _ = std::process::Command::new("kill")
                    .args(["-KILL", &pid])
                    .status();
                std::thread::sleep(std::time::Duration::from_secs(5));
                std::process::abort()
            }
        }
    }
}

/// Before `MPI_Init`: when Open MPI's launcher says every rank of the job is on this node
/// (`OMPI_COMM_WORLD_LOCAL_SIZE` equals `OMPI_COMM_WORLD_SIZE`) and the user named no
/// point-to-point layer (`OMPI_MCA_pml` unset), names `ob1`: the layer Open MPI picks
/// for one node anyway (over its shared-memory transport), but only after probing the
/// network libraries it was built with (UCX, OFI, PSM), which took 0.2 s of every
/// rank's start on the development machine (0.33 s against 0.12 s for a small
/// `mpirun -np 2 radiosity factors`). Called while the process has one thread.
fn one_node_transport() {
    let var = |v: &str| std::env::var(v).ok();
    let (Some(size), Some(local)) = (
        var("OMPI_COMM_WORLD_SIZE"),
        var("OMPI_COMM_WORLD_LOCAL_SIZE"),
    ) else {
        return;
    };
    if size == local && std::env::var_os("OMPI_MCA_pml").is_none() {
        std::env::set_var("OMPI_MCA_pml", "ob1");
    }
}

/// The CPUs this process may run on (`Cpus_allowed_list` of `/proc/self/status`).
fn allowed_cpus() -> Option<Vec<usize>> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let list = status
        .lines()
        .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))?
        .trim();
    let mut cpus = Vec::new();
    for part in list.split(',') {
        let (a, b) = part.split_once('-').unwrap_or((part, part));
        let (a, b): (usize, usize) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
        cpus.extend(a..=b);
    }
    Some(cpus)
}

/// The CPUs the ranks of this node may run on, together (collective over `node`); `None`
/// when some rank cannot tell.
fn node_cpus(node: &SimpleCommunicator) -> Option<Vec<usize>> {
    let mine: Vec<i32> = match allowed_cpus() {
        Some(c) => c.iter().map(|&x| x as i32).collect(),
        None => vec![-1],
    };
    let k = node.size() as usize;
    let mut counts = vec![0 as Count; k];
    node.all_gather_into(&(mine.len() as Count), &mut counts[..]);
    let displs: Vec<Count> = counts
        .iter()
        .scan(0, |at, &c| {
            let d = *at;
            *at += c;
            Some(d)
        })
        .collect();
    let total = counts.iter().map(|&c| c as usize).sum();
    let mut all = vec![0i32; total];
    {
        let mut r = PartitionMut::new(&mut all[..], counts, displs);
        node.all_gather_varcount_into(&mine[..], &mut r);
    }
    if all.contains(&-1) {
        return None;
    }
    let mut cpus: Vec<usize> = all.into_iter().map(|c| c as usize).collect();
    cpus.sort_unstable();
    cpus.dedup();
    Some(cpus)
}

/// `usize` as an MPI count, or the error for one past `int`.
fn count(cluster: &World, n: usize) -> Result<Count> {
    Count::try_from(n).map_err(|_| cluster.fail(format!("{n} elements in one MPI call")))
}

impl Cluster for World {
    fn rank(&self) -> usize {
        self.world.rank() as usize
    }

    fn size(&self) -> usize {
        self.world.size() as usize
    }

    fn compute_pool(&self) -> Option<&rayon::ThreadPool> {
        self.pool.as_ref()
    }

    /// One `MPI_Alltoallv` straight between the packed buffers when every pair's bytes
    /// fit in `ROUND_BYTES / size`, else several, a piece of each pair's bytes at a time
    /// (after an `MPI_Alltoall` of the lengths and an `MPI_Allreduce` of the rounds).
    fn exchange(&self, mut send: Packed) -> Result<Packed> {
        self.fault_point()?;
        let (k, me) = (self.size(), self.rank());
        if send.ranks() != k {
            return Err(self.fail(format!("{} buffers for {k} ranks", send.ranks())));
        }
        let lens: Vec<u64> = (0..k).map(|r| send.part(r).len() as u64).collect();
        let mut rlens = vec![0u64; k];
        self.world.all_to_all_into(&lens[..], &mut rlens[..]);
        let sizes: Vec<usize> = rlens.iter().map(|&l| l as usize).collect();
        let mut out = Packed::zeroed(&sizes);
        let chunk = (ROUND_BYTES / k).max(1) as u64;
        let longest = lens.iter().chain(&rlens).copied().max().unwrap_or(0);
        let mine = [longest.div_ceil(chunk)];
        let mut rounds = [0u64];
        self.world
            .all_reduce_into(&mine[..], &mut rounds[..], SystemOperation::max());
        let counts =
            |c: &[usize]| -> Result<Vec<Count>> { c.iter().map(|&x| count(self, x)).collect() };
        let displs = |c: &[usize]| -> Result<Vec<Count>> {
            let mut at = 0;
            c.iter()
                .map(|&x| {
                    let d = count(self, at);
                    at += x;
                    d
                })
                .collect()
        };
        if rounds[0] <= 1 {
            // Never a dangling pointer: an empty vector's pointer to bytes is 0x1, which
            // Open MPI reads as MPI_IN_PLACE.
            send.data.reserve(1);
            let scounts: Vec<usize> = lens.iter().map(|&l| l as usize).collect();
            let (sc, sd, rc, rd) = (
                counts(&scounts)?,
                displs(&scounts)?,
                counts(&sizes)?,
                displs(&sizes)?,
            );
            let s = Partition::new(&send.data[..], sc, sd);
            let mut r = PartitionMut::new(&mut out.data[..], rc, rd);
            self.world.all_to_all_varcount_into(&s, &mut r);
        } else {
            for round in 0..rounds[0] {
                let lo = round * chunk;
                let piece = |len: u64| len.saturating_sub(lo).min(chunk) as usize;
                let scounts: Vec<usize> = lens.iter().map(|&l| piece(l)).collect();
                let rcounts: Vec<usize> = rlens.iter().map(|&l| piece(l)).collect();
                let mut sendbuf = Vec::with_capacity(scounts.iter().sum::<usize>() + 1);
                for (r, &c) in scounts.iter().enumerate() {
                    let part = send.part(r);
                    sendbuf.extend_from_slice(&part[(lo as usize).min(part.len())..][..c]);
                }
                let mut recvbuf = vec![0u8; rcounts.iter().sum::<usize>() + 1];
                let (sc, sd, rc, rd) = (
                    counts(&scounts)?,
                    displs(&scounts)?,
                    counts(&rcounts)?,
                    displs(&rcounts)?,
                );
                {
                    let s = Partition::new(&sendbuf[..], sc, sd);
                    let mut r = PartitionMut::new(&mut recvbuf[..], rc, rd);
                    self.world.all_to_all_varcount_into(&s, &mut r);
                }
                let mut at = 0;
                for (r, &c) in rcounts.iter().enumerate() {
                    let lo = lo as usize;
                    out.part_mut(r)[lo..lo + c].copy_from_slice(&recvbuf[at..at + c]);
                    at += c;
                }
            }
        }
        let others = |v: &[u64]| -> usize {
            v.iter()
                .enumerate()
                .filter(|&(r, _)| r != me)
                .map(|(_, &l)| l as usize)
                .sum()
        };
        self.add_traffic(others(&lens), others(&rlens));
        Ok(out)
    }

    fn all_gather_f64(&self, mine: &[f64], counts: &[usize], out: &mut [f64]) -> Result<()> {
        let k = self.size();
        if counts.len() != k
            || counts[self.rank()] != mine.len()
            || counts.iter().sum::<usize>() != out.len()
        {
            return Err(self.fail(format!(
                "all-gather of {} values with counts {counts:?} into {}",
                mine.len(),
                out.len()
            )));
        }
        let c: Vec<Count> = counts
            .iter()
            .map(|&x| count(self, x))
            .collect::<Result<_>>()?;
        let mut at = 0;
        let d: Vec<Count> = counts
            .iter()
            .map(|&x| {
                let v = count(self, at);
                at += x;
                v
            })
            .collect::<Result<_>>()?;
        {
            let mut r = PartitionMut::new(out, c, d);
            self.world.all_gather_varcount_into(mine, &mut r);
        }
        self.add_traffic(8 * mine.len() * (k - 1), 8 * (at - mine.len()));
        Ok(())
    }

    /// `MPI_Ibarrier`, tested with sleeps growing from 50 µs to 2 ms in between.
    fn wait_for_all(&self) -> Result<()> {
        let mut req = self.world.immediate_barrier();
        let mut nap = crate::cluster::NAP_FIRST;
        loop {
            match req.test() {
                Ok(_) => return Ok(()),
                Err(r) => {
                    req = r;
                    std::thread::sleep(nap);
                    nap = (nap * 2).min(crate::cluster::NAP_LAST);
                }
            }
        }
    }

    fn all_sum_u64(&self, v: &mut [u64]) -> Result<()> {
        let mine = v.to_vec();
        self.world
            .all_reduce_into(&mine[..], v, SystemOperation::sum());
        self.add_traffic(8 * v.len(), 8 * v.len());
        Ok(())
    }

    /// `MPI_Isend` (tag `ROWS_TAG`), tested with sleeps growing from 50 µs to 2 ms.
    fn send(&self, to: usize, bytes: &[u8]) -> Result<()> {
        self.fault_point()?;
        if to >= self.size() || to == self.rank() {
            return Err(self.fail(format!("a message to rank {to}")));
        }
        count(self, bytes.len())?;
        let dest = self.world.process_at_rank(to as i32);
        ::mpi::request::scope(|scope| {
            let mut req = dest.immediate_send_with_tag(scope, bytes, ROWS_TAG);
            let mut nap = crate::cluster::NAP_FIRST;
            loop {
                match req.test() {
                    Ok(_) => break,
                    Err(r) => {
                        req = r;
                        std::thread::sleep(nap);
                        nap = (nap * 2).min(crate::cluster::NAP_LAST);
                    }
                }
            }
        });
        self.add_traffic(bytes.len(), 0);
        Ok(())
    }

    /// `MPI_Improbe` (tag `ROWS_TAG`, any source), then `MPI_Mrecv` of the matched
    /// message.
    fn try_receive(&self) -> Result<Option<(usize, Vec<u8>)>> {
        let Some((msg, status)) = self
            .world
            .any_process()
            .immediate_matched_probe_with_tag(ROWS_TAG)
        else {
            return Ok(None);
        };
        let len = usize::try_from(status.count(u8::equivalent_datatype()))
            .map_err(|_| self.fail("a message of negative length".into()))?;
        let mut buf = vec![0u8; len];
        msg.matched_receive_into(&mut buf[..]);
        self.add_traffic(0, len);
        Ok(Some((status.source_rank() as usize, buf)))
    }

    fn traffic(&self) -> Traffic {
        self.traffic.get()
    }
}
