"""How long the experts hold one binned action (examples/measurements/action_persistence.py), on a real tiny build."""

import numpy as np
import pytest

from examples.measurements.action_persistence import PersistenceConfig, persistence
from lerobot_jept.evaluation.prompt_probe import task_names
from tests.conftest import TINY, load


def test_persistence_counts_repeated_whole_actions_per_task(tiny_build):
    results = persistence(PersistenceConfig(repo_id="test/mw_tiny_demo", windows=[0, 1]))
    assert set(results) == set(TINY["demo_tasks"])  # builder names, from the build metadata
    dataset = load("test/mw_tiny_demo")
    table = dataset.hf_dataset.with_format("numpy")[:]
    names = task_names(dataset.meta)
    index_of = {
        names[t]: int(i)
        for t, i in zip(dataset.meta.tasks.index, dataset.meta.tasks["task_index"], strict=True)
    }
    for task, row in results.items():
        shares = []
        for ep in np.unique(table["episode_index"][table["task_index"] == index_of[task]]):
            bins = np.rint((np.clip(table["action"][table["episode_index"] == ep], -1, 1) + 1) * 3)
            shares.append((bins[1:] == bins[:-1]).all(1).mean())
        assert row["repeats"] == pytest.approx(np.mean(shares))
        assert row["majority k=0"] == 1.0  # a window of one frame changes nothing
        assert 0.0 < row["majority k=1"] <= 1.0
