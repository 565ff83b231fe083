"""jept-study: the plan, resumption, the report's numbers, and a micro study run for real (slow)."""

import dataclasses
import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from lerobot_jept.evaluation.compare import CompareConfig, compare
from lerobot_jept.evaluation.prompt_probe import bin_accuracy, split_summary
from lerobot_jept.study.config import BuildSpec, MethodSpec, SplitSpec, StudyConfig, StudyError, validate
from lerobot_jept.study.plan import Step, plan, run_folder
from lerobot_jept.study.report import training_curves, write_report
from lerobot_jept.study.run import StudyProgress, estimate_seconds, main, run_group, run_study, step_groups
from tests.conftest import TINY
from tests.lerobot_jept.policies.test_baselines import suite_output

REPO = Path(__file__).parents[3]
CONFIGS = REPO / "examples/configs"
SPLIT = {"demo": ["a"], "video": ["b"], "unseen": ["c"]}


def study(tmp_path: Path, **kwargs) -> StudyConfig:
    defaults = dict(
        name="t",
        splits=[SplitSpec("s", "test/x", ["a"], ["b"], ["c"])],
        methods=[
            MethodSpec("JEPT", config=str(CONFIGS / "train_jept_small_cpu.json")),
            MethodSpec(
                "BC+IDM",
                kind="bc_idm",
                config=str(CONFIGS / "train_dt_star_small_cpu.json"),
                idm_config=str(CONFIGS / "train_idm_small_cpu.json"),
            ),
        ],
        seeds=[1, 2],
        steps=10,
        random_episodes=0,
        output_dir=tmp_path / "study",
    )
    return StudyConfig(**{**defaults, **kwargs})


def test_plan_runs_the_real_entry_points_in_order(tmp_path):
    cfg = study(tmp_path, random_episodes=3)
    steps = plan(cfg)
    keys = [s.key for s in steps]
    assert keys[:2] == ["s/build", "s/random_floor"] and keys[-1] == "s/compare"
    assert keys[2:4] == ["s/JEPT/seed1/train", "s/JEPT/seed1/suite"]
    assert keys[4:8] == [
        "s/BC+IDM/seed1/idm",
        "s/BC+IDM/seed1/relabel",
        "s/BC+IDM/seed1/train",
        "s/BC+IDM/seed1/suite",
    ]
    assert keys[-2] == "s/visualize" and len(steps) == 2 + 2 * 2 + 4 * 2 + 2
    visualize = steps[-2].command
    assert (
        "--policy.path="
        + str(
            run_folder(Path(cfg.output_dir), cfg.splits[0], cfg.methods[0], 1)
            / "train/checkpoints/last/pretrained_model"
        )
        in visualize
    )
    assert any(a.startswith("--baseline.path=") and "BC_IDM/seed1" in a for a in visualize)
    commands = {s.key: s.command for s in steps}
    assert Path(commands["s/build"][0]).name == "jept-build-metaworld"
    assert "--probe_episodes_per_task=4" in commands["s/build"]
    train = commands["s/JEPT/seed2/train"]
    assert Path(train[0]).name == "lerobot-train" and "--seed=2" in train
    assert "--dataset.repo_id=test/x_mix" in train and "--policy.prompt_repo_id=test/x_prompts" in train
    idm = commands["s/BC+IDM/seed1/idm"]
    assert "--dataset.repo_id=test/x_demo" in idm and not any("prompt_repo_id" in a for a in idm)
    relabel = commands["s/BC+IDM/seed1/relabel"]
    bc = commands["s/BC+IDM/seed1/train"]
    root = next(a for a in relabel if a.startswith("--output_root=")).split("=", 1)[1]
    assert f"--dataset.root={root}" in bc and "--heldout_repo_id=test/x_probe" in relabel
    suite = commands["s/JEPT/seed1/suite"]
    assert Path(suite[0]).name == "jept-eval-suite" and "--dataset.repo_id=test/x_mix" in suite
    compare_runs = json.loads(
        next(a for a in commands["s/compare"] if a.startswith("--runs=")).split("=", 1)[1]
    )
    assert list(compare_runs) == ["JEPT", "BC+IDM"] and len(compare_runs["JEPT"]) == 2


def test_the_runs_of_every_split_share_one_pool(tmp_path):
    """Both splits' data first, then every run of both splits in one group (parallel runs never wait for the
    other split's last run), then each split's figures and comparison."""
    splits = [SplitSpec("s", "test/x", ["a"], ["b"], []), SplitSpec("t", "test/y", ["b"], ["a"], [])]
    groups = step_groups(plan(study(tmp_path, splits=splits, random_episodes=3)))
    keys = [[[step.key for step in run] for run in group] for group in groups]
    assert keys[:4] == [[["s/build"]], [["s/random_floor"]], [["t/build"]], [["t/random_floor"]]]
    assert [run[0] for run in keys[4]] == [
        f"{split}/{method}/seed{seed}/{first}"
        for split in "st"
        for seed in (1, 2)
        for method, first in (("JEPT", "train"), ("BC+IDM", "idm"))
    ]
    assert keys[5:] == [[["s/visualize"]], [["s/compare"]], [["t/visualize"]], [["t/compare"]]]


def test_play_episodes_join_the_labelled_frames_of_the_no_video_arm(tmp_path):
    """With play episodes, `labelled` data (and BC+IDM's inverse dynamics) train on _demo + _play, mixed once
    per split by jept-mix; without, on _demo."""
    twin = MethodSpec(
        "J0", config=str(CONFIGS / "train_jept_small_cpu.json"), data="labelled", eval_episodes=3
    )
    cfg = study(tmp_path, build=BuildSpec(play_episodes_per_task=2), methods=[*study(tmp_path).methods, twin])
    commands = {s.key: s.command for s in plan(cfg)}
    assert "--play_episodes_per_task=2" in commands["s/build"]
    mix = commands["s/labelled"]
    assert Path(mix[0]).name == "jept-mix" and "--demo_repo_ids=[test/x_demo, test/x_play]" in mix
    assert "--output_repo_id=test/x_labelled" in mix
    assert "--dataset.repo_id=test/x_labelled" in commands["s/J0/seed1/train"]
    assert "--dataset.repo_id=test/x_labelled" in commands["s/BC+IDM/seed1/idm"]
    assert (
        "--n_episodes=3" in commands["s/J0/seed1/suite"]
        and "--n_episodes=10" in commands["s/JEPT/seed1/suite"]
    )
    plain = {s.key: s.command for s in plan(study(tmp_path, methods=[twin]))}
    assert "s/labelled" not in plain and "--dataset.repo_id=test/x_demo" in plain["s/J0/seed1/train"]


def test_a_method_can_evaluate_another_methods_checkpoints_with_its_own_control_flags(tmp_path):
    """checkpoints_of: no training, the source's checkpoint evaluated with the method's suite_args into its own
    folder, in the source's run after the source's own evaluation (so after its training, also in parallel);
    the method is a column of the comparison; the figures draw trained methods only."""
    decoded = MethodSpec(
        "JEPT, expectation",
        checkpoints_of="JEPT",
        suite_args=["--policy.action_decoding=expectation"],
    )
    cfg = study(tmp_path, methods=[*study(tmp_path).methods, decoded])
    validate(cfg)
    steps = plan(cfg)
    keys = [s.key for s in steps]
    assert "s/JEPT, expectation/seed1/train" not in keys
    suite = next(s for s in steps if s.key == "s/JEPT, expectation/seed1/suite")
    source = run_folder(Path(cfg.output_dir), cfg.splits[0], cfg.methods[0], 1)
    assert f"--policy.path={source / 'train/checkpoints/last/pretrained_model'}" in suite.command
    assert suite.command[-1] == "--policy.action_decoding=expectation"
    assert suite.folder == run_folder(Path(cfg.output_dir), cfg.splits[0], decoded, 1)
    runs = {tuple(s.key for s in run) for group in step_groups(steps) for run in group}
    assert ("s/JEPT/seed1/train", "s/JEPT/seed1/suite", "s/JEPT, expectation/seed1/suite") in runs
    compare = json.loads(next(a for a in steps[-1].command if a.startswith("--runs=")).split("=", 1)[1])
    assert list(compare) == ["JEPT", "BC+IDM", "JEPT, expectation"]
    assert not any("expectation" in a for a in next(s for s in steps if s.key == "s/visualize").command)
    for methods in (
        [decoded, *study(tmp_path).methods],
        [*study(tmp_path).methods, dataclasses.replace(decoded, checkpoints_of="JEPT, expectation")],
    ):
        with pytest.raises(StudyError, match="must be a method listed before it that trains"):
            validate(study(tmp_path, methods=methods))


def test_a_method_can_continue_another_methods_training_to_more_steps(tmp_path):
    """continue_from: LeRobot's resume of the source's last checkpoint into the method's own folder, to its own
    steps, with its args on top; in the source's run after the source's evaluation; a kill during it resumes
    from its own checkpoint. Its training time is estimated from its own finished runs, not the source's."""
    longer = MethodSpec("JEPT, longer", continue_from="JEPT", steps=30, args=["--log_freq=5"])
    cfg = study(tmp_path, methods=[*study(tmp_path).methods, longer])
    validate(cfg)
    steps = plan(cfg)
    train = next(s for s in steps if s.key == "s/JEPT, longer/seed1/train")
    source = run_folder(Path(cfg.output_dir), cfg.splits[0], cfg.methods[0], 1)
    folder = run_folder(Path(cfg.output_dir), cfg.splits[0], longer, 1)
    assert train.command[1:] == [
        f"--config_path={source / 'train/checkpoints/last/pretrained_model/train_config.json'}",
        "--resume=true",
        "--steps=30",
        "--save_freq=30",
        f"--output_dir={folder / 'train'}",
        "--log_freq=5",
    ]
    suite = next(s for s in steps if s.key == "s/JEPT, longer/seed1/suite")
    assert f"--policy.path={folder / 'train/checkpoints/last/pretrained_model'}" in suite.command
    runs = {tuple(s.key for s in run) for group in step_groups(steps) for run in group}
    assert (
        "s/JEPT/seed2/train",
        "s/JEPT/seed2/suite",
        "s/JEPT, longer/seed2/train",
        "s/JEPT, longer/seed2/suite",
    ) in runs
    own = folder / "train/checkpoints/000020/pretrained_model"
    own.mkdir(parents=True)
    (own / "train_config.json").write_text("{}")
    (folder / "train/checkpoints/last").symlink_to("000020")
    before = dict(zip([s.key for s in steps], estimate_seconds(cfg, steps), strict=True))
    assert before["s/JEPT, longer/seed1/train"] == pytest.approx(0.9 * 20)  # the prior, per step it adds
    assert train.prepare() == [
        train.command[0],
        f"--config_path={own / 'train_config.json'}",
        "--resume=true",
    ]
    source.mkdir(parents=True)
    (source / "train.done.json").write_text(json.dumps({"planned": plan(cfg)[2].command, "seconds": 100.0}))
    (folder / "train.done.json").write_text(json.dumps({"planned": train.command, "seconds": 40.0}))
    estimates = dict(zip([s.key for s in steps], estimate_seconds(cfg, steps), strict=True))
    assert estimates["s/JEPT/seed2/train"] == 100.0 and estimates["s/JEPT, longer/seed2/train"] == 40.0
    assert "(JEPT, longer 30)" in write_report(cfg).read_text()
    # the continued runs' intermediate checkpoints, evaluated (LeRobot's folder names); steps no run saves refused
    middle = MethodSpec("JEPT, longer at 20", checkpoints_of="JEPT, longer", checkpoint=20)
    cfg = study(tmp_path, methods=[*cfg.methods, middle], save_freq=10)
    validate(cfg)
    suite = next(s for s in plan(cfg) if s.key == "s/JEPT, longer at 20/seed1/suite")
    assert f"--policy.path={folder / 'train/checkpoints/000020/pretrained_model'}" in suite.command
    for step in (10, 25, 40):  # JEPT's step-10 checkpoint is not in the longer run's folder
        methods = [*cfg.methods[:3], dataclasses.replace(middle, checkpoint=step)]
        with pytest.raises(StudyError, match=r"one of \[20, 30\]"):
            validate(dataclasses.replace(cfg, methods=methods))
    for bad, message in (
        (dataclasses.replace(longer, steps=10), 'give it "steps" above that'),
        (dataclasses.replace(longer, continue_from="nope"), "must be a method listed before it that trains"),
    ):
        with pytest.raises(StudyError, match=message):
            validate(study(tmp_path, methods=[*study(tmp_path).methods, bad]))


@pytest.mark.parametrize(
    "change, message",
    [
        ({"methods": []}, "at least one split, one method and one seed"),
        ({"methods": [MethodSpec("A"), MethodSpec("A")]}, "share a name"),
        ({"methods": [MethodSpec("A", config="nope.json")]}, "nope.json does not exist"),
        ({"methods": [MethodSpec("A", kind="rl")]}, "kind must be train or bc_idm"),
        ({"device": "tpu"}, "--device must be"),
    ],
)
def test_bad_study_files_get_one_clear_error(tmp_path, change, message):
    with pytest.raises(StudyError, match=message):
        validate(study(tmp_path, **change))


def test_killed_training_resumes_from_its_checkpoint_or_restarts_clean(tmp_path):
    cfg = study(tmp_path)
    step = next(s for s in plan(cfg) if s.key == "s/JEPT/seed1/train")
    train = step.folder / "train"
    (train / "logs").mkdir(parents=True)
    assert step.prepare() is None and not train.exists()  # killed before any checkpoint: start clean
    saved = train / "checkpoints/000300/pretrained_model"
    saved.mkdir(parents=True)
    (saved / "train_config.json").write_text("{}")
    (train / "checkpoints/last").symlink_to("000300")  # as LeRobot leaves it
    resumed = step.prepare()
    assert resumed[1:] == [f"--config_path={saved / 'train_config.json'}", "--resume=true"]


def test_training_curves_drop_what_a_killed_run_logged_past_its_checkpoint(tmp_path):
    cfg = study(tmp_path)
    split = cfg.splits[0]
    step = next(s for s in plan(cfg) if s.key == "s/JEPT/seed1/train")
    saved = step.folder / "train/checkpoints/000002/pretrained_model"
    saved.mkdir(parents=True)
    (saved / "train_config.json").write_text(json.dumps({"log_freq": 1}))
    (step.folder / "train/checkpoints/last").symlink_to("000002")

    def logged(losses):
        return "\n".join(f"INFO step:{i + 1} loss:9 loss_act:{v}" for i, v in enumerate(losses))

    # killed at step 3 after the checkpoint of step 2, resumed from it, finished at step 4
    (step.folder / "train.log").write_text(
        f"$ lerobot-train --seed=1\n{logged([4, 3, 2.5])}\n$ {shlex.join(step.prepare())}\n"
        + logged([0, 0, 2, 1]).split("\n", 2)[2]
    )
    assert training_curves(cfg, split)["JEPT"]["loss_act"] == [([1, 2, 3, 4], [4.0, 3.0, 2.0, 1.0])]

    # a run kept without its checkpoints (an archived study): log_freq from the flags the study gave
    shutil.rmtree(step.folder / "train")
    flagged = dataclasses.replace(cfg, train_args=["--log_freq=1"])
    assert training_curves(flagged, split)["JEPT"]["loss_act"] == [([1, 2, 3, 4], [4.0, 3.0, 2.0, 1.0])]
    (step.folder / "train.log").write_text(f"$ lerobot-train --seed=1\n{logged([4, 3])}\n")
    every = json.loads((CONFIGS / "train_jept_small_cpu.json").read_text())["log_freq"]  # the method's config
    assert training_curves(cfg, split)["JEPT"]["loss_act"] == [([every, 2 * every], [4.0, 3.0])]


def test_a_marker_of_another_command_is_refused(tmp_path):
    step = plan(study(tmp_path))[0]
    step.folder.mkdir(parents=True)
    step.marker.write_text(json.dumps({"planned": step.command}))
    assert step.done()
    changed = plan(study(tmp_path, build=BuildSpec(episodes_per_task=99)))[0]
    with pytest.raises(StudyError, match="another command"):
        changed.done()


def test_figures_drawn_with_one_seed_list_stay_done_when_the_list_grows(tmp_path):
    first = next(s for s in plan(study(tmp_path, seeds=[2])) if s.key == "s/visualize")
    assert any("JEPT/seed2" in a for a in first.command)
    first.folder.mkdir(parents=True)
    first.marker.write_text(json.dumps({"planned": first.planned}))
    grown = next(s for s in plan(study(tmp_path, seeds=[1, 2, 3])) if s.key == "s/visualize")
    assert any("JEPT/seed1" in a for a in grown.command) and grown.done()
    # a study run in passes: figures drawn by a pass with JEPT alone stay done for the whole file, and so do
    # figures whose marker names the baseline drawn beside
    alone = study(tmp_path, seeds=[1])
    alone.methods = alone.methods[:1]
    assert next(s for s in plan(alone) if s.key == "s/visualize").done()
    first.marker.write_text(json.dumps({"planned": [*first.planned, "BC+IDM"]}))
    assert grown.done()
    renamed = study(tmp_path, seeds=[1, 2, 3])
    renamed.methods[0].name = "JEPT (plus)"
    with pytest.raises(StudyError, match="another command"):
        next(s for s in plan(renamed) if s.key == "s/visualize").done()


def test_the_progress_bar_weighs_steps_by_what_finished_ones_took(tmp_path):
    cfg = study(tmp_path, random_episodes=3)
    steps = plan(cfg)
    keys = [s.key for s in steps]
    before = dict(zip(keys, estimate_seconds(cfg, steps), strict=True))
    assert before["s/JEPT/seed1/train"] == pytest.approx(0.9 * cfg.steps)  # the prior, per training step
    assert before["s/JEPT/seed1/suite"] == pytest.approx(5.0 * cfg.eval_episodes * 3)  # per episode and task

    def finish(key: str, seconds: float) -> None:
        step = steps[keys.index(key)]
        step.folder.mkdir(parents=True, exist_ok=True)
        step.marker.write_text(json.dumps({"planned": step.planned, "seconds": seconds}))

    finish("s/build", 700.0)
    finish("s/JEPT/seed1/train", 1300.0)
    finish("s/BC+IDM/seed1/train", 500.0)
    after = dict(zip(keys, estimate_seconds(cfg, steps), strict=True))
    assert after["s/build"] == 700.0 and after["s/JEPT/seed1/train"] == 1300.0  # what they took
    assert after["s/JEPT/seed2/train"] == 1300.0 and after["s/BC+IDM/seed2/train"] == 500.0  # same method
    assert after["s/BC+IDM/seed1/idm"] == pytest.approx(0.3 * cfg.steps)  # no idm finished: its prior

    progress = StudyProgress(cfg, steps, [s.done() for s in steps])
    done = 700.0 + 1300.0 + 500.0
    assert progress.bar.n == pytest.approx(done) and progress.bar.total == pytest.approx(sum(after.values()))
    suite = steps[keys.index("s/JEPT/seed2/suite")]
    progress.start(suite)
    assert "3/" in progress.bar.postfix and suite.what in progress.bar.postfix
    assert "<?" in str(progress.bar)  # a step just started says nothing yet of the speed: no ETA of days
    # past its estimate: the bar stops short of the step's end
    progress.running_since[keys.index(suite.key)] -= 10_000.0
    progress.redraw_every = 0.0  # as in a terminal
    progress.running()
    assert progress.bar.n == pytest.approx(done + 0.95 * after["s/JEPT/seed2/suite"])
    finish("s/JEPT/seed2/suite", 40.0)  # quicker than estimated: the other suites of JEPT follow it
    progress.finish(suite)
    assert progress.bar.n == pytest.approx(done + 40.0)
    assert progress.estimates[keys.index("s/JEPT/seed1/suite")] == 40.0
    progress.bar.close()


def test_runs_go_in_parallel_between_the_split_steps_each_in_order(tmp_path):
    cfg = study(tmp_path, random_episodes=3, seeds=[1, 2, 3])
    groups = step_groups(plan(cfg))
    assert [[s.key for s in run] for run in groups[0]] == [["s/build"]]
    assert [[s.key for s in run] for run in groups[1]] == [["s/random_floor"]]
    runs = groups[2]
    assert len(runs) == 2 * 3 and [s.key for s in runs[1]] == [
        "s/BC+IDM/seed1/idm",
        "s/BC+IDM/seed1/relabel",
        "s/BC+IDM/seed1/train",
        "s/BC+IDM/seed1/suite",
    ]
    assert [[[s.key for s in run] for run in group] for group in groups[3:]] == [
        [["s/visualize"]],
        [["s/compare"]],
    ]

    # two runs of two steps each, for real: the runs overlap, each run's steps keep their order, and every
    # command gets cores // 2 torch threads
    def step(key: str) -> Step:
        script = (
            "import os, sys, time; start = time.time(); time.sleep(2); "
            "print(start, time.time(), os.environ.get('OMP_NUM_THREADS'))"
        )
        return Step(key, key, tmp_path / "runs" / key.replace("/", "_"), [sys.executable, "-c", script])

    def times(step: Step) -> list[str]:
        return (step.folder / f"{step.key.split('/')[-1]}.log").read_text().strip().splitlines()[-1].split()

    run_a = [step("s/A/seed1/train"), step("s/A/seed1/suite")]
    run_b = [step("s/B/seed1/train"), step("s/B/seed1/suite")]
    progress = StudyProgress(cfg, run_a + run_b, [False] * 4)
    run_group([run_a, run_b], progress, parallel=2)
    progress.bar.close()
    assert all(s.done() for s in run_a + run_b)
    (a0, a1, threads), (b0, b1, _) = times(run_a[0]), times(run_b[0])
    assert float(b0) < float(a1) and float(a0) < float(b1)  # the two runs' first steps overlap
    for run in (run_a, run_b):
        assert float(times(run[0])[1]) <= float(times(run[1])[0])  # a run's steps one after the other
    assert threads == str(max(1, (os.cpu_count() or 1) // 2))

    # a failing run stops the group with its step's log; the other run finishes the step it was on
    bad = Step("s/C/seed1/train", "bad", tmp_path / "bad", [sys.executable, "-c", "raise SystemExit(3)"])
    slow = [step("s/D/seed1/train"), step("s/D/seed1/suite")]
    with pytest.raises(StudyError, match="s/C/seed1/train failed"):
        run_group([[bad], slow], StudyProgress(cfg, [bad, *slow], [False] * 3), parallel=2)
    assert slow[0].done()


def test_probe_accuracy_on_a_hand_checked_batch():
    predicted = torch.tensor([[0, 1, 2], [3, 3, 3], [6, 5, 4], [1, 1, 1]])
    labels = torch.tensor([[0, 1, 2], [3, 0, 3], [6, 0, 0], [-100, -100, -100]])  # last row unlabelled
    whole, per_dim = bin_accuracy(predicted, labels)
    assert whole == pytest.approx(1 / 3)  # only the first of the three labelled rows is right in full
    assert per_dim == pytest.approx((3 + 2 + 1) / 9)
    assert all(math.isnan(v) for v in bin_accuracy(predicted[3:], labels[3:]))
    rows = {
        "a": {"control_whole": 0.5, "inverse_whole": 0.7, "loss_obs": 2.0, "previous_whole": 0.4},
        "b": {
            "previous_whole": 0.6,
            "control_whole": 0.1,
            "inverse_whole": 0.3,
            "loss_obs": 4.0,
            "swap_changed": {"a": 0.2},
            "swap_control_whole": {"a": 0.05},
        },
        "b2": {
            "control_whole": 0.3,
            "inverse_whole": 0.5,
            "loss_obs": 6.0,
            "swap_changed": {"x": 0.4, "y": 0.6},
            "swap_control_whole": {"x": 0.1, "y": 0.3},
        },
    }
    summary = split_summary(
        rows,
        {"a": 1.0, "b": 0.5, "b2": 0.0},
        {"demo": ["a"], "video": ["b", "b2"], "unseen": ["c"]},
        {"a": 1.0, "b": 1.0, "b2": 0.5},
    )
    assert list(summary) == ["T_demo", "T_vid"]  # no probed unseen task
    assert summary["T_vid"]["control_whole"] == pytest.approx(0.2)
    assert summary["T_vid"]["loss_obs"] == pytest.approx(5.0) and summary["T_vid"]["nc_accuracy"] == 0.25
    assert summary["T_vid"]["nc_accuracy_trained"] == 0.75
    assert (
        summary["T_vid"]["previous_whole"] == 0.6 and summary["T_demo"]["previous_whole"] == 0.4
    )  # b2 has none
    assert summary["T_vid"]["swap_changed"] == pytest.approx((0.2 + 0.5) / 2)  # per task over its mates first
    assert summary["T_vid"]["swap_control_whole"] == pytest.approx((0.05 + 0.2) / 2)
    assert "swap_changed" not in summary["T_demo"]  # a has no scene-mate


def test_report_numbers_are_those_of_the_suite_outputs(tmp_path):
    cfg = study(tmp_path, seeds=[1, 2, 3])
    out = Path(cfg.output_dir)
    runs = {}
    # JEPT: T_vid task b succeeds on 2, 4, 6 of 10 episodes -> 20, 40, 60; DT-like BC+IDM: 0 everywhere.
    for method, hits in (("JEPT", [2, 4, 6]), ("BC+IDM", [0, 0, 0])):
        m = next(x for x in cfg.methods if x.name == method)
        for seed, n in zip(cfg.seeds, hits, strict=True):
            folder = run_folder(out, cfg.splits[0], m, seed) / "suite"
            suite_output(
                folder, SPLIT, {"a": [True] * 10, "b": [True] * n + [False] * (10 - n), "c": [False] * 10}
            )
            results = json.loads((folder / "results.json").read_text())
            probe = {"T_vid": {"control_whole": n / 10, "control_per_dim": 0.5, "previous_whole": 0.45}}
            if method == "JEPT":
                probe["T_vid"].update(inverse_whole=0.9, inverse_per_dim=0.95, loss_obs=1.5)
                probe["T_vid"].update(nc_accuracy=1.0, nc_accuracy_trained=0.9)
                probe["T_vid"].update(swap_changed=n / 10, swap_control_whole=0.1)
            results["prompt_probe"] = {"splits": probe}
            (folder / "results.json").write_text(json.dumps(results))
            runs.setdefault(method, []).append(str(folder))
    compare(CompareConfig(runs=runs, output_dir=out / "s/compare"))
    jept = next(m for m in cfg.methods if m.name == "JEPT")
    jept.eval_episodes = 20  # a method's own episode count is named in the header
    report = write_report(cfg).read_text()
    assert "10 evaluation episodes per task and seed (JEPT 20)" in report
    half = 4.302652729911275 * 20 / math.sqrt(3)  # t(0.975, 2) * sd(20, 40, 60) / sqrt(3)
    # Success and accuracies are clipped to [0, 100]: 40 - 49.7 < 0.
    assert f"| T_vid | 40.0 [0.0, {40 + half:.1f}] | 0.0 [0.0, 0.0] |" in report
    assert f"| JEPT | T_vid | 40.0 [0.0, {40 + half:.1f}] | 50.0 [50.0, 50.0] | 90.0 " in report
    assert (
        f"| 1.500 [1.500, 1.500] | 45.0 [45.0, 45.0] | 100.0 [100.0, 100.0] | 90.0 [90.0, 90.0] "
        f"| 40.0 [0.0, {40 + half:.1f}] "
        "| 10.0 [10.0, 10.0] |" in report
    )
    bc_idm = "| BC+IDM | T_vid | 0.0 [0.0, 0.0] | 50.0 [50.0, 50.0] | - | - | - | 45.0 [45.0, 45.0] | - | - | - | - |"
    assert bc_idm in report
    assert "compare/comparison.png" in report


def test_report_only_compares_what_has_finished_and_runs_nothing_else(tmp_path, capsys):
    """JEPT's two seeds have evaluated (3 and 5 of 10 on the video task), nothing else has run."""
    cfg = study(tmp_path, report_only=True)
    out = Path(cfg.output_dir)
    for seed, n in zip(cfg.seeds, (3, 5), strict=True):
        suite = run_folder(out, cfg.splits[0], cfg.methods[0], seed) / "suite"
        suite_output(
            suite, SPLIT, {"a": [True] * 10, "b": [True] * n + [False] * (10 - n), "c": [False] * 10}
        )
    figures = next(s for s in plan(cfg) if s.key == "s/visualize")
    figures.folder.mkdir(parents=True, exist_ok=True)
    figures.marker.write_text(json.dumps({"planned": ["jept-visualize", "s", "another JEPT"]}))
    with pytest.raises(StudyError, match="another command"):
        run_study(dataclasses.replace(cfg, report_only=False))
    capsys.readouterr()
    report = run_study(cfg).read_text()  # the report alone: that marker only means the figures have not run
    assert "| T_vid | 40.0 [" in report  # JEPT's mean of 30 and 50
    assert "BC+IDM" not in (out / "s/compare/comparison.md").read_text()  # no run of it has evaluated
    assert sorted(p.name for p in out.rglob("*.log")) == ["compare.log"]  # no build, training or evaluation
    printed = capsys.readouterr().out
    assert "the report from 0 finished steps of 15; not run: s/build, s/JEPT/seed1/train" in printed
    assert printed.splitlines()[0].endswith(", s/visualize")  # its marker is of another command


def test_preregistered_test_reads_each_case_over_training_seeds(tmp_path):
    """Two cases (video-only tasks b, d): b passes (margin above both seed ranges, scene-mate's prompt at the
    floor), d fails (inside the spread); the verdict needs min_cases passing, the goal mean and the floor."""
    from lerobot_jept.study.config import PreRegisteredTest

    split = {"demo": ["a"], "video": ["b", "d"], "unseen": []}
    cfg = study(
        tmp_path,
        splits=[SplitSpec("s", "test/x", ["a"], ["b", "d"], [])],
        methods=[
            MethodSpec(
                "R",
                config=str(CONFIGS / "train_jept_small_cpu.json"),
                suite_args=["--scene_mate_prompts=true"],
            ),
            MethodSpec("R0", config=str(CONFIGS / "train_jept_small_cpu.json"), data="labelled"),
        ],
        seeds=[1, 2, 3],
        test=PreRegisteredTest(method="R", baseline="R0", min_cases=1, goal_mean=40.0),
    )
    validate(cfg)
    out = Path(cfg.output_dir)
    hits = {"R": {"b": [6, 7, 8], "d": [3, 5, 1]}, "R0": {"b": [1, 0, 2], "d": [2, 1, 3]}}
    for method in cfg.methods:
        for i, seed in enumerate(cfg.seeds):
            folder = run_folder(out, cfg.splits[0], method, seed) / "suite"
            outcome = {t: [True] * n[i] + [False] * (10 - n[i]) for t, n in hits[method.name].items()}
            suite_output(folder, split, {"a": [True] * 10, **outcome})
            results = json.loads((folder / "results.json").read_text())
            if method.name == "R":
                for task in ("b", "d"):
                    results["per_task"][task]["scene_mate"] = {"prompt_task": "a", "pc_success": 0.0}
            (folder / "results.json").write_text(json.dumps(results))
    (out / "s").mkdir(parents=True, exist_ok=True)
    floor = {t: {"pc_success": 0.0, "successes": [False] * 20} for t in ("a", "b", "d")}
    (out / "s/random_floor.done.json").write_text(json.dumps({"per_task": floor}))
    report = write_report(cfg).read_text()
    verdict = json.loads((out / "test.json").read_text())
    b, d = verdict["cases"]
    assert (b["task"], b["method_seeds"], b["baseline_seeds"]) == ("b", [60.0, 70.0, 80.0], [10.0, 0.0, 20.0])
    assert b["margin"] == pytest.approx(60.0) and b["seed_spread"] == 20.0 and b["passes"]
    assert d["margin"] == pytest.approx(10.0) and d["seed_spread"] == 40.0 and not d["passes"]
    assert b["within_floor"] and b["floor_upper"] == pytest.approx(16.1, abs=0.1)  # Wilson, 0 of 20
    assert verdict["cases_passed"] == 1 and verdict["mean_success"] == pytest.approx((70 + 30) / 2)
    assert verdict["holds"] and "The hypothesis **holds**" in report
    assert "![the test's cases](test.png)" in report and (out / "test.png").stat().st_size > 10_000
    assert "| s | b | 60 / 70 / 80 | 10 / 0 / 20 | +60.0 | 20.0 | yes |" in report
    assert "Per scene pair" not in report  # b and d share no scene

    strict = dataclasses.replace(cfg, test=PreRegisteredTest(method="R", baseline="R0", min_cases=2))
    write_report(strict)
    assert not json.loads((out / "test.json").read_text())["holds"]
    with pytest.raises(StudyError, match="both must be methods"):
        validate(dataclasses.replace(cfg, test=PreRegisteredTest(method="R", baseline="nope")))


def test_video_only_summary_reads_every_method_on_the_episodes_all_of_them_ran(tmp_path):
    """Two splits, one video-only task each. R ran 20 episodes per case, R0 10: both are read on the first 10,
    so R's successes in its last 10 episodes do not count. R0's seed 3 has no suite on the second split: its
    mean and interval come from seeds 1 and 2 only. Welch's p is against the first method, over seeds."""
    from scipy import stats

    # one scene pair (x-open / x-close), each direction the video-only task of one split
    a, b = "x-open", "x-close"
    splits = [SplitSpec("s1", "test/x", [a], [b], []), SplitSpec("s2", "test/y", [b], [a], [])]
    jept = str(CONFIGS / "train_jept_small_cpu.json")
    cfg = study(
        tmp_path,
        splits=splits,
        methods=[
            MethodSpec("R", config=jept, eval_episodes=20),
            MethodSpec("R0", config=jept, data="labelled"),
            MethodSpec("R, decoded", checkpoints_of="R"),
            MethodSpec("R, longer", continue_from="R", steps=20),
        ],
        seeds=[1, 2, 3],
    )
    out = Path(cfg.output_dir)
    # successes in the first ten episodes per (split, seed); R also succeeds in all of its last ten
    hits = {
        "R": {"s1": [4, 6, 8], "s2": [2, 2, 5]},
        "R0": {"s1": [1, 0, 2], "s2": [0, 3, None]},
        "R, decoded": {"s1": [5, 7, 9], "s2": [3, 3, 5]},
        "R, longer": {"s1": [4, 6, 9], "s2": [2, 2, 5]},
    }
    for method in cfg.methods:
        episodes = method.eval_episodes or cfg.eval_episodes
        for split in splits:
            task = split.video_tasks[0]
            for i, seed in enumerate(cfg.seeds):
                n = hits[method.name][split.name][i]
                if n is None:
                    continue
                outcome = [True] * n + [False] * (10 - n) + [True] * (episodes - 10)
                folder = run_folder(out, split, method, seed) / "suite"
                suite_output(folder, {"demo": [], "video": [task], "unseen": []}, {task: outcome})
        (out / split.name).mkdir(parents=True, exist_ok=True)
    for split, floor in zip(splits, (3, 1), strict=True):
        outcomes = [True] * floor + [False] * (20 - floor)
        (out / split.name / "random_floor.done.json").write_text(
            json.dumps({"per_task": {split.video_tasks[0]: {"successes": outcomes}}})
        )
    report = write_report(cfg).read_text()
    summary = json.loads((out / "video_only.json").read_text())
    assert summary["episodes"] == 10 and summary["cases"] == ["x-close (s1)", "x-open (s2)"]
    r, r0 = summary["methods"]["R"], summary["methods"]["R0"]
    assert r["seed_means"] == {"1": 30.0, "2": 40.0, "3": 65.0} and r["mean"] == pytest.approx(45.0)
    assert r0["seed_means"] == {"1": 5.0, "2": 15.0} and r0["counts"]["3"] == [2, None]
    expected = stats.ttest_ind([5.0, 15.0], [30.0, 40.0, 65.0], equal_var=False).pvalue
    assert r0["p_vs_first"] == pytest.approx(expected) and r["p_vs_first"] != r["p_vs_first"]  # NaN
    # R's own checkpoints under another control setting: paired over the seeds (differences 10, 10, 5)
    decoded = summary["methods"]["R, decoded"]
    assert decoded["seed_means"] == {"1": 40.0, "2": 50.0, "3": 70.0} and decoded["paired"]
    expected = stats.ttest_rel([40.0, 50.0, 70.0], [30.0, 40.0, 65.0]).pvalue
    assert decoded["p_vs_first"] == pytest.approx(expected) and not r0["paired"]
    longer = summary["methods"]["R, longer"]  # R's runs trained on: paired as well (differences 0, 0, 5)
    assert longer["paired"] and longer["p_vs_first"] == pytest.approx(
        stats.ttest_rel([30.0, 40.0, 70.0], [30.0, 40.0, 65.0]).pvalue
    )
    assert f"| 40.0, 50.0, 70.0 | {expected:.2f}* |" in report
    assert summary["floor"] == [3, 1]
    assert "| R0 | 1 / 0 / 2 | 0 / 3 / - | 10.0 [0.0, 73.5] | 5.0, 15.0 |" in report
    assert "| random 7-bin (floor) | 3 | 1 | 20.0 | | |" in report
    assert (out / "video_only.png").stat().st_size > 10_000
    # per scene pair: both directions per seed (R0's seed 3 lacks one, so only seeds 1 and 2 count)
    pair = summary["pairs"]["x"]
    assert pair["R"]["seed_means"] == [30.0, 40.0, 65.0] and pair["R0"]["seed_means"] == [5.0, 15.0]
    assert "### Per scene pair" in report and "| method | x |" in report
    assert "| R0 | 10.0 [0.0, 73.5] |" in report and "| random 7-bin (floor) | 20.0 |" in report


@pytest.mark.slow
def test_micro_study_resumes_after_a_kill_and_a_rerun_trains_nothing(tiny_build, tmp_path):
    """The real entry points on the tests' tiny build (its builder re-run is a no-op): JEPT and BC+IDM, one
    seed, 2 steps, 10-step evaluations, and JEPT trained on to 4 steps. Killed (with its children) during
    BC+IDM, re-run, then run again."""
    config = {
        "name": "micro",
        "splits": [
            {
                "name": "tiny",
                "repo_id": "test/mw_tiny",
                "demo_tasks": TINY["demo_tasks"],
                "video_tasks": TINY["video_tasks"],
                "unseen_tasks": TINY["unseen_tasks"],
            }
        ],
        "build": {
            "episodes_per_task": TINY["episodes_per_task"],
            "prompts_per_task": TINY["prompts_per_task"],
            "probe_episodes_per_task": TINY["probe_episodes_per_task"],
            "image_size": TINY["image_size"],
            "num_workers": 1,
            "args": [f"--episodes_per_shard={TINY['episodes_per_shard']}"],
        },
        "methods": [
            {"name": "JEPT", "config": str(CONFIGS / "train_jept_small_cpu.json")},
            {
                "name": "BC+IDM",
                "kind": "bc_idm",
                "config": str(CONFIGS / "train_dt_star_small_cpu.json"),
                "idm_config": str(CONFIGS / "train_idm_small_cpu.json"),
            },
            {"name": "JEPT, longer", "continue_from": "JEPT", "steps": 4},
        ],
        "seeds": [1],
        "steps": 2,
        "train_args": ["--batch_size=2", "--num_workers=0", "--log_freq=1", "--policy.max_prompt_length=4"],
        "eval_episodes": 1,
        "eval_episode_length": 10,
        "random_episodes": 1,
        "output_dir": str(tmp_path / "out"),
    }
    path = tmp_path / "micro.json"
    path.write_text(json.dumps(config))
    out = tmp_path / "out/tiny"
    proc = subprocess.Popen(
        [str(Path(sys.executable).parent / "jept-study"), f"--config={path}"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: the kill takes lerobot-train with it
    )
    deadline = time.time() + 600
    while time.time() < deadline and not (out / "BC_IDM/seed1/idm/train").exists():
        assert proc.poll() is None, "the study ended before the kill"
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (out / "JEPT/seed1/suite.done.json").is_file() and not (
        out / "BC_IDM/seed1/suite.done.json"
    ).exists()
    jept_done = (out / "JEPT/seed1/train.done.json").stat().st_mtime

    main([f"--config={path}"])  # resumes: JEPT is not trained again
    assert (out / "JEPT/seed1/train.done.json").stat().st_mtime == jept_done
    report = (tmp_path / "out/report.md").read_text()
    assert "| T_vid |" in report and "| BC+IDM | T_vid |" in report and "Random 7-bin" in report
    results = json.loads((out / "BC_IDM/seed1/suite/results.json").read_text())
    assert results["policy_type"] == "jept_dt_star" and results["prompt_probe"]["splits"]
    assert (out / "training_curves.png").stat().st_size > 1000
    # JEPT, longer: LeRobot's resume of JEPT's step-2 checkpoint, on to step 4 in its own folder
    longer = out / "JEPT_longer/seed1/train/checkpoints"
    assert sorted(p.name for p in longer.iterdir()) == ["000004", "last"]
    assert json.loads((longer / "last/pretrained_model/train_config.json").read_text())["steps"] == 4
    assert sorted(p.name for p in (out / "JEPT/seed1/train/checkpoints").iterdir()) == ["000002", "last"]
    assert "step:3 " in (out / "JEPT_longer/seed1/train.log").read_text()
    assert (out / "JEPT_longer/seed1/suite/results.json").is_file()
    for figure in ("prompt_embeddings.png", "observation_embeddings.png"):  # jept-visualize, JEPT vs DT*
        assert (out / "visualize" / figure).stat().st_size > 1000 and figure in report

    rerun = subprocess.run(
        [str(Path(sys.executable).parent / "jept-study"), f"--config={path}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "12 steps, 11 already done" in rerun.stdout  # only jept-compare runs again
    assert "lerobot-train" not in rerun.stdout + rerun.stderr


@pytest.mark.parametrize(
    "name",
    [
        "cpu_small",
        "cpu_small_videos",
        "cpu_small_prompt",
        "cpu_transfer",
        "paper_metaworld",
        "paper_table2",
        "paper_robosuite",
        "paper_table4",
    ],
)
def test_shipped_study_files_parse_and_plan(name, monkeypatch):
    import draccus

    from lerobot_jept.evaluation.paper import PAPER_SPLIT

    monkeypatch.chdir(REPO)  # the study files name their train configs relative to the repo
    cfg = draccus.parse(StudyConfig, config_path=f"examples/studies/{name}.json", args=[])
    validate(cfg)
    steps = plan(cfg)
    trains = [s for s in steps if s.key.endswith("/train")]
    assert len(trains) == len(cfg.splits) * len(cfg.methods) * len(cfg.seeds) and len(cfg.seeds) >= 3
    if name == "cpu_small":
        split = cfg.splits[0]
        assert len(split.video_tasks) >= 2 and len(split.unseen_tasks) >= 1 and cfg.device == "cpu"
        assert {m.name for m in cfg.methods} >= {"JEPT", "DT*", "BC+IDM", "Vid2Robot-M"}
    if name == "cpu_small_videos":  # the same split and runs as cpu_small, JEPT with and without the videos
        small = draccus.parse(StudyConfig, config_path="examples/studies/cpu_small.json", args=[])
        assert (cfg.splits, cfg.build, cfg.steps, cfg.seeds) == (
            small.splits,
            small.build,
            small.steps,
            small.seeds,
        )
        assert [(m.config, m.data) for m in cfg.methods] == [
            (small.methods[0].config, d) for d in ("mix", "demo")
        ]
    # the prompt study's configuration: the same scene pairs in a repo of their own, with and without the videos
    if name == "cpu_small_prompt":
        small = draccus.parse(StudyConfig, config_path="examples/studies/cpu_small.json", args=[])
        split = cfg.splits[0]
        assert dataclasses.replace(split, repo_id=small.splits[0].repo_id) == small.splits[0]
        assert cfg.build.args == ["--expert_random_prob=0.15"] and split.repo_id != small.splits[0].repo_id
        assert [(m.data, m.args) for m in cfg.methods] == [
            (d, ["--policy.idm_input=self_state", "--policy.prompt_guidance=2"]) for d in ("mix", "demo")
        ]
        train = next(s for s in steps if s.key.endswith("/train")).command
        assert "--policy.idm_input=self_state" in train and "--policy.prompt_guidance=2" in train
    if name == "cpu_transfer":  # four scene pairs, each task once the demo and once the video-only one
        a, b = cfg.splits
        assert (a.demo_tasks, a.video_tasks) == (b.video_tasks, b.demo_tasks) and len(a.video_tasks) == 4
        assert {t.split("-")[0] for t in a.video_tasks} == {"window", "door", "drawer", "faucet"}
        assert cfg.test.method == "JEPT (plus)" and cfg.build.args == [
            "--expert_random_prob=0.15",
            "--video_episodes_per_task=90",
        ]
        methods = {m.name: m for m in cfg.methods}
        twin = methods[cfg.test.baseline]
        assert (twin.config, twin.args, twin.data, methods[cfg.test.method].data) == (
            methods[cfg.test.method].config,
            methods[cfg.test.method].args,
            "labelled",
            "mix",
        )  # the videos are the only difference
        assert {"DT*", "BC+IDM (self-state)", "Vid2Robot-M", "JEPT (paper)", "JEPT (plus), no prompt"} <= set(
            methods
        )
        assert methods["BC+IDM (self-state)"].idm_args == ["--policy.idm_input=self_state"]
        assert (
            methods["JEPT (plus), no prompt"].args == ["--policy.type=jept_no_prompt"]
            and cfg.random_episodes >= 10
        )
        commands = {s.key: s.command for s in steps}
        # no play episodes (jept-screen: they lower the video-only tasks' inverse dynamics): labelled = _demo
        assert "pairs_a/labelled" not in commands and cfg.build.play_episodes_per_task == 0
        twin_train = commands["pairs_a/JEPT (plus), no videos/seed1000/train"]
        assert "--dataset.repo_id=local/transfer90_pairs_a_demo" in twin_train
        idm_train = commands["pairs_a/BC+IDM (self-state)/seed1000/idm"]
        assert "--dataset.repo_id=local/transfer90_pairs_a_demo" in idm_train
        recipe = commands["pairs_b_mirror/JEPT (plus)/seed2000/suite"]
        assert (
            "--n_episodes=20" in recipe
            and "--scene_mate_prompts=true" in recipe
            and "--splits=[video]" in recipe
        )
        assert "--n_episodes=10" in commands["pairs_a/DT*/seed1000/suite"]
    if name == "paper_metaworld":
        split = cfg.splits[0]
        assert {"demo": split.demo_tasks, "video": split.video_tasks, "unseen": split.unseen_tasks} == {
            k: list(v) for k, v in PAPER_SPLIT.items()
        }
    if name == "paper_table4":
        from lerobot_jept.policies.components.backbone import RAFT_MODELS, VIDEOMAE_SIZES

        backbones = [a.split("=", 1)[1] for m in cfg.methods for a in m.args if "vision_backbone=" in a]
        assert backbones[0] in RAFT_MODELS and backbones[1] in VIDEOMAE_SIZES
        assert "dinov2" in backbones[2] and "samvit" in backbones[3]
        train = next(s for s in trains if "RAFT" in s.key)
        assert any(a.startswith("--policy.backbone_weights_path=weights/raft_large") for a in train.command)
    if name == "paper_table2":
        assert [len(s.video_tasks) for s in cfg.splits] == [0, 2, 4, 6]
        assert cfg.splits[1].video_tasks == ["button-press-topdown-wall-v3", "door-open-v3"]  # Appendix B.2
