//! Shares of a scene's worlds on threads, each its own model and tape: every world's loss and
//! gradients are the bits of the whole scene in one model.

use adflex_distributed::*;
use adflex_kernels::articulation::{urdf, ArticulationBuilder, Articulations};
use adflex_runtime::prelude::*;

fn scene(n: usize) -> ArticulationBuilder {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../kernels/robots/cartpole.urdf"
    );
    let base = urdf::load(path, &Default::default()).unwrap();
    let pole = base.find("pole").unwrap().0;
    let mut b = ArticulationBuilder::new();
    for w in 0..n {
        let mut s = base.clone();
        s.links_mut()[pole].joint.initial = vec![0.05 * (w + 1) as f64];
        b.add_world(&s);
    }
    b
}

fn simulate(all: &ArticulationBuilder, worlds: std::ops::Range<usize>) -> Vec<Vec<f64>> {
    let model: Articulations<f64> = all.worlds_in(worlds).finalize().unwrap();
    let _ = model.mass.clone().requires_grad();
    let mut tape = Tape::new();
    let mut s = model.state();
    for _ in 0..50 {
        s = model.step(&mut tape, &s, None, 1e-2).unwrap();
    }
    let loss = Array::zeros(model.n_worlds());
    adflex_kernels::losses::per_world_sum_of_squares(&mut tape, &model.q_world, &s.q, 1.0, &loss);
    tape.backward(&loss).unwrap();
    let g = model.mass.grad().unwrap().to_vec();
    model
        .worlds
        .iter()
        .enumerate()
        .map(|(i, w)| {
            let mut out = vec![loss.get(i)];
            out.extend(&g[w.links.clone()]);
            out
        })
        .collect()
}

#[test]
fn shares_on_threads_give_the_whole_models_bits() {
    let all = scene(40);
    let whole = WorldOutputs {
        per_world: simulate(&all, 0..40),
    };
    for shards in [2, 3, 7] {
        let out = with_threads(2, || {
            run_worlds_in_threads(40, shards, |w| Ok(simulate(&all, w))).unwrap()
        });
        assert_eq!(out, whole, "{shards} shares");
        assert_eq!(out.sum(1..4), whole.sum(1..4));
    }
}
