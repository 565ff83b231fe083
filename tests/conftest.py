"""Test-session environment: offline Hub, headless rendering, and a private LeRobot home.

These must be set before LeRobot or MuJoCo are imported, hence at the top of conftest.
"""

import os
import tempfile

os.environ["HF_HUB_OFFLINE"] = "1"
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SVT_LOG", "1")
os.environ["HF_LEROBOT_HOME"] = tempfile.mkdtemp(prefix="jept_lerobot_home_")
