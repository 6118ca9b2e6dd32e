"""Reference dynamics of adflex's robot models from Pinocchio and MuJoCo.

Writes robots.json beside this script: for each model, random states and the mass matrix,
the bias forces, the forward dynamics and (Pinocchio) the derivatives of the forward dynamics,
all in adflex's conventions (see `adflex_kernels::articulation`): quaternions x, y, z, w; a
free joint's velocity is the linear then the angular velocity, both in the link frame
(Pinocchio's); derivatives with respect to q in the tangent space.

Run it with the repository's script (it makes the pinned venv):
    kernels/tests/references/regenerate.sh
"""
import json
import pathlib

import numpy as np
import pinocchio as pin
import mujoco

HERE = pathlib.Path(__file__).resolve().parent
ROBOTS = HERE.parent.parent / "robots"
RNG = np.random.default_rng(20261126)
# The external wrenches' draws, apart so that the other references keep their states.
WRENCH_RNG = np.random.default_rng(20261129)
# The rollouts with limits', likewise.
LIMIT_RNG = np.random.default_rng(20261207)


def quat_xyzw(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def random_state(joints, rng, neutral=False):
    """A state in adflex's coordinates: per joint (kind, nq, nv) in model order."""
    q, v = [], []
    for kind in joints:
        if kind in ("revolute", "prismatic"):
            q.append(0.0 if neutral else rng.uniform(-1.2, 1.2))
            v.append(0.0 if neutral else rng.normal())
        elif kind == "ball":
            q.extend([0, 0, 0, 1] if neutral else quat_xyzw(rng))
            v.extend([0, 0, 0] if neutral else rng.normal(size=3))
        elif kind == "free":
            q.extend([0, 0, 0] if neutral else rng.normal(size=3))
            q.extend([0, 0, 0, 1] if neutral else quat_xyzw(rng))
            v.extend([0] * 6 if neutral else rng.normal(size=6))
    return np.array(q, float), np.array(v, float)


def pin_kind(jm):
    name = jm.shortname()
    if name == "JointModelFreeFlyer":
        return "free"
    if name == "JointModelSpherical":
        return "ball"
    if name.startswith("JointModelP"):
        return "prismatic"
    if name.startswith("JointModelR"):
        return "revolute"
    raise ValueError(name)


def to_pin_q(model, q_adflex):
    """adflex's q to Pinocchio's (continuous joints are (cos, sin) there)."""
    out, k = [], 0
    for jm in model.joints[1:]:
        name = jm.shortname()
        if name.startswith("JointModelRUB"):
            out.extend([np.cos(q_adflex[k]), np.sin(q_adflex[k])])
            k += 1
        else:
            n = jm.nq
            out.extend(q_adflex[k:k + n])
            k += n
    return np.array(out)


def pinocchio_model(file, floating):
    path = str(ROBOTS / file)
    if file.endswith(".urdf"):
        if floating:
            return pin.buildModelFromUrdf(path, pin.JointModelFreeFlyer())
        return pin.buildModelFromUrdf(path)
    return pin.buildModelFromMJCF(path)


def pinocchio_reference(file, floating, n_random=4):
    model = pinocchio_model(file, floating)
    data = model.createData()
    kinds = [pin_kind(jm) for jm in model.joints[1:]]
    names = list(model.names[1:])
    states = []
    for s in range(n_random + 1):
        q, v = random_state(kinds, RNG, neutral=(s == 0))
        tau = np.zeros(model.nv) if s == 0 else RNG.normal(size=model.nv)
        qp = to_pin_q(model, q)
        m = pin.crba(model, data, qp)
        m = np.triu(m) + np.triu(m, 1).T
        bias = pin.rnea(model, data, qp, v, np.zeros(model.nv))
        qdd = pin.aba(model, data, qp, v, tau)
        pin.computeABADerivatives(model, data, qp, v, tau)
        state = {
            "q": q.tolist(), "qd": v.tolist(), "tau": tau.tolist(),
            "mass_matrix": m.tolist(), "bias": bias.tolist(), "qdd": qdd.tolist(),
            "dqdd_dq": np.array(data.ddq_dq).tolist(),
            "dqdd_dqd": np.array(data.ddq_dv).tolist(),
            "dqdd_dtau": (np.triu(data.Minv) + np.triu(data.Minv, 1).T).tolist(),
        }
        states.append(rnea_derivatives(model, qp, v, qdd, state))
    return {
        "file": file, "floating_base": floating, "reference": f"pinocchio {pin.__version__}",
        "joints": [{"name": n, "kind": k} for n, k in zip(names, kinds)],
        "states": states,
    }


def pinocchio_derivatives_agree(pm, q, v, tau, dq, dv, h=1e-6):
    """Pinocchio's ABA derivatives against its own central differences. They disagree (by
    about 20% with Pinocchio 4.1) for a body with several joints, which Pinocchio reads from
    MJCF as a composite joint; such references are left out rather than stored wrong."""
    pd = pm.createData()
    worst = 0.0
    for j in range(pm.nv):
        e = np.zeros(pm.nv)
        e[j] = h
        fv = (pin.aba(pm, pd, q, v + e, tau) - pin.aba(pm, pd, q, v - e, tau)) / (2 * h)
        fq = (pin.aba(pm, pd, pin.integrate(pm, q, e), v, tau)
              - pin.aba(pm, pd, pin.integrate(pm, q, -e), v, tau)) / (2 * h)
        worst = max(worst, np.abs(fv - dv[:, j]).max() / max(1, np.abs(dv).max()),
                    np.abs(fq - dq[:, j]).max() / max(1, np.abs(dq).max()))
    return worst < 1e-5


def rnea_derivatives(pm, q, v, qdd, state):
    """`state` with Pinocchio's `d tau / d q` and `d tau / d v` at `(q, v, qdd)`."""
    pd = pm.createData()  # alive while the results, views of it, are copied
    dq, dv, _ = pin.computeRNEADerivatives(pm, pd, q, v, qdd)
    state["dtau_dq"] = np.array(dq).tolist()
    state["dtau_dqd"] = np.array(dv).tolist()
    return state


def aba_derivatives(pm, pd, q, v, tau):
    """Pinocchio's `d qdd / d q` and `d qdd / d v` (left in `pd` too)."""
    pin.computeABADerivatives(pm, pd, q, v, tau)
    return np.array(pd.ddq_dq), np.array(pd.ddq_dv)


def to_mujoco(model, kinds, q, v):
    """adflex's (q, qd) to MuJoCo's (qpos, qvel), and T with qvel = T qd: quaternions w first,
    a free joint's linear velocity in the world frame."""
    qm, T = q.copy(), np.eye(model.nv)
    for j, kind in enumerate(kinds):
        a, d = model.jnt_qposadr[j], model.jnt_dofadr[j]
        if kind == "ball":
            qm[a:a + 4] = np.roll(q[a:a + 4], 1)
        if kind == "free":
            qm[a + 3:a + 7] = np.roll(q[a + 3:a + 7], 1)
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, qm[a + 3:a + 7])
            T[d:d + 3, d:d + 3] = R.reshape(3, 3)
    return qm, T @ v, T


def from_mujoco(model, kinds, qm, vm):
    """MuJoCo's (qpos, qvel) to adflex's (q, qd)."""
    q, v = qm.copy(), vm.copy()
    for j, kind in enumerate(kinds):
        a, d = model.jnt_qposadr[j], model.jnt_dofadr[j]
        if kind == "ball":
            q[a:a + 4] = np.roll(qm[a:a + 4], -1)
        if kind == "free":
            q[a + 3:a + 7] = np.roll(qm[a + 3:a + 7], -1)
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, qm[a + 3:a + 7])
            v[d:d + 3] = R.reshape(3, 3).T @ vm[d:d + 3]
    return q, v


INTEGRATORS = {"Euler": mujoco.mjtIntegrator.mjINT_EULER,
               "RK4": mujoco.mjtIntegrator.mjINT_RK4,
               "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}


def run_rollout(model, data, kinds, integrator, q, v, ctrl, steps):
    """mj_step `steps` times by `integrator` from (q, v) in adflex's terms with the controls
    `ctrl`, at the file's time step or 2 ms if shorter: the states every 50 steps, in adflex's
    terms, and the number of steps that had a constraint."""
    model.opt.timestep = min(model.opt.timestep, 0.002)
    model.opt.integrator = int(INTEGRATORS[integrator])
    mujoco.mj_resetData(model, data)
    data.qpos[:], data.qvel[:], _ = to_mujoco(model, kinds, q, v)
    data.ctrl[:] = ctrl
    out = {"integrator": integrator, "dt": model.opt.timestep, "q0": q.tolist(), "qd0": v.tolist(), "ctrl": ctrl,
           "every": 50, "q": [], "qd": []}
    constrained = 0
    for k in range(1, steps + 1):
        mujoco.mj_step(model, data)
        if data.warning[int(mujoco.mjtWarning.mjWARN_BADQACC)].number:
            raise RuntimeError("the reference rollout blew up")
        constrained += int(data.nefc > 0)
        if k % 50 == 0:
            qa, va = from_mujoco(model, kinds, data.qpos, data.qvel)
            out["q"].append(qa.tolist())
            out["qd"].append(va.tolist())
    return out, constrained


def mujoco_rollout(model, data, kinds, integrator, steps=200):
    """mj_step by `integrator` ("Euler", "RK4" or "implicitfast") from a random state with random
    controls (some outside their range, to check the clamping), contact and limits off (the legs
    of gym's ant, driven hard without limits, blow up at its 10 ms step: `run_rollout` takes 2
    ms)."""
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    q, v = random_state(kinds, RNG)
    ctrl = []
    for u in range(model.nu):
        lo, hi = model.actuator_ctrlrange[u] if model.actuator_ctrllimited[u] else (-1, 1)
        ctrl.append(RNG.uniform(lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo)))
    return run_rollout(model, data, kinds, integrator, q, v, ctrl, steps)[0]


def mujoco_limit_rollout(file, kinds, integrator, steps=200):
    """As `mujoco_rollout`, with the joint limits on (contact still off): every limited joint
    starts up to 5% of its range past one of its limits, moving into it, under gravity and
    random controls within their ranges. MuJoCo's solver runs to convergence (tolerance
    1e-15), so the soft constraints' forces are its exact optimum. Also the number of steps
    that had an active limit."""
    model = mujoco.MjModel.from_xml_path(str(ROBOTS / file))
    data = mujoco.MjData(model)
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    model.opt.tolerance = 1e-15
    model.opt.iterations = 1000
    q, v = random_state(kinds, LIMIT_RNG)
    for j, kind in enumerate(kinds):
        if kind in ("revolute", "prismatic") and model.jnt_limited[j]:
            lo, hi = model.jnt_range[j]
            a, d = model.jnt_qposadr[j], model.jnt_dofadr[j]
            past = LIMIT_RNG.uniform(0, 0.05) * (hi - lo)
            if LIMIT_RNG.uniform() < 0.5:
                q[a], v[d] = lo - past, -abs(v[d])
            else:
                q[a], v[d] = hi + past, abs(v[d])
    ctrl = []
    for u in range(model.nu):
        lo, hi = model.actuator_ctrlrange[u] if model.actuator_ctrllimited[u] else (-1, 1)
        ctrl.append(LIMIT_RNG.uniform(lo, hi))
    out, constrained = run_rollout(model, data, kinds, integrator, q, v, ctrl, steps)
    out["steps_with_limits"] = constrained
    return out


def wrench_reference(model, data, T, tdot):
    """MuJoCo's acceleration (in adflex's velocities) at the state in `data` with no joint
    torque, no control, contact, limits and equality constraints off, and a random wrench
    (xfrc_applied: a force at the centre of mass and a torque, world frame) on every named
    body that has a joint: with qvel = T qd, qacc = T qdd + Tdot qd."""
    bodies = [b for b in range(1, model.nbody) if model.body_jntnum[b] > 0
              and mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)]
    wrench = WRENCH_RNG.normal(size=(len(bodies), 6))
    flags = model.opt.disableflags
    for bit in ["mjDSBL_CONTACT", "mjDSBL_LIMIT", "mjDSBL_EQUALITY"]:
        model.opt.disableflags |= int(getattr(mujoco.mjtDisableBit, bit))
    data.xfrc_applied[:] = 0
    for b, w in zip(bodies, wrench):
        data.xfrc_applied[b] = w
    mujoco.mj_forward(model, data)
    qdd = np.linalg.solve(T, data.qacc - tdot)
    data.xfrc_applied[:] = 0
    model.opt.disableflags = flags
    return {"bodies": [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in bodies],
            "wrench": wrench.tolist(), "qdd": qdd.tolist()}


def mujoco_reference(file, n_random=4):
    """M, bias and qacc from MuJoCo (no contact), converted to adflex's conventions."""
    model = mujoco.MjModel.from_xml_path(str(ROBOTS / file))
    data = mujoco.MjData(model)
    kinds, names = [], []
    for j in range(model.njnt):
        t = model.jnt_type[j]
        kinds.append({int(mujoco.mjtJoint.mjJNT_FREE): "free",
                      int(mujoco.mjtJoint.mjJNT_BALL): "ball",
                      int(mujoco.mjtJoint.mjJNT_SLIDE): "prismatic",
                      int(mujoco.mjtJoint.mjJNT_HINGE): "revolute"}[int(t)])
        names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j))
    states = []
    for s in range(n_random + 1):
        q, v = random_state(kinds, RNG, neutral=(s == 0))
        tau = np.zeros(model.nv) if s == 0 else RNG.normal(size=model.nv)
        qm, vm, T = to_mujoco(model, kinds, q, v)
        data.qpos[:] = qm
        data.qvel[:] = vm
        data.qfrc_applied[:] = 0
        data.ctrl[:] = 0
        mujoco.mj_forward(model, data)
        m = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, m)
        c = data.qfrc_bias.copy()
        # qd_mj = T qd: M_a = T^T M T, c_a = T^T (c + M Tdot qd), Tdot qd = R (w x v_local).
        tdot = np.zeros(model.nv)
        for j, kind in enumerate(kinds):
            if kind == "free":
                d = model.jnt_dofadr[j]
                tdot[d:d + 3] = T[d:d + 3, d:d + 3] @ np.cross(v[d + 3:d + 6], v[d:d + 3])
        ma = T.T @ m @ T
        ca = T.T @ (c + m @ tdot)
        qdd = np.linalg.solve(ma, tau - ca)
        state = {"q": q.tolist(), "qd": v.tolist(), "tau": tau.tolist(),
                 "mass_matrix": ma.tolist(), "bias": ca.tolist(), "qdd": qdd.tolist(),
                 # Joint springs and damping (MuJoCo's qfrc_passive), in adflex's velocities.
                 "passive": (T.T @ data.qfrc_passive).tolist()}
        if s > 0:
            state["link_wrench"] = wrench_reference(model, data, T, tdot)
        # The derivatives from Pinocchio's reading of the same file, once its dynamics are
        # checked against MuJoCo's at this state. Pinocchio's MJCF reader does not read
        # everything MuJoCo's does (e.g. `ref`, `settotalmass`): a file it reads otherwise
        # gets no derivative references.
        pm = pinocchio_model(file, False)
        pd = pm.createData()
        same = pm.nq == model.nq and pm.nv == model.nv
        if same:
            mp = pin.crba(pm, pd, q)
            mp = np.triu(mp) + np.triu(mp, 1).T
            same = (np.abs(mp - ma).max() < 1e-12 * np.abs(ma).max()
                    and np.abs(pin.aba(pm, pd, q, v, tau) - qdd).max()
                    < 1e-10 * max(1, np.abs(qdd).max()))
        if not same:
            print(f"{file}: Pinocchio reads it otherwise than MuJoCo; no derivatives")
        elif pinocchio_derivatives_agree(pm, q, v, tau, *aba_derivatives(pm, pd, q, v, tau)):
            dq, dv = np.array(pd.ddq_dq), np.array(pd.ddq_dv)
            state["dqdd_dq"] = dq.tolist()
            state["dqdd_dqd"] = dv.tolist()
            state["dqdd_dtau"] = (np.triu(pd.Minv) + np.triu(pd.Minv, 1).T).tolist()
            rnea_derivatives(pm, q, v, qdd, state)
        states.append(state)
    return {
        "file": file, "floating_base": False,
        "reference": f"mujoco {mujoco.__version__}, pinocchio {pin.__version__}",
        "joints": [{"name": n, "kind": k} for n, k in zip(names, kinds)],
        "states": states,
        # Every integrator adflex offers; implicitfast needs the fluid's velocity derivative,
        # which adflex does not compute (it refuses the pair).
        "rollouts": [mujoco_rollout(model, data, kinds, i) for i in ["Euler", "RK4", "implicitfast"]
                     if i != "implicitfast" or (model.opt.density == 0 and model.opt.viscosity == 0)],
        "body_mass": model.body_mass[1:].tolist(),
        # The same with the joint limits on (MuJoCo's soft constraints).
        "limit_rollouts": [mujoco_limit_rollout(file, kinds, i) for i in ["Euler", "RK4", "implicitfast"]
                           if model.jnt_limited.any()
                           and (i != "implicitfast" or (model.opt.density == 0 and model.opt.viscosity == 0))],
    }


def main():
    models = [
        pinocchio_reference("cartpole.urdf", False),
        pinocchio_reference("arm7.urdf", False),
        pinocchio_reference("quadruped.urdf", True),
    ]
    for f in sorted(ROBOTS.glob("*.xml")):
        models.append(mujoco_reference(f.name))
    out = {"generated_by": "kernels/tests/references/robots.py", "models": models}
    (HERE / "robots.json").write_text(json.dumps(out, indent=1) + "\n")
    print("wrote", HERE / "robots.json", [m["file"] for m in models])


if __name__ == "__main__":
    main()
