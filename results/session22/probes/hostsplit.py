"""Host time per env step, split by part (perf_counter_ns wrappers), GPU step graph path."""
import sys, os, time, gc, numpy as np, torch, warp as wp, gymnasium as gym
import abd_gym  # noqa
N, TASK, tag = int(sys.argv[1]), sys.argv[2], sys.argv[3]
S = 1000
rng = np.random.default_rng(0)
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
env.reset(seed=0)
for k in range(5): env.step(acts[k])
torch.cuda.synchronize()
pc = time.perf_counter_ns
def plain(n):
    t = np.empty(n)
    for k in range(n):
        a = pc(); env.step(acts[k % 64]); t[k] = pc() - a
    torch.cuda.synchronize()
    return t / 1e3
p0 = plain(S)
acc = {}
def wrap(obj, name, key=None):
    f = getattr(obj, name); key = key or name
    acc[key] = []
    def w(*a, **k):
        t = pc(); r = f(*a, **k); acc[key].append(pc() - t); return r
    setattr(obj, name, w)
for name in ["_prepare_actions", "_replay", "_unpack", "_pending_now", "_defer_pending", "_batch_info", "_device_buffers"]:
    wrap(u, name)
wrap(u.sim, "tick"); wrap(u._next, "took")
wrap(wp, "capture_launch")
host, ev = u._pinned
class EW:
    def __init__(s, e): s.e = e
    def synchronize(s):
        t = pc(); s.e.synchronize(); acc.setdefault("event.synchronize", []).append(pc() - t)
    def record(s, st=None):
        t = pc(); s.e.record(st); acc.setdefault("event.record", []).append(pc() - t)
u._pinned = (host, EW(ev))
te = torch.empty
def empty(*a, **k):
    t = pc(); r = te(*a, **k); acc.setdefault("torch.empty", []).append(pc() - t); return r
torch.empty = empty
for v in acc.values(): v.clear()
tw = plain(S)
torch.empty = te
print(f"{tag} {TASK} N={N} pid={os.getpid()} affinity={sorted(os.sched_getaffinity(0))[:4]}.. ({len(os.sched_getaffinity(0))}) load={open('/proc/loadavg').read().split()[:3]}")
print(f"  plain step: median {np.median(p0):6.1f}  mean {p0.mean():6.1f}  p90 {np.percentile(p0,90):6.1f} us")
print(f"  wrapped   : median {np.median(tw):6.1f}  mean {tw.mean():6.1f} us")
tot = 0
for k, v in acc.items():
    v = np.asarray(v[-S:]) / 1e3
    if len(v) == 0: continue
    print(f"  {k:22s} calls/step {len(v)/S:4.2f}  median {np.median(v):6.2f}  mean {v.mean():6.2f} us")
wait = np.median(np.asarray(acc["event.synchronize"]) / 1e3)
print(f"  host busy (median step - median wait) {np.median(tw) - wait:6.1f} us")
# pure Python speed reference of this process
a = pc(); s = 0
for i in range(200000): s += i
print(f"  python loop 200k adds: {(pc()-a)/1e3:.0f} us")
