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
from dataclasses import dataclass, field
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
    fill_episode_stats(out, list(add))
    if replaced:
        shutil.rmtree(bare, ignore_errors=True)


def fill_episode_stats(root: Path, keys: list[str]) -> None:
    """Write the per-episode stats (``stats/<key>/<stat>`` in ``meta/episodes``) of the numeric features ``keys``
    from the data files. LeRobot's ``add_features``/``modify_features`` copy the episodes metadata as it was, so
    an added feature would have none, and ``delete_episodes``/``split`` stop on the missing values."""
    import pandas as pd
    from lerobot.datasets.compute_stats import get_feature_stats

    data = pd.concat(
        [pd.read_parquet(p, columns=["index", *keys]) for p in sorted((root / "data").glob("*/*.parquet"))]
    )
    data = data.set_index("index").sort_index()
    values = {k: np.stack(data[k].to_numpy()).reshape(len(data), -1) for k in keys}
    for path in sorted((root / "meta/episodes").glob("*/*.parquet")):
        episodes = pd.read_parquet(path)
        spans = list(zip(episodes["dataset_from_index"], episodes["dataset_to_index"], strict=True))
        for key in keys:
            stats = [
                get_feature_stats(values[key][start:stop], axis=0, keepdims=False) for start, stop in spans
            ]
            for name in stats[0]:
                dtype = np.int64 if name == "count" else np.float64
                column = [np.asarray(st[name], dtype).reshape(-1) for st in stats]
                episodes[f"stats/{key}/{name}"] = pd.Series(column, dtype=object)
        episodes.to_parquet(path, index=False)


def push_dataset(repo_id: str, root: Path, tags: list[str], private: bool, error: type[Exception]) -> None:
    """LeRobot's ``push_to_hub`` of the complete repo at ``root``; a failure (network, auth) raises ``error``
    with one line saying the local repo is intact and how to push it again."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    try:
        LeRobotDataset(repo_id, root=root).push_to_hub(tags=tags, private=private)
    except Exception as err:  # whatever the Hub client raises
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise error(
            f"Pushing {repo_id} failed ({type(err).__name__}: {reason}); the repo is complete under {root}. Log in "
            "(`hf auth login`) and push it again with LeRobotDataset(repo_id, root=...).push_to_hub()."
        ) from err


def _video_codecs(info: dict) -> dict[str, tuple]:
    return {
        k: (f.get("info", {}).get("video.codec"), f.get("info", {}).get("video.pix_fmt"))
        for k, f in info["features"].items()
        if f["dtype"] == "video"
    }


def _reencode(repo_id: str, root: Path, codecs: dict[str, tuple]) -> None:
    """Re-encode a staged repo's videos (LeRobot's ``reencode_dataset``) to the first source's codec."""
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets.dataset_tools import reencode_dataset
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    codec, pix_fmt = next(iter(codecs.values()))
    encoder = RGBEncoderConfig(vcodec={"av1": "libsvtav1"}.get(codec, codec), pix_fmt=pix_fmt or "yuv420p")
    reencode_dataset(LeRobotDataset(repo_id, root=root), rgb_encoder=encoder)


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
    robot_type, names, codecs = None, None, None
    for i, (rid, root, labelled) in enumerate(
        [(r, p, True) for r, p in demos] + [(r, p, False) for r, p in videos]
    ):
        dataset = LeRobotDataset(rid, root=root)
        robot_type = robot_type or dataset.meta.robot_type
        part = staging / f"part{i}"
        add_labels(dataset, part, f"{repo_id}_part{i}", labelled, action_feature)
        # One robot type and one set of feature names for LeRobot's aggregation (the sources are recorded;
        # shapes and dtypes were checked to agree, names are labels only).
        info_path = part / "meta/info.json"
        info = json.loads(info_path.read_text())
        info["robot_type"] = robot_type
        names = names or {k: f.get("names") for k, f in info["features"].items()}
        for key, feature in info["features"].items():
            feature["names"] = names.get(key, feature.get("names"))
        info_path.write_text(json.dumps(info, indent=4))
        codecs = codecs or _video_codecs(info)
        if _video_codecs(info) != codecs:  # videos are concatenated: one codec and pixel format for all
            _reencode(f"{repo_id}_part{i}", part, codecs)
        sources.append((f"{repo_id}_part{i}", part))
    tmp = staging / "mix"
    aggregate_datasets(
        repo_ids=[r for r, _ in sources], aggr_repo_id=repo_id, roots=[p for _, p in sources], aggr_root=tmp
    )
    stats = load_stats(tmp)
    stats["action"] = labelled_action_stats(tmp)
    write_stats(stats, tmp)
    return tmp


# jept-mix ----------------------------------------------------------------------------------------------------

BOOKKEEPING = {"timestamp", "frame_index", "episode_index", "index", "task_index"}


@dataclass
class MixConfig:
    """``jept-mix``: a training mix from any LeRobotDatasets (local roots or Hub repo ids).

    demo_repo_ids: labelled repos (``lerobot-record``, ported, or a builder's ``_demo``).
    video_repo_ids: action-free repos (a builder's ``_video``, videos written through LeRobot's API, ...).
    ignore_video_actions: a video repo that has an ``action`` column is refused unless this is true (its actions
        are then treated as absent).
    """

    demo_repo_ids: list[str] = field(default_factory=list)
    video_repo_ids: list[str] = field(default_factory=list)
    output_repo_id: str = ""
    demo_roots: list[str] | None = None
    video_roots: list[str] | None = None
    output_root: str | None = None  # default: $HF_LEROBOT_HOME/<output_repo_id>
    ignore_video_actions: bool = False
    push_to_hub: bool = False
    private: bool = False


class MixError(ValueError):
    pass


def _describe(feature: dict) -> str:
    return f"{feature['dtype']} {tuple(feature['shape'])}"


def check_compatible(demos: list, videos: list, ignore_video_actions: bool) -> None:
    """Raise :class:`MixError` naming every difference between the repos' metadata that would stop the mix,
    with how to fix it. ``demos`` / ``videos``: LeRobotDatasetMetadata."""
    problems = []
    first = (demos or videos)[0]
    for meta in videos:
        if "action" in meta.features and not ignore_video_actions:
            problems.append(
                f"{meta.repo_id} is given as video but has an `action` column: pass --ignore_video_actions=true "
                "to treat its frames as action-free, or list it in --demo_repo_ids."
            )
    for meta in demos:
        if "action" not in meta.features:
            problems.append(
                f"{meta.repo_id} is given as a demo repo but has no `action` column: list it in --video_repo_ids."
            )
    ignore = BOOKKEEPING | {"action", ACTION_LABELLED}
    reference = {k: v for k, v in first.features.items() if k not in ignore}
    for meta in [*demos, *videos][1:]:
        if meta.fps != first.fps:
            problems.append(
                f"{meta.repo_id} runs at {meta.fps} fps, {first.repo_id} at {first.fps}: record or port them at one "
                "frame rate (jept-mix does not resample)."
            )
        mine = {k: v for k, v in meta.features.items() if k not in ignore}
        for key in sorted(set(reference) | set(mine)):
            if key not in mine or key not in reference:
                has, lacks = (first, meta) if key in reference else (meta, first)
                problems.append(
                    f"{has.repo_id} has `{key}` but {lacks.repo_id} has not: rename the camera or state key in one "
                    "of them to match (`lerobot-edit-dataset` cannot rename; port it with the same key), or drop "
                    f"it with `lerobot-edit-dataset --repo_id={has.repo_id} --operation.type=remove_feature "
                    f"--operation.feature_names='[{key}]'`."
                )
            elif (
                tuple(mine[key]["shape"]) != tuple(reference[key]["shape"])
                or mine[key]["dtype"] != reference[key]["dtype"]
            ):
                what = (
                    "record or resize them to one image size"
                    if mine[key]["dtype"] in ("video", "image")
                    else ("they must describe the same robot state")
                )
                problems.append(
                    f"`{key}` is {_describe(reference[key])} in {first.repo_id} but {_describe(mine[key])} in "
                    f"{meta.repo_id}: {what}."
                )
    actions = {tuple(m.features["action"]["shape"]) for m in demos if "action" in m.features}
    if len(actions) > 1:
        problems.append(
            f"The demo repos' actions have different shapes {sorted(actions)}: mix repos of one robot."
        )
    if problems:
        raise MixError("The repos cannot be mixed:\n- " + "\n- ".join(problems))


def _builds(metas: list) -> list[dict]:
    """The builders' metadata (meta/jept_build.json) of the repos that have it."""
    paths = [Path(m.root) / "meta/jept_build.json" for m in metas]
    return [json.loads(p.read_text()) for p in paths if p.is_file()]


def run_mix(cfg: MixConfig) -> Path:
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.utils.constants import HF_LEROBOT_HOME

    if not cfg.output_repo_id or not (cfg.demo_repo_ids or cfg.video_repo_ids):
        raise MixError(
            "Pass --demo_repo_ids='[...]', --video_repo_ids='[...]' and --output_repo_id=ORG/NAME_mix."
        )
    if not cfg.demo_repo_ids:
        raise MixError("A mix needs at least one labelled repo in --demo_repo_ids.")

    def metas(ids, roots):
        roots = roots or [None] * len(ids)
        if len(roots) != len(ids):
            raise MixError("Give one root per repo id (or none).")
        return [LeRobotDatasetMetadata(r, root=root) for r, root in zip(ids, roots, strict=True)]

    demos, videos = metas(cfg.demo_repo_ids, cfg.demo_roots), metas(cfg.video_repo_ids, cfg.video_roots)
    check_compatible(demos, videos, cfg.ignore_video_actions)
    out = Path(cfg.output_root) if cfg.output_root else HF_LEROBOT_HOME / cfg.output_repo_id
    if out.exists():
        raise MixError(f"{out} already exists: choose another --output_repo_id/--output_root, or delete it.")
    staging = out.with_name(out.name + ".staging")
    action = demos[0].features["action"]
    done = mix(
        [(m.repo_id, Path(m.root)) for m in demos],
        [(m.repo_id, Path(m.root)) for m in videos],
        cfg.output_repo_id,
        staging,
        action,
    )
    builds = _builds([*demos, *videos])
    # task strings -> the builders' task names, where a builder described the task (any source's build)
    names = {d: t for b in builds for t, d in b.get("task_descriptions", {}).items()}
    record = {
        "repo_id": cfg.output_repo_id,
        "split": {
            "demo": sorted({names.get(s, s) for m in demos for s in m.tasks.index}),
            "video": sorted({names.get(s, s) for m in videos for s in m.tasks.index}),
            "unseen": [],
        },
        "task_descriptions": {names.get(s, s): s for m in [*demos, *videos] for s in m.tasks.index},
        "repos": {"mix": cfg.output_repo_id},
        "sources": {
            "demo": [{"repo_id": m.repo_id, "robot_type": m.robot_type} for m in demos],
            "video": [{"repo_id": m.repo_id, "robot_type": m.robot_type} for m in videos],
        },
        "mix_format": MIX_FORMAT,
    }
    if builds and builds[0].get("protocol"):
        record["protocol"] = builds[0]["protocol"]
    (done / "meta/jept_build.json").write_text(json.dumps(record, indent=2))
    done.rename(out)
    shutil.rmtree(staging, ignore_errors=True)
    print(
        f"Wrote {cfg.output_repo_id} ({out}): demo tasks {record['split']['demo']}, video tasks {record['split']['video']}."
    )
    if cfg.push_to_hub:
        push_dataset(cfg.output_repo_id, out, ["jept", "mix"], cfg.private, MixError)
    return out


def main() -> None:
    import logging
    import sys

    import draccus

    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(MixConfig)
    try:
        run_mix(cfg)
    except MixError as err:
        sys.exit(f"jept-mix: {err}")
