"""Build jaxcal hand-eye captures (docs/handeye.md) from ViSP's Franka data in `source/`.

    python data/visp_handeye/convert.py OUT_DIR   # writes OUT_DIR/eye_in_hand, OUT_DIR/eye_to_hand

The files in `source/` are read, never changed. Each capture gets `handeye.json`, `poses.csv` and
`images/cam0/000N.png` (a copy of `franka_image-N.png`, which this repository keeps only there).

What the source files mean (ViSP's conventions, from its acquisition program and tutorial):
- `franka_pose_rPe_N.yaml`: a `vpPoseVector` [tx, ty, tz, theta*ux, theta*uy, theta*uz] in m and
  rad, the end effector's pose in the robot's base (ViSP's `aMb` maps b's coordinates into a's):
  jaxcal's `T_base_ee` in the `xyz_rotvec` format.
- `franka_camera.xml`: the RealSense's factory intrinsics (px, py, u0, v0; kud = kdu = 0).
- `chessboard-data.txt` "9 x 6": OpenCV's pattern size (inner corners), so 10 x 7 squares.
- `apriltag-data.txt`: one AprilTag 36h11 of 48 mm, id 10 (the tag in every image).
"""

import json
import re
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "source"
FRAMES = range(1, 9)
CAPTURES = {
    "eye_in_hand": ("data-eye-in-hand", {"kind": "chessboard", "squares": [10, 7], "square_length": 0.0236}),
    "eye_to_hand": (
        "data-eye-to-hand",
        {"kind": "aruco", "dictionary": "DICT_APRILTAG_36h11", "marker_length": 0.048, "first_id": 10},
    ),
}


def pose_vector(path: Path) -> list[float]:
    """The six numbers of a `vpPoseVector` YAML file."""
    values = re.findall(r"-\s*\[\s*([-+0-9.eE]+)\s*\]", path.read_text())
    if len(values) != 6:
        raise ValueError(f"{path}: expected 6 values, found {len(values)}")
    return [float(v) for v in values]


def camera(path: Path) -> dict:
    """Width, height and K of a ViSP camera XML file without distortion."""
    cam = ET.parse(path).getroot().find("camera")
    model = cam.find("model")
    if float(model.findtext("kud")) != 0 or float(model.findtext("kdu")) != 0:
        raise ValueError(f"{path}: distortion coefficients are not zero")
    px, py, u0, v0 = (float(model.findtext(k)) for k in ("px", "py", "u0", "v0"))
    return {
        "width": int(cam.findtext("image_width")),
        "height": int(cam.findtext("image_height")),
        "K": [[px, 0.0, u0], [0.0, py, v0], [0.0, 0.0, 1.0]],
    }


def build(name: str, out: Path, images: bool = True) -> Path:
    """Write capture `name` (a key of `CAPTURES`) to `out / name`."""
    folder, target = CAPTURES[name]
    src, dst = SOURCE / folder, out / name
    (dst / "images" / "cam0").mkdir(parents=True, exist_ok=True)
    rows = ["frame,x,y,z,rx,ry,rz"]
    for i in FRAMES:
        rows.append(
            ",".join([f"{i:04d}", *(repr(v) for v in pose_vector(src / f"franka_pose_rPe_{i}.yaml"))])
        )
        if images:
            shutil.copyfile(src / f"franka_image-{i}.png", dst / "images" / "cam0" / f"{i:04d}.png")
    (dst / "poses.csv").write_text("\n".join(rows) + "\n")
    description = {
        "schema": "jaxcal.handeye",
        "schema_version": 1,
        "arrangement": name,
        "frames": {"base": "panda_link0", "ee": "panda_EE", "target": "calibration_target"},
        "poses": {
            "file": "poses.csv",
            "format": "xyz_rotvec",
            "translation_unit": "m",
            "rotation_unit": "rad",
        },
        "cameras": [
            {
                "name": "cam0",
                **camera(src / "franka_camera.xml"),
                "distortion": [0.0, 0.0, 0.0, 0.0, 0.0],
                "frame_id": "cam0_optical_frame",
            }
        ],
        "target": target,
    }
    (dst / "handeye.json").write_text(json.dumps(description, indent=2) + "\n")
    return dst


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    for capture in CAPTURES:
        print(
            "wrote",
            build(
                capture,
                Path(sys.argv[1]),
                images=(SOURCE / "data-eye-in-hand" / "franka_image-1.png").exists(),
            ),
        )
