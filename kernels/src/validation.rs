//! Validation of a scene: one set of checks, run by every [`ModelBuilder`] method on its
//! inputs and on what it derives from them, and used by the scene-file reader too.
//!
//! A builder method never panics on bad input and never silently changes it (a NaN mass is
//! not a pinned particle): it records a [`Problem`] naming the item (`springs[3]`), the
//! parameter (`ke`) and what to fix, and [`ModelBuilder::try_finalize`] returns them all as a
//! [`ModelError`] ([`ModelBuilder::finalize`] panics with the list).
//!
//! What is checked, in the model's precision `R` (`f32` or `f64`):
//! - particle indices in range, and distinct within an element;
//! - masses, stiffnesses, damping, friction, compliance, radii: finite and `>= 0` (lengths of
//!   shapes, Lame `lambda` of tetrahedra, body inertia: `> 0`);
//! - positions, velocities, gravity, wind, normals, orientations: finite in `R` (`1e39`
//!   overflows `f32`);
//! - what the builder derives: inverse masses finite in `R`; rest lengths of springs and
//!   distance constraints finite and `> 0`; rest shapes of membrane triangles and tetrahedra
//!   not degenerate, with a quality (1 for an equilateral element, 0 for a flat one) of at
//!   least [`min_quality`], an inverse rest matrix `Dm^-1` finite in `R` and an area (volume)
//!   above `R::tiny()`; bending rest angles finite.
//!
//! [`ModelBuilder`]: crate::ModelBuilder
//! [`ModelBuilder::try_finalize`]: crate::ModelBuilder::try_finalize
//! [`ModelBuilder::finalize`]: crate::ModelBuilder::finalize

use std::fmt;

use adflex_runtime::{Real, Vec3};

/// One thing wrong with one item of a scene.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Problem {
    /// The item, as the builder numbers it: `particles[3]`, `springs[0]`, `tets[2]`,
    /// `gravity`, `ground`.
    pub item: String,
    /// The parameter of the builder call that is wrong (`mass`, `ke`, `x`), if it is one
    /// parameter (`indices` for the particle indices of an element; `None` for an element as a
    /// whole, e.g. a degenerate triangle or a zero rest length).
    pub param: Option<&'static str>,
    /// What is wrong, and what to do about it.
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.item)?;
        if let Some(p) = self.param {
            write!(f, ".{p}")?;
        }
        write!(f, ": {}", self.message)
    }
}

/// Everything wrong with a scene, in the order the builder calls were made.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelError {
    /// The problems (at least one).
    pub problems: Vec<Problem>,
}

impl fmt::Display for ModelError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.problems.len();
        write!(
            f,
            "invalid model ({n} problem{}):",
            if n == 1 { "" } else { "s" }
        )?;
        for p in &self.problems {
            write!(f, "\n  {p}")?;
        }
        Ok(())
    }
}

impl std::error::Error for ModelError {}

/// `"f32"` or `"f64"`.
pub(crate) fn precision<R: Real>() -> &'static str {
    if std::mem::size_of::<R>() == 4 {
        "f32"
    } else {
        "f64"
    }
}

/// The largest finite value of `R`.
pub(crate) fn max_of<R: Real>() -> f64 {
    if std::mem::size_of::<R>() == 4 {
        f32::MAX as f64
    } else {
        f64::MAX
    }
}

/// The smallest quality ([`crate::forces::fem_tri::triangle_quality`],
/// [`crate::forces::fem_tet::tet_quality`]) of an element the builder accepts in precision
/// `R`: the square root of `R`'s machine epsilon (3.5e-4 in `f32`, 1.5e-8 in `f64`). Below it,
/// inverting the rest shape loses more than half of `R`'s digits.
pub fn min_quality<R: Real>() -> f64 {
    if std::mem::size_of::<R>() == 4 {
        (f32::EPSILON as f64).sqrt()
    } else {
        f64::EPSILON.sqrt()
    }
}

/// The checks of one item, recording problems into the builder's list.
pub(crate) struct Check<'a> {
    pub(crate) out: &'a mut Vec<Problem>,
    pub(crate) kind: &'static str,
    pub(crate) index: Option<usize>,
}

impl Check<'_> {
    /// Records a problem with `param` (or with the whole item).
    pub(crate) fn fail(&mut self, param: Option<&'static str>, message: String) {
        let item = match self.index {
            Some(k) => format!("{}[{k}]", self.kind),
            None => self.kind.to_string(),
        };
        self.out.push(Problem {
            item,
            param,
            message,
        });
    }

    /// `v` finite and `>= 0`.
    pub(crate) fn nonneg<R: Real>(&mut self, param: &'static str, v: R) -> bool {
        let x = v.to_f64();
        let ok = x.is_finite() && x >= 0.0;
        if !ok {
            self.fail(
                Some(param),
                format!("must be a finite number >= 0 (got {x})"),
            );
        }
        ok
    }

    /// `v` finite and `> 0`.
    pub(crate) fn positive<R: Real>(&mut self, param: &'static str, v: R) -> bool {
        let x = v.to_f64();
        let ok = x.is_finite() && x > 0.0;
        if !ok {
            self.fail(
                Some(param),
                format!("must be a finite number > 0 (got {x})"),
            );
        }
        ok
    }

    /// Every value finite in `R`.
    pub(crate) fn finite<R: Real>(&mut self, param: &'static str, v: &[R]) -> bool {
        let ok = v.iter().all(|x| x.to_f64().is_finite());
        if !ok {
            let vals: Vec<f64> = v.iter().map(|x| x.to_f64()).collect();
            self.fail(
                Some(param),
                format!(
                    "must be finite in {} (got {vals:?}){}",
                    precision::<R>(),
                    overflow_hint::<R>()
                ),
            );
        }
        ok
    }

    pub(crate) fn finite3<R: Real>(&mut self, param: &'static str, v: &Vec3<R>) -> bool {
        self.finite(param, &[v.x, v.y, v.z])
    }

    /// Particle indices `idx` in range (`n` particles) and distinct (a problem with parameter
    /// `indices` if not).
    pub(crate) fn particles(&mut self, n: usize, idx: &[u32]) -> bool {
        for (k, &i) in idx.iter().enumerate() {
            if i as usize >= n {
                self.fail(
                    Some("indices"),
                    format!("particle index {i} out of range ({n} particles)"),
                );
                return false;
            }
            if idx[..k].contains(&i) {
                self.fail(
                    Some("indices"),
                    format!("particle {i} appears twice in {idx:?}: an element needs distinct particles"),
                );
                return false;
            }
        }
        true
    }
}

/// "; f32 holds magnitudes up to 3.4e38" (where a finite input may have overflowed).
pub(crate) fn overflow_hint<R: Real>() -> String {
    format!(
        "; {} holds magnitudes up to {:.1e}",
        precision::<R>(),
        max_of::<R>()
    )
}
