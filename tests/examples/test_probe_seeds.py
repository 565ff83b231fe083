"""The action target over seeds (examples/measurements/probe_seeds.py): on a real probe of a saved checkpoint, and on
hand-made probe outputs whose answer is known."""

import copy
import json

import numpy as np
import pytest
from scipy.stats import t as t_dist

from examples.measurements.probe_seeds import compare_arms, load_probe, markdown
from lerobot_jept.evaluation.cli_args import DatasetArg, PolicyArg
from lerobot_jept.evaluation.prompt_probe import ProbeConfig, run_probe
from tests.conftest import TINY
from tests.lerobot_jept.test_hub import checkpoint  # noqa: F401  (the saved tiny checkpoint, a fixture)


def test_reads_a_real_probe_output(checkpoint, tmp_path):  # noqa: F811
    run_probe(ProbeConfig(PolicyArg(str(checkpoint)), DatasetArg("test/mw_tiny_probe"), output_dir=tmp_path))
    probe = load_probe(str(tmp_path))  # the folder jept-prompt-probe wrote
    assert probe == json.loads((tmp_path / "prompt_probe.json").read_text())
    task = TINY["video_tasks"][0]
    result = compare_arms({"a": [probe, probe], "b": [probe]}, task)
    assert result["split"] == "T_vid"
    row = probe["actions"][task]
    assert result["arms"]["a"]["task"]["control_whole"] == [row["control_whole"]] * 2
    assert result["arms"]["b"]["split"]["loss_obs"] == [probe["splits"]["T_vid"]["loss_obs"]]
    trained = probe["prompt_separability"]["trained_tasks"]["nearest_centroid_accuracy"]
    assert result["arms"]["a"]["nc_trained"] == [trained] * 2
    assert (
        result["target"]["margin"] == 0.0 and not result["target"]["met"] and "welch" not in result["target"]
    )
    assert "needs at least two seeds per arm" in markdown(result)  # arm b has one seed: no spread to beat
    with pytest.raises(SystemExit, match="not in the probed repo"):
        compare_arms({"a": [probe]}, "window-close-v3")

    suite = tmp_path / "suite"  # a jept-eval-suite (jept-study) output carries the probe in results.json
    suite.mkdir()
    (suite / "results.json").write_text(json.dumps({"per_task": {}, "prompt_probe": probe}))
    assert load_probe(str(suite)) == probe
    (suite / "results.json").write_text(json.dumps({"per_task": {}}))
    with pytest.raises(SystemExit, match="has no probe: run jept-eval-suite with --heldout_repo_id"):
        load_probe(str(suite))
    with pytest.raises(SystemExit, match="no prompt_probe.json or results.json"):
        load_probe(str(tmp_path / "nowhere"))


def probe_output(control: float, swaps: dict[str, float]) -> dict:
    return {
        "dataset": "x/probe",
        "actions": {"close": {"control_whole": control, "swap_changed": swaps, "loss_obs": 1.0}},
        "splits": {"T_vid": {"tasks": ["close"], "control_whole": control, "loss_obs": 1.0}},
    }


def test_the_bar_is_the_margin_over_the_larger_range_of_the_two_arms():
    demos = [probe_output(c, {"open": 0.1, "other": 0.3}) for c in (0.20, 0.25, 0.30)]  # range 0.10
    close = [probe_output(c, {"open": 0.5}) for c in (0.36, 0.40, 0.44)]  # mean 0.40, range 0.08
    result = compare_arms({"videos": close, "demos": demos}, "close")
    # a per-scene-mate measure is the mean over the task's scene-mates
    assert result["arms"]["demos"]["task"]["swap_changed"] == pytest.approx([0.2] * 3)
    assert result["target"]["margin"] == pytest.approx(0.15) and result["target"]["spread"] == pytest.approx(
        0.10
    )
    assert result["target"]["met"]
    assert "the target (a margin larger than the spread) is met" in markdown(result)
    # Welch by hand: variances 0.0016 and 0.0025 over 3 seeds each, df from Welch-Satterthwaite
    se2 = (0.0016 / 3, 0.0025 / 3)
    df = sum(se2) ** 2 / (se2[0] ** 2 / 2 + se2[1] ** 2 / 2)
    half = t_dist.ppf(0.975, df) * np.sqrt(sum(se2))
    welch = result["target"]["welch"]
    assert df == pytest.approx(3.816, abs=1e-3)
    assert (welch["low"], welch["high"]) == pytest.approx((0.15 - half, 0.15 + half))
    assert welch["p"] == pytest.approx(2 * t_dist.sf(0.15 / np.sqrt(sum(se2)), df)) and welch["p"] < 0.05
    assert f"95% interval [{100 * (0.15 - half):+.1f}, " in markdown(result)
    assert np.isnan(result["arms"]["videos"]["task"]["inverse_whole"]).all()  # a measure the probe lacks

    wide = copy.deepcopy(demos)
    wide[0]["actions"]["close"]["control_whole"] = 0.05  # the demos' range is now 0.25 > the margin 0.2
    result = compare_arms({"videos": close, "demos": wide}, "close")
    assert result["target"]["margin"] == pytest.approx(0.2) and not result["target"]["met"]
    text = markdown(result)
    assert "is not met" in text
    assert "| control whole (%) | 40.0 [" in text and "20.0 [0.0, " in text  # intervals clipped to [0, 100]
    reversed_arms = compare_arms({"demos": demos, "videos": close}, "close")
    assert not reversed_arms["target"]["met"]  # the first arm must lead
