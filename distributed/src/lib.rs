//! The worlds of one scene spread over processes: each rank simulates a contiguous share of
//! the worlds, and every rank gets every world's outputs (its loss, its gradients) in world
//! order, so that a sum over worlds (the gradient of a parameter the worlds share) is added in
//! one fixed order: the same bits on 1, 2 or 64 ranks, and the same as one process.
//!
//! That rests on adflex's worlds never interacting: a world's results are the same bits
//! whatever the other worlds of its model (`kernels/tests/worlds.rs`), so a rank's share
//! ([`shard`], `ArticulationBuilder::worlds_in`, `ModelBuilder::worlds_in`) computes exactly what the whole scene would.
//!
//! [`run_worlds`] is the whole protocol, on any [`Communicator`]:
//! 1. the ranks compare fingerprints of their scenes ([`fingerprint`]); ranks whose scene
//!    differs from rank 0's end the run with [`DistributedError::ScenesDisagree`] on every rank;
//! 2. each rank runs its worlds; an error or a panic there becomes
//!    [`DistributedError::RankFailed`] naming the rank and the cause, on every rank (never a
//!    hang, never a partial result);
//! 3. the per-world outputs are gathered, in world order, on every rank.
//!
//! A rank that dies (killed, or exiting without finishing) is MPI's to report: `mpirun` ends
//! the job and names the rank (tested in `tests/mpi.rs`).
//!
//! [`SingleProcess`] is the one-rank communicator; with the `mpi` feature, `MpiComm` runs
//! over MPI (Open MPI from Debian's packages here). `docs/distributed.md` explains running on
//! a cluster.
//!
//! ```
//! use adflex_distributed::*;
//!
//! let comm = SingleProcess;
//! // Five worlds whose output is one number each; a parameter's gradient summed over them.
//! let out = run_worlds(&comm, 5, fingerprint(&"scene v1"), |worlds| {
//!     Ok(worlds.map(|w| vec![w as f64 * 0.5]).collect())
//! })
//! .unwrap();
//! assert_eq!(out.per_world.len(), 5);
//! assert_eq!(out.sum(0..1), vec![5.0]);
//! assert_eq!(shard(10, 1, 4), 3..6);
//! ```

use std::fmt;
use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};

#[cfg(feature = "mpi")]
mod mpi_comm;
#[cfg(feature = "mpi")]
pub use mpi_comm::MpiComm;

/// A group of ranks: this process's rank, how many, and the one collective the protocol
/// needs.
pub trait Communicator {
    /// This process's rank, `0..size`.
    fn rank(&self) -> usize;
    /// The number of ranks.
    fn size(&self) -> usize;
    /// Every rank's `local` bytes, in rank order, on every rank (a collective: every rank
    /// calls it).
    fn all_gather_bytes(&self, local: &[u8]) -> Vec<Vec<u8>>;
}

/// One process: rank 0 of 1.
#[derive(Clone, Copy, Debug, Default)]
pub struct SingleProcess;

impl Communicator for SingleProcess {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn all_gather_bytes(&self, local: &[u8]) -> Vec<Vec<u8>> {
        vec![local.to_vec()]
    }
}

/// The worlds of rank `rank` of `size`: contiguous, in rank order, sizes differing by at most
/// one (the first `n_worlds % size` ranks take one more).
///
/// # Panics
/// If `size` is 0 or `rank >= size`.
pub fn shard(n_worlds: usize, rank: usize, size: usize) -> Range<usize> {
    assert!(
        size > 0 && rank < size,
        "shard: rank {rank} of {size} ranks"
    );
    let (base, extra) = (n_worlds / size, n_worlds % size);
    let start = rank * base + rank.min(extra);
    start..start + base + usize::from(rank < extra)
}

/// A 64-bit fingerprint (FNV-1a) of a scene's description, through its `Debug` form (every
/// number of an `ArticulationBuilder` is in it): what the ranks compare before they run.
pub fn fingerprint(scene: &impl fmt::Debug) -> u64 {
    let text = format!("{scene:?}");
    text.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// Why a distributed run ended without a result; every rank returns the same error.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DistributedError {
    /// Rank `rank`'s scene differs from rank 0's (their fingerprints).
    ScenesDisagree { rank: usize, ours: u64, rank0: u64 },
    /// Rank `rank` was given another number of worlds than rank 0.
    WorldCountsDisagree {
        rank: usize,
        ours: usize,
        rank0: usize,
    },
    /// Rank `rank` failed while running its worlds (`worlds`): an error or a panic.
    RankFailed {
        rank: usize,
        worlds: Range<usize>,
        cause: String,
    },
    /// The ranks' outputs do not fit together (a rank gave the wrong number of worlds).
    BadOutput { rank: usize, message: String },
}

impl fmt::Display for DistributedError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DistributedError::ScenesDisagree { rank, ours, rank0 } => write!(
                f,
                "rank {rank}'s scene differs from rank 0's (fingerprint {ours:016x}, rank 0's \
                 {rank0:016x}): every rank must build the same scene"
            ),
            DistributedError::WorldCountsDisagree { rank, ours, rank0 } => write!(
                f,
                "rank {rank} runs {ours} worlds and rank 0 {rank0}: every rank must be given \
                 the same number"
            ),
            DistributedError::RankFailed {
                rank,
                worlds,
                cause,
            } => write!(
                f,
                "rank {rank} failed on worlds {}..{}: {cause}",
                worlds.start, worlds.end
            ),
            DistributedError::BadOutput { rank, message } => {
                write!(f, "rank {rank}'s output: {message}")
            }
        }
    }
}

impl std::error::Error for DistributedError {}

/// Every world's outputs, in world order.
#[derive(Clone, Debug, PartialEq)]
pub struct WorldOutputs {
    /// `per_world[w]`: what world `w`'s rank returned for it.
    pub per_world: Vec<Vec<f64>>,
}

impl WorldOutputs {
    /// The sum over worlds, in world order (world 0 first, from zero), of the components
    /// `range` of each world's output: the gradient of a parameter every world shares. The
    /// same bits on any number of ranks.
    pub fn sum(&self, range: Range<usize>) -> Vec<f64> {
        let mut total = vec![0.0; range.len()];
        for out in &self.per_world {
            for (t, v) in total.iter_mut().zip(&out[range.clone()]) {
                *t += v;
            }
        }
        total
    }
}

/// Runs `work` on this rank's share of `n_worlds` worlds ([`shard`]) and gathers every world's
/// output on every rank. `work` gets its range of worlds and returns one output per world
/// (numbers: a loss, gradients), or an error message. `scene` is the scene's
/// [`fingerprint`], compared across ranks first.
///
/// A rank whose share is empty (fewer worlds than ranks) does not call `work`.
///
/// Errors (the same on every rank): [`DistributedError::ScenesDisagree`] naming the first
/// rank whose scene differs from rank 0's, [`DistributedError::WorldCountsDisagree`] the
/// first given another `n_worlds`; [`DistributedError::RankFailed`] naming the first
/// rank whose `work` returned an error or panicked, with its message;
/// [`DistributedError::BadOutput`] if a rank returned a number of outputs other than its
/// number of worlds.
pub fn run_worlds(
    comm: &dyn Communicator,
    n_worlds: usize,
    scene: u64,
    work: impl FnOnce(Range<usize>) -> Result<Vec<Vec<f64>>, String>,
) -> Result<WorldOutputs, DistributedError> {
    let (rank, size) = (comm.rank(), comm.size());
    // 1. The same scene and number of worlds everywhere.
    let mut mine = scene.to_le_bytes().to_vec();
    mine.extend((n_worlds as u64).to_le_bytes());
    let prints = comm.all_gather_bytes(&mine);
    let word = |b: &[u8], k: usize| {
        let w = b.get(8 * k..8 * k + 8).unwrap_or(&[0; 8]);
        u64::from_le_bytes(w.try_into().unwrap_or([0; 8]))
    };
    let (print0, count0) = (word(&prints[0], 0), word(&prints[0], 1));
    if let Some(r) = prints.iter().position(|p| word(p, 0) != print0) {
        return Err(DistributedError::ScenesDisagree {
            rank: r,
            ours: word(&prints[r], 0),
            rank0: print0,
        });
    }
    if let Some(r) = prints.iter().position(|p| word(p, 1) != count0) {
        return Err(DistributedError::WorldCountsDisagree {
            rank: r,
            ours: word(&prints[r], 1) as usize,
            rank0: count0 as usize,
        });
    }
    // 2. This rank's worlds; a failure is a message for everyone.
    // A rank without worlds (fewer worlds than ranks) runs nothing.
    let mine = shard(n_worlds, rank, size);
    // Status 0: outputs; 1: the work failed (message); 2: wrong number of outputs.
    let result = match mine.is_empty() {
        true => Ok(Vec::new()),
        false => match catch_unwind(AssertUnwindSafe(|| work(mine.clone()))) {
            Ok(Ok(out)) if out.len() == mine.len() => Ok(out),
            Ok(Ok(out)) => Err((
                2u8,
                format!("{} outputs for {} worlds", out.len(), mine.len()),
            )),
            Ok(Err(e)) => Err((1, e)),
            Err(p) => Err((1, format!("panicked: {}", panic_message(&p)))),
        },
    };
    // 3. Status, then the outputs, from every rank.
    let status = match &result {
        Ok(_) => vec![0u8],
        Err((code, e)) => std::iter::once(*code).chain(e.bytes()).collect(),
    };
    let statuses = comm.all_gather_bytes(&status);
    if let Some(r) = statuses.iter().position(|s| s.first() != Some(&0)) {
        let message = String::from_utf8_lossy(statuses[r].get(1..).unwrap_or(&[])).into_owned();
        return Err(match statuses[r].first() {
            Some(2) => DistributedError::BadOutput { rank: r, message },
            _ => DistributedError::RankFailed {
                rank: r,
                worlds: shard(n_worlds, r, size),
                cause: message,
            },
        });
    }
    let local = result.unwrap_or_default();
    let mut bytes = Vec::new();
    for out in &local {
        bytes.extend((out.len() as u64).to_le_bytes());
        for v in out {
            bytes.extend(v.to_le_bytes());
        }
    }
    let all = comm.all_gather_bytes(&bytes);
    let mut per_world = Vec::with_capacity(n_worlds);
    for (r, b) in all.iter().enumerate() {
        let mut at = 0;
        let mut read = |n: usize| -> Result<&[u8], DistributedError> {
            let s = b
                .get(at..at + n)
                .ok_or_else(|| DistributedError::BadOutput {
                    rank: r,
                    message: "truncated".into(),
                })?;
            at += n;
            Ok(s)
        };
        for _ in shard(n_worlds, r, size) {
            let len = u64::from_le_bytes(read(8)?.try_into().unwrap_or([0; 8])) as usize;
            let mut out = Vec::with_capacity(len);
            for _ in 0..len {
                out.push(f64::from_le_bytes(read(8)?.try_into().unwrap_or([0; 8])));
            }
            per_world.push(out);
        }
        if at != b.len() {
            return Err(DistributedError::BadOutput {
                rank: r,
                message: format!("{} bytes left over", b.len() - at),
            });
        }
    }
    Ok(WorldOutputs { per_world })
}

/// Runs `work` on `shards` contiguous shares of `n_worlds` worlds at once, as tasks of the
/// current rayon pool (each share its own model and tape: a small robot's launches are too
/// small to split, its worlds are not), and gathers the outputs in world order. The same bits
/// as one share of all the worlds, or as [`run_worlds`] on any number of ranks.
///
/// Errors: [`DistributedError::RankFailed`] naming the first failing share (as its "rank"),
/// for an error or a panic; [`DistributedError::BadOutput`] for a wrong number of outputs.
///
/// ```
/// use adflex_distributed::*;
///
/// let out = run_worlds_in_threads(10, 2, |worlds| Ok(worlds.map(|w| vec![w as f64]).collect()))
///     .unwrap();
/// assert_eq!(out.per_world[7], vec![7.0]);
/// ```
pub fn run_worlds_in_threads(
    n_worlds: usize,
    shards: usize,
    work: impl Fn(Range<usize>) -> Result<Vec<Vec<f64>>, String> + Sync,
) -> Result<WorldOutputs, DistributedError> {
    let shards = shards.max(1);
    let mut results: Vec<Option<Result<Vec<Vec<f64>>, String>>> = vec![None; shards];
    rayon::scope(|s| {
        for (k, slot) in results.iter_mut().enumerate() {
            let work = &work;
            s.spawn(move |_| {
                let mine = shard(n_worlds, k, shards);
                *slot = Some(match mine.is_empty() {
                    true => Ok(Vec::new()), // more shares than worlds
                    false => match catch_unwind(AssertUnwindSafe(|| work(mine))) {
                        Ok(r) => r,
                        Err(p) => Err(format!("panicked: {}", panic_message(&p))),
                    },
                });
            });
        }
    });
    let mut per_world = Vec::with_capacity(n_worlds);
    for (k, r) in results.into_iter().enumerate() {
        let mine = shard(n_worlds, k, shards);
        match r.unwrap_or_else(|| Err("did not run".into())) {
            Ok(out) if out.len() == mine.len() => per_world.extend(out),
            Ok(out) => {
                return Err(DistributedError::BadOutput {
                    rank: k,
                    message: format!("{} outputs for {} worlds", out.len(), mine.len()),
                })
            }
            Err(cause) => {
                return Err(DistributedError::RankFailed {
                    rank: k,
                    worlds: mine,
                    cause,
                })
            }
        }
    }
    Ok(WorldOutputs { per_world })
}

fn panic_message(p: &Box<dyn std::any::Any + Send>) -> String {
    if let Some(s) = p.downcast_ref::<&str>() {
        s.to_string()
    } else if let Some(s) = p.downcast_ref::<String>() {
        s.clone()
    } else {
        "(a panic without a message)".into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;
    use std::sync::{Arc, Barrier, Mutex};

    /// `size` ranks as threads of this process, for testing the protocol without MPI: round
    /// `k` of `all_gather_bytes` has its own slots, filled by every rank before any reads.
    struct Threads {
        rank: usize,
        size: usize,
        round: Cell<usize>,
        board: Arc<(Mutex<Rounds>, Barrier)>,
    }

    /// Per round, per rank, the bytes given.
    type Rounds = Vec<Vec<Vec<u8>>>;

    impl Communicator for Threads {
        fn rank(&self) -> usize {
            self.rank
        }
        fn size(&self) -> usize {
            self.size
        }
        fn all_gather_bytes(&self, local: &[u8]) -> Vec<Vec<u8>> {
            let k = self.round.get();
            self.round.set(k + 1);
            let (board, barrier) = &*self.board;
            {
                let mut b = board.lock().unwrap();
                while b.len() <= k {
                    b.push(vec![Vec::new(); self.size]);
                }
                b[k][self.rank] = local.to_vec();
            }
            barrier.wait();
            let out = board.lock().unwrap()[k].clone();
            out
        }
    }

    fn on_threads<T: Send>(size: usize, f: impl Fn(&dyn Communicator) -> T + Sync) -> Vec<T> {
        let board = Arc::new((Mutex::new(Vec::new()), Barrier::new(size)));
        std::thread::scope(|s| {
            let handles: Vec<_> = (0..size)
                .map(|rank| {
                    let comm = Threads {
                        rank,
                        size,
                        round: Cell::new(0),
                        board: board.clone(),
                    };
                    let f = &f;
                    s.spawn(move || f(&comm))
                })
                .collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        })
    }

    #[test]
    fn shares_on_threads_give_the_same_outputs_and_name_a_failing_share() {
        let work = |worlds: Range<usize>| -> Result<Vec<Vec<f64>>, String> {
            Ok(worlds.map(|w| vec![(w as f64).sqrt()]).collect())
        };
        let one = run_worlds(&SingleProcess, 11, 1, work).unwrap();
        for shards in [1, 2, 3, 11, 20] {
            // (20 shares of 11 worlds: `work` never sees an empty range.)
            let checked = |w: Range<usize>| {
                assert!(!w.is_empty());
                work(w)
            };
            assert_eq!(run_worlds_in_threads(11, shards, checked).unwrap(), one);
        }
        let e = run_worlds_in_threads(11, 3, |w| {
            if w.start > 0 {
                panic!("boom");
            }
            work(w)
        })
        .unwrap_err();
        assert_eq!(
            e,
            DistributedError::RankFailed {
                rank: 1,
                worlds: 4..8,
                cause: "panicked: boom".into()
            }
        );
    }

    #[test]
    fn shards_cover_the_worlds_in_order() {
        for (n, size) in [(10, 4), (3, 4), (1024, 3), (0, 2)] {
            let mut next = 0;
            for r in 0..size {
                let s = shard(n, r, size);
                assert_eq!(s.start, next);
                next = s.end;
            }
            assert_eq!(next, n);
        }
    }

    #[test]
    fn every_rank_gets_every_world_in_order_and_the_same_sums() {
        let work = |worlds: Range<usize>| -> Result<Vec<Vec<f64>>, String> {
            Ok(worlds
                .map(|w| vec![0.1 * w as f64, 1.0 / (w + 1) as f64])
                .collect())
        };
        let one = run_worlds(&SingleProcess, 13, 7, work).unwrap();
        for size in [2, 3, 4] {
            for out in on_threads(size, |c| run_worlds(c, 13, 7, work).unwrap()) {
                assert_eq!(out, one);
                assert_eq!(out.sum(0..2), one.sum(0..2));
            }
        }
    }

    #[test]
    fn a_failing_or_panicking_rank_or_a_different_scene_ends_every_rank_with_its_name() {
        let errors = on_threads(3, |c| {
            run_worlds(c, 9, 7, |w| {
                if c.rank() == 1 {
                    Err("the solve did not converge".into())
                } else {
                    Ok(w.map(|_| vec![1.0]).collect())
                }
            })
        });
        for e in errors {
            let e = e.unwrap_err();
            assert_eq!(
                e,
                DistributedError::RankFailed {
                    rank: 1,
                    worlds: 3..6,
                    cause: "the solve did not converge".into()
                }
            );
            assert!(
                e.to_string().contains("rank 1 failed on worlds 3..6"),
                "{e}"
            );
        }
        let errors = on_threads(2, |c| {
            run_worlds(c, 4, 7, |w| {
                if c.rank() == 1 {
                    panic!("index out of bounds");
                }
                Ok(w.map(|_| vec![1.0]).collect())
            })
        });
        for e in errors {
            let e = e.unwrap_err().to_string();
            assert!(
                e.contains("rank 1") && e.contains("panicked: index out of bounds"),
                "{e}"
            );
        }
        // Fewer worlds than ranks: the rank without worlds runs nothing.
        for out in on_threads(3, |c| {
            run_worlds(c, 2, 7, |w| {
                assert!(!w.is_empty());
                Ok(w.map(|w| vec![w as f64]).collect())
            })
        }) {
            assert_eq!(out.unwrap().per_world, vec![vec![0.0], vec![1.0]]);
        }
        // A rank given another number of worlds.
        for e in on_threads(2, |c| {
            run_worlds(c, 4 + c.rank(), 7, |w| Ok(w.map(|_| vec![1.0]).collect()))
        }) {
            assert!(matches!(
                e.unwrap_err(),
                DistributedError::WorldCountsDisagree {
                    rank: 1,
                    ours: 5,
                    rank0: 4
                }
            ));
        }
        // A user error that starts like a marker is still the user's error.
        for e in on_threads(2, |c| {
            run_worlds(c, 4, 7, |w| match c.rank() {
                1 => Err("BAD input".into()),
                _ => Ok(w.map(|_| vec![1.0]).collect()),
            })
        }) {
            assert!(matches!(
                e.unwrap_err(),
                DistributedError::RankFailed { rank: 1, .. }
            ));
        }
        let errors = on_threads(3, |c| {
            run_worlds(c, 4, if c.rank() == 2 { 8 } else { 7 }, |w| {
                Ok(w.map(|_| vec![1.0]).collect())
            })
        });
        for e in errors {
            assert!(matches!(
                e.unwrap_err(),
                DistributedError::ScenesDisagree { rank: 2, .. }
            ));
        }
    }
}

/// `docs/distributed.md`: running worlds over threads and processes (its examples are tested).
#[doc = include_str!("../../docs/distributed.md")]
pub mod guide {}
