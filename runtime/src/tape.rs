//! The tape: records launches as they run, then runs their adjoints backward (reverse mode) or
//! their tangents forward (forward mode).
//!
//! A [`Tape`] keeps, for every recorded launch, the kernel bound to handles of its arrays, the
//! launch dimension, the scope it ran in, and the version of every array it read. Backward
//! refuses to run if one of those arrays was written since (it would replay the kernel with the
//! new values and give wrong gradients), and skips the adjoints that cannot matter.
//!
//! Kernels are not the only steps: [`Tape::record_fn`] records a host computation (a linear
//! solve, a copy) with a hand-written backward.

use std::collections::HashSet;
use std::fmt::{self, Write as _};

use crate::array::{AnyArray, Array, Element};
use crate::error::Error;
use crate::kernel::{Access, Kernel, KernelBody, Mode};
use crate::launch::{bind, BoundLaunch};

/// The backward or tangent of a custom step: fails if it cannot produce a right derivative
/// (e.g. its linear solve did not converge).
type StepFn = Box<dyn FnMut() -> Result<(), Error> + Send + Sync>;

/// One array a recorded step read or wrote.
struct Use {
    /// The kernel parameter (static), or `input k` / `output k` of a custom step.
    param: std::borrow::Cow<'static, str>,
    array: Box<dyn AnyArray>,
    /// `array.id()`, kept here: planning a backward over many small steps looks ids up in
    /// every record, and through the box each was a cache miss.
    id: u64,
    /// Version when the step was recorded (before it ran).
    version: u64,
    /// Version right after the step ran (for writes): a later step that finds another
    /// version knows the array was written off the tape in between.
    after: u64,
    atomic: bool,
}

enum Step {
    Launch {
        launch: Box<dyn BoundLaunch>,
        dim: usize,
    },
    Custom {
        name: String,
        backward: StepFn,
        tangent: Option<StepFn>,
        /// It reads or writes [`Dual`](crate::Dual) arrays and was not declared
        /// [`CustomStep::dual_safe`]: its backward and tangent refuse to run.
        dual_unsafe: bool,
    },
}

struct Record {
    step: Step,
    scope: Option<String>,
    reads: Vec<Use>,
    writes: Vec<Use>,
}

impl Record {
    fn name(&self) -> &str {
        match &self.step {
            Step::Launch { launch, .. } => launch.name(),
            Step::Custom { name, .. } => name,
        }
    }

    /// Runs the launch of this record (#`i`) in `mode`; a custom rule that refused `Dual` in
    /// it (see `func::take_refusal`) is an error naming the kernel.
    fn run_launch(&self, i: usize, mode: Mode) -> Result<(), Error> {
        let Step::Launch { launch, dim } = &self.step else {
            unreachable!("run_launch on a custom step")
        };
        launch.run(mode, *dim);
        match crate::func::take_refusal() {
            None => Ok(()),
            Some(message) => Err(Error::InvalidInput {
                what: format!("kernel `{}` (#{i} on the tape)", self.qualified()),
                message,
            }),
        }
    }

    /// `e`, returned by this custom step's backward or tangent (step `i` on the tape), with
    /// the step named in its context.
    fn custom_error(&self, i: usize, e: Error) -> Error {
        let step = self.qualified();
        e.in_context(format!("custom step `{step}` (#{i} on the tape)"))
    }

    /// After a custom step's backward: the step replaced its outputs, so an earlier writer of
    /// one gets no gradient (a launch's stores take theirs element by element, see
    /// `Writer::take`). Outputs that are also inputs are updated in place and keep theirs.
    fn clear_replaced_grads(&self) {
        for u in &self.writes {
            if !self.reads.iter().any(|x| x.id == u.id) {
                u.array.zero_grad();
            }
        }
    }

    /// The name as errors show it: `scope/name` inside a scope.
    fn qualified(&self) -> String {
        match &self.scope {
            Some(s) => format!("{s}/{}", self.name()),
            None => self.name().to_string(),
        }
    }

    fn non_finite(&self, launch: usize, u: &Use, index: usize, pass: &'static str) -> Error {
        Error::NonFinite {
            kernel: self.qualified(),
            launch,
            param: u.param.to_string(),
            array: u.array.label(),
            index,
            pass,
        }
    }
}

/// An input of a tape ([`Tape::inputs`]): an array a recorded step read before any recorded
/// step wrote it.
pub struct TapeInput {
    /// The first step that read it (kernel or custom step name, `scope/name` in a scope).
    pub step: String,
    /// The step's parameter it was bound to (`input k` for a custom step).
    pub param: String,
    /// A handle of the array.
    pub array: Box<dyn AnyArray>,
}

/// What the last [`Tape::backward`] did: how many recorded steps had their adjoint run and how
/// many were skipped because they could not contribute.
///
/// A step's adjoint runs only if the step read an array that depends on an array that
/// requires grad, and wrote an array from which the seeds (the loss) can be reached.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BackwardStats {
    /// Adjoints run.
    pub run: usize,
    /// Adjoints skipped.
    pub skipped: usize,
}

/// Which steps a backward pass runs, which arrays get gradient buffers, and which of those
/// start from zero (intermediates: written on the tape, not seeds).
struct Plan {
    run: Vec<bool>,
    /// Steps that depend on nothing differentiable but overwrite an array the loss depends
    /// on: their adjoint runs only to take (clear) the gradient of what they overwrote, so
    /// that an earlier writer of it gets none.
    consume: Vec<bool>,
    grads: HashSet<u64>,
    zeroed: HashSet<u64>,
}

/// Records launches and runs them backward for gradients (or forward for tangents).
///
/// ```
/// use adflex_runtime::prelude::*;
///
/// // A host step (no kernel needed): y = 3 x, with its backward x.grad += 3 y.grad.
/// let x = Array::from_vec(vec![1.0f64, 2.0]).requires_grad().named("x");
/// let y = Array::<f64>::zeros(2).named("y");
/// let mut tape = Tape::new();
/// let (xb, yb) = (x.clone(), y.clone());
/// tape.record_fn(
///     "triple",
///     &[&x],
///     &[&y],
///     || y.assign(&x.to_vec().iter().map(|v| 3.0 * v).collect::<Vec<_>>()),
///     move || {
///         let gy = yb.grad_buffer().unwrap().to_vec();
///         if let Some(gx) = xb.grad_buffer() {
///             gx.modify(|g| g.iter_mut().zip(&gy).for_each(|(g, d)| *g += 3.0 * d));
///         }
///         Ok(()) // or an `Error`, which `backward` returns, naming this step
///     },
/// );
/// tape.backward(&y).unwrap(); // seeds y.grad with ones
/// assert_eq!(x.grad().unwrap().to_vec(), vec![3.0, 3.0]);
/// ```
pub struct Tape {
    records: Vec<Record>,
    scopes: Vec<String>,
    check_finite: bool,
    /// The first non-finite value a recorded step wrote in `check_finite` mode.
    anomaly: Option<Error>,
    last: BackwardStats,
    /// Arrays whose gradient with respect to their final value is kept (see
    /// [`Tape::retain_grad`]).
    retained: HashSet<u64>,
    /// False for a [`Tape::no_grad`] tape: steps run and nothing is kept.
    recording: bool,
    /// Steps a `no_grad` tape has run (their positions in its errors).
    unrecorded: usize,
}

impl Default for Tape {
    fn default() -> Self {
        Self::new()
    }
}

impl fmt::Debug for Tape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Tape")
            .field(
                "records",
                &self
                    .records
                    .iter()
                    .map(Record::qualified)
                    .collect::<Vec<_>>(),
            )
            .field("check_finite", &self.check_finite)
            .field("last_backward", &self.last)
            .finish()
    }
}

impl Use {
    /// A use of `array` as it is now (its `after` set once the step ran, see `Tape::push`).
    fn new(param: std::borrow::Cow<'static, str>, array: &dyn AnyArray, atomic: bool) -> Self {
        Use {
            param,
            array: array.boxed(),
            id: array.id(),
            version: array.version(),
            after: 0,
            atomic,
        }
    }
}

/// Splits a step's arrays into reads and writes, with their current versions.
fn uses(
    params: &[crate::kernel::ParamInfo],
    arrays: &[Option<&dyn AnyArray>],
) -> (Vec<Use>, Vec<Use>) {
    let (mut reads, mut writes) = (Vec::new(), Vec::new());
    for (p, a) in params.iter().zip(arrays) {
        let Some(a) = a else { continue };
        let u = Use::new(p.name.into(), *a, p.access == Access::Atomic);
        match p.access {
            Access::Read => reads.push(u),
            Access::Store | Access::Atomic => writes.push(u),
            Access::Value | Access::Unused => {}
        }
    }
    (reads, writes)
}

impl Tape {
    /// An empty tape.
    pub fn new() -> Self {
        Tape {
            records: Vec::new(),
            scopes: Vec::new(),
            check_finite: false,
            anomaly: None,
            last: BackwardStats::default(),
            retained: HashSet::new(),
            recording: true,
            unrecorded: 0,
        }
    }

    /// A tape that runs every launch and custom step at once and records nothing, for rollouts
    /// that need no derivatives (evaluating a policy, generating data): the bookkeeping a
    /// recorded step costs (its record, the handles of its arrays, their versions) is skipped,
    /// and nothing is kept alive after the step, so memory stays flat over any number of
    /// steps. Code written against `&mut Tape` runs unchanged. Forward values are bitwise
    /// those of a recording tape.
    ///
    /// Asking it for derivatives ([`Tape::backward`], [`Tape::backward_with`],
    /// [`Tape::tangent`], [`Tape::vjp`], [`Tape::jvp`], ...) is an error that says so, never a
    /// silent zero. [`Tape::check_finite`] still checks each step's outputs.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    /// #[diff_kernel]
    /// fn double(x: &Array<f64>, y: &Array<f64>) {
    ///     y[tid()] = 2.0 * x[tid()];
    /// }
    /// let x = Array::from_vec(vec![1.0, 2.0]).requires_grad();
    /// let y = Array::zeros(2);
    /// let mut tape = Tape::no_grad();
    /// tape.launch(double, 2, (&x, &y));
    /// assert_eq!(y.to_vec(), vec![2.0, 4.0]);
    /// assert!(tape.is_empty());
    /// assert!(tape.backward(&y).is_err()); // "... made by Tape::no_grad ..."
    /// ```
    pub fn no_grad() -> Self {
        Tape {
            recording: false,
            ..Tape::new()
        }
    }

    /// False for a tape made by [`Tape::no_grad`].
    pub fn is_recording(&self) -> bool {
        self.recording
    }

    /// The error of asking a [`Tape::no_grad`] tape for derivatives.
    pub(crate) fn require_recording(&self, what: &str) -> Result<(), Error> {
        if self.recording {
            return Ok(());
        }
        Err(Error::InvalidInput {
            what: what.into(),
            message: "this tape was made by Tape::no_grad() and recorded nothing: record the \
                      steps on a Tape::new() to take derivatives"
                .into(),
        })
    }

    /// Keeps, after each [`Tape::backward`], the gradient of the loss with respect to the
    /// **final** value of `array` (an intermediate some recorded step wrote) in its gradient
    /// buffer, like PyTorch's `retain_grad`.
    ///
    /// Without it, the adjoint of each store takes the gradient of the element it wrote (so
    /// that an earlier, overwritten store gets none), and after backward the buffer of an
    /// array that launches stored into holds the gradient with respect to its value *before*
    /// those stores: zero where they overwrote it. Retaining costs a copy of the buffer.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    /// #[diff_kernel]
    /// fn square(x: &Array<f64>, y: &Array<f64>) {
    ///     let t = tid();
    ///     y[t] = x[t] * x[t];
    /// }
    /// #[diff_kernel]
    /// fn total(y: &Array<f64>, loss: &Array<f64>) {
    ///     loss.atomic_add(0, y[tid()]);
    /// }
    /// let x = Array::from_vec(vec![3.0]).requires_grad();
    /// let (y, loss) = (Array::zeros(1), Array::zeros(1));
    /// let mut tape = Tape::new();
    /// tape.launch(square, 1, (&x, &y));
    /// tape.launch(total, 1, (&y, &loss));
    /// tape.retain_grad(&y);
    /// tape.backward(&loss)?;
    /// assert_eq!(y.grad()?.to_vec(), vec![1.0]); // dloss/dy
    /// assert_eq!(x.grad()?.to_vec(), vec![6.0]);
    /// # Ok::<(), Error>(())
    /// ```
    pub fn retain_grad(&mut self, array: &dyn AnyArray) {
        self.retained.insert(array.id());
    }

    /// Number of recorded steps (launches and custom steps).
    pub fn len(&self) -> usize {
        self.records.len()
    }

    /// Whether nothing is recorded.
    pub fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// Turns the NaN/Inf check (the anomaly mode) on or off (off by default; it reads every
    /// written array after each step).
    ///
    /// When on, [`Tape::launch`] and [`Tape::record_fn`] check the arrays they wrote and keep
    /// the first non-finite value as an [`Error::NonFinite`] (kernel, launch, parameter,
    /// array, first bad index, pass `"forward"`): [`Tape::anomaly`] returns it, and
    /// [`Tape::backward`] and [`Tape::tangent`] return it before running anything (the
    /// integrators of `adflex-kernels` return it from the step that produced it). Backward
    /// checks the gradient buffers of the arrays each adjoint read (pass `"adjoint"`), and
    /// tangent the tangents each step wrote (pass `"tangent"`), and return the first bad one.
    /// Nothing panics.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    ///
    /// #[diff_kernel]
    /// fn root(x: &Array<f64>, y: &Array<f64>) {
    ///     let i = tid();
    ///     y[i] = sqrt(x[i]);
    /// }
    ///
    /// let x = Array::from_vec(vec![4.0, -1.0]).requires_grad().named("x");
    /// let y = Array::zeros(2).named("y");
    /// let mut tape = Tape::new();
    /// tape.check_finite(true);
    /// tape.launch(root, 2, (&x, &y));
    /// let err = tape.anomaly().unwrap().clone();
    /// assert!(matches!(err, Error::NonFinite { index: 1, pass: "forward", .. }), "{err}");
    /// assert_eq!(tape.backward(&y).unwrap_err(), err);
    /// ```
    pub fn check_finite(&mut self, on: bool) {
        self.check_finite = on;
    }

    /// The first NaN or infinity a recorded step wrote while [`Tape::check_finite`] was on
    /// (an [`Error::NonFinite`] naming the kernel, launch, array and index), if any.
    pub fn anomaly(&self) -> Option<&Error> {
        self.anomaly.as_ref()
    }

    /// Refuses custom step `i` if it works on [`Dual`](crate::Dual) arrays without having been
    /// declared [`CustomStep::dual_safe`]: its backward might compute in `f64` and drop their
    /// derivative parts, a silently wrong Hessian-vector product.
    fn dual_safe(&self, i: usize) -> Result<(), Error> {
        match &self.records[i].step {
            Step::Custom {
                dual_unsafe: true, ..
            } => Err(Error::InvalidInput {
                what: format!(
                    "custom step `{}` (#{i} on the tape)",
                    self.records[i].qualified()
                ),
                message: "it works on `Dual` arrays (a second-order pass) but was not declared \
                          dual-safe, so its backward may compute in `f64` and drop the \
                          derivative parts. If its forward, backward and tangent compute in \
                          the arrays' own scalar, declare it with `record_fn(..).dual_safe()`"
                    .into(),
            }),
            _ => Ok(()),
        }
    }

    /// `Err` with [`Tape::anomaly`], if there is one.
    fn no_anomaly(&self) -> Result<(), Error> {
        self.anomaly.clone().map_or(Ok(()), Err)
    }

    /// Runs `kernel` over thread ids `0..dim` with `args` (like [`crate::launch()`]) and records
    /// the launch with the version of every array it reads.
    ///
    /// In [`Tape::check_finite`] mode, a NaN or infinity the launch wrote becomes the tape's
    /// [`Tape::anomaly`] (returned by `backward` and `tangent`); nothing panics.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    ///
    /// #[diff_kernel]
    /// fn scale(x: &Array<f64>, s: f64, y: &Array<f64>) {
    ///     let t = tid();
    ///     y[t] = x[t] * s;
    /// }
    /// #[diff_kernel]
    /// fn total(y: &Array<f64>, loss: &Array<f64>) {
    ///     loss.atomic_add(0, y[tid()]);
    /// }
    ///
    /// let x = Array::from_vec(vec![1.0, 2.0]).requires_grad();
    /// let (y, loss) = (Array::zeros(2), Array::zeros(1));
    /// let mut tape = Tape::new();
    /// tape.launch(scale, 2, (&x, 3.0, &y));
    /// tape.launch(total, 2, (&y, &loss));
    /// tape.backward(&loss)?;
    /// assert_eq!(x.grad()?.to_vec(), vec![3.0, 3.0]);
    /// # Ok::<(), Error>(())
    /// ```
    pub fn launch<K, A>(&mut self, kernel: K, dim: usize, args: A)
    where
        K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
    {
        if !self.recording && !self.check_finite {
            self.unrecorded += 1;
            return crate::launch::launch(kernel, dim, args);
        }
        let launch = bind(kernel, args);
        let (reads, writes) = uses(launch.params(), &launch.arrays());
        launch.run(Mode::Forward, dim);
        self.push(Record {
            step: Step::Launch { launch, dim },
            scope: self.scope_path(),
            reads,
            writes,
        });
    }

    /// Runs `forward` now and records it as a custom step reading `inputs` and writing
    /// `outputs`; `backward` runs in its place during [`Tape::backward`].
    ///
    /// `forward` computes the outputs on the host (e.g. a linear solve). `backward` must read
    /// the gradient of each output (`grad_buffer()`, which is `None` when nothing downstream
    /// needs it) and **add** into the gradient of each input (`grad_buffer()`, `None` when the
    /// input needs none). Capture handles (`Array::clone`) in it. The step takes part in
    /// skipping and in the version check like a launch (its inputs appear as parameters
    /// `input 0`, `input 1`, ...). Give it a tangent with [`CustomStep::with_tangent`] to use
    /// it in [`Tape::tangent`].
    ///
    /// `backward` returns `Ok(())`, or an [`Error`] when it cannot produce a right gradient
    /// (e.g. its adjoint linear solve did not converge): [`Tape::backward`] then stops and
    /// returns that error with the step's name (`scope/name`) and position on the tape in its
    /// context ([`Error::in_context`]); the gradients accumulated so far are incomplete.
    ///
    /// Like [`Tape::launch`] in [`Tape::check_finite`] mode: a non-finite output becomes the
    /// tape's [`Tape::anomaly`].
    /// See the example on [`Tape`].
    pub fn record_fn(
        &mut self,
        name: impl Into<String>,
        inputs: &[&dyn AnyArray],
        outputs: &[&dyn AnyArray],
        forward: impl FnOnce(),
        backward: impl FnMut() -> Result<(), Error> + Send + Sync + 'static,
    ) -> CustomStep<'_> {
        if !self.recording && !self.check_finite {
            self.unrecorded += 1;
            forward();
            return CustomStep {
                tape: self,
                index: usize::MAX,
            };
        }
        let side = |arrays: &[&dyn AnyArray], what: &str| {
            arrays
                .iter()
                .enumerate()
                .map(|(i, a)| Use::new(format!("{what} {i}").into(), *a, false))
                .collect::<Vec<_>>()
        };
        let (reads, writes) = (side(inputs, "input"), side(outputs, "output"));
        let dual = inputs.iter().chain(outputs).any(|a| a.is_dual());
        forward();
        let index = self.push(Record {
            step: Step::Custom {
                name: name.into(),
                backward: Box::new(backward),
                tangent: None,
                dual_unsafe: dual,
            },
            scope: self.scope_path(),
            reads,
            writes,
        });
        CustomStep { tape: self, index }
    }

    /// Pushes a record (whose step just ran) and runs the forward NaN/Inf check; returns its
    /// index.
    fn push(&mut self, mut record: Record) -> usize {
        for u in &mut record.writes {
            u.after = u.array.version();
        }
        let index = self.records.len() + self.unrecorded;
        self.records.push(record);
        if self.check_finite && self.anomaly.is_none() {
            let r = self.records.last().expect("just pushed");
            for u in &r.writes {
                if let Some(i) = u.array.first_non_finite() {
                    self.anomaly = Some(r.non_finite(index, u, i, "forward"));
                    break;
                }
            }
        }
        if !self.recording {
            // Checked, not kept (`check_finite` on a `no_grad` tape).
            self.records.pop();
            self.unrecorded += 1;
            return usize::MAX;
        }
        index
    }

    /// Runs `f` inside a named scope: steps recorded in it are shown as `name/kernel` in errors
    /// and grouped under `name` in [`Tape::to_dot`]. Scopes nest (`outer/inner/kernel`).
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// let mut tape = Tape::new();
    /// let n = tape.scope("step 3", |tape| tape.len());
    /// assert_eq!(n, 0);
    /// ```
    pub fn scope<R>(&mut self, name: impl Into<String>, f: impl FnOnce(&mut Tape) -> R) -> R {
        self.push_scope(name);
        let r = f(self);
        self.pop_scope();
        r
    }

    /// Enters a named scope (see [`Tape::scope`]); pair with [`Tape::pop_scope`].
    pub fn push_scope(&mut self, name: impl Into<String>) {
        self.scopes.push(name.into());
    }

    /// Leaves the innermost scope (no-op outside any scope).
    pub fn pop_scope(&mut self) {
        self.scopes.pop();
    }

    fn scope_path(&self) -> Option<String> {
        (!self.scopes.is_empty()).then(|| self.scopes.join("/"))
    }

    pub(crate) fn writes(&self, id: u64) -> bool {
        self.records
            .iter()
            .any(|r| r.writes.iter().any(|u| u.id == id))
    }

    /// Forward reach: which steps read an array that depends on a source (an array that
    /// requires grad, or one of `sources`), and the set of such arrays.
    fn forward_flags(&self, sources: &HashSet<u64>) -> (Vec<bool>, HashSet<u64>) {
        let mut f = sources.clone();
        for r in &self.records {
            for u in r.reads.iter().chain(&r.writes) {
                if u.array.is_requires_grad() {
                    f.insert(u.id);
                }
            }
        }
        let mut fwd = vec![false; self.records.len()];
        for (i, r) in self.records.iter().enumerate() {
            if r.reads.iter().any(|u| f.contains(&u.id)) {
                fwd[i] = true;
                f.extend(r.writes.iter().map(|u| u.id));
            }
        }
        (fwd, f)
    }

    /// The tape's inputs: every array a recorded step read that no earlier recorded step
    /// wrote, once each, with the first step (its name, `scope/name` inside a scope) and
    /// parameter that read it. For checks such as "every parameter this force reads is one the
    /// solver knows about" (`ImplicitEuler` refuses a force that reads an array requiring grad
    /// that its parameter visitor does not list).
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    ///
    /// #[diff_kernel]
    /// fn scale(x: &Array<f64>, k: &Array<f64>, y: &Array<f64>) {
    ///     let i = tid();
    ///     y[i] = x[i] * k[0];
    /// }
    ///
    /// let x = Array::from_vec(vec![1.0, 2.0]).named("x");
    /// let k = Array::from_vec(vec![3.0]).named("k");
    /// let (y, z) = (Array::zeros(2), Array::zeros(2));
    /// let mut tape = Tape::new();
    /// tape.launch(scale, 2, (&x, &k, &y));
    /// tape.launch(scale, 2, (&y, &k, &z)); // reads y, written above: not an input
    /// let inputs: Vec<String> = tape.inputs().iter().map(|i| i.array.label()).collect();
    /// assert_eq!(inputs, ["x", "k"]);
    /// assert_eq!(tape.inputs()[1].param, "k");
    /// ```
    pub fn inputs(&self) -> Vec<TapeInput> {
        let (mut written, mut seen) = (HashSet::new(), HashSet::new());
        let mut out = Vec::new();
        for r in &self.records {
            for u in &r.reads {
                if !written.contains(&u.id) && seen.insert(u.id) {
                    out.push(TapeInput {
                        step: r.qualified(),
                        param: u.param.to_string(),
                        array: u.array.boxed(),
                    });
                }
            }
            written.extend(r.writes.iter().map(|u| u.id));
        }
        out
    }

    /// Whether the value of `output` depends on `input` through the recorded steps (reads
    /// and writes, whatever the values; `output` itself counts). For a check such as "the loss
    /// does not use this parameter" before an optimization.
    pub fn depends(&self, output: &dyn AnyArray, input: &dyn AnyArray) -> bool {
        let mut needed = HashSet::from([output.id()]);
        for r in self.records.iter().rev() {
            if r.writes.iter().any(|u| needed.contains(&u.id)) {
                needed.extend(r.reads.iter().map(|u| u.id));
            }
        }
        needed.contains(&input.id())
    }

    /// The ids of the arrays on the tape that depend on an array that requires grad or on one
    /// of `sources` (which are included).
    pub(crate) fn forward_reach(&self, sources: &HashSet<u64>) -> HashSet<u64> {
        self.forward_flags(sources).1
    }

    fn check_versions(&self, i: usize) -> Result<(), Error> {
        let r = &self.records[i];
        for u in &r.reads {
            let now = u.array.version();
            // An input that is also an output (a custom step updating it in place) must be
            // as the step left it.
            let expected = r
                .writes
                .iter()
                .find(|w| w.id == u.id)
                .map_or(u.version, |w| w.after);
            if now != expected {
                return Err(Error::ArrayChanged {
                    kernel: r.qualified(),
                    launch: i,
                    param: u.param.to_string(),
                    array: u.array.label(),
                    recorded: expected,
                    now,
                });
            }
        }
        Ok(())
    }

    /// The labels of the arrays with these ids (for errors).
    fn labels(&self, ids: &HashSet<u64>) -> String {
        let mut seen = HashSet::new();
        let mut out = Vec::new();
        for r in &self.records {
            for u in r.reads.iter().chain(&r.writes) {
                if ids.contains(&u.id) && seen.insert(u.id) {
                    out.push(format!("`{}`", u.array.label()));
                }
            }
        }
        out.join(", ")
    }

    /// Refuses a backward pass through an array that was written off the tape (on the host)
    /// after a recorded step wrote it and before a later recorded step used it: the tape
    /// cannot see that write, so the writer's adjoint would receive gradient for values that
    /// were replaced.
    fn check_off_tape_writes(&self, run: &[bool], consume: &[bool]) -> Result<(), Error> {
        // id -> the chain of on-tape writes of the array: its version right after the last
        // one, the last writer whose adjoint runs (if any), and whether a host write broke
        // the chain after such a writer.
        struct Chain {
            after: u64,
            live: Option<usize>,
            cut: bool,
        }
        let mut chains: std::collections::HashMap<u64, Chain> = Default::default();
        for (i, r) in self.records.iter().enumerate() {
            for u in r.reads.iter().chain(&r.writes) {
                if let Some(c) = chains.get_mut(&u.id) {
                    if u.version != c.after && c.live.is_some() {
                        c.cut = true;
                    }
                    if let (true, true, Some(w)) = (c.cut, run[i], c.live) {
                        return Err(Error::WrittenOffTape {
                            array: u.array.label(),
                            writer: self.records[w].qualified(),
                            writer_launch: w,
                            user: r.qualified(),
                            user_launch: i,
                        });
                    }
                }
            }
            for u in &r.writes {
                let runs = run[i] || consume[i];
                let (live, cut) = match chains.get(&u.id) {
                    // A writer whose adjoint runs starts a fresh chain: what it overwrote
                    // or accumulated onto is checked at its own read above.
                    _ if runs => (Some(i), false),
                    Some(c) => (c.live, c.cut),
                    None => (None, false),
                };
                chains.insert(
                    u.id,
                    Chain {
                        after: u.after,
                        live,
                        cut,
                    },
                );
            }
        }
        Ok(())
    }

    /// Reach analysis and version checks for a backward pass from `seeds`. With
    /// `require_reach`, a pass that reaches no array requiring grad (nor a source) is an error.
    fn plan(
        &self,
        seeds: &HashSet<u64>,
        sources: &HashSet<u64>,
        require_reach: bool,
    ) -> Result<Plan, Error> {
        let (fwd, f) = self.forward_flags(sources);
        let mut b = seeds.clone();
        let mut run = vec![false; self.records.len()];
        let mut consume = vec![false; self.records.len()];
        for (i, r) in self.records.iter().enumerate().rev() {
            if fwd[i] && r.writes.iter().any(|u| b.contains(&u.id)) {
                run[i] = true;
                b.extend(r.reads.iter().map(|u| u.id));
            } else if r.writes.iter().any(|u| !u.atomic && b.contains(&u.id)) {
                consume[i] = true;
            }
        }
        for i in (0..self.records.len()).filter(|&i| run[i]) {
            self.check_versions(i)?;
        }
        self.check_off_tape_writes(&run, &consume)?;
        let grads: HashSet<u64> = f.intersection(&b).copied().collect();
        if require_reach {
            let leaves: HashSet<u64> = self
                .records
                .iter()
                .flat_map(|r| &r.reads)
                .filter(|u| u.array.is_requires_grad())
                .map(|u| u.id)
                .chain(sources.iter().copied())
                .collect();
            let leaf = |id: &u64| leaves.contains(id);
            if !grads.iter().any(leaf) {
                return Err(Error::NothingToDifferentiate {
                    seeds: self.labels(seeds),
                });
            }
        }
        let zeroed = self
            .records
            .iter()
            .flat_map(|r| &r.writes)
            .map(|u| u.id)
            .filter(|id| grads.contains(id) && !seeds.contains(id))
            .collect();
        Ok(Plan {
            run,
            consume,
            grads,
            zeroed,
        })
    }

    /// Allocates the gradient buffers of the plan and runs its adjoints in reverse order.
    fn execute(&mut self, plan: &Plan) -> Result<(), Error> {
        for (i, _) in plan.run.iter().enumerate().filter(|(_, &run)| run) {
            self.dual_safe(i)?;
        }
        // Each buffer once: zeroing one again would be a second pass over its memory.
        let mut seen = HashSet::new();
        let mut reset: Vec<&dyn AnyArray> = Vec::new();
        for (r, _) in self.records.iter().zip(&plan.run).filter(|(_, &run)| run) {
            for u in r.reads.iter().chain(&r.writes) {
                let id = u.id;
                if !seen.insert(id) {
                    continue;
                }
                if plan.zeroed.contains(&id) {
                    reset.push(&*u.array);
                } else if plan.grads.contains(&id) {
                    u.array.ensure_grad();
                }
            }
        }
        zero_grads(&reset);
        self.last = BackwardStats::default();
        // Retained gradients, copied before the adjoint of the step that wrote them last.
        let mut kept: Vec<(Box<dyn AnyArray>, Box<dyn AnyArray>)> = Vec::new();
        for i in (0..self.records.len()).rev() {
            if plan.consume[i] {
                // Only to take the gradient of what the step overwrote (see `Plan::consume`).
                self.last.run += 1;
                let r = &self.records[i];
                match &r.step {
                    Step::Launch { .. } => r.run_launch(i, Mode::Adjoint)?,
                    Step::Custom { .. } => {
                        r.clear_replaced_grads();
                    }
                }
                continue;
            }
            if !plan.run[i] {
                self.last.skipped += 1;
                continue;
            }
            self.last.run += 1;
            for u in &self.records[i].writes {
                let id = u.id;
                if self.retained.contains(&id) && !kept.iter().any(|(a, _)| a.id() == id) {
                    if let Some(g) = u.array.grad_any() {
                        kept.push((u.array.boxed(), g.deep_clone_any()));
                    }
                }
            }
            match &mut self.records[i].step {
                Step::Launch { .. } => self.records[i].run_launch(i, Mode::Adjoint)?,
                Step::Custom { backward, .. } => {
                    if let Err(e) = backward() {
                        return Err(self.records[i].custom_error(i, e));
                    }
                }
            }
            let r = &self.records[i];
            if let Step::Custom { .. } = r.step {
                r.clear_replaced_grads();
            }
            if self.check_finite {
                for u in &r.reads {
                    if let Some(k) = u.array.grad_any().and_then(|g| g.first_non_finite()) {
                        return Err(r.non_finite(i, u, k, "adjoint"));
                    }
                }
            }
        }
        for (a, copy) in kept {
            if let Some(g) = a.grad_any() {
                g.copy_from(&*copy);
            }
        }
        Ok(())
    }

    /// Backpropagates from `loss`: sets every component of every element of `loss.grad` to 1
    /// (so a `loss` of several elements is differentiated as their sum), then runs the adjoints
    /// of the recorded steps in reverse order, accumulating into gradient buffers.
    ///
    /// Gradient buffers are allocated for every array on a path from an array that requires
    /// grad to `loss`. Those of intermediates (arrays some recorded step wrote) start from zero
    /// at every backward pass; those of the other arrays (the leaves: parameters, initial
    /// states) accumulate, like PyTorch's `.grad` (clear them with [`Tape::zero`]). Steps that
    /// cannot contribute are skipped ([`Tape::last_backward`]).
    ///
    /// Errors: [`Error::NotOnTape`] if no recorded step wrote `loss`; [`Error::ArrayChanged`]
    /// (before anything runs) if an array read by a step whose adjoint would run was written
    /// since; [`Error::NonFinite`] in [`Tape::check_finite`] mode; the error of a custom
    /// step's backward (e.g. [`Error::NotConverged`]), see [`Tape::record_fn`].
    pub fn backward<T: Element>(&mut self, loss: &Array<T>) -> Result<(), Error> {
        self.backward_sources(loss, &HashSet::new())
    }

    /// [`Tape::backward`] with extra arrays treated as requiring grad (by id).
    pub(crate) fn backward_sources<T: Element>(
        &mut self,
        loss: &Array<T>,
        sources: &HashSet<u64>,
    ) -> Result<(), Error> {
        self.require_recording("Tape::backward")?;
        if !self.writes(loss.id()) {
            return Err(Error::NotOnTape {
                array: loss.label(),
            });
        }
        self.no_anomaly()?;
        let plan = self.plan(&HashSet::from([loss.id()]), sources, sources.is_empty())?;
        loss.ensure_grad().fill(ones::<T>());
        self.execute(&plan)
    }

    /// Backpropagates from `seeds` whose gradient buffers the caller has already written
    /// (e.g. a vector-Jacobian product with a chosen cotangent). Otherwise like
    /// [`Tape::backward`]; the seeds' gradients are not zeroed (other intermediates' are).
    ///
    /// Errors: [`Error::NotOnTape`] if no recorded step wrote a seed, [`Error::NoGrad`] if a
    /// seed has no gradient buffer, and the errors of [`Tape::backward`].
    pub fn backward_with(&mut self, seeds: &[&dyn AnyArray]) -> Result<(), Error> {
        self.require_recording("Tape::backward_with")?;
        for s in seeds {
            if !self.writes(s.id()) {
                return Err(Error::NotOnTape { array: s.label() });
            }
            if !s.has_grad() {
                return Err(Error::NoGrad { array: s.label() });
            }
        }
        self.no_anomaly()?;
        let ids = seeds.iter().map(|s| s.id()).collect();
        let plan = self.plan(&ids, &HashSet::new(), true)?;
        self.execute(&plan)
    }

    /// [`Tape::backward_with`] without the checks, with extra sources (by id).
    /// The ids of every array a recorded step writes.
    pub(crate) fn written_ids(&self) -> HashSet<u64> {
        self.records
            .iter()
            .flat_map(|r| r.writes.iter().map(|u| u.id))
            .collect()
    }

    pub(crate) fn backward_seeded(
        &mut self,
        seeds: &[&dyn AnyArray],
        sources: &HashSet<u64>,
    ) -> Result<(), Error> {
        self.require_recording("Tape::vjp")?;
        let seeds = seeds.iter().map(|s| s.id()).collect();
        let plan = self.plan(&seeds, sources, false)?;
        self.execute(&plan)
    }

    /// What the last backward pass ran and skipped.
    pub fn last_backward(&self) -> BackwardStats {
        self.last
    }

    /// Forward mode over the whole tape: re-runs every recorded step's tangent, in order.
    ///
    /// Set the tangents of the inputs first ([`Array::set_tangent`]); arrays without a tangent
    /// buffer count as constant. Every array a recorded step writes gets a zeroed tangent
    /// buffer before the pass (its tangent is an output, so a tangent set on it is replaced).
    /// Only tangent kernels run: the forward results, versions and accumulations stay as they
    /// are.
    ///
    /// Errors: [`Error::ArrayChanged`] if any array a step read was written since it was
    /// recorded, [`Error::Other`] if a custom step has no tangent, [`Error::NonFinite`] in
    /// [`Tape::check_finite`] mode.
    pub fn tangent(&mut self) -> Result<(), Error> {
        self.require_recording("Tape::tangent")?;
        self.no_anomaly()?;
        for i in 0..self.records.len() {
            self.check_versions(i)?;
            self.dual_safe(i)?;
            if let Step::Custom {
                name,
                tangent: None,
                ..
            } = &self.records[i].step
            {
                return Err(Error::Other(format!(
                    "custom step `{name}` (#{i} on the tape) has no tangent: give one with \
                     `record_fn(..).with_tangent(..)`"
                )));
            }
        }
        let mut seen = HashSet::new();
        for r in &self.records {
            for u in &r.writes {
                if seen.insert(u.id) {
                    u.array.reset_tangent();
                }
            }
        }
        for i in 0..self.records.len() {
            match &mut self.records[i].step {
                Step::Launch { .. } => self.records[i].run_launch(i, Mode::Tangent)?,
                Step::Custom { tangent, .. } => {
                    if let Err(e) = (tangent.as_mut().expect("checked above"))() {
                        return Err(self.records[i].custom_error(i, e));
                    }
                }
            }
            if self.check_finite {
                let r = &self.records[i];
                for u in &r.writes {
                    if let Some(k) = u.array.tangent_any().and_then(|t| t.first_non_finite()) {
                        return Err(r.non_finite(i, u, k, "tangent"));
                    }
                }
            }
        }
        Ok(())
    }

    /// Zeroes the gradient buffers of every array on the tape (those that requires grad
    /// included), keeping the records: call it between two backward passes.
    pub fn zero(&mut self) {
        for r in &self.records {
            for u in r.reads.iter().chain(&r.writes) {
                u.array.zero_grad();
            }
        }
    }

    /// Zeroes the gradients (like [`Tape::zero`]) and forgets every record.
    pub fn reset(&mut self) {
        self.zero();
        self.records.clear();
        self.anomaly = None;
        self.last = BackwardStats::default();
        self.unrecorded = 0;
    }

    /// The tape as a Graphviz DOT graph: a box per step (`#index name`, `dim`, scope; steps of
    /// one scope grouped in a cluster), an ellipse per array (its label; filled if it requires
    /// grad), an edge array -> step per read and step -> array per write (dashed for
    /// `atomic_*`), each labelled with the parameter.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// let dot = Tape::new().to_dot();
    /// assert!(dot.starts_with("digraph tape {"));
    /// ```
    pub fn to_dot(&self) -> String {
        fn esc(s: &str) -> String {
            s.replace('\\', "\\\\")
                .replace('"', "\\\"")
                .replace('\n', "\\n")
        }
        let mut out =
            String::from("digraph tape {\n  rankdir=TB;\n  node [fontname=\"Helvetica\"];\n");
        let mut seen = HashSet::new();
        for r in &self.records {
            for u in r.reads.iter().chain(&r.writes) {
                if seen.insert(u.id) {
                    let fill = if u.array.is_requires_grad() {
                        ", style=filled, fillcolor=lightblue"
                    } else {
                        ""
                    };
                    let _ = writeln!(
                        out,
                        "  a{} [shape=ellipse, label=\"{}\"{fill}];",
                        u.id,
                        esc(&u.array.label())
                    );
                }
            }
        }
        let mut groups: Vec<(Option<&str>, Vec<usize>)> = Vec::new();
        for (i, r) in self.records.iter().enumerate() {
            let s = r.scope.as_deref();
            match groups.iter_mut().find(|(g, _)| *g == s) {
                Some((_, v)) => v.push(i),
                None => groups.push((s, vec![i])),
            }
        }
        for (k, (scope, idx)) in groups.iter().enumerate() {
            let indent = if scope.is_some() { "    " } else { "  " };
            if let Some(s) = scope {
                let _ = writeln!(out, "  subgraph cluster_{k} {{\n    label=\"{}\";", esc(s));
            }
            for &i in idx {
                let r = &self.records[i];
                let mut label = format!("#{i} {}", r.name());
                let style = match &r.step {
                    Step::Launch { dim, .. } => {
                        let _ = write!(label, "\ndim {dim}");
                        ""
                    }
                    Step::Custom { .. } => {
                        label.push_str("\n(custom)");
                        ", style=rounded"
                    }
                };
                if let Some(s) = scope {
                    let _ = write!(label, "\nscope: {s}");
                }
                let _ = writeln!(
                    out,
                    "{indent}l{i} [shape=box{style}, label=\"{}\"];",
                    esc(&label)
                );
            }
            if scope.is_some() {
                out.push_str("  }\n");
            }
        }
        for (i, r) in self.records.iter().enumerate() {
            for u in &r.reads {
                let _ = writeln!(out, "  a{} -> l{i} [label=\"{}\"];", u.id, esc(&u.param));
            }
            for u in &r.writes {
                let dash = if u.atomic { ", style=dashed" } else { "" };
                let _ = writeln!(
                    out,
                    "  l{i} -> a{} [label=\"{}\"{dash}];",
                    u.id,
                    esc(&u.param)
                );
            }
        }
        out.push_str("}\n");
        out
    }
}

/// A custom step just recorded by [`Tape::record_fn`]; lets you attach its tangent.
pub struct CustomStep<'t> {
    tape: &'t mut Tape,
    index: usize,
}

impl CustomStep<'_> {
    /// Declares that the step's forward, backward and tangent compute in the arrays' own
    /// scalar type (generic code, no detour through `f64`), so that run on
    /// [`Dual`](crate::Dual) arrays they carry derivative parts and a Hessian-vector product
    /// ([`crate::second_order`]) may go through the step. Without it, a step on `Dual` arrays
    /// refuses to run backward or forward-mode.
    pub fn dual_safe(self) -> Self {
        if let Some(Step::Custom { dual_unsafe, .. }) =
            self.tape.records.get_mut(self.index).map(|r| &mut r.step)
        {
            *dual_unsafe = false;
        }
        self
    }

    /// The forward-mode rule of the step for [`Tape::tangent`]: it must read the tangents of
    /// the inputs (`tangent_buffer()`, `None` = zero) and write those of the outputs (whose
    /// buffers exist and are zero when it runs).
    ///
    /// The closure returns `()`, or a `Result<(), Error>` when it can fail (e.g. its linear
    /// solve did not converge): [`Tape::tangent`] then stops and returns that error with the
    /// step's name and position on the tape in its context, like [`Tape::backward`].
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// let x = Array::from_vec(vec![2.0_f64]);
    /// let y = Array::<f64>::zeros(1);
    /// let mut tape = Tape::new();
    /// tape.record_fn("fails", &[&x], &[&y], || {}, || Ok(()))
    ///     .with_tangent(|| Err(Error::Other("no convergence".into())));
    /// let err = tape.tangent().unwrap_err().to_string();
    /// assert!(err.contains("no convergence") && err.contains("fails"), "{err}");
    /// ```
    pub fn with_tangent<O: StepOutcome>(
        self,
        mut tangent: impl FnMut() -> O + Send + Sync + 'static,
    ) {
        if let Some(Step::Custom { tangent: t, .. }) =
            self.tape.records.get_mut(self.index).map(|r| &mut r.step)
        {
            *t = Some(Box::new(move || tangent().into_result()));
        }
    }
}

/// What a custom step's tangent returns: `()` (it cannot fail) or `Result<(), Error>`.
pub trait StepOutcome {
    /// As a result.
    fn into_result(self) -> Result<(), Error>;
}

impl StepOutcome for () {
    fn into_result(self) -> Result<(), Error> {
        Ok(())
    }
}

impl StepOutcome for Result<(), Error> {
    fn into_result(self) -> Result<(), Error> {
        self
    }
}

/// The element with every differentiable component 1 (the seed of a loss).
pub(crate) fn ones<T: Element>() -> T {
    let mut one = T::zeroed();
    for k in 0..T::DIM {
        one.set_component(k, 1.0);
    }
    one
}

/// Zeroes the gradient buffers of `arrays` (allocating them zeroed when new), on the pool's
/// threads when there is enough to share: a rollout's intermediate gradients are tens of
/// megabytes, a serial pass over them a few percent of a backward.
fn zero_grads(arrays: &[&dyn AnyArray]) {
    use rayon::prelude::*;
    if rayon::current_num_threads() > 1 && arrays.len() > 1 {
        // Workers lingering after the forward's last launch take this work at once.
        crate::region::Region::host().pool(|| {
            arrays
                .par_iter()
                .with_min_len(4)
                .for_each(|a| a.reset_grad())
        });
    } else {
        arrays.iter().for_each(|a| a.reset_grad());
    }
}
