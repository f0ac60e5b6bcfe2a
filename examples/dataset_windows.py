"""Generate a few scenes, then iterate training windows with a torch DataLoader.

python examples/dataset_windows.py
"""

from __future__ import annotations

import tempfile

from torch.utils.data import DataLoader

from counterscene_env.scene.datagen import generate_dataset
from counterscene_env.world_model.dataset import SceneWindowDataset

with tempfile.TemporaryDirectory() as out:
    generate_dataset(out, "merge", scenes=4, seed=0, progress=False)
    windows = SceneWindowDataset(out)
    batch = next(iter(DataLoader(windows, batch_size=8, shuffle=True)))
    print(f"{len(windows)} windows from 4 scenes")
    for key, value in batch.items():
        print(f"  {key:>14}: {tuple(value.shape)} {value.dtype}")
