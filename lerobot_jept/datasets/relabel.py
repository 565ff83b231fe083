"""``jept-relabel``: the BC+IDM baseline's labelling step. An ``jept_idm`` checkpoint gives every unlabelled frame of a
``_mix`` repo (``observation.action_labelled`` 0) the action bin centre it predicts from (o_t, o_{t+1}); labelled
frames keep their actions unchanged. The result is an ordinary LeRobotDataset: every frame is labelled, a
per-frame ``pseudo_label`` says where the IDM wrote the action, stats cover all frames, and ``meta/jept_relabel.json``
with the IDM checkpoint and its accuracy on held-out labelled frames. BC is then ``jept_dt_star`` trained on it.

    jept-relabel --policy.path=outputs/train/idm/checkpoints/last/pretrained_model \\
        --dataset.repo_id=ORG/NAME_mix --output_repo_id=ORG/NAME_mix_idm [--heldout_repo_id=ORG/HELDOUT_demo]
"""

import json
import logging
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
import torch
from tqdm import tqdm

from lerobot_jept.datasets.mixing import fill_episode_stats, labelled_mask, push_dataset
from lerobot_jept.envs.spec import ACTION_LABELLED
from lerobot_jept.evaluation.cli_args import DatasetArg, PolicyArg
from lerobot_jept.evaluation.suite import BUILD_FILE

RELABEL_FILE = "meta/jept_relabel.json"
PSEUDO_LABEL = "pseudo_label"


@dataclass
class RelabelConfig:
    policy: PolicyArg = field(default_factory=PolicyArg)  # the idm checkpoint
    dataset: DatasetArg = field(default_factory=DatasetArg)  # the mix to relabel
    output_repo_id: str = ""
    output_root: str | None = None  # default: $HF_LEROBOT_HOME/<output_repo_id>
    # Labelled episodes the IDM did not train on, for its accuracy. Default: the labelled episodes of the mix
    # outside the IDM run's --dataset.episodes, or (when it trained on all of them) its training frames,
    # recorded as such.
    heldout_repo_id: str | None = None
    heldout_root: str | None = None
    max_accuracy_frames: int = 2000
    batch_size: int = 64
    push_to_hub: bool = False
    private: bool = False


class RelabelError(ValueError):
    pass


def read_actions(dataset) -> np.ndarray:
    """(N, A) float32 actions of every frame in index order (unlabelled frames: see ``labelled_mask``)."""
    if "action" not in dataset.meta.features:
        raise RelabelError(
            f"{dataset.repo_id} has no `action` column, so nothing tells labelled frames from unlabelled ones: "
            "relabel a mix (the builder's ORG/NAME_mix or jept-mix's output)."
        )
    return np.stack(dataset.hf_dataset.with_format("numpy")["action"]).astype(np.float32)


def load_idm(cfg: RelabelConfig):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_jept.policies.idm.modeling_idm import IDMPolicy

    policy_cfg = PreTrainedConfig.from_pretrained(cfg.policy.path)
    if policy_cfg.type != "jept_idm":
        raise RelabelError(
            f"{cfg.policy.path} is a {policy_cfg.type!r} checkpoint; jept-relabel needs an inverse dynamics model "
            "trained with `lerobot-train --policy.type=jept_idm`."
        )
    cfg.policy.apply(policy_cfg)
    policy = IDMPolicy.from_pretrained(cfg.policy.path, config=policy_cfg).eval()
    pre, _ = make_pre_post_processors(policy_cfg, pretrained_path=cfg.policy.path)
    return policy, pre


def windows(repo_id: str, root: str | None, policy):
    """The repo with (o_t, o_{t+1}) windows of the IDM's inputs."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.utils.constants import OBS_STATE

    fps = LeRobotDatasetMetadata(repo_id, root=root).fps
    keys = [*policy.config.image_keys, OBS_STATE]
    return LeRobotDataset(repo_id, root=root, delta_timestamps={k: [0.0, 1.0 / fps] for k in keys})


@torch.no_grad()
def predict_bins(policy, pre, dataset, indices: list[int], batch_size: int, desc: str) -> np.ndarray:
    """(len(indices), A) predicted bin indices of a_t at the given frames."""
    loader = torch.utils.data.DataLoader(
        torch.utils.data.Subset(dataset, indices), batch_size=batch_size, shuffle=False
    )
    out = []
    for batch in tqdm(loader, desc=desc, unit="batch"):
        batch.pop("action", None)  # the IDM predicts it
        out.append(policy.action_logits(pre(batch)).argmax(-1).cpu().numpy())
    return np.concatenate(out) if out else np.zeros((0, policy.config.resolved_action_dim), dtype=np.int64)


def to_bins(actions: np.ndarray, config) -> np.ndarray:
    """Continuous actions -> bin indices, through the preprocessor's own ``jept_action_bins`` step."""
    from lerobot.processor import TransitionKey

    from lerobot_jept.policies.jept.processor_jept import JeptActionBinsStep

    step = JeptActionBinsStep(config.num_action_bins, *config.action_bounds())
    return step({TransitionKey.ACTION: torch.from_numpy(actions)})[TransitionKey.ACTION].numpy()


def heldout_frames(
    cfg: RelabelConfig, labelled: np.ndarray, source
) -> tuple[str, str | None, list[int], str]:
    """Where the IDM's accuracy is measured: (repo_id, root, frame indices, kind)."""
    rng = np.random.default_rng(0)

    def sample(idx: np.ndarray) -> list[int]:
        idx = np.asarray(idx)
        if len(idx) > cfg.max_accuracy_frames:
            idx = np.sort(rng.choice(idx, cfg.max_accuracy_frames, replace=False))
        return idx.tolist()

    if cfg.heldout_repo_id:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        heldout = LeRobotDataset(cfg.heldout_repo_id, root=cfg.heldout_root)
        ok = labelled_mask(heldout)
        return cfg.heldout_repo_id, cfg.heldout_root, sample(np.flatnonzero(ok)), "heldout_repo"
    train_cfg = Path(cfg.policy.path) / "train_config.json"
    trained_on = None
    if train_cfg.is_file():
        dataset_cfg = json.loads(train_cfg.read_text()).get("dataset", {})
        if dataset_cfg.get("repo_id") == cfg.dataset.repo_id:
            trained_on = dataset_cfg.get("episodes")
    episode = np.asarray(source.hf_dataset.with_format("numpy")["episode_index"]).reshape(-1)
    if trained_on:
        held = labelled & ~np.isin(episode, trained_on)
        if held.any():
            return cfg.dataset.repo_id, cfg.dataset.root, sample(np.flatnonzero(held)), "heldout_episodes"
    logging.warning(
        "jept-relabel: the IDM trained on every labelled episode of %s, so its accuracy is measured on its "
        "training frames; pass --heldout_repo_id (or train it with --dataset.episodes) for a held-out figure.",
        cfg.dataset.repo_id,
    )
    return cfg.dataset.repo_id, cfg.dataset.root, sample(np.flatnonzero(labelled)), "training_frames"


def idm_accuracy(policy, pre, cfg: RelabelConfig, labelled: np.ndarray, source) -> dict:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    repo_id, root, indices, kind = heldout_frames(cfg, labelled, source)
    truth_source = source if repo_id == cfg.dataset.repo_id else LeRobotDataset(repo_id, root=root)
    truth = to_bins(read_actions(truth_source)[indices], policy.config)
    pred = predict_bins(policy, pre, windows(repo_id, root, policy), indices, cfg.batch_size, "IDM accuracy")
    hit = pred == truth
    return {
        "frames": kind,
        "repo_id": repo_id,
        "n_frames": len(indices),
        "whole": float(hit.all(1).mean()) if len(hit) else float("nan"),
        "per_dim": hit.mean(0).tolist() if len(hit) else [],
    }


def write_actions(root: Path, actions: np.ndarray) -> None:
    """Write ``actions`` (N, A), indexed by frame ``index``, as the ``action`` column of the data files (the
    labelled rows get their own values back), mark every frame labelled and refresh the per-episode ``action``
    stats."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for path in sorted((root / "data").glob("*/*.parquet")):
        table = pq.read_table(path)
        column = table["action"]
        fixed = pa.array(list(actions[table["index"].to_numpy()]), type=column.type)
        table = table.set_column(table.schema.get_field_index("action"), table.schema.field("action"), fixed)
        if ACTION_LABELLED in table.column_names:
            flag = table[ACTION_LABELLED]
            one = (
                np.ones(1, np.float32) if pa.types.is_list(flag.type) else np.float32(1)
            )  # (1,) may be scalar
            ones = pa.array([one] * len(table), type=flag.type)
            table = table.set_column(
                table.schema.get_field_index(ACTION_LABELLED), table.schema.field(ACTION_LABELLED), ones
            )
        pq.write_table(table, path)
    fill_episode_stats(
        root, ["action", *([ACTION_LABELLED] if ACTION_LABELLED in table.column_names else [])]
    )


def relabel(cfg: RelabelConfig) -> dict:
    from lerobot.datasets.dataset_tools import add_features, recompute_stats
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.utils.constants import HF_LEROBOT_HOME

    if not (cfg.policy.path and cfg.dataset.repo_id and cfg.output_repo_id):
        raise RelabelError(
            "Pass --policy.path=IDM_CHECKPOINT, --dataset.repo_id=ORG/NAME_mix and --output_repo_id=ORG/NAME_mix_idm."
        )
    out = Path(cfg.output_root) if cfg.output_root else HF_LEROBOT_HOME / cfg.output_repo_id
    if out.exists():
        raise RelabelError(
            f"{out} already exists: choose another --output_repo_id/--output_root, or delete it to relabel again."
        )
    policy, pre = load_idm(cfg)
    source = LeRobotDataset(cfg.dataset.repo_id, root=cfg.dataset.root)
    actions = read_actions(source)
    pseudo = ~labelled_mask(source)
    accuracy = idm_accuracy(policy, pre, cfg, ~pseudo, source)
    bins = predict_bins(
        policy,
        pre,
        windows(cfg.dataset.repo_id, cfg.dataset.root, policy),
        np.flatnonzero(pseudo).tolist(),
        cfg.batch_size,
        "relabel",
    )
    new_actions = actions.copy()
    new_actions[pseudo] = (
        policy.bin_actions(torch.as_tensor(bins, device=policy.bin_centres.device)).cpu().numpy()
    )

    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    flag = {"dtype": "bool", "shape": [1], "names": None}
    add_features(source, {PSEUDO_LABEL: (pseudo, flag)}, output_dir=tmp, repo_id=cfg.output_repo_id)
    write_actions(tmp, new_actions)
    recompute_stats(LeRobotDataset(cfg.output_repo_id, root=tmp))
    record = {
        "source_repo_id": cfg.dataset.repo_id,
        "idm_checkpoint": str(cfg.policy.path),
        "pseudo_labelled_frames": int(pseudo.sum()),
        "labelled_frames": int((~pseudo).sum()),
        "idm_accuracy": accuracy,
    }
    build = Path(source.root) / BUILD_FILE
    if build.is_file():  # the split, so that jept-eval-suite runs on the relabelled repo as on the mix
        shutil.copy(build, tmp / BUILD_FILE)
    (tmp / RELABEL_FILE).write_text(json.dumps(record, indent=2))
    tmp.rename(out)
    print(
        f"Relabelled {record['pseudo_labelled_frames']} of {len(pseudo)} frames of {cfg.dataset.repo_id} into "
        f"{cfg.output_repo_id} ({out}); IDM accuracy on {accuracy['n_frames']} {accuracy['frames']}: whole "
        f"{accuracy['whole']:.3f}, per dimension {[round(a, 3) for a in accuracy['per_dim']]}"
    )
    if cfg.push_to_hub:
        push_dataset(cfg.output_repo_id, out, ["jept", "idm-relabelled"], cfg.private, RelabelError)
    return record


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    import lerobot_policy_jept  # noqa: F401  (registers the policy types)

    cfg = draccus.parse(RelabelConfig)
    try:
        relabel(cfg)
    except RelabelError as err:
        sys.exit(f"jept-relabel: {err}")
