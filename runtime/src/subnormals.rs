//! Subnormal floats inside launches: flushed to zero by default ([`set_flush_subnormals`]).

use std::sync::atomic::{AtomicBool, Ordering};

static FLUSH: AtomicBool = AtomicBool::new(true);

/// Whether launches that start now flush subnormal floats to zero (the default: `true`).
/// See [`set_flush_subnormals`].
pub fn flush_subnormals() -> bool {
    FLUSH.load(Ordering::Relaxed)
}

/// Sets whether launches that start from now on flush subnormal floats to zero (process-wide;
/// a launch already running keeps its mode). `false` gives IEEE gradual underflow.
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

/// Puts this thread's floating-point unit in flush-to-zero mode while alive (if `on`), and
/// restores the mode it found when dropped.
pub(crate) struct Flush {
    saved: Option<Control>,
}

impl Flush {
    pub(crate) fn enter(on: bool) -> Self {
        let saved = on.then(|| {
            let saved = read();
            write(saved | FLUSH_BITS);
            saved
        });
        Flush { saved }
    }
}

impl Drop for Flush {
    fn drop(&mut self) {
        if let Some(saved) = self.saved {
            write(saved);
        }
    }
}

// The control register is read and written by inline assembly that may touch memory (no
// `nomem`), so the compiler keeps the kernel's loads and stores, and with them its arithmetic,
// between the two writes.
//
// Rust's documentation of `_mm_setcsr` counts a changed denormal mode as outside the language's
// model: the compiler assumes IEEE arithmetic, e.g. when it folds constants. What that can
// change here is only whether a value below `MIN_POSITIVE` that the compiler computed ahead of
// time stays subnormal; the same compiled kernel runs on every path and thread count, so the
// bits across thread counts do not depend on it. TensorFlow, XLA and audio DSP code (the
// `no_denormals` crate) rely on the same behaviour of the hardware.

#[cfg(target_arch = "x86_64")]
type Control = u32;
/// MXCSR: flush to zero (bit 15) and denormals are zero (bit 6).
#[cfg(target_arch = "x86_64")]
const FLUSH_BITS: Control = (1 << 15) | (1 << 6);

#[cfg(target_arch = "x86_64")]
fn read() -> Control {
    let mut csr: Control = 0;
    // SAFETY: stores the 4-byte MXCSR into `csr`.
    unsafe { std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack, preserves_flags)) };
    csr
}

#[cfg(target_arch = "x86_64")]
fn write(csr: Control) {
    // SAFETY: loads MXCSR from `csr` (a value read from it, with only the FTZ and DAZ bits
    // changed).
    unsafe { std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack, preserves_flags)) };
}

#[cfg(target_arch = "aarch64")]
type Control = u64;
/// FPCR: flush to zero (bit 24), which on AArch64 covers inputs and results.
#[cfg(target_arch = "aarch64")]
const FLUSH_BITS: Control = 1 << 24;

#[cfg(target_arch = "aarch64")]
fn read() -> Control {
    let fpcr: Control;
    // SAFETY: reads FPCR.
    unsafe { std::arch::asm!("mrs {}, fpcr", out(reg) fpcr, options(nostack, preserves_flags)) };
    fpcr
}

#[cfg(target_arch = "aarch64")]
fn write(fpcr: Control) {
    // SAFETY: writes FPCR (a value read from it, with only the FZ bit changed).
    unsafe { std::arch::asm!("msr fpcr, {}", in(reg) fpcr, options(nostack, preserves_flags)) };
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
type Control = u32;
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
const FLUSH_BITS: Control = 0;
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
fn read() -> Control {
    0
}
#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
fn write(_: Control) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
    fn the_guard_flushes_and_restores() {
        // MXCSR's low six bits are sticky exception flags, which arithmetic sets: not a mode.
        let mode = || {
            read()
                & !(if cfg!(target_arch = "x86_64") {
                    0x3f
                } else {
                    0
                })
        };
        let tiny = std::hint::black_box(1e-20f32);
        let before = mode();
        {
            let _f = Flush::enter(true);
            assert_eq!(std::hint::black_box(tiny) * std::hint::black_box(tiny), 0.0);
        }
        assert_eq!(mode(), before);
        let product = std::hint::black_box(tiny) * std::hint::black_box(tiny);
        assert!(product > 0.0 && product < f32::MIN_POSITIVE);
        let _off = Flush::enter(false);
        assert_eq!(mode(), before);
    }
}
