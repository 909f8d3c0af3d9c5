"""Capture planning: generate, check and pre-evaluate calibration motions before any image is taken.

See `docs/plan.md`. The numeric core (scene geometry, feasibility margins,
the Fisher information of the refinement, the optimisers) is pure JAX and
never imports MuJoCo; `jaxcal.sim.plan` adds the MuJoCo contact and
line-of-sight checks and renders a plan.
"""

from ..io.plan import CapturePlan as CapturePlan
from ..io.plan import Correction as Correction
from ..io.plan import FreeMotion as FreeMotion
from ..io.plan import PlanCamera as PlanCamera
from ..io.plan import PlanTarget as PlanTarget
from ..io.plan import PoseSet as PoseSet
from ..io.plan import Sweep as Sweep
from ..io.plan import plan_from_dict as plan_from_dict
from ..io.plan import plan_to_dict as plan_to_dict
from ._api import TAUGHT as TAUGHT
from ._api import PlanResult as PlanResult
from ._api import Robot as Robot
from ._api import evaluate_plan as evaluate_plan
from ._api import plan as plan
from ._api import plan_robot as plan_robot
from ._api import scene_of as scene_of
from ._api import sweep_plan as sweep_plan
from ._api import workspace as workspace
from ._evaluate import DEFAULT_SIGMA_PX as DEFAULT_SIGMA_PX
from ._evaluate import PlanEvaluation as PlanEvaluation
from ._evaluate import evaluate_views as evaluate_views
from ._evaluate import sigma_for as sigma_for
from ._layout import default_layout as default_layout
from ._plan import load_plan as load_plan
from ._plan import save_plan as save_plan
from ._report import plot_evaluation as plot_evaluation
from ._scene import ALWAYS as ALWAYS
from ._scene import CHECKS as CHECKS
from ._scene import FeasibilityLimits as FeasibilityLimits
