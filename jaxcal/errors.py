"""jaxcal's public exceptions, under one base class.

Every error a user can cause with their input is a `JaxcalError` (a
`ValueError`), raised with a message that names the file, field, frame or
argument at fault. The command line maps them to exit code 2. A result that
was computed but fails a plausibility check is not an exception: it carries
`status == "suspect"` and its reasons (exit code 3); `SuspectResultError` is
raised only when a caller asked for strictness.
"""


class JaxcalError(ValueError):
    """Input jaxcal cannot use as it is; the message says what and where."""


class DatasetError(JaxcalError):
    """A dataset file is missing, malformed or inconsistent (the message names it)."""


class CalibrationError(JaxcalError):
    """The dataset cannot be calibrated as it is (the message says why and where)."""


class VisionError(JaxcalError):
    """An image, target or camera cannot be processed (the message names it)."""


class OutputError(JaxcalError):
    """Results cannot be written where asked (the message names the path and why)."""


class SuspectResultError(JaxcalError):
    """A result failed its plausibility checks and the caller asked for strictness."""


class HandEyeInputError(JaxcalError):
    """Input that cannot give a hand-eye calibration; the message names the input and the frame."""


class ShapeError(HandEyeInputError):
    """An array has the wrong shape (poses that are not 4x4, intrinsics per camera, ...)."""


class LengthMismatchError(HandEyeInputError):
    """Two inputs that must pair up (robot poses and frames, points and touches) differ in length."""


class NotARotationError(HandEyeInputError):
    """A pose's rotation block is not a rotation matrix (or its bottom row is not (0, 0, 0, 1))."""


class NonFiniteError(HandEyeInputError):
    """A NaN or infinite value where an observation is marked valid."""


class TooFewPosesError(HandEyeInputError):
    """Fewer observed robot poses (or touched points) than the problem needs."""


class DegenerateMotionError(HandEyeInputError):
    """The motion cannot identify the transforms: rotations below the minimum or about one axis only."""


class ToolOffsetInputError(JaxcalError):
    """Input that cannot give a tool-offset arc fit; the message names the input."""


class InconsistentPosesError(HandEyeInputError):
    """Robot poses and images disagree: the relative rotation angles between frames differ
    (poses in the wrong order, a wrong unit, another capture's poses)."""


class NotPositiveDefiniteError(HandEyeInputError):
    """A covariance matrix that is not symmetric positive definite (the message names camera and frame)."""


class IntrinsicsError(HandEyeInputError):
    """A camera matrix that is not a pinhole's (a negative focal length, a transposed matrix; names the camera)."""


class NoiseLevelError(HandEyeInputError):
    """A noise level (sigma) that is not finite and positive (names the argument)."""


class PlanError(JaxcalError):
    """A capture plan cannot be made, read or evaluated as asked (the message says why and where)."""


class PlanFileError(PlanError):
    """A plan file is malformed: unknown fields, wrong types or values out of range (the message names
    the file and the field)."""


class UnreachableRegionError(PlanError):
    """The region where accuracy matters holds no configuration the arm can reach."""


class CameraViewError(PlanError):
    """The camera sees the target in none of the configurations tried (not one feasible frame)."""


class BudgetTooSmallError(PlanError):
    """Too few frames to identify anything (or fewer than the plan's structure needs)."""


class BagError(DatasetError):
    """A ROS bag cannot be turned into a dataset (the message names the bag, topic and message)."""


class BagTopicError(BagError):
    """A topic asked for is not in the bag (the message lists the bag's topics with their types)."""


class BagMessageTypeError(BagError):
    """A topic holds messages of another type than the one asked for."""


class BagJointError(BagError):
    """The joint states' names do not match the robot file's actuated joints."""


class BagTimeError(BagError):
    """Images and joint states do not overlap in time (or a topic has too few messages)."""


class BagEncodingError(BagError):
    """An image encoding, compression or camera model that jaxcal does not read."""


class CsvImportError(DatasetError):
    """A CSV table cannot be turned into a dataset (`jaxcal import-csv`): the message names the file,
    the column and the line."""
