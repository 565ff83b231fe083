import lerobot_jept  # noqa: F401
