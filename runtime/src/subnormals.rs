//! Subnormal floats inside launches: the guard that flushes them to zero on one thread
//! ([`Settings::flush_subnormals`](crate::settings::Settings::flush_subnormals) says why;
//! `crate::region` enters it on every thread of a launch).

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
