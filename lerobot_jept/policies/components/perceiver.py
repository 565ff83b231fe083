"""Perceiver-IO resampler (Jaegle et al., 2022): any number of input tokens -> a fixed number of output tokens.

Encoder: learnable latents cross-attend to the inputs, then self-attend; decoder: learnable queries
cross-attend to the latents. Table 5 sizes: single-frame 64 latents -> 8 queries; temporal 128 -> 32.
"""

import torch
from einops import repeat
from torch import Tensor, nn

from lerobot_jept.policies.components.attention import CrossAttentionBlock, SelfAttentionStack


class PerceiverIO(nn.Module):
    """(B, N, input_dim) -> (B, num_queries, dim)."""

    def __init__(
        self,
        input_dim: int,
        dim: int = 512,
        num_latents: int = 64,
        num_queries: int = 8,
        heads: int = 8,
        encoder_cross_layers: int = 1,
        encoder_self_layers: int = 2,
        decoder_cross_layers: int = 1,
        ff_dim: int = 1024,
        dropout: float = 0.1,
    ):
        super().__init__()
        self.latents = nn.Parameter(torch.randn(num_latents, dim) * 0.02)
        self.queries = nn.Parameter(torch.randn(num_queries, dim) * 0.02)
        self.encoder_cross = nn.ModuleList(
            CrossAttentionBlock(dim, heads, ff_dim, dropout, context_dim=input_dim)
            for _ in range(encoder_cross_layers)
        )
        self.encoder_self = SelfAttentionStack(dim, heads, ff_dim, encoder_self_layers, dropout)
        self.decoder_cross = nn.ModuleList(
            CrossAttentionBlock(dim, heads, ff_dim, dropout) for _ in range(decoder_cross_layers)
        )

    def forward(self, x: Tensor) -> Tensor:
        latents = repeat(self.latents, "n d -> b n d", b=x.shape[0])
        for block in self.encoder_cross:
            latents = block(latents, x)
        latents = self.encoder_self(latents)
        out = repeat(self.queries, "n d -> b n d", b=x.shape[0])
        for block in self.decoder_cross:
            out = block(out, latents)
        return out
