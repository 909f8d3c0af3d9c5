"""jaxcal: robot kinematic and hand-eye calibration from fiducial markers, in JAX.

The names below are imported when first used (PEP 562 `__getattr__`): `import
jaxcal` sets JAX up without importing it and loads nothing else, so that a script or a command that
needs the hand-eye solver never pays for OpenCV, matplotlib, ROS bags or the
planner. The `TYPE_CHECKING` block is the public API, for readers, type checkers
and `__getattr__` alike.
"""

import ast
import importlib
import importlib.metadata
from pathlib import Path
from typing import TYPE_CHECKING

from ._cache import configure_jax as _configure_jax
from ._xla import configure_xla as _configure_xla

# XLA compiler defaults for jaxcal's programs (before any backend starts; opt
# out: JAXCAL_XLA_DEFAULTS=0; see jaxcal._xla).
_configure_xla()

# Calibration maths needs float64 (sub-millimetre over metre-scale arms), and
# compiled programs persist across processes (opt out: JAXCAL_NO_CACHE=1; see
# jaxcal._cache). Both hold for the whole process, set the moment JAX is imported: by
# the first module that computes, not here, so that a command's first line comes first.
_configure_jax()

if TYPE_CHECKING:
    from . import distributed as distributed
    from . import vision as vision
    from ._arcdata import ArcData as ArcData
    from ._arcdata import make_arc_data as make_arc_data
    from ._arcdata import stack_sweeps as stack_sweeps
    from ._arcfit import ArcFitResult as ArcFitResult
    from ._arcfit import arc_outliers as arc_outliers
    from ._arcfit import fit_arc as fit_arc
    from ._arcfit import validate_arc_data as validate_arc_data
    from ._axisfit import AxisFitResult as AxisFitResult
    from ._axisfit import fit_axes as fit_axes
    from ._axisfit import parameter_names as parameter_names
    from ._correction import CalibratedModel as CalibratedModel
    from ._correction import Estimate as Estimate
    from ._correction import KinematicCorrection as KinematicCorrection
    from ._correction import parameters_to_model as parameters_to_model
    from ._dh import DHTable as DHTable
    from ._dh import dh_table as dh_table
    from ._dh import from_dh as from_dh
    from ._dh import from_mdh as from_mdh
    from ._dh import table_forward_kinematics as table_forward_kinematics
    from ._dh import table_to_model as table_to_model
    from ._handeye import HandEyePixels as HandEyePixels
    from ._handeye import HandEyePoses as HandEyePoses
    from ._handeye import HandEyeResult as HandEyeResult
    from ._handeye import HandEyeVerdict as HandEyeVerdict
    from ._handeye import KFoldSpread as KFoldSpread
    from ._handeye import MotionConsistency as MotionConsistency
    from ._handeye import TouchData as TouchData
    from ._handeye import TouchResult as TouchResult
    from ._handeye import assess_hand_eye as assess_hand_eye
    from ._handeye import calibrate_hand_eye as calibrate_hand_eye
    from ._handeye import calibrate_touch as calibrate_touch
    from ._handeye import check_motion_consistency as check_motion_consistency
    from ._handeye import check_motion_diversity as check_motion_diversity
    from ._handeye import check_rotations as check_rotations
    from ._handeye import hand_eye_residuals as hand_eye_residuals
    from ._handeye import initialise_hand_eye as initialise_hand_eye
    from ._handeye import initialise_touch as initialise_touch
    from ._handeye import kfold_spread as kfold_spread
    from ._handeye import make_hand_eye_pixels as make_hand_eye_pixels
    from ._handeye import make_hand_eye_poses as make_hand_eye_poses
    from ._handeye import make_touch_data as make_touch_data
    from ._handeye import pad_hand_eye as pad_hand_eye
    from ._handeye import solve_axzb as solve_axzb
    from ._handeye import touch_residuals as touch_residuals
    from ._handeye import validate_hand_eye as validate_hand_eye
    from ._handeye import validate_touch as validate_touch
    from ._kinematics import KinematicModel as KinematicModel
    from ._kinematics import PerturbationScales as PerturbationScales
    from ._kinematics import POEModel as POEModel
    from ._kinematics import commanded_from_motor as commanded_from_motor
    from ._kinematics import forward_kinematics as forward_kinematics
    from ._kinematics import joint_angles as joint_angles
    from ._kinematics import joint_axes as joint_axes
    from ._kinematics import make_model as make_model
    from ._kinematics import perturb_model as perturb_model
    from ._kinematics import poe_forward_kinematics as poe_forward_kinematics
    from ._kinematics import to_poe as to_poe
    from ._kinematics import tool_pose as tool_pose
    from ._lsq import LMOptions as LMOptions
    from ._montecarlo import MonteCarloSetup as MonteCarloSetup
    from ._montecarlo import NoiseModel as NoiseModel
    from ._montecarlo import SweepPlan as SweepPlan
    from ._montecarlo import TrialResult as TrialResult
    from ._montecarlo import default_setup as default_setup
    from ._montecarlo import fit_sweeps as fit_sweeps
    from ._montecarlo import monte_carlo as monte_carlo
    from ._montecarlo import summarize as summarize
    from ._montecarlo import synthesize_sweeps as synthesize_sweeps
    from ._options import RobustOptions as RobustOptions
    from ._tables import PhysicalTable as PhysicalTable
    from ._tables import physical_table as physical_table
    from ._tooloffset import AlignmentResult as AlignmentResult
    from ._tooloffset import CircleFit as CircleFit
    from ._tooloffset import OffsetEstimate as OffsetEstimate
    from ._tooloffset import ToolOffsetResult as ToolOffsetResult
    from ._tooloffset import align_to_principal_point as align_to_principal_point
    from ._tooloffset import calibrate_tool_offset as calibrate_tool_offset
    from ._tooloffset import estimate_offset as estimate_offset
    from ._tooloffset import fit_circle as fit_circle
    from ._tooloffset import validate_arc_points as validate_arc_points
    from .compensation import compensate as compensate
    from .errors import CalibrationError as CalibrationError
    from .errors import DatasetError as DatasetError
    from .errors import DegenerateMotionError as DegenerateMotionError
    from .errors import HandEyeInputError as HandEyeInputError
    from .errors import InconsistentPosesError as InconsistentPosesError
    from .errors import IntrinsicsError as IntrinsicsError
    from .errors import JaxcalError as JaxcalError
    from .errors import LengthMismatchError as LengthMismatchError
    from .errors import NoiseLevelError as NoiseLevelError
    from .errors import NonFiniteError as NonFiniteError
    from .errors import NotARotationError as NotARotationError
    from .errors import NotPositiveDefiniteError as NotPositiveDefiniteError
    from .errors import ShapeError as ShapeError
    from .errors import SuspectResultError as SuspectResultError
    from .errors import TooFewPosesError as TooFewPosesError
    from .errors import ToolOffsetInputError as ToolOffsetInputError
    from .errors import VisionError as VisionError
    from .handeye import HandEyeRun as HandEyeRun
    from .handeye import calibrate_hand_eye_capture as calibrate_hand_eye_capture
    from .io.dh_tables import dh_table_model as dh_table_model
    from .io.dh_tables import read_dh_table as read_dh_table
    from .io.handeye import HandEyeCapture as HandEyeCapture
    from .io.handeye import load_hand_eye_capture as load_hand_eye_capture
    from .io.handeye_results import write_hand_eye_outputs as write_hand_eye_outputs
    from .pipeline import calibrate as calibrate
    from .planning import CapturePlan as CapturePlan
    from .planning import evaluate_plan as evaluate_plan
    from .planning import load_plan as load_plan
    from .planning import plan as plan
    from .planning import save_plan as save_plan
    from .report import write_outputs as write_outputs
    from .stages import CalibrationResult as CalibrationResult
    from .vision import HandEyeObservations as HandEyeObservations
    from .vision import hand_eye_from_detections as hand_eye_from_detections


def _public_names() -> dict[str, tuple[str, str | None]]:
    """Name -> (module, attribute; `None` for a module), read from the `TYPE_CHECKING` block."""
    names = {}
    for node in ast.parse(Path(__file__).read_text(encoding="utf-8")).body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                for alias in imp.names:
                    if imp.module is None:  # `from . import vision`
                        names[alias.asname or alias.name] = ("." + alias.name, None)
                    else:
                        names[alias.asname or alias.name] = ("." * imp.level + imp.module, alias.name)
    return names


_PUBLIC = _public_names()


def __getattr__(name: str):
    """Import a public name, or a public submodule (`jaxcal.robots`), on first use."""
    if name in _PUBLIC:
        module, attribute = _PUBLIC[name]
        value = importlib.import_module(module, __name__)
        value = value if attribute is None else getattr(value, attribute)
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))


try:
    __version__ = importlib.metadata.version("jaxcal")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
