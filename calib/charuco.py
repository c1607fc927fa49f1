"""ChArUco boards: detection, camera intrinsics and Vicon-free extrinsics from shared board views.

Pipeline (OpenCV 5 ``cv2.aruco``): :func:`detect_charuco` runs ``CharucoDetector.detectBoard``
then ``CharucoBoard.matchImagePoints`` on one image and gives a :class:`BoardView` (corner ids,
image points in px, board points in m). :func:`calibrate_intrinsics` feeds the views of one camera
to ``cv2.calibrateCameraExtended`` after checking that they can determine the intrinsics (enough
views and corners, image coverage, board tilt) and refuses a fit above a reprojection ceiling.
:func:`calibrate_extrinsics` takes views of several cameras with fixed intrinsics, groups the
views taken at the same instant (timestamps on one clock, given by the caller), builds a pose graph
(``solvePnP`` board → camera per view, cameras chained through shared instants) and refines all
camera poses and board poses jointly with ``scipy.optimize.least_squares`` (sparse Jacobian,
``soft_l1`` then 3σ rejection and a plain refit).

Frames and units:
    board: origin at the outer corner of the top-left square of the printed board, +X along
        the columns, +Y down the rows, +Z into the board (away from a viewer of the print); metres.
    camera: OpenCV (+Z forward, +X right, +Y down), pixel (0, 0) the centre of the top-left pixel;
        the refinement projects with :func:`calib.camera_model.project_camera`.
    world (extrinsics): the reference camera's frame (``world="camera"``, the default; its
        ``T_world_cam`` is the identity and ``Calibration.world_frame`` is its name), or the
        board's frame at the instant seen by the most cameras (``world="board"``;
        ``world_frame = "board"``), useful when the board lies fixed on the floor.

Board description files are TOML::

    [board]
    squares_x = 7            # squares along the board's X (columns)
    squares_y = 5            # squares along its Y (rows)
    square_length_m = 0.06
    marker_length_m = 0.045
    dictionary = "DICT_4X4_50"
    legacy_pattern = false   # true for boards printed before OpenCV 4.6 with an even row count
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Literal, get_args

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from mocaprig.calib.calibration import Calibration, CameraCalibration
from mocaprig.calib.camera_model import project_camera
from mocaprig.errors import CalibrationError, ValidationError
from mocaprig.validation import check_positive

__all__ = [
    "ArucoDictionary",
    "BoardView",
    "CharucoBoardSpec",
    "IntrinsicsResult",
    "WorldChoice",
    "board_image",
    "calibrate_extrinsics",
    "calibrate_intrinsics",
    "detect_charuco",
    "group_views_by_time",
    "read_board_spec",
    "read_intrinsics",
    "write_board_spec",
    "write_intrinsics",
]

_log = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
I32 = npt.NDArray[np.int32]

#: The predefined ArUco dictionaries a board can use (``cv2.aruco.DICT_*``).
ArucoDictionary = Literal[
    "DICT_4X4_50",
    "DICT_4X4_100",
    "DICT_4X4_250",
    "DICT_4X4_1000",
    "DICT_5X5_50",
    "DICT_5X5_100",
    "DICT_5X5_250",
    "DICT_5X5_1000",
    "DICT_6X6_50",
    "DICT_6X6_100",
    "DICT_6X6_250",
    "DICT_6X6_1000",
    "DICT_7X7_50",
    "DICT_7X7_100",
    "DICT_7X7_250",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
]
_DICTIONARIES: Final = get_args(ArucoDictionary)

#: Where the extrinsic calibration puts the world frame.
WorldChoice = Literal["camera", "board"]

_INTRINSICS_FORMAT: Final = 1


# --------------------------------------------------------------------------------------------
# Board description


@dataclass(frozen=True, slots=True)
class CharucoBoardSpec:
    """A ChArUco board as printed.

    Attributes:
        squares_x: Squares along the board's X axis (columns), ≥ 3.
        squares_y: Squares along its Y axis (rows), ≥ 3.
        square_length_m: Side of one chessboard square (m), as measured on the print.
        marker_length_m: Side of one ArUco marker (m), smaller than the square.
        dictionary: The ArUco dictionary (``cv2.aruco.DICT_*`` name).
        legacy_pattern: The pre-4.6 layout of boards with an even number of rows (calib.io stock
            boards and older prints); a wrong value makes such boards undetectable.

    Raises:
        ValidationError: sizes out of range, an unknown dictionary, or a board with more
            markers than the dictionary holds.
    """

    squares_x: int
    squares_y: int
    square_length_m: float
    marker_length_m: float
    dictionary: ArucoDictionary = "DICT_4X4_50"
    legacy_pattern: bool = False

    def __post_init__(self) -> None:
        for name in ("squares_x", "squares_y"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or not 3 <= int(value) <= 100:
                msg = f"ChArUco board: {name} must be an integer in [3, 100], got {value!r}"
                raise ValidationError(msg)
        check_positive(self.square_length_m, name="ChArUco board square_length_m")
        check_positive(self.marker_length_m, name="ChArUco board marker_length_m")
        if self.square_length_m > 1.0:
            msg = (
                f"ChArUco board: square_length_m = {self.square_length_m} m is over 1 m; "
                "lengths are in metres (millimetres given?)"
            )
            raise ValidationError(msg)
        if self.marker_length_m >= self.square_length_m:
            msg = (
                f"ChArUco board: marker_length_m ({self.marker_length_m}) must be smaller than "
                f"square_length_m ({self.square_length_m})"
            )
            raise ValidationError(msg)
        if self.dictionary not in _DICTIONARIES:
            msg = (
                f"ChArUco board: unknown dictionary {self.dictionary!r}; use one of "
                f"{', '.join(_DICTIONARIES)}"
            )
            raise ValidationError(msg)
        n_markers = (self.squares_x * self.squares_y) // 2
        size = _dictionary(self.dictionary).bytesList.shape[0]
        if n_markers > size:
            msg = (
                f"ChArUco board: {self.squares_x}×{self.squares_y} squares need {n_markers} "
                f"markers but {self.dictionary} holds {size}; choose a larger dictionary"
            )
            raise ValidationError(msg)
        object.__setattr__(self, "squares_x", int(self.squares_x))
        object.__setattr__(self, "squares_y", int(self.squares_y))
        object.__setattr__(self, "square_length_m", float(self.square_length_m))
        object.__setattr__(self, "marker_length_m", float(self.marker_length_m))
        object.__setattr__(self, "legacy_pattern", bool(self.legacy_pattern))

    @property
    def n_corners(self) -> int:
        """Number of inner chessboard corners, ``(squares_x − 1)·(squares_y − 1)``."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the chessboard area (m)."""
        return self.squares_x * self.square_length_m, self.squares_y * self.square_length_m

    @property
    def corners_m(self) -> F64:
        """Board coordinates of the inner corners by id, shape ``(n_corners, 3)`` (m, z = 0)."""
        out: F64 = np.asarray(self.board().getChessboardCorners(), dtype=np.float64)
        return out.reshape(-1, 3)

    def board(self) -> cv2.aruco.CharucoBoard:
        """A new ``cv2.aruco.CharucoBoard`` for this description."""
        b = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y),
            self.square_length_m,
            self.marker_length_m,
            _dictionary(self.dictionary),
        )
        b.setLegacyPattern(self.legacy_pattern)
        return b

    def to_dict(self) -> dict[str, Any]:
        """Plain TOML/JSON-ready view (the ``[board]`` table of a board file)."""
        return {
            "squares_x": self.squares_x,
            "squares_y": self.squares_y,
            "square_length_m": self.square_length_m,
            "marker_length_m": self.marker_length_m,
            "dictionary": self.dictionary,
            "legacy_pattern": self.legacy_pattern,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "board") -> CharucoBoardSpec:
        """Build from :meth:`to_dict`'s view.

        Raises:
            ValidationError: a missing or unknown key, or invalid values (named with ``source``).
        """
        keys = {"squares_x", "squares_y", "square_length_m", "marker_length_m"}
        missing = sorted(keys - set(data))
        unknown = sorted(set(data) - keys - {"dictionary", "legacy_pattern"})
        if missing or unknown:
            msg = (
                f"{source}: board description lacks {missing} / has unknown keys {unknown}; "
                "expected squares_x, squares_y, square_length_m, marker_length_m, dictionary, "
                "legacy_pattern"
            )
            raise ValidationError(msg)
        try:
            return cls(
                squares_x=int(data["squares_x"]),
                squares_y=int(data["squares_y"]),
                square_length_m=float(data["square_length_m"]),
                marker_length_m=float(data["marker_length_m"]),
                dictionary=str(data.get("dictionary", "DICT_4X4_50")),  # type: ignore[arg-type]
                legacy_pattern=bool(data.get("legacy_pattern", False)),
            )
        except (TypeError, ValueError) as err:
            if isinstance(err, ValidationError):
                msg = f"{source}: {err}"
            else:
                msg = f"{source}: board description has a value of the wrong type: {err}"
            raise ValidationError(msg) from err


def _dictionary(name: str) -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def read_board_spec(path: Path) -> CharucoBoardSpec:
    """Read a board description (TOML with a ``[board]`` table, or the table's keys at top level).

    Raises:
        ValidationError: the file is missing, not TOML, or does not describe a board.
    """
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        msg = f"board file {path} does not exist; see `mocaprig calibrate intrinsics --help`"
        raise ValidationError(msg) from err
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        msg = f"board file {path} is not readable TOML: {err}"
        raise ValidationError(msg) from err
    table = data.get("board", data)
    if not isinstance(table, dict):
        msg = f"board file {path}: [board] must be a table"
        raise ValidationError(msg)
    return CharucoBoardSpec.from_dict(table, source=f"board file {path}")


def write_board_spec(path: Path, spec: CharucoBoardSpec, *, overwrite: bool = False) -> None:
    """Write a board description as TOML (``[board]`` table).

    Raises:
        ValidationError: ``path`` exists and ``overwrite`` is false.
    """
    _refuse_existing(path, overwrite)
    Path(path).write_text("[board]\n" + _toml_table(spec.to_dict()), encoding="utf-8")


def board_image(
    spec: CharucoBoardSpec, *, px_per_m: float = 4000.0, margin_m: float | None = None
) -> npt.NDArray[np.uint8]:
    """The printable board (``CharucoBoard.generateImage``) with a white margin.

    Args:
        spec: The board.
        px_per_m: Resolution (4000 px/m ≈ 100 dpi); print at exactly the board's size.
        margin_m: White margin around the squares (m); half a square by default.

    Returns:
        A ``uint8`` image, row 0 = the board's top (board +Y points down the image).
    """
    check_positive(px_per_m, name="px_per_m")
    margin = 0.5 * spec.square_length_m if margin_m is None else float(margin_m)
    w_m, h_m = spec.size_m
    w = round(w_m * px_per_m)
    h = round(h_m * px_per_m)
    img = np.asarray(spec.board().generateImage((w, h), marginSize=0, borderBits=1), np.uint8)
    pad = round(margin * px_per_m)
    out: npt.NDArray[np.uint8] = np.asarray(
        cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255), np.uint8
    )
    return out


# --------------------------------------------------------------------------------------------
# Detection


@dataclass(frozen=True, slots=True)
class BoardView:
    """What one image shows of the board.

    Attributes:
        corner_ids: Ids of the detected inner corners, shape ``(N,)`` (int32).
        image_points: Their pixel positions, shape ``(N, 2)`` (px).
        object_points: Their board coordinates, shape ``(N, 3)`` (m, z = 0).
        markers_seen: ArUco markers of the board's dictionary found in the image (even when no
            corner could be interpolated; helps diagnose a wrong board description).
        t_ns: The image's time on the caller's clock (ns), used to pair views across cameras.
    """

    corner_ids: I32 = field(repr=False)
    image_points: F64 = field(repr=False)
    object_points: F64 = field(repr=False)
    markers_seen: int = 0
    t_ns: int | None = None

    def __post_init__(self) -> None:
        ids = np.asarray(self.corner_ids, dtype=np.int32).reshape(-1)
        img = np.asarray(self.image_points, dtype=np.float64).reshape(-1, 2)
        obj = np.asarray(self.object_points, dtype=np.float64).reshape(-1, 3)
        if not ids.shape[0] == img.shape[0] == obj.shape[0]:
            msg = (
                f"BoardView: {ids.shape[0]} ids, {img.shape[0]} image points and "
                f"{obj.shape[0]} object points; they must match"
            )
            raise ValidationError(msg)
        for a in (ids, img, obj):
            a.setflags(write=False)
        object.__setattr__(self, "corner_ids", ids)
        object.__setattr__(self, "image_points", img)
        object.__setattr__(self, "object_points", obj)

    @property
    def n_corners(self) -> int:
        """Number of detected corners."""
        return int(self.corner_ids.shape[0])

    def with_time(self, t_ns: int) -> BoardView:
        """The same view stamped with ``t_ns``."""
        return BoardView(
            self.corner_ids, self.image_points, self.object_points, self.markers_seen, int(t_ns)
        )


def _to_gray8(image: npt.ArrayLike) -> npt.NDArray[np.uint8]:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or img.size == 0:
        msg = f"detect_charuco(): expected a grey image (H, W), got shape {img.shape}"
        raise ValidationError(msg)
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        # DAVIS APS frames hold 10-bit values in 16-bit words; other 16-bit images use the range.
        full = 1023.0 if int(img.max()) <= 1023 else 65535.0
        return np.clip(img.astype(np.float64) * (255.0 / full) + 0.5, 0, 255).astype(np.uint8)
    if np.issubdtype(img.dtype, np.floating):
        out: npt.NDArray[np.uint8] = np.clip(np.nan_to_num(img) * 255.0 + 0.5, 0, 255).astype(
            np.uint8
        )
        return out
    msg = f"detect_charuco(): unsupported image dtype {img.dtype}; give uint8, uint16 or float"
    raise ValidationError(msg)


def detect_charuco(
    image: npt.ArrayLike,
    spec: CharucoBoardSpec,
    *,
    t_ns: int | None = None,
    min_corners: int = 4,
) -> BoardView:
    """Detect the board's inner corners in one image.

    Args:
        image: Grey image, ``uint8``, ``uint16`` (10-bit DAVIS APS values or full range) or
            float in [0, 1], shape ``(H, W)``.
        spec: The board to look for.
        t_ns: The image's time (ns), stored in the view.
        min_corners: Fewer corners than this count as not seen (empty view).

    Returns:
        A :class:`BoardView`; empty (``n_corners == 0``) when the board was not seen.
    """
    gray = _to_gray8(image)
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _marker_corners, marker_ids = detector.detectBoard(gray)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    empty = BoardView(np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros((0, 3)), n_markers, t_ns)
    if ids is None or corners is None or len(ids) < max(min_corners, 1):
        return empty
    obj, img = board.matchImagePoints(list(corners), ids)
    if obj is None or img is None or len(obj) != len(ids):
        return empty
    return BoardView(
        np.asarray(ids, np.int32).reshape(-1),
        np.asarray(img, np.float64).reshape(-1, 2),
        np.asarray(obj, np.float64).reshape(-1, 3),
        n_markers,
        t_ns,
    )


# --------------------------------------------------------------------------------------------
# Intrinsics


@dataclass(frozen=True, slots=True)
class IntrinsicsResult:
    """One camera's intrinsics from ChArUco views.

    Attributes:
        camera: Camera label, ``"d415/<serial>"`` or ``"davis/<serial>"`` (empty if unknown).
        width: Image width (px).
        height: Image height (px).
        K: ``(3, 3)`` camera matrix (px).
        distortion: ``(5,)`` Brown–Conrady ``(k1, k2, p1, p2, k3)``.
        rms_px: Reprojection RMS over every corner of every view used (px).
        per_view_rms_px: Reprojection RMS of each view used (px), shape ``(V,)``.
        n_views: Views used.
        n_corners: Corners used.
        coverage: Fraction of the image's 8×6 cells holding at least one corner.
        max_tilt_deg: Largest angle between the board's normal and the line of sight.
        sigma: 1σ of ``fx, fy, cx, cy`` (px) and of ``k1, k2, p1, p2, k3`` from the fit.
        board: The board the views came from.
    """

    camera: str
    width: int
    height: int
    K: F64 = field(repr=False)
    distortion: F64 = field(repr=False)
    rms_px: float
    per_view_rms_px: F64 = field(repr=False)
    n_views: int
    n_corners: int
    coverage: float
    max_tilt_deg: float
    sigma: Mapping[str, float]
    board: CharucoBoardSpec

    def to_dict(self) -> dict[str, Any]:
        """Plain TOML/JSON-ready view (what :func:`write_intrinsics` stores)."""
        return {
            "format_version": _INTRINSICS_FORMAT,
            "camera": self.camera,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "distortion": self.distortion.tolist(),
            "rms_px": self.rms_px,
            "per_view_rms_px": self.per_view_rms_px.tolist(),
            "n_views": self.n_views,
            "n_corners": self.n_corners,
            "coverage": self.coverage,
            "max_tilt_deg": self.max_tilt_deg,
            "sigma": dict(self.sigma),
            "board": self.board.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "intrinsics") -> IntrinsicsResult:
        """Build from :meth:`to_dict`'s view.

        Raises:
            CalibrationError: missing keys, a newer ``format_version`` or invalid values.
        """
        version = data.get("format_version")
        if not isinstance(version, int) or version > _INTRINSICS_FORMAT:
            msg = (
                f"{source}: format_version {version!r} is not one this mocaprig reads "
                f"(≤ {_INTRINSICS_FORMAT}); is this an intrinsics file of `mocaprig calibrate "
                "intrinsics`?"
            )
            raise CalibrationError(msg)
        try:
            k = np.array(data["K"], dtype=np.float64)
            dist = np.array(data["distortion"], dtype=np.float64)
            if k.shape != (3, 3) or dist.shape != (5,) or not np.all(np.isfinite(k)):
                msg = f"{source}: K must be 3×3 and distortion 5 numbers"
                raise CalibrationError(msg)
            return cls(
                camera=str(data.get("camera", "")),
                width=int(data["width"]),
                height=int(data["height"]),
                K=k,
                distortion=dist,
                rms_px=float(data["rms_px"]),
                per_view_rms_px=np.array(data.get("per_view_rms_px", []), dtype=np.float64),
                n_views=int(data["n_views"]),
                n_corners=int(data["n_corners"]),
                coverage=float(data.get("coverage", math.nan)),
                max_tilt_deg=float(data.get("max_tilt_deg", math.nan)),
                sigma={str(a): float(b) for a, b in dict(data.get("sigma", {})).items()},
                board=CharucoBoardSpec.from_dict(data["board"], source=f"{source} [board]"),
            )
        except KeyError as err:
            msg = f"{source}: intrinsics lack the key {err.args[0]!r}"
            raise CalibrationError(msg) from err
        except (TypeError, ValueError) as err:
            msg = f"{source}: invalid intrinsics: {err}"
            raise CalibrationError(msg) from err


def write_intrinsics(path: Path, result: IntrinsicsResult, *, overwrite: bool = False) -> None:
    """Write intrinsics as TOML.

    Raises:
        ValidationError: ``path`` exists and ``overwrite`` is false.
    """
    _refuse_existing(path, overwrite)
    d = result.to_dict()
    board = d.pop("board")
    sigma = d.pop("sigma")
    text = _toml_table(d) + "\n[sigma]\n" + _toml_table(sigma) + "\n[board]\n" + _toml_table(board)
    Path(path).write_text(text, encoding="utf-8")


def read_intrinsics(path: Path) -> IntrinsicsResult:
    """Read intrinsics written by :func:`write_intrinsics`.

    Raises:
        CalibrationError: the file is missing, not TOML, or not an intrinsics file.
    """
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        msg = f"intrinsics file {path} does not exist"
        raise CalibrationError(msg) from err
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        msg = f"intrinsics file {path} is not readable TOML: {err}"
        raise CalibrationError(msg) from err
    return IntrinsicsResult.from_dict(data, source=f"intrinsics file {path}")


def _coverage(points: F64, width: int, height: int, *, nx: int = 8, ny: int = 6) -> float:
    if points.size == 0:
        return 0.0
    ix = np.clip((points[:, 0] / width * nx).astype(int), 0, nx - 1)
    iy = np.clip((points[:, 1] / height * ny).astype(int), 0, ny - 1)
    return float(np.unique(iy * nx + ix).size / (nx * ny))


def _tilt_deg(rvec: F64, tvec: F64) -> float:
    """Angle between the board normal and the line of sight to the board origin (deg)."""
    r, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    normal = np.asarray(r, np.float64)[:, 2]
    sight = np.asarray(tvec, np.float64).reshape(3)
    c = abs(float(normal @ sight)) / max(float(np.linalg.norm(sight)), 1e-12)
    return math.degrees(math.acos(min(c, 1.0)))


def calibrate_intrinsics(
    views: Sequence[BoardView],
    image_size: tuple[int, int],
    spec: CharucoBoardSpec,
    *,
    camera: str = "",
    fix_k3: bool = True,
    zero_tangent: bool = False,
    fix_aspect_ratio: bool = False,
    min_views: int = 8,
    min_corners_per_view: int = 6,
    min_coverage: float = 0.35,
    min_tilt_deg: float = 15.0,
    max_rms_px: float = 1.0,
    force: bool = False,
) -> IntrinsicsResult:
    """Calibrate one camera from ChArUco views (``cv2.calibrateCameraExtended``).

    Args:
        views: Views of the board by this camera (empty ones are skipped).
        image_size: ``(width, height)`` of the images (px).
        spec: The board.
        camera: Camera label stored in the result (``"d415/<serial>"``, ``"davis/<serial>"``).
        fix_k3: Keep k3 at 0 (the 4-parameter Brown–Conrady model; right for the D415's rectified
            streams and mild lenses). False fits k3 too (needs many well-spread views).
        zero_tangent: Keep p1 = p2 = 0.
        fix_aspect_ratio: Keep fx/fy at 1.
        min_views: Fewer usable views than this is refused.
        min_corners_per_view: Views with fewer corners (or collinear corners) are skipped.
        min_coverage: Refuse when the corners cover less than this fraction of the image's 8×6
            cells (the distortion is unconstrained where no corner fell).
        min_tilt_deg: Refuse when no view tilts the board this much (fronto-parallel views
            cannot determine the focal length).
        max_rms_px: Refuse a fit with a larger reprojection RMS unless ``force``.
        force: Accept a fit above ``max_rms_px`` (a warning is logged).

    Raises:
        CalibrationError: too few usable views or corners, poor coverage, no tilt, a fit
            above ``max_rms_px``; the message says what to do.
        ValidationError: invalid arguments.
    """
    w, h = (int(image_size[0]), int(image_size[1]))
    if w <= 0 or h <= 0:
        msg = f"calibrate_intrinsics(): image_size must be positive, got {image_size}"
        raise ValidationError(msg)
    who = f"camera {camera!r}" if camera else "the camera"
    board = spec.board()
    used: list[BoardView] = []
    for v in views:
        if v.n_corners < max(min_corners_per_view, 4):
            continue
        ids = v.corner_ids.reshape(-1, 1)
        if board.checkCharucoCornersCollinear(ids):
            continue
        used.append(v)
    seen = sum(1 for v in views if v.n_corners > 0)
    if len(used) < min_views:
        markers = sum(1 for v in views if v.n_corners == 0 and v.markers_seen > 0)
        hint = ""
        if seen == 0 and markers:
            hint = (
                f" ArUco markers were found in {markers} images but no corner: check the board "
                "description (squares_x/squares_y, legacy_pattern)."
            )
        elif seen == 0:
            hint = (
                " The board was never seen: check the dictionary, the camera topic and the "
                "exposure."
            )
        msg = (
            f"intrinsics of {who}: {len(used)} usable views (≥ {min_corners_per_view} "
            f"non-collinear corners) of {len(views)} images, the board seen in {seen}; need "
            f"≥ {min_views}. Record more views, the board filling a third to two thirds of the "
            f"image, tilted 20–45°, over the whole image.{hint}"
        )
        raise CalibrationError(msg)
    obj = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in used]
    img = [v.image_points.astype(np.float32).reshape(-1, 1, 2) for v in used]
    all_img = np.concatenate([v.image_points for v in used])
    coverage = _coverage(all_img, w, h)
    if coverage < min_coverage:
        msg = (
            f"intrinsics of {who}: the corners cover {coverage:.0%} of the image (8×6 cells), "
            f"below {min_coverage:.0%}; the distortion would be extrapolated. Record views with "
            "the board near the edges and corners of the image too."
        )
        raise CalibrationError(msg)
    flags = 0
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    k0 = np.eye(3)
    d0 = np.zeros(5)
    try:
        out = cv2.calibrateCameraExtended(obj, img, (w, h), k0, d0, flags=flags, criteria=criteria)
    except cv2.error as err:
        msg = f"intrinsics of {who}: OpenCV calibrateCamera failed: {err}"
        raise CalibrationError(msg) from err
    rms, k_out, d_out, rvecs, tvecs, std_intr, _std_extr, per_view = out
    k: F64 = np.asarray(k_out, np.float64)
    d_flat = np.asarray(d_out, np.float64).reshape(-1)[:5]
    dist: F64 = np.pad(d_flat, (0, 5 - d_flat.size))
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(dist)) and k[0, 0] > 0):
        msg = f"intrinsics of {who}: the fit diverged (non-finite K); record better-spread views"
        raise CalibrationError(msg)
    tilts = [
        _tilt_deg(np.asarray(r, np.float64), np.asarray(t, np.float64))
        for r, t in zip(rvecs, tvecs, strict=True)
    ]
    max_tilt = float(np.max(tilts))
    if max_tilt < min_tilt_deg:
        msg = (
            f"intrinsics of {who}: the board is nearly fronto-parallel in every view (largest "
            f"tilt {max_tilt:.1f}°, need ≥ {min_tilt_deg:.0f}°); the focal length is not "
            "determined. Record views with the board tilted 20–45° about different axes."
        )
        raise CalibrationError(msg)
    std = np.asarray(std_intr, np.float64).reshape(-1)
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    sigma = {f"{n}_sigma": float(std[i]) for i, n in enumerate(names) if i < std.size}
    rms_f = float(rms)
    if rms_f > max_rms_px:
        msg = (
            f"intrinsics of {who}: reprojection RMS {rms_f:.2f} px is above the {max_rms_px} px "
            "ceiling (wrong board size, motion blur, or a lens the model cannot describe); "
            "re-record sharp views, check the board file, or pass force=True / --force"
        )
        if not force:
            raise CalibrationError(msg)
        _log.warning("%s (accepted: force)", msg)
    result = IntrinsicsResult(
        camera=camera,
        width=w,
        height=h,
        K=k,
        distortion=dist,
        rms_px=rms_f,
        per_view_rms_px=np.asarray(per_view, np.float64).reshape(-1),
        n_views=len(used),
        n_corners=int(sum(v.n_corners for v in used)),
        coverage=coverage,
        max_tilt_deg=max_tilt,
        sigma=sigma,
        board=spec,
    )
    _log.info(
        "intrinsics of %s: fx %.2f fy %.2f cx %.2f cy %.2f, RMS %.3f px over %d views",
        who,
        k[0, 0],
        k[1, 1],
        k[0, 2],
        k[1, 2],
        rms_f,
        len(used),
    )
    return result


# --------------------------------------------------------------------------------------------
# Extrinsics


def group_views_by_time(
    views: Mapping[str, Sequence[BoardView]], *, max_skew_ns: int
) -> list[dict[str, BoardView]]:
    """Group views of several cameras taken at the same instant.

    Views (non-empty, with ``t_ns``) are sorted by time; a group starts at its earliest view and
    takes every later view within ``max_skew_ns`` of it, at most one per camera (the one closest
    to the group's start).

    Args:
        views: Views by camera label; their ``t_ns`` must be on one clock.
        max_skew_ns: Largest time difference (ns) within a group.

    Returns:
        Groups seen by at least two cameras, in time order: camera label → view.

    Raises:
        ValidationError: a non-empty view has no ``t_ns``, or ``max_skew_ns < 0``.
    """
    if max_skew_ns < 0:
        msg = f"max_skew_ns must be >= 0, got {max_skew_ns}"
        raise ValidationError(msg)
    items: list[tuple[int, str, BoardView]] = []
    for cam, vs in views.items():
        for v in vs:
            if v.n_corners == 0:
                continue
            if v.t_ns is None:
                msg = f"a view of camera {cam!r} has no t_ns; stamp views to pair them in time"
                raise ValidationError(msg)
            items.append((int(v.t_ns), cam, v))
    items.sort(key=lambda x: (x[0], x[1]))
    groups: list[dict[str, BoardView]] = []
    i = 0
    while i < len(items):
        t0 = items[i][0]
        group: dict[str, BoardView] = {}
        j = i
        while j < len(items) and items[j][0] - t0 <= max_skew_ns:
            _, cam, v = items[j]
            group.setdefault(cam, v)
            j += 1
        if len(group) >= 2:
            groups.append(group)
        i = j
    return groups


def _rt_to_T(rvec: F64, tvec: F64) -> F64:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(np.asarray(rvec, np.float64).reshape(3)).as_matrix()
    out[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return out


def _inv(T: F64) -> F64:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _solve_pnp(view: BoardView, k: F64, dist: F64) -> tuple[F64, float]:
    """``T_cam_board`` of one view (IPPE, best of its two solutions, then LM) and its RMS px."""
    obj = view.object_points.astype(np.float64)
    img = view.image_points.astype(np.float64)
    n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        return np.full((4, 4), np.nan), math.inf
    best = int(np.argmin(np.asarray(errs).reshape(-1)))
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvecs[best].copy(), tvecs[best].copy())
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    return _rt_to_T(np.asarray(rvec), np.asarray(tvec)), rms


def _parse_label(label: str) -> tuple[Literal["d415", "davis"], str]:
    kind, _, serial = label.partition("/")
    if kind not in ("d415", "davis") or not serial:
        msg = (
            f"camera label {label!r} must be 'd415/<serial>' or 'davis/<serial>' (set the "
            "intrinsics' camera when calibrating them)"
        )
        raise ValidationError(msg)
    return ("d415" if kind == "d415" else "davis"), serial


@dataclass(slots=True)
class _Problem:
    cams: list[str]
    inst: list[dict[str, BoardView]]
    cam_idx: npt.NDArray[np.intp]
    inst_idx: npt.NDArray[np.intp]
    obj: F64
    img: F64
    k: F64
    dist: F64


def _residuals(x: F64, p: _Problem, n_cam: int) -> F64:
    cam_params = np.zeros((n_cam, 6))
    cam_params[1:] = x[: 6 * (n_cam - 1)].reshape(-1, 6)
    inst_params = x[6 * (n_cam - 1) :].reshape(-1, 6)
    # X_ref = R_i X_board + t_i;  X_cam = R_c^T (X_ref − t_c)  (t_c: camera centre in ref).
    r_i = Rotation.from_rotvec(inst_params[p.inst_idx, :3])
    x_ref = r_i.apply(p.obj) + inst_params[p.inst_idx, 3:]
    r_c = Rotation.from_rotvec(cam_params[p.cam_idx, :3])
    x_cam = r_c.inv().apply(x_ref - cam_params[p.cam_idx, 3:])
    # Per-observation intrinsics; no depth test: the solver needs finite residuals everywhere.
    uv = project_camera(x_cam, p.k, p.dist, min_depth_m=None)
    out: F64 = (uv - p.img).reshape(-1)
    return out


def _sparsity(p: _Problem, n_cam: int, n_inst: int) -> Any:
    n_obs = p.obj.shape[0]
    n_par = 6 * (n_cam - 1 + n_inst)
    m = lil_matrix((2 * n_obs, n_par), dtype=np.int8)
    rows = np.arange(n_obs)
    for d in range(6):
        for off in (0, 1):
            r = 2 * rows + off
            has_cam = p.cam_idx > 0
            m[r[has_cam], 6 * (p.cam_idx[has_cam] - 1) + d] = 1
            m[r, 6 * (n_cam - 1) + 6 * p.inst_idx + d] = 1
    return m


def calibrate_extrinsics(
    views: Mapping[str, Sequence[BoardView]],
    intrinsics: Mapping[str, IntrinsicsResult],
    *,
    max_skew_ns: int = 2_000_000,
    world: WorldChoice = "camera",
    reference: str | None = None,
    min_corners: int = 6,
    max_rms_px: float = 1.5,
    force: bool = False,
    software_version: str = "",
    created_utc: str = "",
) -> Calibration:
    """Camera poses from board views shared in time, intrinsics fixed.

    Args:
        views: Views by camera label (``"d415/<serial>"``, ``"davis/<serial>"``), each stamped
            with ``t_ns`` on one clock (e.g. the recording's log time).
        intrinsics: Fixed intrinsics by the same labels.
        max_skew_ns: Views of different cameras this close in time show the same board pose
            (hold the board still for longer than this).
        world: ``"camera"``: the reference camera's frame; ``"board"``: the board's frame at the
            instant seen by the most cameras.
        reference: The reference camera (default: the first label of ``intrinsics``).
        min_corners: Views with fewer corners are not used.
        max_rms_px: Refuse a solution whose overall reprojection RMS is larger, unless ``force``.
        force: Accept a solution above ``max_rms_px`` (a warning is logged).
        software_version: Stored in the calibration.
        created_utc: Stored in the calibration.

    Returns:
        A :class:`Calibration` (``source="charuco"``) whose cameras carry the fixed intrinsics,
        the poses and per-camera residuals (``reprojection_rms_px``, ``views``, ``corners``,
        ``outliers``, ``rotation_sigma_deg``, ``translation_sigma_mm``).

    Raises:
        CalibrationError: a camera shares no view with the others (the pose graph is not
            connected), too few shared views, or a solution above ``max_rms_px``.
        ValidationError: labels without intrinsics, malformed labels.
    """
    if not intrinsics:
        msg = "calibrate_extrinsics(): give the intrinsics of at least two cameras"
        raise ValidationError(msg)
    if str(world) not in ("camera", "board"):
        msg = f"world must be 'camera' or 'board', got {world!r}"
        raise ValidationError(msg)
    cams = list(intrinsics)
    if len(cams) < 2:
        msg = f"calibrate_extrinsics(): need at least two cameras, got {cams}"
        raise ValidationError(msg)
    ref = cams[0] if reference is None else reference
    if ref not in intrinsics:
        msg = f"reference camera {ref!r} has no intrinsics; cameras: {cams}"
        raise ValidationError(msg)
    cams = [ref, *[c for c in cams if c != ref]]
    kinds = {c: _parse_label(c) for c in cams}
    unknown = sorted(set(views) - set(intrinsics))
    if unknown:
        msg = f"views of {unknown} but no intrinsics for them; give their intrinsics files"
        raise ValidationError(msg)
    usable = {c: [v for v in views.get(c, ()) if v.n_corners >= max(min_corners, 4)] for c in cams}
    groups = group_views_by_time(usable, max_skew_ns=max_skew_ns)
    # Per-view board poses.
    k_of = {c: np.asarray(intrinsics[c].K, np.float64) for c in cams}
    d_of = {c: np.asarray(intrinsics[c].distortion, np.float64) for c in cams}
    pnp: list[dict[str, F64]] = []
    kept: list[dict[str, BoardView]] = []
    for g in groups:
        poses: dict[str, F64] = {}
        for c, v in g.items():
            T, rms = _solve_pnp(v, k_of[c], d_of[c])
            if np.all(np.isfinite(T)) and rms < 5.0 * max_rms_px:
                poses[c] = T
        if len(poses) >= 2:
            pnp.append(poses)
            kept.append({c: g[c] for c in poses})
    # Pose graph: chain cameras through shared instants, starting from the reference.
    T_ref_cam: dict[str, F64] = {ref: np.eye(4)}
    while True:
        best: tuple[int, str, F64] | None = None
        for poses, g in zip(pnp, kept, strict=True):
            known = [c for c in poses if c in T_ref_cam]
            if not known:
                continue
            a = max(known, key=lambda c: g[c].n_corners)
            for c in poses:
                if c in T_ref_cam:
                    continue
                score = min(g[a].n_corners, g[c].n_corners)
                if best is None or score > best[0]:
                    T = T_ref_cam[a] @ poses[a] @ _inv(poses[c])
                    best = (score, c, T)
        if best is None:
            break
        T_ref_cam[best[1]] = best[2]
    missing = [c for c in cams if c not in T_ref_cam]
    if missing:
        counts = {c: sum(1 for g in kept if c in g) for c in cams}
        msg = (
            f"board extrinsics: cameras {missing} share no board view with {ref!r}'s group "
            f"(shared views per camera: {counts}); record the board where these cameras and "
            "one already connected see it at the same time (held still), or check max_skew"
        )
        raise CalibrationError(msg)
    # Board poses in the reference frame: from the camera seeing the most corners.
    T_ref_board: list[F64] = []
    for poses, g in zip(pnp, kept, strict=True):
        c = max(poses, key=lambda c: g[c].n_corners)
        T_ref_board.append(T_ref_cam[c] @ poses[c])
    prob = _build_problem(cams, kept, k_of, d_of)
    n_cam, n_inst = len(cams), len(kept)
    x0 = np.concatenate(
        [_pose_params(T_ref_cam[c]) for c in cams[1:]] + [_pose_params(T) for T in T_ref_board]
    )
    jac = _sparsity(prob, n_cam, n_inst)
    sol = least_squares(
        _residuals, x0, jac_sparsity=jac, loss="soft_l1", f_scale=1.0, x_scale="jac",
        method="trf", args=(prob, n_cam),
    )  # fmt: skip
    r = sol.fun.reshape(-1, 2)
    err = np.linalg.norm(r, axis=1)
    sigma = float(np.sqrt(np.mean(err**2)))
    inlier = err <= max(3.0 * sigma, 1.0)
    n_out = int(np.count_nonzero(~inlier))
    if n_out:
        prob = _select(prob, inlier)
        jac = _sparsity(prob, n_cam, n_inst)
    sol = least_squares(
        _residuals, sol.x, jac_sparsity=jac, x_scale="jac", method="trf", args=(prob, n_cam)
    )
    r = sol.fun.reshape(-1, 2)
    err2 = np.sum(r**2, axis=1)
    rms_all = float(np.sqrt(np.mean(err2)))
    dof = max(sol.fun.size - sol.x.size, 1)
    s2 = float(np.sum(sol.fun**2) / dof)
    jd = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    try:
        cov = np.linalg.pinv(jd.T @ jd) * s2
    except np.linalg.LinAlgError:
        cov = np.full((sol.x.size, sol.x.size), np.nan)
    if rms_all > max_rms_px:
        msg = (
            f"board extrinsics: reprojection RMS {rms_all:.2f} px is above the {max_rms_px} px "
            "ceiling (wrong intrinsics or board file, views not simultaneous — lower the time "
            "skew or hold the board still); pass force=True / --force to accept"
        )
        if not force:
            raise CalibrationError(msg)
        _log.warning("%s (accepted: force)", msg)
    cam_params = np.zeros((n_cam, 6))
    cam_params[1:] = sol.x[: 6 * (n_cam - 1)].reshape(-1, 6)
    inst_params = sol.x[6 * (n_cam - 1) :].reshape(-1, 6)
    T_world_ref = np.eye(4)
    world_frame = ref
    if world == "board":
        seen_by = [len(g) for g in kept]
        i_star = max(range(n_inst), key=lambda i: (seen_by[i], -i))
        T_world_ref = _inv(_params_pose(inst_params[i_star]))
        world_frame = "board"
    cameras: list[CameraCalibration] = []
    for ci, c in enumerate(cams):
        sel = prob.cam_idx == ci
        rms_c = float(np.sqrt(np.mean(err2[sel]))) if np.any(sel) else math.nan
        if ci == 0:
            rot_sigma = trans_sigma = 0.0
        else:
            block = cov[6 * (ci - 1) : 6 * ci, 6 * (ci - 1) : 6 * ci]
            rot_sigma = math.degrees(math.sqrt(max(float(np.trace(block[:3, :3])), 0.0)))
            trans_sigma = 1000.0 * math.sqrt(max(float(np.trace(block[3:, 3:])), 0.0))
        kind, serial = kinds[c]
        intr = intrinsics[c]
        cameras.append(
            CameraCalibration(
                name=c,
                kind=kind,
                serial=serial,
                width=intr.width,
                height=intr.height,
                K=intr.K,
                distortion=intr.distortion,
                T_world_cam=T_world_ref @ _params_pose(cam_params[ci]),
                residuals={
                    "reprojection_rms_px": rms_c,
                    "views": float(sum(1 for g in kept if c in g)),
                    "corners": float(np.count_nonzero(sel)),
                    "rotation_sigma_deg": rot_sigma,
                    "translation_sigma_mm": trans_sigma,
                    "intrinsics_rms_px": intr.rms_px,
                },
                source="charuco",
            )
        )
    _log.info(
        "board extrinsics: %d cameras, %d shared instants, RMS %.3f px, %d outliers",
        n_cam,
        n_inst,
        rms_all,
        n_out,
    )
    return Calibration(
        cameras=tuple(cameras),
        world_frame=world_frame,
        statistics={
            "reprojection_rms_px": rms_all,
            "shared_views": float(n_inst),
            "corners": float(prob.obj.shape[0]),
            "outliers": float(n_out),
        },
        software_version=software_version,
        created_utc=created_utc,
    )


def _pose_params(T: F64) -> F64:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _params_pose(x: F64) -> F64:
    return _rt_to_T(x[:3], x[3:6])


def _build_problem(
    cams: list[str],
    inst: list[dict[str, BoardView]],
    k_of: Mapping[str, F64],
    d_of: Mapping[str, F64],
) -> _Problem:
    ci: list[npt.NDArray[np.intp]] = []
    ii: list[npt.NDArray[np.intp]] = []
    obj: list[F64] = []
    img: list[F64] = []
    for i, g in enumerate(inst):
        for c, v in g.items():
            n = v.n_corners
            ci.append(np.full(n, cams.index(c), dtype=np.intp))
            ii.append(np.full(n, i, dtype=np.intp))
            obj.append(v.object_points)
            img.append(v.image_points)
    cam_idx = np.concatenate(ci)
    ks = np.stack([k_of[c] for c in cams])
    ds = np.stack([d_of[c] for c in cams])
    return _Problem(
        cams, inst, cam_idx, np.concatenate(ii), np.concatenate(obj), np.concatenate(img),
        ks[cam_idx], ds[cam_idx],
    )  # fmt: skip


def _select(p: _Problem, keep: npt.NDArray[np.bool_]) -> _Problem:
    return _Problem(
        p.cams, p.inst, p.cam_idx[keep], p.inst_idx[keep], p.obj[keep], p.img[keep],
        p.k[keep], p.dist[keep],
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Small helpers


def _refuse_existing(path: Path, overwrite: bool) -> None:
    if Path(path).exists() and not overwrite:
        msg = f"{path} exists already; not overwriting it (choose another path or --overwrite)"
        raise ValidationError(msg)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    msg = f"cannot write {type(v).__name__} to TOML"
    raise ValidationError(msg)


def _toml_table(d: Mapping[str, Any]) -> str:
    return "".join(f"{k} = {_toml_value(v)}\n" for k, v in d.items())
