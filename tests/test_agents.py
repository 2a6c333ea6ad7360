"""Training side: config validation, the SB3 adapter, a train/save/load/evaluate round trip, learning."""
from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

pytest.importorskip("stable_baselines3")

import abd_gym  # noqa: E402,F401 -- registers the abd_gym/ ids
from gymnasium.vector import AutoresetMode  # noqa: E402
from stable_baselines3.common.vec_env import VecEnv, VecMonitor, VecNormalize  # noqa: E402

from abd_gym.agents import config as agent_config  # noqa: E402
from abd_gym.agents.config import ConfigError, load_config, validate_config  # noqa: E402
from abd_gym.agents.sb3_vec_env import GymnasiumVecEnv, make_vec_env  # noqa: E402

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


CARTPOLE = "abd_gym/CartPole-v0"


def _base_config(**extra):
    cfg = {
        "env_id": CARTPOLE,
        "algo": "ppo",
        "n_envs": 4,
        "n_timesteps": 1000,
        "hyperparams": {"n_steps": 32, "batch_size": 64, "learning_rate": 3e-4},
        "policy_kwargs": {"net_arch": [16], "activation_fn": "nn.Tanh"},
    }
    cfg.update(extra)
    return cfg


# ---------------------------------------------------------------------------------------------
# config validation


@pytest.mark.parametrize(
    "change, key",
    [
        ({"algo": "ppq"}, "algo"),
        ({"env_id": "abd_gym/NoSuchTask-v0"}, "env_id"),
        ({"n_timestep": 1000}, "n_timestep"),
        ({"hyperparams": {"n_steps": "many"}}, "hyperparams.n_steps"),
        ({"hyperparams": {"learning_rate": "fast"}}, "hyperparams.learning_rate"),
        ({"hyperparams": {"gamma": True}}, "hyperparams.gamma"),
        ({"hyperparams": {"n_stepz": 32}}, "hyperparams.n_stepz"),
        ({"hyperparams": {"seed": 3}}, "hyperparams.seed"),
        ({"policy_kwargs": {"activation_fn": "nn.NoSuchLayer"}}, "policy_kwargs.activation_fn"),
        ({"policy_kwargs": {"activation_fn": "os.system"}}, "policy_kwargs.activation_fn"),
        ({"policy_kwargs": {"net_arch": ["wide"]}}, "policy_kwargs.net_arch"),
        ({"policy_kwargs": {"net_arch": [16], "bogus": 1}}, "policy_kwargs.bogus"),
        ({"normalize": {"norm_rewrd": False}}, "normalize.norm_rewrd"),
        ({"normalize": "yes"}, "normalize"),
        ({"n_envs": "8"}, "n_envs"),
        ({"n_envs": 0}, "n_envs"),
        ({"policy": "LstmPolicy"}, "policy"),
    ],
)
def test_config_errors_name_the_key(change, key):
    cfg = _base_config()
    cfg.update(change)
    with pytest.raises(ValueError) as err:
        validate_config(cfg)
    assert isinstance(err.value, ConfigError)
    assert str(err.value).startswith(f"{key}:"), str(err.value)


def test_config_sac_kwargs_checked_against_sac_signature():
    cfg = _base_config(algo="sac", hyperparams={"n_steps": 32})  # PPO's n_steps is SAC's n-step return: an int
    validate_config(cfg)
    cfg["hyperparams"] = {"n_epochs": 10}  # a PPO-only keyword
    with pytest.raises(ValueError, match=r"^hyperparams\.n_epochs:"):
        validate_config(cfg)


def test_config_values_resolved(tmp_path):
    text = yaml.safe_dump(_base_config()).replace("0.0003", "lin_3e-4")
    text += "seed: 7\n"
    path = tmp_path / "c.yaml"
    path.write_text(text + "eval_episodes: 1e1\n")
    cfg = load_config(path, ["hyperparams.clip_range=lin_0.2", "hyperparams.ent_coef=1e-3", "n_envs=2"])
    assert cfg["seed"] == 7 and cfg["n_envs"] == 2 and cfg["eval_episodes"] == 10
    assert cfg["hyperparams"]["ent_coef"] == pytest.approx(1e-3)  # 1e-3 is a number, not a string
    kwargs = agent_config.algorithm_kwargs(cfg)
    assert kwargs["learning_rate"](1.0) == pytest.approx(3e-4)
    assert kwargs["learning_rate"](0.5) == pytest.approx(1.5e-4)
    assert kwargs["clip_range"](0.25) == pytest.approx(0.05)
    import torch.nn as nn

    assert agent_config.policy_kwargs(cfg)["activation_fn"] is nn.Tanh
    assert cfg["device"] == "cpu"  # default device


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_configs_validate(path):
    cfg = load_config(path)
    algo = agent_config.algorithm_class(cfg["algo"])
    assert cfg["env_id"].startswith("abd_gym/")
    assert path.stem.split("_")[-1] == cfg["algo"], "config files are named <task>_<algo>.yaml"
    spec = gym.spec(cfg["env_id"])
    assert spec.reward_threshold is not None, "every task needs a reward_threshold for the summary"
    assert algo is not None and cfg["device"] == "cpu"


@pytest.mark.parametrize("path", sorted((CONFIG_DIR / "gpu").glob("*.yaml")), ids=lambda p: p.stem)
def test_gpu_configs_validate(path):
    cfg = load_config(path)
    assert agent_config.algorithm_class(cfg["algo"]) is not None
    assert path.stem.split("_")[-1] == cfg["algo"], "config files are named <task>_<algo>.yaml"
    assert cfg["device"] == "cuda:0" and cfg["n_envs"] >= 1024  # made for a GPU's batch
    assert cfg["eval_freq"] > 0, "the time-to-solve table needs periodic evaluations"
    assert load_config(f"gpu/{path.stem}") == cfg  # found by name, as abd-gym-train resolves it
    assert agent_config.config_name(path) == f"gpu_{path.stem}"  # runs and summaries tell it from the CPU config


def test_every_task_has_a_gpu_config():
    from abd_gym.vector.registration import env_ids

    tasks = {load_config(p)["env_id"] for p in (CONFIG_DIR / "gpu").glob("*.yaml")}
    assert set(env_ids()) <= tasks


# ---------------------------------------------------------------------------------------------
# the SB3 adapter


def _random_actions(venv, rng):
    space = venv.action_space
    if isinstance(space, gym.spaces.Discrete):
        return rng.integers(0, space.n, size=venv.num_envs)
    return rng.uniform(space.low, space.high, size=(venv.num_envs, *space.shape)).astype(space.dtype)


def test_adapter_api_and_terminal_observation():
    n = 6
    venv = make_vec_env(CARTPOLE, n, seed=3)
    assert isinstance(venv, VecEnv) and venv.autoreset_mode == AutoresetMode.SAME_STEP
    assert venv.num_envs == n
    obs = venv.reset()
    assert isinstance(obs, np.ndarray) and obs.shape == (n, *venv.observation_space.shape)
    rng = np.random.default_rng(0)
    done_steps = 0
    for _ in range(200):
        obs, rew, dones, infos = venv.step(_random_actions(venv, rng))
        assert obs.shape == (n, *venv.observation_space.shape) and obs.dtype == venv.observation_space.dtype
        assert rew.shape == (n,) and rew.dtype == np.float32
        assert dones.shape == (n,) and dones.dtype == bool
        assert isinstance(infos, list) and len(infos) == n and all(isinstance(d, dict) for d in infos)
        has_terminal = np.array(["terminal_observation" in d for d in infos])
        np.testing.assert_array_equal(has_terminal, dones)  # exactly the done worlds
        for i in np.flatnonzero(dones):
            term = infos[i]["terminal_observation"]
            assert term.shape == venv.observation_space.shape
            assert not np.array_equal(term, obs[i]), "the returned obs of a done world is the reset obs"
            assert isinstance(infos[i]["TimeLimit.truncated"], bool)
            done_steps += 1
    assert done_steps > 0, "random play should end some episodes in 200 steps"
    venv.close()


def test_adapter_same_step_and_next_step_agree():
    """The native env in SAME_STEP mode and in NEXT_STEP mode (reset through reset_mask) give SB3 the same stream."""
    n, steps = 4, 150
    kwargs = {"vectorization_mode": "vector_entry_point", "device": "cpu", "max_episode_steps": 30}
    same = GymnasiumVecEnv(gym.make_vec(CARTPOLE, n, autoreset_mode=AutoresetMode.SAME_STEP, **kwargs))
    nxt = GymnasiumVecEnv(gym.make_vec(CARTPOLE, n, **kwargs))  # the env's default: NEXT_STEP
    assert same.autoreset_mode == AutoresetMode.SAME_STEP and nxt.autoreset_mode == AutoresetMode.NEXT_STEP
    same.seed(11)
    nxt.seed(11)
    np.testing.assert_array_equal(same.reset(), nxt.reset())
    rng = np.random.default_rng(1)
    truncations = terminations = 0
    for _ in range(steps):
        a = rng.uniform(-1, 1, size=(n, 1)).astype(np.float32)
        o1, r1, d1, i1 = same.step(a)
        o2, r2, d2, i2 = nxt.step(a)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(d1, d2)
        for i in np.flatnonzero(d1):
            np.testing.assert_array_equal(i1[i]["terminal_observation"], i2[i]["terminal_observation"])
            assert i1[i]["TimeLimit.truncated"] == i2[i]["TimeLimit.truncated"]
            truncations += i1[i]["TimeLimit.truncated"]
            terminations += not i1[i]["TimeLimit.truncated"]
            x, _, theta, _ = i1[i]["terminal_observation"]
            if i1[i]["TimeLimit.truncated"]:
                assert abs(x) <= 2.4 and abs(theta) <= 0.2
            else:
                assert abs(x) > 2.4 or abs(theta) > 0.2
            assert np.all(np.abs(o1[i]) <= 0.05), "a done world starts its next episode"
    assert truncations > 0 and terminations > 0


def test_adapter_refuses_next_step_env_without_partial_reset():
    env = gym.make_vec("CartPole-v1", 4, vectorization_mode="vector_entry_point")  # NEXT_STEP, no reset_mask
    with pytest.raises(ValueError, match="SAME_STEP"):
        GymnasiumVecEnv(env)


def test_partial_reset_check_allows_float_rounding_only():
    # a GPU env's step and reset compute observations in different kernels (~1e-7 apart); a world
    # that was reset moves by far more, and integer observations must match exactly
    from abd_gym.agents.sb3_vec_env import _unchanged

    obs = np.array([[0.3, -1.2], [2.0, 0.01]], dtype=np.float32)
    assert _unchanged(obs, obs * (1 + 6e-8))
    assert not _unchanged(obs, obs + np.float32(1e-3))
    assert _unchanged(np.array([1, 2]), np.array([1, 2])) and not _unchanged(np.array([1, 2]), np.array([1, 3]))
    assert not _unchanged(np.array([True, False]), np.array([True, True]))


def test_adapter_under_vecmonitor_and_vecnormalize():
    n = 5
    base = make_vec_env(CARTPOLE, n, seed=0)
    venv = VecNormalize(VecMonitor(base), gamma=0.99)
    obs = venv.reset()
    rng = np.random.default_rng(2)
    raw_return = np.zeros(n)
    raw_length = np.zeros(n, dtype=int)
    episodes = 0
    for _ in range(300):
        obs, rew, dones, infos = venv.step(_random_actions(venv, rng))
        raw = venv.get_original_reward()
        raw_return += raw
        raw_length += 1
        assert np.all(np.abs(obs) <= venv.clip_obs)
        for i in np.flatnonzero(dones):
            ep = infos[i]["episode"]
            assert ep["r"] == pytest.approx(raw_return[i], rel=1e-5)
            assert ep["l"] == raw_length[i]
            # VecNormalize normalises the terminal observation like the others
            orig = venv.unnormalize_obs(infos[i]["terminal_observation"])
            assert orig.shape == base.observation_space.shape
            raw_return[i] = 0
            raw_length[i] = 0
            episodes += 1
    assert episodes >= n
    assert np.all(np.abs(venv.obs_rms.mean) < 10) and venv.obs_rms.count > 300 * n - 1
    venv.close()


def test_adapter_seed_attrs_methods():
    venv = make_vec_env(CARTPOLE, 3)
    venv.seed(5)
    a = venv.reset()
    venv.seed(5)
    b = venv.reset()
    venv.seed(6)
    c = venv.reset()
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert venv.get_attr("render_mode") == [None, None, None]
    assert venv.get_attr("num_envs", indices=[0, 2]) == [3, 3]
    assert venv.env_is_wrapped(VecMonitor) == [False, False, False]
    with pytest.raises(AttributeError):
        venv.get_attr("no_such_attribute")
    assert venv.has_attr("no_such_attribute") is False
    venv.close()


class _TinyVectorEnv(gym.vector.VectorEnv):
    """A native SAME_STEP vector env in torch: a counter that ends after 3 + world-index steps."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs=3):
        import torch

        self.torch = torch
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.single_action_space = gym.spaces.Box(-1, 1, (1,), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.render_mode = "rgb_array"
        self.t = torch.zeros(num_envs)
        self.limit = 3 + torch.arange(num_envs, dtype=torch.float32)
        self.calls = 0

    def _obs(self):
        return self.torch.stack([self.t, self.limit], dim=1)

    def reset(self, *, seed=None, options=None):
        self.t.zero_()
        return self._obs(), {}

    def step(self, actions):
        assert isinstance(actions, self.torch.Tensor) and actions.shape == (self.num_envs, 1)
        self.t += 1
        done = self.t >= self.limit
        info = {}
        if done.any():
            final = self._obs().clone()
            info = {"final_obs": final, "_final_obs": done.numpy(),
                    "final_info": {"is_success": done.numpy(), "_is_success": done.numpy()},
                    "_final_info": done.numpy()}
            self.t[done] = 0
        return self._obs(), self.torch.ones(self.num_envs), done, self.torch.zeros_like(done), info

    def render(self):
        return tuple(np.full((4, 5, 3), i, dtype=np.uint8) for i in range(self.num_envs))

    def bump(self, k):
        self.calls += k
        return self.calls


def test_adapter_torch_native_env_info_render_and_methods():
    venv = GymnasiumVecEnv(_TinyVectorEnv(3))
    obs = venv.reset()
    assert isinstance(obs, np.ndarray) and obs.shape == (3, 2)
    seen = []
    for step in range(1, 6):
        obs, rew, dones, infos = venv.step(np.zeros((3, 1), np.float32))
        assert isinstance(rew, np.ndarray) and isinstance(dones, np.ndarray)
        for i in range(3):
            if dones[i]:
                assert infos[i]["terminal_observation"][0] == 3 + i
                assert infos[i]["is_success"] is True
                assert infos[i]["TimeLimit.truncated"] is False
                assert obs[i, 0] == 0
                seen.append((step, i))
            else:
                assert infos[i] == {}
    assert seen == [(3, 0), (4, 1), (5, 2)]
    images = venv.get_images()
    assert len(images) == 3 and [int(im[0, 0, 0]) for im in images] == [0, 1, 2]
    assert venv.render().shape == (8, 10, 3)  # SB3 tiles the three frames 2 x 2
    assert venv.env_method("bump", 2, indices=[0, 1]) == [2, 2]  # one batched env: called once
    venv.set_attr("calls", 10)
    assert venv.get_attr("calls") == [10, 10, 10]
    with pytest.raises(ValueError):
        venv.set_attr("calls", 0, indices=[1])  # one value shared by all worlds


# ---------------------------------------------------------------------------------------------
# training through the CLI code path, save, reload, evaluate


def _tiny_config(tmp_path: Path) -> Path:
    cfg = {
        "env_id": CARTPOLE,
        "algo": "ppo",
        "n_envs": 4,
        "n_timesteps": 2048,
        "normalize": True,
        "seed": 3,
        "eval_episodes": 4,
        "checkpoint_freq": 1024,
        "hyperparams": {"n_steps": 128, "batch_size": 128, "n_epochs": 2, "learning_rate": "lin_1e-3"},
        "policy_kwargs": {"net_arch": [16], "activation_fn": "nn.Tanh"},
    }
    path = tmp_path / "tiny_ppo.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_train_save_reload_evaluate(tmp_path):
    from abd_gym.agents import evaluate as agent_eval
    from abd_gym.agents import train as agent_train
    from abd_gym.agents.common import build_eval_env

    run_dir = tmp_path / "run"
    args = agent_train.parse_args(
        [str(_tiny_config(tmp_path)), "--run-dir", str(run_dir), "--seed", "4", "--eval-episodes", "3",
         "--no-progress", "hyperparams.gamma=0.98"]
    )
    cfg, name = agent_train.config_from_args(args)
    assert name == "tiny_ppo" and cfg["seed"] == 4 and cfg["eval_episodes"] == 3
    assert cfg["hyperparams"]["gamma"] == 0.98
    summary, model = agent_train.train(cfg, config_name=name, run_dir=run_dir, progress_bar=False,
                                       return_model=True)

    for f in ("model.zip", "vecnormalize.pkl", "summary.json", "config.yaml"):
        assert (run_dir / f).is_file(), f
    assert list((run_dir / "tensorboard").rglob("events.out.tfevents.*"))
    assert list((run_dir / "checkpoints").glob("model_*_steps.zip"))
    on_disk = json.loads((run_dir / "summary.json").read_text())
    assert on_disk["timesteps"] >= 2048 and on_disk["eval_episodes"] == 3
    for key in ("config", "wall_time_s", "device", "mean_return", "std_return", "reward_threshold", "solved"):
        assert key in on_disk, key
    assert on_disk["reward_threshold"] == gym.spec(CARTPOLE).reward_threshold
    assert on_disk["solved"] == (on_disk["mean_return"] >= on_disk["reward_threshold"])
    assert on_disk["config"]["hyperparams"]["gamma"] == 0.98

    # the reloaded policy acts like the trained one on the same (normalised) observations
    cfg2, loaded, vecnorm = agent_eval.load_run(run_dir)
    env = build_eval_env(cfg2, num_envs=4, seed=123, vecnormalize=vecnorm)
    obs = env.reset()
    rng = np.random.default_rng(0)
    batches = [obs]
    for _ in range(20):
        obs, *_ = env.step(_random_actions(env, rng))
        batches.append(obs)
    obs = np.concatenate(batches)
    a1, _ = model.predict(obs, deterministic=True)
    a2, _ = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(a1, a2)
    assert env.training is False and env.norm_reward is False
    env.close()

    # evaluating the saved run reproduces the summary's evaluation exactly (same seeds, same weights)
    result = agent_eval.evaluate_run(run_dir, episodes=3)
    assert result["mean_return"] == pytest.approx(summary["mean_return"])
    assert result["episode_returns"] == pytest.approx(summary["episode_returns"])

    # the CLI entry points: a bad override fails cleanly; evaluate writes its JSON
    assert agent_train.main([str(_tiny_config(tmp_path)), "hyperparams.n_steps=lots", "--no-progress"]) == 2
    out = tmp_path / "eval.json"
    video = tmp_path / "v.gif"
    argv = [str(run_dir), "--episodes", "2", "--json", str(out),
            "--video", str(video), "--video-episodes", "2", "--video-max-steps", "6"]
    assert agent_eval.main(argv) == 0
    result = json.loads(out.read_text())
    assert result["eval_episodes"] == 2
    assert result["video"]["frames"] == 14  # 2 episodes cut at 6 steps: first state + 6 steps each
    assert result["video"]["episode_returns"] == [None, None]
    from PIL import Image

    with Image.open(video) as gif:
        assert gif.size[0] >= 100 and gif.n_frames > 1


def test_results_table(tmp_path):
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    for k, (ret, thr) in enumerate([(500.0, 475.0), (12.5, 475.0)]):
        d = tmp_path / "runs" / f"r{k}"
        d.mkdir(parents=True)
        summary = {"config_name": f"cfg{k}", "env_id": "X-v0", "algo": "ppo", "seed": k, "timesteps": 1000 * (k + 1),
                   "wall_time_s": 12.0, "device": "cpu", "mean_return": ret, "std_return": 1.5,
                   "eval_episodes": 10, "reward_threshold": thr, "solved": ret >= thr, "run_dir": str(d),
                   "command": f"python -m abd_gym.agents.train cfg{k}"}
        (d / "summary.json").write_text(json.dumps(summary))
    out = tmp_path / "table.md"
    subprocess.run([sys.executable, str(root / "scripts" / "results_table.py"), str(tmp_path / "runs"),
                    "-o", str(out), "--copy-to", str(tmp_path / "copies")], check=True)
    text = out.read_text()
    rows = [line for line in text.splitlines() if line.startswith("| cfg")]
    assert len(rows) == 2
    assert "500.0 ± 1.5" in rows[0] and rows[0].rstrip(" |").endswith("yes")
    assert "12.5 ± 1.5" in rows[1] and rows[1].rstrip(" |").endswith("no")
    assert "`python -m abd_gym.agents.train cfg1`" in text
    assert sorted(p.name for p in (tmp_path / "copies").iterdir()) == ["r0.json", "r1.json"]


# ---------------------------------------------------------------------------------------------
# learning


@pytest.mark.slow
def test_ppo_learns_cartpole(tmp_path):
    """PPO on CartPole (the shipped config, fewer steps) ends well above a random policy."""
    from abd_gym.agents import train as agent_train
    from abd_gym.agents.common import build_eval_env, evaluate

    path = CONFIG_DIR / "cartpole_ppo.yaml"
    cfg = load_config(path, ["n_timesteps=32000", "eval_episodes=10"])
    summary = agent_train.train(cfg, config_name="cartpole_ppo", run_dir=tmp_path / "run", progress_bar=False)

    class _Random:
        def __init__(self, space):
            self.space = space

        def predict(self, obs, state=None, episode_start=None, deterministic=False):
            return np.stack([self.space.sample() for _ in range(len(obs))]), None

    env = build_eval_env(cfg, num_envs=10, seed=99)
    env.action_space.seed(0)
    random_return = evaluate(_Random(env.action_space), env, 20)["mean_return"]
    env.close()
    print(f"random {random_return:.1f}, trained {summary['mean_return']:.1f} in {summary['wall_time_s']:.1f} s")
    assert summary["mean_return"] >= max(4 * random_return, random_return + 100), (random_return, summary)
