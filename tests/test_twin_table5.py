"""``benchmarks/twin_table5.py`` without running anything: its seeds, the commands of every part, the results file
(skip, refuse other settings) and the summary it writes (per-task SR, CSO - IL, the operator budget)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def t5():
    """``benchmarks/twin_table5.py`` as a module, its folder on ``sys.path`` as when it runs (for ``harness``)."""
    with benchmark_module("twin_table5") as module:
        yield module


def test_the_seeds_of_demos_training_and_evaluation_must_not_overlap(t5, capsys):
    args = t5.parse_args([])
    ranges = t5.seed_ranges(args)
    assert ranges["eval"] == range(100000, 100020)
    assert ranges["demos"].stop <= ranges["train"].start and ranges["train"].stop <= ranges["eval"].start
    with pytest.raises(SystemExit):
        t5.parse_args(["--eval-seed=5010"])  # inside R-SFT's / SPO's scenes
    assert "overlap the eval seeds" in capsys.readouterr().err


def test_each_robot_stage_runs_on_the_in_process_twin_with_its_own_seeds(t5, tmp_path):
    args = t5.parse_args(["--trials=7"])
    paths = {p: tmp_path / p for p in ("il_policy", "rsft_policy", "spo_policy", "rsft", "spo", *t5.EVALS)}
    evaluation = t5.stage_command(args, "cube_in_bowl", "eval_cso", paths)
    assert evaluation[1:3] == ["eval", f"--policy.path={tmp_path / 'spo_policy'}"]
    assert "--robot.type=piper_twin_sim" in evaluation and "--operator.type=twin" in evaluation
    assert "--operator.scene_seed=100000" in evaluation and "--episodes_per_task=7" in evaluation
    assert "--operator.episode_time_s=20" in evaluation and "--tasks=put the cube in the bowl" in evaluation
    rsft = t5.stage_command(args, "press_button", "rsft", paths)
    assert "--operator.scene_seed=5000" in rsft and "--successes_per_task=20" in rsft and "--n_strikes=4" in rsft
    spo = t5.stage_command(args, "press_button", "spo", paths)
    assert f"--policy.path={tmp_path / 'rsft_policy'}" in spo and "--group_size=4" in spo
    il = t5.il_command(args, "press_button", {"il": tmp_path / "il", "demos": tmp_path / "demos"})
    assert il[1:4] == ["-m", "lerobot_cso.train", "--policy.type=cso"] and "--steps=4000" in il


def part(sr: float | None = None, episodes: int = 20, person_s: float = 600.0) -> dict:
    record = {
        "wall_s": 10.0,
        "operator": {"episodes": episodes, "discarded": 0, "episode_s": 1.0, "person_s": person_s},
    }
    return record if sr is None else record | {"success_rate": sr}


def test_the_summary_gives_cso_minus_il_per_task_and_on_the_mean_of_finished_tasks(t5):
    results = {"tasks": {}}
    parts = {"demos": part(), "il": part(episodes=0, person_s=0), "eval_il": part(0.3), "rsft": part()}
    results["tasks"]["press_button"] = {"parts": parts | {"eval_rsft": part(0.5), "spo": part(), "eval_cso": part(0.6)}}
    results["tasks"]["cube_in_bowl"] = {"parts": {"demos": part(), "eval_il": part(0.1)}}  # unfinished
    t5.summarize(results)
    press = results["tasks"]["press_button"]
    assert press["sr"] == {"il": 0.3, "rsft": 0.5, "cso": 0.6} and press["cso_minus_il"] == pytest.approx(0.3)
    assert press["wall_s"] == 70.0 and press["operator"]["hours"]["spo"] == pytest.approx(600 / 3600)
    assert results["mean"]["tasks"] == ["press_button"] and results["mean"]["cso_minus_il"] == pytest.approx(0.3)


def test_the_operator_cost_adds_the_rest_move_and_the_arranging_per_episode(t5):
    args = t5.parse_args(["--arrange-s=10", "--rest-time-s=3"])
    cost = t5.operator_cost(args, [4.0, 6.0], extra_s=9.0, extra_n=1)
    assert cost == {"episodes": 2, "discarded": 1, "episode_s": 19.0, "person_s": 19.0 + 3 * 13.0}


def test_a_results_file_of_other_settings_is_refused_and_a_rerun_skips_finished_parts(t5, tmp_path, capsys):
    path = tmp_path / "results.json"
    args = t5.parse_args(["--demos=3"])
    results = t5.load_results(path, t5.config_of(args), "python benchmarks/twin_table5.py --demos=3")
    results["tasks"]["press_button"] = {"parts": {p: part(0.5) for p in t5.PARTS}}
    t5.save_results(path, results)
    with pytest.raises(SystemExit, match="other settings"):
        t5.load_results(path, t5.config_of(t5.parse_args(["--demos=4"])), "x")
    runtime = t5.parse_args(["--demos=3", "--threads=1", f"--work={tmp_path}"])  # where and how fast: same config
    assert t5.load_results(path, t5.config_of(runtime), "y")["command"].endswith("; y")
    t5.main(["--demos=3", "--tasks=press_button", f"--results={path}", f"--work={tmp_path}"])
    assert capsys.readouterr().out.count("done, skipped") == len(t5.PARTS)
    assert json.loads(path.read_text())["mean"]["cso_minus_il"] == 0.0


def test_the_policy_flags_reach_the_il_command_and_the_policy_entry_of_the_config(t5, tmp_path):
    default = t5.config_of(t5.parse_args([]))
    assert default["policy"] == t5.POLICY and "ae_dim" not in default  # older results files stay valid
    args = t5.parse_args(["--ae-dim=192", "--image-shift=0"])
    assert t5.config_of(args)["policy"] == t5.POLICY | {"ae_dim": 192, "image_shift": 0}
    paths = {"il": tmp_path / "il", "demos": tmp_path / "demos"}
    command = t5.il_command(args, "cube_in_bowl", paths)
    assert "--policy.ae_dim=192" in command and "--policy.image_shift=0" in command
    assert "--policy.ae_dim=96" not in command
    for bad in ("--ae-dim=0", "--ae-dim=97", "--image-shift=-1"):
        with pytest.raises(SystemExit):
            t5.parse_args([bad])


def test_the_spo_flags_reach_the_spo_command_and_the_config_only_when_set(t5, tmp_path, capsys):
    paths = {"rsft_policy": tmp_path / "rsft_policy", "spo": tmp_path / "spo"}
    default = t5.parse_args([])
    assert not t5.OPTIONAL.keys() & t5.config_of(default).keys()  # older results files stay valid
    spo_default = t5.stage_command(default, "press_button", "spo", paths)
    assert not [a for a in spo_default if "clip" in a or "pool" in a or "trajectory_mean" in a]
    flags = ["--spo-clip=0.8,1.2", "--spo-state-pool=32", "--spo-skip-uniform-for=3", "--spo-trajectory-mean"]
    args = t5.parse_args(flags)
    spo = t5.stage_command(args, "press_button", "spo", paths)
    assert {"--clip_low=0.8", "--clip_high=1.2", "--state_pool=32", "--skip_uniform_for=3"} <= set(spo)
    assert "--trajectory_mean=true" in spo and t5.config_of(args)["spo_trajectory_mean"] is True
    assert t5.config_of(args)["spo_clip"] == [0.8, 1.2] and t5.seed_ranges(args)["train"] == range(5000, 5040)
    for bad in ("--spo-clip=1.2,0.8", "--spo-clip=0.8", "--spo-state-pool=0", "--spo-skip-uniform-for=-1"):
        with pytest.raises(SystemExit):
            t5.parse_args([bad])
        assert capsys.readouterr().err.splitlines()[-1].split(": error: ")[1].startswith("--spo-")


def test_reuse_copies_the_parts_that_no_differing_setting_changes(t5, tmp_path):
    old_args = t5.parse_args(["--demos=3"])
    old = {"config": t5.config_of(old_args), "command": "x", "tasks": {}}
    old["tasks"]["press_button"] = {"parts": {p: part(0.5) for p in t5.PARTS}}
    old_work = tmp_path / "old" / "press_button"
    for name in ("demos", "il", "eval_il", "rsft", "eval_rsft", "spo", "eval_cso"):
        (old_work / name).mkdir(parents=True)
        (old_work / name / "made_by").write_text(name)
    (old_work / "demos_attempts.jsonl").write_text("{}\n")
    old_path = tmp_path / "old.json"
    t5.save_results(old_path, old)

    def reused(*flags: str) -> list[str]:
        return t5.reusable_parts(t5.config_of(t5.parse_args(["--demos=3", *flags])), old, "press_button")[0]

    assert reused() == list(t5.PARTS)
    assert reused("--spo-k=8") == ["demos", "il", "eval_il", "rsft", "eval_rsft"]
    assert reused("--spo-clip=0.8,1.2") == ["demos", "il", "eval_il", "rsft", "eval_rsft"]
    assert reused("--rsft-epochs=5") == ["demos", "il", "eval_il"]
    assert reused("--trials=50") == ["demos", "il", "rsft", "spo"]  # only the evaluations change
    assert reused("--episode-s=5") == ["demos", "il"] and reused("--ae-dim=192") == ["demos"]
    assert reused("--fps=5") == [] and reused("--arrange-s=5") == []  # a setting the demos depend on
    old["tasks"]["press_button"]["parts"]["rsft"]["failed"] = "too few successes"
    assert reused("--trials=50") == ["demos", "il"]  # a failed part is run again, not copied; nor what follows it
    del old["tasks"]["press_button"]["parts"]["rsft"]["failed"]

    new_work, new_path = tmp_path / "new", tmp_path / "new.json"
    (new_work / "press_button" / "spo.copying").mkdir(parents=True)  # an interrupted copy is redone
    flags = ["--demos=3", "--spo-k=8", f"--reuse={old_path}", f"--reuse-work={tmp_path / 'old'}"]
    args = t5.parse_args([*flags, f"--work={new_work}", f"--results={new_path}", "--stop-after=eval_rsft"])
    t5.main([*flags, f"--work={new_work}", f"--results={new_path}", "--tasks=press_button", "--stop-after=eval_rsft"])
    parts = json.loads(new_path.read_text())["tasks"]["press_button"]["parts"]
    assert list(parts) == ["demos", "il", "eval_il", "rsft", "eval_rsft"]
    assert parts["eval_il"]["success_rate"] == 0.5 and parts["rsft"]["reused_from"] == str(old_path)
    copied = sorted(p.name for p in (new_work / "press_button").iterdir() if p.name != "log.txt")
    assert copied == ["demos", "demos_attempts.jsonl", "eval_il", "eval_rsft", "il", "rsft", "spo.copying"]
    assert (new_work / "press_button" / "rsft" / "made_by").read_text() == "rsft"
    assert t5.config_of(args) == json.loads(new_path.read_text())["config"]
    with pytest.raises(SystemExit):
        t5.parse_args([f"--reuse={old_path}"])  # without --reuse-work


def test_a_fine_tune_setting_reuses_rsfts_collection_and_reruns_its_fine_tune(t5, tmp_path, capsys):
    paths = {"il_policy": tmp_path / "il_policy", "rsft": tmp_path / "rsft", "demos": tmp_path / "demos"}
    assert not [a for a in t5.stage_command(t5.parse_args([]), "press_button", "rsft", paths) if "demo" in a]
    args = t5.parse_args(["--rsft-demo-fraction=0.5"])
    rsft = t5.stage_command(args, "press_button", "rsft", paths)
    assert {
        "--demo_fraction=0.5",
        f"--demos_root={tmp_path / 'demos'}",
        "--demos_repo_id=local/twin_press_button",
    } <= set(rsft)
    assert t5.config_of(args)["rsft_demo_fraction"] == 0.5
    for bad in ("--rsft-demo-fraction=1", "--rsft-demo-fraction=-0.1"):
        with pytest.raises(SystemExit):
            t5.parse_args([bad])
        assert "--rsft-demo-fraction must be in [0, 1)" in capsys.readouterr().err
    for flag in ("demo-detour", "demo-regrasp"):
        key = flag.replace("-", "_")
        assert key not in t5.config_of(t5.parse_args([]))  # older results files stay valid
        assert t5.config_of(t5.parse_args([f"--{flag}=0.04"]))[key] == 0.04
        for bad in ("nan", "inf", "-0.01"):
            with pytest.raises(SystemExit):
                t5.parse_args([f"--{flag}={bad}"])
            assert f"--{flag} must be a finite number >= 0" in capsys.readouterr().err
    assert "demo_close_s" not in t5.config_of(t5.parse_args([]))
    assert t5.config_of(t5.parse_args(["--demo-close-s=1.6"]))["demo_close_s"] == 1.6
    for bad in ("nan", "inf", "0"):
        with pytest.raises(SystemExit):
            t5.parse_args([f"--demo-close-s={bad}"])
        assert "--demo-close-s must be a finite number > 0" in capsys.readouterr().err

    old = {"config": t5.config_of(t5.parse_args(["--demos=3"])), "command": "x", "tasks": {}}
    old["tasks"]["press_button"] = {"parts": {p: part(0.5) for p in t5.PARTS}}

    def reused(*flags: str) -> tuple[list[str], bool]:
        return t5.reusable_parts(t5.config_of(t5.parse_args(["--demos=3", *flags])), old, "press_button")[:2]

    assert reused("--rsft-demo-fraction=0.5") == (["demos", "il", "eval_il"], True)
    assert reused("--rsft-epochs=5", "--rsft-batch=32") == (["demos", "il", "eval_il"], True)
    assert reused("--rsft-demo-fraction=0.5", "--rsft-strikes=3")[1] is False  # the collection changes too
    assert reused("--rsft-demo-fraction=0.5", "--il-steps=2000")[1] is False  # from another IL
    assert reused("--spo-k=8") == (["demos", "il", "eval_il", "rsft", "eval_rsft"], False)  # R-SFT whole

    # the copy: the collection's folders, their journals pointed at the copied IL; no fine-tune, no stage record
    old_work = tmp_path / "old" / "press_button"
    old_il = old_work / "il" / "checkpoints" / "last" / "pretrained_model"
    old_il.mkdir(parents=True)
    (old_il / "model.safetensors").write_bytes(b"IL weights")
    (old_work / "demos").mkdir()
    (old_work / "demos_attempts.jsonl").write_text("{}\n")
    (old_work / "eval_il").mkdir()
    for name in ("journal", "robot_journal", "buffer", "pretrained_model", "train_state"):
        (old_work / "rsft" / name).mkdir(parents=True)
        (old_work / "rsft" / name / "spec.json").write_text(json.dumps({"policy": str(old_il), "n_strikes": 4}))
    for name in ("collection.json", "stage.json"):
        (old_work / "rsft" / name).write_text("{}")
    old_path = tmp_path / "old.json"
    t5.save_results(old_path, old)
    new_work = tmp_path / "new"
    flags = ["--demos=3", "--rsft-demo-fraction=0.5", f"--reuse={old_path}", f"--reuse-work={tmp_path / 'old'}"]
    t5.main(
        [
            *flags,
            f"--work={new_work}",
            f"--results={tmp_path / 'new.json'}",
            "--stop-after=eval_il",
            "--tasks=press_button",
        ]
    )
    entry = json.loads((tmp_path / "new.json").read_text())["tasks"]["press_button"]
    assert list(entry["parts"]) == ["demos", "il", "eval_il"]
    assert entry["rsft_collection_reused_from"] == str(old_path)
    rsft = new_work / "press_button" / "rsft"
    assert sorted(p.name for p in rsft.iterdir()) == ["buffer", "collection.json", "journal", "robot_journal"]
    new_il = new_work / "press_button" / "il" / "checkpoints" / "last" / "pretrained_model"
    for name in ("journal", "robot_journal"):
        assert json.loads((rsft / name / "spec.json").read_text()) == {"policy": str(new_il), "n_strikes": 4}

    # a collection made by another policy than the reused IL is refused, not rebased
    other_il = tmp_path / "other_il"
    other_il.mkdir()
    (other_il / "model.safetensors").write_bytes(b"other weights")
    (old_work / "rsft" / "journal" / "spec.json").write_text(json.dumps({"policy": str(other_il)}))
    with pytest.raises(SystemExit, match="not the reused IL"):
        t5.main(
            [
                *flags,
                f"--work={tmp_path / 'new2'}",
                f"--results={tmp_path / 'new2.json'}",
                "--stop-after=eval_il",
                "--tasks=press_button",
            ]
        )


def test_an_evaluations_record_holds_its_rate_its_cost_and_each_trials_outcome(t5, tmp_path, monkeypatch):
    out = tmp_path / "eval_il"
    folder = out / "robot_journal" / "episodes" / "press_the_button"
    folder.mkdir(parents=True)
    for scene, (ok, ticks) in {0: (True, 40), 1: (False, 100), 2: (True, 60)}.items():
        np.savez(folder / f"{scene:07d}_001.npz", success=ok, length=ticks)
    (out / "eval.json").write_text(json.dumps({"success_rate": {"press the button": {"mean": 2 / 3}}}))
    monkeypatch.setattr(t5, "run", lambda *a, **k: None)  # the stage's command: its outputs are made above
    paths = {"eval_il": out, "home": tmp_path} | {p: tmp_path / p for p in ("il_policy", "rsft_policy", "spo_policy")}
    record = t5.robot_part(t5.parse_args([]), "press_button", "eval_il", paths, out / "log")
    assert record["outcomes"] == {"0000000_001": 1, "0000001_001": 0, "0000002_001": 1}
    assert record["success_rate"] == pytest.approx(2 / 3) and record["successes"] == 2
    # 20 s of episodes at 10 fps, and per episode the 3 s rest move and the 10 s of arranging
    assert record["operator"] == {"episodes": 3, "discarded": 0, "episode_s": 20.0, "person_s": 59.0}


def test_more_spo_iterations_continue_the_copied_spo_from_the_copied_rsft(t5, tmp_path, capsys):
    old = {"config": t5.config_of(t5.parse_args(["--demos=3"])), "command": "x", "tasks": {}}
    old["tasks"]["press_button"] = {"parts": {p: part(0.5) for p in t5.PARTS}}

    def grows(*flags: str) -> bool:
        return t5.reusable_parts(t5.config_of(t5.parse_args(["--demos=3", *flags])), old, "press_button")[2]

    default = t5.parse_args([]).spo_iterations
    assert grows(f"--spo-iterations={default + 2}") and grows(f"--spo-iterations={default + 2}", "--trials=50")
    assert not grows(f"--spo-iterations={default - 1}")  # fewer: SPO runs again
    assert not grows(f"--spo-iterations={default + 2}", "--spo-k=8")  # another SPO setting too
    assert not grows(f"--spo-iterations={default + 2}", "--rsft-epochs=5")  # from another R-SFT

    old_work = tmp_path / "old" / "press_button"
    old_rsft = old_work / "rsft" / "pretrained_model"
    for name in ("demos", "il", "eval_il", "eval_rsft", "spo/state"):
        (old_work / name).mkdir(parents=True)
    old_rsft.mkdir(parents=True)
    (old_rsft / "model.safetensors").write_bytes(b"R-SFT weights")
    (old_work / "demos_attempts.jsonl").write_text("{}\n")
    (old_work / "spo" / "robot_journal").mkdir()
    (old_work / "spo" / "robot_journal" / "spec.json").write_text(json.dumps({"policy": str(old_rsft)}))
    sha = hashlib.sha256(b"R-SFT weights").hexdigest()[:16]
    record = {"spec": {"spo": {"iterations": default}, "policy": {"path": str(old_rsft), "weights_sha256": sha}}}
    (old_work / "spo" / "stage.json").write_text(json.dumps(record | {"complete": True}))
    old_path = tmp_path / "old.json"
    t5.save_results(old_path, old)
    flags = [f"--spo-iterations={default + 2}", f"--reuse={old_path}", f"--reuse-work={tmp_path / 'old'}"]
    flags = ["--demos=3", "--tasks=press_button", *flags]
    new_work = tmp_path / "new"
    t5.main([*flags, f"--work={new_work}", f"--results={tmp_path / 'new.json'}", "--stop-after=eval_rsft"])
    entry = json.loads((tmp_path / "new.json").read_text())["tasks"]["press_button"]
    assert list(entry["parts"]) == ["demos", "il", "eval_il", "rsft", "eval_rsft"]  # SPO is run (continued)
    assert entry["spo_continued_from"] == str(old_path) and "SPO to continue" in capsys.readouterr().out
    new_rsft = new_work / "press_button" / "rsft" / "pretrained_model"
    spo = new_work / "press_button" / "spo"
    assert json.loads((spo / "robot_journal" / "spec.json").read_text()) == {"policy": str(new_rsft)}
    assert json.loads((spo / "stage.json").read_text())["spec"]["policy"] == {
        "path": str(new_rsft),
        "weights_sha256": sha,
    }
    assert (spo / "state").is_dir()

    (old_work / "spo" / "stage.json").write_text(json.dumps({"spec": {"policy": {"path": "x", "weights_sha256": "0"}}}))
    with pytest.raises(SystemExit, match="other weights"):
        t5.main([*flags, f"--work={tmp_path / 'new2'}", f"--results={tmp_path / 'new2.json'}", "--stop-after=il"])


def test_the_paired_differences_pair_the_evaluations_trials_by_scene(t5, tmp_path):
    def trials(part: str, outcomes: dict[int, bool]) -> None:
        folder = tmp_path / part / "robot_journal" / "episodes" / "press_the_button"
        folder.mkdir(parents=True)
        for scene, ok in outcomes.items():  # named as the robot journal names a trial: by its scene
            np.savez(folder / f"{scene:07d}_000.npz", success=ok, length=50)

    trials("eval_il", {100003: False, 100000: True, 100001: True, 100002: False})
    trials("eval_cso", {100000: True, 100001: True, 100002: True, 100003: False})
    trials("eval_rsft", {100000: True, 100001: False, 100002: False})  # one trial short: not paired
    pairs = t5.paired_differences(tmp_path)
    assert list(pairs) == ["cso_minus_il"]
    # differences 0, 0, +1, 0: mean 0.25, sample s.d. 0.5, half-width 1.96 * 0.5 / 2 = 0.49
    cso_il = pairs["cso_minus_il"]
    assert cso_il["ci95"] == pytest.approx([-0.24, 0.74])
    assert {k: cso_il[k] for k in ("mean", "won", "lost", "trials")} == {"mean": 0.25, "won": 1, "lost": 0, "trials": 4}


def test_demonstrations_a_crash_left_unreadable_are_refused_with_what_to_do(t5, tmp_path):
    """A recording killed natively leaves LeRobot's parquet files without their footer: resuming it cannot work,
    so the driver says so (and how to start over) instead of retrying lerobot-record."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = tmp_path / "demos"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps({"total_episodes": 20}))
    data = root / "data" / "chunk-000" / "file-000.parquet"
    data.parent.mkdir(parents=True)
    pq.write_table(pa.table({"index": list(range(100))}), data)
    assert t5.unreadable_parquet(root) is None
    data.write_bytes(data.read_bytes()[:-40])  # the footer never written
    paths = {"demos": root, "demos_log": tmp_path / "demos_attempts.jsonl"}
    with pytest.raises(RuntimeError, match=r"20 demonstrations in .* cannot be resumed \(.*file-000.parquet: .*delete"):
        t5.record_demos(t5.parse_args(["--demos=100"]), "cube_in_bowl", paths, tmp_path / "log.txt")
    assert data.exists()  # nothing deleted for the user
