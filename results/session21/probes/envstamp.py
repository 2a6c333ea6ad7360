"""globaltimer stamps around the env's physics: in the step graph and op by op."""
import sys, numpy as np, torch, warp as wp, gymnasium as gym
sys.path.insert(0, __import__("os").path.dirname(__file__))
import stamps
import abd_gym  # noqa
N = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
TASK = sys.argv[2] if len(sys.argv) > 2 else "CartPole-v0"
S = 300
rng = np.random.default_rng(0)

def make(graph):
    env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0",
                       backend="torch", graph=graph)
    return env

def report(name, t, c):
    wp.synchronize()
    n = int(c.numpy()[0]); a = t.numpy()[: 2 * n].reshape(n, 2).astype(np.int64)
    a = a[-S:]
    d = (a[:, 1] - a[:, 0]) / 1e3
    per = np.diff(a[:, 0]) / 1e3
    print(f"{name:45s} physics {d.mean():6.1f} us (median {np.median(d):6.1f}, p90 {np.percentile(d, 90):6.1f}); period {per.mean():6.1f} us (median {np.median(per):6.1f})", flush=True)
    return d

shape = make(False).action_space.shape
acts = [torch.as_tensor(rng.uniform(-1, 1, shape).astype(np.float32), device="cuda:0") for _ in range(64)]
res = {}
for graph in (True, False, True, False):
    env = make(graph); u = env.unwrapped; sim = u.sim
    t = wp.zeros(2 * 1024, dtype=wp.uint64, device="cuda:0"); c = wp.zeros(1, dtype=wp.int32, device="cuda:0")
    name = "launch_step" if graph else "step"
    inner = getattr(sim, name)
    def wrapped(*a, inner=inner, **kw):
        wp.launch(stamps.stamp, dim=1, inputs=[t, c, 0], device="cuda:0")
        inner(*a, **kw)
        wp.launch(stamps.stamp, dim=1, inputs=[t, c, 1], device="cuda:0")
    setattr(sim, name, wrapped)
    env.reset(seed=0)
    for k in range(S + 20):
        env.step(acts[k % 64])
    res[graph] = report(f"env graph={graph}", t, c)
    it = sim.state.iterations.numpy(); print("   iterations last step mean", it.mean(), "max", it.max())

# the simulator alone: plain graph vs inside capture_if, controls varied outside the graph
sim = u.sim
ctl = [wp.array(rng.uniform(-1, 1, sim.state.control.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
go = wp.ones(1, dtype=wp.int32, device="cuda:0")
def cap(cond):
    t = wp.zeros(2 * 1024, dtype=wp.uint64, device="cuda:0"); c = wp.zeros(1, dtype=wp.int32, device="cuda:0")
    def body():
        wp.launch(stamps.stamp, dim=1, inputs=[t, c, 0], device="cuda:0")
        sim.launch_step(u.frame_skip)
        wp.launch(stamps.stamp, dim=1, inputs=[t, c, 1], device="cuda:0")
    with wp.ScopedCapture(device="cuda:0", force_module_load=False) as cp:
        if cond:
            wp.capture_if(go, on_true=body)
        else:
            body()
    return cp.graph, t, c
for cond in (False, True, False, True):
    g, t, c = cap(cond)
    for k in range(S):
        wp.copy(sim.state.control, ctl[k % 64])
        wp.capture_launch(g)
    report(f"sim alone, capture_if={cond}, controls varied", t, c)
