"""Configuration of the QueST skill-token policy that CSO post-trains (`--policy.type=cso`)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from functools import partial

from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import LRSchedulerConfig
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR

from lerobot_cso.errors import check_number
from lerobot_cso.policy.fast_prior import WEIGHT_FORMATS
from lerobot_cso.policy.observation_encoder import IMAGE_BACKBONES, IMAGE_FITS, auto_backbone
from lerobot_cso.sampling import Sampling

SKILL_TOKENS_KEY = "observation.skill_tokens"
SKILL_START_KEY = "observation.skill_start"
SKILL_STEP_KEY = "observation.skill_step"
# Integer bookkeeping columns of the R-SFT buffer: they reach `forward` because their names start with
# `observation.`, but they are no policy inputs (no normalisation, no encoder).
SKILL_COLUMNS = (SKILL_TOKENS_KEY, SKILL_START_KEY, SKILL_STEP_KEY)
# The largest image_resize accepted: a 4K frame's longer side (100 000 once tried to allocate 120 GB, when the
# resize still enlarged frames).
MAX_IMAGE_RESIZE = 4096


@LRSchedulerConfig.register_subclass("cso_two_phase")
@dataclass
class TwoPhaseCosineSchedulerConfig(LRSchedulerConfig):
    """Cosine decay restarted at the autoencoder → prior boundary (QueST trains each stage with its own cosine).

    The learning rate goes from the peak down to ``min_lr_ratio`` × peak over the first
    ``num_autoencoder_steps`` steps, then restarts and decays again over the remaining steps.
    """

    num_autoencoder_steps: int = 0
    min_lr_ratio: float = 0.1
    num_warmup_steps: int = 0
    # Whether the run starts from an untrained policy (``--policy.type=cso``, no ``--policy.path``): then a run
    # that ends within the autoencoder phase never trains the prior, which ``build`` warns about.
    from_scratch: bool = False

    def build(self, optimizer: Optimizer, num_training_steps: int) -> LambdaLR:
        if self.from_scratch and num_training_steps <= self.num_autoencoder_steps:
            logging.warning(
                f"--steps={num_training_steps} <= --policy.n_autoencoder_steps={self.num_autoencoder_steps}: this "
                "run trains only the skill autoencoder, never the skill prior; raise --steps above "
                f"{self.num_autoencoder_steps} (or lower --policy.n_autoencoder_steps), unless a later run trains "
                "the prior from its checkpoint with --policy.path"
            )
        boundary = min(self.num_autoencoder_steps, num_training_steps)

        def lr_lambda(step: int) -> float:
            start, end = (0, boundary) if step < boundary else (boundary, num_training_steps)
            local, span = step - start, max(1, end - start)
            if local < self.num_warmup_steps:
                return (local + 1) / (self.num_warmup_steps + 1)
            progress = min(1.0, local / span)
            return self.min_lr_ratio + (1 - self.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

        return LambdaLR(optimizer, lr_lambda)


@PreTrainedConfig.register_subclass("cso")
@dataclass
class CSOConfig(PreTrainedConfig):
    """QueST: an FSQ skill autoencoder plus an autoregressive GPT skill prior (numbers from QueST / CSO App. E).

    One ``lerobot-train`` run trains the autoencoder for ``n_autoencoder_steps`` and then the prior with the
    autoencoder frozen; the phase lives in a model buffer so ``--resume`` continues in the right phase.
    """

    n_obs_steps: int = 1
    # A skill is ``chunk_size`` actions, encoded into ``chunk_size / prod(ae_conv_strides)`` tokens.
    chunk_size: int = 32
    n_action_steps: int = 8

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )

    # Skill autoencoder.
    ae_dim: int = 256
    ae_conv_kernels: list[int] = field(default_factory=lambda: [5, 3, 3])
    ae_conv_strides: list[int] = field(default_factory=lambda: [2, 2, 1])
    ae_encoder_layers: int = 2
    ae_decoder_layers: int = 4
    ae_heads: int = 4
    ae_dropout: float = 0.1
    fsq_levels: list[int] = field(default_factory=lambda: [8, 5, 5, 5])

    # Observation encoders. image_backbone: "resnet18" (QueST's stem + layer1 + layer2, the paper size), "conv" (a
    # four-layer conv net that trains on two CPU cores, docs/cso-on-cpu.md) or "auto" (the default: resnet18 on a GPU,
    # conv on a CPU, where a training step at batch 32 on 128² frames took 1.13 s of one core with the stem against 0.65
    # with conv, docs/own-data.md; resolved when the config is made, so config.json names the backbone its weights are
    # for).
    image_backbone: str = "auto"
    # Random-shift augmentation in pixels while training (QueST's; 0 = off).
    image_shift: int = 0
    # Camera frames larger than image_resize² are fitted to it (image_fit) before the encoder, their aspect kept, in
    # training and inference alike; frames that fit are left as they are (never enlarged). Default 128, QueST's size:
    # a 480² LeRobot MetaWorld frame becomes 128². null: off, the frames enter the encoder at the dataset's size.
    image_resize: int | None = 128
    # How a frame larger than image_resize² is fitted: "crop" scales it (antialiased) until its shorter side is
    # image_resize and keeps the centre square (a 640×480 frame: its middle 480 columns, at 128²); "pad" scales it
    # until its longer side is image_resize and centres it on a border of the dataset's mean colour (640×480: 128×96 of
    # picture in 128²). Measured for the default, crop: in the PiPER twin's 640×480 front camera every object placement
    # of its scenes lies in the middle 480 columns, so a crop loses none and gives each object 4/3 the pixels per side
    # a pad would (docs/own-data.md); use "pad" where a camera shows the task near its left or right edge.
    image_fit: str = "crop"
    image_keypoints: int = 128
    image_embed_dim: int = 256
    state_embed_dim: int = 128

    # Skill prior.
    prior_dim: int = 384
    prior_layers: int = 6
    prior_heads: int = 6
    prior_dropout: float = 0.1

    # Task vocabulary: the dataset's task strings in id order; filled from the dataset on first training and
    # saved in config.json, so eval and deployment map text to the same id.
    tasks: list[str] = field(default_factory=list)

    # Sampling used by `select_action` (QueST: top-k 5, temperature 1).
    temperature: float = 1.0
    top_k: int | None = 5
    greedy: bool = False
    # Inference only (`select_action` / `predict_action_chunk`; the CSO hooks and training always use fp32):
    # the prior's weights during decoding ("float32": the same numbers as training; "int8": weight-only int8,
    # faster at batch 1 but not equivalent, see docs/benchmarks.md), and how many queued actions may remain
    # when the next skill's decode starts in a background process from that tick's observation (0: decode
    # synchronously when the queue is empty, the policy's standard behaviour; the decode must finish within
    # `async_decode_lead` control periods, or the tick that needs it waits).
    inference_weights: str = "float32"
    async_decode_lead: int = 0

    # Training.
    n_autoencoder_steps: int = 1000
    decoder_loss_scale: float = 0.0
    freeze_encoders: bool = False
    optimizer_lr: float = 1e-4
    optimizer_min_lr: float = 1e-5
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    optimizer_weight_decay: float = 1e-4
    optimizer_grad_clip_norm: float = 100.0
    scheduler_warmup_steps: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.chunk_size % self.downsample_factor:
            raise ValueError(
                f"chunk_size={self.chunk_size} must be divisible by prod(ae_conv_strides)={self.downsample_factor}"
            )
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(f"n_action_steps must be in [1, chunk_size={self.chunk_size}]")
        if len(self.ae_conv_kernels) != len(self.ae_conv_strides):
            raise ValueError("ae_conv_kernels and ae_conv_strides must have the same length")
        check = partial(check_number, error=ValueError)  # every numeric setting finite and in range (NaN too)
        self.sampling.check(error=ValueError)
        check("ae_dropout", self.ae_dropout, ge=0, lt=1)
        check("prior_dropout", self.prior_dropout, ge=0, lt=1)
        check("decoder_loss_scale", self.decoder_loss_scale, ge=0)
        check("n_autoencoder_steps", self.n_autoencoder_steps, ge=0)
        check("optimizer_lr", self.optimizer_lr, gt=0)
        check("optimizer_min_lr", self.optimizer_min_lr, ge=0, le=self.optimizer_lr)
        for beta in self.optimizer_betas:
            check("each of optimizer_betas", beta, ge=0, lt=1)
        check("optimizer_weight_decay", self.optimizer_weight_decay, ge=0)
        check("optimizer_grad_clip_norm", self.optimizer_grad_clip_norm, gt=0)
        check("scheduler_warmup_steps", self.scheduler_warmup_steps, ge=0)
        if self.image_backbone == "auto":
            self.image_backbone = auto_backbone(self.device)
        if self.image_backbone not in IMAGE_BACKBONES:
            raise ValueError(f"image_backbone must be one of {('auto', *IMAGE_BACKBONES)}, got {self.image_backbone!r}")
        if self.image_shift < 0:
            raise ValueError(f"image_shift must be >= 0, got {self.image_shift}")
        if self.image_fit not in IMAGE_FITS:
            raise ValueError(f"image_fit must be one of {IMAGE_FITS}, got {self.image_fit!r}")
        if self.image_resize is not None and self.image_resize < 1:
            raise ValueError(f"image_resize must be >= 1 (or null: no resize), got {self.image_resize}")
        if self.image_resize is not None and self.image_resize > MAX_IMAGE_RESIZE:
            raise ValueError(
                f"image_resize must be <= {MAX_IMAGE_RESIZE} (frames are never enlarged: a larger one changes "
                f"nothing), got {self.image_resize}"
            )
        if self.inference_weights not in WEIGHT_FORMATS:
            raise ValueError(f"inference_weights must be one of {WEIGHT_FORMATS}, got {self.inference_weights!r}")
        if not 0 <= self.async_decode_lead < self.n_action_steps:
            raise ValueError(f"async_decode_lead must be in [0, n_action_steps={self.n_action_steps})")

    @property
    def sampling(self) -> Sampling:
        """How ``select_action`` draws skills."""
        return Sampling(self.temperature, self.top_k, self.greedy)

    @property
    def downsample_factor(self) -> int:
        return math.prod(self.ae_conv_strides)

    @property
    def n_tokens(self) -> int:
        """Tokens per skill (8 for a 32-action chunk downsampled by 4)."""
        return self.chunk_size // self.downsample_factor

    @property
    def vocab_size(self) -> int:
        """Number of FSQ codes (1000 for levels [8, 5, 5, 5])."""
        return math.prod(self.fsq_levels)

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> TwoPhaseCosineSchedulerConfig:
        return TwoPhaseCosineSchedulerConfig(
            num_autoencoder_steps=self.n_autoencoder_steps,
            min_lr_ratio=self.optimizer_min_lr / self.optimizer_lr,
            num_warmup_steps=self.scheduler_warmup_steps,
            from_scratch=self.pretrained_path is None,
        )

    def validate_features(self) -> None:
        """Check the features a dataset or env gave us; one clear error per problem."""
        if self.action_feature is None:
            raise ValueError("the dataset has no 'action' feature; the cso policy needs one to learn skills")
        if self.robot_state_feature is None and not self.image_features:
            raise ValueError("the cso policy needs 'observation.state' and/or at least one camera image")
        for key, ft in self.image_features.items():
            if len(ft.shape) != 3 or ft.shape[0] != 3:
                raise ValueError(f"image feature {key!r} must be RGB (3, H, W); got shape {tuple(ft.shape)}")
        for key, ft in self.input_features.items():
            if ft.type not in (FeatureType.STATE, FeatureType.VISUAL, FeatureType.ENV):
                raise ValueError(f"unsupported input feature {key!r} of type {ft.type}")
