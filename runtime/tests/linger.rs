//! After a parallel launch the pool's other workers spin for the next one (`set_linger`), and
//! stop when a launch starts or the time has passed; during one, the launching thread waits
//! for the others' shares awake. (The setting is process-wide, so this binary has a single
//! test.)

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use adflex_runtime::__test::{leader_waits, lingerers, split_launches};
use adflex_runtime::launch::{linger, set_linger, SERIAL_BELOW};
use adflex_runtime::prelude::*;

#[adflex_macros::diff_kernel]
fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
    let t = tid();
    y[t] = x[t] * s;
}

#[adflex_macros::diff_kernel]
fn count_ends(pairs: &Array<[u32; 2]>, n: &Array<f32>) {
    let [i, j] = pairs[tid()];
    n.atomic_add(i, 1.0);
    n.atomic_add(j, 1.0);
}

/// A parallel launch split into one range per worker (scatters through an index array).
fn split_launch() {
    let n = SERIAL_BELOW * 2;
    let pairs = Array::from_vec((0..n as u32).map(|i| [i, i + 1]).collect());
    let ends = Array::zeros(n + 1);
    let before = split_launches();
    launch(count_ends, n, (&pairs, &ends));
    assert!(split_launches() > before, "the launch was split");
    assert_eq!((ends.get(0), ends.get(1), ends.get(n)), (1.0, 2.0, 1.0));
}

fn lingering() -> usize {
    lingerers().1
}

/// Waits up to 2 s for `lingering() == n`; false if it never was.
fn reaches(n: usize) -> bool {
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(2) {
        if lingering() == n {
            return true;
        }
        std::thread::yield_now();
    }
    false
}

/// Waits up to 2 s for no lingering job queued or running, in any pool (the counts are the
/// process's, and a dropped pool's workers still run the jobs left in their queues).
fn quiet() -> bool {
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(2) {
        if lingerers() == (0, 0) {
            return true;
        }
        std::thread::yield_now();
    }
    false
}

/// A parallel launch: the first launch of a kernel, mode and size class on a pool takes the
/// parallel path (the launch choice times it first). `class` picks a new size class.
fn parallel_launch(class: u32) {
    let n = SERIAL_BELOW << class;
    let x = Array::from_vec(vec![1.0f32; n]);
    let y = Array::zeros(n);
    launch(scale, n, (&x, 2.0, &y));
    assert_eq!(y.get(n - 1), 2.0);
}

#[test]
fn other_workers_linger_until_the_next_launch_or_the_time_has_passed() {
    assert_eq!(linger(), Duration::from_micros(500), "the default");
    for threads in [2, 3] {
        with_threads(threads, || {
            // Long enough that only the next launch can end the wait within the test.
            set_linger(Duration::from_secs(30));
            parallel_launch(0);
            assert!(
                reaches(threads - 1),
                "{threads} threads: every worker but the launching one lingers (saw {})",
                lingering()
            );
            // The next parallel launch ends their wait; with no lingering set, none follows.
            set_linger(Duration::ZERO);
            parallel_launch(1);
            assert!(
                reaches(0),
                "a launch ends the wait of the lingering workers"
            );
            assert_eq!(lingerers().0, 0, "nothing left queued");
            // A short linger ends by itself.
            set_linger(Duration::from_millis(20));
            parallel_launch(2);
            assert!(reaches(0), "lingering ends when its time has passed");
            // Both ways of running a launch in parallel have the launching thread wait for
            // the other shares (the wait itself: the unit test of `linger::Team`).
            let waits = leader_waits();
            split_launch();
            assert!(leader_waits() > waits, "a split launch's leader waits");
            let waits = leader_waits();
            parallel_launch(9);
            assert!(leader_waits() > waits, "a chunked launch's leader waits");
            // The counts of lingering workers are the process's: let these end before the
            // next pool's launches count them.
            assert!(reaches(0), "lingering ends when its time has passed");
        });
    }

    // With the other worker busy with work of its own, the launching thread runs both halves,
    // and the lingering job it spawns waits in its queue: one, however many launches follow,
    // and when the launching thread runs it (waiting for other pool work), it returns at once.
    assert!(
        quiet(),
        "the pools above left lingering jobs: {:?}",
        lingerers()
    );
    with_threads(2, || {
        set_linger(Duration::from_secs(30));
        static RELEASE: AtomicBool = AtomicBool::new(false);
        static BUSY: AtomicBool = AtomicBool::new(false);
        rayon::spawn(|| {
            BUSY.store(true, Ordering::Release);
            while !RELEASE.load(Ordering::Acquire) {
                std::thread::yield_now();
            }
        });
        while !BUSY.load(Ordering::Acquire) {
            std::thread::yield_now();
        }
        let run_queued = || {
            let t = Instant::now();
            while rayon::yield_local() == Some(rayon::Yield::Executed) {}
            assert!(
                t.elapsed() < Duration::from_secs(5),
                "the launching thread lingered"
            );
            assert_eq!(lingerers(), (0, 0));
        };
        parallel_launch(3);
        assert_eq!(
            lingerers(),
            (1, 0),
            "one lingering job queued, none spinning"
        );
        run_queued();
        for class in 4..7 {
            parallel_launch(class);
        }
        assert_eq!(lingerers(), (1, 0), "still one lingering job queued");
        run_queued();
        RELEASE.store(true, Ordering::Release);
    });

    // From a thread outside the pool (here the global one), every worker of the pool lingers.
    set_linger(Duration::from_secs(30));
    let workers = rayon::current_num_threads();
    parallel_launch(7);
    if workers > 1 {
        assert!(
            reaches(workers),
            "outside the pool, all {workers} workers linger"
        );
    }
    set_linger(Duration::ZERO);
    parallel_launch(8);
    assert!(reaches(0));
    set_linger(Duration::from_micros(500));
}
