"""Stage 1 of CSO, R-SFT (Algorithm 1 lines 1–11, Eq. 6, App. E.2 and G): ``lerobot-cso rsft``.

**Collection.** Per task, initial states are drawn in order from the R-SFT part of the training seed range.
From each state the IL policy runs ``n_strikes`` attempts (one group, batched) with exploratory sampling
(temperature / top-k above evaluation's); every success (or, with ``max_successes_per_state``, the first few
of a state) is kept until the task has ``successes_per_task``; a state where all attempts fail is struck out
and the next state is drawn.

**Durability.** ``<output_dir>/journal`` (a :class:`~lerobot_cso.durable.EpisodeJournal`) is the source of
truth: each kept success is written atomically as ``episodes/<task>/<seed>_<attempt>.npz`` the moment its
episode finishes, and a state's record ``records/<task>/<seed>.json`` (attempts, successes) after all its
episodes. A rerun after ``kill -9`` skips
recorded states and drops episode files of unrecorded ones, so nothing is lost or duplicated. When every
task is full, the journal is materialised as the **success buffer**, a LeRobotDataset v3 at
``<output_dir>/buffer`` with the executed actions, the observations, and per frame the tokens of the skill
being executed (``observation.skill_tokens``), whether the frame is the one the skill was sampled from
(``observation.skill_start``) and the decision index (``observation.skill_step``), plus episode metadata.
With ``buffer_frames: decisions`` a camera world renders only the decision frames, the ones the fine-tune reads;
the buffer's other frames then repeat the image of their skill's decision frame (``observation.skill_start``
marks the true ones).

**Fine-tuning (Eq. 6).** The whole policy is trained on the stored (observation, skill) pairs of the decision
frames (uniformly, or with ``advantage_weighted`` each drawn in proportion to its state's Eq. 8 advantage) the
way ``lerobot-train`` trains it (the policy's AdamW and cosine presets at R-SFT's ``lr`` /
``min_lr``, LeRobot's ``update_policy`` step, ``epochs`` epochs, state saved after each epoch), then its
observation encoders are frozen and ``<output_dir>/pretrained_model`` is saved with ``freeze_encoders: true``.
"""

import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from datasets.exceptions import DatasetGenerationError
from lerobot.configs import parser
from lerobot.configs.types import FeatureType
from lerobot.datasets.lerobot_dataset import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.scripts.lerobot_train import update_policy
from lerobot.utils.logging_utils import MetricsTracker
from tqdm import tqdm

from lerobot_cso import distributed, rollout_stage, seeds
from lerobot_cso.checkpoints import load_policy, save_checkpoint
from lerobot_cso.cso.objectives import group_advantages
from lerobot_cso.durable import (
    EpisodeJournal,
    ResumableState,
    read_json,
    replace_dir,
    restore_interrupted_replace,
    write_json,
)
from lerobot_cso.errors import UsageError, check_number
from lerobot_cso.frames import in_memory
from lerobot_cso.policy.configuration_cso import SKILL_START_KEY, SKILL_STEP_KEY, SKILL_TOKENS_KEY
from lerobot_cso.policy.modeling_cso import CSOPolicy
from lerobot_cso.records import run_alone
from lerobot_cso.rollout.engine import Episode, InitialState, RolloutEngine
from lerobot_cso.rollout_stage import TrainingStageConfig, policy_features
from lerobot_cso.sampling import Sampling
from lerobot_cso.stage import POLICY_ROLES, CheckpointStage, without_added_settings
from lerobot_cso.worlds.base import camera_inputs

TASK_KEY, SEED_KEY, ATTEMPT_KEY, TEMPERATURE_KEY = "rsft.task", "rsft.init_seed", "rsft.attempt", "rsft.temperature"
BUFFER_FRAMES = ("all", "decisions")


def _rsft_sampling() -> Sampling:
    return Sampling(temperature=1.5, top_k=10)  # exploratory collection (App. G)


@dataclass
class RSFTConfig(TrainingStageConfig):
    """Settings of ``lerobot-cso rsft --policy.path=<IL checkpoint> --tasks=MT10 --output_dir=...``."""

    policy_role: ClassVar[str] = POLICY_ROLES["rsft"]

    output_dir: Path = Path("outputs/rsft")
    sampling: Sampling = field(default_factory=_rsft_sampling)
    # Collection (Algorithm 1, App. E.2 / G).
    successes_per_task: int = 200
    n_strikes: int = 10
    # At most this many of a state's successes are kept (None: all of them, the paper's App. E.2 rule). A cap
    # spreads the buffer over more states, so states the policy solves only sometimes weigh as much as the
    # states it always solves.
    max_successes_per_state: int | None = None
    # Not in the paper, which runs all N attempts of a state: once a state holds max_successes_per_state
    # successes, its remaining attempts are not started. On a robot this spares the operator the scenes whose
    # successes would be dropped anyway; in simulation a state's attempts mostly run at once, so it saves little.
    stop_state_at_cap: bool = False
    states_per_round: int = 2  # new initial states per unfinished task per batched rollout call
    # Which camera frames the buffer holds: "all" (every frame rendered), or "decisions": only the frames a skill is
    # sampled from are rendered (the only ones Eq. 6 reads), each repeated over its skill's frames. Rendering is
    # most of a camera collection's time (≈ 10 ms a 64² frame against 0.25 ms a MuJoCo step, docs/cso-on-cpu.md).
    buffer_frames: str = "all"
    max_states_per_task: int = 2000
    # Not in the paper, which collects until every task holds its successes: a task still short of
    # successes_per_task after max_states_per_task initial states keeps what it holds (possibly none; the report
    # shows it) instead of stopping the run with an error. This bounds the collection's cost where the IL
    # policy never solves a task.
    keep_short_tasks: bool = False
    seed: int = 0
    # Fine-tuning (Eq. 6, App. E.2) with the policy's own optimizer and scheduler presets (lerobot-train's),
    # at this peak / final learning rate.
    epochs: int = 20
    batch_size: int = 256
    lr: float = 1e-4
    min_lr: float = 1e-5
    # Not in the paper, whose Eq. 6 weighs every kept success alike: each success is drawn in proportion to its
    # Eq. 8 advantage in its state's N-strikes group, 1 − successes / attempts, so successes of states the policy
    # solves on every attempt are not drawn at all and those of states it rarely solves are drawn most.
    advantage_weighted: bool = False
    # Not in the paper, whose fine-tune reads the buffer alone: this fraction of each epoch's decisions are frames
    # of the IL demonstrations (the LeRobotDataset ``demos_repo_id`` at ``demos_root``; the pipeline's own demos
    # there), each with the frozen autoencoder's tokens of its action chunk, the targets IL trained on.
    demo_fraction: float = 0.0
    demos_root: Path | None = None
    demos_repo_id: str = "local/metaworld_demos"
    # Publishing the success buffer with LeRobot's push_to_hub.
    push_to_hub: bool = False
    repo_id: str = "local/cso_rsft_buffer"

    @property
    def records_frames(self) -> bool:  # type: ignore[override]
        return self.buffer_frames == "all"

    def validate(self) -> list[str]:
        tasks = super().validate()
        if self.buffer_frames not in BUFFER_FRAMES:
            raise UsageError(f"buffer_frames must be one of {', '.join(BUFFER_FRAMES)}, got '{self.buffer_frames}'")
        if not self.world_settings().simulated and not self.records_frames:
            raise UsageError("--buffer_frames=decisions is for simulated worlds: a robot's cameras give every frame")
        for name in ("successes_per_task", "n_strikes", "states_per_round", "max_states_per_task", "batch_size"):
            if getattr(self, name) < 1:
                raise UsageError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.max_successes_per_state is not None and self.max_successes_per_state < 1:
            raise UsageError(f"max_successes_per_state must be >= 1, got {self.max_successes_per_state}")
        if self.stop_state_at_cap and self.max_successes_per_state is None:
            raise UsageError("--stop_state_at_cap=true needs --max_successes_per_state=<a cap>")
        if self.epochs < 0:
            raise UsageError(f"epochs must be >= 0, got {self.epochs}")
        check_number("lr", self.lr, gt=0)
        check_number("min_lr", self.min_lr, gt=0, le=self.lr)
        check_number("demo_fraction", self.demo_fraction, ge=0, lt=1)
        if self.demo_fraction and self.demos_root is None:
            raise UsageError("--demo_fraction needs --demos_root=<the IL demonstrations' LeRobotDataset folder>")
        if self.push_to_hub and self.repo_id.startswith("local/"):
            raise UsageError("--push_to_hub=true needs --repo_id=<user>/<name>")
        return tasks

    def spec(self) -> dict[str, Any]:
        """Settings that define the buffer; a journal made with other settings is refused."""
        keys = (
            "tasks",
            "successes_per_task",
            "n_strikes",
            "max_successes_per_state",
            "stop_state_at_cap",
            "buffer_frames",
            "seed",
        )
        spec = {k: getattr(self, k) for k in keys}
        spec |= {"sampling": asdict(self.sampling), "policy": str(self.policy.pretrained_path)}
        return without_added_settings(spec)  # journals from before a later setting existed stay valid


class Journal:
    """The collection's :class:`~lerobot_cso.durable.EpisodeJournal`: kept successes and tried states per task."""

    def __init__(self, root: Path, spec: dict[str, Any]) -> None:
        self.store = EpisodeJournal(root, spec, what="an R-SFT collection")

    def states(self, task: str) -> dict[int, dict[str, int]]:
        """Recorded initial states of a task: seed → {attempts, successes}."""
        return {int(name): record for name, record in self.store.records(task).items()}

    def episode_files(self, task: str) -> list[Path]:
        return self.store.episode_files(task)

    def drop_unrecorded(self, task: str) -> None:
        """Remove episodes of states whose record is missing (a run killed mid-state); they get redone."""
        recorded = self.states(task)
        for path in self.episode_files(task):
            if int(path.stem.split("_")[0]) not in recorded:
                path.unlink()

    def save_episode(self, episode: Episode, sampling: Sampling) -> None:
        arrays = {
            "states": episode.states.numpy(),
            "actions": episode.actions.numpy(),
            "decision_steps": episode.decision_steps.numpy(),
            "tokens": episode.tokens.numpy(),
            "logprobs": episode.logprobs.numpy(),
            "temperature": np.float32(sampling.temperature),
        }
        arrays.update({f"image_{cam}": frames.numpy() for cam, frames in episode.images.items()})
        self.store.save_episode(episode.task, f"{episode.init_seed:07d}_{episode.sample:03d}", arrays)

    def save_state(self, task: str, seed: int, attempts: int, successes: int) -> None:
        self.store.save_record(task, f"{seed:07d}", {"attempts": attempts, "successes": successes})


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
    sampling, world, main = cfg.sampling, cfg.rollout_world(), distributed.is_main()
    if main:  # the journal is written by the main process alone; the others read it after each round
        for task in tasks:
            journal.drop_unrecorded(task)
    distributed.wait_for_everyone()
    # closed before an error propagates, so that the error line starts a line of its own
    with tqdm(total=cfg.successes_per_task * len(tasks), desc="R-SFT successes", disable=not main) as progress:
        progress.update(sum(len(journal.episode_files(t)) for t in tasks))
        while True:
            kept = {t: len(journal.episode_files(t)) for t in tasks}
            todo = [t for t in tasks if kept[t] < cfg.successes_per_task]
            short = [t for t in todo if len(journal.states(t)) >= cfg.max_states_per_task]
            if short and not cfg.keep_short_tasks:
                raise UsageError(
                    f"{short[0]}: only {kept[short[0]]} successes after {len(journal.states(short[0]))} initial "
                    "states; the IL policy rarely solves it (raise --max_states_per_task, lower "
                    "--successes_per_task or pass --keep_short_tasks=true)"
                )
            todo = [t for t in todo if t not in short]
            if not todo:
                break
            requests = []
            for task in todo:
                tried = journal.states(task)
                fresh = [s for s in world.training_states(task, "rsft", 0, cfg.max_states_per_task) if s not in tried]
                requests += [InitialState(task, s) for s in fresh[: cfg.states_per_round]]
            round_seed = seeds.round_seed(cfg.seed, requests[0].seed)
            needed, per_state = dict(kept), dict.fromkeys(requests, 0)

            def keep(episode: Episode, needed: dict[str, int] = needed, per_state: dict = per_state) -> None:
                state, cap = InitialState(episode.task, episode.init_seed), cfg.max_successes_per_state or cfg.n_strikes
                if episode.success and needed[episode.task] < cfg.successes_per_task and per_state[state] < cap:
                    needed[episode.task] += 1
                    per_state[state] += 1
                    journal.save_episode(episode, sampling)
                    progress.update(1)

            stop_after = cfg.max_successes_per_state if cfg.stop_state_at_cap else None
            filmed = () if cfg.records_frames else range(len(requests))  # decision frames, kept in every trace
            result = engine.rollout(
                requests,
                k=cfg.n_strikes,
                sampling=sampling,
                seed=round_seed,
                on_episode=keep,
                stop_after=stop_after,
                keep_frames=filmed,
            )
            if main:
                for group in result.groups():
                    first = group[0]
                    journal.save_state(first.task, first.init_seed, len(group), sum(e.success for e in group))
            distributed.wait_for_everyone()
    for task in tasks if main else ():
        if (n := len(journal.episode_files(task))) < cfg.successes_per_task:
            print(
                f"R-SFT: {task} keeps {n} of {cfg.successes_per_task} successes, its budget of "
                f"{cfg.max_states_per_task} initial states spent (--keep_short_tasks)",
                flush=True,
            )


def buffer_features(
    state_dim: int, action_dim: int, n_tokens: int, image_shapes: dict[str, tuple[int, ...]]
) -> dict[str, Any]:
    """LeRobotDataset features of the success buffer (``image_shapes``: the policy's image input key -> (H, W, 3))."""
    features: dict[str, Any] = {
        "observation.state": {"dtype": "float32", "shape": (state_dim,), "names": None},
        "action": {"dtype": "float32", "shape": (action_dim,), "names": None},
        SKILL_TOKENS_KEY: {"dtype": "int64", "shape": (n_tokens,), "names": None},
        SKILL_START_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        SKILL_STEP_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        TASK_KEY: {"dtype": "string", "shape": (1,), "names": None},
        SEED_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        ATTEMPT_KEY: {"dtype": "int64", "shape": (1,), "names": None},
        TEMPERATURE_KEY: {"dtype": "float32", "shape": (1,), "names": None},
    }
    for key, shape in image_shapes.items():
        features[key] = {
            "dtype": "image",
            "shape": shape,
            "names": ["height", "width", "channel"],
        }
    return features


def write_buffer(cfg: RSFTConfig, tasks: list[str], journal: Journal, n_tokens: int) -> Path:
    """Materialise the journal as the success buffer (a LeRobotDataset v3), atomically. Its camera frames are
    stored under the policy's own image input keys (``observation.images.<camera>``, or LeRobot's
    ``observation.image``), so that the fine-tune reads them as the policy reads its inputs."""
    out = cfg.output_dir / "buffer"
    work = cfg.output_dir / "buffer.tmp"
    shutil.rmtree(work, ignore_errors=True)
    files = [p for t in tasks for p in journal.episode_files(t)]
    if not files:
        raise UsageError(
            f"the IL policy solved no task in {cfg.max_states_per_task} initial states each: the success buffer "
            "would be empty (raise --max_states_per_task)"
        )
    world = cfg.rollout_world()
    redo = (
        f"R-SFT cannot redo one episode as it drew it: delete {cfg.output_dir} to redo R-SFT (deleting only this file "
        "makes the rerun collect a replacement from a new initial state: another buffer and checkpoint)"
    )
    first = EpisodeJournal.load(files[0], redo=redo)
    cameras = sorted(k.removeprefix("image_") for k in first if k.startswith("image_"))
    keys = {cam: key for key, cam in camera_inputs(policy_features(cfg), world).items()}  # camera -> input key
    image_shapes = {keys[cam]: tuple(first[f"image_{cam}"].shape[1:]) for cam in cameras}
    dims = first["states"].shape[-1], first["actions"].shape[-1]
    features = buffer_features(*dims, n_tokens, image_shapes)
    ds = LeRobotDataset.create(
        cfg.repo_id,
        world.fps,
        features,
        root=work,
        robot_type=world.robot_type,
        use_videos=False,
        video_backend="pyav",
        image_writer_threads=4 if cameras else 0,  # PNG encoding of camera frames, as the demos write theirs
    )
    for path in tqdm(files, desc="writing R-SFT buffer", leave=False):
        task = path.parent.name
        seed, attempt = (int(x) for x in path.stem.split("_"))
        ep = EpisodeJournal.load(path, redo=redo)  # each array read once: an NpzFile decompresses one on every access
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
                "task": world.task_description(task),
            }
            frame.update({keys[cam]: ep[f"image_{cam}"][t] for cam in cameras})
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    replace_dir(work, out)
    return out


class DecisionItems(torch.utils.data.Dataset):
    """Items of ``frames`` reduced to what Eq. 6 reads: the policy's inputs, the task and the skill tokens.

    ``tokens`` (one row per item, optional) replaces the frame's stored skill tokens; every item is a decision.
    """

    def __init__(self, frames: torch.utils.data.Dataset, keys: list[str], tokens: torch.Tensor | None = None) -> None:
        self.frames, self.keys, self.tokens = frames, keys, tokens

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict[str, Any]:
        frame = self.frames[i]
        item = {k: frame[k] for k in self.keys}
        item[SKILL_TOKENS_KEY] = frame[SKILL_TOKENS_KEY] if self.tokens is None else self.tokens[i]
        item[SKILL_START_KEY] = torch.ones(1, dtype=torch.int64)
        return item


def success_advantages(
    tasks: list[str], seeds: list[int], states: dict[str, dict[int, dict[str, int]]]
) -> torch.Tensor:
    """Eq. 8 (:func:`~lerobot_cso.cso.objectives.group_advantages`) of a kept success in its state's N-strikes group,
    1 − successes / attempts, per decision (``tasks[i]``, ``seeds[i]``: the state of decision ``i``; ``states``:
    the collection's records per task)."""

    def advantage(record: dict[str, int]) -> float:
        hits, attempts = record["successes"], record["attempts"]
        rewards = torch.tensor([[1.0] * hits + [0.0] * (attempts - hits)], dtype=torch.float64)
        return float(group_advantages(rewards)[0, 0])  # the group's first reward is a success's

    per_state = {(t, s): advantage(states[t][s]) for t, s in set(zip(tasks, seeds, strict=True))}
    return torch.tensor([per_state[state] for state in zip(tasks, seeds, strict=True)], dtype=torch.float64)


def check_demos(cfg: RSFTConfig) -> None:
    """Refuse a ``demos_root`` that holds no LeRobotDataset, or one whose frames the policy cannot read: each of
    its inputs and its action (state and action of the policy's shape), and only tasks it knows. Run before the
    collection, not after it."""
    root = cfg.demos_root
    if not (root / "meta" / "info.json").is_file():
        raise UsageError(f"--demos_root={root} is not a LeRobotDataset (no meta/info.json)")
    try:
        meta = LeRobotDatasetMetadata(cfg.demos_repo_id, root=root)
    except (OSError, ValueError, KeyError) as e:
        raise UsageError(f"--demos_root={root}: its metadata cannot be read ({' '.join(str(e).split())})") from None
    features = {**(cfg.policy.input_features or {}), **(cfg.policy.output_features or {})}
    problems = []
    for key, feature in features.items():
        have = meta.features.get(key)
        if have is None:
            problems.append(f"no '{key}'")
        elif feature.type is not FeatureType.VISUAL and tuple(have["shape"]) != tuple(feature.shape):
            problems.append(f"'{key}' of shape {tuple(have['shape'])}, the policy's is {tuple(feature.shape)}")
    known = getattr(cfg.policy, "tasks", None)
    unknown = sorted(t for t in meta.tasks.index if known and t not in known) if meta.tasks is not None else []
    if unknown:
        problems.append(f"tasks the policy was not trained on ({'; '.join(map(repr, unknown))})")
    if problems:
        raise UsageError(f"--demos_root={root} does not fit the policy: it has {', '.join(problems)}")


def demo_decisions(cfg: RSFTConfig, policy: CSOPolicy, pre: Callable, keys: list[str], count: int) -> DecisionItems:
    """``count`` demonstration frames (drawn with R-SFT's seed) tokenised by the frozen autoencoder."""
    check_demos(cfg)
    fps = LeRobotDatasetMetadata(cfg.demos_repo_id, root=cfg.demos_root).fps
    chunk = {"action": [i / fps for i in range(policy.config.chunk_size)]}
    ds = LeRobotDataset(cfg.demos_repo_id, root=cfg.demos_root, delta_timestamps=chunk, video_backend="pyav")
    picked = torch.randperm(len(ds), generator=torch.Generator().manual_seed(cfg.seed))[: min(count, len(ds))]
    frames = in_memory(ds, picked.tolist())
    tokens = []
    policy.autoencoder.eval()
    with torch.no_grad():
        for batch in torch.utils.data.DataLoader(frames, batch_size=256):
            tokens.append(policy.autoencoder.encode(pre(batch)["action"])[1].cpu())
    return DecisionItems(frames, keys, torch.cat(tokens))


def _fine_tune_items(
    cfg: RSFTConfig, policy: CSOPolicy, pre: Any, ds: LeRobotDataset, starts: np.ndarray
) -> torch.utils.data.Dataset:
    """The fine-tune's items: the buffer's decision frames, plus ``demo_fraction`` of demonstration frames."""
    items = in_memory(ds, starts.tolist())  # only the decision frames' camera frames are decoded
    if cfg.demo_fraction:
        keys = [*policy.config.input_features, "task"]
        count = round(len(starts) * cfg.demo_fraction / (1 - cfg.demo_fraction))
        demos = demo_decisions(cfg, policy, pre, keys, count)
        print(f"R-SFT fine-tune: {len(starts)} buffer decisions + {len(demos)} demonstration frames", flush=True)
        items = torch.utils.data.ConcatDataset([DecisionItems(items, keys), demos])
    return items


def _advantage_sampler(
    cfg: RSFTConfig, ds: LeRobotDataset, starts: np.ndarray, n_items: int, generator: torch.Generator
) -> torch.utils.data.Sampler:
    """``advantage_weighted``: draws each buffer decision in proportion to its success's Eq. 8 advantage (the
    demonstration frames at the buffer's mean weight)."""
    journal = Journal(cfg.output_dir / "journal", cfg.spec())
    columns = ds.hf_dataset.select(starts.tolist())
    tasks = [str(t) for t in columns[TASK_KEY]]
    weights = success_advantages(
        tasks, [int(np.ravel(s)[0]) for s in columns[SEED_KEY]], {t: journal.states(t) for t in set(tasks)}
    )
    if not weights.sum() > 0:
        raise UsageError("--advantage_weighted=true: every kept success is from a state solved on all its attempts")
    print(f"R-SFT fine-tune: {int((weights > 0).sum())} of {len(weights)} decisions have weight > 0", flush=True)
    if cfg.demo_fraction:  # each demonstration frame at the buffer's mean weight keeps their share
        weights = torch.cat([weights, weights.mean().repeat(n_items - len(weights))])
    return torch.utils.data.WeightedRandomSampler(weights, n_items, replacement=True, generator=generator)


def open_buffer(cfg: RSFTConfig, buffer: Path, delta_timestamps: dict[str, list[float]] | None) -> LeRobotDataset:
    """The success buffer as a LeRobotDataset; ``UsageError`` naming a damaged one (a truncated file), which the
    journal writes again as it was."""
    try:
        return LeRobotDataset(
            cfg.repo_id,
            root=buffer,
            delta_timestamps=delta_timestamps,
            video_backend="pyav",  # as the demos: skips probing torchcodec (a traceback per load where it cannot load)
        )
    except (DatasetGenerationError, OSError, ValueError, KeyError) as e:
        cause = e.__cause__ or e
        raise UsageError(
            f"{buffer} is damaged ({type(cause).__name__}: {' '.join(str(cause).split())[:200]}); delete it and the "
            f"rerun writes it again from {cfg.output_dir / 'journal'}, the same buffer"
        ) from None


def finetune(cfg: RSFTConfig, buffer: Path) -> Path:
    """Eq. 6 on the buffer's decision frames, then freeze the encoders and save the checkpoint.

    Trained as ``lerobot-train`` trains: the policy's optimizer and scheduler presets (at R-SFT's ``lr`` /
    ``min_lr``, one cosine over all epochs) and LeRobot's one-step ``update_policy``; resumable per epoch.
    """
    torch.manual_seed(cfg.seed)  # dropout and initialisation noise: same config, same checkpoint
    policy, pre, post = load_policy(cfg.policy.pretrained_path, cfg.policy)
    policy.set_encoders_frozen(False)
    # Action chunks are only read by QueST's optional decoder loss (and cost LeRobot a query per frame).
    chunk = {"action": [i / cfg.rollout_world().fps for i in range(policy.config.chunk_size)]}
    ds = open_buffer(cfg, buffer, chunk if policy.config.decoder_loss_scale else None)
    starts = np.flatnonzero(np.asarray(ds.hf_dataset[SKILL_START_KEY]).reshape(-1) == 1)
    items = _fine_tune_items(cfg, policy, pre, ds, starts)
    generator = torch.Generator().manual_seed(cfg.seed)
    sampler = _advantage_sampler(cfg, ds, starts, len(items), generator) if cfg.advantage_weighted else None
    loader = torch.utils.data.DataLoader(
        items,
        batch_size=cfg.batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        generator=generator if sampler is None else None,
    )
    optimizer_cfg = replace(policy.config.get_optimizer_preset(), lr=cfg.lr)
    scheduler_cfg = replace(
        policy.config.get_scheduler_preset(), num_autoencoder_steps=0, min_lr_ratio=cfg.min_lr / cfg.lr
    )
    optimizer = optimizer_cfg.build(policy.get_optim_params())
    scheduler = scheduler_cfg.build(optimizer, cfg.epochs * len(loader))
    # Data-parallel under accelerate launch: a shard of every epoch per process, gradients all-reduced.
    accelerator = distributed.accelerator_for(policy)
    policy, optimizer, loader, scheduler = accelerator.prepare(policy, optimizer, loader, scheduler)
    main = accelerator.is_main_process
    if main:
        ResumableState(cfg.output_dir / "train_state")  # undoes an interrupted save before any process reads it
    accelerator.wait_for_everyone()
    state = ResumableState(cfg.output_dir / "train_state")
    start_epoch = (state.progress() or {"epochs_done": 0})["epochs_done"]
    if start_epoch:
        accelerator.load_state(state.directory)
    for epoch in range(start_epoch, cfg.epochs):
        tracker = MetricsTracker(
            cfg.batch_size, len(items), ds.num_episodes, distributed.step_meters(), epoch * len(loader)
        )
        for batch in tqdm(loader, desc=f"R-SFT epoch {epoch + 1}/{cfg.epochs}", leave=False):
            tracker, _ = update_policy(
                tracker, policy, pre(batch), optimizer, optimizer_cfg.grad_clip_norm, accelerator, scheduler
            )
            tracker.step()
        if main:
            print(f"R-SFT epoch {epoch + 1}/{cfg.epochs} ({len(items)} decisions): {tracker}", flush=True)
        state.save({"epochs_done": epoch + 1}, accelerator.save_state, main, accelerator.wait_for_everyone)
    policy = accelerator.unwrap_model(policy)
    policy.set_encoders_frozen(True)  # Algorithm 1, line 11
    out = cfg.output_dir / "pretrained_model"
    if main:
        save_checkpoint(out, policy, pre, post)
    accelerator.wait_for_everyone()
    return out


def run_rsft(cfg: RSFTConfig, make_engine: Callable[..., RolloutEngine] | None = None) -> dict[str, Any]:
    """Collect (resumable), write the buffer, optionally push it, fine-tune; returns the collection report.

    ``make_engine(policy, preprocessor, postprocessor, cfg)`` builds the rollout engine.
    """
    tasks = cfg.validate()
    if cfg.demo_fraction:
        check_demos(cfg)  # before the collection, not after it
    if (cfg.output_dir / "pretrained_model" / "config.json").is_file():
        report = read_json(cfg.output_dir / "collection.json")
        short = [t for t, r in report.items() if r["kept"] < cfg.successes_per_task]
        if short and report[short[0]]["states_tried"] < cfg.max_states_per_task:
            raise UsageError(
                f"{cfg.output_dir} finished with {short[0]} short of successes after "
                f"{report[short[0]]['states_tried']} initial states; a larger --max_states_per_task gives another "
                f"buffer and checkpoint: delete {cfg.output_dir} to redo R-SFT with it"
            )
        print(f"{cfg.output_dir / 'pretrained_model'} exists: R-SFT already complete")
        return report
    main = distributed.is_main()
    if main:  # creates the journal (or refuses one made with other settings) before any process opens it
        Journal(cfg.output_dir / "journal", cfg.spec())
        restore_interrupted_replace(cfg.output_dir / "buffer")
    distributed.wait_for_everyone()
    journal = Journal(cfg.output_dir / "journal", cfg.spec())
    if not (cfg.output_dir / "buffer" / "meta" / "info.json").is_file():
        policy, pre, post = load_policy(cfg.policy.pretrained_path, cfg.policy)
        with distributed.ShardedRollouts((make_engine or rollout_stage.stage_engine)(policy, pre, post, cfg)) as engine:
            collect(cfg, tasks, engine, journal)
        if main:
            write_buffer(cfg, tasks, journal, policy.config.n_tokens)
        distributed.wait_for_everyone()
    report = collection_report(journal, tasks)
    if main:
        write_json(cfg.output_dir / "collection.json", report)
        print(report_table(report))
        if cfg.push_to_hub:
            LeRobotDataset(cfg.repo_id, root=cfg.output_dir / "buffer").push_to_hub()
    with cfg.training():
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


class RSFTStage(CheckpointStage):
    """The pipeline's R-SFT stage: the frozen-encoder checkpoint ``output_dir/pretrained_model``."""

    name = "rsft"
    # A collection stopped at its state budget continues into more states as the longer budget would have run it
    # from the start: the states are a fixed sequence tried in order, each round's sampling seed is its first
    # state's, and a finished R-SFT is not rerun.
    grows = ("rsft.max_states_per_task", "rsft.keep_short_tasks")

    def run(self) -> dict[str, Any]:
        return run_rsft(self.cfg, self.make_engine)

    def proven_origin(self) -> bool:
        """An output holding only a collection (its journal, buffer and report: no fine-tune yet) whose journal was
        made with this run's collection settings and policy: the journal checks its own settings, so a collection
        copied to be fine-tuned anew (``benchmarks/twin_table5.py --reuse``) is adopted."""
        out = self.cfg.output_dir
        collection = {"journal", "robot_journal", "buffer", "collection.json"}
        return all(p.name in collection for p in out.iterdir()) and read_json(out / "journal" / "spec.json") == (
            self.cfg.spec()
        )


@parser.wrap()
def rsft_main(cfg: RSFTConfig) -> None:
    """Entry point of ``lerobot-cso rsft``: resumes or skips only an output of the same settings and checkpoint."""
    run_alone(RSFTStage(cfg), main=distributed.is_main())
    print(f"R-SFT checkpoint (encoders frozen): {cfg.output_dir / 'pretrained_model'}")
