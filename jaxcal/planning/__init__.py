"""Capture planning: generate, check and pre-evaluate calibration motions before any image is taken.

See `docs/plan.md`. The numeric core (scene geometry, feasibility margins,
the Fisher information of the refinement, the optimisers) is pure JAX and
never imports MuJoCo; `jaxcal.sim.plan` adds the MuJoCo contact and
line-of-sight checks and renders a plan.
"""
