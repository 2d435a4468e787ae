"""Argument checks shared by every stage, and the error type that marks bad input.

``InputError`` is what a caller did wrong (a bad argument, file or option): the command line turns it into exit
code 2 with its message. It subclasses ``ValueError``, so ``except ValueError`` keeps catching it. Anything else
that escapes is a bug of ours, reported as such.
"""
from __future__ import annotations

import math
import sys

import numpy as np

__all__ = ["InputError", "integer", "number", "finite_arg", "say"]


class InputError(ValueError):
    """Bad input from the caller: the message says what is wrong and how to fix it."""


def integer(name: str, value, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as a Python int, refusing bools, floats and out-of-range values with an InputError."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if minimum is not None and v < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise InputError(f"{name} must be <= {maximum}, got {v}")
    return v


def number(name: str, value, minimum: float | None = None, maximum: float | None = None,
           above: float | None = None) -> float:
    """``value`` as a finite Python float (bools refused); ``above`` is an exclusive lower bound."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {v}")
    if minimum is not None and v < minimum:
        raise InputError(f"{name} must be >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise InputError(f"{name} must be <= {maximum}, got {v}")
    if above is not None and v <= above:
        raise InputError(f"{name} must be > {above}, got {v}")
    return v


def finite_arg(flag: str = "the option"):
    """An argparse type: a finite number (nan and inf refused, naming ``flag``)."""
    import argparse

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
        return value

    convert.__name__ = f"finite number for {flag}"
    return convert


def say(on: bool, msg: str, stream=None) -> None:
    """One status line (stderr unless ``stream``), when ``on``: the library's one channel besides progress bars."""
    if on:
        print(msg, file=stream or sys.stderr, flush=True)
