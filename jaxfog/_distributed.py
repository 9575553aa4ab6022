"""One render or fit on the devices of several processes (hosts), through JAX's multi-controller runtime.

Every process runs the same program: `jax.distributed.initialize` (before any other JAX call) connects it to the
coordinator (process 0's address), after which `jax.devices()` lists every process's devices and `render` (whose
default devices are `jax.devices()`) shares each render's work items among all of them; each process gets the whole
image, and process 0 alone writes files and prints. There is no scheduler of ours: the processes are started by
hand, by a cluster's launcher (Slurm, Open MPI, Kubernetes) or by a test; docs/distributed.md has the commands.

This module holds what the entry points (`jaxfog render`, `python -m fitting.fit`) share: the command-line options
(`add_arguments`, `launch_of`), `initialize` (Gloo collectives on CPUs, bounded timeouts) and `run_process` (a
process whose run fails ends at once, so that the others end too, within a bounded time, instead of waiting for it).
"""

from __future__ import annotations

import argparse
import os
import sys
import traceback
from typing import Callable, NamedTuple

HEARTBEAT_TIMEOUT_S = 30
"""A process that sends no heartbeat for this long is dead for JAX's coordination service, which then ends every
other process of the run (JAX's own message: "Terminating process because the JAX distributed service detected
fatal errors"). JAX's default is 100 s; heartbeats come from a thread of their own, so a long compile sends them."""

INITIALIZATION_TIMEOUT_S = 300
"""How long `initialize` waits for every process to connect (JAX's default): processes a cluster starts minutes
apart still meet; a process started with a wrong coordinator address fails after this long."""

SHUTDOWN_TIMEOUT_S = 300
"""How long a process that has finished waits at JAX's shutdown barrier for the others to finish (JAX's default):
process 0 writes the files after the last render while the others wait there."""

ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"
"""JAX's environment variable for the coordinator's address; `jax.distributed.initialize` reads it itself."""


class LaunchError(ValueError):
    """A multi-process option or environment that cannot work (a one-line message naming the option)."""


class Launch(NamedTuple):
    """This process's place in a multi-process run: the coordinator `HOST:PORT` (process 0's address, reachable from
    every process), the number of processes and this process's id in `[0, num_processes)`; the count and the id may
    be None, for `jax.distributed.initialize` to take from the cluster's environment (Slurm, Open MPI, ...)."""

    coordinator: str
    num_processes: int | None
    process_id: int | None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of a multi-process run: `--coordinator HOST:PORT --num-processes N --process-id I`."""
    g = parser.add_argument_group("multi-process run (one render on every device of several processes or hosts; "
                                  "docs/distributed.md)")
    g.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                   help=f"process 0's address and a free port there, the same for every process (default: "
                        f"${ENV_COORDINATOR}; neither: one process)")
    g.add_argument("--num-processes", type=int, metavar="N", default=None,
                   help="how many processes take part (default: from Slurm / Open MPI, where JAX finds it)")
    g.add_argument("--process-id", type=int, metavar="I", default=None,
                   help="this process's id in [0, N); process 0 writes the outputs and prints (default: from Slurm "
                        "/ Open MPI)")


def launch_of(coordinator: str | None, num_processes: int | None, process_id: int | None,
              environ=os.environ) -> Launch | None:
    """The options checked (before any work): a `Launch`, or None for a run of one process (none of the options and
    no `$JAX_COORDINATOR_ADDRESS`). Raises `LaunchError` with a one-line message naming the option."""
    env = environ.get(ENV_COORDINATOR) or None
    if coordinator is None and num_processes is None and process_id is None and env is None:
        return None
    if coordinator is None and env is None:
        given = " ".join(f"{o} {v}" for o, v in (("--num-processes", num_processes), ("--process-id", process_id))
                         if v is not None)
        raise LaunchError(f"{given}: a multi-process run needs --coordinator HOST:PORT (process 0's address and a "
                          f"free port, the same for every process) or ${ENV_COORDINATOR}")
    where = "--coordinator" if coordinator is not None else f"${ENV_COORDINATOR}"
    address = coordinator if coordinator is not None else env
    check_address(address, where)
    if num_processes is not None and num_processes < 1:
        raise LaunchError(f"--num-processes {num_processes}: expected a positive integer")
    if process_id is not None and process_id < 0:
        raise LaunchError(f"--process-id {process_id}: expected an integer in [0, N) (N: --num-processes)")
    if num_processes is not None and process_id is not None and process_id >= num_processes:
        raise LaunchError(f"--process-id {process_id} is out of range for --num-processes {num_processes}; valid "
                          f"range [0, {num_processes - 1}]")
    return Launch(address, num_processes, process_id)


def check_address(address: str, where: str = "--coordinator") -> None:
    """`HOST:PORT` (an IPv6 host in brackets, `[::1]:1234`) with a port in [1, 65535], else `LaunchError`."""
    host, sep, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or any(c.isspace() for c in address):
        raise LaunchError(f"{where} {address!r}: expected HOST:PORT, e.g. 10.0.0.1:1234 or localhost:1234")
    if not port.isdigit() or not 1 <= int(port) <= 65535:
        raise LaunchError(f"{where} {address!r}: the port {port!r} is not an integer in [1, 65535]")


def initialize(launch: Launch) -> None:
    """Join the run: `jax.distributed.initialize` with Gloo collectives on CPUs and this module's timeouts. Must run
    before any other JAX call (scene files make JAX arrays: load them afterwards). Raises `LaunchError` when the
    count or id cannot be found or JAX has already started."""
    import inspect

    import jax

    # CPU collectives across processes: Gloo (JAX's default since 0.6 at least; before that there were none unless
    # this was set). GPUs use NCCL whatever this says.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    timeouts = {"heartbeat_timeout_seconds": HEARTBEAT_TIMEOUT_S,  # JAX >= 0.7.0 (before: JAX's 100 s)
                "shutdown_timeout_seconds": SHUTDOWN_TIMEOUT_S}  # a later JAX (0.10.2 has it; before: 300 s)
    known = inspect.signature(jax.distributed.initialize).parameters
    try:
        jax.distributed.initialize(coordinator_address=launch.coordinator, num_processes=launch.num_processes,
                                   process_id=launch.process_id, initialization_timeout=INITIALIZATION_TIMEOUT_S,
                                   **{k: v for k, v in timeouts.items() if k in known})
    except (ValueError, TypeError, RuntimeError) as e:
        text = " ".join(str(e).split())
        if "Number of processes" in text:
            text = "--num-processes not given and not found in the environment (Slurm, Open MPI)"
        elif "process id" in text:
            text = "--process-id not given and not found in the environment (Slurm, Open MPI)"
        raise LaunchError(f"cannot join the run at {launch.coordinator}: {text}") from None
    except Exception as e:  # noqa: BLE001 - a JaxRuntimeError from connecting: the coordinator was not reached
        raise LaunchError(f"cannot join the run at {launch.coordinator} within {INITIALIZATION_TIMEOUT_S} s "
                          f"(is process 0 running, and HOST:PORT its reachable address?): "
                          f"{' '.join(str(e).split())[:300]}") from None


def process_index() -> int:
    """This process's id in the run (0 when JAX's distributed runtime is not initialized)."""
    import jax

    return jax.process_index()


def describe(e: BaseException) -> str:
    """One line for a failure in a process of a multi-process run; a failed collective (another process died or was
    stopped) says so."""
    text = " ".join((str(e) or type(e).__name__).split())
    if type(e).__name__ == "JaxRuntimeError" and ("Gloo" in text or "peer" in text.lower()):
        text = f"another process of the run failed or was stopped ({text[:300]})"
    return text


def run_process(body: Callable[[], int], report: Callable[[BaseException], int]) -> int:
    """Run `body()` (returning an exit code) as one process of a multi-process run. When it raises, `report(e)`
    prints the failure and gives the exit code, and the process ends at once (`os._exit`, after flushing), skipping
    JAX's shutdown barrier, which would hold it until the others finish (they may be waiting for it in a
    collective): the others then fail in their next collective ("connection closed by peer"), or JAX's coordination
    service ends them within `HEARTBEAT_TIMEOUT_S`. A normal return goes through the barrier (process 0 may still
    be writing)."""
    try:
        return body()
    except BaseException as e:  # noqa: BLE001 - every failure ends this process now
        try:
            code = report(e)
        except BaseException:  # noqa: BLE001
            traceback.print_exc()
            code = 1
        end_now(code)
        raise  # pragma: no cover - end_now does not return


def report_unexpected(e: BaseException, prog: str) -> int:
    """The report of a failure that is not an expected one: a traceback (a bug), or one line for a failed collective
    or an interrupt; the exit code."""
    if isinstance(e, KeyboardInterrupt):
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    if type(e).__name__ == "JaxRuntimeError":
        print(f"{prog}: error: process {process_index()}: {describe(e)}; nothing written", file=sys.stderr)
        return 1
    if isinstance(e, SystemExit):
        return e.code if isinstance(e.code, int) else 1
    traceback.print_exception(e)
    return 1


def end_now(code: int) -> None:
    """Flush the output and end this process with `code`, without Python's exit handlers (JAX's shutdown barrier)."""
    for f in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            f.flush()
        except Exception:  # noqa: BLE001 - a closed stream: nothing to flush
            pass
    os._exit(code)
