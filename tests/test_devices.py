"""An unavailable device: one clear error naming the devices there are, before anything is made."""
import gymnasium as gym
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms
from abd_gym.core.devices import available_devices, resolve_device

MISSING = "cuda:99"  # no machine here has a hundred GPUs


def test_available_devices_include_the_cpu():
    assert "cpu" in available_devices()
    assert str(resolve_device("cpu")) == "cpu"


def test_simulator_and_envs_name_the_missing_device():
    message = rf"device '{MISSING}' is not available; available: .*cpu"
    with pytest.raises(ValueError, match=message):
        ag.Simulator(mechanisms.double_pendulum(), num_worlds=2, device=MISSING)
    with pytest.raises(ValueError, match=message):
        gym.make("abd_gym/CartPole-v0", device=MISSING)
    with pytest.raises(ValueError, match=message):
        gym.make_vec("abd_gym/CartPole-v0", num_envs=2, vectorization_mode="vector_entry_point", device=MISSING)


def test_train_cli_refuses_a_missing_device_before_the_run_folder(tmp_path, capsys):
    pytest.importorskip("stable_baselines3")
    from abd_gym.agents import train

    run_dir = tmp_path / "run"
    rc = train.main(["cartpole_ppo", "--device", MISSING, "--run-dir", str(run_dir), "--no-progress"])
    assert rc == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("abd-gym-train")]
    assert err == [f"abd-gym-train: error: device '{MISSING}' is not available; available: "
                   f"{', '.join(available_devices())}"]  # fmt: skip
    assert not run_dir.exists()


def test_train_function_refuses_a_missing_device_before_the_run_folder(tmp_path):
    pytest.importorskip("stable_baselines3")
    from abd_gym.agents.config import load_config
    from abd_gym.agents.train import train

    cfg = load_config("cartpole_ppo", {"device": MISSING})
    with pytest.raises(ValueError, match=f"device '{MISSING}' is not available"):
        train(cfg, config_name="cartpole_ppo", run_dir=tmp_path / "run", progress_bar=False)
    assert not (tmp_path / "run").exists()
