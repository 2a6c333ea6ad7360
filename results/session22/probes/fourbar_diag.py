import numpy as np, torch, gymnasium as gym
import abd_gym  # noqa
kw = dict(num_envs=64, vectorization_mode="vector_entry_point", device="cuda:0", backend="torch", max_episode_steps=25)
g = gym.make_vec("abd_gym/FourBar-v0", **kw)
p = gym.make_vec("abd_gym/FourBar-v0", graph=False, **kw)
h = gym.make_vec("abd_gym/FourBar-v0", graph=False, **kw)
print("holds before:", h.unwrapped.sim.solver.holds, "enable:", h.unwrapped.sim.solver.enable_hold())
for e in (g, p, h): e.reset(seed=8)
d = g.unwrapped.action_dim
actions = torch.rand((80, 64, d), device="cuda:0", generator=torch.Generator("cuda:0").manual_seed(0)) * 2 - 1
prev_done = torch.zeros(64, dtype=torch.bool, device="cuda:0")
for t, a in enumerate(actions):
    og, op, oh = g.step(a.clone()), p.step(a.clone()), h.step(a.clone())
    dgp = (og[0] - op[0]).abs().max(dim=1).values
    dgh = (og[0] - oh[0]).abs().max(dim=1).values
    dph = (op[0] - oh[0]).abs().max(dim=1).values
    bad = torch.nonzero(dgp > 1e-6).flatten().tolist()
    print(f"t={t:2d} g-p {dgp.max().item():.2e} g-h {dgh.max().item():.2e} p-h {dph.max().item():.2e} "
          f"worlds g!=p {bad[:12]} pending(prev done) {torch.nonzero(prev_done).flatten().tolist()[:12]} "
          f"ends {int((og[2]|og[3]).sum())}")
    prev_done = og[2] | og[3]
