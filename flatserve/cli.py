"""The ``flatserve`` command line (console script ``flatserve``).

Subcommands register themselves in :data:`COMMANDS`: a name mapped to a pair
``(add_arguments(parser), run(args) -> int)``.  To add one, define the two
functions and add an entry (``serve`` and ``lightfield`` are added by their
owners).

Example
-------
$ flatserve experiment --trials 1000 --seed 0
"""
from __future__ import annotations

import argparse
import sys
from typing import Callable


# ---- experiment ----
def _case(text: str) -> tuple[int, int]:
    try:
        d, k = (int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected D,K (e.g. 5,1), got {text!r}") from None
    return d, k


def _experiment_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trials", type=int, default=1000, help="trials per (d, k) (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random generator (default 0)")
    p.add_argument("--cases", type=_case, nargs="+", metavar="D,K", default=None,
                   help="the (d, k) cases, e.g. --cases 5,1 6,2 (default the paper's seven: "
                        "2,1 3,1 3,2 4,1 4,2 5,2 6,3)")


def _experiment_run(args: argparse.Namespace) -> int:
    from .errors import InvalidInputError
    from .experiment import CASES, EXPERIMENT_TOL, format_table, run_all

    if args.trials < 1:
        print("flatserve experiment: --trials must be >= 1", file=sys.stderr)
        return 2
    try:
        rows = run_all(args.trials, args.seed, cases=args.cases or CASES)
    except (InvalidInputError, ValueError) as exc:
        print(f"flatserve experiment: {exc}", file=sys.stderr)
        return 2
    print("Paper Sec. 4.3: recover random convex coefficients of a basis of flats")
    print(format_table(rows))
    print(f"(failure: a coefficient off by more than {EXPERIMENT_TOL:g} or a failed round trip; "
          "redrawn: trials whose basis was degenerate, drawn again)")
    return 1 if any(r.failures for r in rows) else 0
# ---- /experiment ----


# ---- lightfield ----
def _lightfield_args(p: argparse.ArgumentParser) -> None:
    from .lightfield.cli import add_arguments

    add_arguments(p)


def _lightfield_run(args: argparse.Namespace) -> int:
    from .lightfield.cli import run

    return run(args)
# ---- /lightfield ----


# ---- serve ----
def _serve_args(p: argparse.ArgumentParser) -> None:
    try:
        from .service.server import add_arguments
    except ImportError as exc:  # the service's dependencies are an extra
        p.set_defaults(_missing=f"flatserve serve needs the service extra: pip install "
                                f"'flatserve[service]' ({exc})")
        return

    add_arguments(p)


def _serve_run(args: argparse.Namespace) -> int:
    if getattr(args, "_missing", None):
        print(args._missing, file=sys.stderr)
        return 2
    from .service.server import serve, settings_from_args

    serve(settings_from_args(args))
    return 0
# ---- /serve ----


#: name -> (help, add_arguments, run)
COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None],
                          Callable[[argparse.Namespace], int]]] = {
    "experiment": ("reproduce the paper's Sec. 4.3 experiment", _experiment_args, _experiment_run),
    "lightfield": ("light fields: the paper's Fig. 11 (bunny), a 360-degree light field, and real captures imported into a service", _lightfield_args, _lightfield_run),
    "serve": ("run the HTTP service (options also from FLATSERVE_* variables)", _serve_args, _serve_run),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="flatserve", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (help_, add_args, _) in COMMANDS.items():
        add_args(sub.add_parser(name, help=help_, description=help_))
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``flatserve`` console script."""
    args = build_parser().parse_args(argv)
    return COMMANDS[args.command][2](args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
