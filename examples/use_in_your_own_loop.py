"""Use a JEPT checkpoint in your own control loop: one Meta-World episode, success printed.

    python examples/use_in_your_own_loop.py --policy_path=PATH_OR_REPO_ID --task=handle-press-v3 \\
        --prompt_repo_id=ORG/NAME_prompts [--image_size=96] [--seed=0]
"""

import argparse

from lerobot.envs.utils import preprocess_observation
from lerobot.policies.factory import make_pre_post_processors

import lerobot_policy_jept  # noqa: F401  LeRobot's factories do not discover plugins: this registers "jept"
from lerobot_jept import JEPTPolicy
from lerobot_jept.envs.metaworld import JeptMetaworldEnv


def run_episode(
    policy_path: str, task: str, prompt_repo_id: str | None, image_size: int | None, seed: int
) -> bool:
    policy = JEPTPolicy.from_pretrained(policy_path)
    overrides = {"device_processor": {"device": str(policy.config.device)}}
    if prompt_repo_id:
        overrides["jept_prompt_video"] = {"repo_id": prompt_repo_id}
    pre, post = make_pre_post_processors(
        policy.config, pretrained_path=policy_path, preprocessor_overrides=overrides
    )
    env = JeptMetaworldEnv(task, image_size=image_size or policy.config.image_size)
    observation, info = env.reset(seed=seed)
    policy.reset()
    done = False
    while not done:
        batch = preprocess_observation(observation) | {"task": env.task_description}
        action = post(policy.select_action(pre(batch)))
        observation, _, terminated, truncated, info = env.step(action[0].numpy())
        done = terminated or truncated
    env.close()
    return bool(info["is_success"])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--policy_path", required=True, help="checkpoint folder or Hub repo id")
    parser.add_argument("--task", required=True, help="Meta-World v3 task, e.g. handle-press-v3")
    parser.add_argument(
        "--prompt_repo_id", help="prompt bank; default: the one the checkpoint was trained with"
    )
    parser.add_argument("--image_size", type=int, help="the dataset's image size; default: the model's")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    success = run_episode(args.policy_path, args.task, args.prompt_repo_id, args.image_size, args.seed)
    print(f"{args.task}: {'success' if success else 'failure'}")


if __name__ == "__main__":
    main()
