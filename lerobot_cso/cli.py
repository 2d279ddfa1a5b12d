"""``lerobot-cso <subcommand> [--a.b=c ...] [--config_path=configs/<file>.yaml]``.

Each subcommand is a function decorated with ``lerobot.configs.parser.wrap()`` over a draccus dataclass,
so it is configured exactly like LeRobot's own scripts. Registering one is one line in ``SUBCOMMANDS``.
Bad input raises :class:`~lerobot_cso.errors.UsageError`: one ``error: ...`` line on stderr, exit code 2 — also
what the argument parser rejects (an unknown ``--robot.type``, a misspelt option), without its usage dump.
"""

import sys
from collections.abc import Callable

from lerobot.utils.import_utils import register_third_party_plugins

from lerobot_cso.cso.rsft import rsft_main
from lerobot_cso.cso.spo import spo_main
from lerobot_cso.demos import demos_main
from lerobot_cso.errors import UsageError, parse_errors_as_usage_errors
from lerobot_cso.evaluation import eval_main
from lerobot_cso.pipeline import pipeline_main

SUBCOMMANDS: dict[str, Callable[[], object]] = {
    "demos": demos_main,
    "eval": eval_main,
    "rsft": rsft_main,
    "spo": spo_main,
    "pipeline": pipeline_main,
}


def _usage() -> str:
    names = ", ".join(SUBCOMMANDS)
    return f"usage: lerobot-cso {{{names}}} [--key=value ...] [--config_path=FILE.yaml]  (--help per subcommand)"


def main(argv: list[str] | None = None) -> int:
    """Dispatch on the first argument; the rest is parsed by the subcommand's config (LeRobot style)."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help"):
        print(_usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    name, rest = args[0], args[1:]
    command = SUBCOMMANDS.get(name)
    if command is None:
        print(f"error: unknown subcommand '{name}'; choose one of: {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        return 2
    sys.argv = [f"lerobot-cso {name}", *rest]  # parser.wrap() reads sys.argv
    register_third_party_plugins()
    try:
        with parse_errors_as_usage_errors():
            command()
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
