//! Checkpointed rollouts give the plain tape's gradients bit for bit.

mod common;

use adflex_runtime::checkpoint::{checkpointed, Checkpoint};
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

fn step(p: &Array<f64>) -> impl FnMut(&mut Tape, &State) -> State + '_ {
    move |tape, s| {
        let x2 = Array::<f64>::zeros(N).named("x");
        let v2 = Array::<f64>::zeros(N).named("v");
        tape.launch(Step, N, (&s.x, &s.v, p, DT, &x2, &v2));
        State {
            x: x2,
            v: v2,
            c: s.c.clone(),
        }
    }
}

fn loss(tape: &mut Tape, s: &State) -> Array<f64> {
    let l = Array::<f64>::zeros(1).named("loss");
    tape.launch(SumSq, N, (&s.x, &l));
    tape.launch(SumSq, 2, (&s.c, &l));
    l
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
        cur = f(&mut tape, &cur);
    }
    let l = loss(&mut tape, &cur);
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
            State {
                x: x2,
                v: v2,
                c: st.c.clone(),
            }
        },
        loss,
    )
    .unwrap_err();
    assert!(
        matches!(err, Error::ArrayChanged { ref array, .. } if array == "shared"),
        "{err}"
    );
}
