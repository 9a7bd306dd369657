"""Command-line value types shared by the subcommands: a wrong value is argparse's clear
"argument --x: …" message and exit 2, never a traceback or a hang."""

from __future__ import annotations

import argparse
import math

from abh3_supervisor.config.endpoint import Endpoint, parse_endpoint


def positive(text: str) -> float:
    """A number above 0 (``inf`` allowed: "no end")."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError("must be more than 0")
    return value


def finite_positive(text: str) -> float:
    """A number above 0 that a timer can wait for."""
    value = positive(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError("must be a finite number")
    return value


def count(text: str) -> int:
    """0 or more."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError("must be 0 or more")
    return value


def endpoint(text: str) -> Endpoint:
    """[HOST:]PORT, where a server of ours listens (127.0.0.1 unless a host is given)."""
    try:
        return parse_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
