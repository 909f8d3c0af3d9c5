"""The orientations of a stop-and-shoot drift check (`jaxcal.drift`).

When the calibration fitted measured orientations and the capture has them, each
is compared with the calibrated prediction moved by the drift fitted to the
points, $\\hat R_i' = \\exp(-\\omega)\\, \\hat R_i \\exp(G^z_i\\, \\delta q)$ ($G^z_i$: how the
zero offsets turn the point's frame): the residual $r_i = \\log(\\hat R_i'^T R_i)$, in
the point's frame, is Gaussian with the covariance the calibration predicts,
$G^R_i \\Sigma G^{R\\,T}_i + \\hat\\sigma^2 \\sigma_{rad,i}^2 I_3$, so that its whitened sum
of squares is about $\\chi^2_{3S}$ (the drift is fitted on the points alone). It
joins the rigid-fit check (`records_check.DriftResidual.fits_rigidly`): a mount
turned on its link, or orientations of another frame, show there first.
"""

import numpy as np

from ._npgeom import rotvec_to_matrix, so3_log
from .records import ResidualStats


def orientation_residuals(
    R_hat: np.ndarray, Gz: np.ndarray, cov: np.ndarray, theta: np.ndarray, R: np.ndarray
) -> tuple[ResidualStats, float]:
    """The residuals of measured orientations `R` `(S, 3, 3)` against the predicted ones `R_hat`
    moved by the drift `theta` `(6[ + joints])` (the device's twist, then the zero offsets' change),
    with `Gz` `(S, 3, joints)` the offsets' turn of each prediction and `cov` `(S, 3, 3)` each
    residual's covariance. **Returns:** the residuals' angles (deg) and their whitened sum of squares."""
    offsets = theta[6:] if len(theta) > 6 else np.zeros(Gz.shape[2])
    R_now = rotvec_to_matrix(theta[3:6]).T @ R_hat @ rotvec_to_matrix(np.einsum("saj,j->sa", Gz, offsets))
    r = so3_log(np.einsum("sba,sbc->sac", R_now, R))
    angle = np.degrees(np.linalg.norm(r, axis=1))
    stats = ResidualStats(
        mean=float(angle.mean()), rms=float(np.sqrt(np.mean(angle**2))), max=float(angle.max())
    )
    return stats, float(np.einsum("sa,sa->", r, np.linalg.solve(cov, r[..., None])[..., 0]))
