//! Where the generated kernels lose time against hand-written code: the hand-written spring
//! forward rewritten step by step towards what the runtime's views do.

use std::time::Duration;

use adflex_runtime::prelude::*;

use crate::kernels_cmp::{Problem, KD};
use crate::timing::{fmt_s, interleaved, Case};

#[cold]
#[inline(never)]
fn oob(i: usize, len: usize) -> ! {
    panic!("index {i} out of bounds (len {len})")
}

struct RawReader<T> {
    ptr: *const T,
    len: usize,
}
impl<T: Copy> RawReader<T> {
    #[inline(always)]
    fn get(&self, i: usize) -> T {
        if i >= self.len {
            oob(i, self.len)
        }
        unsafe { *self.ptr.add(i) }
    }
}

/// A scatter like the runtime's: a direct flag, a log for the other mode.
struct RawScatter<T> {
    ptr: *mut T,
    len: usize,
    direct: bool,
    log: Vec<(u32, T)>,
}
impl<T: Value> RawScatter<T> {
    #[inline(always)]
    fn add(&mut self, i: usize, v: T) {
        if i >= self.len {
            oob(i, self.len)
        }
        if self.direct {
            unsafe { (*self.ptr.add(i)).acc(v) }
        } else {
            self.log.push((i as u32, v));
        }
    }
}

/// Raw-pointer reads and writes (no aliasing information), plain accumulation.
fn raw_direct(
    x: &[Vec3],
    v: &[Vec3],
    pairs: &[[u32; 2]],
    rest: &[f32],
    ke: &[f32],
    kd: f32,
    f: &mut [Vec3],
) {
    let xr = RawReader {
        ptr: x.as_ptr(),
        len: x.len(),
    };
    let vr = RawReader {
        ptr: v.as_ptr(),
        len: v.len(),
    };
    let pr = RawReader {
        ptr: pairs.as_ptr(),
        len: pairs.len(),
    };
    let rr = RawReader {
        ptr: rest.as_ptr(),
        len: rest.len(),
    };
    let kr = RawReader {
        ptr: ke.as_ptr(),
        len: ke.len(),
    };
    let fp = f.as_mut_ptr();
    let flen = f.len();
    for t in 0..pairs.len() {
        let [i, j] = pr.get(t);
        let (i, j) = (i as usize, j as usize);
        let xij = xr.get(i) - xr.get(j);
        let vij = vr.get(i) - vr.get(j);
        let l = xij.norm();
        let d = xij / l;
        let fs = d * (kr.get(t) * (l - rr.get(t)) + kd * d.dot(&vij));
        if i >= flen || j >= flen {
            oob(i.max(j), flen)
        }
        unsafe {
            *fp.add(i) -= fs;
            *fp.add(j) += fs;
        }
    }
}

#[allow(clippy::too_many_arguments)]
/// [`raw_direct`] with the runtime-like scatter (direct flag checked per add, log path).
fn raw_scatter(
    x: &[Vec3],
    v: &[Vec3],
    pairs: &[[u32; 2]],
    rest: &[f32],
    ke: &[f32],
    kd: f32,
    f: &mut [Vec3],
    direct: bool,
) {
    let xr = RawReader {
        ptr: x.as_ptr(),
        len: x.len(),
    };
    let vr = RawReader {
        ptr: v.as_ptr(),
        len: v.len(),
    };
    let pr = RawReader {
        ptr: pairs.as_ptr(),
        len: pairs.len(),
    };
    let rr = RawReader {
        ptr: rest.as_ptr(),
        len: rest.len(),
    };
    let kr = RawReader {
        ptr: ke.as_ptr(),
        len: ke.len(),
    };
    let mut fs_ = RawScatter {
        ptr: f.as_mut_ptr(),
        len: f.len(),
        direct,
        log: Vec::new(),
    };
    for t in 0..pairs.len() {
        let [i, j] = pr.get(t);
        let (i, j) = (i as usize, j as usize);
        let xij = xr.get(i) - xr.get(j);
        let vij = vr.get(i) - vr.get(j);
        let l = xij.norm();
        let d = xij / l;
        let fs = d * (kr.get(t) * (l - rr.get(t)) + kd * d.dot(&vij));
        let mut neg = Vec3::zeros();
        neg.acc_neg(fs);
        fs_.add(i, neg);
        fs_.add(j, fs);
    }
    std::hint::black_box(&fs_.log);
}

/// The runtime's math rules (what the macro emits) on slices.
fn runtime_math(
    x: &[Vec3],
    v: &[Vec3],
    pairs: &[[u32; 2]],
    rest: &[f32],
    ke: &[f32],
    kd: f32,
    f: &mut [Vec3],
) {
    use adflex_runtime::math as m;
    for t in 0..pairs.len() {
        let [i, j] = pairs[t];
        let (i, j) = (i as usize, j as usize);
        let xij = m::sub(x[i], x[j]);
        let vij = m::sub(v[i], v[j]);
        let l = m::length(xij);
        let d = m::div(xij, l);
        let c = m::sub(l, rest[t]);
        let dcdt = m::dot(d, vij);
        let fs = m::mul(d, m::add(m::mul(ke[t], c), m::mul(kd, dcdt)));
        f[i] -= fs;
        f[j] += fs;
    }
}

pub fn main() {
    let p = Problem::<f32>::new(128);
    let t = &p.topo;
    let kd = KD as f32;
    let g = crate::kernels_cmp::GenArrays::new(&p);
    let mut f = vec![Vec3::zeros(); p.x.len()];
    let (mut f2, mut f3, mut f4) = (f.clone(), f.clone(), f.clone());
    let direct = std::hint::black_box(true);
    with_threads(1, || {
        let mut cases = vec![
            Case::new("hand, slices", || {
                f.fill(Vec3::zeros());
                crate::hand::springs_fwd(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f)
            }),
            Case::new("hand, raw pointers + bounds checks", || {
                f2.fill(Vec3::zeros());
                raw_direct(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f2)
            }),
            Case::new("hand, raw pointers + runtime-like scatter", || {
                f3.fill(Vec3::zeros());
                raw_scatter(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f3, direct)
            }),
            Case::new("slices, runtime math rules", || {
                f4.fill(Vec3::zeros());
                runtime_math(&p.x, &p.v, &t.springs, &t.rest, &p.ke, kd, &mut f4)
            }),
            Case::new("generated launch", || {
                g.f.fill(Vec3::zeros());
                g.springs_fwd()
            }),
        ];
        let s = interleaved(&mut cases, 7, Duration::from_millis(100));
        println!(
            "springs forward, N=128 ({} springs), 1 thread:",
            t.springs.len()
        );
        for (c, s) in cases.iter().zip(s) {
            println!("  {:<45} {}", c.name, fmt_s(s));
        }
    });
}
