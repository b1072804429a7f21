"""Dispatcher: ``python -m sync4d.evaluate <name> [options]`` runs ``sync4d.evaluate.<name>.main(options)``."""

from __future__ import annotations

import importlib
import logging
import sys

from sync4d.errors import Sync4DError
from sync4d_tools.evaluate import commands


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    names = commands()
    if not args or args[0] in ("-h", "--help"):
        print(f"usage: python -m sync4d.evaluate <command> [options]\ncommands: {', '.join(names)}")
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in names:
        print(f"unknown evaluation command '{name}'; available: {', '.join(names)}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    module = importlib.import_module(f"sync4d_tools.evaluate.{name}")
    try:
        module.main(rest)
    except Sync4DError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
