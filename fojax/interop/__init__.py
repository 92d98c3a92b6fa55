"""Models, designs and data from and to other tools: python-control, SciPy, MATLAB ``.mat``
files, recorded ``(u, y)`` logs (`estimate`) and sampled-data equivalents (`discretize`).

State-space models: `from_control`, `to_control`, `from_scipy`, `to_scipy`, `state_space`;
``.mat`` files: `load_mat`, `save_mat`."""

from ._discretize import discretize as discretize
from ._estimate import estimate as estimate
from ._mat import load_mat as load_mat, save_mat as save_mat
from ._state_space import (
    from_control as from_control,
    from_scipy as from_scipy,
    state_space as state_space,
    to_control as to_control,
    to_scipy as to_scipy,
)
