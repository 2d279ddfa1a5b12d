"""How forgiving is the twin's cube grasp (issue 36)? The scripted demonstration of cube_in_bowl with its grasp put
off on purpose: the approach, the descent and the close moved by ``d`` mm in a random horizontal direction, or the
gripper's yaw turned by ``e`` degrees (random sign); lift, carry and drop unchanged. Success per (d, e) over the
development scenes 300000 + i.

It runs the physics alone, not the firmware: ``TwinPlant`` with every joint servoed straight to the demonstration's
IK targets every 10 ms (no speed limit, no planner), no waypoint jitter, 20 s per trial. A policy's trial goes
through the simulated firmware instead; what this measures is the scene's tolerance, not a policy's.

    python benchmarks/twin_grasp_tolerance.py [--scenes 30] [--out benchmarks/results/twin_grasp_tolerance.json]
"""

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
from piper_can.firmware import PlantCommand
from piper_twin import demo
from piper_twin.plant import TwinPlant
from piper_twin.scenes import Scene

from lerobot_cso.durable import write_atomic

REST_RAD = (0.0, 1.0, -1.0, 0.0, 1.0, 0.0)  # the Table 5 runs' initial pose
DT_S, EPISODE_S = 0.01, 20.0
GRASP_WAYPOINTS = 3  # above the cube, down to it, the close (demo._cube_in_bowl's order)
GRID = ((0, 0), (5, 0), (10, 0), (15, 0), (20, 0), (25, 0), (0, 15), (0, 30), (0, 45))  # (offset mm, yaw error deg)


def trial(seed: int, offset_mm: float, yaw_error_deg: float, rng: np.random.Generator) -> bool:
    """One scripted trial of scene ``seed`` with its grasp put off; whether the cube ended in the bowl."""
    angle = rng.uniform(0.0, 2 * math.pi)
    offset = np.array([math.cos(angle), math.sin(angle), 0.0]) * offset_mm / 1000
    yaw_error = rng.choice([-1.0, 1.0]) * math.radians(yaw_error_deg)

    def off_plan(
        scene: Scene, model: mujoco.MjModel, data: mujoco.MjData, close_s: float = demo.CLOSE_S
    ) -> tuple[list[demo.Waypoint], float]:
        waypoints, yaw = demo.plan(scene, model, data, close_s)
        moved = [
            demo.Waypoint(w.position + offset, w.gripper_m, w.dwell_s, w.approach) for w in waypoints[:GRASP_WAYPOINTS]
        ]
        return moved + waypoints[GRASP_WAYPOINTS:], yaw + yaw_error

    plant = TwinPlant("cube_in_bowl", seed, REST_RAD, 0.0)
    script = demo.ScriptedDemo(plant.scene, plant.model, noise_m=0.0, planner=off_plan)
    mujoco.mj_kinematics(plant.model, plant.data)
    script.start(plant.data, plant.state().joints_rad, rng)
    for _ in range(int(EPISODE_S / DT_S)):
        targets, gripper_m = script.step(DT_S, plant.state().joints_rad)
        plant.step(DT_S, PlantCommand(tuple(targets), (0.0,) * 6, ("servo",) * 6, gripper_m, "servo"))
        if plant.succeeded():
            return True
    return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=300000, help="the development scenes by default")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.scenes < 1:
        ap.error(f"--scenes must be >= 1, got {args.scenes}")
    if args.out and not (args.out.parent.is_dir() and os.access(args.out.parent, os.W_OK)):
        ap.error(f"--out {args.out}: its folder does not exist or cannot be written")
    rows = []
    for offset_mm, yaw_error_deg in GRID:
        rng = np.random.default_rng(0)
        started = time.perf_counter()
        wins = [trial(args.first_seed + i, offset_mm, yaw_error_deg, rng) for i in range(args.scenes)]
        rows.append(
            {"offset_mm": offset_mm, "yaw_error_deg": yaw_error_deg, "successes": sum(wins), "trials": len(wins)}
        )
        print(
            f"offset {offset_mm:2d} mm, yaw error {yaw_error_deg:2d} deg: {sum(wins)} / {len(wins)}"
            f" ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )
    if args.out:
        result = {
            "what": __doc__.split("\n\n")[0],
            "command": "python " + shlex.join(sys.argv),
            "date": time.strftime("%Y-%m-%d"),
            "rows": rows,
        }
        write_atomic(args.out, (json.dumps(result, indent=1) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
