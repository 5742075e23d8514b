"""The dataset layout's feature keys, in one place.

What `murm collect` writes, what the VQ-VAE and the latent datasets read, what the policy's
inputs are called and what the simulator's observation holds all come from here, so that a
renamed key cannot leave one reader behind. Plain strings: no torch, LeRobot or PyBullet.
"""

GOAL_SUFFIX = "_goal"  # a camera's goal image: `<camera>_goal`
IMAGES_PREFIX = "observation.images."
LATENTS_PREFIX = "observation.latent."
STATE = "observation.state"  # end-effector xyz, finger opening
ENVIRONMENT_STATE = "observation.environment_state"  # object and goal xyz: privileged, for the scripted expert
ACTION = "action"
REWARD = "next.reward"


def goal_key(camera: str) -> str:
    """The goal image's name beside the camera's own (the simulator's `pixels` dict)."""
    return f"{camera}{GOAL_SUFFIX}"


def is_goal(name: str) -> bool:
    return name.endswith(GOAL_SUFFIX)


def image_key(camera: str) -> str:
    return f"{IMAGES_PREFIX}{camera}"


def goal_image_key(camera: str) -> str:
    return f"{IMAGES_PREFIX}{goal_key(camera)}"


def latent_key(camera: str) -> str:
    """The camera's codebook indices in a latent dataset (`murm encode --to-dataset`)."""
    return f"{LATENTS_PREFIX}{camera}"


def latent_goal_key(camera: str) -> str:
    return f"{LATENTS_PREFIX}{goal_key(camera)}"


def _cameras(keys, prefix: str) -> list[str]:
    return [k[len(prefix) :] for k in keys if k.startswith(prefix) and not is_goal(k)]


def image_cameras(keys) -> list[str]:
    """The cameras whose frames (not goal images) are among the feature `keys`, in order."""
    return _cameras(keys, IMAGES_PREFIX)


def latent_cameras(keys) -> list[str]:
    """The cameras a dataset holds codes of, in order (none for a dataset of images)."""
    return _cameras(keys, LATENTS_PREFIX)
