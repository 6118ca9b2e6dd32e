//! Ready-made fluid tasks: smoke control ([`SmokeTask`]), after DiffTaichi's `smoke` example.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::{Flow, FluidGrid, Pressure};

/// `loss[0] += (d - target)^2` over the cells.
#[diff_kernel]
pub fn squared_error<R: Real>(d: &Array<R>, target: &Array<R>, loss: &Array<R>) {
    let t = tid();
    let e = d[t] - target[t];
    loss.atomic_add(0, e * e);
}

/// Smoke control: find the initial velocity `(u0, v0)` (the gradient targets) that carries a
/// disc of smoke to a target density after `steps` steps. The density starts as a disc of
/// radius `0.15` at `(0.5, 0.3)`; the target is two discs of radius `0.1` at `(0.3, 0.65)`
/// and `(0.7, 0.65)`, so the smoke must rise and split. Unit square, `dt = dx` (a velocity of
/// 1 moves one cell per step). The loss is the squared distance of the final density to the
/// target, summed over the cells.
#[derive(Clone, Debug)]
pub struct SmokeTask {
    /// The grid.
    pub grid: FluidGrid,
    /// Initial velocity, `x` component.
    pub u0: Array<f64>,
    /// Initial velocity, `y` component.
    pub v0: Array<f64>,
    /// Initial density.
    pub density0: Array<f64>,
    /// Target density.
    pub target: Array<f64>,
    /// Steps per rollout.
    pub steps: usize,
    /// The pressure solve.
    pub pressure: Pressure,
}

impl SmokeTask {
    /// The task on an `n x n` grid (`n` even), `steps` steps, at rest initially.
    pub fn new(n: usize, steps: usize, pressure: Pressure) -> Result<Self, Error> {
        let grid = FluidGrid::new(n, 1.0 / n as f64)?;
        let disc = |cx: f64, cy: f64, r: f64| {
            move |i: usize, j: usize| {
                let (x, y) = ((i as f64 + 0.5) / n as f64, (j as f64 + 0.5) / n as f64);
                let d = ((x - cx).powi(2) + (y - cy).powi(2)).sqrt();
                // A smooth edge one cell wide.
                (0.5 - (d - r) * n as f64).clamp(0.0, 1.0)
            }
        };
        let field = |f: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
            (0..n * n).map(|t| f(t / n, t % n)).collect()
        };
        let (a, b, c) = (
            disc(0.5, 0.3, 0.15),
            disc(0.3, 0.65, 0.1),
            disc(0.7, 0.65, 0.1),
        );
        Ok(SmokeTask {
            grid,
            u0: Array::zeros(n * n).named("u0").requires_grad(),
            v0: Array::zeros(n * n).named("v0").requires_grad(),
            density0: Array::from_vec(field(&a)).named("density0"),
            target: Array::from_vec(field(&|i, j| b(i, j) + c(i, j))).named("target"),
            steps,
            pressure,
        })
    }

    /// The final density of a rollout (no tape kept).
    pub fn final_density(&self) -> Result<Array<f64>, Error> {
        let mut tape = Tape::new();
        Ok(self.rollout(&mut tape)?.2)
    }

    fn rollout(&self, tape: &mut Tape) -> Result<Flow<f64>, Error> {
        let (mut u, mut v, mut d) = (self.u0.clone(), self.v0.clone(), self.density0.clone());
        for _ in 0..self.steps {
            (u, v, d) = self
                .grid
                .step(tape, &u, &v, &d, self.grid.dx(), &self.pressure)?;
        }
        Ok((u, v, d))
    }

    /// The loss of one rollout, with its gradient accumulated into the gradient buffers of
    /// `u0` and `v0` (zeroed first).
    pub fn loss_and_grad(&self) -> Result<f64, Error> {
        self.u0.zero_grad();
        self.v0.zero_grad();
        let mut tape = Tape::new();
        let (_, _, d) = self.rollout(&mut tape)?;
        let loss = Array::zeros(1).named("loss");
        tape.launch(squared_error, self.grid.cells(), (&d, &self.target, &loss));
        tape.backward(&loss)?;
        Ok(loss.get(0))
    }

    /// One step of normalized gradient descent on the initial velocity, from the gradients
    /// of the last [`SmokeTask::loss_and_grad`]: `p -= lr g / max |g|`, so that no velocity
    /// changes by more than `lr` (cells per step) in one iteration. The peers' scripts
    /// (`bench/peers/*_smoke.py`) take the same step.
    pub fn descend(&self, lr: f64) -> Result<(), Error> {
        let (gu, gv) = (self.u0.grad()?.to_vec(), self.v0.grad()?.to_vec());
        let big = gu
            .iter()
            .chain(&gv)
            .fold(0.0f64, |m, g| m.max(g.abs()))
            .max(1e-30);
        for (p, g) in [(&self.u0, gu), (&self.v0, gv)] {
            p.modify(|p| p.iter_mut().zip(&g).for_each(|(p, g)| *p -= lr * g / big));
        }
        Ok(())
    }
}
