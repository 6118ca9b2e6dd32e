//! `kernels`: the generated spring and bending kernels ([`crate::gen`]) against the
//! hand-written ones ([`crate::hand`]): same results, and the time of each, serial.

use std::time::Duration;

use adflex_runtime::prelude::*;

use crate::timing::{fmt_s, interleaved, Case};
use crate::topo::{cloth, ClothTopo};
use crate::{gen, hand};

/// A deterministic pseudo-random number in `[-1, 1)` from two integers.
pub fn hash01(a: u64, b: u64) -> f64 {
    let mut z = a
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(b.wrapping_mul(0xBF58_476D_1CE4_E5B9))
        .wrapping_add(0x94D0_49BB_1331_11EB);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

fn rvec<R: Real>(seed: u64, k: usize, scale: f64) -> Vec3<R> {
    let k = k as u64 * 3;
    Vec3::new(
        R::lit(scale * hash01(seed, k)),
        R::lit(scale * hash01(seed, k + 1)),
        R::lit(scale * hash01(seed, k + 2)),
    )
}

/// A wrinkled, moving cloth state (so no bending element is flat) and a random cotangent.
pub struct Problem<R: Real> {
    pub topo: ClothTopo<R>,
    pub x: Vec<Vec3<R>>,
    pub v: Vec<Vec3<R>>,
    pub ke: Vec<R>,
    pub brest: Vec<R>,
    pub adj_f: Vec<Vec3<R>>,
}

impl<R: Real> Problem<R> {
    pub fn new(n: usize) -> Self {
        let topo = cloth::<R>(n);
        let h = 1.0 / (n - 1) as f64;
        let x = topo
            .x0
            .iter()
            .enumerate()
            .map(|(k, p)| p + rvec::<R>(1, k, 0.2 * h))
            .collect();
        let v = (0..n * n).map(|k| rvec::<R>(2, k, 0.1)).collect();
        let adj_f = (0..n * n).map(|k| rvec::<R>(3, k, 1.0)).collect();
        Problem {
            ke: vec![R::lit(50.0); topo.springs.len()],
            brest: vec![R::lit(0.0); topo.bends.len()],
            x,
            v,
            adj_f,
            topo,
        }
    }
}

pub const KD: f64 = 0.1;
pub const KE_B: f64 = 0.01;
pub const KD_B: f64 = 0.0;

/// Relative difference `||a - b|| / ||b||` (Euclidean norms over every component).
pub fn rel_err<V: Value>(a: &[V], b: &[V]) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for (p, q) in a.iter().zip(b) {
        for k in 0..V::DIM {
            num += (p.component(k) - q.component(k)).powi(2);
            den += q.component(k).powi(2);
        }
    }
    (num / den.max(1e-300)).sqrt()
}

/// The arrays of the generated side.
pub struct GenArrays<R: Real> {
    pub x: Array<Vec3<R>>,
    pub v: Array<Vec3<R>>,
    pub pairs: Array<[u32; 2]>,
    pub rest: Array<R>,
    pub ke: Array<R>,
    pub quads: Array<[u32; 4]>,
    pub brest: Array<R>,
    pub f: Array<Vec3<R>>,
}

impl<R: Real> GenArrays<R> {
    pub fn new(p: &Problem<R>) -> Self {
        let a = GenArrays {
            x: Array::from_vec(p.x.clone()).named("x"),
            v: Array::from_vec(p.v.clone()).named("v"),
            pairs: Array::from_vec(p.topo.springs.clone()).named("pairs"),
            rest: Array::from_vec(p.topo.rest.clone()).named("rest"),
            ke: Array::from_vec(p.ke.clone()).named("ke"),
            quads: Array::from_vec(p.topo.bends.clone()).named("quads"),
            brest: Array::from_vec(p.brest.clone()).named("brest"),
            f: Array::zeros(p.x.len()).named("f"),
        };
        a.x.ensure_grad();
        a.v.ensure_grad();
        a.ke.ensure_grad();
        a.f.ensure_grad().assign(&p.adj_f);
        a
    }
    pub fn springs_fwd(&self) {
        let kd = R::lit(KD);
        launch(
            gen::eval_springs,
            self.pairs.len(),
            (
                &self.x,
                &self.v,
                &self.pairs,
                &self.rest,
                &self.ke,
                kd,
                &self.f,
            ),
        );
    }
    pub fn springs_adj(&self) {
        let kd = R::lit(KD);
        launch_adjoint(
            gen::eval_springs,
            self.pairs.len(),
            (
                &self.x,
                &self.v,
                &self.pairs,
                &self.rest,
                &self.ke,
                kd,
                &self.f,
            ),
        );
    }
    pub fn bending_fwd(&self) {
        let (ke, kd) = (R::lit(KE_B), R::lit(KD_B));
        launch(
            gen::eval_bending,
            self.quads.len(),
            (&self.x, &self.v, &self.quads, &self.brest, ke, kd, &self.f),
        );
    }
    pub fn bending_adj(&self) {
        let (ke, kd) = (R::lit(KE_B), R::lit(KD_B));
        launch_adjoint(
            gen::eval_bending,
            self.quads.len(),
            (&self.x, &self.v, &self.quads, &self.brest, ke, kd, &self.f),
        );
    }
    pub fn zero(&self) {
        self.f.fill(Vec3::zeros());
        self.x.zero_grad();
        self.v.zero_grad();
        self.ke.zero_grad();
    }
}

/// Relative differences generated vs hand-written:
/// `[springs f, springs adj x, adj v, adj ke, bending f, bending adj x, adj v]`.
pub fn check<R: Real>(n: usize) -> [f64; 7] {
    let p = Problem::<R>::new(n);
    let g = GenArrays::new(&p);
    let t = &p.topo;
    let np = p.x.len();
    let (kd, keb, kdb) = (R::lit(KD), R::lit(KE_B), R::lit(KD_B));
    let mut out = [0.0; 7];
    with_threads(1, || {
        // springs
        g.zero();
        g.springs_fwd();
        g.springs_adj();
        let mut f = vec![Vec3::zeros(); np];
        hand::springs_fwd(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f);
        let (mut ax, mut av, mut ak) = (
            vec![Vec3::zeros(); np],
            vec![Vec3::zeros(); np],
            vec![R::zero(); p.ke.len()],
        );
        hand::springs_adj(
            &p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &p.adj_f, &mut ax, &mut av, &mut ak,
        );
        out[0] = rel_err(&g.f.to_vec(), &f);
        out[1] = rel_err(&g.x.grad().unwrap().to_vec(), &ax);
        out[2] = rel_err(&g.v.grad().unwrap().to_vec(), &av);
        out[3] = rel_err(&g.ke.grad().unwrap().to_vec(), &ak);
        // bending, with damping on so that the v adjoint is checked too
        let kdb = kdb + R::lit(1e-3);
        g.zero();
        launch(
            gen::eval_bending,
            g.quads.len(),
            (&g.x, &g.v, &g.quads, &g.brest, keb, kdb, &g.f),
        );
        launch_adjoint(
            gen::eval_bending,
            g.quads.len(),
            (&g.x, &g.v, &g.quads, &g.brest, keb, kdb, &g.f),
        );
        let mut f = vec![Vec3::zeros(); np];
        hand::bending_fwd(&p.x, &p.v, &t.bends, &p.brest, keb, kdb, &mut f);
        let (mut ax, mut av) = (vec![Vec3::zeros(); np], vec![Vec3::zeros(); np]);
        hand::bending_adj(
            &p.x, &p.v, &t.bends, &p.brest, keb, kdb, &p.adj_f, &mut ax, &mut av,
        );
        out[4] = rel_err(&g.f.to_vec(), &f);
        out[5] = rel_err(&g.x.grad().unwrap().to_vec(), &ax);
        out[6] = rel_err(&g.v.grad().unwrap().to_vec(), &av);
    });
    out
}

/// One row: kernel, N, pass, generated s, hand s.
pub struct Row {
    pub kernel: &'static str,
    pub n: usize,
    pub dim: usize,
    pub pass: &'static str,
    pub generated: f64,
    pub hand: f64,
}

/// Times the four kernels (forward, adjoint; generated and hand) at `n`, f32, one thread.
pub fn time(n: usize, rounds: usize, batch: Duration) -> Vec<Row> {
    let p = Problem::<f32>::new(n);
    let g = GenArrays::new(&p);
    let t = &p.topo;
    let np = p.x.len();
    let (kd, keb, kdb) = (KD as f32, KE_B as f32, KD_B as f32);
    with_threads(1, || {
        let mut f = vec![Vec3::zeros(); np];
        let (mut ax, mut av, mut ak) = (
            vec![Vec3::zeros(); np],
            vec![Vec3::zeros(); np],
            vec![0.0f32; p.ke.len()],
        );
        let mut f2 = f.clone();
        let (mut bx, mut bv) = (ax.clone(), av.clone());
        let mut cases = vec![
            Case::new("springs fwd gen", || {
                g.f.fill(Vec3::zeros());
                g.springs_fwd()
            }),
            Case::new("springs fwd hand", || {
                f.fill(Vec3::zeros());
                hand::springs_fwd(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f)
            }),
            Case::new("springs adj gen", || g.springs_adj()),
            Case::new("springs adj hand", || {
                hand::springs_adj(
                    &p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &p.adj_f, &mut ax, &mut av, &mut ak,
                )
            }),
            Case::new("bending fwd gen", || {
                g.f.fill(Vec3::zeros());
                g.bending_fwd()
            }),
            Case::new("bending fwd hand", || {
                f2.fill(Vec3::zeros());
                hand::bending_fwd(&p.x, &p.v, &t.bends, &p.brest, keb, kdb, &mut f2)
            }),
            Case::new("bending adj gen", || g.bending_adj()),
            Case::new("bending adj hand", || {
                hand::bending_adj(
                    &p.x, &p.v, &t.bends, &p.brest, keb, kdb, &p.adj_f, &mut bx, &mut bv,
                )
            }),
        ];
        let s = interleaved(&mut cases, rounds, batch);
        let (ns, nb) = (t.springs.len(), t.bends.len());
        vec![
            Row {
                kernel: "springs",
                n,
                dim: ns,
                pass: "forward",
                generated: s[0],
                hand: s[1],
            },
            Row {
                kernel: "springs",
                n,
                dim: ns,
                pass: "adjoint",
                generated: s[2],
                hand: s[3],
            },
            Row {
                kernel: "bending",
                n,
                dim: nb,
                pass: "forward",
                generated: s[4],
                hand: s[5],
            },
            Row {
                kernel: "bending",
                n,
                dim: nb,
                pass: "adjoint",
                generated: s[6],
                hand: s[7],
            },
        ]
    })
}

pub fn main(quick: bool) {
    let (rounds, batch) = if quick {
        (2, Duration::from_millis(20))
    } else {
        (7, Duration::from_millis(100))
    };
    println!("machine: {}", crate::timing::machine());
    println!(
        "date: {}, load average at start: {}\n",
        crate::timing::today(),
        crate::timing::loadavg()
    );
    for (name, e) in [("f64", check::<f64>(16)), ("f32", check::<f32>(64))] {
        println!(
            "{name}: relative difference generated vs hand: springs f {:.1e}, adj x {:.1e}, adj v {:.1e}, adj ke {:.1e}; bending f {:.1e}, adj x {:.1e}, adj v {:.1e}",
            e[0], e[1], e[2], e[3], e[4], e[5], e[6]
        );
    }
    println!(
        "\n| kernel | N | threads (dim) | pass | generated | hand-written | generated / hand |"
    );
    println!("|---|---:|---:|---|---:|---:|---:|");
    for n in [64, 128] {
        for r in time(n, rounds, batch) {
            println!(
                "| {} | {} | {} | {} | {} | {} | {:.2} |",
                r.kernel,
                r.n,
                r.dim,
                r.pass,
                fmt_s(r.generated),
                fmt_s(r.hand),
                r.generated / r.hand
            );
        }
    }
}
