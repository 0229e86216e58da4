"""The ``meshbench`` command. Each subcommand lives in ``benchmarks/commands/NAME.py`` and
exposes ``register(subparsers)``; add a module name to ``COMMANDS`` to add a subcommand.
Heavy imports (torch) happen inside the subcommand, so data commands work without them."""

from __future__ import annotations

import argparse
import importlib
import sys

from benchmarks.registry import RegistryError

COMMANDS = ["generate", "simulate", "export", "crosscheck", "compare", "train", "rollout",
            "bench", "run"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshbench", description=__doc__.split("\n")[0])
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                        help="Python file that registers cases/models (repeatable; also "
                             "$MESHBENCH_PLUGINS and the 'meshbench.plugins' entry points)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"benchmarks.commands.{name}").register(sub)
    return parser


def main(argv=None) -> int:
    from benchmarks import plugins
    from groundtruth.implicit import ConvergenceError
    from groundtruth.store import StoreError

    args = build_parser().parse_args(argv)
    try:
        plugins.load_all(args.plugin)
        return int(args.func(args) or 0)
    except (ValueError, RegistryError, StoreError, ConvergenceError, FileNotFoundError,
            FloatingPointError) as e:
        print(f"meshbench {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"meshbench {args.command}: interrupted; finished work is kept, run it again "
              "to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
