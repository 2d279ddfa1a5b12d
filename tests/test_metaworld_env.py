"""The MetaWorld env: replayable seeded initial states, task switching, episode ends, cameras, task sets, seeds,
and the ``cso_metaworld`` LeRobot env config."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from lerobot.envs.factory import make_env_config
from lerobot.envs.utils import close_envs, preprocess_observation

import lerobot_policy_cso  # noqa: F401  (registers cso_metaworld)
from lerobot_cso import seeds
from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv
from lerobot_cso.worlds.metaworld.tasks import all_tasks, resolve_tasks, task_description, task_sets


def trajectory(env: CSOMetaWorldEnv, task: str, seed: int, steps: int = 25) -> np.ndarray:
    obs, _ = env.reset(seed=seed, options={"task": task})
    rng = np.random.default_rng(123)
    states = [obs["agent_pos"]]
    for _ in range(steps):
        obs, *_ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        states.append(obs["agent_pos"])
    return np.stack(states)


def test_seeded_initial_state_replays_exactly_whatever_ran_before():
    env, fresh = CSOMetaWorldEnv("pick-place-v3"), CSOMetaWorldEnv("reach-v3")
    first = trajectory(env, "pick-place-v3", 7)
    trajectory(env, "pick-place-v3", 3)
    trajectory(env, "reach-v3", 7)  # another task in between
    again = trajectory(env, "pick-place-v3", 7)
    other_env = trajectory(fresh, "pick-place-v3", 7)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(first, other_env)
    assert first.dtype == np.float32 and first.shape == (26, 39)
    different = trajectory(env, "pick-place-v3", 8)
    assert not np.allclose(first[0], different[0])  # another seed places the puck/goal elsewhere
    env.close()
    fresh.close()


def test_task_switch_on_reset_and_goal_in_observation():
    env = CSOMetaWorldEnv("reach-v3")
    env.reset(seed=0, options={"task": "button-press-v3"})
    assert env.task == "button-press-v3" and env.task_description == "Press a button"
    obs, _ = env.reset(seed=0)  # keeps the task
    assert env.task == "button-press-v3"
    np.testing.assert_allclose(obs["agent_pos"][-3:], env.sim._target_pos, atol=1e-6)
    env.close()


def test_episode_ends_at_success_or_horizon():
    env = CSOMetaWorldEnv("reach-v3", max_episode_steps=200)
    obs, _ = env.reset(seed=0)
    from metaworld.policies import ENV_POLICY_MAP  # after lerobot_cso, which selects headless rendering

    expert = ENV_POLICY_MAP["reach-v3"]()
    steps = 0
    terminated = truncated = False
    while not (terminated or truncated):
        obs, _, terminated, truncated, info = env.step(expert.get_action(obs["agent_pos"]))
        steps += 1
    assert terminated and not truncated and info["is_success"] and steps < 200
    short = CSOMetaWorldEnv("reach-v3", max_episode_steps=5)
    short.reset(seed=0)
    ends = [short.step(np.zeros(4, np.float32))[2:4] for _ in range(5)]
    assert ends[:4] == [(False, False)] * 4 and ends[4] == (False, True)
    env.close()
    short.close()


def test_parked_env_does_not_move():
    env = CSOMetaWorldEnv("reach-v3")
    obs, _ = env.reset(seed=1)
    parked, _ = env.reset(options={"park": True})
    stepped, reward, terminated, truncated, _ = env.step(np.ones(4, np.float32))
    np.testing.assert_array_equal(parked["agent_pos"], obs["agent_pos"])
    np.testing.assert_array_equal(stepped["agent_pos"], obs["agent_pos"])
    assert (reward, terminated, truncated) == (0.0, False, False)
    env.close()


def test_camera_images_are_128_uint8_and_change_with_the_state():
    env = CSOMetaWorldEnv("reach-v3", cameras=("corner2",))
    first, _ = env.reset(seed=0)
    image = first["pixels"]["corner2"]
    assert image.shape == (128, 128, 3) and image.dtype == np.uint8 and image.std() > 10
    batch = preprocess_observation({"agent_pos": first["agent_pos"][None], "pixels": {"corner2": image[None]}})
    assert batch["observation.images.corner2"].shape == (1, 3, 128, 128)
    for _ in range(10):
        later, *_ = env.step(np.array([1.0, 0.0, 0.0, 0.0], np.float32))
    assert np.abs(later["pixels"]["corner2"].astype(int) - image).sum() > 0
    assert env.render().shape == (128, 128, 3)
    env.close()


def test_task_sets_and_descriptions():
    sets = task_sets()
    assert len(sets["MT10"]) == 10 and len(sets["MT50"]) == 50 and len(sets["ML45-train"]) == 45
    assert not set(sets["ML45-train"]) & set(sets["ML45-test"])
    assert "bin-picking-v3" in sets["ML45-test"] and "pick-place-v3" in sets["ML45-train"]
    from metaworld.policies import ENV_POLICY_MAP

    assert set(all_tasks()) <= set(ENV_POLICY_MAP)  # a scripted expert for every task
    assert len({task_description(t) for t in all_tasks()}) == 50  # push-v3 / push-back-v3 told apart
    assert resolve_tasks("reach-v3, MT10") == ["reach-v3", *[t for t in sets["MT10"] if t != "reach-v3"]]
    with pytest.raises(ValueError, match="unknown MetaWorld task 'reach-v2'.*valid tasks: assembly-v3"):
        resolve_tasks("reach-v2")


def test_seed_ranges_are_disjoint_per_purpose():
    assert not set(seeds.DEMO) & set(seeds.TRAIN) and not set(seeds.TRAIN) & set(seeds.EVAL)
    assert not set(seeds.DEMO) & set(seeds.EVAL)
    demo, train = seeds.demo_seeds(100), seeds.train_seeds(100)
    eval0, eval1 = seeds.eval_seeds(50, 0), seeds.eval_seeds(50, 1)
    assert all(s in seeds.DEMO for s in demo) and all(s in seeds.TRAIN for s in train)
    assert all(s in seeds.EVAL for s in eval0 + eval1) and not set(eval0) & set(eval1)
    with pytest.raises(ValueError):
        seeds.demo_seeds(10, start=len(seeds.DEMO) - 5)
    with pytest.raises(ValueError):
        seeds.eval_seeds(seeds.EVAL_BLOCK + 1)


def test_env_config_features_and_one_vector_env_per_task():
    cfg = make_env_config("cso_metaworld", task="reach-v3,button-press-v3", cameras="corner2", episode_length=50)
    assert cfg.features["agent_pos"].shape == (39,) and cfg.features["pixels/corner2"].shape == (128, 128, 3)
    assert cfg.features_map == {
        "action": "action",
        "agent_pos": "observation.state",
        "pixels/corner2": "observation.images.corner2",
    }
    envs = cfg.create_envs(n_envs=2)
    assert list(envs) == ["reach-v3", "button-press-v3"]
    vec = envs["button-press-v3"][0]
    obs, _ = vec.reset(seed=[0, 1])
    assert obs["agent_pos"].shape == (2, 39) and obs["pixels"]["corner2"].shape == (2, 128, 128, 3)
    assert vec.call("task_description") == ("Press a button",) * 2 and vec.call("_max_episode_steps") == (50, 50)
    # LeRobot's small seeds land in the evaluation range
    direct = CSOMetaWorldEnv("button-press-v3")
    np.testing.assert_array_equal(direct.reset(seed=seeds.EVAL.start + 1)[0]["agent_pos"], obs["agent_pos"][1])
    close_envs(envs)
    direct.close()


def test_plugin_import_is_light():
    code = "import sys, lerobot_policy_cso; assert 'metaworld' not in sys.modules and 'mujoco' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_state_layouts_are_the_full_states_parts():
    """proprio = QueST's hand xyz + gripper now and one frame before (obs[0:4] ++ obs[18:22]); hand = obs[0:4]."""
    full = trajectory(CSOMetaWorldEnv("button-press-v3"), "button-press-v3", 5, steps=3)
    for state, columns in (("proprio", [0, 1, 2, 3, 18, 19, 20, 21]), ("hand", [0, 1, 2, 3])):
        env = CSOMetaWorldEnv("button-press-v3", state=state)
        part = trajectory(env, "button-press-v3", 5, steps=3)
        np.testing.assert_array_equal(part, full[:, columns])
        assert env.observation_space["agent_pos"].shape == (len(columns),)
    np.testing.assert_array_equal(full[1:, 18:22], full[:-1, 0:4])  # the previous frame, as QueST reads it
    with pytest.raises(ValueError, match="unknown state layout"):
        CSOMetaWorldEnv("reach-v3", state="object")


def test_render_every_renders_only_decision_frames_and_the_first_frame_is_framed():
    env = CSOMetaWorldEnv("drawer-close-v3", cameras=("corner2",), image_size=32, state="proprio")
    framed = CSOMetaWorldEnv("drawer-close-v3", cameras=("corner2",), image_size=32)
    framed.reset(seed=2)  # a second reset: the camera pose is surely current
    second, _ = framed.reset(seed=3)
    first, _ = env.reset(seed=3, options={"render_every": 4})
    np.testing.assert_array_equal(first["pixels"]["corner2"], second["pixels"]["corner2"])  # the first frame too
    frames = [first["pixels"]["corner2"]]
    for _ in range(8):
        obs, *_ = env.step(np.array([0.0, 1.0, 0.0, 0.0], np.float32))
        frames.append(obs["pixels"]["corner2"])
    assert all(frames[t] is frames[t - t % 4] for t in range(9))  # steps 1-3 and 5-7 repeat the decision frame
    assert not np.array_equal(frames[0], frames[4]) and not np.array_equal(frames[4], frames[8])  # the hand moved


def test_envs_of_a_task_share_one_renderer_and_render_what_their_own_would():
    """One renderer per task and size in a process (an EGL context each); an env rendering through the renderer built
    from another env's model sees exactly what a renderer of its own model shows."""
    import mujoco

    first = CSOMetaWorldEnv("button-press-v3", cameras=("corner2",), image_size=32, state="proprio")
    other = CSOMetaWorldEnv("button-press-v3", cameras=("corner2",), image_size=32, state="proprio")
    first.reset(seed=1)
    shared, _ = other.reset(seed=7)  # another placement of the button box
    model = other.sim.model
    model.vis.quality.offsamples, model.vis.quality.shadowsize = 0, 0  # as the env's renderer (no multisampling)
    model.vis.global_.offwidth = model.vis.global_.offheight = 32
    own = mujoco.Renderer(model, 32, 32)
    own.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    own.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    own.update_scene(other.sim.data, camera="corner2")
    np.testing.assert_array_equal(shared["pixels"]["corner2"], own.render()[::-1, ::-1])
    assert not np.array_equal(shared["pixels"]["corner2"], first.reset(seed=1)[0]["pixels"]["corner2"])
    own.close()
    from lerobot_cso.worlds.metaworld import env as metaworld_env

    assert metaworld_env._renderer("button-press-v3", 32, other.sim.model) is metaworld_env._renderer(
        "button-press-v3", 32, first.sim.model
    )
