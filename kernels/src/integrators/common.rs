//! Pieces shared by the integrators of this crate: the rigid body step (every particle
//! integrator advances the bodies with the semi-implicit kernel of [`crate::rigid`]), a
//! state built from new particle arrays, and what the Newton solves of
//! [`ImplicitEuler`](super::ImplicitEuler) and [`crate::statics::Equilibrium`] share: private
//! copies of the parameter arrays, flat `f64` vectors, residual checks, input checks.

use adflex_runtime::{AnyArray, Array, Error, Real, Tape, Vec3};

use crate::forces::{real_parts, Param, ParamCopy};
use crate::model::Model;
use crate::precompiled::precompiled;
use crate::solver::newton::Parts;
use crate::state::BodyState;
use crate::state::{Control, State};

/// Advances the rigid bodies of `state` (if any) by `dt` (s) with
/// [`crate::rigid::RigidBodies::integrate`] (semi-implicit Euler), recording on `tape`.
pub(crate) fn step_bodies_generic<R: Real>(
    model: &Model<R>,
    tape: &mut Tape,
    state: &State<R>,
    control: Option<&Control<R>>,
    dt: R,
) -> Option<BodyState<R>> {
    let bodies = model.bodies.as_ref()?;
    let s = state
        .bodies
        .as_ref()
        .expect("the model has rigid bodies but the state has none");
    let (f, t) = model
        .eval_body_forces(tape, state, control)
        .expect("the model has rigid bodies");
    Some(bodies.integrate(
        tape,
        s,
        &f,
        &t,
        model.gravity_per_world(),
        &model.body_world,
        dt,
    ))
}

precompiled! {
    /// [`step_bodies_generic`], by code compiled in this crate for `f32` and `f64`.
    fn step_bodies(
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Option<BodyState<R>> {
        step_bodies_generic(model, tape, state, control, dt)
    }
}

/// The arrays of a state, particles then bodies.
fn state_arrays<R: Real>(s: &State<R>) -> Vec<&dyn AnyArray> {
    let mut out: Vec<&dyn AnyArray> = vec![&s.x, &s.v];
    if let Some(b) = &s.bodies {
        out.extend([&b.x as &dyn AnyArray, &b.q, &b.v, &b.w]);
    }
    out
}

/// The end of every integrator's step (`who`, whose first record is `first` on `tape`): the
/// tape's anomaly if this step recorded it ([`Tape::check_finite`] mode: the first kernel that
/// wrote a NaN/Inf), then the new state, which must be finite: a
/// NaN/Inf in it is an error rather than a state. The error names the first non-finite input
/// that explains it (the old state, a force's parameter array, the control's arrays, the
/// gravity) as [`Error::InvalidInput`], or else the state array and index that became
/// non-finite in this step as [`Error::NonFinite`] (the forces overflowed: a smaller `dt`, or
/// an unstable integrator). One pass over the new state's arrays (a few percent of a
/// semi-implicit step on the cloth benchmark, see `docs/performance.md`).
pub(crate) fn finish_step<R: Real>(
    who: &str,
    model: &Model<R>,
    tape: &Tape,
    first: usize,
    old: &State<R>,
    control: Option<&Control<R>>,
    new: State<R>,
) -> Result<State<R>, Error> {
    // Only an anomaly of this step's records (`first..` on the tape): one of an earlier step
    // was that step's error, and a retry on the same tape must not fail with it again.
    if let Some(e @ Error::NonFinite { launch, .. }) = tape.anomaly() {
        if *launch >= first {
            return Err(e.clone());
        }
    }
    let Some((array, index)) = state_arrays(&new)
        .into_iter()
        .find_map(|a| a.first_non_finite().map(|k| (a, k)))
    else {
        return Ok(new);
    };
    let params = model.params();
    let mut inputs: Vec<&dyn AnyArray> = state_arrays(old);
    inputs.push(&model.particle_inv_mass);
    inputs.extend(params.iter().map(|(_, _, a)| &**a));
    if let Some(c) = control {
        inputs.extend(c.particle_f.iter().map(|a| a as &dyn AnyArray));
        inputs.extend(c.tet_activation.iter().map(|a| a as &dyn AnyArray));
        inputs.extend(c.body_f.iter().map(|a| a as &dyn AnyArray));
        inputs.extend(c.body_t.iter().map(|a| a as &dyn AnyArray));
    }
    for a in inputs {
        if let Some(k) = a.first_non_finite() {
            let owner = params
                .iter()
                .find(|(_, _, p)| p.id() == a.id())
                .map_or(String::new(), |(f, p, _)| format!(" (parameter `{f}.{p}`)"));
            return Err(Error::InvalidInput {
                what: format!("{}[{k}]", a.label()),
                message: format!(
                    "{who}: a NaN or infinite value in an input of the step{owner}; the new \
                     state's `{}[{index}]` is not finite. Fix the value (or whatever computed \
                     it, e.g. an optimizer step)",
                    array.label()
                ),
            });
        }
    }
    check_inputs(who, model, &[], &[])?;
    // From finite inputs: the forces overflowed (a dt beyond the integrator's stability limit,
    // or a singular force); `tape.check_finite(true)` names the first kernel.
    Err(Error::NonFinite {
        kernel: format!("{who} step"),
        launch: first,
        param: "new state".into(),
        array: array.label(),
        index,
        pass: "forward",
    })
}

/// A state with particle arrays `x`, `v` and no bodies (for intermediate stages).
pub(crate) fn particles<R: Real>(x: &Array<Vec3<R>>, v: &Array<Vec3<R>>) -> State<R> {
    State {
        x: x.clone(),
        v: v.clone(),
        bodies: None,
    }
}

/// New, zeroed particle arrays named `x` and `v`, for a step's output.
pub(crate) fn new_xv<R: Real>(n: usize) -> (Array<Vec3<R>>, Array<Vec3<R>>) {
    (Array::zeros(n).named("x"), Array::zeros(n).named("v"))
}

/// Checks a step's `dt` (s): finite and positive, or [`Error::InvalidInput`] naming
/// `integrator`. Returns it in f64.
pub(crate) fn check_dt<R: Real>(integrator: &str, dt: R) -> Result<f64, Error> {
    let d = dt.to_f64();
    if d.is_finite() && d > 0.0 {
        Ok(d)
    } else {
        Err(Error::InvalidInput {
            what: "dt".into(),
            message: format!(
                "{integrator}: the time step must be finite and positive (seconds), got {d}"
            ),
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Private copies of the parameter arrays, and the helpers of the Newton solves
// (ImplicitEuler, statics::Equilibrium).

/// A parameter array of the model and its private copy.
pub(crate) type Link = Box<dyn ParamCopy>;

/// The model and control with every differentiable array the particle forces read replaced
/// by a private copy (with a gradient buffer if `grads`).
pub(crate) struct Copies<R: Real> {
    pub(crate) model: Model<R>,
    pub(crate) control: Option<Control<R>>,
    pub(crate) links: Vec<Link>,
}

/// A clone of `model` (array handles) without its host-side triangle list, which the forces
/// do not use (and which a tape would otherwise keep once per step).
pub(crate) fn forces_only<R: Real>(model: &Model<R>) -> Model<R> {
    let mut m = model.clone();
    m.triangles = Vec::new();
    m
}

/// The copies: the inverse masses, the gravity, every force's parameter arrays (its
/// [`Force::params_mut`](crate::forces::Force::params_mut) visitor, so a force added outside
/// the library is covered), and the control's arrays.
pub(crate) fn copies<R: Real>(
    model: &Model<R>,
    control: Option<&Control<R>>,
    grads: bool,
) -> Copies<R> {
    let mut m = forces_only(model);
    let mut c = control.cloned();
    let mut l = Vec::new();
    l.push(m.particle_inv_mass.substitute(grads));
    l.push(m.gravity.substitute(grads));
    for force in &mut m.forces {
        force.params_mut(&mut |_, p| l.push(p.substitute(grads)));
    }
    if let Some(c) = &mut c {
        if let Some(f) = &mut c.particle_f {
            l.push(f.substitute(grads));
        }
        if let Some(a) = &mut c.tet_activation {
            l.push(a.substitute(grads));
        }
    }
    Copies {
        model: m,
        control: c,
        links: l,
    }
}

/// In `Dual` (a Hessian-vector product), a solver's model (its forces, inverse masses and
/// gravity) and control with their real parts in `f64` ([`Force::to_f64`]). Newton's
/// iterations and every linear solve of the implicit function theorem need only the real
/// parts of the Jacobian, and run on the twin in `f64`, since a `Dual` pass costs several
/// `f64` ones; only the passes that carry the direction (the derivative part of a right-hand
/// side, and `A1^T lambda0`) stay in `Dual`.
///
/// [`Force::to_f64`]: crate::forces::Force::to_f64
pub(crate) struct Twin {
    model: Model<f64>,
    control: Option<Control<f64>>,
    /// The inverse masses (1/kg).
    pub(crate) inv_mass: Vec<f64>,
}

impl Twin {
    /// `None` in `f32` and `f64`, or if a force has no `to_f64` (the solves then run in `R`).
    pub(crate) fn of<R: Real>(model: &Model<R>, control: Option<&Control<R>>) -> Option<Twin> {
        if !R::DUAL {
            return None;
        }
        let forces = model
            .forces
            .iter()
            .map(|f| f.to_f64())
            .collect::<Option<Vec<_>>>()?;
        let model = Model::<f64> {
            worlds: model.worlds.clone(),
            particle_world: model.particle_world.clone(),
            body_world: model.body_world.clone(),
            particle_count: model.particle_count,
            particle_x: real_parts(&model.particle_x),
            particle_v: real_parts(&model.particle_v),
            particle_inv_mass: real_parts(&model.particle_inv_mass),
            gravity: real_parts(&model.gravity),
            particle_radius: model.particle_radius.to_f64(),
            particle_radii: model.particle_radii.as_ref().map(real_parts),
            triangles: Vec::new(),
            forces,
            // The particles' accelerations do not read them (bodies are stepped apart).
            bodies: None,
            distance_constraints: None,
        };
        let control = control.map(|c| Control::<f64> {
            particle_f: c.particle_f.as_ref().map(real_parts),
            tet_activation: c.tet_activation.as_ref().map(real_parts),
            body_f: None,
            body_t: None,
        });
        Some(Twin {
            inv_mass: model.particle_inv_mass.to_vec(),
            model,
            control,
        })
    }

    /// The twin as a solver's copies (array handles: nothing maps back to the originals).
    pub(crate) fn copies(&self) -> Copies<f64> {
        Copies {
            model: self.model.clone(),
            control: self.control.clone(),
            links: Vec::new(),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// The particle systems of the Newton solves.

/// The particles' degrees of freedom in a Newton solve, three per particle.
pub(crate) struct Dofs {
    /// Per DOF: the mass (kg) on free DOFs, 0 on pinned ones. A constant of the host
    /// arithmetic even when a Hessian-vector product's direction moves the inverse masses:
    /// in the implicit-function-theorem solves `M` cancels (`lambda = M^-1 (..)`, then the
    /// seeds `M lambda`), so its derivative part would drop out (the kernels carry the
    /// masses' own, e.g. in `a = w f`).
    pub(crate) mass: Vec<f64>,
    /// Per DOF: whether it is free (inverse mass > 0).
    pub(crate) free: Vec<bool>,
    /// Each world's DOFs (three per particle of [`WorldRanges::particles`]): the blocks
    /// the solves treat apart.
    ///
    /// [`WorldRanges::particles`]: crate::model::WorldRanges::particles
    pub(crate) worlds: Vec<std::ops::Range<usize>>,
}

impl Dofs {
    pub(crate) fn new<R: Real>(model: &Model<R>, inv_mass: &[R]) -> Self {
        let w: Vec<f64> = inv_mass.iter().flat_map(|w| [w.to_f64(); 3]).collect();
        let mut worlds: Vec<std::ops::Range<usize>> = model
            .worlds
            .iter()
            .map(|r| 3 * r.particles.start..3 * r.particles.end)
            .collect();
        // The worlds tile the particles (`ModelBuilder::add_world` appends them); anything
        // else is solved as one block.
        let tiles = worlds.first().is_some_and(|r| r.start == 0)
            && worlds.windows(2).all(|p| p[0].end == p[1].start)
            && worlds.last().is_some_and(|r| r.end == w.len());
        if !tiles {
            worlds.clear();
            worlds.push(0..w.len());
        }
        Dofs {
            worlds,
            mass: w
                .iter()
                .map(|&w| if w > 0.0 { 1.0 / w } else { 0.0 })
                .collect(),
            free: w.iter().map(|&w| w > 0.0).collect(),
        }
    }

    /// Sets the pinned DOFs of `out` to `u`'s: the identity rows of a solve's operator.
    pub(crate) fn pinned_identity(&self, out: &mut [f64], u: &[f64]) {
        for ((o, &u), &free) in out.iter_mut().zip(u).zip(&self.free) {
            if !free {
                *o = u;
            }
        }
    }

    /// `c M u`, part by part (0 on pinned DOFs if `masked`).
    pub(crate) fn mass_product(&self, u: &Parts, c: f64, masked: bool) -> Parts {
        u.map(|u| {
            (0..u.len())
                .map(|k| match !masked || self.free[k] {
                    true => c * self.mass[k] * u[k],
                    false => 0.0,
                })
                .collect()
        })
    }

    /// Zeroes the pinned DOFs of `v`.
    pub(crate) fn mask(&self, v: &mut [f64]) {
        v.iter_mut().zip(&self.free).for_each(|(v, &f)| {
            if !f {
                *v = 0.0
            }
        });
    }
}

/// The accelerations recorded at one iterate of a Newton solve (unknowns `u`), on their own
/// tape.
pub(crate) struct Point<R: Real> {
    pub(crate) tape: Tape,
    pub(crate) x: Array<Vec3<R>>,
    pub(crate) v: Array<Vec3<R>>,
    pub(crate) a: Array<Vec3<R>>,
    pub(crate) u: Vec<f64>,
    pub(crate) a_val: Vec<f64>,
}

/// Where an implicit solve's forward derivative (the implicit function theorem's tangent)
/// takes the inputs' derivatives from.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Through {
    /// Their tangent buffers, by a tangent pass (forward mode).
    Tangents,
    /// Their [`Dual`](adflex_runtime::Dual) derivative parts, read off the accelerations'
    /// (a Hessian-vector product's first sweep).
    DerivativeParts,
}

/// The tangent of the accelerations at `p` for the state tangents `dx`, `dv` and the
/// parameters' own tangents (the copies share them for the pass): the right-hand side of an
/// implicit-function-theorem tangent solve. Fails as the tangent pass fails (`failure`
/// names the solver).
pub(crate) fn acceleration_tangent<R: Real>(
    c: &Copies<R>,
    p: &mut Point<R>,
    dx: &[f64],
    dv: &[f64],
    failure: &crate::solver::newton::PassFailure,
) -> Result<Vec<f64>, Error> {
    for l in &c.links {
        l.share_tangent(true);
    }
    p.x.ensure_tangent().assign(&unflat::<R>(dx));
    p.v.ensure_tangent().assign(&unflat::<R>(dv));
    let ran = p.tape.tangent();
    let ad =
        p.a.tangent_buffer()
            .map_or_else(|| vec![0.0; dx.len()], |t| flat(&t));
    for l in &c.links {
        l.share_tangent(false);
    }
    ran.map_err(|e| failure.in_pass("tangent (forward-mode)", e))?;
    Ok(ad)
}

/// Records the accelerations of the copies' model at `x`, `v` on a new tape.
pub(crate) fn record<R: Real>(
    c: &Copies<R>,
    x: Array<Vec3<R>>,
    v: Array<Vec3<R>>,
    u: &[f64],
) -> Point<R> {
    let mut tape = Tape::new();
    let a = c
        .model
        .eval_accelerations(&mut tape, &particles(&x, &v), c.control.as_ref());
    let a_val = flat(&a);
    Point {
        tape,
        x,
        v,
        a,
        u: u.to_vec(),
        a_val,
    }
}

/// Seeds the accelerations' gradient at `p` with `seed` and runs the adjoint kernels of its
/// scratch tape; returns the gradients of the positions and of the velocities (zeros where
/// one has none), with their derivative parts in `Dual` (an error without context: see
/// `PassFailure::in_pass`).
pub(crate) fn pull<R: Real>(p: &mut Point<R>, seed: &Parts) -> Result<(Parts, Parts), Error> {
    p.x.zero_grad();
    p.v.zero_grad();
    p.a.ensure_grad().assign(&unflat_parts::<R>(seed));
    p.tape.backward_with(&[&p.a])?;
    let grad = |a: &Array<Vec3<R>>| match a.grad() {
        Ok(g) => flat_parts(&g),
        Err(_) => seed.map(|s| vec![0.0; s.len()]),
    };
    Ok((grad(&p.x), grad(&p.v)))
}

pub(crate) fn flat<R: Real>(a: &Array<Vec3<R>>) -> Vec<f64> {
    a.to_vec()
        .iter()
        .flat_map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
        .collect()
}

pub(crate) fn unflat<R: Real>(v: &[f64]) -> Vec<Vec3<R>> {
    v.chunks_exact(3)
        .map(|c| Vec3::new(R::lit(c[0]), R::lit(c[1]), R::lit(c[2])))
        .collect()
}

/// The components of `a` flat, with their derivative parts if `R` is
/// [`Dual`](adflex_runtime::Dual).
pub(crate) fn flat_parts<R: Real>(a: &Array<Vec3<R>>) -> Parts {
    let v = a.to_vec();
    let re = v
        .iter()
        .flat_map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
        .collect();
    let eps = R::DUAL.then(|| {
        v.iter()
            .flat_map(|p| [p.x.eps(), p.y.eps(), p.z.eps()])
            .collect()
    });
    Parts { re, eps }
}

/// Values from flat parts (a derivative part is dropped unless `R` is `Dual`).
pub(crate) fn unflat_parts<R: Real>(v: &Parts) -> Vec<Vec3<R>> {
    let Some(eps) = &v.eps else {
        return unflat(&v.re);
    };
    let c = |k: usize| R::lit(v.re[k]).with_eps(eps[k]);
    (0..v.re.len() / 3)
        .map(|i| Vec3::new(c(3 * i), c(3 * i + 1), c(3 * i + 2)))
        .collect()
}

/// Whether `R` is single precision (it cannot tell 1 from 1 + 1e-10).
pub(crate) fn is_f32<R: Real>() -> bool {
    R::lit(1.0 + 1e-10).to_f64() == 1.0
}

/// The unit roundoff of `R`.
pub(crate) fn epsilon<R: Real>() -> f64 {
    if is_f32::<R>() {
        f32::EPSILON as f64
    } else {
        f64::EPSILON
    }
}

/// `a.grad += g` if `a` has a gradient buffer.
pub(crate) fn add_into<R: Real>(a: &Array<Vec3<R>>, g: &Parts) {
    if let Some(buf) = a.grad_buffer() {
        let add = unflat_parts::<R>(g);
        buf.modify(|d| d.iter_mut().zip(add).for_each(|(d, a)| *d += a));
    }
}

/// What [`check_visited`] looks for in an array the forces read but no visitor lists.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Needs {
    /// A gradient (`requires_grad`, or a gradient buffer): the solver's adjoint would add
    /// scratch products into it, a wrong gradient.
    Gradient,
    /// A tangent buffer: the solver's forward mode would ignore it.
    Tangent,
}

/// [`Error::InvalidInput`] if the force model, recorded on `tape` with the private copies
/// `c` at the state `(x, v)`, read an array that needs a derivative (see [`Needs`]) but is
/// neither the state nor a copy: a parameter no force's
/// [`Force::params_mut`](crate::forces::Force::params_mut) visits, which the solver (`who`)
/// cannot differentiate. The error names the force, the kernel, its parameter and the array.
pub(crate) fn check_visited<R: Real>(
    who: &str,
    c: &Copies<R>,
    tape: &Tape,
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    needs: Needs,
) -> Result<(), Error> {
    let mut known: std::collections::HashSet<u64> = c.links.iter().map(|l| l.copy().id()).collect();
    known.extend([x.id(), v.id()]);
    for input in tape.inputs() {
        let a = &input.array;
        let missed = !known.contains(&a.id())
            && match needs {
                Needs::Gradient => a.is_requires_grad() || a.has_grad(),
                Needs::Tangent => a.tangent_any().is_some(),
            };
        if !missed {
            continue;
        }
        // Which force reads it (only on this error path: one evaluation per force).
        let state = particles(x, v);
        let cx = c.model.context(&state, c.control.as_ref());
        let force = c.model.forces.iter().find(|f| {
            let mut t = Tape::new();
            f.eval(&cx, &mut t, &Array::zeros(x.len()));
            t.inputs().iter().any(|i| i.array.id() == a.id())
        });
        let force = force.map_or("a force".to_string(), |f| format!("force `{}`", f.name()));
        let (what, consequence) = match needs {
            Needs::Gradient => (
                "requires a gradient",
                "its gradient would be wrong (the solver's adjoint works on private copies of \
                 the visited parameters only)",
            ),
            Needs::Tangent => (
                "carries a tangent",
                "its tangent would be ignored (the solver's forward mode works on private copies \
                 of the visited parameters only)",
            ),
        };
        return Err(Error::InvalidInput {
            what: a.label(),
            message: format!(
                "{who}: {force} reads `{}` (parameter `{}` of kernel `{}`), which {what}, but \
                 the force's `params_mut` does not visit it, so {consequence}. Add \
                 `visit(\"{}\", &mut self.<field>)` to its `params_mut`, or use an array that \
                 does not require a gradient",
                a.label(),
                input.param,
                input.step,
                input.param
            ),
        });
    }
    Ok(())
}

/// [`Error::InvalidInput`] for the first NaN/Inf in `arrays` (the state) or in a parameter
/// array the forces read (named by label and index), or in the gravity; `who` names the solver.
pub(crate) fn check_inputs<R: Real>(
    who: &str,
    model: &Model<R>,
    arrays: &[&dyn AnyArray],
    links: &[Link],
) -> Result<(), Error> {
    let arrays = arrays
        .iter()
        .copied()
        .chain(links.iter().map(|l| l.original()));
    for a in arrays {
        if let Some(k) = a.first_non_finite() {
            return Err(Error::InvalidInput {
                what: format!("{}[{k}]", a.label()),
                message: format!(
                    "{who}: a NaN or infinite value in the state or a parameter; every force \
                     and the Newton residual would be NaN. Fix the value (or whatever computed it)"
                ),
            });
        }
    }
    if let Some(k) = model.gravity.first_non_finite() {
        return Err(Error::InvalidInput {
            what: format!("gravity[{k}]"),
            message: format!("{who}: the gravity of world {k} is not finite"),
        });
    }
    Ok(())
}
