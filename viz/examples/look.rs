//! Writes pictures, a GIF, a USD stage and a PLY sequence of a falling cloth and of a
//! tumbling rigid body into the directory given as the first argument (default
//! `target/look`).
//!
//! `cargo run -p adflex-viz --example look -- /tmp/look`

use adflex_kernels::prelude::*;
use adflex_kernels::scenes::cloth;
use adflex_runtime::{Mat33, Quat, Tape, Vec3};
use adflex_viz::export::{self, Format};
use adflex_viz::{plot, render};

fn rollout(model: &Model<f64>, s0: &State<f64>, steps: usize, dt: f64) -> Vec<State<f64>> {
    let mut tape = Tape::new();
    let mut states = vec![s0.clone()];
    for _ in 0..steps {
        let s = SemiImplicitEuler
            .step(model, &mut tape, states.last().unwrap(), None, dt)
            .expect("step");
        states.push(s);
    }
    states
}

fn main() -> Result<(), adflex_viz::Error> {
    let dir = std::path::PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "target/look".into()),
    );
    std::fs::create_dir_all(&dir).expect("output directory");

    // A 12 x 12 cloth pinned at two corners, 0.6 s.
    let scene = cloth::build::<f64>(12);
    let states = rollout(&scene.model, &scene.initial, 600, 1e-3);
    let opts = render::RenderOptions::default();
    render::render_png(
        dir.join("cloth.png"),
        &scene.model,
        states.last().unwrap(),
        &opts,
    )?;
    let small = render::RenderOptions {
        width: 320,
        height: 240,
        ..opts.clone()
    };
    render::render_gif(
        dir.join("cloth.gif"),
        &scene.model,
        &states,
        &small,
        25.0,
        20,
    )?;
    export::write_usda(dir.join("cloth.usda"), &scene.model, &states, 1000.0)?;
    export::write_sequence(
        dir.join("cloth_ply"),
        &scene.model,
        &states[..3],
        Format::Ply,
    )?;

    // A box-shaped body tossed onto the ground.
    let mut b = ModelBuilder::<f64>::new();
    let body = b.add_body(
        Vec3::new(0.0, 0.6, 0.0),
        Quat::new(0.9, 0.3, 0.2, 0.1),
        Vec3::new(0.4, 0.0, 0.0),
        Vec3::new(1.0, 3.0, 0.5),
        1.0,
        Mat33::from_diagonal(&Vec3::new(0.02, 0.03, 0.04)),
    );
    for sx in [-0.2, 0.2] {
        for sy in [-0.1, 0.1] {
            for sz in [-0.15, 0.15] {
                b.add_body_contact_point(body, Vec3::new(sx, sy, sz));
            }
        }
    }
    b.set_ground(Ground::default());
    let model = b.finalize();
    let states = rollout(&model, &model.state(), 400, 1e-3);
    render::render_png(dir.join("body.png"), &model, &states[200], &opts)?;
    export::write_usda(dir.join("body.usda"), &model, &states, 1000.0)?;

    let losses: Vec<f64> = (0..60).map(|k| 3.0 * 0.85f64.powi(k) + 1e-4).collect();
    plot::loss_curve(dir.join("loss.svg"), &losses, "a loss curve")?;
    println!("wrote {}", dir.display());
    Ok(())
}
