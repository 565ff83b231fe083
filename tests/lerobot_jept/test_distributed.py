"""lerobot-train of jept on two processes through ``accelerate launch`` (CPU, gloo): the ranks stay identical
across Algorithm 1's phase switches and the prompt warm-up, and the checkpoint counts the optimizer steps."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from safetensors.torch import load_file

from tests.lerobot_jept.test_end_to_end import CONFIG, MIX, PROMPTS, TINY_TRAIN

BIN = Path(sys.executable).parent
# lerobot-train, with every rank writing a fingerprint of its parameters after each optimizer step.
# A rank that hangs (a collective one rank never reaches, a thread that blocks exit) prints every thread's stack
# and exits, so the launcher fails with the stacks in its output instead of the test waiting forever.
WRAPPER = """
import faulthandler, json, os, sys
faulthandler.dump_traceback_later(HANG_S, exit=True)
import torch
from lerobot_jept.policies.jept.modeling_jept import JEPTPolicy

update = JEPTPolicy.update

def update_and_record(self):
    update(self)
    with torch.no_grad():
        total = sum(p.double().sum().item() for p in self.parameters())
        squares = sum((p.double() ** 2).sum().item() for p in self.parameters())
    with open(os.path.join(os.environ["RANKS_DIR"], f"rank{os.environ['RANK']}.jsonl"), "a") as f:
        f.write(json.dumps([int(self.num_updates), self.phase, total, squares]) + "\\n")

JEPTPolicy.update = update_and_record
from lerobot.scripts.lerobot_train import main
sys.exit(main())
"""
HANG_S = 600


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_processes_stay_identical_across_phase_switches(tiny_build, tmp_path):
    wrapper = tmp_path / "train_and_record.py"
    wrapper.write_text(WRAPPER.replace("HANG_S", str(HANG_S)))
    ranks = tmp_path / "ranks"
    ranks.mkdir()
    steps = 6
    cmd = [
        str(BIN / "accelerate"),
        "launch",
        "--multi_gpu",  # not --cpu: `--cpu --num_processes 2` runs ONE process (see the README)
        "--num_processes=2",
        "--num_machines=1",
        "--mixed_precision=no",
        "--dynamo_backend=no",
        "--main_process_ip=127.0.0.1",
        f"--main_process_port={free_port()}",
        str(wrapper),
        f"--config_path={CONFIG}",
        f"--dataset.repo_id={MIX}",
        f"--policy.prompt_repo_id={PROMPTS}",
        "--policy.phase_steps=2",  # encoder, others, encoder: two phase switches
        "--policy.prompt_warmup_steps=3",
        f"--steps={steps}",
        f"--save_freq={steps}",
        f"--output_dir={tmp_path / 'out'}",
        *TINY_TRAIN,
    ]
    env = {**os.environ, "RANKS_DIR": str(ranks), "CUDA_VISIBLE_DEVICES": "", "OMP_NUM_THREADS": "1"}
    # Both ranks on this host: the rendezvous on a free loopback port, gloo's mesh over loopback.
    env["GLOO_SOCKET_IFNAME"] = "lo"
    try:
        proc = subprocess.run(
            cmd, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=HANG_S + 300
        )
    except subprocess.TimeoutExpired as e:  # the launcher itself hung: show what the ranks printed
        pytest.fail(
            f"accelerate launch still running after {e.timeout} s:\n{e.stdout!s:.3000}\n{e.stderr!s:.5000}"
        )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    logs = {
        r: [json.loads(line) for line in (ranks / f"rank{r}.jsonl").read_text().splitlines()] for r in (0, 1)
    }
    assert [row[0] for row in logs[0]] == list(range(1, steps + 1))
    assert {row[1] for row in logs[0]} == {"encoder", "others"}
    assert logs[0] == logs[1]  # bit-identical parameters on both ranks after every step
    assert len({row[2] for row in logs[0]}) == steps  # and they do move
    weights = load_file(tmp_path / "out/checkpoints/last/pretrained_model/model.safetensors")
    assert int(weights["num_updates"]) == steps
