"""``LAPOPolicy``: latent action policies (LAPO, Schmidt & Jiang, ICLR 2024) conditioned on the prompt video.

Training (one ``forward``): the latent action model reads every transition (o_j, o_j+1) of the sample, labelled
or not, and learns through its forward dynamics loss; the latent policy (DT*'s network over the prompt and the k
context frames) learns to predict each frame's latent action; the decoder learns the real action from the
latent action and the self-state on the labelled frames alone. Control: the latent policy's latent action for
the current frame, decoded to the action bins.
"""

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.utils.constants import OBS_STATE
from torch import Tensor

from lerobot_jept.policies.base import (
    IGNORE_INDEX,
    DiscreteActionPolicy,
    VisualPolicyNet,
    make_action_head,
    make_backbone,
    make_dt_star_transformer,
    make_prompt_encoder,
    make_tokenizer,
)
from lerobot_jept.policies.components.latent_action import LatentActionDecoder, LatentActionModel
from lerobot_jept.policies.lapo.configuration_lapo import LAPOConfig


class LAPO(VisualPolicyNet):
    """Backbone, single-frame tokenizer, Psi_prt and the causal Transformer of DT*, a latent action head, the
    latent action model and the decoder."""

    def __init__(self, config: LAPOConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.tokenizer = make_tokenizer(config, self.backbone.dim)
        self.prompt_encoder = make_prompt_encoder(config, self.backbone.dim)
        self.transformer = make_dt_star_transformer(config)
        self.latent_head = make_action_head(
            config, config.predictor_dim, config.latent_dims, config.latent_levels
        )
        state_dim = config.input_features[OBS_STATE].shape[0]
        cameras = len(config.image_keys)
        mlp = dict(hidden_dim=config.latent_hidden_dim, layers=config.latent_layers)
        self.latent_model = LatentActionModel(
            state_dim + 3 * cameras * config.latent_pixels**2,
            config.latent_dims,
            config.latent_levels,
            config.latent_pixels,
            **mlp,
        )
        self.decoder = LatentActionDecoder(
            config.latent_dims, state_dim, config.resolved_action_dim, config.num_action_bins, **mlp
        )

    def latent_logits(self, prompt: Tensor, obs: Tensor) -> Tensor:
        """E_prt (B, N_prt, D) and obs tokens (B, k, N, D) -> logits (B, k, latent_dims, latent_levels)."""
        return self.latent_head(self.transformer(prompt, obs))

    def decode(self, latent_logits: Tensor, state: Tensor) -> Tensor:
        """The most likely latent action (..., dims, levels) and the self-state (..., S) -> action logits."""
        latent = self.latent_model.quantizer.values(latent_logits.argmax(-1))
        return self.decoder(latent, state)


class LAPOPolicy(DiscreteActionPolicy):
    """LAPO: a latent policy learned from every frame, a decoder to real actions from the labelled ones."""

    config_class = LAPOConfig
    name = "jept_lapo"
    model_class = LAPO

    def get_optim_params(self) -> list[dict]:
        m = self.model
        return self.prompted_lr_groups([m.transformer, m.latent_head, m.latent_model, m.decoder])

    def transitions(
        self, batch: dict[str, Tensor], frames: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The latent model on the sample's k transitions: latent values and level indices (B, k, dims), the
        forward loss per transition (B, k), and which transitions are real (B, k; both frames unpadded).
        Reads the frames and the self-state only."""
        m, k = self.model, self.config.n_obs_steps
        frames = self.camera_frames(batch) if frames is None else frames
        state = batch[OBS_STATE]
        pad = batch.get(f"{self.config.image_key}_is_pad")
        valid = torch.ones(state.shape[:2], dtype=torch.bool, device=state.device) if pad is None else ~pad
        valid = valid[:, :k] & valid[:, 1 : k + 1]
        vectors = m.latent_model.observation_vector(state[:, : k + 1], frames[:, : k + 1])
        if self.training:
            m.latent_model.update_scale(vectors, valid)
        latent, indices, error = m.latent_model(vectors)
        return latent, indices, error, valid

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        cfg, m, k = self.config, self.model, self.config.n_obs_steps
        frames = self.camera_frames(batch)
        latent, indices, error, valid = self.transitions(batch, frames)
        ok = valid.float()
        loss_forward = (error * ok).sum(1) / ok.sum(1).clamp_min(1)

        obs = m.frame_tokens(frames[:, :k], batch[OBS_STATE][:, :k])
        logits = m.latent_logits(self.prompt(batch), obs)  # (B, k, dims, levels)
        targets = indices.masked_fill(~valid[..., None], IGNORE_INDEX)
        ce = F.cross_entropy(
            logits.permute(0, 3, 1, 2), targets, ignore_index=IGNORE_INDEX, reduction="none"
        ).mean(-1)
        loss_latent = (ce * ok).sum(1) / ok.sum(1).clamp_min(1)

        # the decoder: labelled real transitions only, on the latent model's latents (no gradient into it)
        labels = self.action_labels(batch, (*valid.shape, cfg.resolved_action_dim))
        labelled = valid & (labels[..., 0] != IGNORE_INDEX)
        loss_decoder = latent.new_zeros(latent.shape[0])
        if labelled.any():
            rows = labelled.nonzero(as_tuple=True)
            decoded = m.decoder(latent.detach()[rows], batch[OBS_STATE][:, :k][rows])
            per_frame = F.cross_entropy(decoded.flatten(0, 1), labels[rows].flatten(), reduction="none")
            per_frame = per_frame.view(-1, cfg.resolved_action_dim).mean(-1)
            loss_decoder = loss_decoder.index_add(0, rows[0], per_frame) / labelled.sum(1).clamp_min(1)
        has_label = labelled.any(1).float()
        mean_decoder = (loss_decoder * has_label).sum() / has_label.sum().clamp_min(1)

        per_sample = cfg.latent_forward_weight * loss_forward + cfg.latent_policy_weight * loss_latent
        info = {
            "loss_act": mean_decoder.item(),
            "loss_latent_forward": loss_forward.mean().item(),
            "loss_latent_policy": loss_latent.mean().item(),
            "latent_codes_used": torch.unique(indices[valid], dim=0).shape[0] if valid.any() else 0,
            "labelled_fraction": labelled.float().mean().item(),
            **self.learning_rates(),
        }
        if reduction == "none":
            return per_sample + loss_decoder, info
        return per_sample.mean() + mean_decoder, info

    @torch.no_grad()
    def offline_outputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """``control``: logits (B, A, bins) of a_t for the last context frame of a preprocessed training-shaped
        batch, as ``select_action`` chooses it."""
        m, k = self.model, self.config.n_obs_steps
        obs = m.frame_tokens(self.camera_frames(batch)[:, :k], batch[OBS_STATE][:, :k])
        latent_logits = m.latent_logits(self.prompt(batch), obs)[:, -1]
        return {"control": m.decode(latent_logits, batch[OBS_STATE][:, k - 1])}

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """(B, action_dim) actions for the current observation (see ``control_actions``)."""
        prompt = self.episode_prompt(batch)
        obs = self.context_tokens(self.camera_frames(batch), batch[OBS_STATE])
        logits = self.model.decode(self.model.latent_logits(prompt, obs)[:, -1], batch[OBS_STATE])
        return self.control_actions(logits)
