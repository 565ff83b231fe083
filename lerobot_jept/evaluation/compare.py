"""``jept-compare``: several methods' ``jept-eval-suite`` outputs as the paper's Table 1 (Meta-World) or Table 3
(robosuite): one column per method, the mean over training seeds with a 95% interval, the paper's numbers beside
them when the split is the paper's, a grouped bar chart with error bars.

    jept-compare --runs='{JEPT: [outputs/suite/jept_s1000, outputs/suite/jept_s2000], DT*: [outputs/suite/dt_s1000]}' \\
        --output_dir=outputs/compare

Intervals: with two or more seeds, Student's t interval of the per-seed values (seeds are the unit of
replication: training is the noisiest part); with one seed, a percentile bootstrap over that run's evaluation
episodes (resampled within each task), which covers evaluation noise only and is marked so. Intervals are clipped
to [0, 100].
"""

import json
import logging
import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np

from lerobot_jept.evaluation.paper import PAPER_SPLIT, PAPER_TABLE1_ALL, PAPER_TABLE3, TABLE3_ROWS
from lerobot_jept.evaluation.stats import t_interval
from lerobot_jept.evaluation.suite import SCENE_MATE_ROW, summarise


@dataclass
class CompareConfig:
    # method name -> jept-eval-suite output folders, one per training seed
    runs: dict[str, list[str]] = field(default_factory=dict)
    output_dir: Path = Path("outputs/compare")
    confidence: float = 0.95
    bootstrap_samples: int = 2000


class CompareError(ValueError):
    pass


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


def paper_columns(simulator: str, split: dict) -> tuple[dict[str, dict[str, float]], str] | None:
    """The paper's table for this split (Table 1 for the Table 7 split, Table 3 for the default robosuite one)."""
    from dataset_builders.robosuite import DEFAULT_DEMO_TASKS, DEFAULT_UNSEEN_TASKS, DEFAULT_VIDEO_TASKS

    def same(a: dict, b: dict) -> bool:
        return {k: sorted(v) for k, v in a.items()} == {k: sorted(v) for k, v in b.items()}

    if simulator == "metaworld" and same(split, PAPER_SPLIT):
        return PAPER_TABLE1_ALL, "Table 1"
    default = {"demo": DEFAULT_DEMO_TASKS, "video": DEFAULT_VIDEO_TASKS, "unseen": DEFAULT_UNSEEN_TASKS}
    if simulator == "robosuite" and same(split, default):
        table = {m: dict(zip(TABLE3_ROWS, v, strict=True)) for m, v in PAPER_TABLE3.items()}
        return table, "Table 3 (its own T_demo/T_vid tasks)"
    return None


def load_run(folder: str) -> dict:
    path = Path(folder) / "results.json"
    if not path.is_file():
        raise CompareError(f"{path} does not exist: pass folders written by jept-eval-suite --output_dir=...")
    results = json.loads(path.read_text())
    missing = [t for t, r in results["per_task"].items() if "successes" not in r]
    if missing or "simulator" not in results:
        raise CompareError(
            f"{path} has no per-episode outcomes (written by an older jept-eval-suite): "
            "re-run jept-eval-suite on that checkpoint."
        )
    return results


def column_name(method: str, results: list[dict]) -> str:
    """The method's column: its name, with the recipe its JEPT checkpoints were trained with ("JEPT (plus)")
    unless the name already says it."""
    recipes = {r.get("recipe") for r in results} - {None}
    if len(recipes) != 1 or next(iter(recipes)) in method.lower():
        return method
    return f"{method} ({recipes.pop()})"


def bootstrap_interval(run: dict, row: str, confidence: float, samples: int) -> tuple[float, float]:
    """Percentile interval of a table row over resampled episodes (within each task) of one run."""
    rng = np.random.default_rng(0)
    if row == SCENE_MATE_ROW:  # the video-only tasks under their scene-mates' prompts: the mean over them
        outcomes = {
            t: np.asarray(r["scene_mate"]["successes"], float)
            for t, r in run["per_task"].items()
            if "scene_mate" in r
        }
        table = lambda success: sum(success.values()) / len(success)  # noqa: E731
    else:
        outcomes = {t: np.asarray(r["successes"], dtype=float) for t, r in run["per_task"].items()}
        table = lambda success: summarise(run["split"], success)[row]  # noqa: E731
    values = []
    for _ in range(samples):
        success = {t: 100.0 * o[rng.integers(len(o), size=len(o))].mean() for t, o in outcomes.items()}
        values.append(table(success))
    return tuple(float(q) for q in np.quantile(values, [0.5 - confidence / 2, 0.5 + confidence / 2]))


def compare(cfg: CompareConfig) -> dict:
    if not cfg.runs or not all(cfg.runs.values()):
        raise CompareError(
            "Pass --runs='{METHOD: [SUITE_DIR, ...], ...}' with at least one folder per method."
        )
    runs = {method: [load_run(f) for f in folders] for method, folders in cfg.runs.items()}
    first = next(iter(runs.values()))[0]
    split = first["split"]
    for method, results in runs.items():
        for folder, r in zip(cfg.runs[method], results, strict=True):
            if r["split"] != split:
                raise CompareError(
                    f"{folder} was evaluated on another split than {cfg.runs[next(iter(runs))][0]}: compare "
                    "runs of the same mix (the suite reads the split from it)."
                )
    simulator = first["simulator"]
    rows = list(dict.fromkeys(row for results in runs.values() for r in results for row in r["table"]))
    runs = {column_name(method, results): results for method, results in runs.items()}
    table = {}
    for method, results in runs.items():
        table[method] = {}
        for row in rows:
            values = [float(r["table"][row]) for r in results if row in r["table"]]
            if not values:  # a row this method's suites did not evaluate (e.g. the scene-mate's prompt)
                nan = math.nan
                table[method][row] = {
                    "mean": nan,
                    "low": nan,
                    "high": nan,
                    "seeds": [],
                    "interval": "not run",
                }
                continue
            if len(values) >= 2:
                low, high = t_interval(values, cfg.confidence)
                kind = "t over seeds"
            else:
                low, high = bootstrap_interval(results[0], row, cfg.confidence, cfg.bootstrap_samples)
                kind = "bootstrap over episodes (1 seed)"
            table[method][row] = {
                "mean": float(np.mean(values)),
                "low": max(low, 0.0),  # a success rate lies in [0, 100]
                "high": min(high, 100.0),
                "seeds": values,
                "interval": kind,
            }
    paper = paper_columns(simulator, split)
    paper_table, paper_name = paper if paper else ({}, None)
    paper_match = {m: p for m in runs for p in paper_table if _key(p) == _key(m.split(" (")[0])}
    comparison = {
        "simulator": simulator,
        "split": split,
        "confidence": cfg.confidence,
        "runs": cfg.runs,
        "table": table,
        "paper": {m: paper_table[p] for m, p in paper_match.items()} if paper else None,
        "paper_source": paper_name,
    }
    out = Path(cfg.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "comparison.json").write_text(json.dumps(comparison, indent=2))
    text = markdown(comparison, rows)
    (out / "comparison.md").write_text(text)
    bar_chart(comparison, rows, out / "comparison.png")
    print(text)
    print(f"Wrote {out / 'comparison.json'}, {out / 'comparison.md'}, {out / 'comparison.png'}")
    return comparison


def markdown(comparison: dict, rows: list[str]) -> str:
    table, paper = comparison["table"], comparison["paper"] or {}
    level = round(100 * comparison["confidence"])
    columns = [(m, None) for m in table] + [(m, "paper") for m in paper]
    header = "| Task | " + " | ".join(m if src is None else f"{m} (paper)" for m, src in columns) + " |"
    lines = [header, "|---|" + "---:|" * len(columns)]
    for row in rows:
        cells = []
        for method, src in columns:
            if src == "paper":
                cells.append(f"{paper[method][row]:.1f}" if row in paper[method] else "-")
            else:
                c = table[method][row]
                cells.append(
                    "-" if c["mean"] != c["mean"] else f"{c['mean']:.1f} [{c['low']:.1f}, {c['high']:.1f}]"
                )
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    seeds = ", ".join(f"{m}: {len(next(iter(c.values()))['seeds'])}" for m, c in table.items())
    lines += [
        "",
        f"Success %, mean over training seeds [{level}% interval] (seeds per method: {seeds}). "
        "Intervals: Student's t over seeds; with one seed, a bootstrap over its evaluation episodes.",
    ]
    if comparison["paper_source"]:
        lines.append(f"Paper columns: {comparison['paper_source']}.")
    return "\n".join(lines) + "\n"


def bar_chart(comparison: dict, rows: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = comparison["table"]
    methods = list(table)
    width = 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(1.3 * len(rows) + 2, 4.5))
    for i, method in enumerate(methods):
        xs = [r + (i - (len(methods) - 1) / 2) * width for r in range(len(rows))]
        means = [table[method][row]["mean"] for row in rows]
        errors = [
            [m - table[method][row]["low"] for m, row in zip(means, rows, strict=True)],
            [table[method][row]["high"] - m for m, row in zip(means, rows, strict=True)],
        ]
        ax.bar(xs, means, width, yerr=np.clip(errors, 0, None), capsize=2, label=method)
    ax.set_xticks(range(len(rows)), rows, rotation=30, ha="right")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.set_title(
        f"{comparison['simulator']}: mean over seeds, {round(100 * comparison['confidence'])}% interval"
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    logging.basicConfig(level=logging.WARNING)
    cfg = draccus.parse(CompareConfig)
    try:
        compare(cfg)
    except CompareError as err:
        sys.exit(f"jept-compare: {err}")
