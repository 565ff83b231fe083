"""How often a scene-mate's scripted expert would act differently (examples/measurements/expert_swap_ceiling.py), on the real
Meta-World experts."""

import numpy as np
import pytest

from examples.measurements.expert_swap_ceiling import SwapCeilingConfig, main, mate_differences
from lerobot_jept.envs import metaworld as mw


def test_expert_action_of_another_task_reads_the_same_state():
    env = mw.JeptMetaworldEnv("window-open-v3", image_size=16)
    try:
        env.reset(seed=3)
        own = env.expert_action()
        assert np.array_equal(env.expert_action("window-open-v3"), own)
        mate = env.expert_action("window-close-v3")
        assert mate.shape == own.shape and not np.allclose(mate, own)  # the handle is pushed the other way
        with pytest.raises(ValueError, match="window-shut-v3"):
            env.expert_action("window-shut-v3")
    finally:
        env.close()


def test_window_mates_differ_along_the_push_and_never_on_the_gripper():
    cfg = SwapCeilingConfig(episodes=1, seed=0)
    diffs, failed = mate_differences("window-open-v3", ["window-close-v3"], cfg)
    d = diffs["window-close-v3"]
    assert failed == 0 and d.shape[1] == 4 and len(d) > 20  # one successful episode, every recorded step
    assert d[:, 0].mean() > 0.5  # x: window-open pushes the handle one way, window-close the other
    assert not d[:, 3].any()  # both experts hold the gripper closed on the handle (grab effort 1)


def test_tasks_without_a_scene_mate_are_refused():
    with pytest.raises(SystemExit, match="no two of --tasks share a scene"):
        main(["--tasks=[window-open-v3, door-close-v3]"])
