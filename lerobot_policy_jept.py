"""Entry point of the plugin: LeRobot imports this module (by the distribution's name) to register it."""

import lerobot_jept

lerobot_jept.register()
