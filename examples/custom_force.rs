//! A force the library does not have, added to a model and stepped by the library's
//! integrators.
//!
//! Anchor springs pull particles towards fixed points (`f = ke (anchor - x)`). The force is
//! one `#[diff_kernel]` and one `impl Force` in this file; `ModelBuilder::add_force` plugs it
//! in. SemiImplicitEuler and ImplicitEuler (whose gradient comes from the implicit function
//! theorem, through the force's adjoint and tangent kernels) both step it, and the gradient of
//! a rollout's loss with respect to the anchors' stiffness is checked against central finite
//! differences in f64.
//!
//! Run: `cargo run --release --example custom_force`

use adflex::kernels::forces::{Force, ForceContext, Param};
use adflex::prelude::*;
use adflex::runtime::gradcheck::gradcheck;

/// Pulls particle `idx[k]` towards `anchor[k]` with stiffness `ke[k]` (N/m).
#[diff_kernel]
fn eval_anchors<R: Real>(
    x: &Array<Vec3<R>>,
    idx: &Array<u32>,
    anchor: &Array<Vec3<R>>,
    ke: &Array<R>,
    f: &Array<Vec3<R>>,
) {
    let k = tid();
    let i = idx[k];
    f.atomic_add(i, (anchor[k] - x[i]) * ke[k]);
}

/// Its potential, `ke |x - anchor|^2 / 2` (J), added into the particle's world's entry of `e`
/// (one per world: implicit Euler solves each world apart).
#[diff_kernel]
fn anchor_energy<R: Real>(
    x: &Array<Vec3<R>>,
    idx: &Array<u32>,
    anchor: &Array<Vec3<R>>,
    ke: &Array<R>,
    world: &Array<u32>,
    e: &Array<R>,
) {
    let k = tid();
    let i = idx[k];
    let d = x[i] - anchor[k];
    e.atomic_add(world[i] as usize, ke[k] * dot(d, d) * 0.5);
}

/// The force component: its arrays, and how to evaluate it.
#[derive(Clone, Debug)]
struct Anchors<R: Real> {
    idx: Array<u32>,
    anchor: Array<Vec3<R>>,
    ke: Array<R>,
}

impl<R: Real> Force<R> for Anchors<R> {
    fn name(&self) -> &'static str {
        "anchors"
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        tape.launch(
            eval_anchors,
            self.idx.len(),
            (cx.x, &self.idx, &self.anchor, &self.ke, f),
        );
    }
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, e: &Array<R>) -> bool {
        let world = cx.particle_worlds();
        tape.launch(
            anchor_energy,
            self.idx.len(),
            (cx.x, &self.idx, &self.anchor, &self.ke, &world, e),
        );
        true
    }
    /// The differentiable parameters: what ImplicitEuler substitutes, what gradients reach.
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("anchor", &mut self.anchor);
        visit("ke", &mut self.ke);
    }
}

/// `loss += |x|^2` over the particles.
#[diff_kernel]
fn squared_positions(x: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    loss.atomic_add(0, dot(x[t], x[t]));
}

/// A chain of three particles on springs, two of them anchored, falling under gravity.
fn model() -> (Model<f64>, Array<f64>) {
    let mut b = ModelBuilder::<f64>::new();
    let p: Vec<u32> = (0..3)
        .map(|k| b.add_particle(Vec3::new(0.4 * k as f64, 1.0, 0.0), Vec3::zeros(), 1.0))
        .collect();
    b.add_spring(p[0], p[1], 200.0, 0.5);
    b.add_spring(p[1], p[2], 200.0, 0.5);
    let ke = Array::from_vec(vec![50.0, 80.0]).named("anchor_ke");
    b.add_force(Anchors {
        idx: Array::from_vec(vec![p[0], p[2]]),
        anchor: Array::from_vec(vec![Vec3::new(0.0, 1.2, 0.0), Vec3::new(1.0, 1.1, 0.1)])
            .named("anchor"),
        ke: ke.clone(),
    });
    (b.finalize(), ke)
}

fn check<I: Integrator<f64>>(name: &str, integ: &I, model: &Model<f64>, ke: &Array<f64>) {
    let (dt, steps) = (0.01, 20);
    let loss = |tape: &mut Tape| {
        let s = integ
            .rollout(model, tape, &model.state(), None, dt, steps)
            .expect("step");
        let loss = Array::zeros(1).named("loss");
        tape.launch(squared_positions, s.x.len(), (&s.x, &loss));
        loss
    };
    let end = loss(&mut Tape::new()).get(0);
    let report = gradcheck(loss, &[ke]).expect("gradient");
    println!("{name}: loss after {steps} steps of {dt} s = {end:.6}");
    println!("d loss / d anchor_ke, adjoint vs central differences: {report}");
    report.assert_within(1e-5);
}

fn main() {
    let (model, ke) = model();
    println!(
        "forces of the model: {:?}",
        model.forces.iter().map(|f| f.name()).collect::<Vec<_>>()
    );
    check("SemiImplicitEuler", &SemiImplicitEuler, &model, &ke);
    check("ImplicitEuler", &ImplicitEuler::default(), &model, &ke);
}
