"""``benchmarks/twin_dev_scenes.py`` on hand-made evaluation journals: the paired differences it stores, the scene
agreement it counts, and a bad folder refused without touching the results file."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "twin_dev_scenes.py"


def journal(folder: Path, outcomes: list[int]) -> Path:
    """An evaluation's robot journal as ``lerobot-cso eval`` leaves it: one npz per trial (``state_attempt``)."""
    episodes = folder / "robot_journal" / "episodes" / "put_the_cube_in_the_bowl"
    episodes.mkdir(parents=True)
    for state, ok in enumerate(outcomes):
        np.savez(episodes / f"{state:07d}_001.npz", success=np.array(bool(ok)), length=np.array(200 - 100 * ok))
    return folder


def run(results: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), f"--results={results}", *args], capture_output=True, text=True, cwd=ROOT
    )


def test_add_pairs_trials_by_scene_and_agreement_counts_scenes_by_checkpoints_solving_them(tmp_path):
    a = [1] * 30 + [0] * 70  # 30 %
    b = [1] * 20 + [0] * 10 + [1] * 10 + [0] * 60  # 30 %: 20 scenes shared with a, 10 won by each alone
    results = tmp_path / "dev.json"
    first = {f"{s:07d}_001": ok for s, ok in enumerate(a)}
    results.write_text(
        json.dumps({"checkpoints": {"a": {"outcomes": first}}, "paired": {}, "greedy": {"checkpoints": {}}})
    )
    out = run(results, "add", "--name=b", f"--eval={journal(tmp_path / 'b', b)}", "--checkpoint=b's")
    assert out.returncode == 0, out.stderr
    stored = json.loads(results.read_text())
    assert stored["checkpoints"]["b"]["successes"] == 30 and stored["checkpoints"]["b"]["checkpoint"] == "b's"
    pair = stored["paired"]["b_minus_a"]
    # differences: +1 on 10 trials, -1 on 10, 0 on 80 -> mean 0, sd sqrt(20/99), half-width 1.96 sd / 10
    half = 1.96 * np.sqrt(20 / 99) / 10
    assert (pair["won"], pair["lost"], pair["trials"]) == (10, 10, 100)
    assert pair["mean"] == 0.0 and np.allclose(pair["ci95"], [-half, half])

    greedy = [1] * 10 + [0] * 90  # won the first 10 scenes, which a and b both solved
    out = run(
        results, "add", "--name=g", f"--eval={journal(tmp_path / 'g', greedy)}", "--checkpoint=g", "--section=greedy"
    )
    assert out.returncode == 0, out.stderr
    out = run(results, "agreement", "--names=a,b")
    assert out.returncode == 0, out.stderr
    stored = json.loads(results.read_text())
    # solved by both: 20; by one: 10 + 10; by none: 60
    assert stored["scene_agreement"]["scenes_solved_by_k"] == [60, 20, 20]
    assert np.allclose(stored["scene_agreement"]["expected_if_independent"], [49, 42, 9], atol=0.5)  # 100 p^k q^(2-k)
    # a: 10 / 10 where g won, 20 / 90 where it lost
    assert np.allclose(stored["greedy"]["checkpoints"]["g"]["sampled_rate_where_greedy_won_lost"]["a"], [1.0, 20 / 90])


def test_a_folder_without_a_full_evaluation_is_refused_and_the_file_kept(tmp_path):
    results = tmp_path / "dev.json"
    results.write_text(json.dumps({"checkpoints": {}, "paired": {}, "greedy": {"checkpoints": {}}}))
    before = results.read_bytes()
    out = run(results, "add", "--name=x", f"--eval={journal(tmp_path / 'x', [1] * 40)}", "--checkpoint=x")
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"twin_dev_scenes: ValueError: {tmp_path / 'x'} holds 40 finished trials, not 100"
    ]
    assert results.read_bytes() == before


def test_a_failed_trial_is_sorted_by_what_its_gripper_did(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("twin_dev_scenes", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)

    def trial(commanded: list[float], measured: list[float]) -> tuple[np.ndarray, np.ndarray]:
        actions, states = np.zeros((len(commanded), 7)), np.zeros((len(measured), 7))
        actions[:, 6], states[:, 6] = commanded, measured
        return actions, states

    bowl = np.array([0.3, 0.1])
    at = {"bowl": lambda q: np.array([0.3, 0.15, 0.1]), "table": lambda q: np.array([0.3, -0.1, 0.03])}
    open_, shut = [0.06] * 5, [0.0] * 15
    assert module.failure_mode(*trial(open_ * 4, open_ * 4), bowl, at["table"]) == "never closed"
    empty = trial(open_ + shut + open_ + shut, [0.06] * 5 + [0.0] * 15 + [0.06] * 5 + [0.0] * 15)
    assert module.failure_mode(*empty, bowl, at["table"]) == "only closes on nothing"
    held = trial(open_ + shut + open_, [0.06] * 5 + [0.03] * 20)  # the fingers stop on the cube (3 cm)
    assert module.failure_mode(*held, bowl, at["table"]) == "held the cube, opened away from the bowl below 6 cm"
    assert module.failure_mode(*held, bowl, at["bowl"]) == "held the cube, opened within 10 cm of the bowl"
    to_the_end = trial(open_ + shut, [0.06] * 5 + [0.03] * 15)
    assert module.failure_mode(*to_the_end, bowl, at["table"]) == "held the cube to the end"


def test_sort_places_each_trial_in_its_own_scene_and_files_nothing(tmp_path):
    """``sort --scene-seed``: a cube held and let go above the bowl of held-out scene 100000 + 1 is sorted as opened
    by the bowl only against that scene (its bowl lies > 10 cm from the development scene 300001's)."""
    from piper_twin.ik import ArmIK, down_rotation
    from piper_twin.plant import TwinPlant

    plant = TwinPlant("cube_in_bowl", 0)
    ik = ArmIK(plant.model)

    def bowl(seed: int) -> np.ndarray:
        plant.reset(seed)
        return plant.data.mocap_pos[plant.model.body("bowl").mocapid[0]].copy()

    held_out, development = bowl(100001), bowl(300001)
    assert np.linalg.norm(held_out[:2] - development[:2]) > 0.1
    above = held_out + [0.0, 0.0, 0.15]
    joints, error = ik.solve(np.zeros(6), above, down_rotation(above, 0.0))
    assert error < 1e-3
    actions, states = np.zeros((30, 7)), np.zeros((30, 7))
    actions[:, :6] = states[:, :6] = joints
    actions[:, 6] = [0.06] * 5 + [0.0] * 20 + [0.06] * 5  # close, hold, reopen above the bowl
    states[:, 6] = [0.06] * 5 + [0.03] * 25  # the fingers stopped on the cube
    episodes = tmp_path / "eval" / "robot_journal" / "episodes" / "put_the_cube_in_the_bowl"
    episodes.mkdir(parents=True)
    np.savez(episodes / "0000000_001.npz", success=np.array(True), actions=actions, states=states)
    np.savez(episodes / "0000001_001.npz", success=np.array(False), actions=actions, states=states)
    results = tmp_path / "dev.json"
    results.write_text("{}")
    modes = {100000: "held the cube, opened within 10 cm of the bowl", 300000: "held the cube, opened away"}
    for seed, mode in modes.items():
        out = run(results, "sort", f"--eval={tmp_path / 'eval'}", f"--scene-seed={seed}")
        assert out.returncode == 0, out.stderr
        assert out.stdout.startswith(f"{tmp_path / 'eval'}: 1 failed: {mode}"), out.stdout
    assert results.read_text() == "{}"
