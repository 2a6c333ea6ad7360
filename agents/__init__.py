"""Training and evaluation of Stable-Baselines3 agents on the abd_gym tasks.

* :mod:`abd_gym.agents.sb3_vec_env` -- an SB3 ``VecEnv`` over any Gymnasium 1.x ``VectorEnv`` (same-step
  resets, ``terminal_observation``, ``TimeLimit.truncated``), and ``make_vec_env(env_id, n)``.
* :mod:`abd_gym.agents.config` -- the YAML configs in ``configs/`` (installed as ``abd_gym.configs``) (zoo-like keys) and their validation.
* ``python -m abd_gym.agents.train CONFIG [overrides]`` (``abd-gym-train``): train, checkpoint, save,
  evaluate, write ``summary.json`` into ``runs/<config>-<seed>-<timestamp>/``.
* ``python -m abd_gym.agents.evaluate RUN_DIR [--video out.gif]`` (``abd-gym-evaluate``).
* ``python scripts/results_table.py runs/ -o results/training.md``: the Markdown results table.
"""
