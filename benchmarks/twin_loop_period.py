"""The 30 Hz loop with a camera policy on the PiPER's physics twin (issue 36): missed ticks and p99 tick time.

Saves an untrained cso policy with the project's camera architecture (the ``il.policy`` block of
configs/metaworld_vision.yaml: the four-layer conv encoder, its keypoints and embedding, the small prior; images at
its ``demos.image_size``) reading the twin's camera(s) plus the PiPER's 7-D state, 7-D action, saved with its
processors. Starts ``piper-emulator --physics --scene=<scene>`` on private udp_multicast channels (CAN and the
twin's world state), runs ``lerobot-rollout --strategy.type=base --robot.cameras=<piper_twin views>`` against it once
per variant (synchronous decode; the background decode, in its own process, started ``--lead`` ticks before the
queue runs dry), and measures the loop period from the
kernel receive times of the joint commands on the bus (``--clock bus``, a recorder on the bus in this process, as
benchmarks/rollout_loop_period.py does for the state policy on the kinematic firmware; the loop's own send times are
printed beside them as a cross-check) or from the times the loop's ``send_action`` returned (``--clock loop``, no
recorder: a recorder reading every frame on the bus takes CPU from the two cores the loop runs on, which a real arm's
computer does not spend). A period over 1.1 control periods (36.7 ms at 30 Hz) is a missed tick. The CPU time of
the emulator, the rollout (with its decode process) and the recorder is printed as a share of one core, with the
share of the machine's time the hypervisor gave to other guests (steal, /proc/stat) meanwhile.

``lerobot-rollout`` runs as itself (LeRobot's ``main``) behind a few lines that time each camera read of the loop
(``read_latest``: the twin's camera renders in the rollout process on its own capture thread, as a real camera
captures), each ``get_observation``, ``select_action`` and ``send_action`` and how late each of the loop's sleeps
wakes (two clock reads per call), written to a file at exit. The late periods are also counted by their tick's place
in its skill (0: the tick that refills the queue; n_action_steps - 1 - lead: the tick that starts the background
decode). Run:
    OMP_NUM_THREADS=1 ./run.sh python benchmarks/twin_loop_period.py [--duration 60] [--lead 3] [--skip 5]
        [--cameras front[,wrist]] [--scene press_button|cube_in_bowl] [--weights float32|int8]
        [--variants sync,background] [--nice N]   (N < 0: the control loop above the emulator, as root)
        [--fifo P]   (the rollout under SCHED_FIFO priority P, as root)
        [--clock bus|loop]   (the periods from the bus's receive times, or the loop's own send times)
        [--raw FILE]   (the command times and every timed call, as JSON)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml
from lerobot_robot_piper.cli_processes import cli_env, explain, rollout_args
from piper_can.channel_recorder import ChannelRecorder
from piper_can.emulator_process import BIN, start_emulator, unique_udp_channel
from rollout_loop_period import report, save_untrained_piper_policy

ROOT = Path(__file__).resolve().parents[1]

TASK = "press the button"
CAMERA = "{type: piper_twin, view: %s, width: %d, height: %d, group: %s, port: %d, max_age_s: 1.0}"
TIMINGS_ENV = "TWIN_LOOP_TIMINGS"
VARIANTS = ("sync", "background")
# lerobot-rollout's console script, with each camera read, select_action, get/send_action, sleep and garbage
# collection timed: (wall start s, ms).
ROLLOUT = f"""
import atexit, json, os, sys, time
from lerobot_robot_piper.piper_twin_camera import PiperTwinCamera
from lerobot_robot_piper.piper_follower import PiperFollower
from lerobot_cso.policy import CSOPolicy
import lerobot.rollout.strategies.base as base
from lerobot.scripts.lerobot_rollout import main
timings = {{}}
def timed(key_of, original):
    def wrapper(self, *args, **kwargs):
        wall, start = time.time(), time.perf_counter()
        try:
            return original(self, *args, **kwargs)
        finally:
            timings.setdefault(key_of(self), []).append((wall, (time.perf_counter() - start) * 1e3))
    return wrapper
PiperTwinCamera.read_latest = timed(lambda cam: "camera " + cam.config.view, PiperTwinCamera.read_latest)
CSOPolicy.select_action = timed(lambda policy: "select_action", CSOPolicy.select_action)
PiperFollower.get_observation = timed(lambda robot: "get_observation", PiperFollower.get_observation)
PiperFollower.send_action = timed(lambda robot: "send_action", PiperFollower.send_action)
import gc
collecting = {{}}
def collection(phase, info):  # the garbage collector holds the GIL whatever thread it runs on
    if phase == "start":
        collecting["t"] = (time.time(), time.perf_counter())
    elif "t" in collecting:
        wall, start = collecting.pop("t")
        name = "gc generation %d" % info["generation"]
        timings.setdefault(name, []).append((wall, (time.perf_counter() - start) * 1e3))
gc.callbacks.append(collection)
def sleep(seconds, _sleep=base.precise_sleep):
    wall, start = time.time(), time.perf_counter()
    _sleep(seconds)
    timings.setdefault("sleep overshoot", []).append((wall, (time.perf_counter() - start - seconds) * 1e3))
base.precise_sleep = sleep
atexit.register(lambda: open(os.environ["{TIMINGS_ENV}"], "w").write(json.dumps(timings)))
sys.argv[0] = "lerobot-rollout"
sys.exit(main())
"""


def vision_settings(config: Path) -> tuple[dict, int]:
    """The camera policy's settings (without the device) and the image side of a config like metaworld_vision."""
    with open(config) as f:
        cfg = yaml.safe_load(f)
    policy = {k: v for k, v in cfg["il"]["policy"].items() if k != "device"}
    return policy, int(cfg["demos"]["image_size"])


def late_by_place(times: np.ndarray, start: float, select_calls: list, steps: int, limit_ms: float) -> list[int]:
    """Late periods (over ``limit_ms``) after ``start`` counted by their tick's place in its skill: the index of
    the ``select_action`` call before the command, modulo ``steps`` (call 0 refills the queue)."""
    calls = np.array([wall for wall, _ in select_calls])
    counts = [0] * steps
    for before, command in zip(times[:-1], times[1:], strict=True):
        if command >= start and (command - before) * 1000 > limit_ms:
            counts[int(np.searchsorted(calls, command, side="right") - 1) % steps] += 1
    return counts


def cpu_now(emulator_pid: int) -> np.ndarray:
    """CPU seconds (user + system) used so far by the emulator (a live process, /proc), by the children that ended
    (the rollout and its decode process) and by this process (the recorder's thread), then all CPUs' ticks since
    boot and, of them, those stolen by the hypervisor (/proc/stat)."""
    fields = Path(f"/proc/{emulator_pid}/stat").read_text().rsplit(")", 1)[1].split()
    emulator = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    children, own = resource.getrusage(resource.RUSAGE_CHILDREN), resource.getrusage(resource.RUSAGE_SELF)
    with open("/proc/stat") as f:
        ticks = [int(v) for v in f.readline().split()[1:]]
    used = [emulator, children.ru_utime + children.ru_stime, own.ru_utime + own.ru_stime]
    return np.array([*used, sum(ticks[:8]), ticks[7]], dtype=float)


def send_times(calls: list) -> np.ndarray:
    """When each of the loop's ``send_action`` calls returned (wall s): its commands are on the bus by then."""
    return np.array([wall + ms / 1000 for wall, ms in calls])


class LoopRun(NamedTuple):
    """What one rollout against the twin measured (after the first ``skip`` seconds)."""

    periods_ms: np.ndarray  # between joint commands
    calls: dict  # timed call name -> ms
    late_by_place: list[int]  # late periods by their tick's place in its skill
    cpu: dict[str, float]  # process -> share of one core during the rollout
    stolen: float  # the hypervisor's steal meanwhile, share of all cores' time
    late_with_gc: int  # late periods in which a generation 1 or 2 collection began


def loop_run(checkpoint: Path, home: Path, args: argparse.Namespace, side: int, raw: Path | None) -> LoopRun:
    """lerobot-rollout against a fresh twin, measured."""
    group, port = unique_udp_channel()
    state_group, state_port = unique_udp_channel()
    physics = ["--physics", f"--scene={args.scene}", "--scene-seed=3"]
    twin = start_emulator(group, port, *physics, f"--state-group={state_group}", f"--state-port={state_port}")
    cams = ", ".join(f"{c}: {CAMERA % (c, side, side, state_group, state_port)}" for c in args.cameras)
    recorder = ChannelRecorder(group, port) if args.clock == "bus" else None
    timings = home / "timings.json"
    robot = [
        "--robot.type=piper_follower",
        *twin.args("robot"),
        "--robot.feedback_timeout_s=1.0",  # the most a late emulator is allowed (it shares the CPUs)
        "--robot.enable_timeout_s=5",
        f"--robot.cameras={{{cams}}}",
    ]
    rollout = [*rollout_args(checkpoint, robot, TASK, args.duration, args.fps), "--return_to_initial_position=false"]
    command = ["nice", "-n", str(args.nice), str(BIN / "python"), "-c", ROLLOUT, *rollout]
    if args.fifo:  # real-time scheduling (as root): every thread of the rollout above every ordinary process
        command = ["chrt", "--fifo", str(args.fifo), *command]
    before, begin = cpu_now(twin.process.pid), time.monotonic()
    try:
        out = subprocess.run(
            command,
            capture_output=True,
            text=True,
            timeout=args.duration + 240,
            env=cli_env(home) | {TIMINGS_ENV: str(timings)},
            cwd=home,
        )
        used = cpu_now(twin.process.pid) - before
        share = used[:3] / (time.monotonic() - begin)
        # The benchmark's main thread only waits meanwhile: this process's CPU is the recorder's.
        cpu = dict(zip(("emulator", "rollout", "recorder"), share[: 3 if recorder is not None else 2], strict=False))
        stolen = used[4] / used[3]  # a VM's steal: the host ran someone else on our cores (no loop is on time then)
    finally:
        if recorder is not None:
            recorder.stop()
        twin.stop()
    if out.returncode != 0:
        raise RuntimeError(explain(out))
    timed = json.loads(timings.read_text()) if timings.exists() else {}
    sent = send_times(timed.get("send_action", []))
    times = np.array([c.time_s for c in recorder.commands.joints]) if recorder is not None else sent
    start = times[0] + args.skip  # the first commands: connection, the first decode
    calls = {name: np.array([ms for wall, ms in calls if wall >= start]) for name, calls in timed.items()}
    if recorder is not None:  # the cross-check: the same periods from the loop's own clock
        calls["period from send_action returns"] = np.diff(sent[sent >= start]) * 1000
    if raw is not None:
        raw.write_text(json.dumps({"command_time_s": times.tolist(), "clock": args.clock, "calls": timed}))
    steps = json.loads((checkpoint / "config.json").read_text())["n_action_steps"]
    limit_ms = 1.1 * 1000 / args.fps
    late = late_by_place(times, start, timed.get("select_action", []), steps, limit_ms)
    collections = [
        wall
        for name, calls in timed.items()
        if name != "gc generation 0" and name.startswith("gc ")
        for wall, _ in calls
    ]
    periods = np.diff(times[times >= start]) * 1000
    return LoopRun(periods, calls, late, cpu, stolen, late_with(times, start, collections, limit_ms))


def late_with(times: np.ndarray, start: float, events: list[float], limit_ms: float) -> int:
    """Late periods (over ``limit_ms``) after ``start`` during which one of ``events`` (wall s) began."""
    events = np.sort(np.array(events))
    count = 0
    for before, command in zip(times[:-1], times[1:], strict=True):
        if command >= start and (command - before) * 1000 > limit_ms:
            count += int(np.searchsorted(events, command) > np.searchsorted(events, before))
    return count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--lead", type=int, default=3)
    parser.add_argument("--skip", type=float, default=1.0, help="seconds dropped after the first joint command")
    parser.add_argument("--weights", default="float32")
    parser.add_argument("--cameras", type=lambda s: s.split(","), default=["front"], help="e.g. front,wrist")
    parser.add_argument("--scene", default="press_button", choices=("press_button", "cube_in_bowl"))
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "metaworld_vision.yaml")
    parser.add_argument("--nice", type=int, default=0, help="the rollout's niceness (negative: above the emulator's)")
    parser.add_argument("--fifo", type=int, default=0, metavar="P", help="the rollout at SCHED_FIFO P, 1-99 (root)")
    parser.add_argument("--variants", default="sync,background", help="comma-separated: sync, background")
    parser.add_argument(
        "--clock", default="bus", choices=("bus", "loop"), help="periods from the bus's receive times or the loop's"
    )
    parser.add_argument("--raw", type=Path, help="write each variant's command times and timed calls to FILE.<variant>")
    args = parser.parse_args()
    unknown = set(args.variants.split(",")) - set(VARIANTS)
    if unknown:
        parser.error(f"--variants: unknown {', '.join(sorted(unknown))} ({', '.join(VARIANTS)})")
    if not 0 <= args.fifo <= 99:
        parser.error(f"--fifo: a SCHED_FIFO priority is 1-99, got {args.fifo}")
    if args.fifo and os.geteuid() != 0:
        parser.error("--fifo: real-time scheduling needs root")
    if args.raw is not None and not os.access(args.raw.parent, os.W_OK):
        parser.error(f"--raw: cannot write in {args.raw.parent}")
    settings, side = vision_settings(args.config)
    limit_ms = 1.1 * 1000 / args.fps
    print(f"# command: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '')} python {shlex.join(sys.argv)}")
    views = ",".join(args.cameras)
    print(f"# policy: {args.config.name} il.policy, cameras {views} at {side}x{side}, scene {args.scene}")
    print(f"# rollout niceness {args.nice}" + (f", SCHED_FIFO priority {args.fifo}" if args.fifo else ""))
    with open("/proc/loadavg") as f:
        print(f"# load average before: {f.read().strip()}")
    with tempfile.TemporaryDirectory() as tmp:
        home = Path(tmp)
        for variant in args.variants.split(","):
            lead = args.lead if variant == "background" else 0
            name = f"background decode in a process, lead {lead}" if lead else "synchronous decode"
            begin = time.monotonic()
            checkpoint = save_untrained_piper_policy(
                home / f"policy_{variant}", lead, args.weights, settings, tuple(args.cameras), side, TASK
            )
            raw = None if args.raw is None else args.raw.with_name(f"{args.raw.name}.{variant}")
            run = loop_run(checkpoint, home, args, side, raw)
            clock = "the bus's receive times" if args.clock == "bus" else "the loop's send_action returns"
            report(f"{name} ({args.weights}), periods from {clock}", run.periods_ms, limit_ms)
            print(
                "CPU during the rollout (share of one core): "
                + ", ".join(f"{k} {v:.2f}" for k, v in run.cpu.items())
                + f"; stolen by the hypervisor: {100 * run.stolen:.1f} % of all cores' time"
            )
            print(f"late periods by the tick's place in its skill (0: refill): {run.late_by_place}; with a collection")
            print(f"of the garbage collector's generation 1 or 2 in them: {run.late_with_gc}")
            for call, ms in sorted(run.calls.items()):
                if len(ms):
                    print(
                        f"{call}: {len(ms)} calls, median {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms,"
                        f" max {ms.max():.2f} ms"
                        + (f", over {limit_ms:.1f} ms: {(ms > limit_ms).sum()}" if "period" in call else "")
                    )
            with open("/proc/loadavg") as f:
                print(f"# load average after: {f.read().strip()}; variant wall time {time.monotonic() - begin:.0f} s")


if __name__ == "__main__":
    main()
