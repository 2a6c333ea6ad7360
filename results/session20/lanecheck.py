"""Every registered task's scene on the lane-split step (8 CPU fibers; 16 lanes in 2 groups) against one
thread per world, float64, 100 env steps of random actions from the task's initial states (session 20):

    PYTHONPATH=. python results/session20/lanecheck.py [CartPole-v0,FourBar-v0,...]
"""
import numpy as np, warp as wp, time, sys
wp.config.quiet=True
wp.config.enable_cpu_blocks = True
import gymnasium as gym
import abd_gym as ag
from abd_gym.registration import TASKS
tasks = sys.argv[1].split(",") if len(sys.argv) > 1 else list(TASKS)
for task in tasks:
    env = gym.make_vec(f"abd_gym/{task}", num_envs=1, vectorization_mode="vector_entry_point").unwrapped
    sc = env.scene
    W = 4
    rng = np.random.default_rng(5)
    x, xd = env._initial_state(W, rng, {})
    ctrls = [rng.uniform(-1, 1, (W, env.action_dim)) for _ in range(100)]
    res = {}
    for key, kw in (("global", dict(scratch="global")), ("lanes8", dict(scratch="lanes", block_dim=8)),
                    ("lanes16g2", dict(scratch="lanes", block_dim=16, lane_groups=2))):
        t = time.time()
        try:
            sim = ag.Simulator(sc, num_worlds=W, dt=env.dt, dtype="float64", **kw)
        except Exception as e:
            print(task, key, "refused", e); continue
        sim.set_joint_state(x, xd)
        traj, its = [], []
        for k in range(100):
            a = ctrls[k]
            c = np.concatenate([a * env._max_effort[:env.action_dim], np.zeros((W, len(sc.drives) - env.action_dim))], 1)
            sim.set_controls(c)
            sim.step(env.frame_skip)
            traj.append(sim.joint_coordinates()); its.append(sim.newton_iterations())
        res[key] = (np.array(traj), np.array(its), sim.failed_worlds())
        print(f"{task} {key}: failed {res[key][2]} mean its {res[key][1].mean():.2f} ({time.time()-t:.0f}s)", flush=True)
    for key in res:
        if key != "global":
            d = np.abs(np.angle(np.exp(1j * (res[key][0] - res["global"][0])))).max()
            print(f"  {key} vs global: max coord diff {d:.2e}, iterations equal {np.array_equal(res[key][1], res['global'][1])}")
