r"""MATLAB ``.mat`` files in and out (`scipy.io.loadmat` / `scipy.io.savemat`, format 5).

`load_mat` reads a model: the variables ``E, A, B, C, D, L`` in any case (``a`` or
``A``). `save_mat` writes a plant or a design: the plant's matrices and the observer's
under the names of `fojax.GeneralizedFunctionalObserver` / `fojax.UnknownInputObserver`
(``N, J, F, H, S, G, M, P, Q, Wu, Wy`` …), plus its state-space form ``Ao, Bo, Co, Do``
with inputs ``[u; y]`` and output ``ẑ`` (MATLAB: ``ss(Ao, Bo, Co, Do)``). Files are
written atomically and never replace an existing file unless ``overwrite=True``
(`fojax._io.atomic_write`, the writer of `fojax.save_design`).
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from .._errors import InputError
from ..plant import DescriptorSystem


#: The model variables `load_mat` reads; the first three are required.
MODEL_VARIABLES = ("A", "B", "C", "E", "D", "L")
_REQUIRED = ("A", "B", "C")


def _variables(path) -> dict:
    from scipy.io import loadmat

    path = pathlib.Path(path)
    if not path.is_file():
        raise InputError(f"no .mat file at {str(path)!r}; check the path (relative paths are taken from the "
                         "current directory).")
    try:
        raw = loadmat(path)
    except Exception as err:  # scipy raises several types for a file that is not a .mat file
        raise InputError(f"{path} is not a readable MATLAB .mat file (format 4/5; v7.3 / HDF5 files need "
                         f"saving with -v7 in MATLAB): {err}") from None
    out: dict[str, tuple[str, np.ndarray]] = {}
    for k, v in raw.items():
        if k.startswith("__"):
            continue
        key = k.upper()
        if key in out:
            raise InputError(f"{path} has both {out[key][0]!r} and {k!r}; variable names are read in any case, "
                             "so keep one of them.")
        out[key] = (k, v)
    return out


def load_mat(path) -> tuple[DescriptorSystem, np.ndarray | None]:
    r"""Read a descriptor model $E\dot x = Ax + Bu$, $y = Cx + Du$ and a functional $L$
    from a MATLAB ``.mat`` file.

    **Arguments:**

    - `path`: the file; its variables ``A``, ``B``, ``C`` (required), ``E`` (default
      identity), ``D`` (default zero) and ``L`` (optional) are matched in any case.
      Other variables are ignored.

    **Returns:** ``(system, L)``: the `fojax.DescriptorSystem` and ``L`` as a float64
    array (``None`` when the file has none).

    **Raises:** `fojax.errors.InputError` naming a missing variable (and listing the ones the
    file has), a file that is not a .mat file, or two spellings of one name;
    `fojax.errors.ShapeError` / `fojax.errors.NonFiniteError` for matrices of the wrong shape or with
    non-finite entries (as `fojax.DescriptorSystem`).

    !!! example

        ```python
        sys, L = fojax.interop.load_mat("plant.mat")
        design = fojax.design_functional_observer(sys, L)
        ```
    """
    found = _variables(path)
    for name in _REQUIRED:
        if name not in found:
            have = ", ".join(sorted(v[0] for v in found.values())) or "none"
            raise InputError(f"{path} has no variable {name!r} (any case), which a model needs; it has: {have}. "
                             f"Save {', '.join(_REQUIRED)} (and optionally E, D, L) in MATLAB with "
                             "save('file.mat', 'E', 'A', 'B', 'C', 'D', 'L').")

    def get(name):
        return None if name not in found else np.atleast_2d(np.asarray(found[name][1], dtype=float))

    A = get("A")
    E = get("E") if "E" in found else np.eye(A.shape[0])
    system = DescriptorSystem(E, A, get("B"), get("C"), get("D"))
    L = get("L")
    if L is not None:
        from ..plant import check_functional

        L = np.asarray(check_functional(system, L))
    return system, L


def mat_variables(obj) -> dict[str, np.ndarray]:
    """The variables `save_mat` writes for `obj` (a plant, an observer or a design)."""
    from ..observer import AbstractObserver
    from ._state_space import state_space

    out: dict[str, np.ndarray] = {}
    if isinstance(obj, DescriptorSystem):
        for k in "EABCD":
            out[k] = np.asarray(getattr(obj, k), dtype=float)
        return out
    observer = obj if isinstance(obj, AbstractObserver) else getattr(obj, "observer", None)
    if not isinstance(observer, AbstractObserver):
        raise InputError(f"save_mat writes a fojax.DescriptorSystem, an observer or a design; got "
                         f"{type(obj).__name__}.")
    s = getattr(obj, "structure", None)
    if s is not None:
        for k in "EABCL":
            out[k] = np.asarray(getattr(s, k), dtype=float)
        B = out["B"]
        out["D"] = np.zeros((out["C"].shape[0], B.shape[-1])) if s.D is None else np.asarray(s.D, dtype=float)
    if dataclasses.is_dataclass(observer):
        for f in dataclasses.fields(observer):
            v = getattr(observer, f.name)
            if hasattr(v, "shape") and np.ndim(v) >= 1:
                out[f.name] = np.asarray(v, dtype=float)
    if observer.linear_matrices() is not None:
        out["Ao"], out["Bo"], out["Co"], out["Do"] = state_space(observer)
    return out


def save_mat(path, design_or_system, *, overwrite: bool = False) -> pathlib.Path:
    r"""Write a plant, an observer or a design to a MATLAB ``.mat`` file (format 5).

    **Arguments:**

    - `path`: the file (conventionally ``*.mat``); its directory must exist. Inside a
      results folder the path must stay inside it (`fojax.errors.UnsafePathError`).
    - `design_or_system`: a `fojax.DescriptorSystem` (``E, A, B, C, D``), an observer
      (its matrices, e.g. ``N, J, F, H, S, G, M, P, Q, Wu, Wy``, and ``Ao, Bo, Co, Do``:
      the observer as one state-space system with inputs ``[u; y]`` and output ``ẑ``)
      or a design (the observer's variables and the plant's ``E, A, B, C, D`` and ``L``).
    - `overwrite`: replace an existing file (default: `FileExistsError`).

    **Returns:** the path written. Read it back with `scipy.io.loadmat` or MATLAB's
    ``load``; `load_mat` reads the plant and ``L`` back.
    """
    from scipy.io import savemat

    from .._io import atomic_write

    variables = mat_variables(design_or_system)
    return atomic_write(path, lambda f: savemat(f, variables, format="5", oned_as="column"), overwrite=overwrite)
