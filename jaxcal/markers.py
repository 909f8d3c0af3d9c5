"""Fiducial targets: ChArUco boards, ArUco markers and grids, chessboards, circle grids (OpenCV edge).

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
- The grid kinds use the ChArUco convention (origin at the printed pattern's
  top-left corner, x right, y down, z into the board):
  - `chessboard`: `squares` = (columns, rows) of squares, `square_length`;
    features the (columns-1) x (rows-1) inner corners, corner (i, j) at
    ((i+1) s, (j+1) s), id = j (columns-1) + i (OpenCV's
    `findChessboardCornersSB` order). Square (0, 0) is black.
  - `circles`: a symmetric circle grid, `squares` = (columns, rows) of
    circles (OpenCV's pattern size), `square_length` = centre spacing,
    `marker_length` = circle diameter; centre (i, j) at ((i+1/2) s, (j+1/2) s),
    id = j columns + i (`findCirclesGrid` order).
  - `acircles`: OpenCV's asymmetric circle grid, `squares` = (points per
    row, rows), `square_length` = s as in OpenCV's sample (rows s apart,
    circles 2 s apart within a row, odd rows shifted by s), `marker_length` =
    circle diameter; point (j, i) at ((2j + i mod 2 + 1/2) s, (i + 1/2) s),
    id = i columns + j.
  - `aruco_grid`: an ArUco (or AprilTag) grid board, `squares` = (markers
    across, markers down), `marker_length` = marker side, `square_length` =
    marker pitch (side + gap), ids consecutive from `first_id` row by row;
    features the 4 corners of every marker, id = 4 (marker id - first id) +
    corner (OpenCV's `GridBoard` object points).
- AprilTag: any kind with markers takes an AprilTag dictionary
  (`DICT_APRILTAG_36h11`, `DICT_APRILTAG_25h9`, ...).

A target may be symmetric: a square-free chessboard with an even number of
squares in total along its two sides (columns + rows even), or any
symmetric circle grid, looks the same turned 180 degrees (a square one also
at 90), so the image alone cannot tell which corner is id 0.
`TargetSpec.rotations()` lists those turns; the vision front end resolves
chessboards by the colour of their squares (columns + rows odd), and the
hand-eye front end resolves what is left by the robot's motion
(`jaxcal.vision.hand_eye_from_detections`).

Both the renderer (`jaxcal.sim`) and the vision front end build their board
from the same spec, so the texture and the object points cannot disagree.
"""

from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

KINDS = ("charuco", "aruco", "chessboard", "circles", "acircles", "aruco_grid")
#: Kinds whose features form a full grid found at once (no per-feature ids in the image).
GRID_KINDS = ("chessboard", "circles", "acircles")


def aruco_dictionary(name: str):
    """OpenCV's predefined dictionary `name` (e.g. `"DICT_4X4_50"`)."""
    code = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    if code is None:
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise ValueError(f"unknown ArUco dictionary {name!r}; known: {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(code)


#: Pixels per bit cell (a marker's bits and its black border) below which ArUco markers are lost:
#: rendered 4x4 markers 8 or 12 px wide (1.3, 2 px a cell; their shorter side, median over the
#: capture) are found in none of the images, 17 px wide (2.8) in 80-100 % of them.
MIN_PX_PER_CELL = 2.5
#: A target length above this (m) is taken for millimetres given as metres and refused.
MAX_LENGTH_M = 2.0


@dataclass(frozen=True)
class TargetSpec:
    """What is printed on one plate. Lengths in metres.

    - `kind`: `"charuco"` (default), `"aruco"` (one marker), `"chessboard"`,
      `"circles"`, `"acircles"` or `"aruco_grid"` (see the module docstring).
    - `dictionary`: OpenCV dictionary name (kinds with markers).
    - `squares`: (columns, rows): of squares (ChArUco, chessboard), circles
      (circle grids) or markers (ArUco grid).
    - `square_length`, `marker_length`: ChArUco square and marker side; for
      ArUco only `marker_length` is used; chessboard: `square_length`; circle
      grids: spacing and circle diameter; ArUco grid: pitch and marker side.
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
        try:  # JSON gives a list: the target is hashed (detector caches), so it holds a tuple
            squares = tuple(int(n) for n in self.squares)
        except (TypeError, ValueError):
            squares = ()
        if len(squares) != 2 or list(squares) != list(self.squares):
            raise ValueError(
                f"{where}: squares must be two whole numbers (columns, rows), got {self.squares!r}"
            )
        object.__setattr__(self, "squares", squares)
        if self.kind not in KINDS:
            raise ValueError(f"{where}: kind must be one of {KINDS}, got {self.kind!r}")
        if not (self.marker_length > 0 and self.margin >= 0):
            raise ValueError(f"{where}: marker_length must be > 0 and margin >= 0")
        for name in ("square_length", "marker_length", "margin"):
            if getattr(self, name) > MAX_LENGTH_M:
                raise ValueError(
                    f"{where}: {name} = {getattr(self, name):g} m; lengths are in metres "
                    f"(millimetres given? {getattr(self, name):g} mm = {getattr(self, name) / 1e3:g} m)"
                )
        if self.kind == "aruco":
            cols, rows = 1, 1
        else:
            cols, rows = self.squares
        if self.kind == "charuco" and (cols < 2 or rows < 2):
            raise ValueError(f"{where}: a ChArUco board needs at least 2x2 squares, got {self.squares}")
        if self.kind == "chessboard" and (cols < 2 or rows < 2 or (cols - 1) * (rows - 1) < 4):
            raise ValueError(
                f"{where}: a chessboard needs at least 4 inner corners, got {self.squares} squares"
            )
        if self.kind in ("circles", "acircles", "aruco_grid") and (cols < 1 or rows < 1 or cols * rows < 3):
            raise ValueError(f"{where}: a {self.kind} target needs at least 3 features, got {self.squares}")
        if self.kind in ("charuco", "aruco_grid") and not 0 < self.marker_length < self.square_length:
            raise ValueError(f"{where}: need 0 < marker_length < square_length")
        if self.kind in ("chessboard", "circles") and not self.square_length > 0:
            raise ValueError(f"{where}: square_length must be > 0")
        if self.kind == "circles" and not self.marker_length < self.square_length:
            raise ValueError(f"{where}: the circle diameter (marker_length) must be below the spacing")
        if self.kind == "acircles" and not self.marker_length < self.square_length:
            raise ValueError(
                f"{where}: the circle diameter (marker_length) must be below square_length "
                "(neighbouring rows are square_length apart)"
            )
        if self.kind in GRID_KINDS:
            return
        dictionary = aruco_dictionary(self.dictionary)
        n = self.num_markers
        size = dictionary.bytesList.shape[0]
        if self.first_id < 0 or self.first_id + n > size:
            raise ValueError(
                f"{where}: marker ids {self.first_id}..{self.first_id + n - 1} do not fit in "
                f"{self.dictionary} ({size} markers)"
            )

    @property
    def min_marker_px(self) -> float | None:
        """The least side (px) a marker needs in an image to be found: `MIN_PX_PER_CELL` times its
        bit cells and black border. None for kinds without markers."""
        if self.kind in GRID_KINDS:
            return None
        return MIN_PX_PER_CELL * (int(aruco_dictionary(self.dictionary).markerSize) + 2)

    # ------------------------------------------------------------------ structure

    @property
    def num_markers(self) -> int:
        if self.kind == "aruco":
            return 1
        cols, rows = self.squares
        if self.kind == "charuco":
            return (cols * rows) // 2
        if self.kind == "aruco_grid":
            return cols * rows
        return 0

    @property
    def marker_ids(self) -> np.ndarray:
        return self.first_id + np.arange(self.num_markers)

    @property
    def pattern(self) -> tuple[int, int]:
        """OpenCV's pattern size of a grid kind: (inner corners per row, rows) for a chessboard,
        (circles per row, rows) for circle grids."""
        cols, rows = self.squares
        if self.kind == "chessboard":
            return cols - 1, rows - 1
        if self.kind in ("circles", "acircles"):
            return cols, rows
        raise ValueError(f"target {self.name!r}: a {self.kind} target has no OpenCV pattern size")

    def board(self):
        """The OpenCV `CharucoBoard` (ChArUco) or `GridBoard` (ArUco grid)."""
        if self.kind == "aruco_grid":
            return cv2.aruco.GridBoard(
                tuple(self.squares),
                self.marker_length,
                self.square_length - self.marker_length,
                aruco_dictionary(self.dictionary),
                self.marker_ids,
            )
        if self.kind != "charuco":
            raise ValueError(f"target {self.name!r} is a {self.kind} target, not a marker board")
        return cv2.aruco.CharucoBoard(
            tuple(self.squares),
            self.square_length,
            self.marker_length,
            aruco_dictionary(self.dictionary),
            self.marker_ids,
        )

    def points(self) -> np.ndarray:
        """Every feature's 3D point in the target frame, indexed by feature id, (N, 3) m."""
        s = self.square_length
        if self.kind == "charuco":
            return np.asarray(self.board().getChessboardCorners(), np.float64).reshape(-1, 3)
        if self.kind == "aruco":
            h = 0.5 * self.marker_length
            return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        if self.kind == "aruco_grid":  # OpenCV's GridBoard object points, in float64
            cols, _ = self.squares
            row, col = np.divmod(np.arange(self.num_markers), cols)
            m = self.marker_length
            square = np.array([[0.0, 0.0], [m, 0.0], [m, m], [0.0, m]])
            xy = (np.stack([col, row], 1)[:, None, :] * s + square).reshape(-1, 2)
            return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)
        w, h = self.pattern
        j, i = np.divmod(np.arange(w * h), w)  # row j, column i; id = j w + i
        if self.kind == "chessboard":
            xy = np.stack([(i + 1.0) * s, (j + 1.0) * s], axis=1)
        elif self.kind == "circles":
            xy = np.stack([(i + 0.5) * s, (j + 0.5) * s], axis=1)
        else:  # acircles: OpenCV's ((2 j + i % 2) s, i s) with i the row
            xy = np.stack([(2 * i + j % 2 + 0.5) * s, (j + 0.5) * s], axis=1)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    @property
    def num_points(self) -> int:
        return len(self.points())

    def rotations(self) -> list[np.ndarray]:
        """The in-plane turns that map the feature points onto themselves, as id permutations.

        Each entry `perm` (N,) int: feature `k` lands where feature `perm[k]`
        was, under a rotation of the plate about its normal through the
        points' centre (0, 90, 180 or 270 degrees). The first is the identity.
        Chessboards also need the square colours to match (square (0, 0) is
        black), so a board with columns + rows odd has only the identity.
        Boards with marker ids are never symmetric (identity only).
        """
        P = self.points()[:, :2]
        ident = np.arange(len(P))
        if self.kind not in GRID_KINDS:
            return [ident]
        c = P.mean(0)
        scale = np.max(np.abs(P - c)) + 1e-12
        out = [ident]
        for k in (1, 2, 3):
            a = 0.5 * np.pi * k
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            Q = (P - c) @ R.T + c
            d = np.linalg.norm(Q[:, None] - P[None], axis=-1)
            perm = np.argmin(d, axis=1)
            if np.max(d[ident, perm]) > 1e-9 * scale or len(set(perm.tolist())) != len(P):
                continue
            if self.kind == "chessboard" and not self._colours_kept(perm):
                continue
            out.append(perm)
        return out

    def _colours_kept(self, perm: np.ndarray) -> bool:
        """Whether relabelling the inner corners by `perm` keeps every square's colour."""
        w, _ = self.pattern
        j, i = np.divmod(np.arange(len(perm)), w)
        jp, ip = np.divmod(perm, w)
        # The square whose top-left inner corner is corner (i, j) is square (i+1, j+1),
        # black iff i + j is even; after the turn that corner is the square's other end.
        a, b = i[0] + j[0], ip[0] + jp[0]
        return (a - b) % 2 == 0 if self.rotation_angle(perm) in (0, 180) else (a - b) % 2 == 1

    def rotation_angle(self, perm: np.ndarray) -> int:
        """The turn (degrees, 0/90/180/270) that `perm` (one of `rotations()`) stands for."""
        P = self.points()[:, :2]
        c = P.mean(0)
        k = int(np.argmax(np.linalg.norm(P - c, axis=1)))
        u, v = P[k] - c, P[perm[k]] - c
        return int(round(np.degrees(np.arctan2(u[0] * v[1] - u[1] * v[0], u @ v)))) % 360

    @property
    def symmetric(self) -> bool:
        """True when the image alone cannot say which feature is which (see `rotations`)."""
        return len(self.rotations()) > 1

    # ------------------------------------------------------------------ printing

    def pattern_extent(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The printed pattern's top-left corner and unit right/down directions, in the target frame.

        "Top-left" and "down" are as the pattern image is read (row 0 at the top).
        """
        if self.kind == "aruco":
            h = 0.5 * self.marker_length
            return np.array([-h, h, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])
        return np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])

    @property
    def pattern_size(self) -> tuple[float, float]:
        """Width and height of the printed pattern (without margin), m."""
        if self.kind == "aruco":
            return self.marker_length, self.marker_length
        cols, rows = self.squares
        s = self.square_length
        if self.kind == "aruco_grid":
            gap = s - self.marker_length
            return cols * s - gap, rows * s - gap
        if self.kind == "acircles":
            return 2 * cols * s, rows * s
        return cols * s, rows * s

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
        if self.kind in ("charuco", "aruco_grid"):
            pattern = self.board().generateImage((pw, ph), marginSize=0, borderBits=1)
        elif self.kind == "aruco":
            pattern = cv2.aruco.generateImageMarker(aruco_dictionary(self.dictionary), self.first_id, pw, 1)
        else:
            pattern = self._grid_image(pw, ph, px_per_m)
        m = int(round(self.margin * px_per_m))
        image = cv2.copyMakeBorder(pattern, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
        top_left, right, down = self.pattern_extent()
        origin = top_left - (m / px_per_m) * (right + down)
        W, H = image.shape[1] / px_per_m, image.shape[0] / px_per_m
        corners = np.stack([origin, origin + W * right, origin + W * right + H * down, origin + H * down])
        return image, corners

    def _grid_image(self, pw: int, ph: int, px_per_m: float) -> np.ndarray:
        """Chessboard squares or circles drawn at their target-frame positions (pattern origin = (0, 0))."""
        if self.kind == "chessboard":
            cols, rows = self.squares
            v, u = np.mgrid[0:ph, 0:pw]
            i = np.minimum(((u + 0.5) / px_per_m // self.square_length).astype(int), cols - 1)
            j = np.minimum(((v + 0.5) / px_per_m // self.square_length).astype(int), rows - 1)
            return np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)
        image = np.full((ph, pw), 255, np.uint8)
        shift = 4  # sub-pixel centres and radius, 1/16 px
        r = int(round(0.5 * self.marker_length * px_per_m * (1 << shift)))
        for x, y, _ in self.points():
            centre = (
                int(round((x * px_per_m - 0.5) * (1 << shift))),
                int(round((y * px_per_m - 0.5) * (1 << shift))),
            )
            cv2.circle(image, centre, r, 0, thickness=-1, lineType=cv2.LINE_AA, shift=shift)
        return image

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
            sq = d["squares"]
            if (
                not isinstance(sq, (list, tuple))
                or len(sq) != 2
                or not all(
                    isinstance(s, (int, float)) and not isinstance(s, bool) and float(s).is_integer()
                    for s in sq
                )
            ):
                raise ValueError(f"{where}: squares: expected two whole numbers [columns, rows], got {sq!r}")
            d["squares"] = tuple(int(s) for s in sq)
        try:
            return cls(**d)
        except TypeError as e:
            raise ValueError(f"{where}: {e}") from None
