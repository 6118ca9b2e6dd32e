//! After a parallel launch, the pool's other workers wait for the next one awake, for a while
//! ([`Settings::linger`](crate::settings::Settings::linger)), instead of going to sleep; within
//! one, the launching thread waits for the other shares awake ([`Team`]). Only
//! `crate::region` calls this.

use std::sync::atomic::{AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use crate::settings;

/// Bumped when a parallel launch starts: lingering workers go back to the pool to take its work.
static EPOCH: AtomicU64 = AtomicU64::new(0);
/// Lingering jobs spawned and not yet started (at most one per worker: a job nobody takes,
/// all workers busy with other work, is not spawned again at every launch).
static QUEUED: AtomicUsize = AtomicUsize::new(0);
/// Workers lingering now.
static LINGERING: AtomicUsize = AtomicUsize::new(0);
/// Times a launching thread waited for the other shares of its launch ([`Team`]).
static LEADER_WAITS: AtomicUsize = AtomicUsize::new(0);

/// Lingering jobs spawned and not yet started, and workers lingering now (for tests).
pub(crate) fn lingerers() -> (usize, usize) {
    (
        QUEUED.load(Ordering::Acquire),
        LINGERING.load(Ordering::Acquire),
    )
}

/// Times a launching thread, done with its share of a parallel launch, waited for the other
/// shares (for tests).
pub(crate) fn leader_waits() -> usize {
    LEADER_WAITS.load(Ordering::Acquire)
}

/// Called when a parallel launch (or other parallel work of the runtime) is about to hand
/// out its work: lingering workers stop spinning and take it.
pub(crate) fn launch_starts() {
    EPOCH.fetch_add(1, Ordering::AcqRel);
}

/// Called when a parallel launch has ended: up to one job per other worker of the current
/// pool spins until the next parallel launch starts or [`Settings::linger`](crate::settings::Settings::linger) has passed.
pub(crate) fn launch_ended() {
    let ns = settings::linger_ns();
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

/// The shares of one parallel launch, counted as they start and finish. The launching
/// thread, done with its own share while the others still run theirs, waits for them awake
/// (at most [`Settings::linger`](crate::settings::Settings::linger)) rather than in rayon's join, where it sleeps after a few microseconds:
/// waking it then cost 30 to 50 us per launch on a 2-core virtual machine, 5% of the cloth's
/// step (docs/performance.md).
pub(crate) struct Team {
    parts: usize,
    started: AtomicUsize,
    finished: AtomicUsize,
    /// The launching thread's index in the pool (`None` outside one: it blocks on a latch).
    leader: Option<usize>,
    /// How the launching thread's wait ended ([`Wait`] as a number; 0 before it).
    wait: AtomicU8,
}

/// How the launching thread's wait for the other shares ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Wait {
    /// Every share had finished (at once or after spinning).
    Finished = 1,
    /// A share had not started: it may be queued on the launching thread itself, which
    /// returns to rayon to run it.
    NotStarted = 2,
    /// [`Settings::linger`](crate::settings::Settings::linger) passed first (a share preempted by another process); rayon's join waits on.
    TimedOut = 3,
    /// Lingering is off ([`set_linger`](crate::settings::set_linger) with zero).
    Off = 4,
}

impl Team {
    /// A team for a launch of `parts` shares, created on the launching thread.
    pub(crate) fn new(parts: usize) -> Self {
        Team {
            parts,
            started: AtomicUsize::new(0),
            finished: AtomicUsize::new(0),
            leader: rayon::current_thread_index(),
            wait: AtomicU8::new(0),
        }
    }

    /// Runs one share; on the launching thread, then waits for the others.
    pub(crate) fn share<R>(&self, work: impl FnOnce() -> R) -> R {
        self.started.fetch_add(1, Ordering::AcqRel);
        let r = work();
        self.finished.fetch_add(1, Ordering::AcqRel);
        if self.leader.is_some() && rayon::current_thread_index() == self.leader {
            let how = self.wait_for_others();
            self.wait.store(how as u8, Ordering::Release);
            LEADER_WAITS.fetch_add(1, Ordering::AcqRel);
        }
        r
    }

    /// How the launching thread's last wait ended, if it waited.
    #[cfg(test)]
    fn waited(&self) -> Option<Wait> {
        [Wait::Finished, Wait::NotStarted, Wait::TimedOut, Wait::Off]
            .into_iter()
            .find(|w| *w as u8 == self.wait.load(Ordering::Acquire))
    }

    fn wait_for_others(&self) -> Wait {
        let ns = settings::linger_ns();
        if ns == 0 {
            return Wait::Off;
        }
        let until = Instant::now() + Duration::from_nanos(ns);
        loop {
            for _ in 0..64 {
                // `finished` first: a share counted finished was counted started before.
                if self.finished.load(Ordering::Acquire) == self.parts {
                    return Wait::Finished;
                }
                if self.started.load(Ordering::Acquire) < self.parts {
                    return Wait::NotStarted;
                }
                std::hint::spin_loop();
            }
            if Instant::now() >= until {
                return Wait::TimedOut;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicBool;

    use super::*;
    use crate::settings::set_linger;

    /// Spins until `flag` is set (at most 5 s).
    fn until(flag: &AtomicBool) {
        let start = Instant::now();
        while !flag.load(Ordering::Acquire) && start.elapsed() < Duration::from_secs(5) {
            std::hint::spin_loop();
        }
    }

    /// Two shares by `rayon::join` on the current thread: the first (the launching thread's)
    /// waits until the second has started elsewhere, which then takes `second` long.
    fn two_shares(team: &Team, second: Duration) {
        let started = AtomicBool::new(false);
        rayon::join(
            || team.share(|| until(&started)),
            || {
                team.share(|| {
                    started.store(true, Ordering::Release);
                    std::thread::sleep(second);
                })
            },
        );
    }

    // One test: the lingering time is process-wide.
    #[test]
    fn the_launching_thread_waits_awake_for_running_shares_only() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        pool.install(|| {
            // A share running on the other worker: waited for, awake, until it finishes.
            set_linger(Duration::from_secs(30));
            let team = Team::new(2);
            let start = Instant::now();
            two_shares(&team, Duration::from_millis(20));
            assert_eq!(team.waited(), Some(Wait::Finished));
            assert!(start.elapsed() < Duration::from_secs(5));

            // A share not started (the other worker is busy): the launching thread returns
            // to rayon at once and runs it, rather than spinning for the 30 s.
            let (busy, release) = (AtomicBool::new(false), AtomicBool::new(false));
            rayon::scope(|s| {
                s.spawn(|_| {
                    busy.store(true, Ordering::Release);
                    until(&release);
                });
                until(&busy);
                let team = Team::new(2);
                let start = Instant::now();
                let leader = rayon::current_thread_index();
                let ran_on = std::sync::Mutex::new(Vec::new());
                rayon::join(
                    || team.share(|| ran_on.lock().unwrap().push(rayon::current_thread_index())),
                    || team.share(|| ran_on.lock().unwrap().push(rayon::current_thread_index())),
                );
                assert!(start.elapsed() < Duration::from_secs(5), "it spun");
                assert_eq!(*ran_on.lock().unwrap(), vec![leader, leader]);
                release.store(true, Ordering::Release);
            });

            // A share that outlasts the lingering time: the wait ends with it.
            set_linger(Duration::from_millis(1));
            let team = Team::new(2);
            two_shares(&team, Duration::from_millis(200));
            assert_eq!(team.waited(), Some(Wait::TimedOut));

            set_linger(Duration::ZERO);
            let team = Team::new(2);
            two_shares(&team, Duration::from_millis(1));
            assert_eq!(team.waited(), Some(Wait::Off));
        });
        set_linger(Duration::from_micros(500));
    }
}
