"""Every input file is checked at load (issue 13): one test per corruption, the
encoder-glitch detector, and a property-based fuzz of `load_dataset`.

No rendering and no JAX compilation: the cases edit a copy of
`data/ur5e_sweeps` (the shipped 800x600 dataset) or a tiny dataset built from
it with a few 40x30 images; every failing load must leave the files as they were.
"""

import csv
import hashlib
import io
import json
import math
import re
import shutil
import struct
import tempfile
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxcal.cli import main
from jaxcal.errors import DatasetError, JaxcalError
from jaxcal.io import _encoders as enc
from jaxcal.io._images import MAX_PIXELS, image_size
from jaxcal.io.dataset import Dataset, EncoderGlitch, load_dataset

SWEEPS = Path(__file__).resolve().parents[1] / "data" / "ur5e_sweeps"
RATIO = 101.0  # the UR5e's nominal reduction ratio (data/robots/ur5e.urdf)


# --------------------------------------------------------------------------- helpers


def _digest(root: Path) -> dict:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def ds(tmp_path) -> Path:
    dst = tmp_path / "ds"
    shutil.copytree(SWEEPS, dst)
    return dst


def edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    out = edit(data)
    path.write_text(json.dumps(data if out is None else out))


def read_rows(path: Path) -> list[list[str]]:
    return list(csv.reader(io.StringIO(path.read_text())))


def write_rows(path: Path, rows) -> None:
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(rows)


def edit_encoders(root: Path, edit) -> None:
    """`edit(t, motor)` on the encoder log's values (motor angles, rad), in place."""
    rows = read_rows(root / "encoders.csv")
    values = np.array(rows[1:], dtype=np.float64)
    edit(values[:, 0], values[:, 1:])
    write_rows(root / "encoders.csv", [rows[0], *([repr(float(v)) for v in r] for r in values)])


def fails(root: Path, *words: str, exc=DatasetError) -> str:
    """Loading `root` raises `exc` whose message holds every one of `words`; the files are untouched."""
    before = _digest(root)
    with pytest.raises(exc) as e:
        load_dataset(root)
    assert _digest(root) == before
    message = str(e.value)
    for w in words:
        assert w in message, message
    return message


def png(width: int, height: int, value: int = 128) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((height, width), value, np.uint8))
    assert ok
    return buf.tobytes()


def png_header(width: int, height: int) -> bytes:
    """A PNG that claims `width` x `height` pixels (a decompression bomb's header; no pixels follow)."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    )


def test_the_shipped_dataset_loads_clean():
    d = load_dataset(SWEEPS)
    assert d.notes == () and d.encoder_glitches == () and d.encoder_unit == "rad"
    assert len(d.frames["file"]) == 144 and d.encoder_motor.shape == (7201, 6)
    assert d.joint_limits["elbow_joint"].reduction_ratio == RATIO
    assert d.joint_limits["elbow_joint"].velocity == pytest.approx(math.pi)


# --------------------------------------------------------------------------- metadata.json: types and fields


def test_metadata_holding_a_list(ds):
    (ds / "metadata.json").write_text("[1, 2]")
    fails(ds, "metadata.json", "expected a JSON object", "[1, 2]")


def test_metadata_not_json_not_utf8_nan(ds):
    (ds / "metadata.json").write_bytes(b"\xff\xfe{}")
    fails(ds, "metadata.json", "not UTF-8")
    (ds / "metadata.json").write_text("{" * 100000)
    fails(ds, "metadata.json", "not valid JSON")
    text = (SWEEPS / "metadata.json").read_text().replace('"offset_s": null', '"offset_s": NaN')
    (ds / "metadata.json").write_text(text)
    fails(ds, "metadata.json", "NaN is not JSON")


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda m: m["cameras"][0].update(width=None), ["cameras[0].width", "expected an integer", "None"]),
        (lambda m: m["cameras"][0].update(width="wide"), ["cameras[0].width", "'wide'"]),
        (lambda m: m["cameras"][0].update(width=800.5), ["cameras[0].width", "800.5"]),
        (lambda m: m["cameras"][0].update(height=True), ["cameras[0].height", "True"]),
        (lambda m: m["cameras"][0].update(width=0), ["cameras[0].width", "from 1 to 65535", "got 0"]),
        (lambda m: m["cameras"][0].update(name="../../etc"), ["cameras[0].name", "'../../etc'"]),
        (
            lambda m: m["cameras"][0].update(distortion=[0.1, "x", 0, 0, 0]),
            ["cameras[0].distortion[1]", "'x'"],
        ),
        (lambda m: m["cameras"][0].update(distortion=[0.1, 0.2, 0.3]), ["cameras[0].distortion", "4, 5, 8"]),
        (
            lambda m: m["cameras"][0].update(mount="tool0"),
            ["cameras[0].mount", "'tool0'", "nor a link of the robot"],
        ),
        (lambda m: m["cameras"][0].update(distorsion=[0] * 5), ["cameras[0]", "unknown field 'distorsion'"]),
        (lambda m: m.update(cameras=[]), ["cameras", "non-empty list"]),
        (lambda m: m["cameras"].append(dict(m["cameras"][0])), ["camera names are not unique"]),
        (lambda m: m.update(motion=["shoulder_pan_joint"]), ["motion[0]", "expected a JSON object"]),
        (lambda m: m["motion"][0].update(start="soon"), ["motion[0].start", "'soon'"]),
        (lambda m: m["motion"][0].update(end=0.1), ["motion[0]", "end (0.1) must be after start"]),
        (lambda m: m["motion"][2].update(joint="elbow_jiont"), ["motion[2].joint", "unknown joint"]),
        (lambda m: m["clock"].update(offset_s="40ms"), ["clock.offset_s", "'40ms'"]),
        (lambda m: m["clock"].update(drift_ppm=1e6), ["clock.drift_ppm", "from -1000 to 1000", "1000000.0"]),
        (lambda m: m.update(clock=[0.04]), ["clock", "expected a JSON object"]),
        (lambda m: m.update(encoder={"unit": "deg"}), ["unknown field 'encoder'", "'encoders'"]),
        (lambda m: m["encoders"].update(unit="grad"), ["encoders.unit", "'rad', 'deg', 'counts'", "'grad'"]),
        (lambda m: m["encoders"].update(quantity="joint_angle"), ["encoders.quantity", "'joint_angle'"]),
        (lambda m: m["encoders"].update(rate_hz=-5), ["encoders.rate_hz", "-5"]),
        (lambda m: m["encoders"].update(file="../encoders.csv"), ["encoders.file", "stays inside"]),
        (lambda m: m["encoders"].update(file="/etc/passwd"), ["encoders.file", "stays inside"]),
        (lambda m: m["encoders"].update(file="log.csv"), ["log.csv", "encoder log", "missing"]),
        (lambda m: m["encoders"].update(unit="counts", counts_per_rev=None), ["needs counts_per_rev"]),
        (lambda m: m["robot"].update(joints=["shoulder_pan_joint", "elbow"]), ["robot.joints[1]", "'elbow'"]),
        (lambda m: m["robot"].update(joints=m["robot"]["joints"][:5]), ["robot.joints", "base to flange"]),
        (lambda m: m["robot"].update(flange_link="flang"), ["robot.flange_link", "'flang'"]),
        (lambda m: m["robot"].update(urdf="../robot.urdf"), ["robot.urdf", "stays inside"]),
        (lambda m: m["robot"].update(urdf="nope.urdf"), ["nope.urdf", "robot file missing"]),
        (lambda m: m["targets"][0].update(link="flange2"), ["targets[0].link", "'flange2'"]),
        (lambda m: m["targets"][0].update(squares=[5]), ["targets[0].squares", "[columns, rows]"]),
        (lambda m: m["targets"][0].update(square_length="4cm"), ["targets[0].square_length", "'4cm'"]),
        (
            lambda m: m["targets"][0].update(square_length=40),
            [
                "targets[0].square_length",
                "length in metres",
                "at most 10",
                "40 looks like millimetres: 0.04 m?",
            ],
        ),
        (
            lambda m: m["targets"][0].update(marker_length=0.05),
            ["targets[0]", "marker_length < square_length"],
        ),
        (lambda m: m["targets"][0].update(dictionary="DICT_9X9"), ["targets[0]", "DICT_9X9"]),
        (
            lambda m: m["targets"].append(dict(m["targets"][0], name="plate1", first_id=5, link="world")),
            ["targets[1].first_id", "'plate1'", "overlap target 'plate0'", "cannot tell which plate"],
        ),
        (
            lambda m: m["targets"][0].__delitem__("marker_length"),
            ["targets[0]", "missing field 'marker_length'"],
        ),
        (
            lambda m: m["targets"][0]["T_link_target_nominal"][3].__setitem__(3, 2.0),
            ["T_link_target_nominal"],
        ),
        (lambda m: m.update(schema_version=2), ["unknown schema_version 2"]),
        (lambda m: m.update(schema_version=True), ["unknown schema_version True"]),
        (lambda m: m.update(calibration_hint=1), ["unknown field 'calibration_hint'"]),
    ],
)
def test_metadata_field_errors_name_the_field_and_value(ds, edit, words):
    edit_json(ds / "metadata.json", edit)
    message = fails(ds, "metadata.json", *words)
    assert "Traceback" not in message


def test_harmless_extra_fields_are_accepted(ds):
    def edit(m):
        m["x_operator"] = "A. N. Other"  # user notes: keys starting with x_, at any level
        m["cameras"][0]["x_serial"] = "1234"
        m["simulation"] = {"anything": [1, 2]}  # written by jaxcal simulate, not read

    edit_json(ds / "metadata.json", edit)
    assert load_dataset(ds).metadata["x_operator"] == "A. N. Other"


# --------------------------------------------------------------------------- intrinsics


@pytest.mark.parametrize(
    ("K", "words"),
    [
        ([[-643.35, 0, 399.5], [0, 643.35, 299.5], [0, 0, 1]], ["focal lengths", "fx = -643.35"]),
        ([[0, 0, 399.5], [0, 643.35, 299.5], [0, 0, 1]], ["focal lengths", "fx = 0"]),
        ([[643.35, 0, 399.5], [0, 643.35, 299.5], [0, 0, 0]], ["bottom row must be [0, 0, 1]"]),
        ([[643.35, 0, 399.5], [0, 643.35, 299.5], [0, 0, 2]], ["bottom row must be [0, 0, 1]"]),
        ([[643.35, 0, 399.5], [1.0, 643.35, 299.5], [0, 0, 1]], ["below the diagonal must be 0"]),
        ([[643.35, 0, 900.0], [0, 643.35, 299.5], [0, 0, 1]], ["principal point (900, 299.5)", "800x600"]),
        ([[643.35, 0, 399.5], [0, 643.35, -3], [0, 0, 1]], ["principal point"]),
        # A K for images twice as large: its principal point at this image's corner.
        (
            [[1286.7, 0, 799.0], [0, 1286.7, 599.0], [0, 0, 1]],
            ["at the edge of the 800x600 image", "resized"],
        ),
        ([[643.35, 0, 399.5], [0, 643.35, 299.5]], ["cameras[0].K", "3x3 array"]),
        ([[643.35, 0, 399.5], [0, 643.35, 299.5], [0, 0, "1"]], ["cameras[0].K[2][2]", "'1'"]),
    ],
)
def test_bad_intrinsics(ds, K, words):
    edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(K=K))
    fails(ds, "cameras[0].K", *words)


def test_unknown_intrinsics_are_allowed(ds):
    edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(K=None))
    assert load_dataset(ds).cameras[0].K is None


# --------------------------------------------------------------------------- images


def test_one_image_of_another_size(ds):
    (ds / "images/cam0/000007.png").write_bytes(png(640, 480))
    fails(ds, "frames.csv line 9", "000007.png is 640x480 pixels", "says 800x600")


def test_every_image_640x480_while_metadata_says_800x600(ds):
    for p in (ds / "images/cam0").iterdir():
        p.write_bytes(png(640, 480))
    fails(ds, "000000.png is 640x480", "800x600", "so are 143 more of its 144 images")


def test_metadata_640x480_while_every_image_is_800x600(ds):
    edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(width=640, height=480))
    fails(ds, "000000.png is 800x600 pixels", "says 640x480", "so are 143 more")


def test_decompression_bomb_is_refused_from_its_header(ds):
    (ds / "images/cam0/000004.png").write_bytes(png_header(16000, 16000))
    fails(ds, "000004.png", "16000x16000", "more than the 100 megapixels")
    edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(width=16000, height=16000, K=None))
    fails(ds, "cameras[0]", "16000x16000 pixels")


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"not a png", ["000005.png", "not an image file"]),
        (b"", ["000005.png", "not an image file"]),
        (None, ["000005.png", "image file missing"]),
        ("truncate", ["000005.png", "truncated PNG"]),
        ("gif", ["000005.png", "GIF images are not read"]),
        ("dir", ["000005.png", "is a directory"]),
    ],
)
def test_missing_and_broken_images_are_named(ds, content, words):
    victim = ds / "images/cam0/000005.png"
    if content is None:
        victim.unlink()
    elif content == "truncate":
        victim.write_bytes(victim.read_bytes()[:5000])
    elif content == "gif":
        from PIL import Image

        buf = io.BytesIO()
        Image.new("L", (800, 600)).save(buf, "GIF")
        victim.write_bytes(buf.getvalue())
    elif content == "dir":
        victim.unlink()
        victim.mkdir()
    else:
        victim.write_bytes(content)
    fails(ds, "frames.csv line 7", *words, "or delete line 7 of frames.csv")
    # ... and the advice works: without that row the dataset loads, one frame fewer (a captured
    # dataset has no truth.json, whose rows would name the deleted frame).
    (ds / "truth.json").unlink()
    rows = read_rows(ds / "frames.csv")
    write_rows(ds / "frames.csv", rows[:6] + rows[7:])
    assert len(load_dataset(ds).frames.file) == len(rows) - 2


def test_jpeg_sizes_come_from_the_frame_header(ds):
    rows = read_rows(ds / "frames.csv")
    image = cv2.imread(str(ds / rows[3][3]), cv2.IMREAD_GRAYSCALE)
    ok, buf = cv2.imencode(".jpg", image)
    (ds / "images/cam0/000002.jpg").write_bytes(buf.tobytes())
    rows[3][3] = "images/cam0/000002.jpg"
    write_rows(ds / "frames.csv", rows)
    assert image_size(ds / "images/cam0/000002.jpg") == (800, 600)
    assert load_dataset(ds).frames["file"][2] == "images/cam0/000002.jpg"
    (ds / "images/cam0/000002.jpg").write_bytes(buf.tobytes()[:3000])
    fails(ds, "000002.jpg", "truncated JPEG")
    small = cv2.imencode(".jpg", image[:300, :400])[1].tobytes()
    (ds / "images/cam0/000002.jpg").write_bytes(small)
    fails(ds, "000002.jpg is 400x300 pixels")


def test_image_headers_are_cheap():
    files = sorted((SWEEPS / "images/cam0").iterdir())
    image_size(files[0])
    start = time.perf_counter()
    sizes = {image_size(f) for f in files}
    per_100 = (time.perf_counter() - start) / len(files) * 100
    assert sizes == {(800, 600)}
    assert per_100 < 0.05, f"{1e3 * per_100:.1f} ms per 100 images"  # ~1 ms measured; loose for shared CI
    assert MAX_PIXELS == 100_000_000


# --------------------------------------------------------------------------- frames.csv


def test_two_timestamps_swapped(ds):
    rows = read_rows(ds / "frames.csv")
    rows[10][2], rows[11][2] = rows[11][2], rows[10][2]
    write_rows(ds / "frames.csv", rows)
    fails(ds, "frames.csv lines 11 and 12", "frame 9", "must increase strictly")


def test_six_frames_sharing_one_timestamp(ds):
    rows = read_rows(ds / "frames.csv")
    for r in rows[20:26]:
        r[2] = rows[20][2]
    write_rows(ds / "frames.csv", rows)
    fails(ds, "frames.csv lines 21 and 22", "must increase strictly")


def test_repeated_rows_and_pairs(ds):
    rows = read_rows(ds / "frames.csv")
    write_rows(ds / "frames.csv", [*rows[:30], rows[29], *rows[30:]])
    fails(ds, "frames.csv line 31", "repeats line 30")
    other = list(rows[29])
    other[3] = rows[30][3]
    write_rows(ds / "frames.csv", [*rows[:30], other, *rows[31:]])
    fails(ds, "frames.csv line 31", "frame 28 is already on line 30")
    other = list(rows[29])
    other[1] = "1000"
    write_rows(ds / "frames.csv", [*rows, other])
    fails(ds, "frames.csv line 146", "images/cam0/000028.png", "already named on line 30")


@pytest.mark.parametrize(
    ("cell", "value", "words"),
    [
        (1, "100000000", ["line 42", "frame 100000000", "span"]),
        (1, "-3", ["line 42", "'-3' is not a non-negative integer"]),
        (1, "4.0", ["line 42", "'4.0' is not a non-negative integer"]),
        (1, "99999999999", ["line 42", "frame '99999999999' is above the largest capture index 2147483647"]),
        (2, "nan", ["line 42", "timestamp", "NaN/inf"]),
        (2, "soon", ["line 42", "'soon' is not a number"]),
        (0, "cam1", ["line 42", "unknown camera 'cam1'"]),
        (3, "../ur5e/images/cam0/000040.png", ["line 42", "stays inside"]),
        (3, "/tmp/x.png", ["line 42", "stays inside"]),
    ],
)
def test_frame_row_errors(ds, cell, value, words):
    rows = read_rows(ds / "frames.csv")
    rows[41][cell] = value
    write_rows(ds / "frames.csv", rows)
    fails(ds, "frames.csv", *words)


def test_frame_index_far_off_is_refused_but_gaps_are_fine(ds):
    rows = read_rows(ds / "frames.csv")
    for r in rows[1:]:
        r[1] = str(int(r[1]) * 50 + 7_000_000)  # dropped frames between every two; a late start
    write_rows(ds / "frames.csv", rows)
    d = load_dataset(ds)
    assert d.frames["frame"][-1] == 143 * 50 + 7_000_000


def test_frames_table_shape(ds):
    (ds / "frames.csv").write_text("camera,frame,time,file\n")
    fails(ds, "frames.csv line 1", "header must be camera,frame,timestamp,file")
    (ds / "frames.csv").write_text("camera,frame,timestamp,file\n")
    fails(ds, "frames.csv", "no frames")
    (ds / "frames.csv").write_text("camera,frame,timestamp,file\ncam0,0,0.1\n")
    fails(ds, "frames.csv line 2", "expected 4 columns")
    (ds / "frames.csv").unlink()
    fails(ds, "frames.csv", "frames table missing")


# --------------------------------------------------------------------------- the encoder log


def test_encoder_values_a_billion_times_too_large(ds):
    edit_encoders(ds, lambda t, m: m.__imul__(1e9))
    fails(ds, "encoders.csv column 'shoulder_pan_joint'", "outside the robot file's limits")


def test_encoder_log_in_degrees_while_unit_says_rad(ds):
    edit_encoders(ds, lambda t, m: m.__imul__(180.0 / math.pi))
    fails(ds, "encoders.csv column", "encoders.unit is 'rad' but the values look like degrees")


def test_encoder_counts_taken_for_radians(ds):
    edit_encoders(ds, lambda t, m: m.__setitem__(slice(None), np.round(m * 131072 / (2 * math.pi))))
    fails(ds, "encoders.csv column", "look like", "encoder counts")


def test_documented_units_and_file_are_read(ds):
    rad = load_dataset(ds).encoder_motor
    edit_encoders(ds, lambda t, m: m.__imul__(180.0 / math.pi))
    edit_json(ds / "metadata.json", lambda m: m["encoders"].update(unit="deg"))
    np.testing.assert_allclose(load_dataset(ds).encoder_motor, rad, rtol=1e-12, atol=1e-15)
    edit_encoders(ds, lambda t, m: m.__setitem__(slice(None), np.round(m / 360.0 * 131072)))
    edit_json(ds / "metadata.json", lambda m: m["encoders"].update(unit="counts"))
    d = load_dataset(ds)
    assert d.encoder_unit == "counts"
    np.testing.assert_allclose(d.encoder_motor, rad, rtol=0, atol=2 * math.pi / 131072)
    (ds / "logs").mkdir()
    (ds / "encoders.csv").rename(ds / "logs" / "motors.csv")
    edit_json(ds / "metadata.json", lambda m: m["encoders"].update(file="logs/motors.csv"))
    np.testing.assert_allclose(load_dataset(ds).encoder_motor, rad, rtol=0, atol=2 * math.pi / 131072)


def test_swapped_encoder_columns_are_named_before_the_clock(ds):
    """The elbow's and wrist 1's columns swapped: during the elbow's sweep its column stands still
    and wrist 1's turns, refused naming both at load (trial 14: a clock fit that did not converge)."""
    edit_encoders(ds, lambda t, m: m.__setitem__(slice(None), m[:, [0, 1, 3, 2, 4, 5]]))
    fails(ds, "motion[2]", "(elbow_joint)", "moves column 'wrist_1_joint' by 100 %", "swapped?")


def test_positions_past_the_joint_limits_are_noted(ds):
    """The robot file's elbow limits narrowed to +-0.5 rad, its sweep reaching 0.7 (within the unit
    check's margin): a note names the line, the value and the limits (trial 14 found it silent)."""
    urdf = (ds / "robot.urdf").read_text()
    head, tail = urdf.split('name="elbow_joint"', 1)
    tail = re.sub(r'lower="[^"]*" upper="[^"]*"', 'lower="-0.5" upper="0.5"', tail, count=1)
    (ds / "robot.urdf").write_text(head + 'name="elbow_joint"' + tail)
    notes = [n for n in load_dataset(ds).notes if "outside its URDF limits [-0.5, 0.5]" in n]
    assert len(notes) == 1 and "joint 'elbow_joint' reaches" in notes[0], load_dataset(ds).notes


def test_a_log_cut_short_names_the_segments_it_misses(ds):
    """The encoder log ends before the last sweep: that segment's frames will have no joint
    angles, a note naming it (every segment outside the log is a clock mismatch, refused)."""
    rows = read_rows(ds / "encoders.csv")
    last = json.loads((ds / "metadata.json").read_text())["motion"][-1]
    write_rows(ds / "encoders.csv", [rows[0], *(r for r in rows[1:] if float(r[0]) < last["start"] - 0.01)])
    notes = load_dataset(ds).notes
    assert any(
        "motion[5]" in n and "lies outside the encoder log" in n and "no joint angles" in n for n in notes
    )


def test_encoder_timestamps_must_increase(ds):
    edit_encoders(ds, lambda t, m: t.__setitem__(100, t[99]))
    fails(ds, "encoders.csv line 102", "is not after line 101", "timestamps must increase")


def test_encoder_table_shape(ds):
    rows = read_rows(ds / "encoders.csv")
    write_rows(ds / "encoders.csv", [rows[0][:-1], *(r[:-1] for r in rows[1:])])
    fails(
        ds, "encoders.csv line 1", f"no column for joint(s) [{rows[0][-1]!r}]", "expected the robot's joints"
    )
    swapped = [rows[0][0], rows[0][2], rows[0][1], *rows[0][3:]]
    write_rows(ds / "encoders.csv", [swapped, *rows[1:]])
    fails(ds, "encoders.csv line 1", "in another order")
    write_rows(ds / "encoders.csv", [rows[0], rows[1], rows[2][:-1], *rows[3:]])
    fails(ds, "encoders.csv line 3", "expected 7 columns, got 6")
    write_rows(ds / "encoders.csv", [rows[0], rows[1]])
    fails(ds, "encoders.csv", "fewer than 2 encoder readings")
    rows[50][3] = "0x1F"
    write_rows(ds / "encoders.csv", rows)
    fails(ds, "encoders.csv line 51 column 'elbow_joint'", "'0x1F' is not a number")


def test_an_unused_encoder_log_is_noted(ds):
    edit_json(ds / "metadata.json", lambda m: m.update(encoders=None))
    d = load_dataset(ds)
    assert d.encoder_t is None and d.encoder_unit is None
    assert any("is not used" in n for n in d.notes)


def test_a_wrong_rate_is_noted(ds):
    edit_json(ds / "metadata.json", lambda m: m["encoders"].update(rate_hz=100.0))
    (note,) = load_dataset(ds).notes
    assert "rate_hz is 100 Hz" in note and "500 Hz" in note


def _sweep_row(d: Dataset, joint: int) -> int:
    """A row in the middle of joint `joint`'s sweep (moving)."""
    _, start, end = d.segments[joint]
    return int(np.searchsorted(d.encoder_t, 0.5 * (start + end)))


def test_an_isolated_glitch_is_removed_and_reported(ds):
    clean = load_dataset(ds)
    k = _sweep_row(clean, 2)
    edit_encoders(ds, lambda t, m: m.__setitem__((k, 2), m[k, 2] + 40.0))  # 0.4 rad of joint, one sample
    d = load_dataset(ds)
    (g,) = d.encoder_glitches
    assert g == EncoderGlitch(
        "elbow_joint", (k, k), (k + 2, k + 2), clean.encoder_t[k - 1], clean.encoder_t[k + 1], g.size
    )
    assert g.size == pytest.approx(40.0 / RATIO, rel=1e-3)
    assert len(d.encoder_t) == len(clean.encoder_t) - 1 and clean.encoder_t[k] not in d.encoder_t
    np.testing.assert_array_equal(np.delete(clean.encoder_motor, k, axis=0), d.encoder_motor)
    (note,) = d.notes
    assert "1 isolated encoder glitch removed" in note and f"line {k + 2}" in note and "elbow_joint" in note
    t = clean.encoder_t[k - 3 : k + 4]
    np.testing.assert_array_equal(d.in_encoder_glitch(t), [False, False, True, True, True, False, False])


def test_glitch_bursts_and_a_glitch_on_the_first_row(ds):
    clean = load_dataset(ds)
    k = _sweep_row(clean, 4)

    def edit(t, m):
        m[k : k + 3, 4] = 1e6  # three wild samples
        m[0, 0] = -5e3  # the log starts with a bad sample

    edit_encoders(ds, edit)
    d = load_dataset(ds)
    rows = sorted((g.joint, g.rows) for g in d.encoder_glitches)
    assert rows == [("shoulder_pan_joint", (0, 0)), ("wrist_2_joint", (k, k + 2))]
    assert len(d.encoder_t) == len(clean.encoder_t) - 4


def test_a_jump_that_stays_is_an_error(ds):
    clean = load_dataset(ds)
    k = _sweep_row(clean, 1)
    edit_encoders(ds, lambda t, m: m.__setitem__((slice(k, None), 1), m[k:, 1] + 30.0))  # an encoder reset
    fails(ds, f"encoders.csv line {k + 2}", "'shoulder_lift_joint' jumps", "not an isolated glitch")


def test_a_glitchy_log_is_an_error(ds):
    def edit(t, m):
        m[5::40, 0] += 50.0  # one sample in 40: 2.5 % of the rows, 180 glitches

    edit_encoders(ds, edit)
    fails(ds, "encoders.csv", "180 glitches", "unreliable")


def test_continuous_joint_without_limits_still_catches_absurd_values(ds):
    urdf = (ds / "robot.urdf").read_text()
    (ds / "robot.urdf").write_text(
        urdf.replace('name="wrist_3_joint" type="revolute"', 'name="wrist_3_joint" type="continuous"')
    )
    d = load_dataset(ds)
    assert d.joint_limits["wrist_3_joint"].lower is None
    edit_encoders(ds, lambda t, m: m.__setitem__((slice(None), 5), m[:, 5] * 30.0))
    load_dataset(ds)  # 21 rad, far past a revolute joint's +-2 pi, but a continuous joint may turn 3 times
    edit_encoders(ds, lambda t, m: m.__setitem__((slice(None), 5), m[:, 5] * 1e3))
    fails(ds, "column 'wrist_3_joint'", "100 turns")


def test_joint_limits_from_a_transmission_ratio(ds):
    # With a ratio of 1 (no transmission) the same motor angles are 101 times the joint's: far out.
    urdf = (ds / "robot.urdf").read_text()
    start = urdf.index('<transmission name="elbow_joint_trans">')
    end = urdf.index("</transmission>", start) + len("</transmission>")
    (ds / "robot.urdf").write_text(urdf[:start] + urdf[end:])
    fails(ds, "column 'elbow_joint'", "reduction ratio 1", "outside the robot file's limits")


def test_robot_file_errors(ds):
    (ds / "robot.urdf").write_text("<robot name='x'><link name='a'></robot")
    fails(ds, "robot.urdf", "cannot read the robot model")
    (ds / "robot.urdf").unlink()
    fails(ds, "robot.urdf", "robot file missing")


# --------------------------------------------------------------------------- truth.json


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda t: {}, ["truth.json", "missing field 'model'"]),
        (lambda t: [t], ["truth.json", "expected a JSON object"]),
        (lambda t: t["model"].__delitem__("axis"), ["model", "missing field 'axis'"]),
        (lambda t: t["model"].update(joint_names=["a"]), ["model.joint_names", "differ from robot.joints"]),
        (lambda t: t["model"]["axis"].__setitem__(0, [0, 0, 2]), ["model.axis", "unit vector"]),
        (lambda t: t["model"]["T_parent_joint"][1][0].__setitem__(0, 3.0), ["T_parent_joint[1]", "rotation"]),
        (lambda t: t["model"].update(reduction_ratio=[0] * 6), ["model.reduction_ratio", "non-zero"]),
        (lambda t: t["cameras"].update(cam9={}), ["cameras.cam9", "not a camera"]),
        (
            lambda t: t["cameras"]["cam0"].__delitem__("T_mount_cam"),
            ["cameras.cam0", "missing field 'T_mount_cam'"],
        ),
        (lambda t: t["targets"]["plate0"].update(T_link_target="I"), ["targets.plate0.T_link_target", "'I'"]),
        (lambda t: t["clock"].update(offset_s=None), ["clock.offset_s", "None"]),
        (lambda t: t.update(dropped_frames=[-1]), ["dropped_frames[0]", "-1"]),
        (
            lambda t: t["frames"][3].update(row=-1),
            ["frames[3].row", "-1"],
        ),  # rows follow the table: any row >= 0
        (lambda t: t["frames"][3]["visible"].update(plate0="yes"), ["frames[3].visible.plate0", "'yes'"]),
        (lambda t: t["frames"][3].update(q=[0.0] * 5), ["frames[3].q", "6 array"]),
    ],
)
def test_truth_is_checked_at_load(ds, edit, words):
    edit_json(ds / "truth.json", edit)
    fails(ds, *words)


# --------------------------------------------------------------------------- the command line


def test_cli_reports_input_errors_at_load_with_exit_code_2(ds, tmp_path, capsys):
    edit_json(ds / "metadata.json", lambda m: m["cameras"][0].update(width="wide"))
    before = _digest(ds)
    start = time.perf_counter()
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "res"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jaxcal: error: ") and "cameras[0].width" in err and "'wide'" in err
    assert time.perf_counter() - start < 30  # at load, not after detection (~1 s here)
    assert _digest(ds) == before and not (tmp_path / "res").exists()


# --------------------------------------------------------------------------- the glitch detector


def test_detector_on_smooth_motion_far_beyond_the_speed_limit():
    t = np.arange(0.0, 2.0, 0.002)
    x = 3.0 * np.sin(2 * np.pi * 1.5 * t)  # 28 rad/s at most
    assert enc.find_glitches(t, x, 1.0) == ([], [])


def test_detector_finds_spikes_bursts_and_ends():
    t = np.arange(0.0, 1.0, 0.002)
    x = 0.5 * np.sin(3 * t)
    y = x.copy()
    y[100] += 0.2
    y[200:203] -= 0.3
    y[0] = 1.0
    y[-1] = -1.0
    glitches, jumps = enc.find_glitches(t, y, 2.0)
    assert glitches == [(0, 0), (100, 100), (200, 202), (len(t) - 1, len(t) - 1)] and jumps == []


def test_detector_leaves_steps_the_speed_limit_allows_and_reports_jumps_that_stay():
    t = np.arange(0.0, 1.0, 0.002)
    x = np.zeros_like(t)
    x[100] = 0.003  # 1.5 rad/s for one sample: within a 2 rad/s limit
    assert enc.find_glitches(t, x, 2.0) == ([], [])
    x[300:] += 0.5
    glitches, jumps = enc.find_glitches(t, x, 2.0)
    assert glitches == [] and [j.index for j in jumps] == [300] and jumps[0].size == pytest.approx(0.5)


def test_detector_with_uneven_sampling_and_gaps():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.001, 0.003, 600))
    t[300:] += 0.5  # the logger paused for half a second while the joint moved on
    x = 0.8 * t
    assert enc.find_glitches(t, x, 1.0) == ([], [])
    x[150] += 0.1
    assert enc.find_glitches(t, x, 1.0)[0] == [(150, 150)]


@settings(max_examples=60, derandomize=True, deadline=None)
@given(
    speed=st.floats(0.05, 30.0),
    freq=st.floats(0.2, 3.0),
    phase=st.floats(0.0, 6.3),
    spikes=st.lists(
        st.tuples(st.integers(1, 3), st.floats(3.0, 500.0), st.booleans()), min_size=0, max_size=6
    ),
)
def test_detector_recovers_inserted_glitches(speed, freq, phase, spikes):
    """Smooth motion at any speed (up to 30 times the limit), plus isolated runs of 1-3
    samples displaced by 3 to 500 times what the limit allows in a sample: exactly those runs."""
    vmax, dt = 1.0, 0.002
    t = np.arange(0.0, 2.0, dt)
    x = speed / (2 * np.pi * freq) * np.sin(2 * np.pi * freq * t + phase) + 0.1 * speed * t
    expected = []
    for i, (length, size, negative) in enumerate(spikes):
        first = 40 + 150 * i
        x[first : first + length] += (-1 if negative else 1) * size * vmax * dt
        expected.append((first, first + length - 1))
    assert enc.find_glitches(t, x, vmax) == (expected, [])


# --------------------------------------------------------------------------- fuzzing load_dataset


def tiny_dataset(root: Path, frames: int = 6, encoder_rows: int = 400) -> Path:
    """A small valid dataset from data/ur5e_sweeps: 40x30 images (one a JPEG), the first
    rows of its frames, encoder log and truth."""
    root.mkdir(parents=True)
    shutil.copyfile(SWEEPS / "robot.urdf", root / "robot.urdf")
    meta = json.loads((SWEEPS / "metadata.json").read_text())
    meta["cameras"][0].update(width=40, height=30, K=[[32.0, 0.0, 19.5], [0.0, 32.0, 14.5], [0.0, 0.0, 1.0]])
    meta["motion"] = (
        None  # every sweep's segment lies after the log's first rows: refused as a clock mismatch
    )
    (root / "metadata.json").write_text(json.dumps(meta, indent=1))
    rows = read_rows(SWEEPS / "frames.csv")[: frames + 1]
    (root / "images" / "cam0").mkdir(parents=True)
    for i, r in enumerate(rows[1:]):
        image = np.full((30, 40), 40 * i, np.uint8)
        image[5:20, 10:25] = 255 - 40 * i
        if i == frames - 1:
            r[3] = r[3].replace(".png", ".jpg")
        cv2.imwrite(str(root / r[3]), image)
    write_rows(root / "frames.csv", rows)
    lines = (SWEEPS / "encoders.csv").read_text().splitlines()[: encoder_rows + 1]
    (root / "encoders.csv").write_text("\n".join(lines) + "\n")
    truth = json.loads((SWEEPS / "truth.json").read_text())
    truth["frames"] = truth["frames"][:frames]
    (root / "truth.json").write_text(json.dumps(truth))
    return root


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    root = tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds")
    assert isinstance(load_dataset(root), Dataset)
    return root


_leaf = (
    st.none()
    | st.booleans()
    | st.integers(-(2**70), 2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.sampled_from([0, -1, 1e9, 1e-12, "", "rad", "deg", "world", "cam0", "flange", [], {}])
)
JSON_VALUES = st.recursive(
    _leaf,
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=3),
    max_leaves=10,
)
CELLS = st.one_of(
    st.text(max_size=12),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**12), 10**12).map(str),
    st.sampled_from(
        ["", "nan", "inf", "-0", "1e9", "1e400", "cam0", "cam1", "images/cam0/000000.png", "../x"]
    ),
)


def _paths(node, prefix=()):
    """Every (container path, key) in a JSON document."""
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for k, v in items:
        out.append((prefix, k))
        out += _paths(v, (*prefix, k))
    return out


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


def _mutate(root: Path, draw) -> str:
    """One random corruption of the dataset in `root`; returns its description."""
    files = sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())
    kind = draw(
        st.sampled_from(
            ["json", "json", "json", "csv_cell", "csv_cell", "csv_lines", "image", "delete", "bytes"]
        )
    )
    if kind == "json":
        name = draw(st.sampled_from([f for f in ("metadata.json", "truth.json") if f in files] or files))
        try:
            doc = json.loads((root / name).read_text())
        except (ValueError, UnicodeDecodeError):
            return "json (unreadable)"
        spots = _paths(doc)
        op = draw(st.sampled_from(["replace", "delete", "add"]))
        if not spots or op == "add":
            containers = [()] + [(*p, k) for p, k in spots if isinstance(_get(doc, (*p, k)), dict)]
            where = draw(st.sampled_from(containers))
            target = _get(doc, where)
            if isinstance(target, dict):
                target[draw(st.text(max_size=8))] = draw(JSON_VALUES)
            else:
                doc = draw(JSON_VALUES)
        else:
            path, key = draw(st.sampled_from(spots))
            parent = _get(doc, path)
            if op == "replace":
                parent[key] = draw(JSON_VALUES)
            else:
                del parent[key]
        (root / name).write_text(json.dumps(doc))
        return f"json {op} in {name}"
    if kind in ("csv_cell", "csv_lines"):
        name = draw(st.sampled_from(["frames.csv", "encoders.csv"]))
        if name not in files:
            return "csv (gone)"
        lines = (root / name).read_bytes().decode("utf-8", "replace").splitlines()
        if not lines:
            return "csv (empty)"
        i = draw(st.integers(0, len(lines) - 1))
        if kind == "csv_cell":
            cells = lines[i].split(",")
            cells[draw(st.integers(0, len(cells) - 1))] = draw(CELLS)
            lines[i] = ",".join(cells)
        else:
            op = draw(st.sampled_from(["delete", "duplicate", "swap", "blank", "truncate"]))
            j = draw(st.integers(0, len(lines) - 1))
            if op == "delete":
                del lines[i]
            elif op == "duplicate":
                lines.insert(j, lines[i])
            elif op == "swap":
                lines[i], lines[j] = lines[j], lines[i]
            elif op == "blank":
                lines.insert(i, "")
            else:
                text = "\n".join(lines)
                lines = text[: draw(st.integers(0, len(text)))].splitlines()
        (root / name).write_text("\n".join(lines) + "\n")
        return f"{kind} in {name}"
    if kind == "image":
        images = [f for f in files if f.startswith("images/")]
        if not images:
            return "image (none)"
        victim = root / draw(st.sampled_from(images))
        op = draw(st.sampled_from(["truncate", "random", "resize", "empty"]))
        data = victim.read_bytes()
        if op == "truncate":
            victim.write_bytes(data[: draw(st.integers(0, max(0, len(data) - 1)))])
        elif op == "random":
            victim.write_bytes(draw(st.binary(max_size=64)))
        elif op == "resize":
            victim.write_bytes(png(draw(st.integers(1, 64)), draw(st.integers(1, 64))))
        else:
            victim.write_bytes(b"")
        return f"image {op}"
    if kind == "delete":
        (root / draw(st.sampled_from(files))).unlink()
        return "delete"
    victim = root / draw(st.sampled_from(files))
    victim.write_bytes(draw(st.binary(max_size=80)))
    return "bytes"


@settings(
    max_examples=250,
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_fuzzed_datasets_load_or_fail_with_a_named_error_and_stay_untouched(tiny, data):
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        shutil.copytree(tiny, root)
        done = [_mutate(root, data.draw) for _ in range(data.draw(st.integers(1, 3)))]
        before = _digest(root)
        try:
            d = load_dataset(root)
        except JaxcalError as e:
            assert str(e) and "Traceback" not in str(e), done
        else:
            n = len(d.frames["file"])
            assert all(len(v) == n for v in d.frames.values()) and n > 0
            assert all((root / f).is_file() for f in d.frames["file"])
            if d.encoder_t is not None:
                assert np.all(np.diff(d.encoder_t) > 0) and np.all(np.isfinite(d.encoder_motor))
                assert d.encoder_motor.shape == (len(d.encoder_t), len(d.joint_names))
        assert _digest(root) == before, done
