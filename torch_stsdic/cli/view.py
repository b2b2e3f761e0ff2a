"""``stsdic view``: look at a result in the browser, or draw the region a run measures."""

from __future__ import annotations

import argparse
import sys
import threading
import warnings
from pathlib import Path
from typing import Any

from torch_stsdic.cli import options
from torch_stsdic.cli.errors import CommandError, UsageError, one_line

NAME = "view"
HELP = "look at a result in the browser (scrub, read points), or draw the region to measure"

DESCRIPTION = """\
Serve a page on this computer only (127.0.0.1, a free port unless --port) and open it in
the browser (--no-browser: print the address only). Ctrl-C ends it.

stsdic view RESULT.h5 (a 'stsdic run' or 'stsdic stereo' file): the frame's image with a
field over it (u, v, velocities, strains, strain rates, their stds, status, ZNCC; the
colour bar in the file's units), a frame slider and play button; the pointer shows the
values of the point under it, a click plots that point's history with its +- 1 std band,
a second click adds another point to compare. The run's summary is beside it. Stereo
files: U, V, W, their velocities and the 3-D shape (drag to turn it). A file still being
written shows its finished frames and grows as the run goes.

stsdic view FRAMES... (images, no result): draw on the reference frame a box (the
--roi) and polygons: regions to measure and holes to leave out. 'Save' writes the mask
image (--mask-out) that 'stsdic run --mask' reads and prints the 'stsdic run' command with
--roi and --mask. Vertices snap to pixel centres; a polygon holds the pixels inside it and
on its outline.

Everything the page needs ships with torch_stsdic: it works offline.
"""

EPILOG = """\
examples:
  stsdic view result.h5                           # opens the browser
  stsdic view result.h5 --no-browser --port 8765  # then open the printed address
  stsdic view 3d.h5 --image left.tif              # a stereo result over its left images
  stsdic view movie.tif --mask-out mask.png       # draw the region, get the run command
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``stsdic view``."""
    opt = options.add_option
    p.add_argument("inputs", nargs="+", metavar="RESULT.h5|FRAMES",
                   help="a result file, or the image series to draw a region on")
    opt(p, "--port", type=options.int_min(0), default=0, metavar="N",
        help="port on 127.0.0.1", shown="a free one")  # fmt: skip
    p.add_argument("--no-browser", action="store_true", help="do not open a browser; print "
                   "the address only")  # fmt: skip
    opt(p, "--image", default=None, metavar="INPUT",
        help="image series under the fields (RESULT.h5)",
        shown="the inputs the file records, if they still exist")  # fmt: skip
    p.add_argument("--no-image", action="store_true", help="no image under the fields")
    opt(p, "--reference", type=options.int_min(0), default=0, metavar="N",
        help="frame to draw on (FRAMES)")  # fmt: skip
    opt(p, "--mask-out", default="mask.png", metavar="FILE.png",
        help="where 'Save' writes the mask (FRAMES)")  # fmt: skip
    p.add_argument("--overwrite", action="store_true",
                   help="let 'Save' replace an existing --mask-out")
    p.add_argument("--verbose", action="store_true", help="log every request on stderr")


def _is_result(inputs: list[str]) -> bool:
    """Whether ``inputs`` name one HDF5 file (a result) rather than images."""
    if len(inputs) != 1:
        return False
    p = Path(inputs[0])
    if p.suffix.lower() in (".h5", ".hdf5", ".hdf"):
        return True
    if p.is_file():
        with open(p, "rb") as fh:
            return fh.read(8) == b"\x89HDF\r\n\x1a\n"
    return False


def _result_server(args: argparse.Namespace) -> tuple[Any, str]:
    from torch_stsdic.view.server import make_server, result_api
    from torch_stsdic.view.source import open_source

    path = Path(args.inputs[0])
    if not path.exists():
        partial = path.with_name(path.name + ".partial")
        hint = (f"; {partial} exists (a run overwriting it): view that one" if partial.exists()
                else "")
        raise CommandError(f"result file not found: {path}{hint}")
    try:
        src = open_source(path, [args.image] if args.image else None, args.no_image)
    except (OSError, ValueError) as exc:
        if args.image:
            raise CommandError(f"{path} / --image {args.image}: {one_line(exc)}") from exc
        raise
    note = "" if src.images is not None else " (no image: the inputs it records are not " \
        "found; --image names them)"
    if src.n_points == 0 or src.n_rows == 0:
        raise CommandError(f"{path}: the result file holds no frame or no point")
    return make_server(args.port, result_api(src), verbose=args.verbose), \
        f"{path} ({src.n_rows} frames, {src.n_points} points){note}"


def _draw_server(args: argparse.Namespace) -> tuple[Any, str]:
    from torch_stsdic.io import load_series
    from torch_stsdic.view.server import draw_api, make_server
    from torch_stsdic.view.source import ImageSource

    if args.image or args.no_image:
        raise UsageError("--image/--no-image are for a result file; FRAMES are the images")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        series = load_series(args.inputs[0] if len(args.inputs) == 1 else list(args.inputs))
    if args.reference >= len(series):
        raise UsageError(f"--reference {args.reference}: the series has {len(series)} frames")
    out = Path(args.mask_out)
    if out.suffix.lower() not in (".png", ".tif", ".tiff"):
        raise UsageError(f"--mask-out {args.mask_out}: expected a .png or .tif file")
    if out.is_dir():
        raise UsageError(f"--mask-out {args.mask_out} is a folder")

    def saved(answer: dict[str, Any]) -> None:
        if answer.get("mask"):
            print(f"wrote {answer['mask']} ({answer['mask_pixels']} pixels to measure)")
        print(f"{answer['n_points']} grid points; measure them with:\n  {answer['command']}",
              flush=True)

    get, post = draw_api(ImageSource(series), args.reference, list(args.inputs), out,
                         args.overwrite, saved)
    h, w = series.shape[-2:]
    return make_server(args.port, get, post, verbose=args.verbose), \
        f"frame {args.reference} of {args.inputs[0]}{' ...' if len(args.inputs) > 1 else ''}" \
        f" ({w}x{h} px) to draw the region on"


def execute(args: argparse.Namespace) -> int:
    """``stsdic view``: serve the page until Ctrl-C."""
    server, what = _result_server(args) if _is_result(args.inputs) else _draw_server(args)
    url = server.url
    print(f"stsdic view: {what}\n  {url}  (this computer only; Ctrl-C to stop)", flush=True)
    if not args.no_browser:
        threading.Timer(0.2, _open_browser, (url,)).start()
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        print("stsdic view: stopped", file=sys.stderr, flush=True)
    finally:
        server.server_close()
    return 0


def _open_browser(url: str) -> None:
    import webbrowser

    try:
        if not webbrowser.open(url):
            print(f"stsdic view: no browser found; open {url}", file=sys.stderr, flush=True)
    except Exception as exc:  # noqa: BLE001 - the server goes on; the address is printed
        print(f"stsdic view: cannot open a browser ({one_line(exc)}); open {url}",
              file=sys.stderr, flush=True)
