//! Parallel regions: the one place where the runtime's work goes to the thread pool.
//!
//! A launch (serial or parallel, `crate::launch`, `crate::split`) opens a [`Region`] on the
//! calling thread ([`Region::open`]), and so does the tape's parallel zeroing of gradients
//! ([`Region::host`]: no floating-point mode, no lingering after it). The region
//!
//! - reads the [settings](crate::settings) once, when it opens;
//! - puts the calling thread's floating-point unit in the launch's subnormal mode
//!   ([`Settings::flush_subnormals`](crate::settings::Settings::flush_subnormals)) until it
//!   ends (a serial launch runs there, a split launch applies its logs there);
//! - hands work to the pool either as [`Region::shares`] (every share in the same mode, the
//!   launching thread waiting awake for the others: `crate::linger::Team`) or as
//!   [`Region::pool`] (rayon code of its own that does no arithmetic); either starts a new
//!   epoch first, so workers lingering after the previous region take the work at once;
//! - when a launch's region ends after work went to the pool, lets the pool's other workers
//!   linger for the next region ([`Settings::linger`](crate::settings::Settings::linger)),
//!   and restores the calling thread's floating-point mode.
//!
//! Nothing else in the crate calls `crate::linger` or `crate::subnormals`.

use std::cell::Cell;

use rayon::prelude::*;

use crate::linger::{self, Team};
use crate::settings;
use crate::subnormals::Flush;

/// One parallel region (see the module's docs); ends when dropped, or by [`Region::end`].
pub(crate) struct Region {
    /// Whether the region's threads flush subnormals (read from the settings when it opened).
    flush: bool,
    /// Whether the pool's workers linger after the region (launches; not host work).
    linger_after: bool,
    /// Work went to the pool: its workers linger when the region ends.
    pooled: Cell<bool>,
    /// The calling thread's mode, restored when the region ends (dropped after `drop`).
    _here: Flush,
}

impl Region {
    /// Opens a launch's region on the calling thread, with the settings as they are now.
    #[inline]
    pub(crate) fn open() -> Self {
        let flush = settings::flush();
        Region {
            flush,
            linger_after: true,
            pooled: Cell::new(false),
            _here: Flush::enter(flush),
        }
    }

    /// Opens a region for host work on the pool (the tape zeroing gradients), which does no
    /// arithmetic: it wakes lingering workers but keeps every thread's floating-point mode,
    /// and the workers do not linger after it (the launch that follows wakes them if it is
    /// parallel; lingering after the zeroing made the launch-bound cage scene of
    /// `adflex-bench small` 4% slower on a busy 2-core machine, paired runs).
    #[inline]
    pub(crate) fn host() -> Self {
        Region {
            flush: false,
            linger_after: false,
            pooled: Cell::new(false),
            _here: Flush::enter(false),
        }
    }

    /// Runs `share(k)` for `k` in `0..parts` on the pool's workers, each in the region's
    /// floating-point mode, and returns the results in order. The calling thread runs a share
    /// too (it is one of the pool's threads) and, done with it, waits for the others awake.
    pub(crate) fn shares<R: Send>(
        &self,
        parts: usize,
        share: impl Fn(usize) -> R + Sync,
    ) -> Vec<R> {
        self.to_pool();
        let team = Team::new(parts);
        let flush = self.flush;
        (0..parts)
            .into_par_iter()
            .map(|k| {
                team.share(|| {
                    let _flush = Flush::enter(flush);
                    share(k)
                })
            })
            .collect()
    }

    /// Runs `work`, rayon code of its own, on the pool. Its workers keep their own
    /// floating-point mode: for work without arithmetic (zeroing buffers).
    pub(crate) fn pool<R>(&self, work: impl FnOnce() -> R) -> R {
        self.to_pool();
        work()
    }

    /// Ends the region now (as dropping it does).
    #[inline]
    pub(crate) fn end(self) {}

    /// Work is about to go to the pool: workers lingering after the previous region stop
    /// spinning and take it.
    fn to_pool(&self) {
        self.pooled.set(true);
        linger::launch_starts();
    }
}

impl Drop for Region {
    fn drop(&mut self) {
        // A region that panics ends without lingering (the panic goes on to the caller).
        if self.pooled.get() && self.linger_after && !std::thread::panicking() {
            linger::launch_ended();
        }
    }
}
