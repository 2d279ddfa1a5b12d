"""Safety properties: no command beyond the soft limits or the step limit ever reaches the bus."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from piper_can import codec
from piper_can.safety import SDK_SOFT_LIMITS, safe_target
from piper_rig import Rig, make_rig, wait_until

MAX_STEP = 0.2
MAX_GRIPPER_STEP = 0.02
QUANTUM = 1e-5  # > half of 0.001° in radians (8.7e-6): the encoding's rounding


@pytest.fixture(scope="module")
def stepped_rig() -> Iterator[Rig]:
    """Connected and enabled on simulated time, then the emulator is stepped by the test (deterministic;
    the clock stands still, so the watchdog never sees an old frame: its largest setting is plenty)."""
    with make_rig(feedback_timeout_s=1.0, max_step_rad=MAX_STEP, max_gripper_step_m=MAX_GRIPPER_STEP) as rig:
        rig.emulator.stop()
        yield rig


def as_fed_back(joints, gripper) -> tuple[tuple[float, ...], float]:
    """What the arm's feedback frames say for these ground-truth values."""
    frames = codec.encode_joint_positions(joints)
    fed = [p for f in frames for p in codec.decode_feedback(f.arbitration_id, f.data).positions_rad]
    grip = codec.encode(codec.GripperFeedback(gripper, 0.0, 0))
    return tuple(fed), codec.decode_feedback(grip.arbitration_id, grip.data).opening_m


target = st.one_of(st.floats(-4.0, 4.0), st.sampled_from([-1e6, 1e6, 0.0]))


@settings(max_examples=150, deadline=None)
@given(
    goal=st.lists(target, min_size=6, max_size=6),
    gripper=st.one_of(st.floats(-0.1, 0.2), st.sampled_from([-1e3, 1e3])),
    moves=st.integers(0, 60),
)
def test_no_command_beyond_limits_or_step_ever_reaches_the_bus(stepped_rig, goal, gripper, moves):
    rig = stepped_rig
    for _ in range(moves):  # let the arm travel toward the previous targets
        rig.emulator.step()
    rig.emulator.step()
    present, present_gripper = as_fed_back(rig.arm.joints_rad, rig.arm.gripper_m)
    assert wait_until(lambda: rig.driver.state().joint_positions_rad == present, timeout=2.0)
    assert wait_until(lambda: rig.driver.state().gripper.value.opening_m == present_gripper, timeout=2.0)
    rig.drain()

    rig.driver.command(goal, gripper)

    sent = {m.arbitration_id: m.data for m in rig.drain()}
    joints = [
        p for i in codec.ID_JOINT_COMMAND for p in codec.decode_command(i, sent[i]).positions_rad
    ]  # every motion frame the bus carried
    for j, (t, now, (lower, upper)) in enumerate(zip(joints, present, SDK_SOFT_LIMITS.joints_rad, strict=True)):
        assert lower <= t <= upper, f"joint_{j + 1} target {t} outside [{lower}, {upper}]"
        assert abs(t - now) <= MAX_STEP + QUANTUM, f"joint_{j + 1} step {t - now}"
    grip = codec.decode_command(0x159, sent[0x159]).opening_m
    assert 0.0 <= grip <= 0.07
    assert abs(grip - present_gripper) <= MAX_GRIPPER_STEP + 1e-6


finite = st.floats(-10, 10)


@settings(max_examples=500)
@given(goal=finite, present=finite, low=finite, width=st.floats(0, 5), step=st.floats(0.001, 1))
def test_safe_target_caps_the_step_and_never_moves_away_from_the_limits(goal, present, low, width, step):
    bounds = (low, low + width)
    t = safe_target(goal, present, bounds, step)
    assert abs(t - present) <= step + 1e-12
    if bounds[0] <= present <= bounds[1]:
        assert bounds[0] <= t <= bounds[1]
    else:  # outside the limits (pushed there): only ever toward them

        def distance(x: float) -> float:
            return max(bounds[0] - x, x - bounds[1], 0.0)

        assert distance(t) <= distance(present) + 1e-12


def test_safe_target_without_step_limit_only_clamps():
    assert safe_target(5.0, 0.0, (-1.0, 1.0), None) == 1.0
    assert safe_target(0.5, 0.0, (-1.0, 1.0), None) == 0.5
