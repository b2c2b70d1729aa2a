"""`rbdyn`'s entry point: parse the arguments, run the command, turn warnings and Ctrl-C
into one line each."""

import sys
import warnings

from ._common import EXIT_INTERRUPTED, EXIT_USAGE
from ._demo import demo, scenarios_command
from ._fit import fit_command
from ._parser import build_parser
from ._store import export_command, plot_command, verify_command
from ._sweep import sweep_command


def main(argv: list[str] | None = None) -> int:
    """Run the `rbdyn` command on `argv` (default: this process's arguments) and return its
    exit status (`EXIT_*`); argparse exits 2 itself on a bad option."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        with warnings.catch_warnings():  # one line each, without the line that warned
            warnings.showwarning = lambda message, *_, **__: print(
                f"rbdyn {args.command}: warning: {message}", file=sys.stderr
            )
            return _dispatch(parser, args)
    except KeyboardInterrupt:
        print(f"\nrbdyn {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _dispatch(parser, args) -> int:
    if args.command == "sweep":
        for name in ("n", "chunk", "lanes", "devices", "workers"):
            v = getattr(args, name)
            if v is not None and v < 1:
                parser.error(f"--{name} must be ≥ 1")
        if args.seed < 0:
            parser.error("--seed must be ≥ 0")
        return sweep_command(args)
    if args.command == "plot":
        return plot_command(args)
    if args.command == "export":
        return export_command(args)
    if args.command == "verify":
        return verify_command(args)
    if args.command == "fit":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        return fit_command(args)
    if args.command == "scenarios":
        return scenarios_command()
    if args.command == "demo":
        if args.steps < 1:
            parser.error("--steps must be ≥ 1")
        if not 0 < args.duration < float("inf"):  # NaN too
            parser.error("--duration must be a positive number of seconds")
        return demo(args.steps, args.duration)
    return EXIT_USAGE  # unreachable: argparse rejects unknown commands
