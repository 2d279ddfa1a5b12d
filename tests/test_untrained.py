"""``lerobot_cso.untrained``: a seeded fresh cso policy, and its checkpoint that loads back the LeRobot way."""

from __future__ import annotations

import torch
from lerobot.configs.types import FeatureType
from tiny_data import TINY_POLICY_KWARGS

from lerobot_cso.checkpoints import load_policy
from lerobot_cso.untrained import save_untrained_policy, untrained_policy

CAMERA = {"observation.images.cam": (3, 8, 8)}


def test_the_saved_policy_loads_back_with_its_features_weights_and_statistics(tmp_path):
    stats = {
        "observation.state": {"mean": torch.zeros(3), "std": torch.ones(3)},
        "action": {"min": torch.tensor([-1.0, 0.0]), "max": torch.tensor([3.0, 0.5])},
        "observation.images.cam": {"mean": torch.zeros(3, 1, 1), "std": torch.ones(3, 1, 1)},
    }
    path = save_untrained_policy(tmp_path / "policy", stats, ["reach"], 3, 2, CAMERA, **TINY_POLICY_KWARGS)
    policy, _, post = load_policy(path)
    features = policy.config.input_features
    assert features["observation.state"].type == FeatureType.STATE and features["observation.state"].shape == (3,)
    assert features["observation.images.cam"].type == FeatureType.VISUAL
    assert policy.config.output_features["action"].shape == (2,)
    assert policy.config.tasks == ["reach"] and policy.config.n_autoencoder_steps == 0
    # the same seed draws the same weights
    fresh = untrained_policy(["reach"], 3, 2, CAMERA, **TINY_POLICY_KWARGS).state_dict()
    assert all(torch.equal(value, fresh[key]) for key, value in policy.state_dict().items())
    # actions in [-1, 1] come out in the statistics' [min, max]: -1 → min, 1 → max
    assert torch.allclose(post(torch.tensor([[-1.0, 1.0]])), torch.tensor([[-1.0, 0.5]]))


def test_settings_override_the_defaults():
    policy = untrained_policy(["reach"], 3, 2, n_autoencoder_steps=5, **TINY_POLICY_KWARGS)
    assert policy.config.n_autoencoder_steps == 5 and policy.config.device == "cpu"
