"""The build's configuration: the flags every ``jept-build-*`` command shares, the simulator interface, and
the checks that reject bad flags before any work starts."""

import abc
from dataclasses import dataclass, field

ROLES = ("demo", "video", "play", "prompts", "probe")
LABELLED_ROLES = ("demo", "play", "probe")  # recorded with the executed action
# Play: labelled episodes of no task in the scene of a demo or video task (``play:<task>``), where a random bin
# action is held for a random number of steps (kept with PLAY_HOLD_PROB each step), so inverse dynamics fitted
# on the labelled frames sees motions the demo tasks' experts never make.
PLAY_PREFIX = "play:"
PLAY_HOLD_PROB = 0.8
# How a play episode picks its actions: ``random`` (a random bin action, held), or ``reach`` (object-centred
# play: the hand driven to random points around the scene's object with a random gripper command, as a person
# fiddling with the object would; it needs a simulator that exposes the object's position).
PLAY_POLICIES = ("random", "reach")
SPLITS = ("demo", "video", "unseen")
BUILD_FILE = "jept_build.json"  # written in <work dir>/ and in every repo's meta/
# Episode seeds: each (role, shard) owns a disjoint block of SEED_BLOCK seeds, so training episodes and
# prompt videos and probe episodes never share a seed, and all stay clear of lerobot-eval's default seeds (1000 + episode).
SEED_BLOCK = 10_000
ROLE_SEED_BASE = {
    "demo": 10_000_000,
    "video": 10_000_000,
    "prompts": 20_000_000,
    "probe": 30_000_000,
    "play": 40_000_000,
}
# Flags added after builds were made, with the value a build recorded without one had: GIVEN_NOW = the value
# given now (its shards are recorded on top of the existing ones, so an older build resumes with today's defaults).
GIVEN_NOW = "given now"
ADDED_FLAGS = {
    "probe_episodes_per_task": GIVEN_NOW,
    "expert_random_prob": 0.0,
    "play_episodes_per_task": 0,
    "play_policy": "random",
    "video_episodes_per_task": None,  # episodes_per_task's
}
# Flags that change what is written; a repo built with other values is never mixed with new episodes.
CONTENT_FLAGS = (
    "demo_tasks",
    "video_tasks",
    "unseen_tasks",
    "episodes_per_task",
    "video_episodes_per_task",
    "prompts_per_task",
    "probe_episodes_per_task",
    "play_episodes_per_task",
    "play_policy",
    "image_size",
    "seed",
    "action_bins",
    "expert_random_prob",
    "action_repeat",
    "max_episode_steps",
    "episodes_per_shard",
    "vcodec",
)


EXECUTORS = ("local", "datatrove_local", "slurm")


def play_task(task: str) -> str:
    return PLAY_PREFIX + task


def scene_task(task: str) -> str:
    """The simulator task whose scene ``task`` (a task or a play pseudo-task) runs in."""
    return task.removeprefix(PLAY_PREFIX)


def is_play(task: str) -> bool:
    return task.startswith(PLAY_PREFIX)


def task_description(sim: "Simulator", task: str) -> str:
    """The task string written to the datasets (a play pseudo-task's says so)."""
    if is_play(task):
        return f"Play in the scene of: {sim.task_description(scene_task(task))}"
    return sim.task_description(task)


@dataclass
class SlurmArgs:
    """``--slurm.*``: where and how the array job of ``--executor=slurm`` runs."""

    partition: str | None = None
    workers: int = -1  # array tasks running at once (-1: as many as SLURM allows)
    cpus_per_task: int = 2
    mem_per_cpu: int = 4  # GB
    time: str = "24:00:00"


class BuildError(ValueError):
    """A build request that cannot be carried out; the message says how to fix it."""


@dataclass
class BuildConfig:
    """Flags shared by every ``jept-build-*`` command (the simulator's config sets the defaults).

    Attributes:
        repo_id: ``ORG/NAME``; the build writes ``ORG/NAME_demo``, ``_video``, ``_prompts`` and ``_mix``.
        demo_tasks: T_demo, tasks recorded with actions.
        video_tasks: T_vid, tasks recorded as expert videos without actions.
        unseen_tasks: T_unseen, tasks that only get prompt videos.
        episodes_per_task: successful expert episodes per demo/video task.
        video_episodes_per_task: expert videos per video-only task instead (default ``episodes_per_task``):
            more videos of a task is one lever for executing it, and they cost no labels.
        prompts_per_task: prompt videos per task (all three splits), seeds disjoint from training episodes.
        probe_episodes_per_task: held-out labelled episodes per task (all three splits) in ``<repo_id>_probe``,
            seeds disjoint from every other role; 0 for none.
        play_episodes_per_task: labelled play episodes per demo and video task in ``<repo_id>_play`` (task
            ``play:<task>``: that task's scene, random bin actions each held for a few steps, no expert), with
            ``prompts_per_task`` play prompts each; they join the mix as labelled frames, so inverse dynamics
            covers motions the video-only tasks show and no demo makes. 0 for none.
        play_policy: how play episodes act: ``random`` (a random bin action held for a few steps) or ``reach``
            (object-centred: the hand driven to random points around the scene's object, a random gripper
            command per reach; Meta-World only).
        image_size: side of the square camera image.
        seed: base seed; the same flags and seed give the same episodes.
        num_workers: parallel rollout processes (one simulator env per process).
        action_bins: bins per action dimension; experts execute the nearest bin centre.
        expert_random_prob: probability that a step executes (and records) a uniformly random bin action
            instead of the expert's, drawn from the episode's seed. The paper mixes a second policy into its
            experts "to ensure diversity" (Appendix B); without it every recorded action is a function of the
            state, and inverse dynamics learned from the demos can read the action from the state alone.
        action_repeat: simulator steps per recorded step.
        max_episode_steps: recorded steps before an episode is truncated (and rejected as a failure).
        episodes_per_shard: unit of work and of resumption.
        vcodec: video codec of the camera stream (``h264`` at the ``veryfast`` preset costs a fifth of the CPU
            time of LeRobot's default ``libsvtav1``, which matters when rendering on a CPU; ``libsvtav1`` gives
            smaller files).
        root: folder holding the repos; default ``$HF_LEROBOT_HOME`` (where LeRobot looks for ``repo_id``).
        executor: ``local`` (this process and ``num_workers`` pool processes), ``datatrove_local`` (datatrove's
            local executor, ``num_workers`` tasks at once) or ``slurm`` (an array job of shard groups and a
            dependent assembly job, through datatrove; needs the ``[cluster]`` extra). Same shards and episodes.
        tasks: datatrove tasks (shard groups); default one per shard.
        logs_dir: datatrove's logs; default ``<repo_id>.build/datatrove_logs``.
        slurm: partition, workers, cpus_per_task, mem_per_cpu (GB), time of the SLURM jobs.
        push_to_hub: push every repo with LeRobot's ``push_to_hub`` at the end.
        private: create the Hub repos as private.
    """

    repo_id: str = "local/jept"
    demo_tasks: list[str] = field(default_factory=list)
    video_tasks: list[str] = field(default_factory=list)
    unseen_tasks: list[str] = field(default_factory=list)
    episodes_per_task: int = 500
    video_episodes_per_task: int | None = None
    prompts_per_task: int = 10
    probe_episodes_per_task: int = 4
    play_episodes_per_task: int = 0
    play_policy: str = "random"
    image_size: int = 224
    seed: int = 0
    num_workers: int = 1
    action_bins: int = 7
    expert_random_prob: float = 0.0
    action_repeat: int = 2
    max_episode_steps: int = 250
    episodes_per_shard: int = 25
    vcodec: str = "h264"
    root: str | None = None
    executor: str = "local"
    tasks: int | None = None
    logs_dir: str | None = None
    slurm: SlurmArgs = field(default_factory=SlurmArgs)
    push_to_hub: bool = False
    private: bool = False

    def split(self) -> dict[str, list[str]]:
        return {
            "demo": list(self.demo_tasks),
            "video": list(self.video_tasks),
            "unseen": list(self.unseen_tasks),
        }

    def play_tasks(self) -> list[str]:
        """The play pseudo-tasks: one per demo and video task's scene, when play episodes are asked for."""
        if not self.play_episodes_per_task:
            return []
        return [play_task(t) for t in (*self.demo_tasks, *self.video_tasks)]

    def content_flags(self) -> dict:
        return {name: getattr(self, name) for name in CONTENT_FLAGS}

    def videos_per_task(self) -> int:
        """Expert videos recorded per video-only task."""
        return (
            self.episodes_per_task if self.video_episodes_per_task is None else self.video_episodes_per_task
        )


class Simulator(abc.ABC):
    """What a simulator module provides to the core. Instances must be picklable (they go to workers)."""

    name: str  # e.g. "metaworld"
    robot_type: str
    play_policies: tuple[str, ...] = ("random",)  # ``reach`` needs the env's ``hand_and_object()``

    @abc.abstractmethod
    def check_task(self, task: str) -> str:
        """Return ``task`` or raise :class:`BuildError` listing close matches."""

    @abc.abstractmethod
    def task_description(self, task: str) -> str:
        """The task string written to the datasets; equal to the eval env's ``task_description``."""

    @abc.abstractmethod
    def make_env(self, task: str, cfg: BuildConfig, role: str = "demo"):
        """A gymnasium env with ``{"pixels", "agent_pos"}`` observations and an ``expert_action()`` method.
        ``role`` is the repo being recorded (``"prompts"`` may show another embodiment than the others)."""

    @abc.abstractmethod
    def fps(self, cfg: BuildConfig) -> int:
        """Recorded frames per second."""

    @abc.abstractmethod
    def observation_features(self, cfg: BuildConfig) -> dict:
        """LeRobot features of the observation (``observation.image``, ``observation.state``)."""

    @abc.abstractmethod
    def action_feature(self) -> dict:
        """LeRobot feature of the executed action."""

    def protocol(self, cfg: BuildConfig) -> dict:
        """What a reader of the dataset card needs to reproduce the observations."""
        return {
            "simulator": self.name,
            "robot_type": self.robot_type,
            "image_size": cfg.image_size,
            "fps": self.fps(cfg),
            "action_bins": cfg.action_bins,
            "expert_random_prob": cfg.expert_random_prob,
            "action_repeat": cfg.action_repeat,
            "max_episode_steps": cfg.max_episode_steps,
        }


def validate(cfg: BuildConfig, sim: Simulator) -> None:
    """Reject bad flags before any work starts, with one sentence that names the fix."""
    if "/" not in cfg.repo_id or cfg.repo_id.count("/") != 1:
        raise BuildError(f"--repo_id must look like ORG/NAME, got {cfg.repo_id!r}.")
    for name in ("episodes_per_task", "prompts_per_task", "image_size", "num_workers", "episodes_per_shard"):
        if getattr(cfg, name) < 1:
            raise BuildError(f"--{name} must be at least 1, got {getattr(cfg, name)}.")
    if cfg.video_episodes_per_task is not None and cfg.video_episodes_per_task < 1:
        raise BuildError(
            f"--video_episodes_per_task must be at least 1 (or left out: --episodes_per_task's), got "
            f"{cfg.video_episodes_per_task}."
        )
    for name in ("probe_episodes_per_task", "play_episodes_per_task"):
        if getattr(cfg, name) < 0:
            raise BuildError(f"--{name} must be 0 or more, got {getattr(cfg, name)}.")
    if cfg.play_policy not in sim.play_policies:
        raise BuildError(
            f"--play_policy={cfg.play_policy!r} is not available for {sim.name}: use one of "
            f"{', '.join(sim.play_policies)}."
        )
    if cfg.executor not in EXECUTORS:
        raise BuildError(f"--executor must be one of {', '.join(EXECUTORS)}, got {cfg.executor!r}.")
    if cfg.tasks is not None and cfg.tasks < 1:
        raise BuildError(f"--tasks must be at least 1, got {cfg.tasks}.")
    if cfg.action_bins < 2:
        raise BuildError(f"--action_bins must be at least 2, got {cfg.action_bins}.")
    if not 0.0 <= cfg.expert_random_prob < 1.0:
        raise BuildError(f"--expert_random_prob must be in [0, 1), got {cfg.expert_random_prob}.")
    if cfg.action_repeat < 1 or cfg.max_episode_steps < 1:
        raise BuildError("--action_repeat and --max_episode_steps must be at least 1.")
    if not cfg.demo_tasks and not cfg.video_tasks:
        raise BuildError("Nothing to train on: give at least one task in --demo_tasks or --video_tasks.")
    seen: dict[str, str] = {}
    for split, tasks in cfg.split().items():
        for task in tasks:
            sim.check_task(task)
            if task in seen:
                where = "twice in" if seen[task] == split else f"in both {seen[task]}_tasks and"
                raise BuildError(f"Task {task!r} is {where} {split}_tasks: a task belongs to one split only.")
            seen[task] = split
