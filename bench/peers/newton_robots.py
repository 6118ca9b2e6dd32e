"""Peer for the articulation benchmark: Newton's Featherstone solver on the CPU (Warp's CPU
backend) for the repository's robots (kernels/robots/): the 7-DoF arm (arm7.urdf, fixed base,
no contact) and the quadruped (ant.xml, free base, ground contact found by `Model.collide` at
each step by a `CollisionPipeline`). As adflex's `robots` bench: dt 1e-3 s, `--steps` steps from the same start
(q0, qd_i = 0.1 (i mod 5 - 2)), recorded on a `wp.Tape`, then the backward pass of the sum of
the final joint coordinates. Prints one JSON line per model and pass:
{"peer", "model", "what": "step" | "forward_backward", "us"}  (microseconds per step; best of
`--reps` rollouts).

Set up: python3 -m venv ~/.cache/newton-venv && ~/.cache/newton-venv/bin/pip install \
    -r bench/peers/requirements-newton.txt
The first run compiles Newton's kernels (minutes); later runs load them from Warp's cache.
"""
import argparse
import json
import pathlib
import time

import numpy as np
import warp as wp

wp.config.quiet = True
import newton  # noqa: E402

wp.config.log_level = 30  # warnings only: no line per module loaded

ROBOTS = pathlib.Path(__file__).resolve().parents[2] / "kernels" / "robots"


@wp.kernel
def total(q: wp.array(dtype=float), loss: wp.array(dtype=float)):
    t = wp.tid()
    wp.atomic_add(loss, 0, q[t])


def build(name):
    b = newton.ModelBuilder()
    if name == "arm7":
        b.add_urdf(str(ROBOTS / "arm7.urdf"), floating=False)
    else:
        b.add_mjcf(str(ROBOTS / "ant.xml"))
    return b.finalize(device="cpu", requires_grad=True)


def rollout(model, solver, pipeline, steps, backward):
    """Seconds for `steps` steps (and the backward pass if `backward`), and whether the
    gradient is finite. The states and the contacts' buffers are made before the clock starts
    (in Newton's favour: adflex's times include its allocations)."""
    states = [model.state(requires_grad=True) for _ in range(steps + 1)]
    qd0 = np.array([0.1 * (i % 5 - 2) for i in range(model.joint_dof_count)], dtype=np.float32)
    states[0].joint_qd.assign(qd0)
    newton.eval_fk(model, states[0].joint_q, states[0].joint_qd, states[0])
    control = model.control()
    contacts = [pipeline.contacts() for _ in range(steps)] if pipeline else [None] * steps
    loss = wp.zeros(1, dtype=float, device="cpu", requires_grad=True)
    tape = wp.Tape()
    t0 = time.perf_counter()
    with tape:
        for k in range(steps):
            states[k].clear_forces()
            if pipeline:
                pipeline.collide(states[k], contacts[k])
            solver.step(states[k], states[k + 1], control, contacts[k], 1e-3)
        wp.launch(total, dim=model.joint_coord_count, inputs=[states[-1].joint_q, loss],
                  device="cpu")
    if backward:
        tape.backward(loss)
    wp.synchronize()
    t = time.perf_counter() - t0
    finite = True
    if backward:
        finite = bool(np.isfinite(states[0].joint_qd.grad.numpy()).all())
    return t, finite


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--reps", type=int, default=5)
    a = ap.parse_args()
    peer = f"newton {newton.__version__} (warp {wp.__version__}, cpu, SolverFeatherstone)"
    for name in ["arm7", "quadruped"]:
        model = build(name)
        solver = newton.solvers.SolverFeatherstone(model)
        # The arm has no contact (as in adflex's model); the quadruped touches the ground.
        pipeline = newton.CollisionPipeline(model, requires_grad=True) if name != "arm7" else None
        rollout(model, solver, pipeline, 2, True)  # compile or load the kernels
        for what, backward in [("step", False), ("forward_backward", True)]:
            runs = [rollout(model, solver, pipeline, a.steps, backward) for _ in range(a.reps)]
            us = 1e6 * min(t for t, _ in runs) / a.steps
            print(json.dumps({"peer": peer, "model": name, "what": what, "us": us,
                              "gradient_finite": all(f for _, f in runs)}), flush=True)


if __name__ == "__main__":
    main()
