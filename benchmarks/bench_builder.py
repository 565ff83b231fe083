"""Builder throughput, measured against the raw simulator in the same run.

For Meta-World and robosuite, prints ``<sim>_builder_vs_raw: R`` (builder frames/s with 1 worker / raw step+render
frames/s of the same env and settings) and ``<sim>_builder_2workers_speedup: R`` (builder frames/s with 2 workers /
with 1 worker). Rates are steady-state (see :func:`builder_frames_per_second`); start-up times are printed on
their own lines.

Both rates of ``_vs_raw`` count the frames of successful episodes over the same episodes: the raw rate replays
every seed the 1-worker build attempted (its rejected episodes included) with step+render only. The builder
must roll out an episode to know it fails, and the raw loop pays for the same failures, so the ratio measures
what writing costs, not how often the expert fails (a failed ``door-open-v3`` episode runs the full 250 steps,
six times a successful one). ``<sim>_raw_frames_per_s`` counts every frame of that replay.
"""

import argparse
import tempfile
import time

from dataset_builders.core import BuildConfig, Shard, plan_shards, rollout_expert, run_shards


def raw_frames_per_second(sim, cfg: BuildConfig, task: str, seeds: list[int]) -> tuple[float, float, int]:
    """Expert rollouts of ``seeds`` through the same env, with no dataset writing (step + render only):
    frames of the successful episodes per second, all frames per second, and the number of successes."""
    env = sim.make_env(task, cfg)
    rollout_expert(env, seeds[0], cfg.action_bins)  # warm-up: lazy simulator creation, first GL frame
    kept = frames = successes = 0
    start = time.perf_counter()
    for seed in seeds:
        episode, success = rollout_expert(env, seed, cfg.action_bins)
        frames += len(episode)
        kept += len(episode) if success else 0
        successes += success
    elapsed = time.perf_counter() - start
    env.close()
    return kept / elapsed, frames / elapsed, successes


def builder_frames_per_second(sim, cfg: BuildConfig, shards: list[Shard]) -> tuple[float, float, list[int]]:
    """Steady-state throughput of a build, its start-up time and the seeds it attempted.

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
    summaries = run_shards(sim, cfg, shards, progress)
    skip = cfg.num_workers
    if len(kept) <= skip + 1:
        raise SystemExit("bench_builder: too few episodes to measure a rate; raise --episodes.")
    t0 = kept[skip - 1][0]
    frames = sum(f for _, f in kept[skip:])
    attempted = [  # summaries come in the order shards finished
        Shard(s["role"], s["task"], s["index"], s["num_episodes"]).seed(cfg.seed, attempt)
        for s in sorted(summaries, key=lambda s: s["index"])
        for attempt in range(s["attempts"])
    ]
    return frames / (kept[-1][0] - t0), t0 - start, attempted


def bench(sim, config_cls, tasks: list[str], episodes: int) -> dict[str, float]:
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
        one, startup1, attempted = builder_frames_per_second(sim, cfg1, shards)
        raw, raw_all, successes = raw_frames_per_second(sim, cfg1, tasks[0], attempted)
        if successes != sum(shard.num_episodes for shard in shards):
            raise SystemExit(
                "bench_builder: the raw replay of the build's seeds kept other episodes than the build."
            )
        cfg2 = config_cls(**{**base, "repo_id": "bench/b2"}, num_workers=2)
        two, startup2, _ = builder_frames_per_second(
            sim, cfg2, [s for s in plan_shards(cfg2) if s.role == "demo"]
        )
    results[f"{sim.name}_raw_frames_per_s"] = raw_all
    results[f"{sim.name}_raw_kept_frames_per_s"] = raw
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
        for metric, value in bench(sim, config_cls, tasks, args.episodes).items():
            print(f"{metric}: {value:.3f}", flush=True)


if __name__ == "__main__":
    main()
