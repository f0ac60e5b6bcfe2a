"""Read a ScenarioNet pickle without letting it run code.

One job: unpickle a file that may be hostile. The files are Python pickles, and unpickling an
untrusted pickle can run arbitrary code. They are never read with the standard loader:
:class:`SafeUnpickler` resolves only the globals in :data:`ALLOWED_GLOBALS`, an exact
``(module, name)`` allowlist:

- numpy's data-only reconstruction helpers (``_reconstruct``, ``ndarray``, ``dtype``;
  ``scalar`` for numpy scalars and ``_frombuffer`` for protocol-5 arrays), each under both its
  numpy-1 (``numpy.core``) and numpy-2 (``numpy._core``) spelling;
- ``collections.defaultdict`` with the two builtin factories ScenarioNet's converters use,
  ``builtins.int`` and ``builtins.list``. The defaultdict is handed out behind a checker that
  refuses any other factory, so a file cannot make a later missing-key lookup call numpy's
  helpers (or anything else) on our behalf.

Every other global (``os.system``, ``builtins.eval``, ``subprocess.Popen``, any class) raises
:class:`UnsafePickleError` *before* anything is called, so nothing in a hostile file runs.
Persistent ids are refused too, and the Python-level helpers are handed out sealed so that a
BUILD opcode cannot rewrite their attributes for the whole process. The nuScenes-mini and
Waymo files that ScenarioNet writes (protocol 4) name exactly
``numpy.core.multiarray._reconstruct``, ``numpy.ndarray`` and ``numpy.dtype`` (checked with
``pickletools``); their dicts, lists, sets and tuples are pickle opcodes. Protocols 3 to 5
load; protocol 2 would need ``_codecs.encode`` for bytes and is refused. Unpickling can still
allocate memory (a file may describe a huge array); it cannot execute code.
"""

from __future__ import annotations

import pickle
from collections import defaultdict
from typing import Any, BinaryIO

import numpy as np

from counterscene_env.scene.core import SceneError

try:  # numpy >= 2 spelling first
    from numpy._core.multiarray import _reconstruct, scalar
    from numpy._core.numeric import _frombuffer
except ImportError:  # pragma: no cover - older numpy
    from numpy.core.multiarray import _reconstruct, scalar
    from numpy.core.numeric import _frombuffer

__all__ = ["ALLOWED_GLOBALS", "SafeUnpickler", "UnsafePickleError", "safe_load"]


class UnsafePickleError(SceneError):
    """A pickle named a global outside :data:`ALLOWED_GLOBALS` (or a persistent id)."""


class _Sealed:
    """A callable stand-in for a Python-level helper that a pickle's BUILD opcode cannot alter.

    Built-in functions and types reject attribute writes by themselves; a plain Python function
    does not (BUILD could rewrite numpy's own ``_frombuffer.__defaults__`` for the whole
    process), so such helpers are handed out behind this wrapper instead.
    """

    __slots__ = ("_fn",)

    def __init__(self, fn: Any) -> None:
        object.__setattr__(self, "_fn", fn)

    def __call__(self, *args: Any) -> Any:
        return self._fn(*args)

    def __setattr__(self, name: str, value: Any) -> None:
        raise UnsafePickleError(f"refused attribute write {name!r} on an allowed global")


#: The default factories a pickled ``defaultdict`` may carry (what ScenarioNet's converters use).
DEFAULTDICT_FACTORIES = (int, list)


def _defaultdict(factory: Any = None, *args: Any) -> defaultdict:
    """``collections.defaultdict`` as a pickle rebuilds it, for the allowed factories only."""
    if factory is not None and not any(factory is f for f in DEFAULTDICT_FACTORIES):
        raise UnsafePickleError(
            f"refused defaultdict factory {factory!r}: only int and list are allowed"
        )
    if args:
        raise UnsafePickleError("refused defaultdict with initial data in its constructor call")
    return defaultdict(factory)


#: The only globals a ScenarioNet pickle may name: ``(module, name)`` -> object. All of them
#: build numpy arrays, dtypes, scalars or plain containers from plain data and cannot run code.
ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy.core.multiarray", "scalar"): scalar,
    ("numpy._core.multiarray", "scalar"): scalar,
    ("numpy.core.numeric", "_frombuffer"): _Sealed(_frombuffer),
    ("numpy._core.numeric", "_frombuffer"): _Sealed(_frombuffer),
    ("collections", "defaultdict"): _Sealed(_defaultdict),
    ("builtins", "int"): int,
    ("builtins", "list"): list,
}


class SafeUnpickler(pickle.Unpickler):
    """An unpickler that resolves only :data:`ALLOWED_GLOBALS` and no persistent ids."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise UnsafePickleError(
                f"refused global {module}.{name}: a ScenarioNet pickle may only name numpy's "
                f"array reconstruction helpers and defaultdict(int | list) (see ALLOWED_GLOBALS)"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(f"refused persistent id {pid!r}: not used by ScenarioNet pickles")


def safe_load(f: BinaryIO) -> Any:
    """Unpickle one object from an open binary file with :class:`SafeUnpickler`."""
    return SafeUnpickler(f).load()
