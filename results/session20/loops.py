"""Physics of the closed-loop tasks' scenes with each scratch layout at several world counts
(session 20; run from the repository root with it on PYTHONPATH):

    python results/session20/loops.py cuda:0 FourBar-v0,SliderCrank-v0 1024,2048,4096 auto,lanes 200

Each task's scene and its ``_initial_state`` (consistent closed-loop states), fixed random torques
within the drive's limit, best of 3 runs of ``steps`` steps; the largest joint-coordinate
difference of each layout's final state against the first layout's.  Writes $OUT/loops.json."""
import json, os, sys, time
import numpy as np, warp as wp, gymnasium as gym
import abd_gym  # noqa
from abd_gym.simulator import Simulator

dev = sys.argv[1]
tasks = sys.argv[2].split(",")
worlds = [int(w) for w in sys.argv[3].split(",")]
scratches = sys.argv[4].split(",")
steps = int(sys.argv[5]) if len(sys.argv) > 5 else 200
rows = []
for task in tasks:
    env = gym.make_vec(f"abd_gym/{task}", num_envs=1, vectorization_mode="vector_entry_point", device=dev)
    u = env.unwrapped
    scene = u.scene
    for W in worlds:
        rng = np.random.default_rng(0)
        x, xd = u._initial_state(W, rng, {})
        ctrl = rng.uniform(-1, 1, size=(W, len(scene.drives))) * u._max_effort
        finals = {}
        for scratch in scratches:
            try:
                sim = Simulator(scene, num_worlds=W, dt=u.dt, device=dev, scratch=None if scratch == "auto" else scratch)
            except Exception as e:  # noqa
                print(task, W, scratch, "refused:", e, flush=True)
                continue
            sim.set_joint_state(x, xd)
            sim.set_controls(ctrl)
            k = sim.solver.steps_per_launch if sim.solver.multi_step else 1
            n = -(-steps // k) * k
            sim.step(3)
            sim.step(k)
            wp.synchronize_device(sim.device)
            best = 1e9
            for rep in range(3):
                sim.set_joint_state(x, xd)
                wp.synchronize_device(sim.device)
                t0 = time.perf_counter()
                for _ in range(n // k):
                    sim.step(k)
                wp.synchronize_device(sim.device)
                best = min(best, time.perf_counter() - t0)
            coords = sim.joint_coordinates()
            finals[scratch] = coords
            row = dict(task=task, worlds=W, scratch=sim.solver.scratch, asked=scratch, block_dim=sim.solver.block_dim,
                       lane_groups=sim.solver.lane_groups, world_steps_per_second=W * n / best,
                       us_per_step=best / n * 1e6, iterations=float(sim.newton_iterations().mean()),
                       failed=int(sim.failed_worlds().size), residual=float(sim.joint_violation().max()))
            if len(finals) > 1:
                ref = next(iter(finals.values()))
                row["max_coord_diff_vs_first"] = float(np.nanmax(np.abs(coords - ref)))
            rows.append(row)
            print(json.dumps(row), flush=True)
out = os.environ.get("OUT", ".")
json.dump(rows, open(os.path.join(out, "loops.json"), "w"), indent=1)
