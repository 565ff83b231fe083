"""The simulator-independent core of the JEPT dataset builders.

A build turns expert rollouts into four LeRobotDataset v3 repos under ``$HF_LEROBOT_HOME``:

- ``<repo_id>_demo``: T_demo episodes with ``action`` (the bin centre the env executed) and
  ``observation.action_labelled`` = 1;
- ``<repo_id>_video``: T_vid episodes with the same observation features and NO ``action`` feature;
- ``<repo_id>_prompts``: the prompt-video bank, ``prompts_per_task`` observation-only episodes of every task;
- ``<repo_id>_probe``: ``probe_episodes_per_task`` held-out labelled episodes (with ``action``) of every task of
  every split, for offline measures of a checkpoint (``jept-prompt-probe``); never used for training;
- ``<repo_id>_mix``: demo + video episodes in the one repo ``lerobot-train`` needs; video frames have
  ``observation.action_labelled`` = 0 and the neutral action 0, and ``meta/stats.json`` action stats come from
  labelled frames only (``lerobot_jept.datasets.mixing``: a representation LeRobot's dataset tools keep whole).

How it stays resumable and safe to kill. Work is cut into *shards* (up to ``episodes_per_shard`` successful
episodes of one task and one role). A shard is recorded as its own small LeRobotDataset in a ``.tmp`` folder
of the build's work directory (``<repo_id>.build/``) and renamed into place only once finalised, so a shard is
either complete or absent. Re-running the same command skips complete shards. The repos are assembled from
the shards with LeRobot's ``aggregate_datasets`` into a temporary folder that then replaces the repo by a
rename: a repo is always absent or complete, never half written. Each shard draws its episode seeds from
its own range, so the episodes do not depend on the number of workers or on interruptions.

Processes. Each recording process (the build's own, or each of ``num_workers`` pool workers) starts one
rollout process (:class:`Renderer`, spawned: a fresh GL context) that owns the env and runs up to
``ROLLOUTS_AHEAD`` episodes ahead, while the recording process writes the current one with LeRobot's writer.
Results come back in submission order, so a build's episodes do not depend on this overlap either.

A simulator plugs in through :class:`Simulator` (env factory, task names, features). The build is a pipeline of
stages, one module each, run by :func:`build`:

- ``config``: the flags (:class:`BuildConfig`), the simulator interface and ``validate``;
- ``plan``: the shards, the paths, the build record (``check_existing``: resume, or refuse other flags);
- ``record``: rollout processes and the writing of shards (``record_missing``, ``num_workers`` processes);
- ``assemble``: the repos, the mix and the split metadata from the shards;
- ``publish``: dataset cards and the push to the Hub;
- ``executors``: the same record and assemble stages as datatrove pipeline tasks (local, or SLURM).
"""

import json
import time

from dataset_builders.assemble import finish, recover_dir
from dataset_builders.config import (  # noqa: F401  (the builder's public names, importable from core)
    BUILD_FILE,
    ROLES,
    BuildConfig,
    BuildError,
    Simulator,
    validate,
)
from dataset_builders.executors import record_datatrove_local, submit_slurm
from dataset_builders.plan import BuildPaths, Shard, check_existing, plan_shards  # noqa: F401
from dataset_builders.publish import push_repos  # noqa: F401
from dataset_builders.record import (  # noqa: F401
    _RENDERER,
    close_renderer,
    record_missing,
    rollout_expert,
    run_shards,
    worker_init,
)


def build(cfg: BuildConfig, sim: Simulator) -> dict:
    """Run a whole build (validate, record missing shards, assemble repos, write metadata); return summary."""
    from lerobot_jept.envs.rendering import setup_offscreen_gl

    validate(cfg, sim)
    setup_offscreen_gl()
    start = time.perf_counter()
    paths = BuildPaths(cfg)
    for role in (*ROLES, "mix"):
        recover_dir(paths.repo(role))
    record = check_existing(paths, cfg, sim) or {}
    paths.work.mkdir(parents=True, exist_ok=True)
    record.update({"simulator": sim.name, "flags": cfg.content_flags()})
    (paths.work / BUILD_FILE).write_text(json.dumps(record, indent=2))

    shards = plan_shards(cfg)
    if cfg.executor == "slurm":
        jobs = submit_slurm(sim, cfg, paths, shards)
        print(
            f"Submitted the shard groups as SLURM job {jobs['record_job']} and the assembly as job "
            f"{jobs['assemble_job']} (after it); logs in {jobs['logs']}. Re-run the same command to record what a "
            "failed job left missing."
        )
        return jobs
    if cfg.executor == "datatrove_local":
        record_datatrove_local(sim, cfg, paths, shards)
        record_seconds = time.perf_counter() - start
    else:
        record_seconds = record_missing(sim, cfg, paths, shards)
    return finish(cfg, sim, paths, shards, record_seconds, start)
