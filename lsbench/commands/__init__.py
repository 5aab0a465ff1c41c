"""One module per `lsbench` subcommand (asv's commands/): each has NAME, HELP,
setup_arguments(subparsers) and run(args) -> exit code. Imported explicitly: a broken module
fails `lsbench` loudly instead of losing its command."""
from __future__ import annotations

from lsbench.commands import (compare, compare_commits, fit, gate, history, report, run, runs, speedtest,
                              stability, trace)

COMMANDS = (run, gate, trace, report, runs, compare, compare_commits, history, stability, speedtest, fit)
