"""`python -m app make-board --out board.png [--paper A4 --dpi 300 ...]`: a printable ChArUco board page
(PNG, and with --pdf a PDF of the page) and its geometry in a side file ``board.json`` for
`calibrate-camera --board` (docs/tracking.md, "Camera intrinsics")."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from app.cli import UserError
from app.commands.calibrate_camera import geometry_option_error
from fileio import atomic_path, check_output_path
from tracking.charuco import CharucoBoardSpec, PrintedBoard, save_board_file
from vehicles.params import MARKER_DICTIONARY

PAPER_MM = {"A5": (148.0, 210.0), "A4": (210.0, 297.0), "A3": (297.0, 420.0), "A2": (420.0, 594.0),
            "letter": (215.9, 279.4), "legal": (215.9, 355.6), "tabloid": (279.4, 431.8)}
MM_PER_INCH = 25.4


def register(sub):
    p = sub.add_parser(
        "make-board", help="printable ChArUco board (PNG/PDF) and its geometry file for calibrate-camera",
        description="Draw a ChArUco board on a page of the given paper size at the given DPI (lengths are whole "
                    "pixels) and write its geometry beside it (OUT with .json), for `calibrate-camera --board`. "
                    "Print at 100 % (no fit-to-page) and check one square with a ruler.")
    p.add_argument("--out", required=True, help="board image to write (PNG); the geometry goes to the same name .json")
    p.add_argument("--pdf", action="store_true", help="also write the page as PDF (same name .pdf)")
    p.add_argument("--paper", default="A4", help=f"{', '.join(PAPER_MM)} or WIDTHxHEIGHT in mm (default A4)")
    p.add_argument("--dpi", type=int, default=300, help="printer resolution (default 300)")
    p.add_argument("--margin-mm", type=float, default=12.0, help="white border kept free on the page (default 12)")
    p.add_argument("--squares-x", type=int, default=7, help="squares along x (default 7)")
    p.add_argument("--squares-y", type=int, default=5, help="squares along y (default 5)")
    p.add_argument("--square-length", type=float, help="square side (m; default: the largest whole mm that fits)")
    p.add_argument("--marker-length", type=float, help="marker side (m; default 0.75 of the square)")
    p.add_argument("--dictionary", default=MARKER_DICTIONARY, help=f"ArUco dictionary (default {MARKER_DICTIONARY})")
    p.add_argument("--legacy-pattern", action="store_true", help="OpenCV <= 4.5 chessboard colouring")
    p.set_defaults(func=run)


def paper_size_mm(paper: str) -> tuple[float, float]:
    if paper in PAPER_MM:
        return PAPER_MM[paper]
    width, x, height = paper.lower().removesuffix("mm").partition("x")
    try:
        size = (float(width), float(height))
    except ValueError:
        raise UserError(f"--paper: {paper!r} is not one of {', '.join(PAPER_MM)} nor WIDTHxHEIGHT in mm") from None
    if not (x and 20 <= min(size) and max(size) <= 5000):
        raise UserError(f"--paper: {paper!r}: width and height must be in [20, 5000] mm")
    return size


def layout(args) -> tuple[CharucoBoardSpec, tuple[float, float], int, int]:
    """Board geometry in whole pixels, page size (mm, oriented like the board) and square/marker pixels."""
    if not 50 <= args.dpi <= 2400:
        raise UserError(f"--dpi: must be in [50, 2400], got {args.dpi}")
    paper = paper_size_mm(args.paper)
    if (args.squares_x > args.squares_y) != (paper[0] > paper[1]):
        paper = paper[::-1]  # landscape for a wide board
    px_per_m = args.dpi / MM_PER_INCH * 1000
    usable = np.array(paper) / 1000 - 2 * args.margin_mm / 1000 - np.array([0.0, 0.01])  # 10 mm for the caption
    if args.square_length is None:
        fit = min(usable[0] / max(args.squares_x, 1), usable[1] / max(args.squares_y, 1))
        square_m = np.floor(fit * 1000) / 1000
    else:
        square_m = args.square_length
    square_px = int(round(square_m * px_per_m))
    marker_m = 0.75 * square_px / px_per_m if args.marker_length is None else args.marker_length
    marker_px = int(round(marker_m * px_per_m))
    if (square_px - marker_px) % 2:  # an even margin: the marker sits centred on whole pixels
        marker_px -= 1
    if square_px < 20 or marker_px < 12:
        raise UserError(f"board too small to print: squares {square_px} px, markers {marker_px} px at {args.dpi} dpi "
                        "(fewer squares, a larger --paper or a higher --dpi)")
    try:
        spec = CharucoBoardSpec(args.squares_x, args.squares_y, square_px / px_per_m, marker_px / px_per_m,
                                args.dictionary, args.legacy_pattern)
    except ValueError as exc:
        raise geometry_option_error(exc) from None
    if spec.squares_x * square_px > usable[0] * px_per_m + 1 or spec.squares_y * square_px > usable[1] * px_per_m + 1:
        raise UserError(f"a {spec.squares_x} x {spec.squares_y} board of {1000 * spec.square_length_m:.1f} mm squares "
                        f"does not fit on {args.paper} inside a {args.margin_mm:g} mm margin")
    return spec, paper, square_px, marker_px


def page_image(spec: CharucoBoardSpec, paper_mm: tuple[float, float], dpi: int, square_px: int) -> np.ndarray:
    """The whole page (white, board centred, a caption below it) at ``dpi``."""
    import cv2

    width, height = (int(round(side / MM_PER_INCH * dpi)) for side in paper_mm)
    board = spec.board().generateImage((spec.squares_x * square_px, spec.squares_y * square_px), marginSize=0)
    page = np.full((height, width), 255, np.uint8)
    top, left = (height - board.shape[0]) // 2, (width - board.shape[1]) // 2
    page[top:top + board.shape[0], left:left + board.shape[1]] = board
    caption = (f"ChArUco {spec.describe()}. Print at 100 % (no fit to page): one square = "
               f"{1000 * spec.square_length_m:.2f} mm")
    scale = dpi / 300 * 0.9
    (text_w, text_h), _ = cv2.getTextSize(caption, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, dpi // 150))
    scale *= min(1.0, 0.95 * board.shape[1] / text_w)
    cv2.putText(page, caption, (left, top + board.shape[0] + int(1.8 * text_h)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                0, max(1, dpi // 150), cv2.LINE_AA)
    return page


def write_png(path: Path, page: np.ndarray, dpi: int) -> None:
    from PIL import Image  # Pillow, a matplotlib dependency: writes the DPI into the PNG so viewers print to scale

    with atomic_path(path) as tmp:
        Image.fromarray(page).save(tmp, format="PNG", dpi=(dpi, dpi))


def write_pdf(path: Path, page: np.ndarray, paper_mm: tuple[float, float]) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(paper_mm[0] / MM_PER_INCH, paper_mm[1] / MM_PER_INCH))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(page, cmap="gray", vmin=0, vmax=255, interpolation="none")  # embedded as is, scaled to the page
    ax.set_axis_off()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="pdf")


def run(args) -> int:
    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise UserError(f"--out: {out}: the board image is a PNG (name it .png)")
    side, pdf = out.with_suffix(".json"), out.with_suffix(".pdf")
    for path in (out, side) + ((pdf,) if args.pdf else ()):
        check_output_path(path)
    spec, paper, square_px, marker_px = layout(args)
    page = page_image(spec, paper, args.dpi, square_px)
    write_png(out, page, args.dpi)
    if args.pdf:
        write_pdf(pdf, page, paper)
    save_board_file(side, PrintedBoard(spec, args.paper, paper[0], paper[1], args.dpi, out.name))
    print(f"board: {spec.describe()} ({square_px} px squares, {marker_px} px markers at {args.dpi} dpi)")
    print(f"wrote {out}" + (f", {pdf}" if args.pdf else "") + f" and {side}; print at 100 % and check that one square "
          f"measures {1000 * spec.square_length_m:.2f} mm")
    return 0
