"""`a3cqp` command line: train | evaluate | tune | pareto | plot | demo | bench.

Each sub-command lazily imports its module so `a3cqp --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import textwrap
import warnings

# sub-command -> "module:function" taking the remaining argv list and returning an exit code.
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("algorithms.train:main", "train an A2C adaptation policy (point mass by default)"),
    "evaluate": ("envs.evaluate_cli:main", "closed-loop evaluation against fixed-weight baselines: point mass, "
                 "or --scene peg_in_hole|polishing|guidance on the simulated Panda (Table VI)"),
    "tune": ("algorithms.tuning.ga:main", "GA over A2C hyper-parameters (paper Table V, fitness eq. 34)"),
    "pareto": ("algorithms.tuning.nsga2:main", "NSGA-II multi-objective tuning; --pick K writes a Pareto solution"),
    "plot": ("a3cqp_rl.plotting.cli:main", "policy maps (Fig. 5), loss curves (Fig. 4), Panda episodes (Fig. 7/8), "
             "GA and Pareto runs"),
    "demo": ("a3cqp_rl.demo:main", "demos, e.g. `a3cqp demo controller` (Panda QP controller in MuJoCo)"),
    "bench": ("a3cqp_rl.bench_cli:main", "benchmarks against peers measured in the same run "
              "(`a3cqp bench --help` lists them)"),
}


def help_summary(doc: str | None) -> str:
    """A module docstring's first paragraph on one line: the `--help` description (argparse rewraps it)."""
    head = (doc or "").strip().split("\n\n", 1)[0]
    return " ".join(line.strip() for line in head.splitlines())


def seed_arg(text: str) -> int:
    """One `--seed`: an integer in [0, 2**63 - 1] (what torch's generators and NumPy's seed sequences take)."""
    from a3cqp_rl.config import MAX_SEED

    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid seed {text!r}: expected an integer") from None
    if not 0 <= seed <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"seed {seed} is outside [0, 2**63 - 1]")
    return seed


DEBUG_ENV = "A3CQP_DEBUG"
"""Set to 1 (`A3CQP_DEBUG=1 a3cqp ...`), the commands raise their errors with the traceback instead of one line."""


def error_exit(exc: BaseException, text: str | None = None) -> int:
    """A command's error as `error: TEXT` (default: the exception's) on stderr and exit code 2, or the traceback
    where A3CQP_DEBUG is set (not "" or "0")."""
    if os.environ.get(DEBUG_ENV, "") not in ("", "0"):
        raise exc
    print(f"error: {exc if text is None else text}", file=sys.stderr)
    return 2


def positive_int(text: str) -> int:
    """A count option (`--workers`, `--generations`, ...): an integer >= 1, refused before any work starts."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid count {text!r}: expected an integer >= 1") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def add_set_option(parser: argparse.ArgumentParser, example: str, kept: str) -> None:
    """The commands' `--set KEY=VALUE` (repeatable, into `args.overrides` for `config.parse_overrides`); `example`
    a KEY=VALUE of the command's own config, `kept` where the result is recorded."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help=f"override one config value over --config, e.g. --set {example} (VALUE read as YAML; "
                             f"repeatable; {kept})")


class ClosedPipeGuard:
    """Standard output that, once its reader has gone (`a3cqp train ... | head -1`), sends the rest to /dev/null: the
    command still finishes its work and its files, without a 'Broken pipe' error or exit code."""

    def __init__(self, stream) -> None:  # noqa: ANN001
        self._stream = stream

    def write(self, text: str) -> int:
        """Write `text`; after the reader has gone, drop it."""
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._to_devnull()
            return len(text)

    def flush(self) -> None:
        """Flush; after the reader has gone, into /dev/null."""
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._to_devnull()

    def _to_devnull(self) -> None:
        # the descriptor itself, so that the interpreter's own flush at exit finds nothing to complain about
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, self._stream.fileno())
        os.close(null)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self._stream, name)


def _one_line_warning(message, category, filename, lineno, line=None) -> str:  # noqa: ANN001
    """A command's warnings as one plain line; the source line and file path are for library users."""
    return f"warning: {message}\n"


def main(argv: list[str] | None = None) -> int:
    """Dispatch `a3cqp <command> ...` to the command's module; returns the process exit code."""
    if argv is None and not isinstance(sys.stdout, ClosedPipeGuard):  # the console command (tests pass argv)
        sys.stdout = ClosedPipeGuard(sys.stdout)
        warnings.formatwarning = _one_line_warning
    argv = list(sys.argv[1:] if argv is None else argv)
    width = max(map(len, COMMANDS))
    parser = argparse.ArgumentParser(
        prog="a3cqp", description=help_summary(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="commands:\n" + "\n".join(textwrap.fill(v[1], 100, initial_indent=f"  {k:<{width}}  ",
                                                       subsequent_indent=" " * (width + 4)) for k, v in COMMANDS.items())
        + "\n\n`a3cqp COMMAND --help` lists a command's options.")
    parser.add_argument("command", choices=sorted(COMMANDS), help="one of the commands below")
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0 if argv else 2
    args = parser.parse_args(argv[:1])
    module_name, func_name = COMMANDS[args.command][0].split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    return int(func(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
