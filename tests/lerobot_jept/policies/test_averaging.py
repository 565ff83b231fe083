"""jept-average-checkpoints: the mean of a run's checkpoints, loadable as a checkpoint."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from lerobot_jept import JEPTPolicy
from lerobot_jept.policies.averaging import AverageError, average_checkpoints
from tests.lerobot_jept.policies.test_policy import build_policy


def test_the_average_of_three_checkpoints_loads_with_the_mean_weights(tiny_build, tmp_path):
    policy, pre, post = build_policy(tiny_build)
    paths = []
    for i in range(3):  # three "checkpoints" of one run: the weights moved apart
        with torch.no_grad():
            for p in policy.parameters():
                p.add_(0.1 * torch.randn_like(p))
        path = tmp_path / f"{i}/pretrained_model"
        policy.save_pretrained(path)
        pre.save_pretrained(path)
        post.save_pretrained(path)
        paths.append(path)
    (paths[-1] / "train_config.json").write_text("{}")  # the last one's other files come along

    out = average_checkpoints(paths, tmp_path / "average")
    states = [load_file(p / "model.safetensors") for p in paths]
    mean = load_file(out / "model.safetensors")
    assert set(mean) == set(states[0])
    floats = [k for k, v in mean.items() if v.is_floating_point()]
    assert len(floats) > 100 and not torch.equal(states[0][floats[0]], states[2][floats[0]])
    for key, value in mean.items():
        expected = sum(s[key].double() for s in states) / 3 if value.is_floating_point() else states[-1][key]
        torch.testing.assert_close(value, expected.to(value.dtype))
    assert (out / "train_config.json").is_file() and (out / "policy_preprocessor.json").is_file()
    loaded = JEPTPolicy.from_pretrained(out)
    torch.testing.assert_close(loaded.state_dict()[floats[0]], mean[floats[0]])

    with pytest.raises(AverageError, match="at least two"):
        average_checkpoints(paths[:1], tmp_path / "x")
    with pytest.raises(AverageError, match="pretrained_model folders"):
        average_checkpoints([paths[0], tmp_path], tmp_path / "x")
    with pytest.raises(AverageError, match="is one of the checkpoints"):
        average_checkpoints(paths, paths[0])
    other = load_file(paths[1] / "model.safetensors")
    other.pop(floats[0])
    broken = tmp_path / "broken"
    broken.mkdir()
    save_file(other, str(broken / "model.safetensors"))
    with pytest.raises(AverageError, match="checkpoints of one run only"):
        average_checkpoints([paths[0], broken], tmp_path / "x")
    cli = subprocess.run(
        [str(Path(sys.executable).parent / "jept-average-checkpoints"), f"--paths=[{paths[0]}]"],
        capture_output=True,
        text=True,
    )
    assert cli.returncode != 0 and "--output_dir" in cli.stderr
