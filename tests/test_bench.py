"""The benchmark commands at tiny sizes on the CPU: each writes its JSON with every field (the
numbers themselves are measured on a GPU; see README, Performance)."""
import importlib.util
import json
import math

import numpy as np
import pytest

from abd_gym.bench import speed as bench

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
        assert {"case", "dt", "dtype", "tol", "reuse_factor", "diverged", "error_final", "error_max", "error_max_slide",
                "joint_residual", "energy_drift", "world_steps_per_second"} <= set(row)  # fmt: skip
        assert row["reuse_factor"] is False  # the default: a factorisation per Newton iteration
        assert row["joint_residual"] < 1e-4
        assert not row["diverged"] and row["error_max_slide"] is not None  # the cart's slide, in m
    # second order: at dt 0.02 BDF2 tracks the reference better than implicit Euler
    assert ours["bdf2"]["error_max"] < ours["implicit_euler"]["error_max"]
    assert ours["implicit_euler"]["energy_drift"] < 0  # implicit Euler only loses energy
    assert all(row["world_seconds_per_second"] == pytest.approx(row["world_steps_per_second"] * 0.02) for row in ours.values())
    theirs = {row["integrator"]: row for row in r["rows"] if row["engine"] == "mujoco_warp"}
    assert set(theirs) == {"Euler", "implicitfast", "RK4"}
    assert all(0 < row["error_max"] < 0.5 and not row["diverged"] for row in theirs.values())
    # fourth order against first: RK4 at dt 0.02 is far closer to the reference than Euler
    assert theirs["RK4"]["error_max"] < 1e-2 * theirs["Euler"]["error_max"]
    summary = r["summary"]
    assert [(s["case"], s["error"]) for s in summary] == [("cartpole", e) for e in (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)]
    for s in summary:
        assert {"abd_gym", "mujoco_warp", "ratio", "ahead"} <= set(s) and s["ahead"]
    if importlib.util.find_spec("mujoco_warp") is None:
        assert all(math.isnan(row["world_steps_per_second"]) for row in theirs.values())  # not timed
        assert all(s["mujoco_warp"] is None and s["ratio"] is None for s in summary)
    # against each engine's own converged run: MuJoCo's reference is its own, ours a float64 BDF2 run;
    # the two converged models agree closely on this stable, limit-free second
    assert all(row["own_error_max"] == row["error_max"] for row in theirs.values())
    assert all(0 < row["own_error_max"] < 0.5 for row in ours.values())
    assert r["model_gap"]["cartpole"]["error_max"] < 1e-3 and r["limited_reference_worlds"] == {"cartpole": 0.0}
    assert r["complete"] and len(r["summary_own"]) == len(summary)
    # the plot: written where matplotlib is installed (accuracy.png by the run, a saved result by
    # scripts/plot_accuracy.py), nothing and False without it
    from abd_gym.bench.accuracy import plot

    has_mpl = importlib.util.find_spec("matplotlib") is not None
    assert (tmp_path / "accuracy.png").is_file() == has_mpl
    assert plot(r, str(tmp_path / "again.png"), key="error_max", title="t") == has_mpl
    assert (tmp_path / "again.png").is_file() == has_mpl


def test_equal_error_summary_interpolates_in_simulated_time():
    """At each error level: each curve's world-seconds/s interpolated log-log between its dt points,
    "not reached" below its smallest error, its fastest point as a lower bound above its largest;
    the fastest setting of each engine compared."""
    from abd_gym.bench.accuracy import equal_error_summary, rate_at

    def row(engine, integrator, dt, err, sps):
        return dict(engine=engine, case="cartpole", integrator=integrator, dt=dt, dtype="float32", tol=1e-5,
                    reuse_factor=False, error_max=err, world_steps_per_second=sps)  # fmt: skip

    assert rate_at([(2e-2, 5e4), (4e-2, 1e5)], 2.8284271e-2)[0] == pytest.approx(5e4 * 2**0.5, rel=1e-6)
    assert rate_at([(2e-2, 5e4), (4e-2, 1e5)], 1e-2) is None  # not reached
    assert rate_at([(2e-2, 5e4), (4e-2, 1e5)], 1e-1) == (1e5, ">=")
    mj = [row("mujoco_warp", "Euler", 0.01, 4e-2, 1e7), row("mujoco_warp", "Euler", 0.005, 2e-2, 1e7),
          row("mujoco_warp", "RK4", 0.01, 1e-6, 2e6)]  # fmt: skip
    ours = [row("abd_gym", "bdf2", 0.02, 1e-3, 1e7), row("abd_gym", "bdf2", 0.04, 1e-1, 1e7)]
    got = {s["error"]: s for s in equal_error_summary(mj + ours, levels=(1e-3, 3e-2))}
    # at 3e-2 MuJoCo's Euler (rate ∝ error between its points: 7.5e4) beats its RK4 (2e4, a lower
    # bound); ours interpolates 2e5 · 30^(log 2 / log 100) = 3.3e5
    assert got[3e-2]["mujoco_warp"]["integrator"] == "Euler"
    assert got[3e-2]["mujoco_warp"]["world_seconds_per_second"] == pytest.approx(7.5e4, rel=1e-6)
    assert got[3e-2]["abd_gym"]["world_seconds_per_second"] == pytest.approx(2e5 * 30 ** (np.log(2) / np.log(100)), rel=1e-6)
    assert got[3e-2]["ahead"] == "abd_gym" and got[3e-2]["ratio"] > 1
    # at 1e-3 only RK4 reaches (a lower bound): ours 2e5 against ≥ 2e4 is undecided
    assert got[1e-3]["mujoco_warp"] == dict(integrator="RK4", world_seconds_per_second=2e4, bound=">=")
    assert got[1e-3]["ahead"].startswith("undecided (MuJoCo")
    assert all(s["mujoco_warp"] is None for s in equal_error_summary(ours))  # nothing to compare against


def test_memory_counts_each_allocation_once():
    """memory_bytes counts arrays that own memory: the solver's flat views of its scratch (the same
    memory as g, H and Δq) add nothing."""
    import warp as wp

    from abd_gym.sim import mechanisms
    from abd_gym.sim.simulator import Simulator

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
    """abd_gym.core.timestamps: each mark takes the ring's next slot (the GPU's global timer, in ns; 0
    on the CPU), clear empties it, and a ring that overflowed says so."""
    import numpy as np
    import warp as wp

    from abd_gym.core.timestamps import Stamps

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
        assert {"reported", "silent", "gap_mm", "iterations_mean", "worst_gain", "worst_step_gain", "substeps"} <= set(r)
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


def test_cpu_compare_script_times_both_engines(tmp_path, capsys, script):
    """scripts/cpu_compare.py: abd_gym and MuJoCo C on the same starts, one row per case and size."""
    script = script("cpu_compare")
    out = tmp_path / "c.json"
    argv = ["--cases", "pendulum", "--worlds", "1,4", "--steps", "5", "--repeat", "1", "--threads", "2",
            "--json", str(out)]  # fmt: skip
    assert script.main(argv) == 0
    r = json.loads(out.read_text())
    assert r["threads"] == 2 and [row["num_worlds"] for row in r["rows"]] == [1, 4]
    for row in r["rows"]:
        assert row["abd_gym"] > 0 and row["mujoco_euler"] > 0 and row["mujoco_rk4"] > 0
        assert row["ratio_rk4"] == pytest.approx(row["abd_gym"] / row["mujoco_rk4"])
        assert row["mujoco_euler_nonfinite"] == 0 and row["abd_gym_nonfinite"] == 0
    assert "| pendulum | 4 |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        script.main(["--cases", "no_such_case"])


def test_bench_single_against_gymnasium(tmp_path, capsys):
    """``python -m abd_gym.bench single``: a row per task with finite rates, Gymnasium's env and the
    ratio where the task has one, the table printed and the JSON written."""
    rows = bench.main(["single", "--ids", "CartPole-v0,FourBar-v0", "--steps", "30", "--rounds", "1",
                       "--out", str(tmp_path)])  # fmt: skip
    cart, fourbar = rows
    assert cart["peer"] == "CartPole-v1" and cart["ratio"] == cart["steps_per_s"] / cart["peer_steps_per_s"]
    assert min(cart["steps_per_s"], cart["unwrapped_steps_per_s"], cart["peer_steps_per_s"]) > 0
    assert fourbar["peer"] is None and fourbar["ratio"] is None and fourbar["steps_per_s"] > 0
    saved = _load(tmp_path / "single.json")
    assert saved["benchmark"] == "single" and saved["rows"] == rows and saved["steps"] == 30
    assert "abd_gym/CartPole-v0" in capsys.readouterr().out
