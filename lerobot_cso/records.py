"""Stage records: the one rule by which a rerun skips, continues or refuses an existing output.

A record (JSON) holds the spec a stage's output was made with, whether it completed, when, and its summary.
:func:`run_recorded` reads it before the stage does anything: the same spec and a complete output is skipped;
a spec that only grows in one of the stage's ``grows`` keys continues; any other difference over a complete output or
one holding work (:func:`holds_work`) is refused with one line naming every changed setting (``redo_on_change``
stages are simply redone). So is work without the stage's own record (:func:`check_own_record`): its settings are
unknown.

The pipeline keeps one record per stage in ``<output_dir>/stages/``, its specs naming the upstream stage's run;
a stage run by its own command (``lerobot-cso rsft|spo``, :func:`run_alone`) keeps its record in its output dir,
its spec naming its tasks and its input checkpoint (path and weights) instead.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any

from lerobot_cso.durable import output_lock, read_json, write_json
from lerobot_cso.errors import UsageError, interruptible
from lerobot_cso.stage import Stage, without_added_settings

ALONE_RECORD = "stage.json"  # the record of a stage run by its own command, in its output dir
# Settings of a policy that do not change what a stage makes with it: where it runs, where it is published.
RUNTIME_POLICY_FIELDS = (
    "device",
    "pretrained_path",
    "pretrained_revision",
    "push_to_hub",
    "repo_id",
    "private",
    "tags",
    "license",
)


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested JSON data as ``{"a.b.c": leaf}``."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out |= flatten(value, f"{prefix}.{key}" if prefix else key)
    return out


def holds_work(output: Path, record_path: Path) -> bool:
    """Whether ``output`` holds anything a run made besides the stage's record and the ``spec.json`` of journals
    that hold no episode yet: a run that failed before any work (a robot that did not connect) binds no setting."""
    bookkeeping = {record_path, *output.rglob("spec.json")}
    return any(p.is_file() and p not in bookkeeping for p in output.rglob("*"))


def check_own_record(stage: Stage, record_path: Path, record: dict[str, Any] | None, elsewhere: str) -> None:
    """Refuse an output that holds work but not this stage's own record (made by the pipeline when run alone, by a
    stage's own command inside a pipeline, or by an older version): nothing says which settings, inputs or policy
    made it, so it is never continued, skipped or reported, unless the stage proves its origin from the work itself
    (``proven_origin()``: an R-SFT collection whose journal holds this run's collection settings)."""
    output = stage.output()
    alone = output / ALONE_RECORD
    if alone != record_path and alone.is_file():
        raise UsageError(
            f"{output} holds the work of a stage run by its own command ({alone}), not this run's; {elsewhere}"
        )
    proven = getattr(stage, "proven_origin", lambda: False)
    if record is None and holds_work(output, record_path) and not proven():
        raise UsageError(
            f"{output} holds work but no record of the settings, inputs and policy it was made with ({record_path} "
            f"is missing: another command or an older version made it), so it cannot be continued; {elsewhere}"
        )


def run_recorded(
    stage: Stage, record_path: Path, spec: dict[str, Any], label: str, elsewhere: str, write: bool = True
) -> tuple[Any, float]:
    """Run ``stage`` under the record at ``record_path`` (see the module docstring); returns its summary and
    seconds (the recorded ones when skipped). ``label`` prefixes the progress lines; ``elsewhere`` ends the
    refusal (what to delete or choose instead). Only a process with ``write`` writes the record."""
    output, record = stage.output(), read_json(record_path)
    if not stage.redo_on_change:
        check_own_record(stage, record_path, record, elsewhere)
    current = without_added_settings(spec)
    recorded = None if record is None else without_added_settings(record["spec"])
    same = recorded == current
    bound = record is not None and (record["complete"] or holds_work(output, record_path))
    if bound and not same and not stage.redo_on_change:
        old, new = flatten(recorded), flatten(current)
        changed = [k for k in sorted(old.keys() | new.keys()) if old.get(k) != new.get(k)]
        listed = ", ".join(f"{k}: {old.get(k)} → {new.get(k)}" for k in changed)
        if not all(k in stage.grows and isinstance(old.get(k), int) and new.get(k, 0) > old[k] for k in changed):
            raise UsageError(f"{output} was made with other settings or inputs ({listed}); {elsewhere}")
        print(f"{label}: continuing ({listed})", flush=True)
    if same and record["complete"] and stage.complete():
        print(f"{label}: complete, skipped ({output})", flush=True)
        return record["summary"], record["seconds"]
    print(f"{label}: running → {output}", flush=True)
    if write:
        record_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(record_path, {"spec": spec, "complete": False})
    started = time.perf_counter()
    with interruptible(f"stage {stage.name}, writing {output}"):
        summary = stage.run()
    seconds = time.perf_counter() - started
    if write:
        finished = dt.datetime.now().isoformat()
        record = {"spec": spec, "complete": True, "finished_at": finished, "seconds": seconds, "summary": summary}
        write_json(record_path, record)
    print(f"{label}: done in {seconds:.0f} s", flush=True)
    return summary, seconds


def checkpoint_identity(path: Path) -> dict[str, str]:
    """A saved policy as a spec entry: its directory and the sha256 (first 16 hex digits) of its weights."""
    weights = Path(path) / "model.safetensors"
    if not weights.is_file():
        raise UsageError(f"{weights} is missing: --policy.path must be a policy saved with its weights")
    digest = hashlib.sha256()
    with open(weights, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return {"path": str(Path(path).resolve()), "weights_sha256": digest.hexdigest()[:16]}


def policy_overrides(config: Any) -> dict[str, Any]:
    """The settings in which ``config``, a policy config loaded with ``--policy.*`` overrides, differs from the one
    saved at its ``pretrained_path`` (not where it runs or is published: :data:`RUNTIME_POLICY_FIELDS`), as JSON."""
    import draccus
    from lerobot.configs.policies import PreTrainedConfig

    saved, given = draccus.encode(PreTrainedConfig.from_pretrained(config.pretrained_path)), draccus.encode(config)
    keys = sorted((saved.keys() | given.keys()) - set(RUNTIME_POLICY_FIELDS))
    return json.loads(json.dumps({k: given.get(k) for k in keys if saved.get(k) != given.get(k)}, default=str))


def run_alone(stage: Any, main: bool = True) -> Any:
    """Run a checkpoint stage (R-SFT, SPO) by its own command, under its record ``<output_dir>/stage.json``: its
    settings, tasks and input checkpoint (with its ``--policy.*`` overrides) must match that record's to resume or
    skip (more SPO iterations continue); returns the stage's summary. Only the ``main`` process writes the record,
    holding the output dir's lock (:func:`~lerobot_cso.durable.output_lock`) meanwhile."""
    cfg = stage.cfg
    spec = stage.spec() | {"tasks": cfg.validate()}
    overrides = policy_overrides(cfg.policy)  # the --policy.* settings given: what the stage made is theirs
    spec["policy"] = checkpoint_identity(cfg.policy.pretrained_path) | ({"overrides": overrides} if overrides else {})
    elsewhere = "delete it or choose another --output_dir"
    with output_lock(cfg.output_dir) if main else nullcontext():
        return run_recorded(stage, cfg.output_dir / ALONE_RECORD, spec, stage.name, elsewhere, write=main)[0]
