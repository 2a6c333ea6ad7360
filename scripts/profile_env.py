"""Where a vector env's step spends host time: each phase of ``ABDVectorEnv.step`` timed on the
host clock (no synchronisation added), and, on a GPU, Torch's warnings for every operation that
makes the host wait for the device (``torch.cuda.set_sync_debug_mode``).

    python scripts/profile_env.py [--task CartPole-v0] [--envs 1024] [--steps 200] [--device cuda:0]

A phase that waits for the device shows the device's time in its row: with the step graph, only
``pending.fetch`` should (it waits for the last step while this one runs; see abd_gym/vector/pending.py).
With the step graph, the device's time per step is split too, by CUDA events: the replay (the step
graph, and the actions' copy and the graphs before and after it where the step needs them), the
info copies after it, and the gap to the next step (where the device waits for the host); and each
part replayed on its own, back to back, which the host cannot slow.
"""
import argparse
import collections
import time
import warnings

import gymnasium as gym
import numpy as np
import warp as wp

import abd_gym  # noqa: F401 -- registers the ids
from abd_gym.core import graphs
from abd_gym.vector import outcome, step_graph, vector_env

# the env's hooks and the public calls of its layers, each timed where it is looked up
ENV_PHASES = ("controls", "observation", "reward", "terminated", "info")
LAYER_PHASES = (("device_step", ("step", "run", "pending_now")), ("pending", ("fetch", "defer")),
                ("next_episodes", ("took", "restart")), ("sim", ("step", "set_controls", "set_joint_state")))
MODULE_PHASES = ((vector_env, "prepare_actions"), (outcome, "failed_mask"), (step_graph, "StepGraph"))


def device_phases(env, actions, steps):
    """Device time of each part of the graph step, from CUDA events recorded around them."""
    import torch

    u = env.unwrapped
    g = u.device_step.graph
    marks = []
    inner = g.replay

    def replay(a, out=None):
        marks[-1][1].record()
        out = inner(a, out)
        marks[-1][2].record()
        return out

    g.replay = replay
    wp.synchronize_device(u.device)
    t0 = time.perf_counter()
    for k in range(steps):
        marks.append([torch.cuda.Event(enable_timing=True) for _ in range(4)])
        marks[-1][0].record()
        env.step(actions[k % len(actions)])
        marks[-1][3].record()
    torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    g.replay = inner
    pre, posts, mailed = g.pre, g.posts, g.mailed
    names = ("before the replay", "the replay (" + ("actions' copy, " if not mailed else "")
             + ("pre graph, " if pre is not None else "") + "step graph"
             + (", post graph" if posts[0] is not None else "") + ")", "after it (info copies)",
             "gap to the next step")  # fmt: skip
    sums = [0.0] * 4
    for k, e in enumerate(marks):
        for j in range(3):
            sums[j] += e[j].elapsed_time(e[j + 1])
        if k + 1 < len(marks):
            sums[3] += e[3].elapsed_time(marks[k + 1][0])
    print(f"device time per step (CUDA events, {steps} steps; wall {wall / steps * 1e6:.0f} us/step):")
    for name, v in zip(names, sums):
        print(f"  {name:60s} {v / steps * 1e3:8.1f} us/step")


def device_parts(env, actions, steps):
    """Device time of each part of the graph step replayed ``steps`` times back to back (no host
    bookkeeping between replays, so no gap where the device waits for the host), by two CUDA
    events around each run: what the device itself spends on each part of an env step."""
    import torch

    u = env.unwrapped
    g = u.device_step.graph
    physics, posts = g.physics, g.posts
    stream = wp.stream_from_torch(torch.cuda.current_stream(u.arrays.torch_device))
    alone, _ = graphs.capture(u.device, lambda: u.sim.launch_step(u.frame_skip))
    # the graphs alone write where their mail slots point: a buffer that outlives them
    raw = torch.empty(u.device_step.out_head, dtype=torch.float32, device=u.arrays.torch_device)
    a0 = actions[0].contiguous()
    for slot in (0, 1):
        g.pinned.mail_np[slot] = (a0.data_ptr(), raw.data_ptr())

    def graph(k):
        wp.capture_launch(physics[k % 2], stream=stream)
        if posts[k % 2] is not None:
            posts[k % 2].replay()

    parts = (("step graphs alone (check, physics, autoreset, outcome)", graph),
             ("simulator's step alone (its graph)", lambda k: wp.capture_launch(alone, stream=stream)),
             ("whole env step, device work only (replay)", lambda k: g.replay(actions[k % len(actions)])))
    print(f"device time of each part replayed {steps} times back to back (CUDA events):")
    for name, fn in parts:
        fn(0)
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        torch.cuda.synchronize()
        a.record()
        for k in range(steps):
            fn(k)
        b.record()
        torch.cuda.synchronize()
        print(f"  {name:56s} {a.elapsed_time(b) / steps * 1e3:8.1f} us/step")


def main(argv=None):
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CartPole-v0")
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--device", default="cuda:0" if wp.is_cuda_available() else "cpu")
    ap.add_argument("--graph", type=int, default=None, help="1/0: the env step as one CUDA graph or not (default: "
                    "the env's choice)")  # fmt: skip
    args = ap.parse_args(argv)
    extra = {} if args.graph is None else {"graph": bool(args.graph)}
    env = gym.make_vec(f"abd_gym/{args.task}", num_envs=args.envs, vectorization_mode="vector_entry_point",
                       device=args.device, backend="torch", **extra)  # fmt: skip
    u = env.unwrapped
    print(f"{args.task} envs {args.envs} on {args.device}: {type(env).__name__} over {type(u).__name__}, "
          f"autoreset {u.autoreset_mode}, frame_skip {u.frame_skip}, autoreset on the device "
          f"{u.next_episodes is not None}, graph {u.device_step.use_graph}")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = [torch.as_tensor(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32), device=u.arrays.torch_device)
               for _ in range(16)]  # fmt: skip
    for a in actions[:2]:  # kernel loads, then the step graph's capture (at the second step)
        env.step(a)
    wp.synchronize_device(u.device)
    spent = collections.defaultdict(float)
    calls = collections.Counter()

    def timed(name, fn):
        def run(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t
                calls[name] += 1

        return run

    # the task's outcome, compiled by torch.compile, guards on these methods: wrapping them would
    # recompile it (inside the step graph's capture)
    task_code = ("observation", "reward", "terminated", "info") if u.device_step.compile_outcome else ()
    for name in ENV_PHASES:
        if name not in task_code:
            setattr(u, name, timed(name, getattr(u, name)))
    for layer, names in LAYER_PHASES:
        obj = getattr(u, layer)
        for name in names if obj is not None else ():
            setattr(obj, name, timed(f"{layer}.{name}", getattr(obj, name)))
    for module, name in MODULE_PHASES:
        setattr(module, name, timed(name, getattr(module, name)))
    t0 = time.perf_counter()
    for k in range(args.steps):
        env.step(actions[k % len(actions)])
    host = time.perf_counter() - t0
    wp.synchronize_device(u.device)
    total = time.perf_counter() - t0
    print(f"step: {host / args.steps * 1e6:.0f} us on the host, {total / args.steps * 1e6:.0f} us with the device drained")
    for name, s in sorted(spent.items(), key=lambda kv: -kv[1]):
        print(f"  {name:20s} {s / args.steps * 1e6:8.1f} us/step  ({calls[name]} calls)")
    if u.device_step.graph is not None:
        device_phases(env, actions, args.steps)
        device_parts(env, actions, args.steps)
    if wp.get_device(u.device).is_cuda:
        torch.cuda.set_sync_debug_mode("warn")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for k in range(5):
                env.step(actions[k])
        torch.cuda.set_sync_debug_mode(0)
        sites = collections.Counter(f"{w.filename}:{w.lineno}" for w in caught)
        print(f"synchronising torch operations in 5 steps: {sum(sites.values())}")
        for site, n in sites.most_common():
            print(f"  {n:3d}  {site}")
    env.close()


if __name__ == "__main__":
    main()
