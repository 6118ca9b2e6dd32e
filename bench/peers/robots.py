"""Peers for the articulation benchmark: MuJoCo's mj_step, Pinocchio's
computeABADerivatives and computeRNEADerivatives on the repository's robots
(kernels/robots/), one thread. Timed from Python: the binding's call overhead is included.

Prints one JSON line per measurement:
{"peer", "model", "what", "us"}  (median of `--reps` runs of `--iters` calls, microseconds per call)

Set up: python3 -m venv ~/.cache/peers-venv && ~/.cache/peers-venv/bin/pip install -r requirements.txt
Run:    ~/.cache/peers-venv/bin/python robots.py
"""
import argparse
import json
import os
import pathlib
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import mujoco
import pinocchio as pin

ROBOTS = pathlib.Path(__file__).resolve().parents[2] / "kernels" / "robots"


def per_call(f, iters, reps):
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(iters):
            f()
        times.append((time.perf_counter() - t0) / iters)
    return 1e6 * float(np.median(times))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    for name, file in [("arm7", "arm7.urdf"), ("quadruped", "ant.xml")]:
        m = mujoco.MjModel.from_xml_path(str(ROBOTS / file))
        m.opt.timestep = 1e-3
        # The arm has no contact in either system; MuJoCo's Euler integrator, as adflex's step.
        m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
        d = mujoco.MjData(m)
        d.qvel[:] = 0.1 * rng.normal(size=m.nv)
        us = per_call(lambda: mujoco.mj_step(m, d), a.iters, a.reps)
        print(json.dumps({"peer": f"mujoco {mujoco.__version__}", "model": name,
                          "what": "mj_step", "us": us}), flush=True)
    model = pin.buildModelFromUrdf(str(ROBOTS / "arm7.urdf"))
    data = model.createData()
    q = pin.randomConfiguration(model)
    v = rng.normal(size=model.nv)
    tau = rng.normal(size=model.nv)
    us = per_call(lambda: pin.computeABADerivatives(model, data, q, v, tau), a.iters, a.reps)
    print(json.dumps({"peer": f"pinocchio {pin.__version__}", "model": "arm7",
                      "what": "computeABADerivatives", "us": us}), flush=True)
    us = per_call(lambda: pin.computeRNEADerivatives(model, data, q, v, tau), a.iters, a.reps)
    print(json.dumps({"peer": f"pinocchio {pin.__version__}", "model": "arm7",
                      "what": "computeRNEADerivatives", "us": us}), flush=True)
    us = per_call(lambda: pin.aba(model, data, q, v, tau), a.iters, a.reps)
    print(json.dumps({"peer": f"pinocchio {pin.__version__}", "model": "arm7",
                      "what": "aba", "us": us}), flush=True)


if __name__ == "__main__":
    main()
