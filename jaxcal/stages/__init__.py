"""The calibration product as stages (see `docs/architecture.md`).

`jaxcal.calibrate` runs them in order; each is a function from typed inputs
to a typed, immutable record, and none changes another's output:

    setup -> observe -> synchronise -> two_stage -> refine -> verdict -> validate -> assemble

The capture kind (`kinds.CaptureKind`) is resolved once by `setup`; every
difference between kinds is one of its properties.
"""

from .kinds import CaptureKind as CaptureKind
from .kinds import Motion as Motion
from .kinds import Mount as Mount
from .limits import Limits as Limits
from .observe import Observations as Observations
from .observe import observe as observe
from .refine import Refined as Refined
from .refine import refine as refine
from .result import CalibrationResult as CalibrationResult
from .result import assemble as assemble
from .setup import Options as Options
from .setup import Setup as Setup
from .setup import setup as setup
from .synchronise import Sweeps as Sweeps
from .synchronise import Sync as Sync
from .synchronise import synchronise as synchronise
from .two_stage import TwoStage as TwoStage
from .two_stage import two_stage as two_stage
from .validate import Validation as Validation
from .validate import validate as validate
from .verdict import Verdict as Verdict
from .verdict import verdict as verdict
