"""How much of the action one step of motion tells, per task: linear probes on a JEPT checkpoint's embeddings.

    python -m scripts.idm_linear_probe --policy.path=CKPT --dataset.repo_id=ORG/NAME_probe \
        --demo_tasks='[Push and open a window, ...]'

Every second frame of every episode of the labelled repo is encoded (online joint embeddings h_t, h_{t+1}, and
the self-state s_t, s_{t+1}); a logistic regression per action dimension is fitted on the demo tasks' frames of
all but each task's last episode and scored (whole-action accuracy) on every other frame, per task, for the
features h_t, (h_t, h_{t+1}), h_{t+1} - h_t and s_{t+1} - s_t. Used in docs/prompt_collapse.md, section 5.
"""

from dataclasses import dataclass, field

import draccus
import numpy as np
import torch
from lerobot.utils.constants import ACTION, OBS_STATE

import lerobot_policy_jept  # noqa: F401  (registers the processors)
from lerobot_jept.modeling_jept import PROMPT_MASK, PROMPT_VIDEO
from lerobot_jept.prompt_probe import ProbeConfig, load_labelled
from scripts.idm_ceiling import fit_per_dimension


@dataclass
class LinearProbeConfig(ProbeConfig):
    demo_tasks: list[str] = field(default_factory=list)  # task strings the probes are fitted on


@torch.no_grad()
def features(policy, pre, dataset, batch_size: int = 32) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray]:
    bank = pre.steps[[type(s).__name__ for s in pre.steps].index("JeptPromptVideoStep")].bank
    frames = []
    for ep in range(dataset.meta.total_episodes):
        info = dataset.meta.episodes[ep]
        start, length = int(info["dataset_from_index"]), int(info["length"])
        frames += [(ep, i) for i in range(start + 3, start + length - 1, 2)]
    feats = {"h_t": [], "h_t, h_t+1": [], "h_t+1 - h_t": [], "s_t+1 - s_t": []}
    labels, tasks, episodes = [], [], []
    for b in range(0, len(frames), batch_size):
        chunk = frames[b : b + batch_size]
        items = [dataset[i] for _, i in chunk]
        batch = {k: torch.stack([it[k] for it in items]) for k in items[0] if torch.is_tensor(items[0][k])}
        batch["task"] = [it["task"] for it in items]
        video, mask = bank.batch([bank.episodes(batch["task"][0])[0]])  # the prompt does not enter h
        batch[PROMPT_VIDEO] = video.expand(len(items), -1, -1, -1, -1)
        batch[PROMPT_MASK] = mask.expand(len(items), -1)
        p = pre(batch)
        _, _, h = policy._encode_window(p)
        h_t, h_next = h[:, -2].flatten(1), h[:, -1].flatten(1)
        state = p[OBS_STATE]
        feats["h_t"].append(h_t)
        feats["h_t, h_t+1"].append(torch.cat([h_t, h_next], 1))
        feats["h_t+1 - h_t"].append(h_next - h_t)
        feats["s_t+1 - s_t"].append(state[:, -1] - state[:, -2])
        labels.append(p[ACTION][:, -1])
        tasks += batch["task"]
        episodes += [ep for ep, _ in chunk]
    feats = {k: torch.cat(v).numpy() for k, v in feats.items()}
    return feats, torch.cat(labels).numpy(), np.array(tasks), np.array(episodes)


def main() -> None:
    from sklearn.linear_model import LogisticRegression

    cfg = draccus.parse(config_class=LinearProbeConfig)
    torch.set_num_threads(2)
    policy, pre, dataset = load_labelled(cfg)
    feats, labels, tasks, episodes = features(policy, pre, dataset)
    last = {t: episodes[tasks == t].max() for t in set(tasks)}
    train = np.isin(tasks, cfg.demo_tasks) & (episodes != np.array([last[t] for t in tasks]))
    names = sorted(set(tasks))
    print("| features | " + " | ".join(names) + " |")
    print("|---|" + "---:|" * len(names))
    for name, x in feats.items():
        x = (x - x[train].mean(0)) / (x[train].std(0) + 1e-6)
        predicted = fit_per_dimension(lambda: LogisticRegression(max_iter=2000), x[train], labels[train], x)
        hits = (predicted == labels).all(1)
        print(f"| {name} | " + " | ".join(f"{hits[(tasks == t) & ~train].mean():.2f}" for t in names) + " |")


if __name__ == "__main__":
    main()
