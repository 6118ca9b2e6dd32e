"""Peer for the many-worlds benchmark: MuJoCo's batched rollout (`mujoco.rollout`, C++ on a
thread pool) of W cartpoles (kernels/robots/cartpole.urdf), Euler integrator, dt 1/240 s,
a force on the cart, forward only (MuJoCo has no gradients).

Prints one JSON line per case: {"peer", "worlds", "threads", "steps", "us_per_world_step"}
(best of `--reps` runs).

Set up: python3 -m venv ~/.cache/peers-venv && ~/.cache/peers-venv/bin/pip install -r requirements.txt
Run:    ~/.cache/peers-venv/bin/python worlds.py --worlds 1024 --steps 960
"""
import argparse
import json
import os
import pathlib
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import mujoco
from mujoco import rollout

ROBOTS = pathlib.Path(__file__).resolve().parents[2] / "kernels" / "robots"


def case(m, worlds, threads, steps, reps):
    datas = [mujoco.MjData(m) for _ in range(threads)]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    d = mujoco.MjData(m)
    init = np.empty((worlds, mujoco.mj_stateSize(m, spec)))
    for w in range(worlds):
        mujoco.mj_resetData(m, d)
        d.qpos[1] = 0.1 + 0.1 * (w % 8)
        mujoco.mj_getState(m, d, init[w], spec)
    k = np.arange(steps)
    control = np.zeros((worlds, steps, m.nv))
    for w in range(worlds):
        control[w, :, 0] = 0.5 * np.sin(0.01 * k + w)
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        rollout.rollout([m] * worlds, datas, init, control,
                        control_spec=mujoco.mjtState.mjSTATE_QFRC_APPLIED)
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / (worlds * steps)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=960)
    ap.add_argument("--reps", type=int, default=3)
    a = ap.parse_args()
    m = mujoco.MjModel.from_xml_path(str(ROBOTS / "cartpole.urdf"))
    m.opt.timestep = 1.0 / 240.0
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    for worlds, threads in [(1, 1), (a.worlds, 1), (a.worlds, 2)]:
        us = case(m, worlds, threads, a.steps, a.reps)
        print(json.dumps({"peer": f"mujoco {mujoco.__version__} rollout", "worlds": worlds,
                          "threads": threads, "steps": a.steps, "us_per_world_step": us}),
              flush=True)


if __name__ == "__main__":
    main()
