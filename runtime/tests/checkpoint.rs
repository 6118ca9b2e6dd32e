//! Checkpointed rollouts give the plain tape's gradients bit for bit.

mod common;

use adflex_runtime::checkpoint::{checkpointed, Checkpoint, Checkpointed};
use adflex_runtime::prelude::*;
use common::{random, Step, SumSq};

const N: usize = 8;
const M: usize = 3;
const T: usize = 20;
const DT: f64 = 0.05;

#[derive(Clone)]
struct State {
    x: Array<f64>,
    v: Array<f64>,
    /// Passed from step to step unchanged (same handle): read only by the loss.
    c: Array<f64>,
}

impl Checkpoint for State {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        vec![&self.x, &self.v, &self.c]
    }
    fn snapshot(&self) -> Self {
        State {
            x: self.x.deep_clone(),
            v: self.v.deep_clone(),
            c: self.c.deep_clone(),
        }
    }
}

struct Setup {
    s0: State,
    p: Array<f64>,
}

fn setup() -> Setup {
    Setup {
        s0: State {
            x: Array::from_vec(random(N, 1, -1.0, 1.0))
                .requires_grad()
                .named("x0"),
            v: Array::from_vec(random(N, 2, -0.5, 0.5))
                .requires_grad()
                .named("v0"),
            c: Array::from_vec(random(2, 3, 0.5, 1.5))
                .requires_grad()
                .named("c"),
        },
        p: Array::from_vec(random(M, 4, 1.0, 3.0))
            .requires_grad()
            .named("p"),
    }
}

fn step(p: &Array<f64>) -> impl FnMut(&mut Tape, &State) -> Result<State, Error> + '_ {
    move |tape, s| {
        let x2 = Array::<f64>::zeros(N).named("x");
        let v2 = Array::<f64>::zeros(N).named("v");
        tape.launch(Step, N, (&s.x, &s.v, p, DT, &x2, &v2));
        Ok(State {
            x: x2,
            v: v2,
            c: s.c.clone(),
        })
    }
}

fn loss(tape: &mut Tape, s: &State) -> Result<Array<f64>, Error> {
    let l = Array::<f64>::zeros(1).named("loss");
    tape.launch(SumSq, N, (&s.x, &l));
    tape.launch(SumSq, 2, (&s.c, &l));
    Ok(l)
}

fn bits(a: &Array<f64>) -> Vec<u64> {
    a.grad()
        .unwrap()
        .to_vec()
        .iter()
        .map(|g| g.to_bits())
        .collect()
}

fn grads(s: &Setup) -> [Vec<u64>; 4] {
    [bits(&s.s0.x), bits(&s.s0.v), bits(&s.s0.c), bits(&s.p)]
}

fn plain() -> (f64, [Vec<u64>; 4]) {
    let s = setup();
    let mut tape = Tape::new();
    let mut cur = s.s0.clone();
    let mut f = step(&s.p);
    for _ in 0..T {
        cur = f(&mut tape, &cur).unwrap();
    }
    let l = loss(&mut tape, &cur).unwrap();
    tape.backward(&l).unwrap();
    (l.get(0), grads(&s))
}

#[test]
fn checkpointed_equals_plain_tape_bitwise() {
    let (l_plain, g_plain) = plain();
    assert!(g_plain.iter().flatten().any(|&b| f64::from_bits(b) != 0.0));
    for k in [1, 3, 7, T, T + 5] {
        let s = setup();
        let out = checkpointed(&s.s0, T, k, step(&s.p), loss).unwrap();
        assert_eq!(
            out.loss.get(0).to_bits(),
            l_plain.to_bits(),
            "loss, k = {k}"
        );
        assert_eq!(grads(&s), g_plain, "gradients, k = {k}");
        assert_eq!(out.checkpoints, T.div_ceil(k), "k = {k}");
        let last_start = (T - 1) / k * k;
        assert_eq!(out.steps_run, last_start + T, "k = {k}");
    }
}

#[test]
fn checkpointed_without_steps_is_the_loss_alone() {
    let s = setup();
    let out = checkpointed(&s.s0, 0, 4, step(&s.p), loss).unwrap();
    let x = s.s0.x.to_vec();
    let gx = s.s0.x.grad().unwrap().to_vec();
    assert_eq!(gx, x.iter().map(|x| 2.0 * x).collect::<Vec<_>>());
    assert_eq!((out.checkpoints, out.steps_run), (1, 0));
    assert!(s.p.grad().unwrap().to_vec().iter().all(|&g| g == 0.0));
}

#[test]
fn checkpointed_reports_array_changes() {
    // A step that writes a shared array the previous step read (in the same segment).
    let s = setup();
    let shared = Array::from_vec(vec![0.0f64; N]).named("shared");
    let err = checkpointed(
        &s.s0,
        4,
        2,
        |tape: &mut Tape, st: &State| {
            let x2 = Array::<f64>::zeros(N);
            let v2 = Array::<f64>::zeros(N);
            tape.launch(Step, N, (&st.x, &shared, &s.p, DT, &x2, &v2));
            shared.set(0, shared.get(0) + 1.0);
            Ok(State {
                x: x2,
                v: v2,
                c: st.c.clone(),
            })
        },
        loss,
    )
    .unwrap_err();
    assert!(
        matches!(err, Error::ArrayChanged { ref array, .. } if array == "shared"),
        "{err}"
    );
}

#[adflex_macros::diff_kernel]
fn add_scaled<R: Real>(x: &Array<R>, w: &Array<R>, acc: &Array<R>) {
    let i = tid();
    acc.atomic_add(i, w[i] * x[i]);
}

/// A trajectory loss: sum over states `t` of `w_t * |x_t|^2`, the weight depending on the
/// step index so that a wrong index changes the gradient.
fn trajectory_loss(tape: &mut Tape, s: &State, t: usize, acc: &Array<f64>) -> Result<(), Error> {
    if t % 3 == 1 {
        return Ok(()); // states without a loss term
    }
    let w = Array::from_vec(vec![1.0 + t as f64; 1]);
    let sq = Array::<f64>::zeros(1);
    tape.launch(SumSq, N, (&s.x, &sq));
    tape.launch(add_scaled, 1, (&sq, &w, acc));
    Ok(())
}

fn plain_trajectory() -> (f64, [Vec<u64>; 4]) {
    let s = setup();
    let mut tape = Tape::new();
    let acc = Array::<f64>::zeros(1);
    let mut cur = s.s0.clone();
    let mut f = step(&s.p);
    trajectory_loss(&mut tape, &cur, 0, &acc).unwrap();
    for t in 0..T {
        cur = f(&mut tape, &cur).unwrap();
        trajectory_loss(&mut tape, &cur, t + 1, &acc).unwrap();
    }
    tape.backward(&acc).unwrap();
    (acc.get(0), grads(&s))
}

#[test]
fn per_step_losses_equal_a_plain_tape_bitwise() {
    let (l_plain, g_plain) = plain_trajectory();
    assert!(g_plain.iter().flatten().any(|&b| f64::from_bits(b) != 0.0));
    for k in [1, 3, 7, T, T + 5] {
        let s = setup();
        let mut seen = Vec::new();
        let mut f = step(&s.p);
        let out = Checkpointed::new(T)
            .every(k)
            .run(
                &s.s0,
                |tape, st, t| {
                    seen.push(t);
                    f(tape, st)
                },
                trajectory_loss,
            )
            .unwrap();
        let rel = (out.loss.get(0) - l_plain).abs() / l_plain.abs();
        assert!(
            rel < 1e-14,
            "loss {} vs {l_plain}, k = {k}",
            out.loss.get(0)
        );
        assert_eq!(grads(&s), g_plain, "gradients, k = {k}");
        // Every step index, in order within each pass: 0..last_start forward, then each
        // segment's indices.
        let last_start = (T - 1) / k * k;
        assert_eq!(seen.len(), last_start + T, "k = {k}");
        assert!(seen[..last_start].iter().copied().eq(0..last_start));
        let mut segments: Vec<usize> = seen[last_start..].to_vec();
        segments.sort_unstable();
        assert!(segments.into_iter().eq(0..T), "k = {k}");
    }
}

#[test]
fn per_step_losses_with_a_progress_bar_and_the_default_spacing() {
    let (_, g_plain) = plain_trajectory();
    let s = setup();
    let out = Checkpointed::new(T)
        .progress("rollout")
        .run(&s.s0, |tape, st, _| step(&s.p)(tape, st), trajectory_loss)
        .unwrap();
    // ceil(sqrt(20)) = 5 steps per segment.
    assert_eq!(out.checkpoints, 4);
    assert_eq!(grads(&s), g_plain);
}

/// A solver-like error, as a step returns it.
fn failure() -> Error {
    Error::NotConverged {
        solver: "test solver".into(),
        context: String::new(),
        iterations: 3,
        residual: 1.0,
        tolerance: 1e-9,
        hint: "none".into(),
    }
}

#[test]
fn an_error_of_step_7_of_20_comes_out_naming_the_step() {
    // Failing at step 7 in the forward sweep (both entry points, every spacing): an error
    // naming step 7 and the sweep, no panic, and no later step run.
    for k in [1, 3, 5, 7, 8, T] {
        let s = setup();
        let mut ran = Vec::new();
        let mut f = step(&s.p);
        let mut failing = |tape: &mut Tape, st: &State, t: usize| {
            ran.push(t);
            if t == 7 {
                return Err(failure());
            }
            f(tape, st)
        };
        let err = Checkpointed::new(T)
            .every(k)
            .run(&s.s0, &mut failing, trajectory_loss)
            .unwrap_err();
        let shown = err.to_string();
        assert!(
            matches!(err, Error::NotConverged { ref context, .. }
                if context.starts_with("checkpointed rollout, step 7 of 20")),
            "k = {k}: {shown}"
        );
        // Step 7 is in the forward sweep unless it is in the last segment (k = 8: 0, 8, 16;
        // k = 20: one segment), which runs first on the backward tape.
        let last_start = (T - 1) / k * k;
        let pass = if 7 < last_start {
            "forward sweep"
        } else {
            "last segment"
        };
        assert!(shown.contains(pass), "k = {k}: {shown}");
        assert_eq!(ran.last(), Some(&7), "k = {k}: {ran:?}");

        // `checkpointed`: its step is not told the index; the 8th call is step 7 when the
        // forward sweep reaches it.
        if 7 < last_start {
            let s = setup();
            let mut f = step(&s.p);
            let mut calls = 0;
            let err = checkpointed(
                &s.s0,
                T,
                k,
                |tape: &mut Tape, st: &State| {
                    calls += 1;
                    match calls {
                        8 => Err(Error::Other("the solver gave up".into())),
                        _ => f(tape, st),
                    }
                },
                loss,
            )
            .unwrap_err();
            assert_eq!(
                err.to_string(),
                "checkpointed rollout, step 7 of 20 (forward sweep): the solver gave up",
                "k = {k}"
            );
        }

        // A loss that fails: named as the loss of the final state.
        let s = setup();
        let err = checkpointed(&s.s0, T, k, step(&s.p), |_: &mut Tape, _: &State| {
            Err::<Array<f64>, _>(Error::Other("no loss today".into()))
        })
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            format!(
                "checkpointed rollout, loss of state 20 of 20 (last segment {last_start}..20, \
                 run once on the backward tape): no loss today"
            ),
            "k = {k}"
        );
    }
}

#[test]
fn an_error_while_recomputing_a_segment_names_the_step_and_the_recomputation() {
    // A step that fails only the second time step 7 runs: the forward sweep passes, the
    // recomputation of its segment for the backward pass fails, naming step 7.
    let s = setup();
    let mut f = step(&s.p);
    let mut calls_of_7 = 0;
    let err = Checkpointed::new(T)
        .every(5)
        .run(
            &s.s0,
            |tape, st, t| {
                if t == 7 {
                    calls_of_7 += 1;
                    if calls_of_7 == 2 {
                        return Err(Error::InvalidInput {
                            what: "dt".into(),
                            message: "is too large".into(),
                        });
                    }
                }
                f(tape, st)
            },
            trajectory_loss,
        )
        .unwrap_err();
    assert_eq!(calls_of_7, 2);
    assert_eq!(
        err.to_string(),
        Error::InvalidInput {
            what: "dt".into(),
            message: "is too large (in checkpointed rollout, step 7 of 20 (recomputing segment \
                      5..10 for the backward pass))"
                .into(),
        }
        .to_string()
    );
}
