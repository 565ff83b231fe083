"""Success rates of the robosuite scripted experts, as a build would see them (same env, seeding, 7-bin actions
and truncation; no frames rendered)::

    python -m dataset_builders.expert_rates --tasks='[iiwa-square, sawyer-can]' --episodes=20 --num_workers=2

Each task is run by its prompt arm (the arm that records its prompt videos; ``panda-*`` is the executing Panda).
"""

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from functools import partial

import draccus
from tqdm import tqdm

from dataset_builders.core import worker_init
from lerobot_jept.envs import robosuite as rs


@dataclass
class ExpertRatesConfig:
    tasks: list[str] = field(default_factory=rs.available_tasks)
    episodes: int = 20  # seeds seed .. seed + episodes - 1
    seed: int = 0
    action_bins: int = 7
    max_episode_steps: int = 200
    num_workers: int = 1  # processes, each measuring one task at a time


def expert_successes(
    task: str, seeds: range, action_bins: int = 7, max_episode_steps: int = 200
) -> list[bool]:
    env = rs.JeptRobosuiteEnv(task, image_size=32, max_episode_steps=max_episode_steps, embodiment="prompt")
    try:
        return [env.expert_succeeds(seed, action_bins) for seed in seeds]
    finally:
        env.close()


def main(args: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=ExpertRatesConfig, args=args)
    try:
        tasks = [rs.check_task(task) for task in cfg.tasks]
    except ValueError as err:
        raise SystemExit(f"expert_rates: error: {err}") from None
    if cfg.num_workers < 1:
        raise SystemExit(f"expert_rates: error: --num_workers={cfg.num_workers}: use 1 or more processes.")
    seeds = range(cfg.seed, cfg.seed + cfg.episodes)
    measure = partial(
        expert_successes, seeds=seeds, action_bins=cfg.action_bins, max_episode_steps=cfg.max_episode_steps
    )
    pool = None
    if cfg.num_workers > 1:
        pool = ProcessPoolExecutor(
            cfg.num_workers, mp_context=mp.get_context("spawn"), initializer=worker_init
        )
    lines = []
    with pool or nullcontext():
        results = pool.map(measure, tasks) if pool else map(measure, tasks)  # in task order
        for task, successes in tqdm(
            zip(tasks, results, strict=True), desc="expert rates", unit="task", total=len(tasks)
        ):
            lines.append(f"{task}: {sum(successes)}/{len(successes)}")
            tqdm.write(lines[-1])
    print("\n".join(["", f"expert success, seeds {seeds.start}-{seeds.stop - 1}:", *lines]))


if __name__ == "__main__":
    main()
