"""A before/after strip from the videos of two or more evaluations on the same initial states (README's picture).

    python benchmarks/video_strip.py --evals=IL:outputs/.../eval/il,CSO:outputs/.../eval/cso \\
        --tasks=button-press-topdown-v3,door-open-v3 --state=2000001 --frames=7 --out=docs/img/vision_strip.png

For each task, one filmed episode (``--state``, or the lowest filmed initial state; the same states for every
evaluation of one config) is shown as one row per evaluation: ``--frames`` frames evenly spaced over the episode,
titled with the outcome.
"""

import argparse
from pathlib import Path

import av
import matplotlib
import numpy as np


def frames_of(video: Path) -> list[np.ndarray]:
    with av.open(str(video)) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]


def video_of(eval_dir: Path, task: str, state: int | None) -> Path:
    """The video of ``state`` (the lowest filmed state when None) of ``task`` in an evaluation's output."""
    videos = sorted((eval_dir / "videos" / task).glob("*.mp4"), key=lambda p: int(p.name.split("_")[0]))
    if state is not None:
        videos = [v for v in videos if int(v.name.split("_")[0]) == state]
    if not videos:
        filmed = "" if state is None else f" of state {state}"
        raise SystemExit(f"error: {eval_dir} has no video{filmed} of {task} (evaluate with --video_episodes=N)")
    return videos[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--evals", required=True, help="LABEL:DIR,LABEL:DIR,... (evaluation output dirs)")
    parser.add_argument("--tasks", required=True)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--state", type=int, default=None, help="the filmed initial state (default: the lowest)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    evals = [(label, Path(d)) for label, d in (item.split(":", 1) for item in args.evals.split(","))]
    tasks = args.tasks.split(",")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(task, label, video_of(d, task, args.state)) for task in tasks for label, d in evals]
    fig, axes = plt.subplots(len(rows), args.frames, figsize=(1.3 * args.frames, 1.45 * len(rows)), squeeze=False)
    for ax_row, (task, label, video) in zip(axes, rows, strict=True):
        frames = frames_of(video)
        picks = np.linspace(0, len(frames) - 1, args.frames).round().astype(int)
        for ax, t in zip(ax_row, picks, strict=True):
            ax.imshow(frames[t])
            ax.set_xticks([])
            ax.set_yticks([])
        outcome = video.stem.split("_")[1]
        ax_row[0].set_ylabel(f"{label}\n{outcome}", fontsize=8)
        ax_row[0].set_title(f"{task}, state {video.stem.split('_')[0]}", fontsize=8, loc="left")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
