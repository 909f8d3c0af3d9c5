"""The calibration product as stages (see `docs/architecture.md`).

`jaxcal.calibrate` runs them in order; each is a function from typed inputs
to a typed, immutable record, and none changes another's output:

    setup -> observe -> synchronise -> two_stage -> refine -> verdict -> validate -> assemble

The capture kind (`kinds.CaptureKind`) is resolved once by `setup`; every
difference between kinds is one of its properties.
"""

from ._armcheck import finish_arm_score as finish_arm_score
from ._armcheck import start_arm_score as start_arm_score
from ._observe import Observations as Observations
from ._observe import observe as observe
from ._programs import run_ahead as run_ahead
from ._refine import Refined as Refined
from ._refine import refine as refine
from ._setup import CLOCK_MODES as CLOCK_MODES
from ._setup import TWO_STAGE_IS_FINAL as TWO_STAGE_IS_FINAL
from ._setup import Options as Options
from ._setup import Setup as Setup
from ._setup import setup as setup
from ._synchronise import Sweeps as Sweeps
from ._synchronise import Sync as Sync
from ._synchronise import synchronise as synchronise
from ._two_stage import TwoStage as TwoStage
from ._two_stage import two_stage as two_stage
from ._validate import Validation as Validation
from ._validate import validate as validate
from ._verdict import Verdict as Verdict
from ._verdict import verdict as verdict
from .kinds import CaptureKind as CaptureKind
from .kinds import Motion as Motion
from .kinds import Mount as Mount
from .limits import Limits as Limits
from .result import CalibrationResult as CalibrationResult
from .result import assemble as assemble
