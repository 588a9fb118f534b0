"""Argument types and checks shared by the example scripts: a bad option ends as an argparse
usage error (exit code 2, one line naming it) before any computation."""
from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path


def int_at_least(minimum: int):
    """An argparse type: an integer >= ``minimum``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return value
    return parse


def _number(text: str, ok, expected: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """An argparse type: a finite number."""
    return _number(text, lambda v: True, "a finite number")


def non_negative_float(text: str) -> float:
    """An argparse type: a finite number >= 0."""
    return _number(text, lambda v: v >= 0, "a finite number >= 0")


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0."""
    return _number(text, lambda v: v > 0, "a finite number > 0")


def output_folder(parser: argparse.ArgumentParser, folder: Path) -> Path:
    """``--out``, created and checked writable before any computation: a folder that cannot
    be made or written ends as a usage error."""
    if folder.exists() and not folder.is_dir():
        parser.error(f"argument --out: {str(folder)!r} is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        parser.error(f"argument --out: cannot write in the folder {str(folder)!r}: "
                     f"{error.strerror or error}")
    return folder
