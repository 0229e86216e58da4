"""``meshbench convert-checkpoint PATH... [--i-trust-this-file]``: rewrite old-format
checkpoints in the safe format.

meshbench loads checkpoints with ``torch.load(..., weights_only=True)``: tensors and plain
containers only, so opening a run directory received from someone else never runs code. A
checkpoint holding other objects (an old format, or a file crafted to run a command when
unpickled) is refused. This command converts such a file, but only with ``--i-trust-this-file``:
converting loads it once with full unpickling, which runs whatever code the file carries.
Without the flag it only reports which files need converting (exit 2 if any). A PATH may be a
``.pt`` file or a run directory (its ``best.pt`` and ``last.pt``); files are rewritten in place,
atomically. See docs/SECURITY.md."""

from __future__ import annotations

from pathlib import Path


def register(sub):
    p = sub.add_parser("convert-checkpoint", help="rewrite trusted old-format checkpoints "
                       "in the safe (weights-only) format", description=__doc__)
    p.add_argument("paths", nargs="+", metavar="PATH", help="a .pt file or a run directory")
    p.add_argument("--i-trust-this-file", dest="trust", action="store_true",
                   help="load the files with full unpickling (runs any code they carry) and "
                        "rewrite them; only for files whose origin you trust")
    p.set_defaults(func=run)


def _files(paths) -> list[Path]:
    out = []
    for p in map(Path, paths):
        if p.is_dir():
            found = [p / f for f in ("best.pt", "last.pt") if (p / f).exists()]
            if not found:
                raise FileNotFoundError(f"{p}: no best.pt or last.pt in this directory")
            out += found
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(f"{p}: no such file or directory")
    return out


def run(args):
    from meshodenet.training.train import UnsafeCheckpointError, convert_checkpoint, load_checkpoint

    files = _files(args.paths)
    if not args.trust:
        unsafe = []
        for f in files:
            try:
                load_checkpoint(f)
                print(f"{f}: already in the safe format")
            except UnsafeCheckpointError:
                unsafe.append(str(f))
        if unsafe:
            raise ValueError(f"{', '.join(unsafe)}: old format (loading it could run code); "
                             "rerun with --i-trust-this-file ONLY if you trust where it came "
                             "from")
        return 0
    for f in files:
        changed = convert_checkpoint(f)
        print(f"{f}: {'converted' if changed else 'already in the safe format, unchanged'}")
    return 0
