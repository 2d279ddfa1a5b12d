"""IL step rate: ``lerobot-train`` vs ``python -m lerobot_cso.train`` (in-memory frames), side by side.

Each variant trains the demo's policy (``configs/metaworld_demo.yaml``'s ``il.policy``, batch 64) on the same
demos for ``--steps`` steps (the first ``--steps // 4`` in the autoencoder phase), and the variants alternate for
``--rounds`` rounds so that load from other processes hits them alike. Printed: wall seconds and steps/s per
variant and round (start-up included, the same for both).

    python benchmarks/il_data_path.py --demos=outputs/pipeline/metaworld_demo/demos
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import draccus

from lerobot_cso.il import cli_value
from lerobot_cso.pipeline import PipelineConfig

VARIANTS = {  # name: (command, dataloader workers, torch threads)
    "lerobot-train, 2 workers, 1 thread": ([str(Path(sys.executable).parent / "lerobot-train")], 2, 1),
    "in-memory, 0 workers, 1 thread": ([sys.executable, "-m", "lerobot_cso.train"], 0, 1),
    "in-memory, 0 workers, 2 threads": ([sys.executable, "-m", "lerobot_cso.train"], 0, 2),
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", type=Path, required=True, help="a LeRobotDataset root (e.g. the demo's demos/)")
    parser.add_argument("--repo_id", default="local/metaworld_demos")
    parser.add_argument("--config", type=Path, default=Path("configs/metaworld_demo.yaml"))
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    with open(args.config) as f:
        policy = draccus.load(PipelineConfig, f).il.policy
    rates: dict[str, list[float]] = {name: [] for name in VARIANTS}
    for round_ in range(args.rounds):
        for name, (command, workers, threads) in VARIANTS.items():
            with tempfile.TemporaryDirectory() as tmp:
                cmd = [
                    *command,
                    "--policy.type=cso",
                    f"--output_dir={tmp}/run",
                    f"--dataset.root={args.demos}",
                    f"--dataset.repo_id={args.repo_id}",
                    "--dataset.video_backend=pyav",
                    f"--steps={args.steps}",
                    f"--num_workers={workers}",
                    "--batch_size=64",
                    f"--save_freq={args.steps}",
                    f"--log_freq={args.steps}",
                    "--policy.push_to_hub=false",
                    f"--policy.n_autoencoder_steps={args.steps // 4}",
                    *(f"--policy.{k}={cli_value(v)}" for k, v in policy.items()),
                ]
                env = os.environ | {"OMP_NUM_THREADS": str(threads)}
                started = time.perf_counter()
                subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                seconds = time.perf_counter() - started
            rates[name].append(args.steps / seconds)
            print(f"round {round_ + 1} | {name}: {seconds:.1f} s, {args.steps / seconds:.2f} steps/s", flush=True)
    print("\n| variant | steps/s per round |\n|---|---|")
    for name, values in rates.items():
        print(f"| {name} | {', '.join(f'{v:.2f}' for v in values)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
