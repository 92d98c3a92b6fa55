"""The result of `fojax.simulate`."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float


class Solution(eqx.Module):
    r"""Trajectories of a plant and its observers on the output grid ``ts``.

    **Fields:**

    - `ts`: ``(T,)`` output times.
    - `xs`: ``(T, n)`` descriptor states; every row satisfies the algebraic
      constraints (the fast coordinates are solved, not integrated).
    - `ys`: ``(T, p)`` measured outputs ``g(t, x, u)``.
    - `us`: ``(T, m)`` inputs ``u(t)`` (right-continuous at jumps).
    - `observer_states`: tuple with one ``(T, s_i)`` array per observer.
    - `estimates`: tuple with one ``(T, q_i)`` array ``ẑ_i`` per observer.
    - `stats`: dict of arrays (no gradient flows through them):
        - ``"constraint_residual"``: ``max_k ‖U2ᵀ f(t_k, x_k, u_k)‖₂`` over the grid;
        - ``"initial_residual"``: ``‖U2ᵀ f(t0, x0, u0)‖₂`` of the *given* ``x0``;
        - ``"projection_distance"``: ``‖x0_consistent − x0‖₂``;
        - ``"num_steps"``, ``"num_accepted_steps"``, ``"num_rejected_steps"``: steps
          taken (for ``"exact"``: the ``T − 1`` grid steps);
        - ``"success"``: whether the solve succeeded (meaningful with ``throw=False``).
    - `method`: ``"exact"``, ``"diffrax"`` or ``"discrete"`` (static), the method that was used.

    Under `jax.vmap` every array field gains a leading batch axis.
    """

    ts: Float[Array, " T"]
    xs: Float[Array, "T n"]
    ys: Float[Array, "T p"]
    us: Float[Array, "T m"]
    observer_states: tuple[Float[Array, "T s"], ...]
    estimates: tuple[Float[Array, "T q"], ...]
    stats: dict[str, Array]
    method: str = eqx.field(static=True)
