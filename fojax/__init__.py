"""fojax: functional observers for descriptor systems $E\\dot x = Ax + Bu$, $y = Cx$, in JAX.
The names a notebook needs first are here; everything else lives in one subpackage.

**The public API, one rule.** At most 60 names at the top (submodules included): the
plants, faults and signals, the ``design_*`` functions and the regions, the observers,
`simulate` with its steppers and save objects, `Study`/`run_study`, `tune`,
`save_design`/`load_design`, `structure_report`, `load_config`, `estimate`, `discretize`
and the base error `FojaxError`. Every other public name has exactly one home, a
subpackage (`fojax.analysis.is_regular`, `fojax.errors.InputError`,
`fojax.design.verify`, ...); a top-level name is the same object as its home's name
(``fojax.simulate is fojax.simulation.simulate``). No object has two names, no name two
homes, and every public name is documented (``tests/test_public_api.py`` checks all three).

Floors (each imports only the floors below it): ``plant`` (plants, signals, faults) and
``models`` (the thesis's examples) → ``analysis`` (structure) → ``observer`` → ``design``
(LMIs, verified) → ``simulation`` → ``studies`` (Monte Carlo), ``control`` and ``interop``
(python-control, SciPy, MATLAB files, recorded data) → ``tuning`` (optax) → ``results``
(files, reports, figures) → ``config`` (TOML) → ``cli`` (the ``fojax`` program, which the
library never imports). ``errors`` is the ground floor.
"""

import importlib.metadata as _metadata

from . import (
    analysis as analysis,
    config as config,
    control as control,
    design as design,
    errors as errors,
    interop as interop,
    models as models,
    observer as observer,
    plant as plant,
    results as results,
    simulation as simulation,
    studies as studies,
    tuning as tuning,
)
from ._errors import FojaxError as FojaxError
from .analysis import structure_report as structure_report
from .config import load_config as load_config
from .control import design_state_feedback as design_state_feedback
from .design import (
    design_fault_estimator as design_fault_estimator,
    design_finite_time_observer as design_finite_time_observer,
    design_functional_observer as design_functional_observer,
    design_ts_observer as design_ts_observer,
    design_unknown_input_observer as design_unknown_input_observer,
    Disk as Disk,
    HalfPlane as HalfPlane,
    Intersection as Intersection,
    Sector as Sector,
)
from .interop import discretize as discretize, estimate as estimate
from .observer import (
    FiniteTimeObserver as FiniteTimeObserver,
    GeneralizedFunctionalObserver as GeneralizedFunctionalObserver,
    TakagiSugenoObserver as TakagiSugenoObserver,
    UnknownInputObserver as UnknownInputObserver,
)
from .plant import (
    Constant as Constant,
    DescriptorSystem as DescriptorSystem,
    FaultyPlant as FaultyPlant,
    NoisyPlant as NoisyPlant,
    NonlinearDescriptorSystem as NonlinearDescriptorSystem,
    PiecewiseConstant as PiecewiseConstant,
    Ramp as Ramp,
    Sine as Sine,
    Step as Step,
    TakagiSugenoSystem as TakagiSugenoSystem,
    UncertainDescriptorSystem as UncertainDescriptorSystem,
)
from .results import load_design as load_design, save_design as save_design
from .simulation import (
    Auto as Auto,
    Bands as Bands,
    Diffrax as Diffrax,
    Exact as Exact,
    Exponential as Exponential,
    Metrics as Metrics,
    simulate as simulate,
    Trajectory as Trajectory,
)
from .studies import run_study as run_study, Study as Study, StudyResult as StudyResult
from .tuning import tune as tune


__version__ = _metadata.version("fojax")
