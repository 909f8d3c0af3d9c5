"""A planned capture's camera and arm: what they add to the refinement's error.

`jaxcal.evaluate_plan(..., camera_model=, arm=)` (`docs/plan.md`, "Cameras and
arms in the prediction"). The figures come as records
(`jaxcal.records_capture`: `CameraNoise`, `ArmFigures`); the simulator makes
them from its presets, so this module never imports it.

- **The camera**: its sensor noise and compression add `added_sigma_px` to the
  detector's corner noise, in quadrature. Exposure blur and the rolling
  shutter act only while the arm moves: a frame whose exposure window
  (`CameraNoise.window_s` about its stamp) lies in a stop of the plan's motion
  (stop-and-shoot poses held `hold_s`) has neither. A moving frame whose
  corners smear by more than `SMEAR_PX` over the exposure is lost (the
  detector does not find a target smeared so: 4 px, from the renders); the rolling shutter's skew of
  the frames kept is the refinement's own model when the line delay is given
  or estimated (every corner timed at its row), which costs it nothing on
  analytic corners (`docs/performance.md`), so it adds no term here.
- **The arm**: where each frame's joints stand against what the encoders read,
  `offsets (V, joints)`: the gravity sag $10^{-3} c_j \\tau_j(q)$ at the frame's
  configuration, the backlash (the play operator along the plan's commanded
  motion: the link lags the motor by up to half the lost motion, on the side
  the last move came from), and with a latency $L$ the motion in $L$
  ($\\dot q L$, zero for a stopped frame). A latency is exactly a clock offset
  (the log read $L$ late): where the refinement estimates the clock (sweeps) it
  takes it whole, and it adds nothing. A rigid model cannot explain the
  corners they move, $\\delta u_v = P_v\\,\\delta\\theta_v$ ($P_v = \\partial u_v /
  \\partial q_v$), so the least-squares estimate moves by $\\delta x = (J^TJ)^{-1}
  J^T \\delta u$ (the residuals being model minus measurement), and the end
  effector by $G_c\\,\\delta x$ at workspace configuration $c$: a bias, the same
  in every capture of the plan. Encoder quantisation is noise: each reading
  errs uniformly within a count, $2\\pi / (\\text{counts}\\,\\rho) / \\sqrt{12}$ rad
  at the joint ($\\rho$ the reduction ratio), added to the noise part.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._compliance import backlash_offsets, gravity_offsets, per_joint
from ..io.plan import CapturePlan
from ..records_capture import ArmFigures, CameraNoise
from ..robots import link_inertials
from ._scene import PlanScene, frame_geometry

#: A moving frame whose corners smear over more than this during the exposure is lost (px). The
#: renders of `data/ur5e_sweeps`' design (`docs/performance.md`, "Realistic cameras") kept every fast
#: frame at the `global-shutter` preset's 2 ms, whose fastest corners smear by about 5 px (this rule
#: drops 1 of its 117 frames; 2 px, the verdict's bound under which no target is lost, would drop 13,
#: 3 px 8), and kept 4 to 5 and 2 of the shoulder_lift sweep's 24 frames at 5 and 10 ms (this rule
#: keeps 8 and 3): optimistic for long exposures by a few frames of the fastest sweep.
SMEAR_PX = 4.0
#: A frame is stopped when the commanded motion moves no joint by more than this over its window (rad).
STILL_RAD = 1e-12
#: Samples of the motion over a frame's exposure window.
WINDOW_SAMPLES = 9


@eqx.filter_jit
def pixel_jacobians(scene: PlanScene, q: Float[Array, "V joints"]) -> Float[Array, "V N 2 joints"]:
    """$P_v = \\partial u_v / \\partial q_v$: how every corner of every frame moves with its joints."""
    return jax.vmap(jax.jacfwd(lambda qq: frame_geometry(scene, qq).pixels))(q)


def frame_motion(
    plan: CapturePlan, t: np.ndarray, camera: CameraNoise | None
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame at controller times `t (V,)`: whether the arm stands still over the camera's
    exposure window (every frame without a camera model: its stamp only), and the commanded
    joint velocity at the stamp `(V, joints)` (rad/s, central differences)."""
    m = plan.motion()
    lo, hi = camera.window_s if camera is not None else (0.0, 0.0)
    s = np.asarray(t, np.float64)[:, None] + np.linspace(lo, hi, WINDOW_SAMPLES)[None, :]
    q0 = m.at(np.asarray(t, np.float64))
    moved = np.max(np.abs(m.at(s) - q0[:, None, :]), axis=(1, 2))
    h = 1e-4
    qdot = (m.at(np.asarray(t) + h) - m.at(np.asarray(t) - h)) / (2.0 * h)
    return moved <= STILL_RAD, qdot


def blurred(P: np.ndarray, qdot: np.ndarray, exposure_s: float) -> np.ndarray:
    """Frames `(V,)` whose corners smear over more than `SMEAR_PX` in `exposure_s` (`P` from
    `pixel_jacobians`, `qdot (V, joints)`)."""
    speed = np.linalg.norm(np.einsum("vnij,vj->vni", P, qdot), axis=-1)
    return np.max(speed, axis=1) * exposure_s > SMEAR_PX


def arm_offsets(
    plan: CapturePlan,
    robot_source: str,
    scene: PlanScene,
    q: np.ndarray,
    t: np.ndarray,
    qdot: np.ndarray,
    arm: ArmFigures,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`(gravity, backlash, latency (V, joints), quantisation std (joints,))` of frames at commanded
    `q (V, joints)`, times `t (V,)`, velocities `qdot (V, joints)` (see the module docstring)."""
    model = scene.nominal
    types = model.joint_types
    compliance = per_joint(arm.compliance or None, types)
    gravity = np.zeros_like(q)
    if np.any(compliance):
        masses, coms = link_inertials(robot_source)
        gravity = gravity_offsets(model, q, masses, coms, compliance)
    m = plan.motion()
    width = np.radians(per_joint(arm.backlash_deg, types))
    backlash = backlash_offsets(m.times, m.q, q, t, width)
    count = 2.0 * np.pi / (arm.counts_per_rev * np.asarray(model.reduction_ratio, np.float64))
    quantisation = np.where(np.asarray(types) == "revolute", count / np.sqrt(12.0), 0.0)
    return gravity, backlash, qdot * arm.latency_s, quantisation


def propagate(
    pinv: np.ndarray, Gf: np.ndarray, P: np.ndarray, mask: np.ndarray, offsets, joint_std: np.ndarray | None
) -> tuple[dict, np.ndarray, np.ndarray]:
    """The arm's effect through the least-squares map `pinv (f, rows)` (rows in `(V, N, 2)` order) and
    the EE Jacobians `Gf (C, 3, f)` of the free parameters: `(bias_parts, ee_bias (C, 3), cov_q (f, f))`,
    the EE bias RMS (m) of each named offset of `offsets ((name, (V, joints)), ...)`, the EE bias of
    their sum, and the parameters' covariance from joint readings erring by `joint_std (joints,)` rad."""
    V, N = P.shape[:2]
    Pm = P * np.asarray(mask, np.float64)[:, :, None, None]
    A = np.einsum("fvr,vrj->fvj", pinv.reshape(-1, V, 2 * N), Pm.reshape(V, 2 * N, -1))  # (f, V, joints)
    parts, dx = {}, np.zeros(pinv.shape[0])
    for name, d in offsets:
        step = np.einsum("fvj,vj->f", A, np.asarray(d, np.float64))
        parts[name] = float(np.sqrt(np.mean(np.sum((Gf @ step) ** 2, axis=-1))))
        dx = dx + step
    cov_q = np.zeros((pinv.shape[0],) * 2)
    if joint_std is not None:
        cov_q = np.einsum("avj,j,bvj->ab", A, np.asarray(joint_std, np.float64) ** 2, A)
    return parts, Gf @ dx, cov_q


def capture_terms(
    plan: CapturePlan,
    robot_source: str,
    scene: PlanScene,
    q: np.ndarray,
    t: np.ndarray,
    camera: CameraNoise | None,
    arm: ArmFigures | None,
    clock_free: bool,
) -> tuple[np.ndarray, tuple, np.ndarray | None, str]:
    """What the camera and arm models do to frames at `q (V, joints)`, `t (V,)`: `(kept (V,),
    offsets, joint_std, note)`: the frames not lost to blur, the arm's named offsets and reading
    noise at them (`evaluate_views`' arguments; empty / None without an arm; the latency left out
    where the refinement estimates the clock, `clock_free`), and a sentence on the camera's
    exposure and shutter (empty without a camera)."""
    stopped, qdot = frame_motion(plan, t, camera)
    kept, note = np.ones(len(q), bool), ""
    if camera is not None:
        lo, hi = (1e3 * v for v in camera.window_s)
        moving = int(np.sum(~stopped))
        if hi == lo:
            note = "the camera takes each frame at one instant (no exposure, no readout): no blur, no skew"
        elif moving == 0:
            note = (
                f"every frame is taken with the arm stopped over its exposure window ({lo:g} .. {hi:g} ms "
                "about the stamp): exposure blur and the rolling shutter do not apply"
            )
        else:
            P = np.asarray(pixel_jacobians(scene, jnp.asarray(q)))
            kept = ~(blurred(P, qdot, camera.exposure_s) & ~stopped)
            note = (
                f"{moving} of {len(q)} frames move during their exposure window ({lo:g} .. {hi:g} ms about "
                f"the stamp): {int(np.sum(~kept))} lost to blur (a smear over {SMEAR_PX:g} px in "
                f"{1e3 * camera.exposure_s:g} ms)"
                + (
                    "; the rolling shutter's skew is the refinement's own model when the line delay is given "
                    "or estimated (no term)"
                    if camera.readout_s > 0.0
                    else ""
                )
            )
    if arm is None:
        return kept, (), None, note
    gravity, backlash, latency, quantisation = arm_offsets(
        plan, robot_source, scene, q[kept], t[kept], qdot[kept], arm
    )
    offsets = (("gravity", gravity), ("backlash", backlash)) + (() if clock_free else (("latency", latency),))
    return kept, offsets, quantisation, note
