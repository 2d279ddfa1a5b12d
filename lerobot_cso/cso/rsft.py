"""Stage 1 of CSO, R-SFT (Algorithm 1 lines 1–11, Eq. 6, App. E.2 and G): ``lerobot-cso rsft``.

**Collection.** Per task, initial states are drawn in order from the R-SFT part of the training seed range.
From each state the IL policy runs ``n_strikes`` attempts (one group, batched) with exploratory sampling
(temperature / top-k above evaluation's); every success is kept until the task has ``successes_per_task``;
a state where all attempts fail is struck out and the next state is drawn.

**Durability.** ``<output_dir>/journal`` is the source of truth: each kept success is written atomically as
``episodes/<task>/<seed>_<attempt>.npz`` the moment its episode finishes, and a state's record
``states/<task>/<seed>.json`` (attempts, successes) after all its episodes. A rerun after ``kill -9`` skips
recorded states and drops episode files of unrecorded ones, so nothing is lost or duplicated. When every
task is full, the journal is materialised as the **success buffer**, a LeRobotDataset v3 at
``<output_dir>/buffer`` with the executed actions, the observations, and per frame the tokens of the skill
being executed (``observation.skill_tokens``), whether the frame is the one the skill was sampled from
(``observation.skill_start``) and the decision index (``observation.skill_step``), plus episode metadata.

**Fine-tuning (Eq. 6).** The whole policy is trained on the stored (observation, skill) pairs of the decision
frames (AdamW, cosine lr schedule, ``epochs`` epochs, state saved after each epoch), then its observation
encoders are frozen and ``<output_dir>/pretrained_model`` is saved with ``freeze_encoders: true``.
"""

import json
import math
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from accelerate import Accelerator
from lerobot.configs import parser
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from tqdm import tqdm

from lerobot_cso.checkpoints import (
    PolicyPathConfig,
    load_policy,
    replace_dir,
    restore_interrupted_replace,
    save_checkpoint,
    write_atomic,
)
from lerobot_cso.envs import seeds
from lerobot_cso.envs.constants import ACTION_DIM, FPS, HORIZON, STATE_DIM
from lerobot_cso.envs.tasks import resolve_tasks, task_description
from lerobot_cso.errors import UsageError
from lerobot_cso.policy.configuration_cso import SKILL_START_KEY, SKILL_STEP_KEY, SKILL_TOKENS_KEY
from lerobot_cso.rollout.engine import Episode, InitialState, RolloutEngine, Sampling

# R-SFT draws its initial states from the first half of the training range, SPO from the second.
RSFT_SEED_OFFSET = 0
TASK_KEY, SEED_KEY, ATTEMPT_KEY, TEMPERATURE_KEY = "rsft.task", "rsft.init_seed", "rsft.attempt", "rsft.temperature"


@dataclass
class RSFTConfig(PolicyPathConfig):
    """Settings of ``lerobot-cso rsft --policy.path=<IL checkpoint> --tasks=MT10 --output_dir=...``."""

    tasks: str = "MT10"
    output_dir: Path = Path("outputs/rsft")
    # Collection (Algorithm 1, App. E.2 / G).
    successes_per_task: int = 200
    n_strikes: int = 10
    temperature: float = 1.5
    top_k: int | None = 10
    states_per_round: int = 2  # new initial states per unfinished task per batched rollout call
    max_states_per_task: int = 2000
    num_envs: int = 16
    max_steps: int = HORIZON  # episode cap of the rollouts (a failure runs to the cap)
    seed: int = 0
    # Fine-tuning (Eq. 6, App. E.2).
    epochs: int = 20
    batch_size: int = 256
    lr: float = 1e-4
    min_lr: float = 1e-5
    weight_decay: float = 1e-4
    grad_clip_norm: float = 100.0
    # Publishing the success buffer with LeRobot's push_to_hub.
    push_to_hub: bool = False
    repo_id: str = "local/cso_rsft_buffer"

    def validate(self) -> list[str]:
        if self.policy is None or self.policy.pretrained_path is None:
            raise UsageError("--policy.path is required (the IL checkpoint's pretrained_model directory)")
        try:
            tasks = resolve_tasks(self.tasks)
        except ValueError as e:
            raise UsageError(str(e)) from None
        for name in (
            "successes_per_task",
            "n_strikes",
            "states_per_round",
            "max_states_per_task",
            "num_envs",
            "epochs",
            "batch_size",
        ):
            if getattr(self, name) < (0 if name == "epochs" else 1):
                raise UsageError(f"{name} must be >= {0 if name == 'epochs' else 1}, got {getattr(self, name)}")
        if not 1 <= self.max_steps <= HORIZON:
            raise UsageError(f"max_steps must be in [1, {HORIZON}], got {self.max_steps}")
        if self.temperature <= 0 or (self.top_k is not None and self.top_k < 1):
            raise UsageError("temperature must be > 0 and top_k >= 1 (or null)")
        if self.push_to_hub and self.repo_id.startswith("local/"):
            raise UsageError("--push_to_hub=true needs --repo_id=<user>/<name>")
        unknown = [t for t in tasks if task_description(t) not in self.policy.tasks]
        if unknown:
            raise UsageError(f"the policy was not trained on {', '.join(unknown)}")
        return tasks

    def spec(self) -> dict[str, Any]:
        """Settings that define the buffer; a journal made with other settings is refused."""
        keys = ("tasks", "successes_per_task", "n_strikes", "temperature", "top_k", "seed")
        return {k: getattr(self, k) for k in keys} | {"policy": str(self.policy.pretrained_path)}


class Journal:
    """Durable per-episode store of the collection (see the module docstring)."""

    def __init__(self, root: Path, spec: dict[str, Any]) -> None:
        self.root = root
        spec_path = root / "spec.json"
        if spec_path.exists() and json.loads(spec_path.read_text()) != spec:
            raise UsageError(f"{root} holds a collection made with other settings; choose another --output_dir")
        (root / "episodes").mkdir(parents=True, exist_ok=True)
        (root / "states").mkdir(parents=True, exist_ok=True)
        write_atomic(spec_path, json.dumps(spec, indent=2).encode())

    def states(self, task: str) -> dict[int, dict[str, int]]:
        """Recorded initial states of a task: seed → {attempts, successes}."""
        return {int(p.stem): json.loads(p.read_text()) for p in (self.root / "states" / task).glob("*.json")}

    def episode_files(self, task: str) -> list[Path]:
        return sorted((self.root / "episodes" / task).glob("*.npz"))

    def drop_unrecorded(self, task: str) -> None:
        """Remove episodes of states whose record is missing (a run killed mid-state); they get redone."""
        recorded = self.states(task)
        for path in self.episode_files(task):
            if int(path.stem.split("_")[0]) not in recorded:
                path.unlink()

    def save_episode(self, episode: Episode, sampling: Sampling) -> None:
        path = self.root / "episodes" / episode.task / f"{episode.init_seed:07d}_{episode.sample:03d}.npz"
        path.parent.mkdir(exist_ok=True)
        arrays = {
            "states": episode.states.numpy(),
            "actions": episode.actions.numpy(),
            "decision_steps": episode.decision_steps.numpy(),
            "tokens": episode.tokens.numpy(),
            "logprobs": episode.logprobs.numpy(),
            "temperature": np.float32(sampling.temperature),
        }
        arrays.update({f"image_{cam}": frames.numpy() for cam, frames in episode.images.items()})
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        tmp.replace(path)

    def save_state(self, task: str, seed: int, attempts: int, successes: int) -> None:
        directory = self.root / "states" / task
        directory.mkdir(exist_ok=True)
        record = {"attempts": attempts, "successes": successes}
        write_atomic(directory / f"{seed:07d}.json", json.dumps(record).encode())


def collection_report(journal: Journal, tasks: list[str]) -> dict[str, dict[str, int]]:
    """Per task (the paper's Table 7): rollouts run, successes seen, kept, states tried and struck out."""
    report = {}
    for task in tasks:
        states = journal.states(task).values()
        report[task] = {
            "rollouts": sum(s["attempts"] for s in states),
            "successes": sum(s["successes"] for s in states),
            "kept": len(journal.episode_files(task)),
            "states_tried": len(states),
            "states_struck_out": sum(s["successes"] == 0 for s in states),
        }
    return report


def collect(cfg: RSFTConfig, tasks: list[str], engine: RolloutEngine, journal: Journal) -> None:
    """Roll out until every task holds ``successes_per_task`` successes (Algorithm 1, lines 2–9)."""
    sampling = Sampling(temperature=cfg.temperature, top_k=cfg.top_k)
    for task in tasks:
        journal.drop_unrecorded(task)
    progress = tqdm(total=cfg.successes_per_task * len(tasks), desc="R-SFT successes")
    progress.update(sum(len(journal.episode_files(t)) for t in tasks))
    while True:
        kept = {t: len(journal.episode_files(t)) for t in tasks}
        todo = [t for t in tasks if kept[t] < cfg.successes_per_task]
        if not todo:
            break
        requests = []
        for task in todo:
            tried = journal.states(task)
            if len(tried) >= cfg.max_states_per_task:
                raise UsageError(
                    f"{task}: only {kept[task]} successes after {len(tried)} initial states; the IL policy "
                    f"rarely solves it (raise --max_states_per_task or lower --successes_per_task)"
                )
            fresh = [s for s in seeds.train_seeds(cfg.max_states_per_task, RSFT_SEED_OFFSET) if s not in tried]
            requests += [InitialState(task, s) for s in fresh[: cfg.states_per_round]]
        round_seed = cfg.seed * 1_000_003 + requests[0].seed
        needed = dict(kept)

        def keep(episode: Episode, needed: dict[str, int] = needed) -> None:
            if episode.success and needed[episode.task] < cfg.successes_per_task:
                needed[episode.task] += 1
                journal.save_episode(episode, sampling)
                progress.update(1)

        result = engine.rollout(requests, k=cfg.n_strikes, sampling=sampling, seed=round_seed, on_episode=keep)
        for group in result.groups():
            first = group[0]
            journal.save_state(first.task, first.init_seed, len(group), sum(e.success for e in group))
    progress.close()


def buffer_features(cameras: list[str], n_tokens: int, image_shapes: dict[str, tuple[int, ...]]) -> dict[str, Any]:
    features: dict[str, Any] = {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
        "action": {"dtype": "float32", "shape": (ACTION_DIM,), "names": ["dx", "dy", "dz", "gripper"]},
        SKILL_TOKENS_KEY: {"dtype": "int64", "shape": (n_tokens,), "names": None},
        SKILL_START_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        SKILL_STEP_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        TASK_KEY: {"dtype": "string", "shape": (1,), "names": None},
        SEED_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        ATTEMPT_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        TEMPERATURE_KEY: {"dtype": "float32", "shape": (1,), "names": None},
    }
    for cam in cameras:
        features[f"observation.images.{cam}"] = {
            "dtype": "image",
            "shape": image_shapes[cam],
            "names": ["height", "width", "channel"],
        }
    return features


def write_buffer(cfg: RSFTConfig, tasks: list[str], journal: Journal, n_tokens: int) -> Path:
    """Materialise the journal as the success buffer (a LeRobotDataset v3), atomically."""
    out = cfg.output_dir / "buffer"
    work = cfg.output_dir / "buffer.tmp"
    shutil.rmtree(work, ignore_errors=True)
    files = [p for t in tasks for p in journal.episode_files(t)]
    with np.load(files[0]) as first:
        cameras = sorted(k.removeprefix("image_") for k in first.files if k.startswith("image_"))
        image_shapes = {cam: tuple(first[f"image_{cam}"].shape[1:]) for cam in cameras}
    features = buffer_features(cameras, n_tokens, image_shapes)
    ds = LeRobotDataset.create(cfg.repo_id, FPS, features, root=work, robot_type="sawyer", use_videos=False)
    for path in tqdm(files, desc="writing R-SFT buffer", leave=False):
        task = path.parent.name
        seed, attempt = (int(x) for x in path.stem.split("_"))
        with np.load(path) as ep:
            steps = ep["decision_steps"]
            skill = np.searchsorted(steps, np.arange(len(ep["actions"])), side="right") - 1
            for t in range(len(ep["actions"])):
                frame = {
                    "observation.state": ep["states"][t],
                    "action": ep["actions"][t],
                    SKILL_TOKENS_KEY: ep["tokens"][skill[t]].astype(np.int64),
                    SKILL_START_KEY: np.array([int(steps[skill[t]] == t)], dtype=np.int64),
                    SKILL_STEP_KEY: np.array([skill[t]], dtype=np.int64),
                    TASK_KEY: task,
                    SEED_KEY: np.array([seed], dtype=np.int64),
                    ATTEMPT_KEY: np.array([attempt], dtype=np.int64),
                    TEMPERATURE_KEY: np.array([ep["temperature"]], dtype=np.float32),
                    "task": task_description(task),
                }
                frame.update({f"observation.images.{cam}": ep[f"image_{cam}"][t] for cam in cameras})
                ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    replace_dir(work, out)
    return out


def cosine_lr(step: int, total: int, lr: float, min_lr: float) -> float:
    return min_lr + (lr - min_lr) * 0.5 * (1 + math.cos(math.pi * min(1.0, step / max(1, total))))


def finetune(cfg: RSFTConfig, buffer: Path) -> Path:
    """Eq. 6 on the buffer's decision frames, then freeze the encoders and save the checkpoint."""
    torch.manual_seed(cfg.seed)  # dropout and initialisation noise: same config, same checkpoint
    policy, pre, post = load_policy(cfg.policy.pretrained_path, cfg.policy)
    policy.set_encoders_frozen(False)
    # Action chunks are only read by QueST's optional decoder loss (and cost LeRobot a query per frame).
    chunk = {"action": [i / FPS for i in range(policy.config.chunk_size)]}
    ds = LeRobotDataset(cfg.repo_id, root=buffer, delta_timestamps=chunk if policy.config.decoder_loss_scale else None)
    starts = np.flatnonzero(np.asarray(ds.hf_dataset[SKILL_START_KEY]).reshape(-1) == 1)
    generator = torch.Generator().manual_seed(cfg.seed)
    loader = torch.utils.data.DataLoader(
        torch.utils.data.Subset(ds, starts.tolist()), batch_size=cfg.batch_size, shuffle=True, generator=generator
    )
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    accelerator = Accelerator(cpu=policy.config.device == "cpu")
    policy, optimizer, loader = accelerator.prepare(policy, optimizer, loader)
    state_dir, epoch_file = cfg.output_dir / "train_state", cfg.output_dir / "train_state" / "epoch.json"
    restore_interrupted_replace(state_dir)
    start_epoch = json.loads(epoch_file.read_text())["epochs_done"] if epoch_file.exists() else 0
    if start_epoch:
        accelerator.load_state(state_dir)
    total = cfg.epochs * len(loader)
    policy.train()
    for epoch in range(start_epoch, cfg.epochs):
        losses = []
        for i, batch in enumerate(tqdm(loader, desc=f"R-SFT epoch {epoch + 1}/{cfg.epochs}", leave=False)):
            for group in optimizer.param_groups:
                group["lr"] = cosine_lr(epoch * len(loader) + i, total, cfg.lr, cfg.min_lr)
            loss, _ = policy(pre(batch))
            optimizer.zero_grad()
            accelerator.backward(loss)
            accelerator.clip_grad_norm_(policy.parameters(), cfg.grad_clip_norm)
            optimizer.step()
            losses.append(float(loss.detach()))
        print(f"R-SFT epoch {epoch + 1}/{cfg.epochs}: skill NLL {np.mean(losses):.4f} ({len(starts)} decisions)")
        tmp = cfg.output_dir / "train_state.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        accelerator.save_state(tmp)
        write_atomic(tmp / "epoch.json", json.dumps({"epochs_done": epoch + 1}).encode())
        replace_dir(tmp, state_dir)
    policy = accelerator.unwrap_model(policy)
    policy.set_encoders_frozen(True)  # Algorithm 1, line 11
    out = cfg.output_dir / "pretrained_model"
    save_checkpoint(out, policy, pre, post)
    return out


def run_rsft(cfg: RSFTConfig, make_engine: Callable[..., RolloutEngine] = RolloutEngine) -> dict[str, Any]:
    """Collect (resumable), write the buffer, optionally push it, fine-tune; returns the collection report.

    ``make_engine(policy, preprocessor, postprocessor, num_envs=..., max_steps=...)`` builds the rollout engine.
    """
    tasks = cfg.validate()
    if (cfg.output_dir / "pretrained_model" / "config.json").is_file():
        print(f"{cfg.output_dir / 'pretrained_model'} exists: R-SFT already complete")
        return json.loads((cfg.output_dir / "collection.json").read_text())
    journal = Journal(cfg.output_dir / "journal", cfg.spec())
    restore_interrupted_replace(cfg.output_dir / "buffer")
    if not (cfg.output_dir / "buffer" / "meta" / "info.json").is_file():
        policy, pre, post = load_policy(cfg.policy.pretrained_path, cfg.policy)
        with make_engine(policy, pre, post, num_envs=cfg.num_envs, max_steps=cfg.max_steps) as engine:
            collect(cfg, tasks, engine, journal)
        write_buffer(cfg, tasks, journal, policy.config.n_tokens)
    report = collection_report(journal, tasks)
    write_atomic(cfg.output_dir / "collection.json", json.dumps(report, indent=2).encode())
    print(report_table(report))
    if cfg.push_to_hub:
        LeRobotDataset(cfg.repo_id, root=cfg.output_dir / "buffer").push_to_hub()
    finetune(cfg, cfg.output_dir / "buffer")
    return report


def report_table(report: dict[str, dict[str, int]]) -> str:
    lines = ["| task | rollouts | successes | kept | states tried | struck out |", "|---|---:|---:|---:|---:|---:|"]
    for task, r in report.items():
        lines.append(
            f"| {task} | {r['rollouts']} | {r['successes']} | {r['kept']} | {r['states_tried']} | "
            f"{r['states_struck_out']} |"
        )
    return "\n".join(lines)


@parser.wrap()
def rsft_main(cfg: RSFTConfig) -> None:
    """Entry point of ``lerobot-cso rsft``."""
    run_rsft(cfg)
    print(f"R-SFT checkpoint (encoders frozen): {cfg.output_dir / 'pretrained_model'}")
