//! Many worlds in one model: a world's loss and gradients are the same bits whatever the
//! number, order and content of the other worlds and the thread count; per-world parameters
//! get per-world gradients, shared ones the sum; resetting selected worlds.

use adflex_kernels::articulation::{
    urdf, ArticulationBuilder, ArticulationControl, ArticulationState, Articulations,
    GroundContact, Inertial, Joint,
};
use adflex_runtime::prelude::*;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/robots");

fn quadruped() -> ArticulationBuilder {
    let options = urdf::UrdfOptions {
        floating_base: true,
        collisions: true,
        ..Default::default()
    };
    let mut b = urdf::load(format!("{ROBOTS}/quadruped.urdf"), &options).unwrap();
    b.ground = Some(GroundContact::default());
    b
}

/// The scene of identity `j`: a quadruped dropped from a height, with its own gravity, torso
/// mass and joint angles.
fn scene(base: &ArticulationBuilder, j: usize) -> ArticulationBuilder {
    let mut b = base.clone();
    let jf = j as f64;
    b.gravity.z = -9.81 * (1.0 + 0.01 * jf);
    let links = b.links_mut();
    links[0].joint.initial = vec![0.0, 0.0, 0.22 + 0.005 * (j % 7) as f64, 0.0, 0.0, 0.0, 1.0];
    links[0].inertial.mass *= 1.0 + 0.02 * jf;
    for (k, l) in links.iter_mut().enumerate().skip(1) {
        l.joint.initial = vec![0.1 * ((jf + k as f64) * 0.7).sin()];
    }
    b
}

/// What one world gave: its loss and its gradients (masses, gravity, initial velocities,
/// torques of every step).
#[derive(Debug, PartialEq)]
struct WorldResult {
    loss: f64,
    mass: Vec<f64>,
    gravity: [f64; 3],
    qd0: Vec<f64>,
    tau: Vec<f64>,
}

/// Builds the worlds `ids` (scene identities, in this order), rolls them out together, and
/// returns each world's result.
fn run(base: &ArticulationBuilder, ids: &[usize], steps: usize) -> Vec<WorldResult> {
    let mut b = ArticulationBuilder::new();
    for &j in ids {
        b.add_world(&scene(base, j));
    }
    let model: Articulations<f64> = b.finalize().unwrap();
    assert_eq!(model.n_worlds(), ids.len());
    let _ = model.mass.clone().requires_grad();
    let _ = model.gravity.clone().requires_grad();
    let mut tape = Tape::new();
    let s0 = model.state();
    let _ = s0.qd.clone().requires_grad();
    let mut s = ArticulationState {
        q: s0.q.clone(),
        qd: s0.qd.clone(),
    };
    let mut taus = Vec::new();
    for k in 0..steps {
        // Torques that depend on the world's identity, never on its place.
        let mut tau = vec![0.0; model.n_dof];
        for (w, &j) in model.worlds.iter().zip(ids) {
            for (i, d) in w.dofs.clone().enumerate().skip(6) {
                tau[d] = 0.3 * ((j + i) as f64 + 0.05 * k as f64).sin();
            }
        }
        let tau = Array::from_vec(tau).requires_grad();
        let c = ArticulationControl {
            tau: tau.clone(),
            ..model.control()
        };
        s = model.step(&mut tape, &s, Some(&c), 2e-3).unwrap();
        taus.push(tau);
    }
    let loss = Array::zeros(model.n_worlds());
    adflex_kernels::losses::per_world_sum_of_squares(&mut tape, &model.q_world, &s.q, 1.0, &loss);
    adflex_kernels::losses::per_world_sum_of_squares(
        &mut tape,
        &model.dof_world,
        &s.qd,
        1.0,
        &loss,
    );
    tape.backward(&loss).unwrap();
    let (mass, gravity, qd0) = (
        model.mass.grad().unwrap().to_vec(),
        model.gravity.grad().unwrap().to_vec(),
        s0.qd.grad().unwrap().to_vec(),
    );
    let tau: Vec<Vec<f64>> = taus.iter().map(|t| t.grad().unwrap().to_vec()).collect();
    model
        .worlds
        .iter()
        .enumerate()
        .map(|(w, info)| WorldResult {
            loss: loss.get(w),
            mass: mass[info.links.clone()].to_vec(),
            gravity: [gravity[w].x, gravity[w].y, gravity[w].z],
            qd0: qd0[info.dofs.clone()].to_vec(),
            tau: tau
                .iter()
                .flat_map(|t| t[info.dofs.clone()].iter().copied())
                .collect(),
        })
        .collect()
}

#[test]
fn a_world_does_not_know_it_has_neighbours() {
    let base = quadruped();
    let steps = 60;
    let ids: Vec<usize> = (0..64).collect();
    // Every launch split across the threads (the default runs these small ones serially).
    let defaults = adflex_runtime::settings::settings();
    let mut parallel = defaults;
    parallel.serial_below = 1;
    parallel.apply();
    let together = with_threads(2, || run(&base, &ids, steps));
    let together3 = with_threads(3, || run(&base, &ids, steps));
    adflex_runtime::settings::set_settings(defaults);
    assert_eq!(together, together3, "2 and 3 threads");
    // Sanity: the worlds differ, their feet touch the ground, and gradients are there.
    assert_ne!(together[0], together[1]);
    assert!(together.iter().all(|r| r.tau.iter().any(|g| *g != 0.0)));
    assert!(together.iter().all(|r| r.gravity[2] != 0.0));
    // Alone, on one thread and on two.
    for j in [0, 17, 63] {
        for threads in [1, 2] {
            let alone = with_threads(threads, || run(&base, &[j], steps));
            assert_eq!(
                alone[0], together[j],
                "world {j} alone on {threads} threads"
            );
        }
    }
    // In reverse order, on one thread.
    let reversed: Vec<usize> = ids.iter().rev().copied().collect();
    let back = with_threads(1, || run(&base, &reversed, steps));
    for (w, &j) in reversed.iter().enumerate() {
        assert_eq!(
            back[w], together[j],
            "world {j} at place {w} of the reversed order"
        );
    }
}

fn cartpole() -> ArticulationBuilder {
    urdf::load(format!("{ROBOTS}/cartpole.urdf"), &Default::default()).unwrap()
}

#[test]
fn a_thousand_cartpoles_give_each_world_its_own_bits() {
    let base = cartpole();
    let run_cartpoles = |w: usize| {
        let ids: Vec<usize> = (0..w).map(|k| k % 8).collect();
        let mut b = ArticulationBuilder::new();
        for &j in &ids {
            let mut s = base.clone();
            let pole = s.find("pole").unwrap().0;
            s.links_mut()[pole].joint.initial = vec![0.1 + 0.1 * j as f64];
            b.add_world(&s);
        }
        let model: Articulations<f64> = b.finalize().unwrap();
        let _ = model.mass.clone().requires_grad();
        let mut tape = Tape::new();
        let mut s = model.state();
        for _ in 0..50 {
            s = model.step(&mut tape, &s, None, 1e-2).unwrap();
        }
        let loss = Array::zeros(w);
        adflex_kernels::losses::per_world_sum_of_squares(
            &mut tape,
            &model.q_world,
            &s.q,
            1.0,
            &loss,
        );
        tape.backward(&loss).unwrap();
        let g = model.mass.grad().unwrap().to_vec();
        (loss.to_vec(), g)
    };
    let (l1024, g1024) = with_threads(2, || run_cartpoles(1024));
    let (l8, g8) = run_cartpoles(8);
    let n = g8.len() / 8; // links per cartpole
    for w in 0..1024 {
        let k = w % 8;
        assert_eq!(l1024[w], l8[k], "world {w}'s loss");
        assert_eq!(
            g1024[n * w..n * w + n],
            g8[n * k..n * k + n],
            "world {w}'s gradient"
        );
    }
    assert!(l8.iter().all(|l| *l > 0.0));
    assert!(
        (0..8).all(|k| g8[n * k + n - 1] != 0.0),
        "the poles' masses matter: {g8:?}"
    );
}

#[test]
fn shared_parameters_get_the_sum_of_the_worlds_gradients() {
    // One pole mass for four cartpoles, spread onto the model's per-link masses on the tape:
    // its gradient is the sum of the four per-world gradients, which the per-world masses
    // get one by one.
    use adflex_kernels::tied::spread;
    let model: Articulations<f64> = cartpole().replicate(4).finalize().unwrap();
    let start = model.state();
    let angles = [0.1, 0.4, -0.3, 1.0];
    for (w, a) in model.worlds.iter().zip(angles) {
        start.q.set(w.q.start + 1, a);
    }
    let roll = |tape: &mut Tape, model: &Articulations<f64>| {
        let mut s = start.clone();
        for _ in 0..30 {
            s = model.step(tape, &s, None, 1e-2).unwrap();
        }
        let loss = Array::zeros(4);
        adflex_kernels::losses::per_world_sum_of_squares(tape, &model.q_world, &s.q, 1.0, &loss);
        loss
    };
    // Per-world masses.
    let _ = model.mass.clone().requires_grad();
    let mut tape = Tape::new();
    let loss = roll(&mut tape, &model);
    tape.backward(&loss).unwrap();
    let per_world = model.mass.grad().unwrap().to_vec();
    // One mass per kind of link (rail, cart, pole), shared by the four worlds.
    let n = model.worlds[0].links.len();
    let shared = Array::from_vec(model.mass.to_vec()[..n].to_vec()).requires_grad();
    let group = Array::from_vec((0..4 * n).map(|l| (l % n) as u32).collect::<Vec<u32>>());
    let mut tied = model.clone();
    tied.mass = Array::zeros(4 * n);
    let mut tape = Tape::new();
    tape.launch(spread, 4 * n, (&shared, &group, &tied.mass));
    let loss2 = roll(&mut tape, &tied);
    tape.backward(&loss2).unwrap();
    assert_eq!(loss.to_vec(), loss2.to_vec());
    let g = shared.grad().unwrap().to_vec();
    let pole = n - 1;
    let sum_poles: f64 = (0..4).map(|w| per_world[n * w + pole]).sum();
    assert!(
        (g[pole] - sum_poles).abs() <= 1e-12 * sum_poles.abs(),
        "{g:?} vs {sum_poles}"
    );
    // The per-world gradients differ (the worlds started apart).
    assert!(per_world[pole] != per_world[n + pole]);
}

#[test]
fn per_world_gravity_gradients_match_central_differences() {
    let mut b = ArticulationBuilder::new();
    let mut pendulum = ArticulationBuilder::new();
    pendulum.add_link(
        "pole",
        None,
        Joint::revolute(Vec3::y()).initial(&[0.5]),
        Inertial::point(1.0, Vec3::new(0.0, 0.0, 0.5)),
    );
    b.add_world(&pendulum);
    pendulum.gravity = Vec3::new(0.0, 0.0, -1.62);
    b.add_world(&pendulum);
    let model: Articulations<f64> = b.finalize().unwrap();
    let loss_at = |g: &[Vec3<f64>]| {
        let mut m = model.clone();
        m.gravity = Array::from_vec(g.to_vec()).requires_grad();
        let mut tape = Tape::new();
        let mut s = m.state();
        for _ in 0..50 {
            s = m.step(&mut tape, &s, None, 1e-2).unwrap();
        }
        let loss = Array::zeros(2);
        adflex_kernels::losses::per_world_sum_of_squares(&mut tape, &m.q_world, &s.q, 1.0, &loss);
        tape.backward(&loss).unwrap();
        (loss.to_vec(), m.gravity.grad().unwrap().to_vec())
    };
    let g0 = model.gravity.to_vec();
    let (l, grad) = loss_at(&g0);
    assert_ne!(l[0], l[1], "the moon's pendulum swings slower");
    let h = 1e-6;
    for w in 0..2 {
        let (mut up, mut down) = (g0.clone(), g0.clone());
        up[w].z += h;
        down[w].z -= h;
        let (lu, ld) = (loss_at(&up).0, loss_at(&down).0);
        let fd = (lu[w] - ld[w]) / (2.0 * h);
        assert!(
            (grad[w].z - fd).abs() < 1e-6 * fd.abs().max(1e-3),
            "world {w}: {} vs {fd}",
            grad[w].z
        );
        // The other world does not move.
        assert_eq!(lu[1 - w], l[1 - w]);
    }
}

#[test]
fn resetting_selected_worlds() {
    let model: Articulations<f64> = cartpole().replicate(3).finalize().unwrap();
    let mut tape = Tape::new();
    let mut s = model.state();
    s.q.set(1, 0.3);
    s.q.set(3, 0.2);
    s.q.set(5, -0.2);
    for _ in 0..20 {
        s = model.step(&mut tape, &s, None, 1e-2).unwrap();
    }
    let moved = (s.q.to_vec(), s.qd.to_vec());
    let r = model.reset_worlds(&mut tape, &s, &[1]).unwrap();
    let (q, qd) = (r.q.to_vec(), r.qd.to_vec());
    let w1 = &model.worlds[1];
    assert_eq!(q[w1.q.clone()], model.q0[w1.q.clone()]);
    assert!(qd[w1.dofs.clone()].iter().all(|v| *v == 0.0));
    for w in [0, 2] {
        let i = &model.worlds[w];
        assert_eq!(q[i.q.clone()], moved.0[i.q.clone()]);
        assert_eq!(qd[i.dofs.clone()], moved.1[i.dofs.clone()]);
    }
    let e = model.reset_worlds(&mut tape, &s, &[3]).unwrap_err();
    assert!(e.to_string().contains("world 3"), "{e}");
}

#[test]
fn worlds_do_not_share_links() {
    let mut b = cartpole();
    b.add_world(&cartpole());
    let cart = b.find("cart").unwrap(); // world 0's
    b.add_link(
        "extra",
        Some(cart),
        Joint::revolute(Vec3::y()),
        Inertial::point(1.0, Vec3::new(0.0, 0.0, 0.5)),
    );
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(
        e.contains("extra") && e.contains("world 1") && e.contains("world 0"),
        "{e}"
    );
}

#[test]
fn checkpointed_rollouts_over_worlds_give_the_whole_tapes_per_world_gradients() {
    use adflex_runtime::checkpoint::checkpointed;
    let model: Articulations<f64> = cartpole().replicate(16).finalize().unwrap();
    let tau = Array::from_vec(
        (0..model.n_dof)
            .map(|d| 0.1 * (d as f64).sin())
            .collect::<Vec<_>>(),
    )
    .requires_grad();
    let control = ArticulationControl {
        tau: tau.clone(),
        ..model.control()
    };
    let step =
        |tape: &mut Tape, s: &ArticulationState<f64>| model.step(tape, s, Some(&control), 1e-2);
    let loss = |tape: &mut Tape, s: &ArticulationState<f64>| {
        let l = Array::zeros(model.n_worlds());
        adflex_kernels::losses::per_world_sum_of_squares(tape, &model.q_world, &s.q, 1.0, &l);
        Ok(l)
    };
    let mut tape = Tape::new();
    let mut s = model.state();
    for _ in 0..100 {
        s = step(&mut tape, &s).unwrap();
    }
    let l = loss(&mut tape, &s).unwrap();
    tape.backward(&l).unwrap();
    let whole = tau.grad().unwrap().to_vec();
    tau.zero_grad();
    let out = checkpointed(&model.state(), 100, 10, step, loss).unwrap();
    assert_eq!(out.loss.to_vec(), l.to_vec());
    assert_eq!(tau.grad().unwrap().to_vec(), whole, "bit for bit");
    assert!(whole.iter().all(|g| *g != 0.0));
}

#[test]
fn a_share_of_the_worlds_gives_the_same_bits() {
    // Different quadrupeds; worlds 3..7 taken out of the ten by `worlds_in`.
    let base = quadruped();
    let mut all = ArticulationBuilder::new();
    for j in 0..10 {
        all.add_world(&scene(&base, j));
    }
    let roll = |b: &ArticulationBuilder| {
        let model: Articulations<f64> = b.finalize().unwrap();
        let _ = model.mass.clone().requires_grad();
        let mut tape = Tape::new();
        let mut s = model.state();
        for _ in 0..40 {
            s = model.step(&mut tape, &s, None, 2e-3).unwrap();
        }
        let loss = Array::zeros(model.n_worlds());
        adflex_kernels::losses::per_world_sum_of_squares(
            &mut tape,
            &model.q_world,
            &s.q,
            1.0,
            &loss,
        );
        tape.backward(&loss).unwrap();
        (loss.to_vec(), model.mass.grad().unwrap().to_vec(), model)
    };
    let (l_all, g_all, m_all) = roll(&all);
    let share = all.worlds_in(3..7);
    assert_eq!(share.world_count(), 4);
    let (l, g, m) = roll(&share);
    assert_eq!(l[..], l_all[3..7]);
    let links = m_all.worlds[3].links.start..m_all.worlds[6].links.end;
    assert_eq!(g[..], g_all[links]);
    assert_eq!(m.gravity.to_vec()[..], m_all.gravity.to_vec()[3..7]);
}

// ---- particle worlds ----------------------------------------------------------------------

use adflex_kernels::prelude::{ClothGrid, Ground, Integrator, ModelBuilder, SemiImplicitEuler};
use adflex_kernels::{Model, State};
use adflex_macros::diff_kernel;

/// Cloth `j`: its own size, stiffness, throw and gravity, dropped on the ground.
fn cloth_scene(j: usize) -> ModelBuilder<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::new(0.01 * j as f64, -9.8 - 0.1 * j as f64, 0.0);
    let n = 4 + j % 3;
    b.add_cloth_grid(&ClothGrid {
        spring_ke: 40.0 + 5.0 * j as f64,
        origin: Vec3::new(0.0, 0.05 + 0.01 * j as f64, 0.0),
        ..ClothGrid::benchmark(n)
    });
    b.set_ground(Ground::default());
    b
}

/// Each world's loss and gradients (initial velocities, spring stiffnesses, gravity).
type ClothResult = (f64, Vec<Vec3<f64>>, Vec<f64>, Vec3<f64>);

fn run_cloths(ids: &[usize]) -> Vec<ClothResult> {
    run_cloths_with(ids, None)
}

/// [`run_cloths`], with particles of radius `radius` if given (wide enough that neighbours in
/// the cloth touch) and then particle-particle contact if `contact`.
fn run_cloths_with(ids: &[usize], radius: Option<(f64, bool)>) -> Vec<ClothResult> {
    run_cloths_by(ids, radius, &SemiImplicitEuler, 1e-3, 150)
}

/// [`run_cloths_with`], stepped by `integrator` (`steps` steps of `dt`).
fn run_cloths_by<I: Integrator<f64>>(
    ids: &[usize],
    radius: Option<(f64, bool)>,
    integrator: &I,
    dt: f64,
    steps: usize,
) -> Vec<ClothResult> {
    let mut b = ModelBuilder::<f64>::new();
    let mut springs = vec![0];
    for &j in ids {
        let mut scene = cloth_scene(j);
        if let Some((r, contact)) = radius {
            scene.particle_radius = r;
            if contact {
                scene.set_particle_contact(adflex_kernels::prelude::ParticleContact::default());
            }
        }
        b.add_world(&scene);
        springs.push(b.spring_count());
    }
    let model = b.finalize();
    assert_eq!(model.worlds.len(), ids.len());
    let ke = model.springs().unwrap().ke.clone().requires_grad();
    let gravity = model.gravity.clone().requires_grad();
    let s0 = model.state();
    let _ = s0.v.clone().requires_grad();
    let mut tape = Tape::new();
    let s = integrator
        .rollout(&model, &mut tape, &s0, None, dt, steps)
        .unwrap();
    let loss = Array::zeros(ids.len());
    adflex_kernels::losses::per_world_sum_of_squares_vec3(
        &mut tape,
        &model.particle_world,
        &s.x,
        1.0,
        &loss,
    );
    tape.backward(&loss).unwrap();
    let (gv, gk) = (s0.v.grad().unwrap().to_vec(), ke.grad().unwrap().to_vec());
    let gg = gravity.grad().unwrap().to_vec();
    model
        .worlds
        .iter()
        .enumerate()
        .map(|(w, r)| {
            (
                loss.get(w),
                gv[r.particles.clone()].to_vec(),
                gk[springs[w]..springs[w + 1]].to_vec(),
                gg[w],
            )
        })
        .collect()
}

#[test]
fn a_cloth_world_does_not_know_it_has_neighbours() {
    let ids: Vec<usize> = (0..24).collect();
    let defaults = adflex_runtime::settings::settings();
    let mut parallel = defaults;
    parallel.serial_below = 1;
    parallel.apply();
    let together = with_threads(2, || run_cloths(&ids));
    adflex_runtime::settings::set_settings(defaults);
    assert!(together
        .iter()
        .all(|r| r.0 > 0.0 && r.2.iter().any(|g| *g != 0.0)));
    for j in [0, 7, 23] {
        assert_eq!(run_cloths(&[j])[0], together[j], "cloth {j} alone");
    }
    let reversed: Vec<usize> = ids.iter().rev().copied().collect();
    let back = with_threads(1, || run_cloths(&reversed));
    for (w, &j) in reversed.iter().enumerate() {
        assert_eq!(back[w], together[j], "cloth {j} at place {w}");
    }
}

/// Implicit Euler solves each world by its own Newton iteration: cloths of different sizes,
/// stiffnesses and throws, landing on the ground at a large step (line searches, different
/// iteration counts per world), give each world the bits it has alone, in any order and on
/// any thread count, forward and backward (the adjoint solve is per world too).
#[test]
fn implicit_euler_solves_each_world_apart() {
    let ids: Vec<usize> = (0..6).collect();
    let implicit = adflex_kernels::integrators::ImplicitEuler::default();
    let run = |ids: &[usize]| run_cloths_by(ids, None, &implicit, 0.01, 16);
    let together = with_threads(2, || run(&ids));
    assert!(together
        .iter()
        .all(|r| r.0 > 0.0 && r.2.iter().any(|g| *g != 0.0)));
    for j in [0, 4, 5] {
        assert_eq!(run(&[j])[0], together[j], "cloth {j} alone");
    }
    let reversed: Vec<usize> = ids.iter().rev().copied().collect();
    let back = with_threads(1, || run(&reversed));
    for (w, &j) in reversed.iter().enumerate() {
        assert_eq!(back[w], together[j], "cloth {j} at place {w}");
    }
    // At 1/60 s every cloth lands (cloth 3's Newton went round a cycle before the line
    // search's watchdog); capped at 3 iterations, the error names the world farthest from its
    // tolerance, which fails alone too.
    let mut b = ModelBuilder::<f64>::new();
    for j in 0..6 {
        b.add_world(&cloth_scene(j));
    }
    let model = b.finalize();
    let rollout = |i: &adflex_kernels::integrators::ImplicitEuler, m: &Model<f64>| {
        i.rollout(m, &mut Tape::new(), &m.state(), None, 1.0 / 60.0, 12)
    };
    rollout(&implicit, &model).unwrap();
    let capped = adflex_kernels::integrators::ImplicitEuler {
        max_newton: 3,
        ..Default::default()
    };
    let err = rollout(&capped, &model).unwrap_err().to_string();
    let w: usize = err
        .split("in world ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|t| t.parse().ok())
        .unwrap_or_else(|| panic!("no world named: {err}"));
    assert!(err.contains(&format!("in world {w} of 6")), "{err}");
    assert!(rollout(&capped, &cloth_scene(w).finalize()).is_err());
    // The linearized method's second-order term is scaled per world too.
    let linearized = adflex_kernels::integrators::ImplicitEuler::linearized();
    let run = |ids: &[usize]| run_cloths_by(ids, None, &linearized, 0.01, 6);
    let together = run(&ids);
    for j in [1, 5] {
        assert_eq!(run(&[j])[0], together[j], "cloth {j} alone, linearized");
    }
}

/// A hanging net of identity `j`: its own size, stiffness, sag and gravity; corners pinned.
fn net_scene(j: usize) -> ModelBuilder<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::new(0.0, -9.8 - 0.3 * j as f64, 0.0);
    let n = 3 + (j % 3) as u32;
    let h = 0.25 + 0.02 * j as f64;
    for k in 0..n {
        for i in 0..n {
            let corner = (i == 0 || i == n - 1) && (k == 0 || k == n - 1);
            let m = if corner { 0.0 } else { 0.05 + 0.01 * j as f64 };
            b.add_particle(Vec3::new(i as f64 * h, 0.0, k as f64 * h), Vec3::zeros(), m);
        }
    }
    let id = |i: u32, k: u32| k * n + i;
    for k in 0..n {
        for i in 0..n {
            for (p, q) in [(i + 1, k), (i, k + 1)] {
                if p < n && q < n {
                    let ke = 100.0 + 30.0 * j as f64 + 7.0 * (i + k) as f64;
                    b.add_spring_with_rest(id(i, k), id(p, q), 0.9 * h, ke, 0.0);
                }
            }
        }
    }
    b
}

/// Each net's equilibrium loss and the gradients of its springs' stiffnesses and gravity.
fn run_nets(ids: &[usize]) -> Vec<(f64, Vec<f64>, Vec3<f64>)> {
    let mut b = ModelBuilder::<f64>::new();
    let mut springs = vec![0];
    for &j in ids {
        b.add_world(&net_scene(j));
        springs.push(b.spring_count());
    }
    let model = b.finalize();
    let ke = model.springs().unwrap().ke.clone().requires_grad();
    let gravity = model.gravity.clone().requires_grad();
    let mut tape = Tape::new();
    let (eq, stats) = adflex_kernels::statics::Equilibrium::default()
        .solve_with_stats(&model, &mut tape, &model.state())
        .unwrap();
    assert!(stats.converged, "{stats:?}");
    let loss = Array::zeros(ids.len());
    adflex_kernels::losses::per_world_sum_of_squares_vec3(
        &mut tape,
        &model.particle_world,
        &eq.x,
        1.0,
        &loss,
    );
    tape.backward(&loss).unwrap();
    let (gk, gg) = (
        ke.grad().unwrap().to_vec(),
        gravity.grad().unwrap().to_vec(),
    );
    (0..ids.len())
        .map(|w| (loss.get(w), gk[springs[w]..springs[w + 1]].to_vec(), gg[w]))
        .collect()
}

/// `Equilibrium` solves each world by its own Newton iteration and adjoint solve.
#[test]
fn equilibrium_solves_each_world_apart() {
    let ids: Vec<usize> = (0..5).collect();
    let together = with_threads(2, || run_nets(&ids));
    assert!(together
        .iter()
        .all(|r| r.0 > 0.0 && r.1.iter().all(|g| *g != 0.0)));
    for j in [0, 2, 4] {
        assert_eq!(run_nets(&[j])[0], together[j], "net {j} alone");
    }
    let reversed: Vec<usize> = ids.iter().rev().copied().collect();
    let back = with_threads(1, || run_nets(&reversed));
    for (w, &j) in reversed.iter().enumerate() {
        assert_eq!(back[w], together[j], "net {j} at place {w}");
    }
}

#[test]
fn particle_worlds_refuse_what_would_cross_them() {
    use adflex_kernels::prelude::ParticleContact;
    // Particle contact is the environment's: worlds with other laws are refused.
    let mut soft = cloth_scene(1);
    soft.set_particle_contact(ParticleContact {
        ke: 10.0,
        ..ParticleContact::default()
    });
    let mut hard = cloth_scene(0);
    hard.set_particle_contact(ParticleContact::default());
    hard.add_world(&soft);
    let e = hard.try_finalize().unwrap_err().to_string();
    assert!(e.contains("particle_contact"), "{e}");
    // A world's gravity must be finite, as the model's.
    let mut bad = cloth_scene(1);
    bad.gravity = Vec3::new(0.0, f64::NAN, 0.0);
    let mut both = cloth_scene(0);
    both.add_world(&bad);
    let e = both.try_finalize().unwrap_err().to_string();
    assert!(e.contains("gravity[1]"), "{e}");
    // A spring added afterwards between two worlds would couple them.
    let mut two = cloth_scene(0).replicate(2);
    let last = two.particle_count() as u32 - 1;
    two.add_spring(1, last, 10.0, 0.0);
    let e = two.try_finalize().unwrap_err().to_string();
    assert!(e.contains("springs[") && e.contains("worlds [0, 1]"), "{e}");
}

#[test]
fn resetting_selected_cloth_worlds_keeps_the_others_and_their_gradients() {
    let model = cloth_scene(0).replicate(3).finalize();
    let s0 = model.state();
    let _ = s0.v.clone().requires_grad();
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .rollout(&model, &mut tape, &s0, None, 1e-3, 50)
        .unwrap();
    let r = model.reset_worlds(&mut tape, &s, &[1]).unwrap();
    let (x, moved, start) = (r.x.to_vec(), s.x.to_vec(), model.particle_x.to_vec());
    let w1 = model.worlds[1].particles.clone();
    assert_eq!(x[w1.clone()], start[w1.clone()]);
    let w2 = model.worlds[2].particles.clone();
    assert_eq!(x[w2.clone()], moved[w2.clone()]);
    // The gradient flows through the kept worlds only.
    let loss = Array::zeros(3);
    adflex_kernels::losses::per_world_sum_of_squares_vec3(
        &mut tape,
        &model.particle_world,
        &r.x,
        1.0,
        &loss,
    );
    tape.backward(&loss).unwrap();
    let g = s0.v.grad().unwrap().to_vec();
    assert!(g[w1].iter().all(|v| v.norm() == 0.0));
    assert!(g[w2].iter().any(|v| v.norm() > 0.0));
    assert!(model.reset_worlds(&mut tape, &s, &[3]).is_err());
}

#[test]
fn empty_worlds_count_and_shared_laws_must_agree() {
    // Empty worlds are worlds too: a share starting with one keeps its count.
    assert_eq!(ArticulationBuilder::new().replicate(3).world_count(), 3);
    let mut b = ArticulationBuilder::new();
    b.add_world(&ArticulationBuilder::new());
    b.add_world(&cartpole());
    assert_eq!(b.world_count(), 2);
    assert_eq!(b.worlds_in(0..2).world_count(), 2);
    let m: Articulations<f64> = b.finalize().unwrap();
    assert_eq!(m.worlds[0].links, 0..0);
    assert_eq!(m.worlds[1].links, 0..3);
    // Two worlds on different floors: refused, naming the world.
    let mut soft = quadruped();
    soft.ground = Some(GroundContact {
        ke: 1e3,
        ..GroundContact::default()
    });
    let mut two = quadruped();
    two.add_world(&soft);
    let e = two.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("world 1") && e.contains("ground"), "{e}");
    // A robot without a floor of its own joins a model with one.
    let mut mixed = quadruped();
    mixed.add_world(&cartpole());
    assert!(mixed.finalize::<f64>().is_ok());
}

#[test]
#[should_panic(expected = "`gravity (one per world)` has 1 elements, the model needs 2")]
fn a_gravity_array_of_the_wrong_length_is_refused_by_name() {
    let mut model: Articulations<f64> = cartpole().replicate(2).finalize().unwrap();
    model.gravity = Array::from_vec(vec![Vec3::new(0.0, 0.0, -9.81)]);
    let _ = model.step(&mut Tape::new(), &model.state(), None, 1e-2);
}

/// A tumbling body and a particle on a spring, as one world.
fn body_scene() -> ModelBuilder<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let q = Quat::from_polar_decomposition(
        1.0,
        0.4,
        nalgebra::Unit::new_normalize(Vec3::new(1.0, 0.0, 1.0)),
    );
    let inertia = Mat33::from_diagonal(&Vec3::new(0.2, 0.3, 0.4));
    let body = b.add_body(
        Vec3::new(0.0, 0.6, 0.0),
        q,
        Vec3::new(0.3, 0.0, 0.0),
        Vec3::new(0.0, 2.0, 1.0),
        1.5,
        inertia,
    );
    for p in [Vec3::new(0.1, -0.1, 0.1), Vec3::new(-0.1, -0.1, -0.1)] {
        b.add_body_contact_point(body, p);
    }
    let pin = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    let bob = b.add_particle(Vec3::new(0.5, 1.0, 0.0), Vec3::zeros(), 1.0);
    b.add_spring(pin, bob, 100.0, 0.1);
    b.set_ground(Ground::default());
    b
}

#[test]
fn resetting_selected_worlds_with_rigid_bodies() {
    let model = body_scene().replicate(3).finalize();
    let s0 = model.state();
    let v0 = s0.bodies.as_ref().unwrap().v.clone().requires_grad();
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .rollout(&model, &mut tape, &s0, None, 1e-3, 100)
        .unwrap();
    let r = model.reset_worlds(&mut tape, &s, &[1]).unwrap();
    let (rb, sb, b0) = (
        r.bodies.as_ref().unwrap(),
        s.bodies.as_ref().unwrap(),
        &model.bodies.as_ref().unwrap().initial,
    );
    assert_eq!(model.worlds[1].bodies, 1..2);
    assert_eq!(rb.x.get(1), b0.x.get(1));
    assert_eq!(rb.q.get(1), b0.q.get(1));
    assert_eq!(rb.w.get(1), b0.w.get(1));
    for k in [0, 2] {
        assert_eq!(rb.x.get(k), sb.x.get(k));
        assert_eq!(rb.q.get(k), sb.q.get(k));
        assert_eq!(rb.v.get(k), sb.v.get(k));
        assert_ne!(rb.x.get(k), b0.x.get(k), "body {k} moved");
    }
    let p1 = model.worlds[1].particles.clone();
    assert_eq!(r.x.to_vec()[p1.clone()], model.particle_x.to_vec()[p1]);
    // The gradient flows through the kept worlds only.
    let loss = Array::<f64>::zeros(1);
    tape.launch(body_height, 3, (&rb.x, &loss));
    tape.backward(&loss).unwrap();
    let g = v0.grad().unwrap().to_vec();
    assert_eq!(g[1].norm(), 0.0);
    assert!(g[0].norm() > 0.0 && g[2].norm() > 0.0, "{g:?}");
    // A state without the bodies is refused by name.
    let bare = State {
        bodies: None,
        ..s.clone()
    };
    let e = model.reset_worlds(&mut tape, &bare, &[0]).unwrap_err();
    assert!(e.to_string().contains("state.bodies"), "{e}");
}

#[diff_kernel]
fn body_height(x: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let i = tid();
    loss.atomic_add(0, x[i].y + 0.5 * x[i].x);
}

/// A pendulum (a pinned particle and a bob on a spring) on the Earth and on the Moon, as two
/// worlds of one particle model.
fn two_pendulums() -> Model<f64> {
    let mut p = ModelBuilder::<f64>::new();
    let pin = p.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    let bob = p.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    p.add_spring(pin, bob, 1e3, 1.0);
    let mut moon = p.clone();
    moon.gravity = Vec3::new(0.0, -1.62, 0.0);
    let mut b = ModelBuilder::new();
    b.add_world(&p);
    b.add_world(&moon);
    b.finalize()
}

/// Each world's loss (sum of squared positions) after 40 steps of `integrator` with gravity
/// `g`, and its gradient with respect to each world's gravity.
fn pendulum_losses<I: Integrator<f64>>(
    model: &Model<f64>,
    integrator: &I,
    g: &[Vec3<f64>],
) -> (Vec<f64>, Vec<Vec3<f64>>) {
    let mut m = model.clone();
    m.gravity = Array::from_vec(g.to_vec()).requires_grad();
    let mut tape = Tape::new();
    let s = integrator
        .rollout(&m, &mut tape, &m.state(), None, 1e-2, 40)
        .unwrap();
    let loss = Array::zeros(2);
    adflex_kernels::losses::per_world_sum_of_squares_vec3(
        &mut tape,
        &m.particle_world,
        &s.x,
        1.0,
        &loss,
    );
    tape.backward(&loss).unwrap();
    (loss.to_vec(), m.gravity.grad().unwrap().to_vec())
}

/// `d loss_w / d gravity_w` against central differences, for both worlds and every
/// component; `exact_neighbours`: the other world's loss keeps its bits.
/// `h`: the differences' step; `tol`: their relative tolerance.
fn check_pendulum_gravity<I: Integrator<f64>>(
    name: &str,
    integrator: &I,
    exact_neighbours: bool,
    (h, tol): (f64, f64),
) {
    let model = two_pendulums();
    let g0 = model.gravity.to_vec();
    assert_eq!(
        g0,
        vec![Vec3::new(0.0, -9.8, 0.0), Vec3::new(0.0, -1.62, 0.0)]
    );
    let (l, grad) = pendulum_losses(&model, integrator, &g0);
    assert_ne!(l[0], l[1], "{name}: the moon's pendulum swings slower");
    for w in 0..2 {
        for c in 0..3 {
            let (mut up, mut down) = (g0.clone(), g0.clone());
            up[w][c] += h;
            down[w][c] -= h;
            let (lu, ld) = (
                pendulum_losses(&model, integrator, &up).0,
                pendulum_losses(&model, integrator, &down).0,
            );
            let fd = (lu[w] - ld[w]) / (2.0 * h);
            assert!(
                (grad[w][c] - fd).abs() < tol * fd.abs().max(1e-2),
                "{name}, world {w}, component {c}: {} vs differences {fd}",
                grad[w][c]
            );
            if exact_neighbours {
                assert_eq!(lu[1 - w], l[1 - w], "{name}: world {} moved", 1 - w);
            }
        }
    }
}

#[test]
fn particle_worlds_have_their_own_gravity_with_gradients() {
    use adflex_kernels::prelude::{ExplicitEuler, ImplicitEuler, Midpoint, Rk4, Xpbd};
    let fine = (1e-6, 1e-6);
    check_pendulum_gravity("SemiImplicitEuler", &SemiImplicitEuler, true, fine);
    check_pendulum_gravity("Rk4", &Rk4, true, fine);
    check_pendulum_gravity("ExplicitEuler", &ExplicitEuler, true, fine);
    check_pendulum_gravity("Midpoint", &Midpoint, true, fine);
    // XPBD's velocities are position differences over a substep, which amplify the rounding
    // of the positions: a larger step (as in `every_force.rs`).
    check_pendulum_gravity("Xpbd", &Xpbd::default(), true, (1e-4, 1e-4));
    // Through the Newton solve's implicit-function-theorem adjoint.
    check_pendulum_gravity("ImplicitEuler", &ImplicitEuler::default(), false, fine);

    // The equilibrium: the bob hangs lower on the Earth; d(height)/d(g_y) = m / k per world.
    use adflex_kernels::statics::Equilibrium;
    let model = two_pendulums();
    let gravity = model.gravity.clone().requires_grad();
    let mut tape = Tape::new();
    let eq = Equilibrium::default()
        .solve(&model, &mut tape, &model.state())
        .unwrap();
    let heights = Array::zeros(1);
    tape.launch(bob_heights, 1, (&eq.x, &heights));
    tape.backward(&heights).unwrap();
    let g = gravity.grad().unwrap().to_vec();
    for (w, gw) in g.iter().enumerate() {
        let hang = eq.x.get(2 * w + 1);
        let expected = 1.0 + model.gravity.get(w).y.abs() / 1e3;
        assert!((hang.norm() - expected).abs() < 1e-9, "world {w}: {hang:?}");
        assert!((gw.y + 1e-3).abs() < 1e-9, "world {w}: {gw:?}");
    }

    // Rigid bodies fall with their world's gravity.
    let mut moon = body_scene();
    moon.gravity = Vec3::new(0.0, -1.62, 0.0);
    let mut b = body_scene();
    b.set_ground(Ground {
        offset: -100.0,
        ..Ground::default()
    });
    moon.set_ground(Ground {
        offset: -100.0,
        ..Ground::default()
    });
    let mut both = ModelBuilder::new();
    both.add_world(&b);
    both.add_world(&moon);
    let model = both.finalize();
    let s = SemiImplicitEuler
        .rollout(&model, &mut Tape::new(), &model.state(), None, 1e-3, 100)
        .unwrap();
    let v = s.bodies.unwrap().v.to_vec();
    assert!((v[0].y + 9.8 * 0.1).abs() < 1e-9, "{:?}", v[0]);
    assert!((v[1].y + 1.62 * 0.1).abs() < 1e-9, "{:?}", v[1]);
}

#[test]
#[should_panic(expected = "`gravity` (one per world) has 1 elements, the model has 2 worlds")]
fn a_particle_gravity_array_of_the_wrong_length_is_refused_by_name() {
    let mut model = two_pendulums();
    model.gravity = Array::from_vec(vec![Vec3::new(0.0, -9.8, 0.0)]);
    let _ = SemiImplicitEuler.step(&model, &mut Tape::new(), &model.state(), None, 1e-3);
}

/// The sum of the bobs' heights below their pins (particles 1 and 3).
#[diff_kernel]
fn bob_heights(x: &Array<Vec3<f64>>, out: &Array<f64>) {
    out[0] = -x[1].y - x[3].y;
}

#[test]
fn particle_contact_touches_only_particles_of_one_world() {
    use adflex_kernels::prelude::ParticleContact;
    let scene = |particles: &[(f64, f64)]| {
        let mut b = ModelBuilder::<f64>::new();
        b.gravity = Vec3::zeros();
        b.set_particle_contact(ParticleContact::default());
        for &(x, v) in particles {
            b.add_particle(Vec3::new(x, 0.0, 0.0), Vec3::new(v, 0.0, 0.0), 1.0);
        }
        b
    };
    let run = |b: &ModelBuilder<f64>| -> Vec<Vec3<f64>> {
        let model = b.finalize();
        let s = SemiImplicitEuler
            .rollout(&model, &mut Tape::new(), &model.state(), None, 1e-3, 200)
            .unwrap();
        s.x.to_vec()
    };
    // World 0: a particle thrown at a resting one, which it knocks along x; world 1's
    // particle rests overlapping world 0's target (3 mm apart, radii 1 cm).
    let hit = scene(&[(-0.1, 1.0), (0.0, 0.0)]);
    let rest = scene(&[(0.003, 0.0)]);
    let alone = run(&hit);
    assert!(
        alone[1].x > 1e-3,
        "the target was knocked on: {:?}",
        alone[1]
    );
    let mut both = ModelBuilder::new();
    both.add_world(&hit);
    both.add_world(&rest);
    let together = run(&both);
    assert_eq!(together[..2], alone[..], "world 0 keeps its bits");
    assert_eq!(together[2], Vec3::new(0.003, 0.0, 0.0), "world 1 untouched");

    // Cloths that touch themselves: each world's loss and gradients are the same bits alone,
    // among others, in another order and on another number of threads.
    let ids: Vec<usize> = (0..6).collect();
    // (Neighbours are 0.2 to 0.33 m apart.)
    let touching = Some((0.2, true));
    let together = with_threads(2, || run_cloths_with(&ids, touching));
    assert!(together.iter().all(|r| r.0 > 0.0));
    for j in [0, 5] {
        assert_eq!(
            run_cloths_with(&[j], touching)[0],
            together[j],
            "cloth {j} alone"
        );
    }
    let reversed: Vec<usize> = ids.iter().rev().copied().collect();
    let back = with_threads(1, || run_cloths_with(&reversed, touching));
    for (w, &j) in reversed.iter().enumerate() {
        assert_eq!(back[w], together[j], "cloth {j} at place {w}");
    }
    // And contact changed the cloths (the test would pass without it otherwise).
    assert_ne!(
        run_cloths_with(&[3], Some((0.2, false)))[0].0,
        together[3].0
    );
}

/// `ModelBuilder::worlds_in`: a share of different particle worlds (a rigid body with a
/// spring, a cloth with membranes, a soft block) steps each world to the bits it
/// has among all of them; what cannot be split is refused.
#[test]
fn a_share_of_particle_worlds_gives_the_same_bits() {
    use adflex_kernels::prelude::TetGrid;
    let mut soft = ModelBuilder::<f64>::new();
    soft.add_tet_grid(&TetGrid {
        origin: Vec3::new(0.0, 0.02, 0.0),
        ..TetGrid::default()
    });
    soft.set_ground(Ground::default());
    let mut membrane = cloth_scene(1);
    let t = membrane.triangles().to_vec();
    for [i, j, k] in t.into_iter().take(6) {
        membrane.add_triangle_fem(i, j, k, 100.0, 50.0, 0.1);
    }
    let scenes = [cloth_scene(0), body_scene(), membrane, soft, cloth_scene(2)];
    let mut all = ModelBuilder::<f64>::new();
    for s in &scenes {
        all.add_world(s);
    }
    let flat = |s: &State<f64>, w: &adflex_kernels::WorldRanges| {
        let mut out: Vec<u64> = s.x.to_vec()[w.particles.clone()]
            .iter()
            .chain(&s.v.to_vec()[w.particles.clone()])
            .flat_map(|p| [p.x, p.y, p.z])
            .map(f64::to_bits)
            .collect();
        if let Some(b) = &s.bodies {
            let x = b.x.to_vec();
            out.extend(
                x[w.bodies.clone()]
                    .iter()
                    .flat_map(|p| [p.x, p.y, p.z])
                    .map(f64::to_bits),
            );
        }
        out
    };
    let run = |b: &ModelBuilder<f64>| {
        let model = b.finalize();
        let s = SemiImplicitEuler
            .rollout(&model, &mut Tape::new(), &model.state(), None, 1e-3, 200)
            .unwrap();
        let per_world: Vec<Vec<u64>> = model.worlds.iter().map(|w| flat(&s, w)).collect();
        per_world
    };
    let whole = run(&all);
    let share = all.worlds_in(1..4);
    assert_eq!(share.world_count(), 3);
    let part = run(&share);
    for k in 0..3 {
        assert!(!part[k].is_empty());
        assert_eq!(
            part[k],
            whole[k + 1],
            "world {} of the whole, {k} of the share",
            k + 1
        );
    }
    // Each world alone too (the share of one world is that world's scene).
    for (k, s) in scenes.iter().enumerate() {
        assert_eq!(run(&all.worlds_in(k..k + 1))[0], run(s)[0], "world {k}");
    }

    // A force added over all particles cannot be split.
    let mut with_user = all.clone();
    with_user.add_force(adflex_kernels::forces::particle::Drag::<f64>::default());
    let e = with_user
        .worlds_in(0..2)
        .try_finalize()
        .unwrap_err()
        .to_string();
    assert!(e.contains("add_force") && e.contains("worlds_in"), "{e}");
    // An element joining two worlds cannot be split either.
    let mut joined = all.clone();
    joined.add_spring(0, all.particle_count() as u32 - 1, 10.0, 0.0);
    let e = joined
        .worlds_in(0..1)
        .try_finalize()
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("cannot be split") && e.contains("springs"),
        "{e}"
    );
    let bad = std::panic::catch_unwind(|| all.worlds_in(3..6));
    assert!(bad.is_err());
}
