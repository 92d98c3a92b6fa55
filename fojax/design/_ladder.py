"""The one fallback ladder of fojax's host designs.

A design route that can fail for numerical reasons (an LMI solver stopping at
``optimal_inaccurate``, a certificate that does not verify) tries a fixed sequence of
*rungs* — better-conditioned formulations, other objectives, other solvers, other
methods — and returns the first that succeeds, with the refusals of the rungs before it.
Every rung's result is verified by its caller in float64 whatever rung produced it, so the
ladder never decides *what* is accepted, only what is tried.

Users: the functional-observer LMI (`solve_with_fallbacks`: min-gain, then feasibility,
per solver), the unknown-input LMI (preconditioned with ``X' ⪯ 1e2 I``, ``1e4 I``, then
plain) and the state feedback of `fojax.control` (method × certificate penalty). The
per-solver retry with looser settings inside `fojax.design._lmi.solve` is a retry of one
solver call, not a rung: it stays there.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any


def climb(rungs: Iterable[tuple[Any, Callable[[], Any]]], *, refusals: tuple = (Exception,),
          give_up: Callable[[Any, BaseException], bool] | None = None) -> tuple[Any, Any, list]:
    """Run the rungs in order; return ``(label, result, refused)`` of the first that
    returns, where ``refused`` lists ``(label, error)`` of those before it.

    **Arguments:**

    - `rungs`: ``(label, thunk)`` pairs; a thunk raises one of `refusals` when its rung fails.
    - `refusals`: the exception types that mean "try the next rung" (others propagate).
    - `give_up`: ``give_up(label, error)`` → skip the remaining rungs whose label shares the
      failed one's first element (e.g. a larger penalty does not make an infeasible LMI
      feasible).

    **Raises:** `Refused` (with ``.refused``) when every rung failed; the caller turns it
    into its own typed error.
    """
    refused: list = []
    skip: set = set()
    for label, thunk in rungs:
        group = label[0] if isinstance(label, tuple) else None
        if group is not None and group in skip:
            continue
        try:
            return label, thunk(), refused
        except refusals as err:
            refused.append((label, err))
            if give_up is not None and group is not None and give_up(label, err):
                skip.add(group)
    raise Refused(refused)


class Refused(Exception):
    """Every rung of a ladder failed; ``refused`` lists ``(label, error)`` in order."""

    def __init__(self, refused: list):
        super().__init__("; ".join(f"{label}: {err}" for label, err in refused))
        self.refused = refused
