"""The ``meshbench`` command. Each subcommand lives in ``benchmarks/commands/NAME.py`` and
exposes ``register(subparsers)``; add a module name to ``COMMANDS`` to add a subcommand.
Heavy imports (torch) happen inside the subcommand, so data commands work without them; not
even numpy is imported before ``main`` has pinned the kernel settings (``procs.REPRO_ENV``;
torch's are skipped for ``--device cuda``)."""

from __future__ import annotations

import argparse
import importlib
import shlex
import signal
import sys
import threading
from pathlib import Path

COMMANDS = ["generate", "simulate", "export", "crosscheck", "plate_fidelity", "compare", "train",
            "rollout", "animate", "bench", "run", "tolerance", "convert_checkpoint",
            "curves", "convergence"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshbench", description=__doc__.split("\n")[0])
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                        help="Python file that registers cases/models (repeatable; also "
                             "$MESHBENCH_PLUGINS and the 'meshbench.plugins' entry points)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"benchmarks.commands.{name}").register(sub)
    return parser


def _interrupt_message(args, argv, e: BaseException) -> str:
    """What an interruption kept and the command that resumes it, per subcommand."""
    words = list(sys.argv[1:] if argv is None else argv)
    again = "meshbench " + " ".join(shlex.quote(w) for w in words)
    if args.command == "train":
        out = Path(args.out)
        kept = (f"{out / 'last.pt'} keeps the last finished epoch" if (out / "last.pt").exists()
                else "no epoch had finished, nothing was kept")
        if not (out / "last.pt").exists():
            return f"{kept}; start again with `{again}`"
        resume = again if "--resume" in words else again + " --resume"
        return f"{kept}; continue exactly with `{resume}`"
    if args.command == "generate":
        detail = f"{e}; " if str(e) else ""
        return f"{detail}finished trajectories are kept; resume with `{again}`"
    if args.command == "bench" and getattr(args, "what", None) == "scale":
        resume = again if "--resume" in words else again + " --resume"
        return (f"the rows measured so far are in {Path(args.out) / 'scale.csv'}; continue "
                f"with `{resume}`")
    if args.command == "run":
        detail = f"{e}; " if str(e) else "finished runs are kept; "
        return f"{detail}resume with `{again}`"
    return f"nothing partial was written; run `{again}` again"


def main(argv=None) -> int:
    from benchmarks.suite import procs

    # the pins must precede numpy / torch loading their kernels (see procs.REPRO_ENV); numpy's
    # before the command modules load, torch's once --device says whether the model runs on
    # the CPU (torch is not imported while parsing)
    procs.apply_repro_env("cuda")
    from benchmarks.suite import plugins
    from benchmarks.suite.procs import LockBusy
    from benchmarks.suite.registry import RegistryError
    from groundtruth.implicit import ConvergenceError
    from groundtruth.store import StoreError

    args = build_parser().parse_args(argv)
    procs.apply_repro_env(getattr(args, "device", None))
    # SIGTERM stops like Ctrl-C (workers stopped, partial work kept), not mid-write
    old_term = None
    if threading.current_thread() is threading.main_thread():
        old_term = signal.signal(signal.SIGTERM, _sigterm)
    try:
        plugins.load_all(args.plugin)
        return int(args.func(args) or 0)
    except (ValueError, RegistryError, StoreError, ConvergenceError, FileNotFoundError,
            FloatingPointError, LockBusy) as e:
        print(f"meshbench {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"meshbench {args.command}: interrupted; {_interrupt_message(args, argv, e)}",
              file=sys.stderr)
        return 130
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _sigterm(signum, frame):
    raise KeyboardInterrupt()


if __name__ == "__main__":
    sys.exit(main())
