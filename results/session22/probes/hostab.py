"""Per-step host wall time of env.step (no wrappers), with top-up and GC accounting."""
import sys, os, time, gc, numpy as np, torch, gymnasium as gym
import abd_gym  # noqa
N, TASK, tag = int(sys.argv[1]), sys.argv[2], sys.argv[3]
S = int(sys.argv[4]) if len(sys.argv) > 4 else 3000
rng = np.random.default_rng(0)
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device=os.environ.get("DEV", "cuda:0"), backend="torch")
u = env.unwrapped
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device=os.environ.get("DEV", "cuda:0")) for _ in range(64)]
env.reset(seed=0)
for k in range(5): env.step(acts[k])
(torch.cuda.synchronize() if torch.cuda.is_available() else None)
tops = []
top = u._next._top_up
pc = time.perf_counter_ns
def counted():
    a = pc(); r = top(); tops.append((len(tops_at), pc() - a)); return r
tops_at = []
u._next._top_up = counted
gcs = {0: [], 1: [], 2: []}
gstart = [0]
def cb(phase, info):
    if phase == "start": gstart[0] = pc()
    else: gcs[info["generation"]].append(pc() - gstart[0])
gc.callbacks.append(cb)
waits = []
host, ev = u._pinned if u._pinned is not None else (None, None)
class EW:
    def __init__(s, e): s.e = e
    def synchronize(s):
        a = pc(); s.e.synchronize(); waits.append(pc() - a)
    def record(s, st=None): s.e.record(st)
if ev is not None: u._pinned = (host, EW(ev))
t = np.empty(S); top_step = np.zeros(S, bool)
t0 = pc()
for k in range(S):
    n0 = len(tops); a = pc(); env.step(acts[k % 64]); t[k] = pc() - a
    top_step[k] = len(tops) > n0
(torch.cuda.synchronize() if torch.cuda.is_available() else None)
wall = (pc() - t0) / S / 1e3
t /= 1e3
gc.callbacks.remove(cb)
nt = t[~top_step]
w = np.asarray(waits[-S:]) / 1e3 if waits else np.zeros(S)
busy = t - w
print(f"{tag} {TASK} N={N}: wall {wall:6.1f} us/step | median {np.median(t):6.1f} mean {t.mean():6.1f} p90 {np.percentile(t,90):6.1f} p99 {np.percentile(t,99):7.1f} | "
      f"without top-up steps: mean {nt.mean():6.1f} | host busy (step - event wait) median {np.median(busy):5.1f} mean {busy[~top_step].mean():5.1f} | top-ups {len(tops)} costing {sum(x for _, x in tops)/1e3/S:5.1f} us/step (each {np.mean([x for _, x in tops])/1e3 if tops else 0:6.0f} us) | "
      f"gc gen0/1/2 {len(gcs[0])}/{len(gcs[1])}/{len(gcs[2])} costing {sum(sum(v) for v in gcs.values())/1e3/S:5.2f} us/step (max {max([max(v) for v in gcs.values() if v] or [0])/1e3:6.0f} us)", flush=True)
