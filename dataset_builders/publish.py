"""Publishing a build: dataset cards and LeRobot's own ``push_to_hub`` for every repo."""

from dataset_builders.config import BuildError
from dataset_builders.plan import BuildPaths

ROLE_DESCRIPTIONS = {
    "demo": "expert demonstrations (camera, self-state and the executed action) of the T_demo tasks",
    "video": (
        "expert videos of the T_vid tasks: camera and self-state only. This repo has no `action` column by "
        "design: JEPT learns these tasks from video alone"
    ),
    "prompts": "the prompt-video bank: observation-only episodes of every task, looked up by task string",
    "probe": (
        "held-out labelled episodes (camera, self-state and the executed action) of every task of every split, "
        "with seeds disjoint from all other repos: never trained on, they measure a checkpoint offline "
        "(`jept-prompt-probe`, `jept-eval-suite`)"
    ),
    "mix": (
        "the single training repo for `lerobot-train`: demo and video episodes together; video frames have "
        "`observation.action_labelled` = 0 and a neutral action of 0 (stats come from labelled frames only)"
    ),
}


def dataset_card_description(metadata: dict, role: str) -> str:
    """The card text of one repo: its role, the split, the protocol and the expert success rates."""
    split, protocol = metadata["split"], metadata["protocol"]
    lines = [
        f"JEPT {protocol['simulator']} build `{metadata['repo_id']}`, written by `lerobot_policy_jept`'s builder.",
        "",
        f"This repo (`{metadata['repos'][role]}`) holds {ROLE_DESCRIPTIONS[role]}.",
        "",
        "**Task split** (the paper's T_demo / T_vid / T_unseen):",
    ]
    for name, key in (("T_demo", "demo"), ("T_vid", "video"), ("T_unseen", "unseen")):
        lines.append(f"- {name}: {', '.join(split[key]) or '(none)'}")
    lines += [
        "",
        "**Protocol**: "
        + ", ".join(f"{k} {v}" for k, v in protocol.items())
        + " (camera `corner2`, flipped upright; actions are the centres of the bins the expert's actions were "
        "snapped to).",
        "",
        "**Expert success rates** (kept / attempted): "
        + ", ".join(f"{t} {r:.0%}" for t, r in metadata["expert_success_rate"].items()),
        "",
        "Repos of this build: "
        + ", ".join(f"`{r}`" for r in metadata["repos"].values())
        + ". The split and protocol are also in `meta/jept_build.json`.",
    ]
    return "\n".join(lines)


def push_repos(paths: BuildPaths, metadata: dict, private: bool = False) -> None:
    """Push every repo of the build with LeRobot's own ``push_to_hub``; a failure keeps every local file and
    ends in one line (BuildError)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    for role, repo_id in metadata["repos"].items():
        dataset = LeRobotDataset(repo_id, root=paths.repo(role))
        try:
            dataset.push_to_hub(
                tags=["jept", metadata["protocol"]["simulator"], role],
                private=private,
                dataset_description=dataset_card_description(metadata, role),
            )
        except Exception as err:  # network, auth, permissions: whatever the Hub client raises
            reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise BuildError(
                f"Pushing {repo_id} to the Hub failed ({type(err).__name__}: {reason}). Every repo is complete "
                f"locally under {paths.repo(role).parent}; log in (`hf auth login`) and re-run the same command "
                "to push again."
            ) from err
