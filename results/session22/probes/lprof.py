import os, sys, numpy as np, torch, gymnasium as gym
from line_profiler import LineProfiler
import abd_gym  # noqa
from abd_gym.vector_env import ABDVectorEnv
from abd_gym.autoreset import NextEpisodes
N, TASK = int(sys.argv[1]), sys.argv[2]
rng = np.random.default_rng(0)
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device=os.environ.get("DEV", "cuda:0"), backend="torch")
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device=os.environ.get("DEV", "cuda:0")) for _ in range(64)]
env.reset(seed=0)
for k in range(5): env.step(acts[k])
lp = LineProfiler(ABDVectorEnv.step, ABDVectorEnv._step_on_device, ABDVectorEnv._replay, ABDVectorEnv._pending_now,
                  ABDVectorEnv._defer_pending, ABDVectorEnv._prepare_actions, ABDVectorEnv._unpack, NextEpisodes.took)
lp.enable_by_count()
for k in range(2000): env.step(acts[k % 64])
lp.disable_by_count()
lp.print_stats(output_unit=1e-6, stripzeros=True)
