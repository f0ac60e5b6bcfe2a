"""Configuration shared by every layer: the named choices, one checker, and keys and flags
derived from the config dataclasses.

Configs are frozen, documented dataclasses owned by the module they configure (Waymax style):
``sim.SimConfig``, ``world_model.ModelConfig``, ``adversary.guidance.GuidanceConfig``. This
module holds what they share, so that each setting has one source of truth:

- **Choices** are :class:`Choice` enums (:class:`Scenario`, :class:`Selector`,
  :class:`SelectionSource`, :class:`GuidancePreset`, :class:`Sampler`, ...). A field takes
  either the enum member or its string (``Selector.TTC`` or ``"ttc"``) and stores the string,
  so configs stay plain JSON. :meth:`Choice.parse` is the one checker; its error lists the
  valid values.
- **Values** are checked by type and range where they enter, by one set of checkers
  (:func:`check_bool`, :func:`check_int`, :func:`check_real`): a bool is a bool (not the
  string ``"False"``), a count an int (not ``2.5`` or ``True``), a number finite. A dataclass
  declares its ranges in field metadata (:func:`bounded`) and :func:`check_fields` checks
  every field by its annotation. Refusals are ``TypeError`` (wrong type) or ``ValueError``
  (wrong value) naming the key, the value and what is allowed.
- :func:`from_mapping` builds a dataclass from a dict; an unknown key names the valid ones.
- ``cli/flags.py`` reads a dataclass's ``Attributes:`` docstring section and turns its
  fields into ``argparse`` flags: a field added to ``SimConfig`` (with its docstring entry)
  is a ``counterscene stress`` flag and a ``CounterScene-v0`` config key without another
  line of code (docs/design.md, "Configuration").

This module imports nothing from the package: every layer may use it.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import numbers
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

T = TypeVar("T")


class Choice(str, enum.Enum):
    """A named choice. Members are their strings (``Selector.TTC == "ttc"``)."""

    #: What the choice is called in error messages ("selector", "guidance preset", ...).
    __label__: typing.ClassVar[str] = "choice"

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__

    @classmethod
    def values(cls) -> tuple[str, ...]:
        """The valid strings, in definition order."""
        return tuple(m.value for m in cls)

    @classmethod
    def parse(cls, value: Any, key: str | None = None) -> str:
        """``value`` as its plain string if it is one of the choices.

        Raises:
            ValueError: anything else; the message names the key (when given), the value and
                the valid values.
        """
        if isinstance(value, cls):
            return value.value
        if isinstance(value, str) and value in cls.values():
            return value
        where = f" for {key!r}" if key and key.replace("_", " ") != cls.__label__ else ""
        raise ValueError(f"unknown {cls.__label__} {value!r}{where}; valid: {list(cls.values())}")


class Scenario(Choice):
    """highway-env roads that scenes are recorded on (``scene.highway``)."""

    __label__ = "scenario"
    HIGHWAY = "highway"
    MERGE = "merge"
    INTERSECTION = "intersection"
    ROUNDABOUT = "roundabout"


class Yielding(Choice):
    """How recorded intersection traffic gives way (``scene.highway``, ``scene/gap_acceptance.py``)."""

    __label__ = "yielding"
    #: highway-env's rule: target speed 0, decided twice a second, 3 s ahead.
    HIGHWAY_ENV = "highway-env"
    #: A stop point before the crossing, chosen by gap acceptance 6 s ahead.
    GAP_ACCEPTANCE = "gap-acceptance"


#: Prefix of a ScenarioNet directory in a scenario spec (``scenarionet:DIR``).
SCENARIONET_PREFIX = "scenarionet:"
#: Prefix of a CommonRoad scenario directory or XML file in a scenario spec (``commonroad:DIR``).
COMMONROAD_PREFIX = "commonroad:"
#: s of log after its start that ``counterscene paper-tables`` needs of a real scene to seat
#: it: the real-logs table's first horizon (``report.paper_tables.COLUMNS["real"]``). A shorter
#: episode enters none of the table's columns, only its whole-episode rates, where it can
#: hold no event and dilutes them (docs/reproducing_the_paper.md, "Real logs: short scenes").
REAL_MIN_FUTURE = 3.0


class Selector(Choice):
    """Who becomes the adversary: the paper's causal conflict mining, or a baseline."""

    __label__ = "selector"
    CAUSAL = "causal"
    RANDOM = "random"
    DISTANCE = "distance"
    TTC = "ttc"


class SelectionSource(Choice):
    """The future the adversary is selected on: the log (once), or the model (every replan)."""

    __label__ = "selection source"
    LOG = "log"
    MODEL = "model"


class GuidancePreset(Choice):
    """Counterfactual guidance presets: the full method and the paper's ablations."""

    __label__ = "guidance preset"
    FULL = "full"
    NO_JERK = "no_jerk"
    NO_CONFLICT_AWARE = "no_conflict_aware"
    NO_PROGRESSIVE = "no_progressive"
    NO_ADAPTIVE = "no_adaptive"
    MINIMAL = "minimal"
    NONE = "none"


class GuidanceProgress(Choice):
    """What the guidance's progress p measures (the stage multiplier and the compression)."""

    __label__ = "guidance progress"
    #: Closed-loop step over the horizon (the paper's appendix and its public code).
    ROLLOUT = "rollout"
    #: Denoising progress, 1 - t / K (the paper's main text).
    DENOISING = "denoising"


class Sampler(Choice):
    """The world model's sampler: strided DDIM, or all the DDPM steps."""

    __label__ = "sampler"
    DDIM = "ddim"
    DDPM = "ddpm"


class PredictionTarget(Choice):
    """What the denoiser outputs: the clean actions, or the noise."""

    __label__ = "prediction"
    X0 = "x0"
    EPSILON = "epsilon"


class PlanFeatures(Choice):
    """What the denoiser's future tokens read of where the agents' plans go (docs/world_model.md,
    "Network"): nothing (the paper), the noisy actions rolled out, or the previous denoising
    step's clean prediction rolled out (self-conditioning)."""

    __label__ = "plan_features"
    NONE = "none"
    NOISY = "noisy"
    SELF = "self"


class WindowCentres(Choice):
    """Whom training windows are centred on: the scene's ego only, or every vehicle in turn."""

    __label__ = "centres"
    EGO = "ego"
    AGENTS = "agents"


class LaneAnchors(Choice):
    """Where a model window's lanes are centred: on the ego, or on every window agent."""

    __label__ = "lane_anchors"
    EGO = "ego"
    AGENTS = "agents"


def choice_field(choices: type[Choice], default: Choice | str | None) -> Any:
    """A dataclass field whose value is one of ``choices`` (or None when the default is)."""
    value = default.value if isinstance(default, Choice) else default
    return dataclasses.field(default=value, metadata={"choices": choices})


def describe_value(value: Any) -> str:
    return f"got {value!r} ({type(value).__name__})"


def check_bool(key: str, value: Any) -> bool:
    """``value`` if it is a bool (numpy's too); a string such as ``"False"`` is refused."""
    if not isinstance(value, bool | np_bool()):
        raise TypeError(f"{key} must be true or false (a bool), {describe_value(value)}")
    return bool(value)


def check_int(key: str, value: Any, ge: int | None = None, le: int | None = None) -> int:
    """``value`` as an int if it is an integer (not a bool, not ``2.0``) within [ge, le]."""
    if isinstance(value, bool | np_bool()) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{key} must be an int, {describe_value(value)}")
    _check_range(key, value, None, ge, le)
    return int(value)


#: The scenes' step [s]: every source is resampled onto it (``scene/core.py``), and the
#: closed loop and the env run at it.
DEFAULT_DT = 0.1

#: The largest seed of a closed-loop episode: its torch generator takes at most 64 bits
#: (``torch.Generator.manual_seed``); a larger int would fail inside ``reset``.
MAX_SEED = 2**64 - 1


#: The largest first seed of a run (``--seed``, a training seed): 32 bits, so that the seeds
#: derived from it (episode i: seed + i; a training step: seed * 100003 + step) stay in 64.
MAX_RUN_SEED = 2**32 - 1


def check_seed(key: str, value: Any) -> int:
    """``value`` as an int if it is a seed torch and numpy both take: in [0, MAX_SEED]."""
    return check_int(key, value, ge=0, le=MAX_SEED)


def check_real(
    key: str,
    value: Any,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
) -> float:
    """``value`` as a float if it is a finite real number (not a bool, not a string) in
    range."""
    if isinstance(value, bool | np_bool()) or not isinstance(value, numbers.Real):
        raise TypeError(f"{key} must be a number, {describe_value(value)}")
    if not math.isfinite(value):
        raise ValueError(f"{key} must be a finite number, got {value!r}")
    _check_range(key, value, gt, ge, le)
    return float(value)


def _check_range(key: str, value: Any, gt: Any, ge: Any, le: Any) -> None:
    for bound, ok, sign in ((gt, lambda b: value > b, ">"), (ge, lambda b: value >= b, ">=")):
        if bound is not None and not ok(bound):
            raise ValueError(f"{key} must be {sign} {bound}, got {value!r}")
    if le is not None and not value <= le:
        raise ValueError(f"{key} must be <= {le}, got {value!r}")


def np_bool() -> type:
    """numpy's bool type, without importing numpy at this module's import."""
    import numpy as np

    return np.bool_


def bounded(default: Any, **bounds: float) -> Any:
    """A dataclass field with a range for :func:`check_fields` (``gt``, ``ge``, ``le``)."""
    return dataclasses.field(default=default, metadata=bounds)


def check_fields(obj: Any) -> None:
    """Check every field of dataclass ``obj`` by its annotation (``bool``, ``int``, ``float``,
    a :class:`Choice`, each optionally ``| None``) and its :func:`bounded` range; each value
    is stored as its plain Python type (a numpy int as an int, a choice as its string), so
    configs stay plain JSON.

    Raises:
        TypeError: a value of the wrong type; ValueError: one out of range or not a choice.
    """
    hints = _hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        kind = bare_type(hints[f.name])
        if value is None and kind is not hints[f.name]:  # ``X | None``
            continue
        bounds = {k: v for k, v in f.metadata.items() if k in ("gt", "ge", "le")}
        if f.metadata.get("choices") is not None:
            object.__setattr__(obj, f.name, f.metadata["choices"].parse(value, f.name))
        elif kind is bool:
            object.__setattr__(obj, f.name, check_bool(f.name, value))
        elif kind is int:
            object.__setattr__(obj, f.name, check_int(f.name, value, **bounds))
        elif kind is float:
            object.__setattr__(obj, f.name, check_real(f.name, value, **bounds))


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def from_mapping(cls: type[T], values: Mapping, what: str) -> T:
    """``cls(**values)``; an unknown key raises a ValueError naming it and the valid keys.

    ``what`` names the settings in the message ("simulation", "guidance", ...).
    """
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"unknown {what} keys {unknown}; valid keys: {sorted(names)}")
    return cls(**values)


def defaults(cls: type) -> dict[str, Any]:
    """``{field: default}`` of a dataclass whose fields all have plain defaults."""
    return {f.name: f.default for f in dataclasses.fields(cls)}


def bare_type(hint: Any) -> Any:
    """A field's type without its ``| None`` (``int | None`` -> ``int``)."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if len(args) == 1 and type(None) in typing.get_args(hint) else hint
