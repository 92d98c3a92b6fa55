r"""TOML model and study files: format, validation and the objects they describe.

A config file describes one descriptor model, the observers to design for it and
(optionally) a Monte Carlo study and a tuning run. Matrices are nested lists of
numbers (rows). The full reference with examples is ``docs/config.md``; the thesis
examples ship as ``fojax/examples/*.toml`` (see `example_path`). Layout::

    name = "example_4_1_3"               # optional: a short name for result folders
    description = "..."                  # optional

    [model]                              # required
    E = [[1, 0], [0, 0]]                 # (n, n)            required
    A = [[-1, 1], [1, -2]]               # (n, n); (k, n, n) for a T-S model   required
    B = [[1], [0]]                       # (n, m); (k, n, m) allowed for T-S   required
    C = [[1, 0]]                         # (p, n)            required
    L = [[0, 1]]                         # (q, n) functional z = L x           required
    D = [[0]]                            # optional (p, m) feedthrough: y = C x + D u (LTI models)
    mat = "plant.mat"                    # optional: E, A, B, C, D, L (any case) from a MATLAB file
                                         # (path relative to this file; fojax.interop.load_mat);
                                         # without E in the file E = I; a matrix may not be given
                                         # both inline and in the file
    feedback = [[...]]                   # optional (m, n) K: the plant is (E, A + B K, B, C + D K, D)
    x0 = [1, 0]                          # optional initial state (n,)

    [faults]                             # optional: E x' = A x + B u + Fa f, y = C x + Fs f
    Fa = [[...]]                         # (n, nf)   at least one of Fa, Fs
    Fs = [[...]]                         # (p, nf)
    ramp = false                         # Remark 9: ramp faults (f'' = 0)
    estimate_faults = true               # design for [L 0; 0 I] (estimate z and f)
    # a T-S model's faults act on the simulated plant only: its observers estimate z = L x
    # (no fault-augmented T-S design), so it needs estimate_faults = false (and no ramp)

    [uncertainty]                        # optional: A + sum_j delta_j(t) dA_j
    dA = [[[...]]]                       # list of (n, n) directions (or one matrix)
    profile = { kind = "uniform", bound = 0.3 }
        # kind = "constant" (value = [..]), "uniform" (bound: delta_j ~ U[-bound, bound]
        # per sample), or "sine" (amplitude, omega [, phase])

    [takagi_sugeno]                      # optional: [model] A (and B) hold one matrix per rule
    premise = "sinc"                     # rho = sin(y_i)/y_i ("sinc") or rho = y_i ("output")
    index = 1                            # output index i (0-based)
    lower = -0.217                       # rho range [lower, upper] of the sector membership
    upper = 1.0
    plant = "robot_arm"                  # optional: the nonlinear model `fojax study` simulates
                                         # (the rules are checked to be its sector form)
    # a T-S model's [uncertainty] is `parameters = { k = 0.2, ... }` (relative spreads of
    # that nonlinear plant's physical parameters), not dA/profile

    [initial_state]                      # optional, T-S models: x0 + U(-spread, spread)
    spread = [0.05, 0, 0.1, 0, 0]        # (n,) or one number

    [[observer]]                         # zero or more (default: one generalized observer)
    name = "FGDO"                        # optional
    kind = "generalized"                 # "generalized", "PI", "proportional", or (LTI, no
                                         # [faults]) "unknown-input" / "finite-time":
    D = [[...]]                          # unknown-input: (n, l) directions, E x' = ... + D d
    delay = 0.5                          # finite-time: h; and two separated disks
    regions = [{ center = -5.0, radius = 0.5 }, { center = -2.0, radius = 0.5 }]
    method = "auto"                      # finite-time: "auto", "lmi" or "place";
                                         # generalized / PI / proportional (LTI models): "lmi"
                                         # (default: the region LMI), "riccati" (a Riccati +
                                         # Stein route, no SDP, for one disk, half-plane or
                                         # sector; generalized and proportional; large models)
                                         # or "auto" (Riccati where it applies, else LMI)
    region = { disk = { center = -2.0, radius = 1.0 }, decay = 0.5, damping = 0.7 }
        # any non-empty subset; several parts are intersected. Default: disk(-2, 1).
    q0 = 2                               # optional observer order, or
    R = [[...]]                          # optional (q0, n) (of the designed, augmented system)
    q1 = 2                               # optional size of v
    objective = "hinf"                   # optional: "region" (default), "hinf" (minimise a
                                         # certified L2-gain bound from w, nu to zhat - z) or
                                         # "h2" (a certified H2-norm bound; no feedthrough) or
                                         # "centre" (eigenvalues as far inside a disk as the LMI allows)
    Bw = [[...]]                         # "hinf"/"h2": (n, mw) disturbance E x' = ... + Bw w
    Dv = [[...]]                         # "hinf"/"h2": (p, mv) noise y = C x + Dv nu
    balance = true                       # optional, generalized/PI/proportional/unknown-input on LTI
                                         # models: design unit-free (the design routine's balance;
                                         # default: its default)

    [study]                              # optional Monte Carlo settings
    samples = 64
    horizon = 10.0
    dt = 0.01
    seed = 0

    [tuning]                             # optional gradient tuning settings
    steps = 100
    learning_rate = 0.01
    loss = "ise"                         # training loss: "ise" (mean of the integral of e^2;
                                         # default) or "iae" (of |e|)
    robustness = { h2 = 0.1 }            # optional: H2Term / HinfTerm weights ("h2", "hinf") for
                                         # objective = "hinf"/"h2" observers (their channels)

Every problem raises `fojax.errors.ConfigError` naming the file, the key (dotted path, e.g.
``observer[1].region.disk.radius``) and what was expected.
"""

from __future__ import annotations

import difflib
import pathlib
import tomllib

from .._errors import ConfigError
from ._parse import parse_config
from ._spec import Config


def load_config(path) -> Config:
    """Read and validate a TOML model/study file.

    **Arguments:**

    - `path`: the ``.toml`` file (format: module docstring and ``docs/config.md``).

    **Returns:** a `Config`.

    **Raises:** `fojax.errors.ConfigError` naming the file, the key and what was expected
    (missing file, TOML syntax, unknown or missing keys, non-numeric entries, wrong
    shapes, inconsistent dimensions, bad region parameters).
    """
    path = pathlib.Path(path)
    file = str(path)
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(file, "(file)", "does not exist; pass the path of a .toml config file.") from None
    except OSError as e:
        raise ConfigError(file, "(file)", f"cannot be read: {e.strerror}.") from None
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(file, "(file)", "is not UTF-8 text; a TOML file is expected.") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(file, "(syntax)", f"is not valid TOML: {e}.") from None
    return parse_config(data, file)


def example_names() -> list[str]:
    """Names of the example configs shipped in ``fojax/examples`` (without ``.toml``)."""
    import importlib.resources

    root = importlib.resources.files("fojax").joinpath("examples")
    return sorted(p.name[: -len(".toml")] for p in root.iterdir() if p.name.endswith(".toml"))


def example_path(name: str) -> pathlib.Path:
    """Path of a shipped example config, e.g. ``example_path("example_3_3_7")``."""
    import importlib.resources

    names = example_names()
    if name.endswith(".toml"):
        name = name[:-5]
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        raise ConfigError(None, "example", f"no example named {name!r}.{hint} Available: {', '.join(names)}.")
    return pathlib.Path(str(importlib.resources.files("fojax").joinpath("examples", f"{name}.toml")))
