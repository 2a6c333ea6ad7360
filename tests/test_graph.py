"""The captured step (one graph per simulator, loops as conditional nodes) is the plain step:
same trajectories bit for bit, through controls, parameter changes, resets and failures; and the
fused step (one kernel runs each world's whole Newton solve) matches the staged kernels."""
import numpy as np
import pytest

import abd_gym as ag
from abd_gym.sim import mechanisms


def _run(use_graph, fused=True, dtype="float32", threads=None, scratch="global", reuse_factor=False, cpu_workers=1,
         block_dim=None, one_launch=None, integrator="implicit_euler", lane_groups=None, energy_gain=None):  # fmt: skip
    plan = ag.ExecutionPlan(use_graph=use_graph, fused=fused, threads=threads, scratch=scratch, cpu_workers=cpu_workers,
                            block_dim=block_dim, one_launch=one_launch, lane_groups=lane_groups)  # fmt: skip
    sim = ag.Simulator(mechanisms.cartpole(), num_worlds=4, dt=0.01, dtype=dtype, reuse_factor=reuse_factor,
                       integrator=integrator, plan=plan, energy_gain=energy_gain)  # fmt: skip
    rng = np.random.default_rng(3)
    sim.set_joint_state(rng.uniform(-0.3, 0.3, (4, 2)))
    out = []
    for i in range(60):
        sim.set_controls(rng.uniform(-10, 10, (4, 1)))
        if i == 20:
            sim.set_body_mass([[2.0, 0.3]], bodies=["cart", "pole"], worlds=[2])
            sim.set_limit(0, lower=-0.5, upper=0.5, worlds=[1])
        if i == 30:
            sim.reset(worlds=[0])
        if i == 40:
            q = sim.state.q.numpy()
            q[3, 1, 0] = np.nan
            sim.state.q.assign(q)
        sim.step()
        out.append(np.concatenate([sim.body_q().reshape(4, -1), sim.joint_coordinates()], axis=1))
    return np.array(out), sim


def test_graph_step_matches_plain_step():
    plain, _ = _run(False)
    graph, sim = _run(True)
    assert sim._graph
    np.testing.assert_array_equal(np.nan_to_num(graph), np.nan_to_num(plain))
    assert sim.failed_worlds().tolist() == [3]
    assert np.abs(graph[-1, 1, -2]) < 0.5 + 0.05  # the narrowed limit acts in the replayed graph


@pytest.mark.parametrize("reuse_factor", [False, True])
def test_fused_step_matches_staged_kernels(reuse_factor):
    """Same constitutions, same Newton/line-search rules (and the same reuse of a factor); only
    summation order differs."""
    staged, ref = _run(True, fused=False, dtype="float64", reuse_factor=reuse_factor)
    fused, sim = _run(True, fused=True, dtype="float64", reuse_factor=reuse_factor)
    np.testing.assert_allclose(np.nan_to_num(fused), np.nan_to_num(staged), atol=1e-8)
    assert sim.failed_worlds().tolist() == [3]
    np.testing.assert_array_equal(sim.newton_factorizations(), ref.newton_factorizations())
    np.testing.assert_array_equal(sim.newton_iterations(), ref.newton_iterations())
    its, facs = sim.newton_iterations()[:3], sim.newton_factorizations()[:3]
    assert (facs >= 1).all() and ((facs < its).any() if reuse_factor else (facs == its).all())


def test_fewer_threads_than_worlds_is_the_same_step():
    """Threads that solve several worlds in turn, reusing one scratch column, give the same
    trajectories bit for bit (failures, resets and parameter changes included)."""
    one_each, _ = _run(True)
    shared, sim = _run(True, threads=3)  # thread 0 solves worlds 0 and 3
    assert sim.solver.threads == 3 and sim.solver.H.shape[2] == 3
    np.testing.assert_array_equal(np.nan_to_num(shared), np.nan_to_num(one_each))
    assert sim.failed_worlds().tolist() == [3]


@pytest.fixture
def cpu_blocks():
    """Warp's cooperative CPU blocks (a block's threads as fibers that meet at barriers), so the
    lane-split step runs its lanes on the CPU as it does on a GPU."""
    import warp as wp

    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    yield
    wp.config.enable_cpu_blocks = before


@pytest.mark.parametrize("lanes, groups", [(None, None), (8, None), (16, 2), (None, 2)])
def test_lane_split_step_matches_one_thread_per_world(lanes, groups, request):
    """A block of lanes per world (terms in rounds, the factor a column at a time across lanes)
    against one thread per world: the same solve in another summation order, with the same
    iterations and factorisations (limits, drives, resets and a failure included).  On the CPU,
    lanes=None runs one lane a block; 8 runs eight cooperative fibers; 16 in 2 groups, two groups
    of eight, each with its share of the cart-pole's joints, limit and drive (Solver.lane_work) in
    its own copy of the system.  On a GPU, (None, 2) runs two warps a world (the first factoring
    in registers), and 8 runs the four worlds in one warp (three rows a lane in registers); on the
    CPU (None, 2) is the one-lane case again."""
    import warp as wp

    ref, sim0 = _run(True, dtype="float64")  # (before cpu_blocks: the thread per world's kernel as built elsewhere)
    if lanes:
        request.getfixturevalue("cpu_blocks")
    out, sim = _run(True, dtype="float64", scratch="lanes", block_dim=lanes, lane_groups=groups)
    from abd_gym.solver.plan import default_lane_groups

    cpu = wp.get_device(sim.device).is_cpu
    # (narrow worlds, under 32 lanes, take one group unless told)
    narrow = (lanes or 32) < 32
    g = 1 if cpu and not lanes else groups or (1 if narrow else default_lane_groups(wp.get_device(sim.device),
                                                                                     "lanes", 4, 2))  # fmt: skip
    expect = lanes or (1 if cpu else 32 * g)
    assert sim.solver.lanes and sim.solver.block_dim == expect and sim.solver.lane_groups == g
    if sim.solver.lane_groups > 1:  # every group has terms to evaluate
        assert (sim.solver.work[2] > 0).sum() >= sim.solver.lane_groups - 1
    np.testing.assert_allclose(np.nan_to_num(out), np.nan_to_num(ref), atol=1e-9)
    assert sim.failed_worlds().tolist() == [3]
    np.testing.assert_array_equal(sim.newton_iterations(), sim0.newton_iterations())
    np.testing.assert_array_equal(sim.newton_factorizations(), sim0.newton_factorizations())


def test_lane_widths_are_the_same_step(cpu_blocks):
    """Worlds of 16 or 8 lanes (on a GPU two or four worlds to a warp, each waiting only for its own
    lanes, factoring in registers with two or three rows a lane) take the same steps as worlds of
    32, bit for bit: every entry of g and H is summed by one lane in term order and the factor's
    arithmetic is the same whatever lane holds a row (controls, a mass and a limit changed, a reset
    and a failed world in the same warp as healthy ones)."""
    import warp as wp

    ref, sim0 = _run(True, scratch="lanes", block_dim=32, lane_groups=1)  # (4 worlds would take 4 groups)
    for lanes in (16, 8):
        out, sim = _run(True, scratch="lanes", block_dim=lanes)
        per_block = 32 // lanes if wp.get_device(sim.device).is_cuda else 1
        # (on a GPU the 4 worlds' warps, 2 or 1, also run as one lockstep block by default)
        assert sim.solver.block_dim == lanes and sim.solver.worlds_per_block == per_block * sim.solver.lockstep_warps
        np.testing.assert_array_equal(np.nan_to_num(out), np.nan_to_num(ref))
        assert sim.failed_worlds().tolist() == [3]
        np.testing.assert_array_equal(sim.newton_iterations(), sim0.newton_iterations())


def test_lane_split_step_on_a_closed_loop(request):
    """The lane-split step (a GPU's default up to 36 unknowns) on SliderCrank-v0's closed loop of
    three bodies and four joints against one thread per world: on a GPU 32 lanes factor with two
    rows a lane in registers, 16 with three, 8 (over 24 unknowns) in shared memory; the same steps
    to float32 rounding under the task's torques (on the CPU, eight cooperative fibers)."""
    import warp as wp

    from abd_gym.envs.slider_crank import SliderCrankVectorEnv

    env = SliderCrankVectorEnv(1)
    env.scene.planar = False  # 12 unknowns a body (tests/test_planar.py: the lanes in the plane)
    W, rng = 4, np.random.default_rng(2)
    x, xd = env.initial_state(W, rng, {})
    torque = rng.uniform(-1, 1, (W, 1)) * env.max_effort

    def run(scratch, block_dim=None):
        plan = ag.ExecutionPlan(scratch=scratch, block_dim=block_dim)
        sim = ag.Simulator(env.scene, num_worlds=W, dt=env.dt, plan=plan)
        assert sim.model.num_dofs == 36
        sim.set_joint_state(x, xd)
        sim.set_controls(torque)
        sim.step(40)
        return sim.joint_coordinates(), sim

    ref, _ = run("global")
    request.getfixturevalue("cpu_blocks")  # (after the reference: its kernel is the one built without them)
    cuda = wp.get_device(env.sim.device).is_cuda
    for lanes in (32, 16, 8) if cuda else (8,):
        out, sim = run("lanes", lanes)
        assert sim.solver.lanes and sim.solver.block_dim == lanes and not sim.failed_worlds().size
        np.testing.assert_allclose(out, ref, atol=1e-4)
    assert np.abs(out - x).max() > 0.05  # (the crank turned)
    env.close()


def _launches(sim, seed: int, counts, failed: int):
    """sim.step(n) for each n of ``counts`` from random joint states, each under new random controls;
    after the second, world 1's limit narrowed and world ``failed`` made non-finite.  Returns each
    call's body states, joint coordinates and velocities, (calls, worlds, ·)."""
    W = sim.num_worlds
    rng = np.random.default_rng(seed)
    sim.set_joint_state(rng.uniform(-0.3, 0.3, (W, 2)))
    out = []
    for i, n in enumerate(counts):
        sim.set_controls(rng.uniform(-10, 10, (W, 1)))
        sim.step(n)
        out.append(np.concatenate([sim.body_q().reshape(W, -1), sim.joint_coordinates(), sim.joint_velocities()],
                                  axis=1))  # fmt: skip
        if i == 1:
            sim.set_limit(0, lower=-0.2, upper=0.2, worlds=[1])
            q = sim.state.q.numpy()
            q[failed, 1, 0] = np.nan
            sim.state.q.assign(q)
    return np.array(out)


@pytest.mark.parametrize("scratch", ["lanes"])
def test_steps_in_one_launch_are_the_steps_one_by_one(scratch):
    """steps_per_launch: a world's steps in turn in one launch of the one-launch step (sim.step(n)
    in launches of up to 3 steps: 3 + 3 + 1, then 2) are the steps launched one by one, bit for bit
    (with controls, a narrowed limit and a failed world), and the clock advances by every step."""
    import warp as wp

    def run(spl):
        plan = ag.ExecutionPlan(scratch=scratch, one_launch=True, steps_per_launch=spl)
        sim = ag.Simulator(mechanisms.cartpole(), num_worlds=4, dt=0.01, plan=plan)
        return _launches(sim, 3, (7, 2, 7), failed=3), sim

    ref, sim1 = run(1)
    out, sim = run(3)
    assert sim.solver.multi_step and sim.solver.launch_chunks(7) == [3, 3, 1]
    if wp.get_device(sim.device).is_cuda:
        assert sorted(sim._graph) == [1, 2, 3]  # a captured launch per step count
    np.testing.assert_array_equal(np.nan_to_num(out), np.nan_to_num(ref))
    np.testing.assert_allclose(np.asarray(sim.state.time), np.asarray(sim1.state.time))
    np.testing.assert_allclose(np.asarray(sim.state.time), 0.16)
    assert sim.failed_worlds().tolist() == [3]


def test_lockstep_blocks_are_the_same_step():
    """lockstep_warps: on a GPU, blocks of several warps whose worlds start each step of a launch at
    the block's barrier take the same steps as a block a warp, bit for bit (8 worlds of 32 lanes in
    blocks of 8 and 2 warps, of 16 lanes two a warp in blocks of 4 warps; launches of 7 steps with
    controls, a narrowed limit and a failed world); iterations and clocks alike.  On the CPU the
    setting is ignored (a block runs one world)."""
    import warp as wp

    def run(**kw):
        plan = ag.ExecutionPlan(scratch="lanes", lane_groups=1, steps_per_launch=7, **kw)
        sim = ag.Simulator(mechanisms.cartpole(), num_worlds=8, dt=0.01, plan=plan)
        return _launches(sim, 5, (7, 3, 14), failed=5), sim

    ref, sim1 = run(block_dim=32, lockstep_warps=1)
    if not wp.get_device(sim1.device).is_cuda:
        assert run(lockstep_warps=8)[1].solver.lockstep_warps == 1
        pytest.skip("lockstep blocks are CUDA blocks of several warps")
    assert sim1.solver.worlds_per_block == 1
    for kw, per_block in ((dict(block_dim=32, lockstep_warps=8), 8), (dict(block_dim=32, lockstep_warps=2), 2),
                          (dict(block_dim=16, lockstep_warps=4), 8)):  # fmt: skip
        out, sim = run(**kw)
        assert sim.solver.lockstep_warps == kw["lockstep_warps"] and sim.solver.worlds_per_block == per_block
        np.testing.assert_array_equal(np.nan_to_num(out), np.nan_to_num(ref))
        np.testing.assert_array_equal(sim.newton_iterations(), sim1.newton_iterations())
        np.testing.assert_allclose(np.asarray(sim.state.time), np.asarray(sim1.state.time))
        assert sim.failed_worlds().tolist() == [5]
    # a held world (the vector env's autoreset) leaves its block's barrier to the others: they step
    # as in a launch without the hold, it keeps its state
    plan = ag.ExecutionPlan(scratch="lanes", lane_groups=1, block_dim=32, lockstep_warps=8, steps_per_launch=7)
    free, held = (ag.Simulator(mechanisms.cartpole(), num_worlds=8, dt=0.01, plan=plan) for _ in range(2))
    assert held.solver.enable_hold()
    for sim in (free, held):
        sim.set_joint_state(np.random.default_rng(6).uniform(-0.3, 0.3, (8, 2)))
    hold = wp.array([0, 0, 1, 0, 0, 0, 0, 0], dtype=wp.int32, device=held.device)
    q0 = held.state.q.numpy()
    free.step(7)
    held.launch_step(7, hold=hold)
    q, want = held.state.q.numpy(), free.state.q.numpy()
    np.testing.assert_array_equal(q[2], q0[2])
    np.testing.assert_array_equal(np.delete(q, 2, 0), np.delete(want, 2, 0))
    kw = dict(scratch="lanes", block_dim=32, lane_groups=1)
    assert ag.Simulator(mechanisms.cartpole(), num_worlds=8, plan=ag.ExecutionPlan(**kw)).plan.lockstep_warps == 8
    with pytest.raises(ValueError, match="lockstep_warps=4: 6 worlds of 32 lanes do not fill whole blocks"):
        ag.Simulator(mechanisms.cartpole(), num_worlds=6, plan=ag.ExecutionPlan(lockstep_warps=4, **kw))


def test_default_lockstep_warps():
    """Warps a lockstep block by default: the most of 8, 4, 2 that split the worlds into whole
    blocks whose systems fit the block's shared memory (and 50 steps a launch with them, else 2);
    1 with lane groups, one thread a world and on the CPU; a count outside 1 … 8 is refused."""
    from types import SimpleNamespace

    import warp as wp

    from abd_gym.solver.plan import default_lockstep_warps, default_steps_per_launch

    gpu, cpu = SimpleNamespace(is_cuda=True, sm_count=132), SimpleNamespace(is_cuda=False)
    f32 = wp.float32
    assert [default_lockstep_warps(gpu, "lanes", w, 32, 1, 24, f32) for w in (1024, 1020, 1022, 1023)] == [8, 4, 2, 1]
    assert [default_lockstep_warps(gpu, "lanes", w, 16, 1, 24, f32) for w in (2048, 2047)] == [8, 1]
    assert default_lockstep_warps(gpu, "lanes", 4096, 8, 1, 36, f32) == 4  # 32 worlds of 36 unknowns: 95 KB
    assert default_lockstep_warps(gpu, "lanes", 1024, 32, 1, 60, f32) == 4  # 8 of 60 unknowns: 61 KB
    assert default_lockstep_warps(gpu, "lanes", 512, 64, 2, 24, f32) == 1
    assert default_lockstep_warps(gpu, "shared", 1024, 1, 1, 24, f32) == 1
    assert default_lockstep_warps(cpu, "lanes", 1024, 32, 1, 24, f32) == 1
    assert default_steps_per_launch(8) == 50 and default_steps_per_launch(1) == 2
    for bad in (0, 9, 2.0):
        with pytest.raises(ValueError, match="lockstep_warps must be an integer from 1 to 8"):
            ag.Simulator(mechanisms.pendulum(), num_worlds=1, plan=ag.ExecutionPlan(lockstep_warps=bad))


def test_held_worlds_are_not_stepped():
    """launch_step(hold=, go=) on the one-launch step built for it (Solver.enable_hold, before the
    first step): the worlds marked in ``hold`` are not stepped
    and no row of theirs is written (so that the vector env's autoreset may rewrite them on another
    stream meanwhile), the others step bit for bit as without it, and go[0] = 0 steps no world; a
    solver whose step is not one launch, or a hold of the wrong shape or dtype, is refused."""
    import warp as wp

    def make(sim=None, **kw):
        sim = sim or ag.Simulator(mechanisms.cartpole(), num_worlds=4, dt=0.01, plan=ag.ExecutionPlan(**kw))
        rng = np.random.default_rng(3)
        sim.set_joint_state(rng.uniform(-0.3, 0.3, (4, 2)))
        sim.set_controls(rng.uniform(-10, 10, (4, 1)))
        sim.step(2)
        return sim

    def arrays(sim):
        return {k: np.nan_to_num(v.numpy()) for k, v in vars(sim.state).items() if isinstance(v, wp.array)}

    kw = dict(scratch="lanes", one_launch=True, steps_per_launch=3)
    free, held = make(**kw), make(**kw)
    assert not held.solver.holds  # built without the check unless asked, before the first step
    with pytest.raises(RuntimeError, match="before the first step"):
        held.solver.enable_hold()
    held = ag.Simulator(mechanisms.cartpole(), num_worlds=4, dt=0.01, plan=ag.ExecutionPlan(**kw))
    assert held.solver.enable_hold() and held.solver.holds
    held = make(sim=held)
    hold = wp.array([0, 1, 0, 0], dtype=wp.int32, device=held.device)
    before = arrays(held)
    free.step(7)
    held.launch_step(7, hold=hold)
    after, want = arrays(held), arrays(free)
    assert len(after) > 20
    for name, a in after.items():
        np.testing.assert_array_equal(a[[0, 2, 3]], want[name][[0, 2, 3]], err_msg=name)
        np.testing.assert_array_equal(a[1], before[name][1], err_msg=name)
    assert not np.array_equal(after["q"][0], before["q"][0])
    held.launch_step(3, go=wp.zeros(1, dtype=wp.int32, device=held.device))
    for name, a in arrays(held).items():
        np.testing.assert_array_equal(a, after[name], err_msg=name)
    with pytest.raises(ValueError, match=r"hold must be an int32 array of shape \(4,\)"):
        held.launch_step(1, hold=wp.zeros(3, dtype=wp.int32, device=held.device))
    staged = make(scratch="global", one_launch=False)
    assert not staged.solver.enable_hold()
    with pytest.raises(ValueError, match="one-launch step"):
        staged.launch_step(1, hold=hold)


def test_world_queue_steps_every_world_once():
    """The thread-per-world step with fewer threads than worlds: each thread takes its first world,
    then claims the next from the launch's queue whenever its world's solve is over (a GPU warp
    then never idles on its slowest world).  Every world steps once, bit for bit as with a thread
    each, held worlds are left alone, and the queue is empty again after every launch, whether the
    threads run as one launch or as concurrent launches each with its own queue."""
    import warp as wp

    def make(**kw):
        sim = ag.Simulator(mechanisms.cartpole(), num_worlds=7, dt=0.02, plan=ag.ExecutionPlan(**kw))
        rng = np.random.default_rng(11)
        sim.set_joint_state(rng.uniform(-1.0, 1.0, (7, 2)), rng.uniform(-3.0, 3.0, (7, 2)))
        sim.set_controls(rng.uniform(-20, 20, (7, 1)))
        return sim

    ref = make(scratch="global", threads=7, cpu_workers=1, one_launch=True)
    ref.step(5)
    iters = ref.newton_iterations()
    assert iters.min() < iters.max()  # worlds that finish first hand their threads on
    for kw in (dict(threads=2, cpu_workers=1), dict(threads=4, cpu_workers=2), dict(scratch="shared", threads=3)):
        sim = make(one_launch=True, **dict(dict(scratch="global"), **kw))
        assert sim.solver.threads == kw["threads"]
        sim.step(5)
        np.testing.assert_array_equal(sim.state.q.numpy(), ref.state.q.numpy(), err_msg=str(kw))
        np.testing.assert_array_equal(sim.newton_iterations(), iters)
        assert not any(qu.numpy().any() for qu in sim.solver.queues)
    free, held = (make(scratch="global", threads=2, cpu_workers=1, one_launch=True) for _ in range(2))
    assert held.solver.enable_hold()
    hold = wp.array([0, 0, 1, 0, 0, 1, 0], dtype=wp.int32, device=held.device)
    q0 = held.state.q.numpy()
    free.step(3)
    held.launch_step(3, hold=hold)
    q, want = held.state.q.numpy(), free.state.q.numpy()
    np.testing.assert_array_equal(q[[2, 5]], q0[[2, 5]])
    np.testing.assert_array_equal(np.delete(q, [2, 5], 0), np.delete(want, [2, 5], 0))
    held.launch_step(2, go=wp.zeros(1, dtype=wp.int32, device=held.device))
    np.testing.assert_array_equal(held.state.q.numpy(), q)
    assert not any(qu.numpy().any() for qu in held.solver.queues)


def test_default_lane_groups_fill_the_gpu_once():
    """Lane groups a world by default: on a GPU the most of 4, 2, 1 whose warps all fit at once
    (8 a streaming multiprocessor, a block's warps on one) and that each have work (the bodies or
    a term: a cart-pole's limit and drive ride on its prismatic joint's term, so it has 2 terms and
    takes 3 groups); 1 on the CPU and for the other layouts."""
    from types import SimpleNamespace

    from abd_gym.solver.plan import default_lane_groups
    from abd_gym.solver.terms import joint_terms, term_counts

    gpu, cpu = SimpleNamespace(is_cuda=True, sm_count=132), SimpleNamespace(is_cuda=False)
    assert [default_lane_groups(gpu, "lanes", w) for w in (1, 264, 265, 528, 529, 1024)] == [4, 4, 2, 2, 1, 1]
    assert [default_lane_groups(gpu, "lanes", 16, terms) for terms in (0, 1, 2, 3, 5)] == [1, 2, 3, 4, 4]
    assert [default_lane_groups(gpu, "lanes", w, 2) for w in (264, 265, 528, 529)] == [3, 2, 2, 1]
    assert default_lane_groups(cpu, "lanes", 16) == 1 and default_lane_groups(gpu, "shared", 16) == 1
    # no more copies of a world's system than a block's shared memory holds (47 KB)
    assert [default_lane_groups(gpu, "lanes", 16, 9, n) for n in (36, 60, 96)] == [4, 2, 1]
    m = ag.Simulator(mechanisms.cartpole(), num_worlds=1).model
    assert term_counts(m, joint_terms(m)) == dict(revolute_joint=1, prismatic_joint=1, fixed_joint=0, revolute_limit=0,
                                                  prismatic_limit=0, drive=0, passive=0, angle=0)


def test_lane_scratch_bytes():
    """A block's shared memory in the lane-split step: per world, H's packed triangle per lane
    group, g and Δq; 4 worlds of 120 unknowns at 8 lanes need 120,160 B (ptxas on an H100 reported
    120,288 B for that kernel, Warp's own 128 B included, and refused it)."""
    import warp as wp

    from abd_gym.solver.fused import lanes_scratch_words
    from abd_gym.solver.plan import lanes_scratch_bytes

    assert lanes_scratch_words(24, 1) == 300 + 24 + 2 + 24
    assert lanes_scratch_words(24, 3) == 3 * 300 + (2 * 300 + 24 + 2 + 3 + 1) + 24
    assert lanes_scratch_bytes(120, wp.float32, 1, 4) == 120_160
    assert lanes_scratch_bytes(120, wp.float64) == 2 * lanes_scratch_bytes(120, wp.float32) == 60_080


def test_steps_per_launch_must_be_positive():
    with pytest.raises(ValueError, match="steps_per_launch"):
        ag.Simulator(mechanisms.pendulum(), num_worlds=1, plan=ag.ExecutionPlan(steps_per_launch=0))
    with pytest.raises(ValueError, match="lane_groups"):
        ag.Simulator(mechanisms.pendulum(), num_worlds=1, plan=ag.ExecutionPlan(scratch="global", lane_groups=2))
    with pytest.raises(ValueError, match="lane_groups"):
        ag.Simulator(mechanisms.pendulum(), num_worlds=1, plan=ag.ExecutionPlan(scratch="lanes", lane_groups=-1))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_shared_scratch_step_matches_global(dtype):
    """scratch="shared" (H's lower triangle packed, in the CUDA block's shared memory; on the CPU the
    packed columns in global memory) is the same solve as the square global scratch: the same
    products in the same order, so the same trajectories bit for bit, iterations and factorisations
    (limits, drives, resets and a failure included)."""
    ref, sim0 = _run(True, dtype=dtype)
    out, sim = _run(True, dtype=dtype, scratch="shared")
    assert sim.solver.shared and not sim.solver.envelope
    np.testing.assert_array_equal(np.nan_to_num(out), np.nan_to_num(ref))
    assert sim.failed_worlds().tolist() == [3]
    np.testing.assert_array_equal(sim.newton_iterations(), sim0.newton_iterations())
    np.testing.assert_array_equal(sim.newton_factorizations(), sim0.newton_factorizations())


def test_shared_scratch_too_large_is_refused():
    """A block whose threads' systems exceed the shared memory a block may take is refused, naming the sizes."""
    import warp as wp

    for scratch in ("shared", "lanes"):  # the packed scratches take the envelope on a banded scene only
        with pytest.raises(ValueError, match="envelope"):
            ag.Simulator(mechanisms.cartpole(), num_worlds=2, plan=ag.ExecutionPlan(scratch=scratch, envelope=True))
    if not wp.get_device(ag.Simulator(mechanisms.pendulum(), num_worlds=1).device).is_cuda:
        pytest.skip("the shared-memory budget applies on CUDA only")
    with pytest.raises(ValueError, match="scratch='shared': 1 thread"):  # 462 KB: the packed triangle of 480 unknowns
        ag.Simulator(mechanisms.chain(40), num_worlds=2, plan=ag.ExecutionPlan(scratch="shared", envelope=False))
    with pytest.raises(ValueError, match=r"512 thread\(s\) of 24 unknowns need 712704 B .* at most \d+ fit"):
        ag.Simulator(mechanisms.cartpole(), num_worlds=2, plan=ag.ExecutionPlan(scratch="shared", block_dim=512))


@pytest.mark.parametrize("energy_gain", [None, 0.05], ids=["default", "energy_test"])
@pytest.mark.parametrize("one_launch", [True, False])
def test_concurrent_cpu_launches_are_the_same_step(one_launch, energy_gain):
    """cpu_workers=2 (the fused step's 4 threads and 4 worlds as two launches run at once on the
    CPU; with one_launch=False between the captured phases before and after them) gives the
    one-launch, graph-captured step bit for bit, through the same events.  (one_launch is the
    default with lanes only; here the thread-per-world step both ways.)  The CPU runs the retry of
    failed worlds (the last phase) as it comes, uncaptured, and so, with the energy test (off by
    default at this dt), its copy of the state before the step (a first phase)."""
    one, sim1 = _run(True, cpu_workers=1, one_launch=one_launch, energy_gain=energy_gain)
    two, sim2 = _run(True, cpu_workers=2, one_launch=one_launch, energy_gain=energy_gain)
    test = [None] if energy_gain else []  # the energy test's phase before the step
    captured = [g is not None for _, g in sim1._graph[1]]
    assert sim1.solver.capturable and captured == [False] * len(test) + [True, False]
    if sim2.device.is_cpu:  # the concurrent launches are not captured (phases around them are)
        assert sim2.solver.newton_launches == [(0, 2, 0, 2), (2, 2, 2, 4)] and not sim2.solver.capturable
        captured = [g is not None for _, g in sim2._graph[1]]
        if one_launch:  # each launch opens and closes its own worlds' steps
            assert captured == [False] * (len(test) + 2)
        else:
            assert captured == [False] * len(test) + [True, False, True, False]
    np.testing.assert_array_equal(np.nan_to_num(two), np.nan_to_num(one))
    assert sim2.failed_worlds().tolist() == [3]


@pytest.mark.parametrize("scratch,dtype,integrator", [("global", "float32", "implicit_euler"),
                                                      ("global", "float64", "bdf2"),
                                                      ("shared", "float32", "bdf2"),
                                                      ("lanes", "float32", "implicit_euler")])  # fmt: skip
def test_one_launch_step_is_the_bracketed_step(scratch, dtype, integrator, request):
    """one_launch (the fused kernel opens and closes each world's step: finite check, references,
    prediction, velocities, coordinates) against the same kernels launched around it: the same
    functions in the same order per world (the one launch's close also leaves the next step's joint
    references, close_joint, which the kernels' open computes from the same q), so the same
    trajectories, joint coordinates and rates bit for bit, through controls, limits, a reset and a
    failure; BDF2 included (its step sizes and anchors); with lanes on eight CPU fibers, split a
    body or a joint per lane (cooperative CPU blocks for the lanes only: a thread per world's
    kernel needs none, and is then the one the other tests build)."""
    block = 8 if scratch == "lanes" else None
    if scratch == "lanes":
        request.getfixturevalue("cpu_blocks")
    one, sim1 = _run(True, dtype=dtype, scratch=scratch, one_launch=True, integrator=integrator, block_dim=block)
    two, sim2 = _run(True, dtype=dtype, scratch=scratch, one_launch=False, integrator=integrator, block_dim=block)
    assert len(sim1._graph) == 1 and sim1.solver.one_launch and not sim2.solver.one_launch
    np.testing.assert_array_equal(np.nan_to_num(one), np.nan_to_num(two))
    np.testing.assert_array_equal(sim1.joint_velocities(), sim2.joint_velocities())
    assert sim1.failed_worlds().tolist() == [3] == sim2.failed_worlds().tolist()
    np.testing.assert_array_equal(sim1.newton_iterations(), sim2.newton_iterations())


def test_threads_must_be_positive():
    import pytest

    with pytest.raises(ValueError, match="threads"):
        ag.Simulator(mechanisms.cartpole(), num_worlds=2, plan=ag.ExecutionPlan(threads=0))
    with pytest.raises(ValueError, match="cpu_workers"):
        ag.Simulator(mechanisms.cartpole(), num_worlds=2, plan=ag.ExecutionPlan(cpu_workers=0))


def test_scratch_beyond_32_bit_indexing_is_refused():
    """The flat Newton scratch is indexed with 32-bit integers: a staged solver whose n² × worlds
    passes 2³¹ (a 40-link chain, 480 unknowns, 9,400 worlds) is refused with a clear error."""
    import pytest

    with pytest.raises(ValueError, match="exceeds 2\\*\\*31"):
        ag.Simulator(mechanisms.chain(40), num_worlds=9400, plan=ag.ExecutionPlan(fused=False))


def test_default_scratch_by_device_size_and_batch():
    """The layout a simulator picks: a thread per world on the CPU; on a GPU lanes for worlds of up
    to 36 unknowns while their warps fit it at once (32 lanes a world up to 8 warps an SM, then 16
    and 8 lanes: 1,056 / 2,112 / 4,224 worlds on 132 SMs), the shared scratch above that where 32
    systems fit a block, else the global one (the measured crossovers, plan.default_scratch and
    default_lane_width)."""
    from types import SimpleNamespace

    import warp as wp

    from abd_gym.solver.plan import (default_block_dim_shared, default_lane_width, default_scratch,
        resident_threads_shared)

    gpu, cpu = SimpleNamespace(is_cuda=True, sm_count=132), SimpleNamespace(is_cuda=False, sm_count=0)
    assert default_scratch(cpu, 24, wp.float32, True, 16) == "global"
    assert default_scratch(gpu, 24, wp.float32, True, 1024) == "lanes"
    assert default_scratch(gpu, 24, wp.float32, True, 4224) == "lanes"
    assert default_scratch(gpu, 24, wp.float32, True, 4225) == "shared"
    widths = [default_lane_width(gpu, w) for w in (1, 1056, 1057, 2112, 2113, 4224, 4225)]
    assert widths == [32, 32, 16, 16, 8, 8, 0]
    assert default_lane_width(cpu, 16) == 0
    assert default_lane_width(gpu, 1056, wp.float64) == 32 and default_lane_width(gpu, 1057, wp.float64) == 0
    assert default_scratch(gpu, 36, wp.float32, True, 64) == "lanes"  # (a four-bar, a slider-crank)
    # more unknowns (chains): 32 lanes up to 4,096 worlds where a world's system fits 47 KB
    assert [default_lane_width(gpu, w, wp.float32, 60) for w in (1, 1057, 4096, 4097)] == [32, 32, 32, 0]
    assert default_scratch(gpu, 48, wp.float32, True, 64) == "lanes"
    assert default_scratch(gpu, 120, wp.float32, True, 2048) == "lanes"
    # past them, shared where 6 of its systems fit a block (60 unknowns: 6), else global
    assert default_scratch(gpu, 60, wp.float32, True, 4097) == "shared"
    assert default_scratch(gpu, 120, wp.float32, True, 4097) == "global"  # one fits
    assert default_scratch(gpu, 60, wp.float64, True, 4097) == "global"  # three fit
    assert default_scratch(gpu, 120, wp.float64, True, 1024) == "global"  # one system: 60 KB
    assert default_scratch(gpu, 156, wp.float32, True, 1024) == "global"  # 49.6 KB
    assert default_scratch(gpu, 36, wp.float32, True, 4225) == "shared"  # 16 fit a block
    assert default_scratch(gpu, 24, wp.float64, True, 4096) == "shared"  # 17 fit
    assert default_scratch(gpu, 24, wp.float32, False, 64) == "global"  # the staged step has one layout
    # a banded scene's block band (Model.banded): 20 three-body systems a block, 11 of 60 unknowns, 5 of 120
    assert [default_block_dim_shared(n, wp.float32, True) for n in (36, 60, 120)] == [20, 11, 5]
    assert default_block_dim_shared(36, wp.float32) == 16
    # past a wave of them, blocks four of which fill an H100's SM (228 KB): 24 and 13
    h100 = SimpleNamespace(is_cuda=True, sm_count=132, arch=90)
    assert [default_block_dim_shared(36, wp.float32, True, h100, w) for w in (12671, 12672, 16384)] == [20, 24, 24]
    assert default_block_dim_shared(60, wp.float32, True, h100, 131072) == 13
    # threads of the shared step by default: the blocks an SM's 228 KB holds, on every SM (the rest
    # of the worlds from the threads' queue): 4 of 24 three-body systems (58,176 B), 5 of 32
    # cart-poles (44,544 B), 4 of 20 three-body systems (48,672 B); none known for other SMs
    assert resident_threads_shared(h100, 36, wp.float32, True, 24) == 4 * 132 * 24
    assert resident_threads_shared(h100, 24, wp.float32, False, 32) == 5 * 132 * 32
    assert resident_threads_shared(h100, 36, wp.float32, True, 20) == 4 * 132 * 20
    assert resident_threads_shared(SimpleNamespace(is_cuda=True, sm_count=84, arch=89), 36, wp.float32, True, 20) == 0
    assert default_block_dim_shared(24, wp.float32, False, h100, 131072) == 32  # a warp already
    assert default_block_dim_shared(36, wp.float32, True, SimpleNamespace(is_cuda=True, sm_count=84, arch=89),
                                    131072) == 20  # an SM of 100 KB: the 48 KB rule
    assert default_scratch(gpu, 60, wp.float64, True, 4097, band=True) == "global"  # five fit
    assert default_scratch(gpu, 120, wp.float32, True, 4097, band=True) == "global"  # five fit
