"""The smoke-control task of `kernels/src/fluid/scenes.rs` (`SmokeTask`) in JAX on the CPU,
f64, for the time per optimization iteration side by side (`adflex-bench smoke`).

Same grid (n x n, dx = 1/n, dt = dx), same initial and target densities, same step
(semi-Lagrangian advection of u, v and the density by (u, v), then the projection with the
pressure operator built from the same central differences), same loss and the same
normalized gradient-descent update. Pressure: `--pressure cg` uses
`jax.scipy.sparse.linalg.cg` (differentiated implicitly, as adflex's CG step), `--pressure
jacobi --jacobi K` unrolls K Jacobi iterations. The rollout is `lax.scan`, the whole
iteration `jit(value_and_grad)`.

Prints one JSON line: {"peer", "n", "steps", "pressure", "losses", "s_per_iter"}.
"""
import argparse
import json
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

ap = argparse.ArgumentParser()
ap.add_argument("--n", type=int, default=110)
ap.add_argument("--steps", type=int, default=100)
ap.add_argument("--iters", type=int, default=5)
ap.add_argument("--lr", type=float, default=1.0)
ap.add_argument("--pressure", choices=["cg", "jacobi"], default="cg")
ap.add_argument("--jacobi", type=int, default=30)
args = ap.parse_args()
n, steps = args.n, args.steps
dx = 1.0 / n

ii, jj = jnp.meshgrid(jnp.arange(n), jnp.arange(n), indexing="ij")


def disc(cx, cy, r):
    x, y = (ii + 0.5) / n, (jj + 0.5) / n
    d = jnp.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    return jnp.clip(0.5 - (d - r) * n, 0.0, 1.0)


density0 = disc(0.5, 0.3, 0.15)
target = disc(0.3, 0.65, 0.1) + disc(0.7, 0.65, 0.1)


def advect(q, u, v):
    hi = n - 1.0
    x = jnp.clip(ii - u, 0.0, hi)  # dt / dx = 1
    y = jnp.clip(jj - v, 0.0, hi)
    x0 = jnp.minimum(jnp.floor(x), hi - 1.0)
    y0 = jnp.minimum(jnp.floor(y), hi - 1.0)
    ax, ay = x - x0, y - y0
    i, j = x0.astype(jnp.int32), y0.astype(jnp.int32)
    q0 = q[i, j] * (1 - ay) + q[i, j + 1] * ay
    q1 = q[i + 1, j] * (1 - ay) + q[i + 1, j + 1] * ay
    return q0 * (1 - ax) + q1 * ax


def shift(a, di, dj):
    """a[i + di, j + dj], zero outside."""
    p = jnp.pad(a, 2)
    return p[2 + di:2 + di + n, 2 + dj:2 + dj + n]


def divergence(u, v):
    return (shift(u, 1, 0) - shift(u, -1, 0) + shift(v, 0, 1) - shift(v, 0, -1)) / (2 * dx)


inside = lambda di, dj: shift(jnp.ones((n, n)), di, dj)
diag = inside(1, 0) + inside(-1, 0) + inside(0, 1) + inside(0, -1)


def off(p):
    return (inside(1, 0) * shift(p, 2, 0) + inside(-1, 0) * shift(p, -2, 0)
            + inside(0, 1) * shift(p, 0, 2) + inside(0, -1) * shift(p, 0, -2))


def pressure(div):
    b = -4 * dx * dx * div
    if args.pressure == "cg":
        p, _ = jax.scipy.sparse.linalg.cg(lambda p: diag * p - off(p), b, tol=1e-10, maxiter=10000)
        return p
    return jax.lax.fori_loop(0, args.jacobi, lambda _, p: (b + off(p)) / diag, jnp.zeros_like(b))


def step(carry, _):
    u, v, d = carry
    au, av, d = advect(u, u, v), advect(v, u, v), advect(d, u, v)
    p = pressure(divergence(au, av))
    au = au - (shift(p, 1, 0) - shift(p, -1, 0)) / (2 * dx)
    av = av - (shift(p, 0, 1) - shift(p, 0, -1)) / (2 * dx)
    return (au, av, d), None


def loss(uv):
    (_, _, d), _ = jax.lax.scan(step, (uv[0], uv[1], density0), None, length=steps)
    return jnp.sum((d - target) ** 2)


vg = jax.jit(jax.value_and_grad(loss))
uv = jnp.zeros((2, n, n))
losses, times = [], []
for it in range(args.iters + 1):
    t0 = time.perf_counter()
    l, g = vg(uv)
    l.block_until_ready()
    times.append(time.perf_counter() - t0)
    losses.append(float(l))
    uv = uv - args.lr * g / jnp.maximum(jnp.max(jnp.abs(g)), 1e-30)

steady = sorted(times[1:]) if len(times) > 2 else sorted(times)
print(json.dumps({"peer": "jax " + jax.__version__, "n": n, "steps": steps,
                  "pressure": args.pressure if args.pressure == "cg" else f"jacobi {args.jacobi}",
                  "losses": losses, "s_per_iter": steady[len(steady) // 2]}))
