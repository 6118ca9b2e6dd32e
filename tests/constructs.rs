//! Every construct of the kernel language, differentiated: the adjoint against central finite
//! differences in f64 and the tangent against the adjoint (dot-product test); each kernel is
//! generic over the scalar and also runs in f32, where it must agree with f64.

mod common;

use adflex::prelude::*;
use common::{assert_checked, check, Rng};

const TOL: f64 = 1e-6;

/// Runs a kernel on f64 inputs `xs` with `n` outputs and checks it; returns the f64 forward.
macro_rules! check_kernel {
    ($kernel:ident, dim = $dim:expr, inputs = [$($x:ident : $xv:expr),*], outputs = [$($y:ident : $yn:expr),*] $(, extra = ($($e:expr),*))?) => {{
        $(let $x: Array<f64> = Array::from_vec($xv.clone());)*
        $(let $y: Array<f64> = Array::zeros($yn);)*
        let c = check(&[$(&$x),*], &[$(&$y),*], 7, |m| launch_mode(m, $kernel, $dim, ($(&$x,)* $($($e,)*)? $(&$y,)*)));
        assert_checked(&c, TOL);
        // The same source in f32 agrees with f64.
        $(let $x: Array<f32> = Array::from_vec($xv.iter().map(|&v| v as f32).collect());)*
        $(let $y: Array<f32> = Array::zeros($yn);)*
        launch($kernel, $dim, ($(&$x,)* $($($e,)*)? $(&$y,)*));
        let f32_out: Vec<Vec<f32>> = vec![$($y.to_vec()),*];
        $(let $x: Array<f64> = Array::from_vec($xv.clone());)*
        $(let $y: Array<f64> = Array::zeros($yn);)*
        launch($kernel, $dim, ($(&$x,)* $($($e,)*)? $(&$y,)*));
        let f64_out: Vec<Vec<f64>> = vec![$($y.to_vec()),*];
        for (a, b) in f32_out.iter().flatten().zip(f64_out.iter().flatten()) {
            assert!((*a as f64 - b).abs() <= 1e-4 * b.abs().max(1.0), "f32 {a} vs f64 {b}");
        }
        (c, f64_out)
    }};
}

fn inputs(n: usize, seed: u64) -> Vec<f64> {
    Rng(seed).vec(n, 0.5, 1.5)
}

// ---- straight-line code, let mut, operators --------------------------------------------

#[diff_kernel]
fn arith<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    let mut b = a * a - 2.0 * a;
    b += a / (1.0 + a);
    b -= -a;
    b *= 3.0;
    b /= 2.0;
    let c: R = b * b;
    y[t] = c + sqrt(a) * sin(a) - exp(-a) + ln(a) * cos(a) / tan(a) + pow(a, 1.5) + atan2(a, 2.0);
}

#[test]
fn straight_line_arithmetic_and_let_mut() {
    check_kernel!(arith, dim = 5, inputs = [x: inputs(5, 1)], outputs = [y: 5]);
}

// ---- vectors, components, destructuring, builtins ----------------------------------------

#[diff_kernel]
fn vectors<R: Real>(x: &Array<R>, pairs: &Array<[u32; 2]>, y: &Array<R>) {
    let t = tid();
    let [i, j] = pairs[t];
    let a = vec3(
        x[i as usize * 3],
        x[i as usize * 3 + 1],
        x[i as usize * 3 + 2],
    );
    let b = vec3(
        x[j as usize * 3],
        x[j as usize * 3 + 1],
        x[j as usize * 3 + 2],
    );
    let mut c = cross(a, b) + normalize(a - b) * length(b);
    c.y = c.y * 2.0 + a[2];
    c[0] = c.x - dot(a, b);
    let m = outer(a, b) + mat33_identity();
    let r = m * c;
    y[t] = r.x + r.y * r.z + determinant(m) + trace(transpose(m)) + length_sq(c);
}

#[test]
fn vectors_components_and_destructuring() {
    let pairs = Array::from_vec(vec![[0u32, 1], [1, 2], [2, 0], [0, 2]]);
    check_kernel!(vectors, dim = 4, inputs = [x: inputs(9, 2)], outputs = [y: 4], extra = (&pairs));
}

// ---- if / else, if as an expression, match, && and || -----------------------------------

#[diff_kernel]
fn branches<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    let mut b = a;
    if a > 1.0 {
        b = b * b;
    } else if a > 0.8 {
        b = b * 3.0;
    } else {
        b = sin(b);
    }
    let c = if b > 1.2 && a < 1.4 { b * a } else { b + a };
    let d = match t % 3 {
        0 => c * 2.0,
        1 | 2 if a > 0.9 || b > 100.0 => c * c,
        _ => c,
    };
    y[t] = d + select(a > 1.0, a, b);
}

#[test]
fn if_else_match_and_short_circuit() {
    check_kernel!(branches, dim = 12, inputs = [x: inputs(12, 3)], outputs = [y: 12]);
}

// ---- loops with constant bounds (unrolled) and dynamic bounds ----------------------------

#[diff_kernel]
fn loops<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    let mut s = x[t];
    for k in 0..3 {
        s = s * x[(t + k) % n] + 0.1;
    }
    let mut p = s;
    for k in 1..n {
        p = p + x[k] * p * 0.5;
        if k == 2 {
            p = sqrt(p);
        }
    }
    y[t] = p;
}

#[test]
fn constant_and_dynamic_for_loops() {
    check_kernel!(loops, dim = 4, inputs = [x: inputs(4, 4)], outputs = [y: 4], extra = (4usize));
}

// ---- the three loops NVIDIA Warp 1.19 differentiates wrongly -----------------------------

#[diff_kernel]
fn product_loop<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let mut p = 1.0;
    for k in 0..n {
        p = p * x[k];
    }
    y[tid()] = p;
}

#[test]
fn warp_case_product_loop() {
    let xs = inputs(6, 5);
    let (c, _) =
        check_kernel!(product_loop, dim = 1, inputs = [x: xs], outputs = [y: 1], extra = (6usize));
    // The gradient is the product of the others.
    let w = {
        let x: Array<f64> = Array::from_vec(xs.clone());
        let y: Array<f64> = Array::zeros(1);
        let c = check(&[&x], &[&y], 7, |m| {
            launch_mode(m, product_loop, 1, (&x, 6usize, &y))
        });
        c.grad[0][0] / xs[1..].iter().product::<f64>()
    };
    for (k, g) in c.grad[0].iter().enumerate() {
        let others: f64 = xs
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .map(|(_, v)| v)
            .product();
        assert!(
            (g - w * others).abs() < 1e-12,
            "d/dx{k}: {g} vs {}",
            w * others
        );
    }
}

#[diff_kernel]
fn break_loop<R: Real>(x: &Array<R>, n: usize, limit: R, y: &Array<R>) {
    let mut s = 0.0;
    let mut count = 0.0;
    for i in 0..n {
        s = s + x[i] * x[i];
        count = count + 1.0;
        if s > limit {
            break;
        }
    }
    y[tid()] = s * count;
}

#[test]
fn warp_case_loop_with_break() {
    // Breaks after 3 of 8 terms: only those have a gradient.
    let (c, _) = check_kernel!(break_loop, dim = 1, inputs = [x: inputs(8, 6)], outputs = [y: 1], extra = (8usize, 2.0));
    let nonzero = c.grad[0].iter().filter(|g| **g != 0.0).count();
    assert!(
        nonzero > 0 && nonzero < 8,
        "break must cut the gradient: {:?}",
        c.grad[0]
    );
}

#[diff_kernel]
fn while_loop<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let mut i = 0;
    let mut s = 0.0;
    while i < n {
        s = s + x[i] * x[i];
        i += 1;
    }
    y[tid()] = s;
}

#[test]
fn warp_case_while_sum_of_squares() {
    let xs = inputs(7, 7);
    let (c, _) =
        check_kernel!(while_loop, dim = 1, inputs = [x: xs], outputs = [y: 1], extra = (7usize));
    let x: Array<f64> = Array::from_vec(xs.clone());
    let y: Array<f64> = Array::zeros(1);
    y.ensure_grad().fill(1.0);
    x.ensure_grad().fill(0.0);
    launch(while_loop, 1, (&x, 7usize, &y));
    launch_adjoint(while_loop, 1, (&x, 7usize, &y));
    for (g, v) in x.grad().unwrap().to_vec().iter().zip(&xs) {
        assert!((g - 2.0 * v).abs() < 1e-12);
    }
    assert!(c.adjoint_err < TOL);
}

// ---- continue, loop with break, nested loops, early return ----------------------------

#[diff_kernel]
fn continue_and_loop<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    let mut s = 0.0;
    for i in 0..n {
        if i % 2 == 1 {
            continue;
        }
        let mut j = 0;
        let mut q = x[i];
        loop {
            q = q * x[(i + j) % n] + 0.25;
            j += 1;
            if j > t {
                break;
            }
        }
        s = s + q;
    }
    if s > 1000.0 {
        return;
    }
    y[t] = s;
}

#[test]
fn continue_loop_break_nested_and_early_return() {
    check_kernel!(continue_and_loop, dim = 3, inputs = [x: inputs(5, 8)], outputs = [y: 3], extra = (5usize));
}

#[diff_kernel]
fn early_return<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    if a < 1.0 {
        y[t] = a * a;
        return;
    }
    y[t] = a * 3.0;
}

#[test]
fn early_return_in_kernel() {
    check_kernel!(early_return, dim = 8, inputs = [x: inputs(8, 9)], outputs = [y: 8]);
}

// ---- diff funcs: calls, early return in a func, nested calls, no_grad --------------------

#[diff_func]
fn smooth_clamp<R: Real>(a: R, lo: R) -> R {
    if a < lo {
        return lo + 0.1 * (a - lo);
    }
    let mut b = a;
    for _ in 0..2 {
        b = b * 0.9 + 0.1 * a;
    }
    b
}

#[diff_func]
fn energy<R: Real>(a: R, b: R) -> R {
    let d = smooth_clamp(a - b, 0.2);
    d * d + b * no_grad(a * 0.0)
}

#[diff_kernel]
fn call_funcs<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    y[t] = energy(x[t], x[(t + 1) % 6]);
}

#[test]
fn diff_func_calls_with_early_return_and_no_grad() {
    check_kernel!(call_funcs, dim = 6, inputs = [x: inputs(6, 10)], outputs = [y: 6]);
}

#[test]
fn diff_func_is_callable_from_rust() {
    assert!((smooth_clamp::call(0.0f64, 0.2) - (0.2 - 0.02)).abs() < 1e-15);
    let g = DiffFunc::adjoint(&energy, (1.0f64, 0.5), 1.0);
    let h = 1e-6;
    let fd = (energy::call(1.0 + h, 0.5) - energy::call(1.0 - h, 0.5)) / (2.0 * h);
    assert!((g.0 - fd).abs() < 1e-6, "{} vs {fd}", g.0);
}

#[diff_kernel]
fn stop_gradient<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    // Plain Rust (a method call) is allowed inside no_grad; its derivative is zero.
    y[t] = no_grad(a * a + a.max(0.5)) + 3.0 * a;
}

#[test]
fn no_grad_has_zero_derivative() {
    let x: Array<f64> = Array::from_vec(vec![0.7, 1.3]).requires_grad();
    let y: Array<f64> = Array::zeros(2);
    launch(stop_gradient, 2, (&x, &y));
    for (a, b) in y.to_vec().iter().zip([0.49 + 0.7 + 2.1, 1.69 + 1.3 + 3.9]) {
        assert!((a - b).abs() < 1e-12);
    }
    y.ensure_grad().fill(1.0);
    launch_adjoint(stop_gradient, 2, (&x, &y));
    assert_eq!(x.grad().unwrap().to_vec(), vec![3.0, 3.0]);
    x.set_tangent(Some(Array::from_vec(vec![1.0, 2.0])));
    y.ensure_tangent().fill(0.0);
    launch_tangent(stop_gradient, 2, (&x, &y));
    assert_eq!(y.tangent_buffer().unwrap().to_vec(), vec![3.0, 6.0]);
}

// ---- atomic_add / atomic_sub, and reads of an index array -------------------------------

#[diff_kernel]
fn scatter<R: Real>(x: &Array<R>, pairs: &Array<[u32; 2]>, f: &Array<R>) {
    let [i, j] = pairs[tid()];
    let d = x[i] - x[j];
    let e = d * d * d;
    f.atomic_add(i, e);
    f.atomic_sub(j, e * 2.0);
    f[j] += d;
}

#[test]
fn atomic_add_and_sub() {
    let pairs = Array::from_vec(vec![[0u32, 1], [1, 2], [2, 3], [3, 0], [0, 2]]);
    check_kernel!(scatter, dim = 5, inputs = [x: inputs(4, 11)], outputs = [f: 4], extra = (&pairs));
}

/// `y` and the adjoint of `a` scatter at the thread id (they write directly in every chunk of
/// a parallel launch); `w` and the adjoint of `b` elsewhere (they log until their chunk's
/// turn). Several additions per element, so any change of their order changes the bits.
#[diff_kernel]
fn own_and_shared(
    a: &Array<f64>,
    b: &Array<f64>,
    idx: &Array<u32>,
    y: &Array<f64>,
    w: &Array<f64>,
) {
    let t = tid();
    let j = idx[t];
    for k in 0..3 {
        let s = a[t] * b[j] + 0.1 * (k as f64);
        y.atomic_add(t, s * s);
        y.atomic_sub(t, s * 0.3);
        w.atomic_add(j, s * a[t]);
    }
}

#[test]
fn scatters_at_the_thread_id_give_the_serial_bits_on_any_pool() {
    const N: usize = 20_000;
    let run = |threads: usize, passed_twice: bool| {
        let mut rng = Rng(5);
        let a = Array::from_vec((0..N).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<f64>>())
            .requires_grad();
        let other = Array::from_vec((0..N).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<f64>>())
            .requires_grad();
        let b = if passed_twice { a.clone() } else { other };
        let idx = Array::from_vec((0..N as u32).map(|i| (i * 7919 + 3) % N as u32).collect());
        let y = Array::<f64>::from_vec(vec![0.25; N]);
        let w = Array::<f64>::zeros(N);
        let bits = |v: Vec<f64>| v.into_iter().map(f64::to_bits).collect::<Vec<_>>();
        let mut seen = Vec::new();
        with_threads(threads, || {
            // Several launches, each compared: the pool's choice between serial and parallel
            // times both paths.
            for _ in 0..4 {
                let mut tape = Tape::new();
                y.fill(0.25);
                w.fill(0.0);
                a.zero_grad();
                b.zero_grad();
                tape.launch(own_and_shared, N, (&a, &b, &idx, &y, &w));
                let loss = Array::<f64>::zeros(1);
                tape.launch(sum_of_products, N, (&y, &w, &loss));
                tape.backward(&loss).unwrap();
                seen.push((
                    bits(y.to_vec()),
                    bits(w.to_vec()),
                    bits(a.grad().unwrap().to_vec()),
                    bits(b.grad().unwrap().to_vec()),
                ));
            }
        });
        seen
    };
    for passed_twice in [false, true] {
        let serial = run(1, passed_twice);
        for threads in [2, 3] {
            for (k, got) in run(threads, passed_twice).iter().enumerate() {
                assert!(
                    *got == serial[0],
                    "{threads} threads, launch {k}, b passed as a: {passed_twice}"
                );
            }
        }
    }
}

#[diff_kernel]
fn sum_of_products(y: &Array<f64>, w: &Array<f64>, loss: &Array<f64>) {
    let t = tid();
    loss.atomic_add(0, y[t] * w[t] + y[t]);
}

// ---- custom derivatives: a "leaky" contact gradient ---------------------------------------

/// Penetration depth `min(d, 0)`, whose true gradient is zero when out of contact (d > 0). The
/// custom rules let a small fraction `LEAK` through there, so optimizers see inactive contacts.
#[diff_func(adjoint = leaky_depth_adjoint, tangent = leaky_depth_tangent)]
fn leaky_depth<R: Real>(d: R) -> R {
    min(d, 0.0)
}

const LEAK: f64 = 0.01;

fn leaky_slope<R: Real>(d: R) -> R {
    if d < R::lit(0.0) {
        R::lit(1.0)
    } else {
        R::lit(LEAK)
    }
}

fn leaky_depth_adjoint<R: Real>(d: R, adj_out: R) -> (R,) {
    (leaky_slope(d) * adj_out,)
}

fn leaky_depth_tangent<R: Real>(d: R, dd: R) -> R {
    leaky_slope(d) * dd
}

#[diff_kernel]
fn contact<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let c = leaky_depth(x[t] - 1.0);
    y[t] = c * 1000.0;
}

#[test]
fn custom_adjoint_and_tangent_replace_the_generated_ones() {
    let x: Array<f64> = Array::from_vec(vec![0.5, 1.5]);
    let y: Array<f64> = Array::zeros(2);
    launch(contact, 2, (&x, &y));
    assert_eq!(y.to_vec(), vec![-500.0, 0.0]);
    y.ensure_grad().fill(1.0);
    x.ensure_grad().fill(0.0);
    launch_adjoint(contact, 2, (&x, &y));
    // In contact: the true gradient 1000; out of contact: 1000 * LEAK instead of 0.
    assert_eq!(x.grad().unwrap().to_vec(), vec![1000.0, 1000.0 * LEAK]);
    // Forward and reverse mode agree (the custom tangent matches the custom adjoint).
    let c = check(&[&x], &[&y], 3, |m| launch_mode(m, contact, 2, (&x, &y)));
    assert!(c.dot_err < 1e-12);
}

// ---- bad input -------------------------------------------------------------------------

#[diff_kernel]
fn gather(x: &Array<f64>, idx: &Array<u32>, y: &Array<f64>) {
    let t = tid();
    y[t] = x[idx[t]];
}

#[test]
#[should_panic(
    expected = "kernel `gather`: index 7 out of bounds for array `positions` (parameter `x`) of length 3"
)]
fn out_of_bounds_index_names_kernel_array_index_and_length() {
    let x = Array::from_vec(vec![1.0, 2.0, 3.0]).named("positions");
    let idx = Array::from_vec(vec![0u32, 7]);
    let y = Array::zeros(2);
    launch(gather, 2, (&x, &idx, &y));
}

// ---- nests of literal loops, matrix entries assigned, repeated stores --------------------

/// A 16 x 16 nest of literal loops: only as much is unrolled as keeps the body at 64 copies
/// (unrolling all 256 overflowed rustc's stack in a debug build).
#[diff_kernel]
fn loop_nest<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    let mut s = x[t] * 0.5;
    for i in 0..16 {
        for j in 0..16 {
            s = s + sin(x[(t + i) % n] * x[(t + j) % n]) * 0.01;
        }
    }
    y[t] = s;
}

#[test]
fn a_large_nest_of_literal_loops_compiles_and_differentiates() {
    check_kernel!(loop_nest, dim = 3, inputs = [x: inputs(3, 11)], outputs = [y: 3], extra = (3usize));
}

#[diff_kernel]
fn matrix_entry_assign<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    let mut m = mat33_identity() * a;
    m[(0, 1)] = a * a;
    m[(2, 0)] += sin(a);
    y[t] = determinant(m) + m[(0, 1)] * m[(2, 0)];
}

#[test]
fn matrix_entries_can_be_assigned() {
    check_kernel!(matrix_entry_assign, dim = 4, inputs = [x: inputs(4, 12)], outputs = [y: 4]);
}

#[diff_kernel]
fn stores_overwritten<R: Real>(x: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    let a = x[t];
    y[t] = a * 5.0;
    if a > 1.0 {
        y[t] = a * a;
    }
    for k in 0..n {
        if k == 1 {
            y[t] = y_part(a);
        }
    }
}

#[diff_func]
fn y_part<R: Real>(a: R) -> R {
    a * a * a + a * 0.5
}

#[test]
fn overwritten_stores_get_no_gradient() {
    check_kernel!(stores_overwritten, dim = 6, inputs = [x: inputs(6, 13)], outputs = [y: 6], extra = (3usize));
    check_kernel!(stores_overwritten, dim = 6, inputs = [x: inputs(6, 14)], outputs = [y: 6], extra = (1usize));
}

// ---- a user's function named like a builtin is the one called ----------------------------

mod shadowing {
    use super::common::{assert_checked, check};
    use adflex::prelude::*;

    /// Not the builtin `lerp` (`a + (b - a) t`): this one squares `t`.
    #[diff_func]
    fn lerp<R: Real>(a: R, b: R, t: R) -> R {
        a + (b - a) * t * t
    }

    #[diff_kernel]
    fn blend<R: Real>(x: &Array<R>, y: &Array<R>) {
        let t = tid();
        y[t] = lerp(x[t] * 0.0, x[t] * 0.0 + 1.0, x[t]);
    }

    #[test]
    fn a_user_function_named_like_a_builtin_is_called_not_replaced() {
        let x = Array::from_vec(vec![0.5f64, 0.25]);
        let y = Array::zeros(2);
        launch(blend, 2, (&x, &y));
        assert_eq!(y.to_vec(), vec![0.25, 0.0625]); // the builtin would give 0.5, 0.25
                                                    // and its derivative is the user's: d/dt (t^2) = 2t
        let c = check(&[&x], &[&y], 3, |m| launch_mode(m, blend, 2, (&x, &y)));
        assert_checked(&c, 1e-6);
    }

    mod builtin_still_there {
        use adflex::prelude::*;

        #[diff_kernel]
        fn blend<R: Real>(x: &Array<R>, y: &Array<R>) {
            let t = tid();
            y[t] = lerp(x[t] * 0.0, x[t] * 0.0 + 1.0, x[t]);
        }

        #[test]
        fn without_the_user_function_the_builtin_is_called() {
            let x = Array::from_vec(vec![0.5f64, 0.25]);
            let y = Array::zeros(2);
            launch(blend, 2, (&x, &y));
            assert_eq!(y.to_vec(), vec![0.5, 0.25]);
        }
    }
}

// ---- the list of builtins exists once: the guide and the math docs are checked against it ---

#[test]
fn the_guides_builtin_list_is_the_runtimes() {
    use adflex::runtime::math::items::{BUILTINS, CONSTANTS};
    let guide = include_str!("../docs/guide.md");
    let start = guide
        .find("### Builtins")
        .expect("the guide has a Builtins section");
    let section = &guide[start..];
    let section = &section[..section.find("**Singular points**").unwrap()];
    // The list items ("- group: `names ...`", continued on indented lines).
    let mut items: Vec<String> = Vec::new();
    for line in section.lines() {
        if let Some(rest) = line.strip_prefix("- ") {
            items.push(rest.to_string());
        } else if line.starts_with("  ") && !items.is_empty() {
            items.last_mut().unwrap().push_str(line);
        }
    }
    let names = |item: &str| -> Vec<String> {
        let spans: Vec<&str> = item.split('`').skip(1).step_by(2).collect();
        spans
            .iter()
            .flat_map(|s| s.split_whitespace())
            .map(String::from)
            .collect()
    };
    let operators: Vec<String> = items
        .iter()
        .filter(|i| i.starts_with("operators:"))
        .flat_map(|i| names(i))
        .collect();
    let mut listed: Vec<String> = items
        .iter()
        .filter(|i| !i.starts_with("operators:"))
        .flat_map(|i| names(i))
        .collect();
    let mut code: Vec<String> = BUILTINS
        .iter()
        .chain(CONSTANTS)
        .map(|s| s.to_string())
        .collect();
    code.sort_unstable();
    listed.sort_unstable();
    assert_eq!(
        listed, code,
        "docs/guide.md's builtins vs adflex::math::items"
    );
    // The operators the macro emits by name.
    let table = include_str!("../macros/src/builtins.rs");
    for op in &operators {
        assert!(
            table.contains(&format!("(\"{op}\", ")),
            "operator `{op}` not in the macro's table"
        );
    }
    // Every builtin is documented in adflex::math's docs.
    let math_docs = include_str!("../runtime/src/math/mod.rs");
    for name in &code {
        assert!(
            math_docs.contains(&format!("[`{name}`]")),
            "`{name}` missing from adflex::math's docs"
        );
    }
}
