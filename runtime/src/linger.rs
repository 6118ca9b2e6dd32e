//! After a parallel launch, the pool's other workers wait for the next one awake, for a while
//! ([`set_linger`]), instead of going to sleep.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// Bumped when a parallel launch starts: lingering workers go back to the pool to take its work.
static EPOCH: AtomicU64 = AtomicU64::new(0);
/// How long workers linger, in nanoseconds.
static LINGER_NS: AtomicU64 = AtomicU64::new(500_000);
/// Lingering jobs spawned and not yet started (at most one per worker: a job nobody takes,
/// all workers busy with other work, is not spawned again at every launch).
static QUEUED: AtomicUsize = AtomicUsize::new(0);
/// Workers lingering now.
static LINGERING: AtomicUsize = AtomicUsize::new(0);

/// How long, after a parallel launch, the pool's other workers busy-wait for the next launch
/// before they may sleep (the default: 0.5 ms). See [`set_linger`].
pub fn linger() -> Duration {
    Duration::from_nanos(LINGER_NS.load(Ordering::Relaxed))
}

/// Sets how long, after a parallel launch, the pool's other workers busy-wait for the next
/// launch (process-wide); `Duration::ZERO` lets them sleep at once, as rayon's idle workers
/// do.
///
/// A rayon worker that finds no work sleeps after a few microseconds. Waking it costs the
/// launching thread a system call and the worker tens of microseconds before it runs: on a
/// 2-core virtual machine a parallel launch of two 100 us halves took 176 us when it came 50 us
/// after the previous one, and 101 us when it came at once (docs/performance.md). A simulation
/// step is a few launches of 0.05 to 1 ms with a little host work between them (recording
/// them, allocating the next state), so every parallel launch paid that. So after a parallel
/// launch, the pool's other workers spin until the next parallel launch starts or this time
/// has passed, as OpenMP runtimes do (`KMP_BLOCKTIME`, `OMP_WAIT_POLICY`). The cost is CPU
/// time on those cores, at most this long per parallel launch; a program that launches
/// rarely and shares its cores may prefer `Duration::ZERO`. Results do not depend on it.
///
/// ```
/// use std::time::Duration;
/// use adflex_runtime::launch::{linger, set_linger};
/// assert_eq!(linger(), Duration::from_micros(500));
/// set_linger(Duration::ZERO); // workers sleep as soon as a launch ends
/// assert_eq!(linger(), Duration::ZERO);
/// set_linger(Duration::from_micros(500));
/// ```
pub fn set_linger(time: Duration) {
    let ns = u64::try_from(time.as_nanos()).unwrap_or(u64::MAX);
    LINGER_NS.store(ns, Ordering::Relaxed)
}

/// Lingering jobs spawned and not yet started, and workers lingering now (for tests).
#[doc(hidden)]
pub fn lingerers() -> (usize, usize) {
    (
        QUEUED.load(Ordering::Acquire),
        LINGERING.load(Ordering::Acquire),
    )
}

/// Called when a parallel launch (or other parallel work of the runtime) is about to hand
/// out its work: lingering workers stop spinning and take it.
pub(crate) fn launch_starts() {
    EPOCH.fetch_add(1, Ordering::AcqRel);
}

/// Called when a parallel launch has ended: up to one job per other worker of the current
/// pool spins until the next parallel launch starts or [`linger`] has passed.
pub(crate) fn launch_ended() {
    let ns = LINGER_NS.load(Ordering::Relaxed);
    if ns == 0 {
        return;
    }
    let epoch = EPOCH.load(Ordering::Acquire);
    let caller = rayon::current_thread_index();
    // From outside the pool every worker may linger; from inside, all but the caller.
    let want = rayon::current_num_threads() - usize::from(caller.is_some());
    while QUEUED.load(Ordering::Acquire) + LINGERING.load(Ordering::Acquire) < want {
        QUEUED.fetch_add(1, Ordering::AcqRel);
        // Spawned jobs go to the caller's queue, where idle workers take them at once.
        rayon::spawn(move || {
            QUEUED.fetch_sub(1, Ordering::AcqRel);
            // The launching thread goes on with its program (it runs this only when it waits
            // for other pool work); a worker that starts this after the next launch started
            // has work to take.
            if rayon::current_thread_index() == caller || EPOCH.load(Ordering::Acquire) != epoch {
                return;
            }
            LINGERING.fetch_add(1, Ordering::AcqRel);
            let until = Instant::now() + Duration::from_nanos(ns);
            'wait: loop {
                for _ in 0..64 {
                    if EPOCH.load(Ordering::Acquire) != epoch {
                        break 'wait;
                    }
                    std::hint::spin_loop();
                }
                if Instant::now() >= until {
                    break;
                }
            }
            LINGERING.fetch_sub(1, Ordering::AcqRel);
        });
    }
}
