"""Training mixes of labelled and action-free episodes in one LeRobotDataset, written so that LeRobot's own
dataset tools (``lerobot-edit-dataset``: delete_episodes, split, merge, remove_feature, recompute_stats) keep
them whole.

Representation of "no action on this frame": every frame has a finite ``action`` (0 in every dimension where
there is none, a neutral value that any tool can copy, merge and average) and a per-frame
``observation.action_labelled`` (float 1.0 / 0.0). The ``observation.`` prefix makes LeRobot load it over the
same window of frames as the other observations, so the policy's preprocessor (``jept_action_bins``) knows, frame
by frame, which actions are real; it then drops the key, which is never a model input. NaN is not used: LeRobot's
writer turns NaN inside list cells into nulls on merge, and per-episode stats of NaN actions are null.

``mix`` is what the builders' ``_mix`` and ``jept-mix`` both run.
"""

import json
import shutil
from pathlib import Path

import numpy as np

from lerobot_jept.envs.spec import ACTION_LABELLED, action_labelled_feature

MIX_FORMAT = 2  # 1: NaN actions on video frames (read for compatibility); 2: neutral action + ACTION_LABELLED


def labelled_mask(dataset) -> np.ndarray:
    """(N,) bool: which frames of a LeRobotDataset carry a real action (all False without an action column)."""
    table = dataset.hf_dataset.with_format("numpy")
    if "action" not in dataset.meta.features:
        return np.zeros(len(table), dtype=bool)
    if ACTION_LABELLED in dataset.meta.features:
        return np.asarray(table[ACTION_LABELLED]).reshape(-1) > 0.5
    return np.isfinite(np.stack(table["action"])).all(1)  # format 1: NaN-marked


def add_labels(dataset, out: Path, repo_id: str, labelled: bool, action_feature: dict | None = None) -> None:
    """Copy ``dataset`` to ``out`` with ``ACTION_LABELLED`` (all 1 or all 0); an unlabelled copy gets the
    neutral ``action`` (0), replacing any action it had (``action_feature`` gives its shape when it has none)."""
    from lerobot.datasets.dataset_tools import modify_features, remove_feature

    n = dataset.meta.total_frames
    add = {ACTION_LABELLED: (np.full((n, 1), float(labelled), np.float32), action_labelled_feature())}
    if not labelled:
        feature = dataset.meta.features.get("action", action_feature)
        add["action"] = (np.zeros((n, *feature["shape"]), np.float32), dict(feature))
    shutil.rmtree(out, ignore_errors=True)
    replaced = [k for k in add if k in dataset.meta.features]
    if replaced:  # LeRobot adds only new names: drop the old columns first
        bare = out.with_name(out.name + ".bare")
        shutil.rmtree(bare, ignore_errors=True)
        dataset = remove_feature(dataset, replaced, output_dir=bare, repo_id=repo_id)
    modify_features(dataset, add_features=add, output_dir=out, repo_id=repo_id)
    if replaced:
        shutil.rmtree(bare, ignore_errors=True)


def labelled_action_stats(root: Path) -> dict:
    """LeRobot stats of ``action`` over the labelled frames of the repo at ``root``."""
    import pandas as pd
    from lerobot.datasets.compute_stats import get_feature_stats

    frames = [
        pd.read_parquet(p, columns=["action", ACTION_LABELLED])
        for p in sorted((root / "data").glob("*/*.parquet"))
    ]
    actions = np.concatenate([np.stack(f["action"].to_numpy()) for f in frames])
    labelled = np.concatenate([np.stack(f[ACTION_LABELLED].to_numpy()).reshape(-1) for f in frames]) > 0.5
    if not labelled.any():
        raise ValueError(f"{root} has no labelled action: a mix needs at least one labelled (demo) repo.")
    return get_feature_stats(actions[labelled], axis=0, keepdims=False)


def mix(
    demos: list[tuple[str, Path]],
    videos: list[tuple[str, Path]],
    repo_id: str,
    staging: Path,
    action_feature: dict | None = None,
) -> Path:
    """The mix of labelled repos ``demos`` and action-free repos ``videos`` (``(repo_id, root)`` each), written
    under ``staging``; returns its folder, for the caller to move into place. Labelled frames keep their actions;
    video frames get the neutral action; the action stats come from the labelled frames. The caller checks that
    the features agree."""
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.io_utils import load_stats, write_stats
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    shutil.rmtree(staging, ignore_errors=True)
    sources = []
    robot_type = None
    for i, (rid, root, labelled) in enumerate(
        [(r, p, True) for r, p in demos] + [(r, p, False) for r, p in videos]
    ):
        dataset = LeRobotDataset(rid, root=root)
        robot_type = robot_type or dataset.meta.robot_type
        part = staging / f"part{i}"
        add_labels(dataset, part, f"{repo_id}_part{i}", labelled, action_feature)
        info_path = part / "meta/info.json"  # one robot type for LeRobot's aggregation (sources are recorded)
        info = json.loads(info_path.read_text())
        info["robot_type"] = robot_type
        info_path.write_text(json.dumps(info, indent=4))
        sources.append((f"{repo_id}_part{i}", part))
    tmp = staging / "mix"
    aggregate_datasets(
        repo_ids=[r for r, _ in sources], aggr_repo_id=repo_id, roots=[p for _, p in sources], aggr_root=tmp
    )
    stats = load_stats(tmp)
    stats["action"] = labelled_action_stats(tmp)
    write_stats(stats, tmp)
    return tmp
