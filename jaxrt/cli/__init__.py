"""The `jaxrt` command line.

Each subcommand lives in its own module that defines `configure(parser)` and `run(args) -> int`;
this file only wires them together, so modules are imported only when their command runs.
Bad input raises `InputError` (or `ValueError`/`FileNotFoundError` from validation) and is printed
as one line with exit code 2; set JAXRT_DEBUG=1 for the full traceback. argparse's own errors (an
unknown option, a value that is not a number) are one line with exit code 2 as well. With
JAXRT_COORDINATOR (several hosts) the command first joins the other processes; processes other than
0 run the same command but print nothing on stdout and write no files.

`main` first offers the command to a resident worker (`jaxrt serve`, `jaxrt.serve.forward`): where
one runs for this environment and JAXRT_WORKER allows, the command runs there and this process
imports no JAX; otherwise `execute` runs it here. Parsing the arguments imports only the selected
command's module.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from jaxrt import _config
from jaxrt.errors import InputError

__all__ = ["COMMANDS", "build_parser", "execute", "main"]

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "render": ("jaxrt.cli.render", "render a scene file to EXR/PNG"),
    "sweep": ("jaxrt.cli.sweep", "render a parameter sweep of one BRDF model as a labelled image strip"),
    "view": ("jaxrt.cli.view", "open an interactive window with sliders for materials, light and camera"),
    "fit": ("jaxrt.cli.fit", "recover a BRDF's parameters from target renders (--demo for a self-contained run)"),
    "fit-matrix": ("jaxrt.cli.fit_matrix", "fit every model to every other model's renders; table and heat map"),
    "fit-brdf": ("jaxrt.cli.fit_brdf", "fit an analytic model to a measured material in BRDF space"),
    "study": ("jaxrt.cli.study", "fit every analytic model to every measured material (Ngan et al. 2005)"),
    "cache": ("jaxrt.cli.cache", "show or clear the on-disk caches (compiled programs, meshes, BVHs)"),
    "brdf-report": ("jaxrt.cli.brdf_report", "print each BRDF model's albedo table and write a lobe plot PNG"),
    "serve": ("jaxrt.cli.serve", "keep a warm worker process that runs later jaxrt commands (see --help)"),
}


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block), exit code 2, as every other jaxrt error."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The full parser; only the `selected` command's module is imported and configured."""
    parser = OneLineParser(
        prog="jaxrt", description="jaxrt: a JAX array ray tracer for analysing and fitting BRDFs."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=OneLineParser)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if name == selected:
            mod = importlib.import_module(module)
            mod.configure(p)
            p.set_defaults(_run=mod.run)
    return parser


def _command(argv: list[str]) -> str | None:
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    """`jaxrt ARGV`: in a resident worker where one runs for this environment and JAXRT_WORKER allows
    (`jaxrt.serve`; this process then imports no JAX), else here (`execute`). The exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if "jax" not in sys.modules:  # JAX reads its variables when it is imported: one CPU device per core
        _config.command_defaults()
    from jaxrt import serve

    code = serve.forward(argv, _command(argv))
    return execute(argv) if code is None else code


def execute(argv: list[str]) -> int:
    """Run `jaxrt ARGV` in this process; the exit code (argparse's errors and --help raise SystemExit)."""
    argv = list(argv)
    selected = _command(argv)
    parser = build_parser(selected if selected in COMMANDS else None)
    args = parser.parse_args(argv)
    debug = False
    try:
        cfg = _config.config()
        debug = cfg.debug
        if cfg.coordinator is not None:  # several hosts: join them before anything asks JAX for devices
            import contextlib
            import os

            from jaxrt import _devices, fsutil

            _devices.initialize()
            if not fsutil.writes():  # process 0 reports (and writes) for all; errors still reach stderr
                with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
                    return int(args._run(args) or 0)
        return int(args._run(args) or 0)
    except (InputError, ValueError, FileNotFoundError) as e:
        if debug:
            raise
        print(f"jaxrt {args.command}: error: {one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxrt: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
