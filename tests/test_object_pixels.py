"""The encoders' object check: segmentation masks from the simulator, held-out episodes
simulated again, reconstruction error on the object's pixels (`murm check-encoders`)."""

import json
import os
import shutil
import sys

import numpy as np
import pytest

from lerobot_murm.env.objects import OBJECT_COLOURS
from lerobot_murm.features import goal_key
from lerobot_murm.vqvae import object_pixels
from lerobot_murm.vqvae.object_pixels import MIN_VISIBLE_PIXELS, object_metrics

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "helpers"))
from commands import run

MURM = os.path.join(os.path.dirname(sys.executable), "murm")


def test_the_object_mask_covers_the_object_in_the_frame_and_in_the_goal_image(make_env):
    env = make_env(task="place_in_box", cameras=("global", "active"))
    obs, _ = env.reset(seed=3)
    now, goal = env.object_views(), env.object_views(at_goal=True)
    red = np.array(OBJECT_COLOURS["red"][:3]) * 255
    for camera in ("global", "active"):
        pairs = ((now[camera], obs["pixels"][camera]), (goal[camera], obs["pixels"][goal_key(camera)]))
        for (image, mask), observed in pairs:
            np.testing.assert_array_equal(image, observed)  # the same pixels as the observation
            assert mask.sum() >= MIN_VISIBLE_PIXELS
            inside, outside = image[mask].astype(float), image[~mask].astype(float)
            # blurred as the authors blur, the object's pixels mix with their neighbours': still
            # clearly redder than the rest of the image, not twice as red
            assert np.abs(inside - red).sum(axis=1).mean() < 0.7 * np.abs(outside - red).sum(axis=1).mean()
    assert not np.array_equal(now["global"][1], goal["global"][1])  # the object moves to the goal box
    env.client.resetBasePositionAndOrientation(env.task.object_body, [3.0, 3.0, 0.02], [0, 0, 0, 1])
    assert not env.object_views()["global"][1].any()  # out of view: an empty mask


def test_object_metrics_score_the_object_apart_from_the_background():
    errors = np.full((2, 4, 4), 1e-4)
    masks = np.zeros((2, 4, 4), bool)
    masks[0, :2, :2] = True  # 4 pixels in the first image, none in the second
    errors[masks] = 1e-2
    metrics = object_metrics(errors, masks)
    assert metrics["object"]["psnr_db"] == pytest.approx(20.0)
    assert metrics["background"]["psnr_db"] == pytest.approx(40.0)
    assert metrics["whole_image"]["mse"] == pytest.approx((4 * 1e-2 + 28 * 1e-4) / 32)
    assert metrics["object_visible_fraction"] == 0.5 and metrics["object_pixels_mean"] == 2.0


def check_encoders(dataset, encoders, cwd):
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    args = [MURM, "check-encoders", "--dataset", str(dataset), "--encoders", *map(str, encoders)]
    return run(args, cwd=cwd, env=env, timeout=600)


def test_check_encoders_scores_every_held_out_frame_on_the_objects_pixels(tiny_pipeline, tmp_path):
    root, encoder_dir = tiny_pipeline
    encoders = [tmp_path / camera for camera in ("global", "adjacent")]
    for camera, copy in zip(("global", "adjacent"), encoders, strict=True):
        shutil.copytree(encoder_dir / camera, copy)
    result = check_encoders(root, encoders, tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "| place_in_box | global | 101 |" in result.stdout  # one held-out episode: 100 frames and its goal
    for copy in encoders:
        metrics = json.loads((copy / "object_pixels.json").read_text())
        assert metrics["reproduced_fraction"] == 1.0 and metrics["images"] == 101
        assert metrics["object_pixels_mean"] > 0 and 0 <= metrics["object_visible_fraction"] <= 1
        trained = json.loads((copy / "metrics.json").read_text())["heldout"]
        assert metrics["whole_image"]["mse"] == pytest.approx(trained["mse"], rel=1e-4)  # the same held-out images
        assert metrics["object"]["mse"] > 0 and (copy / "object_reconstructions.png").stat().st_size > 0


def test_check_encoders_refuses_a_dataset_it_cannot_simulate_again(tiny_pipeline, tmp_path):
    root, encoder_dir = tiny_pipeline
    changed = tmp_path / "place_in_box"
    shutil.copytree(root, changed)
    summary = changed / "meta" / "murm_collection.json"
    stored = json.loads(summary.read_text())
    stored["recipe"]["base_seed"] += 1  # as if the episodes came from other code: other scenes
    summary.write_text(json.dumps(stored))
    result = check_encoders(changed, [encoder_dir / "global"], tmp_path)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1].startswith("murm check-encoders: no global frame simulated again")
    summary.unlink()
    with pytest.raises(ValueError, match="has no collection recipe"):
        object_pixels.check_encoders("local/place_in_box", changed, [encoder_dir / "global"])
