"""Models, designs and data from and to other tools: python-control, SciPy, MATLAB files,
recorded (u, y) logs."""

from ._discretize import discretize as discretize
