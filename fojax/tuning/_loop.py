"""The optimizer loop of `fojax.tuning.tune`.

One place for what every tuning run does around its jitted step: the host check of
each candidate (a rejected iterate never replaces the parameters), the per-step
history, held-out evaluation every `eval_every` steps, the user callback, the progress
bar, and checkpoints (``path.npz`` + ``path.json``, each written atomically, both
holding the step) with resume.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from .._errors import InputError
from .._io import atomic_write
from ..studies import broadcast_bytes, spans_processes, writes_files


def check_extra_loss(extra_loss, observer, design_params) -> None:
    """Evaluate a user's ``extra_loss(observer, design_params)`` once on the starting
    iterate (host) and refuse anything but a callable returning a finite real scalar."""
    if not callable(extra_loss):
        raise InputError(f"extra_loss must be a function (observer, design_params) -> scalar; got "
                         f"{type(extra_loss).__name__}.")
    value = jnp.asarray(extra_loss(observer, design_params))
    if value.shape != () or not jnp.issubdtype(value.dtype, jnp.floating):
        raise InputError(f"extra_loss must return a real scalar; at the starting design it returned shape "
                         f"{value.shape}, dtype {value.dtype}. Reduce it (e.g. jnp.sum) to one number.")
    if not bool(jnp.isfinite(value)):
        raise InputError(f"extra_loss is {float(value)} at the starting design; it must be finite there.")


#: a tangential candidate must keep at least this fraction of the update's norm
TANGENTIAL_MIN = 1e-6


def backtracked_update(params, updates, margin_fn, min_margin, n_back, margin_grad):
    r"""The optimizer update, halved until the candidate is valid (host).

    The candidates ``params + 0.5**k · updates``, ``k = 0..n_back``, are evaluated in turn by
    `margin_fn` (``params ↦ float``, a compiled program) and the first with
    ``margin_fn(candidate) > min_margin`` (and finite) is taken. When none is valid the same
    halvings of the *tangential* update are tried: the update without its component along
    $-\nabla$ margin, $u_t = u - \min(0, \langle u, g\rangle)\,g/\|g\|^2$ with $g$ =
    ``margin_grad(params)`` (it slides along the region's boundary instead of into it; only
    when $\|u_t\| > 10^{-6}\|u\|$, `TANGENTIAL_MIN`). When none of those is valid either the
    parameters stay (scale 0).

    *Why the tangential candidates:* at an iterate on the boundary (margin just
    above `min_margin`) whose optimizer update points outside, every halving of it is outside
    too, so without them the step is rejected, the next update points the same way, and the
    run stops moving: on the LC filter of ``benchmarks/tuning_circuit.py`` with ``barrier=0``,
    79 of 100 steps were rejected and the training loss stayed at 0.5313 from step 20 on.

    *Why on the host:* inside the jitted step (all ``n_back + 1`` candidates' margins at
    once, the tangential branch under `jax.lax.cond`) the candidates, the margin's gradient
    and the second set of candidates would make that program larger and its compilation
    longer, for a rule that usually takes the first candidate. Evaluated in turn, the first admissible candidate is the same one, and its
    margin is the one `host_check` needs anyway; `margin_grad` is called (and compiled) only
    when no halving is admissible. The candidates are the same floating-point numbers as
    before (``0.5**k`` is a power of two).

    **Returns:** ``(new_params, margin, accepted, backtracks)``: the margin of the taken
    candidate (of the full step when none was valid) and the number of halvings (counted on
    from ``n_back + 1`` for a tangential candidate).
    """
    scales = [0.5**k for k in range(n_back + 1)]

    def at(upd, sc):
        return jax.tree.map(lambda p, u: p + sc * u, params, upd)

    def first_admissible(upd):
        """``(k, candidate, margin)`` of the first admissible halving of `upd`, or ``(None,
        None, margin of the full step)``."""
        m_full = None
        for k, sc in enumerate(scales):
            cand = at(upd, sc)
            m = float(margin_fn(cand))
            m_full = m if k == 0 else m_full
            if np.isfinite(m) and m > min_margin:
                return k, cand, m
        return None, None, m_full

    k, cand, m = first_admissible(updates)
    if k is not None:
        return cand, m, True, k
    m_full = m

    def leaves_dot(x, y):
        return float(sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(x), jax.tree.leaves(y))))

    g = margin_grad(params)
    gu, gg = leaves_dot(g, updates), leaves_dot(g, g)
    if not (np.isfinite(gu) and np.isfinite(gg) and gg > 0 and gu < 0):
        return params, m_full, False, 0
    coef = gu / gg
    tangential = jax.tree.map(lambda u, gi: u - coef * gi, updates, g)
    # an update (almost) straight outward stays rejected
    if not leaves_dot(tangential, tangential) > TANGENTIAL_MIN**2 * leaves_dot(updates, updates):
        return params, m_full, False, 0
    k, cand, m = first_admissible(tangential)
    if k is None:
        return params, m_full, False, 0
    return cand, m, True, n_back + 1 + k


HISTORY_KEYS = ("step", "train_loss", "heldout_loss", "margin", "accepted", "backtracks", "max_real_eig")


def save_checkpoint(path, params, opt_state, step, key, history):
    leaves = jax.tree.leaves((params, opt_state))
    arrays = {f"leaf{i}": np.asarray(x) for i, x in enumerate(leaves)}
    arrays["key"] = np.asarray(key)
    arrays["step"] = np.asarray(int(step))
    atomic_write(path + ".npz", lambda f: np.savez(f, **arrays), overwrite=True)
    meta = {"step": int(step), "history": history}
    atomic_write(path + ".json", lambda f: f.write(json.dumps(meta).encode()), overwrite=True)


def read_checkpoint(path) -> bytes | None:
    """The bytes of the checkpoint pair at `path` (``path.json`` then ``path.npz``, framed
    by the JSON's length), or None when there is none."""
    import os

    if not os.path.exists(path + ".json"):
        return None
    with open(path + ".json", "rb") as f:
        meta = f.read()
    with open(path + ".npz", "rb") as f:
        arrays = f.read()
    return len(meta).to_bytes(8, "little") + meta + arrays


def load_checkpoint(path, params, opt_state, data: bytes | None = None):
    """The state saved at `path` (or in `data`, the bytes of `read_checkpoint`)."""
    import io

    data = read_checkpoint(path) if data is None else data
    n = int.from_bytes(data[:8], "little")
    meta = json.loads(data[8 : 8 + n].decode())
    like = jax.tree.leaves((params, opt_state))
    with np.load(io.BytesIO(data[8 + n :])) as npz:
        saved = sorted((k for k in npz.files if k.startswith("leaf")), key=lambda k: int(k[4:]))
        leaves = [np.asarray(npz[k]) for k in saved]
        key = jnp.asarray(npz["key"])
        npz_step = int(npz["step"]) if "step" in npz else meta["step"]
    want = [(tuple(np.shape(x)), np.dtype(getattr(x, "dtype", type(x)))) for x in like]
    got = [(x.shape, x.dtype) for x in leaves]
    if got != want:
        raise InputError(
            f"checkpoint {path}: it holds the tuning state of another run ({len(got)} arrays of shapes "
            f"{[g[0] for g in got]}; this run's optimizer and parameters have {len(want)} of shapes "
            f"{[w[0] for w in want]}): it was written with another optimizer, parameterization, "
            "precondition or design. Resume with the options of the run that wrote it, or pass another "
            "checkpoint path (or delete its .npz and .json) to start anew.")
    leaves = [jnp.asarray(x) for x in leaves]
    if npz_step != meta["step"]:
        raise InputError(
            f"checkpoint {path}: {path}.npz holds step {npz_step} but {path}.json step {meta['step']} "
            "(the run was killed between the two writes); delete both files to restart the tuning."
        )
    treedef = jax.tree.structure((params, opt_state))
    params, opt_state = jax.tree.unflatten(treedef, leaves)
    return params, opt_state, meta["step"], key, meta["history"]


def run_loop(
    params,
    opt_state,
    key,
    *,
    steps: int,
    step: Callable,
    step_args: tuple,
    backtrack: Callable,
    host_check: Callable,
    heldout_loss: Callable | None,
    eval_every: int,
    callback: Callable | None,
    to_params: Callable,
    path: str | None,
    resume: bool,
    checkpoint_every: int,
    quiet: bool,
    desc: str,
    devices=None,
    place: Callable | None = None,
):
    """Run steps ``start+1 .. steps`` and return ``(params, history)``.

    `step(params, opt_state, *step_args) -> (value, updates, new_opt_state)` is the jitted
    step; `backtrack(params, updates) -> (candidate, margin, ok, backtracks)` the step rule
    (`backtracked_update`, host); `host_check(params, margin) -> (inside, margin,
    max_real_eig)` the float64 check on the host (`margin`: the candidate's, already
    computed, or None); `to_params` maps the optimizer's coordinates to the
    parameterization's parameters (passed to `callback` as ``record["params"]``). With `resume` and an existing checkpoint at `path`, the
    run continues from it (the result equals an uninterrupted run).

    With `devices` spanning several processes (a `jax.distributed` run, every process
    running the same loop) only process 0 writes the checkpoint, and on `resume` process 0
    reads it and sends its bytes to the others (`fojax.studies.broadcast_bytes`):
    every process continues from process 0's checkpoint, whatever its own `path` holds
    (no file system shared by the hosts is needed). `place` maps a loaded ``(params,
    opt_state)`` to the placement of the jitted step's inputs (so that it does not compile
    again).
    """
    history = {k: [] for k in HISTORY_KEYS}
    start = 0
    writer = writes_files(devices)
    if resume and path is not None:
        data = read_checkpoint(path) if writer else None
        if devices is not None and spans_processes(devices):  # every process: process 0's bytes
            data = broadcast_bytes(data, f"{desc}: resuming from checkpoint {path}") or None
        if data is not None:
            params, opt_state, start, key, history = load_checkpoint(path, params, opt_state, data)
            if place is not None:
                params, opt_state = place((params, opt_state))
    for i in tqdm(range(start, steps), disable=quiet or not writer, desc=desc, unit="step"):
        key, _ = jax.random.split(key)
        value, updates, cand_state = step(params, opt_state, *step_args)
        cand, margin_c, accepted, nback = backtrack(params, updates)
        if accepted:
            accepted, margin_h, maxre = host_check(cand, margin_c)
        if accepted:
            params = cand
        else:
            _, margin_h, maxre = host_check(params, None)
        opt_state = cand_state
        evaluate = heldout_loss is not None and (i + 1) % eval_every == 0
        rec = dict(step=i + 1, train_loss=float(value), heldout_loss=heldout_loss(params) if evaluate else float("nan"),
                   margin=margin_h, accepted=accepted, backtracks=int(nback), max_real_eig=maxre)
        for k, v in rec.items():
            history[k].append(v)
        if callback is not None:
            callback(i + 1, dict(rec, params=to_params(params)))
        if writer and path is not None and ((i + 1) % checkpoint_every == 0 or i + 1 == steps):
            save_checkpoint(path, params, opt_state, i + 1, key, history)
    return params, history
