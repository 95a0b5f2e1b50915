"""Progress of a long step (a simulation's loads, a timeline's knots): log records that a command
shows as one updating line on a terminal and leaves out elsewhere (logs, CI, pipes).

The core never prints: it logs ``what: i/n`` at INFO with ``extra={"progress": (i, n)}`` at most once
per :data:`EVERY_S` and at the last item (:func:`steps`); a ``cstomo`` command's log handler
(:func:`cstomo_sensor.tools.common.setup_logging`) draws them.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")

#: Seconds between two progress records of one step.
EVERY_S = 1.0


def steps(items: Iterable[T], log: logging.Logger, what: str, total: int | None = None) -> Iterator[T]:
    """The items of ``items``, with a progress record ``what: 0/n`` before the first, and ``what: i/n
    (s elapsed)`` after item i when :data:`EVERY_S` s have passed since the last one, and after the last."""
    n = total if total is not None else len(items)  # type: ignore[arg-type]
    t0 = last = time.monotonic()
    if n:  # said at once: the first item may be the long one
        log.info("%s: 0/%d", what, n, extra={"progress": (0, n)})
    for i, item in enumerate(items, 1):
        yield item
        now = time.monotonic()
        if now - last >= EVERY_S or i == n:
            last = now
            log.info("%s: %d/%d (%.0f s)", what, i, n, now - t0, extra={"progress": (i, n)})
