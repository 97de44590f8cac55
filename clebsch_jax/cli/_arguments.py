"""The command line's parsing: the program's name, its parser whose errors are one line, the
types of the arguments with their limits (each rejects a bad value with one line naming what was
expected), the `--no-cache` flag and the help text's paragraphs."""

from __future__ import annotations

import argparse
import math
import textwrap

import clebsch_jax as cj

PROG = "clebsch-jax"

MAX_STEPS = 1_000_000
"""Largest accepted `--steps` (keeps the stored diagnostics within a few hundred MB)."""

MAX_BATCH = 10_000
"""Largest accepted `--batch` of `run` (for larger sweeps use `clebsch_jax.sweep`)."""

ORDERS = tuple(sorted({c.order for c in cj.COMPOSITIONS.values()} | {2}))
"""`--order` values without `--scheme gauss`: 2 and the orders of the compositions
(`integrate(..., order=)`)."""

GAUSS_ORDERS = cj.GAUSS_ORDERS
"""`--order` values with `--scheme gauss`."""

SCHEMES = cj.SCHEMES + ("gauss",)
"""`--scheme` values (`integrate(..., scheme=)`)."""

LONG_RUN = 100_000
"""Runs of at least this many member-steps show a progress bar even when stderr is not a terminal."""


class Parser(argparse.ArgumentParser):
    """An `ArgumentParser` whose errors are one line on stderr (exit code 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _whole_number(text: str, low: int, high: float, not_a_number: str, out_of_range: str) -> int:
    """`text` as an int in [low, high]; the messages are formatted with `text` and `value`."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(not_a_number.format(text=text)) from None
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(out_of_range.format(text=text, value=value))
    return value


def parse_steps(text: str) -> int:
    return _whole_number(
        text,
        1,
        MAX_STEPS,
        "expected a whole number of steps, got {text!r}",
        f"expected 1 to {MAX_STEPS:,} steps, got {{value}}",
    )


def parse_dt(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive finite time step, got {text}")
    return value


def parse_order(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = None
    if value not in ORDERS + GAUSS_ORDERS:
        raise argparse.ArgumentTypeError(
            f"expected one of {', '.join(map(str, ORDERS))} (with --scheme gauss "
            f"an even order up to {GAUSS_ORDERS[-1]}), got {text!r}"
        )
    return value


def parse_batch(text: str) -> int:
    return _whole_number(
        text,
        1,
        MAX_BATCH,
        "expected a whole number of members, got {text!r}",
        f"expected 1 to {MAX_BATCH:,} members, got {{value}} (for larger batches use clebsch_jax.sweep)",
    )


def parse_seed(text: str) -> int:
    message = "expected a whole number >= 0, got {text!r}"
    return _whole_number(text, 0, math.inf, message, message)


def parse_chunk(text: str) -> int:
    message = "expected a whole number of steps >= 1, got {text!r}"
    return _whole_number(text, 1, MAX_STEPS, message, message)


def scene_names() -> list:
    from ._scenes import SCENES

    return list(SCENES)


def parse_scene(text: str) -> str:
    name = text.strip().lower().replace("_", "-")
    names = scene_names()
    if name not in names:
        raise argparse.ArgumentTypeError(f"unknown scene {text!r}; known scenes: {', '.join(names)}")
    return name


def paragraphs(*texts: str) -> str:
    """Help text: each paragraph wrapped to 79 columns, except those with line breaks (lists)."""
    return "\n\n".join(t if "\n" in t else textwrap.fill(t, 79) for t in texts)


def add_cache_flag(p) -> None:
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="do not keep compiled programs on disk (by default they are kept in "
        "$CLEBSCH_JAX_CACHE_DIR or ~/.cache/clebsch-jax/xla, so a second run "
        "skips most of the compilation; CLEBSCH_JAX_NO_CACHE=1 does the same)",
    )
