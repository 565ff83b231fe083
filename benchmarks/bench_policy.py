"""Policy speed, each figure a ratio against a baseline measured in the same run.

- ``select_action_cached_speedup``: step time of ``select_action`` recomputing every context frame (backbone +
  Perceiver on all k frames) / step time with the per-frame token cache; the paper's architecture
  (vit_base_patch16_224 at 224 px, k = 8) with random weights, batch 1, same context. Goal >= 5.
- ``select_action_vs_backbone``: the cached ``select_action`` step above / one backbone pass on the new frame
  alone (same model, same run): what a control step costs beyond the one frame it must encode. Goal <= 1.1.
  ``select_action_guided_vs_backbone``: the same with the ``plus`` recipe's guidance on (``prompt_dropout``
  0.1, ``prompt_guidance`` 1: the predictor runs under the prompt and under the null prompt). No goal.
  ``select_action_vs_backbone_flop_ratio``: the same ratio in arithmetic (torch's FLOP counter, one untimed
  cached step and one backbone pass): the time ratio a device running every FLOP at one rate would reach, so
  the floor the architecture sets for ``select_action_vs_backbone``.
- ``train_step_vs_act``: one training step (forward, backward, AdamW) of the small jept configuration / one of
  LeRobot's ACT (its defaults, no pretrained weights) on the same batches of a tiny Meta-World build, same batch
  size. Goal <= 2.
- ``train_step_vs_jept_<type>``: one training step of each baseline (``dt_star``, ``vid2robot``, ``idm``,
  ``idm_self_state`` (``jept_idm --policy.idm_input=self_state``), ``no_prompt``, ``lapo``: the policy types
  ``jept_<type>``)
  in its small configuration / one of the small jept configuration, on batches of
  the same tiny build, same batch size (each policy takes the frames its delta indices ask for), measured in
  the same run. No goal: their costs.
"""

import argparse
import os
import statistics
import tempfile
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_LEROBOT_HOME", tempfile.mkdtemp(prefix="jept_bench_home_"))

import torch  # noqa: E402
from lerobot.configs.types import FeatureType, PolicyFeature  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from lerobot_jept import (  # noqa: E402
    DTStarConfig,
    IDMConfig,
    JEPTConfig,
    JEPTNoPromptConfig,
    JEPTPolicy,
    LAPOConfig,
    Vid2RobotConfig,
)
from lerobot_jept.policies.jept.modeling_jept import PROMPT_VIDEO  # noqa: E402


def sync() -> None:
    """Wait for the GPU's queued work (CUDA runs asynchronously), so that a timer measures the work itself."""
    if torch.cuda.is_initialized():
        torch.cuda.synchronize()


def step_times(fn, repeats: int, warmup: int = 2) -> list[float]:
    """Seconds of each of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def gflop(fn) -> float:
    """GFLOP of one call of ``fn``, as torch's FLOP counter sees them (matrix products, attention)."""
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops() / 1e9


def median_time(fn, repeats: int, warmup: int = 2) -> float:
    return statistics.median(step_times(fn, repeats, warmup))


def select_action_speedup(repeats: int) -> tuple[float, float, float, float, float]:
    """-> (uncached / cached step time, cached step s, backbone pass s, cached step s with guidance, cached
    step GFLOP / backbone pass GFLOP)."""
    features = {
        "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 224, 224)),
        "observation.state": PolicyFeature(FeatureType.STATE, (18,)),
    }
    times = {}
    torch.manual_seed(0)
    # uncached, cached, and cached with the plus recipe's guidance (a second prediction under the null prompt)
    for run, (cached, dropout) in {
        "uncached": (False, 0.0),
        "cached": (True, 0.0),
        "guided": (True, 0.1),
    }.items():
        cfg = JEPTConfig(
            device="cpu",
            pretrained_backbone=False,
            cache_frame_tokens=cached,
            prompt_warmup_steps=0,
            prompt_dropout=dropout,
            input_features=features,
            output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        )
        policy = JEPTPolicy(cfg).eval()
        obs = {
            "observation.image": torch.rand(1, 3, 224, 224),
            "observation.state": torch.randn(1, 18),
            PROMPT_VIDEO: torch.rand(1, 8, 3, 224, 224),
        }
        policy.reset()
        for _ in range(cfg.n_obs_steps):  # a full context, prompt encoded: the steady state of an episode
            policy.select_action(obs)
        times[run] = median_time(lambda p=policy, o=obs: p.select_action(o), repeats, warmup=1)
        if run == "cached":
            policy.requires_grad_(False)  # inference: the FLOP counter's module hooks need no autograd
            step_gflop = gflop(lambda p=policy, o=obs: p.select_action(o))
            image = obs["observation.image"][:, None]
            with torch.no_grad():
                backbone = lambda p=policy, i=image: p.model.backbone_tokens(i)  # noqa: E731
                backbone_s = median_time(backbone, repeats, warmup=1)
                flop_ratio = step_gflop / gflop(backbone)
    return times["uncached"] / times["cached"], times["cached"], backbone_s, times["guided"], flop_ratio


def tiny_build() -> str:
    from dataset_builders.core import build
    from dataset_builders.metaworld import MetaworldBuildConfig, MetaworldSimulator

    cfg = MetaworldBuildConfig(
        repo_id="bench/policy",
        demo_tasks=["button-press-v3", "reach-v3"],
        video_tasks=[],
        unseen_tasks=[],
        episodes_per_task=4,
        prompts_per_task=2,
        probe_episodes_per_task=0,
        image_size=96,
        num_workers=1,
    )
    build(cfg, MetaworldSimulator())
    return "bench/policy"


def train_step_time(cfg, repo: str, batch_size: int, repeats: int) -> float:
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    meta = LeRobotDatasetMetadata(f"{repo}_demo")
    torch.manual_seed(0)
    policy = make_policy(cfg, ds_meta=meta)
    pre, _ = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    ds = LeRobotDataset(f"{repo}_demo", delta_timestamps=resolve_delta_timestamps(cfg, meta))
    loader = iter(torch.utils.data.DataLoader(ds, batch_size=batch_size, shuffle=True, drop_last=True))
    batches = [pre(next(loader)) for _ in range(3)]
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-4)
    policy.train()
    state = {"i": 0}

    def step():
        batch = batches[state["i"] % len(batches)]
        state["i"] += 1
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()
        if hasattr(policy, "update"):
            policy.update()

    return median_time(step, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--batch_size", type=int, default=8)
    args = parser.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)

    speedup, cached_s, backbone_s, guided_s, flop_ratio = select_action_speedup(args.repeats)
    print(f"select_action_cached_s: {cached_s:.3f}")
    print(f"select_action_cached_speedup: {speedup:.2f}")
    print(f"backbone_one_frame_s: {backbone_s:.3f}")
    print(f"select_action_vs_backbone: {cached_s / backbone_s:.2f}")
    print(f"select_action_guided_vs_backbone: {guided_s / backbone_s:.2f}")
    print(f"select_action_vs_backbone_flop_ratio: {flop_ratio:.2f}")

    from lerobot.policies.act.configuration_act import ACTConfig

    repo = tiny_build()
    jept = JEPTConfig.small(
        device="cpu", prompt_repo_id=f"{repo}_prompts", prompt_warmup_steps=0, phase_schedule="joint"
    )
    act = ACTConfig(device="cpu", pretrained_backbone_weights=None)
    jept_s = train_step_time(jept, repo, args.batch_size, args.repeats)
    act_s = train_step_time(act, repo, args.batch_size, args.repeats)
    print(f"train_step_jept_small_s: {jept_s:.3f}")
    print(f"train_step_act_s: {act_s:.3f}")
    print(f"train_step_vs_act: {jept_s / act_s:.2f}")
    small = dict(device="cpu", prompt_repo_id=f"{repo}_prompts")
    baselines = {
        "dt_star": DTStarConfig.small(**small),
        "vid2robot": Vid2RobotConfig.small(**small),
        "idm": IDMConfig.small(**small),
        "idm_self_state": IDMConfig.small(**small, idm_input="self_state"),
        "no_prompt": JEPTNoPromptConfig.small(**small, prompt_warmup_steps=0, phase_schedule="joint"),
        "lapo": LAPOConfig.small(**small),
    }
    for name, config in baselines.items():
        baseline_s = train_step_time(config, repo, args.batch_size, args.repeats)
        print(f"train_step_{name}_s: {baseline_s:.3f}")
        print(f"train_step_vs_jept_{name}: {baseline_s / jept_s:.2f}")


if __name__ == "__main__":
    main()
