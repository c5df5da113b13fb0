"""Loading the authors' TensorFlow reference weights into :class:`EMLP`.

The reference stores dense layers as ``y = x W + b`` with ``W`` of shape (in, out) and biases
of shape (1, ..., out); torch's ``nn.Linear`` holds ``W^T``. Variable names are the checkpoint
object paths without ``/.ATTRIBUTES/VARIABLE_VALUE`` (e.g. ``model/init_features``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch

from emlpack.nn.potential import EMLP, ModelConfig

_BLOCK = "model/interaction_blocks/{i}/"
_LAYERS = {
    "filter1": ("filter_block/filter_weights1", "filter_block/filter_bias1"),
    "filter2": ("filter_block/filter_weights2", "filter_block/filter_bias2"),
    "atom_in": ("int_weights", "int_bias"),
    "conv_out": ("int_weights2", "int_bias2"),
    "atom_out": ("int_weights3", "int_bias3"),
}


def config_from_reference_hparams(hparams: Mapping) -> ModelConfig:
    """ModelConfig from the reference SchNet constructor arguments (its ``.pickle`` dict)."""
    h = dict(hparams)
    if h.get("shared_W_interactions", False):
        raise ValueError("reference models with shared_W_interactions=True are not supported")
    return ModelConfig(
        family="schnet",
        short_range={
            "n_features": int(h["num_features"]),
            "n_filters": int(h["num_filters"]),
            "n_rbf": int(h["n_max"]),
            "n_interactions": int(h["num_layers"]),
            "rbf_start": float(h.get("start", 0.0)),
            "rbf_end": float(h["end"]),
        },
        cutoff=float(h["cutoff"]),
        cutoff_transition=float(h["cutoff_transition_width"]),
    )


def reference_state_dict(variables: Mapping[str, np.ndarray], config: ModelConfig) -> dict:
    """Translate reference variables into an :class:`EMLP` state dict (float32 as stored)."""
    v = {k: np.asarray(a) for k, a in variables.items()}
    used = set()

    def take(key: str) -> torch.Tensor:
        if key not in v:
            raise KeyError(f"reference weights lack variable {key!r}")
        used.add(key)
        return torch.from_numpy(np.array(v[key], dtype=np.float32))

    state = {"short_range.embedding.weight": take("model/init_features")}
    for i in range(config.short_range["n_interactions"]):
        for ours, (w, b) in _LAYERS.items():
            prefix = f"short_range.interactions.{i}.{ours}"
            state[f"{prefix}.weight"] = take(_BLOCK.format(i=i) + w).T.contiguous()
            state[f"{prefix}.bias"] = take(_BLOCK.format(i=i) + b).reshape(-1)
    for k in range(3):
        state[f"short_range.output.{k}.weight"] = take(
            f"model/output_layer/output_weights/{k}"
        ).T.contiguous()
        state[f"short_range.output.{k}.bias"] = take(
            f"model/output_layer/output_biases/{k}").reshape(-1)
    extra = sorted(set(v) - used)
    if extra:
        raise KeyError(f"unexpected reference variables: {extra[:5]}")
    return state


def model_from_reference(
    variables: Mapping[str, np.ndarray],
    hparams: Mapping,
    dtype: torch.dtype | None = torch.float64,
) -> EMLP:
    """An :class:`EMLP` holding the reference's weights (cast to ``dtype``, as the reference's
    float64 models cast their float32 variables)."""
    config = config_from_reference_hparams(hparams)
    model = EMLP(config)
    model.load_state_dict(reference_state_dict(variables, config))
    return model.to(dtype) if dtype is not None else model
