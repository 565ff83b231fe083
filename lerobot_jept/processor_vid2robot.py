"""``make_jept_vid2robot_pre_post_processors``: JEPT's pipeline (prompt video from the bank, action bins)."""

from lerobot_jept.configuration_vid2robot import Vid2RobotConfig
from lerobot_jept.processor_jept import make_jept_pre_post_processors


def make_jept_vid2robot_pre_post_processors(config: Vid2RobotConfig, dataset_stats=None, **kwargs):
    return make_jept_pre_post_processors(config, dataset_stats)
