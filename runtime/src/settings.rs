//! The runtime's process-wide settings, in one value: [`Settings`].
//!
//! Every knob that changes how launches run (not what they compute) is a field of
//! [`Settings`], with its default in [`Settings::default`]. Read them with [`settings`], change
//! them with [`set_settings`] (or [`Settings::apply`]):
//!
//! ```
//! use std::time::Duration;
//! use adflex_runtime::settings::{settings, set_settings, Settings};
//! assert_eq!(settings(), Settings::default());
//! let mut s = settings();
//! s.linger = Duration::ZERO; // idle workers sleep as soon as a launch ends
//! set_settings(s);
//! assert_eq!(settings().linger, Duration::ZERO);
//! Settings::default().apply();
//! ```
//!
//! Results do not depend on any of them except [`Settings::flush_subnormals`], which decides
//! whether values below `MIN_POSITIVE` are flushed to zero inside launches. A launch reads the
//! settings when it starts; one already running keeps what it read.
//!
//! The older setters ([`set_linger`], [`set_flush_subnormals`], also at
//! `adflex_runtime::launch::`) write one field each. What the runtime measures or keeps
//! from one launch to the next (the serial-or-parallel timings, split plans, log buffers) is
//! not a setting: it lives with the code that owns it.

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::time::Duration;

/// How launches run, process-wide. See the [module docs](self).
///
/// New fields may be added: make one from [`settings`] or [`Settings::default`] and change
/// the fields you want.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub struct Settings {
    /// How long, after a parallel launch, the pool's other workers busy-wait for the next one
    /// before they may sleep, and how long the launching thread waits awake for the other
    /// shares of its launch. Default: 0.5 ms. `Duration::ZERO` lets them sleep at once, as
    /// rayon's idle workers do. [`set_linger`] says why.
    pub linger: Duration,
    /// Whether launches flush subnormal floats to zero (x86's FTZ and DAZ, aarch64's FZ), on
    /// every thread that runs them. Default: `true`. `false` gives IEEE gradual underflow.
    /// [`set_flush_subnormals`] says why.
    pub flush_subnormals: bool,
    /// Launches with fewer thread ids than this run serially on the calling thread unless a
    /// serial launch of the same kernel, mode and size took over 20 us (each id costs
    /// microseconds: a thousand worlds' articulated steps); those and larger ones are timed
    /// both ways and take the faster. Default: [`SERIAL_BELOW`] (4096): rayon's per-call
    /// overhead is a few microseconds (docs/performance.md). Results are the same bits either
    /// way.
    pub serial_below: usize,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            linger: Duration::from_nanos(DEFAULT_LINGER_NS),
            flush_subnormals: true,
            serial_below: SERIAL_BELOW,
        }
    }
}

impl Settings {
    /// Makes these the process's settings (the same as [`set_settings`]).
    pub fn apply(self) {
        set_settings(self)
    }
}

/// The settings now.
pub fn settings() -> Settings {
    Settings {
        linger: Duration::from_nanos(linger_ns()),
        flush_subnormals: flush(),
        serial_below: serial_below(),
    }
}

/// Sets every setting (process-wide); launches that start afterwards use them.
pub fn set_settings(s: Settings) {
    set_linger(s.linger);
    set_flush_subnormals(s.flush_subnormals);
    SERIAL_BELOW_NOW.store(s.serial_below, Ordering::Relaxed);
}

/// Launches with fewer thread ids than this run serially by default
/// ([`Settings::serial_below`]; also `adflex_runtime::launch::SERIAL_BELOW`): rayon's
/// per-call overhead is a few microseconds (docs/performance.md).
pub const SERIAL_BELOW: usize = 4096;

// The settings are kept field by field, in atomics: a launch reads the one it needs with one
// load (no lock on the launch path).

const DEFAULT_LINGER_NS: u64 = 500_000;
/// [`Settings::linger`], in nanoseconds.
static LINGER_NS: AtomicU64 = AtomicU64::new(DEFAULT_LINGER_NS);
/// [`Settings::flush_subnormals`].
static FLUSH: AtomicBool = AtomicBool::new(true);
/// [`Settings::serial_below`].
static SERIAL_BELOW_NOW: AtomicUsize = AtomicUsize::new(SERIAL_BELOW);

/// [`Settings::linger`] in nanoseconds.
#[inline]
pub(crate) fn linger_ns() -> u64 {
    LINGER_NS.load(Ordering::Relaxed)
}

/// [`Settings::flush_subnormals`].
#[inline]
pub(crate) fn flush() -> bool {
    FLUSH.load(Ordering::Relaxed)
}

/// [`Settings::serial_below`].
#[inline]
pub(crate) fn serial_below() -> usize {
    SERIAL_BELOW_NOW.load(Ordering::Relaxed)
}

/// How long, after a parallel launch, the pool's other workers busy-wait for the next launch
/// before they may sleep ([`Settings::linger`]; the default: 0.5 ms). See [`set_linger`].
pub fn linger() -> Duration {
    Duration::from_nanos(linger_ns())
}

/// Sets how long, after a parallel launch, the pool's other workers busy-wait for the next
/// launch (process-wide; [`Settings::linger`]); `Duration::ZERO` lets them sleep at once, as
/// rayon's idle workers do.
///
/// A rayon worker that finds no work sleeps after a few microseconds. Waking it costs the
/// launching thread a system call and the worker tens of microseconds before it runs: on a
/// 2-core virtual machine a parallel launch of two 100 us halves took 176 us when it came 50 us
/// after the previous one, and 101 us when it came at once (docs/performance.md). A simulation
/// step is a few launches of 0.05 to 1 ms with a little host work between them (recording
/// them, allocating the next state), so every parallel launch paid that. So after a parallel
/// launch, the pool's other workers spin until the next parallel launch starts or this time
/// has passed, as OpenMP runtimes do (`KMP_BLOCKTIME`, `OMP_WAIT_POLICY`). Within a launch,
/// the launching thread, done with its share, waits for the other shares spinning too, at
/// most this long. The cost is CPU time on those cores, at most this long per parallel
/// launch; a program that launches rarely and shares its cores may prefer `Duration::ZERO`.
/// Results do not depend on it.
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

/// Whether launches that start now flush subnormal floats to zero
/// ([`Settings::flush_subnormals`]; the default: `true`). See [`set_flush_subnormals`].
pub fn flush_subnormals() -> bool {
    flush()
}

/// Sets whether launches that start from now on flush subnormal floats to zero (process-wide;
/// [`Settings::flush_subnormals`]; a launch already running keeps its mode). `false` gives
/// IEEE gradual underflow.
///
/// Arithmetic that produces or reads a subnormal number (below `f32::MIN_POSITIVE`,
/// about 1.2e-38, or `f64::MIN_POSITIVE`, 2.2e-308) takes a slow microcode path on many x86
/// CPUs, up to a hundred times slower than a normal operation. Simulations make such values as
/// a matter of course: a perturbation that spreads from a pinned corner of a cloth decays
/// through them, and so do the adjoints of a long rollout. On an Intel Xeon they made the
/// cloth scene of `docs/scenes.md` up to 1.6x slower (docs/performance.md).
///
/// So every launch (forward, adjoint, tangent, on every thread that runs part of it, including
/// the application of its ordered scatters) runs with the CPU flushing subnormal results to
/// zero and reading subnormal inputs as zero (x86's FTZ and DAZ bits, aarch64's FZ bit), as
/// TensorFlow, XLA and GPUs do; the previous mode is restored when the launch ends, so host
/// code never sees it. Results change only where an exact computation would have a
/// magnitude below `MIN_POSITIVE`; every path of a launch (serial or parallel, any thread
/// count) runs in the same mode, so results stay bitwise identical across thread counts.
/// [`set_flush_subnormals`]`(false)` keeps IEEE subnormals (exact gradual underflow) for
/// launches that start afterwards. On other architectures the setting has no effect. A
/// constant the compiler folds ahead of time follows IEEE rules and may stay subnormal.
///
/// ```
/// use adflex_runtime::prelude::*;
/// use adflex_runtime::launch::{flush_subnormals, set_flush_subnormals};
/// use adflex_macros::diff_kernel;
/// #[diff_kernel]
/// fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
///     let t = tid();
///     y[t] = x[t] * s;
/// }
/// let x = Array::from_vec(vec![1e-20f32]);
/// let y = Array::zeros(1);
/// assert!(flush_subnormals());
/// launch(scale, 1, (&x, 1e-20, &y));
/// # #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
/// assert_eq!(y.get(0), 0.0); // 1e-40 is subnormal: flushed
/// set_flush_subnormals(false);
/// launch(scale, 1, (&x, 1e-20, &y));
/// assert!(y.get(0) > 0.0 && y.get(0) < f32::MIN_POSITIVE); // IEEE gradual underflow
/// set_flush_subnormals(true);
/// ```
pub fn set_flush_subnormals(on: bool) {
    FLUSH.store(on, Ordering::Relaxed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_defaults_are_documented_and_settings_round_trip() {
        let d = Settings::default();
        assert_eq!(d.linger, Duration::from_micros(500));
        assert!(d.flush_subnormals);
        assert_eq!(d.serial_below, 4096);
        // Unit tests run concurrently and other ones set the linger time: this one writes the
        // settings as they are (changing one would change the others' launches).
        let now = settings();
        now.apply();
        assert_eq!(settings(), now);
        assert_eq!(
            (now.flush_subnormals, now.serial_below),
            (flush(), serial_below())
        );
    }
}
