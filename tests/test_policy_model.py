"""The cso policy in-process: overfitting, log-prob hooks, KV cache, save/load, freezing, padding, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from tiny_data import TASKS, TINY_POLICY_KWARGS, make_synthetic_dataset

from lerobot_cso.policy import CSOConfig, CSOPolicy
from lerobot_cso.policy.modeling_cso import masked_l1, skill_nll
from lerobot_cso.policy.skill_prior import draw_tokens, entropy, filtered_log_probs
from lerobot_cso.sampling import Sampling


def tiny_config(**overrides) -> CSOConfig:
    kwargs = {
        **TINY_POLICY_KWARGS,
        "device": "cpu",
        "tasks": list(TASKS),
        "input_features": {"observation.state": PolicyFeature(FeatureType.STATE, (6,))},
        "output_features": {"action": PolicyFeature(FeatureType.ACTION, (3,))},
        **overrides,
    }
    return CSOConfig(**kwargs)


def batch_of(size: int = 4, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {
        "observation.state": torch.randn(size, 6, generator=g),
        "task": [TASKS[i % 2] for i in range(size)],
    }


@pytest.fixture
def policy() -> CSOPolicy:
    torch.manual_seed(0)
    return CSOPolicy(tiny_config()).eval()


def test_overfit_tiny_dataset_reconstruction_and_prior(tmp_path):
    """Both phases learn: L1 reconstruction < 0.08 and prior NLL < 0.7 nats/token on a tiny dataset."""
    torch.manual_seed(0)
    root = tmp_path / "ds"
    make_synthetic_dataset(root, episode_lengths=(48, 48))
    cfg = tiny_config(n_autoencoder_steps=300, ae_dropout=0.0, prior_dropout=0.0)
    ds = LeRobotDataset("local/synthetic", root=root, delta_timestamps={"action": [i / 10 for i in range(32)]})
    pre, _ = make_pre_post_processors(cfg, dataset_stats=ds.meta.stats)
    policy = CSOPolicy(cfg, dataset_meta=ds.meta).train()
    loader = torch.utils.data.DataLoader(ds, batch_size=len(ds), shuffle=False)
    batch = pre(next(iter(loader)))
    opt = torch.optim.AdamW(policy.get_optim_params(), lr=2e-3)
    infos = []
    for _ in range(300 + 200):
        loss, info = policy.forward(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        infos.append(info)
    assert infos[0]["recon_l1"] > 0.3
    assert infos[299]["phase"] == 0 and infos[299]["recon_l1"] < 0.08
    assert infos[300]["phase"] == 1 and infos[300]["nll"] > 3.0
    assert infos[-1]["nll"] < 0.7


def test_teacher_forced_logprobs_equal_sampling_logprobs(policy):
    context = policy.encode_context(batch_of(6))
    tokens, logp = policy.sample_skills(context, generator=torch.Generator().manual_seed(1))
    assert tokens.shape == (6, 8) and tokens.dtype == torch.long
    recomputed = policy.token_logprobs(context, tokens)
    torch.testing.assert_close(recomputed, logp, atol=1e-5, rtol=0)
    # A proper distribution: log-probs are <= 0 and sampling at T=1 is not degenerate.
    assert (logp <= 0).all() and logp.min() < -1


def test_logprobs_are_those_of_the_filtered_distribution(policy):
    context = policy.encode_context(batch_of(5))
    tokens, logp = policy.sample_skills(
        context, Sampling(temperature=0.5, top_k=3), generator=torch.Generator().manual_seed(2)
    )
    torch.testing.assert_close(
        policy.token_logprobs(context, tokens, Sampling(temperature=0.5, top_k=3)), logp, atol=1e-5, rtol=0
    )
    full = policy.token_logprobs(context, tokens)
    assert (logp > full).all()  # renormalising over 3 of 1000 codes raises every sampled token's probability
    # Top-k = 1 at any temperature is greedy: log-prob exactly 0.
    tokens1, logp1 = policy.sample_skills(context, Sampling(top_k=1), generator=torch.Generator().manual_seed(3))
    greedy, _ = policy.sample_skills(context, Sampling(top_k=None, greedy=True))
    assert torch.equal(tokens1, greedy) and torch.all(logp1 == 0)


def test_token_logprobs_carry_gradients_to_the_prior_only(policy):
    context = policy.encode_context(batch_of(2)).detach()
    tokens, _ = policy.sample_skills(context)
    policy.token_logprobs(context, tokens).sum().backward()
    assert all(p.grad is not None for p in policy.prior.parameters() if p.requires_grad)
    assert all(p.grad is None for p in policy.autoencoder.parameters())


def test_kv_cached_sampling_equals_uncached(policy):
    context = policy.encode_context(batch_of(16, seed=4))
    cached = policy.sample_skills(context, generator=torch.Generator().manual_seed(5), use_cache=True)
    uncached = policy.sample_skills(context, generator=torch.Generator().manual_seed(5), use_cache=False)
    assert torch.equal(cached[0], uncached[0])
    torch.testing.assert_close(cached[1], uncached[1], atol=1e-5, rtol=0)


def test_select_action_executes_n_action_steps_then_replans(policy):
    policy.config.greedy = True
    policy.reset()
    batch = batch_of(2)
    chunk = policy.predict_action_chunk(batch)
    assert chunk.shape == (2, 32, 3)
    actions = [policy.select_action(batch) for _ in range(9)]
    torch.testing.assert_close(torch.stack(actions[:8], 1), chunk[:, :8])
    assert len(policy._action_queue) == 7  # the 9th call decoded a fresh skill


def test_save_load_round_trip_identical_actions_and_task_map(policy, tmp_path):
    policy.config.greedy = True
    policy.set_encoders_frozen(True)
    policy.save_pretrained(tmp_path)
    loaded = CSOPolicy.from_pretrained(tmp_path).eval()
    assert loaded.config.tasks == list(TASKS)
    assert loaded.config.freeze_encoders
    assert not any(p.requires_grad for p in loaded.encoders.parameters())
    assert all(p.requires_grad for p in loaded.prior.parameters())
    batch = batch_of(3)
    torch.testing.assert_close(loaded.predict_action_chunk(batch), policy.predict_action_chunk(batch), atol=0, rtol=0)


def test_frozen_encoders_are_left_out_of_the_optimizer(policy):
    n_all = sum(len(g["params"]) for g in policy.get_optim_params())
    policy.set_encoders_frozen(True)
    n_frozen = sum(len(g["params"]) for g in policy.get_optim_params())
    assert n_all - n_frozen == len(policy.parameter_groups()["encoders"])
    policy.train()
    assert not policy.encoders.training and policy.prior.training  # BatchNorm statistics stay put too


def test_padded_chunk_steps_do_not_count():
    pred, target = torch.zeros(1, 4, 2), torch.tensor([[[1.0, 1.0], [3.0, 3.0], [50.0, 50.0], [50.0, 50.0]]])
    is_pad = torch.tensor([[False, False, True, True]])
    assert masked_l1(pred, target, is_pad).item() == pytest.approx(2.0)  # (1 + 3) / 2
    assert masked_l1(pred, target, None).item() == pytest.approx(26.0)  # (1 + 3 + 50 + 50) / 4


def test_entropy_of_a_filtered_distribution_by_hand():
    uniform = filtered_log_probs(torch.zeros(2, 4))
    assert torch.allclose(entropy(uniform), torch.full((2,), math.log(4)))
    # top 2 of logits [ln 3, 0, -5]: probabilities 3/4, 1/4, 0 (the excluded token adds 0, not NaN)
    top2 = filtered_log_probs(torch.tensor([math.log(3.0), 0.0, -5.0]), top_k=2)
    assert entropy(top2).item() == pytest.approx(-(0.75 * math.log(0.75) + 0.25 * math.log(0.25)))


def test_drawn_tokens_follow_the_filtered_distribution():
    """Inverse-CDF draws: frequencies match the top-k probabilities, tokens outside the top k never come, the
    same generator seed gives the same draws, greedy is the argmax."""
    logits = torch.tensor([[2.0, 0.0, 1.0, -1.0, 0.5, 3.0]]).repeat(40_000, 1)
    logp = filtered_log_probs(logits, temperature=1.0, top_k=3)  # keeps tokens 5, 0, 2
    tokens = draw_tokens(logp, generator=torch.Generator().manual_seed(0)).squeeze(1)
    counts = torch.bincount(tokens, minlength=6).float() / len(tokens)
    expected = torch.tensor([2.0, 0.0, 1.0, 0.0, 0.0, 3.0]).exp() * torch.tensor([1.0, 0, 1, 0, 0, 1])
    expected /= expected.sum()  # 0.245, 0, 0.090, 0, 0, 0.665
    assert torch.allclose(counts, expected, atol=0.01), counts
    assert counts[[1, 3, 4]].sum() == 0
    again = draw_tokens(logp, generator=torch.Generator().manual_seed(0)).squeeze(1)
    assert torch.equal(tokens, again)
    assert torch.equal(draw_tokens(logp, greedy=True), torch.full((40_000, 1), 5))


def test_skill_nll_hand_computed():
    logits = torch.log(torch.tensor([[[0.5, 0.25, 0.25], [0.1, 0.8, 0.1]]]))  # one skill of two tokens
    tokens = torch.tensor([[0, 1]])
    expected = -(torch.log(torch.tensor(0.5)) + torch.log(torch.tensor(0.8))) / 2
    torch.testing.assert_close(skill_nll(logits, tokens), expected)
    assert skill_nll(logits, tokens, mask=torch.tensor([False])).item() == 0.0


def test_unknown_task_is_a_clear_error(policy):
    batch = batch_of(2)
    batch["task"] = ["open the door", TASKS[0]]
    with pytest.raises(ValueError, match="unknown task 'open the door'"):
        policy.select_action(batch)


def test_image_shape_differing_from_checkpoint_is_a_clear_error(tmp_path):
    image = {"observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))}
    cfg = tiny_config(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (6,)), **image})
    CSOPolicy(cfg).save_pretrained(tmp_path)
    other = tiny_config(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (6,)),
            "observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, 48, 48)),
        }
    )
    with pytest.raises(ValueError, match=r"'observation.images.cam' has shape \(3, 48, 48\) but the checkpoint"):
        CSOPolicy.from_pretrained(tmp_path, config=other)


def test_image_policy_forward_and_sampling(tmp_path):
    cfg = tiny_config(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (6,)),
            "observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
        }
    )
    policy = CSOPolicy(cfg)
    batch = {**batch_of(2), "observation.images.cam": torch.rand(2, 3, 32, 32), "action": torch.randn(2, 32, 3)}
    loss, info = policy.forward(batch)
    assert info["phase"] == 0 and loss.requires_grad
    assert policy.eval().predict_action_chunk(batch).shape == (2, 32, 3)


def test_decoding_a_prefix_equals_the_prefix_of_the_full_chunk(policy):
    tokens, _ = policy.sample_skills(policy.encode_context(batch_of(3)))
    full = policy.decode_skills(tokens)
    torch.testing.assert_close(policy.decode_skills(tokens, 8), full[:, :8], atol=1e-5, rtol=0)


def test_fit_keeps_the_aspect_by_a_centre_crop_or_a_pad():
    """``image_resize`` fits a non-square frame keeping its aspect (it squashed it to a square): the geometry of a
    640×480 frame at 128, and on small frames, by hand, which pixels a crop keeps and where a pad's border goes."""
    from lerobot_cso.policy.observation_encoder import fit_geometry, fit_images

    assert fit_geometry(480, 640, 128, "crop") == ((128, 171), (128, 128))  # 640 · 128/480 = 170.7
    assert fit_geometry(480, 640, 128, "pad") == ((96, 128), (128, 128))
    assert fit_geometry(480, 480, 128, "crop") == fit_geometry(480, 480, 128, "pad") == ((128, 128), (128, 128))
    assert fit_geometry(64, 48, 128, "crop") == fit_geometry(64, 48, 128, "pad") == ((64, 48), (64, 48))  # fits

    columns = torch.arange(8.0).expand(1, 1, 4, 8)  # a 4×8 frame whose pixels hold their column index
    torch.testing.assert_close(fit_images(columns, 4, "crop"), columns[..., 2:6])  # the middle 4 columns, unscaled
    ones = torch.ones(1, 3, 6, 8)  # 6×8 → ×½ = 3×4, centred in 4×4: a top border of 0 rows, a bottom one of 1
    padded = fit_images(ones, 4, "pad")
    assert padded.shape == (1, 3, 4, 4)
    torch.testing.assert_close(padded[..., :3, :], torch.ones(1, 3, 3, 4))
    torch.testing.assert_close(padded[..., 3:, :], torch.zeros(1, 3, 1, 4))
    cropped = fit_images(ones, 4, "crop")  # 6×8 → ×⅔ = 4×5, centre 4×4
    assert cropped.shape == (1, 3, 4, 4) and torch.allclose(cropped, torch.ones_like(cropped))
    small = torch.rand(1, 3, 3, 4)
    assert fit_images(small, 4, "crop") is small and fit_images(small, 4, "pad") is small  # never enlarged


def test_defaults_fit_a_large_camera_to_128_with_the_backbone_for_the_device():
    """With no image setting a 640×480 camera reaches the encoder at 128² (the conv net on a CPU, QueST's ResNet-18
    stem elsewhere), and the resolved backbone is what config.json holds; explicit settings win."""
    from lerobot_cso.policy.observation_encoder import auto_backbone

    camera = {"observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, 480, 640))}
    cfg = tiny_config(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (6,)), **camera})
    assert (cfg.image_backbone, cfg.image_resize, cfg.image_fit) == ("conv", 128, "crop")
    policy = CSOPolicy(cfg)
    seen = []
    encoder = policy.encoders.images["observation__images__cam"]
    encoder.backbone.register_forward_pre_hook(lambda _, args: seen.append(tuple(args[0].shape)))
    policy.encode_context({**batch_of(2), "observation.images.cam": torch.rand(2, 3, 480, 640)})
    assert seen == [(2, 3, 128, 128)]
    assert auto_backbone("cuda") == auto_backbone("cuda:1") == auto_backbone("mps") == "resnet18"  # the paper's
    explicit = tiny_config(image_backbone="resnet18", image_resize=None)
    assert (explicit.image_backbone, explicit.image_resize) == ("resnet18", None)
    with pytest.raises(ValueError, match="image_resize must be <= 4096"):
        tiny_config(image_resize=100_000)
    with pytest.raises(ValueError, match="image_fit must be one of"):
        tiny_config(image_fit="stretch")


def test_first_training_batch_on_a_cpu_logs_the_encoders_cost_and_keeps_no_gradient(caplog):
    """The first training forward on a CPU logs what the camera encoders cost on that batch and how to make it
    cheaper, without leaving gradients or moving the random state."""
    camera = {"observation.images.cam": PolicyFeature(FeatureType.VISUAL, (3, 32, 32))}
    cfg = tiny_config(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (6,)), **camera})
    policy = CSOPolicy(cfg).train()
    batch = {**batch_of(2), "observation.images.cam": torch.rand(2, 3, 32, 32), "action": torch.randn(2, 32, 3)}
    torch.manual_seed(5)
    with caplog.at_level("INFO"):
        policy.forward(batch)
    after = torch.rand(1)
    torch.manual_seed(5)
    policy.forward(batch)
    assert torch.equal(torch.rand(1), after)  # the measurement drew nothing from the random state
    [line] = [r.getMessage() for r in caplog.records if "cso policy on a CPU" in r.getMessage()]
    assert "(conv; observation.images.cam 32×32) took" in line and "batch of 2" in line, line
    assert "cheaper: a GPU" in line  # conv at 32²: nothing cheaper to suggest but the device
    assert all(p.grad is None for p in policy.parameters())
