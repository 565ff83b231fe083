"""Running a build's shards on datatrove, the engine LeRobot's own large dataset jobs run on (its DROID and
AgiBot porting scripts): ``--executor=datatrove_local`` (datatrove's ``LocalPipelineExecutor``) or
``--executor=slurm`` (``SlurmPipelineExecutor``: an array job of shard groups, then a dependent one-task job that
assembles the repos, and pushes them when asked).

Each datatrove task is a shard group: rank r of T records the shards ``plan[r::T]`` that are not on disk yet,
with the same ``record_shard`` as the local executor, so a shard holds the same seeds and episodes whichever
executor recorded it, and a re-run (after a failed or cancelled job) redoes only the missing shards.
"""

import sys
from pathlib import Path

from dataset_builders.config import BuildConfig, BuildError, Simulator
from dataset_builders.plan import BuildPaths, Shard, plan_shards

try:
    from datatrove.pipeline.base import PipelineStep
except ImportError:  # datatrove is an optional extra; _datatrove() says how to install it
    PipelineStep = object


def _datatrove():
    try:
        import datatrove  # noqa: F401
    except ImportError:
        raise BuildError(
            "--executor=datatrove_local|slurm needs datatrove: pip install 'lerobot_policy_jept[cluster]' "
            "(or `uv sync --extra cluster`)."
        ) from None


class BuildStep(PipelineStep):
    """A datatrove pipeline step of a build: it carries the build's flags and simulator (both picklable)."""

    type = "jept-build"

    def __init__(self, cfg: BuildConfig, sim: Simulator):
        super().__init__()
        self.cfg, self.sim = cfg, sim


class RecordShardGroup(BuildStep):
    """Rank r of T: record the missing shards ``plan[r::T]``."""

    name = "record shards"

    def run(self, data=None, rank: int = 0, world_size: int = 1):
        from dataset_builders.record import close_renderer, record_shard
        from lerobot_jept.envs.rendering import setup_offscreen_gl

        setup_offscreen_gl()
        paths = BuildPaths(self.cfg)
        mine = [s for s in plan_shards(self.cfg)[rank::world_size] if not paths.shard(s).exists()]
        try:
            for shard in mine:
                record_shard(self.sim, self.cfg, shard, lambda *args: None)
                self.stat_update("shards")
        finally:
            close_renderer()


class AssembleBuild(BuildStep):
    """The dependent step: assemble the repos (and push them) once every shard is recorded."""

    name = "assemble repos"

    def run(self, data=None, rank: int = 0, world_size: int = 1):
        from dataset_builders.assemble import finish

        paths = BuildPaths(self.cfg)
        missing = [s.name for s in plan_shards(self.cfg) if not paths.shard(s).exists()]
        if missing:
            raise BuildError(
                f"{len(missing)} shards are missing (first: {missing[0]}): a recording task failed; re-run the "
                "same jept-build command to record them."
            )
        finish(self.cfg, self.sim, paths, plan_shards(self.cfg), record_seconds=0.0)


def num_tasks(cfg: BuildConfig, shards: list[Shard]) -> int:
    return max(1, min(cfg.tasks or len(shards), len(shards)))


def logs_dir(cfg: BuildConfig, paths: BuildPaths) -> Path:
    return Path(cfg.logs_dir) if cfg.logs_dir else paths.work / "datatrove_logs"


def record_datatrove_local(sim: Simulator, cfg: BuildConfig, paths: BuildPaths, shards: list[Shard]) -> None:
    """Record the missing shards with datatrove's ``LocalPipelineExecutor`` (``num_workers`` at once)."""
    _datatrove()
    from datatrove.executor import LocalPipelineExecutor

    executor = LocalPipelineExecutor(
        pipeline=[RecordShardGroup(cfg, sim)],
        tasks=num_tasks(cfg, shards),
        workers=cfg.num_workers,
        logging_dir=str(logs_dir(cfg, paths) / "record"),
        skip_completed=False,  # every rank checks its shards: a deleted or failed shard is recorded again
        start_method="spawn",  # a fresh process has no inherited GL context
    )
    executor.run()
    missing = [s.name for s in shards if not paths.shard(s).exists()]
    if missing:
        raise BuildError(
            f"datatrove finished but {len(missing)} shards are missing (first: {missing[0]}); see the task logs "
            f"in {logs_dir(cfg, paths) / 'record/logs'} and re-run the same command."
        )


def submit_slurm(sim: Simulator, cfg: BuildConfig, paths: BuildPaths, shards: list[Shard]) -> dict:
    """Submit the shard groups as a SLURM array job and the assembly as a job that depends on it."""
    _datatrove()
    from datatrove.executor import SlurmPipelineExecutor

    logs = logs_dir(cfg, paths)
    common = dict(
        time=cfg.slurm.time,
        partition=cfg.slurm.partition,
        venv_path=str(Path(sys.prefix) / "bin/activate"),
        skip_completed=False,
        sbatch_args={},
    )
    record = SlurmPipelineExecutor(
        pipeline=[RecordShardGroup(cfg, sim)],
        tasks=num_tasks(cfg, shards),
        workers=cfg.slurm.workers,
        job_name=f"jept-record-{Path(cfg.repo_id).name}",
        cpus_per_task=cfg.slurm.cpus_per_task,
        mem_per_cpu_gb=cfg.slurm.mem_per_cpu,
        logging_dir=str(logs / "record"),
        slurm_logs_folder=str(logs / "record/slurm"),
        **common,
    )
    assemble = SlurmPipelineExecutor(
        pipeline=[AssembleBuild(cfg, sim)],
        tasks=1,
        job_name=f"jept-assemble-{Path(cfg.repo_id).name}",
        cpus_per_task=max(1, cfg.slurm.cpus_per_task),
        mem_per_cpu_gb=cfg.slurm.mem_per_cpu,
        logging_dir=str(logs / "assemble"),
        slurm_logs_folder=str(logs / "assemble/slurm"),
        depends=record,
        **common,
    )
    assemble.run()
    return {"record_job": record.job_id, "assemble_job": assemble.job_id, "logs": str(logs)}
