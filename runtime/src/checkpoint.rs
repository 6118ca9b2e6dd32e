//! Checkpointing: gradients of long rollouts without keeping every step on a tape.
//!
//! A plain tape keeps every intermediate array of every step alive until `backward`: memory
//! O(T) states for T steps. [`checkpointed`] runs the rollout forward keeping only a copy of
//! every k-th state, then goes backward segment by segment: it re-runs the k steps of a segment
//! from its checkpoint on a fresh tape, seeds the gradient of the segment's last state with the
//! gradient of the next segment's first state, and backpropagates. Live memory is O(T/k + k)
//! states (k near sqrt(T) minimizes it), for about T extra steps of compute.
//!
//! Launches are deterministic, so the recomputed segments give the same bits as the first run
//! and the gradients equal a plain tape's bit for bit.

use std::collections::HashSet;

use crate::array::{AnyArray, Array, Element};
use crate::error::Error;
use crate::tape::{ones, Tape};

/// A simulation state that can be checkpointed: the arrays it holds, and a deep copy.
///
/// Everything a step carries to the next must be in the state. Parameters shared by all steps
/// (stiffnesses, controls) are captured by the step closure instead, and receive gradients
/// from every segment.
///
/// ```
/// use adflex_runtime::checkpoint::Checkpoint;
/// use adflex_runtime::{AnyArray, Array, Vec3};
/// struct State { x: Array<Vec3>, v: Array<Vec3> }
/// impl Checkpoint for State {
///     fn arrays(&self) -> Vec<&dyn AnyArray> { vec![&self.x, &self.v] }
///     fn snapshot(&self) -> Self { State { x: self.x.deep_clone(), v: self.v.deep_clone() } }
/// }
/// ```
pub trait Checkpoint: Sized {
    /// The state's arrays, always in the same order and with the same lengths (distinct arrays).
    fn arrays(&self) -> Vec<&dyn AnyArray>;
    /// A deep copy: new arrays with the same values and no gradients
    /// ([`Array::deep_clone`] on each).
    fn snapshot(&self) -> Self;
}

impl<T: Element> Checkpoint for Array<T> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        vec![self]
    }
    fn snapshot(&self) -> Self {
        self.deep_clone()
    }
}

impl<S: Checkpoint> Checkpoint for Vec<S> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        self.iter().flat_map(Checkpoint::arrays).collect()
    }
    fn snapshot(&self) -> Self {
        self.iter().map(Checkpoint::snapshot).collect()
    }
}

macro_rules! tuple_checkpoint {
    ($($n:tt $t:ident),*) => {
        impl<$($t: Checkpoint),*> Checkpoint for ($($t,)*) {
            fn arrays(&self) -> Vec<&dyn AnyArray> {
                let mut v = Vec::new();
                $(v.extend(self.$n.arrays());)*
                v
            }
            fn snapshot(&self) -> Self {
                ($(self.$n.snapshot(),)*)
            }
        }
    };
}
tuple_checkpoint!(0 A, 1 B);
tuple_checkpoint!(0 A, 1 B, 2 C);
tuple_checkpoint!(0 A, 1 B, 2 C, 3 D);

/// What [`checkpointed`] returns.
pub struct Rollout<L> {
    /// The loss array (its value is the loss of the rollout).
    pub loss: Array<L>,
    /// States kept as checkpoints, the initial state included (`ceil(steps / every)`).
    pub checkpoints: usize,
    /// Steps run in all (the forward sweep plus the recomputed segments), at most `2 * steps`.
    pub steps_run: usize,
}

impl<L: Element> std::fmt::Debug for Rollout<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Rollout")
            .field("loss", &self.loss)
            .field("checkpoints", &self.checkpoints)
            .field("steps_run", &self.steps_run)
            .finish()
    }
}

/// Which arrays of `s` count as sources (depend on something that requires grad).
fn flagged<S: Checkpoint>(s: &S, flags: &[bool]) -> HashSet<u64> {
    s.arrays()
        .iter()
        .zip(flags)
        .filter(|(_, &f)| f)
        .map(|(a, _)| a.id())
        .collect()
}

/// Runs `steps` steps of `step` from `initial`, then `loss` on the final state, and
/// backpropagates, keeping a checkpoint every `every` steps (see the [module docs](self)).
///
/// `step(tape, s)` records one step on `tape` and returns the next state (new arrays), or an
/// error (a solver that did not converge, an invalid input); `loss(tape, s)` records the loss
/// of the final state and returns the loss array (usually of length 1; it is seeded with ones
/// like [`Tape::backward`]). Both must be deterministic functions of the state and the
/// captured parameters, since segments are run twice.
///
/// Gradients accumulate, as with a plain tape, into the arrays of `initial` and the captured
/// arrays that require grad; they are bitwise equal to those of
/// `for _ in 0..steps { s = step(&mut tape, &s) }; tape.backward(&loss(&mut tape, &s))` when
/// those gradient buffers start at zero. Memory: O(steps / every + every) states.
///
/// Errors: the first error of `step` or `loss`, with the step index in its context
/// ([`Error::in_context`]: `"checkpointed rollout, step 7 of 20 (forward sweep)"`, or
/// `"(recomputing segment 6..9 for the backward pass)"` when it happens there), and those of
/// [`Tape::backward`] for each segment. Nothing panics; the rollout stops at the error, and
/// the gradients accumulated so far are incomplete.
///
/// ```
/// use adflex_runtime::prelude::*;
/// use adflex_runtime::checkpoint::checkpointed;
///
/// // x_{t+1} = 2 x_t on the host, loss = x_T: d loss / d x_0 = 2^T.
/// let double = |tape: &mut Tape, x: &Array<f64>| {
///     let y = Array::<f64>::zeros(1);
///     let (xb, yb) = (x.clone(), y.clone());
///     tape.record_fn("double", &[x], &[&y], || y.set(0, 2.0 * x.get(0)), move || {
///         if let Some(g) = xb.grad_buffer() {
///             let d = yb.grad_buffer().unwrap().get(0);
///             g.modify(|g| g[0] += 2.0 * d);
///         }
///         Ok(())
///     });
///     Ok(y)
/// };
/// let x0 = Array::from_vec(vec![1.0f64]).requires_grad();
/// let out = checkpointed(&x0, 10, 3, double, |tape, x| double(tape, x)).unwrap();
/// assert_eq!(out.loss.get(0), 2048.0);
/// assert_eq!(x0.grad().unwrap().get(0), 2048.0);
/// ```
pub fn checkpointed<S, L, F, G>(
    initial: &S,
    steps: usize,
    every: usize,
    mut step: F,
    mut loss: G,
) -> Result<Rollout<L>, Error>
where
    S: Checkpoint,
    L: Element,
    F: FnMut(&mut Tape, &S) -> Result<S, Error>,
    G: FnMut(&mut Tape, &S) -> Result<Array<L>, Error>,
{
    assert!(every >= 1, "checkpointed: `every` must be at least 1");
    run(
        initial,
        steps,
        every,
        &mut |tape, s, _| step(tape, s),
        Loss::Final(&mut loss),
        &Progress::hidden(),
    )
}

/// Checkpointed rollouts with a loss on every state, the step index, and progress: the
/// general form of [`checkpointed`].
///
/// `step(tape, s_t, t)` records step `t` (from 0) and returns `s_{t+1}` (or an error);
/// `loss(tape, s_t, t, acc)` is called on every state `s_0 ..= s_T` and records the kernels
/// that *add* that state's loss into `acc` (with `atomic_add`; doing nothing is fine), or
/// returns an error. An error comes out of [`Checkpointed::run`] with the step index in its
/// context (see [`checkpointed`]). The
/// rollout's loss is the sum of everything added: a trajectory loss, a loss of the final
/// state only (`if t == steps`), or both. The gradients are those of a plain tape that adds
/// every loss into one array, bit for bit; the loss value may differ from such a tape's in
/// the last bits (segments are summed separately).
///
/// ```
/// use adflex_runtime::prelude::*;
/// use adflex_runtime::checkpoint::Checkpointed;
///
/// #[adflex_macros::diff_kernel]
/// fn scale<R: Real>(x: &Array<R>, c: R, y: &Array<R>) { let i = tid(); y[i] = c * x[i]; }
/// #[adflex_macros::diff_kernel]
/// fn add_into<R: Real>(x: &Array<R>, acc: &Array<R>) { acc.atomic_add(0, x[tid()]); }
///
/// // x_{t+1} = 1.5 x_t for 6 steps; loss = sum over t of x_t: d loss / d x_0 = sum 1.5^t.
/// let x0 = Array::from_vec(vec![1.0f64]).requires_grad();
/// let out = Checkpointed::new(6)
///     .every(2)
///     .run(
///         &x0,
///         |tape, x, _t| {
///             let y = Array::zeros(1);
///             tape.launch(scale, 1, (x, 1.5, &y));
///             Ok(y)
///         },
///         |tape, x, _t, acc| {
///             tape.launch(add_into, 1, (x, acc));
///             Ok(())
///         },
///     )
///     .unwrap();
/// let expected: f64 = (0..=6).map(|t| 1.5f64.powi(t)).sum();
/// assert!((out.loss.get(0) - expected).abs() < 1e-12);
/// assert!((x0.grad().unwrap().get(0) - expected).abs() < 1e-12);
/// ```
#[derive(Clone, Debug)]
pub struct Checkpointed {
    steps: usize,
    every: usize,
    loss_len: usize,
    progress: Option<String>,
}

impl Checkpointed {
    /// A rollout of `steps` steps with a checkpoint every `ceil(sqrt(steps))` steps (the memory
    /// optimum), a loss accumulator of one element, and no progress bar.
    pub fn new(steps: usize) -> Self {
        Checkpointed {
            steps,
            every: (steps as f64).sqrt().ceil().max(1.0) as usize,
            loss_len: 1,
            progress: None,
        }
    }

    /// A checkpoint every `every` steps (at least 1; panics on 0).
    pub fn every(mut self, every: usize) -> Self {
        assert!(every >= 1, "Checkpointed::every: must be at least 1");
        self.every = every;
        self
    }

    /// Elements of the loss accumulator `acc` (default 1; the loss is the sum of them all).
    pub fn loss_len(mut self, len: usize) -> Self {
        self.loss_len = len;
        self
    }

    /// Shows a progress bar on the terminal (stderr; hidden when it is not a terminal) for the
    /// forward sweep and the backward segments, labelled `label`.
    pub fn progress(mut self, label: impl Into<String>) -> Self {
        self.progress = Some(label.into());
        self
    }

    /// Runs the rollout forward and backward (see the [type docs](Checkpointed)).
    ///
    /// Errors: those of `step` and `loss`, with the step index in their context (see
    /// [`checkpointed`]), and those of [`Tape::backward`] for each segment.
    pub fn run<S, L, F, G>(
        &self,
        initial: &S,
        mut step: F,
        mut loss: G,
    ) -> Result<Rollout<L>, Error>
    where
        S: Checkpoint,
        L: Element,
        F: FnMut(&mut Tape, &S, usize) -> Result<S, Error>,
        G: FnMut(&mut Tape, &S, usize, &Array<L>) -> Result<(), Error>,
    {
        let progress = match &self.progress {
            Some(label) => Progress::bar(label, 2 * self.steps),
            None => Progress::hidden(),
        };
        let out = run(
            initial,
            self.steps,
            self.every,
            &mut step,
            Loss::Every(&mut loss, self.loss_len),
            &progress,
        );
        progress.finish();
        out
    }
}

/// Where the loss of a rollout comes from.
enum Loss<'a, S, L> {
    /// One array computed from the final state ([`checkpointed`]).
    Final(&'a mut FinalLoss<'a, S, L>),
    /// Added into an accumulator of the given length on every state ([`Checkpointed`]).
    Every(&'a mut EveryLoss<'a, S, L>, usize),
}

/// The per-state loss of [`Checkpointed`]: `(tape, state, step, accumulator)`.
type EveryLoss<'a, S, L> = dyn FnMut(&mut Tape, &S, usize, &Array<L>) -> Result<(), Error> + 'a;

/// The loss of the final state of [`checkpointed`]: `(tape, state)`.
type FinalLoss<'a, S, L> = dyn FnMut(&mut Tape, &S) -> Result<Array<L>, Error> + 'a;

/// The step closure both entry points share: `(tape, state, step index)`.
type Step<'a, S> = dyn FnMut(&mut Tape, &S, usize) -> Result<S, Error> + 'a;

/// An optional terminal progress bar (indicatif).
struct Progress(Option<indicatif::ProgressBar>);

impl Progress {
    fn hidden() -> Self {
        Progress(None)
    }
    fn bar(label: &str, len: usize) -> Self {
        let bar = indicatif::ProgressBar::new(len as u64);
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{prefix} {msg:8} [{bar:30}] {pos}/{len} steps {elapsed} (eta {eta})",
        ) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(label.to_string());
        Progress(Some(bar))
    }
    fn phase(&self, msg: &'static str) {
        if let Some(b) = &self.0 {
            b.set_message(msg);
        }
    }
    fn tick(&self) {
        if let Some(b) = &self.0 {
            b.inc(1);
        }
    }
    fn finish(&self) {
        if let Some(b) = &self.0 {
            b.finish_and_clear();
        }
    }
}

/// The checkpointed rollout both entry points share (see the [module docs](self)).
fn run<S, L>(
    initial: &S,
    steps: usize,
    every: usize,
    step: &mut Step<'_, S>,
    mut loss: Loss<'_, S, L>,
    progress: &Progress,
) -> Result<Rollout<L>, Error>
where
    S: Checkpoint,
    L: Element,
{
    let starts: Vec<usize> = if steps == 0 {
        vec![0]
    } else {
        (0..steps).step_by(every).collect()
    };
    let last_start = *starts.last().expect("at least one segment");
    let mut steps_run = 0;

    // Forward sweep on throwaway tapes, keeping a snapshot at the start of every segment and,
    // for each of its arrays, whether it depends on something that requires grad.
    progress.phase("forward");
    let flags0: Vec<bool> = initial
        .arrays()
        .iter()
        .map(|a| a.is_requires_grad())
        .collect();
    let mut saved: Vec<(S, Vec<bool>)> = Vec::new();
    {
        let mut cur: Option<S> = None;
        let mut flags = flags0.clone();
        for t in 0..last_start {
            let s = cur.as_ref().unwrap_or(initial);
            let sources = flagged(s, &flags);
            let mut tape = Tape::new();
            let next = step(&mut tape, s, t).map_err(|e| at_step(e, "step", t, steps, None))?;
            steps_run += 1;
            progress.tick();
            let reach = tape.forward_reach(&sources);
            flags = next
                .arrays()
                .iter()
                .map(|a| reach.contains(&a.id()) || a.is_requires_grad())
                .collect();
            drop(tape);
            if (t + 1) % every == 0 {
                saved.push((next.snapshot(), flags.clone()));
            }
            cur = Some(next);
        }
    }

    // Backward, segment by segment, last first. Each segment adds its states' losses into a
    // fresh accumulator (seeded with ones), summed into `total` on the host.
    progress.phase("backward");
    let total = match &loss {
        Loss::Every(_, len) => Some(Array::<L>::zeros(*len).named("loss")),
        Loss::Final(_) => None,
    };
    let mut result = None;
    let mut later: Option<S> = None;
    for j in (0..starts.len()).rev() {
        let end = starts.get(j + 1).copied().unwrap_or(steps);
        let (own, flags) = match j {
            0 => (None, flags0.clone()),
            _ => {
                let (s, f) = saved.pop().expect("one checkpoint per segment");
                (Some(s), f)
            }
        };
        let first = own.as_ref().unwrap_or(initial);
        let sources = flagged(first, &flags);
        let mut tape = Tape::new();
        let acc = total
            .as_ref()
            .map(|t| Array::<L>::zeros(t.len()).named("loss"));
        let segment = Some((starts[j], end, j + 1 == starts.len()));
        if let (Loss::Every(f, _), Some(acc), 0) = (&mut loss, &acc, j) {
            f(&mut tape, first, 0, acc)
                .map_err(|e| at_step(e, "loss of state", 0, steps, segment))?;
        }
        let mut cur: Option<S> = None;
        for t in starts[j]..end {
            let next = step(&mut tape, cur.as_ref().unwrap_or(first), t)
                .map_err(|e| at_step(e, "step", t, steps, segment))?;
            steps_run += 1;
            progress.tick();
            if let (Loss::Every(f, _), Some(acc)) = (&mut loss, &acc) {
                f(&mut tape, &next, t + 1, acc)
                    .map_err(|e| at_step(e, "loss of state", t + 1, steps, segment))?;
            }
            cur = Some(next);
        }
        let last = cur.as_ref().unwrap_or(first);
        let mut seeds = Vec::new();
        match later.take() {
            None => {
                if let Loss::Final(f) = &mut loss {
                    let l = f(&mut tape, last)
                        .map_err(|e| at_step(e, "loss of state", steps, steps, segment))?;
                    tape.backward_sources(&l, &sources)?;
                    result = Some(l);
                }
            }
            Some(next_first) => {
                for (a, n) in last.arrays().into_iter().zip(next_first.arrays()) {
                    if let Some(g) = n.grad_any() {
                        a.ensure_grad();
                        a.grad_any().expect("just allocated").add_from(&*g);
                        seeds.push(a);
                    }
                }
            }
        }
        if let Some(acc) = &acc {
            if tape.writes(acc.id()) {
                acc.ensure_grad().fill(ones::<L>());
                seeds.push(acc);
            }
        }
        if !seeds.is_empty() {
            tape.backward_seeded(&seeds, &sources)?;
        }
        if let (Some(total), Some(acc)) = (&total, &acc) {
            total.add_from(acc);
        }
        drop(tape);
        later = own;
    }
    Ok(Rollout {
        loss: result
            .or(total)
            .expect("the last segment computes the loss"),
        checkpoints: starts.len(),
        steps_run,
    })
}

/// `e` with where it happened: `"checkpointed rollout, step 7 of 20 (forward sweep)"`.
/// `segment`: `None` in the forward sweep, else the steps of the segment being run for the
/// backward pass and whether it is the last (run there for the first time).
fn at_step(
    e: Error,
    what: &str,
    t: usize,
    steps: usize,
    segment: Option<(usize, usize, bool)>,
) -> Error {
    let pass = match segment {
        None => "forward sweep".to_string(),
        Some((a, b, true)) => format!("last segment {a}..{b}, run once on the backward tape"),
        Some((a, b, false)) => format!("recomputing segment {a}..{b} for the backward pass"),
    };
    e.in_context(format!(
        "checkpointed rollout, {what} {t} of {steps} ({pass})"
    ))
}
