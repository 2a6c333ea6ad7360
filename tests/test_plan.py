"""The execution plan: what the library derives from device × batch × scene, overridden as one
object; the Simulator's own parameters are the physics and the Newton method."""
import dataclasses
import inspect

import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms
from abd_gym.solver.plan import ExecutionPlan, resolve_plan
from abd_gym.solver.solver import SolverSettings


def test_simulator_takes_the_physics_and_one_plan():
    params = [p for p in inspect.signature(ag.Simulator).parameters if p != "self"]
    assert len(params) <= 14 and "plan" in params
    assert [f.name for f in dataclasses.fields(SolverSettings)] == ["tol", "max_iterations", "max_line_search",
                                                                    "integrator", "reuse_factor", "quadratic_stop",
                                                                    "retry", "energy_gain"]  # fmt: skip


def test_resolved_plan_has_every_choice_and_resolves_to_itself():
    """Simulator.plan: every field derived (no None); resolving it again, or passing it (or a dict of
    its fields) to another simulator, gives the same plan."""
    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=4)
    plan = sim.plan
    assert all(getattr(plan, f.name) is not None for f in dataclasses.fields(plan))
    assert resolve_plan(plan, sim.model) == plan
    assert ag.Simulator(mechanisms.cartpole(), num_worlds=4, plan=plan).plan == plan
    assert ag.Simulator(mechanisms.cartpole(), num_worlds=4, plan=dataclasses.asdict(plan)).plan == plan
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.threads = 2


def test_an_override_keeps_the_rest_derived():
    """A plan naming one choice: that choice is kept, the others are derived as without it."""
    # a thread per world ("global"), where a thread count applies on every device
    default = ag.Simulator(mechanisms.double_pendulum(), num_worlds=4, plan=ExecutionPlan(scratch="global")).plan
    plan = ag.Simulator(mechanisms.double_pendulum(), num_worlds=4, plan=ExecutionPlan(scratch="global", threads=2)).plan
    assert plan.threads == 2 and dataclasses.replace(plan, threads=default.threads) == default
    with pytest.raises(ValueError, match="threads=2 applies to a thread per world"):
        ag.Simulator(mechanisms.double_pendulum(), num_worlds=4, plan=ExecutionPlan(scratch="lanes", threads=2))
    staged = ag.Simulator(mechanisms.double_pendulum(), num_worlds=4, plan={"fused": False}).plan
    assert not staged.fused and staged.scratch == "global" and not staged.one_launch


def test_plan_without_graph_steps_the_same():
    """use_graph=False: the step runs as plain launches, none captured, to the same state."""
    sims = [ag.Simulator(mechanisms.cartpole(), num_worlds=2, plan=ExecutionPlan(use_graph=g)) for g in (True, False)]
    for sim in sims:
        sim.set_joint_state([[0.1, 0.2], [-0.1, 0.3]])
        sim.step(5)
    assert sims[0]._graph and not sims[1]._graph
    np.testing.assert_array_equal(sims[0].body_q(), sims[1].body_q())


@pytest.mark.parametrize("plan, match", [(dict(scratch="tiled"), "scratch must be .* got 'tiled'"),
                                         (dict(fused="yes"), "fused must be True, False or None, got 'yes'"),
                                         (dict(block_dim=0), "block_dim must be a positive integer or None, got 0"),
                                         (dict(fused=False, scratch="lanes"), "scratch='lanes' needs the fused step"),
                                         (dict(max_registers=64), "plan has no field 'max_registers'"),
                                         (dict(limit_secant=1), "limit_secant must be True, False or None, got 1"),
                                         (dict(limit_secant=True, scratch="lanes"),
                                          "limit_secant=True is a thread per world's"),
                                         (dict(limit_secant=True, fused=False), "limit_secant=True is a thread per world's"),
                                         ("lanes", "plan must be an ExecutionPlan")])  # fmt: skip
def test_bad_plans_are_refused_naming_the_value(plan, match):
    with pytest.raises(ValueError, match=match):
        ag.Simulator(mechanisms.pendulum(), num_worlds=1, plan=plan)


def test_bad_settings_are_refused_before_the_model_is_built():
    for kw, match in ((dict(tol=0.0), "tol"), (dict(integrator="rk4"), "integrator"),
                      (dict(quadratic_stop=float("inf")), "quadratic_stop")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            ag.Simulator(mechanisms.pendulum(), **kw)
    with pytest.raises(TypeError):
        ag.Simulator(mechanisms.pendulum(), 1, 0.01, "cpu")  # (everything after dt by name)


def test_limit_secant_where_a_thread_holds_few_worlds():
    """The limits' secant direction by default (plan.default_limit_secant): on a GPU, a thread per
    world, where the launch's threads hold at most 2.75 worlds each (measured: 1.065-1.14x at
    1.0-2.6 worlds a thread, 0.78-0.92x at 3.1-10.3); never on the CPU or with lanes."""
    from types import SimpleNamespace

    from abd_gym.solver.plan import default_limit_secant

    gpu, cpu = SimpleNamespace(is_cuda=True), SimpleNamespace(is_cuda=False)
    assert default_limit_secant(gpu, "shared", 16384, 12672) and default_limit_secant(gpu, "shared", 16384, 16384)
    assert default_limit_secant(gpu, "global", 32768, 12672) and not default_limit_secant(gpu, "shared", 65536, 21120)
    assert default_limit_secant(gpu, "shared", 34848, 12672) and not default_limit_secant(gpu, "shared", 34849, 12672)
    assert not default_limit_secant(gpu, "shared", 131072, 21120) and not default_limit_secant(gpu, "lanes", 1024, 1024)
    assert not default_limit_secant(cpu, "global", 16, 16)
    assert not ag.Simulator(mechanisms.cartpole(), num_worlds=4).plan.limit_secant
