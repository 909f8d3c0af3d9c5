"""Choosing a model by its error on data it was not fitted to: one rule for every such choice.

jaxcal chooses between models it can fit to the same data (the tracker's non-geometric terms,
`jaxcal.stages._points`; the hand-eye robot-noise model, `jaxcal.handeye`) by cross-validation:
each model is fitted without a fold of the samples and predicts them, and its held-out error is
compared with the current choice's, the models visited in a fixed order, the default first. A
model replaces the current choice only when (`improves_on_samples`)

- its held-out error is lower by more than `CV_GAIN` of the current one's (`improves`): a gain
  that small is no reason to change the model; and
- the gain per sample stands out from the spread of the paired per-sample differences, by at
  least `MIN_Z` standard errors (`paired_z`): a held-out mean over few samples moves with the
  samples it happens to hold.

On the tracker's 1000 points the second condition is moot (each term kept on the real UR5 lowers
the mean by 5-6 %; the same terms are kept with it, `docs/performance.md`); on a hand-eye
capture's 8-30 frames it is what keeps a model from being chosen by chance: on ViSP's 8-frame
capture exact robot poses predict the frames left out 15 % better than the estimated noise, by
1.1 standard errors, and land 3.4 deg from every other method's answer (`docs/handeye.md`).
"""

import numpy as np

#: A model replaces the current choice when it lowers the held-out error by more than this share.
CV_GAIN = 0.005
#: ... and, per sample (`improves_on_samples`), by at least this many standard errors of the paired
#: differences (about a 2 % chance of a change when the two models predict equally well).
MIN_Z = 2.0


def improves(candidate: float, current: float) -> bool:
    """Whether a held-out error `candidate` beats `current` by more than `CV_GAIN` of it."""
    return bool(candidate < (1.0 - CV_GAIN) * current)


def paired_z(current: np.ndarray, candidate: np.ndarray) -> float:
    """The mean per-sample gain `current - candidate` over its standard error ($\\bar d / (s_d/\\sqrt n)$);
    `inf` for a gain without spread, 0 for fewer than 2 samples or no gain."""
    d = np.asarray(current, float) - np.asarray(candidate, float)
    if d.size < 2 or not d.mean() > 0:
        return 0.0
    se = d.std(ddof=1) / np.sqrt(d.size)
    return float(d.mean() / se) if se > 0 else float("inf")


def improves_on_samples(
    current: np.ndarray, candidate: np.ndarray, current_error: float, candidate_error: float
) -> bool:
    """`improves(candidate_error, current_error)` with the gain per sample (`current`, `candidate`:
    each sample's held-out loss, paired) at least `MIN_Z` standard errors (`paired_z`)."""
    return improves(candidate_error, current_error) and paired_z(current, candidate) >= MIN_Z
