"""``Vid2RobotConfig``: the Vid2Robot baseline (Jain et al., 2024; paper Section 4.1 and Appendix A.3).

Trained on ``_demo`` it is Vid2Robot-D; on ``_mix`` (behaviour cloning masked on the video frames, the auxiliary
losses on every frame) it is Vid2Robot-M.
"""

from dataclasses import dataclass

from lerobot.configs.policies import PreTrainedConfig

from lerobot_jept.policies.configuration import BehaviourCloningConfig


@PreTrainedConfig.register_subclass("jept_vid2robot")
@dataclass
class Vid2RobotConfig(BehaviourCloningConfig):
    """Vid2Robot (``--policy.type=jept_vid2robot``) built from JEPT's parts, as Appendix A.3 adapts it: the same
    backbone and the same single-frame Perceiver encode prompt frames and observation frames (one module); the
    prompt's frame tokens are resampled by the prompt Perceiver (``prompt_perceiver_*``) into N_prt tokens; the
    observation tokens of the k context frames go through ``predictor_layers`` blocks of block-causal
    self-attention followed by cross-attention to the prompt tokens (Vid2Robot's prompt-robot cross-attention
    Transformer, ``predictor_*`` sizes); JEPT's action head reads a_j from the o_j tokens. Losses:

    - behaviour cloning: cross-entropy over the action bins, on labelled frames only;
    - ``video_contrastive_weight``: prompt/robot video contrastive loss, InfoNCE between the pooled prompt and the
      pooled robot window, same-task samples as positives (Vid2Robot's video-video contrastive loss);
    - ``video_alignment_weight``: temporal cycle consistency between the prompt frames and the robot frames
      (Vid2Robot's video alignment loss), ``aux_temperature`` for both;
    - the text-video contrastive loss is removed (no text here), as in the paper.

    Both auxiliary losses use every frame, labelled or not. JEPT's own options (``joint_embedding_dim``,
    ``temporal_*``, ``obs_head_*``, ``ema_decay``, ``phase_*``, the prompt terms, the recipe) are not options of
    this type. Samples hold the k context frames only.
    """

    video_contrastive_weight: float = 1.0
    video_alignment_weight: float = 1.0
    aux_temperature: float = 0.1
