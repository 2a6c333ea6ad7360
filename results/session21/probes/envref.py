"""Why the op-by-op physics reference (112 us) is faster than the graph's physics under varied actions (137 us)."""
import sys, time, numpy as np, torch, warp as wp, gymnasium as gym
import abd_gym  # noqa
N = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
TASK = sys.argv[2] if len(sys.argv) > 2 else "CartPole-v0"
S = 300
rng = np.random.default_rng(0)

def make(graph):
    env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0",
                       backend="torch", graph=graph)
    env.reset(seed=0)
    return env

shape = make(False).action_space.shape
acts = [torch.as_tensor(rng.uniform(-1, 1, shape).astype(np.float32), device="cuda:0") for _ in range(64)]

def iters(env, steps):
    u = env.unwrapped
    tot, mx, calm = [], [], []
    for k in range(steps):
        env.step(acts[k % 64])
        it = u.sim.state.iterations.numpy()
        tot.append(it.mean()); mx.append(it.max()); calm.append((u.sim.state.calm.numpy() >= 2).mean())
    return np.mean(tot), np.mean(mx), np.mean(calm)

for graph in (True, False):
    env = make(graph)
    m, x, c = iters(env, 200)
    print(f"graph={graph}: mean iterations {m:.3f}  mean of per-step max {x:.2f}  calm>=2 fraction {c:.3f}", flush=True)

# timing: graph env whole loop; op-by-op env with events around each sim.step (bench's reference)
env = make(True); u = env.unwrapped
for k in range(4): env.step(acts[k])
torch.cuda.synchronize()
e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
for rep in range(3):
    e0.record()
    for k in range(S): env.step(acts[k % 64])
    e1.record(); torch.cuda.synchronize()
    print(f"graph env: {e0.elapsed_time(e1) / S * 1e3:.1f} us/step device", flush=True)

env2 = make(False); u2 = env2.unwrapped
sim, inner = u2.sim, u2.sim.step
for k in range(4): env2.step(acts[k])
torch.cuda.synchronize()
for rep in range(3):
    spans = []
    def timed(n=1):
        a, b = wp.Event(u2.device, enable_timing=True), wp.Event(u2.device, enable_timing=True)
        wp.record_event(a); inner(n); wp.record_event(b); spans.append((a, b))
    sim.step = timed
    for k in range(S): env2.step(acts[k % 64])
    torch.cuda.synchronize()
    sim.step = inner
    t = np.array([wp.get_event_elapsed_time(a, b) for a, b in spans]) * 1e3
    print(f"op-by-op env, events around sim.step: mean {t.mean():.1f} us  median {np.median(t):.1f}  p10 {np.percentile(t,10):.1f} p90 {np.percentile(t,90):.1f}", flush=True)

# which stream: warp current vs torch current
print("warp stream", wp.get_stream(u2.device).cuda_stream, "torch stream", torch.cuda.current_stream().cuda_stream)

# sim alone graph with controls from 64 batches (a copy kernel in the graph loop, not captured)
ctl = [wp.array(np.asarray(rng.uniform(-1, 1, (N, sim.state.control.shape[1])), dtype=np.float32), device="cuda:0") for _ in range(64)]
with wp.ScopedCapture(device=u2.device, force_module_load=False) as cap:
    sim.launch_step(u2.frame_skip)
g = cap.graph
for name, vary in (("sim graph, fixed controls", False), ("sim graph, 64 control batches", True), ("sim graph, fixed controls", False)):
    wp.copy(sim.state.control, ctl[0]); wp.synchronize()
    a, b = wp.Event(u2.device, enable_timing=True), wp.Event(u2.device, enable_timing=True)
    spans = []
    wp.record_event(a)
    for k in range(S):
        if vary: wp.copy(sim.state.control, ctl[k % 64])
        x, y = wp.Event(u2.device, enable_timing=True), wp.Event(u2.device, enable_timing=True)
        wp.record_event(x); wp.capture_launch(g); wp.record_event(y); spans.append((x, y))
    wp.record_event(b); wp.synchronize()
    t = np.array([wp.get_event_elapsed_time(x, y) for x, y in spans]) * 1e3
    print(f"{name}: loop {wp.get_event_elapsed_time(a, b) / S * 1e3:.1f} us/step, bracketed mean {t.mean():.1f}", flush=True)
    it = sim.state.iterations.numpy(); print("   last step iterations mean", it.mean(), "max", it.max())
