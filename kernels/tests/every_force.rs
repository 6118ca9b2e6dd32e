//! Every force through every integrator: for each force of [`every_force`] (a small scene with
//! every force the library has, plus one defined here, outside the library) and each
//! integrator, the gradient of a short f64 rollout's loss with respect to the force's parameter
//! arrays, as its own visitor ([`Force::params_mut`]) lists them, against central differences.
//! A force added to the library is covered once it is in [`every_force`], and
//! `the_scene_has_every_library_force` fails until it is.
//!
//! Forces whose parameters are all scalars (ground, particle contact, drag) have no parameter
//! arrays: they are checked with respect to the initial velocities instead, which still runs
//! their adjoint (and, for ImplicitEuler, their tangent) kernels.
//!
//! Run with `--nocapture` to see every report.

use adflex_kernels::contact::ground::Ground;
use adflex_kernels::contact::particle::ParticleContact;
use adflex_kernels::contact::shapes::{Shape, ShapeKind};
use adflex_kernels::forces::particle::Drag;
use adflex_kernels::forces::{Force, ForceContext, Param, BUILTIN_FORCES, LIBRARY_PARAMS};
use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, Xpbd,
};
use adflex_kernels::prelude::RestAngle;
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;

/// A zero-length spring pulling particle `idx[k]` to the fixed point `anchor[k]` with
/// stiffness `ke[k]` (N/m): a force the library does not have.
#[diff_kernel]
fn eval_anchors(
    x: &Array<Vec3<f64>>,
    idx: &Array<u32>,
    anchor: &Array<Vec3<f64>>,
    ke: &Array<f64>,
    f: &Array<Vec3<f64>>,
) {
    let k = tid();
    let i = idx[k];
    f.atomic_add(i, (anchor[k] - x[i]) * ke[k]);
}

#[diff_kernel]
fn anchor_energy(
    x: &Array<Vec3<f64>>,
    idx: &Array<u32>,
    anchor: &Array<Vec3<f64>>,
    ke: &Array<f64>,
    e: &Array<f64>,
) {
    let k = tid();
    let d = x[idx[k]] - anchor[k];
    e.atomic_add(0, 0.5 * ke[k] * dot(d, d));
}

/// The user-defined force: written here, plugged in with `add_force`.
#[derive(Clone, Debug)]
struct Anchors {
    idx: Array<u32>,
    anchor: Array<Vec3<f64>>,
    ke: Array<f64>,
}

impl Force<f64> for Anchors {
    fn name(&self) -> &'static str {
        "anchors"
    }
    fn eval(&self, cx: &ForceContext<'_, f64>, tape: &mut Tape, f: &Array<Vec3<f64>>) {
        tape.launch(
            eval_anchors,
            self.idx.len(),
            (cx.x, &self.idx, &self.anchor, &self.ke, f),
        );
    }
    fn energy(&self, cx: &ForceContext<'_, f64>, tape: &mut Tape, e: &Array<f64>) -> bool {
        tape.launch(
            anchor_energy,
            self.idx.len(),
            (cx.x, &self.idx, &self.anchor, &self.ke, e),
        );
        true
    }
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("anchor", &mut self.anchor);
        visit("ke", &mut self.ke);
    }
}

/// No particle starts with a vertical velocity of exactly 0: the ground's damping term
/// (`min(v.n, 0) kd`, see `contact::law::contact_force`) acts on every particle moving
/// down, in contact or not, and has a kink at `v.n = 0` that central differences straddle.
///
/// A small scene with every force of the library (and the user-defined [`Anchors`]), each
/// active: springs, bending and membranes on a bent quad, a tetrahedron, a particle in the
/// ground, two overlapping particles, a particle on a box, drag.
fn every_force() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = 0.05;
    let v = |x: f64, y: f64, z: f64| Vec3::new(x, y, z);
    // A quad of two triangles, bent along its diagonal.
    let q = [
        b.add_particle(v(0.0, 1.0, 0.0), v(0.1, 0.05, -0.2), 1.0),
        b.add_particle(v(0.5, 1.0, 0.0), v(0.0, 0.3, 0.0), 0.8),
        b.add_particle(v(0.0, 1.0, 0.5), v(-0.2, -0.07, 0.1), 1.2),
        b.add_particle(v(0.5, 1.15, 0.5), v(0.0, -0.1, 0.2), 1.0),
    ];
    b.add_triangle_fem(q[0], q[1], q[2], 200.0, 300.0, 0.5);
    b.add_triangle_fem(q[1], q[3], q[2], 250.0, 280.0, 0.4);
    b.add_bending_edges(2.0, 0.1, RestAngle::Flat);
    for (k, (i, j)) in [(q[0], q[1]), (q[1], q[3]), (q[3], q[2]), (q[2], q[0])]
        .into_iter()
        .enumerate()
    {
        let d = (b.particle_position(i) - b.particle_position(j)).norm();
        b.add_spring_with_rest(
            i,
            j,
            d * (0.9 + 0.05 * k as f64),
            50.0 + 10.0 * k as f64,
            0.3,
        );
    }
    // A tetrahedron, squeezed by its initial velocities.
    let t = [
        b.add_particle(v(1.0, 1.0, 0.0), v(0.2, 0.04, 0.0), 1.0),
        b.add_particle(v(1.3, 1.0, 0.0), v(-0.2, 0.1, 0.0), 1.0),
        b.add_particle(v(1.0, 1.3, 0.05), v(0.0, -0.3, 0.1), 1.0),
        b.add_particle(v(1.05, 1.0, 0.3), v(0.0, -0.06, -0.2), 1.0),
    ];
    b.add_tet(t[0], t[1], t[2], t[3], 300.0, 500.0, 0.2);
    // In the ground, sliding.
    b.add_particle(v(0.5, 0.02, -1.0), v(0.3, -0.1, 0.2), 1.0);
    b.set_ground(Ground::default());
    // Two overlapping particles.
    b.add_particle(v(3.0, 1.0, 0.0), v(0.1, 0.03, 0.2), 1.0);
    b.add_particle(v(3.07, 1.01, 0.0), v(-0.1, 0.1, 0.0), 1.0);
    b.set_particle_contact(ParticleContact::default());
    // On a box (a sphere's rotation would not matter), sliding over it.
    b.add_shape(Shape::new(
        ShapeKind::Box {
            half_extents: v(0.3, 0.3, 0.3),
        },
        v(2.0, 0.5, 0.0),
    ));
    b.add_particle(v(2.05, 0.82, 0.0), v(0.2, -0.1, 0.1), 1.0);
    b.set_drag(Drag {
        kd: 0.3,
        wind: v(1.0, 0.0, 0.5),
    });
    // Outside the library.
    b.add_force(Anchors {
        idx: Array::from_vec(vec![q[0], t[0]]),
        anchor: Array::from_vec(vec![v(0.0, 1.1, 0.0), v(1.0, 0.9, 0.1)]).named("anchor"),
        ke: Array::from_vec(vec![30.0, 40.0]).named("anchor_ke"),
    });
    b.finalize()
}

/// `model` with only the forces named `name`.
fn only(model: &Model<f64>, name: &str) -> Model<f64> {
    let mut m = model.clone();
    m.forces.retain(|f| f.name() == name);
    m
}

#[test]
fn the_scene_has_every_library_force() {
    let m = every_force();
    let names: Vec<&str> = m.forces.iter().map(|f| f.name()).collect();
    for b in BUILTIN_FORCES {
        assert!(
            names.contains(b),
            "every_force() has no `{b}`: add it so every integrator's gradient is checked with it"
        );
    }
    for n in &names {
        assert!(
            BUILTIN_FORCES.contains(n) || *n == "anchors",
            "force `{n}` is not in forces::BUILTIN_FORCES"
        );
    }
    // Each once, in the registry's order, then the added one.
    let mut expected = BUILTIN_FORCES.to_vec();
    expected.push("anchors");
    assert_eq!(names, expected);
}

/// `Force::to_f64`, the copy in `f64` that a Hessian-vector product's implicit solves run on:
/// every library force has it, and it is the same force (every field carried over: a field
/// dropped or swapped would change the force at this state, where each is active).
#[test]
fn every_library_force_has_its_f64_twin() {
    let m = every_force();
    let s = m.state();
    let cx = m.context(&s, None);
    let eval = |f: &dyn Force<f64>| {
        let out = Array::zeros(s.x.len());
        f.eval(&cx, &mut Tape::new(), &out);
        out.to_vec()
    };
    for f in m
        .forces
        .iter()
        .filter(|f| BUILTIN_FORCES.contains(&f.name()))
    {
        let name = f.name();
        let twin = f
            .to_f64()
            .unwrap_or_else(|| panic!("`{name}` has no Force::to_f64"));
        let (a, b) = (eval(&**f), eval(&*twin));
        assert!(a.iter().any(|v| v.norm() > 0.0), "`{name}` is idle here");
        assert_eq!(a, b, "`{name}`: its f64 twin computes another force");
    }
}

/// `loss += |x - x0|^2 / dt^2 + <v, w>` over the particles: of the order of the forces'
/// effect, so that central differences are not swamped by the rounding of `|x|`.
#[test]
fn every_parameter_is_visited() {
    let m = every_force();
    for f in &m.forces {
        let got: Vec<&str> = f.params().iter().map(|(p, _)| *p).collect();
        // The library's forces: their `PARAMS` rows marked as arrays (a visitor that drops one
        // would silently drop it from ImplicitEuler's copies and from the gradient checks
        // below, which both iterate the visitor); the test's own force: its two arrays.
        let want: Vec<&str> = match LIBRARY_PARAMS.iter().find(|(n, _)| *n == f.name()) {
            Some((_, rows)) => rows.iter().filter(|r| r.array).map(|r| r.name).collect(),
            None if f.name() == "anchors" => vec!["anchor", "ke"],
            None => panic!("no parameter rows for `{}`", f.name()),
        };
        assert_eq!(got, want, "parameters visited by `{}`", f.name());
    }
}

#[diff_kernel]
fn rollout_loss(
    x: &Array<Vec3<f64>>,
    x0: &Array<Vec3<f64>>,
    v: &Array<Vec3<f64>>,
    loss: &Array<f64>,
) {
    let t = tid();
    let w = vec3(1.0, 2.0, -0.5);
    let d = (x[t] - x0[t]) * 10.0;
    loss.atomic_add(0, dot(d, d) + dot(v[t], w));
}

/// The loss of a rollout from `s`.
fn loss_of(tape: &mut Tape, model: &Model<f64>, s: &State<f64>) -> Array<f64> {
    let loss = Array::zeros(1).named("loss");
    tape.launch(
        rollout_loss,
        s.x.len(),
        (&s.x, &model.particle_x, &s.v, &loss),
    );
    loss
}

const STEPS: usize = 4;
const DT: f64 = 1e-2;

/// Checks the parameters of every force at once, and the initial velocities, in the whole
/// scene through `integ` with central differences of step `h`, within `tol`.
fn check_whole_scene<I: Integrator<f64>>(name: &str, integ: &I, h: f64, tol: f64) {
    let model = every_force();
    let v0 = model.state().v.named("v0");
    let params = model.params();
    let mut arrays: Vec<&dyn AnyArray> = params.iter().map(|(_, _, a)| &**a).collect();
    arrays.push(&v0);
    let report = rollout_report(integ, &model, &v0, &arrays, h);
    println!("{name}: {report}");
    report.assert_within(tol);
}

/// The gradient check of `arrays` for the loss of a rollout of `model` from its initial
/// positions and the velocities `v0`, with central differences of step `h`.
fn rollout_report<I: Integrator<f64>>(
    integ: &I,
    model: &Model<f64>,
    v0: &Array<Vec3<f64>>,
    arrays: &[&dyn AnyArray],
    h: f64,
) -> adflex_runtime::gradcheck::Report {
    let x0 = model.state().x.named("x0");
    GradCheck::new()
        .step(h)
        .run(
            |tape| {
                let s = State {
                    x: x0.clone(),
                    v: v0.clone(),
                    bodies: None,
                };
                let s = integ.rollout(model, tape, &s, None, DT, STEPS).unwrap();
                loss_of(tape, model, &s)
            },
            arrays,
        )
        .unwrap()
}

/// Checks every force's parameters through `integ` with central differences of step `h`,
/// each relative error within `tol`.
fn check<I: Integrator<f64>>(name: &str, integ: &I, h: f64, tol: f64) {
    let all = every_force();
    let mut failures = Vec::new();
    for force in &all.forces {
        let model = only(&all, force.name());
        let v0 = model.state().v.named("v0");
        let params = force.params();
        let mut arrays: Vec<&dyn AnyArray> = params.iter().map(|(_, a)| &**a).collect();
        if arrays.is_empty() {
            arrays.push(&v0);
        }
        let report = rollout_report(integ, &model, &v0, &arrays, h);
        let what: Vec<&str> = params.iter().map(|(p, _)| *p).collect();
        println!(
            "{name} / {} ({}): {report}",
            force.name(),
            if what.is_empty() {
                "v0".to_string()
            } else {
                what.join(", ")
            }
        );
        if !report.is_within(tol) {
            failures.push(format!("{name} / {}:\n{report}", force.name()));
        }
    }
    assert!(
        failures.is_empty(),
        "gradient checks failed (tolerance {tol:e}):\n{}",
        failures.join("\n")
    );
}

#[test]
fn explicit_euler() {
    check("ExplicitEuler", &ExplicitEuler, 1e-6, 1e-5);
}

#[test]
fn semi_implicit_euler() {
    check("SemiImplicitEuler", &SemiImplicitEuler, 1e-6, 1e-5);
}

#[test]
fn rk4() {
    check("Rk4", &Rk4, 1e-6, 1e-5);
}

#[test]
fn midpoint() {
    check("Midpoint", &Midpoint, 1e-6, 1e-5);
}

#[test]
fn implicit_euler() {
    check("ImplicitEuler", &ImplicitEuler::default(), 1e-6, 1e-5);
}

#[test]
fn linearized_implicit_euler() {
    check(
        "ImplicitEuler::linearized",
        &ImplicitEuler::linearized(),
        1e-6,
        1e-5,
    );
}

/// The forces that are not elastic (contact, drag, the user's anchors) and the elastic ones.
const CONTACT_AND_USER: [&str; 5] = [
    "ground",
    "particle_contact",
    "shape_contact",
    "drag",
    "anchors",
];
const ELASTIC: [&str; 4] = ["springs", "bending", "triangle_fem", "tets"];

/// Implicit-explicit splits of the whole scene: every force explicit in one split and implicit
/// in the other, for the full and the linearized method. Each force's parameters are checked
/// with the rest of the scene present (the split's coupling is what is tested).
#[test]
fn implicit_euler_with_explicit_splits() {
    for (name, integ) in [
        (
            "ImplicitEuler, contact and user forces explicit",
            ImplicitEuler::default().with_explicit(CONTACT_AND_USER),
        ),
        (
            "ImplicitEuler, elastic forces explicit",
            ImplicitEuler::default().with_explicit(ELASTIC),
        ),
        (
            "ImplicitEuler::linearized, contact and user forces explicit",
            ImplicitEuler::linearized().with_explicit(CONTACT_AND_USER),
        ),
    ] {
        check_whole_scene(name, &integ, 1e-6, 1e-5);
    }
}

/// XPBD's velocities are position differences over a substep (`dt / 8`): they amplify the
/// rounding of the positions, so central differences need a larger step (and a looser
/// tolerance: errors up to 3e-5 at `h = 1e-4`).
#[test]
fn xpbd() {
    check("Xpbd", &Xpbd::default(), 1e-4, 1e-4);
}

/// The parameters of every force get a gradient through `ImplicitEuler` (whose private copies
/// come from the forces' visitors): a visitor that missed one would leave it at exactly 0.
#[test]
fn implicit_euler_reaches_every_parameter() {
    let model = every_force();
    let s0 = model.state();
    let mut tape = Tape::new();
    for (_, _, a) in model.params() {
        a.zero_grad();
        a.ensure_grad();
    }
    for (force, param, _) in model.params() {
        assert_eq!(
            model.requires_grad(force, param).unwrap(),
            1,
            "{force}.{param}"
        );
    }
    let s = ImplicitEuler::default()
        .rollout(&model, &mut tape, &s0, None, DT, STEPS)
        .unwrap();
    let loss = loss_of(&mut tape, &model, &s);
    tape.backward(&loss).unwrap();
    for (force, param, a) in model.params() {
        let g = a.grad_any().expect("gradient buffer");
        let norm: f64 = (0..g.len() * g.element_dim())
            .map(|k| g.scalar(k).abs())
            .sum();
        println!("{force}.{param}: |grad|_1 = {norm:e}");
        assert!(
            norm > 0.0,
            "{force}.{param} got no gradient through ImplicitEuler"
        );
    }
}

/// A misspelt force or parameter name marks nothing: an error naming what the model has, not
/// a gradient silently missing later.
#[test]
fn requires_grad_with_a_wrong_name_names_the_parameters() {
    let model = every_force();
    for (force, param) in [("spring", "ke"), ("springs", "stiffness")] {
        let msg = model.requires_grad(force, param).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("{force}.{param}")) && msg.contains("springs.ke"),
            "{msg}"
        );
    }
}

/// docs/guide.md's "Gradient targets" table is the library forces' `PARAMS` rows, row for
/// row (force, parameter, units, array or scalar), and its *array* rows are exactly what
/// `model.params()` gives for a scene with every library force.
#[test]
fn the_guides_parameter_table_is_the_forces() {
    let guide = include_str!("../../docs/guide.md");
    let start = guide
        .find("### Gradient targets: every parameter")
        .expect("the guide's parameter section");
    let mut in_guide = Vec::new();
    for line in guide[start..].lines().skip(1) {
        if line.starts_with("### ") {
            break;
        }
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() == 6 && (cells[4] == "array" || cells[4] == "scalar") {
            in_guide.push(cells[1..5].join(" | ").replace('`', ""));
        }
    }
    let in_files: Vec<String> = LIBRARY_PARAMS
        .iter()
        .flat_map(|(force, rows)| {
            rows.iter().map(move |r| {
                let kind = if r.array { "array" } else { "scalar" };
                format!("{force} | {} | {} | {kind}", r.name, r.units).replace('`', "")
            })
        })
        .collect();
    if in_guide != in_files {
        let rows: Vec<String> = in_files
            .iter()
            .map(|r| {
                let c: Vec<&str> = r.split(" | ").collect();
                format!("| `{}` | `{}` | {} | {} |", c[0], c[1], c[2], c[3])
            })
            .collect();
        panic!(
            "docs/guide.md's parameter table is not the forces' PARAMS; its rows should be:\n{}",
            rows.join("\n")
        );
    }
    let arrays: Vec<String> = LIBRARY_PARAMS
        .iter()
        .flat_map(|(force, rows)| {
            rows.iter()
                .filter(|r| r.array)
                .map(move |r| format!("{force}.{}", r.name))
        })
        .collect();
    let in_model: Vec<String> = every_force()
        .params()
        .iter()
        .filter(|(f, _, _)| BUILTIN_FORCES.contains(f))
        .map(|(f, p, _)| format!("{f}.{p}"))
        .collect();
    assert_eq!(
        arrays, in_model,
        "the forces' array PARAMS vs model.params()"
    );
    // The guide's component table: its energy column is what `Force::energy` says.
    let start = guide
        .find("| force (`name()`) | builder |")
        .expect("the component table");
    let model = every_force();
    let state = model.state();
    for line in guide[start..]
        .lines()
        .skip(2)
        .take_while(|l| l.starts_with('|'))
    {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        let force = cells[1].trim_matches('`');
        let f = model.force_named(force).expect("a library force");
        let has = f.energy(
            &model.context(&state, None),
            &mut Tape::new(),
            &Array::zeros(1),
        );
        assert_eq!(
            cells[4] == "yes",
            has,
            "the guide's energy column for {force}"
        );
    }
    // A scalar row names a field of the component.
    for (force, rows) in LIBRARY_PARAMS {
        let f = model.force_named(force).expect("every library force");
        let fields = format!("{f:?}");
        for r in rows.iter().filter(|r| !r.array) {
            assert!(
                fields.contains(&format!(" {}: ", r.name)),
                "{force}.{} is not a field of {fields}",
                r.name
            );
        }
    }
}
