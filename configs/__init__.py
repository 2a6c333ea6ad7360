"""The training configs (``*.yaml``), installed with the package as ``abd_gym.configs``.

``abd_gym.agents.config.find_config("cartpole_ppo")`` finds ``cartpole_ppo.yaml`` here.
"""
