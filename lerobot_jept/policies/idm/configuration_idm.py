"""``IDMConfig``: the inverse dynamics model of the BC+IDM baseline (paper Section 4.1).

a_t = f(o_t, o_{t+1}), learned on labelled frames (``--policy.type=jept_idm``), then used by ``jept-relabel`` to give
every unlabelled frame of a ``_mix`` repo an action; BC is ``jept_dt_star`` on the relabelled repo.
"""

from dataclasses import dataclass
from typing import ClassVar

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.jept.configuration_jept import JEPT_ONLY_OPTIONS, JEPTConfig


@PreTrainedConfig.register_subclass("jept_idm")
@dataclass
class IDMConfig(JEPTConfig):
    """Inverse dynamics model (``--policy.type=jept_idm``): JEPT's backbone, single-frame Perceiver tokenizer and
    action head (Table 5 defaults; the small configuration is ``examples/configs/train_idm_small_cpu.json``).
    The tokens of o_t and o_{t+1} (N_obs each) go through a bi-directional Transformer of the ``predictor_*``
    sizes, and the action head reads a_t from all of them. Loss: cross-entropy over the action bins on labelled
    frames. No prompt: the IDM sees the transition, not the task. ``--policy.idm_input=self_state``: the IDM is
    an MLP from the self-state and its change (s_t, s_t+1 - s_t) alone, no camera (VPT / BCO style); the change
    carries the action in every scene, so it labels the video-only tasks' frames far better than pixel tokens. Unused (JEPT-only): ``n_obs_steps``,
    ``joint_embedding_dim``, ``temporal_*``, ``obs_head_*``, ``ema_decay``, ``action_loss_weight``,
    ``phase_*``, ``prompt_*`` and ``max_prompt_length``; ``optimizer_lr_encoder`` trains the tokenizer (and a
    trained backbone), ``optimizer_lr_predictor`` the Transformer and the action head.
    """

    ignored_options: ClassVar[tuple[str, ...]] = tuple(
        o for o in JEPT_ONLY_OPTIONS if o not in ("obs_head_hidden_dim", "obs_head_layers", "idm_input")
    )
    recipe: str = "paper"  # JEPT's options at the paper's values: none of them applies to the IDM
    prompt_align_weight: float = 0.0
    prompt_swap_weight: float = 0.0

    @property
    def observation_delta_indices(self) -> list[int]:
        return [0, 1]  # o_t, o_{t+1}

    @property
    def action_delta_indices(self) -> list[int]:
        return [0]
