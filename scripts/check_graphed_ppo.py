"""The CUDA-graph PPO on a GPU against its eager forms, from the same seed:

* the parameters after 1 and 6 updates: graphed update vs SB3's eager arithmetic
  (``GraphedPPO._train``) and vs the weighted arithmetic run eagerly, with each update's wall time,
  on the device rollout (gpu/cartpole_ppo, DevicePPO) and on SB3's rollout (a VecNormalize config
  forced onto it, GraphedPPO);
* the device rollout's buffer after 3 rollouts (its steps and its closing values and GAE replayed
  from graphs from the second rollout on) vs the same code run eagerly, both with the graphed update,
  on gpu/cartpole_ppo and on a VecNormalize config (its normalisation in the graph: the buffer and
  the wrapper's statistics);
* a model saved after graphed training loads on the CPU with the same parameters.

    python scripts/check_graphed_ppo.py [--sb3-config gpu/fourbar_ppo] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch as th

from abd_gym.agents.common import build_model, build_train_env
from abd_gym.agents.config import load_config
from abd_gym.agents.device_normalize import find_vecnormalize
from abd_gym.agents.graphed_update import GraphedMinibatchStep


def train(mode: str, updates: int, config: str, rollout: str):
    """A model on ``config`` after ``updates`` updates on ``rollout`` ("device": DevicePPO, "sb3":
    GraphedPPO); ``mode``: graph, eager (the graphed code without capture), sb3 (SB3's
    arithmetic) or eager_rollout (the graphed update, the device rollout without capture); the
    wall time of each update."""
    cfg = load_config(config, ["device=cuda:0"])
    th.manual_seed(0)
    model = build_model(cfg, build_train_env(cfg, rollout=rollout), rollout=rollout)
    if mode == "eager":
        model._minibatch_step = GraphedMinibatchStep(model, capture=False)
    if mode == "sb3":
        model._graphed_step = lambda: None
    if mode != "graph" and rollout == "device":
        bind = model._bind

        def eager_bind(env):
            bind(env)
            model._rollout_step = model._new_rollout_step(capture=False)

        model._bind = eager_bind
    times, update = [], model.train

    def timed():
        th.cuda.synchronize()
        start = time.perf_counter()
        update()
        th.cuda.synchronize()
        times.append(time.perf_counter() - start)

    model.train = timed
    model.learn(total_timesteps=cfg["n_envs"] * cfg["hyperparams"]["n_steps"] * updates)
    for name in ("train", "_bind", "_graphed_step"):
        model.__dict__.pop(name, None)
    return model, times


def max_diff(a, b) -> float:
    return max(float((p.detach().cpu() - q.detach().cpu()).abs().max()) for p, q in zip(a, b))


def compare(config: str, rollout: str, out: dict) -> dict:
    """Graph, eager and SB3's arithmetic after 1 and 6 updates into ``out[rollout]``; the models
    after 1 update."""
    res = out.setdefault(rollout, {"config": config})
    for updates in (1, 6):
        models = {mode: train(mode, updates, config, rollout) for mode in ("graph", "eager", "sb3")}
        if updates == 1:
            first = {mode: m for mode, (m, _) in models.items()}
        ref = list(models["sb3"][0].policy.parameters())
        for mode, (model, times) in models.items():
            diff = max_diff(model.policy.parameters(), ref)
            res[f"{mode}_{updates}"] = {"max_param_diff_vs_sb3": diff, "update_s": times}
            print(f"{config} ({rollout} rollout) {mode:5s} after {updates} update(s): parameters within "
                  f"{diff:.3g} of SB3's arithmetic; update s {[round(t, 4) for t in times]}")
    return first


def graph_vs_eager_rollout(config: str) -> dict:
    """The largest differences between the graphed and eager device rollouts after 3 rollouts: each
    buffer field, and the VecNormalize wrapper's statistics where the config has one."""
    models = {mode: train(mode, 3, config, "device")[0] for mode in ("graph", "eager_rollout")}
    graph, eager = (m.rollout_buffer.storage for m in models.values())
    res = {"rollout_buffer_max_diff": {k: float((graph[k] - eager[k]).abs().max()) for k in graph}}
    print(f"{config}: third rollout's buffer, graph vs eager: max difference",
          max(res["rollout_buffer_max_diff"].values()))  # fmt: skip
    norms = [find_vecnormalize(m.get_env()) for m in models.values()]
    if norms[0] is not None:
        a, b = norms
        res["vecnormalize_max_diff"] = {
            name: float(np.abs(np.asarray(x) - np.asarray(y)).max())
            for name, x, y in (("obs_mean", a.obs_rms.mean, b.obs_rms.mean), ("obs_var", a.obs_rms.var, b.obs_rms.var),
                               ("ret_var", a.ret_rms.var, b.ret_rms.var), ("obs_count", a.obs_rms.count, b.obs_rms.count),
                               ("ret_count", a.ret_rms.count, b.ret_rms.count), ("returns", a.returns, b.returns))}  # fmt: skip
        print(f"{config}: VecNormalize statistics after 3 rollouts, graph vs eager: {res['vecnormalize_max_diff']}")
    return res


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sb3-config", default="gpu/fourbar_ppo", help="a VecNormalize config")
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    out: dict = {"gpu": th.cuda.get_device_name()}
    first = compare("gpu/cartpole_ppo", "device", out)
    for config, key in (("gpu/cartpole_ppo", "device"), (args.sb3_config, "device_normalize")):
        out.setdefault(key, {"config": config}).update(graph_vs_eager_rollout(config))
    from stable_baselines3 import PPO

    for model, rollout in ((first["graph"], "device"), (compare(args.sb3_config, "sb3", out)["graph"], "sb3")):
        model.save("/tmp/check_graphed_ppo.zip")
        loaded = PPO.load("/tmp/check_graphed_ppo.zip", device="cpu")
        out[rollout]["load_on_cpu_param_diff"] = diff = max_diff(model.policy.parameters(), loaded.policy.parameters())
        print(f"{rollout} rollout: saved after graphed training, loaded on the CPU: parameters within {diff}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
