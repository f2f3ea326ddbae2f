"""`jaxrt serve`: keep a warm worker that runs later `jaxrt` commands of this environment."""

from __future__ import annotations

import argparse
import json
import sys

EPILOG = """\
A `jaxrt` command pays a fixed start-up cost before any work: importing JAX, starting the device
runtime, loading stored programs and cached scenes (seconds; README "Start-up time").
`jaxrt serve` starts a worker process that pays it once: while it runs, `jaxrt render`,
`fit`, `sweep`, ... started from any shell with the same Python, jaxrt checkout and JAX-related
environment variables are run inside it, with their output streamed back, the exit code returned
and Ctrl-C forwarded. Images and fits are bit-identical to a run without the worker.

By default (JAXRT_WORKER=auto) a command typed at a terminal starts a worker when none runs (one
line says so; it exits after 600 idle seconds), and every command uses a running one; scripts,
pipes and CI never start one. A worker holds the memory its jobs used (jaxrt turns JAX's
preallocation of most of a GPU off) until it has been idle for --idle-timeout seconds (default 900
when started here), until `jaxrt serve --stop`, or until it retires after many jobs or when its
memory grows past half the RAM. One job at a time: a command started while the worker is busy runs
in its own process. `view`, `cache` and runs over several hosts (JAXRT_COORDINATOR) never use it.

JAXRT_WORKER=use only uses a running worker; JAXRT_WORKER=start starts one for any command;
JAXRT_WORKER=off never uses one. The worker listens on a Unix socket (mode 0600) in the cache folder.

Examples:
  jaxrt serve                  # start a worker in the background; returns when it is ready
  jaxrt render spheres         # runs in the worker
  jaxrt serve --status         # pid, jobs run, compilations since it started, memory
  jaxrt serve --stop
"""


def configure(parser: argparse.ArgumentParser) -> None:
    from jaxrt import serve

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = EPILOG
    what = parser.add_mutually_exclusive_group()
    what.add_argument("--foreground", action="store_true", help="run the worker in this process (Ctrl-C stops it)")
    what.add_argument("--stop", action="store_true", help="stop the worker of this environment")
    what.add_argument("--status", action="store_true", help="print the worker's state as JSON (exit 1: none runs)")
    parser.add_argument("--idle-timeout", type=float, default=serve.DEFAULT_IDLE_TIMEOUT, metavar="SECONDS",
                        help=f"exit after this long without a job (default {serve.DEFAULT_IDLE_TIMEOUT:g})")


def _warm_up() -> None:
    """What most jobs need first: JAX with the compilation cache on, the devices, the busiest commands."""
    import importlib

    from jaxrt import cli

    for name in ("render", "fit", "sweep"):
        importlib.import_module(cli.COMMANDS[name][0])
    import jax

    jax.devices()


def run(args: argparse.Namespace) -> int:
    from jaxrt import serve
    from jaxrt.errors import InputError

    if not args.idle_timeout > 0:
        raise InputError(f"--idle-timeout {args.idle_timeout:g}: must be a positive number of seconds")
    if args.status or args.stop:
        state = serve.request(b"Q" if args.stop else b"S")
        if state is None:
            print(f"jaxrt serve: no worker runs for this environment ({serve.socket_path()})", file=sys.stderr)
            return 1
        print(json.dumps(state, indent=1) if args.status else f"jaxrt serve: stopping the worker (pid {state['pid']})")
        return 0
    if args.foreground:
        from jaxrt import cli

        return serve.serve(cli.execute, args.idle_timeout, warm_up=_warm_up,
                           ready=lambda p: print(f"jaxrt serve: ready on {p}", flush=True))
    path = serve.socket_path()
    if serve.request(b"S", path) is not None:
        print(f"jaxrt serve: a worker already runs on {path}")
        return 0
    if serve.start(path, args.idle_timeout) is None:
        print(f"jaxrt serve: the worker did not start; see {path.with_suffix('.log')}", file=sys.stderr)
        return 1
    print(f"jaxrt serve: ready on {path} (exits after {args.idle_timeout:g} s idle; jaxrt serve --stop)")
    return 0
