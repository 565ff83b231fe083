"""``JEPTPolicy``: the Joint Embedding Predictive Transformer as a LeRobot policy.

Training (paper Section 3.3, Algorithm 1): the k + 1 frames of a sample are tokenised frame by frame (backbone ->
Perceiver-IO + self-state token), the online temporal encoder gives the predictor's joint embedding inputs, the EMA
copy of the encoder gives the targets, the causal predictor runs over ``[E_prt | o_1, h_2, ..., o_k, h_{k+1}]`` and
``forward`` returns ``L_obs + c * L_act``. ``update()`` (called by LeRobot after every optimizer step) moves the EMA
targets and the step counter that drives the alternating phases and the prompt warm-up.

Control (end of Section 3.2.2): the new frame alone goes through the backbone and the Perceiver, the tokens of the
previous k - 1 frames and the prompt encoding are reused; the predictor predicts h_{t+1}, which is fed back in to
predict a_t.
"""

import copy
import json
from collections import deque
from pathlib import Path

import torch
import torch.nn.functional as F  # noqa: N812
from einops import rearrange
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from lerobot_jept.components.backbone import SpatialBackbone
from lerobot_jept.components.encoders import JointEmbeddingEncoder, ObservationTokenizer, PromptVideoEncoder
from lerobot_jept.components.predictor import ActionHead, CausalPredictor, ObservationHead
from lerobot_jept.configuration_jept import JEPTConfig, PluginVersionError
from lerobot_jept.discretization import bin_centres

PROMPT_VIDEO = "observation.prompt_video"
PROMPT_MASK = "observation.prompt_video_mask"
IGNORE_INDEX = -100  # action labels that take no part in L_act (NaN-marked or padded)


class JointEmbeddingTarget(nn.Module):
    """The single-timestep encoder and the temporal encoder: Psi_obs without its frozen backbone."""

    def __init__(self, config: JEPTConfig, backbone_dim: int, state_dim: int):
        super().__init__()
        self.tokenizer = ObservationTokenizer(
            backbone_dim,
            state_dim,
            perceiver=_perceiver_kwargs(config, "frame"),
            dim=config.perceiver_dim,
        )
        self.temporal = JointEmbeddingEncoder(
            config.perceiver_dim,
            config.temporal_dim,
            config.joint_embedding_dim,
            **_transformer_kwargs(config, "temporal"),
            max_steps=config.n_obs_steps + 1,
            tokens_per_step=config.frame_perceiver_queries + 1,
        )


def _transformer_kwargs(config: JEPTConfig, which: str) -> dict:
    """Self-attention stack sizes of the ``temporal`` encoder or the causal ``predictor`` (Table 5)."""
    return {name: getattr(config, f"{which}_{name}") for name in ("heads", "ff_dim", "layers", "dropout")}


def _perceiver_kwargs(config: JEPTConfig, which: str) -> dict:
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


class PromptAlignment(nn.Module):
    """Supervised contrastive alignment of prompts with trajectories (an addition to the paper, see
    ``JEPTConfig.prompt_align_weight``): the mean E_prt token of each sample's prompt is pulled towards the mean
    target joint embedding of every sample of the same task in the batch and pushed from the others (InfoNCE
    with all same-task samples as positives, as in SupCon). The targets are the EMA encoder's, without
    gradient, so only the prompt encoder and the two projections learn from it."""

    def __init__(self, prompt_dim: int, joint_dim: int, dim: int = 128):
        super().__init__()
        self.prompt_proj = nn.Sequential(nn.LayerNorm(prompt_dim), nn.Linear(prompt_dim, dim))
        self.traj_proj = nn.Sequential(nn.LayerNorm(joint_dim), nn.Linear(joint_dim, dim))

    def forward(self, prompt: Tensor, targets: Tensor, task_ids: Tensor, temperature: float) -> Tensor:
        """prompt (B, N_prt, D), targets (B, k, N, J), task_ids (B,) -> scalar loss."""
        p = F.normalize(self.prompt_proj(prompt.mean(1)), dim=-1)
        t = F.normalize(self.traj_proj(targets.mean((1, 2))), dim=-1)
        log_prob = (p @ t.T / temperature).log_softmax(-1)
        positive = (task_ids[:, None] == task_ids[None, :]).float()
        return -((log_prob * positive).sum(-1) / positive.sum(-1)).mean()


class JEPT(nn.Module):
    """The network: backbone, Psi_obs (online and EMA target), Psi_prt, Psi_pred, Gamma_obs, Gamma_act."""

    def __init__(self, config: JEPTConfig):
        super().__init__()
        self.config = config
        self.backbone = SpatialBackbone(
            config.vision_backbone,
            config.pretrained_backbone,
            config.freeze_backbone,
            config.image_size,
            config.backbone_weights_path,
        )
        state_dim = config.input_features[OBS_STATE].shape[0]
        self.encoder = JointEmbeddingTarget(config, self.backbone.dim, state_dim)
        self.target_encoder = copy.deepcopy(self.encoder).requires_grad_(False)
        self.prompt_encoder = PromptVideoEncoder(
            self.backbone.dim,
            frame_perceiver=_perceiver_kwargs(config, "frame"),
            video_perceiver=_perceiver_kwargs(config, "prompt"),
            dim=config.perceiver_dim,
            max_frames=config.max_prompt_length,
        )
        tokens_per_step = config.frame_perceiver_queries + 1
        self.predictor = CausalPredictor(
            config.perceiver_dim,
            config.joint_embedding_dim,
            config.predictor_dim,
            **_transformer_kwargs(config, "predictor"),
            max_steps=config.n_obs_steps,
            tokens_per_step=tokens_per_step,
        )
        self.obs_head = ObservationHead(
            config.predictor_dim,
            config.joint_embedding_dim,
            config.obs_head_hidden_dim,
            config.obs_head_layers,
        )
        self.action_head = ActionHead(
            config.predictor_dim,
            config.resolved_action_dim,
            config.num_action_bins,
            dim=config.action_head_dim,
            heads=config.action_head_heads,
            layers=config.action_head_layers,
            ff_dim=config.action_head_ff_dim,
        )

        # Prompt-trajectory alignment (config.prompt_align_weight): projections of pooled E_prt and of pooled
        # target joint embeddings into one space, where prompts of a task meet that task's trajectories.
        self.prompt_align = PromptAlignment(config.perceiver_dim, config.joint_embedding_dim)

    def phase_modules(self) -> dict[str, list[nn.Module]]:
        """Algorithm 1's two phases: the joint embedding encoder, and every other trained component."""
        return {
            "encoder": [self.encoder],
            "others": [
                self.prompt_encoder,
                self.predictor,
                self.obs_head,
                self.action_head,
                self.prompt_align,
            ],
        }

    def backbone_tokens(self, images: Tensor) -> Tensor:
        """(..., 3, H, W) in [0, 1] -> (..., P, C), resized to the model's resolution."""
        lead = images.shape[:-3]
        flat = images.reshape(-1, *images.shape[-3:])
        size = self.config.image_size
        if flat.shape[-2:] != (size, size):
            flat = F.interpolate(
                flat, size=(size, size), mode="bilinear", antialias=True, align_corners=False
            )
        tokens = self.backbone(flat)
        return tokens.reshape(*lead, *tokens.shape[1:])

    def tokenize(self, encoder: JointEmbeddingTarget, tokens: Tensor, state: Tensor) -> Tensor:
        """Backbone tokens (B, T, P, C) + state (B, T, S) -> observation tokens (B, T, N_obs, D)."""
        b = tokens.shape[0]
        obs = encoder.tokenizer(
            rearrange(tokens, "b t p c -> (b t) p c"), rearrange(state, "b t s -> (b t) s")
        )
        return rearrange(obs, "(b t) n d -> b t n d", b=b)

    def encode_prompt(self, video: Tensor, mask: Tensor | None) -> Tensor:
        """(B, N, 3, H, W) prompt frames -> E_prt (B, N_prt, D). Only the Perceivers learn from prompts
        (Appendix A.2): the backbone sees them without gradient, even when it is trained on observations."""
        with torch.no_grad():
            tokens = self.backbone_tokens(video)
        return self.prompt_encoder(tokens, mask)

    def predict(self, prompt: Tensor | None, obs: Tensor, emb: Tensor) -> tuple[Tensor, Tensor]:
        """Predicted joint embeddings (B, k, N, J) from the obs tokens and action logits (B, k, A, bins)."""
        z_obs, z_emb = self.predictor(prompt, obs, emb)
        return self.obs_head(z_obs), self.action_head(z_emb)

    @torch.no_grad()
    def update_target(self, decay: float) -> None:
        for target, online in zip(self.target_encoder.parameters(), self.encoder.parameters(), strict=True):
            target.lerp_(online.detach(), 1.0 - decay)


class JEPTPolicy(PreTrainedPolicy):
    """Video-conditioned policy pi(a_t | o_{t-k+1..t}, prompt video) learned from demos and action-free videos."""

    config_class = JEPTConfig
    name = "jept"

    def __init__(self, config: JEPTConfig, **kwargs):
        super().__init__(config)
        config.validate_features()
        self.config = config
        self.model = JEPT(config)
        # Optimizer steps taken; persistent so a resumed run continues the phase and warm-up schedule.
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))
        centres = bin_centres(config.num_action_bins, config.action_low, config.action_high)
        self.register_buffer("bin_centres", torch.as_tensor(centres, dtype=torch.float32), persistent=False)
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *args, **kwargs):
        """LeRobot's loading (safetensors only), with a version mismatch raised as itself, not as the config
        parser's wrapper around it."""
        try:
            return super().from_pretrained(pretrained_name_or_path, *args, **kwargs)
        except Exception as err:
            cause = err
            while cause is not None and not isinstance(cause, PluginVersionError):
                cause = cause.__cause__
            if cause is None:
                raise
            raise cause from None

    # Training ---------------------------------------------------------------------------------------------

    def get_optim_params(self) -> list[dict]:
        cfg, m = self.config, self.model
        groups = [
            (cfg.optimizer_lr_encoder, [m.encoder] + ([] if cfg.freeze_backbone else [m.backbone])),
            (cfg.optimizer_lr_prompt, [m.prompt_encoder, m.prompt_align]),
            (cfg.optimizer_lr_predictor, [m.predictor, m.obs_head, m.action_head]),
        ]
        return [
            {"params": [p for mod in mods for p in mod.parameters() if p.requires_grad], "lr": lr}
            for lr, mods in groups
        ]

    @property
    def phase(self) -> str:
        if self.config.phase_schedule == "joint":
            return "joint"
        return ("encoder", "others")[(int(self.num_updates) // self.config.phase_steps) % 2]

    @property
    def prompt_active(self) -> bool:
        return int(self.num_updates) >= self.config.prompt_warmup_steps

    def _apply_phase(self) -> None:
        """Parameters outside the current phase get no gradient, so AdamW leaves them (and their moments)
        untouched: Algorithm 1's alternation inside LeRobot's single optimizer."""
        phase = self.phase
        for name, modules in self.model.phase_modules().items():
            for module in modules:
                module.requires_grad_(phase in ("joint", name))
        if not self.config.freeze_backbone:
            self.model.backbone.requires_grad_(phase in ("joint", "encoder"))

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        cfg, m = self.config, self.model
        if self.training:
            self._apply_phase()
        state = batch[OBS_STATE]  # (B, k+1, S)
        k = cfg.n_obs_steps
        tokens, obs, h_in = self._encode_window(batch)
        with torch.no_grad():
            target_obs = m.tokenize(m.target_encoder, tokens.detach(), state)
            targets = m.target_encoder.temporal.context_embeddings(target_obs, first=1)
        prompt = self._prompt(batch) if self.prompt_active else None
        pred_h, logits = m.predict(prompt, obs[:, :k], h_in)

        # L_obs (eq. 7): L2 distance per token, averaged over tokens and over the frames whose target is real.
        dist = torch.linalg.vector_norm(pred_h - targets, dim=-1).mean(-1)  # (B, k)
        pad = batch.get(f"{cfg.image_key}_is_pad")
        frame_ok = torch.ones_like(dist) if pad is None else (~pad[:, 1:]).float()
        loss_obs = _frame_mean(dist, frame_ok)

        # L_act (eq. 8): cross-entropy over the bins on labelled frames only.
        labels = self._action_labels(batch, logits.shape[:3])
        ce = F.cross_entropy(
            rearrange(logits, "b k a c -> b c k a"), labels, ignore_index=IGNORE_INDEX, reduction="none"
        )
        labelled = (labels != IGNORE_INDEX).float()
        loss_act = (ce * labelled).sum((1, 2)) / labelled.sum((1, 2)).clamp_min(1)
        per_sample = loss_obs + cfg.action_loss_weight * loss_act

        has_label = labelled.sum((1, 2)) > 0
        extra, extra_info = self._prompt_losses(batch, prompt, obs[:, :k], h_in, targets, dist, frame_ok)
        per_sample = per_sample + extra
        info = {
            "loss_obs": loss_obs.mean().item(),
            "loss_act": (loss_act.sum() / has_label.sum().clamp_min(1)).item(),
            "labelled_fraction": labelled[..., 0].mean().item(),
            "phase_encoder": float(self.phase == "encoder"),
            "prompt_on": float(prompt is not None),
            **extra_info,
        }
        if reduction == "none":
            return per_sample, info
        loss_act_mean = (loss_act * has_label).sum() / has_label.sum().clamp_min(1)
        return loss_obs.mean() + cfg.action_loss_weight * loss_act_mean + extra.mean(), info

    def _prompt_losses(self, batch, prompt, obs, h_in, targets, dist, frame_ok) -> tuple[Tensor, dict]:
        """The prompt terms that are not in the paper (``prompt_align_weight``, ``prompt_swap_weight``), per
        sample (B,). Both train the components of Algorithm 1's second phase only, so they are computed when
        that phase (or the joint schedule) is on and the prompt is past its warm-up."""
        cfg, m = self.config, self.model
        zero = dist.new_zeros(dist.shape[0])
        if prompt is None or (self.training and self.phase == "encoder"):
            return zero, {}
        if cfg.prompt_align_weight == 0 and cfg.prompt_swap_weight == 0:
            return zero, {}
        task_ids = self._task_ids(batch, dist.shape[0], dist.device)
        extra, info = zero, {}
        if cfg.prompt_align_weight > 0:
            align = m.prompt_align(prompt, targets, task_ids, cfg.prompt_align_temperature)
            extra = extra + cfg.prompt_align_weight * align
            info["loss_prompt_align"] = align.item()
        if cfg.prompt_swap_weight > 0:
            # Each sample with the prompt of the next sample of another task (none: no term for it).
            other = task_ids[None, :] != task_ids[:, None]
            n = len(task_ids)
            steps = torch.arange(n, device=dist.device)
            swap_to = torch.where(other, (steps[None, :] - steps[:, None]) % n, n).argmin(-1)
            has_other = other.any(-1).float()
            pred_swapped, _ = m.predict(prompt[swap_to], obs, h_in)
            dist_swapped = torch.linalg.vector_norm(pred_swapped - targets, dim=-1).mean(-1)
            gap = _frame_mean(dist_swapped - dist, frame_ok)
            swap = F.relu(cfg.prompt_swap_margin - gap) * has_other
            extra = extra + cfg.prompt_swap_weight * swap
            info["loss_prompt_swap"] = swap.mean().item()
            info["prompt_swap_gap"] = gap.mean().item()
        return extra, info

    @staticmethod
    def _task_ids(batch: dict, size: int, device) -> Tensor:
        """(B,) task identity of each sample: ``task_index`` as LeRobot's dataset gives it, else ``task``."""
        if "task_index" in batch and torch.is_tensor(batch["task_index"]):
            return batch["task_index"].reshape(size).to(device)
        tasks = batch.get("task")
        if tasks is None:
            raise KeyError(
                "The prompt losses (prompt_align_weight, prompt_swap_weight) need each sample's task: the batch "
                "has neither `task_index` nor `task`. Train from a LeRobotDataset, or set both weights to 0."
            )
        names = sorted(set(tasks))
        return torch.tensor([names.index(t) for t in tasks], device=device)

    @torch.no_grad()
    def offline_action_logits(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Logits (B, A, bins) of a_t for the last context frame of a preprocessed training-shaped batch (k + 1
        frames): ``control`` from the predicted h_{t+1}, as ``select_action`` chooses it; ``inverse`` from the
        real next frame's joint embedding (the inverse dynamics alone)."""
        m, k = self.model, self.config.n_obs_steps
        _, obs, h_in = self._encode_window(batch)
        prompt = self._prompt(batch) if self.prompt_active else None
        _, logits = m.predict(prompt, obs[:, :k], h_in)
        z_next = m.predictor.forward_last_step(prompt, obs[:, :k], h_in[:, : k - 1], m.obs_head)
        return {"control": m.action_head(z_next[:, None])[:, 0], "inverse": logits[:, -1]}

    def _encode_window(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """A training-shaped window (k + 1 frames) -> backbone tokens, observation tokens and the predictor's
        joint embedding inputs h_2..h_{k+1} (each frame encoded over the frames up to it)."""
        m = self.model
        tokens = m.backbone_tokens(batch[self.config.image_key])
        obs = m.tokenize(m.encoder, tokens, batch[OBS_STATE])
        return tokens, obs, m.encoder.temporal.context_embeddings(obs, first=1)

    def _action_labels(self, batch: dict[str, Tensor], shape: torch.Size) -> Tensor:
        """Bin indices (B, k, A) from the discretised ``action``; IGNORE_INDEX where NaN-marked or padded."""
        actions = batch.get(ACTION)
        if actions is None:  # a dataset without actions: visual transition only
            return torch.full(shape, IGNORE_INDEX, dtype=torch.long, device=self.bin_centres.device)
        if actions.is_floating_point():
            raise ValueError(
                "JEPT expects `action` as bin indices from its preprocessor (jept_action_bins). Pass batches "
                "through the policy's preprocessor (make_pre_post_processors) before policy.forward."
            )
        labels = actions.clone()
        pad = batch.get(f"{ACTION}_is_pad")
        if pad is not None:
            labels[pad] = IGNORE_INDEX
        labels[(labels == IGNORE_INDEX).any(-1)] = IGNORE_INDEX  # a frame is labelled in full or not at all
        return labels

    def _prompt(self, batch: dict[str, Tensor]) -> Tensor:
        if PROMPT_VIDEO not in batch:
            raise KeyError(
                f"JEPT needs a prompt video: the batch has no {PROMPT_VIDEO!r}. Set --policy.prompt_repo_id to a "
                "prompt bank (the builder's ORG/NAME_prompts) or pass the prompt video as an observation."
            )
        return self.model.encode_prompt(batch[PROMPT_VIDEO], batch.get(PROMPT_MASK))

    def update(self) -> None:
        """After every optimizer step: move the EMA targets, count the step."""
        self.model.update_target(self.config.ema_decay)
        self.num_updates += 1

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
        card.text += jept_card_section(self.config, dataset_repo_id, dataset_meta)
        return card

    # Control ----------------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Start of an episode: forget the context and the prompt encoding."""
        self._obs_tokens: deque[Tensor] = deque(maxlen=self.config.n_obs_steps)
        self._frames: deque[tuple[Tensor, Tensor]] = deque(maxlen=self.config.n_obs_steps)
        self._prompt_cache: Tensor | None = None
        self._prompt_cached = False

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, 1, action_dim): the action of the current step as a one-step chunk."""
        return self.select_action(batch)[:, None]

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, action_dim) bin-centre actions for the current observation."""
        cfg, m = self.config, self.model
        if not self._prompt_cached:
            self._check_inputs(batch)
        obs = self._context_tokens(batch[cfg.image_key], batch[OBS_STATE])  # (B, k, N, D)
        if not self._prompt_cached:
            self._prompt_cache = self._prompt(batch) if self.prompt_active else None
            self._prompt_cached = True
        h_past = m.encoder.temporal.context_embeddings(obs, first=1)  # h_{t-k+2} .. h_t
        if cfg.cache_frame_tokens:
            z_next = m.predictor.forward_last_step(self._prompt_cache, obs, h_past, m.obs_head)
            logits = m.action_head(z_next[:, None])[:, 0]
        else:  # the reference: two full passes, h_{t+1} predicted by the first and fed back into the second
            placeholder = torch.zeros_like(obs[:, :1, :, : cfg.joint_embedding_dim])
            pred_h, _ = m.predict(self._prompt_cache, obs, torch.cat([h_past, placeholder], 1))
            _, logits = m.predict(self._prompt_cache, obs, torch.cat([h_past, pred_h[:, -1:]], 1))
            logits = logits[:, -1]
        return self.bin_centres[logits.argmax(-1)]

    def _check_inputs(self, batch: dict[str, Tensor]) -> None:
        """Observations from another env (e.g. the stock ``metaworld`` one) fail here with what differs."""
        cfg = self.config
        hint = (
            "This checkpoint was trained on JEPT Meta-World data: evaluate it with --env.type=jept_metaworld "
            "(the builder's observations), or give it observations of the shapes it was trained on."
        )
        for key in (cfg.image_key, OBS_STATE):
            if key not in batch:
                raise ValueError(f"The policy needs {key!r} but the observation has {sorted(batch)}. {hint}")
        expected, got = cfg.input_features[OBS_STATE].shape, tuple(batch[OBS_STATE].shape[1:])
        if tuple(expected) != got:
            raise ValueError(
                f"The env gives observation.state of shape {got} but the policy was trained on {tuple(expected)} "
                f"(the 18-D Sawyer self-state: joint angles, joint velocities, hand position, gripper). {hint}"
            )
        if batch[cfg.image_key].shape[1] != 3:
            raise ValueError(
                f"{cfg.image_key} must be (B, 3, H, W), got {tuple(batch[cfg.image_key].shape)}."
            )

    def _context_tokens(self, image: Tensor, state: Tensor) -> Tensor:
        """Observation tokens of the last k frames (B, k, N, D); the first frame fills the context at the start
        of an episode, as LeRobot's frame clamping does in training."""
        m, k = self.model, self.config.n_obs_steps
        if self.config.cache_frame_tokens:
            new = m.tokenize(m.encoder, m.backbone_tokens(image[:, None]), state[:, None])[:, 0]
            self._obs_tokens.extend([new] * (k - len(self._obs_tokens)) if not self._obs_tokens else [new])
            return torch.stack(list(self._obs_tokens), dim=1)
        self._frames.extend([(image, state)] * (k if not self._frames else 1))
        images = torch.stack([f[0] for f in self._frames], 1)
        states = torch.stack([f[1] for f in self._frames], 1)
        return m.tokenize(m.encoder, m.backbone_tokens(images), states)


def _frame_mean(values: Tensor, frame_ok: Tensor) -> Tensor:
    """(B, k) per-frame values -> (B,) their mean over the frames whose target is real."""
    return (values * frame_ok).sum(-1) / frame_ok.sum(-1).clamp_min(1)


def jept_card_section(config: JEPTConfig, dataset_repo_id: str, dataset_meta=None) -> str:
    """Model card text: training data, prompt bank, task split and how to evaluate the checkpoint."""
    split, protocol = {}, {}
    if dataset_meta is not None and (Path(dataset_meta.root) / "meta/jept_build.json").is_file():
        build = json.loads((Path(dataset_meta.root) / "meta/jept_build.json").read_text())
        split, protocol = build.get("split", {}), build.get("protocol", {})
    lines = [
        "",
        "## JEPT",
        "",
        "Joint Embedding Predictive Transformer (`lerobot_policy_jept` "
        f"{config.plugin_version}): `pip install lerobot_policy_jept`, then LeRobot finds the `jept` policy.",
        "",
        f"- Training data: `{dataset_repo_id}`",
        f"- Prompt bank: `{config.prompt_repo_id}`",
    ]
    for name, key in (("T_demo", "demo"), ("T_vid", "video"), ("T_unseen", "unseen")):
        if key in split:
            lines.append(f"- {name}: {', '.join(split[key]) or '(none)'}")
    size = protocol.get("image_size", config.image_size)
    task = (split.get("unseen") or split.get("demo") or ["button-press-v3"])[0]
    repo = config.repo_id or "<this repo>"
    lines += [
        "",
        "Evaluate:",
        "",
        "```bash",
        f"lerobot-eval --policy.path={repo} --env.type=jept_metaworld --env.task={task} "
        f"--env.image_size={size} --env.prompt_repo_id={config.prompt_repo_id} "
        f"--env.prompt_max_frames={config.max_prompt_length} --eval.n_episodes=50",
        f"jept-eval-suite --policy.path={repo} --dataset.repo_id={dataset_repo_id} --n_episodes=50",
        "```",
        "",
    ]
    return "\n".join(lines)
