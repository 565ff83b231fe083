"""The latent action model of LAPO ("Learning to Act without Actions", Schmidt & Jiang, ICLR 2024).

A latent action is what an inverse dynamics model reads from a transition (o_t, o_{t+1}) once it has gone
through a quantised bottleneck that a forward dynamics model needs to predict o_{t+1} from o_t: the only way
through the bottleneck is the part of the change o_t alone does not predict, the agent's own action. Nothing
here reads an action, so the model learns from every frame, labelled or not.

Observations are read as vectors: the self-state and the camera frames average-pooled to ``pixels`` x ``pixels``
(LAPO predicts pixels too, at full size). The forward model predicts the change of that vector, each feature in
units of its running RMS. The bottleneck is finite scalar quantisation (FSQ, Mentzer et al., 2024): ``dims``
numbers, each rounded to one of ``levels`` values, so a latent action is ``dims`` small integers, read by the
latent policy as ``dims`` classification targets (as the action bins are) and never collapsing onto one code
as a learned codebook can.
"""

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_jept.policies.components.predictor import ObservationHead


class FiniteScalarQuantizer(nn.Module):
    """(..., dims) -> each number squashed into [-1, 1] and rounded to the nearest of ``levels`` evenly spaced
    values (straight-through gradient), and the level indices (..., dims) in [0, levels)."""

    def __init__(self, levels: int):
        super().__init__()
        if levels < 3 or levels % 2 == 0:
            raise ValueError(f"latent_levels must be odd and at least 3 (0 is one level), got {levels}.")
        self.half = (levels - 1) // 2

    def forward(self, z: Tensor) -> tuple[Tensor, Tensor]:
        bounded = torch.tanh(z) * self.half
        rounded = torch.round(bounded)
        straight_through = (bounded + (rounded - bounded).detach()) / self.half
        return straight_through, (rounded + self.half).long()

    def values(self, indices: Tensor) -> Tensor:
        """Level indices (..., dims) -> their values in [-1, 1] (what the decoder reads)."""
        return (indices.float() - self.half) / self.half


class LatentActionModel(nn.Module):
    """Inverse dynamics (o_t, o_{t+1}) -> latent action, through FSQ, and forward dynamics (o_t, latent) ->
    the change of the observation vector.

    ``observation_vector`` (B, T, S) states and (B, T, ..., H, W) frames -> (B, T, F); ``forward`` (B, T + 1, F)
    vectors -> latent values (B, T, dims), level indices (B, T, dims) and the forward model's squared error
    (B, T) per transition.
    """

    def __init__(self, obs_dim: int, dims: int, levels: int, pixels: int, hidden_dim: int, layers: int):
        super().__init__()
        self.pixels = pixels
        self.inverse = ObservationHead(2 * obs_dim, dims, hidden_dim, layers)
        self.quantizer = FiniteScalarQuantizer(levels)
        self.forward_model = ObservationHead(obs_dim + dims, obs_dim, hidden_dim, layers)
        self.register_buffer("scale", torch.ones(obs_dim))
        self.register_buffer("scale_updates", torch.zeros((), dtype=torch.long))

    def observation_vector(self, state: Tensor, frames: Tensor) -> Tensor:
        b, t = state.shape[:2]
        images = frames.float().reshape(b * t, -1, *frames.shape[-2:])
        pooled = F.adaptive_avg_pool2d(images, self.pixels).reshape(b, t, -1)
        return torch.cat([state, pooled], dim=-1)

    @torch.no_grad()
    def update_scale(self, vectors: Tensor, valid: Tensor, momentum: float = 0.01) -> None:
        """Training: move the per-feature RMS of the changes towards this batch's (the first batch sets it)."""
        change = (vectors[:, 1:] - vectors[:, :-1])[valid]
        if change.shape[0] == 0:
            return
        rms = change.pow(2).mean(0).sqrt().clamp_min(1e-6)
        self.scale.copy_(rms if self.scale_updates == 0 else self.scale.lerp(rms, momentum))
        self.scale_updates += 1

    def forward(self, vectors: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        before, change = vectors[:, :-1], (vectors[:, 1:] - vectors[:, :-1]) / self.scale
        latent, indices = self.quantizer(self.inverse(torch.cat([before, change], dim=-1)))
        predicted = self.forward_model(torch.cat([before, latent], dim=-1))
        return latent, indices, (predicted - change).pow(2).mean(-1)


class LatentActionDecoder(nn.Module):
    """(latent values (N, dims), self-state (N, S)) -> action logits (N, action_dim, num_bins): the map from
    latent to real actions, fitted on labelled frames only."""

    def __init__(
        self, dims: int, state_dim: int, action_dim: int, num_bins: int, hidden_dim: int, layers: int
    ):
        super().__init__()
        self.action_dim = action_dim
        self.mlp = ObservationHead(dims + state_dim, action_dim * num_bins, hidden_dim, layers)

    def forward(self, latent: Tensor, state: Tensor) -> Tensor:
        return self.mlp(torch.cat([latent, state], dim=-1)).unflatten(-1, (self.action_dim, -1))
