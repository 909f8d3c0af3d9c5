"""jaxcal: robot kinematic and hand-eye calibration from fiducial markers, in JAX."""

import importlib.metadata

import jax as _jax

from ._xla import configure_xla as _configure_xla

# XLA compiler defaults for jaxcal's programs (before any backend starts; opt
# out: JAXCAL_XLA_DEFAULTS=0; see jaxcal._xla).
_configure_xla()

# Calibration maths needs float64 (sub-millimetre over metre-scale arms);
# importing jaxcal turns it on for the whole process.
_jax.config.update("jax_enable_x64", True)

from ._cache import enable_compilation_cache as _enable_compilation_cache  # noqa: E402

# Compiled programs persist across processes (opt out: JAXCAL_NO_CACHE=1; see jaxcal._cache).
_enable_compilation_cache()

from . import vision as vision  # noqa: E402
from ._arcdata import ArcData as ArcData  # noqa: E402
from ._arcdata import make_arc_data as make_arc_data  # noqa: E402
from ._arcdata import stack_sweeps as stack_sweeps  # noqa: E402
from ._arcfit import ArcFitResult as ArcFitResult  # noqa: E402
from ._arcfit import arc_outliers as arc_outliers  # noqa: E402
from ._arcfit import fit_arc as fit_arc  # noqa: E402
from ._arcfit import validate_arc_data as validate_arc_data  # noqa: E402
from ._axisfit import AxisFitResult as AxisFitResult  # noqa: E402
from ._axisfit import fit_axes as fit_axes  # noqa: E402
from ._axisfit import parameter_names as parameter_names  # noqa: E402
from ._correction import CalibratedModel as CalibratedModel  # noqa: E402
from ._correction import Estimate as Estimate  # noqa: E402
from ._correction import KinematicCorrection as KinematicCorrection  # noqa: E402
from ._correction import parameters_to_model as parameters_to_model  # noqa: E402
from ._dh import DHTable as DHTable  # noqa: E402
from ._dh import dh_table as dh_table  # noqa: E402
from ._dh import table_forward_kinematics as table_forward_kinematics  # noqa: E402
from ._dh import table_to_model as table_to_model  # noqa: E402
from ._handeye import HandEyePixels as HandEyePixels  # noqa: E402
from ._handeye import HandEyePoses as HandEyePoses  # noqa: E402
from ._handeye import HandEyeResult as HandEyeResult  # noqa: E402
from ._handeye import HandEyeVerdict as HandEyeVerdict  # noqa: E402
from ._handeye import KFoldSpread as KFoldSpread  # noqa: E402
from ._handeye import MotionConsistency as MotionConsistency  # noqa: E402
from ._handeye import TouchData as TouchData  # noqa: E402
from ._handeye import TouchResult as TouchResult  # noqa: E402
from ._handeye import assess_hand_eye as assess_hand_eye  # noqa: E402
from ._handeye import calibrate_hand_eye as calibrate_hand_eye  # noqa: E402
from ._handeye import calibrate_touch as calibrate_touch  # noqa: E402
from ._handeye import check_motion_consistency as check_motion_consistency  # noqa: E402
from ._handeye import check_motion_diversity as check_motion_diversity  # noqa: E402
from ._handeye import check_rotations as check_rotations  # noqa: E402
from ._handeye import hand_eye_residuals as hand_eye_residuals  # noqa: E402
from ._handeye import initialise_hand_eye as initialise_hand_eye  # noqa: E402
from ._handeye import initialise_touch as initialise_touch  # noqa: E402
from ._handeye import kfold_spread as kfold_spread  # noqa: E402
from ._handeye import make_hand_eye_pixels as make_hand_eye_pixels  # noqa: E402
from ._handeye import make_hand_eye_poses as make_hand_eye_poses  # noqa: E402
from ._handeye import make_touch_data as make_touch_data  # noqa: E402
from ._handeye import pad_hand_eye as pad_hand_eye  # noqa: E402
from ._handeye import solve_axzb as solve_axzb  # noqa: E402
from ._handeye import touch_residuals as touch_residuals  # noqa: E402
from ._handeye import validate_hand_eye as validate_hand_eye  # noqa: E402
from ._handeye import validate_touch as validate_touch  # noqa: E402
from ._handeye_capture import HandEyeRun as HandEyeRun  # noqa: E402
from ._handeye_capture import calibrate_hand_eye_capture as calibrate_hand_eye_capture  # noqa: E402
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
from ._tables import PhysicalTable as PhysicalTable  # noqa: E402
from ._tables import physical_table as physical_table  # noqa: E402
from ._tooloffset import AlignmentResult as AlignmentResult  # noqa: E402
from ._tooloffset import CircleFit as CircleFit  # noqa: E402
from ._tooloffset import OffsetEstimate as OffsetEstimate  # noqa: E402
from ._tooloffset import ToolOffsetResult as ToolOffsetResult  # noqa: E402
from ._tooloffset import align_to_principal_point as align_to_principal_point  # noqa: E402
from ._tooloffset import calibrate_tool_offset as calibrate_tool_offset  # noqa: E402
from ._tooloffset import estimate_offset as estimate_offset  # noqa: E402
from ._tooloffset import fit_circle as fit_circle  # noqa: E402
from ._tooloffset import validate_arc_points as validate_arc_points  # noqa: E402
from .errors import CalibrationError as CalibrationError  # noqa: E402
from .errors import DatasetError as DatasetError  # noqa: E402
from .errors import DegenerateMotionError as DegenerateMotionError  # noqa: E402
from .errors import HandEyeInputError as HandEyeInputError  # noqa: E402
from .errors import InconsistentPosesError as InconsistentPosesError  # noqa: E402
from .errors import IntrinsicsError as IntrinsicsError  # noqa: E402
from .errors import JaxcalError as JaxcalError  # noqa: E402
from .errors import LengthMismatchError as LengthMismatchError  # noqa: E402
from .errors import NoiseLevelError as NoiseLevelError  # noqa: E402
from .errors import NonFiniteError as NonFiniteError  # noqa: E402
from .errors import NotARotationError as NotARotationError  # noqa: E402
from .errors import NotPositiveDefiniteError as NotPositiveDefiniteError  # noqa: E402
from .errors import ShapeError as ShapeError  # noqa: E402
from .errors import SuspectResultError as SuspectResultError  # noqa: E402
from .errors import TooFewPosesError as TooFewPosesError  # noqa: E402
from .errors import ToolOffsetInputError as ToolOffsetInputError  # noqa: E402
from .errors import VisionError as VisionError  # noqa: E402
from .io.dh_tables import dh_table_model as dh_table_model  # noqa: E402
from .io.dh_tables import read_dh_table as read_dh_table  # noqa: E402
from .io.handeye import HandEyeCapture as HandEyeCapture  # noqa: E402
from .io.handeye import load_hand_eye_capture as load_hand_eye_capture  # noqa: E402
from .io.handeye_results import write_hand_eye_outputs as write_hand_eye_outputs  # noqa: E402
from .pipeline import calibrate as calibrate  # noqa: E402
from .planning import CapturePlan as CapturePlan  # noqa: E402
from .planning import evaluate_plan as evaluate_plan  # noqa: E402
from .planning import load_plan as load_plan  # noqa: E402
from .planning import plan as plan  # noqa: E402
from .planning import save_plan as save_plan  # noqa: E402
from .report import write_outputs as write_outputs  # noqa: E402
from .stages import CalibrationResult as CalibrationResult  # noqa: E402
from .vision import HandEyeObservations as HandEyeObservations  # noqa: E402
from .vision import hand_eye_from_detections as hand_eye_from_detections  # noqa: E402

try:
    __version__ = importlib.metadata.version("jaxcal")
except importlib.metadata.PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0"
