"""What a LeRobot user's own camera data costs on two CPU cores (issue 59), measured side by side.

- ``encoders``: one training step (forward, backward, AdamW) of the default-size cso policy at batch 32 on a 480²
  ``observation.image`` plus the 4-d state, in the skill-prior phase (the phase that reads images), for each
  backbone × ``image_resize`` candidate; the candidates alternate within each round so that load from other
  processes hits them alike. One autoencoder-phase step (no image read) for comparison.
- ``data``: LeRobot's data loader alone (batch 32, 32-action chunks, pyav) on the same 480² frames stored as AV1
  video and as PNG images, with 0 and 2 workers: what decoding costs per batch; and the CPU seconds of one item
  with and without the action chunk (LeRobot's query of the chunk decodes the PNG frames of its rows too), also
  after ``lerobot-edit-dataset --operation.type=convert_image_to_video`` turned the PNG dataset into video.
- ``codecs``: the video dataset's items against its re-encoding to H.264 by ``lerobot-edit-dataset
  --operation.type=reencode_videos``, alternating.
- ``train``: the real ``lerobot-train --policy.type=cso`` with only ``--steps``, ``--batch_size`` and the device
  (plus ``--policy.n_autoencoder_steps=0`` to time the prior phase); seconds per step = the difference of a short
  and a longer run's wall time over the difference of their steps (start-up cancels).
- ``crop``: where the PiPER twin's objects land in its 640×480 ``front`` camera over placement seeds, and which
  share of them a centre crop to 480×480 would cut off (the crop-or-pad choice of ``image_resize``).

    python benchmarks/own_data_costs.py --work=outputs/own_data --results=benchmarks/results/own_data_costs.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

import lerobot_cso  # noqa: F401  (MUJOCO_GL=egl, before anything imports mujoco)

FRAME = 480  # LeRobot's MetaWorld frames
BATCH = 32
CANDIDATES = (("resnet18", 128), ("conv", 128), ("conv", 64), ("resnet18", 64), ("resnet18", None))
REPO_ID = "local/own_data_costs"


def load() -> str:
    """The 1-, 5- and 15-minute load averages."""
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def make_policy(backbone: str, resize: int | None, n_autoencoder_steps: int = 0) -> Any:
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_cso.policy import CSOConfig, CSOPolicy

    config = CSOConfig(
        device="cpu",
        push_to_hub=False,
        image_backbone=backbone,
        image_resize=resize,
        n_autoencoder_steps=n_autoencoder_steps,
        tasks=["task"],
        input_features={
            "observation.image": PolicyFeature(FeatureType.VISUAL, (3, FRAME, FRAME)),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
    )
    return CSOPolicy(config).train()


def train_step(policy: Any, optimizer: torch.optim.Optimizer, batch: dict[str, Any]) -> tuple[float, float]:
    """One training step's (wall, CPU) seconds; the CPU seconds (all threads) barely depend on other load."""
    start, cpu = time.perf_counter(), time.process_time()
    loss, _ = policy.forward(batch)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(policy.parameters(), 100.0)
    optimizer.step()
    optimizer.zero_grad()
    return time.perf_counter() - start, time.process_time() - cpu


def measure_encoders(rounds: int, steps: int) -> dict[str, Any]:
    torch.manual_seed(0)
    batch = {
        "observation.image": torch.randn(BATCH, 3, FRAME, FRAME),
        "observation.state": torch.randn(BATCH, 4),
        "action": torch.randn(BATCH, 32, 4),
        "action_is_pad": torch.zeros(BATCH, 32, dtype=torch.bool),
        "task": ["task"] * BATCH,
    }
    runs = {}
    for backbone, resize in CANDIDATES:
        policy = make_policy(backbone, resize)
        policy._cost_reported = True  # the benchmark times the steps itself
        runs[f"{backbone}@{resize or FRAME}"] = (policy, torch.optim.AdamW(policy.get_optim_params(), lr=1e-4))
    seconds: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[float]] = {name: [] for name in runs}
    for policy, optimizer in runs.values():
        train_step(policy, optimizer, batch)  # warm-up
    loads = []
    for round_ in range(rounds):
        for name, (policy, optimizer) in runs.items():
            if name.endswith(f"@{FRAME}") and round_:  # no resize: seconds per step, one round shows it
                continue
            wall, used = np.mean([train_step(policy, optimizer, batch) for _ in range(steps)], axis=0)
            seconds[name].append(float(wall))
            cpu[name].append(float(used))
            print(f"round {round_ + 1} {name}: {wall:.3f} s/step, {used:.3f} CPU s (load {load()})", flush=True)
        loads.append(load())
    ae = make_policy("conv", 128, n_autoencoder_steps=10**6)
    ae_optimizer = torch.optim.AdamW(ae.get_optim_params(), lr=1e-4)
    train_step(ae, ae_optimizer, batch)
    ae_seconds = [train_step(ae, ae_optimizer, batch) for _ in range(max(3, steps))]
    return {
        "what": "one training step (forward, backward, grad clip, AdamW) at batch 32, 480² image + 4-d state, "
        "default-size policy, skill-prior phase, torch threads as set",
        "torch_threads": torch.get_num_threads(),
        "seconds_per_step": {name: values for name, values in seconds.items()},
        "min_seconds_per_step": {name: min(v) for name, v in seconds.items()},
        "median_seconds_per_step": {name: float(np.median(v)) for name, v in seconds.items()},
        "cpu_seconds_per_step": cpu,
        "min_cpu_seconds_per_step": {name: min(v) for name, v in cpu.items()},
        "autoencoder_phase_wall_cpu_seconds_per_step": np.median(ae_seconds, axis=0).tolist(),
        "loadavg_per_round": loads,
    }


def write_dataset(root: Path, kind: str, episodes: int, length: int) -> None:
    """Rendered MetaWorld ``corner2`` frames at 480² (random actions: the cost of decoding does not depend on
    them) in LeRobot's MetaWorld layout, stored as ``kind`` ("video" or "image")."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_cso.worlds.metaworld.constants import FPS, LEROBOT_CAMERA
    from lerobot_cso.worlds.metaworld.env import CSOMetaWorldEnv

    features = {
        "observation.image": {"dtype": kind, "shape": (FRAME, FRAME, 3), "names": ["height", "width", "channels"]},
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
    }
    ds = LeRobotDataset.create(REPO_ID, FPS, features, root=root, robot_type="sawyer")
    env = CSOMetaWorldEnv("reach-v3", cameras=(LEROBOT_CAMERA,), image_size=FRAME, state="hand")
    rng = np.random.default_rng(0)
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        for _ in range(length):
            action = rng.uniform(-1, 1, 4).astype(np.float32)
            ds.add_frame(
                {
                    "observation.image": obs["pixels"][LEROBOT_CAMERA],
                    "observation.state": obs["agent_pos"].astype(np.float32),
                    "action": action,
                    "task": "reach the goal",
                }
            )
            obs, *_ = env.step(action)
        ds.save_episode()
    env.close()
    ds.finalize()


def measure_loader(root: Path, workers: int, batches: int) -> float:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(
        REPO_ID, root=root, video_backend="pyav", delta_timestamps={"action": [i / 80 for i in range(32)]}
    )
    loader = torch.utils.data.DataLoader(ds, batch_size=BATCH, shuffle=True, num_workers=workers, drop_last=True)
    it = iter(loader)
    next(it)  # workers started, first batch
    start = time.perf_counter()
    for _ in range(batches):
        next(it)
    return (time.perf_counter() - start) / batches


def measure_items(root: Path, items: int) -> dict[str, float]:
    """CPU seconds per ``dataset[i]`` in the main process, without and with the 32-action chunk the policy reads."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    out = {}
    for name, chunk in (("frame only", None), ("frame + 32-action chunk", {"action": [i / 80 for i in range(32)]})):
        ds = LeRobotDataset(REPO_ID, root=root, video_backend="pyav", delta_timestamps=chunk)
        ds[0]
        start = time.process_time()
        for i in range(items):
            ds[(i * 37) % len(ds)]
        out[name] = (time.process_time() - start) / items
    return out


def edit_dataset(root: Path, out: Path, *operation: str) -> Path:
    """``root`` edited by LeRobot's own ``lerobot-edit-dataset`` into ``out`` (kept: a rerun reuses it)."""
    if not out.exists():
        cmd = [str(Path(sys.executable).parent / "lerobot-edit-dataset"), f"--repo_id={REPO_ID}", f"--root={root}"]
        subprocess.run([*cmd, *operation, f"--new_root={out}", f"--new_repo_id={REPO_ID}"], check=True)
    return out


def measure_codecs(video: Path, work: Path, rounds: int) -> dict[str, Any]:
    """CPU seconds per item of the AV1 video dataset and of its re-encoding to H.264, alternating."""
    h264 = edit_dataset(video, work / "h264", "--operation.type=reencode_videos", "--operation.rgb_encoder.vcodec=h264")
    items: dict[str, list[float]] = {"av1 (LeRobot's default)": [], "h264": []}
    for _ in range(rounds):
        for name, root in zip(items, (video, h264), strict=True):
            items[name].append(measure_items(root, 8)["frame + 32-action chunk"])
    return {"cpu_seconds_per_item": items, "loadavg_after": load()}


def lerobot_train(root: Path, out: Path, steps: int, extra: list[str]) -> float:
    cmd = [str(Path(sys.executable).parent / "lerobot-train"), "--policy.type=cso", f"--dataset.repo_id={REPO_ID}"]
    cmd += [f"--dataset.root={root}", f"--output_dir={out}", f"--steps={steps}", f"--batch_size={BATCH}"]
    cmd += ["--policy.device=cpu", "--policy.push_to_hub=false", f"--save_freq={steps}", *extra]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=os.environ | {"WANDB_MODE": "disabled"})
    seconds = time.perf_counter() - start
    if proc.returncode:
        raise RuntimeError(proc.stdout[-2000:] + proc.stderr[-2000:])
    cost = re.search(r"cso policy on a CPU: .*", proc.stdout + proc.stderr)
    print(f"  lerobot-train {steps} steps {extra}: {seconds:.1f} s; {cost.group(0) if cost else 'no cost line'}")
    return seconds


def measure_train(roots: dict[str, Path], work: Path, short: int, long: int, kinds: list[str]) -> dict[str, Any]:
    results = {}
    runs = [(kind, "prior phase", ["--policy.n_autoencoder_steps=0"]) for kind in kinds] + [("video", "defaults", [])]
    for kind, phase, extra in runs:
        times = [lerobot_train(roots[kind], work / f"train_{kind}_{n}", n, extra) for n in (short, long)]
        for n in (short, long):
            shutil.rmtree(work / f"train_{kind}_{n}")
        name = f"{kind}, {phase}"
        results[name] = {"wall_s": times, "seconds_per_step": (times[1] - times[0]) / (long - short)}
        print(f"{name}: {results[name]['seconds_per_step']:.3f} s/step (load {load()})", flush=True)
    return {"steps": [short, long], "runs": results, "loadavg_after": load()}


def measure_crop(seeds: int) -> dict[str, Any]:
    """The twin's objects projected into its 640×480 front camera over ``seeds`` placements of each scene."""
    import mujoco
    from piper_twin.scenes import SCENES, compile_scene

    width, height, keep = 640, 480, 480
    table = {
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, i)
        for m in [compile_scene(SCENES["table"])]
        for i in range(m.nbody)
    }
    out = {}
    for name, scene in SCENES.items():
        if name == "table":
            continue
        model = compile_scene(scene)
        data = mujoco.MjData(model)
        bodies = [i for i in range(model.nbody) if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i) not in table]
        cam = model.camera("front").id
        focal = (height / 2) / np.tan(np.radians(model.cam_fovy[cam]) / 2)
        xs = []
        for seed in range(seeds):
            scene.place(model, data, seed)
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            rotation = data.cam_xmat[cam].reshape(3, 3)
            for body in bodies:
                local = rotation.T @ (data.xpos[body] - data.cam_xpos[cam])
                xs.append(width / 2 + focal * local[0] / -local[2])
        xs = np.array(xs)
        margin = (width - keep) / 2
        cut = (xs < margin) | (xs > width - margin)
        out[name] = {
            "object_x_px": [float(xs.min()), float(xs.max())],
            "share_cut_by_centre_crop": float(cut.mean()),
            "positions": len(xs),
        }
        print(f"crop {name}: x in [{xs.min():.0f}, {xs.max():.0f}] px, {cut.mean():.1%} outside [80, 560]")
    return {"camera": "front, 640x480", "crop": "centre 480x480", "seeds": seeds, "scenes": out}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--results", type=Path, required=True)
    parser.add_argument("--parts", default="crop,encoders,data,codecs,train")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads for the encoder candidates")
    parser.add_argument("--steps", type=int, default=1)
    parser.add_argument("--train_steps", default="4,12", help="the short and the long run's steps")
    parser.add_argument("--train_kinds", default="video,image", help="the datasets whose prior phase is timed")
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--length", type=int, default=100)
    args = parser.parse_args()
    parts = args.parts.split(",")
    results: dict[str, Any] = json.loads(args.results.read_text()) if args.results.is_file() else {}
    results["machine"] = {"cpus": os.cpu_count(), "loadavg_at_start": load()}

    def save() -> None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(json.dumps(results, indent=2) + "\n")

    if "crop" in parts:
        results["crop"] = measure_crop(200)
        save()
    if "encoders" in parts:
        torch.set_num_threads(args.threads)
        results["encoders"] = measure_encoders(args.rounds, args.steps)
        save()
    roots = {kind: args.work / f"data_{kind}" for kind in ("video", "image")}
    if {"data", "codecs", "train"} & set(parts):
        for kind, root in roots.items():
            if not root.exists():
                write_dataset(root, kind, args.episodes, args.length)
    if "data" in parts:
        results["data"] = {
            "what": "seconds per batch of 32 (480² frame, 4-d state, 32-action chunk) from LeRobot's DataLoader, pyav",
            "seconds_per_batch": {
                f"{kind}, {w} workers": measure_loader(root, w, 8) for kind, root in roots.items() for w in (0, 2)
            },
            "cpu_seconds_per_item": {kind: measure_items(root, 6) for kind, root in roots.items()},
            "image converted to video": measure_items(
                edit_dataset(roots["image"], args.work / "converted", "--operation.type=convert_image_to_video"), 6
            ),
            "loadavg_after": load(),
        }
        print(results["data"], flush=True)
        save()
    if "codecs" in parts:
        results["codecs"] = measure_codecs(roots["video"], args.work, 2)
        print(results["codecs"], flush=True)
        save()
    if "train" in parts:
        short, long = (int(n) for n in args.train_steps.split(","))
        results["train"] = measure_train(roots, args.work, short, long, args.train_kinds.split(","))
        save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
