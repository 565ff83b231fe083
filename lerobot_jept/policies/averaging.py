"""``jept-average-checkpoints``: one checkpoint whose weights are the uniform mean of several checkpoints of the
same run (stochastic weight averaging over saved checkpoints).

    jept-average-checkpoints \\
        --paths='[outputs/train/x/checkpoints/002000/pretrained_model, .../002500/pretrained_model, .../003000/pretrained_model]' \\
        --output_dir=outputs/train/x/average_2000-3000

The output is a ``pretrained_model`` folder like LeRobot's: every file of the last path (config, processors,
train config) with ``model.safetensors`` replaced by the mean of the paths' floating-point tensors; integer
tensors (step counters) are the last path's. It loads with ``--policy.path=`` anywhere a checkpoint does.
"""

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import draccus

WEIGHTS = "model.safetensors"


@dataclass
class AverageConfig:
    paths: list[Path] = field(
        default_factory=list
    )  # pretrained_model folders of one run, the last one's files kept
    output_dir: Path | None = None


class AverageError(ValueError):
    pass


def average_checkpoints(paths: list[Path], output_dir: Path) -> Path:
    """Write the mean of ``paths``' weights, with the last path's other files, to ``output_dir``."""
    from safetensors.torch import load_file, save_file

    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise AverageError(f"--paths needs at least two checkpoints to average, got {len(paths)}.")
    missing = [str(p) for p in paths if not (p / WEIGHTS).is_file()]
    if missing:
        raise AverageError(
            f"No {WEIGHTS} in {missing}: pass the checkpoints' pretrained_model folders "
            "(outputs/train/<run>/checkpoints/<step>/pretrained_model)."
        )
    if Path(output_dir).resolve() in {p.resolve() for p in paths}:
        raise AverageError(f"--output_dir={output_dir} is one of the checkpoints: give a new folder.")
    states = [load_file(p / WEIGHTS) for p in paths]
    keys = set(states[-1])
    for path, state in zip(paths, states, strict=True):
        if set(state) != keys or any(state[k].shape != states[-1][k].shape for k in keys):
            raise AverageError(
                f"{path} does not hold the same tensors as {paths[-1]}: average checkpoints of one run only."
            )
    mean = {}
    for key, last in states[-1].items():
        if last.is_floating_point():
            mean[key] = sum(state[key].double() for state in states).div(len(states)).to(last.dtype)
        else:
            mean[key] = last
    output_dir = Path(output_dir)
    shutil.copytree(paths[-1], output_dir, dirs_exist_ok=True, ignore=shutil.ignore_patterns(WEIGHTS))
    save_file({k: v.contiguous() for k, v in mean.items()}, str(output_dir / WEIGHTS))
    return output_dir


def main() -> None:
    logging.basicConfig(level=logging.INFO)
    cfg = draccus.parse(AverageConfig)
    if cfg.output_dir is None:
        raise SystemExit(
            "jept-average-checkpoints: error: give --output_dir, the folder the average is written to."
        )
    try:
        out = average_checkpoints(cfg.paths, cfg.output_dir)
    except AverageError as err:
        raise SystemExit(f"jept-average-checkpoints: error: {err}") from None
    print(f"Averaged {len(cfg.paths)} checkpoints into {out}")


if __name__ == "__main__":
    main()
