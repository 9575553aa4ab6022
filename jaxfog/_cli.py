"""The `jaxfog` command line: `jaxfog render SCENE.json -o OUT.exr [...]` (also `python -m jaxfog`).

Subcommands are entries in `COMMANDS`: a name, a one-line help, `configure(parser)` adding its arguments and
`run(args) -> exit code`: `render`, `convert` (a Mitsuba 3 XML scene to a scene file). The fit is
`python -m fitting.fit`; the benchmarks, not installed, are `python -m benchmarks.bench` etc. from a checkout.
Expected failures (an invalid scene, a bad argument, an unwritable output) print one line `jaxfog: error: ...` and
exit non-zero, without a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Callable, NamedTuple

from ._scene_io import SceneError

EXIT_ERROR = 1
EXIT_USAGE = 2


class CliError(Exception):
    """An expected failure: printed as one line, exit code `EXIT_ERROR`."""


class Command(NamedTuple):
    """A subcommand: `configure(parser)` adds its arguments, `run(args)` returns the exit code."""

    name: str
    help: str
    configure: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


EXPOSURE_RANGE = (-100.0, 100.0)
"""Preview exposure in stops: 2**100 is far beyond any useful preview, and stays finite in float32."""


def _exposure(text: str) -> float:
    value = _float(text)
    lo, hi = EXPOSURE_RANGE
    if not (math.isfinite(value) and lo <= value <= hi):
        raise argparse.ArgumentTypeError(f"{text} is out of range; valid range [{lo:g}, {hi:g}] stops")
    return value


# ------------------------------------------------------------------------------------------------------------ render
def _configure_render(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="SCENE.json", help="scene file (format: notes/ARCHITECTURE.md)")
    p.add_argument("-o", "--output", metavar="OUT.exr", required=True, help="linear float32 OpenEXR to write")
    p.add_argument("--spp", type=_positive_int, metavar="N",
                   help="samples per pixel (default: the file's integrator.spp)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S",
                   help="PRNG seed in [0, 4294967295] (default 0); same seed, same image")
    p.add_argument("--png", metavar="PREVIEW.png", help="also write an 8-bit sRGB preview")
    p.add_argument("--exposure", type=_exposure, default=0.0, metavar="E",
                   help="preview exposure in stops, in [-100, 100]: the PNG shows radiance * 2**E (default 0)")
    p.add_argument("--estimator", choices=("detached", "reparam"), default="detached",
                   help="derivative estimator compiled into the renderer (same image in expectation; default detached)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value, e.g. --set medium.sigma_t=0.8 --set camera.width=32 (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true",
                   help="render beyond the size limits (each side <= 16384 px, <= 4096 x 4096 px, spp <= 2^20, "
                        "max_depth <= 1024, <= 1e11 path segments; also lifted by JAXFOG_NO_LIMITS=1)")
    from ._distributed import add_arguments

    add_arguments(p)  # --coordinator HOST:PORT --num-processes N --process-id I (docs/distributed.md)


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.abspath(a) == os.path.abspath(b)


def _check_output(path: str, ext: str, option: str, inputs=()) -> None:
    """Refuse, before any work, an output that cannot be written or would destroy something: a wrong extension, a
    directory, one of the `inputs` (e.g. the scene file), a missing or unwritable directory, an existing read-only
    file (`_validate.read_only`: also one without write permission bits, which the superuser could replace)."""
    if not path.lower().endswith(ext):
        raise CliError(f"{option} {path}: expected a {ext} file name")
    if os.path.isdir(path):
        raise CliError(f"{option} {path}: is a directory; expected a {ext} file name")
    for other_option, other in inputs:
        if other and _same_file(path, other):
            raise CliError(f"{option} {path}: is also {other_option}; it would be overwritten")
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise CliError(f"{option} {path}: directory {directory} does not exist")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise CliError(f"{option} {path}: not writable (no permission to write in {directory})")
    if read_only(path):
        raise CliError(f"{option} {path}: the file is read-only; expected a writable file or a new name (make it "
                       f"writable to replace it)")


from ._measure import CompileTimer as _CompileTimer  # noqa: E402
from ._validate import read_only
from ._validate import seed_argument as _seed


def _run_render(args: argparse.Namespace) -> int:
    from . import _distributed

    try:  # the multi-process options, checked before any work (None: one process)
        launch = _distributed.launch_of(args.coordinator, args.num_processes, args.process_id)
    except _distributed.LaunchError as e:
        raise CliError(str(e)) from None
    if launch is None or launch.process_id in (None, 0):  # the process that writes (0) checks its outputs first
        _check_output(args.output, ".exr", "-o", [("SCENE.json", args.scene)])
        if args.png:
            _check_output(args.png, ".png", "--png", [("SCENE.json", args.scene), ("-o", args.output)])
    if launch is None:
        return _render_scene(args)

    def one_of_many() -> int:
        _distributed.initialize(launch)  # before anything makes a JAX array (the scene file does)
        return _render_scene(args, writer=_distributed.process_index() == 0)

    return _distributed.run_process(one_of_many, _render_failure)


def _render_failure(e: BaseException) -> int:
    """A multi-process render's failure in this process, printed as `main` prints it (with the process's id); the
    exit code."""
    from ._distributed import LaunchError, process_index, report_unexpected
    from ._validate import LimitError

    if isinstance(e, (LimitError, SceneError, CliError, OSError, LaunchError)):
        print(f"jaxfog: error: process {process_index()}: {_one_line(e)}", file=sys.stderr)
        return EXIT_USAGE if isinstance(e, LimitError) else EXIT_ERROR
    return report_unexpected(e, "jaxfog")


def _render_scene(args: argparse.Namespace, writer: bool = True) -> int:
    """The render itself, after the output checks; on every process of a multi-process run (the same render on all
    of their devices), where only the `writer` (process 0) writes and prints."""
    from ._image import write_exr, write_png
    from ._scene_io import load_scene

    from ._validate import check_size

    sf = load_scene(args.scene, args.overrides)  # validates before anything is compiled
    spp = args.spp if args.spp is not None else sf.spp
    base = os.path.basename(sf.path)
    check_size(sf.scene.camera.width, sf.scene.camera.height, spp, sf.scene.max_depth, force=args.force,
               rr_depth=sf.scene.rr_depth,
               names=dict(width=f"{base}: camera.width", height="camera.height",
                          spp="--spp" if args.spp is not None else f"{base}: integrator.spp",
                          max_depth=f"{base}: integrator.max_depth"),
               override="pass --force (or set JAXFOG_NO_LIMITS=1) to render anyway")

    import jax
    import numpy as np
    from tqdm import tqdm

    from ._render import render

    cam = sf.scene.camera
    t0 = time.perf_counter()
    with tqdm(total=spp, unit="spp", desc=sf.name, disable=args.no_progress or not writer, file=sys.stderr,
              leave=False) as bar:

        def progress(done: int, total: int) -> None:
            bar.update(done - bar.n)

        with _CompileTimer() as compile_timer:
            image = render(sf.scene, jax.random.key(args.seed), spp, estimator=args.estimator, progress=progress)
            image = np.asarray(image)  # waits for the device
    wall = time.perf_counter() - t0

    metadata = {
        "jaxfog:scene": sf.name,
        "jaxfog:scene_file": os.path.abspath(sf.path),
        "jaxfog:spp": str(spp),
        "jaxfog:seed": str(args.seed),
        "jaxfog:estimator": args.estimator,
        "jaxfog:medium": json.dumps(_without_nulls(sf.data["medium"])),
        "jaxfog:overrides": json.dumps(list(args.overrides)),
        "jaxfog:scene_json": json.dumps(sf.data),
        "jaxfog:version": _version(),
    }
    from ._validate import check_finite

    try:  # before anything is written: a failed render never replaces an existing image
        check_finite(image, args.output)
    except FloatingPointError as e:
        kept = "; the existing file is unchanged" if os.path.exists(args.output) else ""
        raise CliError(f"{e}; nothing written{kept} (a parameter at the edge of float32?)") from None
    if not writer:  # another process of a multi-process run: process 0 writes and prints
        return 0
    write_exr(args.output, image, metadata)
    written = [args.output]
    if args.png:
        write_png(args.png, image, exposure=args.exposure)
        written.append(args.png)
    mean = float(np.mean(image, dtype=np.float64))  # float64: a float32 sum of finite values near 3e38 overflows
    print(f"{sf.name}: {cam.width}x{cam.height}, {spp} spp, seed {args.seed}: mean pixel {mean:.4g}")
    print(f"wrote {', '.join(written)}")
    print(f"compile {compile_timer.seconds:.2f} s, wall {wall:.2f} s "
          f"(render {max(wall - compile_timer.seconds, 0.0):.2f} s)")
    if jax.process_count() > 1:
        print(f"on {jax.device_count()} devices of {jax.process_count()} processes")
    return 0


def _without_nulls(value):
    """A validated scene value with the keys that were left out (None) dropped, for compact headers."""
    if isinstance(value, dict):
        return {k: _without_nulls(v) for k, v in value.items() if v is not None}
    return value


def _version() -> str:
    from . import __version__

    return __version__


# ----------------------------------------------------------------------------------------------------------- convert
def _parameter(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return name.strip(), value


def _configure_convert(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="SCENE.xml",
                   help="Mitsuba 3 XML scene (the subset jaxfog models: docs/conventions.md, \"Mitsuba 3\")")
    p.add_argument("-o", "--output", metavar="OUT.json", required=True,
                   help="jaxfog scene file to write (mesh files relative to its folder)")
    p.add_argument("-D", dest="parameters", action="append", default=[], type=_parameter, metavar="NAME=VALUE",
                   help="a value for $NAME in the XML, overriding its <default> (as mitsuba -D; repeatable)")


def _run_convert(args: argparse.Namespace) -> int:
    import warnings

    from ._mitsuba_xml import MitsubaXmlWarning, scene_from_mitsuba_xml, scene_json_text

    _check_output(args.output, ".json", "-o", [("SCENE.xml", args.scene)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MitsubaXmlWarning)
        data = scene_from_mitsuba_xml(args.scene, dict(args.parameters))
    for w in caught:
        print(f"jaxfog: warning: {_one_line(w.message)}", file=sys.stderr)
    folder = os.path.dirname(os.path.abspath(args.output))
    for shape in data["shapes"]:  # mesh files relative to the scene file, as load_scene reads them
        if shape["type"] == "mesh":
            shape["file"] = os.path.relpath(shape["file"], folder)
    text = scene_json_text(data)
    tmp = os.path.join(folder, f".{os.path.basename(args.output)}.tmp-{os.getpid()}")
    try:  # atomic: a reader never sees half a file, a failure leaves the old one
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, args.output)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    cam = data["camera"]
    medium = "no fog" if data.get("medium") is None else "fog"
    print(f"{data['name']}: {cam['width']}x{cam['height']}, {len(data['shapes'])} shapes, "
          f"{len(data['lights'])} lights, {medium}")
    print(f"wrote {args.output}")
    return 0


COMMANDS: list[Command] = [
    Command("render", "render a scene file to an OpenEXR (and optionally a PNG preview)",
            _configure_render, _run_render),
    Command("convert", "convert a Mitsuba 3 XML scene to a jaxfog scene file", _configure_convert, _run_convert),
]
"""The subcommands, in `--help` order. Add `Command(name, help, configure, run)` entries for new ones."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxfog",
        description="jaxfog: a differentiable fog renderer in JAX.",
        epilog="Example: jaxfog render data_synthetic/scenes/spot_fog.json -o spot_fog.exr --png spot_fog.png "
        "--exposure 2 --set medium.sigma_t=0.8",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for cmd in COMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.configure(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `jaxfog` console script and `python -m jaxfog`; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2; argparse has printed the message)
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    from jaxfog._devices import use_cpu_cores

    use_cpu_cores()  # every core as a JAX device (warns if JAX has already started with another count)
    from jaxfog._cache import use_compilation_cache

    use_compilation_cache()  # compiled programs kept on disk: a second run does not compile again ($JAXFOG_CACHE_DIR)
    from ._validate import LimitError

    try:
        return args._run(args)
    except LimitError as e:  # a size beyond the limits: a usage error, with the way to lift it in the message
        print(f"jaxfog: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except (SceneError, CliError, OSError) as e:  # expected failures; anything else is a bug: traceback
        print(f"jaxfog: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("jaxfog: interrupted", file=sys.stderr)
        return 130


def _one_line(e: BaseException) -> str:
    text = str(e) or type(e).__name__
    return " ".join(text.split())


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
