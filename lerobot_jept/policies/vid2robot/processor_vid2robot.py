"""``make_jept_vid2robot_pre_post_processors``: JEPT's pipeline (prompt video from the bank, action bins)."""

from lerobot_jept.policies.jept.processor_jept import make_jept_pre_post_processors
from lerobot_jept.policies.vid2robot.configuration_vid2robot import Vid2RobotConfig


def make_jept_vid2robot_pre_post_processors(config: Vid2RobotConfig, dataset_stats=None, **kwargs):
    return make_jept_pre_post_processors(config, dataset_stats)
