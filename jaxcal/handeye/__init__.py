"""The hand-eye product: a capture on disk calibrated, checked and judged, in named steps.

```
load -> observe (detect, intrinsics, PnP, input checks) -> solve (each robot-noise model and its
k-fold, the model kept) -> judge -> HandEyeRun -> outputs
```

Each step is a function of the records before it (`_observe.observe` -> `Observed`,
`_solve.solve` -> `Solved`, with `_noise`'s models and choice, `_verdict.judge` -> `HandEyeVerdict`), and
`calibrate_hand_eye_capture` calls them in order; `jaxcal.io.handeye_results`
writes a `HandEyeRun`'s outputs. The numeric solve is the core's
(`jaxcal._handeye`); this package is the impure product around it (files,
OpenCV), as `jaxcal.stages` and `jaxcal.pipeline` are for `jaxcal.calibrate`.
No module outside this package imports its private modules
(`tests/test_architecture.py`).
"""

from ._observe import Observed as Observed
from ._observe import camera_intrinsics as camera_intrinsics
from ._observe import detect as detect
from ._observe import load as load
from ._observe import observe as observe
from ._run import HandEyeRun as HandEyeRun
from ._run import calibrate_hand_eye_capture as calibrate_hand_eye_capture
from ._solve import OUTLIER_THRESHOLD as OUTLIER_THRESHOLD
from ._solve import Solved as Solved
from ._solve import hand_eye_solver as hand_eye_solver
from ._solve import solve as solve
from ._verdict import MISFIT_RATIO as MISFIT_RATIO
from ._verdict import judge as judge
