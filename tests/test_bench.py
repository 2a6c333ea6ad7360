"""The benchmark commands at tiny sizes on the CPU: each writes its JSON with every field (the
numbers themselves are measured on a GPU; see README, Performance)."""
import importlib.util
import json
import math

import pytest

from abd_gym import bench

SIM_FIELDS = {"case", "num_worlds", "steps", "dt", "dtype", "device", "seconds", "steps_per_second",
              "world_steps_per_second", "newton_iterations", "newton_factorizations", "joint_residual",
              "converged_fraction", "reuse_factor", "envelope",
              "failed_worlds", "threads", "block_dim", "memory_bytes_per_world"}  # fmt: skip


def _load(path):
    with open(path) as f:
        return json.load(f)


def test_bench_worlds_and_envs(tmp_path):
    bench.main(["--cases", "cartpole", "--worlds", "1,3", "--steps", "2", "--envs", "--tasks", "CartPole-v0",
                "--env-worlds", "2", "--out", str(tmp_path)])  # fmt: skip
    r = _load(tmp_path / "bench.json")
    assert [row["num_worlds"] for row in r["simulator"]] == [1, 3]
    for row in r["simulator"]:
        assert SIM_FIELDS <= set(row) and row["world_steps_per_second"] > 0 and row["failed_worlds"] == 0
        assert row["joint_residual"] < 1e-4 and 0 < row["memory_bytes_per_world"] < 10_000
    assert abs(r["accuracy"][0]["period_error"]) < 0.05  # dt 0.01, implicit Euler, lowest mode
    (env,) = r["envs"]
    assert env["env_steps_per_second"] > 0 and env["raw_steps_per_second"] > 0
    assert env["env_over_raw"] == pytest.approx(env["env_steps_per_second"] / env["raw_steps_per_second"])
    assert env["env_over_physics"] == pytest.approx(env["env_steps_per_second"] / env["physics_steps_per_second"])


def test_bench_threads(tmp_path):
    bench.main(["threads", "--cases", "cartpole", "--worlds", "3", "--threads", "all,1", "--block-dims", "32",
                "--steps", "2", "--out", str(tmp_path)])  # fmt: skip
    rows = _load(tmp_path / "threads.json")["rows"]
    assert [(row["threads"], row["block_dim"]) for row in rows] == [(3, 32), (1, 32)]
    assert all(SIM_FIELDS <= set(row) for row in rows)


def test_bench_compare_without_mujoco_warp(tmp_path):
    bench.main(["compare", "--cases", "cartpole,fourbar", "--worlds", "2", "--ours-only", "3", "--steps", "2",
                "--scratch", "global,lanes", "--repeat", "2", "--accuracy-worlds", "2",
                "--out", str(tmp_path)])  # fmt: skip
    result = _load(tmp_path / "compare.json")
    assert result["repeat"] == 2 and result["steps"] == 2  # each engine timed best-of-2, on record
    assert result["mjw_integrators"] == ["Euler", "RK4"]
    rows = result["rows"]
    assert [(row["case"], row["num_worlds"], row["scratch"]) for row in rows][:4] == [
        ("cartpole", 2, "global"), ("cartpole", 2, "lanes"), ("cartpole", 3, "global"), ("cartpole", 3, "lanes")]
    for row in rows:
        assert {"case", "num_worlds", "scratch", "abd_gym", "mujoco_warp", "ratio", "joint_residual",
                "memory_bytes_per_world", "abd_gym_joint_residual", "abd_gym_loop_closure",
                "abd_gym_limit_penetration", "abd_gym_nonfinite"} <= set(row)  # fmt: skip
        assert row["abd_gym"] > 0 and row["abd_gym_nonfinite"] == 0
        assert row["abd_gym_joint_residual"] < 1e-4 and row["abd_gym_limit_penetration"] < 1e-3  # m
    assert math.isnan(rows[2]["mujoco_warp"])  # ours alone
    if importlib.util.find_spec("mujoco_warp") is None:
        assert math.isnan(rows[0]["mujoco_warp_rk4"]) and math.isnan(rows[0]["ratio_euler"])
    assert math.isnan(rows[0]["abd_gym_loop_closure"])  # the cart-pole has no loop
    assert 0 < rows[-1]["abd_gym_loop_closure"] < 1e-4  # the four-bar's closing hinge holds [m]
    assert "| fourbar | 3 |" in (tmp_path / "compare.md").read_text()


def test_bench_accuracy(tmp_path):
    bench.main(["accuracy", "--cases", "cartpole", "--dts", "0.02", "--dtypes", "float64", "--tols", "1e-5",
                "--integrators", "implicit_euler,bdf2", "--worlds", "2", "--reference-dt", "0.002",
                "--out", str(tmp_path)])  # fmt: skip
    r = _load(tmp_path / "accuracy.json")
    ours = {row["integrator"]: row for row in r["rows"] if row["engine"] == "abd_gym"}
    assert set(ours) == {"implicit_euler", "bdf2"}
    for row in ours.values():
        assert {"case", "dt", "dtype", "tol", "reuse_factor", "error_final", "error_max", "joint_residual",
                "energy_drift", "world_steps_per_second"} <= set(row)  # fmt: skip
        assert row["reuse_factor"] is False  # float64's default: a factorisation per Newton iteration
        assert row["joint_residual"] < 1e-4
    # second order: at dt 0.02 BDF2 tracks the reference better than implicit Euler
    assert ours["bdf2"]["error_max"] < ours["implicit_euler"]["error_max"]
    assert ours["implicit_euler"]["energy_drift"] < 0  # implicit Euler only loses energy
    assert all(row["world_seconds_per_second"] == pytest.approx(row["world_steps_per_second"] * 0.02) for row in ours.values())
    if importlib.util.find_spec("mujoco_warp") is None:
        assert r["equal_error"] == []  # nothing to compare against


def test_equal_error_interpolates_mujoco_warp_in_simulated_time():
    """equal_error: MuJoCo Warp's world-seconds/s at our error, log-log between its dt points,
    first-order extrapolation below its smallest error, its largest-dt point above its largest."""
    from abd_gym.bench_accuracy import equal_error

    def row(engine, dt, err, sps):
        return dict(engine=engine, case="cartpole", integrator="x", dt=dt, dtype="float32", tol=None,
                    reuse_factor=None, error_max=err, world_steps_per_second=sps)  # fmt: skip

    mjw = [row("mujoco_warp", 0.01, 4e-2, 1e7), row("mujoco_warp", 0.005, 2e-2, 1e7)]  # 1e5 and 5e4 world-s/s
    ours = [row("abd_gym", 0.01, 2.8284271e-2, 5e6), row("abd_gym", 0.01, 1e-2, 5e6), row("abd_gym", 0.02, 1.0, 5e6)]
    got = equal_error(mjw + ours)
    assert [g["note"] for g in got] == ["", "extrapolated", "beyond"]
    assert got[0]["mujoco_warp_world_seconds_per_second"] == pytest.approx(5e4 * 2**0.5, rel=1e-6)  # geometric middle
    assert got[1]["mujoco_warp_world_seconds_per_second"] == pytest.approx(2.5e4)  # error ∝ dt below 2e-2
    assert got[2]["mujoco_warp_world_seconds_per_second"] == pytest.approx(1e5)
    assert got[0]["ratio"] == pytest.approx(5e4 / (5e4 * 2**0.5), rel=1e-6)
    assert equal_error(ours) == []  # without MuJoCo Warp rows: nothing to compare


def test_memory_counts_each_allocation_once():
    """memory_bytes counts arrays that own memory: the solver's flat views of its scratch (the same
    memory as g, H and Δq) add nothing."""
    import warp as wp

    from abd_gym import mechanisms
    from abd_gym.simulator import Simulator

    sim = Simulator(mechanisms.double_pendulum(), num_worlds=4)
    s = sim.solver
    assert s.H_flat.ptr == s.H.ptr and s.H_flat.size == s.H.size
    owned = {a.ptr: a.capacity for a in vars(s).values() if isinstance(a, wp.array) and a.deleter is not None}
    assert sim.memory_bytes()["solver"] == sum(owned.values())
    assert s.H.ptr in owned and s.H_flat.deleter is None


def test_env_rate_keeps_the_fastest_window():
    from abd_gym.envs.bench_envs import env_steps_per_second

    rates = env_steps_per_second("CartPole-v0", 2, 3, "cpu", raw=True, repeat=2)
    assert len(rates) == 3 and all(r > 0 and math.isfinite(r) for r in rates)
    with pytest.raises(ValueError, match="repeat"):
        env_steps_per_second("CartPole-v0", 2, 3, "cpu", repeat=0)


def test_timestamps_fill_their_ring_in_order():
    """abd_gym.timestamps: each mark takes the ring's next slot (the GPU's global timer, in ns; 0
    on the CPU), clear empties it, and a ring that overflowed says so."""
    import numpy as np
    import warp as wp

    from abd_gym.timestamps import Stamps

    device = "cuda:0" if wp.is_cuda_available() else "cpu"
    st = Stamps(device, 3)
    for _ in range(3):
        st.mark()
    t = st.read()
    assert t.dtype == np.int64 and len(t) == 3 and np.all(np.diff(t) >= 0)
    assert (t > 0).all() if device != "cpu" else (t == 0).all()
    st.clear()
    assert len(st.read()) == 0
    for _ in range(4):
        st.mark()
    with pytest.raises(RuntimeError, match="4 stamps overflowed a ring of 3"):
        st.read()


def test_bench_robustness(tmp_path):
    md = tmp_path / "robustness.md"
    bench.main(["robustness", "--cases", "prismatic_slam,strength_1e+08", "--worlds", "2", "--steps", "3",
                "--integrators", "implicit_euler", "--dtypes", "float64", "--out", str(tmp_path), "--md", str(md)])  # fmt: skip
    rows = _load(tmp_path / "robustness.json")["rows"]
    assert [(r["case"], r["worlds"], r["steps"]) for r in rows] == [("prismatic_slam", 2, 3), ("strength_1e+08", 2, 3)]
    for r in rows:
        assert {"reported", "silent", "gap_mm", "iterations_mean", "worst_gain"} <= set(r)
        assert r["iterations_max"] >= 1 and r["gap_mm"] < 1.0
    assert "overshoot_over_bound" in rows[0] and "overshoot_over_bound" not in rows[1]
    assert "| prismatic_slam | 0.01 | implicit_euler | float64 | 2 × 3 |" in md.read_text()


def test_bench_classics_against_gymnasium(tmp_path):
    """The classics' table: abd_gym's env and Gymnasium's own, the same task, finite rates, JSON."""
    pytest.importorskip("mujoco")
    from abd_gym.envs import bench_classics

    result = bench_classics.main(["--tasks", "InvertedPendulum-v5", "--worlds", "2", "--steps", "2", "--gym-steps", "1",
                                  "--repeat", "1", "--engines", "abd_gym,gymnasium", "--out", str(tmp_path)])  # fmt: skip
    (row,) = result["rows"]
    assert row["abd_gym"] > 0 and row["gymnasium"] > 0 and math.isnan(row["mujoco_warp"])
    assert json.loads((tmp_path / "classics.json").read_text())["rows"][0]["task"] == "InvertedPendulum-v5"


def test_bench_envs_per_scratch(tmp_path):
    from abd_gym.envs import bench_envs

    bench_envs.main(["--tasks", "CartPole-v0", "--worlds", "2", "--steps", "2", "--scratch", "auto,global",
                     "--out", str(tmp_path)])  # fmt: skip
    rows = json.loads((tmp_path / "envs.json").read_text())["rows"]
    assert [r["scratch"] for r in rows] == ["auto", "global"] and all(r["env_steps_per_second"] > 0 for r in rows)
