"""core.launches.replay: a recorded launch replayed with changed arguments, and on the CPU as the
graph of each set of arguments, does what a plain launch of the same arguments does."""
import numpy as np
import warp as wp

from abd_gym.core import launches, rows


def test_replay_follows_changed_arrays_values_and_dims():
    device = "cpu"
    dst = [wp.zeros(6, dtype=wp.int32, device=device) for _ in range(2)]
    idx = [wp.array(np.array(i, dtype=np.int32), device=device) for i in ([0, 1, 2], [3, 4, 5])]
    recorded = {}
    expect = [np.zeros(6, np.int32) for _ in range(2)]
    calls = [(0, 0, 3, 7), (1, 1, 2, 8), (0, 1, 3, 9), (0, 0, 3, 7), (1, 0, 1, 5), (0, 0, 3, 7)]
    for d, i, n, value in calls:  # each set of arguments twice or more: recorded, then its graph
        for _ in range(2):
            launches.replay(recorded, "fill", rows.fill_int, n, [dst[d], idx[i], value], device)
            expect[d][np.array(idx[i].numpy()[:n])] = value
            for k in range(2):
                np.testing.assert_array_equal(dst[k].numpy(), expect[k])
            dst[d].zero_()
            expect[d][:] = 0
    _, _, (graphs, values) = recorded["fill"]
    assert values == [2] and len(graphs) == 4  # (0, 0, 3, 7) is one graph, replayed
