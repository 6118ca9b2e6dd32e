"""The 'cloth' scene of docs/scenes.md in NVIDIA Warp on the CPU: the peer for the project's cloth benchmark.

Run: python3 warp_cloth.py --n 128 --steps 100
Prints one JSON line: forward seconds per step, forward+backward seconds per step, loss, gradient norms.
"""
import argparse, json, time
import numpy as np
import warp as wp
import os, sys
sys.path.insert(0, os.path.dirname(__file__))
from warp_cloth_scene import build

wp.config.quiet = True

@wp.kernel
def eval_springs(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), idx: wp.array(dtype=int),
                 rest: wp.array(dtype=float), ke: wp.array(dtype=float), kd: float, f: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    i = idx[tid * 2]
    j = idx[tid * 2 + 1]
    xij = x[i] - x[j]
    vij = v[i] - v[j]
    l = wp.length(xij)
    d = xij / l
    c = l - rest[tid]
    dcdt = wp.dot(d, vij)
    fs = d * (ke[tid] * c + kd * dcdt)
    wp.atomic_sub(f, i, fs)
    wp.atomic_add(f, j, fs)

@wp.kernel
def eval_bending(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), idx: wp.array(dtype=int),
                 rest: wp.array(dtype=float), ke: float, kd: float, f: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    i = idx[tid * 4 + 0]
    j = idx[tid * 4 + 1]
    k = idx[tid * 4 + 2]
    l = idx[tid * 4 + 3]
    x1 = x[i]
    x2 = x[j]
    x3 = x[k]
    x4 = x[l]
    v1 = v[i]
    v2 = v[j]
    v3 = v[k]
    v4 = v[l]
    n1 = wp.cross(x3 - x1, x4 - x1)
    n2 = wp.cross(x4 - x2, x3 - x2)
    n1_length = wp.length(n1)
    n2_length = wp.length(n2)
    rcp_n1 = 1.0 / n1_length
    rcp_n2 = 1.0 / n2_length
    m1 = n1 * rcp_n1 * rcp_n1
    m2 = n2 * rcp_n2 * rcp_n2
    e = x4 - x3
    e_hat = wp.normalize(e)
    e_length = wp.length(e)
    # adflex's angle: atan2 of sine and cosine (Warp's stock kernel takes acos of the cosine,
    # which loses half the digits near flat).
    cos_theta = wp.dot(n1, n2) * rcp_n1 * rcp_n2
    sin_theta = wp.dot(wp.cross(n2, n1), e_hat) * rcp_n1 * rcp_n2
    angle = wp.atan2(sin_theta, cos_theta)
    d1 = m1 * e_length
    d2 = m2 * e_length
    d3 = m1 * wp.dot(x1 - x4, e_hat) + m2 * wp.dot(x2 - x4, e_hat)
    d4 = m1 * wp.dot(x3 - x1, e_hat) + m2 * wp.dot(x3 - x2, e_hat)
    f_elastic = ke * (angle - rest[tid])
    f_damp = kd * (wp.dot(d1, v1) + wp.dot(d2, v2) + wp.dot(d3, v3) + wp.dot(d4, v4))
    f_total = 0.0 - e_length * (f_elastic + f_damp)
    wp.atomic_add(f, i, d1 * f_total)
    wp.atomic_add(f, j, d2 * f_total)
    wp.atomic_add(f, k, d3 * f_total)
    wp.atomic_add(f, l, d4 * f_total)

@wp.kernel
def eval_ground(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), ke: float, kd: float, mu: float,
                radius: float, f: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    n = wp.vec3(0.0, 1.0, 0.0)
    c = wp.min(wp.dot(n, x[tid]) - radius, 0.0)
    vn = wp.dot(n, v[tid])
    vt = v[tid] - n * vn
    fn = n * c * ke
    fd = n * wp.min(vn, 0.0) * kd
    # smooth Coulomb friction: |ft| <= mu |fn|, direction -vt, smoothed by vt / (|vt| + eps)
    ft = vt * (mu * c * ke / (wp.length(vt) + 1.0e-2))
    wp.atomic_sub(f, tid, fn + fd - ft)

@wp.kernel
def integrate(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3),
              inv_mass: wp.array(dtype=float), g: wp.vec3, dt: float,
              x_new: wp.array(dtype=wp.vec3), v_new: wp.array(dtype=wp.vec3)):
    tid = wp.tid()
    w = inv_mass[tid]
    v1 = v[tid] + (f[tid] * w + g * wp.step(-w)) * dt
    x_new[tid] = x[tid] + v1 * dt
    v_new[tid] = v1

@wp.kernel
def loss_kernel(x: wp.array(dtype=wp.vec3), x0: wp.array(dtype=wp.vec3), target: wp.vec3, scale: float,
                loss: wp.array(dtype=float)):
    tid = wp.tid()
    d = x[tid] - x0[tid] - target
    wp.atomic_add(loss, 0, wp.dot(d, d) * scale)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    wp.init()
    N, T = a.n, a.steps
    P, springs, rest, bends, inv_mass = build(N)
    dev = "cpu"
    ke_np = np.full(len(springs), 50.0, dtype=np.float32)
    x0 = wp.array(P, dtype=wp.vec3, device=dev, requires_grad=True)
    v0 = wp.zeros(N * N, dtype=wp.vec3, device=dev, requires_grad=True)
    sidx = wp.array(springs.flatten(), dtype=int, device=dev)
    srest = wp.array(rest, dtype=float, device=dev)
    ske = wp.array(ke_np, dtype=float, device=dev, requires_grad=True)
    bidx = wp.array(bends.flatten(), dtype=int, device=dev)
    brest = wp.zeros(len(bends), dtype=float, device=dev)
    im = wp.array(inv_mass, dtype=float, device=dev)
    g = wp.vec3(0.0, -9.8, 0.0)
    dt = 1.0e-3
    xs = [x0] + [wp.zeros(N * N, dtype=wp.vec3, device=dev, requires_grad=True) for _ in range(T)]
    vs = [v0] + [wp.zeros(N * N, dtype=wp.vec3, device=dev, requires_grad=True) for _ in range(T)]
    fs = [wp.zeros(N * N, dtype=wp.vec3, device=dev, requires_grad=True) for _ in range(T)]
    loss = wp.zeros(1, dtype=float, device=dev, requires_grad=True)

    def forward():
        for t in range(T):
            fs[t].zero_()
            wp.launch(eval_springs, dim=len(springs), inputs=[xs[t], vs[t], sidx, srest, ske, 0.1, fs[t]], device=dev)
            wp.launch(eval_bending, dim=len(bends), inputs=[xs[t], vs[t], bidx, brest, 0.01, 0.0, fs[t]], device=dev)
            wp.launch(eval_ground, dim=N * N, inputs=[xs[t], vs[t], 1.0e3, 1.0, 0.5, 0.01, fs[t]], device=dev)
            wp.launch(integrate, dim=N * N, inputs=[xs[t], vs[t], fs[t], im, g, dt, xs[t + 1], vs[t + 1]], device=dev)
        wp.launch(loss_kernel, dim=N * N, inputs=[xs[T], xs[0], wp.vec3(0.0, -0.1, 0.0), 1.0 / (N * N), loss], device=dev)

    # warm-up (compiles kernels)
    loss.zero_(); forward()
    fwd, both = [], []
    for _ in range(a.reps):
        loss.zero_()
        t0 = time.perf_counter(); forward(); wp.synchronize(); fwd.append(time.perf_counter() - t0)
    for _ in range(a.reps):
        loss.zero_()
        tape = wp.Tape()
        t0 = time.perf_counter()
        with tape:
            forward()
        tape.backward(loss)
        wp.synchronize()
        both.append(time.perf_counter() - t0)
        gv = v0.grad.numpy().copy(); gk = ske.grad.numpy().copy()
        tape.zero()
    print(json.dumps({"peer": "warp-cpu", "n": N, "particles": N * N, "springs": len(springs), "bends": len(bends),
                      "steps": T, "fwd_s_per_step": min(fwd) / T, "fwd_bwd_s_per_step": min(both) / T,
                      "loss": float(loss.numpy()[0]), "grad_v0_norm": float(np.linalg.norm(gv)),
                      "grad_ke_norm": float(np.linalg.norm(gk))}))

if __name__ == "__main__":
    main()
