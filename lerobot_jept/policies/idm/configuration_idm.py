"""``IDMConfig``: the inverse dynamics model of the BC+IDM baseline (paper Section 4.1).

a_t = f(o_t, o_{t+1}), learned on labelled frames (``--policy.type=jept_idm``), then used by ``jept-relabel`` to give
every unlabelled frame of a ``_mix`` repo an action; BC is ``jept_dt_star`` on the relabelled repo.
"""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.configuration import RetiredJEPTOptions, VideoPolicyConfig, check_idm_input


@PreTrainedConfig.register_subclass("jept_idm")
@dataclass
class IDMConfig(VideoPolicyConfig, RetiredJEPTOptions):
    """Inverse dynamics model (``--policy.type=jept_idm``): JEPT's backbone, single-frame Perceiver tokenizer and
    action head (Table 5 defaults; the small configuration is ``examples/configs/train_idm_small_cpu.json``).
    The tokens of o_t and o_{t+1} (N_obs each) go through a bi-directional Transformer of the ``predictor_*``
    sizes, and the action head reads a_t from all of them. Loss: cross-entropy over the action bins on labelled
    frames. No prompt: the IDM sees the transition, not the task.

    ``idm_input``: ``"embedding"`` (default) reads the frames' tokens as above; ``"self_state"`` makes the IDM an
    MLP (``obs_head_hidden_dim`` wide, ``obs_head_layers`` deep) from the self-state and its change
    (s_t, s_t+1 - s_t) alone, no camera (VPT / BCO style); the change carries the action in every scene, so it
    labels the video-only tasks' frames far better than pixel tokens. ``optimizer_lr_encoder`` trains the
    tokenizer (and a trained backbone), ``optimizer_lr_predictor`` the Transformer and the action head. The
    prompt options and ``n_obs_steps`` take no part; JEPT's own options (``temporal_*``, ``ema_decay``,
    ``phase_*``, the prompt terms, the recipe) are not options of this type.
    """

    idm_input: str = "embedding"
    obs_head_hidden_dim: int = 256
    obs_head_layers: int = 3

    def __post_init__(self):
        super().__post_init__()
        check_idm_input(self.idm_input)

    @property
    def observation_delta_indices(self) -> list[int]:
        return [0, 1]  # o_t, o_{t+1}

    @property
    def action_delta_indices(self) -> list[int]:
        return [0]
