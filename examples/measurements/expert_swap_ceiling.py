"""How often should a scene-mate's prompt change the action? The experts' own answer, from the simulator.

    python -m examples.measurements.expert_swap_ceiling --tasks='[window-close-v3, window-open-v3]' --episodes=8

`jept-prompt-probe` counts the frames of a task whose chosen action changes when the task's bank prompt is
swapped for a scene-mate's (the target: "most frames"). How many *should* change is a property of the
tasks, not of a checkpoint: this rolls out each task's scripted expert as a build does (same env, seeding, 7-bin
actions, successful episodes only) and, at every recorded step, also asks each scene-mate's scripted expert
(tasks whose names share their first word, as in the probe) what it would do from that same state. Per task and
mate it prints the share of frames whose binned whole action differs, and per dimension (x / y / z / gripper):
the swap rate a policy that follows its prompt the way the experts do would show on these states. A mate expert
reads the state as its own task's observation (Meta-World's scripted policies key on the hand and object
positions), so the figure is the mate's own rule applied off its task's start states. Used in
docs/results.md, "How often should a scene-mate's prompt change the action?".
"""

from dataclasses import dataclass, field

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_jept.envs import metaworld as mw
from lerobot_jept.evaluation.prompt_probe import scene_mates
from lerobot_jept.policies.discretization import bin_centres, to_bin_indices

STUDY_TASKS = [
    "window-open-v3",
    "window-close-v3",
    "door-close-v3",
    "door-open-v3",
    "faucet-close-v3",
    "faucet-open-v3",
]


@dataclass
class SwapCeilingConfig:
    # each task is compared with its scene-mates among these (default: the small study's split)
    tasks: list[str] = field(default_factory=lambda: list(STUDY_TASKS))
    episodes: int = 8  # successful episodes per task
    seed: int = 7_000_000  # episode seeds seed, seed + 1, ... (failed episodes are skipped, as a build does)
    num_bins: int = 7
    max_episode_steps: int = 250


def mate_differences(
    task: str, mates: list[str], cfg: SwapCeilingConfig
) -> tuple[dict[str, np.ndarray], int]:
    """Per mate, (frames, action_dim) booleans: the mate expert's binned action differs from the task expert's
    at the task's recorded states; and the number of failed episodes skipped."""
    env = mw.JeptMetaworldEnv(task, image_size=16, max_episode_steps=cfg.max_episode_steps)
    centres = bin_centres(cfg.num_bins).astype(np.float32)
    diffs: dict[str, list[np.ndarray]] = {m: [] for m in mates}
    kept, failed, seed = 0, 0, cfg.seed
    try:
        while kept < cfg.episodes:
            if failed > 4 * cfg.episodes + 10:
                raise SystemExit(
                    f"expert_swap_ceiling: error: {task}'s expert failed {failed} episodes; check it."
                )
            env.reset(seed=seed)
            episode: dict[str, list[np.ndarray]] = {m: [] for m in mates}
            while True:
                own = to_bin_indices(env.expert_action(), cfg.num_bins)
                for m in mates:
                    episode[m].append(to_bin_indices(env.expert_action(m), cfg.num_bins) != own)
                _, _, terminated, truncated, info = env.step(centres[own])
                if terminated or truncated:
                    break
            seed += 1
            if not info["is_success"]:
                failed += 1
                continue
            kept += 1
            for m in mates:
                diffs[m].extend(episode[m])
    finally:
        env.close()
    return {m: np.stack(d) for m, d in diffs.items()}, failed


def main(args: list[str] | None = None) -> None:
    cfg = draccus.parse(config_class=SwapCeilingConfig, args=args)
    try:
        tasks = [mw.check_task(t) for t in cfg.tasks]
    except ValueError as err:
        raise SystemExit(f"expert_swap_ceiling: error: {err}") from None
    mates = scene_mates(tasks, {t: t for t in tasks})  # the probe's scene pairs
    if not any(mates.values()):
        raise SystemExit(
            "expert_swap_ceiling: error: no two of --tasks share a scene (the first word of their names); "
            "pass scene pairs such as window-open-v3 and window-close-v3."
        )
    rows = [
        "| task | scene-mate | frames | whole action differs | per dim (x / y / z / gripper) |",
        "|---|---|---:|---:|---|",
    ]
    for task in tqdm([t for t in tasks if mates[t]], desc="expert swap ceiling", unit="task"):
        diffs, failed = mate_differences(task, mates[task], cfg)
        for m, d in diffs.items():
            per_dim = " / ".join(f"{v:.2f}" for v in d.mean(axis=0))
            rows.append(f"| {task} | {m} | {len(d)} | {d.any(axis=1).mean():.2f} | {per_dim} |")
        if failed:
            tqdm.write(f"{task}: {failed} failed episodes skipped")
    seeds = f"{cfg.episodes} episodes per task, seeds from {cfg.seed}"
    print(f"\nThe scene-mate's expert's action at the task's own states ({seeds}):")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
