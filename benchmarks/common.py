"""The benchmarks' harness: what every benchmark script shares, so that each script holds only its experiment.

Where things are
- `REPO`, `scene_path(name)`, `load(name, size, overrides)`: the repository, its shipped scenes.
- `OUT`, `out_dir(name)`: where a run writes by default (`bench_out/<name>/` in the repository, not tracked).
- `subprocess_env()`: the environment of a `python -m benchmarks.X` subprocess.

Timing (wall seconds from `time.perf_counter`, CPU seconds of the whole process from `time.process_time`)
- `Stopwatch()`: one block's (or a run's) wall and CPU seconds: `with Stopwatch() as sw: ...`, then `sw.s`, `sw.cpu_s`.
- `time_calls(fn, n, warmup)`: `fn` called `warmup` times untimed (compiles), then `n` times timed; medians.
- `interleave({label: fn}, rounds)`: the functions in turn, A B A B ... (or A B, B A, ...), so that a change of the
  machine's speed hits every label alike; per-label times and per-round ratios against the first label.
- `compile_timed(jitted, *args)`: `jitted.lower(*args).compile()` and its seconds.

Recording
- `machine_info()`: CPU model and cores, Python, jax and its devices, load average, date, git commit.
- `write_json(path, payload)`: JSON with the machine record added, written atomically (`jaxfog.tools.atomic_write`);
  `save_npz(path, **arrays)` likewise for arrays; `command(prog, argv)`: the command line, for the record;
  `read_json(path, missing)`: an earlier run's JSON (to keep the parts not run again); `print_json(obj)`: one JSON
  line on stdout; `run_summary(what, result)`: the closing "wrote ... in N s (load average ...)" line;
  `digest(obj)`: a short hash of a JSON-able key (cache file names).
- `with_args(cfg, args)`: a benchmark's configuration (a dataclass) with the command line's values.
- `print_table(rows, columns)`, `format_table(rows, columns)`: a plain-text (or Markdown) table, on stdout or as
  text; `stderr_log(text)`: a progress line on stderr; `pyplot()`: matplotlib's pyplot without a display,
  `save_figure(fig, path)`: a figure to a file.

Statistics: `mean_and_se(values)`, `block_means(image, n)`; XLA memory: `memory_dict(memory_analysis)` (MiB).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from jaxfog.tools import CompileTimer, atomic_write

REPO = Path(__file__).resolve().parent.parent
"""The repository root (the folder holding `benchmarks/`, `jaxfog/` and `data_synthetic/`)."""

SCENE_DIR = REPO / "data_synthetic" / "scenes"

OUT = REPO / "bench_out"
"""The root of the benchmarks' default output folders (ignored by git; `--out` chooses another)."""


def out_dir(name: str) -> Path:
    """The default output folder of the benchmark `name`: `bench_out/<name>/` in the repository."""
    return OUT / name


def scene_path(name: str) -> Path:
    """A shipped scene by name (`spot_fog`), or a path to a scene file (`.json`)."""
    p = Path(name)
    return p if p.suffix == ".json" else SCENE_DIR / f"{name}.json"


def load(name, size: int | None = None, overrides=()):
    """`jaxfog.load_scene` of a shipped scene (or a `.json` path, or a scene file's dict) at `size x size` pixels
    (None: the file's), with further `"key.path=value"` overrides; returns the `SceneFile`."""
    import jaxfog as jf
    from jaxfog.tools import scene_from_dict

    over = [*([] if size is None else [f"camera.width={size}", f"camera.height={size}"]), *overrides]
    if isinstance(name, dict):
        return scene_from_dict(name, source=name.get("name", "scene"), overrides=over)
    return jf.load_scene(scene_path(name), over)


def subprocess_env(env: dict | None = None) -> dict:
    """The environment for `python -m benchmarks.X` in a subprocess: `env` (default this process's) with the
    repository root first on `PYTHONPATH`, so `benchmarks` and this checkout's `jaxfog` are the ones imported."""
    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


# ================================================================================================== timing
class Stopwatch:
    """Wall seconds (`time.perf_counter`, or `clock`) and CPU seconds of the whole process (`time.process_time`)
    since it was made (or `restart`ed): `s` and `cpu_s` read the time so far; `stop()` (or the end of a `with`
    block) keeps them at that moment.

        with Stopwatch() as sw:
            work()
        print(sw.s, sw.cpu_s)
    """

    def __init__(self, clock: Callable[[], float] = time.perf_counter):
        self.clock = clock
        self.restart()

    def restart(self) -> "Stopwatch":
        self._end = None
        self._t0, self._c0 = self.clock(), time.process_time()
        return self

    def stop(self) -> float:
        """Keeps the times at this moment; returns the wall seconds."""
        self._end = (self.clock(), time.process_time())
        return self.s

    def __enter__(self) -> "Stopwatch":
        return self.restart()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def s(self) -> float:
        """Wall seconds (of the clock)."""
        return (self.clock() if self._end is None else self._end[0]) - self._t0

    @property
    def cpu_s(self) -> float:
        """CPU seconds of the process, all threads."""
        return (time.process_time() if self._end is None else self._end[1]) - self._c0


def _summary(wall: list, cpu: list) -> dict:
    med = lambda x: statistics.median(x) if x else float("nan")  # noqa: E731
    return {"wall_s": wall, "cpu_s": cpu, "median_s": med(wall), "median_cpu_s": med(cpu),
            "min_s": min(wall, default=float("nan")), "min_cpu_s": min(cpu, default=float("nan"))}


def _warm(fn: Callable, warmup: int) -> dict:
    """`warmup` untimed calls `fn(0)`: the first one's wall seconds and the JAX compile seconds of all of them (JAX's
    trace, lower and compile events), both None without a warm-up."""
    if warmup < 1:
        return {"first_call_s": None, "compile_s": None}
    with CompileTimer() as ct:
        with Stopwatch() as first:
            fn(0)
        for _ in range(warmup - 1):
            fn(0)
    return {"first_call_s": first.s, "compile_s": ct.seconds}


def _call(fn: Callable, i: int, rec: dict, keep: bool) -> None:
    with Stopwatch() as sw:
        value = fn(i)
    rec["wall_s"].append(sw.s)
    rec["cpu_s"].append(sw.cpu_s)
    if keep:
        rec["values"].append(value)


def time_calls(fn: Callable[[int], Any], n: int, warmup: int = 1, keep: bool = False) -> dict:
    """`fn(0)` `warmup` times untimed (the first call compiles), then `fn(i)` for i = 0 .. n-1, each timed.

    `fn` must return only once its work is done (`jax.block_until_ready`, or a NumPy result on the host); its
    argument is the call's index (e.g. for a fresh key per call). Returns `wall_s` and `cpu_s` (lists, s per call),
    `median_s`, `median_cpu_s`, `min_s`, `min_cpu_s`, `first_call_s` (the first warm-up call, s; None without one),
    `compile_s` (JAX compile seconds during the warm-up), and with `keep` the return values as `values`."""
    rec = {"wall_s": [], "cpu_s": [], "values": []}
    warm = _warm(fn, warmup)
    for i in range(n):
        _call(fn, i, rec, keep)
    return {**_summary(rec["wall_s"], rec["cpu_s"]), **warm, **({"values": rec["values"]} if keep else {})}


def interleave(fns: dict, rounds: int, warmup: int = 1, alternate: bool = False, keep: bool = False,
               log: Callable[[str], None] | None = None) -> dict:
    """The functions of `fns` (label -> `fn(round)`) called in turn, `rounds` times: A B A B ... (with `alternate`,
    every other round in reverse order: A B, B A, ...), after `warmup` untimed calls `fn(0)` of each.

    Returns, per label, what `time_calls` returns (lists over the rounds), plus `ratio` (per round, this label's wall
    time over the first label's), `ratio_median`, `cpu_ratio` and `cpu_ratio_median` (the same for CPU time): ratios
    inside one round are the numbers to trust on a shared machine. `log(text)` is told each round's end."""
    labels = list(fns)
    recs = {k: {"wall_s": [], "cpu_s": [], "values": [], **_warm(fns[k], warmup)} for k in labels}
    sw = Stopwatch()
    for r in range(rounds):
        for k in (labels[::-1] if alternate and r % 2 else labels):
            _call(fns[k], r, recs[k], keep)
        if log is not None:
            log(f"  round {r + 1}/{rounds} ({sw.s:.0f} s)")
    base = recs[labels[0]]
    out = {}
    for k, rec in recs.items():
        ratio = [a / b for a, b in zip(rec["wall_s"], base["wall_s"])]
        cpu_ratio = [a / b if b > 0 else float("nan") for a, b in zip(rec["cpu_s"], base["cpu_s"])]
        out[k] = {**_summary(rec["wall_s"], rec["cpu_s"]), "first_call_s": rec["first_call_s"],
                  "compile_s": rec["compile_s"], "ratio": ratio,
                  "ratio_median": statistics.median(ratio) if ratio else float("nan"),
                  "cpu_ratio": cpu_ratio, "cpu_ratio_median": statistics.median(cpu_ratio) if ratio else float("nan"),
                  **({"values": rec["values"]} if keep else {})}
    return out


def compile_timed(jitted, *args, **compiler_options):
    """`(compiled, seconds)`: `jitted.lower(*args).compile()` (with XLA `compiler_options` where given) and its wall
    time, trace and lowering included."""
    with Stopwatch() as sw:
        compiled = jitted.lower(*args).compile(**({"compiler_options": compiler_options} if compiler_options else {}))
    return compiled, sw.s


def with_args(cfg, args):
    """The dataclass `cfg` with each field replaced by the command-line argument of the same name (`args`, an
    `argparse.Namespace`) where that is given (not None); lists become tuples."""
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cfg) if getattr(args, f.name, None) is not None}
    return dataclasses.replace(cfg, **{k: tuple(v) if isinstance(v, list) else v for k, v in given.items()})


# =============================================================================================== recording
def git_commit() -> str:
    """The checkout's commit, with "+dirty" when tracked files differ from it ("" outside git)."""
    try:
        run = lambda *a: subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True,  # noqa: E731
                                        timeout=30).stdout.strip()
        rev = run("rev-parse", "HEAD")
        return rev + ("+dirty" if rev and run("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        return ""


def machine_info() -> dict:
    """Where and when a benchmark ran: platform, CPU model, cores, Python, jax and its devices, the load average
    and niceness now, the date (UTC) and the git commit."""
    import jax

    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), "")
    except OSError:
        pass
    return {"platform": platform.platform(), "cpu": cpu or platform.processor(), "python": platform.python_version(),
            "jax": jax.__version__, "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
            "cpu_count": os.cpu_count(), "loadavg_start": list(os.getloadavg()), "nice": os.nice(0),
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "commit": git_commit()}


def command(prog: str, argv: list[str] | None = None) -> str:
    """The command line of this run, for the record: `prog` and `argv` (default this process's arguments)."""
    return " ".join([prog, *(sys.argv[1:] if argv is None else argv)])


def json_default(o):
    """`json.dumps(..., default=json_default)`: numpy scalars and arrays as Python numbers and lists, paths as
    strings."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def write_json(path, payload: dict) -> None:
    """`payload` as indented JSON (numpy values converted), written atomically: a run stopped half-way leaves the
    previous file whole; the folder is created if missing. Adds `machine` (`machine_info()`) to `payload` where it
    has none, and the load average now as its `loadavg_end`."""
    machine = payload.setdefault("machine", machine_info())
    if isinstance(machine, dict):
        machine["loadavg_end"] = list(os.getloadavg())
    text = json.dumps(payload, indent=1, default=json_default)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)

    def write(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    atomic_write(path, write)


_MISSING = object()


def read_json(path, missing=_MISSING):
    """The JSON file `path` (an earlier run's record); `missing` where there is no such file (without `missing`, a
    missing file raises `FileNotFoundError`)."""
    if missing is not _MISSING and not os.path.exists(path):
        return missing
    with open(path) as f:
        return json.load(f)


def print_json(obj, label: str = "") -> None:
    """`obj` as one JSON line on stdout (numpy values converted), after `label` where given, at once."""
    print(*([label] if label else []), json.dumps(obj, default=json_default), flush=True)


def digest(obj, n: int = 12) -> str:
    """The first `n` hex digits of the SHA-256 of `obj` as JSON with sorted keys: a cache file's name part, changing
    whenever anything in `obj` does."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:n]


def run_summary(what: str, result: dict) -> str:
    """The closing line of a run: `wrote WHAT in N s (load average A at start, B at end)`, from `result`'s
    `total_wall_s` and `machine` (as `write_json` completed it)."""
    m = result["machine"]
    return (f"wrote {what} in {result['total_wall_s']:.0f} s (load average {m['loadavg_start'][0]:.1f} at start, "
            f"{m['loadavg_end'][0]:.1f} at end)")


def save_npz(path, compressed: bool = False, **arrays) -> None:
    """`np.savez` (or `np.savez_compressed`) of `arrays` to `path` (ending in `.npz`), written atomically (its folder
    created if missing)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save = np.savez_compressed if compressed else np.savez
    atomic_write(path, lambda tmp: save(tmp, **arrays))


def _cell(row, key, spec) -> str:
    """A table cell's text: `spec` applied to the row's value (`-` where it has none)."""
    v = key(row) if callable(key) else row.get(key)
    if v is None:
        return "-"
    if callable(spec):
        return spec(v)
    try:
        return format(v, spec)
    except (TypeError, ValueError):
        return str(v)


def _numeric(text: str) -> bool:
    """Whether a cell reads as a number (with any marks after it): right-aligned."""
    return text == "-" or re.match(r"[-+]?(\d|\.\d|nan|inf)", text) is not None


def format_table(rows: list, columns: list, markdown: bool = False) -> str:
    """`rows` (dicts) as the text of a table. `columns`: `(header, key)` or `(header, key, spec)` each; `key` is a key
    of the row or a function of it, `spec` a format spec (`".3f"`) or a function of the value to its text. Numbers
    (also with marks after them, `3.2!`) are right-aligned, text left-aligned; a missing value shows as `-`. With
    `markdown`, a Markdown table."""
    cols = [(c[0], c[1], c[2] if len(c) > 2 else "") for c in columns]
    cells = [[_cell(r, key, spec) for _, key, spec in cols] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(h for h, _, _ in cols) + " |", "|" + " --- |" * len(cols)]
        return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in cells])
    widths = [max([len(h)] + [len(row[j]) for row in cells]) for j, (h, _, _) in enumerate(cols)]
    right = [bool(cells) and all(_numeric(row[j].strip()) for row in cells) for j in range(len(cols))]
    fmt = lambda t, j: t.rjust(widths[j]) if right[j] else t.ljust(widths[j])  # noqa: E731
    lines = [" ".join(fmt(h, j) for j, (h, _, _) in enumerate(cols)).rstrip()]
    return "\n".join(lines + [" ".join(fmt(t, j) for j, t in enumerate(row)).rstrip() for row in cells])


def print_table(rows: list, columns: list, markdown: bool = False) -> str:
    """`format_table(rows, columns, markdown)` printed on stdout; returns its text."""
    text = format_table(rows, columns, markdown)
    print(text, flush=True)
    return text


def stderr_log(text: str) -> None:
    """A benchmark's progress line: on stderr (stdout holds the tables), at once."""
    print(text, file=sys.stderr, flush=True)


def pyplot():
    """`matplotlib.pyplot` on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 80) -> None:
    """A figure of `pyplot()`, laid out tight, saved to `path` and closed."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


# ============================================================================================== statistics
def mean_and_se(values):
    """Mean over the first axis of independent samples and its standard error (`std(ddof=1) / sqrt(n)`; nan for one
    sample): NumPy float64 scalars for a 1-D input, arrays otherwise."""
    v = np.asarray(values, np.float64)
    m = v.mean(0)
    return m, (v.std(0, ddof=1) / math.sqrt(len(v)) if len(v) > 1 else m * np.nan)


def block_means(image, n: int = 4):
    """Means of an `(H, W, C)` image over an `n x n` grid of blocks, channels averaged: `(n, n)`, rows top to bottom,
    columns left to right.

    A NumPy (or list) image gives float64; when `n` does not divide H or W the blocks differ by at most one row or
    column (`np.array_split`). A JAX array (also a tracer inside `jit`/`jvp`) stays a JAX array; then H and W must
    be multiples of `n`."""
    if not isinstance(image, np.ndarray):
        import jax

        if isinstance(image, jax.Array):
            H, W = image.shape[:2]
            if H % n or W % n:
                raise ValueError(f"block_means of a JAX array: {H} x {W} is not a multiple of {n}")
            return image.mean(-1).reshape(n, H // n, n, W // n).mean(axis=(1, 3))
    img = np.asarray(image, np.float64).mean(axis=-1)
    H, W = img.shape
    if H % n == 0 and W % n == 0:
        return img.reshape(n, H // n, n, W // n).mean(axis=(1, 3))
    rows, cols = np.array_split(np.arange(H), n), np.array_split(np.arange(W), n)
    return np.array([[img[np.ix_(r, c)].mean() for c in cols] for r in rows])


MIB = 1.0 / (1 << 20)


def memory_dict(memory_analysis) -> dict:
    """XLA's `compiled.memory_analysis()` in MiB: argument, output and temporary buffers, and their total."""
    a, o, t = (memory_analysis.argument_size_in_bytes, memory_analysis.output_size_in_bytes,
               memory_analysis.temp_size_in_bytes)
    return {"argument_mib": a * MIB, "output_mib": o * MIB, "temp_mib": t * MIB, "total_mib": (a + o + t) * MIB}
