"""Camera-to-table extrinsics of a real rig from a ChArUco board lying on the table (OpenCV), and the checks every
imported calibration passes (docs/annotator.md, "Real captures in").

The board (`rig.json`'s "board"): `squares` [columns, rows] of squares, `square_length` and `marker_length` (m, as
printed: measure them), `dictionary` (an OpenCV ArUco dictionary name, e.g. "DICT_5X5_100"), `legacy` (true for
boards drawn by OpenCV < 4.6 with an even number of rows) and `offset` [x, y, z] (m). The board frame is OpenCV's:
origin at the outer corner of the first square (the top-left of `generateImage`'s picture), x along its first row,
y along its first column, z into the board. It lies printed side up on the table with its x axis along the table's
+x, so its y axis points along the table's -y and its z down, and its origin sits at `offset` in the table frame
(z: the board's thickness above the table, usually 0): table = BOARD_AXES board + offset.

Each camera's pose comes from its own view of the board (corners refined to subpixel, PnP: IPPE then
Levenberg-Marquardt), so both cameras land in the one table frame. Residuals (mm): `board_mm` the reprojection error
of each camera's corners expressed on the board (pixels x depth / focal length); `between_cameras_mm` where both
cameras see a corner, the distance between where their rays meet the board's plane; `depth_mm` the median of
measured depth - predicted depth at the corners (a wrong `square_length` or depth scale shows here).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsr_bench.constants import GRID_BOUNDS
from dsr_bench.errors import UserError
from dsr_bench.geometry import Camera, rigid_inverse

#: Board axes in the table frame (columns: the board's x, y, z): x along +x, y along -y, z down.
BOARD_AXES = np.diag([1.0, -1.0, -1.0])
#: Fewest ChArUco corners a camera must see for its pose.
MIN_CORNERS = 6
#: Largest accepted residuals (mm): on the board / between the cameras, and |median depth residual|.
MAX_BOARD_MM = 3.0
MAX_DEPTH_MM = 10.0
#: Most squares a board may have along each side (a printable ChArUco board has a few dozen at most).
MAX_SQUARES = 100


@dataclass(frozen=True)
class Board:
    """A ChArUco board: squares (columns, rows), square and marker edge (m), ArUco dictionary name, OpenCV < 4.6
    layout, origin in the table frame (m)."""

    squares: tuple[int, int]
    square_length: float
    marker_length: float
    dictionary: str
    offset: tuple[float, float, float]
    legacy: bool = False

    @property
    def board_to_table(self) -> np.ndarray:
        """4x4 board frame -> table frame (m)."""
        m = np.eye(4)
        m[:3, :3] = BOARD_AXES
        m[:3, 3] = self.offset
        return m

    def cv_board(self):
        """The OpenCV `cv2.aruco.CharucoBoard`."""
        import cv2

        board = cv2.aruco.CharucoBoard(tuple(int(s) for s in self.squares), float(self.square_length),
                                       float(self.marker_length),
                                       cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)))
        board.setLegacyPattern(bool(self.legacy))
        return board

    def corners_table(self) -> np.ndarray:
        """The chessboard corners (K, 3) in the table frame (m), in OpenCV's corner-id order."""
        corners = np.asarray(self.cv_board().getChessboardCorners(), np.float64).reshape(-1, 3)
        return corners @ BOARD_AXES.T + np.asarray(self.offset)


def parse_board(where: str, spec) -> Board:
    """A `Board` from the rig file's "board" object (module docstring); UserError naming `where` and the fix."""
    import cv2

    hint = ('"board": {"squares": [7, 5], "square_length": 0.06, "marker_length": 0.045, "dictionary": '
            '"DICT_4X4_50", "offset": [x, y, 0]} (m)')
    if not isinstance(spec, dict):
        raise UserError(f"{where}: board must be an object like {hint}")
    missing = [k for k in ("squares", "square_length", "marker_length", "dictionary", "offset") if k not in spec]
    if missing:
        raise UserError(f"{where}: board lacks {', '.join(missing)}; give {hint}")
    from dsr_bench.annotator.inputs import finite, numbers

    squares = spec["squares"]
    if not (isinstance(squares, list) and len(squares) == 2 and all(type(s) is int for s in squares)
            and finite(spec["square_length"]) and finite(spec["marker_length"]) and numbers(spec["offset"], (3,))
            and isinstance(spec["dictionary"], str) and isinstance(spec.get("legacy", False), bool)):
        raise UserError(f"{where}: board squares must be 2 integers, lengths numbers (m), offset 3 numbers, dictionary "
                        f"a name and legacy true/false; give {hint}")
    squares = tuple(squares)
    square, marker = float(spec["square_length"]), float(spec["marker_length"])
    ox, oy, oz = (float(v) for v in spec["offset"])  # 3 numbers: checked above
    offset = (ox, oy, oz)
    if not 2 <= min(squares) <= max(squares) <= MAX_SQUARES:
        raise UserError(f"{where}: board squares must be [columns, rows], each 2..{MAX_SQUARES}; give {hint}")
    if not 0 < marker < square < 0.5:
        raise UserError(f"{where}: board marker_length {marker} must be smaller than square_length {square} (m, "
                        "measured on the print)")
    name = str(spec["dictionary"])
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise UserError(f"{where}: board dictionary {name!r} is not an OpenCV ArUco dictionary; use a name such as "
                        "DICT_4X4_50, DICT_5X5_100 or DICT_6X6_250 (the one the board was made with)")
    return Board(squares, square, marker, name, offset, bool(spec.get("legacy", False)))


@dataclass(frozen=True)
class BoardView:
    """One camera's view of the board: corner ids (K,), their pixels (K, 2), camera-to-table 4x4 (m), RMS
    reprojection error (px)."""

    ids: np.ndarray
    pixels: np.ndarray
    extrinsics: np.ndarray
    reprojection_px: float


def paint_board(color: np.ndarray, table: np.ndarray, camera: Camera, spec, pixels_per_metre: int = 2000
                ) -> np.ndarray:
    """`color` (H, W, 3) uint8 with the ChArUco board `spec` (a rig file's "board") drawn onto the table plane where
    `table` (H, W) bool is true, as the pinhole `camera` sees it: the board's picture (`generateImage` at
    `pixels_per_metre`) warped by the homography of its corners at twice the resolution, then area-averaged (pixel
    centres at integers throughout). What the tests' and the RealSense fixtures' simulated cameras see of a board."""
    import cv2

    cols, rows = spec["squares"]
    ppm = pixels_per_metre
    w, h = round(cols * spec["square_length"] * ppm), round(rows * spec["square_length"] * ppm)
    picture = parse_board("the board", spec).cv_board().generateImage((w, h), marginSize=0, borderBits=1)
    extent = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], np.float64) / ppm  # board frame, m
    uv, z = camera.project(extent @ np.diag([1.0, -1.0, -1.0]).T + np.asarray(spec["offset"]))
    if not np.all(z > 0):
        raise ValueError(f"paint_board: the board is behind camera {camera.name!r}")
    src = np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float32) - 0.5
    hom = cv2.getPerspectiveTransform(src, (2 * uv + 0.5).astype(np.float32))
    size = (2 * camera.width, 2 * camera.height)
    fine = cv2.warpPerspective(picture, hom, size, flags=cv2.INTER_LINEAR, borderValue=0).astype(np.float32)
    cover = cv2.warpPerspective(np.ones((h, w), np.float32), hom, size, flags=cv2.INTER_LINEAR, borderValue=0)
    value = cv2.resize(fine, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    alpha = cv2.resize(cover, (camera.width, camera.height), interpolation=cv2.INTER_AREA) * table
    out = color.astype(np.float32) * (1 - alpha[..., None]) + (value * alpha)[..., None]
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def board_view(image: np.ndarray, intrinsics: np.ndarray, board: Board, where: str) -> BoardView:
    """The camera-to-table extrinsics of a camera (intrinsics (3, 3) px, undistorted image (H, W, 3) uint8 RGB) that
    sees `board` lying on the table; UserError naming `where` (the image) when too few corners are found."""
    import cv2

    cv = board.cv_board()
    gray = cv2.cvtColor(np.ascontiguousarray(image, np.uint8), cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv).detectBoard(gray)
    count = 0 if ids is None else len(ids)
    if count < MIN_CORNERS:
        raise UserError(f"{where}: found {count} ChArUco corners of the board (at least {MIN_CORNERS} needed): check "
                        "the board's squares, dictionary and lengths in the rig file and that the board lies in view")
    ids = ids.reshape(-1).astype(np.int64)
    pixels = corners.reshape(-1, 2).astype(np.float64)
    objects = np.asarray(cv.getChessboardCorners(), np.float64).reshape(-1, 3)[ids]
    k = np.asarray(intrinsics, np.float64)
    ok, rvec, tvec = cv2.solvePnP(objects, pixels, k, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise UserError(f"{where}: the board's pose could not be solved from {count} corners; check the intrinsics")
    rvec, tvec = cv2.solvePnPRefineLM(objects, pixels, k, None, rvec, tvec)
    cam_from_board = np.eye(4)
    cam_from_board[:3, :3] = cv2.Rodrigues(rvec)[0]
    cam_from_board[:3, 3] = tvec.reshape(3)
    projected = cv2.projectPoints(objects, rvec, tvec, k, None)[0].reshape(-1, 2)
    rms = float(np.sqrt(np.mean(np.sum((projected - pixels) ** 2, axis=1))))
    extrinsics = board.board_to_table @ rigid_inverse(cam_from_board)
    return BoardView(ids, pixels, extrinsics, rms)


def _on_board_plane(camera: Camera, pixels: np.ndarray, board: Board) -> np.ndarray:
    """Where the rays of `pixels` (K, 2) meet the board's plane (table z = offset z), table frame (K, 3) m."""
    from dsr_bench.geometry import pinhole_inverse

    rays = np.c_[pixels, np.ones(len(pixels))] @ pinhole_inverse(camera.intrinsics).T @ camera.extrinsics[:3, :3].T
    origin = camera.extrinsics[:3, 3]
    t = (board.offset[2] - origin[2]) / rays[:, 2]
    return origin + rays * t[:, None]


def calibration_residuals(cameras: dict[str, Camera], views: dict[str, BoardView], depths: dict[str, np.ndarray],
                          board: Board) -> dict:
    """Residuals (mm, module docstring) of board-calibrated cameras: per camera board_mm, depth_mm, corners and
    reprojection_px, and between_cameras_mm (None unless two cameras share 3 or more corners). depths: per camera
    the z-depth (H, W) m of the calibration view (0 = missing)."""
    truth = board.corners_table()
    report: dict = {"cameras": {}}
    on_plane = {}
    for name, view in views.items():
        cam = cameras[name]
        on_plane[name] = dict(zip(view.ids.tolist(), _on_board_plane(cam, view.pixels, board)))
        error = _on_board_plane(cam, view.pixels, board) - truth[view.ids]
        _, z = cam.project(truth[view.ids])
        u, v = np.rint(view.pixels).astype(np.int64).T
        inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        measured = depths[name][v[inside], u[inside]]
        has = measured > 0
        depth_mm = float(np.median(measured[has] - z[inside][has]) * 1000) if has.sum() >= MIN_CORNERS else None
        report["cameras"][name] = {"corners": len(view.ids), "reprojection_px": round(view.reprojection_px, 3),
                                   "board_mm": round(float(np.sqrt(np.mean(np.sum(error ** 2, 1)))) * 1000, 3),
                                   "depth_mm": None if depth_mm is None else round(depth_mm, 3)}
    names = list(views)
    report["between_cameras_mm"] = None
    if len(names) == 2:
        shared = sorted(set(on_plane[names[0]]) & set(on_plane[names[1]]))
        if len(shared) >= 3:
            gap = np.array([on_plane[names[0]][i] - on_plane[names[1]][i] for i in shared])
            report["between_cameras_mm"] = round(float(np.sqrt(np.mean(np.sum(gap ** 2, 1)))) * 1000, 3)
            report["shared_corners"] = len(shared)
    return report


def check_residuals(where: str, report: dict) -> None:
    """UserError naming `where` when a residual of `calibration_residuals` exceeds MAX_BOARD_MM / MAX_DEPTH_MM."""
    for name, r in report["cameras"].items():
        if r["board_mm"] > MAX_BOARD_MM:
            raise UserError(f"{where}: the {name} camera's board residual is {r['board_mm']:.1f} mm (at most "
                            f"{MAX_BOARD_MM:g}): check its intrinsics and distortion, and the board's lengths")
        if r["depth_mm"] is not None and abs(r["depth_mm"]) > MAX_DEPTH_MM:
            raise UserError(f"{where}: the {name} camera's depth disagrees with the board by {r['depth_mm']:.1f} mm "
                            f"(at most {MAX_DEPTH_MM:g}): check the board's square_length and marker_length (m, as "
                            "printed), and the camera's fx, fy and depth_scale")
    gap = report.get("between_cameras_mm")
    if gap is not None and gap > MAX_BOARD_MM:
        raise UserError(f"{where}: the cameras disagree by {gap:.1f} mm on the board (at most {MAX_BOARD_MM:g}): check "
                        "both cameras' intrinsics and that neither moved between the board and the capture")


def check_grid_visible(where: str, camera: Camera) -> None:
    """UserError naming `where` unless the four table corners of the grid (GRID_BOUNDS at z = 0) project inside the
    camera's image, in front of it."""
    corners = np.array([[x, y, 0.0] for x in GRID_BOUNDS[0] for y in GRID_BOUNDS[1]])
    uv, z = camera.project(corners)
    for corner, (u, v), depth in zip(corners, uv, z):
        if not (depth > 0 and 0 <= u <= camera.width - 1 and 0 <= v <= camera.height - 1):
            (x0, x1), (y0, y1) = GRID_BOUNDS[0], GRID_BOUNDS[1]
            seen = "behind the camera" if depth <= 0 else f"to pixel ({u:.0f}, {v:.0f})"
            raise UserError(f"{where}: the grid's table corner ({corner[0]:g}, {corner[1]:g}, 0) m projects {seen}, "
                            f"outside the {camera.width}x{camera.height} image: the {camera.name} camera must see the "
                            f"whole grid (x {x0:g}..{x1:g}, y {y0:g}..{y1:g} m); aim it at the workspace or fix its "
                            "extrinsics (camera-to-table, m) or the board's offset")
