"""JEPT (Joint Embedding Predictive Transformer) as a LeRobot policy plugin.

``import lerobot_policy_jept`` (what LeRobot's scripts do) registers the ``jept`` policy type and its baselines
(``jept_dt_star``, ``jept_vid2robot``, ``jept_idm``, ``jept_no_prompt``, ``jept_lapo``), their processor steps and
the ``jept_metaworld`` / ``jept_robosuite`` envs, each when LeRobot loads the registry it extends
(:mod:`lerobot_jept.registration`).
The package-level names below load on first use, so that the dataset builders, which import
``lerobot_jept.envs`` in every worker process, do not pay for the model.
"""

import importlib

from lerobot_jept.registration import register

_EXPORTS = {
    "JEPTConfig": "lerobot_jept.policies.jept.configuration_jept",
    "JEPTPolicy": "lerobot_jept.policies.jept.modeling_jept",
    "make_jept_pre_post_processors": "lerobot_jept.policies.jept.processor_jept",
    "DTStarConfig": "lerobot_jept.policies.dt_star.configuration_dt_star",
    "DTStarPolicy": "lerobot_jept.policies.dt_star.modeling_dt_star",
    "Vid2RobotConfig": "lerobot_jept.policies.vid2robot.configuration_vid2robot",
    "Vid2RobotPolicy": "lerobot_jept.policies.vid2robot.modeling_vid2robot",
    "IDMConfig": "lerobot_jept.policies.idm.configuration_idm",
    "IDMPolicy": "lerobot_jept.policies.idm.modeling_idm",
    "JEPTNoPromptConfig": "lerobot_jept.policies.jept_no_prompt.configuration_jept_no_prompt",
    "JEPTNoPromptPolicy": "lerobot_jept.policies.jept_no_prompt.modeling_jept_no_prompt",
    "LAPOConfig": "lerobot_jept.policies.lapo.configuration_lapo",
    "LAPOPolicy": "lerobot_jept.policies.lapo.modeling_lapo",
    "JeptMetaworldEnvConfig": "lerobot_jept.envs.configs",
    "JeptRobosuiteEnvConfig": "lerobot_jept.envs.configs",
}

__all__ = [*_EXPORTS, "register"]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lerobot_jept' has no attribute {name!r}")
