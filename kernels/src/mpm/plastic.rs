//! The plastic projection of snow (Stomakhin et al. 2013): the singular values of `F` clamped
//! to `[1 - compression, 1 + stretch]`. With the polar decomposition `F = R S` (`S` symmetric),
//! `U clamp(Sigma) V^T = R clamp(S)`, where `clamp(S)` applies the clamp to the eigenvalues of
//! `S`: a spectral function of a symmetric matrix ([`clamp_spectrum2`], [`clamp_spectrum3`]).
//!
//! Its derivatives are written by hand, because the generated ones would go through the
//! eigenvectors, which are not differentiable where eigenvalues coincide (`S = I` at rest; a
//! uniaxial stretch) although the spectral function is. The Daleckii-Krein formula needs no
//! eigenvector derivative: with `S = V diag(l) V^T`,
//! `d clamp(S) = V (D o (V^T dS V)) V^T`, `D_ij` the divided difference
//! `(c(l_i) - c(l_j)) / (l_i - l_j)` of the clamp `c` (its slope where `l_i = l_j`), `o` the
//! elementwise product. The map is self-adjoint, so the adjoint is the same formula. The
//! eigen-decomposition runs in `f64` (nalgebra's `SymmetricEigen`), so the rules are not
//! `dual_safe`: a Hessian-vector product through snow is refused with an error naming
//! the function.

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

/// The divided difference of the clamp between two eigenvalues (its slope at their mean
/// where they agree to rounding).
fn divided_difference(a: f64, b: f64, lo: f64, hi: f64) -> f64 {
    let scale = a.abs().max(b.abs()).max(1.0);
    if (a - b).abs() <= 1e-12 * scale {
        slope(0.5 * (a + b), lo, hi)
    } else {
        (clamp(a, lo, hi) - clamp(b, lo, hi)) / (a - b)
    }
}

/// The spectral clamp and its derivative rules for `N x N` matrices (2 and 3).
macro_rules! spectral_clamp {
    ($n:literal, $mat:ident, $value:ident, $adjoint:ident, $tangent:ident) => {
        /// The symmetric part of `s` in `f64` and its eigen-decomposition.
        fn eigen_of<R: Real>(s: &$mat<R>) -> SymmetricEigen<f64, nalgebra::Const<$n>> {
            let m: SMatrix<f64, $n, $n> = s.map(|v| v.to_f64());
            SymmetricEigen::new((m + m.transpose()) * 0.5)
        }

        /// `V (D o X) V^T` with `X = V^T sym(g) V` (the Daleckii-Krein map), and the diagonal
        /// of `X` (for the bounds' derivatives).
        fn daleckii_krein(
            e: &SymmetricEigen<f64, nalgebra::Const<$n>>,
            g: &SMatrix<f64, $n, $n>,
            lo: f64,
            hi: f64,
        ) -> (SMatrix<f64, $n, $n>, SVector<f64, $n>) {
            let v = &e.eigenvectors;
            let x = v.transpose() * ((g + g.transpose()) * 0.5) * v;
            let l = &e.eigenvalues;
            let d = SMatrix::<f64, $n, $n>::from_fn(|i, j| {
                x[(i, j)] * divided_difference(l[i], l[j], lo, hi)
            });
            (v * d * v.transpose(), x.diagonal())
        }

        /// The value of the spectral clamp: the eigenvalues of `sym(s)` clamped to `[lo, hi]`.
        pub fn $value<R: Real>(s: $mat<R>, lo: R, hi: R) -> $mat<R> {
            let (lo, hi) = (lo.to_f64(), hi.to_f64());
            let e = eigen_of(&s);
            let c = SVector::<f64, $n>::from_fn(|i, _| clamp(e.eigenvalues[i], lo, hi));
            let out = &e.eigenvectors * SMatrix::from_diagonal(&c) * e.eigenvectors.transpose();
            out.map(R::lit)
        }

        /// Adjoint of the spectral clamp (Daleckii-Krein; the bounds get the adjoint's diagonal
        /// entries, in the eigenbasis, of the eigenvalues they clamp).
        pub fn $adjoint<R: Real>(s: $mat<R>, lo: R, hi: R, adj: $mat<R>) -> ($mat<R>, R, R) {
            let (lo, hi) = (lo.to_f64(), hi.to_f64());
            let e = eigen_of(&s);
            let (ds, diag) = daleckii_krein(&e, &adj.map(|v| v.to_f64()), lo, hi);
            let (mut dlo, mut dhi) = (0.0, 0.0);
            for i in 0..$n {
                let l = e.eigenvalues[i];
                if l < lo {
                    dlo += diag[i];
                } else if l > hi {
                    dhi += diag[i];
                }
            }
            (ds.map(R::lit), R::lit(dlo), R::lit(dhi))
        }

        /// Tangent of the spectral clamp.
        pub fn $tangent<R: Real>(s: $mat<R>, lo: R, hi: R, ds: $mat<R>, dlo: R, dhi: R) -> $mat<R> {
            let (lo, hi) = (lo.to_f64(), hi.to_f64());
            let e = eigen_of(&s);
            let (mut out, _) = daleckii_krein(&e, &ds.map(|v| v.to_f64()), lo, hi);
            let v = &e.eigenvectors;
            for i in 0..$n {
                let l = e.eigenvalues[i];
                let db = if l < lo {
                    dlo.to_f64()
                } else if l > hi {
                    dhi.to_f64()
                } else {
                    0.0
                };
                if db != 0.0 {
                    out += v.column(i) * v.column(i).transpose() * db;
                }
            }
            out.map(R::lit)
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
#[diff_func(adjoint = clamp_spectrum2_adjoint, tangent = clamp_spectrum2_tangent)]
pub fn clamp_spectrum2<R: Real>(s: Mat22<R>, lo: R, hi: R) -> Mat22<R> {
    no_grad(clamp_spectrum2_value(s, lo, hi))
}

/// [`clamp_spectrum2`] for 3 x 3 matrices.
#[diff_func(adjoint = clamp_spectrum3_adjoint, tangent = clamp_spectrum3_tangent)]
pub fn clamp_spectrum3<R: Real>(s: Mat33<R>, lo: R, hi: R) -> Mat33<R> {
    no_grad(clamp_spectrum3_value(s, lo, hi))
}
