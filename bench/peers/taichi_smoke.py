"""The smoke-control task of `kernels/src/fluid/scenes.rs` (`SmokeTask`) in Taichi on the CPU,
f64, with the pressure by K unrolled Jacobi iterations (Taichi's tape cannot differentiate a
solve to a tolerance), for the time per optimization iteration side by side
(`adflex-bench smoke`; adflex with `Pressure::Jacobi(K)`).

Same grid, densities, step, loss and normalized gradient-descent update as `jax_smoke.py`.
Prints one JSON line: {"peer", "n", "steps", "pressure", "losses", "s_per_iter"}.
"""
import argparse
import json
import math
import time

import taichi as ti

ap = argparse.ArgumentParser()
ap.add_argument("--n", type=int, default=110)
ap.add_argument("--steps", type=int, default=100)
ap.add_argument("--iters", type=int, default=5)
ap.add_argument("--lr", type=float, default=1.0)
ap.add_argument("--jacobi", type=int, default=30)
ap.add_argument("--threads", type=int, default=0, help="0: all cores")
args = ap.parse_args()
init = dict(arch=ti.cpu, default_fp=ti.f64)
if args.threads > 0:
    init["cpu_max_num_threads"] = args.threads
ti.init(**init)

n, steps, K = args.n, args.steps, args.jacobi
dx = 1.0 / n
shape = (steps + 1, n, n)
u = ti.field(ti.f64, shape=shape, needs_grad=True)
v = ti.field(ti.f64, shape=shape, needs_grad=True)
d = ti.field(ti.f64, shape=shape, needs_grad=True)
au = ti.field(ti.f64, shape=shape, needs_grad=True)
av = ti.field(ti.f64, shape=shape, needs_grad=True)
div = ti.field(ti.f64, shape=shape, needs_grad=True)
p = ti.field(ti.f64, shape=(steps, K + 1, n, n), needs_grad=True)
target = ti.field(ti.f64, shape=(n, n))
loss = ti.field(ti.f64, shape=(), needs_grad=True)


@ti.func
def sample(q: ti.template(), t, x, y):
    hi = n - 1.0
    x = ti.min(ti.max(x, 0.0), hi)
    y = ti.min(ti.max(y, 0.0), hi)
    x0 = ti.min(ti.floor(x), hi - 1.0)
    y0 = ti.min(ti.floor(y), hi - 1.0)
    ax, ay = x - x0, y - y0
    i, j = ti.cast(x0, ti.i32), ti.cast(y0, ti.i32)
    q0 = q[t, i, j] * (1 - ay) + q[t, i, j + 1] * ay
    q1 = q[t, i + 1, j] * (1 - ay) + q[t, i + 1, j + 1] * ay
    return q0 * (1 - ax) + q1 * ax


@ti.kernel
def advect(t: ti.i32):
    for i, j in ti.ndrange(n, n):
        x, y = i - u[t, i, j], j - v[t, i, j]  # dt / dx = 1
        au[t, i, j] = sample(u, t, x, y)
        av[t, i, j] = sample(v, t, x, y)
        d[t + 1, i, j] = sample(d, t, x, y)


@ti.func
def at(q: ti.template(), t, i, j):
    r = 0.0
    if 0 <= i < n and 0 <= j < n:
        r = q[t, i, j]
    return r


@ti.kernel
def divergence(t: ti.i32):
    for i, j in ti.ndrange(n, n):
        div[t, i, j] = (at(au, t, i + 1, j) - at(au, t, i - 1, j)
                        + at(av, t, i, j + 1) - at(av, t, i, j - 1)) / (2 * dx)


@ti.kernel
def jacobi(t: ti.i32, k: ti.i32):
    for i, j in ti.ndrange(n, n):
        diag, off = 0.0, 0.0
        if i + 1 < n:
            diag += 1.0
            if i + 2 < n:
                off += p[t, k, i + 2, j]
        if i >= 1:
            diag += 1.0
            if i >= 2:
                off += p[t, k, i - 2, j]
        if j + 1 < n:
            diag += 1.0
            if j + 2 < n:
                off += p[t, k, i, j + 2]
        if j >= 1:
            diag += 1.0
            if j >= 2:
                off += p[t, k, i, j - 2]
        p[t, k + 1, i, j] = (-4 * dx * dx * div[t, i, j] + off) / diag


@ti.func
def pat(t, i, j):
    r = 0.0
    if 0 <= i < n and 0 <= j < n:
        r = p[t, K, i, j]
    return r


@ti.kernel
def subtract(t: ti.i32):
    for i, j in ti.ndrange(n, n):
        u[t + 1, i, j] = au[t, i, j] - (pat(t, i + 1, j) - pat(t, i - 1, j)) / (2 * dx)
        v[t + 1, i, j] = av[t, i, j] - (pat(t, i, j + 1) - pat(t, i, j - 1)) / (2 * dx)


@ti.kernel
def compute_loss():
    for i, j in ti.ndrange(n, n):
        e = d[steps, i, j] - target[i, j]
        loss[None] += e * e


def forward():
    for t in range(steps):
        advect(t)
        divergence(t)
        for k in range(K):
            jacobi(t, k)
        subtract(t)
    compute_loss()


def disc(cx, cy, r, i, j):
    x, y = (i + 0.5) / n, (j + 0.5) / n
    dd = math.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    return min(max(0.5 - (dd - r) * n, 0.0), 1.0)


for i in range(n):
    for j in range(n):
        d[0, i, j] = disc(0.5, 0.3, 0.15, i, j)
        target[i, j] = disc(0.3, 0.65, 0.1, i, j) + disc(0.7, 0.65, 0.1, i, j)

losses, times = [], []
for it in range(args.iters + 1):
    t0 = time.perf_counter()
    with ti.ad.Tape(loss=loss):
        forward()
    times.append(time.perf_counter() - t0)
    losses.append(float(loss[None]))
    gu, gv = u.grad.to_numpy()[0], v.grad.to_numpy()[0]
    big = max(abs(gu).max(), abs(gv).max(), 1e-30)
    uu, vv = u.to_numpy(), v.to_numpy()
    uu[0] -= args.lr * gu / big
    vv[0] -= args.lr * gv / big
    u.from_numpy(uu)
    v.from_numpy(vv)

steady = sorted(times[2:]) if len(times) > 3 else sorted(times)
print(json.dumps({"peer": "taichi " + ".".join(map(str, ti.__version__)), "n": n, "steps": steps,
                  "pressure": f"jacobi {K}", "losses": losses, "s_per_iter": steady[len(steady) // 2]}))
