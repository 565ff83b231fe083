"""``jept-screen``: how much of the video-only tasks' actions inverse dynamics fitted on the labelled frames can
read, before any policy is trained.

    jept-screen --probe_repo_id=local/t_probe \\
        --arms='{demos: [local/t_demo], demos + play: [local/t_demo, local/t_play]}' [--steps=1] [--history=0] \\
        [--smooth=0] [--seeds='[0,1,2]']

JEPT (and BC+IDM) act on a task seen only as video through inverse dynamics learned from labelled frames
(P(a_t | s_t, s_t+1)). Whether a change to the labelled data (play episodes, random expert actions, more demo
tasks) or to the inverse dynamics' input (``--steps``: the next ``steps`` self-state changes; ``--history``: the
``history`` changes before t as well) or to its readings (``--smooth``: a majority over each episode's
neighbouring frames) can help is a property of the data, measured here in minutes: per arm (a list of labelled repos), an MLP on the true
self-state changes is fitted on every labelled frame of the arm's repos, once per seed, and scored on the
held-out labelled episodes of ``--probe_repo_id`` (a build's ``_probe``). Per probe task and arm it reports

- ``in_support``: the share of frames whose whole binned action occurs anywhere in the arm's labelled frames (a
  classifier fitted on them has never seen the others as a label);
- ``whole``: the share of frames whose whole action the model gets right (mean and 95% t-interval over the
  seeds), ``per_dim`` its accuracy per action dimension;

and, per arm, the mean over the video-only tasks (the build's split). This is the ceiling of acting from a
perfectly predicted next state: what a trained checkpoint reaches is measured by ``jept-prompt-probe``
(control accuracy) and in the simulator by ``jept-eval-suite``. Writes ``screen.json``, ``screen.md`` and
``screen.png`` to ``--output_dir``.
"""

import json
import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from tqdm import tqdm

from lerobot_jept.evaluation.prompt_probe import task_names
from lerobot_jept.evaluation.stats import t_interval
from lerobot_jept.policies.discretization import to_bin_indices


@dataclass
class ScreenConfig:
    probe_repo_id: str = ""  # labelled held-out repo the models are scored on (a build's `_probe`)
    arms: dict[str, list[str]] = field(default_factory=dict)  # arm name -> labelled repos it is fitted on
    root: Path | None = None  # parent folder of every repo (default: $HF_LEROBOT_HOME)
    steps: int = 1  # self-state changes after t given to the model (1 = the next frame only)
    history: int = 0  # self-state changes before t given as well (the arm's lag behind its commanded motion)
    smooth: int = 0  # score a per-dimension majority over this many readings each side, within each episode
    with_state: bool = False  # also give the model s_t itself, as JEPT's self-state inverse dynamics has it
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])  # one fitted model per seed and arm
    num_bins: int = 7  # action bins per dimension over [-1, 1] (the paper's 7)
    max_frames: int = 40_000  # labelled frames per arm, drawn at random beyond this (fit time)
    output_dir: Path = Path("outputs/screen")


class ScreenError(ValueError):
    pass


def load_frames(
    repo_id: str,
    root: Path | None,
    steps: int,
    num_bins: int,
    features: str = "state",
    with_state: bool = False,
    history: int = 0,
) -> dict[str, np.ndarray]:
    """Every frame t with ``history`` frames before it and ``steps`` after it in its episode: the ``history``
    self-state changes up to s_t, then the ``steps`` after it (preceded by s_t itself with ``with_state``; or,
    for ``pixels``, the uint8 frames o_t .. o_t+steps stacked on the channels), binned action, task (the
    builder's task name where the repo has build metadata, else the task string), episode index in its repo."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=None if root is None else root / repo_id)
    for key, fix in (
        ("action", "pass labelled repos (a build's `_demo`, `_play` and `_probe`), not `_video`"),
        ("observation.state", "inverse dynamics is fitted on the self-state; rebuild with it recorded"),
    ):
        if key not in dataset.meta.features:
            raise ScreenError(f"{repo_id} has no `{key}` column: {fix}.")
    names = task_names(dataset.meta) or {}
    tasks = dataset.meta.tasks
    task_of = {int(i): names.get(t, t) for t, i in zip(tasks.index, tasks["task_index"], strict=True)}
    columns = ["episode_index", "observation.state", "action", "task_index"]
    table = dataset.hf_dataset.with_format("numpy", columns=columns)[:]  # one read, not one per episode
    episode, task_index = table["episode_index"], table["task_index"]
    state, action = np.stack(table["observation.state"]), np.stack(table["action"])
    image_key = next((k for k, f in dataset.meta.features.items() if f["dtype"] in ("video", "image")), None)
    if features == "pixels" and image_key is None:
        raise ScreenError(f"{repo_id} has no camera frames: use --features=state.")
    inputs, labels, frame_tasks, frame_episodes = [], [], [], []
    for ep in tqdm(np.unique(episode), desc=f"{repo_id} episodes", unit="ep", leave=False):
        rows = np.flatnonzero(episode == ep)
        starts = range(history, len(rows) - steps)
        if features == "pixels":
            images = np.stack([(dataset[int(r)][image_key].numpy() * 255).round() for r in rows]).astype(
                np.uint8
            )
            inputs += [images[t : t + steps + 1].reshape(-1, *images.shape[2:]) for t in starts]
        else:
            delta = np.diff(state[rows], axis=0)
            own = state[rows] if with_state else np.zeros((len(rows), 0), state.dtype)
            inputs += [np.concatenate([own[t], delta[t - history : t + steps].reshape(-1)]) for t in starts]
        for t in starts:
            labels.append(to_bin_indices(action[rows[t]], num_bins))
            frame_tasks.append(task_of[int(task_index[rows[t]])])
            frame_episodes.append(int(ep))
    return {
        "x": np.array(inputs),
        "y": np.array(labels),
        "task": np.array(frame_tasks),
        "episode": np.array(frame_episodes),
    }


def concat_frames(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def majority(labels: np.ndarray, k: int) -> np.ndarray:
    """Per dimension, the most common bin among the ``k`` frames either side of each frame (one episode's
    (T, D) labels; ties go to the bin seen first)."""
    out = np.empty_like(labels)
    for t in range(len(labels)):
        window = labels[max(0, t - k) : t + k + 1]
        out[t] = [Counter(window[:, d].tolist()).most_common(1)[0][0] for d in range(labels.shape[1])]
    return out


def smoothed(predicted: np.ndarray, episode: np.ndarray, k: int) -> np.ndarray:
    """:func:`majority` over each episode's run of frames in ``predicted`` (N, D)."""
    out = predicted.copy()
    for ep in np.unique(episode):
        rows = np.flatnonzero(episode == ep)
        out[rows] = majority(predicted[rows], k)
    return out


def state_ceiling(
    train: dict[str, np.ndarray],
    probe: dict[str, np.ndarray],
    seed: int = 0,
    epochs: int = 40,
    smooth: int = 0,
) -> dict[str, dict]:
    """Per probe task: :func:`score` of an MLP inverse dynamics fitted on ``train`` (standardised inputs, two
    hidden layers of 128, one softmax over the bins per action dimension, cross-entropy, ``epochs`` passes),
    its readings :func:`smoothed` over ``smooth`` frames each side within each probe episode."""
    import torch
    from torch import nn

    torch.manual_seed(seed)
    mean, std = train["x"].mean(0), train["x"].std(0) + 1e-8
    x_train = torch.from_numpy((train["x"] - mean) / std).float()
    x_test = torch.from_numpy((probe["x"] - mean) / std).float()
    y = torch.from_numpy(train["y"]).long()
    dims, bins = y.shape[1], int(max(train["y"].max(), probe["y"].max())) + 1
    model = nn.Sequential(
        nn.Linear(x_train.shape[1], 128),
        nn.ReLU(),
        nn.Linear(128, 128),
        nn.ReLU(),
        nn.Linear(128, dims * bins),
    )
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3, weight_decay=1e-5)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        for batch in torch.randperm(len(x_train), generator=generator).split(256):
            logits = model(x_train[batch]).view(-1, bins)
            loss = nn.functional.cross_entropy(logits, y[batch].view(-1))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        predicted = model(x_test).view(len(x_test), dims, bins).argmax(-1).numpy()
    for d in range(dims):  # a dimension the labelled frames never move (the gripper of some tasks): that bin
        if len(set(train["y"][:, d])) == 1:
            predicted[:, d] = train["y"][0, d]
    predicted = predicted.astype(train["y"].dtype)
    if smooth:
        predicted = smoothed(predicted, probe["episode"], smooth)
    return score(predicted, train["y"], probe)


def score(predicted: np.ndarray, train_labels: np.ndarray, probe: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per probe task: frames, share of frames whose whole action is in the training labels' support,
    whole-action and per-dimension accuracy of ``predicted`` (N_probe, D) bins."""
    support = {tuple(a) for a in train_labels}
    in_support = np.array([tuple(a) in support for a in probe["y"]])
    hits = predicted == probe["y"]
    out = {}
    for task in sorted(set(probe["task"])):
        rows = probe["task"] == task
        out[task] = {
            "frames": int(rows.sum()),
            "in_demo_support": float(in_support[rows].mean()),
            "whole": float(hits[rows].all(1).mean()),
            "per_dim": [float(v) for v in hits[rows].mean(0)],
        }
    return out


def probe_split(cfg: ScreenConfig) -> dict[str, str]:
    """Builder task name -> its split (demo / video / unseen) from the probe repo's build metadata."""
    from lerobot_jept.evaluation.suite import SuiteError, read_build_metadata

    root = None if cfg.root is None else str(cfg.root / cfg.probe_repo_id)
    try:
        build, _ = read_build_metadata(cfg.probe_repo_id, root)
    except SuiteError:  # a repo that no builder wrote: no split to report
        return {}
    return {task: name for name, tasks in build["split"].items() for task in tasks}


def screen(cfg: ScreenConfig) -> dict:
    """Fit every arm once per seed and score it on the probe repo; returns the per-task and summary results."""
    inputs = {"with_state": cfg.with_state, "history": cfg.history}
    probe = load_frames(cfg.probe_repo_id, cfg.root, cfg.steps, cfg.num_bins, **inputs)
    split = probe_split(cfg)
    rng = np.random.default_rng(0)
    results: dict = {
        "probe_repo_id": cfg.probe_repo_id,
        "steps": cfg.steps,
        "with_state": cfg.with_state,
        "history": cfg.history,
        "smooth": cfg.smooth,
        "seeds": cfg.seeds,
        "arms": {},
    }
    for arm, repos in cfg.arms.items():
        train = concat_frames([load_frames(r, cfg.root, cfg.steps, cfg.num_bins, **inputs) for r in repos])
        if len(train["x"]) > cfg.max_frames:
            keep = rng.choice(len(train["x"]), cfg.max_frames, replace=False)
            train = {key: value[keep] for key, value in train.items()}
        runs = [
            state_ceiling(train, probe, seed, smooth=cfg.smooth)
            for seed in tqdm(cfg.seeds, desc=f"fitting {arm}", unit="seed", leave=False)
        ]
        per_task = {}
        for task in runs[0]:
            whole = [run[task]["whole"] for run in runs]
            per_task[task] = {
                "split": split.get(task, ""),
                "frames": runs[0][task]["frames"],
                "in_support": runs[0][task]["in_demo_support"],
                "whole": whole,
                "whole_mean": float(np.mean(whole)),
                "whole_interval": _interval(whole),
                "per_dim": np.mean([run[task]["per_dim"] for run in runs], 0).round(4).tolist(),
            }
        video = [t for t, r in per_task.items() if r["split"] == "video"]
        per_seed_video = [float(np.mean([run[t]["whole"] for t in video])) for run in runs] if video else []
        results["arms"][arm] = {
            "repos": repos,
            "labelled_frames": len(train["x"]),
            "per_task": per_task,
            "video_only_mean": float(np.mean(per_seed_video)) if video else None,
            "video_only_interval": _interval(per_seed_video) if video else None,
        }
    return results


def _interval(values: list[float]) -> list[float] | None:
    return [round(v, 4) for v in t_interval(values, 0.95)] if len(values) > 1 else None


def markdown(results: dict) -> str:
    arms = list(results["arms"])
    first = results["arms"][arms[0]]["per_task"]
    lines = [
        f"Inverse dynamics on the next {results['steps']} self-state change(s)"
        f"{' and s_t' if results.get('with_state') else ''}"
        f"{f' after the {h} before it' if (h := results.get('history')) else ''}, fitted per arm on its labelled "
        f"frames{f', readings smoothed by a majority over {k} frame(s) each side' if (k := results.get('smooth')) else ''}, scored on {results['probe_repo_id']}; whole-action accuracy, mean [95% interval] over seeds "
        f"{results['seeds']} (share of frames whose action the arm's labels contain).",
        "",
        "| task | split | frames | " + " | ".join(arms) + " |",
        "|---|---|---:|" + "---|" * len(arms),
    ]

    def cell(r: dict) -> str:
        interval = r["whole_interval"]
        spread = f" [{interval[0]:.2f}, {interval[1]:.2f}]" if interval else ""
        return f"{r['whole_mean']:.2f}{spread} ({r['in_support']:.2f})"

    for task, row in first.items():
        cells = [cell(results["arms"][a]["per_task"][task]) for a in arms]
        lines.append(f"| {task} | {row['split'] or '-'} | {row['frames']} | " + " | ".join(cells) + " |")
    summary = []
    for a in arms:
        arm = results["arms"][a]
        if arm["video_only_mean"] is None:
            summary.append("-")
            continue
        interval = arm["video_only_interval"]
        spread = f" [{interval[0]:.2f}, {interval[1]:.2f}]" if interval else ""
        summary.append(f"**{arm['video_only_mean']:.2f}**{spread}")
    lines.append("| **video-only mean** | video | | " + " | ".join(summary) + " |")
    lines.append(
        "| labelled frames | | | " + " | ".join(str(results["arms"][a]["labelled_frames"]) for a in arms)
    )
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = list(results["arms"])
    tasks = list(results["arms"][arms[0]]["per_task"])
    width = 0.8 / len(arms)
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(tasks) * len(arms)), 4))
    for i, arm in enumerate(arms):
        rows = [results["arms"][arm]["per_task"][t] for t in tasks]
        means = [r["whole_mean"] for r in rows]
        errors = [
            [m - (r["whole_interval"] or [m, m])[0] for m, r in zip(means, rows, strict=True)],
            [(r["whole_interval"] or [m, m])[1] - m for m, r in zip(means, rows, strict=True)],
        ]
        xs = np.arange(len(tasks)) + (i - (len(arms) - 1) / 2) * width
        ax.bar(xs, means, width, yerr=np.clip(errors, 0, None), label=arm, capsize=2)
    labels = [f"{t}\n({results['arms'][arms[0]]['per_task'][t]['split'] or '-'})" for t in tasks]
    ax.set_xticks(np.arange(len(tasks)), labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("whole-action accuracy")
    ax.set_ylim(0, 1)
    ax.set_title(f"Inverse dynamics from the true self-state change ({results['probe_repo_id']})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(args: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(config_class=ScreenConfig, args=args)
    if not cfg.probe_repo_id or not cfg.arms:
        raise SystemExit(
            "jept-screen: error: pass --probe_repo_id=ORG/NAME_probe and --arms='{NAME: [ORG/NAME_demo, ...]}' "
            "(each arm: the labelled repos its inverse dynamics is fitted on)."
        )
    if cfg.steps < 1:
        raise SystemExit(f"jept-screen: error: --steps must be at least 1 (the next frame), got {cfg.steps}.")
    if cfg.history < 0:
        raise SystemExit(
            f"jept-screen: error: --history must be 0 or more (changes before t), got {cfg.history}."
        )
    if cfg.smooth < 0:
        raise SystemExit(
            f"jept-screen: error: --smooth must be 0 or more (frames each side), got {cfg.smooth}."
        )
    if not cfg.seeds:
        raise SystemExit("jept-screen: error: --seeds must name at least one seed.")
    try:
        results = screen(cfg)
    except ScreenError as err:
        raise SystemExit(f"jept-screen: error: {err}") from None
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "screen.json").write_text(json.dumps(results, indent=2))
    table = markdown(results)
    (cfg.output_dir / "screen.md").write_text(table + "\n")
    plot(results, cfg.output_dir / "screen.png")
    print(table)
    print(f"\nWrote {cfg.output_dir}/screen.json, screen.md and screen.png")


if __name__ == "__main__":
    main()
