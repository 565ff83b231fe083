"""Transformer building blocks shared by the Perceivers, the temporal encoder and the causal predictor."""

import torch
from torch import Tensor, nn


class FeedForward(nn.Sequential):
    def __init__(self, dim: int, hidden_dim: int, dropout: float = 0.0):
        super().__init__(
            nn.Linear(dim, hidden_dim), nn.GELU(), nn.Dropout(dropout), nn.Linear(hidden_dim, dim)
        )


class CrossAttentionBlock(nn.Module):
    """Pre-norm cross-attention of ``queries`` (B, Nq, D) on ``context`` (B, Nc, Dc), then a feed-forward."""

    def __init__(
        self, dim: int, heads: int, ff_dim: int, dropout: float = 0.0, context_dim: int | None = None
    ):
        super().__init__()
        context_dim = context_dim or dim
        self.norm_q = nn.LayerNorm(dim)
        self.norm_c = nn.LayerNorm(context_dim)
        self.attn = nn.MultiheadAttention(
            dim, heads, dropout=dropout, kdim=context_dim, vdim=context_dim, batch_first=True
        )
        self.norm_ff = nn.LayerNorm(dim)
        self.ff = FeedForward(dim, ff_dim, dropout)

    def forward(self, queries: Tensor, context: Tensor) -> Tensor:
        c = self.norm_c(context)
        queries = queries + self.attn(self.norm_q(queries), c, c, need_weights=False)[0]
        return queries + self.ff(self.norm_ff(queries))


class SelfAttentionStack(nn.Module):
    """``layers`` pre-norm Transformer encoder layers over (B, N, D).

    ``mask`` (N, N) and ``key_padding_mask`` (B, N) are bool, True = blocked.
    """

    def __init__(self, dim: int, heads: int, ff_dim: int, layers: int, dropout: float = 0.0):
        super().__init__()
        layer = nn.TransformerEncoderLayer(
            dim, heads, ff_dim, dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.layers = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(dim)

    def forward(
        self, x: Tensor, mask: Tensor | None = None, key_padding_mask: Tensor | None = None
    ) -> Tensor:
        return self.norm(self.layers(x, mask=mask, src_key_padding_mask=key_padding_mask))

    def forward_selected(self, x: Tensor, selected: Tensor, key_padding_mask: Tensor | None = None) -> Tensor:
        """Outputs (B, M, D) of the tokens ``x[b, selected[b]]`` only (``selected``: (B, M) indices): every layer
        but the last runs on all tokens, the last only on the selected queries. Same values as ``forward``."""
        layers = self.layers.layers
        for layer in layers[:-1]:
            x = layer(x, src_key_padding_mask=key_padding_mask)
        last = layers[-1]
        picked = torch.gather(x, 1, selected[..., None].expand(-1, -1, x.shape[-1]))
        kv = last.norm1(x)
        attn = last.self_attn(
            last.norm1(picked), kv, kv, key_padding_mask=key_padding_mask, need_weights=False
        )[0]
        picked = picked + last.dropout1(attn)
        return self.norm(picked + last._ff_block(last.norm2(picked)))

    # Control (inference, no dropout): each layer's keys and values are kept, so tokens that come later attend to
    # earlier ones without projecting them again. ``KV``: per layer, keys and values (B, heads, N, head_dim).

    def prefix_kv(self, x: Tensor) -> "KV":
        """The keys and values of a prefix of tokens (B, P, D) that attends only to itself (a first group under a
        block-causal mask): the same whatever follows it, so computed once for all that does."""
        return self.forward_after([], x, torch.zeros(x.shape[1], x.shape[1], dtype=torch.bool))[1]

    def forward_after(
        self, prefix: "KV", x: Tensor, mask: Tensor, last: int | None = None
    ) -> tuple[Tensor, "KV"]:
        """``forward`` of the tokens ``x`` (B, M, D) after a prefix whose keys and values are ``prefix`` (an
        empty list: none). ``mask`` (M, P + M), True = blocked, is the rows of ``x`` in the whole sequence's
        mask. Returns the outputs (only the ``last`` tokens' when given: the last layer then runs those queries
        alone) and the keys and values of prefix and ``x`` together, for :meth:`extend`."""
        layers, kv = self.layers.layers, []
        for i, layer in enumerate(layers):
            q, k, v = _project(layer, layer.norm1(x))
            if prefix:
                k, v = torch.cat([prefix[i][0], k], dim=2), torch.cat([prefix[i][1], v], dim=2)
            kv.append((k, v))
            rows = mask
            if last is not None and i == len(layers) - 1:
                x, q, rows = x[:, -last:], q[:, :, -last:], mask[-last:]
            x = x + _attend(layer, q, k, v, ~rows.to(x.device))
            x = x + layer._ff_block(layer.norm2(x))
        return self.norm(x), kv

    def extend(self, kv: "KV", x: Tensor) -> Tensor:
        """Outputs of new tokens ``x`` (B, M, D) appended after the tokens whose keys and values are ``kv``;
        they attend to all of those and to each other (a last group under a block-causal mask), and nothing
        already computed changes: the old tokens never attend to later ones."""
        for layer, (k_old, v_old) in zip(self.layers.layers, kv, strict=True):
            q, k, v = _project(layer, layer.norm1(x))
            x = x + _attend(layer, q, torch.cat([k_old, k], dim=2), torch.cat([v_old, v], dim=2))
            x = x + layer._ff_block(layer.norm2(x))
        return self.norm(x)


KV = list[tuple[Tensor, Tensor]]


def _project(layer: nn.TransformerEncoderLayer, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A layer's query, key and value projections of normalised tokens (B, N, D), each (B, heads, N, D / heads)."""
    attn = layer.self_attn
    q, k, v = nn.functional.linear(x, attn.in_proj_weight, attn.in_proj_bias).chunk(3, dim=-1)
    return tuple(t.unflatten(-1, (attn.num_heads, -1)).transpose(1, 2) for t in (q, k, v))


def _attend(
    layer: nn.TransformerEncoderLayer, q: Tensor, k: Tensor, v: Tensor, allowed: Tensor | None = None
):
    """The layer's multi-head attention on projected queries, keys and values -> (B, Nq, D); ``allowed`` (Nq,
    Nk) bool, True where a query may attend (all, when None)."""
    out = nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=allowed)
    return layer.self_attn.out_proj(out.transpose(1, 2).flatten(2))


def sinusoidal_positions(length: int, dim: int) -> Tensor:
    """(length, dim) fixed sinusoidal position table."""
    position = torch.arange(length, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-torch.log(torch.tensor(10000.0)) / dim))
    table = torch.zeros(length, dim)
    table[:, 0::2] = torch.sin(position * freq)
    table[:, 1::2] = torch.cos(position * freq[: dim // 2])
    return table


class StepPositions(nn.Module):
    """Position of a token in a (time step, token within the step) grid: (T, N, D), T <= max_steps.

    Fixed sinusoids over time steps plus a learned embedding per token slot of a step.
    """

    def __init__(self, max_steps: int, tokens_per_step: int, dim: int):
        super().__init__()
        self.register_buffer("time", sinusoidal_positions(max_steps, dim)[:, None], persistent=False)
        self.token = nn.Parameter(torch.randn(tokens_per_step, dim) * 0.02)

    def forward(self, num_steps: int) -> Tensor:
        return self.time[:num_steps] + self.token
