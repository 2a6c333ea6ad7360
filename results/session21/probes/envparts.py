"""globaltimer stamps between the parts of the env's step graph."""
import sys, numpy as np, torch, warp as wp, gymnasium as gym
sys.path.insert(0, __import__("os").path.dirname(__file__))
import stamps
import abd_gym  # noqa
N = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
TASK = sys.argv[2] if len(sys.argv) > 2 else "CartPole-v0"
S = 300
rng = np.random.default_rng(0)
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped; sim = u.sim
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
clk = stamps.Clock(["start", "physics", "physics_end", "apply_end", "post_end"])
pre, step, post = u._pre, sim.launch_step, u._post
def pre_w(*a, **k):
    clk.stamp("start"); return pre(*a, **k)
def step_w(*a, **k):
    clk.stamp("physics"); r = step(*a, **k); clk.stamp("physics_end"); return r
def post_w(*a, **k):
    r = post(*a, **k); clk.stamp("post_end"); return r
u._pre, sim.launch_step, u._post = pre_w, step_w, post_w
apply = u._next.apply
def apply_w(*a, **k):
    r = apply(*a, **k); clk.stamp("apply_end"); return r
u._next.apply = apply_w
env.reset(seed=0)
for k in range(3):
    env.step(acts[k])
print("graph captured:", u._graph is not None)
for rep in range(2):
    for k in range(S):
        env.step(acts[k % 64])
    T = clk.table(S - 1)
    s = lambda a, b: (T[b] - T[a]) / 1e3
    parts = {"check": s("start", "physics"), "physics": s("physics", "physics_end"), "autoreset": s("physics_end", "apply_end"), "post": s("apply_end", "post_end"),
             "gap to next": (T["start"][1:] - T["post_end"][:-1]) / 1e3, "period": np.diff(T["start"]) / 1e3}
    print("  ".join(f"{k} {np.median(v):.1f}/{v.mean():.1f}" for k, v in parts.items()), flush=True)
