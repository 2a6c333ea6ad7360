"""PPO's minibatch step (loss, backward pass, gradient clipping, Adam) captured as one CUDA graph.

SB3's minibatch step launches ~150 small kernels from Python: ~4.5 ms on an H100/H200 whatever the
batch, far more than the GPU's work on a few thousand samples.  :class:`GraphedMinibatchStep`
records the step once and replays it, so a minibatch costs one graph launch and two index copies.

A graph replays fixed shapes at fixed addresses, which fixes four things:

* every minibatch has ``batch_size`` rows.  SB3's last minibatch of an epoch is smaller (always,
  with a NEXT_STEP rollout, whose reset steps are left out); here it is padded with row 0 and each
  row carries a weight ``w`` (1, or 0 for padding).  Every mean of PPO's loss is
  ``sum(w x) / n`` with ``n = sum(w)``, and the advantages are normalised by their weighted mean and
  unbiased standard deviation ``sqrt(sum(w (A - mean)^2) / (n - 1))`` (when ``n > 1``, as SB3), so a
  padded row adds exactly zero to the loss and its gradient;
* the minibatch is gathered inside the graph, by an index tensor written before each replay, from
  flat copies of the buffer's fields made once an update (:meth:`begin`);
* the learning rate and the clip ranges are device tensors written before each update (SB3's
  schedules change them between updates); Adam runs with ``capturable=True`` (its step count on
  the device);
* the logged statistics (the four losses' parts, the KL estimate, the loss) are summed inside the
  graph in float64 and read once an update (:meth:`means`).

The arithmetic is SB3's ``PPO.train`` except that each mean is a weighted sum over ``n``: parameters
agree with SB3's to float32 rounding (a test compares them), not bit for bit.  On the CPU (no
graphs) :meth:`step` runs the same arithmetic eagerly.  ``target_kl`` is not supported: its early
stop reads the KL estimate between the loss and the optimiser step.
"""
from __future__ import annotations

from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from torch.nn import functional as F

from .cuda_graph import GraphedCall

__all__ = ["GraphedMinibatchStep", "STATS", "ppo_loss"]

# the sums kept per update, in order; the last is the number of minibatches
STATS = ("entropy_loss", "policy_gradient_loss", "value_loss", "clip_fraction", "approx_kl", "loss", "minibatches")
# eager steps before the capture (cuBLAS handles and Adam's state are created there)
_WARMUP = 3


class GraphedMinibatchStep:
    """PPO's minibatch step for ``algo`` at its ``batch_size``, replayed from a CUDA graph on a CUDA device
    (``capture`` False: run eagerly, the same arithmetic).

    Per update: :meth:`begin` (flat copies of the buffer's fields, schedules, zeroed sums), then
    :meth:`step` for each minibatch's indices (any length up to ``batch_size``), then :meth:`means`.
    """

    def __init__(self, algo: PPO, capture: bool | None = None):
        self.algo = algo
        self.device = algo.device
        self.call = GraphedCall(self._step, self.device, warmup=_WARMUP, capture=capture)
        if algo.target_kl is not None:
            raise ValueError(f"target_kl={algo.target_kl}: the graphed update has no early stop on the KL estimate")
        size, dev = algo.batch_size, self.device
        self.idx = th.zeros(size, dtype=th.int64, device=dev)
        self.weight = th.ones(size, dtype=th.float32, device=dev)
        self.clip_range = th.zeros((), dtype=th.float32, device=dev)
        self.clip_range_vf = th.zeros((), dtype=th.float32, device=dev)
        self.sums = th.zeros(len(STATS), dtype=th.float64, device=dev)
        self.last_loss = th.zeros((), dtype=th.float32, device=dev)
        self._has_clip_vf = algo.clip_range_vf is not None
        self.sources: dict[str, th.Tensor] = {}
        self._padded = False
        if self.call.capture:
            self._make_capturable()

    def _make_capturable(self) -> None:
        """Adam with its step count and learning rate on the device (a graph replays no host scalar)."""
        opt = self.algo.policy.optimizer
        for group in opt.param_groups:
            group["capturable"] = True
            group["lr"] = th.tensor(float(group["lr"]), dtype=th.float32, device=self.device)
        for state in opt.state.values():
            if "step" in state:
                state["step"] = state["step"].to(self.device, th.float32)

    def begin(self, buffer: Any, clip_range: float, clip_range_vf: float | None) -> None:
        """Start an update on ``buffer`` (a full :class:`TensorRolloutBuffer`) with this update's clip ranges."""
        buffer.flatten()
        for name in buffer.SAMPLED:
            src = buffer.tensors[name]
            dst = self.sources.get(name)
            if dst is None or dst.shape != src.shape:
                self.sources[name] = dst = th.empty_like(src)
                self.call.reset()  # the captured step reads the old addresses
            dst.copy_(src)
        self.clip_range.fill_(clip_range)
        if clip_range_vf is not None:
            self.clip_range_vf.fill_(clip_range_vf)
        self.sums.zero_()

    def step(self, batch_inds: th.Tensor) -> None:
        """One minibatch: PPO's loss on the rows ``batch_inds`` of the flat fields, backward, clip, Adam."""
        rows = len(batch_inds)
        self.idx[:rows].copy_(batch_inds)
        if rows < len(self.idx):
            self.idx[rows:].zero_()
            self.weight[:rows].fill_(1.0)
            self.weight[rows:].zero_()
            self._padded = True
        elif self._padded:
            self.weight.fill_(1.0)
            self._padded = False
        self.call()

    def means(self) -> dict[str, float]:
        """This update's means over its minibatches (NaN without one) and the last minibatch's loss."""
        *sums, count, last_loss = th.cat([self.sums, self.last_loss.double()[None]]).cpu().tolist()
        out = {name: total / count if count else float("nan") for name, total in zip(STATS, sums)}
        out["last_loss"] = last_loss
        return out

    def _step(self) -> None:
        algo, policy = self.algo, self.algo.policy
        # gradients set to None, not zeroed: the backward pass writes them (in a capture, into the graph's memory)
        policy.optimizer.zero_grad(set_to_none=True)
        loss, parts = self._loss()
        loss.backward()
        th.nn.utils.clip_grad_norm_(policy.parameters(), algo.max_grad_norm)
        policy.optimizer.step()
        self.sums += th.stack([*parts, loss.detach(), th.ones((), device=self.device)]).double()
        self.last_loss.copy_(loss.detach())

    def _loss(self) -> tuple[th.Tensor, list[th.Tensor]]:
        """PPO's loss on the weighted minibatch and the logged parts (in :data:`STATS` order)."""
        src, i = self.sources, self.idx
        samples = RolloutBufferSamples(src["observations"][i], src["actions"][i], src["values"][i].flatten(),
                                       src["log_probs"][i].flatten(), src["advantages"][i].flatten(),
                                       src["returns"][i].flatten())  # fmt: skip
        clip_vf = self.clip_range_vf if self._has_clip_vf else None
        loss, parts = ppo_loss(self.algo, samples, self.clip_range, clip_vf, self.weight)
        return loss, [parts[name] for name in STATS[:5]]


def ppo_loss(algo: PPO, data: RolloutBufferSamples, clip_range: float | th.Tensor,
             clip_range_vf: float | th.Tensor | None,
             weight: th.Tensor | None = None) -> tuple[th.Tensor, dict[str, th.Tensor]]:  # fmt: skip
    """PPO's clipped loss on a minibatch, as SB3's ``PPO.train`` computes it, and its logged parts
    (``entropy_loss``, ``policy_gradient_loss``, ``value_loss``, ``clip_fraction``, ``approx_kl``;
    tensors on the device).

    ``weight`` None: SB3's arithmetic, op for op.  ``weight`` (1 or 0 a row, float32): every mean
    is ``sum(w x) / n`` with ``n = sum(w)`` and the advantages are normalised by their weighted
    mean and unbiased standard deviation when ``n > 1``, so rows of weight 0 change nothing; no
    host reads (the graphed step).
    """
    actions = data.actions
    if isinstance(algo.action_space, spaces.Discrete):
        actions = actions.long().flatten()
    values, log_prob, entropy = algo.policy.evaluate_actions(data.observations, actions)
    values = values.flatten()
    advantages = data.advantages
    if weight is None:
        mean = th.mean
        if algo.normalize_advantage and len(advantages) > 1:
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    else:
        n = weight.sum()

        def mean(x: th.Tensor) -> th.Tensor:
            return (weight * x).sum() / n

        if algo.normalize_advantage:
            centred = advantages - mean(advantages)
            std = th.sqrt((weight * centred**2).sum() / (n - 1))
            advantages = th.where(n > 1, centred / (std + 1e-8), advantages)
    ratio = th.exp(log_prob - data.old_log_prob)
    policy_loss_1 = advantages * ratio
    policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
    policy_loss = -mean(th.min(policy_loss_1, policy_loss_2))
    clip_fraction = mean((th.abs(ratio - 1) > clip_range).float())
    values_pred = values
    if clip_range_vf is not None:
        values_pred = data.old_values + th.clamp(values - data.old_values, -clip_range_vf, clip_range_vf)
    value_loss = F.mse_loss(data.returns, values_pred) if weight is None else mean((data.returns - values_pred) ** 2)
    entropy_loss = -mean(-log_prob) if entropy is None else -mean(entropy)
    loss = policy_loss + algo.ent_coef * entropy_loss + algo.vf_coef * value_loss
    with th.no_grad():
        log_ratio = log_prob - data.old_log_prob
        approx_kl = mean((th.exp(log_ratio) - 1) - log_ratio)
    parts = {"entropy_loss": entropy_loss.detach(), "policy_gradient_loss": policy_loss.detach(),
             "value_loss": value_loss.detach(), "clip_fraction": clip_fraction, "approx_kl": approx_kl}  # fmt: skip
    return loss, parts
