// A one-dimensional damped (or undamped) mass-spring oscillator with its exact solution: the
// test bench of the integrators' accuracy and stability (and of the benchmark charts of
// error against cost and stability against stiffness).
//
// The oscillator is a `Model` of two particles joined by one spring along `x`: an anchor
// pinned at the origin and a mass at `rest_length + displacement`. No gravity. It obeys
// `m u'' + c u' + k u = 0` exactly as long as the mass does not cross the anchor
// (`|u| < 1 m`, see `Trajectory::max_displacement`), so every integrator of the library can be run on it and compared with
// `Oscillator::exact`.

use std::time::Instant;

use adflex_runtime::{Array, Error, Tape, Vec3};

use adflex_kernels::integrators::Integrator;
use adflex_kernels::{Model, ModelBuilder};

/// Rest length of the oscillator's spring (m).
pub const REST_LENGTH: f64 = 1.0;

/// A mass on a spring, `m u'' + c u' + k u = 0`, `u` the displacement from rest (m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Oscillator {
    /// Spring stiffness `k` (N/m; default 100).
    pub stiffness: f64,
    /// Mass `m` (kg; default 1).
    pub mass: f64,
    /// Damping `c` along the spring (N s/m; default 0: undamped).
    pub damping: f64,
    /// Initial displacement `u(0)` (m; default 0.1; keep `|u| < 1`).
    pub displacement: f64,
    /// Initial velocity `u'(0)` (m/s; default 0).
    pub velocity: f64,
}

impl Default for Oscillator {
    fn default() -> Self {
        Oscillator {
            stiffness: 100.0,
            mass: 1.0,
            damping: 0.0,
            displacement: 0.1,
            velocity: 0.0,
        }
    }
}

/// The sampled motion of an [`Oscillator`], one entry per step (the initial state first).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    /// Time step (s).
    pub dt: f64,
    /// Times (s).
    pub t: Vec<f64>,
    /// Displacement from rest (m).
    pub u: Vec<f64>,
    /// Velocity (m/s).
    pub v: Vec<f64>,
    /// Mechanical energy `k u^2 / 2 + m v^2 / 2` (J).
    pub energy: Vec<f64>,
    /// Wall-clock time of the whole simulation (s), stepping only.
    pub seconds: f64,
}

impl Trajectory {
    /// The last displacement (m).
    pub fn final_displacement(&self) -> f64 {
        *self.u.last().expect("a trajectory has its initial state")
    }

    /// The last velocity (m/s).
    pub fn final_velocity(&self) -> f64 {
        *self.v.last().expect("a trajectory has its initial state")
    }

    /// The largest `|u|` along the trajectory (m). The model is the linear oscillator only
    /// while this is below [`REST_LENGTH`]: beyond, the mass has crossed the anchor and the
    /// spring pulls it towards `u = -2` (so an energy ratio above `(1 / u(0))^2`, 100 from the
    /// default `u(0) = 0.1`, has left the linear regime: start from a smaller displacement
    /// to follow a growing solution further).
    pub fn max_displacement(&self) -> f64 {
        self.u.iter().fold(0.0f64, |m, &u| {
            if u.is_nan() || m.is_nan() {
                f64::NAN
            } else {
                m.max(u.abs())
            }
        })
    }

    /// The largest energy along the trajectory over the initial energy (NaN or infinite if the
    /// simulation blew up). See `Trajectory::max_displacement` for where it stops being
    /// that of a linear oscillator.
    pub fn max_energy_ratio(&self) -> f64 {
        let e0 = self.energy[0];
        self.energy.iter().fold(0.0f64, |m, &e| {
            if e.is_nan() || m.is_nan() {
                f64::NAN
            } else {
                m.max(e / e0)
            }
        })
    }

    /// The last energy over the initial energy.
    pub fn final_energy_ratio(&self) -> f64 {
        self.energy
            .last()
            .expect("a trajectory has its initial state")
            / self.energy[0]
    }
}

impl Oscillator {
    /// An oscillator of stiffness `k` (N/m), mass `m` (kg) and damping `c` (N s/m), released
    /// from `u = 0.1 m` at rest.
    pub fn new(k: f64, m: f64, c: f64) -> Self {
        Oscillator {
            stiffness: k,
            mass: m,
            damping: c,
            ..Self::default()
        }
    }

    /// The undamped angular frequency `omega = sqrt(k / m)` (rad/s): an integrator's
    /// stability is a function of `omega dt`.
    pub fn omega(&self) -> f64 {
        (self.stiffness / self.mass).sqrt()
    }

    /// The damping ratio `c / (2 sqrt(k m))` (1 = critical).
    pub fn damping_ratio(&self) -> f64 {
        self.damping / (2.0 * (self.stiffness * self.mass).sqrt())
    }

    /// The time step (s) for a given `omega dt`.
    pub fn dt_for(&self, omega_dt: f64) -> f64 {
        omega_dt / self.omega()
    }

    fn builder(&self) -> ModelBuilder<f64> {
        let mut b = ModelBuilder::<f64>::new();
        b.gravity = Vec3::zeros();
        b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
        b.add_particle(
            Vec3::new(REST_LENGTH + self.displacement, 0.0, 0.0),
            Vec3::new(self.velocity, 0.0, 0.0),
            self.mass,
        );
        b
    }

    /// The oscillator as a `Model`: particle 0 pinned at the origin, particle 1 (the mass) at
    /// `(1 + u(0), 0, 0)`, one spring of rest length 1 m, stiffness `k` and damping `c`, no
    /// gravity.
    pub fn model(&self) -> Model<f64> {
        let mut b = self.builder();
        b.add_spring_with_rest(0, 1, REST_LENGTH, self.stiffness, self.damping);
        b.finalize()
    }

    /// The same oscillator with the spring replaced by an XPBD distance constraint of
    /// compliance `1 / k` (m/N) and no damping, for [`Xpbd`](crate::integrators::Xpbd)
    /// (whose constraint solve then plays the role of the spring force).
    pub fn constraint_model(&self) -> Model<f64> {
        let mut b = self.builder();
        b.add_distance_constraint(0, 1, 1.0 / self.stiffness);
        let mut m = b.finalize();
        // The builder takes the initial distance as the rest distance: use the rest length.
        if let Some(c) = &mut m.distance_constraints {
            c.rest = Array::from_vec(vec![REST_LENGTH]).named("dist_rest");
        }
        m
    }

    /// The exact displacement (m) and velocity (m/s) at time `t` (s), for the under-,
    /// critically and over-damped cases.
    pub fn exact(&self, t: f64) -> (f64, f64) {
        let (u0, v0) = (self.displacement, self.velocity);
        let w0 = self.omega();
        let g = self.damping / (2.0 * self.mass);
        let disc = g * g - w0 * w0;
        if disc.abs() <= 1e-12 * w0 * w0 {
            let (a, b) = (u0, v0 + g * u0);
            let e = (-g * t).exp();
            (e * (a + b * t), e * (b - g * (a + b * t)))
        } else if disc < 0.0 {
            let wd = (-disc).sqrt();
            let (a, b) = (u0, (v0 + g * u0) / wd);
            let (s, c) = (wd * t).sin_cos();
            let e = (-g * t).exp();
            (
                e * (a * c + b * s),
                e * ((b * wd - g * a) * c - (a * wd + g * b) * s),
            )
        } else {
            let q = disc.sqrt();
            let (r1, r2) = (-g + q, -g - q);
            let c1 = (v0 - r2 * u0) / (r1 - r2);
            let c2 = u0 - c1;
            (
                c1 * (r1 * t).exp() + c2 * (r2 * t).exp(),
                c1 * r1 * (r1 * t).exp() + c2 * r2 * (r2 * t).exp(),
            )
        }
    }

    /// The mechanical energy `k u^2 / 2 + m v^2 / 2` (J).
    pub fn energy(&self, u: f64, v: f64) -> f64 {
        0.5 * self.stiffness * u * u + 0.5 * self.mass * v * v
    }

    /// Runs `steps` steps of `dt` (s) of [`Oscillator::model`] with `integrator` (each step on
    /// a fresh tape, so memory stays flat) and returns the trajectory.
    ///
    /// Panics with the integrator's error if a step fails (e.g. implicit Euler's Newton did
    /// not converge): a trajectory with a wrong step is never returned.
    pub fn simulate<I: Integrator<f64> + ?Sized>(
        &self,
        integrator: &I,
        dt: f64,
        steps: usize,
    ) -> Trajectory {
        self.simulate_model(&self.model(), integrator, dt, steps)
    }

    /// Like [`Oscillator::simulate`] on a given model of this oscillator (e.g.
    /// [`Oscillator::constraint_model`]).
    pub fn simulate_model<I: Integrator<f64> + ?Sized>(
        &self,
        model: &Model<f64>,
        integrator: &I,
        dt: f64,
        steps: usize,
    ) -> Trajectory {
        let mut tr = Trajectory {
            dt,
            ..Trajectory::default()
        };
        let mut state = model.state();
        let record = |tr: &mut Trajectory, k: usize, x: Vec3<f64>, v: Vec3<f64>| {
            let (u, v) = (x.x - REST_LENGTH, v.x);
            tr.t.push(k as f64 * dt);
            tr.u.push(u);
            tr.v.push(v);
            tr.energy.push(self.energy(u, v));
        };
        record(&mut tr, 0, state.x.get(1), state.v.get(1));
        let start = Instant::now();
        let mut samples = Vec::with_capacity(steps);
        for k in 0..steps {
            let mut tape = Tape::new();
            state = match integrator.step(model, &mut tape, &state, None, dt) {
                Ok(s) => s,
                // The state overflowed (an unstable method): NaN from here on.
                Err(Error::NonFinite { .. }) => {
                    let nan = Vec3::new(f64::NAN, f64::NAN, f64::NAN);
                    samples.resize(steps, (nan, nan));
                    break;
                }
                Err(e) => panic!("Oscillator: step {k} failed: {e}"),
            };
            samples.push((state.x.get(1), state.v.get(1)));
        }
        tr.seconds = start.elapsed().as_secs_f64();
        for (k, (x, v)) in samples.into_iter().enumerate() {
            record(&mut tr, k + 1, x, v);
        }
        tr
    }
}
