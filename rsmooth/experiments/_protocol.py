"""What every experiment is: a `Config`, a `run`, a summary, registered once.

An experiment module defines

- ``Config``: a frozen dataclass whose fields are declared with :func:`option` (default, help
  text, command-line flag, allowed values or range) and a ``quick()`` classmethod (the reduced
  size of ``--quick``); its ``__post_init__`` calls :func:`check_options` and then checks what
  ties several fields together, raising ``ValueError`` that names the field;
- ``run(config, out, key, progress=True) -> metrics``: writes its figures and
  ``out/metrics.json``, returns the metrics;
- ``summary(metrics) -> dict``: the lines printed after a run (label -> value);
- ``EXPERIMENT``: an :class:`Experiment` that names its command, its summary and its help.

The command line (`rsmooth.cli`) builds each command's options from the ``Config`` fields:
adding an option is one field in one file.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, Callable, Optional, Sequence

_MISSING = dataclasses.MISSING


def option(
    default: Any,
    help: str,
    *,
    flag: Optional[str] = None,
    choices: Optional[tuple] = None,
    min: Optional[float] = None,
    max: Optional[float] = None,
    above: Optional[float] = None,
    below: Optional[float] = None,
    cli: bool = True,
) -> Any:
    """A `Config` field with its help text and the values it accepts.

    Args:
      default: the default value (a tuple for a repeatable option: immutable, shared safely).
      help: one or two sentences: what the field sets and its unit.
      flag: the command-line name without ``--`` (default: the field's name, ``_`` -> ``-``);
        for a bool, ``"on/off"`` names both switches (e.g. ``"keep-best/last"``; default
        ``"NAME/no-NAME"``).
      choices: the allowed values (of each element, for a tuple field).
      min, max: closed bounds of the allowed range (of each element, for a tuple field).
      above, below: open bounds (``above=0``: positive).
      cli: False keeps the field out of the command line (set in code only).

    Returns:
      A `dataclasses.field` carrying these as metadata.
    """
    metadata = {"help": " ".join(help.split()), "flag": flag, "choices": choices, "min": min, "max": max,
                "above": above, "below": below, "cli": cli}
    return dataclasses.field(default=default, metadata=metadata)


def flag(field: dataclasses.Field) -> str:
    """The command-line flag of a `Config` field, with its ``--`` (a bool's "on" switch)."""
    return "--" + (field.metadata.get("flag") or field.name.replace("_", "-")).split("/")[0]


def switches(field: dataclasses.Field) -> tuple[str, str]:
    """The two flags of a bool field, ``("--NAME", "--no-NAME")`` unless its ``flag`` names
    them (``"on/off"``)."""
    names = (field.metadata.get("flag") or field.name.replace("_", "-")).split("/")
    on = names[0]
    return "--" + on, "--" + (names[1] if len(names) > 1 else f"no-{on}")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_options(config) -> None:
    """Checks every field declared with `choices` or bounds (each element of a tuple).

    Raises:
      ValueError: naming the field, its flag, the value and what is allowed.
    """
    for field in dataclasses.fields(config):
        meta = field.metadata
        if not meta:
            continue
        value = getattr(config, field.name)
        values = value if isinstance(value, tuple) else (value,)
        where = f"{field.name} ({flag(field)})"
        for item in values:
            if meta.get("choices") is not None and item not in meta["choices"]:
                allowed = ", ".join(map(str, meta["choices"]))
                raise ValueError(f"{where} must be one of {allowed}, got {item!r}")
            low, high = meta.get("min"), meta.get("max")
            above, below = meta.get("above"), meta.get("below")
            if all(bound is None for bound in (low, high, above, below)) or item is None:
                continue
            if not _is_number(item) or not math.isfinite(item):
                raise ValueError(f"{where} must be a finite number, got {item!r}")
            if (low is not None and item < low or high is not None and item > high
                    or above is not None and not item > above or below is not None and not item < below):
                raise ValueError(f"{where} must be in {_interval(meta)}, got {item!r}")


def _interval(meta) -> str:
    """The allowed range of a field's metadata, e.g. ``(0, 1]``."""
    left = f"({meta['above']}" if meta.get("above") is not None else f"[{meta['min'] if meta.get('min') is not None else '-inf'}"
    right = f"{meta['below']})" if meta.get("below") is not None else f"{meta['max'] if meta.get('max') is not None else 'inf'}]"
    return f"{left}, {right}"


def field_type(config_class, field: dataclasses.Field):
    """The field's annotation, resolved (``from __future__ import annotations`` keeps strings)."""
    hints = typing.get_type_hints(config_class)
    return hints[field.name]


def element_type(annotation):
    """``(kind, element)``: ``("tuple", T)`` for ``tuple[T, ...]``, ``("fixed", (A, B, ...))``
    for a tuple of fixed length, ``("optional", T)`` for ``T | None``, else ``("plain",
    annotation)``.

    Example:
        >>> element_type(tuple[float, ...]), element_type(tuple[float, int]), element_type(int | None)
        (('tuple', <class 'float'>), ('fixed', (<class 'float'>, <class 'int'>)), ('optional', <class 'int'>))
    """
    origin = typing.get_origin(annotation)
    if origin is tuple:
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return "tuple", args[0]
        return "fixed", args
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1:
            return "optional", args[0]
    return "plain", annotation


@dataclasses.dataclass(frozen=True)
class Experiment:
    """One experiment as the command line and the report see it.

    Attributes:
      command: the words after ``rsmooth``, e.g. ``("control", "cube-lift")``.
      name: the output sub-folder, ``./rsmooth-out/NAME``.
      config: the experiment's `Config` class.
      run: ``run(config, out, key, progress=True) -> metrics``.
      summary: metrics -> the lines printed after a run (label -> value).
      help: what the experiment shows, in a sentence or two.
      metrics_doc: the keys of ``metrics.json``.
      x64: float64 (contact solves and DDP need it); rendering runs in float32, which halves its
        time on CPU and is what GPUs are fast at.
      expand: ``config -> None`` (one run into the output folder) or ``[(name, config), ...]``:
        one run per entry, into ``OUT/name`` (e.g. ``control solo-lift --foot all``).
      combine: for an expanded command, ``{name: metrics}`` -> the lines printed after its runs.
    """

    command: tuple[str, ...]
    name: str
    config: type
    run: Callable[..., dict]
    summary: Callable[[dict], dict]
    help: str
    metrics_doc: str
    x64: bool = True
    expand: Optional[Callable[[Any], Optional[Sequence[tuple[str, Any]]]]] = None
    combine: Optional[Callable[[dict], dict]] = None

    @property
    def title(self) -> str:
        """The command's words, e.g. ``"control cube-lift"``: names its runs in the output."""
        return " ".join(self.command)
