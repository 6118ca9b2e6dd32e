"""The reference of `kernels/tests/snow.rs`: Taichi's `mpm99` (its 99-line MLS-MPM example:
fluid, jelly and snow with SVD plasticity) in f64, run on a scene adflex builds the same way,
written to `mpm99.json` (particles' final positions, velocities, deformation gradients and
plastic volume ratios).

The algorithm is mpm99's, written again here (Taichi 1.7.4): `F <- (I + dt C) F`, hardening
`h = exp(10 (1 - Jp))` (0.3 for jelly), `mu = 0` for the fluid, the SVD of `F` with snow's
singular values clamped to [1 - 2.5e-2, 1 + 4.5e-3], `Jp *= sigma / sigma_clamped`, the fluid's
`F` reset to `sqrt(J) I`, the corotated Kirchhoff stress, APIC transfers with quadratic
B-splines, walls three nodes thick. Two conventions are adflex's: a node without mass keeps
a zero velocity (mpm99 divides only where the mass is positive, the same), and the walls stop
the whole velocity of a node moving into them (mpm99 stops the normal component; the floor is
the same, `Floor::Coulomb(0)`): the scene keeps its blocks off the side walls and the ceiling.

One change of mpm99's numerics: Taichi's `ti.svd` of a 2 x 2 matrix treats the stretch `S` of
`F = R S` as diagonal when `|S01| < 1e-5`, which moves a clamped snow particle's `F` by up to
that much per step; the reference (`x`, `v`, `F`, `Jp`) uses the exact SVD of the same
construction (`exact_svd2d`: the polar decomposition, then the eigenvectors of `S` in closed
form). The run with `ti.svd` itself is stored too (`ti_svd_x`, `ti_svd_Jp`), to show the size
of that approximation.

Run: python taichi_mpm99.py (regenerate.sh runs it in a venv with pinned versions). With
`--bench [--n-grid 128] [--steps 200] [--threads N]` it times mpm99 itself (`ti.svd`, f32) for
`adflex-bench snow` and prints one JSON line instead.
"""
import argparse
import json
import math
import os
import time

import taichi as ti

ap = argparse.ArgumentParser()
ap.add_argument("--bench", action="store_true", help="time steps in f32, print one JSON line")
ap.add_argument("--n-grid", type=int, default=32)
ap.add_argument("--steps", type=int, default=500)
ap.add_argument("--threads", type=int, default=1)
args = ap.parse_args()

fp = ti.f32 if args.bench else ti.f64
ti.init(arch=ti.cpu, default_fp=fp, cpu_max_num_threads=args.threads, random_seed=0)

n_grid = args.n_grid
dx = 1.0 / n_grid
dt = 1e-4
steps = args.steps
p_vol = (dx * 0.5) ** 2
p_rho = 1.0
p_mass = p_vol * p_rho
E, nu = 1000.0, 0.2
mu_0, lambda_0 = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
gravity = -50.0
bound = 3

# Blocks as adflex's MpmBuilder::add_rect fills them: two particles per cell and axis, the
# first axis varying slowest. (material: 0 fluid, 1 jelly, 2 snow)
blocks = [
    dict(material=0, lo=(0.15, 0.15), size=(0.2, 0.2), v=(0.0, -1.0)),
    dict(material=1, lo=(0.42, 0.45), size=(0.15, 0.15), v=(0.0, -2.0)),
    dict(material=2, lo=(0.62, 0.2), size=(0.2, 0.2), v=(0.0, -3.0)),
]
xs, vs, mats = [], [], []
for b in blocks:
    counts = [int(math.floor(s / dx)) * 2 for s in b["size"]]
    for i in range(counts[0]):
        for j in range(counts[1]):
            xs.append([b["lo"][a] + ((i, j)[a] + 0.5) * b["size"][a] / counts[a] for a in range(2)])
            vs.append(list(b["v"]))
            mats.append(b["material"])
n = len(xs)

x = ti.Vector.field(2, dtype=float, shape=n)
v = ti.Vector.field(2, dtype=float, shape=n)
C = ti.Matrix.field(2, 2, dtype=float, shape=n)
F = ti.Matrix.field(2, 2, dtype=float, shape=n)
material = ti.field(dtype=int, shape=n)
Jp = ti.field(dtype=float, shape=n)
grid_v = ti.Vector.field(2, dtype=float, shape=(n_grid, n_grid))
grid_m = ti.field(dtype=float, shape=(n_grid, n_grid))


@ti.func
def exact_svd2d(A):
    """U, sigma, V of a 2 x 2 matrix: Taichi's construction without the 1e-5 threshold."""
    R, S = ti.polar_decompose(A)
    c, s = 1.0, 0.0
    s1, s2 = S[0, 0], S[1, 1]
    if S[0, 1] != 0.0:
        tao = 0.5 * (S[0, 0] - S[1, 1])
        w = ti.sqrt(tao**2 + S[0, 1] ** 2)
        t = 0.0
        if tao > 0:
            t = S[0, 1] / (tao + w)
        else:
            t = S[0, 1] / (tao - w)
        c = 1 / ti.sqrt(t**2 + 1)
        s = -t * c
        s1 = c**2 * S[0, 0] - 2 * c * s * S[0, 1] + s**2 * S[1, 1]
        s2 = s**2 * S[0, 0] + 2 * c * s * S[0, 1] + c**2 * S[1, 1]
    V = ti.Matrix([[c, s], [-s, c]])
    if s1 < s2:
        s1, s2 = s2, s1
        V = ti.Matrix([[-s, c], [-c, -s]])
    return R @ V, ti.Matrix([[s1, 0.0], [0.0, s2]]), V


@ti.kernel
def substep(exact: ti.template()):
    for i, j in grid_m:
        grid_v[i, j] = [0, 0]
        grid_m[i, j] = 0
    for p in x:
        base = (x[p] / dx - 0.5).cast(int)
        fx = x[p] / dx - base.cast(float)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        F[p] = (ti.Matrix.identity(float, 2) + dt * C[p]) @ F[p]
        h = ti.exp(10 * (1.0 - Jp[p]))
        if material[p] == 1:
            h = 0.3
        mu, la = mu_0 * h, lambda_0 * h
        if material[p] == 0:
            mu = 0.0
        U, sig, V = ti.svd(F[p])
        if ti.static(exact):
            U, sig, V = exact_svd2d(F[p])
        J = 1.0
        for d in ti.static(range(2)):
            new_sig = sig[d, d]
            if material[p] == 2:
                new_sig = ti.min(ti.max(sig[d, d], 1 - 2.5e-2), 1 + 4.5e-3)
            Jp[p] *= sig[d, d] / new_sig
            sig[d, d] = new_sig
            J *= new_sig
        if material[p] == 0:
            F[p] = ti.Matrix.identity(float, 2) * ti.sqrt(J)
        elif material[p] == 2:
            F[p] = U @ sig @ V.transpose()
        stress = 2 * mu * (F[p] - U @ V.transpose()) @ F[p].transpose() + ti.Matrix.identity(
            float, 2
        ) * la * J * (J - 1)
        stress = (-dt * p_vol * 4 / dx / dx) * stress
        affine = stress + p_mass * C[p]
        for i, j in ti.static(ti.ndrange(3, 3)):
            offset = ti.Vector([i, j])
            dpos = (offset.cast(float) - fx) * dx
            weight = w[i][0] * w[j][1]
            grid_v[base + offset] += weight * (p_mass * v[p] + affine @ dpos)
            grid_m[base + offset] += weight * p_mass
    for i, j in grid_m:
        if grid_m[i, j] > 0:
            grid_v[i, j] = (1 / grid_m[i, j]) * grid_v[i, j]
            grid_v[i, j][1] += dt * gravity
        if i < bound and grid_v[i, j][0] < 0:
            grid_v[i, j] = [0, 0]
        if i > n_grid - bound and grid_v[i, j][0] > 0:
            grid_v[i, j] = [0, 0]
        if j < bound and grid_v[i, j][1] < 0:
            grid_v[i, j][1] = 0
        if j > n_grid - bound and grid_v[i, j][1] > 0:
            grid_v[i, j] = [0, 0]
    for p in x:
        base = (x[p] / dx - 0.5).cast(int)
        fx = x[p] / dx - base.cast(float)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        new_v = ti.Vector.zero(float, 2)
        new_C = ti.Matrix.zero(float, 2, 2)
        for i, j in ti.static(ti.ndrange(3, 3)):
            dpos = ti.Vector([i, j]).cast(float) - fx
            g_v = grid_v[base + ti.Vector([i, j])]
            weight = w[i][0] * w[j][1]
            new_v += weight * g_v
            new_C += 4 * weight * g_v.outer_product(dpos) / dx
        v[p], C[p] = new_v, new_C
        x[p] += dt * v[p]


def run(exact, n_steps=steps):
    for p in range(n):
        x[p] = xs[p]
        v[p] = vs[p]
        material[p] = mats[p]
        F[p] = [[1, 0], [0, 1]]
        C[p] = [[0, 0], [0, 0]]
        Jp[p] = 1.0
    for _ in range(n_steps):
        substep(exact)


if args.bench:
    # mpm99 as it is (ti.svd), f32: the seconds per step, the median of 5 rollouts after one
    # that compiles.
    times = []
    for k in range(6):
        run(False, 1)  # compiles on the first call
        run(False, 0)  # the initial state again: the timed steps are adflex's, from the start
        ti.sync()
        t = time.perf_counter()
        for _ in range(steps):
            substep(False)
        ti.sync()
        times.append((time.perf_counter() - t) / steps)
    times = sorted(times[1:])
    print(json.dumps(dict(peer="taichi", case="mpm99", n_grid=n_grid, particles=n,
                          threads=args.threads, s_per_step=times[len(times) // 2])))
    raise SystemExit
run(False)
ti_svd_x, ti_svd_jp = x.to_numpy().tolist(), Jp.to_numpy().tolist()
run(True)

out = dict(
    about="Taichi 1.7.4 mpm99 in f64 (taichi_mpm99.py); see snow.rs",
    n_grid=n_grid,
    dt=dt,
    steps=steps,
    gravity=gravity,
    E=E,
    nu=nu,
    blocks=blocks,
    x=x.to_numpy().tolist(),
    v=v.to_numpy().tolist(),
    F=F.to_numpy().reshape(n, 4).tolist(),
    Jp=Jp.to_numpy().tolist(),
    ti_svd_x=ti_svd_x,
    ti_svd_Jp=ti_svd_jp,
)
path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "mpm99.json")
with open(path, "w") as f:
    json.dump(out, f)
print(f"{n} particles, {steps} steps -> {path}")
