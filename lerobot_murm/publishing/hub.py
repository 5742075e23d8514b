"""Push a collected dataset to the Hugging Face Hub with its card, and pull one by repo id.

Both go through LeRobot's own code (`LeRobotDataset.push_to_hub`, and the download a
`LeRobotDataset` does when its files are not on disk). Network and authentication
failures become one clear `HubUnavailable` message: the local dataset is unaffected.
"""

from __future__ import annotations

import json
from pathlib import Path

import httpx
from huggingface_hub import constants
from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, OfflineModeIsEnabled
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from lerobot_murm.collection.dataset import SUMMARY_FILE
from lerobot_murm.publishing.card import render_card, render_latent_card
from lerobot_murm.vqvae.latent_dataset import LATENTS_FILE

HUB_ERRORS = (httpx.HTTPError, HfHubHTTPError, LocalEntryNotFoundError, OfflineModeIsEnabled, OSError)


class HubUnavailable(RuntimeError):
    """The Hub could not be reached or refused the request."""


def push_dataset(root: Path, repo_id: str, private: bool = False) -> str:
    """Upload the demonstrations or latent dataset at `root` as `repo_id`, with its MURM card;
    returns the card text."""
    root = Path(root)
    if not (root / SUMMARY_FILE).is_file() and not (root / LATENTS_FILE).is_file():
        raise FileNotFoundError(f"{root} is not a dataset `murm collect` or `murm encode --to-dataset` made")
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    if (root / LATENTS_FILE).exists():
        card = render_latent_card(json.loads((root / LATENTS_FILE).read_text()), dataset.meta.total_episodes, repo_id)
        kind = "latents"
    else:
        summary = json.loads((root / SUMMARY_FILE).read_text())
        card, kind = render_card(summary, repo_id), summary["recipe"]["task"]
    try:
        dataset.push_to_hub(
            private=private,
            tags=["murm", "goal-conditioned", "multi-view", "offline-rl", kind],
            license="apache-2.0",
            dataset_description=card,
        )
    except HUB_ERRORS as error:
        raise HubUnavailable(_explain(error, f"push {root} to {repo_id}")) from error
    return card


def pull_dataset(repo_id: str, root: Path) -> LeRobotDataset:
    """Download `repo_id` into `root` (LeRobot's own download) and return it, ready to read."""
    try:
        return LeRobotDataset(repo_id, root=Path(root), video_backend="pyav")
    except HUB_ERRORS as error:
        raise HubUnavailable(_explain(error, f"pull {repo_id}")) from error


def _explain(error: Exception, action: str) -> str:
    return (
        f"could not {action}: the Hugging Face Hub at {constants.ENDPOINT} is unreachable or refused "
        f"({type(error).__name__}: {error}). Check the network and your token (`hf auth login` or HF_TOKEN); "
        "local datasets are unaffected."
    )
