"""Configuration of the MURM policy (LeRobot policy type `murm`), paper 4.3 and 5.

The frozen VQ-VAE encoders are part of the policy: `encoder_dir` names a folder with
one checkpoint per camera (`<encoder_dir>/<camera>`, as `murm train-vqvae` writes it).
Their architectures and the per-camera reward thresholds are copied into this config
when it is created, so a saved policy describes itself and `lerobot-eval` needs
nothing but the checkpoint.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from lerobot.configs import FeatureType, NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig, OptimizerConfig

from lerobot_murm.device import resolve_device
from lerobot_murm.features import ACTION, goal_image_key, image_key, latent_cameras, latent_goal_key, latent_key
from lerobot_murm.policy.precision import PRECISIONS
from lerobot_murm.vqvae.code_packing import packed_length
from lerobot_murm.vqvae.configuration_vqvae import LATENT_DISTANCE_FILE, VQVAEConfig
from lerobot_murm.vqvae.encoder_files import CONFIG_FILE, WEIGHTS_FILE, check_encoder

METHODS = ("single", "concat", "dropout", "separated_q")
DROPOUT_SCOPES = ("all", "actor")
DROPPED_Q_MODES = ("zeros", "excluded")
EVAL_MASK_MODES = ("paper", "authors")


@OptimizerConfig.register_subclass("fused_adam")
@dataclass
class FusedAdamConfig(AdamConfig):
    """Adam with torch's fused kernel: its element-wise updates took a fifth of an IQL
    step on CPU as separate ops (benchmarks/bench_iql.py)."""

    def build(self, params: list[dict]) -> torch.optim.Optimizer:
        kwargs = asdict(self)
        kwargs.pop("grad_clip_norm")
        return torch.optim.Adam(params, fused=True, **kwargs)


@PreTrainedConfig.register_subclass("murm")
@dataclass
class MurmConfig(PreTrainedConfig):
    """Goal-conditioned IQL on VQ-VAE latents of one or several cameras.

    method: `single` (one camera), `concat` (plain concatenation), `dropout` (whole
    camera pairs zeroed with probability `dropout_p` in training, never all) or
    `separated_q` (one Q per camera, averaged, eq. 11).

    Where the paper is silent, the defaults are the authors' public code (rlkit/PTP
    based): discount 0.995, expectile 0.9, weights clipped at 100, log-std in [-2, -1],
    policy weight decay 1e-4, values clipped to the range a sparse reward can reach.
    Where paper and code disagree, the paper wins and the code's value is a field:
    128 units per camera (code: 256), 15 % future HER (code: more). The inverse
    temperature and latent standardisation are chosen on validation seeds; REPORT.md
    lists every hyperparameter with its source.
    """

    method: str = "separated_q"
    cameras: list[str] = field(default_factory=lambda: ["global", "adjacent"])
    encoder_dir: str | None = None
    # each camera's VQ-VAE config; filled from encoder_dir by load_encoder_settings, stored with the checkpoint
    encoders: dict[str, dict] = field(default_factory=dict)
    epsilon: list[float] | None = None  # eq. 5 per camera; None: the suggestion `murm encode` wrote

    # IQL (paper 4.3 and Table 1)
    discount: float = 0.995
    expectile: float = 0.9
    temperature: float = 1.0  # beta in eq. 8 (inverse temperature); see the class docstring
    max_advantage_weight: float = 100.0
    clip_value: bool = True  # V and TD targets within [-cameras / (1 - discount), 0]
    target_update_rate: float = 0.005  # Polyak tau
    # units per hidden layer (paper 4.3 and Table 1: 128; authors' code: 256)
    hidden_units: int = 128
    # paper 5.1, "FC layers with 128 neurons per viewpoint": V, the policy and the single Q of
    # single/concat/dropout are hidden_units x cameras wide; each separated Q is hidden_units
    # wide (paper 4.3). False: every network hidden_units wide whatever the cameras.
    width_per_camera: bool = True
    q_layers: int = 2
    v_layers: int = 2
    policy_layers: int = 4
    log_std_min: float = -2.0
    log_std_max: float = -1.0
    actor_weight_decay: float = 1e-4
    actor_lr: float = 3e-4
    critic_lr: float = 3e-4
    value_lr: float = 3e-4
    # standardise each latent feature with the dataset's mean and std before the networks (not
    # in the paper; the authors' code feeds raw latents)
    standardize_latents: bool = True
    latent_std_floor: float = 0.05  # standardised inputs: std of a latent feature at least this
    her_ratio: float = 0.15  # future hindsight relabelling
    # each episode's goal is its own last frame even where the dataset has goal images (datasets
    # without goal images, a robot's own recordings, always have these hindsight goals)
    hindsight_goals: bool = False
    dropout_p: float = 0.5  # each camera pair zeroed with this probability in training
    # zero camera pairs in training; None: only for `dropout`. True with `separated_q`
    # combines both MURM methods (the paper leaves open whether its separated-Q runs did)
    view_dropout: bool | None = None
    # which networks see the dropped pairs: "all" (the paper's dropout: V, Q and policy) or
    # "actor" (only the policy; V and Q see every camera, so the advantages that weight the
    # policy come from the full state while the policy learns to act with views missing)
    dropout_scope: str = "all"
    # separated Q with view dropout on every network: "zeros" feeds a dropped camera's Q_k a
    # zero pair, like the other networks; "excluded" leaves the dropped cameras' Q_k out of
    # the mean (eq. 11 over the cameras that remain)
    dropped_q: str = "zeros"
    # matmuls of the training losses in "bf16" (parameters, optimizer state, output layers and
    # losses stay fp32) or "fp32"; "auto": bf16 on CPUs with native bf16 (avx512_bf16/amx_bf16),
    # fp32 elsewhere, GPUs included (measured slower there; policy/precision.py). Not named `dtype`: that
    # field would make lerobot-train wrap forward in accelerate's autocast as well
    precision: str = "auto"

    # evaluation (Table 4): each step, each camera's image is dropped with this probability
    eval_mask_p: float = 0.0
    # "paper": each camera masked with eval_mask_p at every step, never all (paper 5.2);
    # "authors": the authors' public code, on a third of the steps one random camera masked
    # (eval_mask_p unused)
    eval_mask_mode: str = "paper"
    eval_mask_seed: int = 0

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,  # the encoders take images in [0, 1]
            "STATE": NormalizationMode.IDENTITY,  # the policy sees cameras only
            "ENV": NormalizationMode.IDENTITY,
            # to [-1, 1], the policy's action box, by the dataset's range (any robot's joints); the
            # simulator's actions already fill [-1, 1], and `murm train` saves no statistics
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )
    push_to_hub: bool = False

    def __post_init__(self) -> None:
        if not self.device:  # CUDA if present, else CPU: chosen here, as LeRobot would warn on every CPU-only start
            self.device = resolve_device("auto").type
        super().__post_init__()
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {list(METHODS)}")
        if not self.cameras or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras must be a non-empty list of distinct names, got {self.cameras}")
        if self.method == "single" and len(self.cameras) != 1:
            raise ValueError(f"method 'single' takes one camera, got {self.cameras}")
        if self.method != "single" and len(self.cameras) < 2:
            raise ValueError(f"method {self.method!r} needs at least two cameras, got {self.cameras}")
        if not 0.0 <= self.dropout_p < 1.0 or not 0.0 <= self.eval_mask_p < 1.0:
            raise ValueError("dropout_p and eval_mask_p must be in [0, 1)")
        if self.view_dropout is None:
            self.view_dropout = self.method == "dropout"
        if self.view_dropout and self.method in ("single", "concat"):
            raise ValueError(f"view_dropout applies to 'dropout' and 'separated_q', not {self.method!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; choose one of {list(PRECISIONS)}")
        if self.dropout_scope not in DROPOUT_SCOPES:
            raise ValueError(f"unknown dropout_scope {self.dropout_scope!r}; choose one of {list(DROPOUT_SCOPES)}")
        if self.dropped_q not in DROPPED_Q_MODES:
            raise ValueError(f"unknown dropped_q {self.dropped_q!r}; choose one of {list(DROPPED_Q_MODES)}")
        if self.dropped_q == "excluded" and not (
            self.method == "separated_q" and self.view_dropout and self.dropout_scope == "all"
        ):
            raise ValueError("dropped_q 'excluded' needs separated_q with view_dropout and dropout_scope 'all'")
        if self.eval_mask_mode not in EVAL_MASK_MODES:
            raise ValueError(f"unknown eval_mask_mode {self.eval_mask_mode!r}; choose one of {list(EVAL_MASK_MODES)}")
        if self.hidden_units < 1:
            raise ValueError(f"hidden_units must be at least 1, got {self.hidden_units}")
        if self.method == "dropout" and not self.view_dropout:
            raise ValueError("method 'dropout' always drops views; use 'concat' for none")
        self._check_encoder_settings()

    def load_encoder_settings(self) -> None:
        """Fill `encoders` (each camera's VQ-VAE config) and `epsilon` (`murm encode`'s
        suggestion) from `encoder_dir` where the config leaves them empty. The policy and the
        commands call this before any work; the config itself validates without the disk."""
        if not self.encoders:
            self._read_encoders()
        if self.epsilon is None:
            self.epsilon = [self._suggested_epsilon(c) for c in self.cameras]
        self._check_encoder_settings()

    def _check_encoder_settings(self) -> None:
        missing = [c for c in self.cameras if c not in self.encoders]
        if self.encoders and missing:
            raise ValueError(f"no encoder for cameras {missing} (the config has {sorted(self.encoders)})")
        if self.epsilon is not None and len(self.epsilon) != len(self.cameras):
            raise ValueError(f"{len(self.epsilon)} epsilon values for {len(self.cameras)} cameras")

    def _read_encoders(self) -> None:
        if self.encoder_dir is None:
            raise ValueError("set encoder_dir: the folder with one VQ-VAE checkpoint per camera (murm train-vqvae)")
        for camera in self.cameras:
            folder = Path(self.encoder_dir) / camera
            if not (folder / CONFIG_FILE).exists() and not (folder / WEIGHTS_FILE).exists():
                raise FileNotFoundError(f"no VQ-VAE for camera {camera!r}: {folder / CONFIG_FILE} does not exist")
            self.encoders[camera] = check_encoder(folder)  # a torn encoder fails here, before any work

    def _suggested_epsilon(self, camera: str) -> float:
        path = Path(self.encoder_dir or "") / camera / LATENT_DISTANCE_FILE
        if self.encoder_dir is None or not path.exists():
            raise ValueError(
                f"no epsilon for camera {camera!r}: pass epsilon explicitly or run `murm encode` "
                f"with this encoder first (it writes {LATENT_DISTANCE_FILE})"
            )
        return float(json.loads(path.read_text())["suggested_epsilon"])

    def encoder_config(self, camera: str) -> VQVAEConfig:
        if camera not in self.encoders:
            raise ValueError(f"no encoder settings for camera {camera!r} yet: call load_encoder_settings()")
        return VQVAEConfig(**self.encoders[camera])

    @property
    def latent_dim(self) -> int:
        return self.encoder_config(self.cameras[0]).latent_dim

    @property
    def shared_width(self) -> int:
        """Units per layer of V, the policy and the single Q (paper 5.1: 128 per camera)."""
        return self.hidden_units * (len(self.cameras) if self.width_per_camera else 1)

    @property
    def action_dim(self) -> int:
        """The dataset's own action size (the Panda's 4, an SO-101's 6, ...)."""
        if ACTION not in self.output_features:
            raise ValueError(f"the policy's output_features have no {ACTION!r}: set them from the dataset's features")
        return self.output_features[ACTION].shape[0]

    # --- LeRobot's PreTrainedConfig interface -------------------------------------------
    @property
    def drop_n_last_frames(self) -> int:
        """lerobot-train's sampler never picks an episode's last frame: it has no successor."""
        return 1

    @property
    def observation_delta_indices(self) -> None:
        """One row per sample: successors and hindsight goals come from the policy's replay."""
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> FusedAdamConfig:
        # the three networks' learning rates are set per parameter group by the policy
        return FusedAdamConfig(lr=self.critic_lr, grad_clip_norm=0.0)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        """The data has each camera's codes and goal codes (a latent dataset), or its RGB images of
        any size (the policy resizes them as the encoder's frames were), with goal images or
        without (hindsight goals in training, `MurmPolicy.set_goal` in deployment)."""
        if latent_cameras(self.input_features):
            for camera in self.cameras:
                encoder = self.encoder_config(camera)
                length = packed_length(encoder.grid_size**2, encoder.codebook_size)
                for key in (latent_key(camera), latent_goal_key(camera)):
                    if key not in self.input_features:
                        raise ValueError(
                            f"the policy needs {key}; the latent dataset has no codes of camera {camera!r}"
                        )
                    if tuple(self.input_features[key].shape) != (length,):
                        raise ValueError(
                            f"{key} has shape {tuple(self.input_features[key].shape)}; the {camera} "
                            f"encoder's {encoder.grid_size}x{encoder.grid_size} grid of codes packs "
                            f"into ({length},)"
                        )
            return
        visual = {k: ft for k, ft in self.input_features.items() if ft.type is FeatureType.VISUAL}
        for camera in self.cameras:
            for key in (image_key(camera), goal_image_key(camera)):
                if key in visual and visual[key].shape[0] != 3:
                    raise ValueError(f"{key} has shape {tuple(visual[key].shape)}; the encoders take RGB images")
            if image_key(camera) not in visual:
                raise ValueError(f"the policy needs {image_key(camera)}; the data has {sorted(visual)}")
