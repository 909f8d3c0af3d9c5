"""Vision front end: target detection, PnP with covariance, camera intrinsics, hand-eye data (OpenCV).

Impure (OpenCV, NumPy, files); never jitted, never imported by the JAX core.
It returns NumPy arrays in OpenCV's conventions: pixel centres at integer
coordinates, camera axes x right, y down, z forward.
"""

from ._detect import Detection as Detection
from ._detect import VisionError as VisionError
from ._detect import detect as detect
from ._detect import detect_frames as detect_frames
from ._handeye import HandEyeObservations as HandEyeObservations
from ._handeye import hand_eye_from_detections as hand_eye_from_detections
from ._intrinsics import calibrate_intrinsics as calibrate_intrinsics
from ._pose import PoseEstimate as PoseEstimate
from ._pose import estimate_pose as estimate_pose
from ._pose import pose_jacobian as pose_jacobian
