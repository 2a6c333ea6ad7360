import sys, time, numpy as np, torch, gymnasium as gym, warp as wp
import abd_gym  # noqa
N = int(sys.argv[1]); TASK = sys.argv[2]; tag = sys.argv[3]
env = gym.make_vec(f"abd_gym/{TASK}", num_envs=N, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped
env.reset(seed=0)
rng = np.random.default_rng(0)
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(64)]
for k in range(5): env.step(acts[k])
torch.cuda.synchronize()
tops = [0]
top = u._next._top_up
def counted():
    tops[0] += 1; return top()
u._next._top_up = counted
res = []
for w in range(6):
    t = np.empty(200)
    t0 = time.perf_counter()
    for k in range(200):
        a = time.perf_counter(); env.step(acts[k % 64]); t[k] = time.perf_counter() - a
    torch.cuda.synchronize()
    T = (time.perf_counter() - t0) / 200 * 1e6
    res.append(T)
    print(f"{tag} {TASK} window {w}: {T:6.1f} us/step  median {np.median(t)*1e6:6.1f}  p99 {np.percentile(t, 99)*1e6:7.1f}  max {t.max()*1e6:7.1f}  top-ups so far {tops[0]}", flush=True)
print(f"{tag} {TASK} best {min(res):.1f} median {np.median(res):.1f} us/step -> {N / min(res) * 1e6 / 1e6:.2f} M env-steps/s (best)")
