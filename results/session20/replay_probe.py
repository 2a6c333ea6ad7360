"""Where _replay's extra device time goes (CartPole-v0, 1,024 envs)."""
import time, numpy as np, torch, warp as wp, gymnasium as gym
import abd_gym  # noqa
env = gym.make_vec("abd_gym/CartPole-v0", num_envs=1024, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch")
u = env.unwrapped
env.reset(seed=0)
rng = np.random.default_rng(0)
acts = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device="cuda:0") for _ in range(16)]
for a in acts[:4]:
    env.step(a)
torch.cuda.synchronize()
(pre, physics, posts), _, mailed = u._graph
stream = wp.stream_from_torch(torch.cuda.current_stream())
raw = torch.empty(u._out_head, dtype=torch.uint8, device="cuda:0")
a0 = acts[0].contiguous()
S = 300

def timeit(name, fn):
    fn(0)
    torch.cuda.synchronize()
    e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    t0 = time.perf_counter()
    e0.record()
    for k in range(S):
        fn(k)
    t1 = time.perf_counter()
    e1.record()
    torch.cuda.synchronize()
    t2 = time.perf_counter()
    print(f"{name:60s} device {e0.elapsed_time(e1) / S * 1e3:7.1f} us/step  host issue {(t1 - t0) / S * 1e6:7.1f}  wall {(t2 - t0) / S * 1e6:7.1f}", flush=True)

def fixed_mail(k):
    u._mail_np[k % 2] = (a0.data_ptr(), raw.data_ptr())
    wp.capture_launch(physics[k % 2], stream=stream)

def fresh_out(k):
    r = torch.empty(u._out_head, dtype=torch.uint8, device="cuda:0")
    u._mail_np[k % 2] = (a0.data_ptr(), r.data_ptr())
    wp.capture_launch(physics[k % 2], stream=stream)

def one_slot(k):
    u._mail_np[0] = (a0.data_ptr(), raw.data_ptr())
    wp.capture_launch(physics[0], stream=stream)

def varied_actions(k):
    a = acts[k % 16]
    u._mail_np[k % 2] = (a.data_ptr(), raw.data_ptr())
    wp.capture_launch(physics[k % 2], stream=stream)

def replay(k):
    u._replay(acts[k % 16])

def replay_fixed(k):
    u._replay(a0)

def env_step(k):
    env.step(acts[k % 16])

with wp.ScopedCapture(device=u.device, force_module_load=False) as cap:
    u.sim.launch_step(u.frame_skip)
alone = cap.graph
for name, fn in (("sim graph alone", lambda k: wp.capture_launch(alone, stream=stream)),
                 ("step graphs, fixed mail, slots alternating", fixed_mail),
                 ("step graph, one slot", one_slot),
                 ("step graphs, fresh output buffer each", fresh_out),
                 ("step graphs, actions varied", varied_actions),
                 ("_replay, fixed actions", replay_fixed),
                 ("_replay", replay),
                 ("env.step", env_step),
                 ("sim graph alone (again)", lambda k: wp.capture_launch(alone, stream=stream)),
                 ("step graphs, fixed mail (again)", fixed_mail)):
    timeit(name, fn)
print("pending worlds now", int(u._next.pending.numpy().sum()))
