"""Measured against predicted end-effector error of a calibrated dataset.

What is measured: `jaxcal.calibrate` on a synthetic dataset (one with a
`truth.json`, e.g. `jaxcal demo`'s), then

- the measured EE RMS: the flange target's origin in the camera frame over
  the validation's 1000 random configurations, refined model against the
  truth (`validation.ee_rms_mm_after`);
- the predicted 1-sigma EE RMS: the refinement's parameter covariance
  $\\Sigma$ pushed through the Jacobian $J_c$ of that same point at each
  configuration, $\\sqrt{\\mathrm{mean}_c\\,\\mathrm{tr}(J_c \\Sigma J_c^T)}$.

With honest standard deviations (the refinement's are checked by seeded
Monte Carlo in the tests) the measured error is one draw of a quantity whose
RMS is the prediction: a target well below the prediction asks for more data,
not a better solver.

How to run (from the repository root; `jaxcal demo --out D` makes `D/dataset`)::

    .venv/bin/python benchmarks/ee_uncertainty.py jaxcal-demo/dataset --json results/ee_uncertainty.json
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="a synthetic dataset directory (with truth.json)")
    parser.add_argument("--json", help="write the figures here")
    args = parser.parse_args(argv)

    import jax

    import jaxcal

    r = jaxcal.calibrate(args.dataset, progress=False, log=print)  # the stages, and a line while one is long
    if r.refine_fit is None or r.validation is None:
        print(
            f"{args.dataset}: needs a refined calibration of a synthetic dataset (truth.json)",
            file=sys.stderr,
        )
        return 2
    est = r.estimate  # the refinement's vector, covariance and references
    # The validation's configurations (stages._validate, seed 0).
    q = jax.random.uniform(jax.random.key(0), (1000, est.nominal.num_joints), minval=-np.pi, maxval=np.pi)

    def ee(x):
        c = jaxcal.parameters_to_model(est, x)

        def fk(qq):
            T = c.T_cam_base @ jaxcal.forward_kinematics(c.model, qq)[-1] @ c.T_flange_marker[0]
            return T[:3, 3]

        return jax.vmap(fk)(q)

    J = np.asarray(jax.jit(jax.jacfwd(ee))(est.x))
    predicted = float(np.sqrt(np.einsum("cia,ab,cib->c", J, np.asarray(est.cov), J).mean()))
    out = {
        "dataset": str(Path(args.dataset)),
        "ee_rms_mm_measured": r.validation["ee_rms_mm_after"],
        "ee_rms_mm_predicted_1sigma": 1e3 * predicted,
        "ee_rms_mm_two_stage": r.validation["ee_rms_mm_two_stage"],
        "free_parameters": int(np.asarray(est.free).sum()),
    }
    print(json.dumps(out, indent=2) if not args.json else f"wrote {args.json}")
    if args.json:
        from jaxcal.io._files import write_text_atomic

        write_text_atomic(Path(args.json), json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
