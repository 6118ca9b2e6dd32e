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
    /// An iterative solver (a Newton iteration, a Krylov linear solve, a constraint
    /// projection) stopped before it met its tolerance, or its iterate became non-finite.
    /// Its result is not the answer the method promises, so it is reported instead of used.
    NotConverged {
        /// The solver, e.g. `"ImplicitEuler Newton"`, `"ImplicitEuler adjoint linear solve"`,
        /// `"Xpbd constraint solve"`.
        solver: String,
        /// Where: the tape step (`scope/name`, launch index), time step, substep, ...
        context: String,
        /// Iterations run.
        iterations: usize,
        /// The residual reached (NaN or infinite if the iterate is not finite).
        residual: f64,
        /// The tolerance the residual had to meet.
        tolerance: f64,
        /// What to change to make it converge (the solver's own settings).
        hint: String,
    },
    /// An input cannot be computed with: a NaN, infinite or non-positive time step, a NaN
    /// parameter, a NaN initial state.
    InvalidInput {
        /// The input, e.g. `"dt"`, `"spring_ke[3]"` (array label and index).
        what: String,
        /// What is wrong with it and what is expected.
        message: String,
    },
    /// Anything else, with a message.
    Other(String),
}

impl Error {
    /// This error, with `context` prepended to where it happened (for the solver errors'
    /// `context`, e.g. the tape step that ran the solve; [`Error::NonFinite`] after its
    /// kernel's name, `kernel (in context)`; other errors get it as a prefix of their
    /// message).
    pub fn in_context(self, context: impl AsRef<str>) -> Error {
        let ctx = context.as_ref();
        let join = |c: String| {
            if c.is_empty() {
                ctx.to_string()
            } else {
                format!("{ctx}, {c}")
            }
        };
        match self {
            Error::NotConverged {
                solver,
                context,
                iterations,
                residual,
                tolerance,
                hint,
            } => Error::NotConverged {
                solver,
                context: join(context),
                iterations,
                residual,
                tolerance,
                hint,
            },
            Error::InvalidInput { what, message } => Error::InvalidInput {
                what,
                message: format!("{message} (in {ctx})"),
            },
            Error::Other(m) => Error::Other(format!("{ctx}: {m}")),
            Error::NonFinite {
                kernel,
                launch,
                param,
                array,
                index,
                pass,
            } => Error::NonFinite {
                kernel: format!("{kernel} (in {ctx})"),
                launch,
                param,
                array,
                index,
                pass,
            },
            e => e,
        }
    }
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
            Error::NotConverged { solver, context, iterations, residual, tolerance, hint } => {
                write!(f, "{solver} did not converge")?;
                if !context.is_empty() {
                    write!(f, " ({context})")?;
                }
                if residual.is_finite() {
                    write!(
                        f,
                        ": residual {residual:.3e} > tolerance {tolerance:.3e} after {iterations} \
                         iterations"
                    )?;
                } else {
                    write!(
                        f,
                        ": the iterate became non-finite (residual {residual}) after {iterations} \
                         iterations; tolerance {tolerance:.3e}"
                    )?;
                }
                if !hint.is_empty() {
                    write!(f, ". To fix: {hint}")?;
                }
                Ok(())
            }
            Error::InvalidInput { what, message } => write!(f, "invalid input `{what}`: {message}"),
            Error::Other(m) => f.write_str(m),
        }
    }
}

impl std::error::Error for Error {}
