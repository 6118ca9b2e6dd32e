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

/// One axis of a discrete filter on an `n x n` grid: `out[t]` is the sum over `k` of
/// `weights[k] q[t']`, `t'` the cell `k - r` cells from `t` along `axis` (0: `i`, the
/// `x` index; 1: `j`), cells outside the grid counting as zero (`weights.len() = 2 r + 1`).
#[diff_kernel]
pub fn filter_axis<R: Real>(
    q: &Array<R>,
    weights: &Array<R>,
    n: usize,
    r: usize,
    axis: usize,
    out: &Array<R>,
) {
    let t = tid();
    let c = if axis == 0 { t / n } else { t % n };
    let stride = if axis == 0 { n } else { 1 };
    let mut s = 0.0;
    for k in 0..2 * r + 1 {
        if c + k >= r && c + k < n + r {
            s += weights[k] * q[t + k * stride - r * stride];
        }
    }
    out[t] = s;
}

/// Smoke control: find the initial velocity (given by the parameters `u0`, `v0`, the gradient
/// targets; see [`SmokeTask::initial_velocity`]) that carries a disc of smoke to a target
/// density after `steps` steps. The density starts as a disc of radius `0.15` at
/// `(0.5, 0.3)`; the target is two discs of radius `0.1` at `(0.3, 0.65)` and `(0.7, 0.65)`,
/// so the smoke must rise and split. Unit square, `dt = dx` (a velocity of 1 moves one cell
/// per step). The loss is the squared distance of the final density to the target, summed
/// over the cells ([`SmokeTask::distance`]), plus, with [`SmokeTask::with_coarse_loss`], the
/// same distance between both densities filtered.
#[derive(Clone, Debug)]
pub struct SmokeTask {
    /// The grid.
    pub grid: FluidGrid,
    /// The parameters of the initial velocity's `x` component: the velocity itself when
    /// `smoothing_sigma` is 0, else what the filter smooths into it.
    pub u0: Array<f64>,
    /// The same for the `y` component.
    pub v0: Array<f64>,
    /// Initial density.
    pub density0: Array<f64>,
    /// Target density.
    pub target: Array<f64>,
    /// Steps per rollout.
    pub steps: usize,
    /// The pressure solve.
    pub pressure: Pressure,
    /// The standard deviation, in cells, of the Gaussian filter from the parameters `u0`,
    /// `v0` to the initial velocity (0: none, the parameters are the velocity; see
    /// [`SmokeTask::smoothed`]).
    pub smoothing_sigma: f64,
    /// The standard deviation, in cells, of the Gaussian filter applied to the final and the
    /// target density for the loss's coarse term (0: none; see
    /// [`SmokeTask::with_coarse_loss`]).
    pub coarse_sigma: f64,
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
            smoothing_sigma: 0.0,
            coarse_sigma: 0.0,
        })
    }

    /// The same task with the initial velocity the parameters filtered by a Gaussian of
    /// standard deviation `sigma` cells (cut at `3 sigma`, zero outside the walls), so that
    /// gradient steps move smooth velocity fields. On DiffTaichi's task the per-cell
    /// velocity (`sigma = 0`, DiffTaichi's parameterization) lets the optimizer carve the
    /// smoke into filaments; a smooth field carries it as a whole.
    ///
    /// Errors: [`Error::InvalidInput`] naming `SmokeTask::smoothed` if `sigma` is negative,
    /// not finite or more than the grid's `n` cells.
    pub fn smoothed(mut self, sigma: f64) -> Result<Self, Error> {
        self.smoothing_sigma = width("SmokeTask::smoothed: sigma", sigma, self.grid.n())?;
        Ok(self)
    }

    /// The same task with a coarse term added to the loss: the squared distance between the
    /// final and the target density, both filtered by a Gaussian of standard deviation
    /// `sigma` cells. The plain distance has no gradient towards a target the smoke does
    /// not touch (here the smoke starts below both target discs); the filtered one does.
    /// [`SmokeTask::distance`] still measures the plain distance.
    ///
    /// Errors: [`Error::InvalidInput`] naming `SmokeTask::with_coarse_loss` if `sigma` is
    /// negative, not finite or more than the grid's `n` cells.
    pub fn with_coarse_loss(mut self, sigma: f64) -> Result<Self, Error> {
        self.coarse_sigma = width("SmokeTask::with_coarse_loss: sigma", sigma, self.grid.n())?;
        Ok(self)
    }

    /// The initial velocity the parameters give (recorded on `tape`): `(u0, v0)` themselves,
    /// or filtered (see [`SmokeTask::smoothed`]).
    pub fn initial_velocity(&self, tape: &mut Tape) -> (Array<f64>, Array<f64>) {
        if self.smoothing_sigma == 0.0 {
            return (self.u0.clone(), self.v0.clone());
        }
        (
            self.gaussian(tape, &self.u0, self.smoothing_sigma),
            self.gaussian(tape, &self.v0, self.smoothing_sigma),
        )
    }

    /// `q` filtered by a Gaussian of standard deviation `sigma` cells, cut at `3 sigma`,
    /// zero outside the walls (recorded on `tape`).
    fn gaussian(&self, tape: &mut Tape, q: &Array<f64>, sigma: f64) -> Array<f64> {
        let r = (3.0 * sigma).ceil() as usize;
        let w: Vec<f64> = (0..=2 * r)
            .map(|k| (-((k as f64 - r as f64) / sigma).powi(2) / 2.0).exp())
            .collect();
        let total: f64 = w.iter().sum();
        let weights = Array::from_vec(w.iter().map(|w| w / total).collect());
        let (n, cells) = (self.grid.n(), self.grid.cells());
        let mut q = q.clone();
        for axis in 0..2 {
            let out = Array::zeros(cells);
            tape.launch(filter_axis, cells, (&q, &weights, n, r, axis, &out));
            q = out;
        }
        q
    }

    /// The squared distance of a rollout's final density to the target, summed over the cells
    /// (the loss without its coarse term).
    pub fn distance(&self) -> Result<f64, Error> {
        let d = self.final_density()?.to_vec();
        Ok(d.iter()
            .zip(self.target.to_vec())
            .map(|(d, t)| (d - t) * (d - t))
            .sum())
    }

    /// The final density of a rollout (no tape kept).
    pub fn final_density(&self) -> Result<Array<f64>, Error> {
        let mut tape = Tape::new();
        Ok(self.rollout(&mut tape)?.2)
    }

    fn rollout(&self, tape: &mut Tape) -> Result<Flow<f64>, Error> {
        let (mut u, mut v) = self.initial_velocity(tape);
        let mut d = self.density0.clone();
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
        let loss = self.loss(&mut tape)?;
        tape.backward(&loss)?;
        Ok(loss.get(0))
    }

    /// Records a rollout and its loss on `tape` (the one-element array returned), for
    /// [`GradCheck`] or an optimizer's `minimize`.
    pub fn loss(&self, tape: &mut Tape) -> Result<Array<f64>, Error> {
        let (_, _, d) = self.rollout(tape)?;
        let loss = Array::zeros(1).named("loss");
        tape.launch(squared_error, self.grid.cells(), (&d, &self.target, &loss));
        if self.coarse_sigma > 0.0 {
            let (coarse, target) = (
                self.gaussian(tape, &d, self.coarse_sigma),
                self.gaussian(tape, &self.target, self.coarse_sigma),
            );
            tape.launch(squared_error, self.grid.cells(), (&coarse, &target, &loss));
        }
        Ok(loss)
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

/// A filter width: finite, at least 0 and at most the grid's `n` cells (wider, the filter is
/// flat over the grid and only costs time).
fn width(what: &str, sigma: f64, n: usize) -> Result<f64, Error> {
    if sigma.is_finite() && (0.0..=n as f64).contains(&sigma) {
        Ok(sigma)
    } else {
        Err(super::invalid(
            what,
            format!(
                "{sigma} cells; give a finite width from 0 (no filter) to the grid's {n} cells"
            ),
        ))
    }
}
