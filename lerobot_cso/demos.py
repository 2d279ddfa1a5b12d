"""``lerobot-cso demos``: scripted demonstrations in a world that has an expert → a LeRobotDataset v3.

The expert is the world's (``--world.type``, else the world whose tasks ``--tasks`` names; a
:class:`~lerobot_cso.worlds.base.DemoExpert`): MetaWorld's ``metaworld.policies``, LIBERO's pick-and-place
expert (:mod:`lerobot_cso.worlds.libero.expert`), or a third party's world's own. Episode ``i`` of a task starts
from the expert's ``demo_states[i]`` (MetaWorld: ``seeds.DEMO.start + i``; LIBERO: a placement drawn from
``seeds.DEMO_PLACEMENTS.start + i``, never a fixed evaluation state) and is driven by the expert plus Gaussian
action noise (σ = ``noise_std``; unset: the expert's, MetaWorld 0.2 as QueST) drawn from a generator seeded by
``(seed, task, init_seed)``; it ends at the first success or after ``max_steps``. The same config therefore
gives the same dataset, bit for bit, however the work is split over envs or interrupted. With
``keep_failed=false`` failed episodes are dropped and the next seeds are tried until each task has
``episodes_per_task`` successes.

Features: ``observation.state`` (float32; the ``state`` layout: MetaWorld's full 39-d state by default,
``proprio`` for QueST's 8-d camera setting, ``hand`` for LeRobot's 4-d — the expert always reads what it needs,
the dataset keeps the layout's part; LIBERO's 8-d), ``action`` (float32, as executed), optional
``observation.images.<camera>`` (``image_size``², PNG ``image``), ``task`` = the task's language description, and
per-frame episode metadata that LeRobot's tools carry along: ``<world>.task`` (task name), ``<world>.init_seed`` and
``<world>.success`` (the episode's outcome). The episode length is LeRobot's own ``length``. The generation settings
are kept in ``meta/cso_demos.json``; a run on a dir holding a dataset made with other settings, or anything else, is
refused.

**LeRobot's own format** (``--format=lerobot``, MetaWorld): what LeRobot's ``metaworld`` env gives a policy and its
Hub datasets (``lerobot/metaworld_*``) hold, so a Hub user's data can be made offline: ``corner2`` as
``observation.image`` (``image_size``², by default LeRobot's 480², turned as LeRobot turns it; stored as video,
LeRobot's default), the 4-d hand ``observation.state``, the 4-d ``action``, 80 fps and LeRobot's own task
descriptions (for ``push-back-v3`` the sentence LeRobot gives ``push-v3`` too). Nothing else is in the frames: an
episode's task, initial-state seed and outcome are kept in ``meta/cso_episodes.json`` instead (in episode order),
which is what a resumed or topped-up run reads. Other cameras or state layouts are refused.

**An existing dataset instead** (``dataset_root``, with its ``repo_id``): for tasks without a scripted expert, or
a user's own data, the pipeline trains on a LeRobotDataset the user brings, e.g. the Hub's ``lerobot/libero_spatial``
(LeRobot downloads it into ``dataset_root`` when the folder lacks it and the Hub is reachable). Nothing is
generated: :class:`DatasetStage` checks that the dataset fits the world (``observation.state`` and ``action``
shapes, camera names) and holds every task the run names (by language description), and IL trains on it. LeRobot's
own MetaWorld format is one such dataset: a ``corner2`` ``observation.image`` and the 4-d hand state.

Durability: every finished episode is written at once, atomically, to ``<output_dir>.partial/`` (an
:class:`~lerobot_cso.durable.EpisodeJournal`); the dataset is assembled from there when all episodes exist
(appended with ``LeRobotDataset.resume`` when topping up an existing dataset) and swapped into place
(:func:`~lerobot_cso.durable.replace_dir`). A killed run restarts where it stopped: episodes
already staged or already in the dataset (matched by task and initial-state seed) are never rerun or
duplicated.
"""

import dataclasses
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from datasets.utils import logging as hf_logging
from lerobot.configs import parser
from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.utils.constants import OBS_IMAGE, OBS_IMAGES
from tqdm import tqdm

from lerobot_cso.durable import (
    EpisodeJournal,
    output_lock,
    read_json,
    replace_dir,
    restore_interrupted_replace,
    write_json,
)
from lerobot_cso.errors import UsageError, check_number, check_output_dir, interruptible
from lerobot_cso.stage import PIPELINE_FIELDS, settings_spec, without_added_settings
from lerobot_cso.worlds.base import DemoExpert, SimWorld, WorldConfig, camera_inputs
from lerobot_cso.worlds.metaworld.env_config import parse_cameras
from lerobot_cso.worlds.registry import default_world

SPEC_FILE = "meta/cso_demos.json"
EPISODES_FILE = "meta/cso_episodes.json"  # --format=lerobot: [task, init_seed, success] per episode
FORMATS = ("cso", "lerobot")
BRING_A_DATASET = (
    "give a LeRobotDataset of its tasks with --dataset_root=<its folder> --repo_id=<its repo id> "
    "(in the pipeline: --demos.dataset_root, --demos.repo_id)"
)
MAX_ATTEMPTS_PER_EPISODE = 20  # with keep_failed=false: give up on a task after this many tries per episode


@dataclass
class DemosConfig:
    """Settings of ``lerobot-cso demos`` (``--tasks=MT10 --episodes_per_task=10 --output_dir=...``)."""

    # The world whose expert makes the demos (--world.type=metaworld|libero); null: the world --tasks names.
    world: WorldConfig | None = None
    # One task, a comma list, or a set: MT10, MT50, ML45-train, ML45-test; libero_object, libero_object-3, ...
    tasks: str = "ML45-train"
    episodes_per_task: int = 100
    # Std of the Gaussian noise added to the expert's actions; null: the world's (MetaWorld 0.2, LIBERO 0.05).
    noise_std: float | None = None
    seed: int = 0
    keep_failed: bool = True
    # The dataset's layout: cso (observation.images.<camera>, the state layout below, per-frame episode metadata) or
    # lerobot (MetaWorld only: LeRobot's own MetaWorld format, as its metaworld env and the Hub's lerobot/metaworld_*
    # datasets hold it: corner2 as observation.image at 480² unless --image_size, stored as video, the 4-d hand
    # observation.state, 80 fps, LeRobot's task descriptions).
    format: str = "cso"
    # Comma list of cameras to render at image_size × image_size (empty: state only; slow on CPU; with
    # --format=lerobot: its one camera, corner2). MetaWorld: corner, corner2, ..., gripperPOV; LIBERO: image
    # (agentview), image2 (wrist).
    cameras: str = ""
    # Side of the camera images; null: the world's (MetaWorld 128, LIBERO 128; --format=lerobot: 480, at least 32).
    image_size: int | None = None
    # What observation.state holds; null: full (--format=lerobot: hand). MetaWorld: full (39-d, object and goal
    # positions), proprio (QueST's 8-d hand + gripper, now and one frame before; with a camera the policy must find
    # the objects in the image), hand (LeRobot's 4-d). LIBERO: full (its 8-d eef position, axis-angle and gripper
    # joints: what LeRobot's has).
    state: str | None = None
    # Episode cap; null: the world's horizon (MetaWorld 500; LIBERO its suite's, e.g. 280 for libero_object).
    max_steps: int | None = None
    num_envs: int = 4
    output_dir: Path = Path("outputs/demos/metaworld")
    repo_id: str = "local/metaworld_demos"
    # An existing LeRobotDataset (the dataset repo_id, in this folder) to use instead of generating demos, for a
    # world without a scripted expert or a user's own data. The generation settings above are then unused.
    dataset_root: Path | None = None

    def world_settings(self) -> WorldConfig:
        return self.world if self.world is not None else default_world(self.tasks)

    def expert(self) -> DemoExpert:
        """The world's demo expert; ``UsageError`` for a world without one."""
        settings = self.world_settings()
        try:
            expert = settings.demo_expert()
        except ValueError as e:  # its simulator is not installed
            raise UsageError(str(e)) from None
        if expert is None:
            raise UsageError(f"{settings.type} has no scripted expert to generate demos: {BRING_A_DATASET}")
        return expert

    def resolved(self) -> "DemosConfig":
        """These settings with the unset ones (null) taken from the world's expert (unchanged with a given dataset,
        which uses none of them)."""
        if self.dataset_root is not None:
            return self
        expert, tasks = self.expert(), self.validate()
        lerobot = self.format == "lerobot"  # LeRobot's camera, size and state; else the expert's defaults
        image_size = expert.lerobot_image_size if lerobot else expert.image_size
        state = expert.lerobot_state if lerobot else expert.states[0]
        return dataclasses.replace(
            self,
            noise_std=expert.noise_std if self.noise_std is None else self.noise_std,
            cameras=expert.lerobot_camera if lerobot else self.cameras,
            image_size=image_size if self.image_size is None else self.image_size,
            state=state if self.state is None else self.state,
            max_steps=expert.horizon(tasks) if self.max_steps is None else self.max_steps,
        )

    def format_spec(self) -> dict[str, str]:
        """The format's part of a spec: nothing for the default, so records made before the setting still match."""
        return {} if self.format == "cso" else {"format": self.format}

    def spec(self) -> dict[str, Any]:
        """The settings that determine episode content: a dataset only ever grows under one spec."""
        cfg = self.resolved()
        return {
            "noise_std": cfg.noise_std,
            "seed": cfg.seed,
            "keep_failed": cfg.keep_failed,
            "cameras": list(parse_cameras(cfg.cameras)),
            "image_size": cfg.image_size,
            "state": cfg.state,
            "max_steps": cfg.max_steps,
            "fps": self.expert().fps,
        } | self.format_spec()

    def validate(self) -> list[str]:
        """Check every setting (and the given dataset); returns the resolved task list. Raises ``UsageError``."""
        if self.dataset_root is not None:
            return check_dataset(self)[0]
        check_output_dir(self.output_dir)
        expert = self.expert()
        self._check_format(expert)
        tasks = _resolve(self.world_settings().build(self.tasks, None, None), self.tasks)
        try:
            expert.check_tasks(tasks)
        except ValueError as e:
            raise UsageError(f"{e}: {BRING_A_DATASET}") from None
        if self.episodes_per_task <= 0:
            raise UsageError(f"episodes_per_task must be > 0, got {self.episodes_per_task}")
        if self.noise_std is not None:
            check_number("noise_std", self.noise_std, ge=0)
        horizon = expert.horizon(tasks)
        if self.max_steps is not None and not 1 <= self.max_steps <= horizon:
            raise UsageError(f"max_steps must be in [1, {horizon}], got {self.max_steps}")
        if self.num_envs < 1:
            raise UsageError(f"num_envs must be >= 1, got {self.num_envs}")
        unknown = [c for c in parse_cameras(self.cameras) if c not in expert.cameras]
        if unknown:
            raise UsageError(f"unknown camera(s) {', '.join(unknown)}; valid cameras: {', '.join(expert.cameras)}")
        if self.state is not None and self.state not in expert.states:
            raise UsageError(f"state must be one of {', '.join(expert.states)}, got {self.state!r}")
        cameras = parse_cameras(self.cameras) or self.format == "lerobot"
        low = 32 if self.format == "lerobot" else 16  # LeRobot's video encoder (SVT-AV1) crashes on 16² frames
        if cameras and self.image_size is not None and not low <= self.image_size <= 512:
            raise UsageError(f"image_size must be in [{low}, 512], got {self.image_size}")
        return tasks

    def _check_format(self, expert: DemoExpert) -> None:
        """``UsageError`` for an unknown format, or the lerobot format where it cannot hold."""
        if self.format not in FORMATS:
            raise UsageError(f"format must be one of {', '.join(FORMATS)}, got {self.format!r}")
        if self.format == "cso":
            return
        camera = getattr(expert, "lerobot_camera", None)  # only worlds with a LeRobot format of their own have one
        if camera is None:
            world = self.world_settings().type
            raise UsageError(f"--format=lerobot is LeRobot's MetaWorld format; {world} has none: use --format=cso")
        if parse_cameras(self.cameras) not in ((), (camera,)):
            raise UsageError(f"--format=lerobot holds one camera, LeRobot's {camera}; got --cameras={self.cameras}")
        if self.state not in (None, expert.lerobot_state):
            raise UsageError(f"--format=lerobot holds the {expert.lerobot_state} state; got --state={self.state}")


def _resolve(world: SimWorld, spec: str) -> list[str]:
    try:
        return world.resolve_tasks(spec)
    except ValueError as e:
        raise UsageError(str(e)) from None


def check_dataset(cfg: DemosConfig) -> tuple[list[str], LeRobotDatasetMetadata]:
    """The tasks of ``cfg`` and the metadata of the dataset at ``cfg.dataset_root``, checked to fit each other
    and the tasks' world. Raises ``UsageError``."""
    world = cfg.world_settings().build(cfg.tasks, None, None)
    tasks = _resolve(world, cfg.tasks)
    root = cfg.dataset_root
    try:
        meta = LeRobotDatasetMetadata(cfg.repo_id, root=root)
    except (OSError, httpx.HTTPError) as e:  # not on disk, and the Hub is unreachable or has no such dataset
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise UsageError(f"{root} holds no LeRobotDataset and {cfg.repo_id} could not be fetched: {reason}") from None
    for key, dims in (("observation.state", world.state_dims), ("action", (world.action_dim,))):
        shape = tuple(meta.features[key]["shape"]) if key in meta.features else None
        if shape not in [(dim,) for dim in dims]:
            wanted = " or ".join(f"({dim},)" for dim in dims)
            raise UsageError(f"{root}: {world.name} needs '{key}' of shape {wanted}, the dataset has {shape}")
    cameras = list(camera_inputs(meta.features, world).values())  # LeRobot's observation.image: its MetaWorld view
    unknown = [cam for cam in cameras if cam not in world.cameras]
    if unknown:
        raise UsageError(
            f"{root}: camera(s) {', '.join(unknown)} are not {world.name}'s; its cameras: {', '.join(world.cameras)}"
        )
    known = set(meta.tasks.index)
    missing = [task for task in tasks if world.task_description(task) not in known]
    if missing:
        raise UsageError(
            f"{root} has no episodes of {', '.join(missing)} (by task description); its tasks: "
            + "; ".join(map(repr, sorted(known)))
        )
    return tasks, meta


def metadata_keys(expert: DemoExpert) -> tuple[str, str, str]:
    """The per-frame columns naming an episode's task, initial state and outcome."""
    return f"{expert.prefix}.task", f"{expert.prefix}.init_seed", f"{expert.prefix}.success"


def image_key(camera: str, layout: str) -> str:
    """The dataset key of a camera's frames: ``observation.images.<camera>``; LeRobot's single ``observation.image``
    in its own format."""
    return OBS_IMAGE if layout == "lerobot" else f"{OBS_IMAGES}.{camera}"


def dataset_features(
    expert: DemoExpert, cameras: Iterable[str], image_size: int, state: str, layout: str = "cso"
) -> dict[str, dict]:
    """LeRobotDataset features of a demo dataset in format ``layout`` (LeRobot's own: no metadata columns, video)."""
    features: dict[str, dict] = {
        "observation.state": {"dtype": "float32", "shape": (expert.state_dim(state),), "names": None},
        "action": {"dtype": "float32", "shape": (len(expert.action_names),), "names": expert.action_names},
    }
    if layout == "cso":
        task_key, seed_key, success_key = metadata_keys(expert)
        features[task_key] = {"dtype": "string", "shape": (1,), "names": None}
        features[seed_key] = {"dtype": "int64", "shape": (1,), "names": None}
        features[success_key] = {"dtype": "bool", "shape": (1,), "names": None}
    for cam in cameras:
        features[image_key(cam, layout)] = {
            "dtype": "video" if layout == "lerobot" else "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channel"],
        }
    return features


def _staging(cfg: DemosConfig) -> EpisodeJournal:
    """``<output_dir>.partial/``: one ``.npz`` per finished episode (``episodes/<task>/<seed>.npz``)."""
    root = cfg.output_dir.with_name(cfg.output_dir.name + ".partial")
    return EpisodeJournal(root, cfg.spec(), what="an interrupted generation")


def _staged(staging: EpisodeJournal) -> dict[tuple[str, int], bool]:
    """(task, init_seed) → success of every staged episode."""
    out = {}
    for path in staging.episode_files():
        out[(path.parent.name, int(path.stem))] = bool(staging.load(path, ("success",))["success"])
    return out


def existing_episodes(cfg: DemosConfig) -> dict[tuple[str, int], bool]:
    """(task, init_seed) → success of the episodes already in ``output_dir``; refuses a different dataset."""
    out = cfg.output_dir
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return {}
    spec_path = out / SPEC_FILE
    if not spec_path.is_file():
        raise UsageError(f"{out} exists and is not a demo dataset of lerobot-cso; choose another --output_dir")
    spec = without_added_settings(read_json(spec_path))
    wanted = without_added_settings(cfg.spec())
    if spec != wanted:
        diff = {k: (spec.get(k), wanted.get(k)) for k in {**spec, **wanted} if spec.get(k) != wanted.get(k)}
        raise UsageError(
            f"{out} holds a different dataset (setting: (on disk, requested) = {diff}); choose another --output_dir"
        )
    if cfg.format == "lerobot":
        return {(task, seed): ok for task, seed, ok in read_json(out / EPISODES_FILE)}
    ds = LeRobotDataset(cfg.repo_id, root=out, video_backend="pyav")
    keys = metadata_keys(cfg.expert())
    firsts = ds.hf_dataset.select_columns(["episode_index", *keys]).to_pandas().drop_duplicates("episode_index")
    return {
        (task, int(np.asarray(seed).reshape(-1)[0])): bool(np.asarray(ok).reshape(-1)[0])
        for task, seed, ok in zip(*(firsts[key] for key in keys), strict=True)
    }


def _plan(
    tasks: list[str], per_task: int, keep_failed: bool, known: dict[tuple[str, int], bool], states: range
) -> list[tuple]:
    """The next (task, init_seed) to run: per task, the lowest demo states not run yet, enough to fill it."""
    jobs = []
    for task in tasks:
        tried = sorted(s for t, s in known if t == task)
        kept = sum(1 for s in tried if keep_failed or known[(task, s)])
        missing = per_task - kept
        if missing <= 0:
            continue
        if not keep_failed and len(tried) >= MAX_ATTEMPTS_PER_EPISODE * per_task:
            raise UsageError(
                f"the {task} expert succeeded in only {kept} of {len(tried)} episodes; "
                f"use --keep_failed=true or fewer --episodes_per_task"
            )
        candidates = (s for s in states if (task, s) not in known)
        jobs.extend((task, next(candidates)) for _ in range(missing))
    return jobs


def _generate(cfg: DemosConfig, tasks: list[str], staging: EpisodeJournal, known: dict[tuple[str, int], bool]) -> None:
    """Run episodes until every task has its count (staged + in the dataset); each one is staged at once."""
    from lerobot_cso.rollout.backend import Job

    expert = cfg.expert()
    with expert.pool(cfg.num_envs, parse_cameras(cfg.cameras), cfg.image_size, cfg.max_steps) as pool:
        while jobs := _plan(tasks, cfg.episodes_per_task, cfg.keep_failed, known, expert.demo_states):
            controller = expert.controller(cfg.num_envs, cfg.noise_std, cfg.seed)
            for _, trace in pool.run([Job(t, s) for t, s in jobs], controller, progress="demo episodes"):
                arrays = {"success": np.array(trace.success), "states": trace.states, "actions": trace.actions}
                arrays.update({f"image_{cam}": frames for cam, frames in trace.images.items()})
                staging.save_episode(trace.job.task, f"{trace.job.init_seed:07d}", arrays)
                known[(trace.job.task, trace.job.init_seed)] = trace.success


def _assemble(cfg: DemosConfig, tasks: list[str], staging: EpisodeJournal, in_dataset: set[tuple[str, int]]) -> int:
    """Write the staged episodes (task order, then seed order) into the dataset; returns how many."""
    staged = _staged(staging)
    keys = [
        (task, s)
        for task in tasks
        for s in sorted(s for t, s in staged if t == task)
        if (task, s) not in in_dataset and (cfg.keep_failed or staged[(task, s)])
    ]
    if not keys:
        return 0
    cameras = parse_cameras(cfg.cameras)
    expert = cfg.expert()
    lerobot = cfg.format == "lerobot"
    task_key, seed_key, success_key = metadata_keys(expert)
    describe = expert.lerobot_task if lerobot else cfg.world_settings().build(cfg.tasks, None, None).task_description
    work = staging.root / "dataset"
    if work.exists():
        shutil.rmtree(work)  # an assembly that was interrupted: redo it
    writer_threads = 4 if cameras else 0  # PNG encoding of camera frames
    if in_dataset:
        shutil.copytree(cfg.output_dir, work)
        ds = LeRobotDataset.resume(cfg.repo_id, root=work, video_backend="pyav", image_writer_threads=writer_threads)
    else:
        ds = LeRobotDataset.create(
            cfg.repo_id,
            expert.fps,
            dataset_features(expert, cameras, cfg.image_size, cfg.state, cfg.format),
            root=work,
            robot_type=expert.robot_type,
            use_videos=lerobot,
            video_backend="pyav",
            image_writer_threads=writer_threads,
        )
    episodes = (read_json(work / EPISODES_FILE) or []) if lerobot else []  # in episode order
    bars_were_enabled = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()  # one "Map" bar per saved episode otherwise
    try:
        for task, init_seed in tqdm(keys, desc="writing dataset", leave=False):
            ep = staging.load(staging.episode_path(task, f"{init_seed:07d}"))
            success = bool(ep["success"])
            meta = {task_key: task, seed_key: np.array([init_seed], dtype=np.int64), success_key: np.array([success])}
            if lerobot:  # not in LeRobot's frames: kept beside them
                episodes.append([task, init_seed, success])
            for t in range(len(ep["actions"])):
                frame = {
                    "observation.state": expert.dataset_state(ep["states"][t], cfg.state),
                    "action": ep["actions"][t],
                    "task": describe(task),
                }
                frame.update({image_key(cam, cfg.format): ep[f"image_{cam}"][t] for cam in cameras})
                ds.add_frame(frame if lerobot else {**frame, **meta})
            ds.save_episode()
        ds.finalize()
    finally:
        if bars_were_enabled:
            hf_logging.enable_progress_bar()
    if lerobot:
        write_json(work / EPISODES_FILE, episodes)
    write_json(work / SPEC_FILE, cfg.spec())
    replace_dir(work, cfg.output_dir)
    return len(keys)


def generate_demos(cfg: DemosConfig) -> dict[str, Any]:
    """Generate (or resume / top up) the demo dataset; returns a summary per task."""
    tasks = cfg.validate()
    cfg = cfg.resolved()
    restore_interrupted_replace(cfg.output_dir)
    in_dataset = existing_episodes(cfg)
    staging = _staging(cfg)
    known = {**_staged(staging), **in_dataset}
    _generate(cfg, tasks, staging, known)
    written = _assemble(cfg, tasks, staging, set(in_dataset))
    shutil.rmtree(staging.root)
    final = existing_episodes(cfg)
    return {
        "output_dir": str(cfg.output_dir),
        "new_episodes": written,
        "total_episodes": len(final),
        "tasks": {
            task: {
                "episodes": sum(1 for t, _ in final if t == task),
                # over every episode run for the task in this session and kept before (failures included)
                "expert_success_rate": float(np.mean([ok for (t, _), ok in known.items() if t == task])),
            }
            for task in tasks
        },
    }


class DemosStage:
    """The pipeline's demo stage: the dataset generated at ``cfg.output_dir``."""

    name = "demos"
    redo_on_change = False
    grows = ()

    def __init__(self, cfg: DemosConfig) -> None:
        self.cfg = cfg

    def spec(self) -> dict[str, Any]:
        # num_envs only splits the work: the dataset is the same bit for bit.
        cfg = self.cfg.resolved()
        demos = settings_spec(cfg, exclude=(*PIPELINE_FIELDS, "num_envs", "format")) | cfg.format_spec()
        return {"tasks": cfg.validate(), "demos": demos}

    def output(self) -> Path:
        return self.cfg.output_dir

    def complete(self) -> bool:
        return (self.cfg.output_dir / SPEC_FILE).is_file()  # written inside the dataset before it is swapped in

    def run(self) -> dict[str, Any]:
        return generate_demos(self.cfg)


class DatasetStage:
    """The pipeline's demo stage over an existing dataset (``cfg.dataset_root``): checked, never generated.

    Its spec names the dataset and its size, so a dataset that changed is checked again and the IL trained on
    the old one is refused as stale.
    """

    name = "demos"
    redo_on_change = True  # only a check: redoing it is cheap, and it never writes into the user's dataset
    grows = ()

    def __init__(self, cfg: DemosConfig) -> None:
        self.cfg = cfg

    def spec(self) -> dict[str, Any]:
        tasks, meta = check_dataset(self.cfg)
        dataset = {"root": str(self.cfg.dataset_root), "repo_id": self.cfg.repo_id}
        return {"tasks": tasks, "dataset": dataset | {"episodes": meta.total_episodes, "frames": meta.total_frames}}

    def output(self) -> Path:
        return self.cfg.dataset_root

    def complete(self) -> bool:
        return (self.cfg.dataset_root / "meta" / "info.json").is_file()

    def run(self) -> dict[str, Any]:
        _, meta = check_dataset(self.cfg)
        return {
            "dataset_root": str(self.cfg.dataset_root),
            "repo_id": self.cfg.repo_id,
            "total_episodes": meta.total_episodes,
            "total_frames": meta.total_frames,
            "tasks": list(meta.tasks.index),
        }


def demos_stage(cfg: DemosConfig) -> DemosStage | DatasetStage:
    """The demo stage of ``cfg``: the given dataset, or the generated one."""
    return DemosStage(cfg) if cfg.dataset_root is None else DatasetStage(cfg)


@parser.wrap()
def demos_main(cfg: DemosConfig) -> None:
    """Entry point of ``lerobot-cso demos`` (with ``--dataset_root``: only checks that dataset)."""
    if cfg.dataset_root is not None:
        summary = DatasetStage(cfg).run()
        episodes, frames = summary["total_episodes"], summary["total_frames"]
        print(f"{cfg.dataset_root}: {episodes} episodes, {frames} frames; usable for --tasks={cfg.tasks}")
        return
    with output_lock(cfg.output_dir), interruptible(f"generating {cfg.output_dir}"):
        summary = generate_demos(cfg)
    print(f"{summary['output_dir']}: {summary['total_episodes']} episodes ({summary['new_episodes']} new)")
    for task, info in summary["tasks"].items():
        print(f"  {task:32s} {info['episodes']:5d} episodes, expert success {info['expert_success_rate']:.0%}")
