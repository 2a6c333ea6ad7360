"""PPO's minibatch step (loss, backward pass, gradient clipping, Adam) captured as one CUDA graph.

SB3's minibatch step launches about 150 small kernels from Python, whose launch time, whatever the
batch, is far more than the GPU's work on a few thousand samples (results/solver_notes.md).  :class:`GraphedMinibatchStep`
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

:class:`GraphedPPO` is SB3's PPO with this update on a GPU, for SB3's own rollout (the buffer's
NumPy fields go to the device once an update); :class:`~.device_rollout.DevicePPO` extends it with
a rollout kept on the device.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from stable_baselines3.common.utils import explained_variance
from torch.nn import functional as F

from abd_gym.agents.cuda_graph import GraphedCall

__all__ = ["GraphedMinibatchStep", "GraphedPPO", "SAMPLED", "STATS", "ppo_loss", "unchecked_distributions"]

# the fields a minibatch reads, (n_steps * n_envs, ...) each (SB3's flattened buffer)
SAMPLED = ("observations", "actions", "values", "log_probs", "advantages", "returns")
# PPO.train's logged means over the minibatches (train/<name>)
LOSS_LOGS = ("entropy_loss", "policy_gradient_loss", "value_loss", "clip_fraction")
# the sums kept per update, in order; the last is the number of minibatches
STATS = ("entropy_loss", "policy_gradient_loss", "value_loss", "clip_fraction", "approx_kl", "loss", "minibatches")
# eager steps before the capture (cuBLAS handles and Adam's state are created there)
_WARMUP = 3


class GraphedMinibatchStep:
    """PPO's minibatch step for ``algo`` at its ``batch_size``, replayed from a CUDA graph on a CUDA device
    (``capture`` False: run eagerly, the same arithmetic).

    Per update: :meth:`begin` (copies of the rollout's flat fields, schedules, zeroed sums), then
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

    def begin(self, fields: dict[str, Any], clip_range: float, clip_range_vf: float | None) -> None:
        """Start an update on the rollout's flat fields (``SAMPLED``: tensors on any device or NumPy
        arrays, (n, ...) each, copied once) with this update's clip ranges."""
        for name in SAMPLED:
            src = th.as_tensor(fields[name])
            dst = self.sources.get(name)
            if dst is None or dst.shape != src.shape:
                dtype = th.float32 if name == "actions" else src.dtype  # SB3 samples actions as float32
                self.sources[name] = dst = th.empty(src.shape, dtype=dtype, device=self.device)
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


@contextlib.contextmanager
def unchecked_distributions() -> Iterator[None]:
    """Torch distributions built without checking their arguments (``validate_args`` off), restored
    after.  The checks (``Categorical``'s logits, ``Normal``'s scale, each sample's support) each
    read a flag back to the host, a wait for the GPU, at every policy call; the values are the
    same either way.  A non-finite policy is still caught: :meth:`GraphedPPO.train` refuses a
    non-finite loss."""
    before = th.distributions.Distribution._validate_args
    th.distributions.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        th.distributions.Distribution.set_default_validate_args(before)


class GraphedPPO(PPO):
    """SB3's PPO whose update replays its minibatch step from a CUDA graph on a CUDA device without
    ``target_kl`` and without Dict observations (:class:`GraphedMinibatchStep`: parameters equal SB3's to float32 rounding, the
    minibatches SB3's); elsewhere its update is SB3's ``PPO.train`` (the same parameters after it,
    bit for bit).  Either way the logged statistics stay on the device and are read once an update,
    not five times a minibatch, and a non-finite loss raises ``FloatingPointError``.

    The rollout is SB3's: the buffer's NumPy fields go to the device once an update, not once a
    minibatch.  A saved model loads as a plain PPO.
    """

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_minibatch_step"]

    def get_parameters(self) -> dict[str, dict]:
        """SB3's saved state dicts, the optimiser's as a plain Adam's (the graphed update keeps its
        learning rate and step counts on the device, ``capturable``), so that a saved model loads
        anywhere."""
        params = super().get_parameters()
        opt = params.get("policy.optimizer")
        if opt is not None:
            for group in opt["param_groups"]:  # copies made by state_dict
                group["lr"] = float(group["lr"])
                group["capturable"] = False
            opt["state"] = {k: {**v, "step": v["step"].cpu()} if "step" in v else v for k, v in opt["state"].items()}
        return params

    def set_parameters(self, *args: Any, **kwargs: Any) -> None:
        super().set_parameters(*args, **kwargs)
        self._minibatch_step = None  # the optimiser's state was replaced: capture again

    def _update_learning_rate(self, optimizers: Any) -> None:
        lr = self.lr_schedule(self._current_progress_remaining)
        self.logger.record("train/learning_rate", lr)
        for group in self.policy.optimizer.param_groups:
            if isinstance(group["lr"], th.Tensor):  # a graphed update's: written in place
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr

    def train(self) -> None:
        """One update: on a CUDA device without ``target_kl``, each minibatch replayed from a CUDA graph
        (:meth:`_train_graphed`); elsewhere SB3's ``PPO.train`` op for op (:meth:`_train`).  Both read
        their logged statistics to the host once, at the end: SB3 reads five numbers every minibatch
        (``.item()``, ``.cpu()``), and each read waits for every kernel queued before it, so the
        host's launches and the GPU's work never overlap.  A non-finite loss raises
        ``FloatingPointError``."""
        with unchecked_distributions():
            step = self._graphed_step()
            if step is None:
                self._train()
            else:
                self._train_graphed(step)

    def _graphed_step(self) -> GraphedMinibatchStep | None:
        """The CUDA-graph minibatch step on a CUDA device without ``target_kl`` (built once), else None
        (and with Dict observations, whose buffer has a tensor per key)."""
        step = getattr(self, "_minibatch_step", None)
        graphable = self.target_kl is None and not isinstance(self.observation_space, spaces.Dict)
        if step is None and self.device.type == "cuda" and graphable:
            self._minibatch_step = step = GraphedMinibatchStep(self)
        return step

    def _begin_update(self) -> tuple[float, float | None]:
        """``PPO.train``'s start: training mode, the learning rate of this update, its clip ranges."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)  # type: ignore[operator]
        clip_range_vf = None
        if self.clip_range_vf is not None:
            clip_range_vf = self.clip_range_vf(self._current_progress_remaining)  # type: ignore[operator]
        return clip_range, clip_range_vf

    def _train_graphed(self, step: GraphedMinibatchStep) -> None:
        """``PPO.train`` with each minibatch replayed from a CUDA graph (:mod:`.graphed_update`)."""
        clip_range, clip_range_vf = self._begin_update()
        step.begin(self._flat_fields(), clip_range, clip_range_vf)
        for _ in range(self.n_epochs):
            for batch_inds in self._minibatch_indices():
                step.step(batch_inds)
            self._n_updates += 1
        means = step.means()
        self._log_update([means[n] for n in (*LOSS_LOGS, "approx_kl")], means["last_loss"], means["loss"],
                         clip_range, clip_range_vf)  # fmt: skip

    def _train(self) -> None:
        """SB3's ``PPO.train``: the same losses, minibatches, gradient clipping and optimiser steps in
        the same order (the same parameters after it, bit for bit); with ``target_kl`` the KL
        estimate is read every minibatch, as the early stop needs."""
        clip_range, clip_range_vf = self._begin_update()
        logged: dict[str, list[th.Tensor]] = {name: [] for name in LOSS_LOGS}
        approx_kl_divs: list[th.Tensor] = []
        loss = th.zeros((), device=self.device)
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for rollout_data in self.rollout_buffer.get(self.batch_size):
                loss, parts = ppo_loss(self, rollout_data, clip_range, clip_range_vf)
                approx_kl_div = parts.pop("approx_kl")
                for name, value in parts.items():
                    logged[name].append(value)
                approx_kl_divs.append(approx_kl_div)
                if self.target_kl is not None and approx_kl_div.item() > 1.5 * self.target_kl:
                    continue_training = False
                    if self.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {approx_kl_div.item():.2f}")
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
            self._n_updates += 1
            if not continue_training:
                break
        series = [*(logged[n] for n in LOSS_LOGS), approx_kl_divs]
        means = [th.stack(s).double().mean() if s else th.tensor(float("nan"), device=self.device) for s in series]
        *values, last_loss = th.stack([*means, loss.detach().double()]).cpu().tolist()
        self._log_update(values, last_loss, last_loss, clip_range, clip_range_vf)

    def _log_update(self, values: list[float], last_loss: float, checked_loss: float, clip_range: float,
                    clip_range_vf: float | None) -> None:  # fmt: skip
        """``PPO.train``'s records: ``values`` the means over the minibatches of ``LOSS_LOGS`` and the
        KL estimate, ``last_loss`` the last minibatch's loss; a non-finite ``checked_loss`` (the last
        loss, or the mean over the minibatches where the update keeps it) raises."""
        names = [*LOSS_LOGS, "approx_kl"]
        if not np.isfinite(checked_loss):
            raise FloatingPointError(f"PPO's loss is {checked_loss} at update {self._n_updates}: the policy or the "
                                     "rollout's values went non-finite")  # fmt: skip
        for name, value in zip(names, values):
            self.logger.record(f"train/{name}", value)
        self.logger.record("train/loss", last_loss)
        buf = self.rollout_buffer
        self.logger.record("train/explained_variance", explained_variance(buf.values.flatten(), buf.returns.flatten()))
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)

    def _flat_fields(self) -> dict[str, Any]:
        """The fields of SB3's full rollout buffer, flattened as SB3's ``RolloutBuffer.get`` does."""
        buf = self.rollout_buffer
        assert buf.full, ""
        if not buf.generator_ready:
            for name in SAMPLED:
                buf.__dict__[name] = buf.swap_and_flatten(buf.__dict__[name])
            buf.generator_ready = True
        return {name: getattr(buf, name) for name in SAMPLED}

    def _minibatch_indices(self) -> Iterator[th.Tensor]:
        """Each minibatch's rows on the device, in the order SB3's ``RolloutBuffer.get`` draws them
        (a permutation from NumPy's global generator an epoch)."""
        m = self.rollout_buffer.buffer_size * self.rollout_buffer.n_envs
        indices = th.as_tensor(np.random.permutation(m), device=self.device)
        for start in range(0, m, self.batch_size):
            yield indices[start : start + self.batch_size]
