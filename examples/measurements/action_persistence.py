"""How long does an expert hold one binned action? The bound on smoothing inverse dynamics' labels over time.

    python -m examples.measurements.action_persistence --repo_id=ORG/NAME_probe [--windows='[1,2]']

Inverse dynamics reads a video frame's action from one state change, with errors; if the experts held an action
over several frames, a majority over neighbouring frames' readings would correct some of them. Per task of a
labelled repo (a build's `_probe` or `_demo`), this prints the share of frames whose whole binned action equals
the previous frame's, and the share a centred majority filter (per dimension, ``k`` frames each side) leaves
unchanged: applied to perfect labels, the filter can only lose the others (``jept-screen --smooth=k``
applies it to inverse dynamics' readings).
"""

from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np

from lerobot_jept.evaluation.screen import ScreenError, load_frames, majority


@dataclass
class PersistenceConfig:
    repo_id: str = ""  # a labelled repo (a build's `_probe` or `_demo`)
    root: Path | None = None  # its parent folder (default: $HF_LEROBOT_HOME)
    windows: list[int] = field(default_factory=lambda: [1, 2])  # majority filters' half-widths k
    num_bins: int = 7  # action bins per dimension over [-1, 1] (the paper's 7)


def persistence(cfg: PersistenceConfig) -> dict[str, dict[str, float]]:
    frames = load_frames(cfg.repo_id, cfg.root, steps=0, num_bins=cfg.num_bins)  # every frame's binned action
    per_task: dict[str, dict[str, list[float]]] = {}
    for ep in np.unique(frames["episode"]):
        rows = np.flatnonzero(frames["episode"] == ep)
        labels = frames["y"][rows]
        shares = per_task.setdefault(str(frames["task"][rows[0]]), {})
        shares.setdefault("repeats", []).append(float((labels[1:] == labels[:-1]).all(1).mean()))
        for k in cfg.windows:
            kept = (majority(labels, k) == labels).all(1).mean()
            shares.setdefault(f"majority k={k}", []).append(float(kept))
    return {task: {key: float(np.mean(v)) for key, v in shares.items()} for task, shares in per_task.items()}


def main() -> None:
    cfg = draccus.parse(config_class=PersistenceConfig)
    try:
        results = persistence(cfg)
    except ScreenError as err:  # an unlabelled repo: the error names it and the fix
        raise SystemExit(f"action_persistence: error: {err}") from None
    columns = list(next(iter(results.values())))
    print("| task | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for task, row in sorted(results.items()):
        print(f"| {task} | " + " | ".join(f"{row[c]:.2f}" for c in columns) + " |")


if __name__ == "__main__":
    main()
