"""`jaxcal plan --check RESULT --budget N`: the few poses that make a camera drift check most sensitive.

The check (`jaxcal.drift`, `jaxcal._drift_camera`) fits the camera's twist
$\\theta$ with the calibration's error $x = \\hat x + L z$ ($\\kappa \\Sigma = L L^T$, $z \\sim
N(0, I)$, $\\kappa$ as the check takes it) a nuisance. Per view $v$ of a candidate pose, with $A_v = \\partial r_v /
\\partial\\theta$ and $G_v = \\partial r_v / \\partial x \\, L$ (px), the information on
$\\theta$ of a set $S$ of views is the Schur complement

$$ I_S = \\frac{1}{\\sigma^2}\\Big(\\sum_S A_v^T A_v - \\big(\\sum_S A_v^T G_v\\big)
   \\big(\\sigma^2 I + \\sum_S G_v^T G_v\\big)^{-1} \\big(\\sum_S G_v^T A_v\\big)\\Big), $$

additive sums, so a greedy selection costs one small solve per candidate and
step. The criterion is the check's detectable translation along its worst
direction, $\\sqrt{\\lambda^* / \\mu_{min}(I_S[:3, :3])}$ (`jaxcal.drift.detectable`):
each step adds the candidate that lowers it most (E-optimal on the
translation block; ties by D-optimality). Candidates: configurations drawn
uniformly in the calibration dataset's joint ranges (its encoder log) where
the calibrated model puts every corner of the target in the image (a
margin), in front of the camera and facing it within `VIEW_ANGLE_DEG`.
"""

from dataclasses import asdict, astuple, dataclass

import numpy as np

from .._drift_camera import camera_reference, view_jacobians
from .._lsq import normal_inverse
from .._reprojection import make_corner_data
from ..certification import read_result
from ..drift import detectable, result_intrinsics
from ..errors import DatasetError, PlanError
from ..io._files import write_text_atomic
from ..io.checks import calibration_reference
from ..io.dataset import load_dataset
from ..io.result import ESTIMATE_FILE, read_estimate

#: The plate's largest angle to the line of sight (deg), and the image margin (px).
VIEW_ANGLE_DEG, MARGIN_PX = 60.0, 10.0


@dataclass(frozen=True)
class CheckFigures:
    """What a check's poses let it detect (`detectable(C)`, 95 % power): the
    camera's translation (mm) along its worst and best directions and its
    rotation (deg) along the worst."""

    translation_mm_worst: float
    rotation_deg_worst: float
    translation_mm_best: float


@dataclass(frozen=True, eq=False)
class CheckPlan:
    """The poses proposed for a drift check and what they allow.

    - `q` `(budget, joints)` (rad, the encoder log's commanded positions), in the order chosen;
    - `steps`: per pose added, `detectable(C)` of the poses so far (mm, deg);
    - `random`: the same figures of `budget` random visible candidates (median of 20 draws);
    - `candidates`, `visible`: drawn and kept; `sigma_px`: the corner noise assumed.
    """

    result: str
    joint_names: tuple[str, ...]
    q: np.ndarray
    steps: tuple[CheckFigures, ...]
    random: CheckFigures
    candidates: int
    visible: int
    sigma_px: float

    def to_json(self) -> dict:
        return {
            "schema": "jaxcal.check_plan",
            "schema_version": 1,
            "result": self.result,
            "joint_names": list(self.joint_names),
            "q_rad": self.q.tolist(),
            "steps": [asdict(s) for s in self.steps],
            "random": asdict(self.random),
            "candidates": self.candidates,
            "visible": self.visible,
            "sigma_px": self.sigma_px,
        }


def _inputs(result):
    doc, file = read_result(result)
    if "point_fit" in doc or "T_device_base" in doc:
        raise PlanError(f"{file}: jaxcal plan --check plans camera checks; this is a tracker result")
    path = file.parent / ESTIMATE_FILE
    if not path.is_file():
        raise DatasetError(
            f"{path}: missing: plan --check needs the calibration's covariance (calibrate again)"
        )
    est = read_estimate(path)
    ref = calibration_reference(doc, file)
    try:
        if ref.dataset is None:
            raise KeyError("dataset")
        ds = load_dataset(ref.dataset)
    except (DatasetError, OSError, KeyError) as e:
        raise DatasetError(
            f"{file}: plan --check reads the calibration's dataset (camera, target): {e}"
        ) from None
    if ds.encoder_t is None:
        raise DatasetError(f"{ds.root}: plan --check needs the calibration's encoder log (its joint ranges)")
    name = ref.board if est.layout.eye_in_hand else ref.targets[0]
    target = next(t for t in ds.targets if t.name == name)
    return doc, ref, est, ds, ds.camera(ref.camera), target


def _candidates(doc, calibration, est, ds, camera, target, count: int, seed: int):
    """Candidate configurations and, for the visible ones, their per-view `(A, G)` and the problem."""
    q_log = np.asarray(ds.encoder_motor, np.float64) / np.asarray(est.nominal.reduction_ratio)
    lo, hi = q_log.min(0), q_log.max(0)
    q = lo + (hi - lo) * np.random.default_rng(seed).uniform(size=(count, len(lo)))
    pts = np.asarray(target.spec.points(), np.float64)
    t = np.arange(count, dtype=np.float64)
    data = make_corner_data(
        [pts] * count, [np.zeros((len(pts), 2))] * count, np.zeros(count, int), np.arange(count), t, t, q
    )
    _, _, K0, dist0 = result_intrinsics(doc)
    if calibration.sigma_px is None:
        raise DatasetError(
            f"{calibration.file}: plan --check needs the refinement's sigma_px (calibrate again)"
        )
    sigma = calibration.sigma_px
    ref = camera_reference(est, data, K0, dist0, 0.0, sigma, count * len(pts))
    pix, X, A, J = (np.asarray(a) for a in view_jacobians(ref.x, ref.problem))
    inside = (
        (pix[..., 0] > MARGIN_PX)
        & (pix[..., 0] < camera.width - MARGIN_PX)
        & (pix[..., 1] > MARGIN_PX)
        & (pix[..., 1] < camera.height - MARGIN_PX)
        & (X[..., 2] > 0.05)
    ).all(1)
    return q, inside & _facing(X), A, J, ref


def _facing(X: np.ndarray) -> np.ndarray:
    """Per view, whether the plate (its corners `X` `(V, P, 3)`, camera frame) faces the
    camera within `VIEW_ANGLE_DEG`: its plane's normal against the line of sight."""
    centre = X.mean(1, keepdims=True)
    normal = np.linalg.svd(X - centre)[2][:, -1]  # (V, 3)
    sight = centre[:, 0] / np.linalg.norm(centre[:, 0], axis=1, keepdims=True)
    return np.abs(np.sum(normal * sight, axis=1)) > np.cos(np.radians(VIEW_ANGLE_DEG))


def plan_check(result, budget: int = 10, *, candidates: int = 400, seed: int = 0) -> CheckPlan:
    """Greedy selection of `budget` poses for a drift check of the camera result `result`
    (see the module docstring). Raises `PlanError` / `DatasetError` naming the file."""
    doc, calibration, est, ds, camera, target = _inputs(result)
    file = calibration.file
    q, inside, A, J, ref = _candidates(doc, calibration, est, ds, camera, target, candidates, seed)
    keep = np.flatnonzero(inside)
    if len(keep) < budget:
        raise PlanError(
            f"{file}: {len(keep)} of {candidates} random configurations of the calibrated joint ranges show the "
            f"whole target: too few for {budget} poses (draw more: --config candidates=N)"
        )
    # The calibration's covariance as the check uses it (kappa, see `jaxcal._drift_camera`).
    cov = ref.factor * np.asarray(est.cov, np.float64)[: J.shape[-1], : J.shape[-1]]
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    ok = lam > max(lam.max(), 0.0) * 1e-14
    L = V[:, ok] * np.sqrt(lam[ok])
    s2 = ref.sigma_px**2
    Ak, Gk = A[keep], J[keep] @ L  # (C, 2P, 6), (C, 2P, r)
    a = np.einsum("cmi,cmj->cij", Ak, Ak)
    b = np.einsum("cmi,cmj->cij", Ak, Gk)
    g = np.einsum("cmi,cmj->cij", Gk, Gk)
    r = g.shape[-1]

    def info(sa, sb, sg):
        return (sa - sb @ np.linalg.solve(s2 * np.eye(r) + sg, sb.T)) / s2

    def figures(idx) -> CheckFigures:
        d = detectable(normal_inverse(info(a[idx].sum(0), b[idx].sum(0), g[idx].sum(0))))
        return CheckFigures(d.translation_mm_worst, d.rotation_deg_worst, d.translation_mm_best)

    chosen, steps = [], []
    sa, sb, sg = np.zeros((6, 6)), np.zeros((6, r)), np.zeros((r, r))
    for _ in range(budget):
        best, score = None, None
        for c in range(len(keep)):
            if c in chosen:
                continue
            I = info(sa + a[c], sb + b[c], sg + g[c])
            mu = np.linalg.eigvalsh(I[:3, :3])[0]
            key = (mu, np.linalg.slogdet(I)[1])
            if score is None or key > score:
                best, score = c, key
        chosen.append(best)
        sa, sb, sg = sa + a[best], sb + b[best], sg + g[best]
        steps.append(figures(chosen))
    rng = np.random.default_rng(seed + 1)
    draws = [figures(rng.choice(len(keep), budget, replace=False)) for _ in range(20)]
    random = CheckFigures(*(float(np.median(column)) for column in zip(*(astuple(d) for d in draws))))
    return CheckPlan(
        result=str(file),
        joint_names=tuple(est.nominal.joint_names),
        q=q[keep[chosen]],
        steps=tuple(steps),
        random=random,
        candidates=candidates,
        visible=len(keep),
        sigma_px=ref.sigma_px,
    )


def write_poses(plan: CheckPlan, path) -> None:
    """The poses as a CSV: a header naming the joints, one row per pose (rad)."""
    rows = [",".join(plan.joint_names)] + [",".join(f"{v:.9g}" for v in p) for p in plan.q]
    write_text_atomic(path, "\n".join(rows) + "\n")
