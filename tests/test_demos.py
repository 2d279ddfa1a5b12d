"""``lerobot-cso demos``: the LeRobotDataset it writes, determinism, dropping failures, topping up, resuming a
killed run, and bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from metaworld_fixtures import DEMO_EPISODES, DEMO_TASKS, make_demos, shared_demos

from lerobot_cso import cli, seeds
from lerobot_cso.demos import DemosConfig
from lerobot_cso.errors import UsageError
from lerobot_cso.worlds.metaworld.tasks import task_description
from lerobot_cso.worlds.robot.config import RobotWorldConfig


@pytest.fixture(scope="module")
def demos(tmp_path_factory) -> Path:
    return shared_demos(tmp_path_factory)


def load(root: Path) -> LeRobotDataset:
    return LeRobotDataset("local/metaworld_demos", root=root, video_backend="pyav")


def columns(root: Path) -> dict[str, np.ndarray]:
    return load(root).hf_dataset.with_format("numpy")[:]


def episodes(root: Path) -> list[tuple[str, int, bool, int]]:
    """(task, init_seed, success, length) per episode, in episode order."""
    data = columns(root)
    out = []
    for e in np.unique(data["episode_index"]):
        rows = np.flatnonzero(data["episode_index"] == e)
        out.append(
            (
                str(data["metaworld.task"][rows[0]]),
                int(data["metaworld.init_seed"][rows[0]]),
                bool(data["metaworld.success"][rows[0]]),
                len(rows),
            )
        )
    return out


def assert_same_data(a: Path, b: Path) -> None:
    ca, cb = columns(a), columns(b)
    assert ca.keys() == cb.keys()
    for key in ca:
        np.testing.assert_array_equal(ca[key], cb[key], err_msg=key)


def test_dataset_loads_with_declared_features(demos):
    ds = load(demos)
    assert ds.fps == 80 and ds.num_episodes == 2 * DEMO_EPISODES
    features = ds.meta.features
    assert features["observation.state"]["dtype"] == "float32" and tuple(features["observation.state"]["shape"]) == (
        39,
    )
    assert features["action"]["dtype"] == "float32" and tuple(features["action"]["shape"]) == (4,)
    assert features["metaworld.task"]["dtype"] == "string"
    assert features["metaworld.init_seed"]["dtype"] == "int64" and features["metaworld.success"]["dtype"] == "bool"
    item = ds[3]
    assert item["observation.state"].shape == (39,) and item["action"].shape == (4,)
    assert item["task"] == task_description(item["metaworld.task"])
    assert set(ds.meta.tasks.index) == {task_description(t) for t in DEMO_TASKS.split(",")}
    eps = episodes(demos)
    assert [(t, s) for t, s, _, _ in eps] == [(t, s) for t in DEMO_TASKS.split(",") for s in range(DEMO_EPISODES)]
    assert all(s in seeds.DEMO for _, s, _, _ in eps)
    assert [n for *_, n in eps] == list(ds.meta.episodes["length"])
    data = columns(demos)
    assert np.abs(data["action"]).max() <= 1.0


def test_camera_frames_are_stored_as_128px_images(tmp_path):
    make_demos(tmp_path / "cam", "reach-v3", 1, cameras="corner2", max_steps=6)
    ds = load(tmp_path / "cam")
    feature = ds.meta.features["observation.images.corner2"]
    assert feature["dtype"] == "image" and tuple(feature["shape"]) == (128, 128, 3)
    first, last = ds[0]["observation.images.corner2"], ds[5]["observation.images.corner2"]
    assert first.shape == (3, 128, 128) and 0.0 <= float(first.min()) and float(first.max()) <= 1.0
    assert not first.equal(last)


def test_scripted_experts_succeed_on_two_tasks(demos):
    eps = episodes(demos)
    for task in DEMO_TASKS.split(","):
        outcomes = [ok for t, _, ok, _ in eps if t == task]
        assert np.mean(outcomes) >= 0.9, (task, outcomes)
    successful = [n for _, _, ok, n in eps if ok]
    assert max(successful) < 500  # episodes stop at the first success


def test_same_seed_gives_the_same_data_whatever_the_env_count(demos, tmp_path):
    make_demos(tmp_path / "again", DEMO_TASKS, DEMO_EPISODES, num_envs=1)
    assert_same_data(demos, tmp_path / "again")
    make_demos(tmp_path / "other", "reach-v3", 2, seed=1)
    first_two = columns(demos)["action"][columns(demos)["episode_index"] < 2]
    assert not np.array_equal(columns(tmp_path / "other")["action"][: len(first_two)], first_two)


def test_dropping_failed_episodes_tries_further_seeds(tmp_path):
    # 40 steps is too short for most noisy reach-v3 episodes
    make_demos(tmp_path / "all", "reach-v3", 2, max_steps=40)
    make_demos(tmp_path / "ok", "reach-v3", 2, max_steps=40, keep_failed=False)
    kept = episodes(tmp_path / "all")
    assert [s for _, s, _, _ in kept] == [0, 1] and not all(ok for _, _, ok, _ in kept)
    dropped = episodes(tmp_path / "ok")
    assert len(dropped) == 2 and all(ok for _, _, ok, _ in dropped) and max(s for _, s, _, _ in dropped) > 1


def test_top_up_appends_the_missing_episodes_only(tmp_path):
    root = tmp_path / "ds"
    make_demos(root, "reach-v3", 2)
    before = columns(root)
    summary = make_demos(root, "reach-v3,button-press-v3", 3)
    assert summary["new_episodes"] == 4
    assert [(t, s) for t, s, _, _ in episodes(root)] == [("reach-v3", 0), ("reach-v3", 1)] + [
        ("reach-v3", 2),
        ("button-press-v3", 0),
        ("button-press-v3", 1),
        ("button-press-v3", 2),
    ]
    after = columns(root)
    n = len(before["action"])
    np.testing.assert_array_equal(after["action"][:n], before["action"])
    assert make_demos(root, "reach-v3,button-press-v3", 3)["new_episodes"] == 0
    assert not root.with_name("ds.partial").exists()


def test_killed_generation_resumes_to_the_same_dataset(demos, tmp_path):
    root = tmp_path / "killed"
    staged = tmp_path / "killed.partial" / "episodes"
    args = [f"--tasks={DEMO_TASKS}", f"--episodes_per_task={DEMO_EPISODES}", f"--output_dir={root}", "--num_envs=1"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "lerobot_cso.cli", "demos", *args], env=env, stderr=subprocess.DEVNULL
    )
    deadline = time.time() + 120
    while len(list(staged.glob("*/*.npz"))) < 3:
        assert proc.poll() is None and time.time() < deadline, "generation ended before it could be killed"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not root.exists()
    done_before = len(list(staged.glob("*/*.npz")))
    assert 3 <= done_before < 2 * DEMO_EPISODES
    summary = make_demos(root, DEMO_TASKS, DEMO_EPISODES, num_envs=1)
    assert summary["total_episodes"] == 2 * DEMO_EPISODES and summary["new_episodes"] == 2 * DEMO_EPISODES
    pairs = [(t, s) for t, s, _, _ in episodes(root)]
    assert len(set(pairs)) == len(pairs) == 2 * DEMO_EPISODES
    assert_same_data(demos, root)


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    code = cli.main(args)
    err = capsys.readouterr().err.strip().splitlines()
    return code, err[-1] if err else ""


def test_bad_input_is_one_clear_error_and_writes_nothing(demos, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    out = tmp_path / "new"
    code, err = run_cli(["demos", "--tasks=reach-v3,open-sesame-v3", f"--output_dir={out}"], capsys)
    assert code == 2 and err.startswith("error: unknown MetaWorld task 'open-sesame-v3'") and "reach-v3" in err
    code, err = run_cli(["demos", "--episodes_per_task=0", f"--output_dir={out}"], capsys)
    assert code == 2 and "episodes_per_task must be > 0" in err
    assert not out.exists() and not tmp_path.joinpath("new.partial").exists()

    stamp = {p: p.stat().st_mtime_ns for p in demos.rglob("*")}
    code, err = run_cli(["demos", f"--tasks={DEMO_TASKS}", "--noise_std=0.1", f"--output_dir={demos}"], capsys)
    assert code == 2 and "holds a different dataset" in err and "noise_std" in err
    assert {p: p.stat().st_mtime_ns for p in demos.rglob("*")} == stamp
    assert not demos.with_name(demos.name + ".partial").exists()

    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("not a dataset")
    code, err = run_cli(["demos", "--tasks=reach-v3", f"--output_dir={other}"], capsys)
    assert code == 2 and "is not a demo dataset" in err

    code, err = run_cli(["demoz"], capsys)
    assert code == 2 and err == "error: unknown subcommand 'demoz'; choose one of: " + ", ".join(cli.SUBCOMMANDS)


def test_a_given_dataset_is_checked_and_left_as_it_is(demos, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    stamp = {p: p.stat().st_mtime_ns for p in demos.rglob("*")}
    assert cli.main(["demos", f"--tasks={DEMO_TASKS}", f"--dataset_root={demos}"]) == 0
    frames = len(columns(demos)["index"])
    assert capsys.readouterr().out.strip() == f"{demos}: 10 episodes, {frames} frames; usable for --tasks={DEMO_TASKS}"
    code, err = run_cli(["demos", "--tasks=drawer-close-v3,reach-v3", f"--dataset_root={demos}"], capsys)
    assert code == 2 and err.startswith(f"error: {demos} has no episodes of drawer-close-v3 (by task description)")
    assert {p: p.stat().st_mtime_ns for p in demos.rglob("*")} == stamp


def test_the_demo_expert_is_the_worlds(tmp_path):
    """``--world.type`` picks the expert (its defaults fill the settings left unset); a world without one is one line
    naming the way out, before the world is built (the robot world would first ask for a robot)."""
    metaworld = DemosConfig(tasks="reach-v3", output_dir=tmp_path / "mw").resolved()
    assert (metaworld.noise_std, metaworld.image_size, metaworld.max_steps) == (0.2, 128, 500)
    libero = DemosConfig(tasks="libero_object-0", output_dir=tmp_path / "libero").resolved()
    assert (libero.noise_std, libero.image_size, libero.max_steps) == (0.05, 128, 280)
    with pytest.raises(UsageError, match="^robot has no scripted expert to generate demos: give a LeRobotDataset"):
        DemosConfig(world=RobotWorldConfig(), tasks="press", output_dir=tmp_path / "robot").validate()


def test_the_lerobot_format_fills_in_lerobots_settings_and_refuses_others_in_one_line(tmp_path, capsys, monkeypatch):
    """``--format=lerobot`` takes LeRobot's camera, image size and state when they are not given, and makes a spec of
    its own (a dataset of the other format is never reused), while a cso spec stays as before the setting; another
    camera or state, a world without LeRobot's MetaWorld format, a size its video encoder cannot take and an
    unknown format are each one error line."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    out = tmp_path / "ds"
    lerobot = DemosConfig(format="lerobot", tasks="reach-v3", output_dir=out)
    filled = lerobot.resolved()
    assert (filled.cameras, filled.image_size, filled.state) == ("corner2", 480, "hand")
    assert DemosConfig(tasks="reach-v3", output_dir=out).resolved().state == "full"
    cso = DemosConfig(tasks="reach-v3", cameras="corner2", image_size=480, state="hand", output_dir=out).spec()
    assert "format" not in cso and lerobot.spec() == cso | {"format": "lerobot"}
    no_format = "libero has none: use --format=cso"
    refused = [
        ("--cameras=corner", "--format=lerobot holds one camera, LeRobot's corner2; got --cameras=corner"),
        ("--state=full", "--format=lerobot holds the hand state; got --state=full"),
        ("--image_size=16", "image_size must be in [32, 512], got 16"),
        ("--tasks=libero_object-0", f"--format=lerobot is LeRobot's MetaWorld format; {no_format}"),
    ]
    for arg, message in refused:
        code, err = run_cli(["demos", "--format=lerobot", "--tasks=reach-v3", f"--output_dir={out}", arg], capsys)
        assert (code, err) == (2, f"error: {message}")
    code, err = run_cli(["demos", "--format=hub", "--tasks=reach-v3", f"--output_dir={out}"], capsys)
    assert (code, err) == (2, "error: format must be one of cso, lerobot, got 'hub'")
    assert not out.exists()
