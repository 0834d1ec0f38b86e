"""Argument types and the parser of the ``pmsm-agent`` command line: every bad value is one line
on stderr naming the flag and exit status 2 (CONTRACT section 2)."""

from __future__ import annotations

import argparse
import math
import sys


class UsageError(SystemExit):
    """A usage error: its one line is on stderr already; ``message`` for the JSON error object."""

    def __init__(self, message: str):
        super().__init__(2)
        self.message = message


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (``prog: error: ...``) and exit 2."""

    def error(self, message: str):
        text = f"{message} (see --help)"
        sys.stderr.write(f"{self.prog}: error: {text}\n")
        raise UsageError(text)


def number(lo: float | None = None, hi: float | None = None, *, low_open: bool = False, integer: bool = False,
           unit: str = ""):
    """A finite number within [lo, hi] (``low_open``: lo excluded), an int with ``integer``."""
    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if integer else 'a number'}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not finite")
        if lo is not None and (value < lo or (low_open and value == lo)) or hi is not None and value > hi:
            lo_s = "" if lo is None else f"{'>' if low_open else '>='} {lo:g}"
            hi_s = "" if hi is None else f"<= {hi:g}"
            raise argparse.ArgumentTypeError(f"{text} is outside {' and '.join(x for x in (lo_s, hi_s) if x)}"
                                             f"{' ' + unit if unit else ''}")
        return value
    parse.__name__ = "integer" if integer else "number"
    return parse


def fraction(text: str) -> float:
    """A confidence or probability in (0, 1); a percentage is named as such."""
    value = number()(text)
    if not 0.0 < value < 1.0:
        hint = f" (a fraction: {value / 100:g} for {value:g} %)" if 1.0 < value < 100.0 else ""
        raise argparse.ArgumentTypeError(f"{text} is not within (0, 1){hint}")
    return value


def quiet_broken_pipe() -> int:
    """stdout's reader went away (``| head``): stop quietly, as command-line tools do."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except OSError:
        pass
    return 0
