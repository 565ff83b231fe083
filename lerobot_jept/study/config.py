"""The study file: its splits, build, methods, seeds and pre-registered test (read with draccus)."""

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class SplitSpec:
    """One build: its ORG/NAME and its task split (T_demo / T_vid / T_unseen)."""

    name: str = "split"  # folder of its runs and label in the report
    repo_id: str = "local/study"
    demo_tasks: list[str] = field(default_factory=list)
    video_tasks: list[str] = field(default_factory=list)
    unseen_tasks: list[str] = field(default_factory=list)


@dataclass
class BuildSpec:
    """Builder flags shared by every split of the study (``args``: any further builder flags)."""

    episodes_per_task: int = 30
    prompts_per_task: int = 4
    probe_episodes_per_task: int = 4
    play_episodes_per_task: int = 0  # labelled play episodes per demo and video task's scene (in the mix)
    image_size: int = 96
    seed: int = 0
    num_workers: int = 2
    args: list[str] = field(default_factory=list)


@dataclass
class MethodSpec:
    """One column of the tables. ``kind``: ``train`` (``lerobot-train`` with ``config`` on the split's ``data``
    repo: ``mix``; ``demo``; or ``labelled``, every labelled frame of the mix without the videos, i.e. ``_demo``
    plus ``_play`` when the build has play episodes) or ``bc_idm`` (a ``jept_idm`` from ``idm_config`` on the
    labelled frames, ``jept-relabel`` of ``_mix``, then ``config``, a ``jept_dt_star`` config, on the relabelled
    repo). ``args``: ``lerobot-train`` flags of this method (a ``jept`` variant is ``jept`` with overrides).
    ``eval_episodes`` (default: the study's) and ``suite_args`` (added to the study's) set its evaluation.
    ``checkpoints_of``: the name of an earlier method of the study whose checkpoints this one evaluates, with its
    own ``suite_args`` (a control setting, e.g. ``--policy.action_decoding=expectation``); nothing is trained.
    ``steps``: this method's training steps (default: the study's). ``continue_from``: the name of an earlier
    method that trains; this one resumes each of its runs from that run's last checkpoint (LeRobot's resume, into
    its own folder, ``args`` added) and trains on to ``steps``, so a longer-training arm pays only the extra
    steps and shares the shorter arm's first steps exactly. ``checkpoint``: with ``checkpoints_of``, the
    training step of the checkpoint evaluated (one the source saved: a multiple of ``save_freq``, or its last
    step) instead of the last one."""

    name: str = "JEPT"
    kind: str = "train"
    config: str = "examples/configs/train_jept_small_cpu.json"
    data: str = "mix"
    args: list[str] = field(default_factory=list)
    idm_config: str = "examples/configs/train_idm_small_cpu.json"
    idm_args: list[str] = field(default_factory=list)
    eval_episodes: int | None = None
    suite_args: list[str] = field(default_factory=list)
    checkpoints_of: str = ""
    steps: int | None = None
    continue_from: str = ""
    checkpoint: int | None = None


@dataclass
class PreRegisteredTest:
    """The study's test, written in the study file before it runs.

    A case is one video-only task of one split (a scene pair in one direction). The primary measure is the
    case's success rate in the simulator, one value per training seed: seeds, not episodes, are the unit (a
    checkpoint's episodes share it). ``method`` passes a case when its mean over seeds exceeds ``baseline``'s
    (the same recipe on the same data without the videos) by more than the larger of the two arms' seed ranges.
    The hypothesis holds when at least ``min_cases`` cases pass, the mean over all cases reaches ``goal_mean``
    %, and under the scene-mate's prompt (``--scene_mate_prompts``) every case's success is at most
    ``floor_margin`` points above the upper end of its random floor's 95% Wilson interval (the prompt, not the
    scene, drives the behaviour). Welch's p over seeds is reported beside each case."""

    method: str = ""
    baseline: str = ""
    min_cases: int = 6
    goal_mean: float = 50.0
    floor_margin: float = 0.0


@dataclass
class StudyConfig:
    name: str = "study"
    simulator: str = "metaworld"  # metaworld | robosuite
    splits: list[SplitSpec] = field(default_factory=list)
    build: BuildSpec = field(default_factory=BuildSpec)
    methods: list[MethodSpec] = field(default_factory=list)
    seeds: list[int] = field(default_factory=lambda: [1000, 2000, 3000])
    steps: int = 1000
    save_freq: int = 500  # checkpoints a killed run resumes from
    train_args: list[str] = field(default_factory=list)  # lerobot-train flags of every run
    eval_episodes: int = 10  # per task
    eval_batch_size: int = 10
    eval_seed: int = 1000
    eval_episode_length: int | None = None  # default: the build's max_episode_steps
    suite_args: list[str] = field(
        default_factory=list
    )  # jept-eval-suite flags of every run (e.g. --splits=[video])
    # The test fixed before the study runs (see PreRegisteredTest); None for a study without one.
    test: PreRegisteredTest | None = None
    random_episodes: int = 20  # per task, for the random 7-bin floor; 0 skips it
    output_dir: Path | None = None  # default: outputs/study/<name>
    device: str = "cpu"
    # Runs (one method's seed: its training and evaluation) at once, each with cores // parallel torch threads.
    # On a 2-core CPU two one-thread runs do about 1.3-1.5 times the work of one two-thread run.
    parallel: int = 1
    # Build, train and evaluate nothing: compare the runs that have finished and write the report (a study cut
    # short, or one run in pieces from copies of its file that each wrote a report of their own).
    report_only: bool = False


class StudyError(RuntimeError):
    pass


def output_dir(cfg: StudyConfig) -> Path:
    return Path(cfg.output_dir) if cfg.output_dir else Path("outputs/study") / cfg.name


def validate(cfg: StudyConfig) -> None:
    if cfg.simulator not in ("metaworld", "robosuite"):
        raise StudyError(f"simulator must be metaworld or robosuite, got {cfg.simulator!r}.")
    if not cfg.splits or not cfg.methods or not cfg.seeds:
        raise StudyError("The study file must name at least one split, one method and one seed.")
    for names, what in (([s.name for s in cfg.splits], "split"), ([m.name for m in cfg.methods], "method")):
        if len(set(names)) != len(names):
            raise StudyError(f"Two {what}s share a name in {names}: names are folders and columns.")
    for m in cfg.methods:
        source = source_of(cfg, m)
        if source is not None:  # its checkpoints come from the source's config: named so, for the report
            for attr in ("kind", "config", "data", "idm_config"):
                setattr(m, attr, getattr(source, attr))
        if m.kind not in ("train", "bc_idm") or m.data not in DATA:
            raise StudyError(
                f"Method {m.name!r}: kind must be train or bc_idm and data one of {DATA} (got {m.kind}, {m.data})."
            )
        for path in [m.config] + ([m.idm_config] if m.kind == "bc_idm" else []):
            if not Path(path).is_file():
                raise StudyError(
                    f"Method {m.name!r}: train config {path} does not exist (paths are relative to "
                    "the folder jept-study runs in)."
                )
    names = [m.name for m in cfg.methods]
    trained: dict[str, MethodSpec] = {}  # the methods so far that train
    for m in cfg.methods:
        if m.checkpoints_of and m.checkpoints_of not in trained:
            raise StudyError(
                f"Method {m.name!r} evaluates the checkpoints of {m.checkpoints_of!r}, which must be a method "
                f"listed before it that trains (one of {list(trained)})."
            )
        if m.continue_from:
            source = trained.get(m.continue_from)
            if source is None or m.checkpoints_of:
                raise StudyError(
                    f"Method {m.name!r} continues the training of {m.continue_from!r}, which must be a method "
                    f"listed before it that trains (one of {list(trained)}); it cannot also take checkpoints_of."
                )
            if method_steps(cfg, m) <= method_steps(cfg, source):
                raise StudyError(
                    f"Method {m.name!r} continues {m.continue_from!r} past its {method_steps(cfg, source)} steps: "
                    f'give it "steps" above that (got {method_steps(cfg, m)}).'
                )
        if not m.checkpoints_of:
            trained[m.name] = m
        if m.checkpoint is not None and m.checkpoint not in saved_steps(cfg, m.checkpoints_of):
            raise StudyError(
                f"Method {m.name!r}: checkpoint {m.checkpoint} is not a step whose checkpoint "
                f"checkpoints_of ({m.checkpoints_of!r}) saves; one of {saved_steps(cfg, m.checkpoints_of)}."
            )
    if cfg.test is not None and not {cfg.test.method, cfg.test.baseline} <= set(names):
        raise StudyError(
            f"The test compares {cfg.test.method!r} with {cfg.test.baseline!r}; both must be methods of the study "
            f"({names})."
        )
    if cfg.test is not None and not any("--scene_mate_prompts=true" in m.suite_args for m in cfg.methods):
        raise StudyError(
            "The test reads the method's success under the scene-mate's prompt: give its method "
            '"suite_args": ["--scene_mate_prompts=true"].'
        )
    if min(method_steps(cfg, m) for m in cfg.methods) < 1 or cfg.eval_episodes < 1:
        raise StudyError("steps and eval_episodes must be at least 1.")
    if cfg.device not in ("cpu", "cuda", "mps"):
        raise StudyError(f"--device must be cpu, cuda or mps, got {cfg.device!r}.")
    if cfg.parallel < 1:
        raise StudyError(f"--parallel is the number of runs at once, at least 1 (got {cfg.parallel}).")


DATA = ("mix", "demo", "labelled")


def method_steps(cfg: StudyConfig, method: MethodSpec) -> int:
    return method.steps if method.steps is not None else cfg.steps


def method_named(cfg: StudyConfig, name: str) -> MethodSpec | None:
    return next((m for m in cfg.methods if m.name == name), None)


def source_of(cfg: StudyConfig, method: MethodSpec) -> MethodSpec | None:
    """The method whose checkpoints this one evaluates or whose runs it trains on; None for one that trains anew."""
    return method_named(cfg, method.checkpoints_of or method.continue_from)


def start_step(cfg: StudyConfig, method: MethodSpec) -> int:
    """The step a method's runs start from: its source's last step when it continues one, else 0."""
    source = method_named(cfg, method.continue_from)
    return method_steps(cfg, source) if source is not None else 0


def saved_steps(cfg: StudyConfig, name: str) -> list[int]:
    """The steps at which the runs of method ``name`` save a checkpoint (LeRobot: every ``save_freq`` steps and
    the last; a continued run from its source's last step on); none for a name that is not a method."""
    method = method_named(cfg, name)
    if method is None:
        return []
    steps = method_steps(cfg, method)
    every = min(cfg.save_freq, steps)
    return sorted({*range(every, steps + 1, every), steps} - set(range(start_step(cfg, method) + 1)))
