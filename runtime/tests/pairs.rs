//! An adjoint runs two thread ids per iteration, their code interleaved (the macro's `lanes`);
//! its gradients are bitwise those of the ids one by one, in thread-id order, whichever way
//! each `if` goes for the two.

mod common;

use adflex_runtime::launch::SERIAL_BELOW;
use adflex_runtime::prelude::*;
use common::random;

/// Scatters (in the adjoint) into three distinct particles per id, one of them in a branch;
/// both `if`s go either way from one id to the next.
#[adflex_macros::diff_kernel]
fn triple(x: &Array<Vec3<f64>>, ids: &Array<[u32; 3]>, s: &Array<f64>, f: &Array<Vec3<f64>>) {
    let t = tid();
    let [i, j, k] = ids[t];
    let xi = x[i];
    let xj = x[j];
    let w = s[t];
    let d = xi - xj;
    let g = if dot(d, d) > w {
        d * w
    } else {
        cross(d, xi) * 2.0
    };
    if w > 0.5 {
        let xk = x[k];
        f.atomic_add(i, g * xk.x);
    } else {
        f.atomic_sub(j, g);
    }
    f.atomic_add(k, g * w);
}

const PARTICLES: usize = 6;

struct Case {
    x: Vec<Vec3<f64>>,
    ids: Vec<[u32; 3]>,
    s: Vec<f64>,
    adj_f: Vec<Vec3<f64>>,
}

fn vec3s(n: usize, seed: u64) -> Vec<Vec3<f64>> {
    let c = random(3 * n, seed, -1.0, 1.0);
    c.chunks(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect()
}

fn case(n: usize) -> Case {
    let r = random(3 * n, 2, 0.0, PARTICLES as f64);
    let ids = r
        .chunks(3)
        .map(|c| {
            // three distinct particles
            let i = c[0] as u32;
            let j = (i + 1 + c[1] as u32 % (PARTICLES as u32 - 1)) % PARTICLES as u32;
            let k = (0..PARTICLES as u32)
                .cycle()
                .skip(c[2] as usize)
                .find(|&k| k != i && k != j)
                .unwrap();
            [i, j, k]
        })
        .collect();
    Case {
        x: vec3s(PARTICLES, 1),
        ids,
        s: random(n, 3, 0.0, 1.0),
        adj_f: vec3s(PARTICLES, 4),
    }
}

/// `(x.grad, s.grad)` of the adjoint of `ids` (all at once) as bits.
fn adjoint(c: &Case, ids: &[[u32; 3]], s: &[f64]) -> (Vec<Vec3<f64>>, Vec<f64>) {
    let x = Array::from_vec(c.x.clone()).named("x");
    let (ids, s) = (Array::from_vec(ids.to_vec()), Array::from_vec(s.to_vec()));
    let f = Array::<Vec3<f64>>::zeros(PARTICLES).named("f");
    x.ensure_grad();
    s.ensure_grad();
    f.ensure_grad().assign(&c.adj_f);
    launch_adjoint(triple, ids.len(), (&x, &ids, &s, &f));
    (x.grad().unwrap().to_vec(), s.grad().unwrap().to_vec())
}

fn bits(x: &[Vec3<f64>], s: &[f64]) -> Vec<u64> {
    x.iter()
        .flat_map(|v| v.iter().copied())
        .chain(s.iter().copied())
        .map(f64::to_bits)
        .collect()
}

#[test]
fn two_ids_at_a_time_give_the_bits_of_one_at_a_time() {
    for n in [2, 3, 8, 101, SERIAL_BELOW + 1001] {
        let c = case(n);
        // One id per launch (the loop's single-id path), added up in thread-id order.
        let mut gx = vec![Vec3::zeros(); PARTICLES];
        let mut gs = Vec::new();
        let (mut took_then, mut took_else) = (0, 0);
        for t in 0..n {
            let (x1, s1) = adjoint(&c, &c.ids[t..=t], &c.s[t..=t]);
            for (g, d) in gx.iter_mut().zip(&x1) {
                *g += d;
            }
            gs.push(s1[0]);
            let d = c.x[c.ids[t][0] as usize] - c.x[c.ids[t][1] as usize];
            if d.dot(&d) > c.s[t] {
                took_then += 1;
            } else {
                took_else += 1;
            }
        }
        assert!(
            took_then > 0 && took_else > 0 || n < 8,
            "n = {n}: both branches"
        );
        let want = bits(&gx, &gs);
        for threads in 1..=3 {
            let (x, s) = with_threads(threads, || adjoint(&c, &c.ids, &c.s));
            let got = bits(&x, &s);
            let first = got.iter().zip(&want).position(|(a, b)| a != b);
            assert_eq!(
                first, None,
                "n = {n}, {threads} threads: first differing component"
            );
        }
    }
}

/// A constant named like the macro's locals (`a<N>`): the two ids' code is emitted with names
/// of their own (`a1_l0`, `a1_l1`), so the user's `a1` keeps its meaning and the kernel still
/// runs two ids per iteration.
mod consts {
    #[allow(non_upper_case_globals)]
    pub const a1: f64 = 3.0;
}

#[adflex_macros::diff_kernel]
fn named_like_locals(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    let v0 = x[t];
    y[t] = v0 * v0 * consts::a1;
}

#[test]
fn user_names_like_the_generated_ones_keep_their_meaning() {
    let xs = random(SERIAL_BELOW + 7, 5, -1.0, 1.0);
    let x = Array::from_vec(xs.clone());
    let y = Array::<f64>::zeros(xs.len());
    x.ensure_grad();
    y.ensure_grad().fill(1.0);
    launch_adjoint(named_like_locals, xs.len(), (&x, &y));
    let g = x.grad().unwrap().to_vec();
    for (t, (g, x)) in g.iter().zip(&xs).enumerate() {
        let want = 2.0 * x * consts::a1;
        assert!(
            (g - want).abs() <= 1e-14 * want.abs(),
            "x.grad[{t}]: {g} != {want}"
        );
    }
}
