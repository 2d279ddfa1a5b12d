"""Issue 34, item 5: every step, speed, timeout and pose is checked when the config is built (one clear
error), and the clamp refuses a step that would not bound anything."""

from __future__ import annotations

import math

import pytest
from piper_can.safety import safe_target
from piper_can.settings import DriverConfig


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("max_gripper_step_m", -0.01),  # sent the gripper to -0.01 m
        ("max_gripper_step_m", math.nan),  # removed the gripper's cap
        ("max_gripper_step_m", 0.0),
        ("max_step_rad", math.nan),
        ("max_step_rad", (0.2, 0.2, -0.2, 0.2, 0.2, 0.2)),
        ("rest_speed_rad_s", -0.5),  # walked every joint away from the rest pose
        ("rest_speed_rad_s", math.nan),  # removed the rest speed limit
        ("rest_speed_rad_s", 0.0),
        ("rest_speed_rad_s", 10.0),  # above the firmware's 3 rad/s
        ("feedback_timeout_s", 1e9),  # no watchdog at all
        ("feedback_timeout_s", math.nan),
        ("feedback_timeout_s", 0.0),
        ("connect_timeout_s", -1.0),
        ("enable_timeout_s", math.inf),
        ("rest_timeout_s", math.nan),
        ("reset_settle_s", 0.5),  # shorter than the firmware's motor-off: the re-enable would be lost
        ("gripper_effort_nm", 6.0),
        ("gripper_effort_nm", math.nan),
        ("rest_pose_rad", (0.0, -0.3, 0.0, 0.0, 0.0, 0.0)),  # J2 below its 0 rad limit
        ("rest_pose_rad", (math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)),
        ("rest_gripper_m", 0.09),  # past the 0.07 m stroke
        ("rest_gripper_m", -0.01),
        ("speed_percent", 50.5),
        ("speed_percent", True),
        ("bitrate", 0),
    ],
)
def test_a_bad_setting_is_one_clear_error_when_the_config_is_built(setting, value):
    with pytest.raises(ValueError, match=setting) as err:
        DriverConfig(**{setting: value})
    assert "\n" not in str(err.value)


def test_the_defaults_and_sane_settings_are_accepted():
    DriverConfig()
    DriverConfig(feedback_timeout_s=0.3, rest_speed_rad_s=2.0, max_gripper_step_m=None, max_step_rad=None)


@pytest.mark.parametrize("step", [-0.01, 0.0, math.nan, math.inf])
def test_the_clamp_refuses_a_step_that_bounds_nothing(step):
    with pytest.raises(ValueError, match="step limit must be positive and finite"):
        safe_target(0.05, 0.0, (0.0, 0.07), step)
