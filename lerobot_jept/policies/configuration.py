"""``VideoPolicyConfig``: the options every policy type of this package shares (the camera and self-state
inputs, the backbone, the single-frame and prompt Perceivers, the causal Transformer, the action head and its
bins, the optimizer groups, the prompt bank and the caches), with the paper's Tables 5-6 values as defaults, and
the small configuration that trains on a 2-core CPU (:data:`SMALL_CPU_OVERRIDES`).

Each policy type adds only what it uses: ``JEPTConfig`` the joint embedding prediction, its objective, schedule
and recipe; the baselines their own losses. JEPT's options are no options of a baseline
(``--policy.type=jept_dt_star --policy.ema_decay=0.5`` is an unknown argument); checkpoints saved when the
baselines carried them still load (:class:`RetiredJEPTOptions`).
"""

import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import draccus
import numpy as np
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import ConstantWithWarmupSchedulerConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_jept.envs.spec import ACTION_LABELLED
from lerobot_jept.policies.components.backbone import is_temporal
from lerobot_jept.registration import register_processor_steps

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
ACTION_RANGES = ("fixed", "dataset")
ACTION_DECODINGS = ("argmax", "expectation")
IDM_INPUTS = ("embedding", "self_state")  # what an inverse dynamics reads: frame tokens, or the self-state
RETIRED = "retired"  # metadata key of a field kept only to read old checkpoints


def installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lerobot_policy_jept")
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "0.0.0"


class PluginVersionError(ValueError):
    """A checkpoint saved by an incompatible lerobot_policy_jept."""


def check_plugin_version(saved: str, installed: str) -> None:
    """Checkpoints are compatible within one minor series (0.x) or major version (>= 1)."""

    def series(v: str) -> tuple[int, ...]:
        major, minor = (int(p) for p in v.split(".")[:2])
        return (major, minor) if major == 0 else (major,)

    if series(saved) != series(installed):
        raise PluginVersionError(
            f"This checkpoint was saved by lerobot_policy_jept {saved}, but {installed} is installed, and the "
            f"two are not compatible: install the matching plugin (pip install 'lerobot_policy_jept=="
            f"{'.'.join(map(str, series(saved)))}.*') to load it."
        )


def check_idm_input(idm_input: str) -> None:
    if idm_input not in IDM_INPUTS:
        raise ValueError(
            f"idm_input must be one of {IDM_INPUTS}, got {idm_input!r}: pass --policy.idm_input=embedding (what "
            "the paper's inverse dynamics reads) or self_state."
        )


@dataclass
class VideoPolicyConfig(PreTrainedConfig):
    """What every policy type here shares: inputs, one or more cameras ``observation.image*`` (C, H, W) and the
    self-state ``observation.state``; output, a 1-D ``action`` whose every dimension is classified into
    ``num_action_bins`` bins over [``action_low``, ``action_high``]. The prompt video comes from the caller as
    ``observation.prompt_video``, from ``prompt_video`` or from the prompt bank ``prompt_repo_id`` by the
    sample's task string (see ``processor_jept``). Defaults are the paper's Table 5-6 values.

    Args:
        n_obs_steps: context length k (Table 5: 8). Training samples hold k + 1 frames: the k context frames
            and the next one, whose joint embedding is the last target.
        image_size: the model's input resolution (Table 5 backbone: 224). Frames of another size are resized.
        vision_backbone: timm model name of the spatial encoder (paper: ``vit_base_patch16_224``). Visual prior
            injection (Section 4.4) is a change of this name: DINOv2 and SAM are timm names
            (``vit_base_patch14_dinov2.lvd142m``, ``samvit_base_patch16.sa1b``), ``videomae_small`` /
            ``videomae_base`` (Hugging Face VideoMAE) and ``raft_small`` / ``raft_large`` (torchvision optical
            flow) see each frame with the one before it (``components/backbone.py``).
        pretrained_backbone: load the backbone's pretrained weights (through timm, torchvision or a weights file;
            needs the Hub, or ``backbone_weights_path``).
        backbone_weights_path: local weights file (.safetensors or .pth) for the backbone.
        freeze_backbone: keep the backbone fixed (paper: frozen), so the Perceivers act as adaptors.
        perceiver_dim, perceiver_heads, perceiver_encoder_cross_layers, perceiver_encoder_self_layers,
            perceiver_decoder_cross_layers: the Perceiver-IO structure shared by the single-frame and the
            temporal (prompt) Perceivers (Table 5: 512, 8, 1, 2, 1).
        frame_perceiver_latents, frame_perceiver_queries, frame_perceiver_ff_dim, frame_perceiver_dropout:
            single-frame Perceiver-IO (64, 8, 1024, 0.1). N_obs = queries + 1 self-state token = 9.
        prompt_perceiver_latents, prompt_perceiver_queries, prompt_perceiver_ff_dim, prompt_perceiver_dropout:
            the temporal Perceiver-IO of the prompt encoder (128, N_prt = 32, 892, 0.08).
        max_prompt_length: prompt frames at most (250); longer prompts are uniformly subsampled.
        predictor_dim, predictor_heads, predictor_layers, predictor_ff_dim, predictor_dropout: the causal
            Transformer (584, 8, 4, 1168, 0.05).
        action_head_dim, action_head_heads, action_head_layers, action_head_ff_dim: Gamma_act (256, 4, 2, 512).
        num_action_bins, action_low, action_high: the action discretisation (7 bins over the env's [-1, 1]).
        action_range, action_lows, action_highs: not in the paper, whose envs all act in [-1, 1]. ``"fixed"``
            (default): every dimension over [``action_low``, ``action_high``]. ``"dataset"``: each dimension over
            its own [min, max] in the training data (from LeRobot's dataset statistics), for absolute actions
            such as a real arm's joint angles in degrees; the fitted ranges are kept in ``action_lows`` /
            ``action_highs`` and saved with the checkpoint (or given directly).
        action_dim: action size; taken from the dataset's ``action`` feature, needed only for datasets without
            one (expert videos alone).
        action_decoding: how control turns each dimension's bin logits into an action, not in the paper.
            ``"argmax"`` (default, the paper): the most likely bin's centre. ``"expectation"``: the mean of the
            bin centres under the softmax of the logits, a continuous action between neighbouring bins.
        action_smoothing: not in the paper; in control, each action becomes ``(1 - b) a_t + b a_{t-1}`` with
            ``a_{t-1}`` the previous executed (smoothed) action of the episode, ``b`` this value in [0, 1)
            (0, the default: off).
        optimizer_lr_encoder, optimizer_lr_prompt, optimizer_lr_predictor, optimizer_weight_decay,
            optimizer_grad_clip_norm, scheduler_warmup_steps: Table 6 (3e-5, 7e-5, 7e-5, 1e-4, 1.0, 200).
        weight_ema_decay: not in the paper; an exponential moving average of the trained weights, moved after
            every optimizer step with decay ``min(weight_ema_decay, (1 + n) / (10 + n))`` at step n, saved beside
            the weights in the checkpoint and used in eval mode (control, ``lerobot-eval``); train mode, and so
            a resumed run, continues from the trained weights. 0.998 averages over about the last 500 steps.
            None (default): off.
        prompt_repo_id, prompt_root: the prompt bank (a LeRobotDataset of prompt videos, e.g. the builder's
            ``ORG/NAME_prompts``) and an optional local root for it. Training draws a random prompt of each
            sample's task from it; control, when neither the env nor the caller gives a prompt, takes the first
            prompt of the task.
        prompt_video: a video file (any format FFmpeg reads) shown as the prompt in control, in place of a bank
            lookup: ``--policy.prompt_video=clip.mp4`` for ``lerobot-eval``, ``lerobot-rollout`` or
            ``JEPTPolicy.from_pretrained(path, prompt_video=...)``. Decoded once with LeRobot's video decoding,
            subsampled to ``max_prompt_length`` frames. ``prompt_root`` and ``prompt_video`` are local paths and
            are never saved with a checkpoint.
        plugin_version: the lerobot_policy_jept version that made the checkpoint; loading it with an
            incompatible version fails with a message naming the version to install.
        cache_frame_tokens: ``select_action`` reuses per-frame tokens of the previous k - 1 frames (off only
            to check the cache against full recomputation).
        prompt_token_cache: with a frozen backbone, the backbone tokens of each prompt are computed once and
            reused in every training step and evaluation episode (exact: a frozen backbone never changes them);
            bank prompts are keyed by bank and episode, other prompts by their content. Without gradient and in
            eval mode, E_prt itself is also kept per batch of prompts until a parameter it depends on changes,
            so an episode's first control step costs what a later one does.
        prompt_cache_dtype: float32 (exact), bfloat16 or float16 (half the memory, rounded tokens).
        prompt_cache_max_gib: size bound of the prompt-token cache; the least recently used prompts go first.
        backbone_chunk_size: frames per backbone pass (prompt and observation frames), bounding the activation
            memory of long prompts. A backbone trained with batch norm (the small CPU configuration) takes all
            frames in one pass in training, since chunks would change its batch statistics.
        prompt_frame_chunk_size, prompt_checkpointing: frames per pass of the prompt's per-frame Perceiver;
            with more than one chunk in a training step, each chunk's activations are recomputed in the
            backward pass instead of stored (same gradients, memory independent of batch x prompt length).
        compile_model, compile_mode: LeRobot's names (as in ``pi0``): ``torch.compile`` each Perceiver-IO whole
            and each Transformer layer and cross-attention block outside them, in place (regional compilation:
            units of one shape share their compiled code; parameter names and checkpoints unchanged), in
            ``compile_mode`` (``default``, ``reduce-overhead``, ``max-autotune``, ``max-autotune-no-cudagraphs``).
            The frozen backbone stays as it is. The first steps of each phase compile (minutes on a CPU, which
            needs a C++ compiler); the values are those of the eager model up to rounding, and dropout draws its
            masks from inductor's generator instead of torch's.
    """

    n_obs_steps: int = 8
    image_size: int = 224

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,  # the backbone applies its own (timm) normalisation
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.IDENTITY,  # discretised over the env's action range instead
        }
    )

    vision_backbone: str = "vit_base_patch16_224"
    pretrained_backbone: bool = True
    backbone_weights_path: str | None = None
    freeze_backbone: bool = True

    perceiver_dim: int = 512
    perceiver_heads: int = 8
    perceiver_encoder_cross_layers: int = 1
    perceiver_encoder_self_layers: int = 2
    perceiver_decoder_cross_layers: int = 1
    frame_perceiver_latents: int = 64
    frame_perceiver_queries: int = 8
    frame_perceiver_ff_dim: int = 1024
    frame_perceiver_dropout: float = 0.1
    prompt_perceiver_latents: int = 128
    prompt_perceiver_queries: int = 32
    prompt_perceiver_ff_dim: int = 892
    prompt_perceiver_dropout: float = 0.08
    max_prompt_length: int = 250

    predictor_dim: int = 584
    predictor_heads: int = 8
    predictor_layers: int = 4
    predictor_ff_dim: int = 1168
    predictor_dropout: float = 0.05

    action_head_dim: int = 256
    action_head_heads: int = 4
    action_head_layers: int = 2
    action_head_ff_dim: int = 512

    num_action_bins: int = 7
    action_low: float = -1.0
    action_high: float = 1.0
    action_range: str = "fixed"
    action_lows: list[float] | None = None
    action_highs: list[float] | None = None
    action_dim: int | None = None
    action_decoding: str = "argmax"
    action_smoothing: float = 0.0

    optimizer_lr_encoder: float = 3e-5
    optimizer_lr_prompt: float = 7e-5
    optimizer_lr_predictor: float = 7e-5
    optimizer_weight_decay: float = 1e-4
    optimizer_grad_clip_norm: float = 1.0
    scheduler_warmup_steps: int = 200
    weight_ema_decay: float | None = None

    prompt_repo_id: str | None = None
    prompt_root: str | None = None
    prompt_video: str | None = None
    cache_frame_tokens: bool = True
    prompt_token_cache: bool = True
    prompt_cache_dtype: str = "float32"
    prompt_cache_max_gib: float = 8.0
    backbone_chunk_size: int = 64
    prompt_frame_chunk_size: int = 256
    prompt_checkpointing: bool = True
    compile_model: bool = False
    compile_mode: str = "default"
    drop_n_last_frames: int = 1  # the last frame of an episode has no next observation to predict
    plugin_version: str = field(default_factory=installed_version)

    def __post_init__(self):
        super().__post_init__()
        check_plugin_version(self.plugin_version, installed_version())
        register_processor_steps(self)
        if self.prompt_cache_dtype not in ("float32", "bfloat16", "float16"):
            raise ValueError(
                f"prompt_cache_dtype must be float32, bfloat16 or float16, got {self.prompt_cache_dtype!r}."
            )
        if self.compile_mode not in COMPILE_MODES:
            raise ValueError(
                f"compile_mode must be one of {COMPILE_MODES} (torch.compile's modes), got {self.compile_mode!r}."
            )
        if self.n_obs_steps < 1:
            raise ValueError(f"n_obs_steps (the context length k) must be >= 1, got {self.n_obs_steps}.")
        if self.num_action_bins < 2:
            raise ValueError(f"num_action_bins must be >= 2, got {self.num_action_bins}.")
        if not self.action_low < self.action_high:
            raise ValueError(
                f"action_low ({self.action_low}) must be below action_high ({self.action_high})."
            )
        if self.action_decoding not in ACTION_DECODINGS:
            raise ValueError(
                f"action_decoding must be one of {ACTION_DECODINGS}, got {self.action_decoding!r}: pass "
                "--policy.action_decoding=argmax (the most likely bin) or expectation (the mean over the bins)."
            )
        if not 0.0 <= self.action_smoothing < 1.0:
            raise ValueError(
                f"action_smoothing must be in [0, 1) (the previous action's weight), got {self.action_smoothing}."
            )
        if self.weight_ema_decay is not None and not 0.0 < self.weight_ema_decay < 1.0:
            raise ValueError(
                f"weight_ema_decay must be in (0, 1) (e.g. 0.998), or None for no weight average; got "
                f"{self.weight_ema_decay}."
            )
        if self.action_range not in ACTION_RANGES:
            raise ValueError(f"action_range must be one of {ACTION_RANGES}, got {self.action_range!r}.")
        if (self.action_lows is None) != (self.action_highs is None) or (
            self.action_lows is not None
            and (
                len(self.action_lows) != len(self.action_highs)
                or not all(lo < hi for lo, hi in zip(self.action_lows, self.action_highs, strict=True))
            )
        ):
            raise ValueError(
                "action_lows and action_highs give each action dimension's range: both or neither, of one length, "
                f"each low below its high; got {self.action_lows} and {self.action_highs}."
            )

    @classmethod
    def small(cls, **overrides) -> "VideoPolicyConfig":
        """The documented small configuration: trains on a 2-core CPU (random-initialised ResNet-10t
        backbone at 96 px, context 4, narrow Perceivers and Transformers, 8-frame prompts)."""
        own = {f.name for f in dataclasses.fields(cls) if f.init}
        return cls(**{**{k: v for k, v in SMALL_CPU_OVERRIDES.items() if k in own}, **overrides})

    # LeRobot contract -------------------------------------------------------------------------------------

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 2))  # k context frames and the next one

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1))  # a_{t-k+1} .. a_t

    @property
    def reward_delta_indices(self) -> None:
        return None

    def _save_pretrained(self, save_directory) -> None:
        """LeRobot's save (``config.json``, with the choice ``type``), without the local paths (``prompt_root``,
        ``prompt_video``: a checkpoint carries no path of the machine that wrote it) and without the fields kept
        only to read old checkpoints."""
        from lerobot.configs.policies import CONFIG_NAME

        config = draccus.encode(self, PreTrainedConfig)
        for f in dataclasses.fields(self):
            if f.metadata.get(RETIRED):
                del config[f.name]
        config["prompt_root"] = config["prompt_video"] = None
        with open(Path(save_directory) / CONFIG_NAME, "w") as file:
            json.dump(config, file, indent=4)

    def get_optimizer_preset(self) -> AdamWConfig:
        """AdamW with one learning rate per parameter group (the policy's ``get_optim_params``). LeRobot
        replaces any ``--optimizer.*`` flag with this preset, so such a flag is refused, not ignored."""
        given = sorted({arg.split("=")[0] for arg in sys.argv[1:] if arg.startswith("--optimizer.")})
        if given:
            raise ValueError(
                f"{', '.join(given)} would be ignored: {self.type} trains each parameter group at its own rate, "
                "set by --policy.optimizer_lr_encoder, --policy.optimizer_lr_prompt and "
                "--policy.optimizer_lr_predictor (and --policy.optimizer_weight_decay, "
                "--policy.optimizer_grad_clip_norm). For one rate for every parameter instead, pass "
                "--use_policy_training_preset=false with --optimizer.type=adamw --optimizer.lr=... and a "
                "--scheduler.type."
            )
        return AdamWConfig(
            lr=self.optimizer_lr_predictor,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> ConstantWithWarmupSchedulerConfig:
        return ConstantWithWarmupSchedulerConfig(num_warmup_steps=self.scheduler_warmup_steps)

    @property
    def image_keys(self) -> list[str]:
        """The cameras, in a fixed order (each one's frames are tokenised together, tagged by camera)."""
        return sorted(self.image_features)

    @property
    def image_key(self) -> str:
        """The first camera (whose padding marks a window's padded frames)."""
        return self.image_keys[0]

    def fit_action_range(self, dataset_stats: dict | None) -> None:
        """With ``action_range="dataset"``, each action dimension's range is its [min, max] over the training
        data (LeRobot's dataset statistics), kept in ``action_lows`` / ``action_highs`` (and so in the
        checkpoint); once set, they are not fitted again."""
        if self.action_range != "dataset" or self.action_lows is not None:
            return
        stats = (dataset_stats or {}).get(ACTION) or {}
        if "min" not in stats or "max" not in stats:
            raise ValueError(
                "--policy.action_range=dataset takes each action dimension's range from the dataset's statistics "
                "(min and max of `action`), and there are none: train on a LeRobotDataset with an `action` "
                "feature, or give the ranges with --policy.action_lows=[...] --policy.action_highs=[...]."
            )
        lows = np.asarray(stats["min"], dtype=np.float64).reshape(-1)
        highs = np.asarray(stats["max"], dtype=np.float64).reshape(-1)
        constant = highs - lows < 1e-6  # a dimension that never moves: one bin width either side
        lows[constant], highs[constant] = lows[constant] - 1.0, highs[constant] + 1.0
        self.action_lows, self.action_highs = lows.tolist(), highs.tolist()

    def action_bounds(self) -> tuple:
        """The discretisation's range: per-dimension lists (``action_lows``, ``action_highs``), or the one
        range [``action_low``, ``action_high``] of every dimension."""
        if self.action_lows is not None:
            return self.action_lows, self.action_highs
        if self.action_range == "dataset":
            raise ValueError(
                "action_range=dataset but the per-dimension ranges were never fitted: build the policy with "
                "the dataset's statistics (make_policy(cfg, ds_meta=...)) or pass --policy.action_lows/highs."
            )
        return self.action_low, self.action_high

    @property
    def resolved_action_dim(self) -> int:
        if ACTION in self.output_features:
            return self.output_features[ACTION].shape[0]
        if self.action_dim is None:
            raise ValueError(
                "The dataset has no `action` feature (expert videos only), so the action size is unknown: "
                "pass --policy.action_dim=N (4 for Meta-World)."
            )
        return self.action_dim

    def validate_features(self) -> None:
        # The mixes' per-frame label marker is read by the preprocessor, never by the model.
        self.input_features.pop(ACTION_LABELLED, None)
        if not self.image_features:
            raise ValueError(
                "JEPT needs a camera image (an `observation.image*` feature) but the dataset has none: "
                "build it with `jept-build-metaworld` or add an image feature."
            )
        if len(self.image_features) > 1 and is_temporal(self.vision_backbone):
            raise ValueError(
                f"--policy.vision_backbone={self.vision_backbone} pairs each frame with the one before it, which "
                f"is defined for one camera; the dataset has {sorted(self.image_keys)}: keep one with "
                "--rename_map or lerobot.datasets.dataset_tools.remove_feature, or choose a per-frame backbone."
            )
        if OBS_STATE not in self.input_features or self.input_features[OBS_STATE].type != FeatureType.STATE:
            raise ValueError(
                "JEPT needs the robot self-state `observation.state` (paper, Appendix B.1) but the dataset "
                "has none: rebuild the dataset with the state recorded."
            )
        if ACTION in self.output_features:
            shape = self.output_features[ACTION].shape
            if len(shape) != 1:
                raise ValueError(
                    f"JEPT classifies each dimension of a 1-D action into {self.num_action_bins} bins, but "
                    f"the dataset's `action` has shape {tuple(shape)}: flatten it into a vector."
                )
            if self.action_dim is not None and self.action_dim != shape[0]:
                raise ValueError(
                    f"--policy.action_dim={self.action_dim} but the dataset's `action` has {shape[0]} "
                    "dimensions: drop --policy.action_dim (it is only for datasets without actions)."
                )
        self.resolved_action_dim  # noqa: B018  (raises a clear error when there is no action at all)


SMALL_CPU_OVERRIDES = dict(
    n_obs_steps=4,
    image_size=96,
    vision_backbone="resnet10t",
    pretrained_backbone=False,
    freeze_backbone=False,
    perceiver_dim=96,
    perceiver_heads=4,
    perceiver_encoder_self_layers=1,
    frame_perceiver_latents=16,
    frame_perceiver_queries=4,
    frame_perceiver_ff_dim=192,
    prompt_perceiver_latents=16,
    prompt_perceiver_queries=8,
    prompt_perceiver_ff_dim=192,
    max_prompt_length=8,
    joint_embedding_dim=64,
    temporal_dim=96,
    temporal_heads=4,
    temporal_layers=1,
    temporal_ff_dim=192,
    predictor_dim=128,
    predictor_heads=4,
    predictor_layers=2,
    predictor_ff_dim=256,
    action_head_dim=64,
    action_head_heads=4,
    action_head_layers=1,
    action_head_ff_dim=128,
    obs_head_hidden_dim=128,
    phase_steps=100,
    prompt_warmup_steps=100,
    optimizer_lr_encoder=3e-4,
    optimizer_lr_prompt=7e-4,
    optimizer_lr_predictor=7e-4,
    scheduler_warmup_steps=50,
)


# JEPT's options (the joint embedding prediction, its objective, schedule and recipe): no baseline has them.
JEPT_OPTIONS = (
    "joint_embedding_dim",
    "temporal_dim",
    "temporal_heads",
    "temporal_layers",
    "temporal_ff_dim",
    "temporal_dropout",
    "obs_head_hidden_dim",
    "obs_head_layers",
    "action_loss_weight",
    "state_loss_weight",
    "ema_decay",
    "phase_schedule",
    "phase_steps",
    "prompt_warmup_steps",
    "prompt_align_weight",
    "prompt_align_temperature",
    "prompt_swap_weight",
    "prompt_swap_margin",
    "prompt_dropout",
    "prompt_guidance",
    "idm_input",
    "idm_history",
    "recipe",
)

# The JEPT options a baseline's checkpoint saved before they left the baselines' configs still holds: read (so it
# loads and resumes as it was saved) and never used, never offered on the command line, never saved again.
RetiredJEPTOptions = dataclasses.make_dataclass(
    "RetiredJEPTOptions",
    [
        (name, Any, field(default=None, init=False, repr=False, compare=False, metadata={RETIRED: True}))
        for name in JEPT_OPTIONS
    ],
)


@dataclass
class BehaviourCloningConfig(VideoPolicyConfig, RetiredJEPTOptions):
    """Base of the baselines that clone actions from the k context frames (``jept_dt_star``,
    ``jept_vid2robot``, and ``jept_lapo``, which also reads the next frame): JEPT's sizes, no joint embedding
    target, samples of k frames without a next one."""

    drop_n_last_frames: int = 0

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 1))  # o_{t-k+1} .. o_t
