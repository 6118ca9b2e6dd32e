//! The component interface of a force: the [`Force`] trait every force implements (the
//! library's and a user's), what it reads ([`ForceContext`]), its parameter visitor
//! ([`Param`], [`ParamCopy`]), its rows of the guide's parameter table ([`ParamDoc`]), and a
//! library force's builder part (`ForcePart`, crate-internal). See
//! [`crate::forces`] for an example.

use std::any::Any;
use std::fmt::Debug;

use adflex_runtime::{AnyArray, Array, Element, Real, Tape, Vec3};

use crate::state::Control;

/// One row of the guide's parameter table (`docs/guide.md`, "Gradient targets"): a parameter
/// of a library force, its units, and whether it is a differentiable array (what
/// [`Force::params_mut`] visits, in its order) or a scalar shared by all elements. Each
/// library force lists its rows in its file (`PARAMS`); tests check the guide, the visitor
/// and the component's fields against them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParamDoc {
    /// The parameter's name (the visitor's name for an array, the field's for a scalar).
    pub name: &'static str,
    /// Its units (and what it is).
    pub units: &'static str,
    /// A differentiable array (one value per element), or a scalar shared by all elements.
    pub array: bool,
}

impl ParamDoc {
    /// A differentiable parameter array.
    pub const fn array(name: &'static str, units: &'static str) -> Self {
        ParamDoc {
            name,
            units,
            array: true,
        }
    }

    /// A scalar shared by all the force's elements (not a gradient target).
    pub const fn scalar(name: &'static str, units: &'static str) -> Self {
        ParamDoc {
            name,
            units,
            array: false,
        }
    }
}

/// What a force reads besides its own arrays: the state and the step's control.
#[derive(Clone, Copy, Debug)]
pub struct ForceContext<'a, R: Real> {
    /// Particle positions (m).
    pub x: &'a Array<Vec3<R>>,
    /// Particle velocities (m/s).
    pub v: &'a Array<Vec3<R>>,
    /// The step's control, if any.
    pub control: Option<&'a Control<R>>,
    /// The model's particle radius for contact (m), every particle's unless `particle_radii`
    /// is given.
    pub particle_radius: R,
    /// Per-particle contact radii (m), if the model has them ([`crate::Model::particle_radii`]).
    pub particle_radii: Option<&'a Array<R>>,
    /// Per particle: its world ([`crate::Model::particle_world`]), if the model has several
    /// worlds. A force between particles touches only particles of one world.
    pub particle_world: Option<&'a Array<u32>>,
    /// Per particle: its world, zeros in a model of one world ([`crate::Model::particle_world`]
    /// whatever the number of worlds; read it through [`ForceContext::particle_worlds`]).
    pub particle_world_ids: &'a Array<u32>,
}

impl<R: Real> ForceContext<'_, R> {
    /// Per particle: its world, zeros in a model of one world (where an element's energy goes,
    /// [`Force::energy`]): a handle to the model's array, not a copy.
    pub fn particle_worlds(&self) -> Array<u32> {
        self.particle_world_ids.clone()
    }
}

/// A force on the particles: a component of a [`Model`](crate::Model).
///
/// Implement it once, for a `Clone + Debug` struct holding the force's arrays (clones are
/// array handles, which share the data): [`Force::name`], [`Force::eval`], and
/// [`Force::params_mut`], the visitor over every differentiable parameter array the force
/// reads. The visitor is the single list that
/// [`ImplicitEuler`](crate::integrators::ImplicitEuler) copies (it evaluates the force with
/// private copies substituted through the visitor and maps their gradients back), that
/// [`Model::params`](crate::Model::params) and gradient checks perturb, and that
/// [`Model::requires_grad`](crate::Model::requires_grad) finds by name: a parameter the
/// visitor misses gets no gradient through `ImplicitEuler`.
///
/// The force must be differentiable through the tape, i.e. record `#[diff_kernel]` launches
/// (or `record_fn` steps with a backward and a tangent): `ImplicitEuler` needs the adjoint and
/// the tangent of the force.
pub trait Force<R: Real>: ForceClone<R> + Debug + Send + Sync {
    /// A short name (`"springs"`): what [`Model::force_named`](crate::Model::force_named)
    /// and [`Model::requires_grad`](crate::Model::requires_grad) look for.
    fn name(&self) -> &'static str;

    /// Records the force's kernels on `tape`, accumulating the force on each particle (N)
    /// into `f` (with `atomic_add`: other forces accumulate into the same array).
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>);

    /// Records the force's potential energy (J), each element's added into its world's entry
    /// `energy[w]` (`energy` has one entry per world; [`ForceContext::particle_worlds`]
    /// gives each particle's), and returns `true`;
    /// the default (a force without a potential: drag, wind) records nothing and returns
    /// `false`. For a force with damping or friction, the energy of its conservative part
    /// (the library's springs, membranes, tetrahedra, bending and contact penalties do this).
    ///
    /// [`ImplicitEuler`](crate::integrators::ImplicitEuler)'s line search uses it: the
    /// incremental potential it decreases is exact for the forces that define an energy, and
    /// estimated from the force for the others, so defining one makes large steps converge
    /// more reliably; its gradient should be minus the force at zero velocity (the library's
    /// tests check it; bending's differs by a term second order in the bend, see
    /// [`bending_energy`](crate::forces::bending::bending_energy)). A wrong energy cannot make a step wrong, since a step is
    /// converged only when the residual is, but can make it fail to converge.
    fn energy(&self, _cx: &ForceContext<'_, R>, _tape: &mut Tape, _energy: &Array<R>) -> bool {
        false
    }

    /// Calls `visit(name, array)` for every differentiable parameter array the force reads
    /// (not index arrays, not scalars), in a fixed order. `visit` may replace the array
    /// ([`Param::substitute`]): the force must then read the replacement.
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param));

    /// The force in `f64`: the real parts of its values (a [`Dual`](adflex_runtime::Dual)'s
    /// derivative parts dropped; [`real_parts`] converts an array, index arrays are shared).
    /// [`ImplicitEuler`](crate::integrators::ImplicitEuler) then runs a Hessian-vector
    /// product's Newton iterations and linear solves, which need only the real parts, in
    /// `f64` (several times cheaper than in `Dual`), and keeps `Dual` for the passes that carry
    /// the direction. The default, `None`, runs them in `R`: the same result, slower. The
    /// library's forces all have it.
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        None
    }
}

/// The real parts of `a`'s values as a new array of `U`, the same type in `f64`
/// (`Vec3<Dual>` to `Vec3<f64>`), with `a`'s name: for [`Force::to_f64`].
///
/// ```
/// use adflex_kernels::forces::real_parts;
/// use adflex_runtime::{Array, Dual, Vec3};
///
/// let a = Array::from_vec(vec![Vec3::new(Dual::new(1.0, 5.0), Dual::new(2.0, 0.0), Dual::new(3.0, 1.0))]);
/// let b: Array<Vec3<f64>> = real_parts(&a);
/// assert_eq!(b.get(0), Vec3::new(1.0, 2.0, 3.0));
/// ```
///
/// # Panics
/// If `T` and `U` have different numbers of components, or none (an index array: share it,
/// `a.clone()`).
pub fn real_parts<T: Element, U: Element>(a: &Array<T>) -> Array<U> {
    assert!(
        T::DIM == U::DIM && T::DIM > 0,
        "real_parts: `{}` has {} components per element, its f64 type {}; index arrays are \
         shared, not converted",
        a.label(),
        T::DIM,
        U::DIM
    );
    let values = a.to_vec().into_iter().map(|t| {
        let mut u = U::zeroed();
        (0..T::DIM).for_each(|k| u.set_component(k, t.component(k)));
        u
    });
    let out = Array::from_vec(values.collect());
    match a.name() {
        Some(name) => out.named(&*name),
        None => out,
    }
}

/// Cloning and downcasting of a boxed [`Force`]; implemented for every `Force + Clone`.
pub trait ForceClone<R: Real> {
    /// A clone (array handles shared) in a box.
    fn clone_box(&self) -> Box<dyn Force<R>>;
    /// The force as [`Any`], to downcast to its type.
    fn as_any(&self) -> &dyn Any;
}

impl<R: Real, T: Force<R> + Clone + 'static> ForceClone<R> for T {
    fn clone_box(&self) -> Box<dyn Force<R>> {
        Box::new(self.clone())
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl<R: Real> Clone for Box<dyn Force<R>> {
    fn clone(&self) -> Self {
        self.clone_box()
    }
}

impl<R: Real> dyn Force<R> {
    /// Handles of the parameter arrays ([`Force::params_mut`]), with their names. They share
    /// the force's data and gradients: perturbing one perturbs the force.
    pub fn params(&self) -> Vec<(&'static str, Box<dyn AnyArray>)> {
        let mut copy = self.clone_box();
        let mut out = Vec::new();
        copy.params_mut(&mut |name, p| out.push((name, p.array().boxed())));
        out
    }

    /// The force as a `T`, if it is one.
    pub fn downcast_ref<T: 'static>(&self) -> Option<&T> {
        self.as_any().downcast_ref()
    }
}

/// A parameter array as [`Force::params_mut`] shows it: implemented by every
/// [`Array<T>`](Array).
pub trait Param: Send + Sync {
    /// The array.
    fn array(&self) -> &dyn AnyArray;
    /// Marks the array as requiring a gradient ([`Array::requires_grad`]).
    fn set_requires_grad(&self);
    /// Replaces the array by a private copy of its data (requiring a gradient if `grads`) and
    /// returns the pair.
    fn substitute(&mut self, grads: bool) -> Box<dyn ParamCopy>;
}

/// A parameter array and the private copy that replaced it ([`Param::substitute`]).
pub trait ParamCopy: Send + Sync {
    /// The original array.
    fn original(&self) -> &dyn AnyArray;
    /// The private copy that replaced it.
    fn copy(&self) -> &dyn AnyArray;
    /// Adds the copy's gradient into the original's (if both have one).
    fn add_grad(&self);
    /// Zeroes the copy's gradient.
    fn zero_copy_grad(&self);
    /// Gives the copy the original's tangent buffer (`true`) or none (`false`).
    fn share_tangent(&self, on: bool);
}

impl<T: Element> Param for Array<T> {
    fn array(&self) -> &dyn AnyArray {
        self
    }
    fn set_requires_grad(&self) {
        let _ = self.clone().requires_grad();
    }
    fn substitute(&mut self, grads: bool) -> Box<dyn ParamCopy> {
        let copy = self.deep_clone();
        let copy = if grads { copy.requires_grad() } else { copy };
        let original = std::mem::replace(self, copy.clone());
        Box::new(Substituted { original, copy })
    }
}

struct Substituted<T: Element> {
    original: Array<T>,
    copy: Array<T>,
}

impl<T: Element> ParamCopy for Substituted<T> {
    fn original(&self) -> &dyn AnyArray {
        &self.original
    }
    fn copy(&self) -> &dyn AnyArray {
        &self.copy
    }
    fn add_grad(&self) {
        if let (Some(g), Some(c)) = (self.original.grad_buffer(), self.copy.grad_buffer()) {
            AnyArray::add_from(&g, &c);
        }
    }
    fn zero_copy_grad(&self) {
        self.copy.zero_grad();
    }
    fn share_tangent(&self, on: bool) {
        self.copy.set_tangent(if on {
            self.original.tangent_buffer()
        } else {
            None
        });
    }
}

/// A library force's part of a scene description: what
/// [`ModelBuilder`](crate::ModelBuilder) records for it (its own file's builder methods check
/// and record the elements), and the force component it becomes.
pub(crate) trait ForcePart<R: Real>: Clone + Debug {
    /// The force, or `None` if the scene has none of it.
    fn build(&self) -> Option<Box<dyn Force<R>>>;

    /// Appends `other`'s elements as a new world's: their particle indices shifted by
    /// `offset`. A force given whole (the ground, drag, the shapes) is the worlds' shared
    /// environment: `other`'s must be this one's if both have it (`Err` says so).
    fn append(&mut self, other: &Self, offset: u32) -> Result<(), String>;

    /// This force's part of the worlds whose particles are `particles`: the elements inside,
    /// their particle indices shifted down by `particles.start` (elements never span worlds).
    /// A force given whole is the shared environment, kept whole.
    fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self;

    /// The first element whose particles are in different worlds (`world_of` per particle),
    /// as `(element index, its particles)`: such an element would couple the worlds.
    fn spanning_worlds(&self, _world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        None
    }
}

/// The first of `elements` whose particles are not all in one world.
pub(crate) fn first_spanning<const N: usize>(
    elements: &[[u32; N]],
    world_of: &[u32],
) -> Option<(usize, Vec<u32>)> {
    let w = |i: u32| world_of.get(i as usize).copied();
    elements
        .iter()
        .position(|e| e.iter().any(|&i| w(i) != w(e[0])))
        .map(|k| (k, elements[k].to_vec()))
}

/// A force given whole to the builder (the ground, drag, particle contact): present once set.
impl<R: Real, T: Force<R> + Clone + 'static> ForcePart<R> for Option<T> {
    fn build(&self) -> Option<Box<dyn Force<R>>> {
        self.clone().map(|f| Box::new(f) as Box<dyn Force<R>>)
    }

    fn append(&mut self, other: &Self, _offset: u32) -> Result<(), String> {
        shared(self, other)
    }

    fn worlds_in(&self, _particles: &std::ops::Range<u32>) -> Self {
        self.clone()
    }
}

/// Part of the environment every world shares: taken from `other` if `this` has none, else
/// they must be the same (compared by their `Debug` form: every number).
pub(crate) fn shared<T: Clone + Debug>(
    this: &mut Option<T>,
    other: &Option<T>,
) -> Result<(), String> {
    match (&*this, other) {
        (_, None) => Ok(()),
        (None, Some(o)) => {
            *this = Some(o.clone());
            Ok(())
        }
        (Some(a), Some(b)) if format!("{a:?}") == format!("{b:?}") => Ok(()),
        (Some(a), Some(b)) => Err(format!(
            "is shared by all worlds, and the world added has another one ({b:?}, the model \
             {a:?})"
        )),
    }
}

/// The indices of the `elements` whose particles are all in `particles`, and those elements
/// with their indices shifted down by `particles.start` (a share of the worlds).
pub(crate) fn elements_in<const N: usize>(
    elements: &[[u32; N]],
    particles: &std::ops::Range<u32>,
) -> (Vec<usize>, Vec<[u32; N]>) {
    elements
        .iter()
        .enumerate()
        .filter(|(_, e)| e.iter().all(|i| particles.contains(i)))
        .map(|(k, e)| (k, e.map(|i| i - particles.start)))
        .unzip()
}

/// The entries `idx` of `v`.
pub(crate) fn pick<T: Clone>(v: &[T], idx: &[usize]) -> Vec<T> {
    idx.iter().map(|&k| v[k].clone()).collect()
}

/// Element indices shifted by `offset` (a new world's particles).
pub(crate) fn shifted<const N: usize>(
    v: &[[u32; N]],
    offset: u32,
) -> impl Iterator<Item = [u32; N]> + '_ {
    v.iter().map(move |e| e.map(|i| i + offset))
}
