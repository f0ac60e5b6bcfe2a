"""World-model checkpoints: ``model.safetensors`` + ``config.json`` in one directory.

``config.json``::

    {"format": "counterscene-world-model", "version": 1, "preset": "default",
     "architecture": {...ModelConfig fields...},
     "normalization": {"action_mean": [a, w], "action_std": [a, w]},
     "training": {...free-form provenance: data, steps, wall time, losses...}}

Weights are safetensors only: loading never unpickles anything. :func:`load_model` checks the
files, the format and version, the architecture keys, every tensor name and shape, and raises
:class:`CheckpointError` with a message naming the problem.

Model names (:func:`model_dir`): ``None`` and the string ``"default"`` always mean the model
shipped in the package, whatever the working directory holds; every other name, and a
``Path("default")``, is a directory. A directory named ``default`` in the working directory is
reached as ``"./default"`` (:func:`shadowed_default` finds the case, for the CLI's warning).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from counterscene_env.world_model.config import ModelConfig, check_preset_name
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.records import Normalization

FORMAT = "counterscene-world-model"
VERSION = 1
WEIGHTS = "model.safetensors"
CONFIG = "config.json"
DEFAULT_MODEL_DIR = Path(__file__).parent / "weights" / "default"
#: The model name that always means :data:`DEFAULT_MODEL_DIR` (module docstring).
DEFAULT_MODEL = "default"


class CheckpointError(ValueError):
    """A checkpoint directory that cannot be loaded; the message says why."""


def save_model(
    model: WorldModel,
    directory: str | os.PathLike,
    preset: str | None = None,
    training: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``model.safetensors`` and ``config.json`` into ``directory`` (created if needed).

    Both files are written to temporary names first and renamed, so an interrupted save never
    leaves a half-written checkpoint behind.
    """
    from safetensors.torch import save_file

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "preset": preset,
        "architecture": model.config.to_dict(),
        "normalization": model.normalization.to_dict(),
        "training": dict(training or {}),
    }
    tmp_w, tmp_c = out / (WEIGHTS + ".tmp"), out / (CONFIG + ".tmp")
    # One metadata key: safetensors writes several in a random order, and two runs of the
    # same training would then differ in their bytes. The version is in config.json.
    save_file(tensors, str(tmp_w), metadata={"format": FORMAT})
    tmp_c.write_text(json.dumps(meta, indent=1) + "\n")
    # safetensors writes its file owner-only (0600); give it the mode every other file gets.
    os.chmod(tmp_w, os.stat(tmp_c).st_mode & 0o777)
    os.replace(tmp_w, out / WEIGHTS)
    os.replace(tmp_c, out / CONFIG)
    return out


def read_config(directory: str | os.PathLike) -> dict[str, Any]:
    """The validated ``config.json`` of a checkpoint directory."""
    path = Path(directory)
    if path.is_file():
        raise CheckpointError(
            f"{str(path)!r} is a file: a model is the directory that holds {WEIGHTS} and {CONFIG}"
        )
    if not path.is_dir():
        raise CheckpointError(f"model directory {str(path)!r} does not exist")
    cfg_path = path / CONFIG
    if not cfg_path.is_file():
        raise CheckpointError(f"{str(path)!r} has no {CONFIG} (not a CounterScene model directory)")
    try:
        meta = json.loads(cfg_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{cfg_path} is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{cfg_path} is not a {FORMAT} config (format field missing or wrong)"
        )
    if meta.get("version") != VERSION:
        raise CheckpointError(
            f"{cfg_path} has format version {meta.get('version')!r}; this release reads version "
            f"{VERSION}"
        )
    for key in ("architecture", "normalization"):
        if not isinstance(meta.get(key), dict):
            raise CheckpointError(f"{cfg_path} has no {key!r} section")
    try:
        check_preset_name("preset", meta.get("preset"))
    except ValueError as exc:
        raise CheckpointError(f"{cfg_path}: {exc}") from None
    return meta


def _names_default(name: str | os.PathLike | None) -> bool:
    """Whether ``name`` is the string ``"default"`` (a ``Path`` is always a path:
    ``Path("default") == "default"`` is False)."""
    return isinstance(name, str) and name == DEFAULT_MODEL


def model_dir(name: str | os.PathLike | None) -> Path:
    """The checkpoint directory ``name`` stands for: :data:`DEFAULT_MODEL_DIR` for ``None`` and
    the string ``"default"`` (even when the working directory holds a ``default`` directory:
    write ``"./default"`` for that), else ``name`` as a path."""
    if name is None or _names_default(name):
        return DEFAULT_MODEL_DIR
    return Path(name)


def shadowed_default(name: str | os.PathLike | None) -> Path | None:
    """``Path("default")`` when ``name`` is the string ``"default"`` and the working directory
    holds a model directory of that name (a ``config.json`` or ``model.safetensors`` in it),
    which ``name`` does not load (:func:`model_dir`); else ``None``."""
    if not _names_default(name):
        return None
    here = Path(DEFAULT_MODEL)
    return here if any((here / f).is_file() for f in (CONFIG, WEIGHTS)) else None


_SHARED: dict[str, WorldModel] = {}


def shared_model(name: str = "default") -> WorldModel:
    """:func:`load_model`, once per process and name: the envs share one read-only model."""
    if name not in _SHARED:
        _SHARED[name] = load_model(name)
    return _SHARED[name]


def load_model(
    directory: str | os.PathLike | None = "default", device: str | torch.device = "cpu"
) -> WorldModel:
    """Load a checkpoint directory (``"default"`` or ``None``: the model shipped in the package,
    :func:`model_dir`).

    The model comes back in eval mode. Raises :class:`CheckpointError` on a missing file, a
    foreign or newer format, an unknown architecture key, a file that is not safetensors,
    missing or unexpected tensors, or a shape mismatch.
    """
    path = model_dir(directory)
    meta = read_config(path)
    config = _architecture(path, meta)
    normalization = _normalization(path, meta)
    tensors = _read_weights(path)
    model = _build_model(path, config, normalization)
    _check_tensors(path / WEIGHTS, tensors, model.state_dict())
    model.load_state_dict(tensors)
    model.preset = meta.get("preset")
    model.training_info = meta.get("training", {})
    return model.to(device).eval()


def _architecture(path: Path, meta: dict[str, Any]) -> ModelConfig:
    """The ``ModelConfig`` of the config's architecture section."""
    try:
        return ModelConfig.from_mapping(meta["architecture"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path / CONFIG}: bad architecture: {exc}") from None


def _normalization(path: Path, meta: dict[str, Any]) -> Normalization:
    """The action normalization (2 finite means, 2 finite positive stds) of the config."""
    norm = meta["normalization"]
    try:
        normalization = Normalization(
            tuple(float(v) for v in norm["action_mean"]),
            tuple(float(v) for v in norm["action_std"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path / CONFIG}: bad normalization section: {exc!r}") from None
    values = (*normalization.action_mean, *normalization.action_std)
    if (
        len(values) != 4
        or not all(math.isfinite(v) for v in values)
        or min(normalization.action_std) <= 0
    ):
        raise CheckpointError(f"{path / CONFIG}: normalization must be 2 means and 2 positive stds")
    return normalization


def _read_weights(path: Path) -> dict[str, torch.Tensor]:
    """The tensors of ``path/model.safetensors``, loaded on the CPU."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    weights = path / WEIGHTS
    if not weights.is_file():
        raise CheckpointError(f"{str(path)!r} has no {WEIGHTS}")
    try:
        return load_file(str(weights), device="cpu")
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{weights} is not a readable safetensors file: {exc}") from None


def _build_model(path: Path, config: ModelConfig, normalization: Normalization) -> WorldModel:
    """An untrained ``WorldModel`` of the checkpoint's architecture and normalization."""
    try:
        # Its initial values are overwritten by the checkpoint's: drawing them must not move
        # the user's global torch generator (a gym.make would change their later draws).
        with torch.random.fork_rng(devices=[]):
            return WorldModel(config, normalization)
    except (TypeError, ValueError, RuntimeError, ZeroDivisionError) as exc:
        raise CheckpointError(f"{path / CONFIG}: cannot build the architecture: {exc}") from None


def _check_tensors(
    weights: Path, tensors: Mapping[str, torch.Tensor], expected: Mapping[str, torch.Tensor]
) -> None:
    """Check the loaded tensors' names, shapes and finiteness against the model's state dict."""
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise CheckpointError(
            f"{weights} does not match its architecture: missing {missing[:5]}"
            f"{'...' if len(missing) > 5 else ''}, unexpected {unexpected[:5]}"
            f"{'...' if len(unexpected) > 5 else ''}"
        )
    for name, tensor in tensors.items():
        if tensor.shape != expected[name].shape:
            raise CheckpointError(
                f"{weights}: tensor {name!r} has shape {tuple(tensor.shape)}, the architecture in "
                f"{CONFIG} needs {tuple(expected[name].shape)}"
            )
        if not torch.isfinite(tensor).all():
            raise CheckpointError(f"{weights}: tensor {name!r} holds NaN or infinite values")
