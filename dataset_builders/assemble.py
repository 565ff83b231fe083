"""Assembling the repos from the recorded shards: ``_demo``, ``_video``, ``_prompts``, ``_probe`` with LeRobot's
``aggregate_datasets``, ``_mix`` from demo + video, and the split metadata. Each repo is assembled in a staging
folder that replaces it by a rename, so a repo is always absent or complete."""

import json
import os
import shutil
import time
from collections import defaultdict
from pathlib import Path

from dataset_builders.config import (
    BUILD_FILE,
    LABELLED_ROLES,
    ROLES,
    BuildConfig,
    BuildError,
    Simulator,
    is_play,
    task_description,
)
from dataset_builders.plan import BuildPaths, Shard
from dataset_builders.publish import push_repos
from lerobot_jept.datasets.mixing import MIX_FORMAT


def _replace_dir(tmp: Path, final: Path) -> None:
    """Swap ``tmp`` in as ``final`` by renames (the old version is removed only after the swap)."""
    old = final.with_name(final.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if final.exists():
        os.replace(final, old)
    os.replace(tmp, final)
    shutil.rmtree(old, ignore_errors=True)


def recover_dir(final: Path) -> None:
    """Undo a swap interrupted between its two renames (the previous complete version comes back)."""
    old = final.with_name(final.name + ".old")
    if old.exists() and not final.exists():
        os.replace(old, final)


def _with_labels(root: Path, repo_id: str) -> Path:
    """The assembled demo repo at ``root`` with ``observation.action_labelled`` = 1 on every frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_jept.datasets.mixing import add_labels

    out = root.with_name(root.name + "_labelled")
    add_labels(LeRobotDataset(repo_id, root=root), out, repo_id, labelled=True)
    shutil.rmtree(root)
    return out


def _aggregate(sources: list[tuple[str, Path]], repo_id: str, out: Path) -> None:
    from lerobot.datasets.aggregate import aggregate_datasets

    shutil.rmtree(out, ignore_errors=True)
    aggregate_datasets(
        repo_ids=[rid for rid, _ in sources],
        aggr_repo_id=repo_id,
        roots=[p for _, p in sources],
        aggr_root=out,
    )


def build_mix(paths: BuildPaths, action_feature: dict, has_video: bool, has_play: bool) -> None:
    """``_mix`` = the ``_demo`` (and ``_play``) episodes + the ``_video`` episodes with the neutral action,
    unlabelled (``lerobot_jept.datasets.mixing``)."""
    from lerobot_jept.datasets.mixing import mix

    demos = [(paths.repo_id_of(role), paths.repo(role)) for role in ("demo", "play")[: 1 + has_play]]
    videos = [(paths.repo_id_of("video"), paths.repo("video"))] if has_video else []
    staging = paths.work / "staging" / "mixing"
    try:
        done = mix(demos, videos, paths.repo_id_of("mix"), staging, action_feature)
    except ValueError as err:
        raise BuildError(str(err)) from err
    _replace_dir(done, paths.repo("mix"))
    shutil.rmtree(staging, ignore_errors=True)


def dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def assemble(cfg: BuildConfig, sim: Simulator, paths: BuildPaths, record: dict, shards: list[Shard]) -> dict:
    """(Re-)assemble the repos whose shards changed, write the split metadata into every repo and the build
    record; returns the metadata and the per-role episode statistics."""
    summaries = [json.loads((paths.shard(s) / "shard.json").read_text()) for s in shards]
    assembled = record.get("assembled", {})
    if assembled.get("format") != MIX_FORMAT:  # repos assembled by an older version are assembled again
        assembled = {"format": MIX_FORMAT}
    for role in ROLES:
        role_shards = [s for s in shards if s.role == role]
        names = [s.name for s in role_shards]
        if not role_shards or (assembled.get(role) == names and paths.repo(role).exists()):
            continue
        tmp = paths.work / "staging" / role
        _aggregate(
            [(paths.shard_repo_id(s), paths.shard(s)) for s in role_shards], paths.repo_id_of(role), tmp
        )
        if role in LABELLED_ROLES:  # every frame labelled, as in the mix, so that LeRobot can merge them
            tmp = _with_labels(tmp, paths.repo_id_of(role))
        _replace_dir(tmp, paths.repo(role))
        assembled[role] = names
        assembled.pop("mix", None)
    mix_names = [s.name for s in shards if s.role in ("demo", "video", "play")]
    if not cfg.demo_tasks:  # no labelled frame: the videos join demos of another build through jept-mix
        print(
            f"No demo tasks, so no {paths.repo_id_of('mix')} (a mix needs labelled frames): mix "
            f"{paths.repo_id_of('video')} with demos through `jept-mix --demo_repo_ids=[...] "
            f"--video_repo_ids=[{paths.repo_id_of('video')}] --output_repo_id=...`."
        )
    elif assembled.get("mix") != mix_names or not paths.repo("mix").exists():
        build_mix(paths, sim.action_feature(), bool(cfg.video_tasks), bool(cfg.play_tasks()))
        assembled["mix"] = mix_names
    record["assembled"] = assembled

    stats = _episode_stats(summaries)
    metadata = {
        "repo_id": cfg.repo_id,
        "split": cfg.split(),
        "play_tasks": cfg.play_tasks(),  # labelled, in the mix, in no split
        "task_descriptions": {
            t: task_description(sim, t)
            for t in (*(t for ts in cfg.split().values() for t in ts), *cfg.play_tasks())
        },
        "protocol": sim.protocol(cfg),
        "repos": {role: paths.repo_id_of(role) for role in (*ROLES, "mix") if paths.repo(role).exists()},
        "expert_success_rate": {
            task: s["episodes"] / s["attempts"] for task, s in stats["per_task"].items() if not is_play(task)
        },
        "flags": cfg.content_flags(),
    }
    for role in metadata["repos"]:
        (paths.repo(role) / "meta" / BUILD_FILE).write_text(json.dumps(metadata, indent=2))
    record["metadata"] = metadata
    (paths.work / BUILD_FILE).write_text(json.dumps(record, indent=2))
    per_role = stats["per_role"]
    per_role["mix"] = {
        key: sum(per_role[role][key] for role in ("demo", "video", "play"))
        for key in ("episodes", "frames", "attempts")
    }
    return {"metadata": metadata, "per_role": per_role}


def summarise(paths: BuildPaths, assembled: dict, record_seconds: float, total_seconds: float) -> dict:
    """What the build prints and returns: per repo its episodes, frames, rejected attempts and size."""
    metadata, per_role = assembled["metadata"], assembled["per_role"]
    return {
        "record_seconds": record_seconds,
        "total_seconds": total_seconds,
        "repos": {
            role: {
                "repo_id": paths.repo_id_of(role),
                "path": str(paths.repo(role)),
                "episodes": per_role[role]["episodes"],
                "frames": per_role[role]["frames"],
                "rejected": per_role[role]["attempts"] - per_role[role]["episodes"],
                "bytes": dir_size(paths.repo(role)),
            }
            for role in metadata["repos"]
        },
        "expert_success_rate": metadata["expert_success_rate"],
    }


def _episode_stats(summaries: list[dict]) -> dict:
    per_role = defaultdict(lambda: {"episodes": 0, "frames": 0, "attempts": 0})
    per_task = defaultdict(lambda: {"episodes": 0, "attempts": 0})
    for s in summaries:
        for bucket in (per_role[s["role"]], per_task[s["task"]]):
            bucket["episodes"] += s["num_episodes"]
            bucket["attempts"] += s["attempts"]
        per_role[s["role"]]["frames"] += s["frames"]
    return {"per_role": per_role, "per_task": per_task}


def format_summary(summary: dict) -> str:
    lines = [f"{'repo':<40} {'episodes':>9} {'frames':>9} {'rejected':>9} {'size MB':>9}"]
    for info in summary["repos"].values():
        lines.append(
            f"{info['repo_id']:<40} {info['episodes']:>9} {info['frames']:>9} {info['rejected']:>9} "
            f"{info['bytes'] / 1e6:>9.1f}"
        )
    rates = ", ".join(f"{t} {r:.0%}" for t, r in summary["expert_success_rate"].items())
    lines.append(f"expert success (kept / attempted): {rates}")
    lines.append(f"time: {summary['total_seconds']:.1f} s (recording {summary['record_seconds']:.1f} s)")
    return "\n".join(lines)


def finish(
    cfg: BuildConfig,
    sim: Simulator,
    paths: BuildPaths,
    shards: list[Shard],
    record_seconds: float,
    start: float | None = None,
) -> dict:
    """Once every shard is recorded: assemble the repos, print the summary, push when asked."""
    start = time.perf_counter() if start is None else start
    record = json.loads((paths.work / BUILD_FILE).read_text())
    assembled = assemble(cfg, sim, paths, record, shards)
    summary = summarise(paths, assembled, record_seconds, time.perf_counter() - start)
    print(format_summary(summary))
    if cfg.push_to_hub:
        push_repos(paths, assembled["metadata"], private=cfg.private)
    return summary
