"""The MPM walker of `examples/mpm_walker.rs` in Taichi (DiffTaichi's `diffmpm` model), for
the loss curve and the time per iteration side by side (`adflex-bench mpm`).

Two small differences from `diffmpm.py` itself, the same in adflex: a node without mass
keeps a zero velocity (diffmpm divides by `mass + 1e-10` and gives empty nodes gravity; no
particle reads them), and the loss is taken after `steps` steps (diffmpm runs `steps - 1`).

Same scene (a body on four legs, 2 particles per cell and axis, fixed corotated, mu = lambda
= 10, mass = volume = 1), same boundary (walls 3 nodes thick, sticky floor), same controller
(4 sine waves per leg, tanh), same initial weights (the LCG of `initial_weights`), same
loss (minus the mean x after `steps` steps), plain gradient descent. The grid is recomputed
in the backward pass of each step (Taichi's `grad_replaced` idiom), as DiffTaichi does.

Prints one JSON line: {"peer", "n_grid", "particles", "steps", "losses", "s_per_iter"}.
Run: python taichi_mpm.py --n-grid 128 --steps 1024 --iters 80
"""
import argparse
import json
import math
import time

import numpy as np
import taichi as ti

ap = argparse.ArgumentParser()
ap.add_argument("--n-grid", type=int, default=128)
ap.add_argument("--steps", type=int, default=1024)
ap.add_argument("--iters", type=int, default=80)
ap.add_argument("--lr", type=float, default=0.1)
ap.add_argument("--dt", type=float, default=1e-3)
ap.add_argument("--threads", type=int, default=0, help="0: all cores")
args = ap.parse_args()

init = dict(arch=ti.cpu, default_fp=ti.f32, random_seed=0)
if args.threads > 0:
    init["cpu_max_num_threads"] = args.threads
ti.init(**init)

n_grid, steps, dt = args.n_grid, args.steps, args.dt
dx = 1.0 / n_grid
bound, gravity, mu, la, strength = 3, 3.8, 10.0, 10.0, 4.0
waves, omega = 4, 20.0

# The scene (as kernels/src/mpm/scenes.rs).
xs, acts = [], []
off = (0.1, max(0.03, 3.5 * dx))


def rect(x, y, w, h, a):
    nx, ny = int(math.floor(w / dx)) * 2, int(math.floor(h / dx)) * 2
    for i in range(nx):
        for j in range(ny):
            xs.append([off[0] + x + (i + 0.5) * w / nx, off[1] + y + (j + 0.5) * h / ny])
            acts.append(a)


rect(0.0, 0.1, 0.3, 0.1, -1)
for k, x0 in enumerate([0.0, 0.05, 0.2, 0.25]):
    rect(x0, 0.0, 0.05, 0.1, k)
n = len(xs)
n_act = 4

x = ti.Vector.field(2, ti.f32, shape=(steps + 1, n), needs_grad=True)
v = ti.Vector.field(2, ti.f32, shape=(steps + 1, n), needs_grad=True)
C = ti.Matrix.field(2, 2, ti.f32, shape=(steps + 1, n), needs_grad=True)
F = ti.Matrix.field(2, 2, ti.f32, shape=(steps + 1, n), needs_grad=True)
grid_mv = ti.Vector.field(2, ti.f32, shape=(n_grid, n_grid), needs_grad=True)
grid_m = ti.field(ti.f32, shape=(n_grid, n_grid), needs_grad=True)
grid_v = ti.Vector.field(2, ti.f32, shape=(n_grid, n_grid), needs_grad=True)
actuator = ti.field(ti.i32, shape=n)
weights = ti.field(ti.f32, shape=(n_act, waves), needs_grad=True)
bias = ti.field(ti.f32, shape=n_act, needs_grad=True)
actuation = ti.field(ti.f32, shape=(steps, n_act), needs_grad=True)
mean = ti.Vector.field(2, ti.f32, shape=(), needs_grad=True)
loss = ti.field(ti.f32, shape=(), needs_grad=True)


@ti.kernel
def clear_grid():
    for i, j in grid_m:
        grid_mv[i, j] = [0, 0]
        grid_m[i, j] = 0
        grid_mv.grad[i, j] = [0, 0]
        grid_m.grad[i, j] = 0
        grid_v.grad[i, j] = [0, 0]


@ti.kernel
def controller(t: ti.i32):
    for i in range(n_act):
        s = bias[i]
        for j in ti.static(range(waves)):
            s += weights[i, j] * ti.sin(omega * t * dt + j * 2 * math.pi / waves)
        actuation[t, i] = ti.tanh(s)


@ti.kernel
def p2g(t: ti.i32):
    for p in range(n):
        xg = x[t, p] / dx
        base = ti.cast(ti.floor(xg - 0.5), ti.i32)
        fx = xg - base
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        Fp = (ti.Matrix.identity(ti.f32, 2) + dt * C[t, p]) @ F[t, p]
        F[t + 1, p] = Fp
        J = Fp.determinant()
        r, _ = ti.polar_decompose(Fp)
        a = 0.0
        if actuator[p] >= 0:
            a = actuation[t, actuator[p]] * strength
        tau = 2 * mu * (Fp - r) @ Fp.transpose() + ti.Matrix.identity(ti.f32, 2) * la * (J - 1) * J
        tau += Fp @ ti.Matrix([[0.0, 0.0], [0.0, a]]) @ Fp.transpose()
        affine = -(dt * 1.0 * 4.0 / (dx * dx)) * tau + 1.0 * C[t, p]
        for i, j in ti.static(ti.ndrange(3, 3)):
            dpos = (ti.Vector([i, j]) - fx) * dx
            wt = w[i][0] * w[j][1]
            grid_mv[base + ti.Vector([i, j])] += wt * (1.0 * v[t, p] + affine @ dpos)
            grid_m[base + ti.Vector([i, j])] += wt * 1.0


@ti.kernel
def grid_op():
    for i, j in grid_m:
        vo = ti.Vector([0.0, 0.0])
        if grid_m[i, j] > 0:
            vo = grid_mv[i, j] / grid_m[i, j]
            vo[1] -= dt * gravity
        if i < bound and vo[0] < 0:
            vo = ti.Vector([0.0, 0.0])
        if i + bound > n_grid and vo[0] > 0:
            vo = ti.Vector([0.0, 0.0])
        if j < bound and vo[1] < 0:
            vo = ti.Vector([0.0, 0.0])
        if j + bound > n_grid and vo[1] > 0:
            vo = ti.Vector([0.0, 0.0])
        grid_v[i, j] = vo


@ti.kernel
def g2p(t: ti.i32):
    for p in range(n):
        xg = x[t, p] / dx
        base = ti.cast(ti.floor(xg - 0.5), ti.i32)
        fx = xg - base
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        nv = ti.Vector([0.0, 0.0])
        nc = ti.Matrix([[0.0, 0.0], [0.0, 0.0]])
        for i, j in ti.static(ti.ndrange(3, 3)):
            dpos = ti.Vector([i, j]) - fx
            gv = grid_v[base + ti.Vector([i, j])]
            wt = w[i][0] * w[j][1]
            nv += wt * gv
            nc += 4 * wt * gv.outer_product(dpos) / dx
        v[t + 1, p] = nv
        x[t + 1, p] = x[t, p] + dt * nv
        C[t + 1, p] = nc


@ti.kernel
def mean_x():
    for p in range(n):
        mean[None] += x[steps, p] / n


@ti.kernel
def compute_loss():
    loss[None] = -mean[None][0]


@ti.ad.grad_replaced
def advance(t):
    clear_grid()
    controller(t)
    p2g(t)
    grid_op()
    g2p(t)


@ti.ad.grad_for(advance)
def advance_grad(t):
    clear_grid()
    p2g(t)
    grid_op()
    g2p.grad(t)
    grid_op.grad()
    p2g.grad(t)
    controller.grad(t)


def forward():
    for t in range(steps):
        advance(t)
    mean[None] = [0, 0]
    mean_x()
    compute_loss()


def initial_weights():
    s, out = 1, []
    for _ in range(n_act * waves):
        s = (s * 6364136223846793005 + 1442695040888963407) % (1 << 64)
        u = (s >> 11) / float(1 << 53)
        out.append(0.01 * math.sqrt(3.0) * (2.0 * u - 1.0))
    return np.array(out, dtype=np.float32).reshape(n_act, waves)


x0 = np.array(xs, dtype=np.float32)
for p in range(n):
    x[0, p] = x0[p]
    F[0, p] = [[1, 0], [0, 1]]
actuator.from_numpy(np.array(acts, dtype=np.int32))
weights.from_numpy(initial_weights())
bias.from_numpy(np.zeros(n_act, dtype=np.float32))

losses, times = [], []
for it in range(args.iters + 1):
    start = time.perf_counter()
    with ti.ad.Tape(loss=loss):
        forward()
    times.append(time.perf_counter() - start)
    losses.append(float(loss[None]))
    if it == args.iters:
        break
    w, b = weights.to_numpy(), bias.to_numpy()
    weights.from_numpy(w - args.lr * weights.grad.to_numpy())
    bias.from_numpy(b - args.lr * bias.grad.to_numpy())

# The first iterations compile the kernels.
steady = sorted(times[2:]) if len(times) > 3 else sorted(times)
print(json.dumps({
    "peer": "taichi " + ".".join(map(str, ti.__version__)),
    "n_grid": n_grid,
    "particles": n,
    "steps": steps,
    "losses": losses,
    "s_per_iter": steady[len(steady) // 2],
}))
