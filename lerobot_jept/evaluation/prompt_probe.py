"""``jept-prompt-probe``: a checkpoint measured offline on held-out labelled episodes, per task and per split.

Works for every policy type that takes a prompt (``jept``, ``jept_dt_star``, ``jept_vid2robot``), on a labelled
LeRobotDataset that was not trained on: the builder's ``ORG/NAME_probe`` repo (every task of every split, seeds
disjoint from everything else), or any labelled repo.

- Prompt separability. Every episode of the repo is a held-out prompt: its frames, subsampled to the policy's
  ``max_prompt_length``, go through the prompt encoder to E_prt (N_prt x D, flattened). Reported: leave-one-out
  nearest-centroid accuracy over tasks (each prompt against the centroid of the other prompts of its own task
  and the centroids of the other tasks), per task and overall, once over every task of the repo and once over
  the tasks the policy trained on (T_demo and T_vid, from the build's metadata) alone, and the spread (mean
  over dimensions of the standard deviation across prompts, divided by the mean absolute value; a prompt
  embedding collapsed to a constant has spread ~0).
- Action accuracy. On up to ``frames_per_episode`` frames of every episode, the action-bin accuracy (whole
  action and per dimension) of a_t for the last context frame, prompted by the task's first bank prompt:
  ``control`` is the action ``select_action`` would choose (for JEPT: from the predicted h_{t+1});
  ``inverse`` (JEPT only) reads it from the real next frame's joint embedding (the inverse dynamics alone).
  JEPT also reports L_obs, the distance of its predicted next joint embeddings to the EMA targets.
- Prompt swap. The same frames prompted by a scene-mate's bank prompt (tasks whose names share their first
  word, e.g. window-open / window-close; every other task for a repo without the builder's metadata): the
  fraction of frames whose chosen action changes, the whole-action accuracy of the action chosen under the
  wrong prompt (``swap_control_whole``, against ``control_whole`` with the task's own: what the right prompt
  is worth), and for JEPT the fraction whose L_obs rises (the predicted next embedding follows the prompt,
  whether or not the action head reads the difference).
- Per split (T_demo / T_vid / T_unseen, from the build's metadata): the mean over tasks of each measure.

    jept-prompt-probe --policy.path=outputs/train/.../pretrained_model --dataset.repo_id=ORG/NAME_probe \\
        [--prompt_repo_id=ORG/NAME_prompts] [--output_dir=outputs/probe]

Writes ``prompt_probe.json`` and ``prompt_probe.md``; ``jept-eval-suite`` runs it on the build's probe repo.
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
from lerobot_jept.policies.prompts import subsample_indices


@dataclass
class ProbeConfig:
    policy: PolicyArg = field(default_factory=PolicyArg)
    dataset: DatasetArg = field(default_factory=DatasetArg)  # labelled, held-out episodes
    prompt_repo_id: str | None = None  # bank for the action measures (default: the policy's own)
    prompt_root: str | None = None
    frames_per_episode: int = 16
    batch_size: int = 32
    output_dir: Path | None = Path("outputs/prompt_probe")


class ProbeError(ValueError):
    pass


def scene_key(task_name: str) -> str:
    """Tasks that share a scene share the first word of their name (window-open / window-close,
    button-press-topdown / button-press-topdown-wall); for robosuite names (``<arm>-<manipulation>``) the
    manipulation."""
    parts = task_name.split("-")
    return parts[-1] if parts[0] in ("panda", "sawyer", "iiwa", "ur5e") else parts[0]


def separability(embeddings: np.ndarray, labels: list[str]) -> dict:
    """Leave-one-out nearest-centroid accuracy (overall and per task) and spread of (n, d) embeddings."""
    x = embeddings.astype(np.float64)
    tasks = sorted(set(labels))
    y = np.array([tasks.index(t) for t in labels])
    sums = np.stack([x[y == c].sum(0) for c in range(len(tasks))])
    counts = np.array([(y == c).sum() for c in range(len(tasks))], dtype=np.float64)
    correct = np.zeros(len(x), dtype=bool)
    for i in range(len(x)):
        s, n = sums.copy(), counts.copy()
        s[y[i]] -= x[i]
        n[y[i]] -= 1
        valid = n > 0
        centroids = s[valid] / n[valid, None]
        nearest = np.flatnonzero(valid)[np.argmin(((centroids - x[i]) ** 2).sum(-1))]
        correct[i] = nearest == y[i]
    spread = float(x.std(0).mean() / max(np.abs(x).mean(), 1e-12))
    return {
        "nearest_centroid_accuracy": float(correct.mean()),
        "per_task_accuracy": {t: float(correct[y == c].mean()) for c, t in enumerate(tasks)},
        "spread": spread,
        "num_prompts": len(x),
    }


def task_names(meta) -> dict[str, str] | None:
    """Task string -> builder task name (from ``meta/jept_build.json``); None for a repo without one."""
    path = Path(meta.root) / "meta/jept_build.json"
    if not path.is_file():
        return None
    build = json.loads(path.read_text())
    return {string: name for name, string in build["task_descriptions"].items()}


def scene_mates(task_strings: list[str], names: dict[str, str] | None) -> dict[str, list[str]]:
    """Each task string's scene-mates (by :func:`scene_key` of the builder's names); without build metadata,
    every other task of the repo."""
    if names is None:
        return {t: [m for m in task_strings if m != t] for t in task_strings}
    key = {t: scene_key(names.get(t, t)) for t in task_strings}
    return {t: [m for m in task_strings if m != t and key[m] == key[t]] for t in task_strings}


def load_checkpoint(cfg: ProbeConfig):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    policy_cfg = PreTrainedConfig.from_pretrained(cfg.policy.path)
    if policy_cfg.type == "jept_idm":
        raise ProbeError(
            f"{cfg.policy.path} is an inverse dynamics model: it takes no prompt and cannot act. Probe the policy "
            "trained on its labels (jept-relabel, then --policy.type=jept_dt_star) instead."
        )
    cfg.policy.apply(policy_cfg)
    if cfg.prompt_repo_id:
        policy_cfg.prompt_repo_id, policy_cfg.prompt_root = cfg.prompt_repo_id, cfg.prompt_root
    policy = get_policy_class(policy_cfg.type).from_pretrained(cfg.policy.path, config=policy_cfg).eval()
    overrides = {"jept_prompt_video": {"repo_id": policy_cfg.prompt_repo_id, "root": policy_cfg.prompt_root}}
    pre, _ = make_pre_post_processors(
        policy_cfg, pretrained_path=cfg.policy.path, preprocessor_overrides=overrides
    )
    return policy, pre


@torch.no_grad()
def prompt_embeddings(policy, dataset, progress: bool = True) -> tuple[np.ndarray, list[str]]:
    """E_prt (flattened) of every episode of ``dataset`` used as a prompt, with each episode's task."""
    from lerobot_jept.policies.prompts import PromptBank

    cfg = policy.config
    bank = PromptBank(dataset.repo_id, dataset.root, cfg.max_prompt_length, cfg.image_size)
    episodes = range(dataset.meta.total_episodes)
    out, tasks = [], []
    for ep in tqdm(episodes, desc="prompt embeddings", unit="prompt", disable=not progress):
        video, mask = bank.batch([ep])
        e_prt = policy.model.encode_prompt(video.to(policy.bin_centres.device), mask.to(video.device))
        out.append(e_prt.flatten().cpu().numpy())
        tasks.append(dataset.meta.episodes[ep]["tasks"][0])
    return np.stack(out), tasks


def probe_frames(dataset, per_episode: int) -> list[int]:
    """Up to ``per_episode`` frame indices per episode, spread uniformly, each with a next frame."""
    frames = []
    for ep in range(dataset.meta.total_episodes):
        info = dataset.meta.episodes[ep]
        start, length = int(info["dataset_from_index"]), int(info["length"])
        frames += [start + int(i) for i in subsample_indices(length - 1, per_episode)]
    return frames


def bin_accuracy(predicted: torch.Tensor, labels: torch.Tensor) -> tuple[float, float]:
    """Whole-action and per-dimension accuracy of predicted bins (N, A) against labels (N, A), over the
    labelled rows (every label >= 0); NaN without any."""
    labelled = (labels >= 0).all(-1)
    hit = (predicted == labels)[labelled]
    if not len(hit):
        return float("nan"), float("nan")
    return float(hit.all(-1).float().mean()), float(hit.float().mean())


@torch.no_grad()
def action_measures(policy, pre, dataset, names: dict[str, str] | None, cfg: ProbeConfig) -> dict:
    """Per task: control (/ inverse) action accuracy and L_obs with its own bank prompt, and the swap change
    rate."""
    from lerobot.utils.constants import ACTION

    from lerobot_jept.policies.jept.modeling_jept import PROMPT_MASK, PROMPT_VIDEO

    bank = pre.steps[[type(s).__name__ for s in pre.steps].index("JeptPromptVideoStep")].bank
    by_task: dict[str, list[int]] = {}
    for idx in probe_frames(dataset, cfg.frames_per_episode):
        by_task.setdefault(dataset.hf_dataset[idx]["task_index"].item(), []).append(idx)
    task_strings = list(dataset.meta.tasks.index)
    all_mates = scene_mates(task_strings, names)
    names = names or {}
    results = {}
    for task_index, indices in tqdm(sorted(by_task.items()), desc="action probe", unit="task"):
        task = task_strings[task_index]
        if task not in bank.tasks:
            raise ProbeError(
                f"The prompt bank {bank.repo_id} has no prompt of {task!r}: pass --prompt_repo_id=ORG/NAME_prompts "
                "of the build that recorded the probe repo."
            )
        mates = [m for m in all_mates[task] if m in bank.tasks]
        prompts = {task: bank.batch([bank.episodes(task)[0]])}
        prompts.update({m: bank.batch([bank.episodes(m)[0]]) for m in mates})
        outs: dict[str, list[torch.Tensor]] = {"labels": []}
        swapped_actions: dict[str, list[torch.Tensor]] = {m: [] for m in mates}
        rises: dict[str, list[torch.Tensor]] = {m: [] for m in mates}
        for start in range(0, len(indices), cfg.batch_size):
            items = [dataset[i] for i in indices[start : start + cfg.batch_size]]
            batch = {
                k: torch.stack([it[k] for it in items]) for k in items[0] if torch.is_tensor(items[0][k])
            }
            batch["task"] = [it["task"] for it in items]
            outputs = {}
            for name, (video, mask) in prompts.items():
                given = {**batch, PROMPT_VIDEO: video.expand(len(items), -1, -1, -1, -1)}
                given[PROMPT_MASK] = mask.expand(len(items), -1)
                processed = pre(given)
                outputs[name] = policy.offline_outputs(processed)
            outs["labels"].append(processed[ACTION][:, -1].cpu())
            if processed[ACTION].shape[1] > 1:  # a_{t-1}, where the episode has one (not padded)
                previous = processed[ACTION][:, -2].clone()
                pad = processed.get(f"{ACTION}_is_pad")
                if pad is not None:
                    previous[pad[:, -2]] = -1
                outs.setdefault("previous", []).append(previous.cpu())
            for key, value in outputs[task].items():
                outs.setdefault(key, []).append((value.argmax(-1) if value.ndim == 3 else value).cpu())
            for m in mates:
                swapped_actions[m].append(outputs[m]["control"].argmax(-1).cpu())
                if "loss_obs" in outputs[task]:
                    rises[m].append((outputs[m]["loss_obs"] > outputs[task]["loss_obs"]).cpu())
        labels = torch.cat(outs["labels"])
        row = {"task": names.get(task, task), "frames": int((labels >= 0).all(-1).sum())}
        for path in ("control", "inverse"):
            if path in outs:
                row[f"{path}_whole"], row[f"{path}_per_dim"] = bin_accuracy(torch.cat(outs[path]), labels)
        if "loss_obs" in outs:
            row["loss_obs"] = float(torch.cat(outs["loss_obs"]).mean())
        if "previous" in outs:  # the reference of smooth experts: a_t scored as if it were a_{t-1}
            previous = torch.cat(outs["previous"])
            has_previous = (previous >= 0).all(-1, keepdim=True)
            row["previous_whole"] = bin_accuracy(previous, torch.where(has_previous, labels, -1))[0]
        # Per scene-mate: the share of frames whose chosen action changes under its prompt (and per action
        # dimension, to set against examples/measurements/expert_swap_ceiling.py's experts), the accuracy of that action
        # against this task's labels (what the task's own prompt is worth over a wrong one of the same scene),
        # and the share of frames whose L_obs rises.
        own = torch.cat(outs["control"]) if mates else None
        swapped = {names.get(m, m): torch.cat(v) for m, v in swapped_actions.items() if v}
        row["swap_changed"] = {m: float((v != own).any(-1).float().mean()) for m, v in swapped.items()}
        row["swap_changed_per_dim"] = {m: (v != own).float().mean(0).tolist() for m, v in swapped.items()}
        row["swap_control_whole"] = {m: bin_accuracy(v, labels)[0] for m, v in swapped.items()}
        row["swap_raises_loss_obs"] = {
            names.get(m, m): float(torch.cat(v).float().mean()) for m, v in rises.items() if v
        }
        results[task] = row
    return results


SPLIT_NAMES = {"demo": "T_demo", "video": "T_vid", "unseen": "T_unseen"}
ACTION_MEASURES = (
    "control_whole",
    "control_per_dim",
    "inverse_whole",
    "inverse_per_dim",
    "loss_obs",
    "previous_whole",  # labelled a_t equal to a_{t-1}: what repeating the last action scores
)
SWAP_MEASURES = ("swap_changed", "swap_control_whole")  # per scene-mate
MEASURES = (*ACTION_MEASURES, "nc_accuracy", "nc_accuracy_trained", *SWAP_MEASURES)
TRAINED_SPLITS = ("demo", "video")  # the tasks a policy trains on (labels or videos); "unseen" it never sees


def trained_separability(embeddings: np.ndarray, labels: list[str], split: dict) -> dict | None:
    """:func:`separability` over the prompts of the tasks the policy trained on (T_demo and T_vid) alone: an
    unseen task's prompts were never asked to form a cluster of their own, so they can take a trained task's
    nearest centroid (faucet-open's prompts among faucet-close's). None when fewer than two trained tasks were
    probed (nothing to tell apart)."""
    trained = {t for key in TRAINED_SPLITS for t in split.get(key, [])}
    keep = [i for i, t in enumerate(labels) if t in trained]
    if len({labels[i] for i in keep}) < 2:
        return None
    return separability(embeddings[keep], [labels[i] for i in keep])


def split_summary(
    rows: dict[str, dict],
    separability_per_task: dict[str, float],
    split: dict,
    trained_per_task: dict[str, float] | None = None,
) -> dict:
    """Mean over each split's tasks (T_demo / T_vid / T_unseen) of every measure the rows carry, plus the
    E_prt nearest-centroid accuracy (over all probed tasks, and over the trained tasks alone where
    ``trained_per_task`` is given), the share of frames whose action changes under a scene-mate's prompt and
    the accuracy of that action (tasks with a scene-mate only); splits without a probed task are left out."""
    nc = {"nc_accuracy": separability_per_task, "nc_accuracy_trained": trained_per_task or {}}
    out = {}
    for key, tasks in split.items():
        present = [t for t in tasks if t in rows]
        if not present:
            continue
        summary = {"tasks": present}
        for measure in MEASURES:
            if measure in nc:
                values = [nc[measure][t] for t in present if t in nc[measure]]
            elif measure in SWAP_MEASURES:
                values = [np.mean(list(swaps.values())) for t in present if (swaps := rows[t].get(measure))]
            else:
                values = [rows[t][measure] for t in present if measure in rows[t]]
            if values:
                summary[measure] = float(np.mean(values))
        out[SPLIT_NAMES[key]] = summary
    return out


def load_labelled(cfg: ProbeConfig):
    """The checkpoint's policy and preprocessor, and the labelled repo with the policy's frame windows."""
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata

    if not cfg.policy.path or not cfg.dataset.repo_id:
        raise ProbeError(
            "Pass both --policy.path=CHECKPOINT and --dataset.repo_id=ORG/NAME (a labelled repo)."
        )
    policy, pre = load_checkpoint(cfg)
    meta = LeRobotDatasetMetadata(cfg.dataset.repo_id, root=cfg.dataset.root)
    if "action" not in meta.features:
        raise ProbeError(
            f"{cfg.dataset.repo_id} has no `action`: the probe needs labelled held-out episodes, e.g. a build "
            "with every task as a demo task and another --seed (jept-build-metaworld --demo_tasks=[...])."
        )
    dataset = LeRobotDataset(
        cfg.dataset.repo_id,
        root=cfg.dataset.root,
        delta_timestamps=resolve_delta_timestamps(policy.config, meta),
    )
    return policy, pre, dataset


def run_probe(cfg: ProbeConfig, split: dict[str, list[str]] | None = None) -> dict:
    """The probe; ``split`` (builder task names per split) defaults to the probe repo's own build metadata."""
    policy, pre, dataset = load_labelled(cfg)
    meta = dataset.meta
    names = task_names(meta)
    if split is None and names is not None:
        split = json.loads((Path(meta.root) / "meta/jept_build.json").read_text())["split"]
    embeddings, prompt_tasks = prompt_embeddings(policy, dataset)
    labels = [(names or {}).get(t, t) for t in prompt_tasks]
    sep = separability(embeddings, labels)
    trained = trained_separability(embeddings, labels, split) if split else None
    if trained is not None:
        sep["trained_tasks"] = trained
    actions = {row["task"]: row for row in action_measures(policy, pre, dataset, names, cfg).values()}
    trained_per_task = trained["per_task_accuracy"] if trained else None
    results = {
        "policy": cfg.policy.path,
        "policy_type": policy.config.type,
        "dataset": cfg.dataset.repo_id,
        "prompt_bank": policy.config.prompt_repo_id,
        "prompt_separability": sep,
        "actions": actions,
        "splits": split_summary(actions, sep["per_task_accuracy"], split, trained_per_task) if split else {},
    }
    if cfg.output_dir is not None:
        out = Path(cfg.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "prompt_probe.json").write_text(json.dumps(results, indent=2))
        (out / "prompt_probe.md").write_text(markdown(results))
    return results


def _cell(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or value != value else f"{value:.{digits}f}"


def markdown(results: dict) -> str:
    sep = results["prompt_separability"]
    headline = (
        f"Prompt embedding E_prt on {sep['num_prompts']} held-out prompts: nearest-centroid accuracy "
        f"{sep['nearest_centroid_accuracy']:.3f}, spread {sep['spread']:.3f}"
    )
    if trained := sep.get("trained_tasks"):
        headline += (
            f"; over the {trained['num_prompts']} prompts of the trained tasks (T_demo and T_vid) alone: "
            f"nearest-centroid accuracy {trained['nearest_centroid_accuracy']:.3f}"
        )
    lines = [
        headline,
        "",
        "| Task | E_prt NC acc | NC, trained tasks | frames | control whole | control per-dim | inverse whole "
        "| inverse per-dim | L_obs | a_{t-1} repeated, whole | prompt swap changes action (raises L_obs; control "
        "whole under the swap) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    trained_per_task = sep.get("trained_tasks", {}).get("per_task_accuracy", {})
    for task, row in results["actions"].items():
        rises, scored = row.get("swap_raises_loss_obs", {}), row.get("swap_control_whole", {})
        swap = ", ".join(
            f"{m}: {v:.2f} ({_cell(rises.get(m), 2)}; {_cell(scored.get(m), 2)})"
            for m, v in row["swap_changed"].items()
        )
        swap = swap or "-"
        cells = [_cell(sep["per_task_accuracy"].get(task), 2), _cell(trained_per_task.get(task), 2)]
        cells.append(str(row["frames"]))
        cells += [_cell(row.get(k)) for k in ACTION_MEASURES]
        lines.append(f"| {task} | " + " | ".join(cells) + f" | {swap} |")
    if results.get("splits"):
        lines += [
            "",
            "| Split | tasks | E_prt NC acc | NC, trained tasks | control whole | control per-dim | inverse whole "
            "| inverse per-dim | L_obs | a_{t-1} repeated, whole | prompt swap changes action | control whole under "
            "the swap |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for name, row in results["splits"].items():
            cells = [_cell(row.get(k), 2) for k in ("nc_accuracy", "nc_accuracy_trained")]
            cells += [_cell(row.get(k)) for k in ACTION_MEASURES]
            cells += [_cell(row.get("swap_changed"), 2), _cell(row.get("swap_control_whole"))]
            lines.append(f"| {name} | {len(row['tasks'])} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    import lerobot_policy_jept  # noqa: F401  (registers the policy and the envs)

    cfg = draccus.parse(ProbeConfig)
    try:
        results = run_probe(cfg)
    except ProbeError as err:
        sys.exit(f"jept-prompt-probe: {err}")
    print(markdown(results))
    if cfg.output_dir is not None:
        print(f"Wrote {cfg.output_dir}/prompt_probe.json and prompt_probe.md")
