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
    /// A backward pass that reaches no array which requires grad: every gradient would stay
    /// zero.
    NothingToDifferentiate {
        /// The labels of the seeds (the loss).
        seeds: String,
    },
    /// An array was written off the tape (on the host) between the recorded step that wrote
    /// it and a later recorded step that used it.
    WrittenOffTape {
        /// The array's label.
        array: String,
        /// The step that wrote it on the tape.
        writer: String,
        /// Its position on the tape.
        writer_launch: usize,
        /// The later step that used it.
        user: String,
        /// Its position on the tape.
        user_launch: usize,
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
            Error::NothingToDifferentiate { seeds } => write!(
                f,
                "backward from {seeds} reaches no array that requires grad, so every gradient \
                 would be zero: call `.requires_grad()` on the parameters before recording, and \
                 record every step between them and the loss on this tape (a loss computed on \
                 another tape, or from copies, is not connected)"
            ),
            Error::WrittenOffTape { array, writer, writer_launch, user, user_launch } => write!(
                f,
                "array `{array}` was written off the tape after launch #{writer_launch} \
                 (`{writer}`) wrote it and before launch #{user_launch} (`{user}`) used it; the \
                 tape cannot see that write, so `{writer}` would receive gradient for values that \
                 were replaced. Make the write a step of the tape (a kernel, or `Tape::record_fn`), \
                 or write into a new array"
            ),
            Error::Other(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for Error {}
