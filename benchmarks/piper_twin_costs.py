"""What the PiPER twin costs (issue 36): one 200 Hz firmware tick with and without physics, and a camera frame.

The tick: ``PiperEmulator.step`` on a python-can ``virtual`` bus (handle, firmware, physics, 3040 frames/s
sent, the world state published), the arm moving at 50 % speed; the real-time budget is 5 ms. The frame:
``TwinRenderer.render`` per view and size (``MUJOCO_GL=egl`` unless set). No torch. Run:
    ./run.sh python benchmarks/piper_twin_costs.py [--ticks 2000] [--frames 50]
"""

from __future__ import annotations

import argparse
import time

import can
from piper_can import codec
from piper_can.emulator import PiperEmulator
from piper_twin.plant import TwinPlant
from piper_twin.renderer import TwinRenderer
from piper_twin.state_channel import StatePublisher

SIZES = ((64, 64), (128, 96), (320, 240))
POSE = (0.3, 1.2, -1.0, 0.2, 0.5, 0.1)


def tick_ms(scene: str | None, ticks: int) -> float:
    """Mean wall time of one emulator step (ms): ``scene`` None is the kinematic firmware."""
    bus = can.Bus(interface="virtual", channel=f"twin-costs-{scene}")
    plant = None if scene is None else TwinPlant(scene)
    publisher = StatePublisher("239.74.9.9", 45999)
    if plant is not None:
        plant.listeners.append(lambda p: publisher.publish(p.snapshot()))
    emulator = PiperEmulator(bus, plant=plant)
    firmware = emulator.firmware
    try:
        firmware.handle(codec.encode(codec.MotorEnable(codec.MOTOR_ALL, True)))
        for _ in range(10):
            emulator.step()
        mode = codec.ModeControl(codec.CtrlMode.CAN, codec.MoveMode.J, 50, codec.MIT_MODE_POSITION_VELOCITY)
        firmware.handle(codec.encode(mode))
        for frame in codec.encode_joint_targets(POSE):
            firmware.handle(frame)
        start = time.perf_counter()
        for _ in range(ticks):
            emulator.step()
        return (time.perf_counter() - start) / ticks * 1e3
    finally:
        bus.shutdown()
        publisher.close()


def frame_ms(scene: str, view: str, width: int, height: int, frames: int) -> float:
    """Mean wall time of one rendered frame (ms), the arm raised over the scene."""
    snapshot = TwinPlant(scene, pose_rad=POSE).snapshot()
    renderer = TwinRenderer(scene, width, height)
    try:
        renderer.render(snapshot, view)
        start = time.perf_counter()
        for _ in range(frames):
            renderer.render(snapshot, view)
        return (time.perf_counter() - start) / frames * 1e3
    finally:
        renderer.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--frames", type=int, default=50)
    args = parser.parse_args()
    for scene in (None, "table", "press_button", "cube_in_bowl"):
        ms = tick_ms(scene, args.ticks)
        print(f"tick  {scene or 'kinematic':13s} {ms:6.3f} ms per 5 ms tick ({5 / ms:5.1f}x real time)")
    for view in ("front", "wrist"):
        for width, height in SIZES:
            ms = frame_ms("cube_in_bowl", view, width, height, args.frames)
            print(f"frame {view:6s} {width}x{height:<4d} {ms:6.2f} ms")


if __name__ == "__main__":
    main()
