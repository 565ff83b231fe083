"""The paper configuration at scale: the frozen-backbone fast path, each figure measured in this run.

Default ``JEPTConfig()`` (frozen ``vit_base_patch16_224`` at 224 px, k = 8, Table 5 sizes) with random weights,
on synthetic batches shaped like the preprocessor's output (bank prompts carry their ``observation.prompt_id``).

- ``paper_train_step_prompt_cache_speedup``: training step time (forward, backward, AdamW) without / with the
  cached prompt tokens (``prompt_token_cache``), batch 2, 64-frame prompts, the cache warm (as after each bank
  prompt's first use): one step in each of Algorithm 1's phases, which training alternates (each phase's own
  ratio is printed too); blocks of ``--repeats`` timed steps in the order uncached, cached, cached, uncached,
  medians. Goal >= 5. ``paper_train_step_prompt_cache_flop_ratio`` is its arithmetic ceiling, counted in the
  same run (torch's FLOP counter over one untimed step of each kind: matrix products and attention): the speedup
  a device would reach if it ran every step's arithmetic at one rate. ``paper_backbone_gflop_per_s`` is the
  ViT-B's rate on the batch's observation frames and ``paper_train_step_cached_rest_gflop_per_s`` the rate of the
  rest of a cached step pair (its FLOPs past the ViT-B over its seconds past it); as fractions of the ViT-B's
  rate, ``paper_train_step_rest_rate_measured`` is the latter and ``paper_train_step_rest_rate_needed`` the one
  that work (in both steps) would need for the goal of 5 while the ViT-B runs at its measured rate.
- ``paper_train_peak_gib_b32_p250``: peak memory of one training step at batch 32 with 250-frame prompts in
  each of Algorithm 1's two phases (the encoder, then the others), cache warm in bfloat16, measured in a child
  process (CUDA: ``max_memory_allocated``; CPU: the process's peak resident memory, model and batch included)
  so the bench survives a failure and prints the figure reached. Goal <= 24 (the paper's RTX 3090).
- ``select_action_first_step_vs_later``: the first control step of an episode whose 250-frame bank prompt was
  seen before / a later step of the same episode. Goal <= 2.

``--speedup_shape=32,250`` measures the speedup at the paper's batch and prompt length (a GPU's figure);
``--vision_backbone=NAME`` measures the peak with a visual prior in place of the ViT-B; ``--compile_model``
(``--compile_mode=MODE``) measures the speedup with both policies compiled (``compile_model``), its names
ending ``_compiled``. On CUDA every timer waits for the GPU's queued work.
"""

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from benchmarks.bench_policy import gflop, median_time, step_times, sync
from lerobot_jept import JEPTConfig, JEPTPolicy
from lerobot_jept.policies.base import CACHE_DTYPES
from lerobot_jept.policies.jept.modeling_jept import PROMPT_ID, PROMPT_MASK, PROMPT_VIDEO

IMAGE, STATE, SIZE = "observation.image", "observation.state", 224
FEATURES = {
    IMAGE: PolicyFeature(FeatureType.VISUAL, (3, SIZE, SIZE)),
    STATE: PolicyFeature(FeatureType.STATE, (18,)),
}


def paper_policy(device: str, **overrides) -> JEPTPolicy:
    torch.manual_seed(0)
    cfg = JEPTConfig(
        device=device,
        pretrained_backbone=False,
        input_features=FEATURES,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        **overrides,
    )
    return JEPTPolicy(cfg).to(device)


def paper_batch(cfg: JEPTConfig, batch_size: int, prompt_frames: int, device: str) -> dict:
    """A preprocessed training batch: k + 1 frames, bin labels of the k context frames, one bank prompt per
    sample."""
    t = cfg.n_obs_steps + 1
    return {
        IMAGE: torch.rand(batch_size, t, 3, SIZE, SIZE, device=device),
        f"{IMAGE}_is_pad": torch.zeros(batch_size, t, dtype=torch.bool, device=device),
        STATE: torch.randn(batch_size, t, 18, device=device),
        "action": torch.randint(0, cfg.num_action_bins, (batch_size, t - 1, 4), device=device),
        "action_is_pad": torch.zeros(batch_size, t - 1, dtype=torch.bool, device=device),
        "task_index": torch.arange(batch_size, device=device) % 4,
        # bank prompts come from the preprocessor as their decoded uint8 frames
        PROMPT_VIDEO: torch.randint(
            0, 256, (batch_size, prompt_frames, 3, SIZE, SIZE), dtype=torch.uint8, device=device
        ),
        PROMPT_MASK: torch.ones(batch_size, prompt_frames, dtype=torch.bool, device=device),
        PROMPT_ID: torch.arange(batch_size, device=device),
    }


def set_phase(policy: JEPTPolicy, phase: str) -> None:
    """Past the prompt warm-up, in Algorithm 1's ``encoder`` or ``others`` phase."""
    steps = policy.config.phase_steps
    n = policy.config.prompt_warmup_steps
    if (n // steps) % 2 != ("encoder", "others").index(phase):
        n = (n // steps + 1) * steps
    policy.num_updates.fill_(n)
    assert policy.phase == phase and policy.prompt_active


def train_step(policy: JEPTPolicy, optimizer, batch: dict) -> None:
    loss, _ = policy.forward(batch)
    loss.backward()
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)


def fill_prompt_cache(policy: JEPTPolicy, batch: dict) -> None:
    """Warm the prompt-token cache as a bank prompt's first use would, with random tokens of the right shape
    and dtype (random weights either way): 250-frame prompts through ViT-B on a CPU would take an hour."""
    m, cfg = policy.model, policy.config
    cache = m.prompt_cache()
    n = int(batch[PROMPT_MASK][0].sum())
    for i in batch[PROMPT_ID].tolist():
        cache[("bank", i, n)] = torch.randn(
            n,
            m.backbone.num_tokens,
            m.backbone.dim,
            dtype=CACHE_DTYPES[cfg.prompt_cache_dtype],
            device=batch[PROMPT_ID].device,
        )


def prompt_cache_speedup(
    device: str,
    repeats: int,
    batch_size: int = 2,
    prompt_frames: int = 64,
    compile_model: bool = False,
    compile_mode: str = "default",
) -> tuple[dict, dict, tuple[float, float] | None]:
    """Step times and GFLOP without / with the cache in each of Algorithm 1's phases (the training alternates
    them), and the GFLOP and seconds of the backbone's pass over the observation frames (none when compiled).

    Each policy runs in blocks of consecutive steps, as training does (a step right after the other policy's
    step pays for the memory and caches that step left cold), and the blocks come in the order uncached,
    cached, cached, uncached, so that a drift of the machine's speed weighs on both sides alike; the first step
    of each block is not timed, the median of the others is. The FLOPs are counted in the untimed first step of
    the first uncached block and of the second cached one (its cache warm)."""
    runs = {}
    for cached in (False, True):
        policy = paper_policy(
            device, prompt_token_cache=cached, compile_model=compile_model, compile_mode=compile_mode
        ).train()
        optimizer = torch.optim.AdamW(policy.get_optim_params())
        runs[cached] = (policy, optimizer, paper_batch(policy.config, batch_size, prompt_frames, device))
    times, flops = {}, {}
    for phase in ("encoder", "others"):
        samples = {cached: [] for cached in runs}
        for block, cached in enumerate((False, True, True, False)):
            policy, optimizer, batch = runs[cached]
            set_phase(policy, phase)
            step = lambda p=policy, o=optimizer, b=batch: train_step(p, o, b)  # noqa: E731
            if block in (0, 2) and not compile_model:  # compiled kernels run past the FLOP counter
                flops[cached, phase] = gflop(step)
            else:
                step()  # the first cached block's fills the cache
            if compile_model and block < 2:
                step()  # the first block of each policy and phase compiles in its first steps
            samples[cached] += step_times(step, repeats, warmup=0)
        for cached, values in samples.items():
            times[cached, phase] = statistics.median(values)
    if not flops:
        return times, flops, None
    policy, _, batch = runs[True]
    with torch.no_grad():
        observation = lambda: policy.model.backbone_tokens(batch[IMAGE])  # noqa: E731
        backbone = gflop(observation), median_time(observation, repeats + 1, warmup=1)
    return times, flops, backbone


def rest_rates(
    times: dict, flops: dict, backbone: tuple[float, float], frames: int, prompt_frames: int, goal: float = 5
) -> tuple[float, float, float]:
    """The GFLOP/s of a cached step pair's work past the backbone's pass over its ``frames`` observation frames,
    and that rate as a fraction of the backbone's, measured and needed for ``goal``: a step's seconds modelled as
    its backbone GFLOP (observation frames, plus ``prompt_frames`` without the cache) at the backbone's rate and
    the rest of its GFLOP at the rest's rate."""
    phases = ("encoder", "others")
    vit_gflop, vit_s = backbone
    total = {cached: sum(flops[cached, phase] for phase in phases) for cached in (False, True)}
    vit = {True: 2 * vit_gflop, False: 2 * vit_gflop * (frames + prompt_frames) / frames}
    rest = {cached: total[cached] - vit[cached] for cached in (False, True)}
    rest_rate = rest[True] / (sum(times[True, phase] for phase in phases) - 2 * vit_s)
    room = vit[False] - goal * vit[True]  # <= 0: the goal is out of reach at any rate of the rest
    needed = (goal * rest[True] - rest[False]) / room if room > 0 else float("inf")
    return rest_rate, rest_rate / (vit_gflop / vit_s), needed


def peak_child(device: str, batch_size: int, prompt_frames: int, vision_backbone: str) -> None:
    """One training step per phase; prints the peak after each (the parent keeps the last line it got) and the
    step's time (the first step of the process: it includes the kernels' first-use costs)."""
    policy = paper_policy(device, prompt_cache_dtype="bfloat16", vision_backbone=vision_backbone).train()
    batch = paper_batch(policy.config, batch_size, prompt_frames, device)
    fill_prompt_cache(policy, batch)
    optimizer = torch.optim.AdamW(policy.get_optim_params())
    for phase in ("encoder", "others"):
        set_phase(policy, phase)
        sync()
        start = time.perf_counter()
        train_step(policy, optimizer, batch)
        sync()
        print(f"step_s {phase} {time.perf_counter() - start:.2f}", flush=True)
        if device == "cuda":
            peak = torch.cuda.max_memory_allocated() / 2**30
        else:
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux
        print(f"peak_gib {phase} {peak:.2f}", flush=True)


def peak_tag(batch_size: int, prompt_frames: int, vision_backbone: str) -> str:
    """``b32_p250``, with the prior's name when it is not the paper's ViT-B."""
    tag = f"b{batch_size}_p{prompt_frames}"
    return tag if vision_backbone == JEPTConfig.vision_backbone else f"{tag}_{vision_backbone.split('.')[0]}"


def peak_memory(
    device: str, batch_size: int, prompt_frames: int, vision_backbone: str, timeout: int
) -> tuple[float | None, str]:
    cmd = [sys.executable, "-m", "benchmarks.bench_paper_scale", "--child", f"--device={device}"]
    cmd += [
        f"--batch_size={batch_size}",
        f"--prompt_frames={prompt_frames}",
        f"--vision_backbone={vision_backbone}",
    ]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        out, status = run.stdout, f"exit {run.returncode}"
    except subprocess.TimeoutExpired as err:
        out = err.stdout.decode() if isinstance(err.stdout, bytes) else (err.stdout or "")
        status = "timeout"
    tag = peak_tag(batch_size, prompt_frames, vision_backbone)
    for phase, seconds in (line.split()[1:] for line in out.splitlines() if line.startswith("step_s ")):
        print(f"paper_train_step_{tag}_{phase}_s: {seconds}", flush=True)
    peaks = [line.split() for line in out.splitlines() if line.startswith("peak_gib ")]
    if not peaks:
        return None, status
    phases = ",".join(p[1] for p in peaks)
    return max(float(p[2]) for p in peaks), f"{status}, phases reached: {phases}"


def first_step_ratio(device: str, repeats: int) -> tuple[float, float, float]:
    policy = paper_policy(device).eval()
    cfg = policy.config
    shape = (1, cfg.max_prompt_length, 3, SIZE, SIZE)  # a bank prompt, uint8 as the preprocessor gives it
    prompt = torch.randint(0, 256, shape, dtype=torch.uint8, device=device)
    obs = {
        IMAGE: torch.rand(1, 3, SIZE, SIZE, device=device),
        STATE: torch.randn(1, 18, device=device),
        PROMPT_VIDEO: prompt,
        PROMPT_MASK: torch.ones(1, cfg.max_prompt_length, dtype=torch.bool, device=device),
        PROMPT_ID: torch.tensor([0], device=device),
    }
    policy.reset()
    policy.select_action(obs)  # the bank prompt's first use: its tokens and E_prt are computed here
    firsts, laters = [], []
    for _ in range(repeats):
        policy.reset()
        sync()
        start = time.perf_counter()
        policy.select_action(obs)
        sync()
        firsts.append(time.perf_counter() - start)
        laters.append(median_time(lambda: policy.select_action(obs), 3, warmup=0))
    first, later = statistics.median(firsts), statistics.median(laters)
    return first / later, first, later


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--prompt_frames", type=int, default=250)
    parser.add_argument("--peak_timeout", type=int, default=1800)
    parser.add_argument(
        "--vision_backbone",
        default=JEPTConfig.vision_backbone,
        help="the peak's backbone: a visual prior (random weights) in place of the paper's ViT-B",
    )
    parser.add_argument(
        "--speedup_shape",
        default="2,64",
        help="batch size and prompt frames of the speedup's steps (the goal is set at 2,64; 32,250 is the paper's)",
    )
    parser.add_argument(
        "--figures",
        default="speedup,first_step,peak",
        help="which figures to measure, comma-separated (the peak alone takes about 13 minutes on 2 CPU cores)",
    )
    parser.add_argument(
        "--compile_model",
        action="store_true",
        help="the speedup with both policies compiled (--policy.compile_model), names ending _compiled",
    )
    parser.add_argument("--compile_mode", default="default", help="torch.compile's mode with --compile_model")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    figures = set(args.figures.split(","))
    if figures - {"speedup", "first_step", "peak"}:
        parser.error(f"--figures takes speedup, first_step and/or peak, got {args.figures!r}")
    speedup_shape = args.speedup_shape.split(",")
    if len(speedup_shape) != 2 or not all(n.strip().isdigit() and int(n) > 0 for n in speedup_shape):
        parser.error(f"--speedup_shape takes BATCH,FRAMES (e.g. 32,250), got {args.speedup_shape!r}")
    torch.set_num_threads(os.cpu_count() or 1)
    if args.child:
        peak_child(args.device, args.batch_size, args.prompt_frames, args.vision_backbone)
        return

    if "speedup" in figures:
        batch_size, prompt_frames = (int(n) for n in speedup_shape)
        times, flops, backbone = prompt_cache_speedup(
            args.device, args.repeats, batch_size, prompt_frames, args.compile_model, args.compile_mode
        )
        suffix = "" if (batch_size, prompt_frames) == (2, 64) else f"_b{batch_size}_p{prompt_frames}"
        suffix += "_compiled" if args.compile_model else ""
        for phase in ("encoder", "others"):
            uncached, cached = times[False, phase], times[True, phase]
            print(f"paper_train_step{suffix}_{phase}_uncached_s: {uncached:.3f}")
            print(f"paper_train_step{suffix}_{phase}_cached_s: {cached:.3f}")
            if flops:
                gflops = f"{flops[False, phase]:.0f} {flops[True, phase]:.0f}"
                print(f"paper_train_step{suffix}_{phase}_gflop_uncached_cached: {gflops}")
            print(
                f"paper_train_step{suffix}_{phase}_prompt_cache_speedup: {uncached / cached:.2f}", flush=True
            )
        for name, values in (("speedup", times), ("flop_ratio", flops))[: 2 if flops else 1]:
            total = {cached: values[cached, "encoder"] + values[cached, "others"] for cached in (False, True)}
            print(
                f"paper_train_step{suffix}_prompt_cache_{name}: {total[False] / total[True]:.2f}", flush=True
            )
        if backbone is not None:
            frames = batch_size * (JEPTConfig.n_obs_steps + 1)
            rate, measured, needed = rest_rates(times, flops, backbone, frames, batch_size * prompt_frames)
            print(f"paper_backbone{suffix}_gflop_per_s: {backbone[0] / backbone[1]:.0f}")
            print(f"paper_train_step{suffix}_cached_rest_gflop_per_s: {rate:.0f}")
            print(f"paper_train_step{suffix}_rest_rate_measured: {measured:.2f}")
            print(f"paper_train_step{suffix}_rest_rate_needed: {needed:.2f}", flush=True)
    if "first_step" in figures:
        ratio, first, later = first_step_ratio(args.device, args.repeats + 1)
        print(f"select_action_first_step_s: {first:.3f}")
        print(f"select_action_later_step_s: {later:.3f}")
        print(f"select_action_first_step_vs_later: {ratio:.2f}", flush=True)
    if "peak" not in figures:
        return
    peak, status = peak_memory(
        args.device, args.batch_size, args.prompt_frames, args.vision_backbone, args.peak_timeout
    )
    name = f"paper_train_peak_gib_{peak_tag(args.batch_size, args.prompt_frames, args.vision_backbone)}"
    print(f"{name}: {'failed' if peak is None else f'{peak:.2f}'} ({args.device}, {status})")


if __name__ == "__main__":
    main()
