"""The dataset cards: `datasets_cards/murm_demonstrations.md` filled from the collection
summary, `datasets_cards/murm_latents.md` from a latent dataset's description.

It becomes the description section of LeRobot's own dataset card (`push_to_hub`
renders LeRobot's template around it, with the dataset structure).
"""

from __future__ import annotations

from dataclasses import asdict
from importlib.resources import files
from string import Template

from lerobot_murm.collection.dataset import recipe_from_summary
from lerobot_murm.env.cameras import CAMERAS, EndEffectorCamera
from lerobot_murm.env.murm_env import CONTROL_FPS, EPISODE_STEPS, TASK_DESCRIPTIONS
from lerobot_murm.features import goal_image_key, image_key, latent_goal_key, latent_key
from lerobot_murm.vqvae.configuration_vqvae import VQVAEConfig
from lerobot_murm.vqvae.latent_cache import HINDSIGHT

DEMONSTRATIONS_TEMPLATE = "murm_demonstrations.md"
LATENTS_TEMPLATE = "murm_latents.md"

SUCCESS_RULES = {
    "place_in_box": "the cube's centre within 3 cm of the goal box's centre (one of nine boxes)",
    "place_in_random_box": "the cube's centre within 5 cm of the centre of a box placed at random in 3-D",
    "pick_up": "the target object (one of three shapes) lifted 5 cm above where it started",
}


def card_template(name: str) -> Template:
    """The template `datasets_cards/<name>`, read from the installed package (it ships as package data)."""
    return Template((files("lerobot_murm.publishing") / "datasets_cards" / name).read_text(encoding="utf-8"))


def render_card(summary: dict, repo_id: str) -> str:
    recipe = asdict(recipe_from_summary(summary["recipe"]))  # older summaries' two noise knobs read as one
    cameras = recipe["cameras"]
    rows = []
    for camera in cameras:
        mount = "on the hand" if isinstance(CAMERAS[camera], EndEffectorCamera) else "fixed to the world"
        rows.append(f"| `{image_key(camera)}`, `{goal_image_key(camera)}` | {camera} camera, {mount} |")
    rate = summary["success_rate"]
    command = (
        f"murm collect --task {recipe['task']} --episodes {summary['episodes']} --seed {recipe['base_seed']} "
        f"--noise-std {recipe['noise_std']} --noisy-fraction {recipe['noisy_fraction']} "
        f"--cameras {','.join(cameras)}"
    )
    return card_template(DEMONSTRATIONS_TEMPLATE).substitute(
        task=recipe["task"],
        task_text=TASK_DESCRIPTIONS[recipe["task"]].capitalize() + ".",
        success_rule=SUCCESS_RULES[recipe["task"]],
        episodes=summary["episodes"],
        episode_steps=EPISODE_STEPS,
        fps=CONTROL_FPS,
        success_rate="n/a" if rate is None else f"{rate:.1%}",
        n_cameras=len(cameras),
        image_size=recipe["image_size"],
        camera_rows="\n".join(rows),
        noise_std=recipe["noise_std"],
        noisy_percent=f"{recipe['noisy_fraction']:.0%}",
        base_seed=recipe["base_seed"],
        repo_id=repo_id,
        command=command,
    )


def render_latent_card(description: dict, episodes: int, repo_id: str) -> str:
    """The card of a latent dataset, from its `meta/murm_latents.json`."""
    cameras = description["cameras"]
    source = description["source"]["repo_id"]
    grid = VQVAEConfig(**next(iter(cameras.values()))["encoder"]).grid_size
    goal = "its episode's last frame (hindsight goal)" if description.get("goals") == HINDSIGHT else "goal image"
    return card_template(LATENTS_TEMPLATE).substitute(
        source=source,
        episodes=episodes,
        grid=grid,
        camera_rows="\n".join(
            f"| `{latent_key(c)}`, `{latent_goal_key(c)}` | codebook indices of the {c} frame and {goal}, packed |"
            for c in cameras
        ),
        encoder_rows="\n".join(f"| {c} | `{info['encoder_fingerprint']}` |" for c, info in cameras.items()),
        repo_id=repo_id,
        cameras=",".join(cameras),
        command=description["command"],
    )
