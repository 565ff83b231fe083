"""``DTStarConfig``: DT*, JEPT with the joint embedding prediction removed (paper Section 4.1).

DT* is behaviour cloning with a Decision-Transformer-style causal Transformer over ``[E_prt | o_{t-k+1}, ...,
o_t]``: the same backbone, single-frame Perceiver tokenizer, prompt video encoder, action head and bins as JEPT,
the action a_j predicted from the o_j tokens, the loss L_act alone (on labelled frames), no EMA target. Trained
on ``_demo``; on ``_mix`` the video frames contribute nothing.
"""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.configuration import BehaviourCloningConfig


@PreTrainedConfig.register_subclass("jept_dt_star")
@dataclass
class DTStarConfig(BehaviourCloningConfig):
    """DT* (``--policy.type=jept_dt_star``). Every size is JEPT's (Table 5 defaults; the small configuration is
    ``examples/configs/train_dt_star_small_cpu.json``), so a comparison changes only the objective:

    - shared with JEPT: ``vision_backbone`` and the backbone flags, ``perceiver_*`` and ``frame_perceiver_*``
      (the observation tokens), ``prompt_perceiver_*`` and ``max_prompt_length`` (E_prt), ``predictor_*`` (the
      causal Transformer, here over prompt and observation tokens only), ``action_head_*``, the bins, the
      optimizer (``optimizer_lr_encoder`` for the tokenizer and a trained backbone, ``optimizer_lr_prompt``,
      ``optimizer_lr_predictor`` for the Transformer and the action head) and the prompt bank;
    - not options of DT*, as they belong to the joint embedding prediction it removes: JEPT's
      ``joint_embedding_dim``, ``temporal_*``, ``obs_head_*``, ``ema_decay``, ``action_loss_weight`` (the loss is
      L_act alone), ``phase_*`` (one phase), ``prompt_warmup_steps`` (the prompt is always in), the prompt
      terms and the recipe.

    Samples hold the k context frames only (no next frame), so ``drop_n_last_frames`` is 0.
    """
