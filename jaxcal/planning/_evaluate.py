"""Pre-evaluation of a capture plan: the Fisher information of the refinement that will solve it.

The calibration of a capture ends with `jaxcal._refine.refine`: every detected
corner's reprojection error minimised over the correction vector $x$ (the
layout of `jaxcal._correction.ParameterLayout`). Before any image exists, the
corners of a plan's frames are predicted at the nominal robot; with
$J = \\partial \\hat u / \\partial x$ the Jacobian of the very residuals the
refinement solves (`reprojection_residuals`), over the parameters it will
free (`identifiable_mask`, with the capture kind's candidates and threshold),
and i.i.d. Gaussian pixel noise $\\sigma$, the Cramer-Rao bound is

$$\\Sigma = \\sigma^2 (J^T J)^{-1}.$$

The end-effector point $p_c(x)$ (the target's origin in the camera frame; the
camera's in the board frame eye-in-hand: the validation's point) at workspace
configuration $c$ then has covariance $G_c \\Sigma G_c^T$, $G_c = \\partial p_c /
\\partial x$, and the predicted EE RMS over the workspace sample is

$$e^2 = \\frac{1}{C} \\sum_c \\mathrm{tr}(G_c \\Sigma G_c^T) = \\sigma^2\\,
\\mathrm{tr}\\big((J^T J)^{-1} M\\big),\\qquad M = \\frac{1}{C}\\sum_c G_c^T G_c,$$

a smooth function of the frames' joint values: the planner's objective
(`ee_mean_square`). Parameters the plan leaves unidentifiable are held at
nominal by the refinement; their names are reported.

With non-geometric terms (`TermInputs`: `jaxcal._terms`, as the refinement fits
them), every frame's joint angles gain $\\Delta_v = \\sum e\\,b(q_v, a_v)$: their
columns $P_v b$ ($P_v = \\partial u_v / \\partial q_v$) join $J$ as nuisance
parameters ($M$ is zero for them: the EE point is the rigid model's), so the
prediction, and the planner's objective, count what telling the terms from the
geometry costs: a plan with little gravity-torque variety, or whose poses are
all approached from one side, pays for it in the geometry's variance.
"""

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float

from .._correction import ParameterLayout
from .._exported import stored_jit
from .._refine import CornerData, RefineProblem, identifiable_mask, zero_params
from .._reprojection import reprojection_residuals
from .._terms import BASIS_FLOOR, TERM_STD_RAD, column_map, term_basis
from .._terms import names as term_names
from .._uncertainty import tool_points
from ..stages.kinds import CaptureKind
from ._realism import pixel_jacobians, propagate
from ._scene import PlanScene, frame_geometry

#: Corner noise of the detector on rendered images (px, per coordinate): the
#: inlier RMS of the refinement of `jaxcal demo`'s capture (1280x960, 0.9 m).
DEFAULT_SIGMA_PX = 0.045
#: ... at other image widths it grows as the corners' pixels coarsen: the refinement's corner noise
#: on rendered captures of the demo's layout, 0.045 px at 1280 px wide, 0.054 at 800 (`data/ur5e_sweeps`)
#: and 0.056-0.061 at 640, follows $\sigma = 0.045\,(1280 / w)^{0.37}$ (`sigma_for`).
SIGMA_PX_WIDTH, SIGMA_PX_EXPONENT = 1280, 0.37


def sigma_for(width: int, sigma_px: float | None = None) -> float:
    """The corner noise a plan is evaluated at: `sigma_px` where given, else the rendered
    captures' at an image `width` px wide (`DEFAULT_SIGMA_PX` at 1280)."""
    if sigma_px is not None:
        return float(sigma_px)
    return DEFAULT_SIGMA_PX * (SIGMA_PX_WIDTH / width) ** SIGMA_PX_EXPONENT


@dataclass(frozen=True, eq=False)
class TermInputs:
    """The non-geometric terms a prediction counts (`jaxcal._terms`): the families `terms`,
    the links' `masses` and centres of mass `coms` of the basis, and every frame's approach
    flank `approach` `(V, joints)` along the plan's motion."""

    terms: tuple[str, ...]
    masses: np.ndarray
    coms: np.ndarray
    approach: np.ndarray


@eqx.filter_jit
def term_columns(
    scene: PlanScene, q: Float[Array, "V joints"], approach, masses, coms, terms: tuple[str, ...], angle=None
) -> Float[Array, "rows k"]:
    """The terms' columns of the refinement's Jacobian at frames `q`: each frame's corner
    motion per radian of joint $j$ ($P_v$; `angle` `(rows, joints)`, the refinement Jacobian's
    zero-offset columns, when at hand) times the basis of every coefficient of $j$ (rows in
    `(V, N, 2)` order, coefficients in `jaxcal._terms.names` order)."""
    basis = term_basis(terms, scene.nominal, q, masses, coms, approach)  # (V, joints, m)
    joint, col = column_map(terms, scene.nominal.num_joints)
    V = q.shape[0]
    if angle is None:
        angle = jnp.moveaxis(pixel_jacobians(scene, q), -1, 0).reshape(q.shape[1], -1).T  # (rows, joints)
    per_row = jnp.repeat(basis[:, joint, col], angle.shape[0] // V, axis=0)  # (rows, k)
    return angle[:, joint] * per_row


@eqx.filter_jit
def basis_rms(q, approach, masses, coms, nominal, terms: tuple[str, ...]):
    """Each coefficient's basis RMS over the frames `q` (`jaxcal._terms.names` order)."""
    basis = term_basis(terms, nominal, q, masses, coms, approach)
    joint, col = column_map(terms, nominal.num_joints)
    return jnp.sqrt(jnp.mean(basis[:, joint, col] ** 2, axis=0))


@dataclass(frozen=True)
class Design:
    """What the refinement will do with a plan: its capture kind, the candidate
    mask over the flattened `RefineParams` and the identifiability threshold."""

    kind: CaptureKind
    layout: ParameterLayout
    candidates: np.ndarray
    tol: float


def design(scene: PlanScene, sweeps: bool) -> Design:
    """The refinement's set-up for a plan of single-joint sweeps (`sweeps`) or of
    poses / free motion, with an encoder log and known intrinsics (as
    `jaxcal simulate` writes): rates free; the clock offset free with sweeps
    (it is estimated from the arcs), held for poses."""
    segments = (("j", 0.0, 1.0),) if sweeps else ((None, 0.0, 1.0),)
    kind = CaptureKind.of(
        camera_on_flange=scene.eye_in_hand, segments=segments, encoders=True, link_targets=False
    )
    lay = ParameterLayout.of(scene.nominal, 1, eye_in_hand=scene.eye_in_hand)
    cand = lay.candidates(rates=True, clock=kind.single_joint_sweeps, intrinsics=False)
    return Design(kind, lay, cand, kind.identifiability_tol)


@eqx.filter_jit
def corner_problem(
    scene: PlanScene,
    q: Float[Array, "V joints"],
    t: Float[Array, " V"],
    visible: Bool[Array, "V N"] | None = None,
) -> RefineProblem:
    """The refinement's problem for frames at commanded configurations `q` taken at
    controller times `t` (strictly increasing): every corner predicted at the
    nominal robot (so the residuals are zero), `visible` corners only (default all).
    Pure in `q`: the encoder log is the frames' configurations themselves."""
    V, N = q.shape[0], scene.points.shape[0]
    pixels = jax.vmap(lambda qq: frame_geometry(scene, qq).pixels)(q)
    data = CornerData(
        points=jnp.broadcast_to(scene.points, (V, N, 3)),
        pixels=pixels,
        mask=jnp.ones((V, N), bool) if visible is None else jnp.asarray(visible),
        target=jnp.zeros(V, int),
        frame=jnp.arange(V),
        t_cam=t,
        enc_t=t,
        enc_q=q,
        drift_ppm=jnp.zeros(()),
    )
    return RefineProblem(
        nominal=scene.nominal,
        T_flange_marker0=scene.T_mount[None],
        T_cam_base0=scene.T_fixed,
        K0=scene.K,
        dist0=scene.dist,
        offset0_s=jnp.zeros(()),
        data=data,
        eye_in_hand=scene.eye_in_hand,
    )


@eqx.filter_jit
def free_jacobian(problem: RefineProblem, free_idx: np.ndarray) -> Float[Array, "rows f"]:
    """$\\partial r / \\partial x_{free}$ of the refinement's residuals at the nominal robot."""
    flat, unravel = ravel_pytree(zero_params(problem.nominal.num_joints, 1))
    return jax.jacfwd(
        lambda x: reprojection_residuals(unravel(flat.at[free_idx].set(x)), problem).reshape(-1)
    )(flat[free_idx])


@eqx.filter_jit
def ee_jacobians(scene: PlanScene, configs: Float[Array, "C joints"]) -> Float[Array, "C 3 n"]:
    """$G_c = \\partial p_c / \\partial x$ of the end-effector point at every workspace
    configuration, over the axis-fit prefix of the layout (camera, origins, zero
    offsets, mount): the other groups do not move the point."""
    p0 = zero_params(scene.nominal.num_joints, 1)
    flat, unravel = ravel_pytree((p0.cam, p0.correction))

    def points(x):
        cam, corr = unravel(x)
        return tool_points(scene.nominal, scene.T_fixed, scene.T_mount[None], cam, corr, configs)

    return jax.jacfwd(points)(flat)


def ee_gram(G: Float[Array, "C 3 n"], free_idx: np.ndarray, size: int) -> Float[Array, "f f"]:
    """$M = \\frac1C \\sum_c G_c^T G_c$ restricted to the free parameters (zero rows
    for groups beyond the axis-fit prefix)."""
    n = G.shape[-1]
    full = jnp.zeros((size, size)).at[:n, :n].set(jnp.einsum("cia,cib->ab", G, G) / G.shape[0])
    return full[np.ix_(free_idx, free_idx)]


def ee_mean_square(
    J: Float[Array, "rows f"], M: Float[Array, "f f"], sigma_px: float, ridge: float = 1e-9
) -> Float[Array, ""]:
    """Predicted mean-square EE error $\\sigma^2 \\mathrm{tr}((J^TJ)^{-1} M)$ (m^2), by
    Cholesky of the Jacobi-scaled information (a relative `ridge` keeps it finite
    on a degenerate plan)."""
    F = J.T @ J
    d = jnp.sqrt(jnp.maximum(jnp.diag(F), 1e-300))
    Fs = F / d[:, None] / d[None, :] + ridge * jnp.eye(F.shape[0])
    Ms = M / d[:, None] / d[None, :]
    L = jnp.linalg.cholesky(Fs)
    X = jax.scipy.linalg.cho_solve((L, True), Ms)
    return sigma_px**2 * jnp.trace(X)


@dataclass(frozen=True, eq=False)
class PlanEvaluation:
    """The pre-evaluation of a plan (NumPy arrays).

    - `names`: the flattened `RefineParams` names; `candidates`, `free`: what the
      refinement would estimate and what the plan lets it identify; `std`: the
      predicted 1-sigma of every free parameter (zero where held).
    - `ee_sigma`: per workspace configuration the predicted 1-sigma EE position
      error (m); `ee_rms`, `ee_p95` (m) over them.
    - `held_effect`: per held candidate, the EE RMS (m) its prior deviation
      (`PRIOR`) leaves after the free parameters absorb what they can: zero for
      a redundant parameter (a reparametrisation of the others), not for one
      the plan fails to identify.
    - `ratio_interval`: the 5 % and 95 % quantiles of one capture's measured EE
      RMS over `ee_rms` under the Gaussian model: the mean-square EE error is
      $\\delta^T M \\delta = \\sum_i \\lambda_i z_i^2$ with $\\delta \\sim N(0, \\Sigma)$,
      $\\lambda = \\mathrm{eig}(\\Sigma^{1/2} M \\Sigma^{1/2})$; `effective_dof`
      $= (\\sum \\lambda)^2 / \\sum \\lambda^2$: with few, one capture's figure
      scatters widely about the prediction. `error_eigenvalues`: that $\\lambda$
      (m^2); `ratio_percentile`, `outside_probability` and
      `best_band_probability` read the same distribution: where one capture's
      measured/predicted ratio falls in it, how often a capture lands outside a
      band of ratios when the model is exact, and the most any rescaled
      prediction could keep inside that band.
    - `sigma_px`: the pixel noise assumed; `frames`, `corners`: what was used.
    - `singular_values`: of the column-normalised information (free parameters).
    - With a camera or arm model (`jaxcal.evaluate_plan(..., camera_model=, arm=)`,
      `jaxcal.planning._realism`): `camera_model`, `arm_model` (their names);
      `added_sigma_px` (in `sigma_px` already); `camera_note` (what the camera's
      exposure and shutter do to the frames); `frames_lost_to_blur`; `ee_bias`:
      per workspace configuration the norm of the EE bias the arm leaves (m; the
      noise part `ee_sigma` includes the encoders' quantisation); `bias_parts`:
      the bias RMS of each cause (m). `ee_bias_rms`, `ee_total_rms` and
      `ee_total_p95` read them.
    - With non-geometric terms (`evaluate_views(..., terms=)`): `terms`, the families
      the refinement fits beside the geometry (the noise part and `ee_bias` are what
      is left with them); `term_std`: each candidate coefficient's predicted 1-sigma (one
      whose basis does not vary over the frames is none, as in the refinement); and
      `ee_bias_rigid`, `bias_parts_rigid`: the arm's bias without them.
    """

    names: tuple[str, ...]
    candidates: np.ndarray
    free: np.ndarray
    std: np.ndarray
    ee_sigma: np.ndarray
    ee_rms: float
    ee_p95: float
    held_effect: dict
    sigma_px: float
    frames: int
    corners: int
    singular_values: np.ndarray
    ratio_interval: tuple[float, float] = (np.nan, np.nan)
    effective_dof: float = np.nan
    error_eigenvalues: np.ndarray = field(default_factory=lambda: np.zeros(0))
    camera_model: str | None = None
    arm_model: str | None = None
    added_sigma_px: float = 0.0
    camera_note: str = ""
    frames_lost_to_blur: int = 0
    ee_bias: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias_parts: dict = field(default_factory=dict)
    terms: tuple[str, ...] = ()
    term_std: dict | None = None
    #: The candidate coefficients the frames do not pin (`jaxcal._terms.TERM_STD_RAD`): held at
    #: zero, as the calibration will hold them.
    terms_unpinned: tuple[str, ...] = ()
    ee_bias_rigid: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bias_parts_rigid: dict = field(default_factory=dict)
    #: A plan's frames that fail its feasibility checks on this robot and scene (left out, as the
    #: detector would miss them), and why the first fails (`jaxcal.planning.evaluate_plan`).
    frames_infeasible: int = 0
    infeasible_note: str = ""

    @property
    def ee_bias_rms(self) -> float:
        """The RMS over the workspace of the EE bias the arm leaves (m; 0 without an arm model)."""
        return float(np.sqrt(np.mean(self.ee_bias**2))) if self.ee_bias.size else 0.0

    @property
    def ee_bias_rigid_rms(self) -> float:
        """The arm's EE bias RMS without the non-geometric terms (m; 0 without terms or an arm)."""
        return float(np.sqrt(np.mean(self.ee_bias_rigid**2))) if self.ee_bias_rigid.size else 0.0

    def total_interval(self, probability: float = 0.9) -> tuple[float, float]:
        """The central `probability` interval of one capture's EE RMS, noise and bias (m): the noise
        part's draws (`ratio_percentile`'s model) with the bias added in quadrature."""
        r = np.sqrt((self._ratio_draws() * self.ee_rms) ** 2 + self.ee_bias_rms**2)
        lo, hi = np.quantile(r, [0.5 - probability / 2, 0.5 + probability / 2])
        return float(lo), float(hi)

    @property
    def ee_total(self) -> np.ndarray:
        """Per workspace configuration the RMS EE error over captures, noise and bias (m):
        $\\sqrt{\\sigma_c^2 + |b_c|^2}$."""
        bias = self.ee_bias if self.ee_bias.size else np.zeros_like(self.ee_sigma)
        return np.sqrt(self.ee_sigma**2 + bias**2)

    @property
    def ee_total_rms(self) -> float:
        """The EE RMS over the workspace and over captures, noise and bias together (m)."""
        return float(np.sqrt(self.ee_rms**2 + self.ee_bias_rms**2))

    @property
    def ee_total_p95(self) -> float:
        """The 95th percentile over the workspace of `ee_total` (m)."""
        return float(np.percentile(self.ee_total, 95))

    def _ratio_draws(self) -> np.ndarray:
        """Draws of one capture's EE RMS over `ee_rms` under the Gaussian model
        (`RATIO_DRAWS`, seed 0: the same draws every call)."""
        lam = np.maximum(np.asarray(self.error_eigenvalues, np.float64), 0.0)
        if lam.size == 0 or lam.sum() <= 0:
            raise ValueError("this evaluation has no error distribution (nothing identifiable)")
        z = np.random.default_rng(0).standard_normal((RATIO_DRAWS, lam.size))
        return np.sqrt((z**2 @ lam) / lam.sum())

    def ratio_percentile(self, measured_rms: float) -> float:
        """The probability that one capture's EE RMS comes out at most `measured_rms`
        (m) when the prediction's model is exact: uniform over captures for an
        honest prediction; near 0 or 1, a capture the model does not explain."""
        return float(np.mean(self._ratio_draws() <= measured_rms / self.ee_rms))

    def ratio_quantile(self, probability: float) -> float:
        """One capture's EE RMS over `ee_rms` at `probability` (0.5: the median capture)."""
        return float(np.quantile(self._ratio_draws(), probability))

    def outside_probability(self, lo: float = 0.6, hi: float = 1.5) -> float:
        """The probability that one capture's measured/predicted EE RMS falls outside
        `[lo, hi]` when the prediction's model is exact."""
        r = self._ratio_draws()
        return float(np.mean((r < lo) | (r > hi)))

    def best_band_probability(self, lo: float = 0.6, hi: float = 1.5) -> tuple[float, float]:
        """The most probability any point prediction can put inside `[lo, hi]`.

        Returns `(probability, scale)`: with the model exact, the prediction
        `scale * ee_rms` has one capture's measured/predicted ratio inside
        `[lo, hi]` with `probability`, and no other scale does better. It bounds
        what a band criterion can ask of single captures of this design,
        whatever the predictor: one capture's own scatter leaves the rest outside.
        """
        r = np.sort(self._ratio_draws())
        inside = np.searchsorted(r, (hi / lo) * r, side="right") - np.arange(r.size)
        best = int(np.argmax(inside))
        return float(inside[best] / r.size), float(r[best] / lo)

    @property
    def held(self) -> list[str]:
        """Candidates the refinement would hold at nominal (dependent on others for this plan)."""
        return [n for n, c, f in zip(self.names, self.candidates, self.free) if c and not f]

    @property
    def unidentifiable(self) -> list[str]:
        """Held candidates that matter: their prior deviation moves the end effector by more
        than `MATTERS` after the free parameters absorb what they can."""
        return [n for n, e in self.held_effect.items() if e > MATTERS]

    @property
    def ee_rms_with_held(self) -> float:
        """The predicted EE RMS with the held parameters' prior effect added in quadrature (m)."""
        return float(np.sqrt(self.ee_rms**2 + sum(e**2 for e in self.held_effect.values())))

    def summary(self) -> dict:
        """Plain-Python figures (mm)."""
        spread = bool(self.error_eigenvalues.size) and np.isfinite(self.ee_rms)
        out = {
            "ee_rms_mm": 1e3 * float(self.ee_rms),
            "ee_p95_mm": 1e3 * float(self.ee_p95),
            "sigma_px": self.sigma_px,
            "frames": self.frames,
            "corners": self.corners,
            "free_parameters": int(self.free.sum()),
            "held_redundant": [n for n in self.held if n not in self.unidentifiable],
            "unidentifiable": self.unidentifiable,
            "ee_rms_mm_with_held": 1e3 * self.ee_rms_with_held,
            "ratio_interval_90": list(self.ratio_interval),
            "effective_dof": self.effective_dof,
            "outside_0.6_1.5_probability": self.outside_probability() if spread else None,
            # One capture's EE RMS: its median and 90 % interval under the same model.
            "one_capture_ee_rms_mm_median": 1e3 * self.ee_rms * self.ratio_quantile(0.5) if spread else None,
            "one_capture_ee_rms_mm_90": [1e3 * self.ee_rms * r for r in self.ratio_interval]
            if spread
            else None,
        }
        if self.frames_infeasible:
            out |= {"frames_infeasible": self.frames_infeasible, "infeasible_note": self.infeasible_note}
        if self.camera_model is not None or self.arm_model is not None:
            out |= {
                "camera_model": self.camera_model,
                "arm_model": self.arm_model,
                "added_sigma_px": self.added_sigma_px,
                "camera_note": self.camera_note,
                "frames_lost_to_blur": self.frames_lost_to_blur,
                # The EE error over the workspace: noise (ee_rms_mm), the arm's bias, both (RMS over captures).
                "ee_noise_rms_mm": 1e3 * float(self.ee_rms),
                "ee_bias_rms_mm": 1e3 * self.ee_bias_rms,
                "ee_bias_parts_mm": {k: 1e3 * v for k, v in self.bias_parts.items()},
                "ee_total_rms_mm": 1e3 * self.ee_total_rms,
                "ee_total_p95_mm": 1e3 * self.ee_total_p95,
                # One capture's EE RMS, noise and bias: its 90 % interval (the noise part's spread, the bias fixed).
                "one_capture_total_ee_rms_mm_90": [1e3 * v for v in self.total_interval()]
                if spread
                else None,
            }
        if self.terms:
            out |= {
                "terms": list(self.terms),
                "term_std": dict(self.term_std or {}),
                "terms_unpinned": list(self.terms_unpinned),
                "ee_bias_rms_mm_without_terms": 1e3 * self.ee_bias_rigid_rms,
                "ee_bias_parts_mm_without_terms": {k: 1e3 * v for k, v in self.bias_parts_rigid.items()},
            }
        return out


def prior_scales(layout: ParameterLayout) -> np.ndarray:
    """How far each parameter may sit from nominal before calibration (1 sigma, SI
    units): the perturbations `jaxcal simulate` draws (joint origins 1 mm and
    0.2 deg, zero offsets 0.5 deg, mounts and the camera 2 mm and 1 deg, ratios
    1 %); used only to weigh what held parameters leave behind."""
    out = np.zeros(layout.size)
    pose = lambda mm, deg: np.r_[np.full(3, 1e-3 * mm), np.full(3, np.radians(deg))]  # noqa: E731
    out[layout.index("cam")] = pose(2.0, 1.0)
    out[layout.index("origin")] = np.tile(pose(1.0, 0.2), len(layout.joints))
    out[layout.index("zero")] = np.radians(0.5)
    out[layout.index("tool")] = np.tile(pose(2.0, 1.0), layout.num_markers)
    out[layout.index("rate")] = 0.01
    out[layout.index("clock")] = 1.0
    return out


#: Draws of the Gaussian model behind `PlanEvaluation.ratio_percentile` and
#: `outside_probability` (their Monte Carlo error: about 0.003).
RATIO_DRAWS = 20_000

#: A held parameter whose prior deviation moves the end effector by more than this (m RMS) matters.
MATTERS = 1e-6


def evaluate_views(
    scene: PlanScene,
    q: np.ndarray,
    t: np.ndarray,
    configs: np.ndarray,
    *,
    sweeps: bool,
    sigma_px: float = DEFAULT_SIGMA_PX,
    visible: np.ndarray | None = None,
    offsets=(),
    joint_std: np.ndarray | None = None,
    terms: TermInputs | None = None,
) -> PlanEvaluation:
    """Pre-evaluate frames at commanded configurations `q (V, joints)`, controller
    times `t (V,)` (increasing), over the workspace `configs (C, joints)`.

    **Arguments:** the scene; the frames; the workspace sample; `sweeps`: the
    refinement of single-joint sweeps (else of poses); `sigma_px`: the corner
    noise (px per coordinate); `visible (V, N)`: the corners detected (default all);
    `offsets`: `(name, (V, joints))` pairs, where the joints stand against what the
    encoders read (rad: an arm's sag, backlash), whose EE bias is predicted
    (`jaxcal.planning._realism.propagate`); `joint_std (joints,)`: the readings'
    own noise (rad), added to the noise part; `terms`: non-geometric terms the
    refinement fits beside the geometry (the module docstring): the noise part and
    the bias are then those left with them, the bias without them beside.

    **Returns:** a `PlanEvaluation`.
    """
    d = design(scene, sweeps)
    vis = None if visible is None else jnp.asarray(visible)
    names = tuple(d.layout.names())
    cand_idx = np.flatnonzero(d.candidates)
    frames = (
        jnp.asarray(q),
        jnp.asarray(t),
        vis,
        jnp.asarray(d.candidates),
        cand_idx,
        jnp.asarray(configs),
        d.tol,
    )
    free, J, G, corners = (np.asarray(a) for a in _evaluation_terms(scene, *frames))
    in_free = free[cand_idx]
    corners = int(corners)
    n = len(names)
    std = np.zeros(n)
    Gc = np.zeros((len(configs), 3, cand_idx.size))  # the EE Jacobian over the candidates
    axis = cand_idx < G.shape[-1]
    Gc[:, :, axis] = G[:, :, cand_idx[axis]]
    Jf, Gf = J[:, in_free], Gc[:, :, in_free]
    if not in_free.any():
        return _nothing_free(names, d.candidates, free, len(configs), sigma_px, len(q), corners)
    pinv, sv = least_squares_map(Jf)
    rigid, with_terms = pinv, None
    mask = np.ones((len(q), scene.points.shape[0]), bool) if visible is None else np.asarray(visible, bool)
    if terms is not None:
        pinv, sv, with_terms = _with_terms(scene, q, terms, mask, Jf, sigma_px)
    cov_f = sigma_px**2 * (pinv @ pinv.T)
    parts, bias, parts_rigid, bias_rigid = {}, np.zeros(0), {}, np.zeros(0)
    if len(offsets) or joint_std is not None:
        P = np.asarray(pixel_jacobians(scene, jnp.asarray(q)))
        parts, b, cov_q = propagate(pinv, Gf, P, mask, offsets, joint_std)
        cov_f = cov_f + cov_q
        bias = np.linalg.norm(b, axis=-1) if len(offsets) else bias
        if terms is not None and len(offsets):
            parts_rigid, b_rigid, _ = propagate(rigid, Gf, P, mask, offsets, None)
            bias_rigid = np.linalg.norm(b_rigid, axis=-1)
    std[np.flatnonzero(free)] = np.sqrt(np.maximum(np.diag(cov_f), 0.0))
    ee = np.sqrt(np.maximum(np.einsum("cia,ab,cib->c", Gf, cov_f, Gf), 0.0))
    interval, dof, lam = ratio_spread(cov_f, np.einsum("cia,cib->ab", Gf, Gf) / len(configs))
    prior = prior_scales(d.layout)
    held = {}
    for k in np.flatnonzero(~in_free):
        delta = -pinv @ J[:, k]  # the free parameters absorbing a unit of parameter k
        e = Gc[:, :, k] + Gf @ delta
        held[names[cand_idx[k]]] = float(prior[cand_idx[k]] * np.sqrt(np.mean(np.sum(e**2, axis=-1))))
    return PlanEvaluation(
        names=names,
        candidates=d.candidates,
        free=free,
        std=std,
        ee_sigma=ee,
        ee_rms=float(np.sqrt(np.mean(ee**2))),
        ee_p95=float(np.percentile(ee, 95)),
        held_effect=held,
        sigma_px=float(sigma_px),
        frames=int(len(q)),
        corners=corners,
        singular_values=sv,
        ratio_interval=interval,
        effective_dof=dof,
        error_eigenvalues=lam,
        ee_bias=bias,
        bias_parts=parts,
        terms=() if with_terms is None else with_terms[0],
        term_std=None if with_terms is None else with_terms[1],
        terms_unpinned=() if with_terms is None else with_terms[2],
        ee_bias_rigid=bias_rigid,
        bias_parts_rigid=parts_rigid,
    )


def _nothing_free(names, candidates, free, configs: int, sigma_px: float, frames: int, corners: int):
    """The evaluation of frames that determine no parameter: every EE sigma infinite."""
    n = len(names)
    ee = np.full(configs, np.inf)
    return PlanEvaluation(
        names,
        candidates,
        free,
        np.zeros(n),
        ee,
        np.inf,
        np.inf,
        {},
        float(sigma_px),
        frames,
        corners,
        np.zeros(0),
    )


def _with_terms(scene: PlanScene, q, terms: TermInputs, mask, Jf, sigma_px: float):
    """The free parameters' least-squares map with the terms' coefficients fitted beside
    them, its singular values, and the terms with their coefficients' standard deviations."""
    frames = (jnp.asarray(q), jnp.asarray(terms.approach), jnp.asarray(terms.masses), jnp.asarray(terms.coms))
    T = np.asarray(term_columns(scene, *frames, tuple(terms.terms))) * np.repeat(mask.reshape(-1), 2)[:, None]
    # As the calibrations: a coefficient whose basis does not vary over the frames is no candidate,
    # and one the frames do not pin (`TERM_STD_RAD`) is held at zero.
    rms = np.asarray(basis_rms(*frames, scene.nominal, tuple(terms.terms)))
    free = rms >= BASIS_FLOOR
    while True:  # until every coefficient left is pinned (the set only shrinks)
        aug, sv = least_squares_map(np.concatenate([Jf, T[:, free]], axis=1))
        std = sigma_px * np.linalg.norm(aug[Jf.shape[1] :], axis=1)
        loose = np.flatnonzero(free)[std * rms[free] > TERM_STD_RAD]
        if not loose.size:
            break
        free[loose] = False
    names_t = np.array(term_names(terms.terms, names_of(scene)))
    unpinned = tuple(str(n) for n in names_t[(rms >= BASIS_FLOOR) & ~free])
    term_std = {str(n): float(v) for n, v in zip(names_t[free], std, strict=True)}
    return aug[: Jf.shape[1]], sv, (tuple(terms.terms), term_std, unpinned)


def names_of(scene: PlanScene) -> tuple[str, ...]:
    return tuple(scene.nominal.joint_names)


def least_squares_map(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(pinv (f, rows), singular values)`: the least-squares map of the columns of `J`
    (Jacobi-scaled SVD, directions below 1e-12 of the largest dropped)."""
    scale = np.linalg.norm(J, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    U, sv, Vt = np.linalg.svd(J / scale, full_matrices=False)
    keep = sv > 1e-12 * sv[0]
    return (Vt[keep].T / sv[keep]) @ U[:, keep].T / scale[:, None], sv


def ratio_spread(
    cov: np.ndarray, M: np.ndarray, draws: int = 20000
) -> tuple[tuple[float, float], float, np.ndarray]:
    """The 90 % interval of one capture's EE RMS over its prediction, the
    effective number of independent error directions, and the eigenvalues
    $\\lambda$ of the mean-square EE error (see `PlanEvaluation`)."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    half = V * np.sqrt(np.maximum(w, 0.0))
    lam = np.maximum(np.linalg.eigvalsh(half.T @ M @ half), 0.0)
    if lam.sum() <= 0:
        return (np.nan, np.nan), np.nan, lam
    z = np.random.default_rng(0).standard_normal((draws, lam.size))
    r = np.sqrt((z**2 @ lam) / lam.sum())
    lo, hi = np.percentile(r, [5.0, 95.0])
    return (float(lo), float(hi)), float(lam.sum() ** 2 / np.sum(lam**2)), lam


def _terms(scene, q, t, visible, candidates, cand_idx, configs, tol):
    """The identifiable parameters, the refinement's Jacobian over the candidates, the EE
    Jacobians and the number of corners of frames `q`, `t`: `evaluate_views`' JAX part."""
    problem = corner_problem(scene, q, t, visible)
    free, _ = identifiable_mask(problem, zero_params(scene.nominal.num_joints, 1), candidates, tol=tol)
    return free, free_jacobian(problem, cand_idx), ee_jacobians(scene, configs), jnp.sum(problem.data.mask)


# One stored program (`jaxcal._exported`): a second `jaxcal plan --evaluate` neither traces nor compiles
# it. With XLA's optimisations: its Jacobians over every corner run about 3x faster so.
_evaluation_terms = stored_jit(_terms, "plan_evaluation", compiler_options=None)
