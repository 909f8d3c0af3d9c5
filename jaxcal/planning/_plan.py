"""Capture plan files: `save_plan` and `load_plan` (`docs/plan.md`).

The plan's records and its JSON object live in `jaxcal.io.plan` (the file format);
here a robot given as a URDF file is resolved against the plan file's folder.
"""

import json
import os
from dataclasses import replace
from pathlib import Path

from ..errors import DatasetError, PlanFileError
from ..io._files import resolved, write_text_atomic
from ..io._schema import read_json
from ..io.plan import CapturePlan, plan_from_dict, plan_to_dict
from ..robots import shipped


def save_plan(plan: CapturePlan, path) -> Path:
    """Write `plan` as JSON to `path`, atomically. A robot given as a URDF file is
    recorded relative to the plan file's folder, as `load_plan` reads it."""
    path = Path(path)
    robot = Path(plan.robot)
    if plan.robot not in shipped() and robot.is_file():
        plan = replace(plan, robot=os.path.relpath(resolved(robot), resolved(path).parent))
    write_text_atomic(path, json.dumps(plan_to_dict(plan), indent=1) + "\n")
    return path


def load_plan(path) -> CapturePlan:
    """Read and check a plan file (`docs/plan.md`); a `PlanFileError` names the field at fault.
    A relative URDF path in `robot` is read relative to the plan file's folder."""
    path = Path(path)
    try:
        plan = plan_from_dict(read_json(path, "plan file"), path)
    except DatasetError as e:
        raise PlanFileError(str(e)) from None
    robot = Path(plan.robot)
    if plan.robot in shipped():
        return plan
    found = robot if robot.is_absolute() else path.parent / robot
    if not found.is_file():
        raise PlanFileError(
            f"{path}: field 'robot': {plan.robot!r} is neither a shipped robot ({shipped()}) nor a URDF file "
            f"(looked for {found}; a relative path is read from the plan file's folder)"
        )
    return replace(plan, robot=str(resolved(found)))
