"""A `KinematicModel` as plain JSON (the `model` block of `result.json` and `truth.json`)."""

import numpy as np

from .._kinematics import KinematicModel, make_model


def model_to_json(model: KinematicModel) -> dict:
    """The model's arrays as nested lists, with its joint and link names and types."""
    return {
        "joint_names": list(model.joint_names),
        "joint_types": list(model.joint_types),
        "link_names": list(model.link_names),
        "T_parent_joint": np.asarray(model.T_parent_joint).tolist(),
        "axis": np.asarray(model.axis).tolist(),
        "zero_offset": np.asarray(model.zero_offset).tolist(),
        "reduction_ratio": np.asarray(model.reduction_ratio).tolist(),
        "T_last_flange": np.asarray(model.T_last_flange).tolist(),
    }


def model_from_json(d: dict) -> KinematicModel:
    """Inverse of `model_to_json` (raises `ValueError`/`KeyError` on a malformed dict)."""
    return make_model(
        np.asarray(d["T_parent_joint"]),
        np.asarray(d["axis"]),
        joint_names=d["joint_names"],
        joint_types=d["joint_types"],
        link_names=d["link_names"],
        zero_offset=np.asarray(d["zero_offset"]),
        reduction_ratio=np.asarray(d["reduction_ratio"]),
        T_last_flange=np.asarray(d["T_last_flange"]),
    )
