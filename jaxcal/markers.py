"""Fiducial targets: ChArUco boards and single ArUco markers (OpenCV edge).

A `TargetSpec` says what is printed on a plate, and defines the plate's own
frame through the 3D points of its features (what PnP is solved against):

- ChArUco: OpenCV's board frame. Origin at the outer corner of the first
  chessboard square, x along the squares' columns, y along the rows, z into
  the board (away from a viewer who reads it): the printed face is on the
  -z side. Features are the inner chessboard corners, id = OpenCV's
  ChArUco corner id.
- ArUco: OpenCV's single-marker frame (`SOLVEPNP_IPPE_SQUARE`): origin at the
  marker centre, x right, y up, z out of the printed face. Features are the 4
  marker corners (top-left, top-right, bottom-right, bottom-left), id =
  4 * (marker id - first id) + corner, the row in `TargetSpec.points()`.

Both the renderer (`jaxcal.sim`) and the vision front end build their board
from the same spec, so the texture and the object points cannot disagree.
"""

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

KINDS = ("charuco", "aruco")


def aruco_dictionary(name: str):
    """OpenCV's predefined dictionary `name` (e.g. `"DICT_4X4_50"`)."""
    code = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    if code is None:
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise ValueError(f"unknown ArUco dictionary {name!r}; known: {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(code)


@dataclass(frozen=True)
class TargetSpec:
    """What is printed on one plate. Lengths in metres.

    - `kind`: `"charuco"` (default) or `"aruco"` (one marker).
    - `dictionary`: OpenCV dictionary name.
    - `squares`: ChArUco (columns, rows).
    - `square_length`, `marker_length`: ChArUco square and marker side; for
      ArUco only `marker_length` is used.
    - `first_id`: the first marker id (ChArUco boards use consecutive ids from
      it, so several boards in one scene stay distinguishable).
    - `margin`: white border around the pattern on the plate.
    """

    kind: str = "charuco"
    dictionary: str = "DICT_4X4_50"
    squares: tuple[int, int] = (4, 3)
    square_length: float = 0.05
    marker_length: float = 0.037
    first_id: int = 0
    margin: float = 0.01
    name: str = field(default="target", compare=False)

    def __post_init__(self):
        where = f"target {self.name!r}"
        if self.kind not in KINDS:
            raise ValueError(f"{where}: kind must be one of {KINDS}, got {self.kind!r}")
        dictionary = aruco_dictionary(self.dictionary)
        if not (self.marker_length > 0 and self.margin >= 0):
            raise ValueError(f"{where}: marker_length must be > 0 and margin >= 0")
        if self.kind == "charuco":
            cols, rows = self.squares
            if cols < 2 or rows < 2:
                raise ValueError(f"{where}: a ChArUco board needs at least 2x2 squares, got {self.squares}")
            if not 0 < self.marker_length < self.square_length:
                raise ValueError(f"{where}: need 0 < marker_length < square_length")
        n = self.num_markers
        size = dictionary.bytesList.shape[0]
        if self.first_id < 0 or self.first_id + n > size:
            raise ValueError(
                f"{where}: marker ids {self.first_id}..{self.first_id + n - 1} do not fit in "
                f"{self.dictionary} ({size} markers)"
            )

    # ------------------------------------------------------------------ structure

    @property
    def num_markers(self) -> int:
        if self.kind == "aruco":
            return 1
        cols, rows = self.squares
        return (cols * rows) // 2

    @property
    def marker_ids(self) -> np.ndarray:
        return self.first_id + np.arange(self.num_markers)

    def board(self):
        """The OpenCV `CharucoBoard` (ChArUco only)."""
        if self.kind != "charuco":
            raise ValueError(f"target {self.name!r} is a single ArUco marker, not a board")
        return cv2.aruco.CharucoBoard(
            tuple(self.squares),
            self.square_length,
            self.marker_length,
            aruco_dictionary(self.dictionary),
            self.marker_ids,
        )

    def points(self) -> np.ndarray:
        """Every feature's 3D point in the target frame, indexed by feature id, (N, 3) m."""
        if self.kind == "charuco":
            return np.asarray(self.board().getChessboardCorners(), np.float64).reshape(-1, 3)
        h = 0.5 * self.marker_length
        return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])

    @property
    def num_points(self) -> int:
        return len(self.points())

    # ------------------------------------------------------------------ printing

    def pattern_extent(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The printed pattern's top-left corner and unit right/down directions, in the target frame.

        "Top-left" and "down" are as the pattern image is read (row 0 at the top).
        """
        if self.kind == "charuco":
            return np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        h = 0.5 * self.marker_length
        return np.array([-h, h, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])

    @property
    def pattern_size(self) -> tuple[float, float]:
        """Width and height of the printed pattern (without margin), m."""
        if self.kind == "charuco":
            cols, rows = self.squares
            return cols * self.square_length, rows * self.square_length
        return self.marker_length, self.marker_length

    def image(self, px_per_m: float = 4000.0) -> tuple[np.ndarray, np.ndarray]:
        """The plate as printed (pattern plus white margin), greyscale uint8.

        **Returns:** `(image, corners)`: the image and the target-frame positions
        of its top-left, top-right, bottom-right and bottom-left outer corners
        (4, 3). Pixel $(u, v)$ (OpenCV's pixel-centre convention) covers the
        point `corners[0] + ((u + 0.5) right + (v + 0.5) down) / px_per_m`.
        """
        w, h = self.pattern_size
        pw, ph = int(round(w * px_per_m)), int(round(h * px_per_m))
        if abs(pw - w * px_per_m) > 1e-6 or abs(ph - h * px_per_m) > 1e-6:
            raise ValueError(f"target {self.name!r}: px_per_m must give a whole number of pixels")
        if self.kind == "charuco":
            pattern = self.board().generateImage((pw, ph), marginSize=0, borderBits=1)
        else:
            pattern = cv2.aruco.generateImageMarker(aruco_dictionary(self.dictionary), self.first_id, pw, 1)
        m = int(round(self.margin * px_per_m))
        image = cv2.copyMakeBorder(pattern, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
        top_left, right, down = self.pattern_extent()
        origin = top_left - (m / px_per_m) * (right + down)
        W, H = image.shape[1] / px_per_m, image.shape[0] / px_per_m
        corners = np.stack([origin, origin + W * right, origin + W * right + H * down, origin + H * down])
        return image, corners

    def front_normal(self) -> np.ndarray:
        """Unit normal of the printed face, pointing toward a viewer who reads it (target frame)."""
        _, right, down = self.pattern_extent()
        return -np.cross(right, down)

    # ------------------------------------------------------------------ serialisation

    def to_dict(self) -> dict:
        d = asdict(self)
        d["squares"] = list(self.squares)
        return d

    @classmethod
    def from_dict(cls, d: dict, *, where: str = "target") -> "TargetSpec":
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"{where}: unknown fields {sorted(unknown)}; known fields are {sorted(known)}")
        d = dict(d)
        if "squares" in d:
            d["squares"] = tuple(int(s) for s in d["squares"])
        try:
            return cls(**d)
        except TypeError as e:
            raise ValueError(f"{where}: {e}") from None
