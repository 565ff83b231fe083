"""``Vid2RobotPolicy``: Vid2Robot (Jain et al., 2024) with JEPT's parts, as the paper's Appendix A.3 adapts it.

Training: prompt frames and the k context frames go through the same backbone and single-frame Perceiver; the
prompt's frame tokens are resampled into N_prt prompt tokens; the observation tokens attend block-causally to
each other and cross-attend to the prompt tokens; the action head reads a_j from the o_j tokens. ``forward``
returns the behaviour cloning loss on labelled frames plus the two auxiliary losses on every frame (prompt/robot
video contrastive, temporal cycle consistency). Control: only the new frame is encoded; the prompt tokens are
computed once per episode.
"""

import torch
from einops import rearrange
from torch import Tensor, nn

from lerobot_jept.policies.base import (
    PROMPT_ID,
    PROMPT_MASK,
    PROMPT_VIDEO,
    ContextActionPolicy,
    VisualPolicyNet,
    make_action_head,
    make_backbone,
    make_prompt_encoder,
    make_tokenizer,
)
from lerobot_jept.policies.components.alignment import PromptAlignment, cycle_consistency_loss
from lerobot_jept.policies.components.attention import CrossAttentionBlock, StepPositions
from lerobot_jept.policies.components.token_groups import DT_STAR_RULES, attention_mask, dt_star_groups
from lerobot_jept.policies.vid2robot.configuration_vid2robot import Vid2RobotConfig


class PromptCrossAttentionTransformer(nn.Module):
    """Observation tokens (B, k, N, D) attend block-causally to each other (the ``obs`` rules of DT*) and
    cross-attend to the prompt tokens (B, N_prt, D), ``layers`` times -> hidden states (B, k, N, width)."""

    def __init__(
        self,
        dim: int,
        width: int,
        heads: int,
        ff_dim: int,
        layers: int,
        dropout: float,
        max_steps: int,
        tokens_per_step: int,
    ):
        super().__init__()
        self.inp = nn.Linear(dim, width)
        self.positions = StepPositions(max_steps, tokens_per_step, width)
        self.self_blocks = nn.ModuleList(
            nn.TransformerEncoderLayer(
                width, heads, ff_dim, dropout, activation="gelu", batch_first=True, norm_first=True
            )
            for _ in range(layers)
        )
        self.cross_blocks = nn.ModuleList(
            CrossAttentionBlock(width, heads, ff_dim, dropout, context_dim=dim) for _ in range(layers)
        )
        self.norm = nn.LayerNorm(width)

    def forward(self, obs: Tensor, prompt: Tensor) -> Tensor:
        b, k, n, _ = obs.shape
        x = rearrange(self.inp(obs) + self.positions(k), "b k n d -> b (k n) d")
        mask = attention_mask(dt_star_groups(0, k, n), DT_STAR_RULES).to(x.device)
        for self_block, cross_block in zip(self.self_blocks, self.cross_blocks, strict=True):
            x = cross_block(self_block(x, src_mask=mask), prompt)
        return rearrange(self.norm(x), "b (k n) d -> b k n d", k=k)


class Vid2Robot(VisualPolicyNet):
    """Backbone, one single-frame Perceiver (+ state token) for prompt and observation frames, the prompt
    resampler, the prompt-robot cross-attention Transformer, Gamma_act and the contrastive projections."""

    def __init__(self, config: Vid2RobotConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.tokenizer = make_tokenizer(config, self.backbone.dim)
        self.prompt_encoder = make_prompt_encoder(config, self.backbone.dim)
        self.prompt_encoder.frame_perceiver = self.tokenizer.perceiver  # one Perceiver for prompt and robot
        self.transformer = PromptCrossAttentionTransformer(
            config.perceiver_dim,
            config.predictor_dim,
            config.predictor_heads,
            config.predictor_ff_dim,
            config.predictor_layers,
            config.predictor_dropout,
            max_steps=config.n_obs_steps,
            tokens_per_step=config.frame_perceiver_queries + 1,
        )
        self.action_head = make_action_head(config, config.predictor_dim)
        self.contrastive = PromptAlignment(config.perceiver_dim, config.perceiver_dim)

    def encode_prompt_frames(
        self, video: Tensor, mask: Tensor | None, ids: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """(B, N, 3, H, W) -> prompt tokens (B, N_prt, D) and per-frame embeddings (B, N, D)."""
        tokens = self.prompt_backbone_tokens(video, mask, ids)
        return self.prompt_encoder(tokens, mask), self.prompt_encoder.encode_frames(tokens).mean(2)

    def action_logits(self, prompt: Tensor, obs: Tensor) -> Tensor:
        """Prompt tokens (B, N_prt, D), obs tokens (B, k, N, D) -> logits (B, k, A, bins)."""
        return self.action_head(self.transformer(obs, prompt))


class Vid2RobotPolicy(ContextActionPolicy):
    """Vid2Robot-D (trained on ``_demo``) / Vid2Robot-M (on ``_mix``)."""

    config_class = Vid2RobotConfig
    name = "jept_vid2robot"
    model_class = Vid2Robot

    def get_optim_params(self) -> list[dict]:
        m = self.model  # the encoder group holds the Perceiver shared with the prompt
        return self.prompted_lr_groups([m.transformer, m.action_head, m.contrastive])

    def auxiliary_losses(self, batch: dict[str, Tensor], obs: Tensor) -> tuple[Tensor, Tensor, dict]:
        """Prompt/robot video contrastive and temporal cycle consistency, on every frame."""
        cfg, m = self.config, self.model
        if PROMPT_VIDEO not in batch:
            batch = {**batch, **self.deployment_prompt(batch)}
        prompt_mask = batch.get(PROMPT_MASK)
        prompt, prompt_frames = m.encode_prompt_frames(batch[PROMPT_VIDEO], prompt_mask, batch.get(PROMPT_ID))
        task_ids = self.task_ids(batch, obs.shape[0], obs.device)
        contrastive = m.contrastive(prompt, obs, task_ids, cfg.aux_temperature)
        pad = batch.get(f"{cfg.image_key}_is_pad")
        robot_ok = torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device) if pad is None else ~pad
        prompt_ok = (
            torch.ones(prompt_frames.shape[:2], dtype=torch.bool, device=obs.device)
            if prompt_mask is None
            else prompt_mask.bool()
        )
        alignment = cycle_consistency_loss(
            obs.mean(2), prompt_frames, robot_ok, prompt_ok, cfg.aux_temperature
        )
        aux = cfg.video_contrastive_weight * contrastive + cfg.video_alignment_weight * alignment
        info = {"loss_video_contrastive": contrastive.item(), "loss_video_alignment": alignment.mean().item()}
        return prompt, aux, info
