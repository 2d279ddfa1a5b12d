"""Stage 2 of CSO, SPO (Algorithm 1 lines 12–22, Eq. 7–9, App. E.2): ``lerobot-cso spo``.

Each of ``iterations`` (M) iterations: π_old ← π; collect ``groups_per_iteration`` (B) groups of
``group_size`` (K) rollouts, each group from one initial state of the SPO part of the training seed range;
compute group-relative advantages (Eq. 8; leave-one-out for ``ript``); drop groups whose rewards are all equal
and draw new states (dynamic rejection; optionally from a fixed pool of states that skips, for a while, the
states whose group was uniform: ``state_pool``, ``skip_uniform_for``); then ``epochs`` (N) epochs of minibatch
updates of the **skill prior only** with the clipped objective of :mod:`lerobot_cso.cso.objectives` at the
chosen granularity.

The observation encoders stay frozen (Algorithm 1): the encoder context of each decision is cached during the
rollout and the optimizer holds the prior's parameters alone, so the encoders are bit-identical before and after.
With ``encoder_freeze=false`` (the paper's ablation, Table 2) the rollouts keep each decision's encoder inputs
instead, and the updates recompute the contexts from them, so the encoders learn from the SPO loss too.
π_old's log-probs are recomputed right after collection by teacher forcing with the same function as the
updated policy's (dropout off), so the first minibatch has ratio exactly 1. Ratios use the softmax at the
sampling temperature over all codes (``ratio_top_k: null``, as RIPT), not the top-k-truncated one, so a token
that leaves the top-k keeps a finite ratio.

Every iteration is checkpointed atomically (policy, processors, optimizer, seed cursor, skip memory, history); a rerun
continues after the last finished iteration. Logged per iteration: SR of the collected groups, rejection
rate, clip fraction (and its low / high sides), mean ratio, approximate KL, the prior's entropy on the iteration's
decisions, loss, grad norm, number of updates (``target_kl`` can end an iteration's epochs early), episodes, env
steps, wall time — console table, ``log.jsonl``, PNG plots, and wandb when ``--wandb.enable=true``.
"""

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import matplotlib
import numpy as np
import torch
from accelerate import Accelerator
from lerobot.configs import parser
from lerobot.configs.default import WandBConfig
from lerobot.scripts.lerobot_train import update_policy
from lerobot.utils.logging_utils import MetricsTracker

from lerobot_cso import distributed, rollout_stage, seeds
from lerobot_cso.checkpoints import load_policy, save_checkpoint
from lerobot_cso.cso.objectives import (
    PRESETS,
    Advantage,
    Granularity,
    Objective,
    advantages,
    clipped_surrogate_loss,
    reject_uniform_groups,
    surrogate_units,
)
from lerobot_cso.durable import ResumableState, read_json, replace_dir, write_atomic
from lerobot_cso.errors import UsageError, check_number
from lerobot_cso.policy import CSOPolicy
from lerobot_cso.policy.skill_prior import entropy, token_logprob
from lerobot_cso.records import run_alone
from lerobot_cso.rollout.engine import Episode, InitialState, RolloutEngine
from lerobot_cso.rollout_stage import TrainingStageConfig
from lerobot_cso.sampling import Sampling
from lerobot_cso.stage import POLICY_ROLES, CheckpointStage

LOG_COLUMNS = (
    "iteration",
    "success_rate",
    "rejection_rate",
    "clip_fraction",
    "clip_low_fraction",
    "clip_high_fraction",
    "ratio_mean",
    "approx_kl",
    "entropy",
    "loss",
    "grad_norm",
    "updates",
    "episodes",
    "env_steps",
    "seconds",
)
UPDATE_STATS = (
    "loss",
    "grad_norm",
    "clip_fraction",
    "clip_low_fraction",
    "clip_high_fraction",
    "ratio_mean",
    "approx_kl",
)


@dataclass
class SPOConfig(TrainingStageConfig):
    """Settings of ``lerobot-cso spo --policy.path=<R-SFT checkpoint> --tasks=MT10 --output_dir=...``."""

    policy_role: ClassVar[str] = POLICY_ROLES["spo"]
    records_frames: ClassVar[bool] = False  # the update reads the cached encoder contexts only

    output_dir: Path = Path("outputs/spo")
    # The objective's preset: skill (SPO, Eq. 9) | token (GRPO) | trajectory (GSPO) | ript (RIPT-VLA); each names
    # a ratio granularity, an advantage estimator and a clip range, which the next settings override one by one.
    objective: str = "skill"
    # The ratio's granularity: token | skill | trajectory; null: the preset's.
    ratio: str | None = None
    # The advantage estimator: group_mean (Eq. 8) | leave_one_out (RIPT); null: the preset's.
    advantage: str | None = None
    iterations: int = 30  # M
    groups_per_iteration: int = 150  # B
    group_size: int = 8  # K
    epochs: int = 4  # N
    minibatch_trajectories: int = 64
    lr: float = 1e-6
    weight_decay: float = 0.0
    grad_clip_norm: float = 1.0
    # Ratio clip range [clip_low, clip_high]; null → the objective's default (skill: [0.93, 1.15]).
    clip_low: float | None = None
    clip_high: float | None = None
    # Top-k of the distribution the ratios are computed under (null: the full softmax at the sampling
    # temperature, as RIPT).
    ratio_top_k: int | None = None
    # Stop an iteration's epochs early once a minibatch's approximate KL exceeds this (CleanRL); null: never.
    target_kl: float | None = None
    # Give up on an iteration's collection after drawing this many times B groups (all rejected).
    max_draw_factor: int = 4
    # Draw from a fixed pool of this many training states per task, cycling (as RIPT draws from its demos'
    # initial states); null: a fresh training state at every draw (the paper's "a new initial state is sampled").
    state_pool: int | None = None
    # With a pool: a state whose group was uniform (all successes or all failures) is not drawn again until
    # this many further iterations have passed (RIPT's rollout-stats skipping, applied to both outcomes).
    skip_uniform_for: int = 0
    # Average each trajectory's skills (tokens) before the trajectories, so every trajectory weighs the same; false:
    # Eq. 9's sum over a trajectory's skills, where a failure that runs to the time limit outweighs a short success.
    trajectory_mean: bool = False
    # Algorithm 1 keeps the observation encoders frozen during SPO; false updates them with the prior (the ablation).
    encoder_freeze: bool = True
    seed: int = 0
    wandb: WandBConfig = field(default_factory=WandBConfig)

    def validate(self) -> list[str]:
        tasks = super().validate()
        if self.objective not in PRESETS:
            raise UsageError(f"objective must be one of {', '.join(PRESETS)}, got '{self.objective}'")
        if self.ratio not in (None, *Granularity):
            raise UsageError(f"ratio must be one of {', '.join(Granularity)} or null, got '{self.ratio}'")
        if self.advantage not in (None, *Advantage):
            raise UsageError(f"advantage must be one of {', '.join(Advantage)} or null, got '{self.advantage}'")
        for name in ("iterations", "groups_per_iteration", "epochs", "minibatch_trajectories", "max_draw_factor"):
            if getattr(self, name) < 1:
                raise UsageError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.group_size < 2:
            raise UsageError(f"group_size must be >= 2 for group-relative advantages, got {self.group_size}")
        if self.state_pool is not None and self.state_pool < 1:
            raise UsageError(f"state_pool must be >= 1 or null, got {self.state_pool}")
        if self.skip_uniform_for < 0:
            raise UsageError(f"skip_uniform_for must be >= 0, got {self.skip_uniform_for}")
        check_number("lr", self.lr, gt=0)
        check_number("weight_decay", self.weight_decay, ge=0)
        check_number("grad_clip_norm", self.grad_clip_norm, gt=0)
        check_number("target_kl", self.target_kl, gt=0, optional=True)
        check_number("ratio_top_k", self.ratio_top_k, ge=1, optional=True)
        if not self.encoder_freeze and not self.world_settings().simulated:
            raise UsageError("--encoder_freeze=false (the ablation) runs in simulation only, not on a robot")
        low, high = self.loss_objective().clip
        check_number("clip_low", low, gt=0, le=1)
        check_number("clip_high", high, ge=1)
        return tasks

    @property
    def keeps_inputs(self) -> bool:  # type: ignore[override]
        """Without the freeze the updates recompute the contexts, so the rollouts keep the encoders' inputs."""
        return not self.encoder_freeze

    def ratio_sampling(self) -> Sampling:
        """The distribution the ratios are taken under: the sampling temperature, top-k ``ratio_top_k``."""
        return Sampling(self.sampling.temperature, self.ratio_top_k)

    def loss_objective(self) -> Objective:
        """The preset ``objective`` with the axes these settings override."""
        base = PRESETS[self.objective]
        low, high = base.clip
        return Objective(
            Granularity(self.ratio or base.granularity),
            Advantage(self.advantage or base.advantage),
            (low if self.clip_low is None else self.clip_low, high if self.clip_high is None else self.clip_high),
        )


@dataclass
class Batch:
    """Accepted groups as padded tensors: N trajectories × D decisions × n tokens."""

    contexts: torch.Tensor  # (N, D, P, d)
    tokens: torch.Tensor  # (N, D, n)
    mask: torch.Tensor  # (N, D) bool
    advantages: torch.Tensor  # (N,)
    # Encoders not frozen: their inputs {key: (N, D, ...)} and each trajectory's task description, from which the
    # contexts are recomputed with gradients; empty with frozen encoders.
    inputs: dict[str, torch.Tensor] = field(default_factory=dict)
    tasks: list[str] = field(default_factory=list)

    @classmethod
    def from_groups(
        cls, groups: list[list[Episode]], estimator: Advantage, device: torch.device | str = "cpu"
    ) -> "Batch":
        """The groups' episodes padded to the longest, on ``device`` (the policy's: rollouts keep them on the CPU)."""
        episodes = [e for g in groups for e in g]
        rewards = torch.tensor([[float(e.success) for e in g] for g in groups])
        d_max = max(len(e.tokens) for e in episodes)
        first = episodes[0]
        contexts = first.contexts.new_zeros(len(episodes), d_max, *first.contexts.shape[1:])
        tokens = first.tokens.new_zeros(len(episodes), d_max, first.tokens.shape[-1])
        mask = torch.zeros(len(episodes), d_max, dtype=torch.bool)
        inputs = {k: v.new_zeros(len(episodes), d_max, *v.shape[1:]) for k, v in first.inputs.items()}
        for i, e in enumerate(episodes):
            d = len(e.tokens)
            contexts[i, :d], tokens[i, :d], mask[i, :d] = e.contexts, e.tokens, True
            for key, value in e.inputs.items():
                inputs[key][i, :d] = value
        adv = advantages(estimator, rewards).reshape(-1)
        tensors = (t.to(device) for t in (contexts, tokens, mask, adv))
        tasks = [e.task_description for e in episodes] if inputs else []
        return cls(*tensors, {k: v.to(device) for k, v in inputs.items()}, tasks)


def decision_contexts(policy: CSOPolicy, batch: Batch, rows: torch.Tensor) -> torch.Tensor:
    """The contexts (M, P, d) of the valid decisions of trajectories ``rows``: cached, or with encoders that are
    not frozen, recomputed from their inputs (with gradients when enabled)."""
    mask = batch.mask[rows]
    if not batch.inputs:
        return batch.contexts[rows][mask]
    per_row = mask.sum(1).tolist()
    tasks = [task for r, n in zip(rows.tolist(), per_row, strict=True) for task in [batch.tasks[r]] * n]
    return policy.encode_context({k: v[rows][mask] for k, v in batch.inputs.items()} | {"task": tasks})


def decision_log_distributions(policy: CSOPolicy, batch: Batch, rows: torch.Tensor, sampling: Sampling) -> torch.Tensor:
    """Teacher-forced log-distributions (M, n, V) of the valid decisions of trajectories ``rows`` under
    ``sampling``'s distribution (with gradients when enabled)."""
    tokens = batch.tokens[rows][batch.mask[rows]]
    return policy.token_log_distributions(decision_contexts(policy, batch, rows), tokens, sampling)


def padded_token_logprobs(batch: Batch, rows: torch.Tensor, log_distributions: torch.Tensor) -> torch.Tensor:
    """The sampled tokens' log-probs (len(rows), D, n) under ``log_distributions`` (those of the valid decisions of
    ``rows``); zeros where padded."""
    tokens, mask = batch.tokens[rows], batch.mask[rows]
    out = torch.zeros(tokens.shape, dtype=torch.float32, device=tokens.device)
    out[mask] = token_logprob(log_distributions, tokens[mask])
    return out


def padded_logprobs(policy: CSOPolicy, batch: Batch, rows: torch.Tensor, sampling: Sampling) -> torch.Tensor:
    """Teacher-forced per-token log-probs (len(rows), D, n) of the valid decisions under ``sampling``'s
    distribution; zeros where padded."""
    return padded_token_logprobs(batch, rows, decision_log_distributions(policy, batch, rows, sampling))


def old_logprobs(policy: CSOPolicy, batch: Batch, sampling: Sampling) -> tuple[torch.Tensor, float]:
    """π_old's teacher-forced per-token log-probs (N, D, n) of the whole batch under ``sampling``'s distribution,
    zeros where padded, and the prior's mean per-token entropy (nats) on those decisions: how spread it is where it
    acted (logged per iteration, before the updates). One forward pass, without gradients."""
    rows = torch.arange(len(batch.tokens))
    with torch.no_grad():
        log_distributions = decision_log_distributions(policy, batch, rows, sampling)
    return padded_token_logprobs(batch, rows, log_distributions), entropy(log_distributions).mean().item()


def trained_parameters(policy: CSOPolicy) -> list[torch.nn.Parameter]:
    """What SPO updates: the prior, and the observation encoders when they are not frozen."""
    return [p for module in (policy.prior, policy.encoders) for p in module.parameters() if p.requires_grad]


def draw_states(
    cfg: SPOConfig, tasks: list[str], cursor: int, n: int, skip_until: dict[str, int], iteration: int
) -> tuple[list[int], list[InitialState], int]:
    """The next ``n`` draw positions, their initial states and the new cursor.

    Position ``p`` is task ``tasks[p % T]``. Without a pool it names that task's ``p``-th SPO training state
    (every draw is fresh); with ``state_pool`` P, positions cycle over ``P·T`` and name the task's
    ``(p // T)``-th state, skipping those with ``skip_until[p] > iteration``, at most one pass per call (so
    fewer than ``n`` when the pool is exhausted).
    """
    world = cfg.rollout_world()
    if cfg.state_pool is None:
        positions = list(range(cursor, cursor + n))
        cursor += n
    else:
        size = cfg.state_pool * len(tasks)
        positions = []
        for _ in range(size):
            if len(positions) == n:
                break
            position, cursor = cursor % size, cursor + 1
            if skip_until.get(str(position), 0) <= iteration:
                positions.append(position)
    per_task = 1 if cfg.state_pool is None else len(tasks)  # pool positions cycle over the tasks' states
    states = []
    for p in positions:
        task = tasks[p % len(tasks)]
        states.append(InitialState(task, world.training_states(task, "spo", p // per_task, 1)[0]))
    return positions, states, cursor


def collect_groups(
    cfg: SPOConfig,
    tasks: list[str],
    engine: RolloutEngine,
    cursor: int,
    round_seed: int,
    iteration: int = 0,
    skip_until: dict[str, int] | None = None,
) -> tuple[list[list[Episode]], dict[str, float], int]:
    """Draw groups of K until B are accepted (dynamic rejection); returns groups, stats, new seed cursor.

    With a state pool, ``skip_until`` (updated in place) holds, per draw position, the first iteration at
    which a state whose group was uniform may be drawn again.
    """
    skip_until = {} if skip_until is None else skip_until
    accepted: list[list[Episode]] = []
    outcomes: list[float] = []
    drawn = env_steps = 0
    while len(accepted) < cfg.groups_per_iteration and drawn < cfg.max_draw_factor * cfg.groups_per_iteration:
        n = cfg.groups_per_iteration - len(accepted)
        positions, states, cursor = draw_states(cfg, tasks, cursor, n, skip_until, iteration)
        if not states:
            break  # every state of the pool is being skipped
        # A pool draws its states again in later iterations: a robot's journal must keep each draw's attempts
        # apart (named by this draw's seed), or a later draw would replay an earlier policy's episodes.
        pooled = None if cfg.state_pool is None else round_seed + drawn
        result = engine.rollout(
            states, k=cfg.group_size, sampling=cfg.sampling, seed=round_seed + drawn, round_id=pooled
        )
        groups = result.groups()
        rewards = torch.tensor([[float(e.success) for e in g] for g in groups])
        keep = reject_uniform_groups(rewards)
        accepted += [g for g, k in zip(groups, keep.tolist(), strict=True) if k]
        if cfg.state_pool is not None:
            for position, k in zip(positions, keep.tolist(), strict=True):
                if not k:
                    skip_until[str(position)] = iteration + 1 + cfg.skip_uniform_for
        outcomes += rewards.reshape(-1).tolist()
        drawn += len(groups)
        env_steps += sum(e.length for e in result.episodes)
    stats = {
        "success_rate": float(np.mean(outcomes)) if outcomes else 0.0,
        "rejection_rate": 1 - len(accepted) / drawn if drawn else 0.0,
        "episodes": len(outcomes),
        "env_steps": env_steps,
    }
    return accepted, stats, cursor


class ClippedObjective(torch.nn.Module):
    """SPO's loss on one minibatch as a module, so that LeRobot's ``update_policy`` takes SPO's optimizer step as it
    takes R-SFT's and ``lerobot-train``'s. ``forward(rows)`` is this process's share of Eq. 9 (the clipped
    surrogate, :func:`~lerobot_cso.cso.objectives.clipped_surrogate_loss`) on trajectories ``rows`` of the data set
    with :meth:`use`, normalised by the whole minibatch's unit count. ``train()`` leaves the policy in eval mode:
    dropout and augmentation stay off, so π_old and π are evaluated identically."""

    def __init__(self, cfg: SPOConfig, policy: CSOPolicy) -> None:
        super().__init__()
        self.cfg, self.policy = cfg, policy
        self.objective = cfg.loss_objective()
        self.data: tuple[Batch, torch.Tensor] | None = None

    def use(self, batch: Batch, old: torch.Tensor) -> None:
        """The iteration's data and its log-probs under π_old."""
        self.data = (batch, old)

    def train(self, mode: bool = True) -> "ClippedObjective":
        self.training = mode
        return self

    def forward(self, rows: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
        batch, old = self.data
        granularity = self.objective.granularity
        n_tokens, mean = batch.tokens.shape[-1], self.cfg.trajectory_mean
        units = surrogate_units(batch.mask[rows], n_tokens, granularity, mean)
        mine = rows[distributed.shard_rows(len(rows))]
        if not len(mine):  # every process steps together: this one adds no gradient
            return sum(p.sum() for p in trained_parameters(self.policy)) * 0.0, {"weight": 0.0}
        new = padded_logprobs(self.policy, batch, mine, self.cfg.ratio_sampling())
        loss, stats = clipped_surrogate_loss(
            new, old[mine], batch.mask[mine], batch.advantages[mine], granularity, self.objective.clip, units, mean
        )
        weight = float(surrogate_units(batch.mask[mine], n_tokens, granularity, mean))
        logged = {**asdict(stats), "loss": loss.item() * float(units) / max(weight, 1.0), "weight": weight}
        processes = distributed.state().num_processes
        return (loss * processes if processes > 1 else loss), logged  # DDP averages: the sum is the minibatch's


def update(
    cfg: SPOConfig,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    accelerator: Accelerator,
    batch: Batch,
    generator: torch.Generator,
) -> dict[str, float]:
    """N epochs of minibatch updates of the prior on one iteration's data (Algorithm 1, line 21), each an
    ``update_policy`` step of ``model`` (a :class:`ClippedObjective`, wrapped in DDP by ``accelerator`` when there
    are several processes).

    Data-parallel over processes (:mod:`lerobot_cso.distributed`): every process holds the whole batch and the same
    minibatches and back-propagates its rows of each; DDP's average of the scaled shares is the minibatch's
    gradient, so every replica takes the same step.
    """
    objective = accelerator.unwrap_model(model)
    objective.policy.eval()
    n = len(batch.tokens)
    old, entropy = old_logprobs(objective.policy, batch, cfg.ratio_sampling())
    objective.use(batch, old)
    tracker = MetricsTracker(cfg.minibatch_trajectories, n, n, distributed.step_meters())
    rows: list[dict[str, float]] = []
    for _ in range(cfg.epochs):
        if rows and cfg.target_kl is not None and rows[-1]["approx_kl"] > cfg.target_kl:
            break
        for idx in torch.randperm(n, generator=generator).split(cfg.minibatch_trajectories):
            tracker, logged = update_policy(tracker, model, idx, optimizer, cfg.grad_clip_norm, accelerator)
            weight = logged.pop("weight")
            rows.append({**distributed.weighted_mean(logged, weight), "grad_norm": tracker.grad_norm.val})
            if cfg.target_kl is not None and rows[-1]["approx_kl"] > cfg.target_kl:
                break
    stats = {key: float(np.mean([r[key] for r in rows])) for key in UPDATE_STATS}
    return stats | {"updates": len(rows), "entropy": entropy}


def plot_history(history: list[dict[str, float]], path: Path) -> None:
    """PNG of success rate and clip fraction per iteration."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    its = [h["iteration"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
    for ax, key, label in zip(axes, ("success_rate", "clip_fraction"), ("success rate", "clip fraction"), strict=True):
        ax.plot(its, [h[key] for h in history], marker="o")
        ax.set_xlabel("iteration")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def format_row(row: dict[str, float]) -> str:
    return " | ".join(f"{row[c]:.4g}" if isinstance(row[c], float) else str(row[c]) for c in LOG_COLUMNS)


def _finish_copy(cfg: SPOConfig, state: ResumableState) -> None:
    """A run complete in ``state``: copy its final policy into place if a kill came before that copy."""
    if distributed.is_main() and not (cfg.output_dir / "pretrained_model" / "config.json").is_file():
        tmp = cfg.output_dir / "pretrained_model.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(state.directory / "pretrained_model", tmp)
        replace_dir(tmp, cfg.output_dir / "pretrained_model")
    distributed.wait_for_everyone()


def _load(cfg: SPOConfig, state: ResumableState, resume: bool) -> tuple[CSOPolicy, Any, Any, torch.optim.Optimizer]:
    """The policy (the input checkpoint, or the saved one when resuming), its processors and the optimizer."""
    source = state.directory / "pretrained_model" if resume else cfg.policy.pretrained_path
    policy, pre, post = load_policy(source, cfg.policy if not resume else None)
    policy.set_encoders_frozen(cfg.encoder_freeze)
    optimizer = torch.optim.AdamW(trained_parameters(policy), lr=cfg.lr, weight_decay=cfg.weight_decay)
    if resume:
        optimizer.load_state_dict(torch.load(state.directory / "optimizer.pt"))
    return policy, pre, post, optimizer


def _wandb_run(cfg: SPOConfig) -> Any:
    """The main process's wandb run with ``--wandb.enable=true``; None otherwise."""
    if not (cfg.wandb.enable and distributed.is_main()):
        return None
    import wandb

    return wandb.init(
        project=cfg.wandb.project,
        entity=cfg.wandb.entity,
        mode=cfg.wandb.mode,
        config=json.loads(json.dumps(asdict(cfg), default=str)),
        resume="allow",
        id=cfg.wandb.run_id,
    )


def _save_iteration(
    cfg: SPOConfig,
    state: ResumableState,
    progress: dict[str, Any],
    policy: CSOPolicy,
    processors: tuple[Any, Any],
    optimizer: torch.optim.Optimizer,
) -> None:
    """The main process saves the iteration (checkpoint, optimizer, progress), the log and the plot."""

    def write(directory: Path) -> None:
        save_checkpoint(directory / "pretrained_model", policy, *processors)
        torch.save(optimizer.state_dict(), directory / "optimizer.pt")

    state.save(progress, write)
    history = progress["history"]
    write_atomic(cfg.output_dir / "log.jsonl", "".join(json.dumps(h) + "\n" for h in history).encode())
    plot_history(history, cfg.output_dir / "spo.png")


def run_spo(cfg: SPOConfig, make_engine: Callable[..., RolloutEngine] | None = None) -> list[dict[str, float]]:
    """Run (or resume) SPO; returns the per-iteration history. The final policy is ``output_dir/pretrained_model``.

    ``make_engine(policy, preprocessor, postprocessor, cfg)`` builds the rollout engine.
    """
    tasks = cfg.validate()
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    main = distributed.is_main()
    if main:
        ResumableState(cfg.output_dir / "state")  # undoes an interrupted save before any process reads it
    distributed.wait_for_everyone()
    state = ResumableState(cfg.output_dir / "state")
    saved = state.progress()
    progress = saved or {"iteration": 0, "cursor": 0, "history": [], "skip_until": {}}
    if progress["iteration"] >= cfg.iterations:
        print(f"SPO already complete ({progress['iteration']} iterations) in {cfg.output_dir}")
        _finish_copy(cfg, state)
        return progress["history"]
    policy, pre, post, optimizer = _load(cfg, state, resume=saved is not None)
    accelerator = distributed.accelerator_for(policy)
    model = accelerator.prepare(ClippedObjective(cfg, policy))
    generator = torch.Generator().manual_seed(cfg.seed)
    run = _wandb_run(cfg)
    history, cursor, skip_until = progress["history"], progress["cursor"], progress.get("skip_until", {})
    if main:
        print(" | ".join(LOG_COLUMNS))
    with distributed.ShardedRollouts((make_engine or rollout_stage.stage_engine)(policy, pre, post, cfg)) as engine:
        for iteration in range(progress["iteration"], cfg.iterations):
            started = time.perf_counter()
            round_seed = seeds.round_seed(cfg.seed, iteration * 10_007)
            groups, stats, cursor = collect_groups(cfg, tasks, engine, cursor, round_seed, iteration, skip_until)
            generator.manual_seed(round_seed)
            if groups:
                with cfg.training():
                    batch = Batch.from_groups(groups, cfg.loss_objective().advantage, policy.config.device)
                    stats |= update(cfg, model, optimizer, accelerator, batch, generator)
            else:  # every group was uniform: nothing to learn from this iteration
                stats |= dict.fromkeys(UPDATE_STATS, 0.0) | {"ratio_mean": 1.0, "updates": 0, "entropy": None}
            row = {"iteration": iteration + 1, **stats, "seconds": time.perf_counter() - started}
            history.append(row)
            if main:
                print(format_row(row), flush=True)
                if run is not None:
                    run.log(row, step=iteration + 1)
                progress = {"iteration": iteration + 1, "cursor": cursor, "history": history, "skip_until": skip_until}
                _save_iteration(cfg, state, progress, policy, (pre, post), optimizer)
            distributed.wait_for_everyone()
    if main:
        save_checkpoint(cfg.output_dir / "pretrained_model", policy, pre, post)
    if run is not None:
        run.finish()
    distributed.wait_for_everyone()
    return history


class SPOStage(CheckpointStage):
    """The pipeline's SPO stage: the CSO checkpoint ``output_dir/pretrained_model`` and its history."""

    name = "spo"
    # A finished run continued to more iterations is the longer run: the lr is constant and each iteration's
    # draws depend only on the seed and the iteration's index (the pool and its skip memory are checkpointed).
    grows = ("spo.iterations",)

    def run(self) -> list[dict[str, float]]:
        return run_spo(self.cfg, self.make_engine)

    def history(self) -> list[dict[str, float]]:
        """The per-iteration log rows."""
        return read_json(self.cfg.output_dir / "log.jsonl", lines=True)


@parser.wrap()
def spo_main(cfg: SPOConfig) -> None:
    """Entry point of ``lerobot-cso spo``: resumes or skips only an output of the same settings and checkpoint."""
    run_alone(SPOStage(cfg), main=distributed.is_main())
    print(f"SPO checkpoint: {cfg.output_dir / 'pretrained_model'}")
