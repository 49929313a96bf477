"""The `rsmooth` command: one sub-command per registered experiment.

The commands and their options are made from :func:`rsmooth.experiments.registry`: each field
of an experiment's ``Config`` (declared with :func:`rsmooth.experiments._protocol.option`) is
an option whose default, ``None``, keeps the Config's value (or ``Config.quick()``'s); the
Config checks the values, and a ``ValueError`` it raises ends the command as a usage error
that names the flag (exit code 2). Adding an option is adding a field.

Every experiment also takes `--out DIR` (default `./rsmooth-out/NAME`), `--seed N` and
`--quick` (a reduced size that finishes in a couple of minutes on 2 CPU cores), shows a
progress bar, and writes `DIR/metrics.json` beside its figures. `DIR/rsmooth-files.json` lists
the files a run wrote: a run into the folder of an earlier one first removes those (and no
other file), and a non-empty folder that no run wrote into is refused. Errors of the operating
system (a folder that cannot be written) end the command with a one-line message and exit code
1; Ctrl-C ends it with exit code 130.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import gc
import inspect
import os
import re
import signal
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Iterable, Optional

import typer

from rsmooth import _files
from rsmooth.experiments import _protocol, registry

try:  # Typer parses help texts as Rich markup where Rich is installed: "[...]" stays as written
    from rich.markup import escape as _escape
except ImportError:  # pragma: no cover - Typer then prints help texts as they are

    def _escape(text: str) -> str:
        return text


DEFAULT_ROOT = Path("rsmooth-out")
# `rsmooth demo`: one experiment of each part a newcomer asks about (the smoothing estimators,
# perturbed optimizers, the perturbed renderer, randomized DDP), chosen for a run of about a
# minute once compiled; `rsmooth report --quick` runs them all (minutes).
DEMO = (("experiment", "estimators"), ("experiment", "perturbed-argmax"), ("render", "pose"), ("control", "cube-lift"))

GROUPS = {
    "experiment": "Experiments on the smoothing core and on contact.",
    "sim": "Simulation with hard frictional contact.",
    "render": "Differentiable perturbed rendering tasks.",
    "control": "Optimal control through contact: DDP, randomized DDP, and policy gradients (first, zeroth, alpha order).",
}

# The options every experiment takes, before its Config's.
COMMON = ("out", "seed", "quick")


def _fail(message: str) -> None:
    """Ends the command with a one-line error on stderr and exit code 1."""
    typer.echo(f"rsmooth: error: {message}", err=True)
    raise typer.Exit(1)


def _os_error_message(error: OSError) -> str:
    """``strerror: filename`` (e.g. ``Permission denied: out/metrics.json``), else the error's text."""
    if error.strerror and error.filename is not None:
        return f"{error.strerror}: {os.fsdecode(error.filename)}"
    return str(error) or type(error).__name__


def _prepare(name: str, out: Optional[Path], seed: int, x64: bool = True):
    """The output folder, made ready (:func:`rsmooth._files.prepare_output_folder`: the files of
    the previous run into it removed), and the key of `seed`."""
    import jax

    # Set before the experiment creates any array (and in a report, only ever from float32 to
    # float64: see _execute).
    jax.config.update("jax_enable_x64", x64)
    out = Path(out) if out is not None else DEFAULT_ROOT / name
    return _files.prepare_output_folder(out), jax.random.key(seed)


def _report(name: str, out: Path, start: float, summary: dict) -> None:
    typer.echo(f"{name}: done in {time.perf_counter() - start:.1f} s, artifacts in {out}/")
    for key, value in summary.items():
        typer.echo(f"  {key}: {value}")


def _execute(experiment: _protocol.Experiment, config, out: Optional[Path], seed: int, root: Optional[Path] = None):
    """Runs `experiment` with `config` into `out` (default ``./rsmooth-out/NAME``, or
    ``root/NAME``), recording the files it writes; returns the folder and the metrics."""
    # `rsmooth demo` and `rsmooth report` run several experiments in one process (run_report
    # runs the float32 ones first): once float64 is on they keep it, rather than switching the
    # precision back under float64 arrays that already exist.
    import jax

    x64 = experiment.x64 or (root is not None and bool(jax.config.jax_enable_x64))
    out, key = _prepare(experiment.name, out if root is None else root / experiment.name, seed, x64)
    with _files.recording_outputs(out):
        metrics = experiment.run(config, out, key)
    return out, metrics


def _run(
    experiment: _protocol.Experiment, config, out: Optional[Path], seed: int, root: Optional[Path] = None,
    title: Optional[str] = None,
) -> dict:
    """Runs `experiment` with `config` into `out` (default ``./rsmooth-out/NAME``, or
    ``root/NAME``) and prints its summary; returns its metrics."""
    start = time.perf_counter()
    try:
        out, metrics = _execute(experiment, config, out, seed, root)
    except _files.OutputFolderError as error:
        _fail(str(error))
    except OSError as error:  # a folder or file that cannot be written: permission denied, disk full...
        _fail(_os_error_message(error))
    _report(title or experiment.title, out, start, experiment.summary(metrics))
    return metrics


def _error_text(error: BaseException) -> str:
    """An error as the report shows it: its type and message, then the last frames."""
    frames = traceback.format_exception(error)
    return "".join(frames[-1:] + ["\n"] + frames[-4:-1]).rstrip()


def run_report(experiments: Iterable[_protocol.Experiment], out: Path, seed: int, quick: bool) -> Path:
    """Runs `experiments` (their quick or default Config) into ``out/NAME`` each, then writes
    ``out/index.html`` (:mod:`rsmooth.report`). An experiment that raises is shown with its
    error, and the others still run; returns the page's path."""
    from rsmooth import _xla, report

    out = _files.prepare_output_folder(out)
    experiments = tuple(experiments)
    entries = {}
    # float32 experiments (rendering) first, in float32; then the float64 ones (see _execute)
    for experiment in sorted(experiments, key=lambda e: e.x64):
        config = experiment.config.quick() if quick else experiment.config()
        folder = out / experiment.name
        command = f"rsmooth {experiment.title}{' --quick' if quick else ''} --seed {seed} --out {folder}"
        start = time.perf_counter()
        metrics, error = None, None
        try:
            folder, metrics = _execute(experiment, config, None, seed, root=out)
        except Exception as caught:  # shown on the page; the other experiments still run
            error = _error_text(caught)
            typer.echo(f"{experiment.title}: failed: {type(caught).__name__}: {caught}", err=True)
        else:
            _report(experiment.title, folder, start, experiment.summary(metrics))
        files = tuple(_files.listed_files(folder)) if folder.is_dir() else ()
        entries[experiment.name] = report.Entry(
            title=experiment.title, folder=experiment.name, command=command, help=" ".join(experiment.help.split()),
            settings=dataclasses.asdict(config), metrics=metrics, error=error,
            wall_time_s=time.perf_counter() - start, files=files,
        )
        _xla.release_compiled_programs()  # many programs in one process (see there)
    with _files.recording_outputs(out):
        page = report.write_page(out, [entries[e.name] for e in experiments], report.machine(),
                                 profile="quick" if quick else "default")
    return page


# -- options from Config fields ---------------------------------------------------------------


def cli_fields(config_class) -> list[dataclasses.Field]:
    """The fields of `config_class` that are command-line options (declared with
    :func:`~rsmooth.experiments._protocol.option`, ``cli`` not False)."""
    return [f for f in dataclasses.fields(config_class) if f.metadata.get("help") is not None and f.metadata.get("cli", True)]


def _format(value: Any, field: dataclasses.Field) -> str:
    """A default as the help shows it: a bool as its flag, a tuple as its values."""
    if isinstance(value, bool):
        on, off = _protocol.switches(field)
        return on if value else off
    if isinstance(value, tuple):
        return ", ".join(_format(item, field) for item in value) if value else "none"
    if isinstance(value, float):
        return f"{value:g}"
    return "none" if value is None else str(value)


def _option_help(config_class, field: dataclasses.Field) -> str:
    """The field's help text, its allowed values, and its default (and quick) value."""
    meta = field.metadata
    parts = [meta["help"]]
    kind, _ = _protocol.element_type(_protocol.field_type(config_class, field))
    if kind == "tuple":
        parts.append("Repeatable.")
    if meta.get("choices") is not None:
        parts.append("One of: " + ", ".join(map(str, meta["choices"])) + ".")
    default = _format(getattr(config_class(), field.name), field)
    quick = _format(getattr(config_class.quick(), field.name), field)
    parts.append(f"(default {default}" + (f", quick {quick})" if quick != default else ")"))
    return _escape(" ".join(parts))


def _option_type(config_class, field: dataclasses.Field):
    """The type Typer parses the option's value as (always optional: None keeps the Config's)."""
    annotation = _protocol.field_type(config_class, field)
    kind, element = _protocol.element_type(annotation)
    scalars = (int, float, str, bool)
    if kind == "tuple" and element in scalars and element is not bool:
        return Optional[list[element]]
    if kind == "fixed" and all(item in scalars for item in element):
        return Optional[tuple[element]]
    if kind in ("plain", "optional") and element in scalars:
        return Optional[element]
    raise TypeError(f"{config_class.__module__}.{config_class.__qualname__}.{field.name}: no command-line option for "
                    f"{annotation!r}; declare it with cli=False")


def _parameter(config_class, field: dataclasses.Field) -> inspect.Parameter:
    """The command function's parameter of a Config field."""
    annotation = _option_type(config_class, field)
    declaration = "/".join(_protocol.switches(field)) if annotation == Optional[bool] else _protocol.flag(field)
    option = typer.Option(None, declaration, help=_option_help(config_class, field), show_default=False)
    return inspect.Parameter(field.name, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=annotation)


def _named_flags(config_class, message: str) -> list[str]:
    """The flags of the command-line fields that `message` names, in the order it names them."""
    found = []
    for field in cli_fields(config_class):
        match = re.search(rf"(?<![\w-]){re.escape(field.name)}(?![\w-])", message)
        if match:
            found.append((match.start(), _protocol.flag(field)))
    return [name for _, name in sorted(found)]


def make_config(experiment: _protocol.Experiment, quick: bool, values: dict[str, Any]):
    """The experiment's Config (or quick one) with the options given (those not None, or not an
    empty repeated option).

    Raises:
      typer.BadParameter: the Config rejects the values (a usage error: exit code 2), naming
        the flags of the fields its message names.
    """
    config_class = experiment.config
    choices = {field.name for field in cli_fields(config_class) if field.metadata.get("choices") is not None}
    changes = {}
    for name, value in values.items():
        if isinstance(value, list):  # a repeated option; a selection (of choices) once each, in order
            value = tuple(dict.fromkeys(value)) if name in choices else tuple(value)
        if value is not None and value != ():
            changes[name] = value
    try:
        config = config_class.quick() if quick else config_class()
        return dataclasses.replace(config, **changes) if changes else config
    except ValueError as error:
        flags = _named_flags(config_class, str(error))
        raise typer.BadParameter(str(error), param_hint=flags or None) from None


def _doc(*paragraphs: str) -> str:
    # The METRICS_DOC strings are wrapped for the source; Typer keeps single newlines, which
    # then wrap again at the terminal's width into ragged lines: one line per paragraph.
    return _escape("\n\n".join(" ".join(part.split()) for doc in paragraphs for part in doc.split("\n\n")))


def _command(experiment: _protocol.Experiment):
    """The command function of `experiment`: its signature (``__signature__``, which Typer
    reads) holds ``--out``, ``--seed``, ``--quick`` and one option per command-line field."""
    fields = cli_fields(experiment.config)
    taken = [field.name for field in fields if field.name in COMMON]
    if taken:
        raise ValueError(f"{experiment.title}: Config fields {taken} clash with --out, --seed, --quick")
    keyword = inspect.Parameter.KEYWORD_ONLY
    common = [
        inspect.Parameter("out", keyword, annotation=Optional[Path], default=typer.Option(
            None, "--out", help=f"Output folder (default ./{DEFAULT_ROOT}/{experiment.name}).", show_default=False)),
        inspect.Parameter("seed", keyword, annotation=int, default=typer.Option(0, "--seed", help="Seed of the jax.random key.")),
        inspect.Parameter("quick", keyword, annotation=bool, default=typer.Option(
            False, "--quick", help="Reduced size: about two minutes on 2 CPU cores.")),
    ]

    def command(out: Optional[Path], seed: int, quick: bool, **values):
        config = make_config(experiment, quick, values)
        runs = experiment.expand(config) if experiment.expand is not None else None
        if runs is None:
            _run(experiment, config, out, seed)
            return
        root = Path(out) if out is not None else DEFAULT_ROOT / experiment.name
        results = {name: _run(experiment, each, root / name, seed, title=f"{experiment.title} {name}") for name, each in runs}
        if experiment.combine is not None:
            for key, value in experiment.combine(results).items():
                typer.echo(f"{key}: {value}")

    command.__name__ = "_".join(experiment.command).replace("-", "_")
    command.__signature__ = inspect.Signature(common + [_parameter(experiment.config, field) for field in fields])
    command.__annotations__ = {}  # Typer takes the types from the signature
    return command


def build_app(experiments: Iterable[_protocol.Experiment]) -> typer.Typer:
    """The `rsmooth` application: a group per first word of the commands (help from
    :data:`GROUPS`), a command per experiment, `report` and `demo` (:data:`DEMO` at their quick
    sizes)."""
    experiments = list(experiments)
    app = typer.Typer(
        help="rsmooth: randomized smoothing for optimizing non-smooth physical processes (JAX).",
        no_args_is_help=True,
        add_completion=False,
    )
    groups: dict[str, typer.Typer] = {}
    for experiment in experiments:
        *path, name = experiment.command
        parent = app
        for depth in range(len(path)):
            words = tuple(path[: depth + 1])
            if words not in groups:
                groups[words] = typer.Typer(help=GROUPS.get(words[-1], ""), no_args_is_help=True)
                parent.add_typer(groups[words], name=words[-1])
            parent = groups[words]
        parent.command(name, help=_doc(experiment.help, experiment.metrics_doc))(_command(experiment))

    names = [e.name for e in experiments]

    def report_pages(out: Path, seed: int, quick: bool, commands: Optional[tuple] = None) -> None:
        chosen = experiments if commands is None else [e for c in commands for e in experiments if e.command == c]
        try:
            page = run_report(chosen, out, seed, quick)
        except _files.OutputFolderError as error:
            _fail(str(error))
        except OSError as error:
            _fail(_os_error_message(error))
        typer.echo(f"report: {page}")

    @app.command(help=(
        "Runs every experiment into OUT/NAME and writes OUT/index.html: a static page that works "
        "offline, with each experiment's figures, animations, metrics, settings and the command that "
        "reproduces it (a failed experiment shows its error). --quick: the reduced sizes, about "
        "10 minutes on 2 CPU cores; otherwise the experiments' default (paper) sizes: hours."))
    def report(
        out: Path = typer.Option(..., "--out", help="Root folder: index.html and one sub-folder per experiment."),
        seed: int = typer.Option(0, "--seed", help="Seed of the jax.random key of every experiment."),
        quick: bool = typer.Option(False, "--quick", help="The experiments' reduced sizes."),
        only: list[str] = typer.Option([], "--only", help=(
            "Run only this experiment (repeatable), by the name of its folder: " + ", ".join(names) + ".")),
        skip: list[str] = typer.Option([], "--skip", help="Leave this experiment out (repeatable; names as --only)."),
    ):
        for option, given in (("--only", only), ("--skip", skip)):
            unknown = [name for name in given if name not in names]
            if unknown:
                _fail(f"{option}: unknown experiment {', '.join(map(repr, unknown))}; one of: {', '.join(names)}")
        chosen = [e.command for e in experiments if (not only or e.name in only) and e.name not in skip]
        if not chosen:
            _fail("--only and --skip leave no experiment to run")
        report_pages(out, seed, quick, tuple(chosen))

    @app.command(help=(
        "A tour of four experiments at their quick sizes into ./rsmooth-out/ (or --out), with their "
        "report page: gradient estimators on discontinuous functions, the perturbed argmax, pose "
        "estimation with the perturbed renderer, DDP against randomized DDP on a cube. About a minute "
        "on 2 CPU cores once JAX's compilation cache holds their programs (the first run compiles them); "
        "`rsmooth report --quick` runs every experiment."))
    def demo(
        out: Path = typer.Option(DEFAULT_ROOT, "--out", help="Root folder: index.html and one sub-folder per experiment."),
        seed: int = typer.Option(0, "--seed", help="Seed of the jax.random key."),
    ):
        report_pages(out, seed, True, DEMO)

    return app


app = build_app(registry().values())


class _Interrupted(BaseException):
    """Raised in the main thread by the command's SIGINT handler. Not a `KeyboardInterrupt`,
    which Click turns into an ordinary exit, through the interpreter's shutdown."""


def _frame_after_dropping_callbacks(frame):
    """The frame that a garbage-collection callback or a ``__del__`` method interrupted, where
    `frame` runs inside one (Python prints an exception raised there and drops it: JAX's gc
    callback runs during compilation, and a Ctrl-C raised in it was lost); None otherwise."""
    codes = {getattr(callback, "__code__", None) for callback in gc.callbacks}
    outside = None
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            outside = frame.f_back
        frame = frame.f_back
    return outside


def _trace_no_frame(frame, event, arg):
    return None


class _InterruptHandler:
    """The command's SIGINT handler: raises :class:`_Interrupted` in the main thread.

    Inside a callback that would drop it, it is raised instead when the interrupted frame runs
    its next line (a trace function set on that frame). It is also raised again every half
    second (by sending SIGINT to the process) until :func:`main` has caught it, in case it was
    lost all the same (e.g. turned into an error of a host callback, and that one handled)."""

    def __init__(self):
        self.received = threading.Event()
        self.caught = threading.Event()

    def __call__(self, signum, frame):
        if not self.received.is_set():
            self.received.set()
            threading.Thread(target=self._repeat, name="rsmooth-interrupt", daemon=True).start()
        outside = _frame_after_dropping_callbacks(frame)
        if outside is None:
            raise _Interrupted()
        outside.f_trace = self._raise_on_next_line
        if sys.gettrace() is None:  # frames' own trace functions run only while one is set
            sys.settrace(_trace_no_frame)

    @staticmethod
    def _raise_on_next_line(frame, event, arg):
        frame.f_trace = None
        if sys.gettrace() is _trace_no_frame:
            sys.settrace(None)
        raise _Interrupted()

    def _repeat(self):
        while not self.caught.wait(0.5):
            os.kill(os.getpid(), signal.SIGINT)

    def exit(self) -> None:
        """Prints that the run was interrupted and ends the process with code 130 (128 + SIGINT).

        By `os._exit`, without the interpreter's shutdown: an interrupted XLA compilation goes
        on in a worker thread, and the shutdown destroyed the JAX backend under it (a
        segmentation fault). Nothing is lost by skipping it: files are written atomically
        (rsmooth._files), and the `finally` blocks of the interrupted code have already run.
        """
        self.caught.set()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        try:
            sys.stderr.write("\nrsmooth: interrupted\n")
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        os._exit(130)


def main():  # the console-script entry point
    # A crash inside XLA (a segmentation fault) prints the Python stack where it happened
    # instead of ending the process without a word.
    faulthandler.enable()
    handler = _InterruptHandler()
    # A shell starts background jobs with SIGINT ignored: keep it so.
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, handler)

    try:
        from rsmooth import _xla

        # before JAX starts its backend (see rsmooth._xla)
        _xla.apply_cpu_defaults(render=sys.argv[1:2] == ["render"])
        _xla.enable_compilation_cache()
        app()
    except BaseException:
        # Whatever ended the run after a Ctrl-C (the interrupt itself, or an error it caused,
        # e.g. in a host callback) ends it as an interrupt.
        if handler.received.is_set():
            handler.exit()
        raise


if __name__ == "__main__":
    main()
