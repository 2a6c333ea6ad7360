"""The CUDA-graph PPO on a GPU against its eager forms, from the same seed (gpu/cartpole_ppo):

* the parameters after 1 and 6 updates: graphed update vs SB3's eager arithmetic (``DevicePPO._train``)
  and vs the weighted arithmetic run eagerly, with each update's wall time;
* the buffer of the first rollout: graphed ``RolloutStep`` vs the same code run eagerly;
* a model saved after graphed training loads on the CPU with the same parameters.

    python scripts/check_graphed_ppo.py [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import time

import torch as th

from abd_gym.agents.common import build_model, build_train_env
from abd_gym.agents.config import load_config
from abd_gym.agents.graphed_rollout import RolloutStep
from abd_gym.agents.graphed_update import GraphedMinibatchStep


def train(mode: str, updates: int):
    """A DevicePPO on gpu/cartpole_ppo after ``updates`` updates; ``mode``: graph, eager (the graphed
    code without capture) or sb3 (SB3's arithmetic); the wall time of each update."""
    cfg = load_config("gpu/cartpole_ppo", ["device=cuda:0"])
    th.manual_seed(0)
    model = build_model(cfg, build_train_env(cfg, rollout="device"), rollout="device")
    if mode == "eager":
        model._minibatch_step = GraphedMinibatchStep(model, capture=False)
    if mode == "sb3":
        model._graphed_step = lambda: None
    if mode != "graph":
        bind = model._bind

        def eager_bind(env):
            bind(env)
            model._rollout_step = RolloutStep(model, capture=False)

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


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    out: dict = {"device": th.cuda.get_device_name()}
    buffers = {}
    for updates in (1, 6):
        models = {mode: train(mode, updates) for mode in ("graph", "eager", "sb3")}
        if updates == 1:  # one rollout from the same parameters: the same transitions
            buffers = {mode: models[mode][0].rollout_buffer.storage for mode in ("graph", "eager")}
        ref = list(models["sb3"][0].policy.parameters())
        for mode, (model, times) in models.items():
            diff = max_diff(model.policy.parameters(), ref)
            out[f"{mode}_{updates}"] = {"max_param_diff_vs_sb3": diff, "update_s": times}
            print(f"{mode:5s} after {updates} update(s): parameters within {diff:.3g} of SB3's arithmetic; "
                  f"update s {[round(t, 4) for t in times]}")
    graph, eager = buffers["graph"], buffers["eager"]
    out["rollout_buffer_max_diff"] = {k: float((graph[k] - eager[k]).abs().max()) for k in graph}
    print("first rollout's buffer, graph vs eager: max difference", max(out["rollout_buffer_max_diff"].values()))
    model = models["graph"][0]
    model.save("/tmp/check_graphed_ppo.zip")
    from stable_baselines3 import PPO

    loaded = PPO.load("/tmp/check_graphed_ppo.zip", device="cpu")
    out["load_on_cpu_param_diff"] = max_diff(model.policy.parameters(), loaded.policy.parameters())
    print("saved after graphed training, loaded on the CPU: parameters within", out["load_on_cpu_param_diff"])
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
