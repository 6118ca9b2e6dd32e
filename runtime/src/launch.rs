//! Launching kernels over the rayon thread pool.
//!
//! A launch on a one-thread pool, one smaller than [`SERIAL_BELOW`] ids unless its serial
//! runs were slow (over 20 us three times in a row: costly ids, such as a thousand worlds'
//! articulated steps), or one of a kernel that measured faster serially (each kernel, mode
//! and size is timed both ways), runs on the calling thread in thread-id order and scatters
//! straight into its targets. Any other launch runs in parallel in one of two ways. If the
//! macro proved its scatters go through index arrays read at the thread id (a mesh's
//! springs), it is split into one contiguous range per worker, each writing directly all it
//! alone touches and logging the rest, and the logs are applied in range order (`split`).
//! Otherwise its thread ids run in chunks of at most [`CHUNK`] (16 chunks for a smaller
//! launch; set by the size, never by the thread count), each logging its scatters and
//! applying its logs when every earlier chunk has applied its own. Both add in thread-id
//! order, so the result is bitwise identical for any number of threads and from run to run.
//!
//! Launches flush subnormal floats to zero, on every thread that runs them; host code keeps
//! IEEE subnormals. [`set_flush_subnormals`] says why and turns it off. After a parallel
//! launch the pool's other workers wait for the next one awake for a while; [`set_linger`]
//! says why and sets how long.

use std::ops::Range;

use crate::array::{AnyArray, Token};
use crate::chunk_order::ChunkOrder;
use crate::kernel::{Access, Exec, Kernel, KernelBody, Mode, ParamInfo, ScatterLog};
use crate::region::Region;
pub use crate::settings::{flush_subnormals, linger, set_flush_subnormals, set_linger};
use crate::{settings, split};

/// The most thread ids per chunk of a parallel launch.
pub const CHUNK: usize = 2048;
pub use crate::settings::SERIAL_BELOW;

/// Chunks a launch of fewer than `CHUNKS * CHUNK` ids is cut into: enough for the workers to
/// share a small launch whose ids are costly (a thousand worlds' articulated steps).
const CHUNKS: usize = 16;

/// Thread ids per chunk of a parallel launch of `dim` ids.
fn chunk_len(dim: usize) -> usize {
    dim.div_ceil(CHUNKS).clamp(1, CHUNK)
}

/// A kernel bound to its (owned) arguments: what a tape records and replays.
pub trait BoundLaunch: Send + Sync {
    /// The kernel's name.
    fn name(&self) -> &'static str;
    /// The kernel's parameters.
    fn params(&self) -> &'static [ParamInfo];
    /// The array passed for each parameter.
    fn arrays(&self) -> Vec<Option<&dyn AnyArray>>;
    /// Runs `0..dim` in `mode`.
    fn run(&self, mode: Mode, dim: usize);
}

pub(crate) struct Bound<K, O> {
    pub(crate) kernel: K,
    pub(crate) args: O,
}

impl<K: KernelBody<O>, O: Send + Sync + 'static> BoundLaunch for Bound<K, O> {
    fn name(&self) -> &'static str {
        K::NAME
    }
    fn params(&self) -> &'static [ParamInfo] {
        K::PARAMS
    }
    fn arrays(&self) -> Vec<Option<&dyn AnyArray>> {
        K::arrays(&self.args)
    }
    fn run(&self, mode: Mode, dim: usize) {
        run_bound(&self.kernel, &self.args, mode, dim)
    }
}

/// Binds `kernel` to `args` (taking handles of the arrays).
pub fn bind<K, A>(kernel: K, args: A) -> Box<dyn BoundLaunch>
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    Box::new(Bound {
        kernel,
        args: K::to_owned(&args),
    })
}

/// Runs `kernel` over thread ids `0..dim` with `args` (forward mode, not recorded).
///
/// ```
/// use adflex_runtime::prelude::*;
/// use adflex_macros::diff_kernel;
/// #[diff_kernel]
/// fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
///     let t = tid();
///     y[t] = x[t] * s;
/// }
/// let x = Array::from_vec(vec![1.0f32, 2.0, 3.0]);
/// let y = Array::zeros(3);
/// launch(scale, 3, (&x, 2.0, &y));
/// assert_eq!(y.to_vec(), vec![2.0, 4.0, 6.0]);
/// ```
pub fn launch<K, A>(kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    run_bound(&kernel, &K::to_owned(&args), Mode::Forward, dim)
}

/// Runs the tangent (forward-mode) kernel: reads the tangent buffers of the inputs
/// ([`crate::Array::set_tangent`]) and writes those of the outputs (which must exist and
/// start at zero for accumulated outputs).
pub fn launch_tangent<K, A>(kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    run_bound(&kernel, &K::to_owned(&args), Mode::Tangent, dim)
}

/// Runs the adjoint (reverse-mode) kernel once: reads the gradient buffers of the outputs and
/// accumulates into those of the inputs. A [`crate::Tape`] does this for you.
pub fn launch_adjoint<K, A>(kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    run_bound(&kernel, &K::to_owned(&args), Mode::Adjoint, dim)
}

/// Runs `kernel` in `mode` (forward, adjoint or tangent); see [`launch`], [`launch_adjoint`],
/// [`launch_tangent`].
pub fn launch_mode<K, A>(mode: Mode, kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    run_bound(&kernel, &K::to_owned(&args), mode, dim)
}

/// The largest pool [`with_threads`] builds: 4 threads per core, at least 64. More threads
/// than that only add start-up time (each has its own stack) and contention.
pub fn max_threads() -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (4 * cores).max(64)
}

/// Runs `f` with a thread pool of `threads` threads (launches inside use it). Results are
/// bitwise the same for any number of threads.
///
/// ```
/// use adflex_runtime::with_threads;
/// assert_eq!(with_threads(2, rayon::current_num_threads), 2);
/// ```
///
/// # Panics
/// If `threads` is 0 or above [`max_threads`], with a message naming both.
pub fn with_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    let max = max_threads();
    if threads == 0 || threads > max {
        panic!(
            "with_threads({threads}): the pool must have between 1 and {max} threads (4 per core \
             of this machine, at least 64); launches use all the cores of the global pool by \
             default"
        );
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("building a rayon thread pool")
        .install(f)
}

fn run_bound<K: KernelBody<O>, O: Sync>(kernel: &K, args: &O, mode: Mode, dim: usize) {
    let arrays = K::arrays(args);
    with_locks(K::NAME, K::PARAMS, &arrays, mode, &mut |locked, shared| {
        // This thread runs a serial launch and applies a split one's logs.
        let region = Region::open();
        let threads = rayon::current_num_threads();
        // Two parameters scattering into one buffer (an array passed twice, read by both, in
        // the adjoint) keep two logs, which cannot be merged back into thread-id order: such
        // launches run serially.
        let may_split = threads > 1 && shared.is_empty() && dim > 1;
        let key = (
            std::any::TypeId::of::<K>(),
            mode,
            dim.max(1).ilog2(),
            threads,
        );
        // A small launch's slot in the table of slow keys (hashed only where it is read).
        let small = (may_split && dim < settings::serial_below()).then(|| slow::slot(&key));
        let timed = may_split
            && match small {
                Some(slot) => slow::marked(slot),
                None => true,
            };
        let serial = !timed || choice::serial(key);
        // (Read only when the launch is timed: a one-thread pool's launches are not.)
        let start = (timed || small.is_some()).then(std::time::Instant::now);
        let mut built = false;
        let split = match serial || dim >= u32::MAX as usize {
            true => None,
            false => split::plan(kernel, args, mode, dim, threads, locked, shared, &mut built),
        };
        if serial {
            let logs = kernel.run(mode, args, 0..dim, &Exec::new(true, locked, shared, 0..dim));
            debug_assert!(logs.iter().all(|l| l.0.is_none()));
        } else {
            match split {
                Some(plan) => split::run(kernel, args, mode, &plan, locked, shared, &region),
                None => run_ordered(dim, &region, &|r, k, order| {
                    kernel.run(
                        mode,
                        args,
                        r.clone(),
                        &Exec::ordered(locked, shared, r, order, k),
                    )
                }),
            }
            // The pool's workers linger from here (timed with the launch, as before).
            region.end();
        }
        // The first launch that plans its split is not a fair sample of the parallel path
        // (a plan is made once per index arrays' version); later ones that plan again are.
        if timed {
            if !(built && choice::first_build(key)) {
                let seconds = start
                    .expect("a timed launch reads the clock")
                    .elapsed()
                    .as_secs_f64();
                choice::record(key, serial, seconds);
            }
        } else if let (Some(slot), Some(start)) = (small, start) {
            slow::record(slot, start.elapsed());
        }
    });
}

/// Small launches that are slow: fewer than [`SERIAL_BELOW`] ids, each costing microseconds
/// (a thousand worlds' articulated steps). A key whose serial launches took longer than
/// [`slow::SERIAL`] [`slow::RUNS`] times in a row is marked, and from then on its launches are
/// timed both ways as large ones are (`choice`); one slow launch (a page fault, a preempted
/// thread) marks nothing. The marks are counters in a fixed table, read without a lock by
/// every small launch; two keys that share a slot only make a quick launch timed both ways,
/// and the timing keeps it serial.
mod slow {
    use std::hash::{Hash, Hasher};
    use std::sync::atomic::{AtomicU8, Ordering};
    use std::time::Duration;

    use super::choice::Key;

    /// A serial launch slower than this may gain from the pool: waking a worker and ordering
    /// the chunks cost a few microseconds (docs/performance.md).
    pub(super) const SERIAL: Duration = Duration::from_micros(20);
    /// Slow serial launches in a row that mark a key.
    pub(super) const RUNS: u8 = 3;

    /// Slow serial launches in a row, per slot (4,096 slots).
    static SLOW: [AtomicU8; 4096] = [const { AtomicU8::new(0) }; 4096];

    /// The slot of `key`.
    #[inline]
    pub(super) fn slot(key: &Key) -> usize {
        let mut h = Mix(0);
        key.hash(&mut h);
        (h.0 >> 52) as usize
    }

    /// Whether the key of `slot` (or one sharing it) is marked.
    #[inline]
    pub(super) fn marked(slot: usize) -> bool {
        SLOW[slot].load(Ordering::Relaxed) >= RUNS
    }

    /// A serial launch of the key of `slot` took `time`.
    #[inline]
    pub(super) fn record(slot: usize, time: Duration) {
        let runs = SLOW[slot].load(Ordering::Relaxed);
        if time > SERIAL {
            SLOW[slot].store(runs.saturating_add(1).min(RUNS), Ordering::Relaxed);
        } else if runs > 0 && runs < RUNS {
            SLOW[slot].store(0, Ordering::Relaxed);
        }
    }

    /// A multiply-rotate hash: the key is a few words, and every small launch hashes it.
    struct Mix(u64);

    impl Hasher for Mix {
        fn write(&mut self, bytes: &[u8]) {
            for b in bytes {
                self.write_u64(u64::from(*b));
            }
        }
        fn write_u64(&mut self, n: u64) {
            self.0 = (self.0.rotate_left(5) ^ n).wrapping_mul(0x517c_c1b7_2722_0a95);
        }
        fn write_u32(&mut self, n: u32) {
            self.write_u64(u64::from(n));
        }
        fn write_usize(&mut self, n: usize) {
            self.write_u64(n as u64);
        }
        fn write_isize(&mut self, n: isize) {
            self.write_u64(n as u64);
        }
        fn finish(&self) -> u64 {
            self.0
        }
    }

    #[cfg(test)]
    mod tests {
        use std::any::TypeId;

        use super::*;
        use crate::kernel::Mode;

        #[test]
        fn a_key_slow_several_times_in_a_row_is_marked_and_its_neighbours_mostly_not() {
            struct K;
            let key = |class, threads| (TypeId::of::<K>(), Mode::Tangent, class, threads);
            let s = slot(&key(9, 3));
            let (slow, quick) = (SERIAL * 2, SERIAL / 2);
            record(s, slow);
            record(s, quick);
            for _ in 1..RUNS {
                record(s, slow);
            }
            assert!(!marked(s), "a quick launch restarts the count");
            record(s, slow);
            assert!(marked(s));
            record(s, quick);
            assert!(marked(s), "a mark stays");
            // Other size classes and pool sizes of the same kernel spread over the table.
            let others = (0..12)
                .flat_map(|c| (1..9).map(move |t| (c, t)))
                .filter(|&k| k != (9, 3))
                .filter(|&(c, t)| marked(slot(&key(c, t))))
                .count();
            assert!(others <= 1, "{others} other keys share the mark");
        }
    }
}

/// Serial or parallel, per launch, by measurement: the two paths give the same bits (both
/// add in thread-id order), so a launch may take either. Each (kernel, mode, size class,
/// pool size) is timed both ways, then runs the faster, trying parallel again every
/// [`choice::PROBE`] launches of a serial key and serial every [`choice::PROBE_SERIAL`] of a
/// parallel one: so a launch that does not gain from a second thread (a small
/// scatter-bound kernel, or a core busy with another process) runs serially, and one that
/// gains runs in parallel.
mod choice {
    use std::any::TypeId;
    use std::collections::HashMap;
    use std::sync::{Mutex, PoisonError};

    use crate::kernel::Mode;

    /// Every this many launches of a key that runs serially, the parallel path is timed again
    /// (to return to it once a busy core is free).
    pub(super) const PROBE: u32 = 32;
    /// Every this many launches of a key that runs in parallel, the serial path is timed again.
    /// Rarer: a parallel path that slows (another process on a core) is seen at every launch,
    /// and each serial probe costs a launch at about half speed (32 cost the cloth 2.5%).
    pub(super) const PROBE_SERIAL: u32 = 256;

    pub(super) type Key = (TypeId, Mode, u32, usize);

    /// Seconds per launch of each path; launches so far. A launch faster than the estimate
    /// replaces it, a slower one moves it a quarter of the way: one slow launch (a page fault,
    /// a preempted worker) must not keep a key on its slower path until many probes have
    /// averaged it away, while a path that stays slow (a busy core) is seen within a few
    /// launches.
    #[derive(Default)]
    struct Times {
        serial: Option<f64>,
        parallel: Option<f64>,
        launches: u32,
    }

    static TIMES: Mutex<Option<HashMap<Key, Times>>> = Mutex::new(None);

    fn with<R>(f: impl FnOnce(&mut HashMap<Key, Times>) -> R) -> R {
        let mut g = TIMES.lock().unwrap_or_else(PoisonError::into_inner);
        f(g.get_or_insert_with(HashMap::new))
    }

    /// Whether the next launch of `key` runs serially.
    pub(super) fn serial(key: Key) -> bool {
        with(|m| {
            let t = m.entry(key).or_default();
            t.launches = t.launches.wrapping_add(1);
            match (t.serial, t.parallel) {
                (_, None) => false,
                (None, _) => true,
                (Some(s), Some(p)) => {
                    let faster_serial = s < p;
                    let every = if faster_serial { PROBE } else { PROBE_SERIAL };
                    if t.launches % every == 0 {
                        !faster_serial
                    } else {
                        faster_serial
                    }
                }
            }
        })
    }

    static BUILT: Mutex<Option<std::collections::HashSet<Key>>> = Mutex::new(None);

    /// Whether this is the first launch of `key` that planned a split.
    pub(super) fn first_build(key: Key) -> bool {
        let mut g = BUILT.lock().unwrap_or_else(PoisonError::into_inner);
        g.get_or_insert_with(Default::default).insert(key)
    }

    /// Records how long a launch of `key` took on the path it took.
    pub(super) fn record(key: Key, serial: bool, seconds: f64) {
        with(|m| {
            let t = m.entry(key).or_default();
            let slot = if serial {
                &mut t.serial
            } else {
                &mut t.parallel
            };
            *slot = Some(match *slot {
                Some(old) if seconds > old => 0.75 * old + 0.25 * seconds,
                _ => seconds,
            });
        })
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn times_both_paths_then_takes_the_faster_and_probes_the_other() {
            struct K;
            let key = (TypeId::of::<K>(), Mode::Adjoint, 13, 2);
            assert!(!serial(key)); // parallel first
            record(key, false, 2.0);
            assert!(serial(key)); // then serial
            record(key, true, 1.0);
            let picks: Vec<bool> = (0..2 * PROBE).map(|_| serial(key)).collect();
            let parallel = picks.iter().filter(|s| !**s).count();
            assert_eq!(
                parallel, 2,
                "one probe of the slower path per {PROBE} launches"
            );
            // The parallel path getting faster flips the choice.
            for _ in 0..20 {
                record(key, false, 0.1);
            }
            assert!(!serial(key) || !serial(key));
            let picks: Vec<bool> = (0..2 * PROBE_SERIAL).map(|_| serial(key)).collect();
            let serial_picks = picks.iter().filter(|s| **s).count();
            assert_eq!(
                serial_picks, 2,
                "one probe of the serial path per {PROBE_SERIAL} launches"
            );
        }

        #[test]
        fn one_slow_launch_costs_one_probe_not_many() {
            struct K;
            let key = (TypeId::of::<K>(), Mode::Forward, 16, 2);
            assert!(!serial(key));
            record(key, false, 1.0);
            assert!(serial(key));
            record(key, true, 2.0);
            assert!(!serial(key));
            // A parallel launch 100 times slower (a preempted worker) sends the key serial...
            record(key, false, 100.0);
            assert!(serial(key));
            // ...until the next probe of the parallel path, which is fast again.
            let mut launches = 1;
            while serial(key) {
                record(key, true, 2.0);
                launches += 1;
                assert!(launches <= PROBE, "no parallel probe in {PROBE} launches");
            }
            record(key, false, 1.0);
            assert!(
                !serial(key),
                "a fast probe brings the key back to its faster path"
            );
            // A path that stays slow is left within a few launches.
            let mut slow = 0;
            while !serial(key) {
                record(key, false, 3.0);
                slow += 1;
                assert!(
                    slow <= 4,
                    "a path slower at every launch is kept {slow} launches"
                );
            }
        }
    }
}

/// Runs `kernel` in `mode` over `0..dim` on the calling thread only, in thread-id order (the
/// same bits as [`launch_mode`]). It compiles less code per kernel than [`launch_mode`] (no
/// thread-pool path): for programs with very many small kernels, such as generated tests.
pub fn launch_serial<K, A>(mode: Mode, kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    let owned = K::to_owned(&args);
    let arrays = K::arrays(&owned);
    with_locks(K::NAME, K::PARAMS, &arrays, mode, &mut |locked, shared| {
        let _region = Region::open();
        let _ = kernel.run(
            mode,
            &owned,
            0..dim,
            &Exec::new(true, locked, shared, 0..dim),
        );
    });
}

/// Locks what a launch uses (in one global order, by id, so that two launches never wait for
/// each other), starts a new store-claim epoch on what it stores into, runs `run` with the
/// locked buffers, and bumps the versions of what it wrote.
fn with_locks(
    kernel: &str,
    params: &[ParamInfo],
    arrays: &[Option<&dyn AnyArray>],
    mode: Mode,
    run: &mut LockedRun,
) {
    let targets = lock_targets(kernel, params, arrays, mode);
    let _held = crate::array::HeldGroup::enter(
        targets.iter().map(|t| (t.id, t.write, &*t.target)),
        "launching a kernel on",
    );
    let _locks: Vec<_> = targets
        .iter()
        .map(|t| t.target.lock(t.write, Token(())))
        .collect();
    let locked: Vec<(u64, bool)> = targets.iter().map(|t| (t.id, t.write)).collect();
    // Under the locks: the buffers the stores of this launch go to, as locked (a buffer
    // swapped in meanwhile is refused by the views' lock check).
    for t in targets.iter().filter(|t| t.claim) {
        t.target.new_claim_epoch(Token(()));
    }
    run(&locked, &shared_scatters(params, arrays, mode));
    mark_written(params, arrays, mode);
}

/// The buffers that two or more parameters scatter into in `mode`: only gradients in the
/// adjoint, of an array passed for two `Read` parameters (an array scattered into in forward
/// or tangent mode is written, so it cannot be passed twice: `lock_targets`).
fn shared_scatters(params: &[ParamInfo], arrays: &[Option<&dyn AnyArray>], mode: Mode) -> Vec<u64> {
    if mode != Mode::Adjoint {
        return Vec::new();
    }
    let read = |k: usize| arrays[k].filter(|_| params[k].access == Access::Read);
    let mut shared = Vec::new();
    for i in 0..params.len().min(arrays.len()) {
        let Some(a) = read(i) else { continue };
        if (0..i).any(|k| read(k).is_some_and(|b| b.id() == a.id())) {
            if let Some(g) = a.grad_any() {
                shared.push(g.id());
            }
        }
    }
    shared
}

/// The body of a launch, given the (id, for writing) of every buffer it holds locked and the
/// buffers two parameters scatter into.
type LockedRun<'a> = dyn FnMut(&[(u64, bool)], &[u64]) + 'a;

/// A buffer a launch locks: one of its arrays, or a gradient or tangent buffer (owned: the
/// array hands out a new handle).
enum Target<'a> {
    Array(&'a dyn AnyArray),
    Buffer(Box<dyn AnyArray>),
}

impl<'a> std::ops::Deref for Target<'a> {
    type Target = dyn AnyArray + 'a;
    fn deref(&self) -> &(dyn AnyArray + 'a) {
        match self {
            Target::Array(a) => *a,
            Target::Buffer(b) => &**b,
        }
    }
}

/// A buffer a launch locks.
struct LockTarget<'a> {
    id: u64,
    /// The parameter passing the array, or `usize::MAX` for its gradient or tangent.
    param: usize,
    target: Target<'a>,
    /// Locked for writing (some use of it writes).
    write: bool,
    /// A `Store` parameter writes it in this mode: its store claims start a new epoch.
    claim: bool,
}

/// What a launch must lock, sorted by id, each once (for writing if any use writes it): the
/// arrays (written only in forward mode) and the gradient or tangent buffers the mode reads or
/// writes. Panics if one array is passed for two parameters and one of them writes it: the
/// kernel would read its own output, or two writes would race.
fn lock_targets<'a>(
    kernel: &str,
    params: &[ParamInfo],
    arrays: &[Option<&'a dyn AnyArray>],
    mode: Mode,
) -> Vec<LockTarget<'a>> {
    debug_assert_eq!(params.len(), arrays.len());
    // Every use, with its parameter (an array) or `usize::MAX` (a gradient or tangent
    // buffer), sorted by id: an alias is two neighbours (a kernel has tens of parameters, so
    // sorting beats comparing every pair).
    let mut uses = Vec::with_capacity(2 * arrays.len());
    let forward = mode == Mode::Forward;
    for (i, (p, a)) in params.iter().zip(arrays).enumerate() {
        let Some(a) = *a else { continue };
        let (writes, store) = (p.access.writes(), p.access == Access::Store);
        uses.push(LockTarget {
            id: a.id(),
            param: i,
            target: Target::Array(a),
            write: writes && forward,
            claim: store && forward,
        });
        let buffer = match mode {
            Mode::Forward => None,
            // Reads scatter into their gradients, stores take theirs, atomics read theirs.
            Mode::Adjoint => a.grad_any().map(|g| (g, p.access != Access::Atomic)),
            // Reads read their tangents, stores and atomics write theirs.
            Mode::Tangent => a.tangent_any().map(|t| (t, writes)),
        };
        if let Some((b, write)) = buffer {
            uses.push(LockTarget {
                id: b.id(),
                param: usize::MAX,
                target: Target::Buffer(b),
                write,
                claim: store,
            });
        }
    }
    uses.sort_unstable_by_key(|t| (t.id, t.param));
    let writes = |k: usize| params.get(k).is_some_and(|p| p.access.writes());
    for w in uses.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        if a.id == b.id && b.param != usize::MAX && (writes(a.param) || writes(b.param)) {
            panic!(
                "kernel `{kernel}`: array `{}` is passed as both `{}` and `{}`, and the kernel \
                 writes one of them; pass distinct arrays",
                a.target.label(),
                params[a.param].name,
                params[b.param].name
            );
        }
    }
    // Each once, for writing if any use writes it.
    uses.dedup_by(|later, kept| {
        let same = later.id == kept.id;
        if same {
            kept.write |= later.write;
            kept.claim |= later.claim;
        }
        same
    });
    uses
}

/// Bumps the versions of what the launch wrote: the arrays it writes in forward mode; in the
/// other modes only gradient or tangent buffers, which carry no version that tapes check.
fn mark_written(params: &[ParamInfo], arrays: &[Option<&dyn AnyArray>], mode: Mode) {
    if mode != Mode::Forward {
        return;
    }
    for (p, a) in params.iter().zip(arrays) {
        if let (true, Some(a)) = (p.access.writes(), a) {
            a.mark_written(Token(()));
        }
    }
}

/// Runs the chunks of `0..dim` on the pool's workers, claimed in order, each applying its logs
/// when every earlier chunk has applied its own (thread-id order, whatever the thread count),
/// while later chunks run. A chunk whose log grows large applies it early, at its turn
/// ([`crate::kernel::Scatter`]), so memory does not grow with the contributions.
fn run_ordered(dim: usize, region: &Region, run: &RunChunk) {
    let len = chunk_len(dim);
    let chunks = dim.div_ceil(len);
    let order = ChunkOrder::default();
    let workers = rayon::current_num_threads().clamp(1, chunks.max(1));
    // Each worker claims chunks until none is left, and applies logs.
    region.shares(workers, |_| run_chunks(dim, len, &order, chunks, run));
}

/// Claims and runs chunks in order until none is left (one worker of [`run_ordered`]).
fn run_chunks(dim: usize, len: usize, order: &ChunkOrder, chunks: usize, run: &RunChunk) {
    loop {
        let k = order.claim();
        if k >= chunks {
            break;
        }
        let range = k * len..((k + 1) * len).min(dim);
        // Wakes the waiters if this chunk panics (they would wait for its turn forever).
        struct FailOnUnwind<'o>(&'o ChunkOrder);
        impl Drop for FailOnUnwind<'_> {
            fn drop(&mut self) {
                if std::thread::panicking() {
                    self.0.fail();
                }
            }
        }
        let guard = FailOnUnwind(order);
        let logs = run(range, k, order);
        order.finish(k, logs);
        drop(guard);
    }
}

/// Runs one chunk (its thread ids, its index) and returns its logs.
type RunChunk<'a> = dyn Fn(Range<usize>, usize, &ChunkOrder) -> Vec<ScatterLog> + Sync + 'a;
