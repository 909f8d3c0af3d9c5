"""Classic hand-eye calibration, solved on image features (seed method 4) and by TCP touch (seed 5).

Two arrangements share one algebra. Per robot pose $f$ the board's pose in
camera $c$ is

$$T^{cam_c}_{board}(f) = X_c\\, B_f\\, Y,$$

- eye-to-hand (camera fixed, board on the end effector): $X_c = T_{cam\\_base}$,
  $B_f = T_{base\\_ee}(f)$, $Y = T_{ee\\_board}$;
- eye-in-hand (camera on the end effector, board fixed): $X_c = T_{cam\\_ee}$,
  $B_f = T_{base\\_ee}(f)^{-1}$, $Y = T_{base\\_board}$.

This is the robot-world-hand-eye form $A W = X B$ with $A = T^{cam}_{board}$
and $W = Y^{-1}$. Instead of pairing motions (Tsai-Lenz $AX = XB$), the
estimator keeps one unique transform per camera and one shared object
transform and minimises the difference between predicted and measured image
features directly (the reprojection error of every board corner), which is
the maximum-likelihood estimate under pixel noise. A pose-level variant
(measured $T^{cam}_{board}$ from PnP, as OpenCV's protocol gives) whitens the
pose error instead. Robot poses may be treated as noisy: with pixels, one
correction per pose with a Gaussian prior; with poses, the corrections are
marginalised (each frame's pose error whitened by $\\Sigma_A + J \\Sigma_r J^T$,
`model.pose_error_covariance`), so the solve keeps its 6 (cameras + 1) unknowns.

Modules, by role: `data` (measurements, `make_*`, `validate_hand_eye`), `checks`
(rotations, motion diversity), `model` (parameters and residuals), `closed`
(closed-form start), `solve` (`calibrate_hand_eye`, `HandEyeResult`), `touch`
(TCP touch), `common` (the pose error and the LM call), `consistency` (robot
against camera rotation angles, before solving), `noise` (the robot pose noise
estimated as a variance component), `assess` (k-fold spread and verdicts, after).

Pipeline (all pure, jittable and vmappable):
1. Closed-form start. Board poses from pixels by a planar homography (Zhang's
   decomposition); then rotations from the top eigenvector of
   $\\sum_c n_c S_c^T S_c$, $S_c$ the mean over frames of the $9\\times 9$
   matrices $R_{B_f} \\otimes R_{A_{cf}}$ (Shah's Kronecker method, extended
   to several cameras sharing $W$), and translations by linear least squares.
2. Robust Levenberg-Marquardt: a Cauchy loss per (camera, frame) group.
3. Outliers: groups whose whitened residual RMS exceeds `outlier_threshold`
   times the median are rejected and reported.
4. Plain Levenberg-Marquardt on the remaining groups (the ML estimate), and a
   covariance from the Jacobian.

Every pose is optimised as a 6-vector tangent delta about its start,
$X = X_0 \\exp(\\xi)$ with $\\xi = (v, w)$ (translation first, m and rad).
"""

from .._npgeom import rotation_angle as rotation_angle
from ..errors import DegenerateMotionError as DegenerateMotionError
from ..errors import HandEyeInputError as HandEyeInputError
from ..errors import InconsistentPosesError as InconsistentPosesError
from ..errors import IntrinsicsError as IntrinsicsError
from ..errors import LengthMismatchError as LengthMismatchError
from ..errors import NoiseLevelError as NoiseLevelError
from ..errors import NonFiniteError as NonFiniteError
from ..errors import NotARotationError as NotARotationError
from ..errors import NotPositiveDefiniteError as NotPositiveDefiniteError
from ..errors import ShapeError as ShapeError
from ..errors import TooFewPosesError as TooFewPosesError
from .assess import MAX_ROBOT_SIGMA_DEG as MAX_ROBOT_SIGMA_DEG
from .assess import MAX_ROBOT_SIGMA_M as MAX_ROBOT_SIGMA_M
from .assess import ROBOT_SIGMA_OPTIONS as ROBOT_SIGMA_OPTIONS
from .assess import HandEyeVerdict as HandEyeVerdict
from .assess import KFoldSpread as KFoldSpread
from .assess import assess_hand_eye as assess_hand_eye
from .assess import describe_robot_noise as describe_robot_noise
from .assess import fold_blocks as fold_blocks
from .assess import implausible_robot_noise as implausible_robot_noise
from .assess import kfold_spread as kfold_spread
from .assess import max_noise_level as max_noise_level
from .assess import noise_explains_fit as noise_explains_fit
from .assess import pose_difference as pose_difference
from .assess import robot_correction_rms as robot_correction_rms
from .assess import robot_noise as robot_noise
from .assess import std_ratio as std_ratio
from .checks import MIN_AXIS_SEPARATION_DEG as MIN_AXIS_SEPARATION_DEG
from .checks import MIN_POINTS_PER_VIEW as MIN_POINTS_PER_VIEW
from .checks import MIN_POSES as MIN_POSES
from .checks import MIN_ROTATION_DEG as MIN_ROTATION_DEG
from .checks import check_motion_diversity as check_motion_diversity
from .checks import check_rotations as check_rotations
from .closed import board_poses_from_pixels as board_poses_from_pixels
from .closed import initialise_hand_eye as initialise_hand_eye
from .closed import solve_axzb as solve_axzb
from .consistency import MotionConsistency as MotionConsistency
from .consistency import check_motion_consistency as check_motion_consistency
from .consistency import motion_consistency as motion_consistency
from .data import FRAME_BUCKETS as FRAME_BUCKETS
from .data import HandEyeData as HandEyeData
from .data import HandEyePixels as HandEyePixels
from .data import HandEyePoses as HandEyePoses
from .data import bucket as bucket
from .data import make_hand_eye_pixels as make_hand_eye_pixels
from .data import make_hand_eye_poses as make_hand_eye_poses
from .data import pad_hand_eye as pad_hand_eye
from .data import validate_hand_eye as validate_hand_eye
from .heldout import HeldOut as HeldOut
from .heldout import px_text as px_text
from .heldout import reprojection_squares as reprojection_squares
from .heldout import robot_pixel_scale as robot_pixel_scale
from .model import HandEyeParams as HandEyeParams
from .model import HandEyeReference as HandEyeReference
from .model import hand_eye_residuals as hand_eye_residuals
from .model import predicted_board_poses as predicted_board_poses
from .noise import ROBOT_SIGMA_START as ROBOT_SIGMA_START
from .noise import robot_noise_update as robot_noise_update
from .noise import robot_sigma6 as robot_sigma6
from .solve import HandEyeResult as HandEyeResult
from .solve import calibrate_hand_eye as calibrate_hand_eye
from .touch import TouchData as TouchData
from .touch import TouchParams as TouchParams
from .touch import TouchResult as TouchResult
from .touch import calibrate_touch as calibrate_touch
from .touch import initialise_touch as initialise_touch
from .touch import make_touch_data as make_touch_data
from .touch import touch_residuals as touch_residuals
from .touch import validate_touch as validate_touch
