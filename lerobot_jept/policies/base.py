"""What JEPT and its baselines (``jept_dt_star``, ``jept_vid2robot``, ``jept_idm``) share, robomimic-style: one base network with
the frozen-or-trained spatial backbone and the prompt path, builders for the parts the paper shares between them
(single-frame Perceiver tokenizer, prompt video encoder, action head), and one base policy with the action bins,
the masked action loss, the prompt lookup, the per-frame token cache of control and LeRobot's Hub hooks.
"""

import dataclasses
import json
from collections import OrderedDict, deque
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812
from einops import rearrange
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from lerobot_jept.envs.rendering import INSTALL
from lerobot_jept.policies.components.attention import CrossAttentionBlock
from lerobot_jept.policies.components.backbone import SpatialBackbone
from lerobot_jept.policies.components.encoders import ObservationTokenizer, PromptVideoEncoder
from lerobot_jept.policies.components.perceiver import PerceiverIO
from lerobot_jept.policies.components.predictor import ActionHead, DTStarTransformer, SelfStateInverseDynamics
from lerobot_jept.policies.components.weight_average import WeightAverage
from lerobot_jept.policies.configuration import PluginVersionError, VideoPolicyConfig
from lerobot_jept.policies.discretization import bin_centres
from lerobot_jept.policies.prompts import PromptBank, load_prompt_video, resize_frames, unit_float

PROMPT_VIDEO = "observation.prompt_video"
PROMPT_MASK = "observation.prompt_video_mask"
# (B,) int64 identity of a bank prompt (bank fingerprint and episode), set by the jept_prompt_video step; a prompt
# given by the caller has none and is identified by its content.
PROMPT_ID = "observation.prompt_id"
CACHE_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
IGNORE_INDEX = -100  # action labels that take no part in the action loss (unlabelled or padded frames)


def transformer_kwargs(config: VideoPolicyConfig, which: str) -> dict:
    """Self-attention stack sizes of the ``temporal`` encoder or the causal ``predictor`` (Table 5)."""
    return {name: getattr(config, f"{which}_{name}") for name in ("heads", "ff_dim", "layers", "dropout")}


def perceiver_kwargs(config: VideoPolicyConfig, which: str) -> dict:
    """Perceiver-IO arguments: the shared structure plus the ``frame_`` or ``prompt_`` sizes of Table 5."""
    return dict(
        num_latents=getattr(config, f"{which}_perceiver_latents"),
        num_queries=getattr(config, f"{which}_perceiver_queries"),
        ff_dim=getattr(config, f"{which}_perceiver_ff_dim"),
        dropout=getattr(config, f"{which}_perceiver_dropout"),
        heads=config.perceiver_heads,
        encoder_cross_layers=config.perceiver_encoder_cross_layers,
        encoder_self_layers=config.perceiver_encoder_self_layers,
        decoder_cross_layers=config.perceiver_decoder_cross_layers,
    )


def compile_units(model: nn.Module, mode: str) -> None:
    """``torch.compile`` in place each Perceiver-IO of ``model`` whole and each Transformer layer and
    cross-attention block outside them, the backbone left as it is (``compile_model``). Compiling these rather
    than the whole forward keeps the Python around them (prompt caches, phase switches) eager, and units of one
    shape share their compiled code."""
    # each unit's shape x train or eval x gradient mode is a graph of its own: torch's default of 8 per code
    # object would leave the later ones eager
    torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
    skip = ("backbone.",)
    for name, module in model.named_modules():  # parents come before their children
        if isinstance(module, (PerceiverIO, nn.TransformerEncoderLayer, CrossAttentionBlock)) and not (
            f"{name}.".startswith(skip)
        ):
            module.compile(mode=mode)
            skip += (f"{name}.",)


def make_backbone(config: VideoPolicyConfig) -> SpatialBackbone:
    return SpatialBackbone(
        config.vision_backbone,
        config.pretrained_backbone,
        config.freeze_backbone,
        config.image_size,
        config.backbone_weights_path,
    )


def make_tokenizer(config: VideoPolicyConfig, backbone_dim: int) -> ObservationTokenizer:
    """The single-timestep encoder: per-frame Perceiver-IO + self-state token (N_obs = queries + 1)."""
    state_dim = config.input_features[OBS_STATE].shape[0]
    return ObservationTokenizer(
        backbone_dim,
        state_dim,
        perceiver=perceiver_kwargs(config, "frame"),
        dim=config.perceiver_dim,
        num_cameras=len(config.image_keys),
    )


def make_prompt_encoder(config: VideoPolicyConfig, backbone_dim: int) -> PromptVideoEncoder:
    return PromptVideoEncoder(
        backbone_dim,
        frame_perceiver=perceiver_kwargs(config, "frame"),
        video_perceiver=perceiver_kwargs(config, "prompt"),
        dim=config.perceiver_dim,
        max_frames=config.max_prompt_length,
        chunk_size=config.prompt_frame_chunk_size,
        checkpointing=config.prompt_checkpointing,
    )


def make_action_head(
    config: VideoPolicyConfig, width: int, outputs: int | None = None, classes: int | None = None
) -> ActionHead:
    """Gamma_act at the config's sizes: ``outputs`` queries (default: the action dimensions) of ``classes``
    logits each (default: the action bins)."""
    return ActionHead(
        width,
        outputs or config.resolved_action_dim,
        classes or config.num_action_bins,
        dim=config.action_head_dim,
        heads=config.action_head_heads,
        layers=config.action_head_layers,
        ff_dim=config.action_head_ff_dim,
    )


def make_dt_star_transformer(config: VideoPolicyConfig) -> DTStarTransformer:
    """DT*'s causal Transformer over ``[E_prt | o_t-k+1, ..., o_t]`` at the ``predictor_*`` sizes."""
    return DTStarTransformer(
        config.perceiver_dim,
        config.predictor_dim,
        **transformer_kwargs(config, "predictor"),
        max_steps=config.n_obs_steps,
        tokens_per_step=config.frame_perceiver_queries + 1,
    )


def make_state_inverse_dynamics(config: VideoPolicyConfig) -> SelfStateInverseDynamics:
    """The inverse dynamics on the self-state and its change (``idm_input="self_state"``)."""
    return SelfStateInverseDynamics(
        config.predictor_dim,
        config.input_features[OBS_STATE].shape[0],
        config.resolved_action_dim,
        config.num_action_bins,
        config.obs_head_hidden_dim,
        config.obs_head_layers,
        config.idm_history or 0,  # jept_idm reads the one change (its retired field is None)
        getattr(config, "chunk_size", 1),  # jept_idm reads actions, it predicts no change
    )


def content_key(frames: Tensor) -> str:
    """A digest of a prompt's frames (their exact float bytes): the cache key of a prompt not from a bank."""
    import hashlib

    data = frames.detach().float().contiguous().cpu().numpy().tobytes()
    return hashlib.blake2b(data, digest_size=16).hexdigest() + f":{tuple(frames.shape)}"


def parameter_versions(modules: list[nn.Module]) -> tuple:
    """The in-place versions of the modules' parameters and buffers: every optimizer step and every load changes
    them, so a cache of their outputs keyed by them is never stale."""
    return tuple(t._version for m in modules for t in (*m.parameters(), *m.buffers()))


class VisualPolicyNet(nn.Module):
    """Base of the networks. Subclasses set ``backbone`` (a :class:`SpatialBackbone`) and, when they take a
    prompt, ``prompt_encoder``; :meth:`frame_tokens` is how they turn frames into observation tokens."""

    config: VideoPolicyConfig
    backbone: SpatialBackbone

    def backbone_tokens(self, images: Tensor) -> Tensor:
        """(..., 3, H, W) in [0, 1] (or uint8 in [0, 255], converted chunk by chunk: bank prompts come so) ->
        (..., P, C), resized to the model's resolution, ``backbone_chunk_size``
        frames at a time (memory does not grow with the number of frames beyond one chunk's activations). Chunks
        are exact only when a frame's tokens do not depend on the other frames of its pass: a backbone whose
        batch norm normalises by batch statistics (trained, in training mode: the small CPU configuration)
        takes all frames in one pass, as before chunking existed.

        A temporal prior (optical flow, VideoMAE) pairs each frame with the one before it along the last leading
        axis (time: (B, T, ...) windows, (N, ...) prompt frames); the first frame is paired with itself."""
        lead = images.shape[:-3]
        flat = images.reshape(-1, *images.shape[-3:])
        before = None
        if self.backbone.temporal:
            before = torch.cat([images[..., :1, :, :, :], images[..., :-1, :, :, :]], dim=-4)
            before = before.reshape(flat.shape)
        size, chunk = self.config.image_size, max(1, self.config.backbone_chunk_size)
        if self.backbone.uses_batch_statistics:
            chunk = len(flat)
        out = []
        for start in range(0, len(flat), chunk):
            parts = [unit_float(x[start : start + chunk]) for x in (flat, before) if x is not None]
            if parts[0].shape[-2:] != (size, size):
                parts = [
                    F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
                    for x in parts
                ]
            out.append(self.backbone(*parts))
        tokens = torch.cat(out) if len(out) > 1 else out[0]
        return tokens.reshape(*lead, *tokens.shape[1:])

    def prompt_keys(self, video: Tensor, real: Tensor, ids: Tensor | None) -> list[tuple]:
        """The cache key of each prompt of a batch: a bank prompt by its id and length, another by content."""
        bank = [-1] * video.shape[0] if ids is None else ids.tolist()  # one device sync for the batch
        lengths = real.sum(1).tolist()
        return [
            ("bank", i, n) if i >= 0 else ("content", content_key(video[b][real[b]]))
            for b, (i, n) in enumerate(zip(bank, lengths, strict=True))
        ]

    def prompt_backbone_tokens(self, video: Tensor, mask: Tensor | None, ids: Tensor | None = None) -> Tensor:
        """Backbone tokens (B, N, P, C) of prompt frames (B, N, 3, H, W), without gradient.

        The fast path (exact): with a frozen backbone and ``prompt_token_cache``, a prompt's tokens never change,
        so they are computed once per prompt (bank prompts by ``ids``, others by their content) and kept, in
        ``prompt_cache_dtype`` on the policy's device, the least recently used dropped past
        ``prompt_cache_max_gib``; the batch comes back in that dtype (the prompt encoder casts chunk by chunk)
        and padded frames get zero tokens (the prompt encoder masks them out). Otherwise every frame goes
        through the backbone, as the reference path."""
        cfg = self.config
        with torch.no_grad():
            if not (cfg.freeze_backbone and cfg.prompt_token_cache):
                return self.backbone_tokens(video)
            cache = self.prompt_cache()
            b, n = video.shape[:2]
            real = torch.ones(b, n, dtype=torch.bool, device=video.device) if mask is None else mask.bool()
            keys = self.prompt_keys(video, real, ids)
            for i, key in enumerate(keys):
                if key in cache:
                    cache.move_to_end(key)
                else:
                    cache[key] = self.backbone_tokens(video[i][real[i]]).to(
                        CACHE_DTYPES[cfg.prompt_cache_dtype]
                    )
            first = cache[keys[0]]
            out = first.new_zeros(b, n, *first.shape[1:])
            for i, key in enumerate(keys):
                out[i, real[i]] = cache[key]
            size = sum(t.numel() * t.element_size() for t in cache.values())
            while len(cache) > b and size > cfg.prompt_cache_max_gib * 2**30:
                _, dropped = cache.popitem(last=False)
                size -= dropped.numel() * dropped.element_size()
            return out

    def prompt_cache(self) -> OrderedDict:
        """The prompt-token cache (key -> tokens (N, P, C)), emptied when the backbone's weights have changed
        since it was filled (a checkpoint loaded into this model)."""
        versions = parameter_versions([self.backbone])
        if self.__dict__.get("_prompt_token_versions") != versions:
            self.__dict__["_prompt_token_cache"] = OrderedDict()
            self.__dict__["_prompt_token_versions"] = versions
        return self.__dict__["_prompt_token_cache"]

    def clear_prompt_cache(self) -> None:
        for name in ("_prompt_token_cache", "_prompt_token_versions", "_prompt_embedding_cache"):
            self.__dict__.pop(name, None)

    @staticmethod
    def tokenize(tokenizer: ObservationTokenizer, tokens: Tensor, state: Tensor) -> Tensor:
        """Backbone tokens (B, T, P, C), or (B, T, K, P, C) of K cameras, + state (B, T, S) -> observation tokens
        (B, T, N_obs, D)."""
        b = tokens.shape[0]
        obs = tokenizer(rearrange(tokens, "b t ... c -> (b t) ... c"), rearrange(state, "b t s -> (b t) s"))
        return rearrange(obs, "(b t) n d -> b t n d", b=b)

    def frame_tokens(self, images: Tensor, state: Tensor) -> Tensor:
        """Frames (B, T, 3, H, W), or (B, T, K, 3, H, W) of K cameras, + state (B, T, S) -> observation tokens
        (B, T, N_obs, D), through the model's ``tokenizer``."""
        return self.tokenize(self.tokenizer, self.backbone_tokens(images), state)

    def encode_prompt(self, video: Tensor, mask: Tensor | None, ids: Tensor | None = None) -> Tensor:
        """(B, N, 3, H, W) prompt frames -> E_prt (B, N_prt, D). Only the Perceivers learn from prompts
        (Appendix A.2): the backbone sees them without gradient, even when it is trained on observations."""
        cfg = self.config
        if not (cfg.prompt_token_cache and not self.training and not torch.is_grad_enabled()):
            return self.prompt_encoder(self.prompt_backbone_tokens(video, mask, ids), mask)
        # control repeats the same prompts every episode: keep E_prt while the parameters stay the same (exact)
        real = (
            torch.ones(video.shape[:2], dtype=torch.bool, device=video.device)
            if mask is None
            else mask.bool()
        )
        key = (
            tuple(self.prompt_keys(video, real, ids)),
            parameter_versions([self.prompt_encoder, self.backbone]),
        )
        cached = self.__dict__.get("_prompt_embedding_cache")
        if cached is None or cached[0] != key:
            cached = (key, self.prompt_encoder(self.prompt_backbone_tokens(video, mask, ids), mask))
            self.__dict__["_prompt_embedding_cache"] = cached
        return cached[1]


class DiscreteActionPolicy(PreTrainedPolicy):
    """Base policy: actions classified into ``num_action_bins`` bins per dimension (the preprocessor's
    ``jept_action_bins`` gives the labels, ``select_action`` returns bin centres), a step counter that LeRobot
    advances through ``update()``, the prompt from the batch, and the checkpoint and Hub behaviour."""

    config_class = VideoPolicyConfig  # every subclass sets its own (LeRobot requires both on every class)
    name = "discrete_action_policy"
    model_class: type[VisualPolicyNet]  # the network, built from the config

    def __init__(self, config: VideoPolicyConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.model = self.model_class(config)
        if config.compile_model:
            compile_units(self.model, config.compile_mode)
        if config.weight_ema_decay is not None:
            self.weight_average = WeightAverage(self.model, config.weight_ema_decay)
        # Optimizer steps taken; persistent so a resumed run continues any step-driven schedule.
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))
        config.fit_action_range(kwargs.get("dataset_stats"))
        centres = bin_centres(config.num_action_bins, *config.action_bounds())
        self.register_buffer("bin_centres", torch.as_tensor(centres, dtype=torch.float32), persistent=False)
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *args, **kwargs):
        """LeRobot's loading (safetensors only), with a version mismatch raised as itself, not as the config
        parser's wrapper around it. Config options can be given by name (``prompt_video="clip.mp4"``), as
        ``--policy.<option>`` gives them to LeRobot's commands."""
        options = {
            name: kwargs.pop(name)
            for name in list(kwargs)
            if name in {f.name for f in dataclasses.fields(cls.config_class) if f.init}
        }
        try:
            if options:
                from lerobot.configs.policies import PreTrainedConfig

                config = kwargs.pop("config", None) or PreTrainedConfig.from_pretrained(
                    pretrained_name_or_path
                )
                kwargs["config"] = dataclasses.replace(config, **options)
            return super().from_pretrained(pretrained_name_or_path, *args, **kwargs)
        except Exception as err:
            cause = err
            while cause is not None and not isinstance(cause, PluginVersionError):
                cause = cause.__cause__
            if cause is None:
                raise
            raise cause from None

    # Training ---------------------------------------------------------------------------------------------

    def camera_frames(self, batch: dict[str, Tensor]) -> Tensor:
        """The frames the model sees: (..., 3, H, W) of the one camera, or (..., K, 3, H, W) of the config's
        cameras in order, each at the model's resolution."""
        keys = self.config.image_keys
        if len(keys) == 1:
            return batch[keys[0]]
        size = self.config.image_size
        frames = [
            resize_frames(unit_float(batch[key]).flatten(0, -4), size).view(
                *batch[key].shape[:-2], size, size
            )
            for key in keys
        ]
        return torch.stack(frames, dim=-4)

    def bin_actions(self, indices: Tensor) -> Tensor:
        """(..., A) bin indices -> (..., A) actions at the bin centres (each dimension's own with per-dimension
        ranges)."""
        centres = self.bin_centres
        if centres.ndim == 1:
            return centres[indices]
        return torch.gather(centres.expand(*indices.shape[:-1], *centres.shape), -1, indices[..., None])[
            ..., 0
        ]

    def control_actions(self, logits: Tensor) -> Tensor:
        """(B, A, bins) logits of a_t -> the (B, A) actions to execute, decoded as ``action_decoding`` says (the
        most likely bin's centre, or the mean of the centres under the softmax) and, with ``action_smoothing``
        b, mixed with the episode's previous action: (1 - b) a_t + b a_{t-1}."""
        cfg = self.config
        if cfg.action_decoding == "expectation":
            action = (logits.float().softmax(-1) * self.bin_centres).sum(-1)
        else:
            action = self.bin_actions(logits.argmax(-1))
        if cfg.action_smoothing and self._last_action is not None:
            action = (1.0 - cfg.action_smoothing) * action + cfg.action_smoothing * self._last_action
        self._last_action = action
        return action

    def lr_groups(self, groups: list[tuple[str, float, list[nn.Module]]]) -> list[dict]:
        """AdamW parameter groups ``[(name, lr, modules), ...]`` of the trainable parameters; a parameter shared
        by two modules (Vid2Robot's one Perceiver) goes to the first group that names it. The groups' rates are
        logged by name (:meth:`learning_rates`)."""
        seen: set[int] = set()
        out = []
        for name, lr, modules in groups:
            params = [p for m in modules for p in m.parameters() if p.requires_grad and id(p) not in seen]
            seen.update(id(p) for p in params)
            out.append({"params": params, "lr": lr, "name": name})
        self.__dict__["_group_rates"] = {name: lr for name, lr, _ in groups}
        return out

    def learning_rates(self) -> dict[str, float]:
        """``lr_<group>``: each parameter group's rate at this training step, under the policy's scheduler
        preset (linear warm-up over ``scheduler_warmup_steps``, then constant); LeRobot's own ``lr`` is the first
        group's. Empty unless LeRobot trains with the policy's groups (``use_policy_training_preset``)."""
        rates = self.__dict__.get("_group_rates")
        if not rates or not self.training:
            return {}
        warmup, step = self.config.scheduler_warmup_steps, int(self.num_updates)
        factor = step / warmup if step < warmup else 1.0
        return {f"lr_{name}": lr * factor for name, lr in rates.items()}

    def prompted_lr_groups(self, predictor: list[nn.Module]) -> list[dict]:
        """The three groups of a policy with a prompt encoder: the tokenizer (and a trained backbone) at
        ``optimizer_lr_encoder``, the prompt encoder at ``optimizer_lr_prompt``, ``predictor`` at
        ``optimizer_lr_predictor``."""
        cfg = self.config
        return self.lr_groups(
            [
                ("encoder", cfg.optimizer_lr_encoder, self.encoder_modules()),
                ("prompt", cfg.optimizer_lr_prompt, [self.model.prompt_encoder]),
                ("predictor", cfg.optimizer_lr_predictor, predictor),
            ]
        )

    def encoder_modules(self) -> list[nn.Module]:
        """The single-frame tokenizer, with the backbone when it is trained (the ``optimizer_lr_encoder`` group
        of the baselines)."""
        return [self.model.tokenizer] + ([] if self.config.freeze_backbone else [self.model.backbone])

    def update(self) -> None:
        """After every optimizer step: count it, move the weight average (``weight_ema_decay``)."""
        if "weight_average" in self._modules:
            self.weight_average.update(self.model, int(self.num_updates))
        self.num_updates += 1

    def train(self, mode: bool = True):
        """Train or eval mode; with ``weight_ema_decay``, eval mode runs on the weight average and train mode on
        the trained weights (:class:`WeightAverage`)."""
        super().train(mode)
        if "weight_average" in self._modules:
            self.weight_average.use(self.model, averaged=not mode)
        return self

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """LeRobot's saving, with the trained weights under their names in either mode (:class:`WeightAverage`)."""
        if "weight_average" not in self._modules:
            return super()._save_pretrained(save_directory, state_dict)
        with self.weight_average.trained_weights(self.model):
            return super()._save_pretrained(save_directory, state_dict)

    def action_labels(self, batch: dict[str, Tensor], shape: torch.Size) -> Tensor:
        """Bin indices (B, T, A) from the discretised ``action``; IGNORE_INDEX where unlabelled or padded."""
        actions = batch.get(ACTION)
        if actions is None:  # a dataset without actions: no action loss
            return torch.full(shape, IGNORE_INDEX, dtype=torch.long, device=self.bin_centres.device)
        if actions.is_floating_point():
            raise ValueError(
                f"{self.name} expects `action` as bin indices from its preprocessor (jept_action_bins). Pass "
                "batches through the policy's preprocessor (make_pre_post_processors) before policy.forward."
            )
        labels = actions.reshape(shape).clone()
        pad = batch.get(f"{ACTION}_is_pad")
        if pad is not None:
            labels[pad.reshape(shape[:2])] = IGNORE_INDEX
        labels[(labels == IGNORE_INDEX).any(-1)] = IGNORE_INDEX  # a frame is labelled in full or not at all
        return labels

    def action_loss(
        self, logits: Tensor, batch: dict[str, Tensor], first: int = 0, labels: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Cross-entropy over the bins of logits (B, T, A, bins) on labelled frames only (eq. 8), from frame
        ``first`` on -> per-sample loss (B,) (mean over the sample's labelled frames, 0 without any) and the
        labelled mask (B, T, A). The labels are the batch's (:meth:`action_labels`) unless ``labels`` gives
        others (B, T, A), IGNORE_INDEX where there is none."""
        labels = self.action_labels(batch, logits.shape[:3]) if labels is None else labels.clone()
        labels[:, :first] = IGNORE_INDEX
        ce = F.cross_entropy(
            rearrange(logits, "b t a c -> b c t a"), labels, ignore_index=IGNORE_INDEX, reduction="none"
        )
        labelled = (labels != IGNORE_INDEX).float()
        return (ce * labelled).sum((1, 2)) / labelled.sum((1, 2)).clamp_min(1), labelled

    @staticmethod
    def labelled_mean(loss: Tensor, labelled: Tensor) -> Tensor:
        """Mean of per-sample action losses (B,) over the samples with at least one labelled frame."""
        has_label = (labelled.sum((1, 2)) > 0).float()
        return (loss * has_label).sum() / has_label.sum().clamp_min(1)

    def task_ids(self, batch: dict, size: int, device) -> Tensor:
        """(B,) task identity of each sample: ``task_index`` as LeRobot's dataset gives it, else ``task``."""
        if "task_index" in batch and torch.is_tensor(batch["task_index"]):
            return batch["task_index"].reshape(size).to(device)
        tasks = batch.get("task")
        if tasks is None:
            raise KeyError(
                f"{self.name}'s prompt losses need each sample's task: the batch has neither `task_index` nor "
                "`task`. Train from a LeRobotDataset."
            )
        names = sorted(set(tasks))
        return torch.tensor([names.index(t) for t in tasks], device=device)

    def prompt(self, batch: dict[str, Tensor]) -> Tensor:
        if PROMPT_VIDEO not in batch:
            batch = {**batch, **self.deployment_prompt(batch)}
        return self.model.encode_prompt(batch[PROMPT_VIDEO], batch.get(PROMPT_MASK), batch.get(PROMPT_ID))

    def deployment_prompt(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The prompt of a batch that brings none (control, where neither the env nor the caller gives one):
        the video file ``prompt_video``, else the first prompt of the batch's task in the bank
        ``prompt_repo_id``; both are read from this policy's config, so options given at evaluation or rollout
        apply. Each is decoded once and kept."""
        cfg = self.config
        image = batch[cfg.image_key]
        size = image.shape[0]
        if cfg.prompt_video:
            if self.__dict__.get("_prompt_file", (None,))[0] != cfg.prompt_video:
                frames = load_prompt_video(cfg.prompt_video, cfg.max_prompt_length, cfg.image_size)
                self.__dict__["_prompt_file"] = (cfg.prompt_video, frames)
            video = self.__dict__["_prompt_file"][1][None].expand(size, -1, -1, -1, -1)
            mask = torch.ones(video.shape[:2], dtype=torch.bool)
        elif cfg.prompt_repo_id:
            tasks = batch.get("task")
            if tasks is None:
                raise KeyError(
                    f"{self.name} looks its prompt up by the `task` string, and the batch has none: pass "
                    "--policy.prompt_video=clip.mp4 or the prompt video as observation.prompt_video."
                )
            tasks = [tasks] * size if isinstance(tasks, str) else list(tasks)
            bank = self.__dict__.get("_prompt_bank")
            if bank is None or (bank.repo_id, bank.root) != (cfg.prompt_repo_id, cfg.prompt_root):
                bank = PromptBank(cfg.prompt_repo_id, cfg.prompt_root, cfg.max_prompt_length, cfg.image_size)
                self.__dict__["_prompt_bank"] = bank
            video, mask = bank.batch([bank.episodes(task)[0] for task in tasks], as_uint8=True)
        else:
            raise KeyError(
                f"{self.name} needs a prompt video: the batch has no {PROMPT_VIDEO!r}. Pass "
                "--policy.prompt_video=clip.mp4 (a video file of the task), --policy.prompt_repo_id=ORG/NAME_prompts "
                "(a prompt bank, looked up by the task string), or the prompt video as an observation."
            )
        return {PROMPT_VIDEO: video.to(image.device), PROMPT_MASK: mask.to(image.device)}

    # Hub -------------------------------------------------------------------------------------------------

    def push_model_to_hub(self, cfg, *args, **kwargs):
        """LeRobot's push. A failure (no network, bad token) ends the run with one line and keeps every local
        file: lerobot-train saves the checkpoints before it pushes."""
        try:
            return super().push_model_to_hub(cfg, *args, **kwargs)
        except Exception as err:  # whatever the Hub client raises
            reason = str(err).strip().splitlines()[0] if str(err).strip() else ""
            raise SystemExit(
                f"Pushing the policy to {self.config.repo_id} failed ({type(err).__name__}: {reason}). The "
                f"checkpoints under {cfg.output_dir} are intact; log in (`hf auth login`) and upload one with "
                f"`hf upload {self.config.repo_id} {cfg.output_dir}/checkpoints/last/pretrained_model`."
            ) from err

    def generate_model_card(self, dataset_repo_id, model_type, license, tags, cfg=None, dataset_meta=None):
        card = super().generate_model_card(dataset_repo_id, model_type, license, tags, cfg, dataset_meta)
        card.text += card_section(self.config, dataset_repo_id, dataset_meta)
        return card

    @torch.no_grad()
    def observation_embedding(self, batch: dict[str, Tensor]) -> Tensor:
        """(B, D): the observation tokens of the last context frame of a preprocessed training-shaped batch,
        averaged over tokens (what ``jept-visualize`` projects for the paper's Figure 3)."""
        obs = self.model.frame_tokens(self.camera_frames(batch), batch[OBS_STATE])
        return obs[:, self.config.n_obs_steps - 1].mean(1)

    # Control ----------------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Start of an episode: forget the context and the prompt encoding."""
        self._obs_tokens: deque[Tensor] = deque(maxlen=self.config.n_obs_steps)
        self._frames: deque[tuple[Tensor, Tensor]] = deque(maxlen=self.config.n_obs_steps)
        self._prompt_cache: Tensor | None = None
        self._prompt_cached = False
        self._last_action: Tensor | None = None

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, 1, action_dim): the action of the current step as a one-step chunk."""
        return self.select_action(batch)[:, None]

    def episode_prompt(self, batch: dict[str, Tensor], active: bool = True) -> Tensor | None:
        """The prompt encoding of the episode, computed on its first control step (the inputs are checked
        then) and reused until ``reset``; None when ``active`` is False (JEPT's prompt warm-up)."""
        if not self._prompt_cached:
            self.check_inputs(batch)
            self._prompt_cache = self.prompt(batch) if active else None
            self._prompt_cached = True
        return self._prompt_cache

    def check_inputs(self, batch: dict[str, Tensor]) -> None:
        """Observations from another env (e.g. the stock ``metaworld`` one) fail here with what differs."""
        cfg = self.config
        hint = (
            "Give it observations like those it was trained on: for data of jept-build-metaworld, "
            "--env.type=jept_metaworld; of jept-build-robosuite, --env.type=jept_robosuite; on a robot, the "
            "cameras and joints its dataset was recorded with."
        )
        for key in (*cfg.image_keys, OBS_STATE):
            if key not in batch:
                raise ValueError(f"The policy needs {key!r} but the observation has {sorted(batch)}. {hint}")
        expected, got = cfg.input_features[OBS_STATE].shape, tuple(batch[OBS_STATE].shape[1:])
        if tuple(expected) != got:
            raise ValueError(
                f"The observation gives observation.state of shape {got} but the policy was trained on "
                f"{tuple(expected)}. {hint}"
            )
        for key in cfg.image_keys:
            if batch[key].shape[1] != 3:
                raise ValueError(f"{key} must be (B, 3, H, W), got {tuple(batch[key].shape)}.")

    def context_tokens(self, image: Tensor, state: Tensor) -> Tensor:
        """Observation tokens of the last k frames (B, k, N, D); the first frame fills the context at the start
        of an episode, as LeRobot's frame clamping does in training. With ``cache_frame_tokens`` only the new
        frame is encoded; otherwise the whole context is, every step (the reference)."""
        m, k = self.model, self.config.n_obs_steps
        if self.config.cache_frame_tokens:
            if m.backbone.temporal and self._frames:  # a temporal prior pairs the new frame with the last
                last_image, last_state = self._frames[-1]
                new = m.frame_tokens(
                    torch.stack([last_image, image], 1), torch.stack([last_state, state], 1)
                )[:, 1]
            else:
                new = m.frame_tokens(image[:, None], state[:, None])[:, 0]
            self._frames.append((image, state))
            self._obs_tokens.extend([new] * (k - len(self._obs_tokens)) if not self._obs_tokens else [new])
            return torch.stack(list(self._obs_tokens), dim=1)
        self._frames.extend([(image, state)] * (k if not self._frames else 1))
        images = torch.stack([f[0] for f in self._frames], 1)
        states = torch.stack([f[1] for f in self._frames], 1)
        return m.frame_tokens(images, states)


class ContextActionPolicy(DiscreteActionPolicy):
    """Base of the baselines that read the actions of the k context frames from their own tokens (``jept_dt_star``,
    ``jept_vid2robot``): the model's ``action_logits(prompt, obs)`` gives (B, k, A, bins); control takes the last."""

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        """Behaviour cloning on the labelled frames, plus :meth:`auxiliary_losses` (per sample)."""
        m = self.model
        obs = m.frame_tokens(self.camera_frames(batch), batch[OBS_STATE])  # (B, k, N, D)
        prompt, aux, info = self.auxiliary_losses(batch, obs)
        loss_act, labelled = self.action_loss(m.action_logits(prompt, obs), batch)
        mean = self.labelled_mean(loss_act, labelled)
        info = {
            "loss_act": mean.item(),
            "labelled_fraction": labelled[..., 0].mean().item(),
            **info,
            **self.learning_rates(),
        }
        return (loss_act + aux if reduction == "none" else mean + aux.mean()), info

    def auxiliary_losses(self, batch: dict[str, Tensor], obs: Tensor) -> tuple[Tensor, Tensor, dict]:
        """The prompt encoding, per-sample auxiliary losses (B,) on every frame, and what to log."""
        return self.prompt(batch), obs.new_zeros(obs.shape[0]), {}

    @torch.no_grad()
    def offline_outputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """``control``: logits (B, A, bins) of a_t for the last frame of a preprocessed training-shaped batch,
        as ``select_action`` chooses it."""
        obs = self.model.frame_tokens(self.camera_frames(batch), batch[OBS_STATE])
        return {"control": self.model.action_logits(self.prompt(batch), obs)[:, -1]}

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, action_dim) actions for the current observation (see ``control_actions``)."""
        prompt = self.episode_prompt(batch)
        obs = self.context_tokens(self.camera_frames(batch), batch[OBS_STATE])
        return self.control_actions(self.model.action_logits(prompt, obs)[:, -1])


def frame_mean(values: Tensor, frame_ok: Tensor) -> Tensor:
    """(B, k) per-frame values -> (B,) their mean over the frames whose target is real."""
    return (values * frame_ok).sum(-1) / frame_ok.sum(-1).clamp_min(1)


def card_section(config: VideoPolicyConfig, dataset_repo_id: str, dataset_meta=None) -> str:
    """Model card text: training data, prompt bank, task split and how to evaluate the checkpoint."""
    split, protocol = {}, {}
    if dataset_meta is not None and (Path(dataset_meta.root) / "meta/jept_build.json").is_file():
        build = json.loads((Path(dataset_meta.root) / "meta/jept_build.json").read_text())
        split, protocol = build.get("split", {}), build.get("protocol", {})
    title = "JEPT" if config.type == "jept" else f"{config.type} (a JEPT baseline)"
    lines = [
        "",
        f"## {title}",
        "",
        "Joint Embedding Predictive Transformer and its baselines (`lerobot_policy_jept` "
        f"{config.plugin_version}): once the package is installed, LeRobot finds the `{config.type}` policy.",
        "",
        f"- Training data: `{dataset_repo_id}`",
        f"- Prompt bank: `{config.prompt_repo_id}`",
    ]
    for name, key in (("T_demo", "demo"), ("T_vid", "video"), ("T_unseen", "unseen")):
        if key in split:
            lines.append(f"- {name}: {', '.join(split[key]) or '(none)'}")
    repo = config.repo_id or "<this repo>"
    lines += ["", "Evaluate or deploy:", "", "```bash"]
    if protocol.get("simulator") in ("metaworld", "robosuite"):
        size = protocol.get("image_size", config.image_size)
        task = (split.get("unseen") or split.get("demo") or [None])[0]
        lines += [
            INSTALL[protocol["simulator"]],
            f"lerobot-eval --policy.path={repo} --env.type=jept_{protocol['simulator']} --env.task={task} "
            f"--env.image_size={size} --env.prompt_repo_id={config.prompt_repo_id} "
            f"--env.prompt_max_frames={config.max_prompt_length} --eval.n_episodes=50",
            f"jept-eval-suite --policy.path={repo} --dataset.repo_id={dataset_repo_id} --n_episodes=50",
        ]
    else:
        lines += [
            "pip install lerobot_policy_jept",
            f"lerobot-rollout --policy.path={repo} --policy.prompt_video=clip.mp4 --robot.type=<your robot> ...",
        ]
    lines += ["```", ""]
    return "\n".join(lines)
