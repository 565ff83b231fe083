"""Planning a build: its shards (the unit of work and of resumption), where everything is written, and the
build record that makes a re-run resume instead of mixing builds of other flags."""

import json
from dataclasses import dataclass
from pathlib import Path

from dataset_builders.config import (
    ADDED_FLAGS,
    BUILD_FILE,
    GIVEN_NOW,
    ROLE_SEED_BASE,
    ROLES,
    SEED_BLOCK,
    BuildConfig,
    BuildError,
    Simulator,
)


@dataclass(frozen=True)
class Shard:
    """Up to ``episodes_per_shard`` successful episodes of one task for one role."""

    role: str
    task: str
    index: int
    num_episodes: int

    @property
    def name(self) -> str:
        return f"{self.role}/{self.task}/{self.index:04d}"

    def seed(self, base_seed: int, attempt: int) -> int:
        if attempt >= SEED_BLOCK:
            raise BuildError(f"Shard {self.name} needed more than {SEED_BLOCK} attempts.")
        return (base_seed * 1_000_003 + ROLE_SEED_BASE[self.role] + self.index * SEED_BLOCK + attempt) % 2**31


def plan_shards(cfg: BuildConfig) -> list[Shard]:
    """Every shard of the build, in the order episodes appear in the repos."""
    jobs = [
        ("demo", cfg.demo_tasks, cfg.episodes_per_task),
        ("video", cfg.video_tasks, cfg.videos_per_task()),
        ("play", cfg.play_tasks(), cfg.play_episodes_per_task),
    ]
    all_tasks = [*cfg.demo_tasks, *cfg.video_tasks, *cfg.unseen_tasks]
    jobs.append(("prompts", [*all_tasks, *cfg.play_tasks()], cfg.prompts_per_task))
    jobs.append(("probe", all_tasks, cfg.probe_episodes_per_task))
    shards = []
    for role, tasks, per_task in jobs:
        for task in tasks:
            for index, start in enumerate(range(0, per_task, cfg.episodes_per_shard)):
                shards.append(Shard(role, task, index, min(cfg.episodes_per_shard, per_task - start)))
    return shards


class BuildPaths:
    """Where a build writes: the repos under ``root`` and the shards in ``<repo_id>.build``."""

    def __init__(self, cfg: BuildConfig):
        from lerobot.utils.constants import HF_LEROBOT_HOME

        self.root = Path(cfg.root) if cfg.root else HF_LEROBOT_HOME
        self.repo_id = cfg.repo_id
        self.work = self.root / f"{cfg.repo_id}.build"

    def repo_id_of(self, role: str) -> str:
        return f"{self.repo_id}_{role}"

    def repo(self, role: str) -> Path:
        return self.root / self.repo_id_of(role)

    def shard(self, shard: Shard) -> Path:
        return self.work / "shards" / shard.name

    def shard_repo_id(self, shard: Shard) -> str:
        return f"{self.repo_id}.build_{shard.role}_{shard.task}_{shard.index:04d}"


def check_existing(paths: BuildPaths, cfg: BuildConfig, sim: Simulator) -> dict | None:
    """The previous build record, after checking it was made with the same content flags."""
    record_path = paths.work / BUILD_FILE
    if not record_path.exists():
        existing = [paths.repo_id_of(r) for r in (*ROLES, "mix") if paths.repo(r).exists()]
        if existing:
            raise BuildError(
                f"{', '.join(existing)} already exist(s) under {paths.root} but were not built by this builder "
                f"(no {record_path}); choose another --repo_id or delete them."
            )
        return None
    record = json.loads(record_path.read_text())
    wanted = {"simulator": sim.name, **cfg.content_flags()}
    added = {name: wanted[name] if old == GIVEN_NOW else old for name, old in ADDED_FLAGS.items()}
    previous = {"simulator": record.get("simulator"), **added, **record.get("flags", {})}
    changed = [f"--{k}={previous.get(k)!r} (now {v!r})" for k, v in wanted.items() if previous.get(k) != v]
    if changed:
        raise BuildError(
            f"{cfg.repo_id} was built with different flags: {'; '.join(changed)}. Re-run with the original "
            f"flags to resume it, use another --repo_id, or delete {paths.work} and the {cfg.repo_id}_* repos."
        )
    return record
