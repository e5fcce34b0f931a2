"""What every ``dualphys`` sub-command shares: the positive-integer argument type and the one-line failure
(``dualphys <command>: <message>`` on stderr, exit 1). The pipeline's commands (pipeline/cli.py) and the client's
(service/client/commands.py) both use them."""

from __future__ import annotations

import argparse
import sys


def positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def fail(command: str, message: str) -> int:
    print(f"dualphys {command}: {message}", file=sys.stderr)
    return 1
