"""How well can inverse dynamics learned on the demo tasks alone act on the other tasks, from the true state?

    python -m examples.measurements.idm_ceiling --demo_repo_id=ORG/NAME_demo --probe_repo_id=ORG/NAME_probe [--features=pixels]

A property of the data, not of a checkpoint: JEPT's actions on a video-only task come from inverse dynamics
learned on the demo tasks (P(a_t | o_t, o_t+1), Section 3.2). Per task of the labelled probe repo, this prints

- the share of frames whose whole binned action occurs anywhere in the demo repo (a classifier fitted on the demos
  has never seen the others as a label);
- the whole-action and per-dimension accuracy of an MLP inverse-dynamics model fitted on every frame of the demo
  repo, whose input is the true change of the self-state over the next ``--steps`` steps
  (s_t+1 - s_t, ..., s_t+steps - s_t+steps-1), i.e. the best case of a perfect next-frame embedding;
- with ``--features=pixels``, the same for a small CNN fitted on the camera frames o_t, ..., o_t+steps themselves
  (the repo's resolution): what the images can tell of the action, before any embedding;
- with ``--features=embedding --policy_path=CKPT``, the same MLP fitted on a JEPT checkpoint's joint embeddings
  (h_t, h_t+1), on their self-state token alone and on their visual tokens alone, against the raw self-states
  (s_t, s_t+1) of the same frames and the checkpoint's own inverse dynamics: which part of the joint embedding
  carries inverse dynamics that transfers from the demo tasks to the others; and the state-token model scored on
  the h_t+1 the checkpoint predicts, what it would act from.

On the demo tasks' own held-out episodes this is near 1; how far it falls on a video-only task bounds what any
inverse dynamics fitted on these demos can reach there. Used in docs/results.md ("With the paper's inverse
dynamics the videos do not help").
"""

from dataclasses import dataclass
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

from lerobot_jept.evaluation.prompt_probe import task_names
from lerobot_jept.evaluation.screen import load_frames, score, state_ceiling


@dataclass
class CeilingConfig:
    demo_repo_id: str = ""  # labelled repo the inverse dynamics is fitted on (a build's `_demo`)
    probe_repo_id: str = ""  # labelled held-out repo it is scored on (a build's `_probe`)
    root: Path | None = None  # parent folder of both repos (default: $HF_LEROBOT_HOME)
    steps: int = 1  # self-state changes after t given to the model (1 = the next frame only)
    # "state": the true self-state changes; "pixels": the frames, through a small CNN; "embedding": the joint
    # embeddings of the checkpoint at --policy_path (and their parts), against the raw self-states
    features: str = "state"
    policy_path: str = ""  # a JEPT checkpoint (.../pretrained_model), for --features=embedding
    frames_per_episode: int = 16  # embedding: frames per episode, spread as jept-prompt-probe spreads them
    epochs: int = 20  # CNN training epochs (pixels)
    num_bins: int = 7  # action bins per dimension over [-1, 1] (the paper's 7)
    seed: int = 0


def fit_cnn(
    x_train: np.ndarray,
    y_train: np.ndarray,
    x_test: np.ndarray,
    num_bins: int,
    seed: int = 0,
    epochs: int = 20,
) -> np.ndarray:
    """A small CNN (four stride-2 convolutions, one linear layer per action dimension's bins) fitted with
    cross-entropy on uint8 frame stacks (N, C, H, W) -> (N_test, D) predicted bins."""
    import torch
    from torch import nn

    torch.manual_seed(seed)
    dims = y_train.shape[1]
    widths = [x_train.shape[1], 32, 64, 128, 128]
    layers = [
        m
        for a, b in zip(widths[:-1], widths[1:], strict=True)
        for m in (nn.Conv2d(a, b, 3, stride=2, padding=1), nn.ReLU())
    ]
    model = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(128, dims * num_bins))
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    images = lambda x: torch.from_numpy(x).float() / 255 - 0.5  # noqa: E731
    labels = torch.from_numpy(y_train).long()
    for _ in tqdm(range(epochs), desc="CNN epochs", unit="epoch", leave=False):
        for batch in torch.randperm(len(x_train)).split(64):
            logits = model(images(x_train[batch.numpy()])).view(-1, num_bins)
            loss = nn.functional.cross_entropy(logits, labels[batch].view(-1))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    model.eval()
    with torch.no_grad():
        out = [
            model(images(x_test[i : i + 256])).view(-1, dims, num_bins).argmax(-1)
            for i in range(0, len(x_test), 256)
        ]
    return torch.cat(out).numpy()


def ceiling(
    demo: dict[str, np.ndarray],
    probe: dict[str, np.ndarray],
    seed: int = 0,
    features: str = "state",
    num_bins: int = 7,
    epochs: int = 20,
) -> dict[str, dict]:
    """Per probe task: frames, share of frames whose whole action is in the demos' support, accuracies of the
    inverse dynamics fitted on the demos (an MLP on state changes, or a CNN on the frames)."""
    if features == "pixels":
        return score(fit_cnn(demo["x"], demo["y"], probe["x"], num_bins, seed, epochs), demo["y"], probe)
    return state_ceiling(demo, probe, seed)


# The inputs an inverse dynamics of the frame pair (t, t+1) is fitted on with --features=embedding, all from the
# same windows: the raw self-states, the checkpoint's joint embeddings (h_t, h_t+1) as its action head receives
# them in training (online encoder, each frame over the frames up to it), and the two kinds of tokens in them.
EMBEDDING_PARTS = ("self-state", "joint embedding", "its self-state token", "its visual tokens")
# The state-token model scored on (h_t, h_t+1) with h_t+1 the one the checkpoint predicts under the task's prompt
# (what it would act from), and the checkpoint's own inverse dynamics from the real h_t+1.
PREDICTED = "its self-state token, h_t+1 predicted"
OWN_INVERSE = "the checkpoint's inverse dynamics"


@torch.no_grad()
def embedding_frames(
    policy_path: str,
    repo_id: str,
    root: Path | None,
    frames_per_episode: int,
    batch_size: int = 64,
    seed: int = 0,
) -> dict:
    """Per frame t (``frames_per_episode`` per episode, as ``jept-prompt-probe`` picks them): the inputs of
    :data:`EMBEDDING_PARTS` (``parts``, each (N, F)), the self-state tokens of h_t and of the h_t+1 the
    checkpoint predicts under the task's bank prompt (``predicted``), the binned label a_t (``y``), the task, and
    the bins the checkpoint's own inverse dynamics chooses from the real next frame (``own``)."""
    from lerobot.utils.constants import ACTION, OBS_STATE

    import lerobot_policy_jept  # noqa: F401  (registers the policy types)
    from lerobot_jept.evaluation.cli_args import DatasetArg, PolicyArg
    from lerobot_jept.evaluation.prompt_probe import ProbeConfig, load_labelled, probe_frames

    probe_cfg = ProbeConfig(
        policy=PolicyArg(path=policy_path),
        dataset=DatasetArg(repo_id=repo_id, root=None if root is None else str(root / repo_id)),
    )
    policy, pre, dataset = load_labelled(probe_cfg)
    if policy.name != "jept":
        raise ValueError(
            f"{policy_path} is a {policy.name!r} policy: --features=embedding reads JEPT's joint embeddings."
        )
    names = task_names(dataset.meta) or {}
    indices = probe_frames(dataset, frames_per_episode)
    torch.manual_seed(seed)  # the preprocessor draws each dataset sample's bank prompt among its task's
    out: dict[str, list] = {name: [] for name in (*EMBEDDING_PARTS, "predicted", "y", "own", "task")}
    k = policy.config.n_obs_steps
    for start in tqdm(
        range(0, len(indices), batch_size), desc=f"{repo_id} embeddings", unit="batch", leave=False
    ):
        items = [dataset[i] for i in indices[start : start + batch_size]]
        batch = {
            key: torch.stack([it[key] for it in items]) for key in items[0] if torch.is_tensor(items[0][key])
        }
        batch["task"] = [it["task"] for it in items]
        state = batch[OBS_STATE][:, -2:].flatten(1)  # s_t, s_t+1 as recorded (the MLP standardises them)
        processed = pre(batch)
        _, obs, h_in = policy._encode_window(processed)
        prompt = policy.prompt(processed) if policy.prompt_active else None
        pred_h, logits, *_ = policy.model.predict(prompt, obs[:, :k], h_in, processed[OBS_STATE])
        h = h_in[:, -2:]  # (B, 2, N_obs, J): h_t, h_t+1; the last token of each is the self-state token
        parts = (state, h.flatten(1), h[:, :, -1].flatten(1), h[:, :, :-1].flatten(1))
        for name, part in zip(EMBEDDING_PARTS, parts, strict=True):
            out[name].append(part.float().cpu().numpy())
        out["predicted"].append(torch.cat([h[:, 0, -1], pred_h[:, -1, -1]], 1).float().cpu().numpy())
        out["y"].append(processed[ACTION][:, -1].cpu().numpy())
        out["own"].append(logits[:, -1].argmax(-1).cpu().numpy())  # offline_outputs' ``inverse``
        out["task"] += [names.get(t, t) for t in batch["task"]]
    arrays = {k: np.concatenate(v) if k != "task" else np.array(v) for k, v in out.items()}
    return {
        "parts": {name: arrays[name] for name in EMBEDDING_PARTS},
        "predicted": arrays["predicted"],
        "y": arrays["y"],
        "own": arrays["own"],
        "task": arrays["task"],
    }


def embedding_ceiling(demo: dict, probe: dict, seed: int = 0) -> dict[str, dict[str, dict]]:
    """Per input of :data:`EMBEDDING_PARTS`, the MLP inverse dynamics fitted on the demo frames and scored per
    probe task (as :func:`ceiling`); the state-token model also on the predicted h_t+1 (:data:`PREDICTED`); and
    the checkpoint's own inverse dynamics on the same probe frames."""
    fitted = {name: demo["parts"][name] for name in EMBEDDING_PARTS}
    # the state-token model: fitted on the real pairs, scored on the predicted ones
    fitted[PREDICTED] = demo["parts"]["its self-state token"]
    scored = {**probe["parts"], PREDICTED: probe["predicted"]}
    results = {
        name: ceiling(
            {"x": x, "y": demo["y"], "task": demo["task"]},
            {"x": scored[name], "y": probe["y"], "task": probe["task"]},
            seed,
        )
        for name, x in fitted.items()
    }
    results[OWN_INVERSE] = score(probe["own"], demo["y"], probe)
    return results


def embedding_markdown(results: dict[str, dict[str, dict]], demo_tasks: set[str]) -> str:
    """Rows: probe tasks; columns: whole-action accuracy (mean per-dimension accuracy) per input."""
    inputs = list(results)
    lines = [
        "| task | in demos | frames | " + " | ".join(f"{name}: whole (per dim)" for name in inputs) + " |",
        "|---|---|---:|" + "---:|" * len(inputs),
    ]
    for task, first in results[inputs[0]].items():
        cells = [
            f"{results[n][task]['whole']:.2f} ({np.mean(results[n][task]['per_dim']):.2f})" for n in inputs
        ]
        lines.append(
            f"| {task} | {'yes' if task in demo_tasks else 'no'} | {first['frames']} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def markdown(results: dict[str, dict], demo_tasks: set[str], features: str = "state") -> str:
    name = "state" if features == "state" else "pixel"
    lines = [
        f"| task | in demos | frames | whole action in demo support | {name}-IDM whole | {name}-IDM per dim |",
        "|---|---|---:|---:|---:|---|",
    ]
    for task, r in results.items():
        per_dim = " / ".join(f"{v:.2f}" for v in r["per_dim"])
        lines.append(
            f"| {task} | {'yes' if task in demo_tasks else 'no'} | {r['frames']} | {r['in_demo_support']:.2f} "
            f"| {r['whole']:.2f} | {per_dim} |"
        )
    return "\n".join(lines)


def main() -> None:
    cfg = draccus.parse(config_class=CeilingConfig)
    if not cfg.demo_repo_id or not cfg.probe_repo_id:
        raise SystemExit(
            "Pass --demo_repo_id=ORG/NAME_demo and --probe_repo_id=ORG/NAME_probe (labelled repos)."
        )
    if cfg.steps < 1:
        raise SystemExit(f"--steps must be at least 1 (the next frame), got {cfg.steps}.")
    if cfg.features not in ("state", "pixels", "embedding"):
        raise SystemExit(f"--features must be state, pixels or embedding, got {cfg.features!r}.")
    if cfg.features == "embedding":
        if not cfg.policy_path:
            raise SystemExit(
                "--features=embedding reads a checkpoint's joint embeddings: pass --policy_path=CKPT."
            )
        demo, probe = (
            embedding_frames(cfg.policy_path, repo, cfg.root, cfg.frames_per_episode, seed=cfg.seed)
            for repo in (cfg.demo_repo_id, cfg.probe_repo_id)
        )
        print(embedding_markdown(embedding_ceiling(demo, probe, cfg.seed), set(demo["task"])))
        return
    demo = load_frames(cfg.demo_repo_id, cfg.root, cfg.steps, cfg.num_bins, cfg.features)
    probe = load_frames(cfg.probe_repo_id, cfg.root, cfg.steps, cfg.num_bins, cfg.features)
    results = ceiling(demo, probe, cfg.seed, cfg.features, cfg.num_bins, cfg.epochs)
    print(markdown(results, set(demo["task"]), cfg.features))


if __name__ == "__main__":
    main()
