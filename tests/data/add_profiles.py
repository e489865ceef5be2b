"""Stores demonstration profiles in the bundled model without retraining it.

The bundled model predates ``dhg train`` storing profiles. Its training data is reproducible
(``dhg synth --out data/default``, seed 0); this checks that the regenerated records are the ones
the model was trained on (the SHA-256 in its metadata), builds their profiles exactly as
``dhg train`` does (:func:`dhg.learning.train._profiles`) and rewrites the model file with them in its
``dhg.json``. The weights are untouched, so the golden outputs stay valid.

    dhg synth --out data/default && .venv/bin/python tests/data/add_profiles.py data/default
"""

from __future__ import annotations

import json
import sys
import warnings

import torch

from dhg.data.dataset import load_dataset
from dhg.learning.torchscript import META_NAME, read_model_meta
from dhg.learning.train import _profiles
from dhg.learning.weights import default_model_path


def main(data_dir: str) -> None:
    path = default_model_path()
    meta = read_model_meta(path)
    ds = load_dataset(data_dir)
    sha = ds.card["files"]["records.parquet"]["sha256"]
    if sha != meta["data"]["records_sha256"]:
        raise SystemExit(
            f"{data_dir} is not the data {path} was trained on ({sha[:12]} != {meta['data']['records_sha256'][:12]})"
        )
    meta["profiles"] = _profiles(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        module = torch.jit.load(str(path))
        tmp = path.with_name(f".{path.name}.tmp")
        torch.jit.save(module, str(tmp), _extra_files={META_NAME: json.dumps(meta, indent=1)})
    tmp.replace(path)
    print(f"{path}: profiles of {meta['profiles']['episodes']} expert episodes stored")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "data/default")
