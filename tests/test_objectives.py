"""Hand-computed checks of the CSO objectives (lerobot_cso/cso/objectives.py).

Log-probs are built as new = old + log(ratio) with chosen ratios, so every expected value below is plain
arithmetic on those ratios. Gradients are d loss / d new_logprobs: for an unclipped unit with ratio r,
d(r) / d(log-prob of one of its tokens) is r for a token or skill ratio and r / n_tokens_of_trajectory for
the GSPO ratio; clipped units get zero gradient.
"""

import math
from dataclasses import astuple

import pytest
import torch

from lerobot_cso.cso.objectives import (
    PRESETS,
    Advantage,
    Granularity,
    Objective,
    advantages,
    clipped_surrogate_loss,
    default_clip,
    group_advantages,
    leave_one_out_advantages,
    reject_uniform_groups,
    surrogate_units,
)

OLD_LOGP = -1.3  # any value: only new - old matters
PAD = float("nan")  # padded entries hold garbage that must never leak


def make_logprobs(ratios: list, mask: list) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(new leaf requiring grad, old, mask) from per-token ratios (N, D, n); padded steps get PAD."""
    r = torch.tensor(ratios, dtype=torch.float64)
    m = torch.tensor(mask, dtype=torch.bool)
    old = torch.full_like(r, OLD_LOGP)
    new = torch.where(m[..., None], old + r.log(), PAD)
    old = torch.where(m[..., None], old, PAD)
    return new.requires_grad_(True), old, m


def k3(ratios: list[float]) -> float:
    """Mean over tokens of (r - 1) - ln r."""
    return sum(r - 1 - math.log(r) for r in ratios) / len(ratios)


def run(new, old, mask, adv, granularity, clip=None):
    loss, stats = clipped_surrogate_loss(new, old, mask, torch.tensor(adv, dtype=torch.float64), granularity, clip)
    (grad,) = torch.autograd.grad(loss, new)
    return loss.item(), grad, stats


# ---- advantages and dynamic rejection -------------------------------------------------------------------

REWARDS = torch.tensor([[1.0, 0.0, 0.0, 1.0], [1.0, 1.0, 1.0, 0.0]])


def test_group_advantages_eq8():
    # group means 2/4 = 0.5 and 3/4 = 0.75
    expected = torch.tensor([[0.5, -0.5, -0.5, 0.5], [0.25, 0.25, 0.25, -0.75]])
    torch.testing.assert_close(group_advantages(REWARDS), expected)
    torch.testing.assert_close(advantages("group_mean", REWARDS), expected)


def test_leave_one_out_advantages():
    # group 0 (sum 2): R=1 -> 1 - (2-1)/3 = 2/3;  R=0 -> 0 - 2/3 = -2/3
    # group 1 (sum 3): R=1 -> 1 - (3-1)/3 = 1/3;  R=0 -> 0 - 3/3 = -1
    expected = torch.tensor([[2 / 3, -2 / 3, -2 / 3, 2 / 3], [1 / 3, 1 / 3, 1 / 3, -1.0]])
    torch.testing.assert_close(leave_one_out_advantages(REWARDS), expected)
    torch.testing.assert_close(advantages(Advantage.LEAVE_ONE_OUT, REWARDS), expected)
    # integer rewards are accepted
    torch.testing.assert_close(leave_one_out_advantages(REWARDS.long()), expected)
    with pytest.raises(ValueError):
        leave_one_out_advantages(torch.ones(3, 1))


def test_reject_uniform_groups():
    rewards = torch.tensor([[1, 1, 1], [0, 0, 0], [1, 0, 1], [0.5, 0.5, 0.5], [0.0, 0.0, 0.5]])
    keep = reject_uniform_groups(rewards)
    assert keep.dtype == torch.bool
    assert keep.tolist() == [False, False, True, False, True]
    # exactly the groups whose Eq. 8 advantages are not all zero
    assert keep.tolist() == (group_advantages(rewards) != 0).any(dim=1).tolist()


# ---- token and RIPT: per-token ratio, token-mean ----------------------------------------------------------

# N=2, D=2, n=2. Trajectory 1 has only decision 0 (decision 1 padded). A = [+1, -0.5]. 6 valid tokens.
TOKEN_RATIOS = [[[1.5, 1.0], [0.5, 1.25]], [[0.6, 1.1], [1.0, 1.0]]]
TOKEN_MASK = [[True, True], [True, False]]
TOKEN_ADV = [1.0, -0.5]


def test_token_granularity():
    new, old, mask = make_logprobs(TOKEN_RATIOS, TOKEN_MASK)
    loss, grad, stats = run(new, old, mask, TOKEN_ADV, "token")
    # clip [0.8, 1.28], min(rA, clip(r)A):
    #   traj 0 (A=+1):   1.5 -> 1.28 (clipped) | 1.0 -> 1.0 | 0.5 -> min(0.5, 0.8) = 0.5 | 1.25 -> 1.25
    #   traj 1 (A=-0.5): 0.6 -> min(-0.3, -0.4) = -0.4 (clipped) | 1.1 -> -0.55
    # sum = 1.28 + 1 + 0.5 + 1.25 - 0.4 - 0.55 = 3.08; loss = -3.08 / 6
    assert loss == pytest.approx(-3.08 / 6)
    # grad = -A r / 6 on unclipped tokens, 0 on clipped and padded ones
    expected = torch.tensor([[[0.0, -1.0], [-0.5, -1.25]], [[0.0, 0.55], [0.0, 0.0]]]) / 6
    torch.testing.assert_close(grad, expected.double())
    assert stats.clip_fraction == pytest.approx(2 / 6)
    assert (stats.clip_low_fraction, stats.clip_high_fraction) == pytest.approx((1 / 6, 1 / 6))  # 0.6 | 1.5
    assert stats.ratio_mean == pytest.approx((1.5 + 1 + 0.5 + 1.25 + 0.6 + 1.1) / 6)
    assert stats.approx_kl == pytest.approx(k3([1.5, 1.0, 0.5, 1.25, 0.6, 1.1]))


def test_ript_is_the_token_ratio_at_its_own_clip():
    new, old, mask = make_logprobs(TOKEN_RATIOS, TOKEN_MASK)
    ript = PRESETS["ript"]
    loss, grad, stats = run(new, old, mask, TOKEN_ADV, ript.granularity, ript.clip)
    # clip [0.8, 1.2]: as for token, but 1.25 is now clipped to 1.2 as well
    #   traj 0: 1.2 (clipped) + 1.0 + 0.5 + 1.2 (clipped);  traj 1: -0.4 (clipped) - 0.55
    # sum = 2.95; loss = -2.95 / 6
    assert loss == pytest.approx(-2.95 / 6)
    expected = torch.tensor([[[0.0, -1.0], [-0.5, 0.0]], [[0.0, 0.55], [0.0, 0.0]]]) / 6
    torch.testing.assert_close(grad, expected.double())
    assert stats.clip_fraction == pytest.approx(3 / 6)
    assert (stats.clip_low_fraction, stats.clip_high_fraction) == pytest.approx((1 / 6, 2 / 6))  # 0.6 | 1.5, 1.25


# ---- skill (SPO, Eq. 9): ratio = product of the 8 token ratios of one decision -----------------------------


def test_skill_granularity_sums_token_log_ratios():
    n = 8
    ones = [1.0] * n

    def skill(*head):
        return list(head) + ones[len(head) :]

    ratios = [
        [skill(1.5, 0.8), skill(0.9), skill(1.05)],  # traj 0: skill ratios 1.2, 0.9, 1.05
        [skill(2.0, 0.5), skill(0.9), ones],  # traj 1: skill ratios 1.0, 0.9, (padded)
    ]
    mask = [[True, True, True], [True, True, False]]
    new, old, mask = make_logprobs(ratios, mask)
    loss, grad, stats = run(new, old, mask, [1.0, -1.0], "skill")
    # clip [0.93, 1.15], 5 valid skills:
    #   traj 0 (A=+1): 1.2 -> 1.15 (clipped) | 0.9 -> min(0.9, 0.93) = 0.9 | 1.05 -> 1.05
    #   traj 1 (A=-1): 1.0 -> -1.0 | 0.9 -> min(-0.9, -0.93) = -0.93 (clipped)
    # sum = 1.15 + 0.9 + 1.05 - 1.0 - 0.93 = 1.17; loss = -1.17 / 5
    # (a mean of token log-ratios would give 1.2^(1/8) = 1.023 for skill (0, 0): unclipped, nonzero grad)
    assert loss == pytest.approx(-1.17 / 5)
    # every token of an unclipped skill gets -A * r_skill / 5
    per_skill = torch.tensor([[0.0, -0.9, -1.05], [1.0, 0.0, 0.0]]) / 5
    torch.testing.assert_close(grad, per_skill.double()[..., None].expand(2, 3, n))
    assert stats.clip_fraction == pytest.approx(2 / 5)
    assert stats.ratio_mean == pytest.approx((1.2 + 0.9 + 1.05 + 1.0 + 0.9) / 5)
    assert stats.approx_kl == pytest.approx(k3([1.5, 0.8, 0.9, 1.05, 2.0, 0.5, 0.9] + [1.0] * (5 * n - 7)))


# ---- trajectory (GSPO): geometric mean of all valid token ratios of the trajectory -------------------------


def test_trajectory_granularity():
    c = 1.01**4
    ratios = [
        [[c, 1.0], [1.0, 1.0]],  # traj 0: 4 tokens, s = (1.01^4)^(1/4) = 1.01
        [[1.002**2, 1.0], [1.0, 1.0]],  # traj 1: 2 valid tokens, s = 1.002
        [[0.99**4, 1.0], [1.0, 1.0]],  # traj 2: 4 tokens, s = 0.99
        [[1.0, 1.0], [1.0, 1.0]],  # traj 3: fully padded -> not a unit
    ]
    mask = [[True, True], [True, False], [True, True], [False, False]]
    new, old, mask = make_logprobs(ratios, mask)
    loss, grad, stats = run(new, old, mask, [1.0, -1.0, 0.5, 2.0], "trajectory")
    # clip [0.997, 1.004], 3 valid trajectories:
    #   traj 0 (A=+1):   1.01 -> 1.004 (clipped)
    #   traj 1 (A=-1):   1.002 inside -> -1.002
    #   traj 2 (A=+0.5): 0.99 -> min(0.495, 0.4985) = 0.495
    # loss = -(1.004 - 1.002 + 0.495) / 3 = -0.497 / 3
    assert loss == pytest.approx(-0.497 / 3)
    # d s / d token log-prob = s / n_tokens; grad = -A * s / n_tokens / 3 on each valid token
    expected = torch.zeros(4, 2, 2, dtype=torch.float64)
    expected[1, 0] = 1.002 / 2 / 3
    expected[2] = -0.5 * 0.99 / 4 / 3
    torch.testing.assert_close(grad, expected)
    assert stats.clip_fraction == pytest.approx(1 / 3)
    assert stats.ratio_mean == pytest.approx((1.01 + 1.002 + 0.99) / 3)


# ---- masking, defaults, edge cases -----------------------------------------------------------------------


@pytest.mark.parametrize("granularity", list(Granularity))
def test_padding_affects_neither_loss_nor_gradient(granularity):
    torch.manual_seed(0)
    n_traj, d_max, n = 3, 4, 8
    lengths = torch.tensor([4, 2, 1])
    mask = torch.arange(d_max)[None, :] < lengths[:, None]
    old = -torch.rand(n_traj, d_max, n, dtype=torch.float64) * 3
    new = old + 0.05 * torch.randn_like(old)
    adv = torch.tensor([0.5, -0.25, 1.0], dtype=torch.float64)
    results = []
    for fill in (0.0, 1.0, 1e4, float("nan")):  # RIPT pads with 1.0; any other garbage as well
        pad = ~mask[..., None].expand_as(old)
        new_p = new.masked_fill(pad, fill).requires_grad_(True)
        old_p = old.masked_fill(pad, -fill)
        results.append(run(new_p, old_p, mask, adv.tolist(), granularity))
    loss0, grad0, stats0 = results[0]
    assert math.isfinite(loss0)
    assert torch.all(grad0[~mask] == 0)
    assert grad0[mask].abs().sum() > 0
    for loss, grad, stats in results[1:]:
        assert loss == pytest.approx(loss0, rel=1e-12)
        torch.testing.assert_close(grad, grad0, rtol=1e-12, atol=0)
        assert astuple(stats) == pytest.approx(astuple(stats0), rel=1e-12)


def test_surrogate_units_by_hand():
    mask = torch.tensor([[True, True, False], [True, False, False], [False, False, False]])
    counts = {g: int(surrogate_units(mask, 8, g)) for g in Granularity}
    assert counts == {"token": 24, "skill": 3, "trajectory": 2}


def test_trajectory_mean_weighs_a_long_failure_as_much_as_a_short_success():
    # a success of 1 skill (A = +0.5) and a failure of 3 skills (A = -0.5) of one group, every ratio 1 (unclipped)
    new, old, mask = make_logprobs([[[1.0] * 8] * 3, [[1.0] * 8] * 3], [[True, False, False], [True, True, True]])
    adv = torch.tensor([0.5, -0.5], dtype=torch.float64)
    eq9, _ = clipped_surrogate_loss(new, old, mask, adv, Granularity.SKILL)
    assert eq9.item() == pytest.approx(-(0.5 - 3 * 0.5) / 4)  # skill mean: the failure's 3 skills outweigh
    loss, _ = clipped_surrogate_loss(new, old, mask, adv, Granularity.SKILL, trajectory_mean=True)
    assert loss.item() == pytest.approx(0.0)  # -(0.5 / 1 - 1.5 / 3) / 2
    (grad,) = torch.autograd.grad(loss, new)
    # d loss / d log-prob of a token = -A r / (2 trajectories * the trajectory's skills)
    assert grad[0, 0] == pytest.approx(torch.full((8,), -0.25, dtype=torch.float64))
    assert grad[1] == pytest.approx(torch.full((3, 8), 0.5 / 6, dtype=torch.float64))
    assert int(surrogate_units(mask, 8, Granularity.SKILL, trajectory_mean=True)) == 2


@pytest.mark.parametrize("trajectory_mean", [False, True])
@pytest.mark.parametrize("granularity", list(Granularity))
def test_row_shards_normalised_by_the_whole_minibatch_add_up_to_it(granularity, trajectory_mean):
    """What a data-parallel SPO update relies on: rows split over processes, each loss divided by the whole
    minibatch's unit count, sum to the minibatch's loss and gradient."""
    torch.manual_seed(1)
    mask = torch.arange(4)[None, :] < torch.tensor([4, 2, 1, 3, 2])[:, None]
    old = -torch.rand(5, 4, 8, dtype=torch.float64) * 3
    new = (old + 0.2 * torch.randn_like(old)).requires_grad_(True)
    adv = torch.tensor([0.5, -0.25, 1.0, -1.0, 0.1], dtype=torch.float64)
    whole, _ = clipped_surrogate_loss(new, old, mask, adv, granularity, trajectory_mean=trajectory_mean)
    (grad_whole,) = torch.autograd.grad(whole, new)
    units = surrogate_units(mask, 8, granularity, trajectory_mean)
    parts = [
        clipped_surrogate_loss(new[r], old[r], mask[r], adv[r], granularity, None, units, trajectory_mean)[0]
        for r in (slice(0, 5, 2), slice(1, 5, 2))
    ]
    (grad_parts,) = torch.autograd.grad(sum(parts), new)
    assert float(sum(parts).detach()) == pytest.approx(float(whole.detach()), rel=1e-12)
    torch.testing.assert_close(grad_parts, grad_whole, rtol=1e-12, atol=1e-15)


def test_no_valid_decision_gives_zero_loss():
    new = torch.zeros(2, 3, 8, requires_grad=True)
    loss, stats = clipped_surrogate_loss(new, new.detach() + 1, torch.zeros(2, 3, dtype=torch.bool), torch.ones(2))
    assert loss.item() == 0.0 and stats.clip_fraction == 0.0 and stats.approx_kl == 0.0


def test_old_logprobs_get_no_gradient_and_identical_policies_give_unit_ratio():
    old = torch.randn(2, 3, 8, requires_grad=True)
    mask = torch.ones(2, 3, dtype=torch.bool)
    for granularity in Granularity:
        loss, stats = clipped_surrogate_loss(
            old.detach().clone().requires_grad_(True), old, mask, torch.tensor([1.0, -1.0]), granularity
        )
        loss.backward()
        assert old.grad is None
        assert stats.ratio_mean == pytest.approx(1.0) and stats.clip_fraction == 0.0
        assert stats.approx_kl == 0.0


def test_default_clip_ranges():
    assert default_clip("skill") == (0.93, 1.15)
    assert default_clip("token") == (0.8, 1.28)
    assert default_clip("trajectory") == (0.997, 1.004)
    assert default_clip("ript") == (0.8, 1.2)
    assert set(PRESETS) == {"skill", "token", "trajectory", "ript"}
    with pytest.raises(ValueError):
        default_clip("sequence")


def test_explicit_clip_overrides_default():
    new, old, mask = make_logprobs(TOKEN_RATIOS, TOKEN_MASK)
    # token granularity with RIPT's range reproduces the RIPT loss
    loss, _, stats = run(new, old, mask, TOKEN_ADV, "token", clip=(0.8, 1.2))
    assert loss == pytest.approx(-2.95 / 6) and stats.clip_fraction == pytest.approx(0.5)


def test_the_presets_are_the_papers_objectives_as_three_independent_choices():
    """``skill``, ``token`` and ``trajectory`` differ in their ratio only (and its clip); RIPT is the token ratio
    with the leave-one-out advantage; every granularity pairs with every estimator."""
    assert PRESETS["skill"] == Objective(Granularity.SKILL, Advantage.GROUP_MEAN, (0.93, 1.15))
    assert {name: PRESETS[name].granularity for name in ("skill", "token", "trajectory")} == {
        "skill": "skill",
        "token": "token",
        "trajectory": "trajectory",
    }
    assert {p.advantage for name, p in PRESETS.items() if name != "ript"} == {Advantage.GROUP_MEAN}
    assert PRESETS["ript"] == Objective(Granularity.TOKEN, Advantage.LEAVE_ONE_OUT, (0.8, 1.2))
    rewards = torch.tensor([[1.0, 0.0, 0.0]])
    torch.testing.assert_close(advantages("leave_one_out", rewards), 1.5 * advantages("group_mean", rewards))
