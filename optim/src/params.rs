//! The parameters of an optimization: arrays of any element type, flattened into one vector of
//! `f64` and written back, with optional bounds.

use adflex_runtime::{AnyArray, Array, Element, Error, Tape};

/// Bounds on every scalar component of a parameter array.
///
/// Gradient descent, Adam, Gauss-Newton and Levenberg-Marquardt keep a bounded parameter
/// inside by projection (clamping each update or trial point), so it may start on its bound;
/// L-BFGS by a change of variables (`p = lo + e^u`, `p = hi - e^u`, or
/// `p = lo + (hi - lo) sigmoid(u)`), so a bounded parameter must start strictly inside.
/// Newton-CG and Gauss-Newton by the KKT system take unbounded parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    /// Lower bound (`-inf`: none).
    pub lower: f64,
    /// Upper bound (`+inf`: none).
    pub upper: f64,
}

impl Bounds {
    /// No bounds.
    pub const NONE: Bounds = Bounds {
        lower: f64::NEG_INFINITY,
        upper: f64::INFINITY,
    };
    /// `p >= lower`.
    pub fn at_least(lower: f64) -> Self {
        Bounds {
            lower,
            ..Self::NONE
        }
    }
    /// `p <= upper`.
    pub fn at_most(upper: f64) -> Self {
        Bounds {
            upper,
            ..Self::NONE
        }
    }
    /// `lower <= p <= upper`.
    pub fn between(lower: f64, upper: f64) -> Self {
        Bounds { lower, upper }
    }
    /// `p >= 0` (a stiffness, a mass, a length): `at_least(0)`. L-BFGS keeps it strictly
    /// positive; gradient descent and Adam project onto the closed bound, so a step past it
    /// lands on exactly 0. Where 0 is not allowed (a mass: 0 pins the particle), use
    /// `at_least(floor)` with a small positive floor.
    pub fn positive() -> Self {
        Self::at_least(0.0)
    }
    fn clamp(&self, p: f64) -> f64 {
        p.max(self.lower).min(self.upper)
    }
    /// `p(u)` and `dp/du` of the change of variables L-BFGS uses.
    fn param_of_free(self, u: f64) -> (f64, f64) {
        match (self.lower.is_finite(), self.upper.is_finite()) {
            (false, false) => (u, 1.0),
            (true, false) => (self.lower + u.exp(), u.exp()),
            (false, true) => (self.upper - u.exp(), -u.exp()),
            (true, true) => {
                let s = 1.0 / (1.0 + (-u).exp());
                let w = self.upper - self.lower;
                (self.lower + w * s, w * s * (1.0 - s))
            }
        }
    }
    /// The inverse of [`Bounds::param_of_free`]; `None` if `p` is not strictly inside.
    fn free_of_param(self, p: f64) -> Option<f64> {
        match (self.lower.is_finite(), self.upper.is_finite()) {
            (false, false) => Some(p),
            (true, false) => (p > self.lower).then(|| (p - self.lower).ln()),
            (false, true) => (p < self.upper).then(|| (self.upper - p).ln()),
            (true, true) => (p > self.lower && p < self.upper).then(|| {
                let s = (p - self.lower) / (self.upper - self.lower);
                (s / (1.0 - s)).ln()
            }),
        }
    }
}

struct Entry {
    array: Box<dyn AnyArray>,
    bounds: Bounds,
}

/// The arrays an optimizer changes: every differentiable scalar component of each, in order,
/// as one vector (`Vec3` elements give 3 components, `f32` arrays are widened to `f64`).
///
/// Adding an array marks it as requiring a gradient. The arrays are handles: the optimizer
/// writes the values it tries into the arrays the simulation reads.
///
/// ```
/// use adflex_optim::{Bounds, Params};
/// use adflex_runtime::{Array, Vec3};
///
/// let rest = Array::from_vec(vec![1.0f64, 2.0]);
/// let v0 = Array::from_vec(vec![Vec3::new(0.0f32, 1.0, 2.0)]);
/// let params = Params::new().with(&v0).bounded(&rest, Bounds::positive());
/// assert_eq!(params.len(), 5);
/// assert_eq!(params.values(), vec![0.0, 1.0, 2.0, 1.0, 2.0]);
/// params.set_values(&[0.0, 0.0, 0.0, 3.0, 4.0]);
/// assert_eq!(rest.to_vec(), vec![3.0, 4.0]);
/// assert!(rest.is_requires_grad());
/// ```
#[derive(Default)]
pub struct Params {
    entries: Vec<Entry>,
}

impl std::fmt::Debug for Params {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list()
            .entries(
                self.entries
                    .iter()
                    .map(|e| (e.array.label(), e.array.len(), e.bounds)),
            )
            .finish()
    }
}

impl Params {
    /// No parameters.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds `array` (unbounded) and marks it as requiring a gradient.
    pub fn with<T: Element>(self, array: &Array<T>) -> Self {
        self.bounded(array, Bounds::NONE)
    }

    /// Adds `array` with `bounds` on each of its components and marks it as requiring a
    /// gradient. Panics if the bounds are empty (`lower > upper`) or NaN, or if the array is
    /// already a parameter.
    pub fn bounded<T: Element>(mut self, array: &Array<T>, bounds: Bounds) -> Self {
        assert!(
            bounds.lower <= bounds.upper,
            "Params: bounds {:?} of `{}` are empty or NaN",
            bounds,
            array.label()
        );
        assert!(
            !self.entries.iter().any(|e| e.array.id() == array.id()),
            "Params: `{}` is added twice",
            array.label()
        );
        let _marked = array.clone().requires_grad();
        self.entries.push(Entry {
            array: Box::new(array.clone()),
            bounds,
        });
        self
    }

    /// Number of scalar components.
    pub fn len(&self) -> usize {
        self.entries.iter().map(|e| e.array.n_scalars()).sum()
    }

    /// True if there are no components.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn components(&self) -> impl Iterator<Item = (&Entry, usize)> {
        self.entries
            .iter()
            .flat_map(|e| (0..e.array.n_scalars()).map(move |k| (e, k)))
    }

    /// The current values, flattened.
    pub fn values(&self) -> Vec<f64> {
        self.components().map(|(e, k)| e.array.scalar(k)).collect()
    }

    /// Writes `values` (flattened, [`Params::len`] of them) into the arrays. Panics on a
    /// length mismatch.
    pub fn set_values(&self, values: &[f64]) {
        assert_eq!(
            values.len(),
            self.len(),
            "Params::set_values: {} values for {} components",
            values.len(),
            self.len()
        );
        for ((e, k), &x) in self.components().zip(values) {
            e.array.set_scalar(k, x);
        }
    }

    /// The gradients, flattened. Errors with [`Error::NoGrad`] naming the array if one has no
    /// gradient buffer.
    pub fn grads(&self) -> Result<Vec<f64>, Error> {
        let mut out = Vec::with_capacity(self.len());
        for e in &self.entries {
            let g = e.array.grad_any().ok_or_else(|| Error::NoGrad {
                array: e.array.label(),
            })?;
            out.extend((0..g.n_scalars()).map(|k| g.scalar(k)));
        }
        Ok(out)
    }

    /// [`Error::InvalidInput`] naming the first parameter none of `losses` depends on in
    /// `tape`.
    pub(crate) fn check_used(&self, tape: &Tape, losses: &[&dyn AnyArray]) -> Result<(), Error> {
        let unused = |e: &&Entry| !losses.iter().any(|l| tape.depends(*l, &*e.array));
        match self.entries.iter().find(unused) {
            Some(e) => Err(Error::InvalidInput {
                what: format!("optimization parameter {}", e.array.label()),
                message: format!(
                    "the recorded loss `{}` does not depend on it: pass the array the \
                     simulation reads (e.g. from `model.param(..)`), or remove it from the \
                     parameters",
                    losses
                        .iter()
                        .map(|l| l.label())
                        .collect::<Vec<_>>()
                        .join("`, `")
                ),
            }),
            None => Ok(()),
        }
    }

    /// The arrays, in order.
    pub(crate) fn arrays(&self) -> Vec<&dyn AnyArray> {
        self.entries.iter().map(|e| &*e.array).collect()
    }

    /// [`Error::InvalidInput`] naming the first bounded parameter: `method` takes unbounded
    /// ones.
    pub(crate) fn check_unbounded(&self, method: &str) -> Result<(), Error> {
        match self.entries.iter().find(|e| e.bounds != Bounds::NONE) {
            Some(e) => Err(Error::InvalidInput {
                what: format!("optimization parameter {}", e.array.label()),
                message: format!(
                    "it has bounds {:?}; {method} takes unbounded parameters: bound it by a \
                     change of variables in the simulation, or use L-BFGS",
                    e.bounds
                ),
            }),
            None => Ok(()),
        }
    }

    /// Zeroes the gradients of the arrays (before each evaluation of the loss).
    pub fn zero_grads(&self) {
        for e in &self.entries {
            e.array.zero_grad();
        }
    }

    /// Names each component: `label[i]` or `label[i].k` (for error messages).
    pub(crate) fn component_name(&self, index: usize) -> String {
        let (e, k) = self
            .components()
            .nth(index)
            .expect("component index in range");
        let d = e.array.element_dim().max(1);
        match d {
            1 => format!("{}[{}]", e.array.label(), k),
            _ => format!("{}[{}].{}", e.array.label(), k / d, k % d),
        }
    }

    /// The norm of the projected gradient: components at a bound whose descent direction
    /// leaves the bounds count as 0 (a minimum on a bound is stationary for projection).
    pub(crate) fn projected_grad_norm(&self, values: &[f64], grad: &[f64]) -> f64 {
        self.pinned(values, grad)
            .iter()
            .zip(grad)
            .map(|(&out, &g)| if out { 0.0 } else { g * g })
            .sum::<f64>()
            .sqrt()
    }

    /// Per component, whether it is at a bound with its descent direction leaving the bounds
    /// (a projected step leaves it where it is).
    pub(crate) fn pinned(&self, values: &[f64], grad: &[f64]) -> Vec<bool> {
        self.components()
            .zip(values.iter().zip(grad))
            .map(|((e, _), (&p, &g))| {
                (p <= e.bounds.lower && g > 0.0) || (p >= e.bounds.upper && g < 0.0)
            })
            .collect()
    }

    /// Whether any parameter has bounds.
    pub(crate) fn is_bounded(&self) -> bool {
        self.entries.iter().any(|e| e.bounds != Bounds::NONE)
    }

    /// [`Error::InvalidInput`] naming the first component outside its bounds (or NaN):
    /// `method` keeps bounds by projection, from a start inside them or on them.
    pub(crate) fn check_inside(&self, values: &[f64], method: &str) -> Result<(), Error> {
        for (i, ((e, _), &p)) in self.components().zip(values).enumerate() {
            if !(p >= e.bounds.lower && p <= e.bounds.upper) {
                return Err(Error::InvalidInput {
                    what: self.component_name(i),
                    message: format!(
                        "starts at {p}, outside its bounds [{}, {}]; {method} keeps bounds by \
                         projection: start inside them or on them",
                        e.bounds.lower, e.bounds.upper
                    ),
                });
            }
        }
        Ok(())
    }

    /// Clamps `values` into the bounds (projection).
    pub(crate) fn project(&self, values: &mut [f64]) {
        for ((e, _), x) in self.components().zip(values) {
            *x = e.bounds.clamp(*x);
        }
    }

    /// Values in the free variables of the change of variables, or an error naming the first
    /// component not strictly inside its bounds.
    pub(crate) fn free_of_params(&self, values: &[f64]) -> Result<Vec<f64>, Error> {
        self.components()
            .zip(values)
            .enumerate()
            .map(|(i, ((e, _), &p))| {
                e.bounds
                    .free_of_param(p)
                    .ok_or_else(|| Error::InvalidInput {
                        what: self.component_name(i),
                        message: format!(
                            "starts at {p}, not strictly inside its bounds [{}, {}]; L-BFGS keeps \
                         bounds by a change of variables, start inside them",
                            e.bounds.lower, e.bounds.upper
                        ),
                    })
            })
            .collect()
    }

    /// Values and `dp/du` from the free variables.
    pub(crate) fn params_of_free(&self, free: &[f64]) -> (Vec<f64>, Vec<f64>) {
        self.components()
            .zip(free)
            .map(|((e, _), &u)| e.bounds.param_of_free(u))
            .unzip()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn changes_of_variables_invert_and_differentiate() {
        for b in [
            Bounds::NONE,
            Bounds::at_least(0.5),
            Bounds::at_most(-1.0),
            Bounds::between(-2.0, 3.0),
        ] {
            for p in [-1.5, -1.2, 0.7, 2.9] {
                let Some(u) = b.free_of_param(p) else {
                    continue;
                };
                let (q, d) = b.param_of_free(u);
                assert!((q - p).abs() < 1e-12, "{b:?} {p}");
                let h = 1e-6;
                let fd = (b.param_of_free(u + h).0 - b.param_of_free(u - h).0) / (2.0 * h);
                assert!(
                    (fd - d).abs() < 1e-6 * (1.0 + d.abs()),
                    "{b:?} {p}: {fd} {d}"
                );
            }
        }
        assert_eq!(Bounds::positive().free_of_param(0.0), None);
    }
}
