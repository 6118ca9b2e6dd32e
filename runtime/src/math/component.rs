//! Component access: `extract(v, k)` (what `v.x`, `v[k]`, `m[(r, c)]` lower to) and
//! `replace(v, k, x)` (what `v.x = e` lowers to). Indices are not differentiable; an index out
//! of range panics.

use nalgebra::{Matrix2, Matrix3, Quaternion, Vector2, Vector3, Vector4};

use crate::{Real, Value};

/// Component access of a value with index type `K`: vectors and quaternions by `usize`
/// (quaternions in storage order x, y, z, w), matrices by `(row, col)`, and arrays `[T; N]`.
pub trait ComponentRule<K: Copy>: Value {
    /// The component's type.
    type Out: Value;
    /// The zero index (the adjoint of an index).
    const ZERO_INDEX: K;
    /// Component `k`.
    fn comp_get(self, k: K) -> Self::Out;
    /// `self` with component `k` set to `x`.
    fn comp_set(self, k: K, x: Self::Out) -> Self;
}

macro_rules! component_vector {
    ($($t:ident),*) => {$(
        impl<R: Real> ComponentRule<usize> for $t<R> {
            type Out = R;
            const ZERO_INDEX: usize = 0;
            #[inline(always)]
            fn comp_get(self, k: usize) -> R {
                self[k]
            }
            #[inline(always)]
            fn comp_set(mut self, k: usize, x: R) -> Self {
                self[k] = x;
                self
            }
        }
    )*};
}
component_vector!(Vector2, Vector3, Vector4);

impl<R: Real> ComponentRule<usize> for Quaternion<R> {
    type Out = R;
    const ZERO_INDEX: usize = 0;
    #[inline(always)]
    fn comp_get(self, k: usize) -> R {
        self.coords[k]
    }
    #[inline(always)]
    fn comp_set(mut self, k: usize, x: R) -> Self {
        self.coords[k] = x;
        self
    }
}

macro_rules! component_matrix {
    ($($t:ident),*) => {$(
        impl<R: Real> ComponentRule<(usize, usize)> for $t<R> {
            type Out = R;
            const ZERO_INDEX: (usize, usize) = (0, 0);
            #[inline(always)]
            fn comp_get(self, k: (usize, usize)) -> R {
                self[k]
            }
            #[inline(always)]
            fn comp_set(mut self, k: (usize, usize), x: R) -> Self {
                self[k] = x;
                self
            }
        }
    )*};
}
component_matrix!(Matrix2, Matrix3);

impl<T: Value + Default, const N: usize> ComponentRule<usize> for [T; N] {
    type Out = T;
    const ZERO_INDEX: usize = 0;
    #[inline(always)]
    fn comp_get(self, k: usize) -> T {
        self[k]
    }
    #[inline(always)]
    fn comp_set(mut self, k: usize, x: T) -> Self {
        self[k] = x;
        self
    }
}

/// Component `k` of `v`: `Vec2/3/4` and `Quat` (x, y, z, w) by `usize`, `Mat22/33` by
/// `(row, col)`, `[T; N]` by `usize`. Panics if `k` is out of range. No singular points.
#[inline(always)]
pub fn extract<V: ComponentRule<K>, K: Copy>(v: V, k: K) -> V::Out {
    v.comp_get(k)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`extract`]: `(adj` in component `k` and zero elsewhere`, 0)`.
#[inline]
pub fn adj_extract<V: ComponentRule<K>, K: Copy>(_v: V, k: K, adj: V::Out) -> (V, K) {
    (V::zeroed().comp_set(k, adj), V::ZERO_INDEX)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`extract`]: component `k` of `dv`.
#[inline]
pub fn tan_extract<V: ComponentRule<K>, K: Copy>(_v: V, k: K, dv: V, _dk: K) -> V::Out {
    dv.comp_get(k)
}

/// `v` with component `k` replaced by `x` (same types as [`extract`]). No singular points.
#[inline(always)]
pub fn replace<V: ComponentRule<K>, K: Copy>(v: V, k: K, x: V::Out) -> V {
    v.comp_set(k, x)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`replace`]: `(adj` with component `k` zeroed`, 0, adj[k])`.
#[inline]
pub fn adj_replace<V: ComponentRule<K>, K: Copy>(
    _v: V,
    k: K,
    _x: V::Out,
    adj: V,
) -> (V, K, V::Out) {
    (
        adj.comp_set(k, V::Out::zeroed()),
        V::ZERO_INDEX,
        adj.comp_get(k),
    )
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`replace`]: `dv` with component `k` replaced by `dx`.
#[inline]
pub fn tan_replace<V: ComponentRule<K>, K: Copy>(
    _v: V,
    k: K,
    _x: V::Out,
    dv: V,
    _dk: K,
    dx: V::Out,
) -> V {
    dv.comp_set(k, dx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::{Mat22, Mat33, Quat, Vec2, Vec3, Vec4};

    fn rc(n: usize) -> impl Fn(&mut Rng) -> (usize, usize) {
        move |rng| (rng.below(n), rng.below(n))
    }

    fd_tests! {
        extract_v2: extract, adj_extract, tan_extract [Vec2<R> = any, usize = idx(2)];
        extract_v3: extract, adj_extract, tan_extract [Vec3<R> = any, usize = idx(3)];
        extract_v4: extract, adj_extract, tan_extract [Vec4<R> = any, usize = idx(4)];
        extract_q: extract, adj_extract, tan_extract [Quat<R> = any, usize = idx(4)];
        extract_m22: extract, adj_extract, tan_extract [Mat22<R> = any, (usize, usize) = rc(2)];
        extract_m33: extract, adj_extract, tan_extract [Mat33<R> = any, (usize, usize) = rc(3)];
        extract_array_r: extract, adj_extract, tan_extract [[R; 3] = any, usize = idx(3)];
        extract_array_v3: extract, adj_extract, tan_extract [[Vec3<R>; 2] = any, usize = idx(2)];
        extract_array_u32: extract, adj_extract, tan_extract [[u32; 2] = just([4u32, 5]), usize = idx(2)];
        replace_v2: replace, adj_replace, tan_replace [Vec2<R> = any, usize = idx(2), R = any];
        replace_v3: replace, adj_replace, tan_replace [Vec3<R> = any, usize = idx(3), R = any];
        replace_v4: replace, adj_replace, tan_replace [Vec4<R> = any, usize = idx(4), R = any];
        replace_q: replace, adj_replace, tan_replace [Quat<R> = any, usize = idx(4), R = any];
        replace_m22: replace, adj_replace, tan_replace [Mat22<R> = any, (usize, usize) = rc(2), R = any];
        replace_m33: replace, adj_replace, tan_replace [Mat33<R> = any, (usize, usize) = rc(3), R = any];
        replace_array_r: replace, adj_replace, tan_replace [[R; 3] = any, usize = idx(3), R = any];
        replace_array_u32: replace, adj_replace, tan_replace [[u32; 2] = just([4u32, 5]), usize = idx(2), u32 = just(7u32)];
    }

    #[test]
    fn values() {
        let v = Vec3::new(1.0f32, 2.0, 3.0);
        assert_eq!(extract(v, 2), 3.0);
        assert_eq!(replace(v, 0, 5.0), Vec3::new(5.0, 2.0, 3.0));
        let q = Quat::new(4.0f64, 1.0, 2.0, 3.0); // w, i, j, k
        assert_eq!([0, 1, 2, 3].map(|k| extract(q, k)), [1.0, 2.0, 3.0, 4.0]);
        let m = Mat22::new(1.0f64, 2.0, 3.0, 4.0);
        assert_eq!(extract(m, (0, 1)), 2.0);
        assert_eq!(replace(m, (1, 0), 9.0), Mat22::new(1.0, 2.0, 9.0, 4.0));
        assert_eq!(
            adj_extract(m, (1, 0), 1.0),
            (Mat22::new(0.0, 0.0, 1.0, 0.0), (0, 0))
        );
        let e = [3u32, 4];
        assert_eq!(extract(e, 1), 4);
        assert_eq!(adj_extract(e, 1, 0), ([0, 0], 0));
        assert_eq!(
            adj_replace(v, 1, 0.0, Vec3::new(1.0, 2.0, 3.0)),
            (Vec3::new(1.0, 0.0, 3.0), 0, 2.0)
        );
    }

    #[test]
    #[should_panic]
    fn out_of_range() {
        extract(Vec3::new(1.0f32, 2.0, 3.0), 3);
    }
}
