//! `Parts`: the host vectors of the library's solves, with the derivative parts of a
//! Hessian-vector product beside their values.

/// A host vector of a gradient solve: its values and, when the model's scalar is
/// [`Dual`](adflex_runtime::Dual), their derivative parts (the second sweep of a
/// Hessian-vector product; `None` in `f32`/`f64`). A linear map with real coefficients acts
/// on both parts alike ([`Parts::map`], [`Parts::zip`]).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Parts {
    pub re: Vec<f64>,
    pub eps: Option<Vec<f64>>,
}

impl Parts {
    /// Values without derivative parts.
    pub fn real(re: Vec<f64>) -> Self {
        Parts { re, eps: None }
    }

    /// The linear map `f` applied to each part.
    pub fn map(&self, f: impl Fn(&[f64]) -> Vec<f64>) -> Parts {
        Parts {
            re: f(&self.re),
            eps: self.eps.as_deref().map(f),
        }
    }

    /// The linear map `f` of `self` and `other` applied part by part (a missing derivative
    /// part is zero).
    pub fn zip(&self, other: &Parts, f: impl Fn(&[f64], &[f64]) -> Vec<f64>) -> Parts {
        let eps = match (&self.eps, &other.eps) {
            (None, None) => None,
            (a, b) => {
                let zeros = vec![0.0; self.re.len().max(other.re.len())];
                Some(f(
                    a.as_deref().unwrap_or(&zeros),
                    b.as_deref().unwrap_or(&zeros),
                ))
            }
        };
        Parts {
            re: f(&self.re, &other.re),
            eps,
        }
    }
}

/// What to do instead when forward mode meets a solve on a `Dual` tape (its tangent rule
/// computes in `f64`; a Hessian-vector product does not need it).
pub(crate) const NO_DUAL_TANGENT: &str =
    "take Jacobian and Gauss-Newton products in f64; Hessian-vector products need `backward` only";
