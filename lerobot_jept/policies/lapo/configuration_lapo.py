"""``LAPOConfig``: the latent-action baseline, LAPO ("Learning to Act without Actions", Schmidt & Jiang, ICLR
2024), conditioned on the prompt video and built from JEPT's parts."""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.configuration import BehaviourCloningConfig


@PreTrainedConfig.register_subclass("jept_lapo")
@dataclass
class LAPOConfig(BehaviourCloningConfig):
    """LAPO (``--policy.type=jept_lapo``; the small configuration is ``examples/configs/train_lapo_small_cpu.json``).
    Three parts, trained together in one run, each on what it may see:

    - the latent action model (:mod:`lerobot_jept.policies.components.latent_action`): inverse dynamics from each
      transition (o_j, o_j+1) of the sample to a latent action (``latent_dims`` numbers of ``latent_levels``
      levels each, finite scalar quantisation), and forward dynamics that must predict the change of the
      observation vector (self-state and the frames pooled to ``latent_pixels`` x ``latent_pixels``) from o_j
      and that latent. Every frame, labelled or not; it never reads an action.
    - the latent policy: DT*'s network (backbone, single-frame Perceiver, prompt video encoder, causal
      Transformer over ``[E_prt | o_t-k+1, ..., o_t]``), whose action head reads each frame's latent action
      (one query per latent number, ``latent_levels`` classes each) instead of the real one. Every frame; its
      targets are the latent model's (no gradient flows into the latent model from them).
    - the decoder: an MLP from (latent action, self-state) to the action bins, fitted on the labelled frames
      only, on the latent model's latents of their real transitions.

    Control: the latent policy's most likely latent action, decoded. LAPO fits its decoder after the rest and
    may fine-tune the latent policy's head with rewards; here the parts train at once (the latents are detached)
    and nothing uses rewards. ``latent_hidden_dim`` / ``latent_layers`` size the three MLPs.

    Shared with JEPT: the backbone, ``perceiver_*``, ``frame_perceiver_*``, ``prompt_perceiver_*``,
    ``predictor_*``, ``action_head_*`` (the latent policy's head), the bins, the optimizer groups
    (``optimizer_lr_encoder``, ``optimizer_lr_prompt``, ``optimizer_lr_predictor``, the last for the
    Transformer, its head, the latent model and the decoder) and the prompt bank. JEPT's own options
    (``joint_embedding_dim``, ``temporal_*``, ``obs_head_*``, ``ema_decay``, ``phase_*``, the prompt terms, the
    recipe) are not options of this type. Samples hold the k context frames and the next one.
    """

    latent_dims: int = 4
    latent_levels: int = 5
    latent_pixels: int = 8
    latent_hidden_dim: int = 256
    latent_layers: int = 3
    latent_forward_weight: float = 1.0
    latent_policy_weight: float = 1.0
    drop_n_last_frames: int = 1  # the last frame of an episode has no transition

    def __post_init__(self):
        super().__post_init__()
        if self.latent_levels < 3 or self.latent_levels % 2 == 0:
            raise ValueError(
                f"--policy.latent_levels must be odd and at least 3 (levels are symmetric around 0), got "
                f"{self.latent_levels}."
            )
        if self.latent_dims < 1 or self.latent_pixels < 1:
            raise ValueError("--policy.latent_dims and --policy.latent_pixels must be at least 1.")

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.n_obs_steps, 2))  # k context frames and the next one
