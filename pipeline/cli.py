"""``plate-inspect``: simulate, calibrate, acquire, inspect (and ``serve`` from the service package).

Exit codes (docs/formats.md): 0 done (pass or fail), 2 bad input (a one-line reason
on stderr naming the file and field), 3 capture not measurable, 4 hardware failure
(``acquire``: a one-line reason naming the device and the step), 1 internal error.

Subcommands that live outside ``pipeline/`` (the service's ``serve``) are found
through the entry-point group ``plate_inspect.commands``: each entry is a
function ``register(subparsers)`` that adds its own subparser with a
``handler`` default. The pipeline never imports the service.

Kept as one module (~530 lines): every command's arguments beside its handler, so the CLI's
help and behaviour are read in one place.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import logging
import math
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import replace
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from pipeline.formats import AcquisitionError, InputError, PipelineError
from pipeline.parallel import configure_process

if TYPE_CHECKING:
    import numpy as np

    from pipeline.simulate import CaptureSpec, Cutout, Dent, Floor, PlateSpec
    from pipeline.stations import EarlyStations

EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_NOT_MEASURABLE, EXIT_HARDWARE = 0, 1, 2, 3, 4
#: ``simulate capture --plate-size``'s default (PlateSpec's own), mm.
_PLATE_SIZE = "3000x3000"


class BadArgument(ValueError):
    """A command-line value that cannot be used; reported like bad input (exit 2)."""


def _pair(
    text: str, *, sep: str = "x", kind: Callable[[str], int] = int, name: str
) -> tuple[int, int]:
    parts = text.lower().split(sep)
    try:
        if len(parts) != 2:
            raise ValueError
        first, second = parts
        return kind(first), kind(second)
    except ValueError:
        raise BadArgument(f"{name}: expected two numbers as A{sep}B, got {text!r}") from None


def _plate_size(text: str) -> tuple[float, float] | None:
    """``--plate-size WxL`` in mm (None: the default, PlateSpec's own)."""
    if text == _PLATE_SIZE:
        return None
    parts = text.lower().split("x")
    try:
        width, length = (float(v) for v in parts)
    except ValueError:
        raise BadArgument(f"--plate-size: expected WIDTHxLENGTH in mm, got {text!r}") from None
    return width, length


def _dent(text: str) -> Dent:
    from pipeline.simulate import Dent

    try:
        x, y, r, d = (float(v) for v in text.split(","))
    except ValueError:
        raise BadArgument(f"--dent: expected X_MM,Y_MM,RADIUS_MM,DEPTH_MM, got {text!r}") from None
    return Dent(x_mm=x, y_mm=y, radius_mm=r, depth_mm=d)


def _cutout(text: str) -> Cutout:
    from pipeline.simulate import Cutout

    try:
        values = [float(v) for v in text.split(",")]
        if len(values) == 3:
            return Cutout.circle(*values)
        if len(values) in (4, 5):
            return Cutout(*values)
        raise ValueError
    except ValueError as err:
        detail = f": {err}" if str(err) else ""
        raise BadArgument(
            f"--cutout: expected X_MM,Y_MM,RADIUS_MM (a round hole) or X_MM,Y_MM,WIDTH_MM,HEIGHT_MM[,CORNER_MM], "
            f"got {text!r}{detail}"
        ) from None


def _floor(args: argparse.Namespace, size_mm: tuple[float, float]) -> Floor | None:
    from pipeline.simulate import Floor, rail_supports

    if args.floor is None:
        if args.supports:
            raise BadArgument("--supports: expected --floor too (supports stand on the floor)")
        return None
    if not args.floor > 0:
        raise BadArgument(f"--floor: expected a distance > 0 mm below the plate, got {args.floor}")
    if args.supports < 0:
        raise BadArgument(f"--supports: expected a number of rails >= 0, got {args.supports}")
    supports = rail_supports(size_mm, args.floor, args.supports) if args.supports else ()
    return Floor(gap_mm=args.floor, albedo=args.floor_albedo, supports=supports)


# --------------------------------------------------------------------------- simulate


def _cmd_simulate_capture(args: argparse.Namespace) -> int:
    from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

    width, height = _pair(args.size, name="--size")
    plate_size = _plate_size(args.plate_size)
    plate = PlateSpec(
        shape=args.shape,
        radius_mm=None if args.shape == "plane" else args.radius,
        radius2_mm=args.radius2,
        convex=not args.concave,
        dents=tuple(_dent(d) for d in args.dent),
        distance_mm=args.distance,
        outline=args.outline,
        cutouts=tuple(_cutout(c) for c in args.cutout),
    )
    try:
        if plate_size is not None:
            plate = replace(plate, size_mm=plate_size)
        plate = replace(plate, floor=_floor(args, plate.size_mm))
    except (
        ValueError
    ) as err:  # a spec the simulator refuses (Floor, Support): bad input, not a defect
        raise BadArgument(str(err)) from None
    capture = CaptureSpec(
        n_lights=args.lights,
        noise=args.noise,
        bit_depth=args.bit_depth,
        specular=args.specular,
        stereo=not args.no_stereo,
        working_distance_mm=None if args.no_working_distance else args.distance,
        width=width,
        height=height,
        light_elevation_deg=args.elevation,
        near_field_mm=args.near_field,
        led_mu=args.led_mu,
        light_error_deg=args.light_error_deg,
        manifest_lights="nominal" if args.nominal_lights else "exact",
        texture=args.texture,
    )
    if args.stations is not None:
        return _simulate_stations(args, plate, capture)
    out = simulate_capture(
        args.out,
        plate=plate,
        capture=capture,
        plate_id=args.plate_id,
        tolerance_mm=args.tolerance,
        seed=args.seed,
    )
    print(out)
    return EXIT_OK


def _simulate_stations(args: argparse.Namespace, plate: PlateSpec, capture: CaptureSpec) -> int:
    """``simulate capture --stations N``: one bundle per conveyor station of a long plate."""
    from pipeline.simulate import simulate_stations

    if args.stations < 2:
        raise BadArgument(f"--stations: expected at least 2 stations, got {args.stations}")
    if args.station_spacing is None or not args.station_spacing > 0:
        raise BadArgument(
            f"--station-spacing: expected the conveyor's step > 0 mm with --stations, got {args.station_spacing}"
        )
    try:
        bundles = simulate_stations(
            args.out,
            n_stations=args.stations,
            spacing_mm=args.station_spacing,
            plate=plate,
            capture=capture,
            plate_id=args.plate_id,
            tolerance_mm=args.tolerance,
            seed=args.seed,
            encoder_error_mm=args.encoder_error,
            yaw_deg=args.yaw,
        )
    except ValueError as err:
        raise BadArgument(str(err)) from None
    for bundle in bundles:
        print(bundle)
    return EXIT_OK


def _cmd_simulate_boards(args: argparse.Namespace) -> int:
    from pipeline.simulate import default_rig, render_calibration_pairs

    width, height = _pair(args.size, name="--size")
    cols, rows = _pair(args.board, name="--board")
    paths = render_calibration_pairs(
        args.out,
        rig=default_rig(width=width, height=height),
        n_pairs=args.pairs,
        inner_corners=(cols, rows),
        square_mm=args.square,
        seed=args.seed,
    )
    print(f"{len(paths)} images in {args.out}")
    return EXIT_OK


# --------------------------------------------------------------------------- calibrate


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from pipeline.calibration import calibrate_stereo, calibration_document

    cols, rows = _pair(args.board, name="--board")
    if not args.square > 0:
        raise BadArgument(f"--square: expected a positive size in mm, got {args.square}")
    report = calibrate_stereo(args.dir, inner_corners=(cols, rows), square_mm=args.square)
    for view in report.views:
        print(f"  {view.key}: left {view.left_error_px:.3f} px, right {view.right_error_px:.3f} px")
    for key, reason in report.rejected:
        print(f"  {key}: not used: {reason}")
    print(
        f"{len(report.views)} pairs, stereo RMS {report.rms_px:.3f} px "
        f"(left {report.left_rms_px:.3f}, right {report.right_rms_px:.3f}), baseline {report.rig.baseline_mm:.1f} mm"
    )
    Path(args.out).write_text(json.dumps(calibration_document(report), indent=2) + "\n")
    print(f"wrote {args.out}")
    return EXIT_OK


# --------------------------------------------------------------------------- calibrate-lights


def _cmd_calibrate_lights(args: argparse.Namespace) -> int:
    from pipeline.io import light_calibration_document, load_capture
    from pipeline.lights.calibration import calibrate_lights

    captures = [load_capture(path) for path in args.bundles]
    cal = calibrate_lights(
        captures
    )  # a CaptureError: valid bundles that give no light calibration (exit 3)
    for k in range(cal.lights.n):
        p, a = cal.lights.positions_mm[k], cal.lights.axes[k]
        print(
            f"  light {k:2d}: position [{p[0]:8.1f} {p[1]:8.1f} {p[2]:8.1f}] mm +- {cal.position_std_mm[k]:.1f}, "
            f"axis [{a[0]:+.3f} {a[1]:+.3f} {a[2]:+.3f}], mu {cal.lights.mu[k]:.3f}, "
            f"intensity {cal.lights.intensity[k]:.4g}, lit {100 * cal.lit_fraction[k]:.0f} % of the plate"
        )
    print(
        f"{cal.lights.n} lights from {len(captures)} bundle(s): rms {cal.rms:.5f} (of the mean sample), "
        f"{cal.n_samples} samples of {cal.block_px} x {cal.block_px} px, {cal.iterations} iterations, {cal.seconds:.1f} s"
    )
    Path(args.out).write_text(
        json.dumps(light_calibration_document(cal.lights, cal.rms), indent=2) + "\n"
    )
    print(f"wrote {args.out}")
    return EXIT_OK


# --------------------------------------------------------------------------- acquire


def _cmd_acquire(args: argparse.Namespace) -> int:
    from pipeline.acquisition import StreamedFrames, acquire, acquire_stations, load_cell_config
    from pipeline.run import EarlyStations, warm_up

    if not args.plate_id.strip():
        raise BadArgument("--plate-id: expected a plate id, got an empty one")
    if (args.target is None) != (args.result is None):
        raise BadArgument(
            "--target, --result: expected both (inspect what is photographed) or neither"
        )
    timeout = {}
    if args.frame_timeout is not None:
        if not args.frame_timeout > 0:
            raise BadArgument(f"--frame-timeout: expected seconds > 0, got {args.frame_timeout}")
        timeout["frame_timeout_s"] = args.frame_timeout

    def progress(stage: str, fraction: float) -> None:
        if args.verbose:
            print(f"[{100 * fraction:5.1f} %] {stage}", file=sys.stderr)

    cell = load_cell_config(args.config)
    if args.target is not None:
        warm_up()  # kernel loading is start-up, not part of the measurement's timings
    if cell.conveyor is None:
        # with --target each frame is folded for the inspection as it arrives
        frames = StreamedFrames.for_cell(cell) if args.target is not None else {}
        out = acquire(
            args.config, args.plate_id, args.out, progress=progress, frames=frames, **timeout
        )
        returned_at = time.monotonic()
        record = json.loads((out / "capture.json").read_text())["acquisition"]
        print(
            f"{args.plate_id}: {len(record['frames'])} frames ({len(record['frames']) - 3} photometric, dark, stereo pair) "
            f"in {record['total_s']:.2f} s ({record['time_per_image_s'] * 1000:.0f} ms per image)"
        )
        print(f"wrote {out}")
        if args.target is not None:
            _inspect_acquired([out], args, returned_at, progress, None, frames)
        return EXIT_OK
    with contextlib.ExitStack() as stack:
        early = None
        if args.target is not None:
            # each station reconstructed while the conveyor moves on and the next is photographed
            early = stack.enter_context(EarlyStations(args.target, args.out))
        bundles = acquire_stations(
            args.config,
            args.plate_id,
            args.out,
            progress=progress,
            station_done=None if early is None else early.station_done,
            **timeout,
        )
        returned_at = time.monotonic()
        _print_stations(args.plate_id, bundles, args.out)
        if early is not None:
            _inspect_acquired(bundles, args, returned_at, progress, early)
    return EXIT_OK


def _inspect_acquired(
    bundles: list[Path],
    args: argparse.Namespace,
    returned_at: float,
    progress: Callable[[str, float], None],
    early: EarlyStations | None,
    frames: dict[str, np.ndarray] | None = None,
) -> None:
    """``acquire --target --result``: the bundles just photographed inspected (stations taken from
    ``early``, one view's images from ``frames`` in memory), ``timings_s.after_last_frame`` added,
    the result printed."""
    from pipeline.acquisition import add_after_last_frame, last_frame_time
    from pipeline.run import inspect

    last_frame_at = last_frame_time(bundles[-1], returned_at)
    capture: Path | list[Path] = bundles if len(bundles) > 1 else bundles[0]
    result = inspect(
        capture, args.target, out_dir=args.result, progress=progress, early=early, frames=frames
    )
    doc = dict(result.document)
    if last_frame_at is not None:
        add_after_last_frame(doc, Path(args.result), last_frame_at)
    _print_result(doc, Path(args.result))


def _print_stations(plate_id: str, bundles: list[Path], out: str) -> None:
    """What ``acquire`` took at each station."""
    for bundle in bundles:
        doc = json.loads((bundle / "capture.json").read_text())
        record = doc["acquisition"]
        print(
            f"{plate_id} station {doc['station']['index']}: travel {doc['station']['travel_mm']:.1f} mm "
            f"(moved in {record['conveyor']['move_s']:.2f} s), {len(record['frames'])} frames in "
            f"{record['total_s']:.2f} s"
        )
    print(f"wrote {len(bundles)} station bundles in {out}: {' '.join(b.name for b in bundles)}")


# --------------------------------------------------------------------------- inspect


def _cmd_inspect(args: argparse.Namespace) -> int:
    from pipeline.run import InspectOptions, inspect, warm_up

    if not args.no_warm_up:
        warm_up()  # kernel loading is start-up, not part of the measurement's timings

    def progress(stage: str, fraction: float) -> None:
        if args.verbose:
            print(f"[{100 * fraction:5.1f} %] {stage}", file=sys.stderr)

    result = inspect(
        args.capture if len(args.capture) > 1 else args.capture[0],
        args.target,
        out_dir=args.out,
        progress=progress,
        options=InspectOptions(normals_method=args.normals),
    )
    _print_result(result.document, Path(args.out))
    return EXIT_OK


def _print_result(doc: dict[str, Any], out: Path) -> None:
    """The one line of an inspection's result (and ``after_last_frame`` when timed), its file."""
    radius = doc["radius_mm"]
    dev = doc["deviation_mm"]
    after = doc["timings_s"].get("after_last_frame")
    print(
        f"{doc['plate_id']}: {doc['verdict'].upper()}"
        + (
            f"  radius {radius:.1f} mm ({doc['radius_error_pct']:+.3f} %)"
            if radius is not None
            else ""
        )
        + f"  deviation rms {dev['rms']:.2f} mm, max {dev['max_abs']:.2f} mm, {doc['within_tolerance_pct']:.2f} % within"
        f" {doc['tolerance_mm']} mm  ({doc['timings_s']['total']:.2f} s"
        + ("" if after is None else f"; {after:.2f} s after the last frame")
        + ")"
    )
    print(f"wrote {out / 'result.json'}")


def _cmd_gauge_study(args: argparse.Namespace) -> int:
    from pipeline import gauge
    from pipeline.run import warm_up

    warm_up()
    if args.bundles:
        if args.target is None:
            raise BadArgument("--target: expected the plate's target with --bundles")
        if len(args.bundles) < 2:
            raise BadArgument(f"--bundles: expected at least 2 bundles, got {len(args.bundles)}")
        with _workdir(args.out) as work:
            result = gauge.bundles_study(args.bundles, args.target, workdir=work)
    else:
        width, height = _pair(args.size, name="--size")
        if args.n < 2:
            raise BadArgument(f"--n: expected at least 2 repeats, got {args.n}")
        if not (math.isfinite(args.specular) and args.specular >= 0):
            raise BadArgument(f"--specular: expected a number >= 0, got {args.specular}")
        result = gauge.simulated_study(
            n=args.n,
            width=width,
            height=height,
            n_lights=args.lights,
            near_field_mm=args.near_field_mm,
            specular=args.specular,
            seed=args.seed,
            workdir=args.out,
        )
    print(result.table())
    return EXIT_OK


def _workdir(out: str | None) -> Any:
    """A context giving the study's working folder: ``out`` (kept) or a temporary one."""
    import contextlib
    import tempfile

    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        return contextlib.nullcontext(Path(out))
    return tempfile.TemporaryDirectory(prefix="plate-inspect-gauge-")


# --------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``plate-inspect`` with its subcommands, the service's ones from the entry points."""
    parser = argparse.ArgumentParser(
        prog="plate-inspect",
        description="Forming inspection of ship hull plates (photometric stereo + binocular depth).",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="print progress and warnings")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_simulate(sub)
    _add_calibrate(sub)
    _add_acquire(sub)
    _add_inspect(sub)
    _add_gauge_study(sub)
    for entry in entry_points(group="plate_inspect.commands"):
        entry.load()(sub)
    return parser


def _add_simulate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``plate-inspect simulate capture | boards``."""
    sim = sub.add_parser("simulate", help="render simulated captures or calibration boards")
    sim_sub = sim.add_subparsers(dest="what", required=True, metavar="WHAT")
    cap = sim_sub.add_parser(
        "capture", help="render a capture bundle of a plate (+ target.json, truth.npz)"
    )
    cap.add_argument("out", help="output folder")
    cap.add_argument(
        "--shape", choices=["plane", "cylinder", "sphere", "saddle"], default="cylinder"
    )
    cap.add_argument("--radius", type=float, default=5000.0, help="radius, mm (default 5000)")
    cap.add_argument("--radius2", type=float, default=None, help="saddle: second radius, mm")
    cap.add_argument(
        "--concave", action="store_true", help="bent away from the cameras (default: convex)"
    )
    cap.add_argument(
        "--dent",
        action="append",
        default=[],
        metavar="X,Y,R,D",
        help="local dent at plate coordinates X,Y mm, radius R mm, depth D mm (negative: bump); repeatable",
    )
    cap.add_argument(
        "--outline",
        choices=["rectangle", "trapezoid", "curved"],
        default="rectangle",
        help="plate outline (not a rectangle: the target is written as a mesh, target.stl)",
    )
    cap.add_argument(
        "--cutout",
        action="append",
        default=[],
        metavar="X,Y,R",
        help="opening through the plate at plate coordinates X,Y mm: radius R mm, or X,Y,W,H[,CORNER] "
        "for a rounded rectangle; repeatable (the target is then written as a mesh); "
        "a negative X needs the = form: --cutout=-500,200,150",
    )
    _add_surroundings_arguments(cap)
    _add_light_and_camera_arguments(cap)
    cap.add_argument(
        "--texture", choices=["rusty", "painted", "uniform"], default="rusty", help="plate albedo"
    )
    cap.add_argument("--no-stereo", action="store_true", help="omit the stereo pair")
    cap.add_argument(
        "--no-working-distance",
        action="store_true",
        help="omit working_distance_mm from the bundle",
    )
    cap.add_argument(
        "--tolerance", type=float, default=2.0, help="tolerance written to target.json, mm"
    )
    cap.add_argument("--plate-id", default="SIM-0001")
    cap.add_argument("--seed", type=int, default=0)
    _add_station_arguments(cap)
    cap.set_defaults(handler=_cmd_simulate_capture)
    boards = sim_sub.add_parser(
        "boards", help="render checkerboard pairs for `plate-inspect calibrate`"
    )
    boards.add_argument("out", help="output folder")
    boards.add_argument("--pairs", type=int, default=12)
    boards.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    boards.add_argument("--square", type=float, default=100.0, help="square size, mm (default 100)")
    boards.add_argument("--size", default="1224x1024", help="image size WIDTHxHEIGHT px")
    boards.add_argument("--seed", type=int, default=0)
    boards.set_defaults(handler=_cmd_simulate_boards)


def _add_station_arguments(cap: argparse.ArgumentParser) -> None:
    """``simulate capture``: the plate's size and the conveyor stations of a long plate."""
    cap.add_argument(
        "--plate-size",
        default=_PLATE_SIZE,
        metavar="WxL",
        help="plate size across x and along y (its axis, the conveyor's), mm (default 3000x3000)",
    )
    cap.add_argument(
        "--stations",
        type=int,
        default=None,
        metavar="N",
        help="render N conveyor stations of the plate, OUT/station_00 ... (docs/stations.md)",
    )
    cap.add_argument(
        "--station-spacing", type=float, default=None, metavar="MM", help="conveyor step, mm"
    )
    cap.add_argument(
        "--encoder-error",
        type=float,
        default=4.0,
        metavar="MM",
        help="with --stations: the encoder's travel is off by up to this, mm (default 4)",
    )
    cap.add_argument(
        "--yaw",
        type=float,
        default=0.3,
        metavar="DEG",
        help="with --stations: each station yaws by up to this, deg (default 0.3)",
    )


def _add_surroundings_arguments(cap: argparse.ArgumentParser) -> None:
    """``simulate capture``: what lies around and under the plate."""
    cap.add_argument(
        "--floor",
        type=float,
        default=None,
        metavar="MM",
        help="a lit, textured shop floor this far below the plate's lowest point, mm "
        "(default: a dark conveyor 40 mm behind the plate)",
    )
    cap.add_argument(
        "--floor-albedo", type=float, default=0.55, help="mean albedo of the floor (default 0.55)"
    )
    cap.add_argument(
        "--supports",
        type=int,
        default=0,
        metavar="N",
        help="with --floor: N rails 200-400 mm high (at most the floor's distance) across the plate",
    )


def _add_light_and_camera_arguments(cap: argparse.ArgumentParser) -> None:
    """``simulate capture``: the lights, the sensor and the working distance."""
    cap.add_argument(
        "--lights", type=int, default=12, help="number of light directions (default 12)"
    )
    cap.add_argument(
        "--noise",
        type=float,
        default=0.004,
        help="sensor noise, fraction of full scale (default 0.004)",
    )
    cap.add_argument("--bit-depth", type=int, choices=[8, 12, 16], default=16)
    cap.add_argument(
        "--specular", type=float, default=0.0, help="specular lobe strength (default 0: Lambertian)"
    )
    cap.add_argument(
        "--size", default="1224x1024", help="image size WIDTHxHEIGHT px (default 1224x1024)"
    )
    cap.add_argument(
        "--distance", type=float, default=3000.0, help="working distance, mm (default 3000)"
    )
    cap.add_argument(
        "--elevation",
        type=float,
        default=45.0,
        help="angle of the lights from the optical axis, seen from the plate centre, deg (default 45)",
    )
    cap.add_argument(
        "--near-field",
        type=float,
        default=None,
        metavar="MM",
        help="point lights (LEDs) this high above the plate, mm (default: distant lights)",
    )
    cap.add_argument(
        "--led-mu", type=float, default=0.0, help="LED beam profile exponent cos^mu (default 0)"
    )
    cap.add_argument(
        "--light-error-deg",
        type=float,
        default=0.0,
        help="write the lights turned by this angle about the plate centre (a bumped light)",
    )
    cap.add_argument(
        "--nominal-lights",
        action="store_true",
        help="with --near-field: write only each light's direction from the plate centre",
    )


def _add_calibrate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``plate-inspect calibrate`` and ``plate-inspect calibrate-lights``."""
    cal = sub.add_parser("calibrate", help="stereo calibration from checkerboard pairs (Zhang)")
    cal.add_argument("dir", help="folder of left<KEY>.<ext> / right<KEY>.<ext> pairs")
    cal.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    cal.add_argument("--square", required=True, type=float, help="square size, mm")
    cal.add_argument("--out", default="calibration.json", help="output stereo-calibration/1 file")
    cal.set_defaults(handler=_cmd_calibrate)

    lc = sub.add_parser(
        "calibrate-lights", help="measure the point lights (LEDs) on a flat reference plate"
    )
    lc.add_argument(
        "bundles",
        nargs="+",
        metavar="BUNDLE",
        help="capture bundle(s) of a flat, matte plate with a stereo pair (plate-capture/1); "
        "several (the plate at other heights) are fitted jointly",
    )
    lc.add_argument("--out", required=True, help="output light-calibration/1 file")
    lc.set_defaults(handler=_cmd_calibrate_lights)


def _add_acquire(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``plate-inspect acquire``."""
    acq = sub.add_parser(
        "acquire",
        help="photograph a plate in the cell and write a capture bundle (a cell with a conveyor: one "
        "per station, OUT/station_00 ...)",
    )
    acq.add_argument("config", help="cell configuration (cell-config/1)")
    acq.add_argument("--plate-id", required=True, help="the plate's id, written into the bundle")
    acq.add_argument(
        "--out",
        required=True,
        help="bundle folder to write (must not exist); with a conveyor, the folder of the stations' bundles",
    )
    acq.add_argument(
        "--frame-timeout",
        type=float,
        default=None,
        metavar="S",
        help="seconds a frame may take beyond its exposure before the camera counts as gone (default 2)",
    )
    acq.add_argument(
        "--target",
        default=None,
        help="inspect the plate against this target (plate-target/1) once photographed (with --result); "
        "with a conveyor each station is reconstructed as soon as it is photographed",
    )
    acq.add_argument(
        "--result",
        default=None,
        metavar="DIR",
        help="where the inspection writes result.json and its artifacts (with --target)",
    )
    acq.set_defaults(handler=_cmd_acquire)


def _add_inspect(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``plate-inspect inspect``."""
    ins = sub.add_parser("inspect", help="measure a capture bundle against its target")
    ins.add_argument(
        "capture",
        nargs="+",
        help="capture bundle: folder or .zip (plate-capture/1); several: the conveyor stations of one "
        "plate, measured as one (docs/stations.md)",
    )
    ins.add_argument("--target", required=True, help="target file (plate-target/1)")
    ins.add_argument("--out", required=True, help="output folder for result.json and artifacts")
    ins.add_argument(
        "--normals", choices=["robust", "lstsq"], default="robust", help="photometric estimator"
    )
    ins.add_argument(
        "--no-warm-up",
        action="store_true",
        help="skip loading the compiled kernels on a small simulated plate first (~0.4 s); "
        "the first inspection of a process then includes that loading in its timings",
    )
    ins.set_defaults(handler=_cmd_inspect)


def _add_gauge_study(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``plate-inspect gauge-study``."""
    gs = sub.add_parser(
        "gauge-study",
        help="type-1 gauge study: one plate measured n times, Cg and Cgk of its radius and deviation",
    )
    gs.add_argument(
        "--bundles", nargs="+", help="capture bundles of one plate (else the simulated cell)"
    )
    gs.add_argument("--target", help="the plate's target (with --bundles)")
    gs.add_argument("--n", type=int, default=25, help="simulated repeats (default 25)")
    gs.add_argument("--size", default="1224x1024", help="simulated image size WIDTHxHEIGHT px")
    gs.add_argument("--lights", type=int, default=12, help="simulated lights (default 12)")
    gs.add_argument(
        "--near-field-mm",
        type=float,
        help="simulated LEDs this high above the plate, positions given (default: distant lights)",
    )
    gs.add_argument(
        "--specular",
        type=float,
        default=0.0,
        help="simulated glossy coating: the specular lobe's strength against the diffuse (default 0, matte)",
    )
    gs.add_argument("--seed", type=int, default=0, help="first seed of the simulated repeats")
    gs.add_argument("--out", help="keep the bundles and results here (default: a temporary folder)")
    gs.set_defaults(handler=_cmd_gauge_study)


def main(argv: list[str] | None = None) -> int:
    """Run ``plate-inspect`` with ``argv`` (default: the command line); returns the exit code."""
    configure_process()  # the process's thread policy, before any kernel runs
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.handler(args) or EXIT_OK)
    except (InputError, BadArgument, FileNotFoundError, NotADirectoryError) as err:
        print(f"plate-inspect {args.command}: {_one_line(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (
        AcquisitionError
    ) as err:  # a camera or the light controller failed (acquire left no bundle)
        print(f"plate-inspect {args.command}: {_one_line(err)}", file=sys.stderr)
        return EXIT_HARDWARE
    except (
        PipelineError
    ) as err:  # valid input that cannot be measured (inspect wrote result.json saying why)
        print(f"plate-inspect {args.command}: {_one_line(err)}", file=sys.stderr)
        return EXIT_NOT_MEASURABLE
    except KeyboardInterrupt:
        return EXIT_INTERNAL
    except Exception as err:
        traceback.print_exc()
        print(f"plate-inspect {args.command}: internal error: {_one_line(err)}", file=sys.stderr)
        return EXIT_INTERNAL


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())


def run() -> NoReturn:
    """The console script ``plate-inspect``: :func:`main` on the command line, then exit.

    Before exiting, the objects alive are frozen out of the garbage collector (``gc.freeze``): the
    interpreter's finalisation otherwise walks every object of numba, scipy and OpenCV once more for
    cycles, 0.23 s after an inspection at 1224x1024 (0.08 s with them frozen, measured to the process's
    end). Objects are still freed, files closed and atexit handlers run. Not in :func:`main`, which
    tests and other programs call in their own process."""
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
