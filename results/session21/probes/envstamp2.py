import sys, time, numpy as np, torch, warp as wp, gymnasium as gym
sys.path.insert(0, __import__("os").path.dirname(__file__))
import stamps
import abd_gym  # noqa
N, TASK, tag = int(sys.argv[1]), sys.argv[2], sys.argv[3]
S = 300
rng = np.random.default_rng(0)
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped; sim = u.sim
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
clk = stamps.Clock(["p0", "p1", "end"])
step, post = sim.launch_step, u._post
def step_w(*a, **k):
    clk.stamp("p0"); r = step(*a, **k); clk.stamp("p1"); return r
def post_w(*a, **k):
    r = post(*a, **k); clk.stamp("end"); return r
sim.launch_step, u._post = step_w, post_w
env.reset(seed=0)
for k in range(5): env.step(acts[k])
for rep in range(2):
    t0 = time.perf_counter()
    for k in range(S): env.step(acts[k % 64])
    torch.cuda.synchronize(); wall = (time.perf_counter() - t0) / S * 1e6
    T = clk.table(S - 1)
    phys = (T["p1"] - T["p0"]) / 1e3; per = np.diff(T["p0"]) / 1e3; tail = (T["end"] - T["p1"]) / 1e3
    gap = (T["p0"][1:] - T["end"][:-1]) / 1e3
    print(f"{tag}: wall {wall:6.1f}  physics median {np.median(phys):6.1f}  after physics {np.median(tail):5.1f}  end->next physics {np.median(gap):5.1f}  period median {np.median(per):6.1f} mean {per.mean():6.1f}", flush=True)
