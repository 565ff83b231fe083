"""``jept-eval-suite``: the paper's Table 1 (Meta-World) or Table 3 (robosuite) for one checkpoint, through
LeRobot's own ``eval_main``.

Every demo, video and unseen task recorded in the mix repo's split metadata (``meta/jept_build.json``) is
evaluated with ``--env.type=jept_metaworld`` or ``jept_robosuite`` under the build's protocol (image size, action repeat, truncation)
and prompt bank. Writes ``results.json``, ``results.md`` (Table 1's rows: T_demo average, T_vid average, each
unseen task, seen average, unseen average) and ``results.png``, plus LeRobot's eval_info.json and videos per
task under ``tasks/<task>/``. The results also carry ``jept-prompt-probe``'s offline measures on held-out labelled
episodes (action-bin accuracy per task and per split, L_obs for JEPT, prompt separability and swap): on the
build's ``ORG/NAME_probe`` repo, or on ``--probe_repo_id``; ``--probe=false`` skips them.

    jept-eval-suite --policy.path=outputs/train/.../pretrained_model --dataset.repo_id=ORG/NAME_mix \\
        --n_episodes=50 --output_dir=outputs/suite
"""

import dataclasses
import json
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
from tqdm import tqdm

from lerobot_jept.evaluation.cli_args import DatasetArg, PolicyArg
from lerobot_jept.evaluation.paper import PAPER_SPLIT, PAPER_TABLE1

BUILD_FILE = "meta/jept_build.json"
TITLES = {
    "metaworld": "JEPT on Meta-World (Table 1 layout)",
    "robosuite": "JEPT on robosuite (Table 3 layout)",
}


@dataclass
class SuiteConfig:
    policy: PolicyArg = field(default_factory=PolicyArg)
    dataset: DatasetArg = field(default_factory=DatasetArg)
    n_episodes: int = 50  # per task (the paper: 50 = 10 prompt videos x 5 seeds)
    batch_size: int = 10  # parallel envs per task
    use_async_envs: bool = False
    seed: int = 1000
    episode_length: int | None = None  # default: the build's max_episode_steps (shorter: a quick check)
    output_dir: Path = Path("outputs/suite")
    prompt_repo_id: str | None = None  # default: the build's prompt bank
    prompt_root: str | None = None
    # Offline measures (jept-prompt-probe) on a labelled repo of held-out episodes, joined to results.json /
    # results.md: the build's ORG/NAME_probe by default, or this repo.
    probe: bool = True
    probe_repo_id: str | None = None
    probe_root: str | None = None
    # Which of the build's splits to evaluate (demo, video, unseen); every one by default.
    splits: list[str] = field(default_factory=lambda: ["demo", "video", "unseen"])
    # Also evaluate each video-only task under its scene-mate's prompt (the build's other task in the same
    # scene, e.g. window-open's prompt in window-close's scene): if the prompt, not the scene, drives the
    # behaviour, the intended task's success falls to its floor. Written as the row "T_vid, scene-mate's prompt".
    scene_mate_prompts: bool = False
    # Episodes per task of the random 7-bin policy on the same env seeds (the floor each row is read against),
    # printed beside the rows; 0 skips it.
    floor_episodes: int = 0


class SuiteError(ValueError):
    pass


def read_build_metadata(repo_id: str, root: str | None) -> tuple[dict, Path]:
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata(repo_id, root=root)
    path = Path(meta.root) / BUILD_FILE
    if not path.is_file():
        raise SuiteError(
            f"{repo_id} has no {BUILD_FILE}: the suite needs the task split that jept-build-metaworld records. "
            "Pass the builder's ORG/NAME_mix repo."
        )
    return json.loads(path.read_text()), Path(meta.root)


RECIPE_TYPES = ("jept", "jept_no_prompt")  # the types trained by a recipe (the baselines have none)
SCENE_MATE_ROW = "T_vid, scene-mate's prompt"


def scene_mate_of(build: dict, video_tasks: list[str]) -> dict[str, str]:
    """Each video-only task's scene-mate: the build's other task (any split) whose name shares its scene."""
    from lerobot_jept.evaluation.prompt_probe import scene_key

    every = [t for tasks in build["split"].values() for t in tasks]
    mates = {}
    for task in video_tasks:
        others = [t for t in every if t != task and scene_key(t) == scene_key(task)]
        if not others:
            raise SuiteError(
                f"--scene_mate_prompts: {task} has no scene-mate in the build (no other task shares its scene); "
                "build its pair (e.g. window-open-v3 with window-close-v3) or drop the flag."
            )
        mates[task] = others[0]
    return mates


def summarise(split: dict[str, list[str]], success: dict[str, float]) -> dict[str, float]:
    """Table 1's rows (success %): group averages, every unseen task, seen = mean of the T_demo and T_vid
    averages (as the paper's numbers are), unseen = mean over unseen tasks."""

    def mean(values):
        return sum(values) / len(values) if values else float("nan")

    rows = {}
    if split["demo"]:
        rows["T_demo"] = mean([success[t] for t in split["demo"]])
    if split["video"]:
        rows["T_vid"] = mean([success[t] for t in split["video"]])
    for task in split["unseen"]:
        rows[task] = success[task]
    rows["Seen average"] = mean([rows[g] for g in ("T_demo", "T_vid") if g in rows])
    rows["Unseen average"] = mean([success[t] for t in split["unseen"]])
    return rows


def markdown(
    rows: dict[str, float],
    per_task: dict[str, dict],
    paper: bool,
    policy_type: str = "jept",
    floor: dict[str, float] | None = None,
) -> str:
    header = f"| Task | {policy_type} (this run) |" + (" random 7-bin |" if floor else "")
    header += " JEPT (paper) |" if paper else ""
    lines = [header, "|---|---:|" + ("---:|" if floor else "") + ("---:|" if paper else "")]
    for name, value in rows.items():
        cell = f"| {name} | {value:.1f} |"
        if floor:
            shown = floor.get(name, float("nan"))
            cell += " - |" if shown != shown else f" {shown:.1f} |"
        lines.append(cell + (f" {PAPER_TABLE1[name]:.1f} |" if paper else ""))
    lines += ["", "| Task | Split | Success (%) | Episodes |", "|---|---|---:|---:|"]
    for task, r in per_task.items():
        lines.append(f"| {task} | {r['split']} | {r['pc_success']:.1f} | {r['n_episodes']} |")
    return "\n".join(lines) + "\n"


def bar_chart(rows: dict[str, float], path: Path, paper: bool, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(rows)
    fig, ax = plt.subplots(figsize=(1.2 * len(names) + 2, 4))
    width = 0.4 if paper else 0.6
    xs = range(len(names))
    ax.bar([x - (width / 2 if paper else 0) for x in xs], [rows[n] for n in names], width, label="this run")
    if paper:
        ax.bar([x + width / 2 for x in xs], [PAPER_TABLE1[n] for n in names], width, label="paper")
        ax.legend()
    ax.set_xticks(list(xs), names, rotation=30, ha="right")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def random_floor(build: dict, tasks: list[str], episodes: int, seed: int, length: int | None = None) -> dict:
    """Success of a policy that picks every action dimension's bin uniformly at random, per task, on the
    evaluation seeds ``seed`` + episode (those of ``eval_main`` with ``--seed``), under the build's protocol
    (``length``: the episode length, default the build's). Returns {task: {pc_success, successes}}."""
    import numpy as np

    from lerobot_jept.envs.rendering import setup_offscreen_gl
    from lerobot_jept.policies.discretization import bin_centres

    setup_offscreen_gl()
    protocol = build["protocol"]
    length = length or protocol["max_episode_steps"]
    rng = np.random.default_rng(seed)
    per_task = {}
    for task in tqdm(tasks, desc="random floor", unit="task", leave=False):
        env = make_env(protocol["simulator"], task, protocol, length)
        env.draw_images = False  # the random policy never looks
        low, high = float(env.action_space.low.min()), float(env.action_space.high.max())
        centres = np.asarray(bin_centres(protocol["action_bins"], low, high), dtype=np.float32)
        successes = []
        for episode in range(episodes):
            env.reset(seed=seed + episode)
            success = False
            while True:
                action = centres[rng.integers(len(centres), size=env.action_space.shape)]
                _, _, terminated, truncated, info = env.step(action)
                success = success or bool(info.get("is_success", False))
                if terminated or truncated:
                    break
            successes.append(success)
        env.close()
        per_task[task] = {"pc_success": 100.0 * float(np.mean(successes)), "successes": successes}
    return per_task


def make_env(simulator: str, task: str, protocol: dict, length: int):
    if simulator == "metaworld":
        from lerobot_jept.envs.metaworld import JeptMetaworldEnv

        return JeptMetaworldEnv(
            task,
            image_size=protocol["image_size"],
            action_repeat=protocol["action_repeat"],
            max_episode_steps=length,
        )
    from lerobot_jept.envs.robosuite import JeptRobosuiteEnv

    return JeptRobosuiteEnv(task, image_size=protocol["image_size"], max_episode_steps=length)


def evaluate_task(
    cfg: SuiteConfig, task: str, build: dict, prompt_repo_id: str, out: Path, prompt_task: str | None = None
) -> dict:
    """One task through LeRobot's ``eval_main`` with the ``jept_metaworld`` env (showing ``prompt_task``'s
    prompts when given, else the task's own); returns its eval_info."""
    from lerobot.configs.default import EvalConfig
    from lerobot.configs.eval import EvalPipelineConfig
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.scripts.lerobot_eval import eval_main

    from lerobot_jept.envs.configs import JeptMetaworldEnvConfig, JeptRobosuiteEnvConfig

    policy = PreTrainedConfig.from_pretrained(cfg.policy.path)
    policy.pretrained_path = Path(cfg.policy.path)
    cfg.policy.apply(policy)
    protocol = build["protocol"]
    common = dict(
        task=task,
        image_size=protocol["image_size"],
        episode_length=cfg.episode_length or protocol["max_episode_steps"],
        prompt_repo_id=prompt_repo_id,
        prompt_root=cfg.prompt_root,
        prompt_max_frames=getattr(policy, "max_prompt_length", 250),
        prompt_task=prompt_task,
    )
    if protocol["simulator"] == "metaworld":
        env = JeptMetaworldEnvConfig(**common, action_repeat=protocol["action_repeat"])
    else:
        env = JeptRobosuiteEnvConfig(**common)
    batch = max(1, min(cfg.batch_size, cfg.n_episodes))
    eval_cfg = EvalPipelineConfig(
        env=env,
        eval=EvalConfig(n_episodes=cfg.n_episodes, batch_size=batch, use_async_envs=cfg.use_async_envs),
        output_dir=out,
        seed=cfg.seed,
    )
    eval_cfg.policy = policy
    eval_main(eval_cfg)
    return json.loads((out / "eval_info.json").read_text())


TASK_FILE = "suite_task.json"  # per task folder: the settings it was evaluated under and its result


def run_settings(cfg: SuiteConfig, build: dict, prompt_repo_id: str) -> dict:
    """What a task's rollouts depend on besides the task itself: the checkpoint's weights (their hash, so a
    retrained checkpoint at the same path is evaluated again), the command line's policy overrides, the
    build, prompt bank, episodes, env seeds and episode length."""
    import hashlib

    weights = Path(cfg.policy.path) / "model.safetensors"
    digest = cfg.policy.path
    if weights.is_file():
        with weights.open("rb") as f:  # streamed, not read whole into memory
            digest = hashlib.file_digest(f, "sha256").hexdigest()
    return {
        "weights": digest,
        "policy_overrides": {k: v for k, v in dataclasses.asdict(cfg.policy).items() if k != "path"},
        "dataset": cfg.dataset.repo_id,
        "build_protocol": build.get("protocol"),
        "prompt_repo_id": prompt_repo_id,
        "n_episodes": cfg.n_episodes,
        "batch_size": cfg.batch_size,
        "seed": cfg.seed,
        "episode_length": cfg.episode_length,
    }


def finished_task(folder: Path, stamp: dict) -> dict | None:
    """The result of a task evaluated before under the same settings (a suite run again into the same
    ``--output_dir`` picks up where it stopped, and adding ``--scene_mate_prompts`` runs only the new rows);
    None when it must be evaluated."""
    path = folder / TASK_FILE
    if not path.is_file():
        return None
    done = json.loads(path.read_text())
    return done["result"] if done.get("settings") == json.loads(json.dumps(stamp)) else None


def run_suite(cfg: SuiteConfig) -> dict:
    if not cfg.policy.path or not cfg.dataset.repo_id:
        raise SuiteError("Pass both --policy.path=CHECKPOINT and --dataset.repo_id=ORG/NAME_mix.")
    build, _ = read_build_metadata(cfg.dataset.repo_id, cfg.dataset.root)
    simulator = build.get("protocol", {}).get("simulator")
    if simulator not in TITLES:
        raise SuiteError(
            f"{cfg.dataset.repo_id} was built from {simulator!r}; the suite runs {sorted(TITLES)}."
        )
    split = build["split"]
    from lerobot.configs.policies import PreTrainedConfig

    saved = PreTrainedConfig.from_pretrained(cfg.policy.path)
    policy_type, recipe = saved.type, getattr(saved, "recipe", None) if saved.type in RECIPE_TYPES else None
    probe_repo_id = (cfg.probe_repo_id or build["repos"].get("probe")) if cfg.probe else None
    prompt_repo_id = cfg.prompt_repo_id or build["repos"].get("prompts")
    if not prompt_repo_id:
        raise SuiteError(
            f"{cfg.dataset.repo_id} names no prompt bank (a jept-mix output): pass --prompt_repo_id=ORG/NAME_prompts."
        )
    unknown = sorted(set(cfg.splits) - set(split))
    if unknown or not cfg.splits:
        raise SuiteError(f"--splits takes some of {sorted(split)}, got {cfg.splits}.")
    split = {role: (tasks if role in cfg.splits else []) for role, tasks in split.items()}
    runs = [(t, role, None) for role in ("demo", "video", "unseen") for t in split[role]]
    if cfg.scene_mate_prompts:
        runs += [(t, "video", mate) for t, mate in scene_mate_of(build, split["video"]).items()]
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = run_settings(cfg, build, prompt_repo_id)
    per_task = {}
    for task, role, mate in tqdm(runs, desc="suite tasks", unit="task"):
        folder = out / "tasks" / (task if mate is None else f"{task}.prompt_{mate}")
        stamp = {**settings, "task": task, "prompt_task": mate}
        result = finished_task(folder, stamp)
        if result is None:
            info = evaluate_task(cfg, task, build, prompt_repo_id, folder, prompt_task=mate)
            overall = info["overall"]
            result = {
                "split": role,
                "pc_success": float(overall["pc_success"]),
                "n_episodes": int(overall["n_episodes"]),
                "successes": [bool(s) for t in info["per_task"] for s in t["metrics"]["successes"]],
                "eval_info": str(folder / "eval_info.json"),
            }
            (folder / TASK_FILE).write_text(json.dumps({"settings": stamp, "result": result}, indent=2))
        if mate is None:
            per_task[task] = result
        else:
            per_task[task]["scene_mate"] = {"prompt_task": mate, **result}
    rows = summarise(split, {t: r["pc_success"] for t, r in per_task.items()})
    mates = [r["scene_mate"]["pc_success"] for r in per_task.values() if "scene_mate" in r]
    if mates:
        rows[SCENE_MATE_ROW] = sum(mates) / len(mates)
    paper = (
        policy_type == "jept"
        and simulator == "metaworld"
        and {k: sorted(v) for k, v in split.items()} == {k: sorted(v) for k, v in PAPER_SPLIT.items()}
    )
    results = {
        "policy": cfg.policy.path,
        "policy_type": policy_type,
        "recipe": recipe,
        "simulator": simulator,
        "dataset": cfg.dataset.repo_id,
        "n_episodes": cfg.n_episodes,
        "seed": cfg.seed,
        "split": split,
        "per_task": per_task,
        "table": rows,
        "paper_table": PAPER_TABLE1 if paper else None,
    }
    floor_rows = None
    if cfg.floor_episodes > 0:
        floor = random_floor(
            build,
            [t for t, _, mate in runs if mate is None],
            cfg.floor_episodes,
            cfg.seed,
            cfg.episode_length,
        )
        results["random_floor"] = floor
        floor_rows = summarise(split, {t: r["pc_success"] for t, r in floor.items()})
        if SCENE_MATE_ROW in rows:  # under another prompt, the floor is that of the task itself
            floor_rows[SCENE_MATE_ROW] = floor_rows.get("T_vid", float("nan"))
        results["random_floor_table"] = floor_rows
    table = markdown(rows, per_task, paper, policy_type, floor_rows)
    if probe_repo_id:
        from lerobot_jept.evaluation.prompt_probe import ProbeConfig, run_probe
        from lerobot_jept.evaluation.prompt_probe import markdown as probe_markdown

        probe = run_probe(
            ProbeConfig(
                cfg.policy,
                DatasetArg(probe_repo_id, cfg.probe_root),
                prompt_repo_id=prompt_repo_id,
                prompt_root=cfg.prompt_root,
                output_dir=out,
            ),
            split=split,
        )
        results["prompt_probe"] = probe
        table += f"\n## Offline probe on {probe_repo_id}\n\n" + probe_markdown(probe)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(table)
    bar_chart(rows, out / "results.png", paper, TITLES[simulator])
    print(table)
    print(f"Wrote {out / 'results.json'}, {out / 'results.md'}, {out / 'results.png'}")
    return results


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    import lerobot_policy_jept  # noqa: F401  (registers the policy and the envs)

    cfg = draccus.parse(SuiteConfig)
    try:
        run_suite(cfg)
    except SuiteError as err:
        sys.exit(f"jept-eval-suite: {err}")
