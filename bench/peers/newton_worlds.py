"""Peer for the many-worlds benchmark: Newton's worlds on the CPU (Warp's CPU backend).

W cart-poles (kernels/robots/cartpole.urdf) replicated as W worlds (`ModelBuilder.replicate`),
SolverFeatherstone, dt 1/240 s, a force on each cart, `--steps` steps recorded on a
`wp.Tape`, then the backward pass of the sum of the final joint coordinates squared (as
adflex's bench). Prints one JSON line per case:
{"peer", "worlds", "steps", "forward_us_per_world_step", "forward_backward_us_per_world_step"}

Set up: python3 -m venv ~/.cache/newton-venv && ~/.cache/newton-venv/bin/pip install newton==1.8.0
(it brings warp-lang 1.19.0). The first run compiles Newton's kernels (minutes), later runs
load them from Warp's cache.
"""
import argparse
import json
import pathlib
import time

import numpy as np
import warp as wp

wp.config.quiet = True
import newton  # noqa: E402

ROBOTS = pathlib.Path(__file__).resolve().parents[2] / "kernels" / "robots"


@wp.kernel
def squares(q: wp.array(dtype=float), loss: wp.array(dtype=float)):
    t = wp.tid()
    wp.atomic_add(loss, 0, q[t] * q[t])


def case(worlds, steps):
    cart = newton.ModelBuilder()
    cart.add_urdf(str(ROBOTS / "cartpole.urdf"), floating=False)
    b = newton.ModelBuilder()
    b.replicate(cart, worlds)
    model = b.finalize(device="cpu", requires_grad=True)
    solver = newton.solvers.SolverFeatherstone(model)
    q0 = model.joint_q.numpy()
    q0[1::2] = 0.1 + 0.1 * (np.arange(worlds) % 8)
    model.joint_q.assign(q0)
    states = [model.state(requires_grad=True) for _ in range(steps + 1)]
    newton.eval_fk(model, model.joint_q, model.joint_qd, states[0])
    controls = []
    for k in range(steps):
        c = model.control(requires_grad=True)
        f = np.zeros(model.joint_dof_count, dtype=np.float32)
        f[0::2] = 0.5 * np.sin(0.01 * k + np.arange(worlds))
        c.joint_f.assign(f)
        controls.append(c)
    loss = wp.zeros(1, dtype=float, device="cpu", requires_grad=True)
    t0 = time.perf_counter()
    tape = wp.Tape()
    with tape:
        for k in range(steps):
            states[k].clear_forces()
            solver.step(states[k], states[k + 1], controls[k], None, 1.0 / 240.0)
        wp.launch(squares, dim=model.joint_coord_count,
                  inputs=[states[-1].joint_q, loss], device="cpu")
    wp.synchronize()
    t1 = time.perf_counter()
    tape.backward(loss)
    wp.synchronize()
    t2 = time.perf_counter()
    g = controls[0].joint_f.grad.numpy()
    return (1e6 * (t1 - t0) / (worlds * steps), 1e6 * (t2 - t0) / (worlds * steps),
            bool(np.isfinite(g).all()))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=960)
    a = ap.parse_args()
    for worlds in [1, a.worlds]:
        fwd, both, finite = case(worlds, a.steps)
        print(json.dumps({"peer": f"newton {newton.__version__} (warp {wp.__version__}, cpu)",
                          "worlds": worlds, "steps": a.steps,
                          "forward_us_per_world_step": fwd,
                          "forward_backward_us_per_world_step": both,
                          "gradient_finite": finite}), flush=True)


if __name__ == "__main__":
    main()
