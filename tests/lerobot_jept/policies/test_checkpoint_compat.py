"""Checkpoints saved by the flat package layout (every module directly under ``lerobot_jept/``) still load and act
identically: the pinned commit's own files save one checkpoint of every policy type with its outputs on a fixed
input, and today's code loads each and gives the same outputs."""

import json
import os
import subprocess
import sys
import tarfile
from io import BytesIO
from pathlib import Path

import torch

ROOT = Path(__file__).parents[3]
FLAT_LAYOUT = "571a56916710c30c47368832c9a29038c80516ed"  # the last commit of the flat layout
TYPES = {
    "jept": "JEPTConfig",
    "jept_dt_star": "DTStarConfig",
    "jept_vid2robot": "Vid2RobotConfig",
    "jept_idm": "IDMConfig",
    "jept_no_prompt": "JEPTNoPromptConfig",
    "jept_lapo": "LAPOConfig",
}

# Shared by both sides (run as source in each): a fixed input and what each type outputs on it; control steps for
# the policies that act, the action logits of a transition for the inverse dynamics model.
OUTPUTS = """
import torch

def outputs(policy, name):
    g = torch.Generator().manual_seed(1)
    images, states = torch.rand(2, 3, 3, 32, 32, generator=g), torch.randn(2, 3, 4, generator=g)
    prompt = {
        "observation.prompt_video": torch.randint(0, 256, (2, 4, 3, 32, 32), generator=g, dtype=torch.uint8),
        "observation.prompt_video_mask": torch.ones(2, 4, dtype=torch.bool),
    }
    with torch.no_grad():
        if name == "jept_idm":
            return policy.action_logits({"observation.image": images[:, :2], "observation.state": states[:, :2]})
        policy.reset()
        steps = [{"observation.image": images[:, j], "observation.state": states[:, j], **prompt} for j in range(3)]
        return torch.stack([policy.select_action(step) for step in steps], 1)
"""

# Runs in the pinned tree: a policy of each type in the small configuration on synthetic features, saved with its
# outputs.
SAVE = (
    OUTPUTS
    + """
import json, sys
from pathlib import Path
import lerobot_jept
import lerobot_policy_jept
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import get_policy_class

out, types = Path(sys.argv[1]), json.loads(sys.argv[2])
assert Path(lerobot_jept.__file__).parent.parent == Path.cwd(), lerobot_jept.__file__  # the pinned tree's code
features = {
    "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
    "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
}
for name, cls in types.items():
    torch.manual_seed(0)
    cfg = getattr(lerobot_jept, cls).small(
        device="cpu", image_size=32, max_prompt_length=4, input_features=features,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    policy = get_policy_class(name)(cfg).eval()
    policy.save_pretrained(out / name)
    torch.save(outputs(policy, name), out / name / "outputs.pt")
"""
)


def test_checkpoints_of_the_flat_layout_load_and_act_identically(tmp_path):
    archive = subprocess.run(
        ["git", "archive", FLAT_LAYOUT], cwd=ROOT, capture_output=True, check=True
    ).stdout
    old = tmp_path / "flat"
    with tarfile.open(fileobj=BytesIO(archive)) as tar:
        tar.extractall(old, filter="data")
    assert (old / "lerobot_jept/modeling_jept.py").is_file()  # the flat layout indeed
    env = {**os.environ, "PYTHONPATH": str(old)}
    saved = tmp_path / "checkpoints"
    subprocess.run(
        [sys.executable, "-c", SAVE, str(saved), json.dumps(TYPES)], cwd=old, env=env, check=True, timeout=900
    )

    from lerobot.policies.factory import get_policy_class

    import lerobot_policy_jept  # noqa: F401  (registers the types, as LeRobot's scripts do)

    assert get_policy_class("jept").__module__ == "lerobot_jept.policies.jept.modeling_jept"  # today's layout
    scope: dict = {}
    exec(OUTPUTS, scope)
    for name in TYPES:
        policy = get_policy_class(name).from_pretrained(saved / name).eval()
        assert policy.config.type == name
        expected = torch.load(saved / name / "outputs.pt")
        assert expected.shape[0] == 2 and expected.shape[-1] in (4, 7), (name, expected.shape)
        assert torch.equal(scope["outputs"](policy, name), expected), name
