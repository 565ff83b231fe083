"""JEPT (Joint Embedding Predictive Transformer) as a LeRobot policy plugin.

Importing this package registers the ``jept`` policy type, its processor steps and the ``jept_metaworld`` and
``jept_robosuite`` envs.
"""

from lerobot_jept.configuration_jept import JEPTConfig
from lerobot_jept.envs.configs import JeptMetaworldEnvConfig, JeptRobosuiteEnvConfig
from lerobot_jept.modeling_jept import JEPTPolicy
from lerobot_jept.processor_jept import make_jept_pre_post_processors

__all__ = [
    "JEPTConfig",
    "JEPTPolicy",
    "JeptMetaworldEnvConfig",
    "JeptRobosuiteEnvConfig",
    "make_jept_pre_post_processors",
]
