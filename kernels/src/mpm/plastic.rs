//! The plastic projection of snow (Stomakhin et al. 2013): the singular values of `F` clamped
//! to `[1 - compression, 1 + stretch]`. With the polar decomposition `F = R S` (`S` symmetric),
//! `U clamp(Sigma) V^T = R clamp(S)`, where `clamp(S)` applies the clamp to the eigenvalues of
//! `S`: a spectral function of a symmetric matrix ([`clamp_spectrum2`], [`clamp_spectrum3`]).
//!
//! Its derivatives are written by hand, because the generated ones would go through the
//! eigenvectors, which are not differentiable where eigenvalues coincide (`S = I` at rest; a
//! uniaxial stretch) although the spectral function is. The Daleckii-Krein formula needs no
//! eigenvector derivative: with `S = V diag(l) V^T`, `X^ = V^T X V`,
//! `d clamp(S) = V (D o dS^) V^T`, `D_ij` the divided difference
//! `c[l_i, l_j] = (c(l_i) - c(l_j)) / (l_i - l_j)` of the clamp `c` (its slope where
//! `l_i = l_j`), `o` the elementwise product. The map is self-adjoint, so the adjoint is the
//! same formula. The bounds move the clamped eigenvalues: `d clamp / d lo = V diag(l_i < lo)
//! V^T`, and likewise for `hi`.
//!
//! Second order (Hessian-vector products run the rules in [`Dual`]): the second derivative
//! along `(H, a, b)` and `(K, c, d)` (a matrix and the two bounds' steps each) is, entry `ij`
//! in the eigenbasis,
//! `sum_k c[l_i, l_k, l_j] (H^_ik K^_kj + K^_ik H^_kj) + g[l_i, l_j] (H^_ij c + K^_ij a) +
//! h[l_i, l_j] (H^_ij d + K^_ij b)`, with `c[., ., .]` the clamp's second divided difference
//! and `g`, `h` the divided differences of `l < lo` and `l > hi` (the Daleckii-Krein formula
//! of second order; the clamp is piecewise linear, so `c[l, l, l] = 0`). The eigen-decomposition
//! runs in `f64` (nalgebra's `SymmetricEigen`); the rules read the `Dual` parts of their
//! arguments and write those of their results, so they are `dual_safe`.

use adflex_macros::diff_func;
use adflex_runtime::prelude::*;
use nalgebra::{SMatrix, SVector, SymmetricEigen};

/// The clamp of one eigenvalue.
fn clamp(l: f64, lo: f64, hi: f64) -> f64 {
    l.max(lo).min(hi)
}

/// The clamp's slope: 1 inside `[lo, hi]` (its ends included, as the forward value there is
/// `l` itself), 0 outside.
fn slope(l: f64, lo: f64, hi: f64) -> f64 {
    if l >= lo && l <= hi {
        1.0
    } else {
        0.0
    }
}

/// Which piece of the clamp `l` is on: -1 below `lo`, 0 inside `[lo, hi]`, 1 above `hi`.
fn piece(l: f64, lo: f64, hi: f64) -> i8 {
    if l < lo {
        -1
    } else if l > hi {
        1
    } else {
        0
    }
}

/// Whether two eigenvalues agree to rounding (their divided differences are then limits).
fn coincide(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1.0)
}

/// The divided difference of the clamp between two eigenvalues: exactly its slope where both
/// are on one piece (so that second divided differences of one piece are exactly 0), its
/// slope at their mean where they agree to rounding.
fn divided_difference(a: f64, b: f64, lo: f64, hi: f64) -> f64 {
    if coincide(a, b) {
        slope(0.5 * (a + b), lo, hi)
    } else if piece(a, lo, hi) == piece(b, lo, hi) {
        slope(a, lo, hi)
    } else {
        (clamp(a, lo, hi) - clamp(b, lo, hi)) / (a - b)
    }
}

/// The clamp's second divided difference `c[a, b, e]` (symmetric in its arguments; 0 where
/// all three agree, the clamp being piecewise linear).
fn second_divided_difference(a: f64, b: f64, e: f64, lo: f64, hi: f64) -> f64 {
    // Order them so that the first and last are the farthest apart.
    let mut v = [a, b, e];
    v.sort_by(f64::total_cmp);
    let [a, b, e] = v;
    if !coincide(a, e) {
        (divided_difference(a, b, lo, hi) - divided_difference(b, e, lo, hi)) / (a - e)
    } else {
        0.0
    }
}

/// The divided difference of the bounds' derivative `l < lo` (`below`) or `l > hi`: 0 where
/// the eigenvalues coincide or are on the same side.
fn bound_divided_difference(a: f64, b: f64, lo: f64, hi: f64, below: bool) -> f64 {
    let side = |l: f64| f64::from(u8::from(if below { l < lo } else { l > hi }));
    if coincide(a, b) {
        0.0
    } else {
        (side(a) - side(b)) / (a - b)
    }
}

/// The spectral clamp and its derivative rules for `N x N` matrices (2 and 3).
macro_rules! spectral_clamp {
    ($n:literal, $mat:ident, $value:ident, $adjoint:ident, $tangent:ident) => {
        type Eigen = SymmetricEigen<f64, nalgebra::Const<$n>>;
        type M = SMatrix<f64, $n, $n>;

        /// The symmetric part of `s`'s values (`f64`) and its eigen-decomposition.
        fn eigen_of<R: Real>(s: &$mat<R>) -> Eigen {
            let m: M = s.map(|v| v.to_f64());
            SymmetricEigen::new((m + m.transpose()) * 0.5)
        }

        /// The symmetric part of `g` in the eigenbasis: `V^T sym(g) V`.
        fn in_basis(e: &Eigen, g: &M) -> M {
            let v = &e.eigenvectors;
            v.transpose() * ((g + g.transpose()) * 0.5) * v
        }

        /// The `Dual` parts of a matrix's entries (zero for `f32` and `f64`).
        fn eps_of<R: Real>(m: &$mat<R>) -> M {
            m.map(|v| v.eps())
        }

        /// `value` with the `Dual` parts `eps` (ignored unless `R` is `Dual`).
        fn with_eps<R: Real>(value: &M, eps: &M) -> $mat<R> {
            $mat::from_fn(|i, j| R::lit(value[(i, j)]).with_eps(eps[(i, j)]))
        }

        /// The first derivative along `(x, a, b)` (`x` in the eigenbasis, `a`, `b` the
        /// bounds' steps), in the eigenbasis.
        fn first(e: &Eigen, x: &M, a: f64, b: f64, lo: f64, hi: f64) -> M {
            let l = &e.eigenvalues;
            M::from_fn(|i, j| {
                let mut d = x[(i, j)] * divided_difference(l[i], l[j], lo, hi);
                if i == j {
                    d += match piece(l[i], lo, hi) {
                        -1 => a,
                        1 => b,
                        _ => 0.0,
                    };
                }
                d
            })
        }

        /// The second derivative along `(x, a, b)` and `(y, c, d)` (see the module docs), in
        /// the eigenbasis.
        #[allow(clippy::too_many_arguments)]
        fn second(e: &Eigen, x: &M, a: f64, b: f64, y: &M, c: f64, d: f64, lo: f64, hi: f64) -> M {
            let l = &e.eigenvalues;
            M::from_fn(|i, j| {
                let mut s = 0.0;
                for k in 0..$n {
                    s += second_divided_difference(l[i], l[k], l[j], lo, hi)
                        * (x[(i, k)] * y[(k, j)] + y[(i, k)] * x[(k, j)]);
                }
                let g = bound_divided_difference(l[i], l[j], lo, hi, true);
                let h = bound_divided_difference(l[i], l[j], lo, hi, false);
                s + g * (x[(i, j)] * c + y[(i, j)] * a) + h * (x[(i, j)] * d + y[(i, j)] * b)
            })
        }

        /// `<x, y>` weighted by the divided differences of `l < lo` (`below`) or `l > hi`:
        /// the bounds' share of a second derivative's pairing.
        fn bound_pairing(e: &Eigen, x: &M, y: &M, lo: f64, hi: f64, below: bool) -> f64 {
            let l = &e.eigenvalues;
            let mut s = 0.0;
            for i in 0..$n {
                for j in 0..$n {
                    s +=
                        bound_divided_difference(l[i], l[j], lo, hi, below) * x[(i, j)] * y[(i, j)];
                }
            }
            s
        }

        /// From the eigenbasis back: `V x V^T`.
        fn back(e: &Eigen, x: &M) -> M {
            &e.eigenvectors * x * e.eigenvectors.transpose()
        }

        /// The value of the spectral clamp: the eigenvalues of `sym(s)` clamped to `[lo, hi]`
        /// (in `Dual`, with its first derivative along the arguments' `Dual` parts).
        pub fn $value<R: Real>(s: $mat<R>, lo: R, hi: R) -> $mat<R> {
            let e = eigen_of(&s);
            let (lo_f, hi_f) = (lo.to_f64(), hi.to_f64());
            let c = SVector::<f64, $n>::from_fn(|i, _| clamp(e.eigenvalues[i], lo_f, hi_f));
            let out = back(&e, &M::from_diagonal(&c));
            let mut eps = M::zeros();
            if R::DUAL {
                let x = in_basis(&e, &eps_of(&s));
                eps = back(&e, &first(&e, &x, lo.eps(), hi.eps(), lo_f, hi_f));
            }
            with_eps(&out, &eps)
        }

        /// Adjoint of the spectral clamp (Daleckii-Krein; the bounds get the adjoint's diagonal
        /// entries, in the eigenbasis, of the eigenvalues they clamp). In `Dual`, the `Dual`
        /// parts are its derivative along the arguments' (second order).
        pub fn $adjoint<R: Real>(s: $mat<R>, lo: R, hi: R, adj: $mat<R>) -> ($mat<R>, R, R) {
            let e = eigen_of(&s);
            let (lo_f, hi_f) = (lo.to_f64(), hi.to_f64());
            let g = in_basis(&e, &adj.map(|v| v.to_f64()));
            let ds = back(&e, &first(&e, &g, 0.0, 0.0, lo_f, hi_f));
            let clamped = |m: &M, side: i8| -> f64 {
                (0..$n)
                    .filter(|&i| piece(e.eigenvalues[i], lo_f, hi_f) == side)
                    .map(|i| m[(i, i)])
                    .sum()
            };
            let (dlo, dhi) = (clamped(&g, -1), clamped(&g, 1));
            if !R::DUAL {
                return (ds.map(R::lit), R::lit(dlo), R::lit(dhi));
            }
            // d adjoint = adjoint(d adj) + D2 clamp[(ds, dlo, dhi), (adj, 0, 0)] paired.
            let x = in_basis(&e, &eps_of(&s));
            let (a, b) = (lo.eps(), hi.eps());
            let ge = in_basis(&e, &eps_of(&adj));
            let ds_eps = back(
                &e,
                &(first(&e, &ge, 0.0, 0.0, lo_f, hi_f)
                    + second(&e, &x, a, b, &g, 0.0, 0.0, lo_f, hi_f)),
            );
            let dlo_eps = clamped(&ge, -1) + bound_pairing(&e, &x, &g, lo_f, hi_f, true);
            let dhi_eps = clamped(&ge, 1) + bound_pairing(&e, &x, &g, lo_f, hi_f, false);
            (
                with_eps(&ds, &ds_eps),
                R::lit(dlo).with_eps(dlo_eps),
                R::lit(dhi).with_eps(dhi_eps),
            )
        }

        /// Tangent of the spectral clamp. In `Dual`, the `Dual` parts are its derivative along
        /// the arguments' (second order).
        pub fn $tangent<R: Real>(s: $mat<R>, lo: R, hi: R, ds: $mat<R>, dlo: R, dhi: R) -> $mat<R> {
            let e = eigen_of(&s);
            let (lo_f, hi_f) = (lo.to_f64(), hi.to_f64());
            let y = in_basis(&e, &ds.map(|v| v.to_f64()));
            let (c, d) = (dlo.to_f64(), dhi.to_f64());
            let out = back(&e, &first(&e, &y, c, d, lo_f, hi_f));
            let mut eps = M::zeros();
            if R::DUAL {
                let x = in_basis(&e, &eps_of(&s));
                let ye = in_basis(&e, &eps_of(&ds));
                eps = back(
                    &e,
                    &(first(&e, &ye, dlo.eps(), dhi.eps(), lo_f, hi_f)
                        + second(&e, &x, lo.eps(), hi.eps(), &y, c, d, lo_f, hi_f)),
                );
            }
            with_eps(&out, &eps)
        }
    };
}

mod two {
    use super::*;
    spectral_clamp!(
        2,
        Mat22,
        clamp_spectrum2_value,
        clamp_spectrum2_adjoint,
        clamp_spectrum2_tangent
    );
}
mod three {
    use super::*;
    spectral_clamp!(
        3,
        Mat33,
        clamp_spectrum3_value,
        clamp_spectrum3_adjoint,
        clamp_spectrum3_tangent
    );
}
pub use three::{clamp_spectrum3_adjoint, clamp_spectrum3_tangent, clamp_spectrum3_value};
pub use two::{clamp_spectrum2_adjoint, clamp_spectrum2_tangent, clamp_spectrum2_value};

/// The eigenvalues of the symmetric part of `s` clamped to `[lo, hi]` (`lo <= hi`), with the
/// same eigenvectors: `V clamp(diag(l)) V^T` (see the [module docs](self) for its
/// derivatives). Snow's plastic projection applies it to the stretch of `F = R S`.
#[diff_func(adjoint = clamp_spectrum2_adjoint, tangent = clamp_spectrum2_tangent, dual_safe)]
pub fn clamp_spectrum2<R: Real>(s: Mat22<R>, lo: R, hi: R) -> Mat22<R> {
    no_grad(clamp_spectrum2_value(s, lo, hi))
}

/// [`clamp_spectrum2`] for 3 x 3 matrices.
#[diff_func(adjoint = clamp_spectrum3_adjoint, tangent = clamp_spectrum3_tangent, dual_safe)]
pub fn clamp_spectrum3<R: Real>(s: Mat33<R>, lo: R, hi: R) -> Mat33<R> {
    no_grad(clamp_spectrum3_value(s, lo, hi))
}
