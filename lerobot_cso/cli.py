"""``lerobot-cso <subcommand> [--a.b=c ...] [--config_path=configs/<file>.yaml]``.

Each subcommand is a function decorated with ``lerobot.configs.parser.wrap()`` over a draccus dataclass,
so it is configured exactly like LeRobot's own scripts. Registering one is one line in ``SUBCOMMANDS``; its module
is imported only when it runs (torch and LeRobot take seconds), so ``lerobot-cso --help`` and a misspelt
subcommand answer at once. A subcommand's ``--help`` is kept once made (:func:`help_cache`, per install), so it too
answers at once the next time, and an option it does not list is refused from it without those imports.
Bad input raises :class:`~lerobot_cso.errors.UsageError`: one ``error: ...`` line on stderr, exit code 2 — also
what the argument parser rejects (an unknown ``--robot.type``, a misspelt option, a value of the wrong type),
without its usage dump. A full disk is one ``error:`` line naming the file, exit code 1. Ctrl-C ends the command
with one line saying where it stopped, exit code 130. After either, the work it finished is saved, and the same
command resumes from it (an evaluation, written only at its end, starts over).
"""

import contextlib
import errno
import hashlib
import importlib
import inspect
import io
import os
import re
import sys
import sysconfig
from collections.abc import Callable
from pathlib import Path

from lerobot_cso.errors import (
    EnvWorkerError,
    UsageError,
    check_config_path,
    interrupted_where,
    parse_errors_as_usage_errors,
)
from lerobot_cso.stage import POLICY_ROLES

ROBOT_WORLD_FIELDS = ("robot", "teleop", "operator", "display_data")  # --world.<field>, spelt --<field> for short
ROLLOUT_STAGES = ("eval", "rsft", "spo")
# What a Ctrl-C leaves of a command that writes its output only at the end (the others resume their saved work).
RESTARTS = {"eval": "nothing is written before it ends, so the same command starts it over"}
SUBCOMMANDS: dict[str, str] = {  # name -> "module:function"
    "demos": "lerobot_cso.demos:demos_main",
    "eval": "lerobot_cso.evaluation:eval_main",
    "rsft": "lerobot_cso.cso.rsft:rsft_main",
    "spo": "lerobot_cso.cso.spo:spo_main",
    "pipeline": "lerobot_cso.pipeline:pipeline_main",
}


def _usage() -> str:
    names = ", ".join(SUBCOMMANDS)
    return f"usage: lerobot-cso {{{names}}} [--key=value ...] [--config_path=FILE.yaml]  (--help per subcommand)"


def robot_world_args(args: list[str]) -> list[str]:
    """A rollout stage's ``--robot.*``, ``--teleop.*``, ``--operator.*`` and ``--display_data`` as the robot world's
    ``--world.*`` settings, with ``--world.type=robot`` when no ``--world.type`` is given (the short spelling)."""
    short = [a for a in args if a.startswith("--") and a[2:].split("=")[0].split(".")[0] in ROBOT_WORLD_FIELDS]
    if not short:
        return args
    spelt = [f"--world.{a.removeprefix('--')}" if a in short else a for a in args]
    if not any(a.startswith("--world.type") for a in args):
        spelt.insert(0, "--world.type=robot")
    return spelt


def _command(name: str) -> Callable[[], object]:
    module, function = SUBCOMMANDS[name].split(":")
    return getattr(importlib.import_module(module), function)


def help_cache(name: str) -> Path:
    """Where the ``--help`` text of subcommand ``name`` is kept for this install: named after the state of
    lerobot_cso's sources and of the environment's site-packages (an edit, or a package or plugin installed or
    removed, makes another one)."""
    package = Path(__file__).parent
    state = [(str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(package.rglob("*.py"))]
    state += [(d, os.stat(d).st_mtime_ns, 0) for d in sorted({sysconfig.get_path(k) for k in ("purelib", "platlib")})]
    key = hashlib.sha256(repr(state).encode()).hexdigest()[:16]
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "lerobot_cso" / "help"
    return root / f"{name}-{key}.txt"


def _help_text(command: Callable[[], object]) -> str:
    """The ``--help`` of a ``parser.wrap()`` command (LeRobot's scoped help of its config class)."""
    from lerobot.configs.parser import print_scoped_help

    fn = inspect.unwrap(command)
    spec = inspect.getfullargspec(fn)
    with contextlib.redirect_stdout(io.StringIO()) as text:
        print_scoped_help(spec.annotations[spec.args[0]], [])
    return text.getvalue()


def _keep_help(name: str, command: Callable[[], object]) -> str:
    """Make and keep the ``--help`` of subcommand ``name`` (a cache: a failure to write it changes nothing)."""
    from lerobot_cso.durable import write_atomic

    text = _help_text(command)
    path = help_cache(name)
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, text.encode(), shared=True)
    return text


def unlisted_options(args: list[str], help_text: str) -> list[str]:
    """The ``--options`` in ``args`` whose setting (its first part: ``sampling`` of ``--sampling.top_k``) the help
    does not list; a misspelt part below it is left to the parser, as choices (``--world.type``) and plugins add
    their own."""
    listed = set(re.findall(r"--([\w.]+)", help_text))
    return [a for a in args if a.startswith("--") and a[2:].split("=")[0].split(".")[0] not in listed]


def main(argv: list[str] | None = None) -> int:
    """Dispatch on the first argument; the rest is parsed by the subcommand's config (LeRobot style)."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help"):
        print(_usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in SUBCOMMANDS:
        print(f"error: unknown subcommand '{name}'; choose one of: {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        return 2
    if name in ROLLOUT_STAGES:
        rest = robot_world_args(rest)
    sys.argv = [f"lerobot-cso {name}", *rest]  # parser.wrap() reads sys.argv
    kept = help_cache(name)
    if rest in (["--help"], ["-h"]) and kept.is_file():
        print(kept.read_text(), end="")
        return 0
    unlisted = unlisted_options(rest, kept.read_text()) if kept.is_file() else []
    if unlisted:
        print(f"error: unrecognized arguments: {' '.join(unlisted)}", file=sys.stderr)
        return 2
    given = {a.lstrip("-").split("=")[0].split(".")[0] for a in rest if a.startswith("-")}
    if name in POLICY_ROLES and not given & {"policy", "config_path", "h", "help"}:  # said as validate() says it
        print(f"error: --policy.path is required ({POLICY_ROLES[name]})", file=sys.stderr)
        return 2
    try:
        check_config_path(rest)
        # Inside the try: the imports take seconds (minutes on a loaded machine), and a Ctrl-C may land in them.
        from lerobot.utils.import_utils import register_third_party_plugins

        register_third_party_plugins()
        command = _command(name)
        if not kept.is_file():
            help_text = _keep_help(name, command)
            if rest in (["--help"], ["-h"]):
                print(help_text, end="")
                return 0
        with parse_errors_as_usage_errors():
            command()
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno != errno.ENOSPC and "No space left on device" not in str(e):
            raise
        where = f" writing {e.filename}" if e.filename else ""
        print(
            f"\nerror: lerobot-cso {name} stopped: no space left on the device{where}; free some and rerun: "
            f"{RESTARTS.get(name, 'the work it finished is saved, and the same command resumes from it')}",
            file=sys.stderr,
        )
        return 1
    except EnvWorkerError as e:
        print(
            f"\nerror: lerobot-cso {name} stopped: {e} (its traceback is above); "
            f"{RESTARTS.get(name, 'the work it finished is saved, and the same command resumes from it')}",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt as e:
        where = interrupted_where(e)
        # On a line of its own: a progress bar may hold the cursor (the "\n" ends it).
        print(
            f"\ninterrupted: lerobot-cso {name} stopped{f' in {where}' if where else ''}; "
            f"{RESTARTS.get(name, 'the work it finished is saved, and the same command resumes from it')}",
            file=sys.stderr,
        )
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
