"""The plan: every step of a study with its command (or function) and the marker that says it is done."""

import json
import re
import shlex
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lerobot_jept.study.config import (
    MethodSpec,
    SplitSpec,
    StudyConfig,
    StudyError,
    method_steps,
    output_dir,
    source_of,
)


@dataclass
class Step:
    key: str  # unique, also the marker's name
    what: str  # shown on the progress bar
    folder: Path  # outputs and log
    command: list[str] | None = None
    function: Callable[[], dict] | None = None
    prepare: Callable[[], list[str] | None] | None = None  # before running: may replace the command (resume)
    always: bool = False  # re-run every time (cheap summaries)

    # The run (split, method, seed) whose steps this one follows, when its key does not name it (an evaluation of
    # another method's checkpoints)
    run: tuple[str, ...] | None = None
    signature: list[str] | None = None  # what the marker must record (default: the command)
    # A marker that records more than the signature after it still counts (figures drawn with a baseline beside)
    prefix: bool = False

    @property
    def marker(self) -> Path:
        return self.folder / f"{self.key.split('/')[-1]}.done.json"

    @property
    def planned(self) -> list[str]:
        return self.signature or self.command or []

    def done(self) -> bool:
        """Finished by an earlier run of the same study; a marker of another command is an error (the output
        folder holds another study's runs), never silently reused or overwritten."""
        if self.always or not self.marker.is_file():
            return False
        recorded = json.loads(self.marker.read_text()).get("planned")
        if recorded != self.planned and not (
            self.prefix and (recorded or [])[: len(self.planned)] == self.planned
        ):
            raise StudyError(
                f"{self.marker} was written for another command:\n  {shlex.join(recorded or [])}\nnow:\n  "
                f"{shlex.join(self.planned)}\nThe study file changed since that run: pass another --output_dir, "
                f"or delete {self.folder} to redo it."
            )
        return True


def lerobot_home() -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME)


def bin_path(name: str) -> str:
    return str(Path(sys.prefix) / "bin" / name)


def labelled_repo(cfg: StudyConfig, split: SplitSpec) -> str:
    """Every labelled frame of the split's build: ``_demo``, plus ``_play`` when it has play episodes (mixed by
    the split's ``labelled`` step)."""
    return f"{split.repo_id}_labelled" if cfg.build.play_episodes_per_task else f"{split.repo_id}_demo"


def slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def build_command(cfg: StudyConfig, split: SplitSpec) -> list[str]:
    b = cfg.build
    return [
        bin_path(f"jept-build-{cfg.simulator}"),
        f"--repo_id={split.repo_id}",
        f"--demo_tasks=[{', '.join(split.demo_tasks)}]",
        f"--video_tasks=[{', '.join(split.video_tasks)}]",
        f"--unseen_tasks=[{', '.join(split.unseen_tasks)}]",
        f"--episodes_per_task={b.episodes_per_task}",
        f"--prompts_per_task={b.prompts_per_task}",
        f"--probe_episodes_per_task={b.probe_episodes_per_task}",
        *([f"--play_episodes_per_task={b.play_episodes_per_task}"] if b.play_episodes_per_task else []),
        f"--image_size={b.image_size}",
        f"--seed={b.seed}",
        f"--num_workers={b.num_workers}",
        *b.args,
    ]


def train_step(
    cfg: StudyConfig,
    key: str,
    folder: Path,
    config: str,
    data: list[str],
    seed: int,
    extra: list[str],
    prompts: str | None,
    steps: int,
    start: Path | None = None,
) -> Step:
    """``lerobot-train`` into ``folder/train``; resumes from its last checkpoint after a kill. With ``start`` (a
    checkpoint's ``pretrained_model`` of another run), the run begins as LeRobot's resume of that checkpoint, in
    its own folder, with its training config and ``extra`` on top."""
    out = folder / "train"
    common = [f"--steps={steps}", f"--save_freq={min(cfg.save_freq, steps)}", f"--output_dir={out}"]
    if start is not None:
        command = [bin_path("lerobot-train"), f"--config_path={start / 'train_config.json'}", "--resume=true"]
        command += [*common, *extra]
    else:
        command = [
            bin_path("lerobot-train"),
            f"--config_path={config}",
            *data,
            *([f"--policy.prompt_repo_id={prompts}"] if prompts else []),
            f"--seed={seed}",
            *common,
            f"--policy.device={cfg.device}",
            *cfg.train_args,
            *extra,
        ]

    def prepare() -> list[str] | None:
        last = out / "checkpoints/last/pretrained_model/train_config.json"
        if last.is_file():  # killed after a checkpoint: LeRobot's own resume, from the numbered checkpoint
            # `last` points at (so the log says which step the run resumed from: training_curves)
            resolved = out / "checkpoints" / (out / "checkpoints/last").resolve().name
            config = resolved / "pretrained_model/train_config.json"
            return [bin_path("lerobot-train"), f"--config_path={config}", "--resume=true"]
        shutil.rmtree(out, ignore_errors=True)  # killed before any checkpoint: start clean
        return None

    return Step(key, key, folder, command, prepare=prepare)


def checkpoint(folder: Path, step: int | None = None, total_steps: int = 0) -> Path:
    """A run's checkpoint: its last, or the one LeRobot saved at ``step`` of ``total_steps``."""
    if step is None:
        return folder / "train/checkpoints/last/pretrained_model"
    from lerobot.common.train_utils import get_step_identifier

    return folder / "train/checkpoints" / get_step_identifier(step, total_steps) / "pretrained_model"


def run_folder(out: Path, split: SplitSpec, method: MethodSpec, seed: int) -> Path:
    return out / slug(split.name) / slug(method.name) / f"seed{seed}"


def plan(cfg: StudyConfig) -> list[Step]:
    """Every split's data first, then the runs of every split (one pool: with ``parallel`` runs at once, no split
    waits for another's last run), then each split's figures and comparison."""
    return [
        *(step for split in cfg.splits for step in data_steps(cfg, split)),
        *(step for split in cfg.splits for step in run_steps(cfg, split)),
        *(step for split in cfg.splits for step in summary_steps(cfg, split)),
    ]


def data_steps(cfg: StudyConfig, split: SplitSpec) -> list[Step]:
    """The split's build, its labelled frames (with play episodes) and its random floor."""
    split_dir = output_dir(cfg) / slug(split.name)
    steps = [Step(f"{split.name}/build", f"build {split.repo_id}", split_dir, build_command(cfg, split))]
    if cfg.build.play_episodes_per_task:
        steps.append(
            Step(
                f"{split.name}/labelled",
                f"labelled frames {split.repo_id}",
                split_dir,
                [
                    bin_path("jept-mix"),
                    f"--demo_repo_ids=[{split.repo_id}_demo, {split.repo_id}_play]",
                    f"--output_repo_id={labelled_repo(cfg, split)}",
                ],
                prepare=lambda split=split: shutil.rmtree(
                    lerobot_home() / labelled_repo(cfg, split), ignore_errors=True
                ),
            )
        )
    if cfg.random_episodes > 0:
        steps.append(
            Step(
                f"{split.name}/random_floor",
                f"random floor {split.name}",
                split_dir,
                function=lambda split=split: random_floor(cfg, split),
                signature=[
                    "random_floor",
                    f"episodes={cfg.random_episodes}",
                    f"seed={cfg.eval_seed}",
                    f"length={cfg.eval_episode_length}",
                ],
            )
        )
    return steps


def run_steps(cfg: StudyConfig, split: SplitSpec) -> list[Step]:
    """Per seed and method: training (BC+IDM: inverse dynamics, relabelling, behaviour cloning) and evaluation."""
    out = output_dir(cfg)
    steps = []
    for seed in cfg.seeds:  # seed by seed: a study cut short still compares every method
        for method in cfg.methods:
            folder = run_folder(out, split, method, seed)
            key = f"{split.name}/{method.name}/seed{seed}"
            prompts = f"{split.repo_id}_prompts"
            run, start, evaluated = None, None, checkpoint(folder)
            steps_of = method_steps(cfg, method)
            source = source_of(cfg, method)
            if source is not None:  # after the other method's own steps
                run = (split.name, source.name, f"seed{seed}")
                if method.checkpoints_of:  # its checkpoints
                    evaluated = checkpoint(
                        run_folder(out, split, source, seed), method.checkpoint, method_steps(cfg, source)
                    )
                else:  # trained on from its last checkpoint
                    start = checkpoint(run_folder(out, split, source, seed))
            if method.kind == "bc_idm" and source is None:
                idm = folder / "idm"
                demo = [f"--dataset.repo_id={labelled_repo(cfg, split)}"]
                idm_args = (method.idm_config, demo, seed, method.idm_args, None, steps_of)
                steps.append(train_step(cfg, f"{key}/idm", idm, *idm_args))
                relabelled = f"{split.repo_id}_mix_idm"
                relabel_root = folder / "relabelled"
                steps.append(
                    Step(
                        f"{key}/relabel",
                        f"{key}/relabel",
                        folder,
                        [
                            bin_path("jept-relabel"),
                            f"--policy.path={checkpoint(idm)}",
                            f"--dataset.repo_id={split.repo_id}_mix",
                            f"--output_repo_id={relabelled}",
                            f"--output_root={relabel_root}",
                            f"--heldout_repo_id={split.repo_id}_probe",
                        ],
                        prepare=lambda root=relabel_root: shutil.rmtree(root, ignore_errors=True),
                    )
                )
                data = [f"--dataset.repo_id={relabelled}", f"--dataset.root={relabel_root}"]
            elif method.data == "labelled":
                data = [f"--dataset.repo_id={labelled_repo(cfg, split)}"]
            else:
                data = [f"--dataset.repo_id={split.repo_id}_{method.data}"]
            if not method.checkpoints_of:
                train = train_step(
                    cfg,
                    f"{key}/train",
                    folder,
                    method.config,
                    data,
                    seed,
                    method.args,
                    prompts,
                    steps_of,
                    start,
                )
                train.run = run
                steps.append(train)
            episodes = method.eval_episodes or cfg.eval_episodes
            suite = [
                bin_path("jept-eval-suite"),
                f"--policy.path={evaluated}",
                f"--policy.device={cfg.device}",
                f"--dataset.repo_id={split.repo_id}_mix",
                f"--n_episodes={episodes}",
                f"--batch_size={min(cfg.eval_batch_size, episodes)}",
                f"--seed={cfg.eval_seed}",
                f"--output_dir={folder / 'suite'}",
            ]
            if cfg.eval_episode_length:
                suite.append(f"--episode_length={cfg.eval_episode_length}")
            suite += [*cfg.suite_args, *method.suite_args]
            steps.append(Step(f"{key}/suite", f"{key}/eval", folder, suite, run=run))
    return steps


def summary_steps(cfg: StudyConfig, split: SplitSpec) -> list[Step]:
    """The split's figures and its comparison of every method over the seeds."""
    out = output_dir(cfg)
    split_dir = out / slug(split.name)
    steps = visualize_steps(cfg, split, split_dir)
    runs = {m.name: [run_folder(out, split, m, s) / "suite" for s in cfg.seeds] for m in cfg.methods}
    if cfg.report_only:  # the runs that have evaluated
        runs = {
            name: [f for f in folders if (f / "results.json").is_file()] for name, folders in runs.items()
        }
    runs = {name: [str(f) for f in folders] for name, folders in runs.items() if folders}
    if runs:  # none in a report of a study whose runs have not evaluated yet
        steps.append(
            Step(
                f"{split.name}/compare",
                f"compare {split.name}",
                split_dir,
                [
                    bin_path("jept-compare"),
                    f"--runs={json.dumps(runs)}",
                    f"--output_dir={split_dir / 'compare'}",
                ],
                always=True,
            )
        )
    return steps


def policy_type(method: MethodSpec) -> str:
    return json.loads(Path(method.config).read_text())["policy"]["type"]


def visualize_steps(cfg: StudyConfig, split: SplitSpec, split_dir: Path) -> list[Step]:
    """``jept-visualize`` of the first JEPT method's first seed against the first other method's, on the probe
    repo (Figures 3 and 5). Drawn once per split, with the seed list's first seed and the methods at that time."""
    trained = [m for m in cfg.methods if not m.checkpoints_of]
    jept = [m for m in trained if policy_type(m) == "jept"]
    others = [m for m in trained if policy_type(m) != "jept"]
    if not jept:
        return []
    seed = cfg.seeds[0]
    command = [
        bin_path("jept-visualize"),
        f"--policy.path={checkpoint(run_folder(output_dir(cfg), split, jept[0], seed))}",
        f"--policy.device={cfg.device}",
        f"--dataset.repo_id={split.repo_id}_probe",
        f"--output_dir={split_dir / 'visualize'}",
    ]
    if others:
        command.insert(
            3, f"--baseline.path={checkpoint(run_folder(output_dir(cfg), split, others[0], seed))}"
        )
        command.insert(4, f"--baseline.device={cfg.device}")
    # the marker names the JEPT method, not the seed nor the baseline: a study resumed or extended with another
    # seed list, or run in passes (its JEPT arms first, the baselines later), keeps the figures it drew first
    signature = ["jept-visualize", split.name, jept[0].name]
    return [
        Step(
            f"{split.name}/visualize",
            f"t-SNE figures {split.name}",
            split_dir,
            command,
            signature=signature,
            prefix=True,
        )
    ]


def random_floor(cfg: StudyConfig, split: SplitSpec) -> dict:
    """The random 7-bin policy's success per task of the split (:func:`lerobot_jept.evaluation.suite.random_floor`) on the
    suite's evaluation seeds, under the build's protocol."""
    from lerobot_jept.evaluation.suite import random_floor as floor_of
    from lerobot_jept.evaluation.suite import read_build_metadata

    build, _ = read_build_metadata(f"{split.repo_id}_mix", None)
    tasks = [*split.demo_tasks, *split.video_tasks, *split.unseen_tasks]
    per_task = floor_of(build, tasks, cfg.random_episodes, cfg.eval_seed, cfg.eval_episode_length)
    return {"episodes": cfg.random_episodes, "per_task": per_task}
