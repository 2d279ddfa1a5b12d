"""QueST skill-token policy for LeRobot, with the hooks CSO needs (sampling log-probs, teacher forcing, freezing)."""

from __future__ import annotations

import json
import logging
import time
from collections import deque
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION
from torch import Tensor, nn
from torch.nn import functional as F  # noqa: N812

from lerobot_cso.policy.background_decode import DecodeProcess, PendingDecode
from lerobot_cso.policy.configuration_cso import (
    SKILL_COLUMNS,
    SKILL_START_KEY,
    SKILL_TOKENS_KEY,
    CSOConfig,
)
from lerobot_cso.policy.fast_prior import FastSkillSampler
from lerobot_cso.policy.observation_encoder import ContextEncoder, fit_geometry
from lerobot_cso.policy.skill_autoencoder import SkillAutoencoder
from lerobot_cso.policy.skill_prior import SkillPrior, filtered_log_probs, token_logprob
from lerobot_cso.sampling import FULL, Sampling

_NO_DECAY = (nn.LayerNorm, nn.GroupNorm, nn.BatchNorm2d, nn.Embedding)
# What a config.json written before a setting existed meant by leaving it out (its default then).
LEGACY_DEFAULTS = {"image_backbone": "resnet18", "image_resize": None}


def skill_nll(logits: Tensor, tokens: Tensor, mask: Tensor | None = None, reduction: str = "mean") -> Tensor:
    """Eq. 6 (and the IL objective, Eq. 2): −log π(Z_t | s_t), the token cross-entropy of each skill.

    ``logits`` (B, n, V), ``tokens`` (B, n), ``mask`` (B,) selects the samples that carry a skill. With
    ``reduction="none"`` returns the per-sample mean token NLL (B,), zero where masked.
    """
    per_sample = F.cross_entropy(logits.transpose(1, 2), tokens, reduction="none").mean(dim=1)
    if mask is None:
        mask = torch.ones_like(per_sample, dtype=torch.bool)
    per_sample = per_sample * mask
    if reduction == "none":
        return per_sample
    return per_sample.sum() / mask.sum().clamp(min=1)


def masked_l1(prediction: Tensor, target: Tensor, is_pad: Tensor | None, reduction: str = "mean") -> Tensor:
    """L1 reconstruction loss over the real (non-padded) steps of action chunks (B, T, A)."""
    valid = torch.ones(prediction.shape[:2], device=prediction.device) if is_pad is None else (~is_pad).float()
    per_sample = ((prediction - target).abs().mean(-1) * valid).sum(1) / valid.sum(1).clamp(min=1)
    return per_sample if reduction == "none" else per_sample.mean()


class CSOPolicy(PreTrainedPolicy):
    """QueST policy: skill autoencoder (actions ⇄ tokens) + context encoders + autoregressive skill prior."""

    config_class = CSOConfig
    name = "cso"

    def __init__(self, config: CSOConfig, dataset_stats: Any = None, dataset_meta: Any = None, **kwargs: Any):
        for key in SKILL_COLUMNS:  # bookkeeping columns of the R-SFT buffer are no inputs
            config.input_features.pop(key, None)
        if not config.tasks and dataset_meta is not None and dataset_meta.tasks is not None:
            config.tasks = list(dataset_meta.tasks.sort_values("task_index").index)
        super().__init__(config)
        config.validate_features()
        self.config = config
        action_dim = config.action_feature.shape[-1]
        self.autoencoder = SkillAutoencoder(
            action_dim=action_dim,
            chunk_size=config.chunk_size,
            dim=config.ae_dim,
            conv_kernels=config.ae_conv_kernels,
            conv_strides=config.ae_conv_strides,
            encoder_layers=config.ae_encoder_layers,
            decoder_layers=config.ae_decoder_layers,
            heads=config.ae_heads,
            dropout=config.ae_dropout,
            fsq_levels=config.fsq_levels,
        )
        self.encoders = ContextEncoder(
            config.input_features,
            n_tasks=len(config.tasks),
            dim=config.prior_dim,
            image_keypoints=config.image_keypoints,
            image_embed_dim=config.image_embed_dim,
            state_embed_dim=config.state_embed_dim,
            image_backbone=config.image_backbone,
            image_shift=config.image_shift,
            image_resize=config.image_resize,
            image_fit=config.image_fit,
        )
        self.prior = SkillPrior(
            vocab_size=config.vocab_size,
            n_tokens=config.n_tokens,
            dim=config.prior_dim,
            layers=config.prior_layers,
            heads=config.prior_heads,
            dropout=config.prior_dropout,
        )
        # Training phase lives in a persistent buffer so that `--resume` continues where it stopped.
        self.register_buffer("autoencoder_steps_done", torch.zeros((), dtype=torch.long))
        self._task_ids = {task: i for i, task in enumerate(config.tasks)}
        self.set_encoders_frozen(config.freeze_encoders)
        self._decode_process: DecodeProcess | None = None  # with async_decode_lead > 0: see select_action
        self._cost_reported = False  # see _report_cpu_cost
        self.reset()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, *, config: CSOConfig | None = None, **kwargs):
        """Load a checkpoint; a dataset/env whose feature shapes differ from the checkpoint is a clear error, and a
        config.json older than a setting gets that setting's default of its day (:data:`LEGACY_DEFAULTS`)."""
        path = Path(pretrained_name_or_path)
        if path.is_dir():
            written = json.loads((path / "config.json").read_text())
            saved = CSOConfig.from_pretrained(path)
            config = config or saved
            for key, value in LEGACY_DEFAULTS.items():
                if key not in written:
                    setattr(config, key, value)
            for key, ft in {**saved.input_features, **saved.output_features}.items():
                new = {**config.input_features, **config.output_features}.get(key)
                if key not in SKILL_COLUMNS and new is not None and tuple(new.shape) != tuple(ft.shape):
                    raise ValueError(
                        f"feature {key!r} has shape {tuple(new.shape)} but the checkpoint was trained with "
                        f"{tuple(ft.shape)}"
                    )
        return super().from_pretrained(pretrained_name_or_path, config=config, **kwargs)

    # ----------------------------------------------------------------------------------------------- groups
    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """Named parameter groups: 'autoencoder', 'encoders' (observation + task) and 'prior'."""
        return {
            "autoencoder": list(self.autoencoder.parameters()),
            "encoders": list(self.encoders.parameters()),
            "prior": list(self.prior.parameters()),
        }

    def set_encoders_frozen(self, frozen: bool) -> None:
        """Freeze (or unfreeze) the observation and task encoders; recorded in the config so it survives save."""
        self.config.freeze_encoders = frozen
        for p in self.encoders.parameters():
            p.requires_grad_(not frozen)
        self.train(self.training)

    def get_optim_params(self) -> list[dict[str, Any]]:
        """AdamW groups: weight decay on linear/conv weights only; frozen parameters left out."""
        decay, no_decay = [], []
        for module in self.modules():
            for name, p in module.named_parameters(recurse=False):
                if not p.requires_grad:
                    continue
                (no_decay if name == "bias" or isinstance(module, _NO_DECAY) else decay).append(p)
        return [{"params": decay}, {"params": no_decay, "weight_decay": 0.0}]

    # ---------------------------------------------------------------------------------------- CSO hooks
    def task_ids(self, tasks: list[str] | str, batch_size: int, device: torch.device) -> Tensor:
        """Map task strings to embedding ids; an unknown task string is an error, never a silent id 0."""
        if isinstance(tasks, str):
            tasks = [tasks] * batch_size
        unknown = sorted({t for t in tasks if t not in self._task_ids})
        if unknown:
            raise ValueError(
                f"unknown task {unknown[0]!r}; this policy knows {len(self._task_ids)} task(s): "
                f"{sorted(self._task_ids)}"
            )
        return torch.tensor([self._task_ids[t] for t in tasks], dtype=torch.long, device=device)

    def encode_context(self, batch: dict[str, Any]) -> Tensor:
        """Preprocessed batch (normalised observations + 'task' strings) → context tokens (B, 2, prior_dim)."""
        key = next(iter(self.encoders.image_keys + self.encoders.lowdim_keys))
        if "task" not in batch:
            raise ValueError("the batch has no 'task'; the cso policy is conditioned on the task string")
        ids = self.task_ids(batch["task"], batch[key].shape[0], batch[key].device)
        return self.encoders(batch, ids)

    def sample_skills(
        self,
        context: Tensor,
        sampling: Sampling = FULL,
        generator: torch.Generator | None = None,
        use_cache: bool = True,
    ) -> tuple[Tensor, Tensor]:
        """Sample one skill per row: token ids (B, n) and per-token log-probs of the filtered distribution."""
        return self.prior.sample(context, sampling, generator, use_cache)

    def token_log_distributions(self, context: Tensor, tokens: Tensor, sampling: Sampling = FULL) -> Tensor:
        """Each token's log-distribution (B, n, V) by teacher forcing on given tokens (B, n) under ``sampling``'s
        distribution, with gradients."""
        return filtered_log_probs(self.prior.logits(context, tokens), sampling.temperature, sampling.top_k)

    def token_logprobs(self, context: Tensor, tokens: Tensor, sampling: Sampling = FULL) -> Tensor:
        """Per-token log-probs (B, n) of given tokens by teacher forcing under ``sampling``'s distribution, with
        gradients."""
        return token_logprob(self.token_log_distributions(context, tokens, sampling), tokens)

    def decode_skills(self, tokens: Tensor, n_actions: int | None = None) -> Tensor:
        """Token ids (B, n) → the first ``n_actions`` (default: all) normalised actions (B, n_actions, A)."""
        return self.autoencoder.decode_tokens(tokens, n_actions)

    # ------------------------------------------------------------------------------------ LeRobot API
    def reset(self) -> None:
        pending: PendingDecode | None = getattr(self, "_next_chunk", None)
        self._next_chunk: PendingDecode | None = None
        if pending is not None:  # a decode started for the previous episode: waited for (an error raised), dropped
            pending.result()
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)
        self._sampler: FastSkillSampler | None = None  # rebuilt from the current weights on next use
        if self.config.async_decode_lead and not self.training:
            # LeRobot's rollout resets the policy in its set-up: the process's seconds of start are spent there,
            # not by the first tick of the control loop (inside its --duration, the arm holding still).
            self._start_decode_process()

    def train(self, mode: bool = True) -> CSOPolicy:
        super().train(mode)
        if self.config.freeze_encoders:  # frozen encoders keep their BatchNorm statistics too
            self.encoders.eval()
        self._sampler = None  # weights may change while training: an int8 copy would go stale
        if getattr(self, "_decode_process", None) is not None:  # and so would the decode process's copy
            self.reset()
            self._decode_process.close()
            self._decode_process = None
        return self

    def _sample_for_inference(self, batch: dict[str, Any]) -> Tensor:
        """Tokens for a preprocessed batch with the config's sampling and ``inference_weights``."""
        cfg = self.config
        if self._sampler is None:
            self._sampler = FastSkillSampler(self.prior, cfg.inference_weights)
        tokens, _ = self._sampler.sample(self.encode_context(batch), cfg.sampling)
        return tokens

    def _executed_chunk(self, batch: dict[str, Any]) -> Tensor:
        """Sample a skill and decode only its executed prefix (B, n_action_steps, A)."""
        return self.decode_skills(self._sample_for_inference(batch), self.config.n_action_steps)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        return self.decode_skills(self._sample_for_inference(batch))

    @torch.no_grad()
    def select_action(self, batch: dict[str, Any], **kwargs: Any) -> Tensor:
        """Decode a skill, execute its first ``n_action_steps`` actions, then replan.

        With ``async_decode_lead = L > 0`` the next skill is decoded in a process of its own (a copy of this
        policy, started by ``reset`` in eval mode or else by the first call: seconds either way) from the
        observation of the tick on which L actions remain queued, so the control loop keeps ticking while it runs;
        the queue is refilled from it when it runs dry (waiting only if the decode is not done yet).
        """
        lead = self.config.async_decode_lead
        if lead:  # started by reset in eval mode, else now, before the first action (never mid-motion)
            self._start_decode_process()
        if not self._action_queue:
            pending, self._next_chunk = self._next_chunk, None
            chunk = self._executed_chunk(batch) if pending is None else pending.result()
            self._action_queue.extend(chunk.transpose(0, 1))
        action = self._action_queue.popleft()
        if lead and len(self._action_queue) == lead and self._next_chunk is None:
            self._next_chunk = self._decode_process.decode(batch)
        return action

    def _start_decode_process(self) -> None:
        """Start the background decode's process (seconds) unless it is running."""
        if self._decode_process is None:
            self._decode_process = DecodeProcess(self)

    def _report_cpu_cost(self, batch: dict[str, Any]) -> None:
        """On a CPU, at the first training batch: time the camera encoders' forward and backward on it (after a
        two-image warm-up; no gradient kept, batch statistics and random state restored) and log what it costs
        and how to make it cheaper."""
        images = self.encoders.images
        trained = [p for p in images.parameters() if p.requires_grad]
        if not self.encoders.image_keys or not trained or batch[self.encoders.image_keys[0]].device.type != "cpu":
            return
        buffers = {name: b.clone() for name, b in images.named_buffers()}
        with torch.random.fork_rng(devices=[]):  # the CPU's random state (the batch is on the CPU)
            for rows in (slice(0, 2), slice(None)):
                start = time.perf_counter()
                encoded = self.encoders.encode_images({key: batch[key][rows] for key in self.encoders.image_keys})
                torch.autograd.grad(sum(e.sum() for e in encoded), trained)
                seconds = time.perf_counter() - start
        with torch.no_grad():
            for name, b in images.named_buffers():
                b.copy_(buffers[name])
        cfg, frames, largest = self.config, [], 0
        for key in self.encoders.image_keys:
            shape = tuple(batch[key].shape[-2:])
            read = shape if cfg.image_resize is None else fit_geometry(*shape, cfg.image_resize, cfg.image_fit)[1]
            frames.append(f"{key} {shape[0]}×{shape[1]}" + ("" if read == shape else f" → {read[0]}×{read[1]}"))
            largest = max(largest, *read)
        cheaper = [] if cfg.image_backbone == "conv" else ["--policy.image_backbone=conv"]
        cheaper += ["--policy.image_resize=64"] if largest > 64 else []
        logging.info(
            f"cso policy on a CPU: the camera encoders ({cfg.image_backbone}; {', '.join(frames)}) took "
            f"{seconds:.2f} s forward and backward on this batch of {len(batch[self.encoders.image_keys[0]])}, a "
            "cost every skill-prior step pays (autoencoder steps read no image); cheaper: "
            + ", ".join([*cheaper, "a GPU"])
        )

    @property
    def in_autoencoder_phase(self) -> bool:
        return int(self.autoencoder_steps_done) < self.config.n_autoencoder_steps

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """Phase 1: autoencoder L1 reconstruction; phase 2: prior NLL on frozen-autoencoder (or stored) tokens."""
        if self.training and not self._cost_reported:
            self._cost_reported = True
            self._report_cpu_cost(batch)
        if SKILL_TOKENS_KEY not in batch and self.in_autoencoder_phase:
            reconstruction, tokens = self.autoencoder(batch[ACTION])
            loss = masked_l1(reconstruction, batch[ACTION], batch.get("action_is_pad"), reduction)
            if self.training:
                self.autoencoder_steps_done += 1
            info = {"phase": 0, "recon_l1": float(loss.detach().mean()), "n_codes": int(tokens.unique().numel())}
            return loss, info

        context = self.encode_context(batch)
        if SKILL_TOKENS_KEY in batch:  # R-SFT buffer: tokens sampled online; only decision frames carry one
            tokens = batch[SKILL_TOKENS_KEY].long()
            mask = batch[SKILL_START_KEY].reshape(-1).bool()
        else:
            was_training = self.autoencoder.training
            self.autoencoder.eval()
            with torch.no_grad():
                _, tokens = self.autoencoder.encode(batch[ACTION])
            self.autoencoder.train(was_training)
            mask = None
        logits = self.prior.logits(context, tokens)
        loss = skill_nll(logits, tokens, mask, reduction)
        valid = torch.ones(len(tokens), dtype=torch.bool, device=tokens.device) if mask is None else mask
        accuracy = (logits.argmax(-1) == tokens)[valid].float().mean() if valid.any() else torch.zeros(())
        info = {"phase": 1, "nll": float(loss.detach().mean()), "token_acc": float(accuracy)}
        if self.config.decoder_loss_scale > 0 and ACTION in batch:
            with torch.no_grad():  # QueST's decoder fine-tuning: decode tokens sampled from the prior
                sampled = torch.multinomial(logits.detach().softmax(-1).flatten(0, 1), 1).view_as(tokens)
            l1 = masked_l1(self.decode_skills(sampled), batch[ACTION], batch.get("action_is_pad"), reduction)
            loss = loss + self.config.decoder_loss_scale * l1
            info["decoder_l1"] = float(l1.detach().mean())
        return loss, info
