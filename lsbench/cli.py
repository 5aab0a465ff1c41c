"""`lsbench` command line: one subcommand per module of lsbench/commands/."""
from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    from lsbench.commands import COMMANDS
    from lsbench.commands.common import Parser  # one-line errors, exit 2

    p = Parser(prog="lsbench", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.setup_arguments(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    from lsbench.commands.common import UsageError
    from lsbench.inputs.rays import RayError
    from lsbench.inputs.scenario import ScenarioError
    from lsbench.inputs.scene import SceneError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (SceneError, RayError, ScenarioError, UsageError) as exc:
        print(f"lsbench: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # runner.Interrupted says where the records are
        print(f"lsbench: interrupted; {exc or 'finished cases are kept in results.jsonl'}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
