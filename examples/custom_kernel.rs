//! Write your own force kernel, launch it on a tape and check its gradient.
//!
//! A ring of particles joined by damped springs; the loss is the squared norm of the net force
//! on each particle. The gradient with respect to every spring's stiffness comes from the
//! adjoint kernels the macro generated; it is printed beside central finite differences.
//!
//! Run: `cargo run --release --example custom_kernel`

use adflex::prelude::*;

/// The force of one damped spring on its first particle (Hooke along the spring plus damping).
#[diff_func]
fn spring_force<R: Real>(xij: Vec3<R>, vij: Vec3<R>, rest: R, ke: R, kd: R) -> Vec3<R> {
    let l = length(xij);
    let d = xij / l;
    d * (ke * (l - rest) + kd * dot(d, vij))
}

#[diff_kernel]
fn eval_springs<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    ke: &Array<R>,
    kd: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let fs = spring_force(x[i] - x[j], v[i] - v[j], rest[t], ke[t], kd);
    f.atomic_sub(i, fs);
    f.atomic_add(j, fs);
}

#[diff_kernel]
fn force_norm<R: Real>(f: &Array<Vec3<R>>, loss: &Array<R>) {
    let fi = f[tid()];
    loss.atomic_add(0, dot(fi, fi));
}

struct Ring {
    x: Array<Vec3<f64>>,
    v: Array<Vec3<f64>>,
    pairs: Array<[u32; 2]>,
    rest: Array<f64>,
    ke: Array<f64>,
}

/// Runs the forward pass on `tape`; returns the loss array.
fn loss(tape: &mut Tape, r: &Ring) -> Array<f64> {
    let f = Array::zeros(r.x.len()).named("f");
    let loss = Array::zeros(1).named("loss");
    tape.launch(
        eval_springs,
        r.pairs.len(),
        (&r.x, &r.v, &r.pairs, &r.rest, &r.ke, 0.1, &f),
    );
    tape.launch(force_norm, f.len(), (&f, &loss));
    loss
}

fn main() -> Result<(), Error> {
    let n = 8;
    let x: Vec<Vec3<f64>> = (0..n)
        .map(|k| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            Vec3::new(
                a.cos() * (1.0 + 0.1 * (3.0 * a).sin()),
                a.sin(),
                0.05 * k as f64,
            )
        })
        .collect();
    let v: Vec<Vec3<f64>> = (0..n)
        .map(|k| Vec3::new(0.0, 0.1 * k as f64, 0.0))
        .collect();
    let pairs: Vec<[u32; 2]> = (0..n as u32).map(|k| [k, (k + 1) % n as u32]).collect();
    let ring = Ring {
        x: Array::from_vec(x).named("x"),
        v: Array::from_vec(v).named("v"),
        pairs: Array::from_vec(pairs).named("pairs"),
        rest: Array::from_vec(vec![0.7; n]).named("rest"),
        ke: Array::from_vec((0..n).map(|k| 10.0 + k as f64).collect())
            .named("ke")
            .requires_grad(),
    };

    let mut tape = Tape::new();
    let l = loss(&mut tape, &ring);
    tape.backward(&l)?;
    let grad = ring.ke.grad()?.to_vec();
    println!("loss = {:.6}", l.get(0));
    println!(
        "{:>6} {:>16} {:>16} {:>10}",
        "spring", "adjoint dL/dke", "central diff", "rel err"
    );
    let h = 1e-6;
    let mut worst: f64 = 0.0;
    for (k, g) in grad.iter().enumerate() {
        let ke0 = ring.ke.get(k);
        ring.ke.set(k, ke0 + h);
        let lp = loss(&mut Tape::new(), &ring).get(0);
        ring.ke.set(k, ke0 - h);
        let lm = loss(&mut Tape::new(), &ring).get(0);
        ring.ke.set(k, ke0);
        let fd = (lp - lm) / (2.0 * h);
        let rel = (g - fd).abs() / fd.abs().max(1e-12);
        worst = worst.max(rel);
        println!("{k:>6} {g:>16.9e} {fd:>16.9e} {rel:>10.1e}");
    }
    println!("worst relative error: {worst:.1e}");
    assert!(worst < 1e-6, "adjoint and finite differences disagree");
    Ok(())
}
