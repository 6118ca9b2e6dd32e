//! The kernels of a 2D grid fluid on an `n x n` collocated grid (cell `(i, j)` at index
//! `i * n + j`): semi-Lagrangian advection, central-difference divergence and gradient, and
//! the Jacobi iteration of the pressure equation those two operators imply.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

/// Semi-Lagrangian advection of the field `q` by the velocity `(u, v)` (m/s): cell `tid`
/// takes the bilinear interpolation of `q` at its centre traced back by `dt (u, v)`, i.e.
/// `scale = dt / dx` cells per m/s, clamped to the grid.
#[diff_kernel]
pub fn advect<R: Real>(
    q: &Array<R>,
    u: &Array<R>,
    v: &Array<R>,
    n: usize,
    scale: R,
    out: &Array<R>,
) {
    let t = tid();
    let hi = (n - 1) as R;
    let x = clamp((t / n) as R - u[t] * scale, 0.0, hi);
    let y = clamp((t % n) as R - v[t] * scale, 0.0, hi);
    let x0 = min(floor(x), hi - 1.0);
    let y0 = min(floor(y), hi - 1.0);
    let ax = x - x0;
    let ay = y - y0;
    let i = x0 as usize;
    let j = y0 as usize;
    let q0 = q[i * n + j] * (1.0 - ay) + q[i * n + j + 1] * ay;
    let q1 = q[(i + 1) * n + j] * (1.0 - ay) + q[(i + 1) * n + j + 1] * ay;
    out[t] = q0 * (1.0 - ax) + q1 * ax;
}

/// Divergence of `(u, v)` at cell `tid` by central differences, the velocity outside the
/// grid being zero (closed walls): `(u[i+1] - u[i-1] + v[j+1] - v[j-1]) / (2 dx)`.
#[diff_kernel]
pub fn divergence<R: Real>(u: &Array<R>, v: &Array<R>, n: usize, dx: R, div: &Array<R>) {
    let t = tid();
    let i = t / n;
    let j = t % n;
    let mut d = 0.0;
    if i + 1 < n {
        d += u[t + n];
    }
    if i >= 1 {
        d -= u[t - n];
    }
    if j + 1 < n {
        d += v[t + 1];
    }
    if j >= 1 {
        d -= v[t - 1];
    }
    div[t] = d / (2.0 * dx);
}

/// `(u, v) - grad p` at cell `tid`, the gradient by central differences with `p = 0`
/// outside the grid.
#[diff_kernel]
pub fn subtract_gradient<R: Real>(
    u: &Array<R>,
    v: &Array<R>,
    p: &Array<R>,
    n: usize,
    dx: R,
    u_out: &Array<R>,
    v_out: &Array<R>,
) {
    let t = tid();
    let i = t / n;
    let j = t % n;
    let mut gx = 0.0;
    let mut gy = 0.0;
    if i + 1 < n {
        gx += p[t + n];
    }
    if i >= 1 {
        gx -= p[t - n];
    }
    if j + 1 < n {
        gy += p[t + 1];
    }
    if j >= 1 {
        gy -= p[t - 1];
    }
    u_out[t] = u[t] - gx / (2.0 * dx);
    v_out[t] = v[t] - gy / (2.0 * dx);
}

/// One Jacobi iteration of the pressure equation `A p = -4 dx^2 div`, where `A = -4 dx^2 D G`
/// is the operator of [`divergence`] after [`subtract_gradient`] (so the projected velocity's
/// divergence is exactly zero at the solution): `A_ii` counts the cell's neighbours inside
/// the grid, `A_i,i±2 = -1` along an axis when both cells on that side are inside.
/// `rhs_scale = -4 dx^2`.
#[diff_kernel]
pub fn pressure_jacobi<R: Real>(
    p: &Array<R>,
    div: &Array<R>,
    n: usize,
    rhs_scale: R,
    out: &Array<R>,
) {
    let t = tid();
    let i = t / n;
    let j = t % n;
    let mut diag = 0.0;
    let mut off = 0.0;
    if i + 1 < n {
        diag += 1.0;
        if i + 2 < n {
            off += p[t + 2 * n];
        }
    }
    if i >= 1 {
        diag += 1.0;
        if i >= 2 {
            off += p[t - 2 * n];
        }
    }
    if j + 1 < n {
        diag += 1.0;
        if j + 2 < n {
            off += p[t + 2];
        }
    }
    if j >= 1 {
        diag += 1.0;
        if j >= 2 {
            off += p[t - 2];
        }
    }
    out[t] = (div[t] * rhs_scale + off) / diag;
}

/// Semi-Lagrangian advection in 3D ([`advect`], trilinear; cell `(i, j, k)` at index
/// `(i n + j) n + k`).
#[diff_kernel]
pub fn advect3<R: Real>(
    q: &Array<R>,
    u: &Array<R>,
    v: &Array<R>,
    w: &Array<R>,
    n: usize,
    scale: R,
    out: &Array<R>,
) {
    let t = tid();
    let hi = (n - 1) as R;
    let x = clamp((t / (n * n)) as R - u[t] * scale, 0.0, hi);
    let y = clamp(((t / n) % n) as R - v[t] * scale, 0.0, hi);
    let z = clamp((t % n) as R - w[t] * scale, 0.0, hi);
    let x0 = min(floor(x), hi - 1.0);
    let y0 = min(floor(y), hi - 1.0);
    let z0 = min(floor(z), hi - 1.0);
    let ax = x - x0;
    let ay = y - y0;
    let az = z - z0;
    let i = x0 as usize;
    let j = y0 as usize;
    let k = z0 as usize;
    let c00 = q[(i * n + j) * n + k] * (1.0 - az) + q[(i * n + j) * n + k + 1] * az;
    let c01 = q[(i * n + j + 1) * n + k] * (1.0 - az) + q[(i * n + j + 1) * n + k + 1] * az;
    let c10 = q[((i + 1) * n + j) * n + k] * (1.0 - az) + q[((i + 1) * n + j) * n + k + 1] * az;
    let c11 =
        q[((i + 1) * n + j + 1) * n + k] * (1.0 - az) + q[((i + 1) * n + j + 1) * n + k + 1] * az;
    let c0 = c00 * (1.0 - ay) + c01 * ay;
    let c1 = c10 * (1.0 - ay) + c11 * ay;
    out[t] = c0 * (1.0 - ax) + c1 * ax;
}

/// Divergence in 3D ([`divergence`]).
#[diff_kernel]
pub fn divergence3<R: Real>(
    u: &Array<R>,
    v: &Array<R>,
    w: &Array<R>,
    n: usize,
    dx: R,
    div: &Array<R>,
) {
    let t = tid();
    let i = t / (n * n);
    let j = (t / n) % n;
    let k = t % n;
    let mut d = 0.0;
    if i + 1 < n {
        d += u[t + n * n];
    }
    if i >= 1 {
        d -= u[t - n * n];
    }
    if j + 1 < n {
        d += v[t + n];
    }
    if j >= 1 {
        d -= v[t - n];
    }
    if k + 1 < n {
        d += w[t + 1];
    }
    if k >= 1 {
        d -= w[t - 1];
    }
    div[t] = d / (2.0 * dx);
}

/// `(u, v, w) - grad p` in 3D ([`subtract_gradient`]).
#[diff_kernel]
pub fn subtract_gradient3<R: Real>(
    u: &Array<R>,
    v: &Array<R>,
    w: &Array<R>,
    p: &Array<R>,
    n: usize,
    dx: R,
    u_out: &Array<R>,
    v_out: &Array<R>,
    w_out: &Array<R>,
) {
    let t = tid();
    let i = t / (n * n);
    let j = (t / n) % n;
    let k = t % n;
    let mut gx = 0.0;
    let mut gy = 0.0;
    let mut gz = 0.0;
    if i + 1 < n {
        gx += p[t + n * n];
    }
    if i >= 1 {
        gx -= p[t - n * n];
    }
    if j + 1 < n {
        gy += p[t + n];
    }
    if j >= 1 {
        gy -= p[t - n];
    }
    if k + 1 < n {
        gz += p[t + 1];
    }
    if k >= 1 {
        gz -= p[t - 1];
    }
    u_out[t] = u[t] - gx / (2.0 * dx);
    v_out[t] = v[t] - gy / (2.0 * dx);
    w_out[t] = w[t] - gz / (2.0 * dx);
}

/// One Jacobi iteration of the pressure equation in 3D ([`pressure_jacobi`]).
#[diff_kernel]
pub fn pressure_jacobi3<R: Real>(
    p: &Array<R>,
    div: &Array<R>,
    n: usize,
    rhs_scale: R,
    out: &Array<R>,
) {
    let t = tid();
    let i = t / (n * n);
    let j = (t / n) % n;
    let k = t % n;
    let mut diag = 0.0;
    let mut off = 0.0;
    if i + 1 < n {
        diag += 1.0;
        if i + 2 < n {
            off += p[t + 2 * n * n];
        }
    }
    if i >= 1 {
        diag += 1.0;
        if i >= 2 {
            off += p[t - 2 * n * n];
        }
    }
    if j + 1 < n {
        diag += 1.0;
        if j + 2 < n {
            off += p[t + 2 * n];
        }
    }
    if j >= 1 {
        diag += 1.0;
        if j >= 2 {
            off += p[t - 2 * n];
        }
    }
    if k + 1 < n {
        diag += 1.0;
        if k + 2 < n {
            off += p[t + 2];
        }
    }
    if k >= 1 {
        diag += 1.0;
        if k >= 2 {
            off += p[t - 2];
        }
    }
    out[t] = (div[t] * rhs_scale + off) / diag;
}
