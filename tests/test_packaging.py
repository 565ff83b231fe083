"""The package as a LeRobot user gets it: a wheel installed with plain uv into a new Python 3.12 environment
that holds only LeRobot, from outside the checkout (so no setting of this repository applies)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
CONFIG = ROOT / "examples/configs/train_jept_small_cpu.json"
UV = shutil.which("uv") or str(Path.home() / ".local/bin/uv")
SIMULATORS = ("metaworld", "robosuite", "mujoco", "mink")


BASE_PYTHON = Path(sys.base_prefix) / "bin" / f"python{sys.version_info.major}.{sys.version_info.minor}"


def run(args: list, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "UV_PYTHON_DOWNLOADS": "never"}
    proc = subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True, env=env)
    assert proc.returncode == 0, f"{args[:3]} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    return proc


def test_plugin_import_loads_no_simulator_and_prints_nothing(tmp_path):
    code = (
        "import sys, lerobot_policy_jept\n"
        f"loaded = sorted({{m.split('.')[0] for m in sys.modules}} & set({SIMULATORS!r}))\n"
        "assert not loaded, loaded\n"
        "assert 'torch' not in sys.modules\n"
    )
    proc = run([sys.executable, "-c", code], tmp_path)
    assert proc.stdout == "" and proc.stderr == ""


@pytest.mark.slow
def test_wheel_installs_into_a_plain_lerobot_env_and_trains(tiny_build, tmp_path):
    run(
        [
            UV,
            "build",
            "--no-config",
            "--python",
            BASE_PYTHON,
            "--wheel",
            "--out-dir",
            tmp_path / "dist",
            ROOT,
        ],
        tmp_path,
    )
    (wheel,) = (tmp_path / "dist").glob("lerobot_policy_jept-*.whl")
    venv = tmp_path / "venv"
    python, bin_dir = venv / "bin/python", venv / "bin"
    run([UV, "venv", "--no-config", "--python", BASE_PYTHON, venv], tmp_path)
    run([UV, "pip", "install", "--no-config", "--python", python, "lerobot==0.6.1"], tmp_path)
    run([UV, "pip", "install", "--no-config", "--python", python, wheel], tmp_path)
    # the simulators are extras, and they resolve with LeRobot's numpy too
    installed = run([UV, "pip", "freeze", "--no-config", "--python", python], tmp_path).stdout
    assert not any(line.split("==")[0] in SIMULATORS for line in installed.splitlines()), installed
    run([UV, "pip", "install", "--no-config", "--dry-run", "--python", python, f"{wheel}[sim]"], tmp_path)

    help_text = run([bin_dir / "lerobot-train", "--policy.type=jept", "--help"], tmp_path).stdout
    assert "--policy.prompt_repo_id" in help_text
    out = tmp_path / "train"
    run(
        [
            bin_dir / "lerobot-train",
            f"--config_path={CONFIG}",
            "--dataset.repo_id=test/mw_tiny_mix",
            "--policy.prompt_repo_id=test/mw_tiny_prompts",
            "--policy.max_prompt_length=4",
            "--batch_size=4",
            "--num_workers=0",
            "--steps=2",
            "--save_freq=2",
            f"--output_dir={out}",
        ],
        tmp_path,
    )
    assert (out / "checkpoints/last/pretrained_model/model.safetensors").is_file()


def test_a_policy_type_taken_by_another_package_does_not_take_the_plugin_down(tmp_path):
    """Another package owning ``idm`` keeps it; the plugin still registers every ``jept_*`` type and says which
    name to use."""
    code = (
        "from dataclasses import dataclass\n"
        "from lerobot.configs.policies import PreTrainedConfig\n"
        "@PreTrainedConfig.register_subclass('idm')\n"
        "@dataclass\n"
        "class OtherIDMConfig(PreTrainedConfig):\n"
        "    pass\n"
        "import lerobot_policy_jept\n"
        "known = PreTrainedConfig.get_known_choices()\n"
        "assert known['idm'] is OtherIDMConfig, known['idm']\n"
        "assert {'jept', 'jept_idm', 'jept_dt_star', 'jept_vid2robot', 'dt_star', 'vid2robot'} <= set(known)\n"
    )
    proc = run([sys.executable, "-W", "always", "-c", code], tmp_path)
    assert "--policy.type=jept_idm" in proc.stderr


def test_training_another_policy_type_on_a_mix_warns(tiny_build, tmp_path):
    """lerobot-train of a policy type that cannot read the mix's label marker (ACT, diffusion, ...) on a _mix
    repo warns with the fix; on the labelled repo, with a jept type, or in another command, it says nothing."""
    from lerobot_jept.registration import mix_warning

    train = "/venv/bin/lerobot-train"
    message = mix_warning([train, "--policy.type=act", "--dataset.repo_id=test/mw_tiny_mix"])
    assert "test/mw_tiny_mix is a mix" in message and "--policy.type=act" in message and "_demo" in message
    assert mix_warning([train, "--policy.type=act", "--dataset.repo_id=test/mw_tiny_demo"]) is None
    assert mix_warning([train, "--policy.type=jept", "--dataset.repo_id=test/mw_tiny_mix"]) is None
    assert (
        mix_warning(["/venv/bin/lerobot-eval", "--policy.type=act", "--dataset.repo_id=test/mw_tiny_mix"])
        is None
    )
    config = tmp_path / "train.json"  # the type and the repo from a config file
    config.write_text(
        json.dumps({"policy": {"type": "diffusion"}, "dataset": {"repo_id": "test/mw_tiny_mix"}})
    )
    assert "--policy.type=diffusion" in mix_warning([train, f"--config_path={config}"])


@pytest.mark.slow
def test_lerobot_train_of_act_on_a_mix_prints_the_warning(tiny_build, tmp_path):
    """The warning above, from a real lerobot-train of LeRobot's ACT on the tiny mix (one step)."""
    lerobot_train = Path(sys.executable).parent / "lerobot-train"
    args = ["--policy.type=act", "--policy.pretrained_backbone_weights=null", "--policy.push_to_hub=false"]
    args += ["--policy.device=cpu", "--steps=1", "--batch_size=2", "--num_workers=0"]
    proc = subprocess.run(
        [lerobot_train, "--dataset.repo_id=test/mw_tiny_mix", *args, f"--output_dir={tmp_path / 'act'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=os.environ.copy(),
    )
    assert "test/mw_tiny_mix is a mix of labelled and action-free episodes" in proc.stderr
    assert "--policy.type=act does not read that marker" in proc.stderr
