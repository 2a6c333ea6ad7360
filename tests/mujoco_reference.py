"""MuJoCo C's RK4 runs that the MJCF import and export tests hold abd_gym against."""
import numpy as np

REFERENCE_DT = 1e-4  # MuJoCo RK4 step of the reference [s]


def rk4_qpos(m, qpos, qvel, ctrl=None, duration=1.0, each_step=None):
    """(worlds, nq) qpos after ``duration`` [s] of MuJoCo RK4 at REFERENCE_DT from each state
    (``m`` is set to RK4 at that step); ``each_step(d)`` is called after every step."""
    import mujoco

    m.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    m.opt.timestep = REFERENCE_DT
    d, out = mujoco.MjData(m), []
    for q, v in zip(qpos, qvel):
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = q, v
        if ctrl is not None:
            d.ctrl[:] = ctrl
        for _ in range(round(duration / REFERENCE_DT)):
            mujoco.mj_step(m, d)
            if each_step is not None:
                each_step(d)
        out.append(d.qpos.copy())
    return np.array(out)
