"""``jept-visualize``: the paper's embedding figures (Section 4.2, Appendix C) as PNGs, with scikit-learn's t-SNE.

    jept-visualize --policy.path=outputs/train/.../pretrained_model --dataset.repo_id=ORG/NAME_probe \\
        [--baseline.path=outputs/train/dt_star/.../pretrained_model] [--output_dir=outputs/visualize]

- ``prompt_embeddings.png`` (Figure 5): E_prt of every episode of the labelled repo used as a prompt, one colour
  per task, one marker per split (T_demo / T_vid / T_unseen), for the policy (and the baseline beside it).
- ``observation_embeddings.png`` (Figure 3): the observation embedding of every frame of one episode of a demo,
  a video and an unseen task (JEPT: the joint embedding of the frame over its k-frame context; a baseline: its
  observation tokens of the frame, averaged), each model's set projected by one t-SNE, coloured by task.
  Embeddings of tasks seen only as video or not at all that land among the demo task's are what the paper
  shows for JEPT; separate islands are the "out-of-distribution" picture of its baselines.

Also writes ``embeddings.npz`` (the raw embeddings and labels) so the figures can be redrawn.
"""

import json
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

from lerobot_jept.evaluation.cli_args import DatasetArg, PolicyArg
from lerobot_jept.evaluation.prompt_probe import (
    ProbeConfig,
    ProbeError,
    load_labelled,
    prompt_embeddings,
    task_names,
)

SPLIT_MARKERS = {"demo": "o", "video": "^", "unseen": "s"}


@dataclass
class VisualizeConfig:
    policy: PolicyArg = field(default_factory=PolicyArg)
    baseline: PolicyArg = field(default_factory=PolicyArg)  # optional second model, drawn beside
    dataset: DatasetArg = field(default_factory=DatasetArg)  # labelled held-out repo (the build's _probe)
    tasks: list[str] = field(
        default_factory=list
    )  # Figure 3's demo, video and unseen task (default: first of each)
    max_frames: int = 200  # per episode in Figure 3
    perplexity: float = 30.0
    seed: int = 0
    output_dir: Path = Path("outputs/visualize")


def tsne(x: np.ndarray, perplexity: float, seed: int) -> np.ndarray:
    from sklearn.manifold import TSNE

    perplexity = min(perplexity, max(1.0, (len(x) - 1) / 3))  # t-SNE needs perplexity < n
    return TSNE(n_components=2, perplexity=perplexity, init="pca", random_state=seed).fit_transform(
        x.astype(np.float32)
    )


@torch.no_grad()
def episode_embeddings(policy, pre, dataset, episode: int, max_frames: int) -> np.ndarray:
    """(T, D) observation embeddings of up to ``max_frames`` frames of one episode (each with a next frame)."""
    from lerobot_jept.policies.prompts import subsample_indices

    info = dataset.meta.episodes[episode]
    start, length = int(info["dataset_from_index"]), int(info["length"])
    frames = [start + int(i) for i in subsample_indices(length - 1, max_frames)]
    out = []
    for chunk in range(0, len(frames), 32):
        items = [dataset[i] for i in frames[chunk : chunk + 32]]
        batch = {k: torch.stack([it[k] for it in items]) for k in items[0] if torch.is_tensor(items[0][k])}
        batch["task"] = [it["task"] for it in items]
        out.append(policy.observation_embedding(pre(batch)).cpu().numpy())
    return np.concatenate(out)


def split_of(build: dict | None, name: str) -> str:
    for split, tasks in (build or {}).get("split", {}).items():
        if name in tasks:
            return split
    return "demo"


def figure3_episodes(cfg: VisualizeConfig, dataset, names: dict[str, str], build: dict | None) -> list[int]:
    """One episode of the chosen (or first) demo, video and unseen task of the repo."""
    by_task: dict[str, int] = {}
    for ep in range(dataset.meta.total_episodes):
        by_task.setdefault(names.get(dataset.meta.episodes[ep]["tasks"][0], ""), ep)
    wanted = list(cfg.tasks)
    if not wanted:
        for split in ("demo", "video", "unseen"):
            wanted += [t for t in (build or {}).get("split", {}).get(split, []) if t in by_task][:1]
        wanted = wanted or list(by_task)[:3]
    missing = [t for t in wanted if t not in by_task]
    if missing:
        raise ProbeError(f"{cfg.dataset.repo_id} has no episode of {missing}; it has {sorted(by_task)}.")
    return [by_task[t] for t in wanted]


def visualize(cfg: VisualizeConfig) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not cfg.policy.path or not cfg.dataset.repo_id:
        raise ProbeError(
            "Pass --policy.path=CHECKPOINT and --dataset.repo_id=ORG/NAME_probe (a labelled repo)."
        )
    models = [("policy", cfg.policy)] + ([("baseline", cfg.baseline)] if cfg.baseline.path else [])
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays, figures = {}, {}
    fig5, axes5 = plt.subplots(1, len(models), figsize=(6.5 * len(models), 5.5), squeeze=False)
    fig3, axes3 = plt.subplots(1, len(models), figsize=(6.5 * len(models), 5.5), squeeze=False)
    for col, (role, path) in enumerate(tqdm(models, desc="models", unit="model")):
        policy, pre, dataset = load_labelled(ProbeConfig(path, cfg.dataset))
        names = task_names(dataset.meta) or {}
        build_path = Path(dataset.meta.root) / "meta/jept_build.json"
        build = json.loads(build_path.read_text()) if build_path.is_file() else None
        label = policy.config.type

        e_prt, tasks = prompt_embeddings(policy, dataset, progress=False)
        tasks = [names.get(t, t) for t in tasks]
        xy = tsne(e_prt.reshape(len(e_prt), -1), cfg.perplexity, cfg.seed)
        arrays[f"{role}_prompt"], arrays[f"{role}_prompt_tasks"] = e_prt, np.array(tasks)
        ax = axes5[0][col]
        for task in sorted(set(tasks)):
            idx = [i for i, t in enumerate(tasks) if t == task]
            split = split_of(build, task)
            ax.scatter(xy[idx, 0], xy[idx, 1], marker=SPLIT_MARKERS[split], s=40, label=f"{task} ({split})")
        ax.set_title(f"E_prt of held-out prompts: {label}")
        ax.legend(fontsize=7, loc="best")

        episodes = figure3_episodes(cfg, dataset, names, build)
        sets = [episode_embeddings(policy, pre, dataset, ep, cfg.max_frames) for ep in episodes]
        ep_tasks = [names.get(dataset.meta.episodes[ep]["tasks"][0], "?") for ep in episodes]
        xy = tsne(np.concatenate(sets), cfg.perplexity, cfg.seed)
        arrays[f"{role}_observation"] = np.concatenate(sets)
        arrays[f"{role}_observation_tasks"] = np.repeat(ep_tasks, [len(s) for s in sets])
        ax, start = axes3[0][col], 0
        for task, s in zip(ep_tasks, sets, strict=True):
            split = split_of(build, task)
            ax.scatter(
                xy[start : start + len(s), 0],
                xy[start : start + len(s), 1],
                s=10,
                marker=SPLIT_MARKERS[split],
                label=f"{task} ({split})",
            )
            start += len(s)
        ax.set_title(f"Observation embeddings along one episode per task: {label}", fontsize=9)
        ax.legend(fontsize=7, loc="best")
        figures[role] = {"policy_type": policy.config.type, "path": path.path, "figure3_tasks": ep_tasks}
    for fig, name in ((fig5, "prompt_embeddings.png"), (fig3, "observation_embeddings.png")):
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
    np.savez_compressed(out / "embeddings.npz", **arrays)
    result = {
        "dataset": cfg.dataset.repo_id,
        "models": figures,
        "files": [
            str(out / n) for n in ("prompt_embeddings.png", "observation_embeddings.png", "embeddings.npz")
        ],
    }
    print("Wrote " + ", ".join(result["files"]))
    return result


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    import lerobot_policy_jept  # noqa: F401  (registers the policies)

    cfg = draccus.parse(VisualizeConfig)
    try:
        visualize(cfg)
    except ProbeError as err:
        sys.exit(f"jept-visualize: {err}")
