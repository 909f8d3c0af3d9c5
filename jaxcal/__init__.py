"""jaxcal: robot kinematic and hand-eye calibration from fiducial markers, in JAX."""

import importlib.metadata

import jax as _jax

# Calibration maths needs float64 (sub-millimetre over metre-scale arms);
# importing jaxcal turns it on for the whole process.
_jax.config.update("jax_enable_x64", True)

from ._arcfit import ArcData as ArcData  # noqa: E402
from ._arcfit import ArcFitResult as ArcFitResult  # noqa: E402
from ._arcfit import fit_arc as fit_arc  # noqa: E402
from ._arcfit import make_arc_data as make_arc_data  # noqa: E402
from ._arcfit import validate_arc_data as validate_arc_data  # noqa: E402
from ._axisfit import AxisFitResult as AxisFitResult  # noqa: E402
from ._axisfit import KinematicCorrection as KinematicCorrection  # noqa: E402
from ._axisfit import fit_axes as fit_axes  # noqa: E402
from ._axisfit import parameter_names as parameter_names  # noqa: E402
from ._kinematics import KinematicModel as KinematicModel  # noqa: E402
from ._kinematics import PerturbationScales as PerturbationScales  # noqa: E402
from ._kinematics import POEModel as POEModel  # noqa: E402
from ._kinematics import commanded_from_motor as commanded_from_motor  # noqa: E402
from ._kinematics import forward_kinematics as forward_kinematics  # noqa: E402
from ._kinematics import from_dh as from_dh  # noqa: E402
from ._kinematics import from_mdh as from_mdh  # noqa: E402
from ._kinematics import joint_angles as joint_angles  # noqa: E402
from ._kinematics import joint_axes as joint_axes  # noqa: E402
from ._kinematics import make_model as make_model  # noqa: E402
from ._kinematics import perturb_model as perturb_model  # noqa: E402
from ._kinematics import poe_forward_kinematics as poe_forward_kinematics  # noqa: E402
from ._kinematics import to_poe as to_poe  # noqa: E402
from ._kinematics import tool_pose as tool_pose  # noqa: E402
from ._montecarlo import MonteCarloSetup as MonteCarloSetup  # noqa: E402
from ._montecarlo import NoiseModel as NoiseModel  # noqa: E402
from ._montecarlo import SweepPlan as SweepPlan  # noqa: E402
from ._montecarlo import TrialResult as TrialResult  # noqa: E402
from ._montecarlo import default_setup as default_setup  # noqa: E402
from ._montecarlo import fit_sweeps as fit_sweeps  # noqa: E402
from ._montecarlo import monte_carlo as monte_carlo  # noqa: E402
from ._montecarlo import summarize as summarize  # noqa: E402
from ._montecarlo import synthesize_sweeps as synthesize_sweeps  # noqa: E402
from .pipeline import CalibrationError as CalibrationError  # noqa: E402
from .pipeline import CalibrationResult as CalibrationResult  # noqa: E402
from .pipeline import calibrate as calibrate  # noqa: E402
from .report import write_outputs as write_outputs  # noqa: E402

try:
    __version__ = importlib.metadata.version("jaxcal")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
