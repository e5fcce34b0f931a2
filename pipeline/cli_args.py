"""Argument types the ``dualphys`` sub-commands share: the pipeline's (cli/main.py) and the client's
(service/client/cli.py). The two command modules do not import each other."""

from __future__ import annotations

import argparse


def positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v

