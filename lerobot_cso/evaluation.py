"""``lerobot-cso eval``: per-task success rates of a policy, mean ± std over seeds.

Evaluation seed ``s`` fixes the sampling RNG and the initial states, which the world chooses
(:meth:`~lerobot_cso.worlds.base.World.eval_states`; on LIBERO every seed reuses the benchmark's 50 fixed
init states per task, as the paper's protocol does). On MetaWorld episode ``i`` of a task starts
from ``seeds.EVAL.start + s * seeds.EVAL_BLOCK + i``: the states are fixed per seed (the same for every
checkpoint), disjoint between seeds, and disjoint from every demo and training-rollout state
(:mod:`lerobot_cso.seeds`). The spread over seeds covers initial states and
sampling, so it is meaningful even with greedy decoding.

Default sampling is QueST's: top-k = 5 at temperature 1. The std is the sample std over seeds (ddof=1;
undefined, reported as null, with a single seed). Outputs: a markdown table on stdout, and ``eval.json``,
``eval.csv`` and ``eval.png`` (bar chart) in ``output_dir``. With ``video_episodes=N`` the first N episodes of
each task under the first evaluation seed are also written as videos of the camera the policy sees,
``videos/<task>/<initial state>_<success|failure>.mp4``, one frame per decision (the frames the policy read).
"""

import csv
import datetime as dt
import json
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from lerobot.configs import parser

from lerobot_cso import rollout_stage
from lerobot_cso.durable import output_lock, read_json
from lerobot_cso.errors import UsageError, check_output_dir, interruptible
from lerobot_cso.rollout_stage import RolloutStageConfig, policy_features
from lerobot_cso.worlds.base import camera_inputs


@dataclass
class EvalConfig(RolloutStageConfig):
    """Settings of ``lerobot-cso eval`` (``--policy.path=... --tasks=MT10 --seeds=0,1,2``)."""

    records_frames: ClassVar[bool] = False  # only outcomes are kept

    tasks: str = "ML45-train"
    episodes_per_task: int = 50
    # Comma list of evaluation seeds; each picks its own block of initial states and sampling RNG.
    seeds: str = "0"
    # Videos of the first N episodes per task of the first seed (the policy's camera; needs a camera policy).
    video_episodes: int = 0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.output_dir is None:
            self.output_dir = Path("outputs/eval/cso") / f"{dt.datetime.now():%Y-%m-%d_%H-%M-%S}"

    def eval_seeds(self) -> list[int]:
        try:
            values = [int(s) for s in self.seeds.split(",") if s.strip()]
        except ValueError:
            raise UsageError(f"seeds must be a comma list of integers, got '{self.seeds}'") from None
        n_seeds = self.rollout_world().eval_seeds
        if not values or any(not 0 <= s < n_seeds for s in values) or len(set(values)) != len(values):
            raise UsageError(f"seeds must be distinct integers in [0, {n_seeds}), got '{self.seeds}'")
        return values

    def validate(self) -> list[str]:
        """Check every setting; returns the resolved task list. Raises ``UsageError``."""
        tasks = super().validate()
        most = self.rollout_world().eval_states_per_seed
        if not 0 < self.episodes_per_task <= most:
            raise UsageError(f"episodes_per_task must be in [1, {most}], got {self.episodes_per_task}")
        if not 0 <= self.video_episodes <= self.episodes_per_task:
            raise UsageError(f"video_episodes must be in [0, episodes_per_task], got {self.video_episodes}")
        features = policy_features(self)  # none on the pipeline's stand-in for a policy still to be trained
        if self.video_episodes and features and not camera_inputs(features, self.rollout_world()):
            raise UsageError("video_episodes: the policy reads no camera, so there is no frame to write")
        if self.video_episodes:
            check_output_dir(self.output_dir / "videos", "--video_episodes: its folder")
        self.eval_seeds()
        return tasks


def write_videos(output_dir: Path, episodes: list[Any], camera: str, fps: float) -> list[Path]:
    """One MP4 per episode of the frames its decisions read (LeRobot's ``write_video``), plus its last frame."""
    from lerobot.utils.io_utils import write_video

    paths = []
    for e in episodes:
        frames = e.images[camera]
        steps = [*e.decision_steps.tolist(), len(frames) - 1]
        path = output_dir / "videos" / e.task / f"{e.init_seed}_{'success' if e.success else 'failure'}.mp4"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_video(path, [frames[t].numpy() for t in steps], fps=max(1, round(fps)))
        paths.append(path)
    return paths


def _stats(values: list[float]) -> tuple[float, float | None]:
    mean = float(np.mean(values))
    return mean, (float(np.std(values, ddof=1)) if len(values) > 1 else None)


def standard_error(rate: float, episodes: int) -> float:
    """Binomial standard error of a success rate measured on ``episodes`` independent episodes."""
    return float(np.sqrt(rate * (1 - rate) / episodes))


def summarize(success: dict[str, dict[int, float]], episodes_per_task: int | None = None) -> dict[str, Any]:
    """Per task and overall (mean over tasks, per seed): success rates per seed, mean and std over seeds.

    With ``episodes_per_task`` (per seed), each row also has ``se``, the binomial standard error of its mean
    over all its episodes; the overall one is sqrt(sum of the tasks' se²) / number of tasks.
    """
    seed_list = sorted(next(iter(success.values())))
    rows = {}
    for task, per_seed in success.items():
        mean, std = _stats([per_seed[s] for s in seed_list])
        rows[task] = {"per_seed": {str(s): per_seed[s] for s in seed_list}, "mean": mean, "std": std}
        if episodes_per_task is not None:
            rows[task]["se"] = standard_error(mean, episodes_per_task * len(seed_list))
    overall_per_seed = {s: float(np.mean([success[t][s] for t in success])) for s in seed_list}
    mean, std = _stats(list(overall_per_seed.values()))
    rows["overall"] = {"per_seed": {str(s): v for s, v in overall_per_seed.items()}, "mean": mean, "std": std}
    if episodes_per_task is not None:
        rows["overall"]["se"] = float(np.sqrt(sum(rows[t]["se"] ** 2 for t in success)) / len(success))
    return rows


def markdown_table(rows: dict[str, Any]) -> str:
    """Success rates in % as a markdown table: one column per seed, then mean ± std."""
    seed_names = list(next(iter(rows.values()))["per_seed"])
    lines = [
        "| task | " + " | ".join(f"seed {s}" for s in seed_names) + " | mean ± std |",
        "|---|" + "---:|" * (len(seed_names) + 1),
    ]
    for task, row in rows.items():
        cells = [f"{100 * v:.1f}" for v in row["per_seed"].values()]
        spread = "" if row["std"] is None else f" ± {100 * row['std']:.1f}"
        name = f"**{task}**" if task == "overall" else task
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {100 * row['mean']:.1f}{spread} |")
    return "\n".join(lines)


def write_outputs(output_dir: Path, rows: dict[str, Any], record: dict[str, Any]) -> None:
    """``eval.json`` (everything), ``eval.csv`` (the table) and ``eval.png`` (bar chart with std error bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "eval.json").write_text(json.dumps({**record, "success_rate": rows}, indent=2))
    seed_names = list(next(iter(rows.values()))["per_seed"])
    with open(output_dir / "eval.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["task", *(f"seed_{s}" for s in seed_names), "mean", "std"])
        for task, row in rows.items():
            std = "" if row["std"] is None else row["std"]
            writer.writerow([task, *row["per_seed"].values(), row["mean"], std])
    names = list(rows)
    means = [100 * rows[n]["mean"] for n in names]
    errors = [0.0 if rows[n]["std"] is None else 100 * rows[n]["std"] for n in names]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.35 * len(names) + 2), 4.5))
    colors = ["tab:orange" if n == "overall" else "tab:blue" for n in names]
    ax.bar(names, means, yerr=errors, capsize=3, color=colors)
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(0, 105)
    ax.set_title(f"{record['policy_path']} — {len(seed_names)} seed(s) × {record['episodes_per_task']} episodes")
    ax.tick_params(axis="x", labelrotation=90)
    fig.tight_layout()
    fig.savefig(output_dir / "eval.png", dpi=100)
    plt.close(fig)


def evaluate(cfg: EvalConfig) -> dict[str, Any]:
    """Run the evaluation; returns the summary rows (also written to ``cfg.output_dir``)."""
    from lerobot_cso import distributed
    from lerobot_cso.checkpoints import load_policy

    tasks = cfg.validate()
    eval_seed_list = cfg.eval_seeds()
    path = cfg.policy.pretrained_path
    policy, pre, post = load_policy(path, cfg.policy)
    world = cfg.rollout_world()
    camera = next(iter(camera_inputs(policy.config.input_features, world).values()), None)  # the one filmed
    success: dict[str, dict[int, float]] = {task: {} for task in tasks}
    episodes, throughput, videos = [], [], []
    with distributed.ShardedRollouts(rollout_stage.stage_engine(policy, pre, post, cfg)) as engine:
        for s in eval_seed_list:
            states = [(task, init) for task in tasks for init in world.eval_states(task, s, cfg.episodes_per_task)]
            first = s == eval_seed_list[0]
            filmed = [i for i in range(len(states)) if first and i % cfg.episodes_per_task < cfg.video_episodes]
            result = engine.rollout(
                states, k=1, sampling=cfg.sampling, seed=s, progress=f"eval seed {s}", keep_frames=filmed
            )
            if filmed and distributed.is_main():
                kept = [result.episodes[i] for i in filmed]
                fps = world.fps / policy.config.n_action_steps
                videos += [str(p) for p in write_videos(cfg.output_dir, kept, camera, fps)]
            for task in tasks:
                success[task][s] = float(np.mean([e.success for e in result.episodes if e.task == task]))
            episodes += [
                {"seed": s, "task": e.task, "init_seed": e.init_seed, "success": e.success, "length": e.length}
                for e in result.episodes
            ]
            throughput.append(
                {"seed": s, "env_steps_per_s": result.env_steps_per_s, "decisions_per_s": result.decisions_per_s}
            )
    rows = summarize(success, cfg.episodes_per_task)
    record = {
        "policy_path": str(path),
        "tasks": tasks,
        "episodes_per_task": cfg.episodes_per_task,
        "seeds": eval_seed_list,
        "sampling": asdict(cfg.sampling),
        "max_steps": cfg.horizon(),
        "world": world.name,
        "throughput": throughput,
        "episodes": episodes,
        "videos": videos,
    }
    if distributed.is_main():
        write_outputs(cfg.output_dir, rows, record)
    distributed.wait_for_everyone()
    return rows


class EvalStage:
    """A pipeline evaluation (``eval_<label>``), redone whenever its settings or its policy change."""

    redo_on_change = True
    grows = ()

    def __init__(self, label: str, cfg: EvalConfig) -> None:
        self.name, self.cfg = f"eval_{label}", cfg

    def spec(self) -> dict[str, Any]:
        return {"eval": self.cfg.stage_spec()}

    def output(self) -> Path:
        return self.cfg.output_dir

    def complete(self) -> bool:
        return (self.cfg.output_dir / "eval.json").is_file()

    def run(self) -> dict[str, Any]:
        rows = evaluate(self.cfg)
        print(markdown_table(rows), flush=True)
        return rows

    def success_rate(self) -> dict[str, Any]:
        """The summary rows of the finished evaluation."""
        return read_json(self.cfg.output_dir / "eval.json")["success_rate"]


@parser.wrap()
def eval_main(cfg: EvalConfig) -> None:
    """Entry point of ``lerobot-cso eval``: the main process holds the output dir's lock while it evaluates."""
    from lerobot_cso import distributed

    with (
        output_lock(cfg.output_dir) if distributed.is_main() else nullcontext(),
        interruptible(f"evaluating into {cfg.output_dir}"),
    ):
        rows = evaluate(cfg)
    print(markdown_table(rows))
    print(f"\nwrote {cfg.output_dir}/eval.json, eval.csv, eval.png")
