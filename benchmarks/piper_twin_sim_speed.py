"""How much faster than real time ``piper_twin_sim`` runs the PiPER's control loop (issue 36, item 6).

One control tick as ``lerobot-cso``'s robot world runs it, without the policy: ``get_observation`` (the driver's
state and the cameras rendered from the plant) and ``send_action`` (the command, then one control period of
simulated time: the firmware and the physics every 5 ms). Reported per fps and camera size: wall and CPU time per
tick (ms), and the speed-up over real time (the period over the time per tick). On a shared machine the CPU time
is the fairer figure. Run:
    ./run.sh python benchmarks/piper_twin_sim_speed.py [--ticks 300]
"""

from __future__ import annotations

import argparse
import math
import time
import uuid

from lerobot.robots import make_robot_from_config
from lerobot_robot_piper import PiperTwinCameraConfig, PiperTwinSimConfig

KEYS = [*(f"joint_{j}.pos" for j in range(1, 7)), "gripper.pos"]
CENTRE = (0.0, 1.2, -1.0, 0.0, 0.5, 0.0)


def tick_ms(fps: int, size: tuple[int, int] | None, ticks: int) -> tuple[float, float]:
    """Mean wall and CPU time (ms) of one observe + act tick at ``fps``, with one front camera of ``size``."""
    cameras = {} if size is None else {"front": PiperTwinCameraConfig(view="front", width=size[0], height=size[1])}
    config = PiperTwinSimConfig(
        channel=f"twin-sim-speed-{uuid.uuid4().hex[:8]}",
        cameras=cameras,
        motion_mode="position",
        speed_percent=100,
        scene="press_button",
        fps=fps,
        initial_pose=list(CENTRE),
    )
    robot = make_robot_from_config(config)
    robot.connect()
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        for t in range(ticks):
            robot.get_observation()
            swing = 0.3 * math.sin(2 * math.pi * t / (2 * fps))  # one sweep of J1 every 2 s
            robot.send_action(dict(zip(KEYS, (CENTRE[0] + swing, *CENTRE[1:], 0.03), strict=True)))
        return (time.perf_counter() - wall) / ticks * 1e3, (time.process_time() - cpu) / ticks * 1e3
    finally:
        robot.disconnect()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=300)
    args = parser.parse_args()
    print("| fps | camera | wall ms/tick | CPU ms/tick | x real time (wall) | x real time (CPU) |")
    print("|---:|---|---:|---:|---:|---:|")
    for fps in (10, 30):
        for size in (None, (32, 32), (128, 96)):
            wall, cpu = tick_ms(fps, size, args.ticks)
            period = 1e3 / fps
            camera = "none" if size is None else f"front {size[0]}x{size[1]}"
            speed = f"{period / wall:.1f} | {period / cpu:.1f}"
            print(f"| {fps} | {camera} | {wall:.2f} | {cpu:.2f} | {speed} |", flush=True)


if __name__ == "__main__":
    main()
