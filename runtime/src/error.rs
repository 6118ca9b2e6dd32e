//! Errors of the runtime. Each names the kernel, launch, array and index involved.

use std::fmt;

/// An error of the runtime (tape, gradients, checks).
#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// `grad()` of an array that neither requires grad nor got a gradient buffer.
    NoGrad {
        /// The array's label.
        array: String,
    },
    /// An array a recorded launch read was written before `backward`.
    ArrayChanged {
        /// The kernel of the launch that read the array.
        kernel: String,
        /// Position of the launch on the tape.
        launch: usize,
        /// The kernel parameter the array was passed as.
        param: String,
        /// The array's label.
        array: String,
        /// Version when recorded.
        recorded: u64,
        /// Version at `backward`.
        now: u64,
    },
    /// `backward` on an array that no recorded launch wrote.
    NotOnTape {
        /// The array's label.
        array: String,
    },
    /// A launch produced a NaN or infinite value (debug mode).
    NonFinite {
        /// The kernel.
        kernel: String,
        /// Position of the launch on the tape (or 0 for an untaped launch).
        launch: usize,
        /// The parameter.
        param: String,
        /// The array's label.
        array: String,
        /// The first bad index.
        index: usize,
        /// Forward or adjoint.
        pass: &'static str,
    },
    /// Anything else, with a message.
    Other(String),
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::NoGrad { array } => write!(
                f,
                "array `{array}` has no gradient: call .requires_grad() on it before recording"
            ),
            Error::ArrayChanged { kernel, launch, param, array, recorded, now } => write!(
                f,
                "array `{array}` (param `{param}` of kernel `{kernel}`, launch #{launch} on the tape) \
                 was written after the launch read it (version {recorded} -> {now}); its adjoint \
                 would replay with the new values and give wrong gradients. Write into a new array \
                 instead, or reset the tape and record again"
            ),
            Error::NotOnTape { array } => write!(
                f,
                "backward from `{array}`, which no launch recorded on this tape wrote"
            ),
            Error::NonFinite { kernel, launch, param, array, index, pass } => write!(
                f,
                "{pass} of kernel `{kernel}` (launch #{launch}) wrote a NaN/Inf into `{array}` \
                 (param `{param}`) at index {index}"
            ),
            Error::Other(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for Error {}
