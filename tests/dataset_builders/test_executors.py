"""The builder on datatrove: ``--executor=datatrove_local`` and ``--executor=slurm`` (through datatrove's own
SlurmPipelineExecutor, against a stand-in ``sbatch`` that runs the submitted array job's ranks here) record the
same repos, byte for byte, as the local executor."""

import os
import stat
import sys
from pathlib import Path

import pytest

from dataset_builders.core import BuildError, build
from dataset_builders.metaworld import MetaworldBuildConfig, MetaworldSimulator

FLAGS = dict(
    demo_tasks=["reach-v3"],
    video_tasks=["drawer-close-v3"],
    unseen_tasks=[],
    episodes_per_task=2,
    prompts_per_task=1,
    probe_episodes_per_task=1,
    image_size=48,
    episodes_per_shard=1,
    num_workers=2,
)
ROLES = ("demo", "video", "prompts", "probe", "mix")

SBATCH = """#!/bin/bash
# Stand-in for SLURM's sbatch: runs every rank of the submitted (array) job here, one after the other, with the
# variables SLURM sets, then answers as sbatch does.
script="${@: -1}"
array=$(grep -oP '^#SBATCH --array=\\K[0-9]+-[0-9]+' "$script")
if [ -n "$array" ]; then first=${array%-*}; last=${array#*-}; else first=0; last=0; fi
id=$((RANDOM + 1))
echo "$*" >> "$STANDIN_LOG"
for ((i=first; i<=last; i++)); do
  SLURM_ARRAY_TASK_ID=$i SLURM_ARRAY_JOB_ID=$id SLURM_JOB_ID=$id SLURM_NODELIST=localhost SLURM_NODEID=0 \\
    RUN_OFFSET=0 bash "$script" >> "$STANDIN_LOG" 2>&1 || { echo "rank $i of job $id failed" >&2; exit 1; }
done
echo "Submitted batch job $id"
"""
SCONTROL = """#!/bin/bash
# Stand-in for scontrol: `scontrol show hostnames NODELIST` (one node here).
[ "$1 $2" = "show hostnames" ] && echo "$3"
"""
SRUN = """#!/bin/bash
# Stand-in for srun: run the command (its last two words: launch_pickled_pipeline FILE).
exec "${@: -2}"
"""


def payload(root: Path) -> dict[str, bytes]:
    """Every parquet and mp4 file of the build's repos, by path."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for role in ROLES
        for p in sorted((root / f"test/ex_{role}").rglob("*"))
        if p.suffix in (".parquet", ".mp4")
    }


@pytest.fixture(scope="module")
def local_build(tmp_path_factory):
    root = tmp_path_factory.mktemp("local")
    build(MetaworldBuildConfig(repo_id="test/ex", root=str(root), **FLAGS), MetaworldSimulator())
    return payload(root)


@pytest.mark.slow
def test_datatrove_local_gives_the_same_bytes(local_build, tmp_path):
    cfg = MetaworldBuildConfig(repo_id="test/ex", root=str(tmp_path), executor="datatrove_local", **FLAGS)
    build(cfg, MetaworldSimulator())
    got = payload(tmp_path)
    assert set(got) == set(local_build) and len(got) >= 10
    assert all(got[name] == data for name, data in local_build.items())
    # A re-run finds every shard recorded and changes nothing.
    build(cfg, MetaworldSimulator())
    assert payload(tmp_path) == got


@pytest.mark.slow
def test_slurm_array_job_and_dependent_assembly(local_build, tmp_path, monkeypatch):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, text in (("sbatch", SBATCH), ("srun", SRUN), ("scontrol", SCONTROL)):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod((bin_dir / name).stat().st_mode | stat.S_IEXEC)
    log = tmp_path / "standin.log"
    monkeypatch.setenv(
        "PATH", f"{bin_dir}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    )
    monkeypatch.setenv("STANDIN_LOG", str(log))
    root = tmp_path / "root"
    cfg = MetaworldBuildConfig(
        repo_id="test/ex", root=str(root), executor="slurm", tasks=3, logs_dir=str(tmp_path / "logs"), **FLAGS
    )
    cfg.slurm.partition = "cpu"
    jobs = build(cfg, MetaworldSimulator())
    assert jobs["record_job"] and jobs["assemble_job"]
    submitted = log.read_text()
    assert f"--dependency=afterok:{jobs['record_job']}" in submitted  # the assembly waits for the shards
    launch = (tmp_path / "logs/record/launch_script.slurm").read_text()
    assert "#SBATCH --array=0-2" in launch and "#SBATCH --partition=cpu" in launch
    got = payload(root)
    assert set(got) == set(local_build) and all(got[name] == data for name, data in local_build.items())


def test_missing_datatrove_or_bad_executor_names_the_fix(tmp_path, monkeypatch):
    with pytest.raises(BuildError, match="--executor must be one of local, datatrove_local, slurm"):
        build(
            MetaworldBuildConfig(repo_id="test/ex", root=str(tmp_path), executor="k8s", **FLAGS),
            MetaworldSimulator(),
        )
    monkeypatch.setitem(sys.modules, "datatrove", None)  # as if the [cluster] extra were not installed
    cfg = MetaworldBuildConfig(repo_id="test/ex", root=str(tmp_path), executor="datatrove_local", **FLAGS)
    with pytest.raises(BuildError, match=r"lerobot_policy_jept\[cluster\]"):
        build(cfg, MetaworldSimulator())
