//! The order in which the chunks of a parallel launch apply their scatter logs.
//!
//! Chunk `k`'s additions into a target must come after those of chunks `0..k` (thread-id
//! order, so the bits do not depend on the thread count). A finished chunk *deposits* its logs
//! and its worker goes on to the next chunk; whichever worker deposits the chunk whose turn it
//! is applies it, then every deposited chunk after it, in order. No worker waits at the end of
//! a chunk (it did before: with two workers, one often slept until the other finished).
//!
//! A running chunk whose turn has come (every earlier chunk applied) writes directly
//! (`Scatter::checkpoint`): nothing can be applied before it finishes, since it is the next
//! one to deposit.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex, PoisonError};

use crate::scatter_log::ScatterLog;

/// Deposited chunks a worker may leave unapplied before it waits for them: bounds the memory
/// of logs held while one slow chunk runs.
const MAX_PENDING: usize = 8;

#[derive(Default)]
struct State {
    /// Chunks applied: `applied` is the one whose turn it is.
    applied: usize,
    /// A worker is applying deposited chunks (others only deposit).
    applying: bool,
    /// A chunk panicked: nothing more is applied, nobody waits.
    failed: bool,
    /// Finished chunks waiting for their turn, with their logs.
    pending: BTreeMap<usize, Vec<ScatterLog>>,
}

/// See the module's docs. Chunks are claimed in order by running workers, so the chunk whose
/// turn it is always runs, or is deposited: waiting for it cannot deadlock.
#[derive(Default)]
pub(crate) struct ChunkOrder {
    next: AtomicUsize,
    /// `state.applied`, for running chunks to poll without the lock.
    applied: AtomicUsize,
    state: Mutex<State>,
    changed: Condvar,
}

impl std::fmt::Debug for ChunkOrder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ChunkOrder")
            .field("claimed", &self.next.load(Ordering::Relaxed))
            .field("applied", &self.applied.load(Ordering::Relaxed))
            .finish()
    }
}

impl ChunkOrder {
    /// The next chunk to run (in order).
    pub(crate) fn claim(&self) -> usize {
        self.next.fetch_add(1, Ordering::Relaxed)
    }

    /// Whether chunks `0..k` are applied (chunk `k`'s turn), without blocking. Acquire: the
    /// earlier chunks' writes are visible once this is true.
    pub(crate) fn is_turn(&self, k: usize) -> bool {
        self.applied.load(Ordering::Acquire) == k
    }

    /// Blocks until chunks `0..k` are applied (true), or a chunk panicked (false: the launch
    /// is failing with that panic; the caller applies nothing).
    pub(crate) fn wait_turn(&self, k: usize) -> bool {
        let mut st = self.lock();
        while st.applied < k && !st.failed {
            st = self.wait(st);
        }
        st.applied >= k
    }

    /// Chunk `k` has finished with `logs`: deposits them, and applies every deposited chunk
    /// whose turn has come unless another worker is doing so.
    pub(crate) fn finish(&self, k: usize, logs: Vec<ScatterLog>) {
        let mut st = self.lock();
        if st.failed {
            return;
        }
        st.pending.insert(k, logs);
        if !st.applying {
            st.applying = true;
            loop {
                let next = st.applied;
                let Some(logs) = st.pending.remove(&next) else {
                    break;
                };
                drop(st);
                for log in logs.iter().filter_map(|l| l.0.as_deref()) {
                    // SAFETY: chunk `next`'s turn, and it has finished: the running chunks
                    // write only logs and their own stores (none of them is in turn), and
                    // no other worker applies (`applying`).
                    unsafe { log.apply() }
                }
                st = self.lock();
                st.applied = next + 1;
                self.applied.store(next + 1, Ordering::Release);
                self.changed.notify_all();
                if st.failed {
                    break;
                }
            }
            st.applying = false;
        }
        while st.pending.len() > MAX_PENDING && !st.failed {
            st = self.wait(st);
        }
    }

    /// A chunk panicked: wakes every waiter (they give up, so that the panic the launch
    /// reports is that chunk's own) and drops the deposited logs.
    pub(crate) fn fail(&self) {
        let mut st = self.lock();
        st.failed = true;
        st.pending.clear();
        self.changed.notify_all();
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn wait<'g>(&self, st: std::sync::MutexGuard<'g, State>) -> std::sync::MutexGuard<'g, State> {
        self.changed
            .wait(st)
            .unwrap_or_else(PoisonError::into_inner)
    }
}
