"""Graph node costs: 20 repetitions of a part in one graph, replayed; device µs per repetition."""
import sys, numpy as np, torch, warp as wp, gymnasium as gym
import abd_gym  # noqa
from abd_gym import env_kernels
N = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
TASK = sys.argv[2] if len(sys.argv) > 2 else "CartPole-v0"
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped; sim = u.sim
rng = np.random.default_rng(0)
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
env.reset(seed=0)
for k in range(30): env.step(acts[k % 64])
torch.cuda.synchronize()
R = 20

@wp.kernel
def empty(x: wp.array(dtype=wp.float32)):
    w = wp.tid()
    x[w] = x[w] + 1.0

x = wp.zeros(N, dtype=wp.float32, device="cuda:0")
go = wp.ones(1, dtype=wp.int32, device="cuda:0")
pend_np = (rng.random(N) < 0.05).astype(np.int32)
def set_pending(p):
    u._next.pending.assign(p)

def timeit(name, body, pending=None):
    if pending is not None: set_pending(pending)
    body()  # load
    wp.synchronize()
    with wp.ScopedCapture(device="cuda:0", force_module_load=False) as cp:
        for _ in range(R): body()
    g = cp.graph
    best = 1e9
    for rep in range(5):
        if pending is not None: set_pending(pending)
        wp.synchronize()
        e0, e1 = wp.Event("cuda:0", enable_timing=True), wp.Event("cuda:0", enable_timing=True)
        wp.record_event(e0)
        for _ in range(10): wp.capture_launch(g)
        wp.record_event(e1); wp.synchronize()
        best = min(best, wp.get_event_elapsed_time(e0, e1) * 1e3 / (10 * R))
    print(f"{name:55s} {best:6.2f} us", flush=True)

k = u._wp
check = env_kernels.check_actions(sim.model.dtype, True, True)
u._mail_np[0] = (acts[0].data_ptr(), 0)
abuf = torch.zeros_like(acts[0])
timeit("empty kernel", lambda: wp.launch(empty, dim=N, inputs=[x], device="cuda:0"))
timeit("capture_if(go){empty}", lambda: wp.capture_if(go, on_true=lambda: wp.launch(empty, dim=N, inputs=[x], device="cuda:0")))
timeit("check_actions (mailed)", lambda: wp.launch(check, dim=N, inputs=[wp.from_torch(abuf), k["effort"], k["bad"], go, sim.state.control, u._mail_dev, 0], device="cuda:0"))
nxt = u._next
take = lambda: sim._replay("queue_take", abd_gym.autoreset._take(sim.model.dtype), N, [nxt.pending, nxt.taken, nxt.queue, nxt.xx, k["elapsed"], 1, nxt.task_queue, nxt._no_task, 0])
restart = lambda: sim.set_joint_state_where(nxt.pending, nxt.xx)
for p, nm in ((np.zeros(N, np.int32), "none pending"), (pend_np, "5% pending")):
    timeit(f"take, {nm}", take, p)
    timeit(f"restart_where, {nm}", restart, p)
    timeit(f"apply (take+restart), {nm}", lambda: nxt.apply(k["elapsed"], k["task"]), p)
