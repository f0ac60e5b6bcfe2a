"""Gymnasium's vector-env conventions, shared by the vector envs (``envs/vector.py``,
``envs/sharded.py``): one seed per env, reset masks, per-env options and the vector info
format (``infos[key]`` an array over envs, ``infos["_" + key]`` the mask of those that
reported it)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode


def _info_array(value: Any, n: int) -> np.ndarray:
    """An empty info array for ``n`` envs of ``value``'s kind (as Gymnasium makes them)."""
    if type(value) in (int, float, bool) or isinstance(value, np.number):
        return np.zeros(n, dtype=type(value))
    if isinstance(value, np.ndarray):
        return np.zeros((n, *value.shape), dtype=value.dtype)
    return np.full(n, None, dtype=object)


def _widened(array: np.ndarray, value: Any, mask: np.ndarray | None) -> np.ndarray:
    """``array``, widened if it cannot hold ``value``: int or bool to float for a float,
    anything to object for a value of another kind (envs not yet reported stay None)."""
    if array.dtype == object:
        return array
    if isinstance(value, (bool, np.bool_)):
        fits = array.dtype == np.bool_
    elif isinstance(value, (int, np.integer)):
        fits = array.dtype.kind in "iuf"
    elif isinstance(value, (float, np.floating)):
        if array.dtype.kind in "iub" and array.ndim == 1:
            return array.astype(np.float64)
        fits = array.dtype.kind == "f"
    else:
        fits = isinstance(value, np.ndarray) and value.shape == array.shape[1:]
    if fits:
        return array
    widened = np.full(len(array), None, dtype=object)
    reported = np.zeros(len(array), np.bool_) if mask is None else mask
    for i in np.flatnonzero(reported):
        widened[i] = array[i].item() if array.ndim == 1 else array[i]
    return widened


def expand_seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """One seed per env: None for all, ``s`` gives env ``i`` the seed ``s + i``, or a list of
    ``n``."""
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        return [int(seed) + i for i in range(n)]
    if isinstance(seed, np.ndarray) and seed.ndim == 1:  # e.g. rng.integers(..., size=n)
        seed = seed.tolist()
    if isinstance(seed, Sequence) and not isinstance(seed, str):
        if len(seed) != n:
            raise ValueError(f"seed needs one entry per env ({n}), got {seed!r}")
        # numpy's ints as ints; anything else is left for the env's own check to refuse
        return [int(s) if isinstance(s, np.integer) else s for s in seed]
    raise TypeError(f"seed must be None, an int or a list of {n}, got {seed!r}")


def reset_mask(mask: Any, n: int, started: bool) -> np.ndarray:
    """``options["reset_mask"]`` checked: a ``[n]`` bool array with a True entry (None: all);
    the first reset of a vector env resets every env."""
    if mask is None:
        return np.ones(n, np.bool_)
    if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
        raise TypeError(f"options['reset_mask'] must be a numpy bool array, got {mask!r}")
    if mask.shape != (n,) or not mask.any():
        raise ValueError(
            f"options['reset_mask'] must have shape ({n},) and a True entry, got {mask!r}"
        )
    if not started and not mask.all():
        raise ValueError("the first reset resets every env (no reset_mask)")
    return mask


def per_env_values(values: Any, key: str, n: int) -> list:
    """``options[key]``, a list of one value per env (None: None for every env)."""
    if values is None:
        return [None] * n
    if isinstance(values, np.ndarray) and values.ndim == 1:  # numpy's ints as ints
        values = values.tolist()
    if not isinstance(values, Sequence) or len(values) != n:
        raise ValueError(f"options[{key!r}] must be a list of {n} (None: default)")
    return list(values)


def attr_values(values: Any, n: int) -> list:
    """``set_attr``'s values: one value for all ``n`` envs, or a list or tuple of one per env."""
    if not isinstance(values, (list, tuple)):
        return [values] * n
    if len(values) != n:
        raise ValueError(f"set_attr needs {n} values, got {len(values)}")
    return list(values)


def env_indices(indices: Sequence[int], n: int) -> list[int]:
    """``call_at``'s env indices, each checked to lie in ``[0, n)``."""
    indices = [int(i) for i in indices]
    if any(not 0 <= i < n for i in indices):
        raise ValueError(f"env indices must be in [0, {n}), got {indices}")
    return indices


def add_info(vector_infos: dict, env_info: dict, env_num: int, num_envs: int) -> dict:
    """Gymnasium's vector info format (``VectorEnv._add_info``), where a key's values may
    differ in type between envs (a ``tier`` of 1 in one, None in another; an int and a
    float): the array widens to float or object instead of refusing or truncating."""
    for key, value in env_info.items():
        if isinstance(value, dict):
            vector_infos[key] = add_info(vector_infos.get(key, {}), value, env_num, num_envs)
        else:
            array = vector_infos.get(key)
            if array is None:
                array = _info_array(value, num_envs)
            array = _widened(array, value, vector_infos.get(f"_{key}"))
            array[env_num] = value
            vector_infos[key] = array
        mask = vector_infos.get(f"_{key}", np.zeros(num_envs, np.bool_))
        mask[env_num] = True
        vector_infos[f"_{key}"] = mask
    return vector_infos


def unbatch_info(infos: dict, i: int) -> dict:
    """Env ``i``'s info dict from Gymnasium's vector info format (``infos[key][i]`` where
    ``infos["_" + key][i]``), numpy scalars as Python values."""
    out = {}
    for key, value in infos.items():
        if key.startswith("_") or not infos.get(f"_{key}", np.zeros(i + 1, bool))[i]:
            continue
        if isinstance(value, dict):
            out[key] = unbatch_info(value, i)
        else:
            item = value[i]
            out[key] = item.item() if isinstance(item, np.generic) else item
    return out


def check_vector_modes(
    render_mode: str | None, autoreset_mode: AutoresetMode | str, render_modes: Sequence[str]
) -> AutoresetMode:
    """Refuse a render mode outside ``render_modes`` (or None); the autoreset mode parsed."""
    if render_mode not in (None, *render_modes):
        raise ValueError(
            f"render_mode must be None or one of {list(render_modes)}, got {render_mode!r}"
        )
    try:
        return AutoresetMode(autoreset_mode)
    except ValueError:
        modes = [m.value for m in AutoresetMode]
        raise ValueError(f"autoreset_mode must be one of {modes}, got {autoreset_mode!r}") from None
