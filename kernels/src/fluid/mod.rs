//! Grid fluids in 2D and 3D: an incompressible, inviscid fluid (smoke) on an `n x n` (or
//! `n x n x n`, [`FluidGrid::new_3d`] with [`FluidGrid::step_3d`]) collocated grid of spacing
//! `dx`, with closed walls. A step advects the velocity and any carried fields
//! semi-Lagrangianly ([`kernels::advect`]), then projects the velocity onto zero divergence
//! by a pressure solve. Every launch is on a tape, so a rollout differentiates with respect to
//! the initial velocity, the carried fields and anything they depend on.
//!
//! The pressure equation is `A p = -4 dx^2 div u`, with `A = -4 dx^2 D G` built from the same
//! central differences that measure the divergence (`D`, [`kernels::divergence`]) and
//! subtract the gradient (`G`, [`kernels::subtract_gradient`]): symmetric positive definite
//! for an even `n`, and the projected velocity has zero divergence (to the solver's
//! tolerance). Two ways to solve it ([`Pressure`]):
//!
//! - [`Pressure::Jacobi`]: a fixed number of Jacobi iterations, each a launch on the tape;
//!   its gradient is the exact gradient of the truncated iteration (by unrolling), and its
//!   memory grows with the iteration count.
//! - [`Pressure::Cg`]: conjugate gradients to a tolerance, one step on the tape whose adjoint
//!   is one more solve with `A^T = A` (the implicit function theorem: `d L / d b = A^-T
//!   d L / d p`) and whose tangent is one solve too; memory independent of the iteration
//!   count. A solve that does not converge is an error
//!   ([`Error::NotConverged`]), in the forward pass and
//!   in the adjoint.
//!
//! As the Jacobi count grows, its gradient tends to the CG one (tested).
//!
//! ```
//! use adflex_kernels::fluid::{FluidGrid, Pressure};
//! use adflex_runtime::prelude::*;
//!
//! let grid = FluidGrid::new(16, 1.0 / 16.0).unwrap();
//! let (u, v) = (Array::from_vec(vec![0.3f64; 256]), Array::zeros(256));
//! let mut tape = Tape::new();
//! let (pu, pv) = grid.project(&mut tape, &u, &v, &Pressure::cg()).unwrap();
//! let div = grid.divergence(&mut tape, &pu, &pv).unwrap();
//! assert!(div.to_vec().iter().all(|d| d.abs() < 1e-7));
//! ```

pub mod kernels;

use adflex_runtime::prelude::*;

use crate::solver::krylov::{cg, SolveSettings};
use kernels::{
    advect, advect3, divergence, divergence3, pressure_jacobi, pressure_jacobi3, subtract_gradient,
    subtract_gradient3,
};

/// The fields a smoke step carries: the velocity's `x` and `y` components and the density.
pub type Flow<R> = (Array<R>, Array<R>, Array<R>);

/// The state of a smoke grid: the velocity's components (2 or 3, as the grid's dimension)
/// and the density, one value per cell each.
#[derive(Clone, Debug)]
pub struct FluidState<R: Real> {
    /// `[u, v]` or `[u, v, w]`.
    pub velocity: Vec<Array<R>>,
    /// The advected density.
    pub density: Array<R>,
}

impl<R: Real> adflex_runtime::checkpoint::Checkpoint for FluidState<R> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        let mut a: Vec<&dyn AnyArray> = self.velocity.iter().map(|v| v as _).collect();
        a.push(&self.density);
        a
    }
    fn snapshot(&self) -> Self {
        FluidState {
            velocity: self.velocity.iter().map(Array::deep_clone).collect(),
            density: self.density.deep_clone(),
        }
    }
}

/// How the pressure equation is solved (see the [module docs](self)).
#[derive(Clone, Debug, PartialEq)]
pub enum Pressure {
    /// This many Jacobi iterations from `p = 0`, unrolled on the tape.
    Jacobi(usize),
    /// Conjugate gradients to the tolerance, with an implicit-function-theorem adjoint.
    Cg(SolveSettings),
}

impl Pressure {
    /// Conjugate gradients to a relative residual of `1e-10` (at most 10,000 iterations).
    pub fn cg() -> Self {
        Pressure::Cg(SolveSettings {
            rel_tol: 1e-10,
            abs_tol: 1e-30,
            max_iter: 10_000,
        })
    }
}

/// An `n x n` grid (or `n x n x n`, [`FluidGrid::new_3d`]) of spacing `dx`: cell `(i, j)` at
/// index `i * n + j`, `(i, j, k)` at `(i * n + j) * n + k`, `i` along `x`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FluidGrid {
    n: usize,
    dx: f64,
    dim: usize,
}

impl FluidGrid {
    /// A grid of `n x n` cells of size `dx`. Errors if `n` is odd or below 4 (the pressure
    /// operator is singular for odd `n`) or `dx` is not finite and positive.
    pub fn new(n: usize, dx: f64) -> Result<Self, Error> {
        Self::with_dim(n, dx, 2)
    }

    /// A 3D grid of `n x n x n` cells of size `dx` (the same conditions as [`FluidGrid::new`]).
    pub fn new_3d(n: usize, dx: f64) -> Result<Self, Error> {
        Self::with_dim(n, dx, 3)
    }

    fn with_dim(n: usize, dx: f64, dim: usize) -> Result<Self, Error> {
        if n < 4 || n & 1 == 1 {
            return Err(invalid(
                "n",
                format!("{n}: the grid needs an even number of cells, at least 4"),
            ));
        }
        if !(dx.is_finite() && dx > 0.0) {
            return Err(invalid("dx", format!("{dx} must be finite and positive")));
        }
        Ok(FluidGrid { n, dx, dim })
    }

    /// Cells per axis.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Cell size (m).
    pub fn dx(&self) -> f64 {
        self.dx
    }

    /// 2 or 3.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Cells in the grid.
    pub fn cells(&self) -> usize {
        self.n.pow(self.dim as u32)
    }

    /// An error unless the grid has `dim` dimensions.
    fn want(&self, dim: usize, what: &str) -> Result<(), Error> {
        if self.dim == dim {
            Ok(())
        } else {
            Err(invalid(
                what,
                format!("is for {dim}D grids; this grid is {}D", self.dim),
            ))
        }
    }

    fn check<R: Real>(&self, a: &Array<R>) -> Result<(), Error> {
        if a.len() == self.cells() {
            Ok(())
        } else {
            Err(invalid(
                &a.label(),
                format!("{} values for a grid of {} cells", a.len(), self.cells()),
            ))
        }
    }

    /// `q` advected by `(u, v)` over `dt` (semi-Lagrangian, bilinear), recorded on `tape`.
    /// Stable for any `dt`; accurate while `|u| dt` is a few cells at most. 2D grids only
    /// ([`FluidGrid::step_3d`] advects in 3D); errors for a 3D grid or a field of the wrong
    /// length.
    pub fn advect<R: Real>(
        &self,
        tape: &mut Tape,
        q: &Array<R>,
        u: &Array<R>,
        v: &Array<R>,
        dt: f64,
    ) -> Result<Array<R>, Error> {
        self.want(2, "FluidGrid::advect")?;
        check_dt(dt)?;
        for a in [q, u, v] {
            self.check(a)?;
        }
        let out = Array::zeros(self.cells()).named(format!("advected {}", q.label()));
        let scale = R::lit(dt / self.dx);
        tape.launch(advect, self.cells(), (q, u, v, self.n, scale, &out));
        Ok(out)
    }

    /// The divergence of `(u, v)` (closed walls) on a 2D grid, recorded on `tape`; errors for
    /// a 3D grid ([`FluidGrid::divergence_3d`]) or a field of the wrong length.
    pub fn divergence<R: Real>(
        &self,
        tape: &mut Tape,
        u: &Array<R>,
        v: &Array<R>,
    ) -> Result<Array<R>, Error> {
        self.want(2, "FluidGrid::divergence")?;
        for a in [u, v] {
            self.check(a)?;
        }
        let div = Array::zeros(self.cells()).named("divergence");
        let args = (u, v, self.n, R::lit(self.dx), &div);
        tape.launch(divergence, self.cells(), args);
        Ok(div)
    }

    /// The divergence of `(u, v, w)` on a 3D grid, recorded on `tape`; errors for a 2D grid
    /// or a field of the wrong length.
    pub fn divergence_3d<R: Real>(
        &self,
        tape: &mut Tape,
        u: &Array<R>,
        v: &Array<R>,
        w: &Array<R>,
    ) -> Result<Array<R>, Error> {
        self.want(3, "FluidGrid::divergence_3d")?;
        for a in [u, v, w] {
            self.check(a)?;
        }
        let div = Array::zeros(self.cells()).named("divergence");
        let args = (u, v, w, self.n, R::lit(self.dx), &div);
        tape.launch(divergence3, self.cells(), args);
        Ok(div)
    }

    /// The pressure for the divergence `div` (see the [module docs](self)).
    pub fn pressure<R: Real>(
        &self,
        tape: &mut Tape,
        div: &Array<R>,
        method: &Pressure,
    ) -> Result<Array<R>, Error> {
        self.check(div)?;
        let scale = -4.0 * self.dx * self.dx;
        match method {
            Pressure::Jacobi(k) => {
                let mut p = Array::zeros(self.cells()).named("pressure");
                for _ in 0..*k {
                    let next = Array::zeros(self.cells()).named("pressure");
                    let args = (&p, div, self.n, R::lit(scale), &next);
                    if self.dim == 2 {
                        tape.launch(pressure_jacobi, self.cells(), args);
                    } else {
                        tape.launch(pressure_jacobi3, self.cells(), args);
                    }
                    p = next;
                }
                Ok(p)
            }
            Pressure::Cg(s) => self.pressure_cg(tape, div, scale, s),
        }
    }

    /// `A x = b` by CG on the host, or the error naming the solve.
    fn solve(&self, b: &[f64], s: &SolveSettings, what: &str) -> Result<Vec<f64>, Error> {
        let (n, dim) = (self.n, self.dim);
        let mut x = vec![0.0; b.len()];
        let info = cg(
            |p, out| apply_pressure_operator(n, dim, p, out),
            b,
            &mut x,
            None,
            s,
        );
        if info.converged {
            Ok(x)
        } else {
            Err(Error::NotConverged {
                solver: format!("fluid pressure CG ({what})"),
                context: format!("{dim}D grid of {n} cells per axis"),
                iterations: info.iterations,
                residual: info.residual,
                tolerance: info.tolerance,
                hint: "raise max_iter or rel_tol of Pressure::Cg, or check the velocity for NaN"
                    .into(),
            })
        }
    }

    /// `A x = pre b` for the values of `b` and, in `Dual`, for its derivative parts (the
    /// operator is constant, so each part is its own solve: the second-order rule of a linear
    /// solve); returns `post x`.
    fn solve_parts<R: Real>(
        &self,
        b: &[R],
        (pre, post): (f64, f64),
        s: &SolveSettings,
        what: &str,
    ) -> Result<Vec<R>, Error> {
        let re: Vec<f64> = b.iter().map(|d| pre * d.to_f64()).collect();
        let x = self.solve(&re, s, what)?;
        let eps = match R::DUAL {
            true => {
                let eps: Vec<f64> = b.iter().map(|d| pre * d.eps()).collect();
                self.solve(&eps, s, what)?
            }
            false => vec![0.0; x.len()],
        };
        Ok(x.into_iter()
            .zip(eps)
            .map(|(x, e)| R::lit(post * x).with_eps(post * e))
            .collect())
    }

    fn pressure_cg<R: Real>(
        &self,
        tape: &mut Tape,
        div: &Array<R>,
        scale: f64,
        s: &SolveSettings,
    ) -> Result<Array<R>, Error> {
        let grid = *self;
        let x = grid.solve_parts(&div.to_vec(), (scale, 1.0), s, "forward")?;
        let p = Array::from_vec(x).named("pressure");
        let (pb, db, settings) = (p.clone(), div.clone(), *s);
        let (pt, dt) = (p.clone(), div.clone());
        tape.record_fn(
            "fluid pressure CG",
            &[div],
            &[&p],
            || {},
            move || {
                // d L / d div = scale A^-T d L / d p, and A is symmetric.
                let (Some(gp), Some(gd)) = (pb.grad_buffer(), db.grad_buffer()) else {
                    return Ok(());
                };
                let lambda = grid.solve_parts(&gp.to_vec(), (1.0, scale), &settings, "adjoint")?;
                gd.modify(|gd| gd.iter_mut().zip(lambda).for_each(|(gd, l)| *gd += l));
                Ok(())
            },
        )
        .dual_safe()
        .with_tangent(move || -> Result<(), Error> {
            let out = pt.ensure_tangent();
            let Some(td) = dt.tangent_buffer() else {
                out.modify(|o| o.iter_mut().for_each(|o| *o = R::zero()));
                return Ok(());
            };
            let x = grid.solve_parts(&td.to_vec(), (scale, 1.0), &settings, "tangent")?;
            out.assign(&x);
            Ok(())
        });
        Ok(p)
    }

    /// `(u, v)` projected onto zero divergence: the divergence, the pressure by `method`, and
    /// the gradient subtracted, all on `tape`.
    pub fn project<R: Real>(
        &self,
        tape: &mut Tape,
        u: &Array<R>,
        v: &Array<R>,
        method: &Pressure,
    ) -> Result<(Array<R>, Array<R>), Error> {
        self.want(2, "FluidGrid::project")?;
        self.check(u)?;
        self.check(v)?;
        let div = self.divergence(tape, u, v)?;
        let p = self.pressure(tape, &div, method)?;
        let (pu, pv) = (
            Array::zeros(self.cells()).named("u"),
            Array::zeros(self.cells()).named("v"),
        );
        tape.launch(
            subtract_gradient,
            self.cells(),
            (u, v, &p, self.n, R::lit(self.dx), &pu, &pv),
        );
        Ok((pu, pv))
    }

    /// One step of smoke: the velocity and the `density` advected by the velocity, then the
    /// velocity projected. Returns `(u, v, density)`.
    pub fn step<R: Real>(
        &self,
        tape: &mut Tape,
        u: &Array<R>,
        v: &Array<R>,
        density: &Array<R>,
        dt: f64,
        method: &Pressure,
    ) -> Result<Flow<R>, Error> {
        self.want(2, "FluidGrid::step")?;
        check_dt(dt)?;
        for a in [u, v, density] {
            self.check(a)?;
        }
        let au = self.advect(tape, u, u, v, dt)?;
        let av = self.advect(tape, v, u, v, dt)?;
        let d = self.advect(tape, density, u, v, dt)?;
        let (pu, pv) = self.project(tape, &au, &av, method)?;
        Ok((pu, pv, d))
    }
}

/// The 3D forms of [`FluidGrid::project`] and [`FluidGrid::step`].
impl FluidGrid {
    /// `(u, v, w)` projected onto zero divergence on a 3D grid.
    pub fn project_3d<R: Real>(
        &self,
        tape: &mut Tape,
        [u, v, w]: [&Array<R>; 3],
        method: &Pressure,
    ) -> Result<[Array<R>; 3], Error> {
        self.want(3, "FluidGrid::project_3d")?;
        for a in [u, v, w] {
            self.check(a)?;
        }
        let div = self.divergence_3d(tape, u, v, w)?;
        let p = self.pressure(tape, &div, method)?;
        let out = [(); 3].map(|_| Array::zeros(self.cells()).named("velocity"));
        tape.launch(
            subtract_gradient3,
            self.cells(),
            (
                u,
                v,
                w,
                &p,
                self.n,
                R::lit(self.dx),
                &out[0],
                &out[1],
                &out[2],
            ),
        );
        Ok(out)
    }

    /// One step of smoke on a 3D grid: the velocity `[u, v, w]` and the density advected
    /// (trilinear), then the velocity projected. Returns the velocity and the density.
    pub fn step_3d<R: Real>(
        &self,
        tape: &mut Tape,
        velocity: [&Array<R>; 3],
        density: &Array<R>,
        dt: f64,
        method: &Pressure,
    ) -> Result<([Array<R>; 3], Array<R>), Error> {
        self.want(3, "FluidGrid::step_3d")?;
        check_dt(dt)?;
        let [u, v, w] = velocity;
        for a in [u, v, w, density] {
            self.check(a)?;
        }
        let scale = R::lit(dt / self.dx);
        let advected = |tape: &mut Tape, q: &Array<R>| {
            let out = Array::zeros(self.cells()).named(format!("advected {}", q.label()));
            tape.launch(advect3, self.cells(), (q, u, v, w, self.n, scale, &out));
            out
        };
        let (au, av, aw, d) = (
            advected(tape, u),
            advected(tape, v),
            advected(tape, w),
            advected(tape, density),
        );
        let projected = self.project_3d(tape, [&au, &av, &aw], method)?;
        Ok((projected, d))
    }
}

/// `out = A p` for the pressure operator of [`kernels::pressure_jacobi`] (`dim = 2`) or
/// [`kernels::pressure_jacobi3`] (`dim = 3`), on the host in f64.
pub fn apply_pressure_operator(n: usize, dim: usize, p: &[f64], out: &mut [f64]) {
    let cells = n.pow(dim as u32);
    // One row along the last axis (stride 1) at a time, each row's cells summing their
    // neighbours axis by axis (`+` then `-`), the order the bits depend on.
    let row = |r: usize, o: &mut [f64]| {
        // The row's coordinates on the axes before the last, with their strides.
        let before: [(usize, usize); 2] = match dim {
            2 => [(r, n), (0, 0)],
            _ => [(r / n, n * n), (r % n, n)],
        };
        let before = &before[..dim - 1];
        let at = |c: usize, t: usize, stride: usize, diag: &mut f64, off: &mut f64| {
            if c + 1 < n {
                *diag += 1.0;
                if c + 2 < n {
                    *off += p[t + 2 * stride];
                }
            }
            if c >= 1 {
                *diag += 1.0;
                if c >= 2 {
                    *off += p[t - 2 * stride];
                }
            }
        };
        let cell = |k: usize| {
            let t = r * n + k;
            let (mut diag, mut off) = (0.0, 0.0);
            for &(c, stride) in before {
                at(c, t, stride, &mut diag, &mut off);
            }
            at(k, t, 1, &mut diag, &mut off);
            diag * p[t] - off
        };
        // Cells two or more from every wall have all their neighbours: the same sums, unrolled
        // (`0 + a` is `a` exactly).
        let interior = n >= 5 && before.iter().all(|&(c, _)| c >= 2 && c + 2 < n);
        if !interior {
            o.iter_mut().enumerate().for_each(|(k, o)| *o = cell(k));
            return;
        }
        let t0 = r * n;
        for k in (0..2).chain(n - 2..n) {
            o[k] = cell(k);
        }
        match dim {
            2 => {
                for (k, o) in o.iter_mut().enumerate().take(n - 2).skip(2) {
                    let t = t0 + k;
                    let off = p[t + 2 * n] + p[t - 2 * n] + p[t + 2] + p[t - 2];
                    *o = 4.0 * p[t] - off;
                }
            }
            _ => {
                let m = n * n;
                for (k, o) in o.iter_mut().enumerate().take(n - 2).skip(2) {
                    let t = t0 + k;
                    let off = p[t + 2 * m]
                        + p[t - 2 * m]
                        + p[t + 2 * n]
                        + p[t - 2 * n]
                        + p[t + 2]
                        + p[t - 2];
                    *o = 6.0 * p[t] - off;
                }
            }
        }
    };
    for (r, o) in out[..cells].chunks_mut(n).enumerate() {
        row(r, o);
    }
}

fn check_dt(dt: f64) -> Result<(), Error> {
    if dt.is_finite() && dt > 0.0 {
        Ok(())
    } else {
        Err(invalid("dt", format!("{dt} must be finite and positive")))
    }
}

fn invalid(what: &str, message: String) -> Error {
    Error::InvalidInput {
        what: what.into(),
        message,
    }
}

pub mod scenes;
