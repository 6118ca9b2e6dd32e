//! The corpus generator: random kernels and functions in the kernel language, from a seed.
//!
//! Every value a generated program computes stays in a known range. The generator tracks an
//! interval for each scalar (and for each component of vectors and matrices) and only emits an
//! operation where it is smooth and well conditioned: `sqrt`, `ln`, `pow` and divisors get
//! arguments bounded away from 0, `normalize` and `length` vectors bounded away from 0,
//! `inverse` diagonally dominant matrices, quaternions are unit. A value whose range grows past
//! a cap is squashed (`B * tanh(x / B)` for scalars, `v / (1 + |v|^2 / 100)` for vectors and
//! matrices). A `let mut` local has a fixed range (its envelope) and every assignment to it is
//! squashed into that range, so loops, branches and early exits never let values drift.
//! So finite differences stay accurate (values O(1)..O(100), derivatives bounded) and the
//! checks can use tight tolerances.

use std::collections::BTreeSet;
use std::fmt::Write;

// ---- random numbers --------------------------------------------------------------------------

/// xorshift64* (deterministic, no dependencies).
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng((seed ^ 0x9E37_79B9_7F4A_7C15) | 1)
    }
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    pub fn f(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    pub fn chance(&mut self, p: f64) -> bool {
        self.f() < p
    }
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f()
    }
    pub fn int(&mut self, lo: usize, hi: usize) -> usize {
        lo + self.below(hi - lo + 1)
    }
    /// An index chosen with the given weights.
    pub fn weighted(&mut self, w: &[u32]) -> usize {
        let total: u32 = w.iter().sum();
        let mut r = (self.next() % total as u64) as u32;
        for (i, &x) in w.iter().enumerate() {
            if r < x {
                return i;
            }
            r -= x;
        }
        unreachable!()
    }
}

// ---- intervals ---------------------------------------------------------------------------------

#[derive(Clone, Copy, Debug)]
pub struct Iv {
    pub lo: f64,
    pub hi: f64,
}

fn iv(lo: f64, hi: f64) -> Iv {
    assert!(
        lo <= hi && lo.is_finite() && hi.is_finite(),
        "bad interval [{lo}, {hi}]"
    );
    Iv { lo, hi }
}

impl Iv {
    fn pt(c: f64) -> Iv {
        iv(c, c)
    }
    fn add(self, o: Iv) -> Iv {
        iv(self.lo + o.lo, self.hi + o.hi)
    }
    fn sub(self, o: Iv) -> Iv {
        iv(self.lo - o.hi, self.hi - o.lo)
    }
    fn neg(self) -> Iv {
        iv(-self.hi, -self.lo)
    }
    fn mul(self, o: Iv) -> Iv {
        let c = [
            self.lo * o.lo,
            self.lo * o.hi,
            self.hi * o.lo,
            self.hi * o.hi,
        ];
        iv(
            c.iter().cloned().fold(f64::INFINITY, f64::min),
            c.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
        )
    }
    fn scale(self, c: f64) -> Iv {
        self.mul(Iv::pt(c))
    }
    fn hull(self, o: Iv) -> Iv {
        iv(self.lo.min(o.lo), self.hi.max(o.hi))
    }
    /// Largest magnitude.
    fn mag(self) -> f64 {
        self.lo.abs().max(self.hi.abs())
    }
    /// Smallest magnitude.
    fn mig(self) -> f64 {
        if self.lo > 0.0 {
            self.lo
        } else if self.hi < 0.0 {
            -self.hi
        } else {
            0.0
        }
    }
    fn div(self, d: Iv) -> Iv {
        assert!(d.mig() > 0.0);
        self.mul(iv(1.0 / d.hi, 1.0 / d.lo))
    }
    fn sqr(self) -> Iv {
        iv(self.mig() * self.mig(), self.mag() * self.mag())
    }
    /// Image under an increasing function.
    fn inc(self, f: impl Fn(f64) -> f64) -> Iv {
        iv(f(self.lo), f(self.hi))
    }
    fn within(self, o: Iv) -> bool {
        self.lo >= o.lo && self.hi <= o.hi
    }
}

/// Generate `m[(r, c)] = e` (rejected by the macro: "tuples are not supported in kernels
/// (except as a matrix index `m[(r, c)]`)"; reported, off until fixed).
const MAT_COMPONENT_STORE: bool = false;
/// Generate `(k * 2 + t) % n` for the index `k` of an unrolled loop (does not compile: the
/// constant `k` and `2` are untyped literals, `mul`'s `MulRule<B>::Out` leaves them `i32`;
/// reported, off until fixed).
const MUL_UNROLLED_INDEX: bool = false;
/// Generate calls of `#[diff_func]`s inside `no_grad(..)` (do not compile: "expected function,
/// found `f35`"; reported, off until fixed).
const CALL_IN_NO_GRAD: bool = false;
/// Generate stores to `y[t]` that a later store overwrites (`y[t] = a; .. y[t] = b;`, or a
/// store in a loop or a branch): only the last store of an element may receive its gradient.
const REPEATED_STORE: bool = true;

/// Sizes of the generated programs. They set the compile time: the macro emits ~10
/// statements per operation over the forward, adjoint and tangent kernels, each compiled in f32
/// and f64, and a kernel costs ~0.5 s of compile time even when tiny.
#[derive(Clone, Copy, Debug)]
pub struct Sizes {
    /// Statements of a kernel body (nested blocks take from the same budget).
    pub kernel_stmts: (usize, usize),
    /// Statements of a `#[diff_func]` body.
    pub func_stmts: (usize, usize),
    /// Probability that a scalar expression is a leaf where depth allows more.
    pub leaf_p: f64,
    /// Every how many kernels (and functions) may use matrices and quaternions (they compile
    /// slowly).
    pub linalg_every: usize,
    /// Largest expression depth of a statement.
    pub stmt_depth: usize,
}

impl Sizes {
    /// The checked-in corpus (compiles in under 2 minutes on 2 cores).
    pub const DEFAULT: Sizes = Sizes {
        kernel_stmts: (2, 4),
        func_stmts: (1, 2),
        leaf_p: 0.6,
        linalg_every: 8,
        stmt_depth: 2,
    };
    /// Larger programs, for bug hunting with other seeds (`ADFLEX_CORPUS_SIZE=big`).
    pub const BIG: Sizes = Sizes {
        kernel_stmts: (5, 10),
        func_stmts: (2, 4),
        leaf_p: 0.35,
        linalg_every: 2,
        stmt_depth: 3,
    };
}

static SIZES: std::sync::OnceLock<Sizes> = std::sync::OnceLock::new();

/// Sets the sizes (once, before generating).
pub fn set_sizes(s: Sizes) {
    SIZES.set(s).expect("sizes set twice");
}

pub fn sizes() -> Sizes {
    *SIZES.get_or_init(|| Sizes::DEFAULT)
}

fn exp(k: &str) -> bool {
    std::env::var("ADFLEX_CORPUS_EXPERIMENT").map_or(false, |v| v.contains(k))
}

const UNIT: Iv = Iv { lo: -1.0, hi: 1.0 };
const INPUT: Iv = Iv { lo: 0.5, hi: 1.5 };
/// Scalars whose magnitude may exceed this are squashed.
const CAP: f64 = 8.0;

/// A float literal rounded to 2 decimals (and its value).
fn lit(v: f64) -> (String, f64) {
    let r = (v * 100.0).round() / 100.0;
    let r = if r == 0.0 { 0.0 } else { r };
    let s = format!("{r:?}");
    (if r < 0.0 { format!("({s})") } else { s }, r)
}

fn round_up(v: f64) -> f64 {
    (v * 100.0).ceil() / 100.0
}

fn round_down(v: f64) -> f64 {
    (v * 100.0).floor() / 100.0
}

// ---- typed expressions -------------------------------------------------------------------

#[derive(Clone)]
struct S {
    s: String,
    iv: Iv,
}

#[derive(Clone)]
struct V {
    s: String,
    c: [Iv; 3],
    /// A lower bound of the length.
    nlo: f64,
}

#[derive(Clone)]
struct M {
    s: String,
    /// Row-major.
    c: [Iv; 9],
}

#[derive(Clone)]
struct Q {
    s: String,
}

fn vnlo(c: &[Iv; 3]) -> f64 {
    c.iter().map(|x| x.mig() * x.mig()).sum::<f64>().sqrt()
}

fn vnhi(c: &[Iv; 3]) -> f64 {
    c.iter().map(|x| x.mag() * x.mag()).sum::<f64>().sqrt()
}

fn vmag(c: &[Iv; 3]) -> f64 {
    c.iter().map(|x| x.mag()).fold(0.0, f64::max)
}

fn mmag(c: &[Iv; 9]) -> f64 {
    c.iter().map(|x| x.mag()).fold(0.0, f64::max)
}

fn v_of(s: String, c: [Iv; 3]) -> V {
    let nlo = vnlo(&c);
    V { s, c, nlo }
}

/// Margin of diagonal dominance: min over rows of `|m_rr| - sum |m_rc|` (positive diagonal).
fn dominance(c: &[Iv; 9]) -> f64 {
    (0..3)
        .map(|r| {
            let d = c[r * 3 + r].lo;
            let off: f64 = (0..3).filter(|&k| k != r).map(|k| c[r * 3 + k].mag()).sum();
            d - off
        })
        .fold(f64::INFINITY, f64::min)
}

#[derive(Clone)]
enum Ty {
    S(Iv),
    V([Iv; 3], f64),
    M([Iv; 9]),
    Q,
}

#[derive(Clone)]
struct Var {
    name: String,
    ty: Ty,
    mutable: bool,
}

#[derive(Clone)]
struct IntVar {
    name: String,
    /// Known to be in `0..n` (usable as an index as it is).
    safe: bool,
    /// The index of an unrolled loop: a constant, whose integer type Rust infers from use.
    unrolled: bool,
    /// A `let mut` index (`j = (j + c) % n` keeps it in `0..n`).
    mutable: bool,
}

/// A generated `#[diff_func]`'s signature.
#[derive(Clone)]
pub struct FuncSig {
    pub name: String,
    params: Vec<Ty>,
    ret: Ty,
}

/// Counts of the constructs the corpus contains.
#[derive(Default, Debug)]
pub struct Features {
    pub counts: std::collections::BTreeMap<&'static str, usize>,
}

impl Features {
    fn hit(&mut self, k: &'static str) {
        *self.counts.entry(k).or_default() += 1;
    }
}

#[derive(Clone, Copy, PartialEq)]
enum LoopKind {
    /// Unrolled (constant bounds).
    Const,
    /// Dynamic (`for k in 0..n`, `while`, `loop`).
    Dynamic,
}

// ---- the generator --------------------------------------------------------------------------

pub struct Gen<'a> {
    pub rng: Rng,
    pub feat: &'a mut Features,
    funcs: &'a [FuncSig],
    kernel: bool,
    n_inputs: usize,
    has_idx: bool,
    atomic: bool,
    scopes: Vec<Vec<Var>>,
    ints: Vec<Vec<IntVar>>,
    loops: Vec<LoopKind>,
    next: usize,
    /// Statements left to generate.
    budget: i32,
    pub called: BTreeSet<usize>,
    /// In a `#[diff_func]`: the return type, and the hull of what `return` statements return.
    ret: Option<Ty>,
    ret_iv: Option<RetIv>,
    /// No `#[diff_func]` calls (inside `no_grad`).
    no_calls: bool,
    /// Matrices and quaternions are allowed (they compile slowly: a quarter of the kernels).
    linalg: bool,
    /// The kernel has a value parameter `p: R` (passed `VALUE_PARAM`).
    pub value_param: bool,
    /// `let mut` booleans in scope (per scope).
    bools: Vec<Vec<String>>,
    /// The index of every store to `y`: `t`, or a shift `(t + c) % n` that the macro cannot
    /// prove is the thread's own (a run-time checked store). One per kernel, so that each
    /// thread stores to one element.
    store_index: String,
}

#[derive(Clone)]
enum RetIv {
    S(Iv),
    V([Iv; 3], f64),
}

fn ind(n: usize) -> String {
    "    ".repeat(n)
}

impl<'a> Gen<'a> {
    fn new(rng: Rng, feat: &'a mut Features, funcs: &'a [FuncSig]) -> Self {
        Gen {
            rng,
            feat,
            funcs,
            kernel: true,
            n_inputs: 2,
            has_idx: false,
            atomic: false,
            scopes: vec![Vec::new()],
            ints: vec![Vec::new()],
            loops: Vec::new(),
            next: 0,
            budget: 0,
            called: BTreeSet::new(),
            ret: None,
            ret_iv: None,
            no_calls: false,
            linalg: true,
            value_param: false,
            bools: vec![Vec::new()],
            store_index: "t".into(),
        }
    }

    fn fresh(&mut self, p: &str) -> String {
        self.next += 1;
        format!("{p}{}", self.next - 1)
    }

    fn push_scope(&mut self) {
        self.scopes.push(Vec::new());
        self.ints.push(Vec::new());
        self.bools.push(Vec::new());
    }

    fn pop_scope(&mut self) {
        self.scopes.pop();
        self.ints.pop();
        self.bools.pop();
    }

    fn bool_vars(&self) -> Vec<String> {
        self.bools.iter().flatten().cloned().collect()
    }

    fn declare(&mut self, name: &str, ty: Ty, mutable: bool) {
        self.scopes.last_mut().unwrap().push(Var {
            name: name.to_string(),
            ty,
            mutable,
        });
    }

    fn declare_int(&mut self, name: &str, safe: bool, unrolled: bool) {
        self.ints.last_mut().unwrap().push(IntVar {
            name: name.to_string(),
            safe,
            unrolled,
            mutable: false,
        });
    }

    /// The visible variables (a shadowed one only in its newest binding).
    fn vars(&self) -> Vec<Var> {
        let mut seen = BTreeSet::new();
        let mut vs: Vec<Var> = Vec::new();
        for v in self.scopes.iter().rev().flat_map(|s| s.iter().rev()) {
            if seen.insert(v.name.clone()) {
                vs.push(v.clone());
            }
        }
        vs.reverse();
        vs
    }

    fn int_vars(&self) -> Vec<IntVar> {
        self.ints.iter().flatten().cloned().collect()
    }

    fn pick_var(&mut self, f: impl Fn(&Var) -> bool) -> Option<Var> {
        let vs: Vec<Var> = self.vars().into_iter().filter(|v| f(v)).collect();
        if vs.is_empty() {
            None
        } else {
            let i = self.rng.below(vs.len());
            Some(vs[i].clone())
        }
    }

    fn lit_in(&mut self, x: Iv) -> (String, f64) {
        let lo = x.lo.max(-CAP);
        let hi = x.hi.min(CAP).max(lo);
        let v = self.rng.range(lo, hi);
        lit(v)
    }

    // ---- integer expressions ----

    /// An index in `0..n` (kernels only).
    fn index(&mut self) -> String {
        let ints = self.int_vars();
        let mut opts: Vec<String> = vec!["t".into()];
        let c = self.rng.int(1, 5);
        opts.push(format!("(t + {c}) % n"));
        if self.rng.chance(0.015) {
            // an index computed from data: piecewise constant, so no derivative through it
            let j = self.rng.below(self.n_inputs);
            self.feat.hit("data-dependent index");
            return format!("((x{j}[t] * 4.0) as usize % n)");
        }
        if self.has_idx {
            opts.push("idx[t]".into());
            opts.push(format!("idx[(t + {c}) % n]"));
        }
        for iv in &ints {
            if iv.safe {
                opts.push(iv.name.clone());
            }
            opts.push(format!("({} + {c}) % n", iv.name));
            if iv.unrolled && !MUL_UNROLLED_INDEX {
                opts.push(format!("({} + t + {c}) % n", iv.name));
            } else {
                opts.push(format!("({} * 2 + t) % n", iv.name));
            }
        }
        let i = self.rng.below(opts.len());
        opts.swap_remove(i)
    }

    /// An integer value for conditions and `match`: `t` or a loop index.
    fn int_subject(&mut self) -> Option<String> {
        let mut opts: Vec<String> = self.int_vars().into_iter().map(|v| v.name).collect();
        if self.kernel {
            opts.push("t".into());
        }
        if opts.is_empty() {
            None
        } else {
            let i = self.rng.below(opts.len());
            Some(opts.swap_remove(i))
        }
    }

    // ---- scalar expressions ----

    fn squash(&mut self, e: S) -> S {
        if e.iv.mag() <= CAP {
            return e;
        }
        self.feat.hit("squash");
        let b = 5.0;
        S {
            s: self.sq_call(&e.s, "5.0"),
            iv: e.iv.inc(|x| b * (x / b).tanh()),
        }
    }

    /// `e` squashed into the interval `into` (a `let mut` envelope or a parameter's range).
    fn squash_into(&mut self, e: S, into: Iv) -> S {
        if e.iv.within(into) {
            return e;
        }
        let m = (into.lo + into.hi) / 2.0;
        let r = (into.hi - into.lo) / 2.0;
        let (ms, mv) = lit(m);
        let (rs, rv) = lit(r);
        // The rounded centre and radius must keep the image inside `into`.
        let (rs, rv) = if mv - rv < into.lo || mv + rv > into.hi {
            let r2 = round_down((mv - into.lo).min(into.hi - mv));
            lit(r2)
        } else {
            (rs, rv)
        };
        let s = if mv == 0.0 {
            self.sq_call(&e.s, &rs)
        } else if self.no_calls {
            format!("({ms} + {rs} * tanh(({} - {ms}) / {rs}))", e.s)
        } else {
            format!("sqi({}, {ms}, {rs})", e.s)
        };
        S {
            s,
            iv: e.iv.inc(|x| mv + rv * ((x - mv) / rv).tanh()),
        }
    }

    /// A scalar bounded away from zero: `[>= 0.3, <= CAP]`.
    fn pos(&mut self, d: u32) -> S {
        let e = self.scalar(d);
        if e.iv.lo >= 0.3 && e.iv.hi <= CAP {
            return e;
        }
        match self.rng.below(6) {
            0 if e.iv.mag() <= 2.5 => {
                let s = self.share(&e.s, |s| format!("1.0 + {s} * {s}"));
                S {
                    s: format!("({s})"),
                    iv: e.iv.sqr().add(Iv::pt(1.0)),
                }
            }
            0 | 1 => S {
                s: format!("exp(tanh({}))", e.s),
                iv: e.iv.inc(|x| x.tanh().exp()),
            },
            2 => S {
                s: format!("(2.0 + sin({}))", e.s),
                iv: iv(1.0, 3.0),
            },
            3 => S {
                s: format!("(1.5 + tanh({}))", e.s),
                iv: e.iv.inc(|x| 1.5 + x.tanh()),
            },
            4 if e.iv.mag() <= 2.5 => {
                let s = self.share(&e.s, |s| format!("{s} * {s} + 0.5"));
                S {
                    s: format!("sqrt({s})"),
                    iv: e.iv.sqr().add(Iv::pt(0.5)).inc(f64::sqrt),
                }
            }
            _ => S {
                s: format!("(1.2 + cos({}))", e.s),
                iv: iv(0.2, 2.2),
            },
        }
    }

    /// A scalar of magnitude at most `b`.
    fn bounded(&mut self, d: u32, b: f64) -> S {
        let e = self.scalar(d);
        if e.iv.mag() <= b {
            return e;
        }
        let (bs, bv) = lit(b);
        S {
            s: self.sq_call(&e.s, &bs),
            iv: e.iv.inc(|x| bv * (x / bv).tanh()),
        }
    }

    fn leaf(&mut self) -> S {
        loop {
            match self.rng.weighted(&[
                if self.kernel { 8 } else { 0 },
                8,
                2,
                2,
                1,
                1,
                if self.kernel { 1 } else { 0 },
            ]) {
                0 => {
                    let j = self.rng.below(self.n_inputs);
                    let i = self.index();
                    self.feat.hit("array read");
                    return S {
                        s: format!("x{j}[{i}]"),
                        iv: INPUT,
                    };
                }
                1 => {
                    if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::S(_))) {
                        let Ty::S(x) = v.ty else { unreachable!() };
                        return S { s: v.name, iv: x };
                    }
                }
                2 => {
                    let (s, v) = lit(self.rng.range(-2.0, 2.0));
                    return S { s, iv: Iv::pt(v) };
                }
                3 => {
                    if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::V(..))) {
                        let Ty::V(c, _) = v.ty else { unreachable!() };
                        self.feat.hit("component read");
                        let ints = self.int_vars();
                        return match self.rng.below(3) {
                            0 => {
                                let k = self.rng.below(3);
                                S {
                                    s: format!("{}.{}", v.name, ["x", "y", "z"][k]),
                                    iv: c[k],
                                }
                            }
                            1 if !ints.is_empty() => {
                                let k = &ints[self.rng.below(ints.len())];
                                S {
                                    s: format!("{}[{} % 3]", v.name, k.name),
                                    iv: c[0].hull(c[1]).hull(c[2]),
                                }
                            }
                            _ => {
                                let k = self.rng.below(3);
                                S {
                                    s: format!("{}[{k}]", v.name),
                                    iv: c[k],
                                }
                            }
                        };
                    }
                }
                4 => {
                    if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::M(_))) {
                        let Ty::M(c) = v.ty else { unreachable!() };
                        let (r, k) = (self.rng.below(3), self.rng.below(3));
                        self.feat.hit("matrix component read");
                        return S {
                            s: format!("{}[({r}, {k})]", v.name),
                            iv: c[r * 3 + k],
                        };
                    }
                }
                5 => {
                    if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::Q)) {
                        let k = self.rng.below(4);
                        self.feat.hit("quaternion component read");
                        return S {
                            s: format!("{}.{}", v.name, ["x", "y", "z", "w"][k]),
                            iv: UNIT,
                        };
                    }
                }
                _ => {
                    if let Some(i) = self.int_subject() {
                        self.feat.hit("int as float");
                        return S {
                            s: format!("({i} as R * 0.1)"),
                            iv: iv(0.0, 1.6),
                        };
                    }
                }
            }
        }
    }

    fn scalar(&mut self, d: u32) -> S {
        if d == 0 || self.rng.chance(sizes().leaf_p) {
            return self.leaf();
        }
        let e = self.scalar_op(d);
        self.squash(e)
    }

    fn unary(&mut self, f: &'static str, a: S, r: Iv) -> S {
        self.feat.hit(f);
        S {
            s: format!("{f}({})", a.s),
            iv: r,
        }
    }

    fn scalar_op(&mut self, d: u32) -> S {
        let w = [
            8,                                // 0 + -
            6,                                // 1 *
            3,                                // 2 /
            2,                                // 3 neg
            8,                                // 4 smooth unary
            4,                                // 5 sqrt/ln/log
            3,                                // 6 pow/powi
            2,                                // 7 atan2
            4,                                // 8 min/max/clamp
            2,                                // 9 abs/sign/floor/...
            3,                                // 10 select / if-expr
            2,                                // 11 match-expr
            5,                                // 12 vector-derived
            if !self.linalg { 0 } else { 8 }, // 13 matrix-derived
            if !self.linalg { 0 } else { 5 }, // 14 quaternion-derived
            if self.funcs.is_empty() || self.no_calls {
                0
            } else {
                3
            }, // 15 call
            2,                                // 16 no_grad
            2,                                // 17 lerp/smoothstep/step
            2,                                // 18 vec2 / vec4 / mat22
            1,                                // 19 block expression
        ];
        match self.rng.weighted(&w) {
            0 => {
                let a = self.scalar(d - 1);
                let b = self.scalar(d - 1);
                if self.rng.chance(0.5) {
                    S {
                        s: format!("{} + {}", a.s, b.s),
                        iv: a.iv.add(b.iv),
                    }
                    .paren()
                } else {
                    S {
                        s: format!("{} - {}", a.s, b.s),
                        iv: a.iv.sub(b.iv),
                    }
                    .paren()
                }
            }
            1 => {
                let a = self.scalar(d - 1);
                let b = self.scalar(d - 1);
                S {
                    s: format!("{} * {}", a.s, b.s),
                    iv: a.iv.mul(b.iv),
                }
                .paren()
            }
            2 => {
                let a = self.scalar(d - 1);
                let b = self.pos(d - 1);
                self.feat.hit("div");
                S {
                    s: format!("{} / {}", a.s, b.s),
                    iv: a.iv.div(b.iv),
                }
                .paren()
            }
            3 => {
                let a = self.scalar(d - 1);
                self.feat.hit("neg");
                S {
                    s: format!("(-{})", a.s),
                    iv: a.iv.neg(),
                }
            }
            4 => {
                let a = self.scalar(d - 1);
                match self.rng.below(9) {
                    0 => self.unary("sin", a, UNIT),
                    1 => self.unary("cos", a, UNIT),
                    2 => {
                        let r = a.iv.inc(f64::tanh);
                        self.unary("tanh", a, r)
                    }
                    3 => {
                        let r = a.iv.inc(f64::atan);
                        self.unary("atan", a, r)
                    }
                    4 => {
                        let a = if a.iv.hi <= 2.0 && a.iv.lo >= -CAP {
                            a
                        } else {
                            self.bounded_from(a, 2.0)
                        };
                        let r = a.iv.inc(f64::exp);
                        self.unary("exp", a, r)
                    }
                    5 => {
                        let a = self.bounded_from(a, 2.0);
                        if self.rng.chance(0.5) {
                            let r = a.iv.inc(f64::sinh);
                            self.unary("sinh", a, r)
                        } else {
                            let r = iv(a.iv.mig().cosh(), a.iv.mag().cosh());
                            self.unary("cosh", a, r)
                        }
                    }
                    6 => {
                        self.feat.hit("tan");
                        S {
                            s: format!("tan(tanh({}))", a.s),
                            iv: a.iv.inc(|x| x.tanh().tan()),
                        }
                    }
                    7 => {
                        self.feat.hit("asin");
                        S {
                            s: format!("asin(0.9 * tanh({}))", a.s),
                            iv: a.iv.inc(|x| (0.9 * x.tanh()).asin()),
                        }
                    }
                    _ => {
                        self.feat.hit("acos");
                        S {
                            s: format!("acos(0.9 * sin({}))", a.s),
                            iv: iv(0.0, std::f64::consts::PI),
                        }
                    }
                }
            }
            5 => {
                let a = self.pos(d - 1);
                match self.rng.below(5) {
                    0 | 1 => {
                        let r = a.iv.inc(f64::sqrt);
                        self.unary("sqrt", a, r)
                    }
                    2 | 3 => {
                        let r = a.iv.inc(f64::ln);
                        self.unary("ln", a, r)
                    }
                    _ => {
                        if self.rng.chance(0.5) {
                            let r = a.iv.inc(f64::log2);
                            self.unary("log2", a, r)
                        } else {
                            let r = a.iv.inc(f64::log10);
                            self.unary("log10", a, r)
                        }
                    }
                }
            }
            6 => {
                if self.rng.chance(0.6) {
                    let base = self.pos(d - 1);
                    let base = if base.iv.hi <= 4.0 {
                        base
                    } else {
                        self.bounded_from(base, 4.0)
                    };
                    let (es, eiv) = if self.rng.chance(0.5) {
                        let (s, v) = lit(self.rng.range(-1.5, 2.5));
                        (s, Iv::pt(v))
                    } else {
                        let e = self.scalar(d - 1);
                        (format!("sin({})", e.s), UNIT)
                    };
                    let lb = base.iv.inc(f64::ln);
                    let r = lb.mul(eiv).inc(f64::exp);
                    self.feat.hit("pow");
                    S {
                        s: format!("pow({}, {es})", base.s),
                        iv: r,
                    }
                } else {
                    let a = self.bounded(d - 1, 2.5);
                    let n = self.rng.int(2, 3) as i32;
                    self.feat.hit("powi");
                    let r = if n == 2 {
                        a.iv.sqr()
                    } else {
                        a.iv.inc(|x| x.powi(3))
                    };
                    S {
                        s: format!("powi({}, {n})", a.s),
                        iv: r,
                    }
                }
            }
            7 => {
                let a = self.scalar(d - 1);
                let b = self.pos(d - 1);
                self.feat.hit("atan2");
                let half = std::f64::consts::FRAC_PI_2;
                if self.rng.chance(0.5) {
                    S {
                        s: format!("atan2({}, {})", a.s, b.s),
                        iv: iv(-half, half),
                    }
                } else {
                    S {
                        s: format!("atan2({}, {})", b.s, a.s),
                        iv: iv(0.0, std::f64::consts::PI),
                    }
                }
            }
            8 => {
                let a = self.scalar(d - 1);
                match self.rng.below(3) {
                    0 => {
                        let b = self.scalar(d - 1);
                        self.feat.hit("min");
                        S {
                            s: format!("min({}, {})", a.s, b.s),
                            iv: iv(a.iv.lo.min(b.iv.lo), a.iv.hi.min(b.iv.hi)),
                        }
                    }
                    1 => {
                        let b = self.scalar(d - 1);
                        self.feat.hit("max");
                        S {
                            s: format!("max({}, {})", a.s, b.s),
                            iv: iv(a.iv.lo.max(b.iv.lo), a.iv.hi.max(b.iv.hi)),
                        }
                    }
                    _ => {
                        self.feat.hit("clamp");
                        if self.rng.chance(0.5) {
                            let (l, lv) = self.lit_in(a.iv);
                            let (h, hv) = lit(lv + self.rng.range(0.1, 1.5));
                            S {
                                s: format!("clamp({}, {l}, {h})", a.s),
                                iv: iv(lv, hv),
                            }
                        } else {
                            let lo = self.scalar(d - 1);
                            let w = self.pos(0);
                            let hi_iv = lo.iv.add(w.iv);
                            S {
                                s: format!("clamp({}, {lo}, {lo} + {w})", a.s, lo = lo.s, w = w.s),
                                iv: iv(
                                    lo.iv.lo.max(a.iv.lo.min(hi_iv.lo)),
                                    hi_iv.hi.min(a.iv.hi.max(lo.iv.hi)),
                                ),
                            }
                        }
                    }
                }
            }
            9 => {
                let a = self.scalar(d - 1);
                match self.rng.below(5) {
                    0 | 1 => {
                        self.feat.hit("abs");
                        S {
                            s: format!("abs({})", a.s),
                            iv: iv(a.iv.mig(), a.iv.mag()),
                        }
                    }
                    2 => {
                        let b = self.scalar(d - 1);
                        self.feat.hit("sign");
                        let m = b.iv.mag();
                        S {
                            s: format!("(sign({}) * {})", a.s, b.s),
                            iv: iv(-m, m),
                        }
                    }
                    3 => {
                        self.feat.hit("floor");
                        let s = self.share(&a.s, |s| format!("floor({s}) * 0.5 + {s}"));
                        S {
                            s: format!("({s})"),
                            iv: a.iv.inc(f64::floor).scale(0.5).add(a.iv),
                        }
                    }
                    _ => {
                        if self.rng.chance(0.5) {
                            self.feat.hit("round");
                            let s = self.share(&a.s, |s| format!("round({s}) * 0.25 + {s}"));
                            S {
                                s: format!("({s})"),
                                iv: a.iv.inc(f64::round).scale(0.25).add(a.iv),
                            }
                        } else {
                            self.feat.hit("ceil");
                            let s = self.share(&a.s, |s| format!("ceil({s}) * 0.25 - {s}"));
                            S {
                                s: format!("({s})"),
                                iv: a.iv.inc(f64::ceil).scale(0.25).sub(a.iv),
                            }
                        }
                    }
                }
            }
            10 => {
                let c = self.cond(d - 1);
                let a = self.scalar(d - 1);
                let b = self.scalar(d - 1);
                if self.rng.chance(0.5) {
                    self.feat.hit("select");
                    S {
                        s: format!("select({c}, {}, {})", a.s, b.s),
                        iv: a.iv.hull(b.iv),
                    }
                } else if self.rng.chance(0.6) {
                    self.feat.hit("if expression");
                    S {
                        s: format!("(if {c} {{ {} }} else {{ {} }})", a.s, b.s),
                        iv: a.iv.hull(b.iv),
                    }
                } else {
                    let c2 = self.cond(d - 1);
                    let e = self.scalar(d - 1);
                    self.feat.hit("if else-if expression");
                    S {
                        s: format!(
                            "(if {c} {{ {} }} else if {c2} {{ {} }} else {{ {} }})",
                            a.s, b.s, e.s
                        ),
                        iv: a.iv.hull(b.iv).hull(e.iv),
                    }
                }
            }
            11 => {
                let Some(subj) = self.int_subject() else {
                    return self.leaf();
                };
                let a = self.scalar(d - 1);
                let b = self.scalar(d - 1);
                let c = self.scalar(d - 1);
                self.feat.hit("match expression");
                let m = self.rng.int(3, 4);
                let arms = match self.rng.below(3) {
                    0 => format!("0 => {}, 1 => {}, _ => {}", a.s, b.s, c.s),
                    1 => format!("0 | 2 => {}, 1 => {}, _ => {}", a.s, b.s, c.s),
                    _ => format!("0..=1 => {}, 2 => {}, _ => {}", a.s, b.s, c.s),
                };
                S {
                    s: format!("(match {subj} % {m} {{ {arms} }})"),
                    iv: a.iv.hull(b.iv).hull(c.iv),
                }
            }
            12 => {
                let v = self.vec(d - 1);
                match self.rng.below(5) {
                    0 | 1 => {
                        let w = self.vec(d - 1);
                        self.feat.hit("dot");
                        let r = (0..3)
                            .map(|k| v.c[k].mul(w.c[k]))
                            .fold(Iv::pt(0.0), Iv::add);
                        S {
                            s: format!("dot({}, {})", v.s, w.s),
                            iv: r,
                        }
                    }
                    2 if v.nlo >= 0.2 => {
                        self.feat.hit("length");
                        S {
                            s: format!("length({})", v.s),
                            iv: iv(v.nlo, vnhi(&v.c)),
                        }
                    }
                    3 => {
                        self.feat.hit("length_sq");
                        S {
                            s: format!("length_sq({})", v.s),
                            iv: iv(v.nlo * v.nlo, vnhi(&v.c).powi(2)),
                        }
                    }
                    _ => {
                        let k = self.rng.below(3);
                        self.feat.hit("component of an expression");
                        S {
                            s: format!("{}.{}", v.paren_s(), ["x", "y", "z"][k]),
                            iv: v.c[k],
                        }
                    }
                }
            }
            13 => {
                let m = self.mat(d - 1);
                match self.rng.below(4) {
                    0 => {
                        self.feat.hit("determinant");
                        let dom = dominance(&m.c);
                        let rows: f64 = (0..3)
                            .map(|r| (0..3).map(|k| m.c[r * 3 + k].mag()).sum::<f64>())
                            .product();
                        let lo = if dom > 0.0 { dom.powi(3) } else { -rows };
                        S {
                            s: format!("determinant({})", m.s),
                            iv: iv(lo, rows),
                        }
                    }
                    1 => {
                        self.feat.hit("trace");
                        S {
                            s: format!("trace({})", m.s),
                            iv: m.c[0].add(m.c[4]).add(m.c[8]),
                        }
                    }
                    2 => {
                        let n = self.mat(d - 1);
                        self.feat.hit("ddot");
                        let r = (0..9)
                            .map(|k| m.c[k].mul(n.c[k]))
                            .fold(Iv::pt(0.0), Iv::add);
                        S {
                            s: format!("ddot({}, {})", m.s, n.s),
                            iv: r,
                        }
                    }
                    _ => {
                        let (r, k) = (self.rng.below(3), self.rng.below(3));
                        self.feat.hit("matrix component of an expression");
                        S {
                            s: format!("{}[({r}, {k})]", m.paren_s()),
                            iv: m.c[r * 3 + k],
                        }
                    }
                }
            }
            14 => {
                let q = self.quat(d - 1);
                if self.rng.chance(0.3) {
                    self.feat.hit("quat_length");
                    S {
                        s: format!("quat_length({})", q.s),
                        iv: iv(0.99, 1.01),
                    }
                } else {
                    let k = self.rng.below(4);
                    self.feat.hit("quaternion component of an expression");
                    S {
                        s: format!("{}.{}", q.paren_s(), ["x", "y", "z", "w"][k]),
                        iv: UNIT,
                    }
                }
            }
            15 => {
                let cands: Vec<usize> = (0..self.funcs.len())
                    .filter(|&i| matches!(self.funcs[i].ret, Ty::S(_)))
                    .collect();
                if cands.is_empty() {
                    return self.leaf();
                }
                let fi = cands[self.rng.below(cands.len())];
                let f = self.funcs[fi].clone();
                let args = self.call_args(&f, d - 1);
                self.called.insert(fi);
                self.feat.hit("diff_func call");
                let Ty::S(r) = f.ret else { unreachable!() };
                S {
                    s: format!("{}({args})", f.name),
                    iv: r,
                }
            }
            16 => {
                let a = self.no_grad_arg(d - 1);
                let b = self.scalar(d - 1);
                self.feat.hit("no_grad");
                // no_grad of a piecewise-constant value: its derivative is 0 also for central
                // differences (away from the jumps).
                match self.rng.below(3) {
                    0 => S {
                        s: format!("(no_grad(floor({})) * 0.1 + {})", a.s, b.s),
                        iv: a.iv.inc(f64::floor).scale(0.1).add(b.iv),
                    },
                    1 => {
                        let m = b.iv.mag();
                        S {
                            s: format!("(no_grad(step({})) * {})", a.s, b.s),
                            iv: iv(-m, m).hull(Iv::pt(0.0)),
                        }
                    }
                    _ => {
                        let s = self.share(&a.s, |s| format!("no_grad({s}.floor() - {s}.floor())"));
                        S {
                            s: format!("({s} + {})", b.s),
                            iv: b.iv,
                        }
                    }
                }
            }
            17 => {
                let a = self.scalar(d - 1);
                match self.rng.below(3) {
                    0 => {
                        let b = self.scalar(d - 1);
                        let t = self.scalar(d - 1);
                        self.feat.hit("lerp");
                        let r = a.iv.add(b.iv.sub(a.iv).mul(t.iv));
                        S {
                            s: format!("lerp({}, {}, {})", a.s, b.s, t.s),
                            iv: r,
                        }
                    }
                    1 => {
                        self.feat.hit("smoothstep");
                        let (e0, v0) = self.lit_in(a.iv);
                        let (e1, _) = lit(v0 + self.rng.range(0.2, 2.0));
                        S {
                            s: format!("smoothstep({e0}, {e1}, {})", a.s),
                            iv: iv(0.0, 1.0),
                        }
                    }
                    _ => {
                        let b = self.scalar(d - 1);
                        self.feat.hit("step");
                        let m = b.iv.mag();
                        S {
                            s: format!("(step({}) * {})", a.s, b.s),
                            iv: iv(-m, m),
                        }
                    }
                }
            }
            18 => {
                let a = self.bounded(d - 1, 3.0);
                let b = self.bounded(d - 1, 3.0);
                match self.rng.below(4) {
                    0 => {
                        let p = self.pos(0);
                        self.feat.hit("vec2");
                        let hi = (a.iv.mag().powi(2) + p.iv.hi.powi(2)).sqrt();
                        S {
                            s: format!("length(vec2({}, {}))", a.s, p.s),
                            iv: iv(p.iv.lo, hi),
                        }
                    }
                    1 => {
                        let c = self.bounded(0, 3.0);
                        let e = self.bounded(0, 3.0);
                        self.feat.hit("vec4");
                        let r =
                            a.iv.mul(c.iv)
                                .add(b.iv.mul(e.iv))
                                .add(a.iv.mul(e.iv))
                                .add(Iv::pt(0.5).mul(b.iv));
                        let (bs, es) = (b.s.clone(), e.s.clone());
                        let inner = self.share(&bs, |b| {
                            format!("dot(vec4(ZA, {b}, ZA, 0.5), vec4({}, ZE, ZE, {b}))", c.s)
                        });
                        let inner = self.share(&a.s, |a| inner.replace("ZA", a));
                        let s = self.share(&es, |e| inner.replace("ZE", e));
                        S { s, iv: r }
                    }
                    2 => {
                        self.feat.hit("mat22");
                        let c = self.bounded(0, 3.0);
                        let e = self.bounded(0, 3.0);
                        let r = a.iv.mul(e.iv).sub(b.iv.mul(c.iv));
                        match self.rng.below(3) {
                            0 => S {
                                s: format!(
                                    "determinant(mat22({}, {}, {}, {}))",
                                    a.s, b.s, c.s, e.s
                                ),
                                iv: r,
                            },
                            1 => {
                                // trace(I + [a c; b e]) = 2 + a + e
                                self.feat.hit("mat22_cols");
                                S {
                                    s: format!("trace(mat22_identity() + mat22_cols(vec2({}, {}), vec2({}, {})))", a.s, b.s, c.s, e.s),
                                    iv: a.iv.add(e.iv).add(Iv::pt(2.0)),
                                }
                            }
                            _ => {
                                self.feat.hit("mat22 * vec2");
                                let r2 = a.iv.mul(c.iv).add(b.iv.mul(e.iv));
                                S {
                                    s: format!(
                                        "(mat22({}, {}, 0.5, 0.25) * vec2({}, {})).x",
                                        a.s, b.s, c.s, e.s
                                    ),
                                    iv: r2,
                                }
                            }
                        }
                    }
                    _ => {
                        // a diagonally dominant 2x2: |diag| >= 4, |offdiag| <= 3.
                        self.feat.hit("mat22 inverse");
                        let r = self.rng.below(2);
                        let k = self.rng.below(2);
                        let inner = self.share(&b.s, |b| {
                            format!("inverse(mat22_rows(vec2(4.5 + tanh(ZA), {b}), vec2(ZA * 0.5, 5.0 + sin({b}))))[({r}, {k})]")
                        });
                        let s = self.share(&a.s, |a| inner.replace("ZA", a));
                        S {
                            s: format!("({s})"),
                            iv: iv(-2.0, 2.0),
                        }
                    }
                }
            }
            _ => {
                // A block expression with a local.
                let a = self.scalar(d - 1);
                let name = self.fresh("b");
                let b = self.scalar(d - 1);
                self.feat.hit("block expression");
                S {
                    s: format!("{{ let {name} = {}; {name} * {} }}", a.s, b.s),
                    iv: a.iv.mul(b.iv),
                }
                .paren()
            }
        }
    }

    /// The argument of a `no_grad(..)`: calls of `#[diff_func]`s inside `no_grad` do not
    /// compile (the macro emits them as plain calls of the function's unit struct; reported),
    /// so none are generated there unless `CALL_IN_NO_GRAD`.
    fn no_grad_arg(&mut self, d: u32) -> S {
        let saved = self.no_calls;
        self.no_calls = !CALL_IN_NO_GRAD;
        let a = self.scalar(d);
        self.no_calls = saved;
        a
    }

    /// `b * tanh(x / b)`: a call of the helper `sq`, or inline inside `no_grad`.
    fn sq_call(&self, x: &str, b: &str) -> String {
        if self.no_calls {
            format!("({b} * tanh({x} / {b}))")
        } else {
            format!("sq({x}, {b})")
        }
    }

    fn bounded_from(&mut self, a: S, b: f64) -> S {
        if a.iv.mag() <= b {
            return a;
        }
        let (bs, bv) = lit(b);
        S {
            s: self.sq_call(&a.s, &bs),
            iv: a.iv.inc(|x| bv * (x / bv).tanh()),
        }
    }

    fn call_args(&mut self, f: &FuncSig, d: u32) -> String {
        let mut args = Vec::new();
        for p in &f.params {
            match p {
                Ty::S(range) => {
                    let e = self.scalar(d);
                    let e = self.squash_into(e, *range);
                    args.push(e.s);
                }
                Ty::V(c, nlo) => {
                    if *nlo > 0.0 {
                        // a vector with components in [0.3, 3]
                        let mut cs = Vec::new();
                        for k in 0..3 {
                            let e = self.scalar(d.min(1));
                            let e = self.squash_into(e, iv(c[k].lo, c[k].hi));
                            cs.push(e.s);
                        }
                        args.push(format!("vec3({}, {}, {})", cs[0], cs[1], cs[2]));
                    } else {
                        let v = self.vec(d);
                        let v = if vmag(&v.c) <= c[0].hi {
                            v
                        } else {
                            self.vsquash(v)
                        };
                        args.push(v.s);
                    }
                }
                _ => unreachable!(),
            }
        }
        args.join(", ")
    }

    fn cond(&mut self, d: u32) -> String {
        let nb = if self.bool_vars().is_empty() { 0 } else { 2 };
        match self.rng.weighted(&[10, 3, 2, 1, 1, nb]) {
            5 => {
                let bs = self.bool_vars();
                let b = bs[self.rng.below(bs.len())].clone();
                self.feat.hit("bool variable read");
                if self.rng.chance(0.5) {
                    b
                } else {
                    format!("!{b}")
                }
            }
            0 => {
                // (a literal would make a constant condition: draw again)
                let mut a = self.scalar(d);
                for _ in 0..3 {
                    if a.iv.lo < a.iv.hi {
                        break;
                    }
                    a = self.scalar(d);
                }
                let (c, _) = self.lit_in(a.iv);
                let op = [">", "<", ">=", "<="][self.rng.below(4)];
                if self.rng.chance(0.3) {
                    let b = self.scalar(d);
                    format!("{} {op} {}", a.s, b.s)
                } else {
                    format!("{} {op} {c}", a.s)
                }
            }
            1 => {
                let Some(i) = self.int_subject() else {
                    return self.cond(d);
                };
                self.feat.hit("integer condition");
                match self.rng.below(3) {
                    0 => format!("{i} % 2 == {}", self.rng.below(2)),
                    1 => format!("{i} < {}", self.rng.int(1, 4)),
                    _ => format!("{i} == {}", self.rng.below(4)),
                }
            }
            2 => {
                let a = self.cond(d.saturating_sub(1));
                let b = self.cond(d.saturating_sub(1));
                self.feat.hit("&& ||");
                if self.rng.chance(0.5) {
                    format!("({a} && {b})")
                } else {
                    format!("({a} || {b})")
                }
            }
            3 => {
                let a = self.cond(d.saturating_sub(1));
                self.feat.hit("!");
                format!("!({a})")
            }
            _ => {
                let a = self.no_grad_arg(d);
                let (c, _) = self.lit_in(a.iv);
                self.feat.hit("no_grad condition");
                format!("no_grad({}) > {c}", a.s)
            }
        }
    }

    // ---- vectors ----

    fn vsquash(&mut self, v: V) -> V {
        self.feat.hit("vector squash");
        let nhi = vnhi(&v.c);
        let f = 1.0 / (1.0 + nhi * nhi * 0.01);
        let g = |r: f64| r / (1.0 + r * r * 0.01);
        let c = v.c.map(|x| {
            if x.lo >= 0.0 {
                iv(x.lo * f, x.hi.min(5.0))
            } else if x.hi <= 0.0 {
                iv(x.lo.max(-5.0), x.hi * f)
            } else {
                iv(x.lo.max(-5.0), x.hi.min(5.0))
            }
        });
        let nlo = g(v.nlo).min(g(nhi)).min(5.0);
        let s = if self.no_calls {
            let s = self.share(&v.s, |w| {
                format!("{w} * (1.0 / (1.0 + length_sq({w}) * 0.01))")
            });
            format!("({s})")
        } else {
            format!("vsq({})", v.s)
        };
        V {
            s,
            c,
            nlo: nlo.min(vnhi(&c)),
        }
    }

    fn vec(&mut self, d: u32) -> V {
        let v = if d == 0 || self.rng.chance(0.25) {
            self.vec_leaf(d)
        } else {
            self.vec_op(d)
        };
        if vmag(&v.c) > CAP {
            self.vsquash(v)
        } else {
            v
        }
    }

    fn vec_leaf(&mut self, d: u32) -> V {
        if self.rng.chance(0.6) {
            if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::V(..))) {
                let Ty::V(c, nlo) = v.ty else { unreachable!() };
                return V { s: v.name, c, nlo };
            }
        }
        let a = self.scalar(d.min(1));
        let b = self.scalar(d.min(1));
        let c = self.scalar(d.min(1));
        self.feat.hit("vec3");
        v_of(
            format!("vec3({}, {}, {})", a.s, b.s, c.s),
            [a.iv, b.iv, c.iv],
        )
    }

    /// A vector with length bounded away from 0.
    fn vec_safe(&mut self, d: u32) -> V {
        for _ in 0..4 {
            let v = self.vec(d);
            if v.nlo >= 0.3 {
                return v;
            }
        }
        let a = self.pos(d.min(1));
        let b = self.scalar(d.min(1));
        let c = self.pos(0);
        self.feat.hit("vec3");
        v_of(
            format!("vec3({}, {}, {})", a.s, b.s, c.s),
            [a.iv, b.iv, c.iv],
        )
    }

    fn vec_op(&mut self, d: u32) -> V {
        let nm = if self.linalg { 1 } else { 0 };
        match self
            .rng
            .weighted(&[6, 4, 2, 3, 3, 2, 3 * nm, 2 * nm, 2, 1, 2, 2, 1])
        {
            0 => {
                let a = self.vec(d - 1);
                let b = self.vec(d - 1);
                if self.rng.chance(0.5) {
                    v_of(
                        format!("({} + {})", a.s, b.s),
                        [0, 1, 2].map(|k| a.c[k].add(b.c[k])),
                    )
                } else {
                    v_of(
                        format!("({} - {})", a.s, b.s),
                        [0, 1, 2].map(|k| a.c[k].sub(b.c[k])),
                    )
                }
            }
            1 => {
                let a = self.vec(d - 1);
                let s = self.scalar(d - 1);
                let c = [0, 1, 2].map(|k| a.c[k].mul(s.iv));
                let nlo = a.nlo * s.iv.mig();
                let st = if self.rng.chance(0.5) {
                    format!("({} * {})", a.s, s.s)
                } else {
                    format!("({} * {})", s.s, a.s)
                };
                let mut v = v_of(st, c);
                v.nlo = v.nlo.max(nlo);
                v
            }
            2 => {
                let a = self.vec(d - 1);
                let p = self.pos(d - 1);
                self.feat.hit("vector / scalar");
                let c = [0, 1, 2].map(|k| a.c[k].div(p.iv));
                let mut v = v_of(format!("({} / {})", a.s, p.s), c);
                v.nlo = v.nlo.max(a.nlo / p.iv.hi);
                v
            }
            3 => {
                let a = self.vec(d - 1);
                let b = self.vec(d - 1);
                self.feat.hit("cross");
                let c = [
                    a.c[1].mul(b.c[2]).sub(a.c[2].mul(b.c[1])),
                    a.c[2].mul(b.c[0]).sub(a.c[0].mul(b.c[2])),
                    a.c[0].mul(b.c[1]).sub(a.c[1].mul(b.c[0])),
                ];
                v_of(format!("cross({}, {})", a.s, b.s), c)
            }
            4 => {
                let a = self.vec_safe(d - 1);
                self.feat.hit("normalize");
                let nhi = vnhi(&a.c);
                let c = a.c.map(|x| {
                    if x.lo > 0.0 {
                        iv(x.lo / nhi, 1.0)
                    } else if x.hi < 0.0 {
                        iv(-1.0, x.hi / nhi)
                    } else {
                        UNIT
                    }
                });
                V {
                    s: format!("normalize({})", a.s),
                    c,
                    nlo: 0.99,
                }
            }
            5 => {
                let a = self.vec(d - 1);
                self.feat.hit("vector neg");
                V {
                    s: format!("(-{})", a.s),
                    c: a.c.map(Iv::neg),
                    nlo: a.nlo,
                }
            }
            6 => {
                let m = self.mat(d - 1);
                let a = self.vec(d - 1);
                self.feat.hit("matrix * vector");
                let c = [0, 1, 2].map(|r| {
                    (0..3)
                        .map(|k| m.c[r * 3 + k].mul(a.c[k]))
                        .fold(Iv::pt(0.0), Iv::add)
                });
                v_of(format!("({} * {})", m.s, a.s), c)
            }
            7 => {
                let q = self.quat(d - 1);
                let a = self.vec(d - 1);
                let n = vnhi(&a.c);
                let f = if self.rng.chance(0.5) {
                    "quat_rotate"
                } else {
                    "quat_rotate_inv"
                };
                self.feat.hit(f);
                V {
                    s: format!("{f}({}, {})", q.s, a.s),
                    c: [iv(-n, n); 3],
                    nlo: a.nlo * 0.99,
                }
            }
            8 => {
                let a = self.vec(d - 1);
                let b = self.vec(d - 1);
                if self.rng.chance(0.5) {
                    self.feat.hit("cw_mul");
                    v_of(
                        format!("cw_mul({}, {})", a.s, b.s),
                        [0, 1, 2].map(|k| a.c[k].mul(b.c[k])),
                    )
                } else {
                    let x = self.pos(0);
                    let y = self.pos(0);
                    let z = self.pos(0);
                    self.feat.hit("cw_div");
                    v_of(
                        format!("cw_div({}, vec3({}, {}, {}))", a.s, x.s, y.s, z.s),
                        [a.c[0].div(x.iv), a.c[1].div(y.iv), a.c[2].div(z.iv)],
                    )
                }
            }
            9 => {
                let a = self.vec(d - 1);
                let b = self.vec(d - 1);
                let t = self.scalar(d - 1);
                self.feat.hit("lerp vector");
                let t01 = format!("(0.5 + 0.5 * sin({}))", t.s);
                let c = [0, 1, 2].map(|k| a.c[k].hull(b.c[k]));
                v_of(format!("lerp({}, {}, {t01})", a.s, b.s), c)
            }
            10 => {
                let c = self.cond(d - 1);
                let a = self.vec(d - 1);
                let b = self.vec(d - 1);
                let cc = [0, 1, 2].map(|k| a.c[k].hull(b.c[k]));
                let nlo = a.nlo.min(b.nlo);
                let s = if self.rng.chance(0.5) {
                    self.feat.hit("select vector");
                    format!("select({c}, {}, {})", a.s, b.s)
                } else {
                    self.feat.hit("if expression vector");
                    format!("(if {c} {{ {} }} else {{ {} }})", a.s, b.s)
                };
                let mut v = v_of(s, cc);
                v.nlo = v.nlo.max(nlo);
                v
            }
            11 => {
                // A vector built from scalars, one of them derived from another vector.
                let a = self.vec(d - 1);
                let s = self.scalar(d - 1);
                let k = self.rng.below(3);
                let comps = [a.c[(k + 1) % 3], s.iv, a.c[k]];
                self.feat.hit("vec3 of components");
                let name = ["x", "y", "z"];
                let s = format!(
                    "{{ let {tmp} = {a}; vec3({tmp}.{k1}, {s}, {tmp}.{k0}) }}",
                    tmp = self.fresh("w"),
                    a = a.s,
                    k1 = name[(k + 1) % 3],
                    k0 = name[k],
                    s = s.s
                );
                v_of(s, comps)
            }
            _ => {
                let a = self.vec(d - 1);
                self.feat.hit("skew * vector");
                let b = self.vec(0);
                let c = [
                    a.c[1].mul(b.c[2]).sub(a.c[2].mul(b.c[1])),
                    a.c[2].mul(b.c[0]).sub(a.c[0].mul(b.c[2])),
                    a.c[0].mul(b.c[1]).sub(a.c[1].mul(b.c[0])),
                ];
                v_of(format!("(skew({}) * {})", a.s, b.s), c)
            }
        }
    }

    // ---- matrices ----

    fn msquash(&mut self, m: M) -> M {
        self.feat.hit("matrix squash");
        // each entry keeps its sign and shrinks, to at most 5 in magnitude
        let c =
            m.c.map(|x| iv(x.lo.max(-5.0).min(0.0), x.hi.min(5.0).max(0.0)));
        let s = if self.no_calls {
            let s = self.share(&m.s, |w| {
                format!("{w} * (1.0 / (1.0 + ddot({w}, {w}) * 0.01))")
            });
            format!("({s})")
        } else {
            format!("msq({})", m.s)
        };
        M { s, c }
    }

    fn mat(&mut self, d: u32) -> M {
        let m = if d == 0 || self.rng.chance(0.25) {
            self.mat_leaf(d)
        } else {
            self.mat_op(d)
        };
        if mmag(&m.c) > CAP {
            self.msquash(m)
        } else {
            m
        }
    }

    fn mat_leaf(&mut self, d: u32) -> M {
        if self.rng.chance(0.6) {
            if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::M(_))) {
                let Ty::M(c) = v.ty else { unreachable!() };
                return M { s: v.name, c };
            }
        }
        match self.rng.below(5) {
            0 => {
                let a = self.vec(d.min(1));
                self.feat.hit("diag");
                let z = Iv::pt(0.0);
                M {
                    s: format!("diag({})", a.s),
                    c: [a.c[0], z, z, z, a.c[1], z, z, z, a.c[2]],
                }
            }
            1 => {
                let a = self.vec(d.min(1));
                let b = self.vec(d.min(1));
                self.feat.hit("outer");
                let mut c = [Iv::pt(0.0); 9];
                for r in 0..3 {
                    for k in 0..3 {
                        c[r * 3 + k] = a.c[r].mul(b.c[k]);
                    }
                }
                M {
                    s: format!("outer({}, {})", a.s, b.s),
                    c,
                }
            }
            2 => {
                let a = self.vec(d.min(1));
                let b = self.vec(d.min(1));
                let e = self.vec(d.min(1));
                let rows = self.rng.chance(0.5);
                self.feat
                    .hit(if rows { "mat33_rows" } else { "mat33_cols" });
                let vs = [&a, &b, &e];
                let mut c = [Iv::pt(0.0); 9];
                for r in 0..3 {
                    for k in 0..3 {
                        c[r * 3 + k] = if rows { vs[r].c[k] } else { vs[k].c[r] };
                    }
                }
                M {
                    s: format!(
                        "{}({}, {}, {})",
                        if rows { "mat33_rows" } else { "mat33_cols" },
                        a.s,
                        b.s,
                        e.s
                    ),
                    c,
                }
            }
            3 => {
                let q = self.quat(d.min(1));
                self.feat.hit("quat_to_mat33");
                M {
                    s: format!("quat_to_mat33({})", q.s),
                    c: [UNIT; 9],
                }
            }
            _ => {
                let mut es = Vec::new();
                let mut c = [Iv::pt(0.0); 9];
                for k in 0..9 {
                    let e = if self.rng.chance(0.5) {
                        self.leaf()
                    } else {
                        let (s, v) = lit(self.rng.range(-1.0, 1.0));
                        S { s, iv: Iv::pt(v) }
                    };
                    c[k] = e.iv;
                    es.push(e.s);
                }
                self.feat.hit("mat33");
                M {
                    s: format!("mat33({})", es.join(", ")),
                    c,
                }
            }
        }
    }

    /// A diagonally dominant matrix (margin >= 0.5): `I * (2.5 + tanh(s)) + m * small`.
    fn mat_dd(&mut self, d: u32) -> M {
        if let Some(v) = self.pick_var(|v| matches!(&v.ty, Ty::M(c) if dominance(c) >= 0.5)) {
            if self.rng.chance(0.5) {
                let Ty::M(c) = v.ty else { unreachable!() };
                return M { s: v.name, c };
            }
        }
        let m = self.mat(d);
        let s = self.scalar(d);
        let mag = mmag(&m.c).max(0.3);
        let (fs, fv) = lit(round_down(0.3 / mag).max(0.01));
        let k = s.iv.inc(|x| 2.5 + x.tanh());
        let mut c = m.c.map(|x| x.scale(fv));
        for r in 0..3 {
            c[r * 3 + r] = c[r * 3 + r].add(k);
        }
        self.feat.hit("diagonally dominant matrix");
        M {
            s: format!(
                "(mat33_identity() * (2.5 + tanh({})) + {} * {fs})",
                s.s,
                m.paren_s()
            ),
            c,
        }
    }

    fn mat_op(&mut self, d: u32) -> M {
        match self.rng.weighted(&[3, 3, 3, 2, 3, 2, 2, 2]) {
            0 => {
                let a = self.mat(d - 1);
                let b = self.mat(d - 1);
                if self.rng.chance(0.5) {
                    M {
                        s: format!("({} + {})", a.s, b.s),
                        c: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| a.c[k].add(b.c[k])),
                    }
                } else {
                    M {
                        s: format!("({} - {})", a.s, b.s),
                        c: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| a.c[k].sub(b.c[k])),
                    }
                }
            }
            1 => {
                let a = self.mat(d - 1);
                let s = self.scalar(d - 1);
                self.feat.hit("matrix * scalar");
                M {
                    s: format!("({} * {})", a.s, s.s),
                    c: a.c.map(|x| x.mul(s.iv)),
                }
            }
            2 => {
                let a = self.mat(d - 1);
                let b = self.mat(d - 1);
                self.feat.hit("matrix * matrix");
                let mut c = [Iv::pt(0.0); 9];
                for r in 0..3 {
                    for k in 0..3 {
                        c[r * 3 + k] = (0..3)
                            .map(|j| a.c[r * 3 + j].mul(b.c[j * 3 + k]))
                            .fold(Iv::pt(0.0), Iv::add);
                    }
                }
                M {
                    s: format!("({} * {})", a.s, b.s),
                    c,
                }
            }
            3 => {
                let a = self.mat(d - 1);
                self.feat.hit("transpose");
                let c = [0, 3, 6, 1, 4, 7, 2, 5, 8].map(|k| a.c[k]);
                M {
                    s: format!("transpose({})", a.s),
                    c,
                }
            }
            4 => {
                let a = self.mat_dd(d - 1);
                let dom = dominance(&a.c);
                assert!(dom >= 0.4, "{dom}");
                self.feat.hit("inverse");
                let b = 1.0 / dom;
                M {
                    s: format!("inverse({})", a.s),
                    c: [iv(-b, b); 9],
                }
            }
            5 => {
                let a = self.vec(d - 1);
                self.feat.hit("skew");
                let z = Iv::pt(0.0);
                M {
                    s: format!("skew({})", a.s),
                    c: [
                        z,
                        a.c[2].neg(),
                        a.c[1],
                        a.c[2],
                        z,
                        a.c[0].neg(),
                        a.c[1].neg(),
                        a.c[0],
                        z,
                    ],
                }
            }
            6 => {
                let a = self.mat_dd(d - 1);
                a
            }
            _ => {
                let c = self.cond(d - 1);
                let a = self.mat(d - 1);
                let b = self.mat(d - 1);
                self.feat.hit("select matrix");
                M {
                    s: format!("select({c}, {}, {})", a.s, b.s),
                    c: [0, 1, 2, 3, 4, 5, 6, 7, 8].map(|k| a.c[k].hull(b.c[k])),
                }
            }
        }
    }

    // ---- quaternions (always unit) ----

    fn quat(&mut self, d: u32) -> Q {
        if d == 0 || self.rng.chance(0.3) {
            if let Some(v) = self.pick_var(|v| matches!(v.ty, Ty::Q)) {
                return Q { s: v.name };
            }
        }
        let d = d.max(1);
        match self.rng.weighted(&[3, 3, 2, 1, 1, 1]) {
            0 => {
                let a = self.scalar(d - 1);
                let b = self.scalar(d - 1);
                let c = self.scalar(d - 1);
                let w = self.pos(d - 1);
                self.feat.hit("quat_normalize");
                Q {
                    s: format!("quat_normalize(quat({}, {}, {}, {}))", a.s, b.s, c.s, w.s),
                }
            }
            1 => {
                let axis = self.vec_safe(d - 1);
                let angle = self.scalar(d - 1);
                self.feat.hit("quat_from_axis_angle");
                Q {
                    s: format!("quat_from_axis_angle(normalize({}), {})", axis.s, angle.s),
                }
            }
            2 => {
                let p = self.quat(d - 1);
                let q = self.quat(d - 1);
                if self.rng.chance(0.5) {
                    self.feat.hit("quat_mul");
                    Q {
                        s: format!("quat_mul({}, {})", p.s, q.s),
                    }
                } else {
                    self.feat.hit("quaternion * quaternion");
                    Q {
                        s: format!("({} * {})", p.s, q.s),
                    }
                }
            }
            3 => {
                let p = self.quat(d - 1);
                self.feat.hit("quat_inverse");
                Q {
                    s: format!("quat_inverse({})", p.s),
                }
            }
            4 => {
                let p = self.quat(d - 1);
                self.feat.hit("quat_conjugate");
                Q {
                    s: format!("quat_conjugate({})", p.s),
                }
            }
            _ => {
                if self.rng.chance(0.5) {
                    self.feat.hit("quat_identity");
                    let p = self.quat(d - 1);
                    Q {
                        s: format!("quat_mul(quat_identity(), {})", p.s),
                    }
                } else {
                    let p = self.quat(d - 1);
                    self.feat.hit("quat_normalize");
                    Q {
                        s: format!("quat_normalize({})", p.s),
                    }
                }
            }
        }
    }

    // ---- statements ----

    /// The envelope of a new `let mut` scalar initialised with a value in `x`.
    fn envelope(&mut self, x: Iv) -> Iv {
        if x.lo >= 0.3 && self.rng.chance(0.5) {
            iv(
                round_down(x.lo * 0.5).max(0.1),
                round_up(x.hi.max(3.0) * 1.5).min(CAP),
            )
        } else {
            let b = round_up(x.mag().max(3.0)).min(CAP);
            iv(-b, b)
        }
    }

    /// `let mut s = <leaf>;`: a value that branches and loops add into.
    fn accumulator(&mut self, indent: usize, out: &mut String) {
        // an input (kernels) or a parameter (functions), so the accumulator depends on them
        let e = loop {
            let e = self.leaf();
            if e.s.starts_with('x') || !self.kernel && e.iv.lo != e.iv.hi {
                break e;
            }
        };
        let env = self.envelope(e.iv);
        let name = self.fresh("s");
        writeln!(out, "{}let mut {name} = {};", ind(indent), e.s).unwrap();
        self.feat.hit("let mut");
        self.declare(&name, Ty::S(env), true);
    }

    fn stmts(&mut self, n: usize, depth: u32, indent: usize, out: &mut String) {
        for j in 0..n {
            // at least one statement per block, so no branch or loop is empty
            if self.budget <= 0 && j > 0 {
                break;
            }
            self.stmt(depth, indent, out);
        }
    }

    fn block(&mut self, n: usize, depth: u32, indent: usize) -> String {
        let mut s = String::new();
        self.push_scope();
        self.stmts(n, depth, indent, &mut s);
        self.fold_locals(indent, &mut s);
        self.pop_scope();
        s
    }

    /// A `let mut` scalar declared outside the innermost scope.
    fn outer_mutable_scalar(&mut self) -> Option<(String, Iv)> {
        let n = self.scopes.len();
        let vs: Vec<Var> = self.scopes[..n - 1]
            .iter()
            .flatten()
            .filter(|v| v.mutable && matches!(v.ty, Ty::S(_)))
            .cloned()
            .collect();
        if vs.is_empty() {
            return None;
        }
        let v = vs[self.rng.below(vs.len())].clone();
        let Ty::S(e) = v.ty else { unreachable!() };
        Some((v.name, e))
    }

    /// At the end of a block: adds what the block's locals hold into an outer `let mut`
    /// scalar, so the block's values reach the output (and loops carry them).
    fn fold_locals(&mut self, indent: usize, out: &mut String) {
        let locals: Vec<Var> = self.scopes.last().unwrap().clone();
        let Some((name, env)) = self.outer_mutable_scalar() else {
            return;
        };
        if locals.is_empty() {
            if !self.loops.is_empty() && self.rng.chance(0.5) {
                self.assign_scalar(&name, env, indent, out);
            }
            return;
        }
        let sum = self.sum_of(&locals, false);
        let (c, cv) = lit(self.rng.range(0.2, 0.8));
        let e = S {
            s: format!("{name} * {c} + tanh({})", sum.s),
            iv: env.scale(cv).add(sum.iv.inc(f64::tanh)),
        };
        let e = self.squash_into(e, env);
        self.feat.hit("fold block locals");
        writeln!(out, "{}{name} = {};", ind(indent), e.s).unwrap();
    }

    /// `f(x)` for a template that uses `x` more than once: binds `x` to a local first unless
    /// it is a plain name (so generated code does not grow exponentially).
    fn share(&mut self, x: &str, f: impl FnOnce(&str) -> String) -> String {
        if x.chars().all(|c| c.is_alphanumeric() || c == '_') {
            return f(x);
        }
        let w = self.fresh("w");
        let body = f(&w);
        format!("{{ let {w} = {x}; {body} }}")
    }

    fn mutable_scalar(&mut self) -> Option<(String, Iv)> {
        let v = self.pick_var(|v| v.mutable && matches!(v.ty, Ty::S(_)))?;
        let Ty::S(e) = v.ty else { unreachable!() };
        Some((v.name, e))
    }

    fn assign_scalar(&mut self, name: &str, env: Iv, indent: usize, out: &mut String) {
        let i = ind(indent);
        let d = self.rng.int(1, sizes().stmt_depth) as u32;
        match self.rng.below(6) {
            0 | 1 => {
                let e = self.scalar(d);
                let e = self.squash_into(e, env);
                writeln!(out, "{i}{name} = {};", e.s).unwrap();
            }
            2 => {
                // a compound assignment, then squashed back into the envelope
                let e = self.scalar(d);
                let (op, r) = match self.rng.below(4) {
                    0 => ("+=", env.add(e.iv)),
                    1 => ("-=", env.sub(e.iv)),
                    2 => ("*=", env.mul(e.iv)),
                    _ => {
                        let p = self.pos(d - 1);
                        writeln!(out, "{i}{name} /= {};", p.s).unwrap();
                        self.feat.hit("compound assignment");
                        let r = env.div(p.iv);
                        let sq = self.squash_into(
                            S {
                                s: name.to_string(),
                                iv: r,
                            },
                            env,
                        );
                        if sq.s != name {
                            writeln!(out, "{i}{name} = {};", sq.s).unwrap();
                        }
                        return;
                    }
                };
                self.feat.hit("compound assignment");
                writeln!(out, "{i}{name} {op} {};", e.s).unwrap();
                let sq = self.squash_into(
                    S {
                        s: name.to_string(),
                        iv: r,
                    },
                    env,
                );
                if sq.s != name {
                    writeln!(out, "{i}{name} = {};", sq.s).unwrap();
                }
            }
            3 => {
                // a recurrence: the new value depends on the old
                let e = self.scalar(d - 1);
                let (c, cv) = lit(self.rng.range(0.3, 0.9));
                let r = env.scale(cv).add(e.iv.inc(f64::tanh));
                let sq = self.squash_into(
                    S {
                        s: format!("{name} * {c} + tanh({})", e.s),
                        iv: r,
                    },
                    env,
                );
                writeln!(out, "{i}{name} = {};", sq.s).unwrap();
            }
            4 => {
                let e = self.scalar(d - 1);
                let r = env.mul(UNIT).add(UNIT);
                let sq = self.squash_into(
                    S {
                        s: format!("{name} * sin({}) + cos({name})", e.s),
                        iv: r,
                    },
                    env,
                );
                writeln!(out, "{i}{name} = {};", sq.s).unwrap();
            }
            _ => {
                let e = self.scalar(d);
                let r = env.add(e.iv).scale(0.5);
                let sq = self.squash_into(
                    S {
                        s: format!("({name} + {}) * 0.5", e.s),
                        iv: r,
                    },
                    env,
                );
                writeln!(out, "{i}{name} = {};", sq.s).unwrap();
            }
        }
    }

    fn stmt(&mut self, depth: u32, indent: usize, out: &mut String) {
        self.budget -= 1;
        let i = ind(indent);
        let in_loop = !self.loops.is_empty();
        let dyn_ok = self
            .loops
            .iter()
            .filter(|l| **l == LoopKind::Dynamic)
            .count()
            < 2;
        let w = [
            6,                                // 0 let scalar
            5,                                // 1 let mut scalar
            8,                                // 2 assign mutable scalar
            3,                                // 3 let vec
            3,                                // 4 mutable vec / component assignment
            if !self.linalg { 0 } else { 5 }, // 5 matrices
            if !self.linalg { 0 } else { 4 }, // 6 quaternions
            if depth > 0 { 5 } else { 0 },    // 7 if
            if depth > 0 { 2 } else { 0 },    // 8 match
            if depth > 0 { 3 } else { 0 },    // 9 const for
            if depth > 0 && dyn_ok && !exp("nodyn") {
                4
            } else {
                0
            }, // 10 dynamic loop
            if in_loop { 7 } else { 0 },      // 11 break / continue
            1,                                // 12 early return
            if self.kernel && self.atomic { 3 } else { 0 }, // 13 atomic
            if self.funcs.is_empty() { 0 } else { 2 }, // 14 call into a local
            if self.kernel { 2 } else { 0 },  // 15 carried integer index
            2,                                // 16 carried bool
            if self.kernel && !self.atomic && REPEATED_STORE {
                2
            } else {
                0
            }, // 17 store again
        ];
        match self.rng.weighted(&w) {
            0 => {
                let d = self.rng.int(1, sizes().stmt_depth) as u32;
                let e = self.scalar(d);
                // sometimes shadow an existing immutable scalar (`let a = .. a ..;`)
                let shadow = if self.rng.chance(0.15) {
                    self.pick_var(|v| !v.mutable && matches!(v.ty, Ty::S(_)))
                } else {
                    None
                };
                if let Some(old) = shadow {
                    let Ty::S(x) = old.ty else { unreachable!() };
                    let (c, cv) = lit(self.rng.range(0.3, 0.9));
                    let e = self.squash(S {
                        s: format!("{} * {c} + {}", old.name, e.s),
                        iv: x.scale(cv).add(e.iv),
                    });
                    writeln!(out, "{i}let {} = {};", old.name, e.s).unwrap();
                    self.feat.hit("shadowing let");
                    self.declare(&old.name, Ty::S(e.iv), false);
                    return;
                }
                let name = self.fresh("a");
                if self.rng.chance(0.15) {
                    writeln!(out, "{i}let {name}: R = {};", e.s).unwrap();
                } else {
                    writeln!(out, "{i}let {name} = {};", e.s).unwrap();
                }
                self.declare(&name, Ty::S(e.iv), false);
            }
            1 => {
                let d = self.rng.int(1, sizes().stmt_depth) as u32;
                let e = self.scalar(d);
                let env = self.envelope(e.iv);
                let name = self.fresh("s");
                writeln!(out, "{i}let mut {name} = {};", e.s).unwrap();
                self.feat.hit("let mut");
                self.declare(&name, Ty::S(env), true);
            }
            2 => {
                let Some((name, env)) = self.mutable_scalar() else {
                    self.budget += 1;
                    return self.stmt(depth, indent, out);
                };
                self.feat.hit("reassignment");
                self.assign_scalar(&name, env, indent, out);
            }
            3 => {
                let d = self.rng.int(1, sizes().stmt_depth) as u32;
                let v = self.vec(d);
                let name = self.fresh("v");
                writeln!(out, "{i}let {name} = {};", v.s).unwrap();
                self.declare(&name, Ty::V(v.c, v.nlo), false);
            }
            4 => {
                if let Some(var) = self.pick_var(|v| v.mutable && matches!(v.ty, Ty::V(..))) {
                    let Ty::V(c, _) = var.ty else { unreachable!() };
                    let name = var.name;
                    match self.rng.below(4) {
                        0 | 1 => {
                            let k = self.rng.below(3);
                            let r_ = self.rng.int(1, sizes().stmt_depth) as u32;
                            let e = self.scalar(r_);
                            let e = self.squash_into(e, c[k]);
                            self.feat.hit("component assignment");
                            if self.rng.chance(0.3) {
                                let comp = ["x", "y", "z"][k];
                                let e = self.scalar(1);
                                writeln!(out, "{i}{name}.{comp} += {};", e.s).unwrap();
                                let sq = self.squash_into(
                                    S {
                                        s: format!("{name}.{comp}"),
                                        iv: c[k].add(e.iv),
                                    },
                                    c[k],
                                );
                                writeln!(out, "{i}{name}.{comp} = {};", sq.s).unwrap();
                                self.feat.hit("component compound assignment");
                            } else if self.rng.chance(0.5) {
                                writeln!(out, "{i}{name}.{} = {};", ["x", "y", "z"][k], e.s)
                                    .unwrap();
                            } else {
                                writeln!(out, "{i}{name}[{k}] = {};", e.s).unwrap();
                            }
                        }
                        2 => {
                            let w = self.vec(1);
                            let r = [0, 1, 2].map(|k| c[k].add(w.c[k]));
                            writeln!(out, "{i}{name} += {};", w.s).unwrap();
                            self.feat.hit("vector compound assignment");
                            self.vec_back_into(&name, &c, r, indent, out);
                        }
                        _ => {
                            let w = self.vec(2);
                            self.feat.hit("vector reassignment");
                            let tmp = self.fresh("w");
                            writeln!(out, "{i}let {tmp} = {};", w.s).unwrap();
                            self.vec_back_into_named(&name, &tmp, &c, w.c, indent, out);
                        }
                    }
                } else {
                    let v = if self.rng.chance(0.5) {
                        self.vec_safe(1)
                    } else {
                        self.vec(1)
                    };
                    let name = self.fresh("u");
                    // envelope: the initial range widened, symmetric or positive
                    let c = v.c.map(|x| {
                        if x.lo >= 0.3 {
                            iv(
                                round_down(x.lo * 0.5),
                                round_up(x.hi.max(2.0) * 1.5).min(CAP),
                            )
                        } else {
                            let b = round_up(x.mag().max(2.0)).min(CAP);
                            iv(-b, b)
                        }
                    });
                    writeln!(out, "{i}let mut {name} = {};", v.s).unwrap();
                    self.feat.hit("let mut vector");
                    self.declare(&name, Ty::V(c, vnlo(&c)), true);
                }
            }
            5 => {
                if let Some(var) = self.pick_var(|v| v.mutable && matches!(v.ty, Ty::M(_))) {
                    let name = var.name;
                    let (r, k) = (self.rng.below(3), self.rng.below(3));
                    if MAT_COMPONENT_STORE && self.rng.chance(0.5) {
                        let e = self.scalar(1);
                        let e = self.squash_into(e, iv(-1.0, 1.0));
                        self.feat.hit("matrix component assignment");
                        writeln!(out, "{i}{name}[({r}, {k})] = {};", e.s).unwrap();
                    } else {
                        let m = self.mat(1);
                        self.feat.hit("matrix reassignment");
                        let prod = if self.rng.chance(0.5) {
                            format!("{name} * {}", m.paren_s())
                        } else {
                            format!("transpose({name}) + {}", m.paren_s())
                        };
                        writeln!(out, "{i}{name} = msq({prod});").unwrap();
                    }
                } else if self.rng.chance(0.5) {
                    let r_ = self.rng.int(1, sizes().stmt_depth) as u32;
                    let m = self.mat(r_);
                    let name = self.fresh("m");
                    writeln!(out, "{i}let {name} = {};", m.s).unwrap();
                    self.declare(&name, Ty::M(m.c), false);
                } else {
                    let m = self.mat(1);
                    let m = if mmag(&m.c) <= 1.0 {
                        m
                    } else {
                        self.msquash(m)
                    };
                    let name = self.fresh("m");
                    writeln!(out, "{i}let mut {name} = {};", m.s).unwrap();
                    self.feat.hit("let mut matrix");
                    // envelope: entries within [-5, 5] (the matrix squash keeps them there)
                    self.declare(&name, Ty::M([iv(-5.0, 5.0); 9]), true);
                }
            }
            6 => {
                if let Some(var) = self.pick_var(|v| v.mutable && matches!(v.ty, Ty::Q)) {
                    let q = self.quat(1);
                    self.feat.hit("quaternion reassignment");
                    writeln!(
                        out,
                        "{i}{} = quat_normalize(quat_mul({}, {}));",
                        var.name, var.name, q.s
                    )
                    .unwrap();
                } else {
                    let r_ = self.rng.int(1, sizes().stmt_depth) as u32;
                    let q = self.quat(r_);
                    let mutable = self.rng.chance(0.5);
                    let name = self.fresh("q");
                    writeln!(
                        out,
                        "{i}let {}{name} = {};",
                        if mutable { "mut " } else { "" },
                        q.s
                    )
                    .unwrap();
                    self.declare(&name, Ty::Q, mutable);
                }
            }
            7 => {
                let c = self.cond(1);
                self.feat.hit("if statement");
                let n = self.rng.int(1, 2);
                let then = self.block(n, depth - 1, indent + 1);
                write!(out, "{i}if {c} {{\n{then}{i}}}").unwrap();
                match self.rng.below(3) {
                    0 => writeln!(out).unwrap(),
                    1 => {
                        let n = self.rng.int(1, 2);
                        let els = self.block(n, depth - 1, indent + 1);
                        write!(out, " else {{\n{els}{i}}}\n").unwrap();
                    }
                    _ => {
                        let c2 = self.cond(1);
                        self.feat.hit("else if");
                        let b1 = self.block(1, depth - 1, indent + 1);
                        let b2 = self.block(1, depth - 1, indent + 1);
                        write!(out, " else if {c2} {{\n{b1}{i}}} else {{\n{b2}{i}}}\n").unwrap();
                    }
                }
            }
            8 => {
                let Some(subj) = self.int_subject() else {
                    self.budget += 1;
                    return self.stmt(depth, indent, out);
                };
                self.feat.hit("match statement");
                let m = self.rng.int(3, 4);
                let guard = format!("1 | 2 if {}", self.cond(1));
                let pats: Vec<&str> = match self.rng.below(4) {
                    0 => vec!["0", "1"],
                    1 => vec!["0 | 2", "1"],
                    2 => vec!["0", &guard],
                    _ => vec!["0..=1", "2"],
                };
                if pats[1] == guard {
                    self.feat.hit("match guard");
                }
                writeln!(out, "{i}match {subj} % {m} {{").unwrap();
                for p in pats.iter().chain(std::iter::once(&"_")) {
                    let r_ = self.rng.int(0, 2);
                    let b = self.block(r_, depth - 1, indent + 2);
                    write!(out, "{i}    {p} => {{\n{b}{i}    }}\n").unwrap();
                }
                writeln!(out, "{i}}}").unwrap();
            }
            9 => {
                let k = self.fresh("k");
                let (lo, hi, incl) = (self.rng.below(2), self.rng.int(2, 4), self.rng.chance(0.25));
                let range = if incl {
                    format!("{lo}..={}", hi - 1)
                } else {
                    format!("{lo}..{hi}")
                };
                self.feat.hit("for loop (constant bounds)");
                self.loops.push(LoopKind::Const);
                self.push_scope();
                self.declare_int(&k, true, true);
                let body = self.loop_body(depth, indent + 1);
                self.pop_scope();
                self.loops.pop();
                write!(out, "{i}for {k} in {range} {{\n{body}{i}}}\n").unwrap();
            }
            10 => self.dyn_loop(depth, indent, out),
            11 => {
                let c = self.cond(1);
                let kw = if self.rng.chance(0.5) {
                    "break"
                } else {
                    "continue"
                };
                self.feat
                    .hit(if kw == "break" { "break" } else { "continue" });
                writeln!(out, "{i}if {c} {{\n{i}    {kw};\n{i}}}").unwrap();
            }
            12 => {
                let c = self.cond(1);
                self.feat.hit("early return");
                if self.kernel {
                    let w = self.output_write(indent + 1);
                    writeln!(out, "{i}if {c} {{\n{w}{i}    return;\n{i}}}").unwrap();
                } else {
                    let e = self.ret_value(1);
                    writeln!(out, "{i}if {c} {{\n{i}    return {e};\n{i}}}").unwrap();
                }
            }
            13 => {
                let r_ = self.rng.int(1, sizes().stmt_depth) as u32;
                let e = self.scalar(r_);
                let idx = self.index();
                self.feat.hit("atomic");
                match self.rng.below(4) {
                    0 => writeln!(out, "{i}f.atomic_add({idx}, {});", e.s).unwrap(),
                    1 => writeln!(out, "{i}f.atomic_sub({idx}, {});", e.s).unwrap(),
                    2 => writeln!(out, "{i}f[{idx}] += {};", e.s).unwrap(),
                    _ => writeln!(out, "{i}f[{idx}] -= {};", e.s).unwrap(),
                }
            }
            15 => {
                let js: Vec<IntVar> = self.int_vars().into_iter().filter(|v| v.mutable).collect();
                if js.is_empty() {
                    let j = self.fresh("j");
                    let c = self.rng.below(LEN);
                    writeln!(out, "{i}let mut {j} = (t + {c}) % n;").unwrap();
                    self.ints.last_mut().unwrap().push(IntVar {
                        name: j,
                        safe: true,
                        unrolled: false,
                        mutable: true,
                    });
                    self.feat.hit("let mut index");
                } else {
                    let j = &js[self.rng.below(js.len())].name;
                    let c = self.rng.int(1, LEN - 1);
                    writeln!(out, "{i}{j} = ({j} + {c}) % n;").unwrap();
                    self.feat.hit("index reassignment");
                }
            }
            16 => {
                let bs = self.bool_vars();
                let c = self.cond(1);
                if bs.is_empty() {
                    let b = self.fresh("f");
                    writeln!(out, "{i}let mut {b} = {c};").unwrap();
                    self.bools.last_mut().unwrap().push(b);
                    self.feat.hit("let mut bool");
                } else {
                    let b = bs[self.rng.below(bs.len())].clone();
                    if self.rng.chance(0.5) {
                        writeln!(out, "{i}{b} = {c};").unwrap();
                    } else {
                        writeln!(out, "{i}if {c} {{\n{i}    {b} = !{b};\n{i}}}").unwrap();
                    }
                    self.feat.hit("bool reassignment");
                }
            }
            17 => {
                // a store that a later one overwrites (the adjoint must not count it)
                let w = self.output_write(indent);
                out.push_str(&w);
                self.feat.hit("repeated store");
            }
            _ => {
                let fi = self.rng.below(self.funcs.len());
                let f = self.funcs[fi].clone();
                let args = self.call_args(&f, 1);
                self.called.insert(fi);
                self.feat.hit("diff_func call");
                let name = self.fresh("c");
                writeln!(out, "{i}let {name} = {}({args});", f.name).unwrap();
                self.declare(&name, f.ret.clone(), false);
            }
        }
    }

    /// Writes `name = w` for a vector `w` (held in `tmp`) squashed into `name`'s envelope.
    fn vec_back_into_named(
        &mut self,
        name: &str,
        tmp: &str,
        env: &[Iv; 3],
        w: [Iv; 3],
        indent: usize,
        out: &mut String,
    ) {
        let i = ind(indent);
        if (0..3).all(|k| w[k].within(env[k])) {
            writeln!(out, "{i}{name} = {tmp};").unwrap();
            return;
        }
        let cs: Vec<String> = (0..3)
            .map(|k| {
                self.squash_into(
                    S {
                        s: format!("{tmp}.{}", ["x", "y", "z"][k]),
                        iv: w[k],
                    },
                    env[k],
                )
                .s
            })
            .collect();
        writeln!(out, "{i}{name} = vec3({}, {}, {});", cs[0], cs[1], cs[2]).unwrap();
    }

    fn vec_back_into(
        &mut self,
        name: &str,
        env: &[Iv; 3],
        now: [Iv; 3],
        indent: usize,
        out: &mut String,
    ) {
        if (0..3).all(|k| now[k].within(env[k])) {
            return;
        }
        let i = ind(indent);
        let tmp = self.fresh("w");
        writeln!(out, "{i}let {tmp} = {name};").unwrap();
        self.vec_back_into_named(name, &tmp, env, now, indent, out);
    }

    fn loop_body(&mut self, depth: u32, indent: usize) -> String {
        let mut s = String::new();
        let n = self.rng.int(1, 2);
        self.stmts(n, depth - 1, indent, &mut s);
        // make sure the loop carries something: fold its locals into an outer accumulator
        self.fold_locals(indent, &mut s);
        s
    }

    fn dyn_loop(&mut self, depth: u32, indent: usize, out: &mut String) {
        let i = ind(indent);
        let kernel = self.kernel;
        let choice =
            self.rng
                .weighted(&[if kernel { 4 } else { 0 }, 3, 2, if kernel { 1 } else { 0 }]);
        self.loops.push(LoopKind::Dynamic);
        self.push_scope();
        match choice {
            0 => {
                let k = self.fresh("k");
                let lo = self.rng.below(3);
                self.feat.hit("for loop (dynamic bounds)");
                self.declare_int(&k, true, false);
                let body = self.loop_body(depth, indent + 1);
                write!(out, "{i}for {k} in {lo}..n {{\n{body}{i}}}\n").unwrap();
            }
            1 => {
                // while with a counter (incremented first, so `continue` cannot skip it)
                let c = self.fresh("i");
                let bound = if kernel {
                    "n".to_string()
                } else {
                    format!("{}", self.rng.int(2, 4))
                };
                self.feat.hit("while loop");
                // the condition first: it can only use what is declared before the loop
                let extra = if self.rng.chance(0.3) {
                    let cnd = self.cond(0);
                    self.feat.hit("while with a data-dependent condition");
                    format!(" && {cnd}")
                } else {
                    String::new()
                };
                self.declare_int(&c, false, false);
                let body = self.loop_body(depth, indent + 1);
                let zero = if kernel { "0" } else { "0usize" };
                write!(out, "{i}let mut {c} = {zero};\n{i}while {c} < {bound}{extra} {{\n{i}    {c} += 1;\n{body}{i}}}\n").unwrap();
            }
            2 => {
                let c = self.fresh("i");
                let bound = if kernel {
                    "n".to_string()
                } else {
                    format!("{}", self.rng.int(2, 4))
                };
                self.feat.hit("loop with break");
                self.declare_int(&c, false, false);
                let body = self.loop_body(depth, indent + 1);
                let zero = if kernel { "0" } else { "0usize" };
                // the exit test comes first: a `continue` in the body must not skip it
                write!(out, "{i}let mut {c} = {zero};\n{i}loop {{\n{i}    {c} += 1;\n{i}    if {c} > {bound} {{\n{i}        break;\n{i}    }}\n{body}{i}}}\n").unwrap();
            }
            _ => {
                // a data-dependent trip count: runs until a sum passes a threshold
                let k = self.fresh("k");
                let acc = self.fresh("s");
                let j = self.rng.below(self.n_inputs);
                let (th, _) = lit(self.rng.range(1.0, 4.0));
                self.feat.hit("data-dependent break");
                self.declare_int(&k, true, false);
                let body = self.loop_body(depth, indent + 1);
                write!(
                    out,
                    "{i}let mut {acc} = 0.0;\n{i}for {k} in 0..n {{\n{i}    {acc} = {acc} + x{j}[{k}];\n{body}{i}    if {acc} > {th} {{\n{i}        break;\n{i}    }}\n{i}}}\n"
                )
                .unwrap();
            }
        }
        self.pop_scope();
        self.loops.pop();
    }

    /// Sum of the live values (so most of what the program computes reaches the output).
    fn live_sum(&mut self) -> S {
        let vars = self.vars();
        self.sum_of(&vars, true)
    }

    /// A weighted sum of (a scalar of) each of `vars`.
    fn sum_of(&mut self, vars: &[Var], extra: bool) -> S {
        let mut terms: Vec<S> = Vec::new();
        for v in vars.iter().cloned() {
            let (c, cv) =
                lit(self.rng.range(0.2, 1.0) * if self.rng.chance(0.3) { -1.0 } else { 1.0 });
            let t = match v.ty {
                Ty::S(x) => S {
                    s: format!("{} * {c}", v.name),
                    iv: x.scale(cv),
                },
                Ty::V(x, _) => {
                    if self.rng.chance(0.5) {
                        let k = self.rng.below(3);
                        S {
                            s: format!("{}.{} * {c}", v.name, ["x", "y", "z"][k]),
                            iv: x[k].scale(cv),
                        }
                    } else {
                        let r = (0..3).map(|k| x[k].sqr()).fold(Iv::pt(0.0), Iv::add);
                        S {
                            s: format!("dot({n}, {n}) * {c}", n = v.name),
                            iv: r.scale(cv),
                        }
                    }
                }
                Ty::M(x) => S {
                    s: format!("trace({}) * {c}", v.name),
                    iv: x[0].add(x[4]).add(x[8]).scale(cv),
                },
                Ty::Q => {
                    let k = self.rng.below(4);
                    S {
                        s: format!("{}.{} * {c}", v.name, ["x", "y", "z", "w"][k]),
                        iv: UNIT.scale(cv),
                    }
                }
            };
            let t = if t.iv.mag() > 10.0 { self.squash(t) } else { t };
            terms.push(t);
        }
        if terms.is_empty() || extra && self.rng.chance(0.3) {
            terms.push(self.scalar(2));
        }
        let iv = terms.iter().fold(Iv::pt(0.0), |a, t| a.add(t.iv));
        S {
            s: terms
                .iter()
                .map(|t| t.s.clone())
                .collect::<Vec<_>>()
                .join(" + "),
            iv,
        }
    }

    /// The kernel's write of its output (before an early return, and at the end).
    fn output_write(&mut self, indent: usize) -> String {
        let i = ind(indent);
        let mut e = self.live_sum();
        // and an input, so the output always depends on the inputs
        let j = self.rng.below(self.n_inputs);
        let (c, cv) = lit(self.rng.range(0.2, 1.0));
        e = S {
            s: format!("{} + x{j}[t] * {c}", e.s),
            iv: e.iv.add(INPUT.scale(cv)),
        };
        if self.atomic {
            let idx = self.index();
            if self.rng.chance(0.5) {
                format!("{i}f.atomic_add({idx}, {});\n", e.s)
            } else {
                format!("{i}f.atomic_sub({idx}, {});\n", e.s)
            }
        } else if indent == 1 && self.rng.chance(0.12) {
            // the final store on both branches of an `if`
            let c = self.cond(1);
            let e2 = self.live_sum();
            self.feat.hit("store in both branches");
            format!(
                "{i}if {c} {{\n{i}    y[{y}] = {};\n{i}}} else {{\n{i}    y[{y}] = {};\n{i}}}\n",
                e.s,
                e2.s,
                y = self.store_index
            )
        } else {
            format!("{i}y[{}] = {};\n", self.store_index, e.s)
        }
    }

    fn ret_value(&mut self, d: u32) -> String {
        match self.ret.clone().unwrap() {
            Ty::S(_) => {
                let e = self.live_sum();
                let e = self.bounded_from(e, 6.0);
                self.merge_ret(RetIv::S(e.iv));
                e.s
            }
            Ty::V(..) => {
                let v = self.vec(d);
                let v = if vmag(&v.c) <= 6.0 {
                    v
                } else {
                    self.vsquash(v)
                };
                self.merge_ret(RetIv::V(v.c, v.nlo));
                v.s
            }
            _ => unreachable!(),
        }
    }

    fn merge_ret(&mut self, r: RetIv) {
        self.ret_iv = Some(match (self.ret_iv.take(), r) {
            (None, r) => r,
            (Some(RetIv::S(a)), RetIv::S(b)) => RetIv::S(a.hull(b)),
            (Some(RetIv::V(a, n)), RetIv::V(b, m)) => {
                RetIv::V([0, 1, 2].map(|k| a[k].hull(b[k])), n.min(m))
            }
            _ => unreachable!(),
        });
    }
}

impl S {
    fn paren(self) -> S {
        S {
            s: format!("({})", self.s),
            iv: self.iv,
        }
    }
}

impl V {
    fn paren_s(&self) -> String {
        if self.s.chars().all(|c| c.is_alphanumeric() || c == '_') {
            self.s.clone()
        } else {
            format!("({})", self.s)
        }
    }
}

impl M {
    fn paren_s(&self) -> String {
        if self.s.chars().all(|c| c.is_alphanumeric() || c == '_') {
            self.s.clone()
        } else {
            format!("({})", self.s)
        }
    }
}

impl Q {
    fn paren_s(&self) -> String {
        if self.s.chars().all(|c| c.is_alphanumeric() || c == '_') {
            self.s.clone()
        } else {
            format!("({})", self.s)
        }
    }
}

/// The builtins every kernel `i` uses one of (`FOCUS[i % FOCUS.len()]`), so each appears in
/// the corpus a few times whatever the random choices.
pub const FOCUS: &[&str] = &[
    "sqrt",
    "sin",
    "cos",
    "tan",
    "asin",
    "acos",
    "atan",
    "atan2",
    "sinh",
    "cosh",
    "tanh",
    "exp",
    "ln",
    "log2",
    "log10",
    "pow",
    "powi",
    "abs",
    "sign",
    "floor",
    "ceil",
    "round",
    "min",
    "max",
    "clamp",
    "lerp",
    "select",
    "step",
    "smoothstep",
    "rem",
    "dot",
    "cross",
    "length",
    "length_sq",
    "normalize",
    "outer",
    "cw_mul",
    "cw_div",
    "transpose",
    "determinant",
    "inverse",
    "trace",
    "ddot",
    "skew",
    "diag",
    "vec2",
    "vec4",
    "mat22",
    "mat33",
    "mat22_cols",
    "mat33_cols",
    "mat22_rows",
    "mat33_rows",
    "mat22_identity",
    "mat33_identity",
    "quat",
    "quat_identity",
    "quat_mul",
    "quat_conjugate",
    "quat_inverse",
    "quat_normalize",
    "quat_rotate",
    "quat_rotate_inv",
    "quat_from_axis_angle",
    "quat_to_mat33",
    "quat_length",
    "replace",
];

impl<'a> Gen<'a> {
    /// A scalar expression that uses builtin `f` (with arguments in its safe domain).
    fn focus_expr(&mut self, f: &str) -> S {
        self.feat.hit("focus builtin");
        let any = |g: &mut Self| g.scalar(1);
        let unit_q = |g: &mut Self| g.quat(1).s;
        match f {
            "sqrt" | "ln" | "log2" | "log10" => {
                let a = self.pos(1);
                let r = match f {
                    "sqrt" => a.iv.inc(f64::sqrt),
                    "ln" => a.iv.inc(f64::ln),
                    "log2" => a.iv.inc(f64::log2),
                    _ => a.iv.inc(f64::log10),
                };
                S {
                    s: format!("{f}({})", a.s),
                    iv: r,
                }
            }
            "sin" | "cos" => S {
                s: format!("{f}({})", any(self).s),
                iv: UNIT,
            },
            "tanh" | "atan" => S {
                s: format!("{f}({})", any(self).s),
                iv: iv(-1.6, 1.6),
            },
            "tan" => S {
                s: format!("tan(tanh({}))", any(self).s),
                iv: iv(-1.6, 1.6),
            },
            "asin" => S {
                s: format!("asin(0.9 * tanh({}))", any(self).s),
                iv: iv(-1.2, 1.2),
            },
            "acos" => S {
                s: format!("acos(0.9 * sin({}))", any(self).s),
                iv: iv(0.0, 3.2),
            },
            "sinh" | "cosh" | "exp" => {
                let a = self.bounded(1, 2.0);
                S {
                    s: format!("{f}({})", a.s),
                    iv: iv(-7.4, 7.4),
                }
            }
            "atan2" => {
                let (a, b) = (any(self), self.pos(1));
                S {
                    s: format!("atan2({}, {})", a.s, b.s),
                    iv: iv(-1.6, 1.6),
                }
            }
            "pow" => {
                let a = self.bounded(1, 1.0);
                let (e, _) = lit(self.rng.range(-1.5, 2.5));
                S {
                    s: format!("pow(1.5 + {}, {e})", a.s),
                    iv: iv(0.0, 11.2),
                }
                .paren_sq(self)
            }
            "powi" => {
                let a = self.bounded(1, 2.0);
                S {
                    s: format!("powi({}, 3)", a.s),
                    iv: iv(-8.0, 8.0),
                }
            }
            "abs" | "floor" | "ceil" | "round" | "step" => {
                let a = self.bounded(1, 3.0);
                S {
                    s: format!("({f}({s}) * 0.5 + {s})", s = a.s),
                    iv: iv(-4.5, 4.5),
                }
            }
            "sign" => {
                let (a, b) = (self.bounded(1, 3.0), self.bounded(1, 3.0));
                S {
                    s: format!("(sign({}) * {})", a.s, b.s),
                    iv: iv(-3.0, 3.0),
                }
            }
            "min" | "max" => {
                let (a, b) = (self.bounded(1, 3.0), self.bounded(1, 3.0));
                S {
                    s: format!("{f}({}, {})", a.s, b.s),
                    iv: iv(-3.0, 3.0),
                }
            }
            "clamp" => {
                let a = self.bounded(1, 3.0);
                S {
                    s: format!("clamp({}, -0.5, 1.25)", a.s),
                    iv: iv(-0.5, 1.25),
                }
            }
            "lerp" => {
                let (a, b, t) = (
                    self.bounded(1, 3.0),
                    self.bounded(1, 3.0),
                    self.bounded(1, 1.0),
                );
                S {
                    s: format!("lerp({}, {}, {})", a.s, b.s, t.s),
                    iv: iv(-9.0, 9.0),
                }
                .paren_sq(self)
            }
            "select" => {
                let c = self.cond(1);
                let (a, b) = (self.bounded(1, 3.0), self.bounded(1, 3.0));
                S {
                    s: format!("select({c}, {}, {})", a.s, b.s),
                    iv: iv(-3.0, 3.0),
                }
            }
            "smoothstep" => {
                let a = self.bounded(1, 3.0);
                S {
                    s: format!("smoothstep(0.25, 1.75, {})", a.s),
                    iv: iv(0.0, 1.0),
                }
            }
            "rem" => {
                let a = self.bounded(1, 3.0);
                S {
                    s: format!("((t % 4) as R * {})", a.s),
                    iv: iv(-9.0, 9.0),
                }
                .paren_sq(self)
            }
            "dot" | "length_sq" => {
                let (a, b) = (self.vec(1), self.vec(1));
                let s = if f == "dot" {
                    format!("dot({}, {})", a.s, b.s)
                } else {
                    format!("length_sq({})", a.s)
                };
                S {
                    s,
                    iv: iv(-200.0, 200.0),
                }
                .paren_sq(self)
            }
            "cross" => {
                let (a, b) = (self.vec(1), self.vec(1));
                S {
                    s: format!("cross({}, {}).y", a.s, b.s),
                    iv: iv(-200.0, 200.0),
                }
                .paren_sq(self)
            }
            "length" => {
                let a = self.vec_safe(1);
                S {
                    s: format!("length({})", a.s),
                    iv: iv(0.0, 14.0),
                }
                .paren_sq(self)
            }
            "normalize" => {
                let a = self.vec_safe(1);
                S {
                    s: format!("normalize({}).z", a.s),
                    iv: UNIT,
                }
            }
            "outer" | "cw_mul" => {
                let (a, b) = (self.vec(1), self.vec(1));
                let s = if f == "outer" {
                    format!("outer({}, {})[(1, 2)]", a.s, b.s)
                } else {
                    format!("cw_mul({}, {}).x", a.s, b.s)
                };
                S {
                    s,
                    iv: iv(-64.0, 64.0),
                }
                .paren_sq(self)
            }
            "cw_div" => {
                let a = self.vec(1);
                let (x, y) = (self.pos(0), self.pos(0));
                S {
                    s: format!("cw_div({}, vec3({}, {}, 2.0)).y", a.s, x.s, y.s),
                    iv: iv(-40.0, 40.0),
                }
                .paren_sq(self)
            }
            "transpose" | "trace" | "ddot" | "skew" | "diag" | "mat33" | "mat33_cols"
            | "mat33_rows" | "mat33_identity" => {
                let (a, b) = (self.vec(1), self.vec(1));
                let x = any(self);
                let s = match f {
                    "transpose" => format!("transpose(outer({}, {}))[(0, 2)]", a.s, b.s),
                    "trace" => format!("trace(outer({}, {}))", a.s, b.s),
                    "ddot" => format!("ddot(outer({}, {}), diag({}))", a.s, b.s, a.s),
                    "skew" => format!("(skew({}) * {}).z", a.s, b.s),
                    "diag" => format!("(diag({}) * {}).x", a.s, b.s),
                    "mat33" => format!(
                        "trace(mat33({x}, 1.0, 0.5, -0.25, {x}, 2.0, 0.75, 0.5, {x}))",
                        x = x.s
                    ),
                    "mat33_cols" => format!("mat33_cols({}, {}, {})[(2, 0)]", a.s, b.s, a.s),
                    "mat33_rows" => format!("mat33_rows({}, {}, {})[(2, 0)]", a.s, b.s, a.s),
                    _ => format!(
                        "(mat33_identity() * {} + outer({}, {}))[(1, 1)]",
                        x.s, a.s, b.s
                    ),
                };
                S {
                    s,
                    iv: iv(-500.0, 500.0),
                }
                .paren_sq(self)
            }
            "determinant" | "inverse" => {
                let m = self.mat_dd(1);
                let dom = dominance(&m.c);
                let s = if f == "determinant" {
                    format!("ln(determinant({}))", m.s)
                } else {
                    format!("inverse({})[(0, 1)]", m.s)
                };
                // ln(det) for a dominant matrix: det in [dom^3, 5^3 * 27]
                S {
                    s,
                    iv: iv(-(1.0 / dom).max(3.0 * dom.ln().abs()), 8.0),
                }
                .paren_sq(self)
            }
            "vec2" | "mat22" | "mat22_cols" | "mat22_rows" | "mat22_identity" => {
                let (a, b) = (self.bounded(1, 2.0), self.bounded(1, 2.0));
                let s = match f {
                    "vec2" => format!("dot(vec2({}, {}), vec2(0.5, -1.5))", a.s, b.s),
                    "mat22" => format!("determinant(mat22({}, {}, -0.5, 1.5))", a.s, b.s),
                    "mat22_cols" => {
                        format!("mat22_cols(vec2({}, {}), vec2(1.0, 2.0))[(1, 0)]", a.s, b.s)
                    }
                    "mat22_rows" => format!(
                        "(mat22_rows(vec2({}, 0.5), vec2({}, 2.0)) * vec2(1.0, -1.0)).y",
                        a.s, b.s
                    ),
                    _ => format!(
                        "trace(mat22_identity() * {} + mat22({}, 1.0, 0.5, {}))",
                        a.s, b.s, a.s
                    ),
                };
                S {
                    s,
                    iv: iv(-20.0, 20.0),
                }
                .paren_sq(self)
            }
            "vec4" => {
                let (a, b) = (self.bounded(1, 2.0), self.bounded(1, 2.0));
                S {
                    s: format!("length_sq(vec4({}, {}, 0.5, {}))", a.s, b.s, a.s),
                    iv: iv(0.0, 8.5),
                }
            }
            "quat" | "quat_normalize" | "quat_length" => {
                let (a, b) = (self.bounded(1, 2.0), self.pos(1));
                let q = format!("quat({}, 0.25, {}, 1.0)", a.s, b.s);
                let s = match f {
                    "quat_length" => format!("quat_length({q})"),
                    "quat" => format!("quat_normalize({q}).w"),
                    _ => format!("quat_normalize({q}).x"),
                };
                S {
                    s,
                    iv: iv(-10.0, 10.0),
                }
                .paren_sq(self)
            }
            "quat_identity" | "quat_mul" | "quat_conjugate" | "quat_inverse" | "quat_to_mat33" => {
                let (p, q) = (unit_q(self), unit_q(self));
                let s = match f {
                    "quat_identity" => format!("quat_mul(quat_identity(), {p}).y"),
                    "quat_mul" => format!("quat_mul({p}, {q}).z"),
                    "quat_conjugate" => format!("quat_conjugate({p}).x"),
                    "quat_inverse" => format!("quat_inverse({p}).y"),
                    _ => format!("quat_to_mat33({p})[(0, 1)]"),
                };
                S { s, iv: UNIT }
            }
            "quat_rotate" | "quat_rotate_inv" | "quat_from_axis_angle" => {
                let v = self.vec(1);
                let n = vnhi(&v.c);
                let s = match f {
                    "quat_from_axis_angle" => {
                        let axis = self.vec_safe(0);
                        let angle = any(self);
                        format!(
                            "quat_rotate(quat_from_axis_angle(normalize({}), {}), {}).x",
                            axis.s, angle.s, v.s
                        )
                    }
                    _ => format!("{f}({}, {}).z", unit_q(self), v.s),
                };
                S { s, iv: iv(-n, n) }.paren_sq(self)
            }
            _ => {
                // "replace": a component assignment through a block
                let v = self.vec(1);
                let x = any(self);
                let w = self.fresh("w");
                S {
                    s: format!(
                        "{{ let mut {w} = {}; {w}.y = {}; dot({w}, {w}) }}",
                        v.s, x.s
                    ),
                    iv: iv(0.0, 300.0),
                }
                .paren_sq(self)
            }
        }
    }
}

impl S {
    /// Parenthesised, and squashed if it may exceed the cap.
    fn paren_sq(self, g: &mut Gen) -> S {
        let e = self.paren();
        g.squash(e)
    }
}

// ---- whole functions and kernels ---------------------------------------------------------

/// A generated `#[diff_func]`: its signature and source.
pub struct Func {
    pub sig: FuncSig,
    pub src: String,
    /// Indices of the functions it calls.
    pub calls: BTreeSet<usize>,
}

fn ty_str(t: &Ty) -> &'static str {
    match t {
        Ty::S(_) => "R",
        Ty::V(..) => "Vec3<R>",
        Ty::M(_) => "Mat33<R>",
        Ty::Q => "Quat<R>",
    }
}

pub fn gen_func(idx: usize, seed: u64, earlier: &[FuncSig], feat: &mut Features) -> Func {
    let mut g = Gen::new(Rng::new(seed), feat, earlier);
    g.kernel = false;
    g.linalg = idx % sizes().linalg_every == 0;
    let name = format!("g{idx:02}");
    // parameters: 1-3, scalar ([-3, 3] or [0.5, 2]) or vector ([-6, 6] or [0.3, 3])
    let np = g.rng.int(1, 3);
    let mut params = Vec::new();
    let mut decl = Vec::new();
    for p in 0..np {
        let pname = ["a", "b", "c"][p];
        let ty = if g.rng.chance(0.7) {
            if g.rng.chance(0.5) {
                Ty::S(iv(-3.0, 3.0))
            } else {
                Ty::S(iv(0.5, 2.0))
            }
        } else if g.rng.chance(0.5) {
            Ty::V([iv(-6.0, 6.0); 3], 0.0)
        } else {
            let c = [iv(0.3, 3.0); 3];
            Ty::V(c, vnlo(&c))
        };
        // some scalar parameters are `mut` and get reassigned (squashed into their range)
        let mutable = matches!(ty, Ty::S(_)) && g.rng.chance(0.3);
        if mutable {
            g.feat.hit("mut parameter");
        }
        decl.push(format!(
            "{}{pname}: {}",
            if mutable { "mut " } else { "" },
            ty_str(&ty)
        ));
        g.declare(pname, ty.clone(), mutable);
        params.push(ty);
    }
    let ret = if g.rng.chance(0.75) {
        Ty::S(iv(0.0, 0.0))
    } else {
        Ty::V([Iv::pt(0.0); 3], 0.0)
    };
    g.ret = Some(ret.clone());
    g.budget = g.rng.int(sizes().func_stmts.0, sizes().func_stmts.1) as i32;
    let mut body = String::new();
    g.accumulator(1, &mut body);
    let n = g.budget as usize;
    g.stmts(n, 2, 1, &mut body);
    let tail = g.ret_value(2);
    let ret_ty = match g.ret_iv.clone().unwrap() {
        RetIv::S(x) => Ty::S(x),
        RetIv::V(c, nlo) => Ty::V(c, nlo),
    };
    let src = format!(
        "#[diff_func]\nfn {name}<R: Real>({}) -> {} {{\n{body}    {tail}\n}}\n",
        decl.join(", "),
        ty_str(&ret)
    );
    let calls = g.called.clone();
    Func {
        sig: FuncSig {
            name,
            params,
            ret: ret_ty,
        },
        src,
        calls,
    }
}

/// A generated kernel.
pub struct Kernel {
    pub name: String,
    pub src: String,
    pub n_inputs: usize,
    pub has_idx: bool,
    pub idx: Vec<u32>,
    pub calls: BTreeSet<usize>,
    pub value_param: bool,
}

/// The value passed for a kernel's value parameter `p: R`.
pub const VALUE_PARAM: f64 = 0.75;

/// Length of every array and number of threads.
pub const LEN: usize = 6;

pub fn gen_kernel(idx: usize, seed: u64, funcs: &[FuncSig], feat: &mut Features) -> Kernel {
    let mut g = Gen::new(Rng::new(seed), feat, funcs);
    g.kernel = true;
    g.linalg = idx % sizes().linalg_every == 0;
    g.n_inputs = if g.rng.chance(0.8) {
        2
    } else {
        g.rng.int(3, 4)
    };
    g.atomic = g.rng.chance(0.3);
    g.has_idx = g.atomic || g.rng.chance(0.25);
    g.value_param = g.rng.chance(0.25);
    // (its own generator, so that the rest of the kernel is drawn as before)
    let mut shift = Rng::new(seed ^ 0x5707_E5EE_D000_0001);
    if !g.atomic && shift.chance(0.25) {
        g.store_index = format!("(t + {}) % n", shift.int(1, LEN - 1));
        g.feat.hit("store at a shifted index");
    }
    let name = format!("k{idx:03}");
    let mut params: Vec<String> = (0..g.n_inputs)
        .map(|j| format!("x{j}: &Array<R>"))
        .collect();
    if g.has_idx {
        params.push("idx: &Array<u32>".into());
    }
    params.push("n: usize".into());
    if g.value_param {
        params.push("p: R".into());
        g.declare("p", Ty::S(Iv::pt(VALUE_PARAM)), false);
        g.feat.hit("value parameter");
    }
    params.push(if g.atomic {
        "f: &Array<R>".into()
    } else {
        "y: &Array<R>".into()
    });
    let ids: Vec<u32> = (0..LEN).map(|_| g.rng.below(LEN) as u32).collect();
    g.budget = g.rng.int(sizes().kernel_stmts.0, sizes().kernel_stmts.1) as i32;
    let mut body = String::new();
    writeln!(body, "    let t = tid();").unwrap();
    for _ in 0..g.rng.int(1, 2) {
        g.accumulator(1, &mut body);
    }
    // the kernel's focus builtin, into a local that the output reads
    let e = g.focus_expr(FOCUS[idx % FOCUS.len()]);
    let local = g.fresh("a");
    writeln!(body, "    let {local} = {};", e.s).unwrap();
    g.declare(&local, Ty::S(e.iv), false);
    // sometimes an index and a flag that branches and loops update (carried non-float values)
    if g.rng.chance(0.3) {
        let j = g.fresh("j");
        let c = g.rng.below(LEN);
        writeln!(body, "    let mut {j} = (t + {c}) % n;").unwrap();
        g.ints.last_mut().unwrap().push(IntVar {
            name: j,
            safe: true,
            unrolled: false,
            mutable: true,
        });
        g.feat.hit("let mut index");
    }
    if g.rng.chance(0.3) {
        let b = g.fresh("f");
        let c = g.cond(1);
        writeln!(body, "    let mut {b} = {c};").unwrap();
        g.bools.last_mut().unwrap().push(b);
        g.feat.hit("let mut bool");
    }
    let n = g.budget as usize;
    g.stmts(n, 2, 1, &mut body);
    let w = g.output_write(1);
    body.push_str(&w);
    if g.atomic {
        g.feat.hit("atomic kernel");
    }
    let src = format!(
        "#[diff_kernel]\nfn {name}<R: Real>({}) {{\n{body}}}\n",
        params.join(", ")
    );
    Kernel {
        name,
        src,
        n_inputs: g.n_inputs,
        has_idx: g.has_idx,
        idx: ids,
        calls: g.called.clone(),
        value_param: g.value_param,
    }
}
