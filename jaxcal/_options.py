"""The fits' options as objects.

Every public fit takes the solver's settings as `options: LMOptions`
(`jaxcal._lsq.LMOptions`: `rtol`, `atol`, `max_steps`) and, where it can
down-weight outliers, the loss as `robust: RobustOptions | None` (`None`: plain
least squares). Each fit's signature shows its own defaults (a fit on whitened
residuals stops at a coarser `atol` than one in metres).
"""

import equinox as eqx

from ._robust import check_loss


class RobustOptions(eqx.Module):
    """Iteratively reweighted least squares with a robust loss, then an inlier solve.

    `rounds` solves, each reweighting the samples by `loss` (`"cauchy"` or
    `"huber"`) of their residuals in robust standard deviations with constant `c`;
    then, with `reject` (a radius in robust sigmas; `None`: none), one solve on
    the samples within `reject` (weight 1, the others 0), whose Jacobian gives
    honest standard deviations. `reject = 3.7` drops a clean sample with
    probability $e^{-3.7^2/2} \\approx 10^{-3}$ (see `jaxcal._robust`).
    """

    loss: str = eqx.field(static=True, default="cauchy")
    c: float = 3.0
    reject: float | None = 3.7
    rounds: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if self.loss is None:
            raise ValueError(
                "RobustOptions: loss must be 'cauchy' or 'huber' (plain least squares: robust=None)"
            )
        check_loss(self.loss)
        if self.rounds < 1:
            raise ValueError(f"RobustOptions: rounds must be at least 1, got {self.rounds}")


def robust_terms(robust: RobustOptions | None) -> tuple:
    """`(loss, c, reject, rounds)` of `robust`; `None`: one plain least-squares round."""
    if robust is None:
        return None, 3.0, None, 1
    return robust.loss, robust.c, robust.reject, robust.rounds
