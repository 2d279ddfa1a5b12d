"""Policy-optimisation objectives of CSO as pure tensor functions (paper Section 4, Eq. 5-9, Appendix E).

Shapes used throughout:
  rewards          (G, K)                 G groups of K trajectories, each group from one initial state
  log-probs        (N, D_max, n_tokens)   per-token log-probs of the sampled skill tokens, N trajectories
                                          padded to D_max decision steps, n_tokens (= 8) tokens per skill
  decision_mask    (N, D_max) bool        True on real decision steps, False on padding
  advantages       (N,)                   one advantage per trajectory, broadcast to its skills/tokens

Padded entries may hold any value (RIPT pads with 1.0; NaN is fine too): they are replaced by a zero
log-ratio before anything else, so they reach neither the loss nor the gradient.

An :class:`Objective` is three independent choices, as TRL separates ``importance_sampling_level`` from
``loss_type``: the ratio's :class:`Granularity`, the :class:`Advantage` estimator and the clip range. ``skill``
(SPO), ``token`` (GRPO), ``trajectory`` (GSPO) and ``ript`` (RIPT-VLA) are named presets of them
(:data:`PRESETS`); a new objective is one more preset, a new estimator one more function of :data:`ESTIMATORS`.
"""

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import torch
from torch import Tensor


class Granularity(StrEnum):
    """Unit at which the importance ratio is computed and clipped (paper Table 3, D.6, E.3)."""

    TOKEN = "token"  # GRPO/DAPO-style: one ratio per token
    SKILL = "skill"  # SPO (Eq. 9): one ratio per skill = the n_tokens tokens of one decision step
    TRAJECTORY = "trajectory"  # GSPO (Eq. 5): one length-normalised ratio per trajectory


class Advantage(StrEnum):
    """How a trajectory's advantage is estimated from its group's rewards."""

    GROUP_MEAN = "group_mean"  # Eq. 8
    LEAVE_ONE_OUT = "leave_one_out"  # RIPT's RLOO


@dataclass(frozen=True)
class Objective:
    """A policy-optimisation objective: the ratio's granularity, the advantage estimator, the clip bounds
    (1 - eps_low, 1 + eps_high) on the ratio."""

    granularity: Granularity
    advantage: Advantage
    clip: tuple[float, float]


PRESETS: dict[str, Objective] = {
    # Paper E.2 / Table 9 best row; the clip is calibrated for the SUM of token log-ratios (`clipped_surrogate_loss`).
    "skill": Objective(Granularity.SKILL, Advantage.GROUP_MEAN, (0.93, 1.15)),
    # DAPO's clip-higher, as the paper's token-level baseline (E.3; best row of Table 9).
    "token": Objective(Granularity.TOKEN, Advantage.GROUP_MEAN, (0.8, 1.28)),
    # Paper E.3 (best row of Table 9). E.3 calls this GSPO's "official" range, but the GSPO paper uses
    # eps_low = 3e-4, eps_high = 4e-4, i.e. (0.9997, 1.0004), which Table 9 lists as a worse setting.
    "trajectory": Objective(Granularity.TRAJECTORY, Advantage.GROUP_MEAN, (0.997, 1.004)),
    # RIPT-VLA's released code: per-token ratio, leave-one-out advantage, ppo_clip_range = ppo_clip_high = 0.2.
    "ript": Objective(Granularity.TOKEN, Advantage.LEAVE_ONE_OUT, (0.8, 1.2)),
}


def preset(name: str) -> Objective:
    """The objective named ``name``; ``ValueError`` naming the presets otherwise."""
    if name not in PRESETS:
        raise ValueError(f"objective must be one of {', '.join(PRESETS)}, got '{name}'")
    return PRESETS[name]


def default_clip(name: str) -> tuple[float, float]:
    """The (lower, upper) ratio clip bounds of the objective ``name``."""
    return preset(name).clip


def _as_float_groups(rewards: Tensor) -> Tensor:
    if rewards.ndim != 2:
        raise ValueError(f"rewards must have shape (G, K), got {tuple(rewards.shape)}")
    return rewards if rewards.is_floating_point() else rewards.float()


def group_advantages(rewards: Tensor) -> Tensor:
    """Eq. 8: A(tau) = R(tau) - mean of R over the trajectory's group. (G, K) -> (G, K); no std scaling."""
    rewards = _as_float_groups(rewards)
    return rewards - rewards.mean(dim=1, keepdim=True)


def leave_one_out_advantages(rewards: Tensor) -> Tensor:
    """RIPT's RLOO advantage: A_k = R_k - mean_{j != k} R_j. (G, K) -> (G, K); needs K >= 2.

    Equals K / (K - 1) times the Eq. 8 advantage of the same group.
    """
    rewards = _as_float_groups(rewards)
    k = rewards.shape[1]
    if k < 2:
        raise ValueError("leave-one-out advantages need at least 2 trajectories per group")
    return rewards - (rewards.sum(dim=1, keepdim=True) - rewards) / (k - 1)


ESTIMATORS: dict[Advantage, Callable[[Tensor], Tensor]] = {
    Advantage.GROUP_MEAN: group_advantages,
    Advantage.LEAVE_ONE_OUT: leave_one_out_advantages,
}


def advantages(estimator: Advantage | str, rewards: Tensor) -> Tensor:
    """The advantages (G, K) of an estimator for rewards (G, K)."""
    return ESTIMATORS[Advantage(estimator)](rewards)


def reject_uniform_groups(rewards: Tensor) -> Tensor:
    """Dynamic rejection (Section 4.2, Algorithm 1): keep-mask (G,) bool, False where all K rewards are equal.

    Such groups have all-zero advantages and carry no learning signal.
    """
    rewards = _as_float_groups(rewards)
    return (rewards != rewards[:, :1]).any(dim=1)


@dataclass(frozen=True)
class SurrogateStats:
    """Diagnostics of one loss evaluation (detached floats).

    clip_fraction: fraction of valid ratio units (tokens, skills or trajectories, by granularity) where the
        clipped branch is the active minimum, i.e. A > 0 and ratio > upper, or A < 0 and ratio < lower; these
        units get zero gradient (the paper's "clipping fraction", Table 3).
    approx_kl: k3 estimator of KL(pi_old || pi) per token, mean over valid tokens of (r - 1) - log r with
        r = exp(log pi - log pi_old); non-negative, and token-level for every granularity so it is comparable.
    ratio_mean: mean over valid units of the ratio that is clipped.
    """

    clip_fraction: float
    clip_low_fraction: float
    clip_high_fraction: float
    approx_kl: float
    ratio_mean: float


def surrogate_units(
    decision_mask: Tensor, n_tokens: int, granularity: Granularity | str, trajectory_mean: bool = False
) -> Tensor:
    """How many units (tokens, skills or trajectories) :func:`clipped_surrogate_loss` averages over; with
    ``trajectory_mean``, the trajectories."""
    granularity = Granularity(granularity)
    if trajectory_mean:
        return (decision_mask.sum(dim=1) > 0).sum()
    if granularity is Granularity.TOKEN:
        return decision_mask.sum() * n_tokens
    if granularity is Granularity.SKILL:
        return decision_mask.sum()
    return (decision_mask.sum(dim=1) > 0).sum()


def trajectory_means(objective: Tensor, unit_mask: Tensor) -> Tensor:
    """Each trajectory's mean objective over its valid units: (N, D[, n]) -> (N,), 0 for one without a unit.

    Not the paper's aggregation: Eq. 9 sums over a trajectory's skills, so a trajectory weighs in proportion to its
    length; this weighs every trajectory equally (GRPO's per-sequence mean). Where failures run to the time limit
    and successes stop early, Eq. 9's negative advantages outweigh the positive ones skill by skill, and the
    objective lowers the probability of what was sampled on the whole; here each group's advantages still sum to 0.
    """
    dims = tuple(range(1, objective.ndim))
    return objective.sum(dim=dims) / unit_mask.sum(dim=dims).clamp(min=1)


def clipped_surrogate_loss(
    new_logprobs: Tensor,
    old_logprobs: Tensor,
    decision_mask: Tensor,
    advantages: Tensor,
    granularity: Granularity | str = Granularity.SKILL,
    clip: tuple[float, float] | None = None,
    n_units: Tensor | None = None,
    trajectory_mean: bool = False,
) -> tuple[Tensor, SurrogateStats]:
    """PPO-style clipped surrogate at a chosen granularity; returns (loss = -objective, stats).

    The loss is the sum of the units' objectives over ``n_units`` (default: this batch's valid units, see
    :func:`surrogate_units`); a process of a data-parallel update passes its whole minibatch's count, so the
    processes' losses add up to the minibatch's. The stats always refer to this batch.

    Per valid unit u with ratio r_u and its trajectory's advantage A: objective_u = min(r_u A, clip(r_u) A),
    with clip bounds `clip` or those of the preset of the granularity's name (`default_clip`). `old_logprobs` is
    treated as a constant.

    - ``skill`` (SPO, Eq. 9): r(Z_t) = exp(sum_j [log pi(z_t^j) - log pi_old(z_t^j)]) over the n_tokens
      tokens of decision t. The SUM (not the mean) is the literal reading of Eq. 7, pi(Z_t) = prod_j
      pi(z_t^j), so r is the true probability ratio of the whole skill. The default [0.93, 1.15] is calibrated
      for it: it bounds the change of a skill's probability to -7 % / +15 % (about -0.9 % / +1.8 % per token
      over 8 tokens). Under the mean reading the same bounds would allow a skill's probability to move by
      0.93^8 = 0.56x to 1.15^8 = 3.06x, a far looser trust region than PPO's; and Table 9's clip fractions
      (SPO 11.2 % at [0.93, 1.15] vs token-level 3.5 % at [0.8, 1.28]) fit the wider spread of a sum.
      Aggregation: mean over all valid skills of the batch. Eq. 9 sums over the skills of a trajectory and
      averages over trajectories; the skill-mean equals that times the batch constant N_traj / N_skills, so
      the gradient direction is exactly Eq. 9's (every skill weighted equally, longer trajectories contribute
      more skills), while the scale stays O(|A|) whatever the horizon, so the learning rate and gradient
      clipping do not depend on episode length.
    - ``token`` (GRPO/DAPO; RIPT-VLA's released code too, with the symmetric clip 0.2 and
      `leave_one_out_advantages`): one ratio per token, token-mean over the valid tokens of the batch.
    - ``trajectory`` (GSPO, Eq. 5 with GSPO's length normalisation): r(tau) = exp(mean of the token log-ratios
      over all valid tokens of the trajectory), the geometric mean of the token ratios; mean over the
      trajectories that have at least one valid decision (GSPO's sequence mean).

    ``trajectory_mean`` (token and skill granularity): each trajectory's units are averaged first
    (:func:`trajectory_means`), then the trajectories, so a long trajectory weighs no more than a short one;
    ``n_units`` then counts trajectories (:func:`surrogate_units`).
    """
    granularity = Granularity(granularity)
    lower, upper = default_clip(granularity.value) if clip is None else clip
    if new_logprobs.ndim != 3 or new_logprobs.shape != old_logprobs.shape:
        raise ValueError("new/old log-probs must both have shape (N, D_max, n_tokens)")
    if decision_mask.shape != new_logprobs.shape[:2] or advantages.shape != new_logprobs.shape[:1]:
        raise ValueError("decision_mask must be (N, D_max) and advantages (N,)")

    token_mask = decision_mask.bool().unsqueeze(-1).expand_as(new_logprobs)
    token_log_ratio = torch.where(token_mask, new_logprobs - old_logprobs.detach(), 0.0)
    advantages = advantages.detach().to(token_log_ratio.dtype)

    if granularity is Granularity.TOKEN:
        log_ratio, unit_mask = token_log_ratio, token_mask
        unit_adv = advantages[:, None, None].expand_as(log_ratio)
    elif granularity is Granularity.SKILL:
        log_ratio, unit_mask = token_log_ratio.sum(dim=-1), decision_mask.bool()
        unit_adv = advantages[:, None].expand_as(log_ratio)
    else:
        n_tokens = token_mask.sum(dim=(1, 2))
        log_ratio = token_log_ratio.sum(dim=(1, 2)) / n_tokens.clamp(min=1)
        unit_mask, unit_adv = n_tokens > 0, advantages

    ratio = torch.exp(log_ratio)
    unclipped = ratio * unit_adv
    clipped = ratio.clamp(lower, upper) * unit_adv
    objective = torch.where(unit_mask, torch.minimum(unclipped, clipped), 0.0)
    n_units_here = unit_mask.sum().clamp(min=1)
    if trajectory_mean and granularity is not Granularity.TRAJECTORY:
        per_trajectory = trajectory_means(objective, unit_mask)
        here = (decision_mask.sum(dim=1) > 0).sum().clamp(min=1)
        loss = -per_trajectory.sum() / (here if n_units is None else n_units.clamp(min=1))
    else:
        loss = -objective.sum() / (n_units_here if n_units is None else n_units.clamp(min=1))

    with torch.no_grad():
        was_clipped = (clipped < unclipped) & unit_mask
        below = was_clipped & (ratio < lower)
        k3 = torch.where(token_mask, torch.expm1(token_log_ratio) - token_log_ratio, 0.0)
        stats = SurrogateStats(
            clip_fraction=(was_clipped.sum() / n_units_here).item(),
            clip_low_fraction=(below.sum() / n_units_here).item(),
            clip_high_fraction=((was_clipped & ~below).sum() / n_units_here).item(),
            approx_kl=(k3.sum() / token_mask.sum().clamp(min=1)).item(),
            ratio_mean=(torch.where(unit_mask, ratio, 0.0).sum() / n_units_here).item(),
        )
    return loss, stats
