"""A warm start for the workflow's many short jobs: a server that imported the package once forks one child per job.

Each ``crashfuse`` job of the workflow is a new Python process, and a quarter of the default run's job time was
spent importing numpy, scipy, scikit-learn, pandas and matplotlib again (docs/workflow.md, "Cost").
``crashfuse forkserver ADDRESS`` imports them once and listens on a Unix socket. A ``crashfuse`` command that
finds ``CRASHFUSE_FORKSERVER=ADDRESS`` in its environment (:func:`forward`) hands its arguments, working directory,
environment and standard streams to the server, which forks a child that runs the command as the process itself
would have, and the command exits with the child's exit code (:func:`wanted` says when).

To Snakemake the job is still a process of its own: its output goes to its log, its exit code is the command's,
and killing it ends the child (the child leaves as soon as the command's connection closes). Where no server
answers at the address (a cluster node, a server stopped) the command runs in its own process, as without one.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys
import threading

__all__ = ["ADDRESS", "PRELOAD", "THREAD_VARIABLES", "wanted", "forward", "serve"]

ADDRESS = "CRASHFUSE_FORKSERVER"  # environment variable: the server's Unix socket
# What the workflow's repeated jobs (train, rollout, score, figure, auto) import.
PRELOAD = ("crashfuse.cli", "crashfuse.method.model", "crashfuse.method.rollout", "crashfuse.method.selection",
           "crashfuse.evaluation.fold", "crashfuse.io.prediction", "crashfuse.reporting.plots")
# The thread counts Snakemake sets for each job (its `threads`); a numerical library reads them once, at import.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "GOTO_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
_LENGTH = struct.Struct("!Q")  # request length, sent with the standard streams
_EXIT = struct.Struct("!i")  # the child's exit code


def wanted(argv: list[str]) -> bool:
    """Whether ``crashfuse argv`` should be handed to a server: one is named, the command is not the server
    itself, and it does not run in a SLURM job (whose work belongs in its allocation, not in a server's child)."""
    return bool(os.environ.get(ADDRESS)) and argv[:1] != ["forkserver"] and "SLURM_JOB_ID" not in os.environ


def forward(address: str, argv: list[str]) -> int | None:
    """Run ``crashfuse argv`` in a child of the server at ``address``; its exit code, or None if none answers.

    Parameters
    ----------
    address : str
        Path of the server's Unix socket.
    argv : list of str
        The command's arguments (without the program name).

    Returns
    -------
    int or None
        The command's exit code (1 if the child ended without one); None when no server accepted the
        command, which then has not run.
    """
    request = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ)}).encode()
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        try:
            conn.connect(address)
            socket.send_fds(conn, [_LENGTH.pack(len(request))], [0, 1, 2])
        except OSError:
            return None
        conn.sendall(request)
        reply = _receive_exactly(conn, _EXIT.size)
    if reply is None:
        print("crashfuse: the job's forked process ended without an exit code (killed?)", file=sys.stderr)
        return 1
    return _EXIT.unpack(reply)[0]


def serve(address: str, *, while_stdin_open: bool = False) -> None:
    """Import :data:`PRELOAD`, listen at ``address`` and fork a child per command until stopped.

    Parameters
    ----------
    address : str
        Path of the Unix socket to create; removed again when the server stops (SIGTERM, SIGINT).
    while_stdin_open : bool
        Also stop when standard input closes: a server started on a pipe ends with the process that
        started it, however that one ends (even SIGKILL).
    """
    import importlib

    for module in PRELOAD:
        importlib.import_module(module)
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children are reaped by the kernel: nobody waits for them
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    if while_stdin_open:
        threading.Thread(target=_terminate_at_end_of_stdin, daemon=True).start()
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listener:
        listener.bind(address)
        try:
            listener.listen(64)
            while True:
                conn, _ = listener.accept()
                sys.stdout.flush(), sys.stderr.flush()
                if os.fork() == 0:
                    listener.close()
                    _run_child(conn)  # never returns
                conn.close()
        except KeyboardInterrupt:
            pass
        finally:
            os.unlink(address)


def _run_child(conn: socket.socket) -> None:
    """In the forked child: become the command's process, run it, send its exit code, exit."""
    code = 1
    try:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)  # the command's own subprocesses are waited for
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        request = _receive_request(conn)
        threading.Thread(target=_exit_when_closed, args=(conn,), daemon=True).start()
        from crashfuse import cli

        code = cli.main(request["argv"])
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else 1
    except BaseException:  # noqa: BLE001 - reported as the interpreter would, then exit 1
        import traceback

        traceback.print_exc()
    finally:
        sys.stdout.flush(), sys.stderr.flush()
        try:
            conn.sendall(_EXIT.pack(code))
        finally:
            os._exit(code)


def _receive_request(conn: socket.socket) -> dict:
    """Take over the command's standard streams, working directory and environment; its request."""
    message, fds, _, _ = socket.recv_fds(conn, _LENGTH.size, 3)
    if len(message) != _LENGTH.size or len(fds) != 3:
        raise ConnectionError("crashfuse forkserver: a malformed request")
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    request = json.loads(_receive_exactly(conn, _LENGTH.unpack(message)[0]))
    os.chdir(request["cwd"])
    _match_threads(request["env"])
    os.environ.clear()
    os.environ.update(request["env"])
    sys.argv = ["crashfuse", *request["argv"]]
    return request


def _match_threads(env: dict) -> None:
    """Give the BLAS the thread count the command's environment asks for, as a fresh process would read it."""
    threads = env.get("OPENBLAS_NUM_THREADS") or env.get("OMP_NUM_THREADS")
    if threads != (os.environ.get("OPENBLAS_NUM_THREADS") or os.environ.get("OMP_NUM_THREADS")):
        from threadpoolctl import threadpool_limits

        threadpool_limits(int(threads) if threads and threads.isdigit() else os.cpu_count())


def _terminate_at_end_of_stdin() -> None:
    # os.read, not sys.stdin: a child forked meanwhile must not inherit a stdin buffer's lock held here.
    while os.read(0, 4096):
        pass
    os.kill(os.getpid(), signal.SIGTERM)


def _exit_when_closed(conn: socket.socket) -> None:
    """The command sends nothing after its request: end of stream means it was killed, so is the child."""
    try:
        conn.recv(1)
    finally:
        os._exit(128 + signal.SIGTERM)


def _receive_exactly(conn: socket.socket, size: int) -> bytes | None:
    """``size`` bytes from ``conn``, or None if it closes first."""
    data = b""
    while len(data) < size:
        chunk = conn.recv(size - len(data))
        if not chunk:
            return None
        data += chunk
    return data
