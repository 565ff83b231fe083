"""Success rates of the robosuite scripted experts, as a build would see them (same env, seeding, 7-bin actions
and truncation; no frames rendered)::

    python -m dataset_builders.expert_rates --tasks='[iiwa-square, sawyer-can]' --episodes=20

Each task is run by its prompt arm (the arm that records its prompt videos; ``panda-*`` is the executing Panda).
"""

from dataclasses import dataclass, field

import draccus
from tqdm import tqdm

from lerobot_jept.envs import robosuite as rs


@dataclass
class ExpertRatesConfig:
    tasks: list[str] = field(default_factory=rs.available_tasks)
    episodes: int = 20  # seeds seed .. seed + episodes - 1
    seed: int = 0
    action_bins: int = 7
    max_episode_steps: int = 200


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
    seeds = range(cfg.seed, cfg.seed + cfg.episodes)
    lines = []
    for task in tqdm(tasks, desc="expert rates", unit="task"):
        successes = expert_successes(task, seeds, cfg.action_bins, cfg.max_episode_steps)
        lines.append(f"{task}: {sum(successes)}/{len(successes)}")
        tqdm.write(lines[-1])
    print("\n".join(["", f"expert success, seeds {seeds.start}-{seeds.stop - 1}:", *lines]))


if __name__ == "__main__":
    main()
