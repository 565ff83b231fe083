"""Builder throughput, measured against the raw simulator in the same run.

For Meta-World and robosuite, prints ``<sim>_builder_vs_raw: R`` (builder frames/s with 1 worker / raw step+render frames/s of the same env
and settings) and ``<sim>_builder_2workers_speedup: R`` (builder frames/s with 2 workers / with 1 worker). Rates
are steady-state (see :func:`builder_frames_per_second`); start-up times are printed on their own lines.
"""

import argparse
import tempfile
import time

from dataset_builders.core import BuildConfig, Shard, plan_shards, rollout_expert, run_shards


def raw_frames_per_second(sim, cfg: BuildConfig, task: str, seconds: float) -> float:
    """Expert rollouts through the same env, with no dataset writing: step + render only."""
    env = sim.make_env(task, cfg)
    env.reset(
        seed=0
    )  # envs that build their simulator lazily (robosuite) do it here, before the clock starts
    frames, start, seed = 0, time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        episode, _ = rollout_expert(env, seed, cfg.action_bins)
        frames += len(episode)
        seed += 1
    elapsed = time.perf_counter() - start
    env.close()
    return frames / elapsed


def builder_frames_per_second(sim, cfg: BuildConfig, shards: list[Shard]) -> tuple[float, float]:
    """Steady-state throughput of a build and its start-up time.

    Throughput counts the frames of the episodes kept after the first ``num_workers`` ones, over the time from
    that point to the last episode: like the raw figure (measured after a warm-up), it leaves out what a build
    pays once (spawning processes, imports, creating the env and GL context), which a real build (hundreds of
    episodes per task) amortises. Start-up is the time to the ``num_workers``-th episode, reported on its own.
    """
    kept: list[tuple[float, int]] = []

    def progress(role, episodes, frames, rejected):
        if episodes:
            kept.append((time.perf_counter(), frames))

    start = time.perf_counter()
    run_shards(sim, cfg, shards, progress)
    skip = cfg.num_workers
    if len(kept) <= skip + 1:
        raise SystemExit("bench_builder: too few episodes to measure a rate; raise --episodes.")
    t0 = kept[skip - 1][0]
    frames = sum(f for _, f in kept[skip:])
    return frames / (kept[-1][0] - t0), t0 - start


def bench(sim, config_cls, tasks: list[str], episodes: int, raw_seconds: float) -> dict[str, float]:
    results = {}
    with tempfile.TemporaryDirectory() as root:
        base = dict(
            repo_id="bench/b",
            demo_tasks=tasks,
            video_tasks=[],
            unseen_tasks=[],
            prompts_per_task=1,
            episodes_per_task=episodes,
            episodes_per_shard=max(1, episodes // 2),  # two shards: one per worker in the 2-worker build
            root=root,
        )
        cfg1 = config_cls(**base, num_workers=1)
        shards = [s for s in plan_shards(cfg1) if s.role == "demo"]
        # Warm-up: imports, first GL context, encoder start-up are not throughput.
        raw_frames_per_second(sim, cfg1, tasks[0], 2.0)
        raw = raw_frames_per_second(sim, cfg1, tasks[0], raw_seconds)
        one, startup1 = builder_frames_per_second(sim, cfg1, shards)
        cfg2 = config_cls(**{**base, "repo_id": "bench/b2"}, num_workers=2)
        two, startup2 = builder_frames_per_second(
            sim, cfg2, [s for s in plan_shards(cfg2) if s.role == "demo"]
        )
    results[f"{sim.name}_raw_frames_per_s"] = raw
    results[f"{sim.name}_builder_frames_per_s_1worker"] = one
    results[f"{sim.name}_builder_frames_per_s_2workers"] = two
    results[f"{sim.name}_builder_startup_s_1worker"] = startup1
    results[f"{sim.name}_builder_startup_s_2workers"] = startup2
    results[f"{sim.name}_builder_vs_raw"] = one / raw
    results[f"{sim.name}_builder_2workers_speedup"] = two / one
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=50, help="episodes per task in each timed build")
    parser.add_argument("--raw_seconds", type=float, default=10.0)
    parser.add_argument("--sims", default="metaworld,robosuite", help="comma-separated simulators to measure")
    args = parser.parse_args()
    from dataset_builders.metaworld import MetaworldBuildConfig, MetaworldSimulator
    from dataset_builders.robosuite import RobosuiteBuildConfig, RobosuiteSimulator

    setups = {
        "metaworld": (MetaworldSimulator(), MetaworldBuildConfig, ["door-open-v3"]),
        "robosuite": (RobosuiteSimulator(), RobosuiteBuildConfig, ["panda-lift"]),
    }
    for name in args.sims.split(","):
        sim, config_cls, tasks = setups[name]
        for metric, value in bench(sim, config_cls, tasks, args.episodes, args.raw_seconds).items():
            print(f"{metric}: {value:.3f}", flush=True)


if __name__ == "__main__":
    main()
