"""What the ``fojax`` commands share: progress messages, config lookup, the command's
machine-readable result (``--json``), and the optional figures."""

from __future__ import annotations

import pathlib
import sys
import time


class _Progress:
    """Step messages with elapsed times (nothing when quiet)."""

    def __init__(self, quiet: bool):
        self.quiet = quiet

    def say(self, *args):
        if not self.quiet:
            print(*args, flush=True)

    def step(self, message: str):
        progress = self

        class _Step:
            def __enter__(self):
                self.t0 = time.perf_counter()
                progress.say(f"{message} ...")
                return self

            def __exit__(self, *exc):
                if exc[0] is None:
                    progress.say(f"  done in {time.perf_counter() - self.t0:.1f} s")
                return False

        return _Step()


def resolve_config(path: str) -> str:
    """A config path, or the shipped example of that name (``fojax check example_3_3_7``)."""
    from ..config import example_names, example_path

    p = pathlib.Path(path)
    if not p.exists() and p.suffix in ("", ".toml") and p.parent == pathlib.Path(".") and (
        p.stem in example_names()
    ):
        return str(example_path(p.stem))
    return path


def _load(path):
    from ..config import load_config

    return load_config(path)


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split("\n")[0].split())


def _region_words(spec) -> str:
    if spec.kind == "finite-time":
        return " and ".join(r.describe() for r in spec.regions)
    return spec.region.describe()


def _default_region(dt=None):
    """The region of a file without ``[[observer]]``: the disk (-2, 1), or for a discrete-time
    model (``dt`` set) the z-plane disk (0, 0.5), as for an ``[[observer]]`` without ``region``."""
    from ..design import DiscreteDisk, Disk

    return Disk(-2.0, 1.0) if dt is None else DiscreteDisk(0.0, 0.5)



def figures_available(out: _Progress) -> bool:
    """Whether the figures can be drawn (Matplotlib, the ``plot`` extra); if not, the
    command says once on stderr that it writes none and how to get them."""
    from ..results._plots import matplotlib_available, PLOT_EXTRA

    if matplotlib_available():
        return True
    print(f"fojax: no figures are written: {PLOT_EXTRA}", file=sys.stderr, flush=True)
    return False


class _Unavailable(Exception):
    """A command that is not available in this installation (exit code 3)."""
