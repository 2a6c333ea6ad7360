"""An imported model's motion against MuJoCo's own: ``compare_with_mujoco``.

The check an MJCF/URDF import deserves before a task is built on it (docs/mjcf_task.md): the same
states stepped by abd_gym and by MuJoCo itself, with MuJoCo's RK4 at a step far below abd_gym's
(1e-4 s by default) as the reference, and the qpos difference at every abd_gym step.  Halving
``dt`` divides a faithful import's difference by about four (BDF2's second order); a difference
that does not shrink points at something the import maps only approximately (docs/mjcf.md), or at
a joint limit, where MuJoCo's soft limit and abd_gym's cubic one stop a joint differently.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from ..sim.scene import Scene
from ..sim.simulator import Simulator
from .importer import load

REFERENCE_DT = 1e-4  # MuJoCo's RK4 step of the reference [s]


@dataclass
class MujocoComparison:
    """``compare_with_mujoco``'s result.  ``times`` (T,) [s] after each abd_gym step; ``errors``
    (T, N): the largest |qpos difference| over the compared joints, per step and world [rad or m];
    ``joint_names`` the compared joints (the scene's, but those that close loops, which have no
    qpos); ``qpos`` and ``reference`` (N, joints): the last step's qpos of abd_gym and of MuJoCo."""

    times: np.ndarray
    errors: np.ndarray
    joint_names: list
    qpos: np.ndarray
    reference: np.ndarray

    @property
    def max_error(self) -> float:
        """The largest |qpos difference| over every step, world and joint [rad or m]."""
        return float(self.errors.max()) if self.errors.size else 0.0

    @property
    def final_error(self) -> float:
        """The largest |qpos difference| at the last step [rad or m]."""
        return float(self.errors[-1].max()) if self.errors.size else 0.0


def compare_with_mujoco(source, states, seconds: float = 1.0, dt: float = 0.002, *, ctrl=None,
                        dtype: str = "float64", integrator: str = "bdf2", reference_dt: float = REFERENCE_DT,
                        exclude=(), ignore_contacts: bool = False) -> MujocoComparison:  # fmt: skip
    """Step ``source`` in abd_gym and in MuJoCo from the same ``states`` for ``seconds`` [s] and
    return their qpos differences (MujocoComparison).

    ``source``: what ``Scene.from_mjcf`` reads (a path to an MJCF or URDF file, an XML string, a
    ``mujoco.MjModel``; ``exclude`` and ``ignore_contacts`` are passed on), or a scene that
    ``Scene.from_mjcf`` / ``from_urdf`` made (its ``imported.model``; the scene itself is stepped).
    ``states``: (qpos, qvel) in MuJoCo's layout, (nq,) and (nv,) or one row per world (N, nq) and
    (N, nv); the worlds are stepped together.  ``ctrl``: MuJoCo controls held constant, (nu,) or
    (N, nu) (abd_gym's drive inputs are ``imported.ctrl_scale`` · ctrl); default none.
    abd_gym steps by ``dt`` with ``dtype`` and ``integrator``; MuJoCo by RK4 at ``reference_dt``,
    which must divide ``dt``.  Needs the ``mujoco`` package (``pip install "abd-gym[mjcf]"``).
    """
    import mujoco

    scene = source if isinstance(source, Scene) else Scene.from_mjcf(source, exclude=exclude, ignore_contacts=ignore_contacts)
    info = scene.imported
    if info is None or info.model is None:
        raise ValueError("compare_with_mujoco needs an MJCF/URDF model, or a scene made by Scene.from_mjcf or from_urdf")
    m = load(info.model)
    substeps = round(dt / reference_dt)
    if not (dt > 0 and substeps >= 1 and abs(substeps * reference_dt - dt) <= 1e-9 * dt):
        raise ValueError(f"reference_dt {reference_dt} must divide dt {dt}")
    steps = round(seconds / dt)
    if steps < 1:
        raise ValueError(f"seconds must be at least one step of dt {dt}, got {seconds}")

    # the scene's joints that have a qpos (the loop-closing ones do not), and where they sit in MuJoCo's
    names = [n for n in info.joint_names if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) >= 0]
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in names]
    qadr, vadr = m.jnt_qposadr[ids], m.jnt_dofadr[ids]
    qpos = np.atleast_2d(np.asarray(states[0], dtype=np.float64))
    qvel = np.atleast_2d(np.asarray(states[1], dtype=np.float64))
    N = qpos.shape[0]
    if qpos.shape != (N, m.nq) or qvel.shape != (N, m.nv):
        raise ValueError(f"states must be qpos ({m.nq},) or (N, {m.nq}) and qvel ({m.nv},) or (N, {m.nv}), "
                         f"got {np.shape(states[0])} and {np.shape(states[1])}")  # fmt: skip
    u = None if ctrl is None else np.broadcast_to(np.asarray(ctrl, dtype=np.float64), (N, m.nu))

    nj = scene.num_joints
    sim = Simulator(scene, num_worlds=N, dt=dt, dtype=dtype, integrator=integrator)
    x, xd = np.zeros((N, nj)), np.zeros((N, nj))
    x[:, : len(names)], xd[:, : len(names)] = qpos[:, qadr], qvel[:, vadr]
    sim.set_joint_state(x, xd)
    if u is not None:
        sim.set_controls(u * info.ctrl_scale)

    ref = copy.deepcopy(m)  # the reference's integrator and step, not the model's
    ref.opt.integrator, ref.opt.timestep = mujoco.mjtIntegrator.mjINT_RK4, reference_dt
    datas = [mujoco.MjData(ref) for _ in range(N)]
    for w, d in enumerate(datas):
        d.qpos[:], d.qvel[:] = qpos[w], qvel[w]
        if u is not None:
            d.ctrl[:] = u[w]
    errors = np.zeros((steps, N))
    for k in range(steps):
        sim.step()
        ours = sim.joint_angles_unwrapped()[:, : len(names)]
        for w, d in enumerate(datas):
            mujoco.mj_step(ref, d, nstep=substeps)
            errors[k, w] = np.abs(ours[w] - d.qpos[qadr]).max(initial=0.0)
    reference = np.array([d.qpos[qadr] for d in datas])
    return MujocoComparison(times=dt * np.arange(1, steps + 1), errors=errors, joint_names=names, qpos=ours,
                            reference=reference)  # fmt: skip

