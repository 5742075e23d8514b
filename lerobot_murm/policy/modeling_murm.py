"""The MURM policy: frozen per-camera VQ-VAE encoders + goal-conditioned IQL (paper Algorithm 1).

One `forward` serves both trainers, and both draw transitions from the same sampler
(`replay.LatentReplay`). The fast trainer (`murm train`) hands `forward` the transitions
it sampled. Under `lerobot-train` the policy, given the dataset's metadata at
construction, holds the latents of every row in memory (read from a latent dataset's
codes, or encoded once from an image dataset), and `forward` turns the rows LeRobot's
sampler chose (the batch's `index`) into transitions: successor, hindsight goal and
reward come from the sampler `murm train` uses, not from the frames in the batch.
Under `lerobot-train` the actions are the batch's own, as LeRobot's preprocessor normalised
them with the dataset's statistics (any robot's action, mapped to the policy's [-1, 1]).
Either way the loss is IQL's three losses summed: each network's loss reaches only its
own parameters (the others are detached), so one Adam with a parameter group per network
is three Adams, and LeRobot's single optimizer step trains all three.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor, nn

from lerobot_murm.features import ACTION, goal_image_key, image_key
from lerobot_murm.policy import iql
from lerobot_murm.policy.configuration_murm import MurmConfig
from lerobot_murm.policy.iql import DoubleQ, GaussianPolicy, camera_keep_mask, mlp, polyak_update
from lerobot_murm.policy.precision import compute_dtype, matmul_precision, resolve_precision
from lerobot_murm.policy.process_group import keep_process_group_until_exit
from lerobot_murm.policy.replay import (
    TRANSITION_ACTION,
    TRANSITION_DONE,
    TRANSITION_KEEP,
    TRANSITION_NEXT_STATE,
    TRANSITION_REWARD,
    TRANSITION_STATE,
    LatentReplay,
    replay_for_dataset,
)
from lerobot_murm.vqvae.modeling_vqvae import VQVAE
from lerobot_murm.vqvae.resize import fit_images

LOGGED = ("value_loss", "critic_loss", "actor_loss", "q", "v", "reward", "adv_weight")


class MurmPolicy(PreTrainedPolicy):
    config_class = MurmConfig
    name = "murm"

    def __init__(self, config: MurmConfig, dataset_stats: Any = None, dataset_meta: Any = None, **kwargs: Any):
        super().__init__(config)
        # Adam's moments of parameters whose gradient stays zero (dead units, inputs that are
        # always 0) decay into subnormal floats within ~1000 steps, and subnormal arithmetic
        # made CPU training 15x slower by step 2000: flush them to zero (process-wide, harmless).
        torch.set_flush_denormal(True)
        keep_process_group_until_exit()  # a multi-process lerobot-train must not hang at exit
        config.load_encoder_settings()
        if config.input_features:
            config.validate_features()
        self.cameras = list(config.cameras)
        self.encoders = nn.ModuleDict({camera: VQVAE(config.encoder_config(camera)) for camera in self.cameras})
        self.encoders.requires_grad_(False)
        self.register_buffer("epsilon", torch.tensor(config.epsilon, dtype=torch.float32))
        # per-feature statistics of each camera's latents: the networks see standardised inputs
        self.register_buffer("latent_mean", torch.zeros(len(self.cameras), config.latent_dim))
        self.register_buffer("latent_std", torch.ones(len(self.cameras), config.latent_dim))
        pair_dim, action_dim = 2 * config.latent_dim, config.action_dim
        state_dim = pair_dim * len(self.cameras)
        separated = config.method == "separated_q"
        self.critic = DoubleQ(
            groups=len(self.cameras) if separated else 1,
            group_dim=pair_dim if separated else state_dim,
            action_dim=action_dim,
            hidden=config.hidden_units if separated else config.shared_width,
            layers=config.q_layers,
        )
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.value = mlp(state_dim, config.shared_width, config.v_layers, 1)
        self.actor = GaussianPolicy(
            state_dim, action_dim, config.shared_width, config.policy_layers, config.log_std_min, config.log_std_max
        )
        self.mask_generator = torch.Generator().manual_seed(config.eval_mask_seed)
        # each camera's goal latent from `set_goal`, for observations without goal images; not saved
        self.goal: dict[str, Tensor] = {}
        # the training data's latents, for lerobot-train; a plain attribute: never saved or synced
        self.replay: LatentReplay | None = None
        if dataset_meta is not None:  # a fresh policy for lerobot-train: encoders, replay and statistics
            from lerobot_murm.vqvae.frames import open_dataset

            self.load_encoders()
            dataset = open_dataset(dataset_meta.repo_id, dataset_meta.root)
            self.replay = replay_for_dataset(config, dataset, cache_dir=None, device=config.device or "cpu")
            self.fit_latent_statistics(self.replay.latents)

    def fit_latent_statistics(self, latents: list[Tensor]) -> None:
        """Per-feature mean and std of each camera's (N, latent_dim) latents; std floored so that
        a code that almost never changes does not blow up when it does. Without
        `standardize_latents` the statistics stay 0 and 1 and the networks see raw latents."""
        if not self.config.standardize_latents:
            return
        for k, z in enumerate(latents):
            self.latent_mean[k] = z.mean(0)
            self.latent_std[k] = z.std(0).clamp(min=self.config.latent_std_floor)

    def normalize(self, state: Tensor) -> Tensor:
        """Standardise (B, cameras, 2 * latent) states; z and z_goal share their camera's statistics.
        One fused multiply-add over the batch: a subtraction and a division each allocated a
        batch-sized temporary, and their page faults cost more than the arithmetic (BENCHMARKS.md)."""
        scale = self.latent_std.reciprocal().repeat(1, 2)
        return torch.addcmul(-self.latent_mean.repeat(1, 2) * scale, state, scale)

    def load_encoders(self) -> None:
        """Copy the trained VQ-VAE weights from `config.encoder_dir` into the policy."""
        for camera in self.cameras:
            trained = VQVAE.load(f"{self.config.encoder_dir}/{camera}")
            if trained.config.latent_dim != self.encoders[camera].config.latent_dim:
                raise ValueError(
                    f"the {camera} encoder in {self.config.encoder_dir} changed since this config was made"
                )
            self.encoders[camera].load_state_dict(trained.state_dict())

    def train(self, mode: bool = True) -> MurmPolicy:
        super().train(mode)
        self.encoders.eval()  # frozen: never update the codebooks' EMA
        return self

    def get_optim_params(self) -> list[dict]:
        c = self.config
        return [
            {"params": list(self.critic.parameters()), "lr": c.critic_lr},
            {"params": list(self.value.parameters()), "lr": c.value_lr},
            {"params": list(self.actor.parameters()), "lr": c.actor_lr, "weight_decay": c.actor_weight_decay},
        ]

    def reset(self) -> None:
        """Nothing to clear: the policy acts on the current observation and goal only (the goal
        `set_goal` stored stays: a goal photographed once serves every episode after it)."""

    # --- goals -----------------------------------------------------------------------------
    @torch.no_grad()
    def set_goal(self, images: dict[str, Tensor | np.ndarray]) -> None:
        """The goal `select_action` drives towards when an observation carries no goal images (a
        robot's cameras give none): one image per camera, as a camera gives it (H x W x 3 uint8)
        or as LeRobot's processors do (3 x H x W floats in [0, 1]), any size (resized as the
        encoder's frames were). Observations with goal images (the simulator's) use their own."""
        missing = [c for c in self.cameras if c not in images]
        if missing:
            raise ValueError(f"set_goal needs an image of every camera {self.cameras}; missing {missing}")
        device = self.epsilon.device
        self.goal = {c: self.encode(c, as_image(images[c]).to(device)) for c in self.cameras}

    def set_goal_from_dataset(self, dataset: LeRobotDataset, index: int) -> None:
        """Frame `index` of an image dataset as the goal (an episode's last frame: where it ended)."""
        missing = [image_key(c) for c in self.cameras if image_key(c) not in dataset.meta.features]
        if missing:
            raise ValueError(f"the dataset at {dataset.root} has no images {missing} to take a goal from")
        frame = dataset[index]
        self.set_goal({c: frame[image_key(c)] for c in self.cameras})

    def update(self) -> None:
        """Called by the trainers after each optimizer step: Polyak-average the target critic."""
        polyak_update(self.critic_target, self.critic, self.config.target_update_rate)

    # --- observations -> latent states ---------------------------------------------------
    @torch.no_grad()
    def encode(self, camera: str, images: Tensor) -> Tensor:
        """(..., 3, H, W) images in [0, 1] of any size (brought to the encoder's by the rule its
        training frames followed, `resize.fit_images`) -> (..., latent_dim) latents."""
        images = fit_images(images, self.encoders[camera].config.image_size)
        flat = images.reshape(-1, *images.shape[-3:])
        return self.encoders[camera].encode(flat).view(*images.shape[:-3], -1)

    def state_from_observation(self, batch: dict[str, Tensor], mask_p: float = 0.0, mask_mode: str = "paper") -> Tensor:
        """(B, cameras, 2 * latent) standardised state of one observation, cameras masked
        (Table 4) by `mask_mode`: "paper", each camera with probability mask_p; "authors",
        on a third of the steps one random camera (the authors' public code). A camera whose
        image the observation lacks (one that dropped out) is masked too."""
        present = torch.tensor([image_key(c) in batch for c in self.cameras])
        return self.masked_state(self.observation_latents(batch), mask_p, mask_mode, present)

    def observation_latents(self, batch: dict[str, Tensor], goals: Tensor | None = None) -> Tensor:
        """(B, cameras, 2 * latent) raw (z, zg) latents of an observation: the encoders' work,
        which the seeds of a stack (one set of encoders) do once for all their episodes. A
        camera missing from the observation has z = 0 (`masked_state` hides it). `goals`:
        the rows' goal latents from `goal_state`, already encoded, instead of the batch's goals."""
        self._rows(batch)  # an observation without any of the cameras is refused
        if goals is None:
            goals = self.goal_state(batch)
        pairs = []
        for k, c in enumerate(self.cameras):
            goal = goals[..., k, :]
            z = self.encode(c, batch[image_key(c)]) if image_key(c) in batch else torch.zeros_like(goal)
            pairs.append(torch.cat([z, goal], dim=-1))
        return torch.stack(pairs, dim=1)

    def goal_state(self, batch: dict[str, Tensor]) -> Tensor:
        """(B, cameras, latent) goal latents of an observation (`goal_latents` per camera). A goal
        stays for a whole episode, so an evaluation encodes it once, at the episode's reset."""
        rows, device = self._rows(batch)
        return torch.stack([self.goal_latents(c, batch, rows, device) for c in self.cameras], dim=-2)

    def _rows(self, batch: dict[str, Tensor]) -> tuple[torch.Size, torch.device]:
        frames = [batch[image_key(c)] for c in self.cameras if image_key(c) in batch]
        if not frames:
            raise ValueError(f"the observation has no image of any of the policy's cameras {self.cameras}")
        return frames[0].shape[:-3], frames[0].device

    def goal_latents(self, camera: str, batch: dict[str, Tensor], rows: torch.Size, device: torch.device) -> Tensor:
        """(*rows, latent) goal latents of `camera`: the observation's goal images where it has
        them, else the goal `set_goal` stored."""
        if goal_image_key(camera) in batch:
            return self.encode(camera, batch[goal_image_key(camera)])
        if camera not in self.goal:
            raise ValueError(
                f"no goal for camera {camera!r}: the observation has no {goal_image_key(camera)}; "
                "give the policy a goal with set_goal (or set_goal_from_dataset) first"
            )
        return self.goal[camera].to(device).expand(*rows, -1)

    def masked_state(
        self, latents: Tensor, mask_p: float = 0.0, mask_mode: str = "paper", present: Tensor | None = None
    ) -> Tensor:
        """The standardised state of `observation_latents`, cameras masked by `mask_mode` and,
        where `present` (cameras,) is False, for want of an image.

        Several cameras: a masked camera's (z, zg) pair is zeroed as in dropout training, and
        a step that would mask every camera masks none (the paper's rule; of the cameras
        present). One camera: its image goes black, so the policy sees a blank view (the
        latent of a black image).
        """
        visible = self._evaluation_visibility(latents.shape[0], mask_p, mask_mode).to(latents.device)
        if present is not None and len(self.cameras) > 1:  # one camera is always present (observation_latents)
            present = present.to(latents.device)
            visible = torch.where((visible & present).any(-1, keepdim=True), visible & present, present)
        if len(self.cameras) > 1:
            return self.normalize(latents) * visible.unsqueeze(-1)
        camera, dim = self.cameras[0], self.config.latent_dim
        size = self.config.encoder_config(camera).image_size
        blank = self.encode(camera, torch.zeros(1, 3, size, size, device=latents.device))
        z = torch.where(visible, latents[:, 0, :dim], blank)
        return self.normalize(torch.cat([z, latents[:, 0, dim:]], dim=-1).unsqueeze(1))

    def _evaluation_visibility(self, batch_size: int, mask_p: float, mask_mode: str) -> Tensor:
        """(B, cameras) bool, True where a camera's image reaches the policy at this step."""
        cameras = len(self.cameras)
        if mask_mode == "authors":
            masked = torch.rand(batch_size, generator=self.mask_generator) < 1 / 3
            which = torch.randint(cameras, (batch_size,), generator=self.mask_generator)
            return ~(torch.nn.functional.one_hot(which, cameras).bool() & masked.unsqueeze(1))
        if mask_p == 0:
            return torch.ones(batch_size, cameras, dtype=torch.bool)
        if cameras == 1:
            return (torch.rand(batch_size, generator=self.mask_generator) >= mask_p).unsqueeze(1)
        return camera_keep_mask(batch_size, cameras, mask_p, generator=self.mask_generator)

    # --- acting ----------------------------------------------------------------------------
    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        state = self.state_from_observation(batch, self.config.eval_mask_p, self.config.eval_mask_mode)
        return self.actor.act(state.flatten(1), deterministic=True).unsqueeze(1)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        return self.predict_action_chunk(batch)[:, 0]

    # --- learning --------------------------------------------------------------------------
    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """IQL's loss on a batch of transitions (`murm train`) or of LeRobot dataset rows (`lerobot-train`)."""
        if TRANSITION_STATE in batch:
            transition = batch
        else:  # dataset rows (lerobot-train), with their actions as LeRobot's preprocessor normalised them
            transition = self.transitions_of_rows(batch["index"]) | {TRANSITION_ACTION: batch[ACTION]}
        device = transition[TRANSITION_STATE].device
        with matmul_precision(resolve_precision(self.config.precision, device), device):
            loss, logged = self.iql_loss(transition)
        return loss, dict(zip(LOGGED, logged.tolist(), strict=True))  # one device sync, not seven

    def transitions_of_rows(self, rows: Tensor) -> dict[str, Tensor]:
        """The replay's transitions from dataset rows `rows` (LeRobot's sampler never picks an
        episode's last frame: `MurmConfig.drop_n_last_frames`), on the rows' device."""
        if self.replay is None:
            raise RuntimeError(
                "this policy holds no training data: make it with the dataset's metadata (lerobot-train)"
            )
        return {k: v.to(rows.device) for k, v in self.replay.transitions(rows).transition().items()}

    def iql_loss(self, transition: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """IQL's summed loss and the `LOGGED` values as one tensor. Pure: no random draw (the
        sampler drew the dropout mask) and no host synchronisation, so that a CUDA graph can
        capture it. A seed stack's transitions and weights have its seed dimension in front;
        then every loss and logged value has it too (one per seed)."""
        c = self.config
        dtype = compute_dtype(transition[TRANSITION_STATE].device)  # the networks' inputs, cast once for all of them
        views = iql.drop_views(
            self.normalize(transition[TRANSITION_STATE]).to(dtype),
            self.normalize(transition[TRANSITION_NEXT_STATE]).to(dtype),
            transition[TRANSITION_KEEP] if c.view_dropout else None,
            separated_q=c.method == "separated_q",
            scope=c.dropout_scope,
            dropped_q=c.dropped_q,
        )
        action, reward, done = transition[TRANSITION_ACTION], transition[TRANSITION_REWARD], transition[TRANSITION_DONE]
        with torch.no_grad():
            q_target = self.critic_target(views.critic, action, views.q_heads).min(-2).values  # clipped double Q
            target = iql.td_target(self.value, reward, done, views.next_state, c.discount)
            if c.clip_value:  # a sparse reward in [-cameras, 0] bounds every return
                q_target = q_target.clamp(-len(self.cameras) / (1 - c.discount), 0.0)
                target = target.clamp(-len(self.cameras) / (1 - c.discount), 0.0)
        value_loss, v = iql.value_loss(self.value, views.state, q_target, c.expectile)
        critic_loss = iql.critic_loss(self.critic, views.critic, action, views.q_heads, target)
        actor_loss, weights = iql.actor_loss(
            self.actor, views.actor, action, q_target - v, c.temperature, c.max_advantage_weight
        )
        loss = value_loss + critic_loss + actor_loss
        logged = torch.stack(
            [value_loss, critic_loss, actor_loss, q_target.mean(-1), v.mean(-1), reward.mean(-1), weights.mean(-1)],
            dim=-1,
        ).detach()
        return loss, logged


def as_image(image: Tensor | np.ndarray) -> Tensor:
    """A camera's image as (3, H, W) floats in [0, 1], from H x W x 3 uint8 (a camera's frame) or
    3 x H x W (LeRobot's processed frames, or a dataset's)."""
    image = torch.as_tensor(image)
    if image.ndim != 3 or 3 not in (image.shape[0], image.shape[-1]):
        raise ValueError(f"a goal image is H x W x 3 or 3 x H x W, got shape {tuple(image.shape)}")
    if image.shape[0] != 3:
        image = image.permute(2, 0, 1)
    return image.float() / 255 if image.dtype == torch.uint8 else image.float()
