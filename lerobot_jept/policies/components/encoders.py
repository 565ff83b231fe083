"""Visual encoders (paper, Section 3.2.1 and Appendix A.2).

- :class:`ObservationTokenizer`: the single-timestep encoder, shared by the joint embedding encoder and the
  causal predictor's observation tokens: backbone tokens -> Perceiver-IO (N_q queries) plus the self-state
  through an MLP as one more token -> (B, N_obs = N_q + 1, D).
- :class:`JointEmbeddingEncoder` (Psi_obs): observation tokens of k frames -> bi-directional temporal
  Transformer -> joint embeddings h (B, k, N_obs, joint_dim).
- :class:`PromptVideoEncoder` (Psi_prt): prompt frames -> backbone -> per-frame Perceiver -> a second Perceiver
  over the flattened frame tokens -> E_prt (B, N_prt, D).
"""

import torch
from einops import rearrange
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from lerobot_jept.policies.components.attention import SelfAttentionStack, StepPositions, sinusoidal_positions
from lerobot_jept.policies.components.perceiver import PerceiverIO


class ObservationTokenizer(nn.Module):
    """Backbone tokens (B, N, C) of one camera, or (B, K, N, C) of K cameras, + state (B, S) -> (B, N_q + 1, D).

    With several cameras, each camera's tokens get that camera's learned embedding and the Perceiver reads
    them all at once, so one observation is N_q + 1 tokens whatever the number of cameras.
    """

    def __init__(self, backbone_dim: int, state_dim: int, perceiver: dict, dim: int, num_cameras: int = 1):
        super().__init__()
        self.perceiver = PerceiverIO(backbone_dim, dim=dim, **perceiver)
        self.state_mlp = nn.Sequential(nn.Linear(state_dim, dim), nn.GELU(), nn.Linear(dim, dim))
        if num_cameras > 1:
            self.camera_embedding = nn.Parameter(torch.randn(num_cameras, backbone_dim) * 0.02)

    def forward(self, backbone_tokens: Tensor, state: Tensor) -> Tensor:
        if backbone_tokens.ndim == 4:  # (B, K, N, C): the cameras, each tagged
            backbone_tokens = (backbone_tokens + self.camera_embedding[None, :, None]).flatten(1, 2)
        visual = self.perceiver(backbone_tokens)
        return torch.cat([visual, self.state_mlp(state)[:, None]], dim=1)


class JointEmbeddingEncoder(nn.Module):
    """Observation tokens (B, T, N_obs, D_in) -> joint embeddings h (B, T, N_obs, joint_dim), bi-directional.

    :meth:`context_embeddings` gives each frame the embedding computed from the frames up to it only: the
    predictor's input h_j must not carry information about o_{j+1}, its own L_obs target (see README,
    "Design notes").
    """

    def __init__(
        self,
        input_dim: int,
        dim: int,
        joint_dim: int,
        heads: int,
        ff_dim: int,
        layers: int,
        dropout: float,
        max_steps: int,
        tokens_per_step: int,
    ):
        super().__init__()
        self.inp = nn.Linear(input_dim, dim) if input_dim != dim else nn.Identity()
        self.positions = StepPositions(max_steps, tokens_per_step, dim)
        self.temporal = SelfAttentionStack(dim, heads, ff_dim, layers, dropout)
        self.out = nn.Linear(dim, joint_dim)

    def forward(self, obs_tokens: Tensor, frame_padding: Tensor | None = None) -> Tensor:
        """``frame_padding`` (B, T) bool, True for frames the others must not attend to."""
        b, t, n, _ = obs_tokens.shape
        x = self.inp(obs_tokens) + self.positions(t)
        key_padding = None if frame_padding is None else frame_padding.repeat_interleave(n, dim=1)
        x = self.temporal(rearrange(x, "b t n d -> b (t n) d"), key_padding_mask=key_padding)
        return rearrange(self.out(x), "b (t n) d -> b t n d", t=t, n=n)

    def context_embeddings(self, obs_tokens: Tensor, first: int = 0) -> Tensor:
        """(B, T, N, D_in) -> (B, T - first, N, joint_dim): frame j (j >= ``first``) encoded bi-directionally
        over frames 0..j only. One batched pass over the windows, window j padding out the frames after j.
        """
        b, t, n, _ = obs_tokens.shape
        steps = torch.arange(t, device=obs_tokens.device)
        ends = steps[first:]
        windows = len(ends)
        padding = (steps[None, :] > ends[:, None]).repeat(b, 1).repeat_interleave(n, dim=1)  # (B*W, T*N)
        x = self.inp(obs_tokens) + self.positions(t)
        x = rearrange(x, "b t n d -> b (t n) d").repeat_interleave(windows, dim=0)
        # only the tokens of each window's last frame are needed from the last layer
        selected = (ends[:, None] * n + torch.arange(n, device=x.device)).repeat(b, 1)  # (B*W, N)
        h = self.out(self.temporal.forward_selected(x, selected, padding))
        return rearrange(h, "(b w) n d -> b w n d", b=b)


class PromptVideoEncoder(nn.Module):
    """Backbone tokens of N prompt frames (B, N, P, C) -> E_prt (B, N_prt, D).

    The per-frame Perceiver runs ``chunk_size`` frames at a time; when a batch holds more than one chunk and
    gradients are on, each chunk's activations are recomputed in the backward pass (activation checkpointing)
    instead of kept, so training memory grows with B x N only through the per-frame outputs (B, N, Q, D).
    """

    def __init__(
        self,
        backbone_dim: int,
        frame_perceiver: dict,
        video_perceiver: dict,
        dim: int,
        max_frames: int,
        chunk_size: int = 256,
        checkpointing: bool = True,
    ):
        super().__init__()
        self.frame_perceiver = PerceiverIO(backbone_dim, dim=dim, **frame_perceiver)
        self.register_buffer("frame_pos", sinusoidal_positions(max_frames, dim)[:, None], persistent=False)
        self.video_perceiver = PerceiverIO(dim, dim=dim, **video_perceiver)
        self.chunk_size, self.checkpointing = max(1, chunk_size), checkpointing

    def _frames(self, tokens: Tensor) -> Tensor:
        return self.frame_perceiver(tokens.to(self.frame_perceiver.latents.dtype))

    def encode_frames(self, frame_tokens: Tensor) -> Tensor:
        """(B, N, P, C) -> per-frame tokens (B, N, Q, D); the tokens may be in a cache dtype (bfloat16)."""
        b = frame_tokens.shape[0]
        flat = rearrange(frame_tokens, "b n p c -> (b n) p c")
        chunks = flat.split(self.chunk_size)
        recompute = self.checkpointing and len(chunks) > 1 and torch.is_grad_enabled()
        out = [
            checkpoint(self._frames, part, use_reentrant=False) if recompute else self._frames(part)
            for part in chunks
        ]
        per_frame = torch.cat(out) if len(out) > 1 else out[0]
        return rearrange(per_frame, "(b n) q d -> b n q d", b=b)

    def forward(self, frame_tokens: Tensor, frame_mask: Tensor | None = None) -> Tensor:
        """``frame_mask`` (B, N) True for real frames; padded frames are zeroed out of the video tokens."""
        per_frame = self.encode_frames(frame_tokens)
        n = per_frame.shape[1]
        per_frame = per_frame + self.frame_pos[:n]
        if frame_mask is not None:
            per_frame = per_frame * frame_mask[:, :, None, None]
        return self.video_perceiver(rearrange(per_frame, "b n q d -> b (n q) d"))
